//! One session's rendering: a technique, tone mapping and readback. Blocking: call it from a
//! render thread, never from an async task.

use std::sync::Arc;
use std::time::Duration;

use crate::passes::tonemap::ToneParams;
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::photon::Photon;
use crate::techniques::progressive::{Estimator, Progressive, accum_bytes};
use crate::{Change, Engine, EngineError, GpuVolume, Scene};

/// A tone-mapped picture read back from the GPU.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Row-major RGBA8, row 0 at the top, sRGB.
    pub rgba: Vec<u8>,
    pub iteration: u32,
    pub target_iterations: u32,
    pub converged: bool,
}

pub struct Renderer {
    technique: Box<dyn Technique>,
    volume: Arc<GpuVolume>,
    tone_params: wgpu::Buffer,
    rgba: wgpu::Buffer,
    tone_bind_group: wgpu::BindGroup,
    width: u32,
    height: u32,
}

/// GPU bytes a session needs for a viewport: the technique's buffers plus tone mapping and
/// its readback copy.
pub fn session_bytes(width: u32, height: u32) -> u64 {
    accum_bytes(width, height) + 2 * width as u64 * height as u64 * 4 + 64 * 1024
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
        let technique: Box<dyn Technique> = match technique {
            "raymarch" => Box::new(Progressive::new(
                engine,
                Estimator::Raymarch,
                volume.clone(),
                scene,
            )?),
            "pathtrace" => Box::new(Progressive::new(
                engine,
                Estimator::Pathtrace,
                volume.clone(),
                scene,
            )?),
            "photon" => Box::new(Photon::new(
                engine,
                volume.clone(),
                scene,
                crate::technique_options::photon_params(&scene.technique_options.photon),
            )?),
            "manylight" => Box::new(crate::techniques::manylight::Manylight::new(
                engine,
                volume.clone(),
                scene,
                crate::technique_options::manylight_config(&scene.technique_options.manylight),
            )?),
            "irradiance" => Box::new(crate::techniques::irradiance::Irradiance::new(
                engine,
                volume.clone(),
                scene,
                crate::technique_options::irradiance_config(&scene.technique_options.irradiance),
            )?),
            other => return Err(EngineError::UnknownTechnique(other.to_owned())),
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
        })
    }

    pub fn technique_name(&self) -> &'static str {
        self.technique.name()
    }

    pub fn volume(&self) -> &Arc<GpuVolume> {
        &self.volume
    }

    /// Applies an edit; `scene` already holds the new state.
    pub fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
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

    /// Progressive work for about `budget`.
    pub fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError> {
        let report = self.technique.step(engine, scene, budget)?;
        engine.gpu.check()?;
        Ok(report)
    }

    pub fn iteration(&self) -> u32 {
        self.technique.iteration()
    }

    pub fn converged(&self, scene: &Scene) -> bool {
        self.technique.iteration() >= self.technique.target_iterations(scene)
    }

    pub fn stats(&self) -> TechniqueStats {
        let mut stats = self.technique.stats();
        stats.memory_bytes += 2 * self.width as u64 * self.height as u64 * 4;
        stats
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
