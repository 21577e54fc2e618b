//! One session's rendering: a technique, tone mapping and readback. Blocking: call it from a
//! render thread, never from an async task.

use std::sync::Arc;
use std::time::Duration;

use voxlight_protocol::{TechniqueKind, TransferFunction};

use crate::brightness::{BrightnessMatch, mean_rgb};
use crate::passes::tonemap::ToneParams;
use crate::preview::{LightDetail, Preview, PreviewReport};
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::photon::Photon;
use crate::techniques::progressive::{Estimator, Progressive, accum_bytes};
use crate::{Change, Engine, EngineError, GpuVolume, Scene};

pub use crate::frame::Frame;

pub struct Renderer {
    technique: Box<dyn Technique>,
    volume: Arc<GpuVolume>,
    tone_params: wgpu::Buffer,
    rgba: wgpu::Buffer,
    tone_bind_group: wgpu::BindGroup,
    width: u32,
    height: u32,
    /// Made at the first preview (a session that never moves never pays for it).
    preview: Option<Preview>,
    /// Edits the preview already shows and the technique has not seen yet.
    pending: Pending,
    /// The preview's gain toward the technique's brightness.
    brightness: BrightnessMatch,
    /// The edit count the preview image showed when it was last rendered at full resolution:
    /// it is compared with the technique's picture once the technique has refined that scene
    /// (read back then, once per drag, not at every preview).
    reference: Option<u64>,
    /// Edits deferred or applied so far.
    edits: u64,
}

/// Edits queued for the technique while they are shown by the preview (`Renderer::defer`),
/// merged: a drag of many camera or TF edits reaches the technique as one of each.
#[derive(Debug, Default)]
struct Pending {
    /// The TF before the first queued TF edit.
    tf_old: Option<TransferFunction>,
    camera: bool,
    lights: bool,
    params: bool,
    iterations: bool,
}

impl Pending {
    fn push(&mut self, change: &Change) {
        match change {
            Change::Tf { old, .. } => {
                if self.tf_old.is_none() {
                    self.tf_old = Some(old.clone());
                }
            }
            Change::Camera => self.camera = true,
            Change::Lights => self.lights = true,
            Change::Params => self.params = true,
            Change::Iterations => self.iterations = true,
            // Applied at once (Renderer::defer), never queued.
            Change::Viewport => {}
        }
    }

    /// The merged edits for `scene` (the state after all of them), in an order after which
    /// every technique holds what it would after seeing each edit: restarts (params, lights)
    /// first, then the camera (the view-dependent state, redone for the final view), then the
    /// TF update against the TF before the first edit (view-independent state such as photons,
    /// cache entries and virtual lights), then more iterations. Camera before TF: `photon`
    /// then updates its photons and starts the camera's gather again with the new TF, where
    /// the other order updated segments (seconds at 512² on lavapipe) that the camera edit
    /// then gathered afresh.
    fn take(&mut self, scene: &Scene) -> Vec<Change> {
        let mut changes = Vec::new();
        if std::mem::take(&mut self.params) {
            changes.push(Change::Params);
        }
        if std::mem::take(&mut self.lights) {
            changes.push(Change::Lights);
        }
        if std::mem::take(&mut self.camera) {
            changes.push(Change::Camera);
        }
        if let Some(old) = self.tf_old.take()
            && old != scene.tf
        {
            changes.push(Change::tf(&old, &scene.tf));
        }
        if std::mem::take(&mut self.iterations) {
            changes.push(Change::Iterations);
        }
        changes
    }

    fn is_empty(&self) -> bool {
        self.tf_old.is_none() && !self.camera && !self.lights && !self.params && !self.iterations
    }
}

/// GPU bytes a session needs for a viewport: the technique's buffers plus tone mapping and
/// its readback copy, and the interactive preview's image.
pub fn session_bytes(width: u32, height: u32) -> u64 {
    let pixels = width as u64 * height as u64;
    accum_bytes(width, height)
        + 2 * pixels * 4
        + pixels * crate::preview::BYTES_PER_PIXEL
        + 64 * 1024
}

impl Renderer {
    pub fn new(
        engine: &Engine,
        technique: &str,
        volume: Arc<GpuVolume>,
        scene: &Scene,
    ) -> Result<Self, EngineError> {
        scene.validate().map_err(EngineError::InvalidScene)?;
        check_budget(engine, scene)?;
        let kind = TechniqueKind::from_name(technique)
            .ok_or_else(|| EngineError::UnknownTechnique(technique.to_owned()))?;
        let technique: Box<dyn Technique> = match kind {
            TechniqueKind::Raymarch => Box::new(Progressive::new(
                engine,
                Estimator::Raymarch,
                volume.clone(),
                scene,
            )?),
            TechniqueKind::Pathtrace => Box::new(Progressive::new(
                engine,
                Estimator::Pathtrace,
                volume.clone(),
                scene,
            )?),
            TechniqueKind::Photon => Box::new(Photon::new(
                engine,
                volume.clone(),
                scene,
                crate::techniques::photon::PhotonParams::from_options(
                    &scene.technique_options.photon,
                ),
            )?),
            TechniqueKind::Manylight => Box::new(crate::techniques::manylight::Manylight::new(
                engine,
                volume.clone(),
                scene,
                crate::techniques::manylight::ManylightConfig::from_options(
                    &scene.technique_options.manylight,
                ),
            )?),
            TechniqueKind::Irradiance => Box::new(crate::techniques::irradiance::Irradiance::new(
                engine,
                volume.clone(),
                scene,
                crate::techniques::irradiance::IrradianceConfig::from_options(
                    &scene.technique_options.irradiance,
                ),
            )?),
        };
        Self::with_technique(engine, technique, volume, scene)
    }

    /// A renderer around a technique built by the caller (tests and benchmarks that configure
    /// one beyond its defaults).
    pub fn with_technique(
        engine: &Engine,
        technique: Box<dyn Technique>,
        volume: Arc<GpuVolume>,
        scene: &Scene,
    ) -> Result<Self, EngineError> {
        check_budget(engine, scene)?;
        let brightness = BrightnessMatch::new(technique.multiple_scattering());
        let (tone_params, rgba, tone_bind_group) =
            tone_resources(engine, technique.output(), scene);
        engine.gpu.check()?;
        Ok(Self {
            technique,
            volume,
            tone_params,
            rgba,
            tone_bind_group,
            width: scene.viewport.width,
            height: scene.viewport.height,
            preview: None,
            pending: Pending::default(),
            brightness,
            reference: None,
            edits: 0,
        })
    }

    pub fn technique_name(&self) -> &'static str {
        self.technique.name()
    }

    pub fn volume(&self) -> &Arc<GpuVolume> {
        &self.volume
    }

    /// Records an edit that the preview shows at once and the technique sees at its next
    /// `step` (merged with the other deferred edits); a viewport change is applied at once.
    /// `scene` already holds the new state.
    pub fn defer(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        if *change == Change::Viewport {
            return self.apply(engine, scene, change);
        }
        self.match_brightness(engine)?;
        self.edits += 1;
        self.pending.push(change);
        Ok(())
    }

    /// Before an edit changes the scene: when the technique has refined the scene of the last
    /// full-resolution preview (no edit since, none waiting, at least one iteration), its mean
    /// sets the preview's brightness match for the previews of this edit and the next ones.
    fn match_brightness(&mut self, engine: &Engine) -> Result<(), EngineError> {
        let (Some(edits), Some(preview)) = (self.reference.take(), &self.preview) else {
            return Ok(());
        };
        if edits != self.edits || !self.pending.is_empty() || self.technique.iteration() == 0 {
            return Ok(());
        }
        let means = preview.means(engine, 1)?;
        let technique = mean_rgb(&self.read_hdr(engine)?);
        self.brightness.update(&means, technique);
        Ok(())
    }

    /// How the preview's brightness is matched to the technique (`preview::BrightnessMatch`).
    pub fn brightness_match(&self) -> BrightnessMatch {
        self.brightness
    }

    /// Whether deferred edits wait for the technique.
    pub fn has_pending(&self) -> bool {
        !self.pending.is_empty()
    }

    /// Hands the deferred edits to the technique.
    pub fn catch_up(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        for change in self.pending.take(scene) {
            self.technique.apply(engine, scene, &change)?;
        }
        engine.gpu.check()
    }

    /// Applies an edit (after any deferred ones); `scene` already holds the new state.
    pub fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        self.catch_up(engine, scene)?;
        self.edits += 1;
        if *change == Change::Viewport {
            check_budget(engine, scene)?;
        }
        self.technique.apply(engine, scene, change)?;
        if *change == Change::Viewport {
            let (params, rgba, bind_group) = tone_resources(engine, self.technique.output(), scene);
            self.tone_params = params;
            self.rgba = rgba;
            self.tone_bind_group = bind_group;
            self.width = scene.viewport.width;
            self.height = scene.viewport.height;
        }
        engine.gpu.check()
    }

    /// The longest one submission of the technique should take (`Technique::set_part_time`).
    pub fn set_part_time(&mut self, part: Option<Duration>) {
        self.technique.set_part_time(part);
    }

    /// Progressive work for about `budget`.
    pub fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError> {
        self.catch_up(engine, scene)?;
        let report = self.technique.step(engine, scene, budget)?;
        engine.gpu.check()?;
        Ok(report)
    }

    pub fn iteration(&self) -> u32 {
        self.technique.iteration()
    }

    /// The technique's picture of `scene` is final: no deferred edit waits for it and it has
    /// its target iterations.
    pub fn converged(&self, scene: &Scene) -> bool {
        !self.has_pending() && self.technique.iteration() >= self.technique.target_iterations(scene)
    }

    pub fn stats(&self) -> TechniqueStats {
        let mut stats = self.technique.stats();
        stats.memory_bytes += 2 * self.width as u64 * self.height as u64 * 4
            + self.preview.as_ref().map_or(0, Preview::bytes);
        stats
    }

    /// Renders the interactive preview of `scene` at resolution `divisor` (1, 2, 4 or 8 per
    /// axis): what viewers see while edits stream in, whatever the technique.
    pub fn preview_frame(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        divisor: u32,
        detail: LightDetail,
    ) -> Result<(Frame, PreviewReport), EngineError> {
        self.preview_frame_until(engine, scene, divisor, detail, None)?
            .ok_or_else(|| EngineError::Gpu("a preview nobody could stop was stopped".into()))
    }

    /// As `preview_frame`, but with `stop` a long preview runs in parts and is abandoned
    /// (None) when `stop` says so between them (`Preview::render_until`).
    pub fn preview_frame_until(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        divisor: u32,
        detail: LightDetail,
        stop: Option<&mut dyn FnMut() -> bool>,
    ) -> Result<Option<(Frame, PreviewReport)>, EngineError> {
        let multiple_scattering = self.technique.multiple_scattering();
        let preview = self.preview.get_or_insert_with(|| {
            Preview::new(engine, self.volume.clone(), scene, multiple_scattering)
        });
        let rendered =
            preview.render_until(engine, scene, divisor, detail, &self.brightness, stop)?;
        // A full-resolution preview is what the technique's picture of this scene will be
        // compared with (at the next edit).
        self.reference = (divisor == 1 && rendered.is_some()).then_some(self.edits);
        Ok(rendered)
    }

    /// The preview, once one was rendered.
    pub fn preview(&self) -> Option<&Preview> {
        self.preview.as_ref()
    }

    /// The preview, once one was rendered, to configure (`Preview::set_part_time`).
    pub fn preview_mut(&mut self) -> Option<&mut Preview> {
        self.preview.as_mut()
    }

    /// Tone maps the current estimate and reads it back as RGBA8.
    pub fn frame(&self, engine: &Engine, scene: &Scene) -> Result<Frame, EngineError> {
        let params = ToneParams {
            width: self.width,
            height: self.height,
            exposure: scene.params.exposure,
            pad0: 0,
        };
        engine
            .gpu
            .queue
            .write_buffer(&self.tone_params, 0, bytemuck::bytes_of(&params));
        let mut encoder =
            engine
                .gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("tonemap"),
                });
        engine
            .tonemap
            .encode(&mut encoder, &self.tone_bind_group, self.width, self.height);
        engine.gpu.queue.submit([encoder.finish()]);
        let rgba = engine.gpu.read_buffer(&self.rgba)?;
        Ok(Frame {
            width: self.width,
            height: self.height,
            rgba,
            iteration: self.technique.iteration(),
            target_iterations: self.technique.target_iterations(scene),
            converged: self.converged(scene),
            divisor: 1,
            preview: false,
            preview_match: None,
        })
    }

    /// The linear HDR estimate (mean radiance per pixel, rgb), row 0 at the top.
    pub fn read_hdr(&self, engine: &Engine) -> Result<Vec<[f32; 3]>, EngineError> {
        let bytes = engine.gpu.read_buffer(self.technique.output())?;
        let sums: &[[f32; 4]] = bytemuck::try_cast_slice(&bytes)
            .map_err(|e| EngineError::Gpu(format!("HDR readback has an odd size: {e}")))?;
        Ok(sums
            .iter()
            .map(|s| {
                let n = s[3].max(1.0);
                [s[0] / n, s[1] / n, s[2] / n]
            })
            .collect())
    }
}

fn check_budget(engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
    let (width, height) = (scene.viewport.width, scene.viewport.height);
    let max_pixels = engine.max_viewport_pixels();
    if width as u64 * height as u64 > max_pixels {
        return Err(EngineError::ViewportTooLarge {
            width,
            height,
            needed: session_bytes(width, height),
            max_pixels,
        });
    }
    Ok(())
}

fn tone_resources(
    engine: &Engine,
    accum: &wgpu::Buffer,
    scene: &Scene,
) -> (wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup) {
    let device = &engine.gpu.device;
    let params = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("tonemap params"),
        size: size_of::<ToneParams>() as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let rgba = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("tonemap rgba8"),
        size: scene.viewport.width as u64 * scene.viewport.height as u64 * 4,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let bind_group = engine
        .tonemap
        .bind_group(&engine.gpu, &params, accum, &rgba);
    (params, rgba, bind_group)
}
