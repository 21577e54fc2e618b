//! Technique `manylight` (Weber et al. 2013, ../shared/papers/many-light-transmittance-caching.txt;
//! steps in docs/architecture.md):
//! - single scattering from the real lights by the `raymarch` estimator; multiple scattering
//!   gathered from virtual spherical lights (VSLs) left by random walks from the lights, the
//!   transmittance from each read from its adaptive volumetric shadow map (AVSM) or ray marched;
//! - VSLs and AVSMs are built at the start and after edits of the TF, lights or parameters; a TF
//!   edit retraces only the paths and rebuilds only the maps it can change (historygrams);
//! - the first frame after an edit reuses the previous lights and maps, re-weighted (the
//!   paper's Eq. 6 for TF edits, exact ratios for g and density), then they are rebuilt;
//! - beyond the paper: past the first iteration, every `iterations_per_set` iterations a new,
//!   independent set of light paths is traced and averaged in, so the picture converges
//!   instead of keeping one set's structured error.

mod config;
pub mod gpu;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytemuck::Zeroable;
use voxlight_protocol::{TechniqueDetails, TransferFunction};

use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::manylight::gpu::{
    CHUNK_STRIDE, GatherChunk, MAX_NODES, ManylightParams, TransmittanceMode, VirtualLight,
    avsm_bytes, gather_chunk,
};
use crate::techniques::progressive::{Estimator, Progressive};
use crate::tf::{TF_LUT_SIZE, bake, opacity_query_historygram, query_historygram};
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
    /// Iterations rendered with one set of virtual lights before the next, independent set
    /// is traced (0: one set for the whole picture, as in the paper). With new sets the
    /// picture converges to the VSL-radius-limited answer instead of one set's.
    pub iterations_per_set: u32,
}

impl Default for ManylightConfig {
    /// Sized for interactive use on a software adapter; a GPU server can afford the paper's
    /// 1000 VLs at 48² × 8.
    fn default() -> Self {
        Self {
            vls: 256,
            // Orders past 9 carry a few percent in dense, bright media (−7% in the densest
            // blocks of the Mitsuba comparison with 8); roulette ends most paths well before.
            max_bounces: 32,
            // Each set's maps average out with the sets' (the Mitsuba sun scene measures the
            // same error at 8 as at 16 after 16 iterations, in 40% of the time; the CT at 96
            // iterations the same at 4 as at 8, in 56% of the time, and the time buys sets).
            face_res: 4,
            nodes: 8,
            mode: TransmittanceMode::AvsmTrilinear,
            // About a voxel edge of the 48³ grids. With the kernel that keeps a light's power
            // within the radius (manylight/common.wgsl) the CT's volume blocks measure 1.003 of
            // Mitsuba's mean at 0.025, 1.009 at 0.02 with a little more noise (seeds 1–4, 96
            // iterations: RMSE 4.5% against 4.7%).
            vsl_radius: 0.025,
            iterations_per_set: 1,
        }
    }
}

impl ManylightConfig {
    pub fn vl_count(&self) -> u32 {
        self.vls
    }

    /// Light slots (each with its shadow map): the lights a build stores, plus a quarter for
    /// a TF edit's retraced paths, which may leave more lights than before.
    pub fn slot_count(&self) -> u32 {
        self.vls + self.vls / 4
    }
}

/// Paths traced per stored virtual light at most, before giving up on filling the slots (a
/// nearly empty medium).
const MAX_PATHS_PER_VL: u32 = 256;

/// Largest change of g handled by re-weighting the lights (the second moment of the
/// per-vertex weight f_new/f_old grows fast with it: 1.3 at 0 → 0.3, 3.3 at 0 → 0.6).
const MAX_REWEIGHTED_G_CHANGE: f32 = 0.3;

/// Fewest shadow maps a step rebuilds while a TF edit is carried out progressively.
const MIN_MAPS_PER_STEP: usize = 8;

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
    buffers: Buffers,
    /// Virtual-light slots in use (holes included), and light paths traced for them.
    count: u32,
    paths_traced: u64,
    /// Per traced path, its historygrams (opacity lo, hi, colour lo, hi): also for the paths
    /// that left no light, which a TF edit can make scatter.
    path_hists: Vec<[u32; 4]>,
    /// Per slot, the bins its shadow map's rays crossed (read back after each build).
    map_hists: Vec<u64>,
    /// Density scale and phase asymmetry the lights and maps were built with.
    built_density: f32,
    built_g: f32,
    /// The lights in their slots as traced (before g re-weighting).
    built_lights: Vec<VirtualLight>,
    /// The g the current powers on the GPU are weighted for.
    weighted_g: f32,
    bind_group: wgpu::BindGroup,
    /// The virtual lights and shadow maps no longer match the scene.
    stale: bool,
    /// After an edit, the next step renders one iteration with the previous virtual lights
    /// and shadow maps (the first frame comes at once), and the step after rebuilds them.
    preview_pending: bool,
    /// The TF the lights and maps were built with (a TF edit rebuilds only what it changes).
    built_tf: TransferFunction,
    /// Only TF edits made them stale: a partial rebuild (update_tf) will do.
    tf_only: bool,
    pub last_build: BuildTimes,
    pub last_update: Option<TfUpdate>,
    /// A TF edit's partial rebuild still being carried out, a few maps per step.
    pending: Option<PendingUpdate>,
    /// A full rebuild's maps still to build (`begin_rebuild`), a few per step.
    pending_maps: Option<PendingMaps>,
    /// Which independent set of light paths the slots hold (0 after `new`; each new set in
    /// `step` takes the next; it picks the paths' random numbers).
    light_set: u32,
    /// Iterations completed with the current set.
    set_iterations: u32,
}

/// The rest of a full rebuild in `step`: the lights are traced, the maps of slots
/// `next..count` are still to build.
struct PendingMaps {
    next: u32,
    started: Instant,
    /// How long tracing the lights took.
    vls: Duration,
    /// How long the maps built so far took (their rate sizes the next part).
    building: Duration,
    /// The picture restarts with the new lights (an edit's rebuild), or goes on
    /// averaging (a new independent set of the same scene).
    restarts_picture: bool,
}

/// The rest of a TF edit's partial rebuild.
struct PendingUpdate {
    /// (slot, its new light, whether its map is built), by slot.
    slots: Vec<(u32, VirtualLight, bool)>,
    /// The first slot not yet carried out.
    next: usize,
    started: Instant,
    update: TfUpdate,
}

/// The per-session buffers.
struct Buffers {
    params: wgpu::Buffer,
    vls: wgpu::Buffer,
    avsm: wgpu::Buffer,
    /// Gather chunk descriptors, one per `CHUNK_STRIDE`.
    chunks: wgpu::Buffer,
    /// One tracing batch's virtual lights, `max_bounces` slots per path.
    scratch: wgpu::Buffer,
    /// Data bins per macrocell (RangeGrid::bin_masks), as (lo, hi) words.
    cell_bins: wgpu::Buffer,
    /// Paths to retrace, or slots whose maps to build (ManylightParams::list_count).
    work_list: wgpu::Buffer,
    /// Per slot, (lo, hi) bins its map's rays crossed.
    avsm_hist: wgpu::Buffer,
}

impl Buffers {
    fn bytes(&self) -> u64 {
        [
            &self.params,
            &self.vls,
            &self.avsm,
            &self.chunks,
            &self.scratch,
            &self.cell_bins,
            &self.work_list,
            &self.avsm_hist,
        ]
        .iter()
        .map(|b| b.size())
        .sum()
    }
}

/// What a TF edit's partial rebuild did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TfUpdate {
    pub paths: u64,
    /// Paths whose historygrams met the edit's queries, traced again.
    pub paths_retraced: u64,
    pub lights: u32,
    /// Lights that came from retraced paths (their maps are new).
    pub lights_replaced: u32,
    /// Maps built: the replaced lights' and those whose rays crossed changed opacity.
    pub maps_rebuilt: u32,
    /// The slots could not hold the retraced paths' lights: everything was rebuilt.
    pub full_rebuild: bool,
    pub time: Duration,
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
        let shadow_bytes = avsm_bytes(config.slot_count(), config.face_res, config.nodes);
        let binding_limit = engine.gpu.limits.max_storage_buffer_binding_size;
        // Shadow maps are one storage binding; the build dispatches one z layer per light.
        if shadow_bytes > binding_limit {
            return Err(EngineError::OutOfMemory {
                needed: shadow_bytes,
                available: binding_limit,
            });
        }
        if config.slot_count() > 65535 {
            return Err(EngineError::InvalidScene(format!(
                "manylight: {} virtual lights, at most 65535",
                config.slot_count()
            )));
        }
        let cell_bin_masks = volume.ranges.bin_masks();
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
            config.slot_count() as u64 * size_of::<VirtualLight>() as u64,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let bins: Vec<[u32; 2]> = cell_bin_masks
            .iter()
            .map(|&m| [m as u32, (m >> 32) as u32])
            .collect();
        let cell_bins = buffer(
            "manylight cell bins",
            (bins.len() * 8) as u64,
            wgpu::BufferUsages::STORAGE,
        );
        engine
            .gpu
            .queue
            .write_buffer(&cell_bins, 0, bytemuck::cast_slice(&bins));
        let work_list = buffer(
            "manylight work list",
            BATCH_PATHS.max(config.slot_count()) as u64 * 4,
            wgpu::BufferUsages::STORAGE,
        );
        let avsm_hist = buffer(
            "manylight avsm historygrams",
            config.slot_count() as u64 * 8,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let avsm = buffer("manylight avsm", shadow_bytes, wgpu::BufferUsages::STORAGE);
        let most_chunks = config
            .slot_count()
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
        let buffers = Buffers {
            params,
            vls,
            avsm,
            chunks,
            scratch,
            cell_bins,
            work_list,
            avsm_hist,
        };
        let bind_group = bind_group(engine, &base, &buffers);
        let mut technique = Self {
            base,
            config,
            buffers,
            count: 0,
            paths_traced: 0,
            path_hists: Vec::new(),
            map_hists: Vec::new(),
            built_density: scene.params.density_scale,
            built_g: scene.params.g,
            built_lights: Vec::new(),
            weighted_g: scene.params.g,
            bind_group,
            stale: true,
            preview_pending: false,
            built_tf: scene.tf.clone(),
            tf_only: false,
            last_build: BuildTimes::default(),
            last_update: None,
            pending_maps: None,
            pending: None,
            light_set: 0,
            set_iterations: 0,
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
                &self.buffers.chunks,
                c as u64 * CHUNK_STRIDE,
                bytemuck::bytes_of(&chunk),
            );
        }
    }

    /// The parameters, with `first_path` for a light-tracing batch.
    fn write_params_from(&self, engine: &Engine, scene: &Scene, first_path: u64) {
        let params = self.params_for(scene, first_path);
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.params, 0, bytemuck::bytes_of(&params));
    }

    fn params_for(&self, scene: &Scene, first_path: u64) -> ManylightParams {
        // Stored lights stand for all produced ones when the last batch overflowed the slots.
        let power_scale = self.power_scale() as f32;
        ManylightParams {
            capacity: self.config.slot_count(),
            count: self.count,
            first_path: first_path as u32,
            max_bounces: self.config.max_bounces,
            face_res: self.config.face_res,
            nodes: self.config.nodes,
            mode: self.config.mode as u32,
            seed: light_set_seed(scene.seed, self.light_set),
            vsl_radius: self.config.vsl_radius,
            built_density: self.built_density,
            power_scale,
            list_count: 0,
            fixed_majorant: fixed_majorant(scene, &self.config) as u32,
            pad0: 0,
            pad1: 0,
            pad2: 0,
        }
    }

    fn chunk_count(&self) -> u32 {
        self.config
            .slot_count()
            .div_ceil(gather_chunk(self.config.mode))
    }

    /// Traces the virtual lights and builds their shadow maps now, timing each on its own.
    pub fn rebuild(&mut self, engine: &Engine, scene: &Scene) -> Result<BuildTimes, EngineError> {
        self.rebuild_paths(engine, scene, None)
    }

    /// `rebuild`, or with `paths` set, exactly light paths 0..paths whatever lights they leave
    /// (what a TF edit's partial rebuild must equal; fails when the slots cannot hold them).
    pub fn rebuild_paths(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        paths: Option<u64>,
    ) -> Result<BuildTimes, EngineError> {
        let vls = self.trace_lights(engine, scene, paths)?;
        let started = Instant::now();
        self.build_maps(engine, scene, None)?;
        self.last_build = BuildTimes {
            vls,
            avsm: started.elapsed(),
        };
        Ok(self.last_build)
    }

    /// `rebuild` in parts, for `step`: traces the lights now and leaves their maps to
    /// `advance_maps` (an edit then waits for a few maps, not for all: ~3 s at 512² on
    /// lavapipe). Until the last is built no iteration is rendered.
    fn begin_rebuild(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        restarts_picture: bool,
    ) -> Result<(), EngineError> {
        let vls = self.trace_lights(engine, scene, None)?;
        // Every slot's map words start cleared, as a whole build's do.
        self.clear_map_hists(engine);
        self.pending_maps = Some(PendingMaps {
            next: 0,
            started: Instant::now(),
            vls,
            building: Duration::ZERO,
            restarts_picture,
        });
        Ok(())
    }

    /// Whether the next iteration wants a new independent set of virtual lights: the current
    /// one has served its iterations, and the picture is between iterations past its first
    /// (so a camera drag, which renders first iterations only, never waits for a set).
    fn wants_new_set(&self) -> bool {
        self.config.iterations_per_set > 0
            && self.set_iterations >= self.config.iterations_per_set
            && self.base.iteration() > 0
            && self.base.between_iterations()
    }

    /// Traces the next independent set of light paths; its maps are built by `advance_maps`
    /// while the picture waits (it keeps averaging once they are built).
    fn begin_new_set(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        self.light_set = self.light_set.wrapping_add(1);
        self.begin_rebuild(engine, scene, false)
    }

    /// The light set the slots hold (see `light_set`).
    pub fn light_set(&self) -> u32 {
        self.light_set
    }

    /// Clears every slot's map historygram words (a build of all maps starts from them).
    fn clear_map_hists(&self, engine: &Engine) {
        engine.gpu.queue.write_buffer(
            &self.buffers.avsm_hist,
            0,
            &vec![0u8; self.buffers.avsm_hist.size() as usize],
        );
    }

    /// Builds at most `max_maps` more maps of the full rebuild under way. Blocks.
    fn advance_maps(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        max_maps: usize,
    ) -> Result<(), EngineError> {
        let Some(mut pending) = self.pending_maps.take() else {
            return Ok(());
        };
        let end = (pending.next as usize + max_maps.max(1)).min(self.count as usize) as u32;
        let slots: Vec<u32> = (pending.next..end).collect();
        let started = Instant::now();
        if !slots.is_empty() {
            self.build_maps(engine, scene, Some(&slots))?;
        }
        engine.gpu.wait_idle()?;
        pending.building += started.elapsed();
        pending.next = end;
        if pending.next < self.count {
            self.pending_maps = Some(pending);
        } else {
            self.last_build = BuildTimes {
                vls: pending.vls,
                avsm: pending.started.elapsed(),
            };
        }
        Ok(())
    }

    /// Maps a step builds: half the budget at the rate of the build under way, else of the
    /// last one, at least `MIN_MAPS_PER_STEP` (and that many while no rate is known).
    fn maps_per_step(&self, budget: Duration) -> usize {
        let per_map = match &self.pending_maps {
            Some(p) if p.next > 0 => p.building.as_secs_f64() / p.next as f64,
            _ => self.last_build.avsm.as_secs_f64() / self.count.max(1) as f64,
        };
        if per_map <= 0.0 {
            return MIN_MAPS_PER_STEP;
        }
        ((0.5 * budget.as_secs_f64() / per_map) as usize).max(MIN_MAPS_PER_STEP)
    }

    /// The lights of a rebuild (see `rebuild_paths`), traced and uploaded; their maps are
    /// the caller's. Returns how long it took.
    fn trace_lights(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        paths: Option<u64>,
    ) -> Result<Duration, EngineError> {
        // The passes read the scene uniforms of the next iteration.
        self.base.encode_uniforms(engine, scene)?;
        self.pending = None;
        self.pending_maps = None;
        self.built_density = scene.params.density_scale;
        self.built_g = scene.params.g;
        self.built_tf = scene.tf.clone();
        let started = Instant::now();
        // A build stores `vls` lights; a rebuild of given paths may use every slot.
        let capacity = match paths {
            None => self.config.vls as usize,
            Some(_) => self.config.slot_count() as usize,
        };
        let mut lights: Vec<VirtualLight> = Vec::with_capacity(capacity);
        let mut hists = Vec::new();
        let most = paths.unwrap_or(self.config.vls as u64 * MAX_PATHS_PER_VL as u64);
        // Batches of paths; whole paths are kept in order while they fit, so the set does not
        // depend on scheduling and the paths counted are exactly those kept. (Stopping before
        // the first path that does not fit leaves long paths out a little more often: a bias
        // of the order of 1 / paths. Sets of a fixed path count, tried in stop 33, measured
        // the same means against Mitsuba within their noise.)
        // The first batch is sized by the paths the last set needed (a set of 256 lights
        // takes tens of paths; tracing and reading back 4096 dominated a new set's cost);
        // which paths are kept does not depend on the batch size.
        let mut batch_paths = self.first_batch_paths(paths);
        'batches: while (hists.len() as u64) < most {
            let batch = self.trace_batch(engine, scene, hists.len() as u64, batch_paths, None)?;
            batch_paths = BATCH_PATHS;
            for path in batch.chunks_exact(self.config.max_bounces as usize) {
                let live: Vec<&VirtualLight> = path.iter().filter(|v| v.is_live()).collect();
                if lights.len() + live.len() > capacity {
                    if paths.is_some() {
                        return Err(EngineError::InvalidScene(format!(
                            "manylight: {most} paths leave more than {capacity} virtual lights"
                        )));
                    }
                    break 'batches;
                }
                lights.extend(live);
                hists.push(path_hist(&path[0]));
                if hists.len() as u64 == most || (paths.is_none() && lights.len() == capacity) {
                    break 'batches;
                }
            }
        }
        if !lights.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.buffers.vls, 0, bytemuck::cast_slice(&lights));
        }
        self.paths_traced = hists.len() as u64;
        self.path_hists = hists;
        self.count = lights.len() as u32;
        self.built_lights = lights;
        self.weighted_g = scene.params.g;
        self.set_iterations = 0;
        self.write_params(engine, scene);
        self.stale = false;
        Ok(started.elapsed())
    }

    /// Paths the first tracing batch of a set traces: all `paths` when given, else a quarter
    /// more than the last set kept (at least 64), at most `BATCH_PATHS`.
    fn first_batch_paths(&self, paths: Option<u64>) -> u32 {
        let wanted = match paths {
            Some(p) => p,
            None if self.paths_traced > 0 => (self.paths_traced + self.paths_traced / 4).max(64),
            None => BATCH_PATHS as u64,
        };
        wanted.min(BATCH_PATHS as u64) as u32
    }

    /// Traces one batch of light paths: `count` (at most `BATCH_PATHS`) from `first_path`, or
    /// the listed ones. Returns `max_bounces` slots per path.
    fn trace_batch(
        &self,
        engine: &Engine,
        scene: &Scene,
        first_path: u64,
        count: u32,
        list: Option<&[u32]>,
    ) -> Result<Vec<VirtualLight>, EngineError> {
        self.write_params_from(engine, scene, first_path);
        if let Some(list) = list {
            self.write_list(engine, scene, list);
        }
        let paths = list.map_or(count.min(BATCH_PATHS), |l| l.len() as u32);
        self.submit_pass(
            engine,
            "manylight vls",
            &engine.manylight.vls,
            [paths.div_ceil(64), 1, 1],
        );
        // Only the slots of the paths traced.
        let bytes =
            paths as u64 * self.config.max_bounces as u64 * size_of::<VirtualLight>() as u64;
        let bytes = engine
            .gpu
            .read_buffer_range(&self.buffers.scratch, 0, bytes)?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }

    /// Puts `list` in the work list and its length in the parameters (0 turns it off).
    fn write_list(&self, engine: &Engine, scene: &Scene, list: &[u32]) {
        if !list.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.buffers.work_list, 0, bytemuck::cast_slice(list));
        }
        let mut params: ManylightParams = self.params_for(scene, 0);
        params.list_count = list.len() as u32;
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.params, 0, bytemuck::bytes_of(&params));
    }

    /// Builds the shadow maps of every slot, or of the listed slots, and reads back which
    /// data bins each map's rays crossed. Blocks.
    fn build_maps(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        slots: Option<&[u32]>,
    ) -> Result<(), EngineError> {
        let zero = [0u32; 2];
        match slots {
            None => self.clear_map_hists(engine),
            Some(list) => {
                for &slot in list {
                    engine.gpu.queue.write_buffer(
                        &self.buffers.avsm_hist,
                        slot as u64 * 8,
                        bytemuck::cast_slice(&zero),
                    );
                }
                self.write_list(engine, scene, list);
            }
        }
        let layers = slots.map_or(self.count, |l| l.len() as u32);
        if layers > 0 {
            let r = self.config.face_res;
            self.submit_pass(
                engine,
                "manylight avsm",
                &engine.manylight.avsm,
                [(6 * r * r).div_ceil(64), 1, layers],
            );
        }
        // Back to every slot for the gather.
        self.write_params(engine, scene);
        let bytes = engine.gpu.read_buffer(&self.buffers.avsm_hist)?;
        let words: &[[u32; 2]] = bytemuck::cast_slice(&bytes);
        self.map_hists = words
            .iter()
            .map(|w| w[0] as u64 | (w[1] as u64) << 32)
            .collect();
        Ok(())
    }

    /// A TF edit answered by a full rebuild.
    fn full_update(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        started: Instant,
    ) -> Result<(), EngineError> {
        self.rebuild_paths(engine, scene, None)?;
        let update = TfUpdate {
            paths: self.paths_traced,
            paths_retraced: self.paths_traced,
            lights: self.count,
            lights_replaced: self.count,
            maps_rebuilt: self.count,
            full_rebuild: true,
            time: started.elapsed(),
        };
        self.last_update = Some(update);
        Ok(())
    }

    /// A TF edit from the built TF to `scene.tf`, all at once: traces again only the light
    /// paths whose historygrams meet the edit, puts their lights in the slots the old ones
    /// held (holes with no power where fewer come back), and builds the maps of the new
    /// lights and of the lights whose map rays crossed bins whose opacity changed. The lights
    /// and maps then equal a full rebuild of the same paths with the new TF. Blocks.
    pub fn update_tf(&mut self, engine: &Engine, scene: &Scene) -> Result<TfUpdate, EngineError> {
        self.begin_tf_update(engine, scene)?;
        while self.pending.is_some() {
            self.advance_tf_update(engine, scene, usize::MAX)?;
        }
        Ok(self.last_update.unwrap_or_default())
    }

    /// The first half of `update_tf`: traces the affected paths again and plans which slots
    /// get which light and which maps are built; `advance_tf_update` carries it out, a few
    /// maps at a time (the paper's progressive redistribution), while the other slots keep
    /// their lights and maps. Falls back to a full rebuild when the kept lights were traced
    /// with another density scale or g, or the slots cannot hold the new lights.
    fn begin_tf_update(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        let started = Instant::now();
        // A previous edit's slots still to be carried out hold lights of an older TF: finish
        // it first, so that every slot is of `built_tf` (and a full rebuild's maps, whose
        // map historygrams the update reads).
        while self.pending.is_some() {
            self.advance_tf_update(engine, scene, usize::MAX)?;
        }
        self.advance_maps(engine, scene, usize::MAX)?;
        if scene.params.density_scale != self.built_density || scene.params.g != self.built_g {
            return self.full_update(engine, scene, started);
        }
        let widen = |q: u64| q | (q << 1) | (q >> 1);
        let query = widen(query_historygram(&self.built_tf, &scene.tf));
        let opacity_query = widen(opacity_query_historygram(&self.built_tf, &scene.tf));
        self.base.encode_uniforms(engine, scene)?;
        let affected: Vec<u32> = self
            .path_hists
            .iter()
            .enumerate()
            .filter(|(_, h)| {
                let opacity = h[0] as u64 | (h[1] as u64) << 32;
                let colour = h[2] as u64 | (h[3] as u64) << 32;
                (opacity & opacity_query) | (colour & query) != 0
            })
            .map(|(p, _)| p as u32)
            .collect();
        // Retrace them (the same random numbers per path, the new TF).
        let mut retraced: Vec<VirtualLight> = Vec::new();
        let mut hists = Vec::new();
        for chunk in affected.chunks(BATCH_PATHS as usize) {
            let slots = self.trace_batch(engine, scene, 0, BATCH_PATHS, Some(chunk))?;
            for path in slots.chunks_exact(self.config.max_bounces as usize) {
                hists.push((path[0].path as usize, path_hist(&path[0])));
                retraced.extend(path.iter().filter(|v| v.is_live()));
            }
        }
        // The old lights of those paths leave their slots; the new ones fill them in order.
        let is_affected = |p: u32| affected.binary_search(&p).is_ok();
        let mut free: Vec<u32> = (0..self.count)
            .filter(|&i| {
                let light = &self.built_lights[i as usize];
                light.path == u32::MAX || is_affected(light.path)
            })
            .collect();
        let appended = retraced.len().saturating_sub(free.len());
        if self.count as usize + appended > self.config.slot_count() as usize {
            return self.full_update(engine, scene, started);
        }
        for (path, hist) in hists {
            self.path_hists[path] = hist;
        }
        free.extend(self.count..self.count + appended as u32);
        let hole = VirtualLight {
            path: u32::MAX,
            ..VirtualLight::zeroed()
        };
        let lights_replaced = retraced.len() as u32;
        let mut new_lights = retraced.into_iter();
        // (slot, its light, whether its map is built): the freed slots in order, then the
        // kept lights whose map rays crossed bins whose opacity changed.
        let mut slots: Vec<(u32, VirtualLight, bool)> = free
            .iter()
            .map(|&slot| match new_lights.next() {
                Some(light) => (slot, light, true),
                None => (slot, hole, false),
            })
            .collect();
        slots.extend((0..self.count).filter_map(|i| {
            let light = self.built_lights[i as usize];
            let outdated = light.path != u32::MAX
                && !is_affected(light.path)
                && self
                    .map_hists
                    .get(i as usize)
                    .is_some_and(|&h| h & opacity_query != 0);
            outdated.then_some((i, light, true))
        }));
        slots.sort_by_key(|&(slot, _, _)| slot);
        let maps = slots.iter().filter(|s| s.2).count() as u32;
        self.built_tf = scene.tf.clone();
        self.stale = false;
        self.pending = Some(PendingUpdate {
            slots,
            next: 0,
            started,
            update: TfUpdate {
                paths: self.paths_traced,
                paths_retraced: affected.len() as u64,
                lights: self.count + appended as u32,
                lights_replaced,
                maps_rebuilt: maps,
                full_rebuild: false,
                time: Duration::ZERO,
            },
        });
        Ok(())
    }

    /// Carries out the planned TF update for the next slots, building at most `max_maps`
    /// maps; the lights and maps of those slots change together. Blocks.
    fn advance_tf_update(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        max_maps: usize,
    ) -> Result<(), EngineError> {
        let Some(mut pending) = self.pending.take() else {
            return Ok(());
        };
        let mut maps = Vec::new();
        while let Some(&(slot, light, build)) = pending.slots.get(pending.next) {
            if build && maps.len() >= max_maps.max(1) {
                break;
            }
            pending.next += 1;
            let index = slot as usize;
            if index == self.built_lights.len() {
                self.built_lights.push(light);
            } else {
                self.built_lights[index] = light;
            }
            engine.gpu.queue.write_buffer(
                &self.buffers.vls,
                index as u64 * size_of::<VirtualLight>() as u64,
                bytemuck::bytes_of(&light),
            );
            if build {
                maps.push(slot);
            }
        }
        self.count = self.built_lights.len() as u32;
        self.weighted_g = self.built_g;
        self.write_params(engine, scene);
        if !maps.is_empty() {
            // Only these slots' map words are cleared and rewritten; the others stand.
            self.build_maps(engine, scene, Some(&maps))?;
        }
        engine.gpu.wait_idle()?;
        if pending.next < pending.slots.len() {
            self.pending = Some(pending);
        } else {
            self.last_update = Some(TfUpdate {
                time: pending.started.elapsed(),
                ..pending.update
            });
        }
        Ok(())
    }

    /// One compute pass of `pipeline` over `groups` workgroups, in its own submission.
    fn submit_pass(
        &self,
        engine: &Engine,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        groups: [u32; 3],
    ) {
        let mut encoder = self.encoder(engine, label);
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(label),
                timestamp_writes: None,
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &self.bind_group, &[0]);
            pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
        }
        engine.gpu.queue.submit([encoder.finish()]);
    }

    fn encoder(&self, engine: &Engine, label: &str) -> wgpu::CommandEncoder {
        engine
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// The next band of an iteration (the raymarch estimator's single scattering, then the
    /// gather pass, over the same rows; one submission) and waits for it; returns whether the
    /// iteration completed. A short iteration is one band; a long one (seconds at 512² on a
    /// software adapter) runs as bands of about `progressive::BAND_TIME`, so that an edit
    /// waits for a band, not for the iteration. Bit-exact with a whole iteration: the random
    /// numbers depend on the pixel and the iteration only.
    fn iterate_band(&mut self, engine: &Engine, scene: &Scene) -> Result<bool, EngineError> {
        let started = Instant::now();
        let mut encoder = self.encoder(engine, "manylight iteration");
        let band = self.base.encode_band(engine, scene, &mut encoder)?;
        self.encode_gather(engine, &mut encoder, band.rows);
        engine.gpu.queue.submit([encoder.finish()]);
        engine.gpu.wait_idle()?;
        Ok(self.base.finish_band(started.elapsed()))
    }

    /// Runs every iteration as `bands` bands (tests of the banded path).
    pub fn fix_bands(&mut self, bands: u32) {
        self.base.fix_bands(bands);
    }

    /// Re-weights every light for a new Henyey-Greenstein g without new paths: the directions
    /// leaving each earlier vertex of its path were sampled with the built g, so its power
    /// gains Π f_g(cos) / f_built(cos) over those vertices (exact; the paper's §5.2 keeps the
    /// lights unweighted).
    fn reweight_phase(&mut self, engine: &Engine, g: f32) {
        // The factor of vertex k builds on vertex k − 1's.
        let (by_vertex, order) = self.lights_by_vertex();
        let mut factors = vec![1.0f64; self.built_lights.len()];
        for i in order {
            let light = &self.built_lights[i];
            if light.path == u32::MAX || light.vertices <= 1.0 {
                continue;
            }
            if let Some(&previous) = by_vertex.get(&(light.path, light.vertices as u32 - 1)) {
                let before = self.built_lights[previous].direction;
                let cos = (0..3).map(|k| before[k] * light.direction[k]).sum::<f32>();
                factors[i] =
                    factors[previous] * phase_hg(cos, g) / phase_hg(cos, self.built_g).max(1e-30);
            }
        }
        let factors: Vec<[f64; 3]> = factors.iter().map(|&f| [f; 3]).collect();
        self.upload_weighted(engine, &factors);
        self.weighted_g = g;
    }

    /// Uploads the traced lights with their powers multiplied by `factors` (per slot, rgb).
    fn upload_weighted(&self, engine: &Engine, factors: &[[f64; 3]]) {
        let lights: Vec<VirtualLight> = self
            .built_lights
            .iter()
            .zip(factors)
            .map(|(light, factor)| VirtualLight {
                power: [0, 1, 2].map(|k| (light.power[k] as f64 * factor[k]) as f32),
                ..*light
            })
            .collect();
        if !lights.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.buffers.vls, 0, bytemuck::cast_slice(&lights));
        }
    }

    /// The slot of each light by (path, vertex), and the slots in vertex order (each light
    /// after the earlier vertices of its path).
    fn lights_by_vertex(&self) -> (HashMap<(u32, u32), usize>, Vec<usize>) {
        let mut by_vertex = HashMap::new();
        for (i, light) in self.built_lights.iter().enumerate() {
            if light.path != u32::MAX {
                by_vertex.insert((light.path, light.vertices as u32), i);
            }
        }
        let mut order: Vec<usize> = (0..self.built_lights.len()).collect();
        order.sort_by_key(|&i| self.built_lights[i].vertices as u32);
        (by_vertex, order)
    }

    /// The immediate update after a TF edit (the paper's Eq. 6 with our analog distance
    /// sampling, where T_new / p_new · σs_new at a vertex is its new albedo): every light keeps
    /// its position and map, and its power takes Π albedo_new / albedo_old over the vertices of
    /// its path up to it. Approximate (the positions and maps are the old TF's, and roulette
    /// is not redone); the partial rebuild then replaces what the edit changed. Lights whose
    /// paths the edit cannot change get a factor of exactly 1.
    fn reweight_for_tf(&mut self, engine: &Engine, old: &TransferFunction, new: &TransferFunction) {
        let (old_lut, new_lut) = (bake(old), bake(new));
        let classify = |lut: &[[f32; 4]], v: f32| -> [f32; 4] {
            let x = v.clamp(0.0, 1.0) * (TF_LUT_SIZE - 1) as f32;
            let i = (x as usize).min(TF_LUT_SIZE - 2);
            let f = x - i as f32;
            [0, 1, 2, 3].map(|k| lut[i][k] + (lut[i + 1][k] - lut[i][k]) * f)
        };
        let (by_vertex, order) = self.lights_by_vertex();
        let mut factors = vec![[1.0f64; 3]; self.built_lights.len()];
        for i in order {
            let light = self.built_lights[i];
            if light.path == u32::MAX {
                continue;
            }
            let (a_old, a_new) = (
                classify(&old_lut, light.value),
                classify(&new_lut, light.value),
            );
            let before = by_vertex
                .get(&(light.path, (light.vertices as u32).saturating_sub(1)))
                .filter(|_| light.vertices > 1.0)
                .map_or([1.0; 3], |&p| factors[p]);
            factors[i] = [0, 1, 2].map(|k| {
                let ratio = if a_old[k] > 0.0 {
                    a_new[k] as f64 / a_old[k] as f64
                } else {
                    0.0
                };
                before[k] * ratio
            });
        }
        self.upload_weighted(engine, &factors);
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
        self.advance_maps(engine, scene, usize::MAX)?;
        self.base.encode_uniforms(engine, scene)?;
        engine.gpu.wait_idle()?;
        let started = Instant::now();
        let (_, height) = self.base.size();
        for _ in 0..iterations {
            let mut encoder = self.encoder(engine, "manylight gather timing");
            self.encode_gather(engine, &mut encoder, height);
            engine.gpu.queue.submit([encoder.finish()]);
        }
        engine.gpu.wait_idle()?;
        Ok(started.elapsed())
    }

    /// The gather dispatches of one band of `rows` rows (the scene uniforms' band), one per
    /// chunk of virtual lights.
    fn encode_gather(&self, engine: &Engine, encoder: &mut wgpu::CommandEncoder, rows: u32) {
        let (width, _) = self.base.size();
        let height = rows;
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
        let bytes = engine.gpu.read_buffer(&self.buffers.vls)?;
        Ok(bytemuck::cast_slice(&bytes).to_vec())
    }
}

fn bind_group(engine: &Engine, base: &Progressive, buffers: &Buffers) -> wgpu::BindGroup {
    use crate::passes::builder::{buffer, record};
    let technique = [
        buffer(6, &buffers.params),
        buffer(7, &buffers.vls),
        buffer(8, &buffers.avsm),
        record(9, &buffers.chunks, size_of::<GatherChunk>() as u64),
        buffer(10, &buffers.scratch),
        buffer(11, &buffers.cell_bins),
        buffer(12, &buffers.work_list),
        buffer(13, &buffers.avsm_hist),
    ];
    let entries = [base.bindings().entries().as_slice(), &technique].concat();
    engine
        .manylight
        .layout
        .bind_group(&engine.gpu, "manylight", &entries)
}

/// Whether light paths are tracked against the fixed majorant `density_scale`: it makes their
/// historygrams exact (only the values they read), but a flight through empty space takes
/// about density × length steps, so dense media use the macrocell majorants (historygrams of
/// whole cells' value ranges: an opacity edit then reaches more paths).
fn fixed_majorant(scene: &Scene, config: &ManylightConfig) -> bool {
    // The volume's longest side is 1: a crossing is at most √3 long.
    let steps_per_path =
        scene.params.density_scale as f64 * 3f64.sqrt() * (config.max_bounces + 1) as f64;
    steps_per_path <= FIXED_MAJORANT_STEPS
}

/// Most expected tentative collisions per light path for the fixed majorant (well inside
/// llvmpipe's share of its loop limit per lane, and cheap on any device).
const FIXED_MAJORANT_STEPS: f64 = 2048.0;

/// A path's historygrams as kept per path: opacity lo, hi, colour lo, hi.
fn path_hist(slot: &VirtualLight) -> [u32; 4] {
    [
        slot.opacity_lo,
        slot.opacity_hi,
        slot.colour_lo,
        slot.colour_hi,
    ]
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
                self.bind_group = bind_group(engine, &self.base, &self.buffers);
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
            // A new TF: the light paths and maps it can change are rebuilt (update_tf); until
            // then the lights are re-weighted for the new albedos (the paper's Eq. 6).
            Change::Tf { old, .. } => {
                if self.count > 0 && self.pending.is_none() && self.weighted_g == self.built_g {
                    self.reweight_for_tf(engine, old, &scene.tf);
                }
                // No immediate response from maps a full rebuild has not finished.
                self.preview_pending = self.count > 0 && self.pending_maps.is_none();
                self.tf_only = !self.stale || self.tf_only;
                self.stale = true;
            }
            // New lights or parameters: new light paths and shadow maps.
            Change::Lights | Change::Params => {
                self.preview_pending = self.count > 0 && self.pending_maps.is_none();
                self.tf_only = false;
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
            let completed = loop {
                if self.iterate_band(engine, scene)? {
                    break true;
                }
                if budget.is_zero() || started.elapsed() >= budget {
                    break false;
                }
            };
            self.preview_pending = !completed;
            return Ok(StepReport {
                iterations_done: completed as u32,
                iteration: self.base.iteration(),
                converged: false,
                gpu_time: started.elapsed(),
            });
        }
        if self.stale && self.base.iteration() < target {
            if self.tf_only && self.count > 0 && self.pending_maps.is_none() {
                self.begin_tf_update(engine, scene)?;
            } else {
                self.begin_rebuild(engine, scene, true)?;
            }
            self.tf_only = false;
            self.base.restart();
        }
        let mut done = 0;
        loop {
            if let Some(restarts) = self.pending_maps.as_ref().map(|p| p.restarts_picture) {
                // A full rebuild's maps, in parts; the picture waits for the last.
                self.advance_maps(engine, scene, self.maps_per_step(budget))?;
                if restarts {
                    self.base.restart();
                }
            } else if self.pending.is_some() {
                // A few maps per step, sized to half the budget by the last build's rate. The
                // picture waits for the last of them (the immediate response stays on screen):
                // an iteration between parts would restart with each change of the lights, and
                // on a slow adapter one iteration costs more than the whole rebuild (at 512² on
                // lavapipe an iteration takes 6–9 s, all 256 maps ~3 s).
                self.advance_tf_update(engine, scene, self.maps_per_step(budget))?;
                self.base.restart();
            } else if self.base.iteration() < target {
                if self.wants_new_set() {
                    self.begin_new_set(engine, scene)?;
                } else if self.iterate_band(engine, scene)? {
                    self.set_iterations += 1;
                    done += 1;
                }
            } else {
                break;
            }
            if budget.is_zero() || started.elapsed() >= budget {
                break;
            }
        }
        Ok(StepReport {
            iterations_done: done,
            iteration: self.base.iteration(),
            converged: self.pending.is_none()
                && self.pending_maps.is_none()
                && self.base.iteration() >= target,
            gpu_time: started.elapsed(),
        })
    }

    /// While a TF edit's maps are still being rebuilt the picture is not final, whatever
    /// its iteration count.
    fn target_iterations(&self, scene: &Scene) -> u32 {
        if self.pending.is_some() || self.pending_maps.is_some() {
            scene.target_iterations.max(self.base.iteration() + 1)
        } else {
            scene.target_iterations
        }
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
            memory_bytes: base.memory_bytes + self.buffers.bytes(),
            details: TechniqueDetails {
                virtual_lights: Some(self.count),
                shadow_map_bytes: Some(self.buffers.avsm.size()),
                build_ms: Some((self.last_build.vls + self.last_build.avsm).as_secs_f32() * 1000.0),
                light_paths_retraced_pct: self
                    .last_update
                    .map(|u| 100.0 * u.paths_retraced as f32 / u.paths.max(1) as f32),
                shadow_maps_rebuilt_pct: self
                    .last_update
                    .map(|u| 100.0 * u.maps_rebuilt as f32 / u.lights.max(1) as f32),
                ..base.details
            },
            ..base
        }
    }
}

/// The seed of light set `set`'s paths: the scene's for the first, independent for the others.
fn light_set_seed(seed: u32, set: u32) -> u32 {
    seed ^ set.wrapping_mul(0x9e37_79b9)
}

/// Henyey-Greenstein phase function (shared/common.wgsl's phase_hg).
fn phase_hg(cos_theta: f32, g: f32) -> f64 {
    let (cos_theta, g) = (cos_theta as f64, g as f64);
    let denom = 1.0 + g * g - 2.0 * g * cos_theta;
    (1.0 - g * g) / (4.0 * std::f64::consts::PI * denom * denom.sqrt())
}
