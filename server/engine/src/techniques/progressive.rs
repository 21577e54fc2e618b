//! The progressive per-pixel techniques: each iteration adds one radiance sample per pixel to
//! the HDR estimate. `raymarch` (shaders/raymarch.wgsl) is single scattering with shadow rays;
//! `pathtrace` (shaders/pathtrace.wgsl) is the unbiased multiple-scattering reference. Both
//! use the same per-session buffers.
//!
//! - An iteration that takes longer than `BAND_TIME` (seconds at full resolution on a
//!   software adapter) runs as bands, one per submission, so that `step` returns within about
//!   a band and the render thread can show an edit that came meanwhile instead of holding it
//!   for the whole iteration. Band k of n holds the 8-row blocks k, k + n, k + 2n, …
//!   (shared/common.wgsl `band_row`): interleaved, every band costs about the same (contiguous bands
//!   did not: the empty rows above a CT are cheap, the ones through it dear), and each 8×8
//!   workgroup still covers adjacent rows. The samples are the same as a whole dispatch's (the
//!   random numbers depend on the pixel and the iteration only).

use std::sync::Arc;
use std::time::{Duration, Instant};

use voxlight_protocol::MAX_LIGHTS;

use crate::gpu::TfTexture;
use crate::gpu_timer::GpuTimer;
use crate::passes::builder;
use crate::passes::estimator::{EstimatorBindings, EstimatorPass};
use crate::scene_gpu::{GpuLight, SceneUniforms, gpu_lights};
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::tf::bake;
use crate::{Change, Engine, EngineError, GpuVolume, Scene};

/// Which estimator a `Progressive` technique runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Estimator {
    Raymarch,
    Pathtrace,
}

impl Estimator {
    pub fn name(self) -> &'static str {
        match self {
            Estimator::Raymarch => "raymarch",
            Estimator::Pathtrace => "pathtrace",
        }
    }

    fn pass(self, engine: &Engine) -> &EstimatorPass {
        match self {
            Estimator::Raymarch => &engine.raymarch,
            Estimator::Pathtrace => &engine.pathtrace,
        }
    }
}

pub struct Progressive {
    estimator: Estimator,
    volume: Arc<GpuVolume>,
    scene_buf: wgpu::Buffer,
    tf_lut: TfTexture,
    lights: wgpu::Buffer,
    accum: wgpu::Buffer,
    cell_max_opacity: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    width: u32,
    height: u32,
    iteration: u32,
    /// Iterations submitted per wait, adapted to the step budget.
    batch: u32,
    /// Bands an iteration runs as (1: whole), chosen at each iteration's start from the last
    /// one's time so that a band takes about `BAND_TIME`.
    bands: u32,
    /// The next band of the iteration in progress (0 between iterations).
    next_band: u32,
    /// Wall time of the iteration in progress's bands so far.
    iteration_time: Duration,
    /// `bands` was set by `fix_bands`, not measured.
    fixed_bands: bool,
    timer: Option<GpuTimer>,
}

/// An iteration longer than this runs in bands of about this long.
const BAND_TIME: Duration = Duration::from_millis(25);

/// Bands of a first iteration, before its time is known (on a fast adapter that first
/// iteration costs this many submissions, then whole iterations follow).
const FIRST_BANDS: u32 = 32;

/// Bands for an iteration that takes `iteration`: each about `BAND_TIME`, at most one per
/// 8-row block.
fn bands_for(iteration: Duration, height: u32) -> u32 {
    let bands = (iteration.as_secs_f64() / BAND_TIME.as_secs_f64()).ceil();
    (bands as u32).clamp(1, blocks(height))
}

/// 8-row blocks of an image `height` rows tall (the unit of a band).
fn blocks(height: u32) -> u32 {
    height.div_ceil(8).max(1)
}

/// Rows to dispatch for band `band` of `bands` of an image `height` rows tall (whole blocks;
/// the shader skips rows past the image).
pub(crate) fn band_rows(height: u32, band: u32, bands: u32) -> u32 {
    (blocks(height) - band).div_ceil(bands) * 8
}

/// One band of an iteration: the dispatch's `row_offset`/`row_stride` (shared/common.wgsl
/// `band_row`) and the rows it dispatches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Band {
    pub offset: u32,
    pub stride: u32,
    pub rows: u32,
}

/// Bytes of the HDR accumulation buffer for a viewport.
pub fn accum_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * 16
}

impl Progressive {
    pub fn new(
        engine: &Engine,
        estimator: Estimator,
        volume: Arc<GpuVolume>,
        scene: &Scene,
    ) -> Result<Self, EngineError> {
        let gpu = &engine.gpu;
        let (uniform, storage) = (wgpu::BufferUsages::UNIFORM, wgpu::BufferUsages::STORAGE);
        let scene_buf = gpu.buffer(
            "estimator scene",
            size_of::<SceneUniforms>() as u64,
            uniform,
        );
        let tf_lut = gpu.tf_texture("estimator tf lut");
        let lights_size = (MAX_LIGHTS * size_of::<GpuLight>()) as u64;
        let lights = gpu.buffer("estimator lights", lights_size, uniform);
        let (width, height) = (scene.viewport.width, scene.viewport.height);
        let accum_size = accum_bytes(width, height);
        let accum_usage = storage | wgpu::BufferUsages::COPY_SRC;
        let accum = gpu.buffer("estimator accum", accum_size, accum_usage);
        let cells_size = (volume.ranges.cell_count() * 4) as u64;
        let cell_max_opacity = gpu.buffer("estimator cell max opacity", cells_size, storage);
        let bind_group = estimator.pass(engine).bind_group(
            gpu,
            &EstimatorBindings {
                scene: &scene_buf,
                volume: &volume.view,
                tf_lut: &tf_lut.view,
                lights: &lights,
                accum: &accum,
                cell_max_opacity: &cell_max_opacity,
            },
        );
        let technique = Self {
            estimator,
            volume,
            scene_buf,
            tf_lut,
            lights,
            accum,
            cell_max_opacity,
            bind_group,
            width,
            height,
            iteration: 0,
            batch: 1,
            bands: FIRST_BANDS.min(blocks(height)),
            next_band: 0,
            iteration_time: Duration::ZERO,
            fixed_bands: false,
            timer: GpuTimer::new(&engine.gpu, estimator.name()),
        };
        technique.write_tf(engine, scene);
        technique.write_lights(engine, scene);
        Ok(technique)
    }

    /// No iteration is part way through its bands.
    pub(crate) fn between_iterations(&self) -> bool {
        self.next_band == 0
    }

    /// Runs every iteration as `bands` bands, whatever they take: for tests and benchmarks of
    /// the banded path, which otherwise only long iterations take.
    pub fn fix_bands(&mut self, bands: u32) {
        self.bands = bands.clamp(1, blocks(self.height));
        self.fixed_bands = true;
    }

    fn encoder(&self, engine: &Engine) -> wgpu::CommandEncoder {
        builder::encoder(&engine.gpu, self.estimator.name())
    }

    /// Renders the next band of the iteration in progress and waits for it; returns its wall
    /// time (bands are not timed by queries). After the last band the iteration counts and the
    /// next one's band count is chosen.
    fn band(&mut self, engine: &Engine, scene: &Scene) -> Result<Duration, EngineError> {
        let started = Instant::now();
        let mut encoder = self.encoder(engine);
        self.encode_band(engine, scene, &mut encoder)?;
        engine.gpu.queue.submit([encoder.finish()]);
        engine.gpu.wait_idle()?;
        let took = started.elapsed();
        self.finish_band(took);
        Ok(took)
    }

    /// Writes the uniforms of the next band of the iteration in progress (row_offset and
    /// row_stride) and encodes its estimator dispatch; returns the band (row_offset,
    /// row_stride, rows to dispatch) for passes that add to the same pixels (`manylight`'s
    /// gather). The caller submits, waits, then calls `finish_band`.
    pub(crate) fn encode_band(
        &self,
        engine: &Engine,
        scene: &Scene,
        encoder: &mut wgpu::CommandEncoder,
    ) -> Result<Band, EngineError> {
        let mut uniforms = SceneUniforms::new(scene, &self.volume, self.iteration)
            .map_err(EngineError::InvalidScene)?;
        let band = Band {
            offset: self.next_band,
            stride: self.bands,
            rows: band_rows(self.height, self.next_band, self.bands),
        };
        uniforms.row_offset = band.offset;
        uniforms.row_stride = band.stride;
        engine
            .gpu
            .queue
            .write_buffer(&self.scene_buf, 0, bytemuck::bytes_of(&uniforms));
        self.estimator
            .pass(engine)
            .encode(encoder, &self.bind_group, self.width, band.rows, None);
        Ok(band)
    }

    /// Counts a band that took `took` (its passes included): after the last band of an
    /// iteration the iteration counts and the next one's band count is chosen from the
    /// iteration's time. Returns whether the iteration completed.
    pub(crate) fn finish_band(&mut self, took: Duration) -> bool {
        self.iteration_time += took;
        self.next_band += 1;
        if self.next_band < self.bands {
            return false;
        }
        self.next_band = 0;
        self.iteration += 1;
        if !self.fixed_bands {
            self.bands = bands_for(self.iteration_time, self.height);
        }
        self.iteration_time = Duration::ZERO;
        true
    }

    /// The buffers the estimator binds (for techniques that add passes over the same ones).
    pub(crate) fn bindings(&self) -> EstimatorBindings<'_> {
        EstimatorBindings {
            scene: &self.scene_buf,
            volume: &self.volume.view,
            tf_lut: &self.tf_lut.view,
            lights: &self.lights,
            accum: &self.accum,
            cell_max_opacity: &self.cell_max_opacity,
        }
    }

    /// Writes the scene uniforms of the next iteration.
    pub(crate) fn encode_uniforms(
        &self,
        engine: &Engine,
        scene: &Scene,
    ) -> Result<(), EngineError> {
        let uniforms = SceneUniforms::new(scene, &self.volume, self.iteration)
            .map_err(EngineError::InvalidScene)?;
        engine
            .gpu
            .queue
            .write_buffer(&self.scene_buf, 0, bytemuck::bytes_of(&uniforms));
        Ok(())
    }

    /// Starts the picture over.
    pub(crate) fn restart(&mut self) {
        self.iteration = 0;
        self.next_band = 0;
        self.iteration_time = Duration::ZERO;
    }

    pub(crate) fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn write_tf(&self, engine: &Engine, scene: &Scene) {
        let lut = bake(&scene.tf);
        let queue = &engine.gpu.queue;
        self.tf_lut.write(queue, &lut);
        let cells = self.volume.ranges.max_opacity(&lut);
        queue.write_buffer(&self.cell_max_opacity, 0, bytemuck::cast_slice(&cells));
    }

    fn write_lights(&self, engine: &Engine, scene: &Scene) {
        let (lights, _) = gpu_lights(&scene.lights);
        if !lights.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.lights, 0, bytemuck::cast_slice(&lights));
        }
    }
}

impl Technique for Progressive {
    fn name(&self) -> &'static str {
        self.estimator.name()
    }

    fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        match change {
            Change::Tf { .. } => self.write_tf(engine, scene),
            Change::Lights => self.write_lights(engine, scene),
            Change::Viewport => {
                *self = Progressive::new(engine, self.estimator, self.volume.clone(), scene)?;
            }
            Change::Camera | Change::Params => {}
            // More iterations continue the same picture.
            Change::Iterations => return Ok(()),
        }
        self.restart();
        Ok(())
    }

    fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError> {
        let target = scene.target_iterations;
        let start = Instant::now();
        let mut done = 0;
        let mut gpu_time = Duration::ZERO;
        while self.iteration < target {
            if self.bands > 1 {
                gpu_time += self.band(engine, scene)?;
                if self.next_band == 0 {
                    done += 1;
                }
                if budget.is_zero() || start.elapsed() >= budget {
                    break;
                }
                continue;
            }
            // A zero budget asks for one iteration now (the first frame after an edit).
            let batch = if budget.is_zero() { 1 } else { self.batch }.min(target - self.iteration);
            let batch_start = Instant::now();
            for i in 0..batch {
                self.encode_uniforms(engine, scene)?;
                let mut encoder = self.encoder(engine);
                let last = i + 1 == batch;
                let writes = self.timer.as_ref().and_then(|t| t.writes(i == 0, last));
                self.estimator.pass(engine).encode(
                    &mut encoder,
                    &self.bind_group,
                    self.width,
                    self.height,
                    writes,
                );
                if let (true, Some(timer)) = (last, &self.timer) {
                    timer.resolve(&mut encoder);
                }
                engine.gpu.queue.submit([encoder.finish()]);
                self.iteration += 1;
            }
            engine.gpu.wait_idle()?;
            gpu_time += match &self.timer {
                Some(timer) => timer.read(&engine.gpu)?,
                None => batch_start.elapsed(),
            };
            done += batch;
            // Fill about half the remaining budget with the next batch.
            let per_iteration = batch_start.elapsed() / batch;
            if !self.fixed_bands {
                self.bands = bands_for(per_iteration, self.height);
            }
            let remaining = budget.saturating_sub(start.elapsed());
            if remaining.is_zero() {
                break;
            }
            let fit =
                (remaining.as_secs_f64() / per_iteration.as_secs_f64().max(1e-6) * 0.5) as u32;
            if fit == 0 {
                break;
            }
            self.batch = fit.clamp(1, 64);
        }
        Ok(StepReport {
            iterations_done: done,
            iteration: self.iteration,
            converged: self.iteration >= target,
            gpu_time,
        })
    }

    fn output(&self) -> &wgpu::Buffer {
        &self.accum
    }

    fn multiple_scattering(&self) -> bool {
        self.estimator != Estimator::Raymarch
    }

    fn iteration(&self) -> u32 {
        self.iteration
    }

    fn stats(&self) -> TechniqueStats {
        TechniqueStats {
            name: self.name(),
            iteration: self.iteration,
            memory_bytes: accum_bytes(self.width, self.height)
                + self.cell_max_opacity.size()
                + TfTexture::BYTES
                + (MAX_LIGHTS * size_of::<GpuLight>()) as u64
                + size_of::<SceneUniforms>() as u64,
            ..TechniqueStats::default()
        }
    }
}
