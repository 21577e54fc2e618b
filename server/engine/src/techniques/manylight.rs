//! Technique `manylight` (Weber et al. 2013, ../shared/papers/many-light-transmittance-caching.txt):
//! single scattering from the real lights by the `raymarch` estimator, plus multiple scattering
//! gathered from virtual spherical lights (VSLs) left by random walks from the lights, with the
//! transmittance from each VSL read from its adaptive volumetric shadow map (AVSM) or, as the
//! baseline, ray marched. The VSLs and AVSMs are built when the session starts and rebuilt
//! after edits of the TF, lights or parameters; iterations then refine the picture (pixel and
//! scattering-location jitter) with the same virtual lights. After an edit the first frame
//! reuses the previous virtual lights and shadow maps (an immediate, approximate response; the
//! paper first re-weights them with its Eq. 6, which is not done here), then they are rebuilt
//! and the picture restarts.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::passes::manylight::{
    CHUNK_STRIDE, GatherChunk, MAX_NODES, ManylightParams, TransmittanceMode, VirtualLight,
    avsm_bytes, gather_chunk,
};
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::progressive::{Estimator, Progressive};
use crate::{Change, Engine, EngineError, GpuVolume, Scene};

/// The knobs of `manylight`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ManylightConfig {
    /// Virtual lights: light paths are traced until this many scattering events are stored.
    pub vls: u32,
    /// Most virtual lights one path leaves (scattering orders gathered: up to this + 1).
    pub max_bounces: u32,
    /// AVSM texels per cube-face edge (the paper: 40–48).
    pub face_res: u32,
    /// AVSM nodes per texel (the paper: 8–12).
    pub nodes: u32,
    pub mode: TransmittanceMode,
    /// VSL radius in world units (the volume's longest side is 1).
    pub vsl_radius: f32,
}

impl Default for ManylightConfig {
    /// Sized for interactive use on a software adapter; a GPU server can afford the paper's
    /// 1000 VLs at 48² × 8.
    fn default() -> Self {
        Self {
            vls: 256,
            max_bounces: 8,
            face_res: 16,
            nodes: 8,
            mode: TransmittanceMode::AvsmTrilinear,
            vsl_radius: 0.02,
        }
    }
}

impl ManylightConfig {
    pub fn vl_count(&self) -> u32 {
        self.vls
    }
}

/// Paths traced per stored virtual light at most, before giving up on filling the slots (a
/// nearly empty medium).
const MAX_PATHS_PER_VL: u32 = 256;

/// Largest change of g handled by re-weighting the lights (the second moment of the
/// per-vertex weight f_new/f_old grows fast with it: 1.3 at 0 → 0.3, 3.3 at 0 → 0.6).
const MAX_REWEIGHTED_G_CHANGE: f32 = 0.3;

/// Light paths per tracing batch (the scratch buffer holds `max_bounces` lights for each).
const BATCH_PATHS: u32 = 4096;

/// How long the last rebuild of the virtual lights and their shadow maps took.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BuildTimes {
    pub vls: Duration,
    pub avsm: Duration,
}

pub struct Manylight {
    base: Progressive,
    config: ManylightConfig,
    params: wgpu::Buffer,
    vls: wgpu::Buffer,
    avsm: wgpu::Buffer,
    /// Gather chunk descriptors, one per `CHUNK_STRIDE`.
    chunks: wgpu::Buffer,
    /// One tracing batch's virtual lights, `max_bounces` slots per path.
    scratch: wgpu::Buffer,
    /// Virtual lights held, and light paths traced to produce them.
    count: u32,
    paths_traced: u64,
    /// Density scale and phase asymmetry the lights and maps were built with.
    built_density: f32,
    built_g: f32,
    /// The lights as traced (path by path, in order), for exact re-weighting on g edits.
    built_lights: Vec<VirtualLight>,
    /// The g the current powers on the GPU are weighted for.
    weighted_g: f32,
    bind_group: wgpu::BindGroup,
    /// The virtual lights and shadow maps no longer match the scene.
    stale: bool,
    /// After an edit, the next step renders one iteration with the previous virtual lights
    /// and shadow maps (the first frame comes at once), and the step after rebuilds them.
    preview_pending: bool,
    pub last_build: BuildTimes,
}

impl Manylight {
    pub fn new(
        engine: &Engine,
        volume: Arc<GpuVolume>,
        scene: &Scene,
        config: ManylightConfig,
    ) -> Result<Self, EngineError> {
        if config.vls == 0
            || config.max_bounces == 0
            || config.face_res == 0
            || !(2..=MAX_NODES).contains(&config.nodes)
            || !config.vsl_radius.is_finite()
            || config.vsl_radius <= 0.0
        {
            return Err(EngineError::InvalidScene(format!(
                "manylight: bad configuration {config:?}"
            )));
        }
        let shadow_bytes = avsm_bytes(config.vl_count(), config.face_res, config.nodes);
        let binding_limit = engine.gpu.limits.max_storage_buffer_binding_size;
        // Shadow maps are one storage binding; the build dispatches one z layer per light.
        if shadow_bytes > binding_limit {
            return Err(EngineError::OutOfMemory {
                needed: shadow_bytes,
                available: binding_limit,
            });
        }
        if config.vl_count() > 65535 {
            return Err(EngineError::InvalidScene(format!(
                "manylight: {} virtual lights, at most 65535",
                config.vl_count()
            )));
        }
        let base = Progressive::new(engine, Estimator::Raymarch, volume, scene)?;
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            engine.gpu.buffer(label, size, usage)
        };
        let params = buffer(
            "manylight params",
            size_of::<ManylightParams>() as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let vls = buffer(
            "manylight virtual lights",
            config.vl_count() as u64 * size_of::<VirtualLight>() as u64,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let avsm = buffer("manylight avsm", shadow_bytes, wgpu::BufferUsages::STORAGE);
        let most_chunks = config
            .vl_count()
            .div_ceil(gather_chunk(TransmittanceMode::RayMarched));
        let chunks = buffer(
            "manylight gather chunks",
            most_chunks as u64 * CHUNK_STRIDE,
            wgpu::BufferUsages::UNIFORM,
        );
        let scratch = buffer(
            "manylight vl scratch",
            BATCH_PATHS as u64 * config.max_bounces as u64 * size_of::<VirtualLight>() as u64,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let bind_group = bind_group(engine, &base, &params, &vls, &avsm, &chunks, &scratch);
        let mut technique = Self {
            base,
            config,
            params,
            vls,
            avsm,
            chunks,
            scratch,
            count: 0,
            paths_traced: 0,
            built_density: scene.params.density_scale,
            built_g: scene.params.g,
            built_lights: Vec::new(),
            weighted_g: scene.params.g,
            bind_group,
            stale: true,
            preview_pending: false,
            last_build: BuildTimes::default(),
        };
        technique.write_params(engine, scene);
        Ok(technique)
    }

    pub fn config(&self) -> ManylightConfig {
        self.config
    }

    /// Switches how transmittance from the virtual lights is found (the picture restarts).
    pub fn set_mode(&mut self, engine: &Engine, scene: &Scene, mode: TransmittanceMode) {
        self.config.mode = mode;
        self.write_params(engine, scene);
        self.base.restart();
    }

    fn write_params(&mut self, engine: &Engine, scene: &Scene) {
        self.write_params_from(engine, scene, 0);
        let queue = &engine.gpu.queue;
        let size = gather_chunk(self.config.mode);
        for c in 0..self.chunk_count() {
            let chunk = GatherChunk {
                first: c * size,
                count: size,
                pad0: 0,
                pad1: 0,
            };
            queue.write_buffer(
                &self.chunks,
                c as u64 * CHUNK_STRIDE,
                bytemuck::bytes_of(&chunk),
            );
        }
    }

    /// The parameters, with `first_path` for a light-tracing batch.
    fn write_params_from(&self, engine: &Engine, scene: &Scene, first_path: u64) {
        // Stored lights stand for all produced ones when the last batch overflowed the slots.
        let power_scale = self.power_scale() as f32;
        let params = ManylightParams {
            capacity: self.config.vls,
            count: self.count,
            first_path: first_path as u32,
            max_bounces: self.config.max_bounces,
            face_res: self.config.face_res,
            nodes: self.config.nodes,
            mode: self.config.mode as u32,
            seed: scene.seed,
            vsl_radius: self.config.vsl_radius,
            built_density: self.built_density,
            power_scale,
            pad0: 0.0,
        };
        engine
            .gpu
            .queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
    }

    fn chunk_count(&self) -> u32 {
        self.config
            .vl_count()
            .div_ceil(gather_chunk(self.config.mode))
    }

    /// Traces the virtual lights and builds their shadow maps now, timing each on its own.
    pub fn rebuild(&mut self, engine: &Engine, scene: &Scene) -> Result<BuildTimes, EngineError> {
        // The passes read the scene uniforms of the next iteration.
        self.base.encode_uniforms(engine, scene)?;
        self.built_density = scene.params.density_scale;
        self.built_g = scene.params.g;
        let started = Instant::now();
        let capacity = self.config.vls as usize;
        let mut lights: Vec<VirtualLight> = Vec::with_capacity(capacity);
        let mut traced = 0u64;
        let per_path_slots = self.config.max_bounces as usize;
        // Batches of paths; whole paths are kept in order while they fit, so the set does not
        // depend on scheduling and the paths counted are exactly those kept (unbiased).
        'batches: while traced < capacity as u64 * MAX_PATHS_PER_VL as u64 {
            self.write_params_from(engine, scene, traced);
            let mut encoder = self.encoder(engine, "manylight vls");
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("manylight vls"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(&engine.manylight.vls);
                pass.set_bind_group(0, &self.bind_group, &[0]);
                pass.dispatch_workgroups(BATCH_PATHS / 64, 1, 1);
            }
            engine.gpu.queue.submit([encoder.finish()]);
            let bytes = engine.gpu.read_buffer(&self.scratch)?;
            let batch: &[VirtualLight] = bytemuck::cast_slice(&bytes);
            for path in batch.chunks_exact(per_path_slots) {
                let live: Vec<&VirtualLight> = path
                    .iter()
                    .filter(|v| v.power.iter().any(|&p| p > 0.0))
                    .collect();
                if lights.len() + live.len() > capacity {
                    break 'batches;
                }
                lights.extend(live);
                traced += 1;
                if lights.len() == capacity {
                    break 'batches;
                }
            }
        }
        if !lights.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.vls, 0, bytemuck::cast_slice(&lights));
        }
        self.paths_traced = traced;
        self.count = lights.len() as u32;
        self.built_lights = lights;
        self.weighted_g = scene.params.g;
        self.write_params(engine, scene);
        let vls = started.elapsed();
        let started = Instant::now();
        let mut encoder = self.encoder(engine, "manylight avsm");
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("manylight avsm"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&engine.manylight.avsm);
            pass.set_bind_group(0, &self.bind_group, &[0]);
            let r = self.config.face_res;
            pass.dispatch_workgroups(r.div_ceil(8), (6 * r).div_ceil(8), self.count.max(1));
        }
        engine.gpu.queue.submit([encoder.finish()]);
        engine.gpu.wait_idle()?;
        self.last_build = BuildTimes {
            vls,
            avsm: started.elapsed(),
        };
        self.stale = false;
        Ok(self.last_build)
    }

    fn encoder(&self, engine: &Engine, label: &str) -> wgpu::CommandEncoder {
        engine
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// One iteration: the raymarch estimator's single scattering, then the gather pass.
    fn iterate(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        let mut encoder = self.encoder(engine, "manylight iteration");
        self.base.encode_next(engine, scene, &mut encoder)?;
        self.encode_gather(engine, &mut encoder);
        engine.gpu.queue.submit([encoder.finish()]);
        self.base.advance();
        Ok(())
    }

    /// Re-weights every light for a new Henyey-Greenstein g without new paths: the directions
    /// leaving each earlier vertex of its path were sampled with the built g, so its power
    /// gains Π f_g(cos) / f_built(cos) over those vertices (exact; the paper's §5.2 keeps the
    /// lights unweighted).
    fn reweight_phase(&mut self, engine: &Engine, g: f32) {
        let mut lights = self.built_lights.clone();
        let mut factor = 1.0f64;
        for (k, light) in lights.iter_mut().enumerate() {
            if light.vertices <= 1.0 {
                factor = 1.0; // a new path
            } else {
                let previous = self.built_lights[k - 1].direction;
                let cos = (0..3)
                    .map(|i| previous[i] * light.direction[i])
                    .sum::<f32>();
                factor *= phase_hg(cos, g) / phase_hg(cos, self.built_g).max(1e-30);
            }
            for c in &mut light.power {
                *c = (*c as f64 * factor) as f32;
            }
        }
        if !lights.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.vls, 0, bytemuck::cast_slice(&lights));
        }
        self.weighted_g = g;
    }

    /// Runs `iterations` gather passes alone (no single scattering) and waits: the cost of
    /// multiple scattering with the current transmittance mode (benchmarks).
    pub fn time_gather(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        iterations: u32,
    ) -> Result<Duration, EngineError> {
        if self.stale {
            self.rebuild(engine, scene)?;
        }
        self.base.encode_uniforms(engine, scene)?;
        engine.gpu.wait_idle()?;
        let started = Instant::now();
        for _ in 0..iterations {
            let mut encoder = self.encoder(engine, "manylight gather timing");
            self.encode_gather(engine, &mut encoder);
            engine.gpu.queue.submit([encoder.finish()]);
        }
        engine.gpu.wait_idle()?;
        Ok(started.elapsed())
    }

    /// The gather dispatches of one iteration, one per chunk of virtual lights.
    fn encode_gather(&self, engine: &Engine, encoder: &mut wgpu::CommandEncoder) {
        let (width, height) = self.base.size();
        let tile = crate::passes::TILE;
        for c in 0..self.chunk_count() {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("manylight gather"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&engine.manylight.gather);
            pass.set_bind_group(0, &self.bind_group, &[(c as u64 * CHUNK_STRIDE) as u32]);
            pass.dispatch_workgroups(width.div_ceil(tile), height.div_ceil(tile), 1);
        }
    }

    /// Virtual lights held after the last build, and the light paths traced for them.
    pub fn virtual_light_count(&self) -> (u32, u64) {
        (self.count, self.paths_traced)
    }

    /// What each stored light's power is multiplied by in the gather: 1 / paths kept.
    pub fn power_scale(&self) -> f64 {
        if self.paths_traced == 0 {
            0.0
        } else {
            1.0 / self.paths_traced as f64
        }
    }

    /// The virtual lights as traced (for tests).
    pub fn read_virtual_lights(&self, engine: &Engine) -> Result<Vec<VirtualLight>, EngineError> {
        let bytes = engine.gpu.read_buffer(&self.vls)?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }
}

fn bind_group(
    engine: &Engine,
    base: &Progressive,
    params: &wgpu::Buffer,
    vls: &wgpu::Buffer,
    avsm: &wgpu::Buffer,
    chunks: &wgpu::Buffer,
    scratch: &wgpu::Buffer,
) -> wgpu::BindGroup {
    let b = base.bindings();
    fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
        wgpu::BindGroupEntry {
            binding,
            resource: buffer.as_entire_binding(),
        }
    }
    engine
        .gpu
        .device
        .create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("manylight"),
            layout: &engine.manylight.layout,
            entries: &[
                entry(0, b.scene),
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(b.volume),
                },
                entry(2, b.tf_lut),
                entry(3, b.lights),
                entry(4, b.accum),
                entry(5, b.cell_max_opacity),
                entry(6, params),
                entry(7, vls),
                entry(8, avsm),
                wgpu::BindGroupEntry {
                    binding: 9,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: chunks,
                        offset: 0,
                        size: wgpu::BufferSize::new(size_of::<GatherChunk>() as u64),
                    }),
                },
                entry(10, scratch),
            ],
        })
}

impl Technique for Manylight {
    fn name(&self) -> &'static str {
        "manylight"
    }

    fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        self.base.apply(engine, scene, change)?;
        match change {
            Change::Viewport => {
                self.bind_group = bind_group(
                    engine,
                    &self.base,
                    &self.params,
                    &self.vls,
                    &self.avsm,
                    &self.chunks,
                    &self.scratch,
                );
            }
            // A new density scale re-weights the lights and rescales their maps exactly
            // (T^(s/s_built), the paper's §5); exposure is display only; a new g re-weights
            // their powers exactly, unless it moved so far from the traced one that the
            // weights' variance would swamp the picture: then new paths.
            Change::Params if (scene.params.g - self.built_g).abs() <= MAX_REWEIGHTED_G_CHANGE => {
                if scene.params.g != self.weighted_g {
                    self.reweight_phase(engine, scene.params.g);
                }
            }
            // A new medium or new lights: new light paths and shadow maps.
            Change::Tf { .. } | Change::Lights | Change::Params => {
                self.preview_pending = self.count > 0;
                self.stale = true;
            }
            Change::Camera | Change::Iterations => {}
        }
        Ok(())
    }

    fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError> {
        let started = Instant::now();
        let target = scene.target_iterations;
        if self.stale && self.preview_pending && self.base.iteration() < target {
            // The immediate response: the new TF/lights for single scattering and the view,
            // the previous virtual lights for multiple scattering; discarded once rebuilt.
            self.preview_pending = false;
            self.iterate(engine, scene)?;
            engine.gpu.wait_idle()?;
            return Ok(StepReport {
                iterations_done: 1,
                iteration: self.base.iteration(),
                converged: false,
                gpu_time: started.elapsed(),
            });
        }
        if self.stale && self.base.iteration() < target {
            self.rebuild(engine, scene)?;
            self.base.restart();
        }
        let mut done = 0;
        while self.base.iteration() < target {
            self.iterate(engine, scene)?;
            done += 1;
            engine.gpu.wait_idle()?;
            if budget.is_zero() || started.elapsed() >= budget {
                break;
            }
        }
        Ok(StepReport {
            iterations_done: done,
            iteration: self.base.iteration(),
            converged: self.base.iteration() >= target,
            gpu_time: started.elapsed(),
        })
    }

    fn output(&self) -> &wgpu::Buffer {
        self.base.output()
    }

    fn iteration(&self) -> u32 {
        self.base.iteration()
    }

    fn stats(&self) -> TechniqueStats {
        let base = self.base.stats();
        TechniqueStats {
            name: self.name(),
            memory_bytes: base.memory_bytes
                + self.vls.size()
                + self.avsm.size()
                + self.params.size()
                + self.chunks.size()
                + self.scratch.size(),
            virtual_lights: Some(self.count),
            shadow_map_bytes: Some(self.avsm.size()),
            build_ms: Some((self.last_build.vls + self.last_build.avsm).as_secs_f32() * 1000.0),
            ..base
        }
    }
}

/// Henyey-Greenstein phase function (common.wgsl's phase_hg).
fn phase_hg(cos_theta: f32, g: f32) -> f64 {
    let (cos_theta, g) = (cos_theta as f64, g as f64);
    let denom = 1.0 + g * g - 2.0 * g * cos_theta;
    (1.0 - g * g) / (4.0 * std::f64::consts::PI * denom * denom.sqrt())
}
