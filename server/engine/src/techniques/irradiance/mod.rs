//! Technique `irradiance`: Monte-Carlo volume rendering whose first scattering event takes its
//! irradiance from a cache built while rendering (Khlebnikov et al. 2014,
//! ../shared/papers/parallel-irradiance-caching.txt; its steps and how the paper's megakernel
//! became frames of dispatches are in docs/architecture.md, "`irradiance`").
//!
//! - Each frame runs the paper's three procedures in its time fractions (§4.1, §6): rendering
//!   16 × 8 blocks (optionally by "expected gain" priorities), entry creation (the 7-point
//!   estimate, ellipsoidal zones along the extinction gradient, §4.2) and update (radius
//!   reduction where entries disagree, §4.3); `rounds_owed` / `DispatchPlan` plan it.
//! - Entries live in a multi-reference octree built on the CPU (`octree`, §4.4); object- or
//!   screen-space locking keeps neighbouring misses from creating the same entry (§5).
//!
//! Beyond the paper:
//! - the cached irradiance includes multiple scattering (its future work): entries' samples are
//!   full paths (up to `bounces` − 1 more events), so the picture converges to `pathtrace`'s for
//!   an isotropic phase function; `bounces` = 1 is the paper's single scattering;
//! - each entry carries the historygrams of the data bins its estimate depended on (through
//!   extinction: every macrocell its rays crossed; through albedo: its paths' vertices), so a TF
//!   edit drops only the entries it can change (`Invalidation::Historygram`);
//! - the seven estimation points share their random numbers, which makes the irradiance ratios
//!   of Eq. 6 far steadier than independent estimates;
//! - every step runs in a fixed order, so a run with a fixed schedule is repeatable.
//!
//! The cache assumes an isotropic phase function at the first scattering event (as the paper);
//! with |g| > 0.001 the technique renders plain MCVR and says so in its stats.

mod config;
pub mod gpu;
pub mod octree;

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use voxlight_protocol::{Light, TechniqueDetails, TransferFunction};

use crate::scene_gpu::gpu_lights;
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::irradiance::gpu::{
    BLOCK_HEIGHT, BLOCK_WIDTH, COUNTER_CREATED, COUNTER_DROPPED, COUNTER_ENTRIES, COUNTER_HITS,
    COUNTER_ISSUED, COUNTER_LOST, COUNTER_MISSES, COUNTER_PENDING, COUNTER_REDUCTIONS,
    COUNTER_WORDS, CacheEntry, DISPATCH_STRIDE, DispatchInfo, FLAG_CACHE, FLAG_MARCHED_VIEW,
    FLAG_NO_CREATION, FLAG_SAMPLED_HISTORYGRAMS, FLAG_SCREEN_LOCKING, FLAG_TRACED_DIRECT,
    FLAG_VALIDATE_HITS, IrradianceBindGroups, IrradianceBindings, IrradianceParams,
    PRIORITY_UNSAMPLED, Pass, Request, UPDATE_WORKGROUP,
};
use crate::techniques::progressive::{Estimator, Progressive, accum_bytes};
use crate::tf::{opacity_query_historygram, query_historygram};
use crate::{Change, Engine, EngineError, GpuVolume, Scene};
use octree::{Octree, zone_half_extent};

/// Which primitive a cache miss locks before it may request a new entry (§5).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Locking {
    /// The deepest octree node holding the miss.
    Object,
    /// The miss's 16 × 8 block of the image, after a rejection test on the block's share of
    /// misses.
    Screen,
}

/// What a TF edit does to the cache.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Invalidation {
    /// Drop the entries whose historygrams meet the edit's query historygrams.
    Historygram,
    /// Drop every entry (what the paper does).
    Clear,
}

/// What an entry's opacity historygram records of the rays its estimate marched or tracked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Historygrams {
    /// The bins of every value sampled (every voxel-step of a marched shadow ray, every
    /// tentative collision of a tracked one), and all bins of macrocells skipped as empty: as
    /// the historygram paper records a ray-marched path. A feature thinner than the samples'
    /// spacing can be missed.
    Samples,
    /// All bins any value of each macrocell crossed can take: conservative (an edit that
    /// could change the estimate always drops it), but coarse.
    Cells,
}

/// How a camera ray finds its scattering event.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ViewEvent {
    /// Delta tracking to the first collision, as Exposure Render: a ray either collides or
    /// not, a variance of its own in thin media.
    DeltaTracking,
    /// Picked among a jittered march's samples in proportion to T·(1 − e^(−σt·dt)), the
    /// march's total weight and transmittance exact (the `raymarch` estimator): only where
    /// along the ray remains random.
    Marched,
}

/// What a cache entry's irradiance holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CachedLight {
    /// All the light arriving at the entry, the directional and point lights' direct light
    /// included (the paper). Its shadow edges are interpolated across zones.
    All,
    /// Only the indirect light (the environment and light the medium scattered): the render
    /// pass traces the directional and point lights' direct light at its event with a shadow
    /// ray. Where there is no indirect light (single scattering without an environment) the
    /// cache holds all the light instead.
    Indirect,
}

/// The knobs of `irradiance`; the defaults are the paper's Table 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IrradianceConfig {
    /// Use the cache (false: plain MCVR with the same estimator, the paper's baseline).
    pub cache: bool,
    /// What entries hold (beyond the paper: `Indirect` by default).
    pub cached_light: CachedLight,
    pub locking: Locking,
    /// Draw the blocks to render by "expected gain" (Eq. 12) instead of in turn.
    pub priorities: bool,
    /// Most scattering events on a camera path (1: single scattering, as in the paper).
    pub bounces: u32,
    /// γ: accepted relative error of an entry's irradiance estimate (Eq. 5).
    pub gamma: f32,
    /// ε: accepted relative extrapolation error at a zone's edge (Eq. 9–10).
    pub epsilon: f32,
    /// Δ, the offset of the six extra estimation points, in voxels.
    pub delta_voxels: f32,
    /// Δ is at most this many mean free paths at the entry's centre (0: always
    /// `delta_voxels`). In dense media the irradiance falls by e within a free path, far below
    /// two voxels: a stencil two voxels wide cannot see that, and a zone is never narrower
    /// than its Δ (Eq. 9).
    pub delta_free_paths: f32,
    pub min_radius_voxels: f32,
    pub max_radius_voxels: f32,
    /// Relative disagreement of overlapping entries the update resolves.
    pub update_threshold: f32,
    /// Share of a frame for creating entries (min, max) and for updating them (min, max), and
    /// the exponent of the hit rate that moves them (§6).
    pub creation_fraction: (f32, f32),
    pub update_fraction: (f32, f32),
    pub fraction_exponent: f32,
    /// Entries being created at once (None: the paper's 1000 scaled to the viewport from
    /// 1280 × 720, at least 16).
    pub max_pending: Option<u32>,
    pub entry_capacity: u32,
    /// Samples per estimation point before Eq. 5 may stop the estimate, and at most.
    pub min_samples: u32,
    pub max_samples: u32,
    /// Where an entry's irradiance is darker than this fraction of the scene's brightest
    /// unshadowed irradiance, Eq. 5 bounds its error relative to that floor instead: a shadowed
    /// entry need not be estimated to 10% of almost nothing (the paper's purely relative
    /// bound spends its largest sample counts where the picture is black).
    pub dark_floor: f32,
    /// Frames of this length (equal-time comparisons): rendering gets what creation and update
    /// leave, as many blocks as fit. None: one image's worth of blocks per frame.
    pub frame_time: Option<Duration>,
    pub invalidation: Invalidation,
    pub historygrams: Historygrams,
    pub view_event: ViewEvent,
    /// Scattering events per camera sample with `ViewEvent::Marched` (1–16), drawn by
    /// systematic resampling along the march. Where the direct light is traced (no cache, or
    /// `CachedLight::Indirect`) each event gets a shadow ray per light and one of them, chosen
    /// uniformly, the cache lookup or the traced path for the rest; with `CachedLight::All`
    /// each costs a lookup and one of those the cache misses is path traced for all of them.
    pub view_picks: u32,
    /// Beyond the paper: the update also estimates the irradiance afresh at its point and
    /// shrinks every entry whose prediction there lies outside that estimate's 95% interval
    /// widened by the update threshold (a shadow edge cast into a zone from outside it, which
    /// the zone's own stencil cannot see; the paper's update only compares entries).
    pub validate_hits: bool,
    /// Beyond the paper: share of a frame for validation rounds of their own (0: none). A
    /// validation round checks one point per 16 × 8 block as `validate_hits` does, and only
    /// that: at the update's 1–2% of a frame too few points are checked to find the zones a
    /// shadow edge crosses (the cache of all the light stayed 1.6–3.4% too bright).
    pub validation_fraction: f32,
    /// Validation rounds per frame instead of `validation_fraction` (repeatable runs; with
    /// `fixed_rounds` and None, no validation rounds).
    pub validation_rounds: Option<u32>,
    /// Validation rounds: the relative disagreement, beyond the fresh estimate's 95% interval,
    /// at which an entry is shrunk (a zone's own extrapolation may err by ε at its edge, so
    /// below ε this also trims zones that are only as wrong as Eq. 9–10 allow), and the
    /// samples of that estimate.
    pub validation_threshold: f32,
    pub validation_samples: u32,
    /// How often the octree is rebuilt with the radii the update shrank.
    pub rebuild_interval: Duration,
    /// Time over which the hit rate is measured.
    pub hit_rate_window: Duration,
    /// Creation and update rounds per frame instead of time fractions (repeatable runs).
    pub fixed_rounds: Option<(u32, u32)>,
    /// The octree starts complete to this depth (8^depth object-space locks). None: deep
    /// enough for eight locks per pending entry (2–4).
    pub lock_depth: Option<u32>,
}

impl Default for IrradianceConfig {
    fn default() -> Self {
        Self {
            cache: true,
            cached_light: CachedLight::Indirect,
            locking: Locking::Object,
            priorities: true,
            bounces: DEFAULT_BOUNCES,
            gamma: 0.1,
            epsilon: 0.1,
            delta_voxels: 2.0,
            delta_free_paths: 1.0,
            min_radius_voxels: 0.01,
            // The paper's 16 voxels extrapolate far past the stencil (Δ = 2 voxels): on the CTs
            // of ../shared/data at 64³ that biased pixels by 15–20% RMS against a converged
            // reference, 4 voxels by 5–7% (docs/benchmarks.md).
            max_radius_voxels: 4.0,
            update_threshold: 0.1,
            creation_fraction: (0.05, 0.15),
            update_fraction: (0.01, 0.02),
            fraction_exponent: 3.0,
            max_pending: None,
            entry_capacity: 32768,
            min_samples: 16,
            max_samples: 256,
            dark_floor: 0.05,
            frame_time: None,
            invalidation: Invalidation::Historygram,
            historygrams: Historygrams::Samples,
            view_event: ViewEvent::Marched,
            // A second event shares the march and costs a shadow ray per light: with multiple
            // scattering plain MCVR's variance per sample fell by 11–29% at the same frame time
            // on lavapipe; more did not pay (docs/benchmarks.md).
            view_picks: 2,
            validate_hits: false,
            validation_fraction: 0.0,
            validation_rounds: None,
            validation_threshold: 0.1,
            validation_samples: 8,
            rebuild_interval: Duration::from_millis(1000),
            hit_rate_window: Duration::from_millis(100),
            fixed_rounds: None,
            lock_depth: None,
        }
    }
}

/// Scattering events a camera path may have by default (as `pathtrace`, MAX_BOUNCES in
/// shared/path.wgsl).
pub const DEFAULT_BOUNCES: u32 = 1024;

/// |g| above which the cache (isotropic at the first event) is not used.
const ISOTROPIC_G: f32 = 1e-3;

/// Render passes per frame at most (a block is rendered at most this often in one frame).
const MAX_RENDER_PASSES: usize = 8;
/// Creation, update and validation rounds per frame at most.
const MAX_CREATE_ROUNDS: u32 = 48;
const MAX_UPDATE_ROUNDS: u32 = 16;
const MAX_VALIDATION_ROUNDS: u32 = 32;
/// Dispatch descriptors per frame.
const DISPATCH_SLOTS: u32 = 128;
/// Workgroups one dispatch may have along x.
const MAX_WORKGROUPS: usize = 65535;
/// The phases of a frame that are timed: rendering, creation, update, validation, the rest.
const PHASES: usize = 5;
const PHASE_RENDER: usize = 0;
const PHASE_CREATE: usize = 1;
const PHASE_UPDATE: usize = 2;
const PHASE_VALIDATE: usize = 3;
const PHASE_TAIL: usize = 4;
/// The paper's pending entries and the viewport they were set for (Table 1).
const PAPER_PENDING: f64 = 1000.0;
const PAPER_PIXELS: f64 = 1280.0 * 720.0;

/// What the cache holds and did; `stats` and benchmarks report it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CacheStats {
    pub entries: u32,
    pub references: u64,
    pub octree_nodes: u32,
    pub pending: u32,
    /// Hit rate over the last `hit_rate_window`.
    pub hit_rate: f32,
    pub hits: u64,
    pub misses: u64,
    pub created: u64,
    pub requests_issued: u64,
    /// Requests refused because the pending list or the cache was full.
    pub requests_dropped: u64,
    pub radius_reductions: u64,
    /// Whether the cache is in use (not with an anisotropic phase function or `cache` off).
    pub active: bool,
    /// The last TF edit: entries before it and entries kept.
    pub last_edit: Option<(u32, u32)>,
    pub creation_rounds: u64,
    pub update_rounds: u64,
    pub validation_rounds: u64,
}

/// A copy of the cache (benchmarks compare TF-edit strategies from one state).
#[derive(Debug, Clone)]
pub struct CacheSnapshot {
    pub entries: Vec<CacheEntry>,
    pub radii: Vec<f32>,
}

/// Per-frame times of the three procedures.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameTimes {
    pub render: Duration,
    pub create: Duration,
    pub update: Duration,
    /// Validation rounds (`validation_fraction`).
    pub validate: Duration,
    /// The requests pass, read-backs and the octree upload.
    pub bookkeeping: Duration,
    pub blocks_rendered: u32,
}

impl FrameTimes {
    pub fn total(&self) -> Duration {
        self.render + self.create + self.update + self.validate + self.bookkeeping
    }
}

/// Timestamps at the start and end of each phase of a frame, where the adapter has them.
struct PhaseTimer {
    query_set: wgpu::QuerySet,
    resolved: wgpu::Buffer,
}

impl PhaseTimer {
    fn new(engine: &Engine) -> Option<Self> {
        let gpu = &engine.gpu;
        gpu.has_timestamps.then(|| Self {
            query_set: gpu.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("irradiance phases"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * PHASES as u32,
            }),
            resolved: gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("irradiance phase times"),
                size: (16 * PHASES) as u64,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
        })
    }

    fn writes(
        &self,
        phase: usize,
        first: bool,
        last: bool,
    ) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        (first || last).then_some(wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: first.then_some(2 * phase as u32),
            end_of_pass_write_index: last.then_some(2 * phase as u32 + 1),
        })
    }

    fn resolve(&self, encoder: &mut wgpu::CommandEncoder, to: &wgpu::Buffer, offset: u64) {
        encoder.resolve_query_set(&self.query_set, 0..2 * PHASES as u32, &self.resolved, 0);
        encoder.copy_buffer_to_buffer(&self.resolved, 0, to, offset, (16 * PHASES) as u64);
    }

    /// Each used phase's time from the resolved ticks.
    fn durations(
        &self,
        engine: &Engine,
        ticks: &[u64],
        used: [bool; PHASES],
    ) -> [Duration; PHASES] {
        let period = engine.gpu.queue.get_timestamp_period() as f64;
        std::array::from_fn(|p| {
            if used[p] {
                let ns = ticks[2 * p + 1].saturating_sub(ticks[2 * p]) as f64 * period;
                Duration::from_nanos(ns as u64)
            } else {
                Duration::ZERO
            }
        })
    }
}

/// Where a frame's read-back buffer keeps what (byte offsets).
struct ReadbackLayout {
    counters: u64,
    priorities: u64,
    entries: u64,
    radii: u64,
    timestamps: u64,
    timestamp_bytes: u64,
    total: u64,
}

impl ReadbackLayout {
    fn new(blocks: u64, max_pending: u64) -> Self {
        let counters = (COUNTER_WORDS * 4) as u64;
        let priorities = counters;
        let entries = (priorities + blocks * 4).next_multiple_of(16);
        let radii = entries + max_pending * size_of::<CacheEntry>() as u64;
        let timestamps = (radii + max_pending * 24).next_multiple_of(16);
        let timestamp_bytes = (16 * PHASES) as u64;
        Self {
            counters,
            priorities,
            entries,
            radii,
            timestamps,
            timestamp_bytes,
            total: timestamps + timestamp_bytes,
        }
    }
}

/// Exponential smoothing of a measured cost.
fn smooth(old: Option<f64>, new: f64) -> f64 {
    match old {
        Some(old) => 0.7 * old + 0.3 * new,
        None => new,
    }
}

/// Smoothing that one outlier (at most 4× the estimate) cannot wreck.
fn robust_smooth(old: Option<f64>, new: f64) -> f64 {
    match old {
        Some(old) => smooth(Some(old), new.min(4.0 * old)),
        None => new,
    }
}

/// Copies `size` bytes of a MAP_READ buffer out, after the queue is idle.
fn map_read(engine: &Engine, buffer: &wgpu::Buffer, size: u64) -> Result<Vec<u8>, EngineError> {
    let (sender, receiver) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, ..size, move |result| {
        let _ = sender.send(result);
    });
    engine.gpu.wait_idle()?;
    receiver
        .recv_timeout(Duration::from_secs(5))
        .map_err(|_| EngineError::Gpu("irradiance read-back never completed".into()))?
        .map_err(|e| EngineError::Gpu(format!("irradiance read-back failed: {e}")))?;
    let bytes = buffer
        .get_mapped_range(..size)
        .map_err(|e| EngineError::Gpu(format!("irradiance read-back mapping failed: {e}")))?
        .to_vec();
    buffer.unmap();
    Ok(bytes)
}

/// GPU buffers whose size depends on the viewport.
struct PixelBuffers {
    pixel_aux: wgpu::Buffer,
    blocks: wgpu::Buffer,
    words: wgpu::Buffer,
}

/// Buffers that hold the cache (they survive viewport changes).
struct CacheBuffers {
    params: wgpu::Buffer,
    dispatch: wgpu::Buffer,
    entries: wgpu::Buffer,
    radii: wgpu::Buffer,
    octree: wgpu::Buffer,
    requests: wgpu::Buffer,
    cell_bins: wgpu::Buffer,
    bounds: wgpu::Buffer,
}

/// How the image is divided into blocks, and where `words` and `blocks` keep what.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Layout {
    blocks_x: u32,
    blocks_y: u32,
    block_count: u32,
    node_capacity: u32,
    ref_capacity: u32,
    max_pending: u32,
    lock_depth: u32,
}

impl Layout {
    fn new(width: u32, height: u32, config: &IrradianceConfig) -> Self {
        let blocks_x = width.div_ceil(BLOCK_WIDTH);
        let blocks_y = height.div_ceil(BLOCK_HEIGHT);
        let auto_pending = (PAPER_PENDING * (width as f64 * height as f64) / PAPER_PIXELS)
            .round()
            .clamp(16.0, PAPER_PENDING) as u32;
        let max_pending = config.max_pending.unwrap_or(auto_pending).max(1);
        let lock_depth = config.lock_depth.unwrap_or_else(|| {
            // Smallest depth with 8^depth ≥ 8 · max_pending.
            let mut depth = 2;
            while depth < 4 && 8u64.pow(depth) < 8 * max_pending as u64 {
                depth += 1;
            }
            depth
        });
        let min_nodes = (8u32.pow(lock_depth.min(6) + 1) - 1) / 7;
        Self {
            blocks_x,
            blocks_y,
            block_count: blocks_x * blocks_y,
            node_capacity: min_nodes.saturating_add(config.entry_capacity.saturating_mul(4)),
            ref_capacity: config
                .entry_capacity
                .saturating_mul(octree::MAX_REFERENCES as u32),
            max_pending,
            lock_depth,
        }
    }

    fn node_claim_offset(&self) -> u32 {
        COUNTER_WORDS as u32
    }
    fn node_held_offset(&self) -> u32 {
        self.node_claim_offset().saturating_add(self.node_capacity)
    }
    fn block_claim_offset(&self) -> u32 {
        self.node_held_offset().saturating_add(self.node_capacity)
    }
    fn block_held_offset(&self) -> u32 {
        self.block_claim_offset().saturating_add(self.block_count)
    }
    fn words(&self) -> u32 {
        self.block_held_offset().saturating_add(self.block_count)
    }
    /// Blocks the render list holds (each pass at most every block).
    fn list_capacity(&self) -> u32 {
        self.block_count * MAX_RENDER_PASSES as u32
    }

    /// `words` as after a reset: counters zero, no claims, no locks held.
    fn fresh_words(&self, entries: u32) -> Vec<u32> {
        let mut words = vec![0u32; self.words() as usize];
        words[COUNTER_ENTRIES] = entries;
        let claims = |w: &mut Vec<u32>, at: u32, n: u32| {
            w[at as usize..(at + n) as usize].fill(u32::MAX);
        };
        claims(&mut words, self.node_claim_offset(), self.node_capacity);
        claims(&mut words, self.block_claim_offset(), self.block_count);
        words
    }
}

/// GPU bytes of the technique's own buffers for a viewport (besides the shared volume).
pub fn irradiance_bytes(width: u32, height: u32, config: &IrradianceConfig, cells: usize) -> u64 {
    let layout = Layout::new(width, height, config);
    let pixels = width as u64 * height as u64;
    let entries = config.entry_capacity as u64;
    // Nodes and references as Layout sizes them, without its u32 saturation.
    let (nodes, refs) = (entries * 4 + 37449, entries * octree::MAX_REFERENCES as u64);
    accum_bytes(width, height)
        + pixels * 16
        + (layout.list_capacity() + layout.block_count) as u64 * 4
        + (COUNTER_WORDS as u64 + 2 * nodes + 2 * layout.block_count as u64) * 4
        + entries * (size_of::<CacheEntry>() as u64 + 24)
        + (nodes * 4 + refs) * 4
        + layout.max_pending as u64 * size_of::<Request>() as u64
        + cells as u64 * 8
        + entries * 16
        + DISPATCH_SLOTS as u64 * DISPATCH_STRIDE
}

/// What the CPU keeps of every entry (for the octree and TF edits).
#[derive(Debug, Clone, Copy)]
struct Mirror {
    entry: CacheEntry,
    radii: [f32; 6],
}

pub struct Irradiance {
    base: Progressive,
    config: IrradianceConfig,
    layout: Layout,
    cache: CacheBuffers,
    pixels: PixelBuffers,
    bind_groups: IrradianceBindGroups,
    octree: Octree,
    root_min: [f32; 3],
    root_edge: f32,
    voxel: f32,
    mirror: Vec<Mirror>,
    pending: u32,
    /// The octree has room for no more entries.
    full: bool,
    octree_dirty: bool,
    last_rebuild: Instant,
    reductions_at_rebuild: u64,
    frame: u32,
    /// Blocks rendered since the picture restarted.
    block_renders: u64,
    /// Next block of the round-robin order.
    cursor: u32,
    priorities: Vec<f32>,
    /// Time owed to creation and update (seconds; may go negative).
    creation_credit: f64,
    update_credit: f64,
    validation_credit: f64,
    /// Measured costs: per block rendered, per request and creation round, per update round.
    block_cost: Option<f64>,
    request_round_cost: Option<f64>,
    update_round_cost: Option<f64>,
    validation_round_cost: Option<f64>,
    /// (time, hits, misses) of recent frames.
    hit_history: VecDeque<(Instant, u64, u64)>,
    counters: [u32; COUNTER_WORDS],
    stats: CacheStats,
    /// Density scale and g the cache's entries were estimated with.
    cache_density: f32,
    cache_g: f32,
    cache_bounces: u32,
    bookkeeping_cost: Option<f64>,
    /// Seconds the frames so far ran over their `frame_time` (negative: under), taken off the
    /// next frame's rendering so that equal time per frame holds on average, not only as planned.
    time_debt: f64,
    /// The longest one frame (one submission) should take where a whole image's worth of
    /// blocks takes longer (`Technique::set_part_time`): frames are then sized to it, as with
    /// `frame_time`, so that an edit waits for a part, not for an image (~3 s at 512² on
    /// lavapipe). None: whole frames.
    part_time: Option<Duration>,
    pub last_frame: FrameTimes,
    lcg: u64,
    timer: Option<PhaseTimer>,
    /// Each frame's read-back (ReadbackLayout).
    readback: wgpu::Buffer,
}

impl Irradiance {
    pub fn new(
        engine: &Engine,
        volume: Arc<GpuVolume>,
        scene: &Scene,
        config: IrradianceConfig,
    ) -> Result<Self, EngineError> {
        validate(&config)?;
        let (width, height) = (scene.viewport.width, scene.viewport.height);
        let cells = volume.ranges.cell_count();
        let needed = irradiance_bytes(width, height, &config, cells);
        if needed > engine.session_budget {
            return Err(EngineError::OutOfMemory {
                needed,
                available: engine.session_budget,
            });
        }
        let layout = Layout::new(width, height, &config);
        let binding_limit = engine.gpu.limits.max_storage_buffer_binding_size;
        let largest = [
            config.entry_capacity as u64 * size_of::<CacheEntry>() as u64,
            (layout.node_capacity as u64 * 4 + layout.ref_capacity as u64) * 4,
            layout.words() as u64 * 4,
            layout.max_pending as u64 * size_of::<Request>() as u64,
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        if largest > binding_limit {
            return Err(EngineError::OutOfMemory {
                needed: largest,
                available: binding_limit,
            });
        }
        let extent = volume.extent;
        let voxel = (0..3)
            .map(|k| extent[k] / volume.dims[k] as f32)
            .fold(f32::INFINITY, f32::min);
        let root_edge = extent.iter().fold(0.0f32, |a, &b| a.max(b)) * (1.0 + 1e-4);
        let root_min = [-0.5 * root_edge; 3];
        let bins: Vec<[u32; 2]> = volume
            .ranges
            .bin_masks()
            .iter()
            .map(|&m| [m as u32, (m >> 32) as u32])
            .collect();
        let base = Progressive::new(engine, Estimator::Pathtrace, volume, scene)?;
        let gpu = &engine.gpu;
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        let cache = CacheBuffers {
            params: gpu.buffer(
                "irradiance params",
                size_of::<IrradianceParams>() as u64,
                wgpu::BufferUsages::UNIFORM,
            ),
            dispatch: gpu.buffer(
                "irradiance dispatch",
                DISPATCH_SLOTS as u64 * DISPATCH_STRIDE,
                wgpu::BufferUsages::UNIFORM,
            ),
            entries: gpu.buffer(
                "irradiance entries",
                config.entry_capacity as u64 * size_of::<CacheEntry>() as u64,
                storage,
            ),
            radii: gpu.buffer(
                "irradiance radii",
                config.entry_capacity as u64 * 24,
                storage,
            ),
            octree: gpu.buffer(
                "irradiance octree",
                (layout.node_capacity as u64 * 4 + layout.ref_capacity as u64) * 4,
                wgpu::BufferUsages::STORAGE,
            ),
            requests: gpu.buffer(
                "irradiance requests",
                layout.max_pending as u64 * size_of::<Request>() as u64,
                storage,
            ),
            cell_bins: gpu.buffer(
                "irradiance cell bins",
                (bins.len() * 8) as u64,
                wgpu::BufferUsages::STORAGE,
            ),
            bounds: gpu.buffer(
                "irradiance entry bounds",
                config.entry_capacity as u64 * 16,
                wgpu::BufferUsages::STORAGE,
            ),
        };
        gpu.queue
            .write_buffer(&cache.cell_bins, 0, bytemuck::cast_slice(&bins));
        let pixels = pixel_buffers(engine, width, height, &layout);
        let bind_groups = bind_groups(engine, &base, &cache, &pixels);
        let mut technique = Self {
            base,
            config,
            layout,
            cache,
            pixels,
            bind_groups,
            octree: Octree::new(
                root_min,
                root_edge,
                layout.lock_depth,
                octree::MAX_DEPTH - 1,
            ),
            root_min,
            root_edge,
            voxel,
            mirror: Vec::new(),
            pending: 0,
            full: false,
            octree_dirty: true,
            last_rebuild: Instant::now(),
            reductions_at_rebuild: 0,
            frame: 0,
            block_renders: 0,
            cursor: 0,
            priorities: Vec::new(),
            creation_credit: 0.0,
            update_credit: 0.0,
            validation_credit: 0.0,
            block_cost: None,
            request_round_cost: None,
            update_round_cost: None,
            validation_round_cost: None,
            hit_history: VecDeque::new(),
            counters: [0; COUNTER_WORDS],
            stats: CacheStats::default(),
            cache_density: scene.params.density_scale,
            cache_g: scene.params.g,
            cache_bounces: config.bounces,
            bookkeeping_cost: None,
            time_debt: 0.0,
            part_time: None,
            last_frame: FrameTimes::default(),
            lcg: 0x853c_49e6_748f_ea9b ^ scene.seed as u64,
            timer: PhaseTimer::new(engine),
            readback: readback_buffer(engine, &layout),
        };
        technique.reset_words(engine);
        technique.upload_octree(engine)?;
        technique.restart(engine);
        Ok(technique)
    }

    pub fn config(&self) -> IrradianceConfig {
        self.config
    }

    pub fn cache_stats(&self) -> CacheStats {
        let mut stats = self.stats;
        stats.entries = self.mirror.len() as u32;
        stats.references = self.octree.reference_count() as u64;
        stats.octree_nodes = self.octree.node_count() as u32;
        stats.pending = self.pending;
        stats.hit_rate = self.hit_rate() as f32;
        stats
    }

    /// Per pixel, row 0 at the top: the mean radiance, and the variance of the mean of its
    /// luminance (from its samples' squared luminance; 0 below two samples).
    pub fn read_estimate(&self, engine: &Engine) -> Result<(Vec<[f32; 3]>, Vec<f32>), EngineError> {
        let sums: Vec<[f32; 4]> =
            bytemuck::pod_collect_to_vec(&engine.gpu.read_buffer(self.base.bindings().accum)?);
        let aux: Vec<[f32; 4]> =
            bytemuck::pod_collect_to_vec(&engine.gpu.read_buffer(&self.pixels.pixel_aux)?);
        let mut mean = Vec::with_capacity(sums.len());
        let mut variance = Vec::with_capacity(sums.len());
        for (s, a) in sums.iter().zip(&aux) {
            let n = s[3];
            let m = if n > 0.0 {
                [s[0] / n, s[1] / n, s[2] / n]
            } else {
                [0.0; 3]
            };
            let lum = 0.2126 * m[0] + 0.7152 * m[1] + 0.0722 * m[2];
            variance.push(if n >= 2.0 {
                ((a[3] - n * lum * lum) / (n - 1.0)).max(0.0) / n
            } else {
                0.0
            });
            mean.push(m);
        }
        Ok((mean, variance))
    }

    /// The cache's entries, as created (radii as the update left them at the last rebuild).
    pub fn entries(&self) -> Vec<CacheEntry> {
        self.mirror.iter().map(|m| m.entry).collect()
    }

    fn cache_active(&self, scene: &Scene) -> bool {
        self.config.cache && scene.params.g.abs() <= ISOTROPIC_G
    }

    /// Whether the render pass traces the directional and point lights' direct light at every
    /// event: always but with a cache that holds all the light (without a cache this is plain
    /// MCVR's best estimator).
    fn traced_direct(&self, scene: &Scene) -> bool {
        !self.cache_active(scene) || cached_light(&self.config, scene) == CachedLight::Indirect
    }

    fn write_params(&self, engine: &Engine, scene: &Scene) {
        let mut flags = 0;
        if self.cache_active(scene) {
            flags |= FLAG_CACHE;
        }
        if self.traced_direct(scene) {
            flags |= FLAG_TRACED_DIRECT;
        }
        if self.config.locking == Locking::Screen {
            flags |= FLAG_SCREEN_LOCKING;
        }
        if self.full {
            flags |= FLAG_NO_CREATION;
        }
        if self.config.historygrams == Historygrams::Samples {
            flags |= FLAG_SAMPLED_HISTORYGRAMS;
        }
        if self.config.view_event == ViewEvent::Marched {
            flags |= FLAG_MARCHED_VIEW;
        }
        if self.config.validate_hits {
            flags |= FLAG_VALIDATE_HITS;
        }
        let refs_offset = 4 * self.octree.node_count() as u32;
        let params = IrradianceParams {
            root_min: self.root_min,
            root_edge: self.root_edge,
            delta: self.config.delta_voxels * self.voxel,
            gamma: self.config.gamma,
            epsilon: self.config.epsilon,
            min_radius: self.config.min_radius_voxels * self.voxel,
            max_radius: self.config.max_radius_voxels * self.voxel,
            update_threshold: self.config.update_threshold,
            frame: self.frame,
            flags,
            blocks_x: self.layout.blocks_x,
            blocks_y: self.layout.blocks_y,
            block_count: self.layout.block_count,
            node_count: self.octree.node_count() as u32,
            refs_offset,
            node_claim_offset: self.layout.node_claim_offset(),
            node_held_offset: self.layout.node_held_offset(),
            block_claim_offset: self.layout.block_claim_offset(),
            block_held_offset: self.layout.block_held_offset(),
            entry_capacity: self.config.entry_capacity,
            max_pending: self.layout.max_pending,
            pending: self.pending,
            min_samples: self.config.min_samples,
            max_samples: self.config.max_samples,
            bounces: self.config.bounces,
            priority_offset: self.layout.list_capacity(),
            voxel: self.voxel,
            dark_floor: self.config.dark_floor * brightest_irradiance(scene),
            delta_free_paths: self.config.delta_free_paths,
            view_picks: self.config.view_picks,
            validation_threshold: self.config.validation_threshold,
            validation_samples: self.config.validation_samples,
            pad0: 0,
            pad1: 0,
        };
        engine
            .gpu
            .queue
            .write_buffer(&self.cache.params, 0, bytemuck::bytes_of(&params));
    }

    /// Counters, claims and locks as after a reset, with `entries` entries in the cache and no
    /// pending requests.
    fn reset_words(&mut self, engine: &Engine) {
        let words = self.layout.fresh_words(self.mirror.len() as u32);
        engine
            .gpu
            .queue
            .write_buffer(&self.pixels.words, 0, bytemuck::cast_slice(&words));
        self.counters = [0; COUNTER_WORDS];
        self.counters[COUNTER_ENTRIES] = self.mirror.len() as u32;
        self.pending = 0;
    }

    fn upload_octree(&mut self, engine: &Engine) -> Result<(), EngineError> {
        let (words, refs_offset) = self.octree.flatten();
        let capacity = self.cache.octree.size() / 4;
        if words.len() as u64 > capacity {
            return Err(EngineError::Gpu(format!(
                "irradiance octree needs {} words, has room for {capacity} (refs at {refs_offset})",
                words.len()
            )));
        }
        engine
            .gpu
            .queue
            .write_buffer(&self.cache.octree, 0, bytemuck::cast_slice(&words));
        self.octree_dirty = false;
        Ok(())
    }

    /// Starts the picture over (the cache stays).
    fn restart(&mut self, engine: &Engine) {
        let mut encoder =
            engine
                .gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("irradiance restart"),
                });
        encoder.clear_buffer(self.base.bindings().accum, 0, None);
        encoder.clear_buffer(&self.pixels.pixel_aux, 0, None);
        engine.gpu.queue.submit([encoder.finish()]);
        self.base.restart();
        self.block_renders = 0;
        self.priorities.clear();
    }

    /// Drops every entry and pending request.
    fn clear_cache(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        self.mirror.clear();
        self.octree = Octree::new(
            self.root_min,
            self.root_edge,
            self.layout.lock_depth,
            octree::MAX_DEPTH - 1,
        );
        self.full = false;
        self.reset_words(engine);
        self.upload_octree(engine)?;
        self.cache_density = scene.params.density_scale;
        self.cache_g = scene.params.g;
        self.cache_bounces = self.config.bounces;
        Ok(())
    }

    /// Keeps only the entries `keep` accepts (pending requests are dropped), with the radii
    /// the update left them.
    fn retain_entries(
        &mut self,
        engine: &Engine,
        keep: impl Fn(&CacheEntry) -> bool,
    ) -> Result<(), EngineError> {
        self.read_radii(engine)?;
        self.mirror.retain(|m| keep(&m.entry));
        self.upload_mirror(engine);
        self.octree = Octree::new(
            self.root_min,
            self.root_edge,
            self.layout.lock_depth,
            octree::MAX_DEPTH - 1,
        );
        self.full = false;
        for i in 0..self.mirror.len() {
            self.insert_into_octree(i);
        }
        self.reset_words(engine);
        self.upload_octree(engine)
    }

    fn upload_mirror(&self, engine: &Engine) {
        let entries: Vec<CacheEntry> = self.mirror.iter().map(|m| m.entry).collect();
        let radii: Vec<f32> = self.mirror.iter().flat_map(|m| m.radii).collect();
        let queue = &engine.gpu.queue;
        if !entries.is_empty() {
            queue.write_buffer(&self.cache.entries, 0, bytemuck::cast_slice(&entries));
            queue.write_buffer(&self.cache.radii, 0, bytemuck::cast_slice(&radii));
            self.upload_bounds(engine);
        }
    }

    /// Each entry's centre and largest radius (the lookup's quick rejection).
    fn upload_bounds(&self, engine: &Engine) {
        let bounds: Vec<[f32; 4]> = self
            .mirror
            .iter()
            .map(|m| {
                let p = m.entry.position;
                [
                    p[0],
                    p[1],
                    p[2],
                    m.radii.iter().fold(0.0f32, |a, &b| a.max(b)),
                ]
            })
            .collect();
        if !bounds.is_empty() {
            engine
                .gpu
                .queue
                .write_buffer(&self.cache.bounds, 0, bytemuck::cast_slice(&bounds));
        }
    }

    /// A copy of the cache.
    pub fn snapshot(&mut self, engine: &Engine) -> Result<CacheSnapshot, EngineError> {
        self.read_radii(engine)?;
        Ok(CacheSnapshot {
            entries: self.mirror.iter().map(|m| m.entry).collect(),
            radii: self.mirror.iter().flat_map(|m| m.radii).collect(),
        })
    }

    /// Replaces the cache with a snapshot (pending requests are dropped; the picture restarts).
    pub fn restore(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        snapshot: &CacheSnapshot,
    ) -> Result<(), EngineError> {
        if snapshot.entries.len() > self.config.entry_capacity as usize {
            return Err(EngineError::InvalidScene(
                "snapshot holds more entries than the cache".into(),
            ));
        }
        self.mirror = snapshot
            .entries
            .iter()
            .zip(snapshot.radii.chunks_exact(6))
            .map(|(&entry, r)| Mirror {
                entry,
                radii: std::array::from_fn(|i| r[i]),
            })
            .collect();
        self.upload_mirror(engine);
        self.octree = Octree::new(
            self.root_min,
            self.root_edge,
            self.layout.lock_depth,
            octree::MAX_DEPTH - 1,
        );
        for i in 0..self.mirror.len() {
            self.insert_into_octree(i);
        }
        self.reset_words(engine);
        self.upload_octree(engine)?;
        self.restart(engine);
        self.write_params(engine, scene);
        Ok(())
    }

    /// Reads the radii back into the mirror (the update shrinks them on the GPU).
    fn read_radii(&mut self, engine: &Engine) -> Result<(), EngineError> {
        if self.mirror.is_empty() {
            return Ok(());
        }
        let bytes =
            engine
                .gpu
                .read_buffer_range(&self.cache.radii, 0, self.mirror.len() as u64 * 24)?;
        let radii: &[f32] = bytemuck::try_cast_slice(&bytes)
            .map_err(|e| EngineError::Gpu(format!("radii readback: {e}")))?;
        for (m, r) in self.mirror.iter_mut().zip(radii.chunks_exact(6)) {
            m.radii = std::array::from_fn(|i| r[i]);
        }
        Ok(())
    }

    fn insert_into_octree(&mut self, index: usize) {
        if self.octree.node_count() + self.octree.max_new_nodes_per_insert()
            > self.layout.node_capacity as usize
            || self.octree.reference_count() + octree::MAX_REFERENCES
                > self.layout.ref_capacity as usize
        {
            if !self.full {
                tracing::warn!(
                    entries = self.mirror.len(),
                    "irradiance cache octree is full; no more entries are created"
                );
            }
            self.full = true;
            return;
        }
        let m = &self.mirror[index];
        let axes = orthonormal_basis(m.entry.normal);
        // A hair wider than the radii, so rounding never hides a zone's edge from a lookup.
        let half = zone_half_extent(axes, m.radii.map(|r| r * 1.001));
        let _ = self.octree.insert(index as u32, m.entry.position, half);
        self.octree_dirty = true;
    }

    /// The rebuild of §4.4 with the radii the update shrank (nodes are kept: pending requests
    /// hold their indices).
    fn rebuild_octree(&mut self, engine: &Engine) -> Result<(), EngineError> {
        self.read_radii(engine)?;
        self.upload_bounds(engine);
        self.octree.clear_references();
        for i in 0..self.mirror.len() {
            self.insert_into_octree(i);
        }
        self.last_rebuild = Instant::now();
        self.reductions_at_rebuild = self.stats.radius_reductions;
        self.upload_octree(engine)
    }

    fn hit_rate(&self) -> f64 {
        let (hits, misses) = self
            .hit_history
            .iter()
            .fold((0u64, 0u64), |(h, m), &(_, dh, dm)| (h + dh, m + dm));
        if hits + misses == 0 {
            1.0
        } else {
            hits as f64 / (hits + misses) as f64
        }
    }

    /// Shares of a frame for creation and update at the current hit rate (§6).
    fn fractions(&self) -> (f64, f64) {
        let h = self.hit_rate().powf(self.config.fraction_exponent as f64);
        let lerp = |(lo, hi): (f32, f32)| lo as f64 + (1.0 - h) * (hi - lo) as f64;
        (
            lerp(self.config.creation_fraction),
            lerp(self.config.update_fraction),
        )
    }

    fn next_random(&mut self) -> f64 {
        lcg_uniform(&mut self.lcg)
    }

    /// The blocks of the next frame's render passes: `renders` block renders, in turn or by
    /// priority (every block with an unsampled pixel first, then in proportion to its
    /// expected gain by systematic sampling).
    fn plan_blocks(&mut self, renders: usize) -> Vec<Vec<u32>> {
        let n = self.layout.block_count as usize;
        let mut counts = vec![0usize; n];
        let mut left = renders.min(n * MAX_RENDER_PASSES);
        // Priorities only once every block has been rendered since the restart: frames of
        // fewer blocks than the image (`frame_limit`) cover it in turn first, so that the first
        // picture (`iteration` 1) has no block left black.
        if self.config.priorities && self.priorities.len() == n && self.block_renders >= n as u64 {
            for i in 0..n {
                let b = (self.cursor as usize + i) % n;
                if left > 0 && self.priorities[b] >= PRIORITY_UNSAMPLED {
                    counts[b] = 1;
                    left -= 1;
                }
            }
            let total: f64 = self
                .priorities
                .iter()
                .filter(|p| **p < PRIORITY_UNSAMPLED && p.is_finite() && **p > 0.0)
                .map(|&p| p as f64)
                .sum();
            if left > 0 && total > 0.0 {
                let step = total / left as f64;
                let mut next = self.next_random() * step;
                let mut cumulative = 0.0;
                for (b, &p) in self.priorities.iter().enumerate() {
                    if !(p < PRIORITY_UNSAMPLED && p.is_finite() && p > 0.0) {
                        continue;
                    }
                    cumulative += p as f64;
                    while next < cumulative && left > 0 {
                        if counts[b] < MAX_RENDER_PASSES {
                            counts[b] += 1;
                        }
                        left -= 1;
                        next += step;
                    }
                }
            }
        }
        // In turn: whatever priorities did not place.
        while left > 0 {
            let b = self.cursor as usize;
            self.cursor = ((self.cursor as usize + 1) % n) as u32;
            if counts[b] < MAX_RENDER_PASSES {
                counts[b] += 1;
                left -= 1;
            } else if counts.iter().all(|&c| c >= MAX_RENDER_PASSES) {
                break;
            }
        }
        let passes = counts.iter().copied().max().unwrap_or(0);
        (0..passes)
            .map(|j| {
                let mut pass: Vec<u32> =
                    (0..n as u32).filter(|&b| counts[b as usize] > j).collect();
                shuffle(&mut pass, || self.next_random());
                pass
            })
            .filter(|pass| !pass.is_empty())
            .collect()
    }

    fn encoder(engine: &Engine, label: &str) -> wgpu::CommandEncoder {
        crate::passes::builder::encoder(&engine.gpu, label)
    }

    fn submit_and_time(
        engine: &Engine,
        encoder: wgpu::CommandEncoder,
    ) -> Result<Duration, EngineError> {
        let start = Instant::now();
        engine.gpu.queue.submit([encoder.finish()]);
        engine.gpu.wait_idle()?;
        Ok(start.elapsed())
    }

    /// One frame: rendering, then (with the cache and `cache_work`) creation rounds, update
    /// rounds and the requests pass, then priorities.
    pub fn frame(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        cache_work: bool,
    ) -> Result<FrameTimes, EngineError> {
        let frame_started = Instant::now();
        let cache_on = self.cache_active(scene);
        self.stats.active = cache_on;
        let (tc, tu) = if cache_on {
            self.fractions()
        } else {
            (0.0, 0.0)
        };
        // Creation and update rounds of this frame: time owed to each procedure is spent in
        // whole rounds (a round of every pending request, an update round of every block),
        // at most one frame's share or one round ahead.
        let n = self.layout.block_count as usize;
        let frame_limit = self.frame_limit();
        let frame_time = match frame_limit {
            Some(t) => t.as_secs_f64(),
            None => self.block_cost.unwrap_or(0.0) * n as f64 / (1.0 - tc - tu).max(0.5),
        };
        let (mut create_rounds, mut update_rounds, mut validation_rounds) = (0u32, 0u32, 0u32);
        let mut planned = 0.0;
        if cache_on && cache_work {
            let fixed_validation = self
                .config
                .validation_rounds
                .or(self.config.fixed_rounds.map(|_| 0));
            if let Some(v) = fixed_validation {
                validation_rounds = if self.mirror.is_empty() { 0 } else { v };
            } else if !self.mirror.is_empty() && self.config.validation_fraction > 0.0 {
                let (rounds, cost) = rounds_owed(
                    &mut self.validation_credit,
                    self.config.validation_fraction as f64 * frame_time,
                    self.validation_round_cost,
                    MAX_VALIDATION_ROUNDS,
                );
                validation_rounds = rounds;
                planned += cost;
            }
            if let Some((c, u)) = self.config.fixed_rounds {
                create_rounds = if self.pending > 0 { c } else { 0 };
                update_rounds = if self.mirror.len() >= 2 { u } else { 0 };
            } else {
                let schedule = |credit: &mut f64, share: f64, round: Option<f64>, most: u32| {
                    rounds_owed(credit, share * frame_time, round, most)
                };
                if self.pending > 0 {
                    let round = self.request_round_cost.map(|c| c * self.pending as f64);
                    let (rounds, cost) =
                        schedule(&mut self.creation_credit, tc, round, MAX_CREATE_ROUNDS);
                    create_rounds = rounds;
                    planned += cost;
                }
                if self.mirror.len() >= 2 {
                    let (rounds, cost) = schedule(
                        &mut self.update_credit,
                        tu,
                        self.update_round_cost,
                        MAX_UPDATE_ROUNDS,
                    );
                    update_rounds = rounds;
                    planned += cost;
                }
            }
        }
        // Rendering gets the rest of the frame.
        let renders = match (frame_limit, self.block_cost) {
            (Some(frame), Some(cost)) => {
                let left = frame.as_secs_f64()
                    - planned
                    - self.bookkeeping_cost.unwrap_or(0.0)
                    - self.time_debt;
                (left / cost.max(1e-9)).round() as usize
            }
            _ => n,
        }
        .clamp(1, n * MAX_RENDER_PASSES);
        let passes = self.plan_blocks(renders);
        self.write_params(engine, scene);
        self.base.encode_uniforms(engine, scene)?;

        let plan = DispatchPlan::new(
            &passes,
            PlannedRounds {
                create: create_rounds,
                pending: self.pending,
                update: update_rounds,
                validate: validation_rounds,
                block_count: self.layout.block_count,
                frame: self.frame,
                priorities: self.config.priorities,
            },
        )?;
        let DispatchPlan {
            infos,
            list,
            render_dispatches,
            create_first,
            update_first,
            validate_first,
            priority_first,
        } = plan;
        let blocks_rendered = list.len() as u32;
        let mut times = FrameTimes {
            blocks_rendered,
            ..FrameTimes::default()
        };
        let queue = &engine.gpu.queue;
        queue.write_buffer(&self.pixels.blocks, 0, bytemuck::cast_slice(&list));
        let mut padded = vec![0u8; infos.len() * DISPATCH_STRIDE as usize];
        for (i, info) in infos.iter().enumerate() {
            let at = i * DISPATCH_STRIDE as usize;
            padded[at..at + size_of::<DispatchInfo>()].copy_from_slice(bytemuck::bytes_of(info));
        }
        queue.write_buffer(&self.cache.dispatch, 0, &padded);

        // One submission: rendering, creation rounds, update rounds, then the requests and
        // priority passes and the copies the CPU reads back (one map per frame).
        let passes_gpu = &engine.irradiance;
        let timer = self.timer.as_ref();
        let split = timer.is_none();
        let mut phase_times = [Duration::ZERO; PHASES];
        let mut used = [false; PHASES];
        let mut encoder = Self::encoder(engine, "irradiance frame");
        let mut phase = |encoder: &mut wgpu::CommandEncoder,
                         index: usize,
                         passes: &mut dyn Iterator<Item = (Pass, u32, u32)>|
         -> Result<(), EngineError> {
            let all: Vec<_> = passes.filter(|p| p.2 > 0).collect();
            used[index] |= !all.is_empty();
            for (i, &(pass, slot, workgroups)) in all.iter().enumerate() {
                let writes = timer.and_then(|t| t.writes(index, i == 0, i + 1 == all.len()));
                let groups = &self.bind_groups;
                passes_gpu.encode_timed(encoder, pass, groups, slot, workgroups, writes);
            }
            if split && !all.is_empty() {
                let full = std::mem::replace(encoder, Self::encoder(engine, "irradiance frame"));
                phase_times[index] = Self::submit_and_time(engine, full)?;
            }
            Ok(())
        };
        phase(
            &mut encoder,
            PHASE_RENDER,
            &mut render_dispatches
                .iter()
                .map(|&(slot, count)| (Pass::Render, slot, count)),
        )?;
        let pending = if cache_on { self.pending } else { 0 };
        phase(
            &mut encoder,
            PHASE_CREATE,
            &mut (0..create_rounds).map(|r| (Pass::Create, create_first + r, pending)),
        )?;
        let update_groups = self.layout.block_count.div_ceil(UPDATE_WORKGROUP);
        phase(
            &mut encoder,
            PHASE_UPDATE,
            &mut (0..if cache_on { update_rounds } else { 0 })
                .map(|r| (Pass::Update, update_first + r, update_groups)),
        )?;
        phase(
            &mut encoder,
            PHASE_VALIDATE,
            &mut (0..if cache_on { validation_rounds } else { 0 })
                .map(|r| (Pass::Update, validate_first + r, update_groups)),
        )?;
        let requests = (cache_on && cache_work).then_some((Pass::Requests, 0, 1));
        let priority_passes: Vec<_> = if self.config.priorities {
            (0..n)
                .step_by(MAX_WORKGROUPS)
                .enumerate()
                .map(|(i, first)| {
                    (
                        Pass::Priority,
                        priority_first + i as u32,
                        (n - first).min(MAX_WORKGROUPS) as u32,
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        phase(
            &mut encoder,
            PHASE_TAIL,
            &mut requests.into_iter().chain(priority_passes),
        )?;

        // Read-back: counters, priorities, the entries that may have been finished, times.
        let known = self.mirror.len() as u64;
        let entry_size = size_of::<CacheEntry>() as u64;
        let new_entries = (self.layout.max_pending as u64)
            .min((self.config.entry_capacity as u64).saturating_sub(known));
        let layout = ReadbackLayout::new(n as u64, self.layout.max_pending as u64);
        encoder.copy_buffer_to_buffer(&self.pixels.words, 0, &self.readback, 0, layout.counters);
        if self.config.priorities {
            encoder.copy_buffer_to_buffer(
                &self.pixels.blocks,
                self.layout.list_capacity() as u64 * 4,
                &self.readback,
                layout.priorities,
                n as u64 * 4,
            );
        }
        if cache_on && new_entries > 0 {
            encoder.copy_buffer_to_buffer(
                &self.cache.entries,
                known * entry_size,
                &self.readback,
                layout.entries,
                new_entries * entry_size,
            );
            encoder.copy_buffer_to_buffer(
                &self.cache.radii,
                known * 24,
                &self.readback,
                layout.radii,
                new_entries * 24,
            );
        }
        if let Some(timer) = timer {
            timer.resolve(&mut encoder, &self.readback, layout.timestamps);
        }
        let tail_started = Instant::now();
        engine.gpu.queue.submit([encoder.finish()]);
        let bytes = map_read(engine, &self.readback, layout.total)?;
        if split {
            phase_times[PHASE_TAIL] += tail_started.elapsed();
        } else if let Some(timer) = timer {
            let at = layout.timestamps as usize;
            let ticks: Vec<u64> =
                bytemuck::pod_collect_to_vec(&bytes[at..at + layout.timestamp_bytes as usize]);
            phase_times = timer.durations(engine, &ticks, used);
        }
        times.render = phase_times[PHASE_RENDER];
        times.create = phase_times[PHASE_CREATE];
        times.update = phase_times[PHASE_UPDATE];
        times.validate = phase_times[PHASE_VALIDATE];
        let bookkeeping = Instant::now();
        if blocks_rendered > 0 {
            let cost = times.render.as_secs_f64() / blocks_rendered as f64;
            self.block_cost = Some(smooth(self.block_cost, cost));
        }
        self.block_renders += blocks_rendered as u64;
        if charge_rounds(
            &mut self.creation_credit,
            &mut self.request_round_cost,
            times.create,
            create_rounds as u64 * pending as u64,
        ) {
            self.stats.creation_rounds += create_rounds as u64;
        }
        if charge_rounds(
            &mut self.update_credit,
            &mut self.update_round_cost,
            times.update,
            if cache_on { update_rounds as u64 } else { 0 },
        ) {
            self.stats.update_rounds += update_rounds as u64;
        }
        if charge_rounds(
            &mut self.validation_credit,
            &mut self.validation_round_cost,
            times.validate,
            if cache_on {
                validation_rounds as u64
            } else {
                0
            },
        ) {
            self.stats.validation_rounds += validation_rounds as u64;
        }
        if self.config.priorities {
            let at = layout.priorities as usize;
            self.priorities = bytemuck::pod_collect_to_vec(&bytes[at..at + n * 4]);
        }
        if cache_on {
            let (at, radii) = (layout.entries as usize, layout.radii as usize);
            self.read_counters(
                &bytes[..layout.counters as usize],
                &bytes[at..radii],
                &bytes[radii..layout.timestamps as usize],
            )?;
            if self.octree_dirty {
                self.upload_octree(engine)?;
            }
            if self.stats.radius_reductions > self.reductions_at_rebuild
                && self.last_rebuild.elapsed() >= self.config.rebuild_interval
            {
                self.rebuild_octree(engine)?;
            }
        }
        // Everything but rendering, creation and update: the tail passes, read-back, octree
        // upload and the CPU's share of the frame (all of it counts against a frame's time).
        let elapsed = frame_started.elapsed();
        times.bookkeeping = elapsed
            .saturating_sub(times.render + times.create + times.update + times.validate)
            .max(phase_times[PHASE_TAIL] + bookkeeping.elapsed());
        self.bookkeeping_cost = Some(smooth(
            self.bookkeeping_cost,
            times.bookkeeping.as_secs_f64(),
        ));
        // Estimates of the blocks' and rounds' costs miss in both directions, and the misses do
        // not cancel (the in-turn runs of bench convergence overran plain's frames by 3–9%).
        if let Some(frame) = frame_limit {
            let frame = frame.as_secs_f64();
            self.time_debt = (self.time_debt + elapsed.as_secs_f64() - frame).clamp(-frame, frame);
        }
        self.frame = self.frame.wrapping_add(1);
        self.last_frame = times;
        Ok(times)
    }

    /// Reads the counters; stores the entries finished this frame (read back speculatively,
    /// from the first unknown slot on) in the octree.
    fn read_counters(
        &mut self,
        counters: &[u8],
        finished: &[u8],
        finished_radii: &[u8],
    ) -> Result<(), EngineError> {
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(counters);
        let delta = |k: usize| words[k].wrapping_sub(self.counters[k]) as u64;
        let (hits, misses) = (delta(COUNTER_HITS), delta(COUNTER_MISSES));
        self.stats.hits += hits;
        self.stats.misses += misses;
        self.stats.created += delta(COUNTER_CREATED);
        self.stats.requests_issued += delta(COUNTER_ISSUED);
        self.stats.requests_dropped += delta(COUNTER_DROPPED) + delta(COUNTER_LOST);
        self.stats.radius_reductions += delta(COUNTER_REDUCTIONS);
        let now = Instant::now();
        self.hit_history.push_back((now, hits, misses));
        while self.hit_history.len() > 1
            && self
                .hit_history
                .front()
                .is_some_and(|(t, _, _)| now.duration_since(*t) > self.config.hit_rate_window)
        {
            self.hit_history.pop_front();
        }
        self.pending = words[COUNTER_PENDING];
        let entries = words[COUNTER_ENTRIES] as usize;
        self.counters.copy_from_slice(&words[..COUNTER_WORDS]);
        let known = self.mirror.len();
        if entries > known {
            let size = size_of::<CacheEntry>();
            let count = entries - known;
            if finished.len() < count * size {
                return Err(EngineError::Gpu(format!(
                    "irradiance: {count} entries finished, {} read back",
                    finished.len() / size
                )));
            }
            let new: Vec<CacheEntry> = bytemuck::pod_collect_to_vec(&finished[..count * size]);
            let radii: Vec<f32> = bytemuck::pod_collect_to_vec(&finished_radii[..count * 24]);
            for (entry, r) in new.iter().zip(radii.chunks_exact(6)) {
                self.mirror.push(Mirror {
                    entry: *entry,
                    radii: std::array::from_fn(|h| r[h]),
                });
                self.insert_into_octree(self.mirror.len() - 1);
            }
        }
        Ok(())
    }

    /// A TF edit: drops the entries it can change (or all of them), keeps the rest.
    fn apply_tf(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        old: &TransferFunction,
    ) -> Result<(), EngineError> {
        let before = self.mirror.len() as u32;
        let query = query_historygram(old, &scene.tf);
        let opacity_query = opacity_query_historygram(old, &scene.tf);
        if query == 0 {
            self.stats.last_edit = Some((before, before));
            return Ok(());
        }
        match self.config.invalidation {
            Invalidation::Clear => self.clear_cache(engine, scene)?,
            Invalidation::Historygram => {
                self.retain_entries(engine, |e| !e.meets(query, opacity_query))?
            }
        }
        self.stats.last_edit = Some((before, self.mirror.len() as u32));
        Ok(())
    }

    /// The time a frame is sized to: `frame_time`, else `part_time` where a whole image's
    /// worth of blocks is estimated to take longer than it.
    fn frame_limit(&self) -> Option<Duration> {
        if self.config.frame_time.is_some() {
            return self.config.frame_time;
        }
        // A frame's bookkeeping (the priority and requests passes, the read-back, the octree)
        // does not shrink with it: frames at least eight times as long (~100–200 ms at 512² on
        // lavapipe) took the drag bench's still 23 s after the drag, whole frames 18 s, 40 ms
        // frames 103 s and four times the bookkeeping 37 s.
        let bookkeeping = self.bookkeeping_cost.unwrap_or(0.0);
        let part = self.part_time?.as_secs_f64().max(8.0 * bookkeeping);
        let whole = self.block_cost? * self.layout.block_count as f64 + bookkeeping;
        (whole > part).then(|| Duration::from_secs_f64(part))
    }

    /// Sets the time per frame (None: an image's worth of blocks per frame).
    pub fn set_frame_time(&mut self, frame_time: Option<Duration>) {
        if frame_time.is_none() {
            self.time_debt = 0.0;
        }
        self.config.frame_time = frame_time;
    }

    /// Sets how TF edits treat the cache.
    pub fn set_invalidation(&mut self, invalidation: Invalidation) {
        self.config.invalidation = invalidation;
    }
}

/// What a cache configured so holds for this scene: the indirect light only where asked for
/// and where there is some (more than one bounce, or an environment); else all the light.
pub fn cached_light(config: &IrradianceConfig, scene: &Scene) -> CachedLight {
    // The environment radiance the shaders see (scene.env_radiance).
    let (_, environment) = gpu_lights(&scene.lights);
    let has_indirect = config.bounces > 1 || environment.iter().any(|&c| c > 0.0);
    match config.cached_light {
        CachedLight::Indirect if has_indirect => CachedLight::Indirect,
        _ => CachedLight::All,
    }
}

/// The next number in [0, 1) of a 64-bit linear congruential generator (the CPU side's draws:
/// which blocks a frame renders and in what order).
fn lcg_uniform(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*state >> 11) as f64 / (1u64 << 53) as f64
}

/// A random order (Fisher–Yates, `uniform` in [0, 1)) for a render pass's blocks. Which block a
/// workgroup renders does not change the picture, but it changes how evenly a device's cores
/// share the work: llvmpipe gives each of its threads one contiguous run of a dispatch's
/// workgroups, so blocks in raster order put a band of dense, slow blocks on one core while the
/// other idles. On the 2-core VM a frame of half the chest's blocks took 85% as long as all of
/// them (36.4 ms against 42.5), and the cache runs, whose frames render part of the image, paid
/// about 1.4× plain MCVR's render time per block.
fn shuffle(blocks: &mut [u32], mut uniform: impl FnMut() -> f64) {
    for i in (1..blocks.len()).rev() {
        let j = ((uniform() * (i + 1) as f64) as usize).min(i);
        blocks.swap(i, j);
    }
}

/// Luminance of the irradiance a point of the volume receives at most, unshadowed: every
/// directional light's, every point light's at the volume's centre, and 4π times the
/// environment's radiance.
pub fn brightest_irradiance(scene: &Scene) -> f32 {
    let lum = |c: [f32; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
    scene
        .lights
        .iter()
        .map(|light| match *light {
            Light::Directional { irradiance, .. } => lum(irradiance),
            Light::Point {
                position,
                intensity,
            } => lum(intensity) / position.iter().map(|x| x * x).sum::<f32>().max(1e-4),
            Light::Environment { radiance } => 4.0 * std::f32::consts::PI * lum(radiance),
        })
        .sum()
}

/// The radii an entry starts with: validity_radius in irradiance/common.wgsl.
pub fn validity_radius(sigma: f32, delta: f32, epsilon: f32, min_r: f32, max_r: f32) -> f32 {
    let magnitude = sigma.abs();
    let mut r = max_r;
    if magnitude > 0.0 {
        let c = if sigma < 0.0 {
            (1.0 + epsilon).ln()
        } else {
            -(1.0 - epsilon).ln()
        };
        r = (delta + c / magnitude).min(max_r);
    }
    r.max(min_r)
}

/// The columns (t, b, n) of orthonormal_basis in shared/common.wgsl.
pub fn orthonormal_basis(n: [f32; 3]) -> [[f32; 3]; 3] {
    let s = if n[2] >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (s + n[2]);
    let b = n[0] * n[1] * a;
    [
        [1.0 + s * n[0] * n[0] * a, s * b, -s * n[0]],
        [b, s + n[1] * n[1] * a, -n[1]],
        n,
    ]
}

fn validate(config: &IrradianceConfig) -> Result<(), EngineError> {
    let positive = |x: f32| x.is_finite() && x > 0.0;
    let fraction = |(lo, hi): (f32, f32)| (0.0..=0.45).contains(&lo) && lo <= hi && hi <= 0.45;
    let ok = config.bounces >= 1
        && positive(config.gamma)
        && config.epsilon > 0.0
        && config.epsilon < 1.0
        && positive(config.delta_voxels)
        && config.delta_free_paths.is_finite()
        && config.delta_free_paths >= 0.0
        && positive(config.min_radius_voxels)
        && config.min_radius_voxels <= config.max_radius_voxels
        && config.max_radius_voxels.is_finite()
        && positive(config.update_threshold)
        && fraction(config.creation_fraction)
        && fraction(config.update_fraction)
        && (0.0..=0.45).contains(&config.validation_fraction)
        && config.creation_fraction.1 + config.update_fraction.1 + config.validation_fraction < 0.9
        && config
            .validation_rounds
            .is_none_or(|v| v <= MAX_VALIDATION_ROUNDS)
        && positive(config.validation_threshold)
        && (2..=256).contains(&config.validation_samples)
        && positive(config.fraction_exponent)
        && config.entry_capacity >= 1
        && config.min_samples >= 2
        && (0.0..1.0).contains(&config.dark_floor)
        && config.min_samples <= config.max_samples
        && config.max_pending.is_none_or(|p| (1..=65535).contains(&p))
        && config.lock_depth.is_none_or(|d| d <= 6)
        && (1..=16).contains(&config.view_picks);
    if ok {
        Ok(())
    } else {
        Err(EngineError::InvalidScene(format!(
            "irradiance: bad configuration {config:?}"
        )))
    }
}

fn readback_buffer(engine: &Engine, layout: &Layout) -> wgpu::Buffer {
    engine.gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("irradiance read-back"),
        size: ReadbackLayout::new(layout.block_count as u64, layout.max_pending as u64).total,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

fn pixel_buffers(engine: &Engine, width: u32, height: u32, layout: &Layout) -> PixelBuffers {
    let gpu = &engine.gpu;
    let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
    PixelBuffers {
        pixel_aux: gpu.buffer(
            "irradiance pixel aux",
            width as u64 * height as u64 * 16,
            storage,
        ),
        blocks: gpu.buffer(
            "irradiance blocks",
            (layout.list_capacity() + layout.block_count) as u64 * 4,
            storage,
        ),
        words: gpu.buffer("irradiance words", layout.words() as u64 * 4, storage),
    }
}

fn bind_groups(
    engine: &Engine,
    base: &Progressive,
    cache: &CacheBuffers,
    pixels: &PixelBuffers,
) -> IrradianceBindGroups {
    engine.irradiance.bind_groups(
        &engine.gpu,
        &IrradianceBindings {
            estimator: base.bindings(),
            params: &cache.params,
            dispatch: &cache.dispatch,
            entries: &cache.entries,
            radii: &cache.radii,
            octree: &cache.octree,
            words: &pixels.words,
            pixel_aux: &pixels.pixel_aux,
            blocks: &pixels.blocks,
            requests: &cache.requests,
            cell_bins: &cache.cell_bins,
            bounds: &cache.bounds,
        },
    )
}

impl Technique for Irradiance {
    fn name(&self) -> &'static str {
        "irradiance"
    }

    fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        self.base.apply(engine, scene, change)?;
        match change {
            Change::Iterations => return Ok(()),
            Change::Camera => {}
            Change::Tf { old, .. } => self.apply_tf(engine, scene, old)?,
            Change::Lights => self.clear_cache(engine, scene)?,
            Change::Params => {
                let cache_stale = scene.params.density_scale != self.cache_density
                    || scene.params.g != self.cache_g;
                if cache_stale {
                    self.clear_cache(engine, scene)?;
                } else {
                    // Only the exposure changed: tone mapping shows it.
                    return Ok(());
                }
            }
            Change::Viewport => {
                let (width, height) = (scene.viewport.width, scene.viewport.height);
                let layout = Layout::new(width, height, &self.config);
                // Node capacity follows the entry capacity, so the cache buffers still fit.
                self.layout = Layout {
                    node_capacity: self.layout.node_capacity,
                    ref_capacity: self.layout.ref_capacity,
                    max_pending: self.layout.max_pending,
                    lock_depth: self.layout.lock_depth,
                    ..layout
                };
                self.pixels = pixel_buffers(engine, width, height, &self.layout);
                self.readback = readback_buffer(engine, &self.layout);
                self.bind_groups = bind_groups(engine, &self.base, &self.cache, &self.pixels);
                self.reset_words(engine);
                self.cursor = 0;
                self.block_cost = None;
            }
        }
        self.restart(engine);
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
        let before = self.iteration();
        let mut gpu_time = Duration::ZERO;
        while self.iteration() < target {
            // A zero budget asks for one frame now (the first after an edit: a picture, or
            // with `part_time` a part of one).
            let times = self.frame(engine, scene, !budget.is_zero())?;
            gpu_time += times.total();
            if budget.is_zero() || start.elapsed() >= budget {
                break;
            }
        }
        Ok(StepReport {
            iterations_done: self.iteration() - before,
            iteration: self.iteration(),
            converged: self.iteration() >= target,
            gpu_time,
        })
    }

    fn output(&self) -> &wgpu::Buffer {
        self.base.bindings().accum
    }

    fn set_part_time(&mut self, part: Option<Duration>) {
        self.part_time = part;
    }

    /// Image-sized rounds of block renders since the picture restarted.
    fn iteration(&self) -> u32 {
        (self.block_renders / self.layout.block_count.max(1) as u64) as u32
    }

    fn stats(&self) -> TechniqueStats {
        let cache = self.cache_stats();
        let (w, h) = self.base.size();
        TechniqueStats {
            name: self.name(),
            iteration: self.iteration(),
            memory_bytes: irradiance_bytes(
                w,
                h,
                &self.config,
                self.cache.cell_bins.size() as usize / 8,
            ),
            details: TechniqueDetails {
                cache_entries: Some(cache.entries),
                octree_references: Some(cache.references),
                cache_hit_rate: Some(cache.hit_rate),
                pending_entries: Some(cache.pending),
                cache_active: Some(cache.active),
                cache_entries_kept_pct: cache
                    .last_edit
                    .filter(|&(before, _)| before > 0)
                    .map(|(before, kept)| 100.0 * kept as f32 / before as f32),
                ..TechniqueDetails::default()
            },
        }
    }
}

/// Rounds of one cache procedure this frame: the time owed to it (`credit`, carried from frame
/// to frame, plus this frame's `share` in seconds, capped at one share or one round) spent in
/// whole rounds of `round` seconds (this frame's share when not measured yet), at most `most`.
/// Returns the rounds and the time they are planned to take; `frame` takes their measured time
/// off the credit. A slow round (a first dispatch, a busy machine) delays the next ones by at
/// most two frames' shares.
fn rounds_owed(credit: &mut f64, share: f64, round: Option<f64>, most: u32) -> (u32, f64) {
    let round = round.unwrap_or(share).max(1e-9);
    let owed = credit.max(-2.0 * share) + share;
    *credit = owed.min(share.max(round));
    let rounds = (*credit / round).floor().clamp(0.0, most as f64) as u32;
    (rounds, rounds as f64 * round)
}

/// The rounds a frame runs besides rendering (`frame` numbers the update rounds).
#[derive(Debug, Clone, Copy)]
struct PlannedRounds {
    create: u32,
    pending: u32,
    update: u32,
    /// Validation rounds (update dispatches with `validate` set).
    validate: u32,
    block_count: u32,
    frame: u32,
    priorities: bool,
}

/// Charges a phase's measured time to its credit and its cost estimate per unit of work
/// (`units`: rounds, times the requests each serves for creation); false when none ran. An
/// estimate that keeps every round from running decays, so that it heals (a first dispatch
/// that compiled the shader, a busy machine).
fn charge_rounds(
    credit: &mut f64,
    unit_cost: &mut Option<f64>,
    spent: Duration,
    units: u64,
) -> bool {
    if units == 0 {
        if let Some(cost) = unit_cost {
            *cost *= 0.95;
        }
        return false;
    }
    *credit -= spent.as_secs_f64();
    *unit_cost = Some(robust_smooth(
        *unit_cost,
        spent.as_secs_f64() / units as f64,
    ));
    true
}

/// One frame's dispatches, as the passes read them from the dispatch buffer: render chunks
/// (of the block list) first, then the creation rounds, the update rounds, the validation
/// rounds and the priority chunks, each a slot of `infos`.
#[derive(Debug, PartialEq)]
struct DispatchPlan {
    infos: Vec<DispatchInfo>,
    /// The blocks to render, in order (render chunks index into it).
    list: Vec<u32>,
    /// (slot, workgroups) of each render dispatch.
    render_dispatches: Vec<(u32, u32)>,
    create_first: u32,
    update_first: u32,
    validate_first: u32,
    priority_first: u32,
}

impl DispatchPlan {
    fn new(passes: &[Vec<u32>], rounds: PlannedRounds) -> Result<Self, EngineError> {
        let mut infos: Vec<DispatchInfo> = Vec::new();
        let mut list: Vec<u32> = Vec::new();
        let mut render_dispatches = Vec::new();
        for pass in passes {
            for chunk in pass.chunks(MAX_WORKGROUPS) {
                render_dispatches.push((infos.len() as u32, chunk.len() as u32));
                infos.push(DispatchInfo {
                    first: list.len() as u32,
                    count: chunk.len() as u32,
                    round: 0,
                    validate: 0,
                });
                list.extend_from_slice(chunk);
            }
        }
        // `n` rounds over `count` items, numbered from `round` on; the first one's slot.
        let mut push_rounds = |n: u32, count: u32, round: u32, validate: u32| {
            let first = infos.len() as u32;
            infos.extend((0..n).map(|r| DispatchInfo {
                first: 0,
                count,
                round: round.wrapping_add(r),
                validate,
            }));
            first
        };
        let create_first = push_rounds(rounds.create.min(MAX_CREATE_ROUNDS), rounds.pending, 0, 0);
        let update_first = push_rounds(
            rounds.update.min(MAX_UPDATE_ROUNDS),
            rounds.block_count,
            rounds.frame.wrapping_mul(MAX_UPDATE_ROUNDS),
            0,
        );
        let validate_first = push_rounds(
            rounds.validate.min(MAX_VALIDATION_ROUNDS),
            rounds.block_count,
            rounds.frame.wrapping_mul(MAX_VALIDATION_ROUNDS),
            1,
        );
        let priority_first = infos.len() as u32;
        if rounds.priorities {
            let n = rounds.block_count as usize;
            for first in (0..n).step_by(MAX_WORKGROUPS) {
                infos.push(DispatchInfo {
                    first: first as u32,
                    count: (n - first).min(MAX_WORKGROUPS) as u32,
                    round: 0,
                    validate: 0,
                });
            }
        }
        if infos.len() > DISPATCH_SLOTS as usize {
            return Err(EngineError::Gpu(format!(
                "irradiance frame needs {} dispatches, has {DISPATCH_SLOTS}",
                infos.len()
            )));
        }
        Ok(DispatchPlan {
            infos,
            list,
            render_dispatches,
            create_first,
            update_first,
            validate_first,
            priority_first,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounds_owed_spends_the_share_in_whole_rounds() {
        // A 10 ms share and 4 ms rounds: 2 rounds now; the credit holds the share until
        // `frame` takes the rounds' measured time off it.
        let mut credit = 0.0;
        let (rounds, planned) = rounds_owed(&mut credit, 0.010, Some(0.004), 48);
        assert_eq!(rounds, 2);
        assert!((planned - 0.008).abs() < 1e-12);
        assert!((credit - 0.010).abs() < 1e-12, "credit {credit}");
        // A slow round (credit far below zero) delays the next ones by two shares at most.
        let mut credit = -1.0;
        let (rounds, _) = rounds_owed(&mut credit, 0.010, Some(0.004), 48);
        assert_eq!(rounds, 0);
        assert!((credit - -0.010).abs() < 1e-12, "credit {credit}");
        // Never more than `most`, and a round not measured yet costs the share.
        let mut credit = 0.0;
        assert_eq!(rounds_owed(&mut credit, 0.010, Some(1e-6), 3).0, 3);
        let mut credit = 0.0;
        assert_eq!(rounds_owed(&mut credit, 0.010, None, 48).0, 1);
    }

    fn rounds(create: u32, update: u32, block_count: u32, priorities: bool) -> PlannedRounds {
        PlannedRounds {
            create,
            pending: 7,
            update,
            validate: 0,
            block_count,
            frame: 3,
            priorities,
        }
    }

    #[test]
    fn the_dispatch_plan_renders_first_then_rounds_then_priorities() {
        let passes = vec![vec![4, 5, 6], vec![1, 2]];
        let plan = DispatchPlan::new(&passes, rounds(2, 1, 9, true)).expect("plan");
        assert_eq!(plan.list, vec![4, 5, 6, 1, 2]);
        assert_eq!(plan.render_dispatches, vec![(0, 3), (1, 2)]);
        assert_eq!((plan.infos[1].first, plan.infos[1].count), (3, 2));
        assert_eq!(
            (plan.create_first, plan.update_first, plan.priority_first),
            (2, 4, 5)
        );
        assert_eq!(
            (
                plan.infos[2].count,
                plan.infos[2].round,
                plan.infos[3].round
            ),
            (7, 0, 1)
        );
        // Update rounds are numbered by frame, so each frame updates other entries.
        assert_eq!(plan.infos[4].round, 3 * MAX_UPDATE_ROUNDS);
        assert_eq!((plan.infos[5].first, plan.infos[5].count), (0, 9));
        assert_eq!(plan.infos.len(), 6);
        assert!(plan.infos.iter().all(|i| i.validate == 0));
        // Validation rounds: update dispatches over every block, after the update rounds,
        // flagged, and numbered by frame too.
        let plan = DispatchPlan::new(
            &passes,
            PlannedRounds {
                validate: 3,
                ..rounds(2, 1, 9, true)
            },
        )
        .expect("plan");
        assert_eq!(
            (plan.update_first, plan.validate_first, plan.priority_first),
            (4, 5, 8)
        );
        let validation = &plan.infos[5..8];
        assert!(validation.iter().all(|i| i.validate == 1 && i.count == 9));
        assert_eq!(validation[2].round, 3 * MAX_VALIDATION_ROUNDS + 2);
        assert_eq!(plan.infos[4].validate, 0);
        assert_eq!(plan.infos[8].validate, 0);
    }

    #[test]
    fn the_dispatch_plan_chunks_large_passes_and_refuses_too_many_slots() {
        let big: Vec<u32> = (0..(MAX_WORKGROUPS as u32 + 10)).collect();
        let plan = DispatchPlan::new(&[big], rounds(0, 0, 4, false)).expect("plan");
        assert_eq!(
            plan.render_dispatches,
            vec![(0, MAX_WORKGROUPS as u32), (1, 10)]
        );
        assert_eq!(plan.infos[1].first, MAX_WORKGROUPS as u32);
        let many: Vec<Vec<u32>> = (0..DISPATCH_SLOTS).map(|i| vec![i]).collect();
        assert!(DispatchPlan::new(&many, rounds(1, 0, 4, false)).is_err());
    }

    #[test]
    fn shuffled_blocks_are_a_permutation_out_of_raster_order() {
        let mut state = 7u64;
        let mut blocks: Vec<u32> = (0..72).collect();
        shuffle(&mut blocks, || lcg_uniform(&mut state));
        let mut sorted = blocks.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..72).collect::<Vec<u32>>());
        // A contiguous half (what llvmpipe gives one thread) mixes both halves of the image.
        let from_top = blocks[..36].iter().filter(|&&b| b < 36).count();
        assert!(
            (8..=28).contains(&from_top),
            "{from_top} of the first 36 from the top half"
        );
        // A draw of exactly 1 (rounding) still picks an index in range (it would panic).
        let mut two = vec![5u32, 6];
        shuffle(&mut two, || 1.0);
        assert_eq!(two, [5, 6]);
    }

    #[test]
    fn validity_radius_follows_eq_9_and_10() {
        // Irradiance falling by a factor 2 over Δ = 1: σ = ln 2; the extrapolation E0·e^(−σx)
        // reaches (1 − ε)·E_Δ at x = Δ + ln(1/(1 − ε))/σ.
        let sigma = 2f32.ln();
        let r = validity_radius(sigma, 1.0, 0.1, 0.01, 100.0);
        let e_delta = 0.5f32;
        assert!(((-sigma * r).exp() - 0.9 * e_delta).abs() < 1e-5);
        // Growing irradiance: (1 + ε)·E_Δ.
        let r = validity_radius(-sigma, 1.0, 0.1, 0.01, 100.0);
        assert!(((sigma * r).exp() - 1.1 * 2.0).abs() < 1e-4);
        // Flat irradiance: the largest zone; huge gradients: never below Δ, clamped above.
        assert_eq!(validity_radius(0.0, 1.0, 0.1, 0.01, 16.0), 16.0);
        assert!(validity_radius(1e6, 1.0, 0.1, 0.01, 16.0) >= 1.0);
    }

    #[test]
    fn basis_is_orthonormal_and_keeps_the_normal() {
        for n in [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.6, 0.0, 0.8],
            [0.48, -0.6, 0.64],
        ] {
            let b = orthonormal_basis(n);
            for i in 0..3 {
                for j in 0..3 {
                    let dot: f32 = (0..3).map(|k| b[i][k] * b[j][k]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-5, "{n:?}: axes {i}·{j} = {dot}");
                }
            }
            assert_eq!(b[2], n);
        }
    }

    #[test]
    fn pending_entries_scale_with_the_viewport_as_in_table_1() {
        let config = IrradianceConfig::default();
        assert_eq!(Layout::new(1280, 720, &config).max_pending, 1000);
        assert_eq!(Layout::new(64, 64, &config).max_pending, 16);
        assert_eq!(Layout::new(1920, 1080, &config).max_pending, 1000);
        let layout = Layout::new(100, 50, &config);
        assert_eq!((layout.blocks_x, layout.blocks_y), (7, 7));
        let words = layout.fresh_words(5);
        assert_eq!(words[COUNTER_ENTRIES], 5);
        assert_eq!(words[layout.node_claim_offset() as usize], u32::MAX);
        assert_eq!(words[layout.node_held_offset() as usize], 0);
        assert_eq!(words[layout.block_claim_offset() as usize], u32::MAX);
        assert_eq!(*words.last().unwrap(), 0);
    }

    #[test]
    fn bad_configurations_are_refused() {
        let bad = [
            IrradianceConfig {
                bounces: 0,
                ..Default::default()
            },
            IrradianceConfig {
                epsilon: 1.0,
                ..Default::default()
            },
            IrradianceConfig {
                creation_fraction: (0.2, 0.1),
                ..Default::default()
            },
            IrradianceConfig {
                min_samples: 1,
                ..Default::default()
            },
        ];
        for config in bad {
            assert!(validate(&config).is_err(), "{config:?}");
        }
        validate(&IrradianceConfig::default()).unwrap();
    }

    #[test]
    fn an_indirect_cache_holds_all_the_light_where_there_is_no_indirect_light() {
        let sun = Light::Directional {
            direction: [0.0, 0.0, -1.0],
            irradiance: [1.0; 3],
        };
        let sky = |radiance| Light::Environment { radiance };
        let scene = |lights| Scene {
            lights,
            ..Scene::default()
        };
        let config = |bounces, cached_light| IrradianceConfig {
            bounces,
            cached_light,
            ..Default::default()
        };
        use CachedLight::{All, Indirect};
        let cases = [
            (config(DEFAULT_BOUNCES, Indirect), vec![sun], Indirect),
            (config(1, Indirect), vec![sun], All),
            (config(1, Indirect), vec![sun, sky([0.0; 3])], All),
            (config(1, Indirect), vec![sun, sky([0.1; 3])], Indirect),
            (config(DEFAULT_BOUNCES, All), vec![sun], All),
        ];
        for (config, lights, want) in cases {
            assert_eq!(
                cached_light(&config, &scene(lights.clone())),
                want,
                "{lights:?}"
            );
        }
    }
}
