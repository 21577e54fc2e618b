//! Technique `photon`: volumetric photon mapping with historygrams (Jönsson et al. 2012). Its
//! steps, the incremental TF update and why that update equals a full recompute bit for bit are
//! in docs/architecture.md, "`photon`".
//!
//! - A progressive pass traces `photons_per_pass` more paths (shaders/photon/trace.wgsl),
//!   rebuilds the hash grid over every record (photon/grid.wgsl), gathers every view-ray
//!   segment from all photons so far and composites (photon/gather.wgsl); each pass's photons
//!   are gathered with that pass's shrinking radius (`pass_kernels`).
//! - A TF edit (`update_tf`) retraces only the paths its split query historygram can change,
//!   keeps the changed records in a change list, and regathers or updates from the changes
//!   only the segments they reach (the delta gather, or the delta scatter of photon/scatter.wgsl).
//!   With per-sample photon sums (`PhotonParams::sample_cache_bytes`, where they fit) the
//!   changes update the sums instead (`add_changes_to_sums`), and the segments recomposite from
//!   them.
//! - A camera edit keeps the photons and gathers again.
//! - What a gather does is planned by pure, tested steps (`GridPlan`, `touch_entries`,
//!   `GatherInProgress::part`); `begin_gather` and `gather_part` only record the dispatches.
//! - A pass's trace runs in parts of about `GATHER_PART_TIME` (paths are independent); a TF
//!   edit first finishes it with the TF it started with, a camera edit lets it finish, and
//!   its last part starts the pass's gather.
//! - A gather runs in parts of about `GATHER_PART_TIME`, so that `step` returns between them
//!   and an edit waits for a part, not for the gather (~9 s at 512² on lavapipe); segments are
//!   independent, so the parts give one dispatch's bits. A camera or light edit drops a gather
//!   under way; a TF edit updates the photons and restarts a full gather under way with the
//!   new TF, and finishes any other gather first (its update starts from the old TF's segments).
//! - A gather runs in rounds within the device's loop limit (`round_budget`); fixed-point sums
//!   make the result independent of where a round ends.
//! - `census` counts a full recompute's work per record (benchmarks): compared between two TFs
//!   it bounds what any bit-exact update between them can save.

pub mod census;
mod config;
pub mod gpu;
pub mod slots;

use std::cell::{Cell, RefCell};
use std::sync::Arc;
use std::time::{Duration, Instant};

use voxlight_protocol::{Light, TechniqueDetails, TransferFunction};

use crate::gpu::TfTexture;
use crate::scene_gpu::{SceneUniforms, default_step};
use crate::technique::{StepReport, Technique, TechniqueStats};
use crate::techniques::photon::gpu::{
    COUNTER_CHANGED, COUNTER_CHANGES, COUNTER_CUT, COUNTER_DEFERRED, COUNTER_DELTA, COUNTER_LIST,
    COUNTER_RECOLOURED, COUNTER_RETRACED, COUNTER_SCATTER, COUNTER_SCATTER_OVERFLOW,
    COUNTER_SEGMENTS, COUNTER_SPATIAL, COUNTER_TOUCH, COUNTER_WORDS, EMIT_DIRECTIONAL,
    EMIT_ENVIRONMENT, EMIT_POINT, GRID_CHANGES, GRID_RECORDS, GatherState, MODE_FULL, MODE_UPDATE,
    PASS_KERNEL_ENTRIES, PhotonBindings, PhotonChange, PhotonEmitter, PhotonPass, PhotonPath,
    PhotonRecord, PhotonUniforms, RecordResume, SAMPLE_WORDS, SLOT_WORDS, SPATIAL_AXES,
    SPATIAL_CELLS, SPATIAL_NONE, Segment, WORKGROUP, dispatch_groups, dispatch_linear,
};
use crate::tf::{
    bake, collision_query_historygram, opacity_query_historygram, opacity_rise_historygram,
    opaque_bins, query_historygram,
};
use crate::{Change, Engine, EngineError, GpuVolume, Scene};
pub use census::{Census, WorkBound};
pub use slots::RecordLayout;

/// Parameters of the photon map (the paper's Pn, Sn, Vn and the gather radius).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotonParams {
    /// Photon paths traced per progressive pass.
    pub photons_per_pass: u32,
    /// Passes after which the picture is converged (also capped by the scene's iterations).
    pub max_passes: u32,
    /// Scattering events stored per path (Sn), the cap on a path's length: 1 = single
    /// scattering; the paper's 2 truncates multiple scattering (−10% on the Mitsuba blob scene,
    /// docs/validation.md). With Russian roulette most paths end well before it; the default
    /// is high enough that the cap cuts no energy that shows (−4% at 16 on the albedo-0.99
    /// scene), since a path's records need not have fixed slots (`record_slots`).
    pub bounces: u32,
    /// Record slots per path on average (the map's memory; 8, where the Mitsuba scenes' passes
    /// take at most a third of their pools): where `bounces` is larger, a path
    /// has `slots::INLINE_SLOTS` of its own and takes chunks from its pass's shared pool as it
    /// grows (`RecordLayout`). Where a pass's paths need more than its pool holds, the
    /// session doubles this and recomputes the map (`make_room`); an update whose paths would
    /// is done as a full recompute.
    pub record_slots: u32,
    /// Russian roulette: a path goes on past interaction `roulette_from` − 1 with this
    /// probability, its power divided by it (>= 1: off, every path runs to the cap or out of
    /// the volume). A constant rather than the albedo, so that a path's length does not depend
    /// on the TF's colours and a colour edit stays a recolouring. High (0.95), because in a
    /// medium of albedo near 1 the orders past a few dozen are carried by the rare paths that
    /// survive that long, each weighted 1 / survival^k: at 0.85 a pass of 16384 paths almost
    /// never has one, and the picture came out 1% dark with 6.7% block error on the Mitsuba
    /// `dense` scene (0.95: 0.6%, 3.7%; docs/validation.md).
    pub roulette_survival: f32,
    /// The first interaction (>= 1) that plays the roulette.
    pub roulette_from: u32,
    /// Progressive radius reduction (Knaus & Zwicker 2011, the (i + α) / (i + 1) rule in 3D):
    /// pass i's photons are gathered with r_i, r_i³ = r_0³ · Π_{k<i} (k + α) / (k + 1), and the
    /// picture is the mean of the passes' estimates, so that kernel blur falls with passes as
    /// noise does. In (0, 1]; 1 keeps one radius. The schedule depends on the pass index only,
    /// so an incremental update gathers every photon with the radius a full recompute does.
    pub radius_alpha: f32,
    /// Gather radius of the first pass (= hash-grid cell edge) in world units; 0 picks 1.5
    /// voxel edges, but at least 1/150 of the longest side (the grid stays within
    /// `MAX_GRID_CELLS`). 2.5 voxel edges, the old default, blurred thin structure: on the
    /// Mitsuba CT scene the block RMSE over the volume fell from 7.1% to 4.0% at 1.5
    /// (docs/validation.md), on the blob scene it stayed at 2.7–2.9%.
    pub radius: f32,
    /// View-ray segments per pixel (Vn).
    pub segments: u32,
    /// View-ray march step in voxel edges.
    pub gather_step_voxels: f32,
    /// How a view-ray segment learns that photons within its reach changed (its own
    /// historygram covers only its samples' data values). Every choice keeps the update exact;
    /// they differ in how many segments they recompute.
    pub invalidation: Invalidation,
    /// Loop iterations (photons, cells, samples) one gather invocation runs per round before it
    /// keeps its place for the next; 0 takes the device's loop limit (`Gpu::loop_limit`; one
    /// round where there is none). The result does not depend on it.
    pub gather_budget: u32,
    /// Entries of the change list (old and new versions of the records an update changes, one
    /// entry for both where only the power changed); 0 sizes it to the map's records. An update
    /// that changes more gathers its photon-stale segments afresh instead of from the changes
    /// alone: the same bits, more work.
    pub change_list: u32,
    /// Bytes the delta scatter may take (a slot per segment, and per segment it updates that
    /// segment's sample weights); 0 turns it off, and every segment an update changes by its
    /// photons alone is gathered from the change grid instead. The result does not depend on
    /// it: segments past its capacity are gathered.
    pub scatter_bytes: u64,
    /// Bytes the per-sample photon sums may take (28 per lattice sample a view ray can hold:
    /// pixels × the box diagonal in steps); 0, or a view that needs more, turns them off.
    /// With them a segment is the sum over its samples of each sample's photon sum weighted
    /// once, so a segment whose opacity changed recomposites from the sums instead of
    /// gathering its photons again (photon/common.wgsl, `sample_sums`). Both formulations are
    /// exact; they differ in rounding, so an update always uses the one its full gather used.
    pub sample_cache_bytes: u64,
}

/// How segments detect changed photons after a TF edit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Invalidation {
    /// Any changed photon makes every segment stale (data historygrams alone, made exact).
    AnyPhoton,
    /// The paper's spatial historygram: 3×64 bits, one 64-bin mask per axis of the positions of
    /// changed photons; a segment is stale when its box grown by the radius meets all three.
    SpatialHistogram,
    /// A dirty bit per half-size hash cell (dilated by two, the gather radius): a segment is
    /// stale when one of its samples lies in a dirty cell. Finer than the paper's; costs
    /// cells bytes.
    DirtyCells,
}

impl Invalidation {
    /// The protocol's name of this choice (`photon.invalidation`).
    pub fn name(self) -> &'static str {
        match self {
            Invalidation::AnyPhoton => "any_photon",
            Invalidation::SpatialHistogram => "spatial3x64",
            Invalidation::DirtyCells => "dirty_cells",
        }
    }

    fn uniform(self) -> u32 {
        match self {
            Invalidation::AnyPhoton => SPATIAL_NONE,
            Invalidation::SpatialHistogram => SPATIAL_AXES,
            Invalidation::DirtyCells => SPATIAL_CELLS,
        }
    }
}

impl Default for PhotonParams {
    fn default() -> Self {
        Self {
            photons_per_pass: 16384,
            max_passes: 8,
            bounces: 256,
            record_slots: 8,
            roulette_survival: 0.95,
            roulette_from: 2,
            radius_alpha: 2.0 / 3.0,
            radius: 0.0,
            segments: 8,
            gather_step_voxels: 1.0,
            invalidation: Invalidation::DirtyCells,
            gather_budget: 0,
            change_list: 0,
            scatter_bytes: 64 << 20,
            sample_cache_bytes: 256 << 20,
        }
    }
}

/// One gather round: which half of the segment list it reads, its iteration budget per
/// segment, and how many invocations per segment (all but the first idle).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Round {
    input: u32,
    budget: u32,
    stride: u32,
    /// The first list slot of this dispatch (a part of the round).
    first: u32,
}

/// A gather under way (`begin_gather`): the round it is in and the list slots of that round
/// dispatched so far.
#[derive(Debug, Clone, Copy)]
struct GatherInProgress {
    mode: u32,
    query: Query,
    /// Which half of the segment list this round reads.
    input: u32,
    /// Rounds completed.
    rounds: u32,
    /// Segments this round's list holds (0: the gather is done; it composites next).
    listed: u32,
    /// List slots of this round dispatched so far.
    next: u32,
    /// Whether the marks passes marked every pixel whose segments this update computes, so
    /// that only those are recomposited (`composite_changed`).
    pixels_marked: bool,
    /// Whether the composite already ran after the last segment was computed (`begin_gather`
    /// submits it with `remarch_from_sums`).
    composited: bool,
}

/// One part of a gather round (`GatherInProgress::part`): what `gather_part` dispatches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct GatherPart {
    round: Round,
    /// List slots this part gathers (`slots × round.stride` invocations).
    slots: u32,
    /// The half of the segment list where this round leaves the segments it does not finish;
    /// its counter is cleared before the round's first part (`clear_output`).
    output: u32,
    clear_output: bool,
    /// Whether this part ends its round.
    ends_round: bool,
    /// The counter word holding the next round's list length, read after a part that ends a
    /// bounded round (None: nothing to read; an unbounded round leaves no segment).
    next_list: Option<usize>,
}

impl GatherInProgress {
    /// A gather of the `listed` segments in half `input` of the segment list.
    fn new(mode: u32, query: Query, listed: u32, input: u32) -> Self {
        Self {
            mode,
            query,
            input,
            rounds: 0,
            listed,
            next: 0,
            pixels_marked: false,
            composited: false,
        }
    }

    /// The next part: at most `max_slots` (at least one) of this round's list slots, with
    /// `lane_budget` loop iterations per lane (u32::MAX: unbounded, one round). The segments
    /// left after a round are the heaviest: each further round gives them twice the budget on
    /// half as many lanes per SIMD batch of `lanes`, down to one lane.
    fn part(&self, lane_budget: u32, lanes: u32, max_slots: u32) -> GatherPart {
        let lanes = lanes.clamp(1, 64);
        let stride = if lane_budget < u32::MAX {
            (1u32 << self.rounds.min(6)).min(lanes)
        } else {
            1
        };
        let budget = lane_budget.saturating_mul(stride);
        let slots = (self.listed - self.next).min(max_slots.max(1));
        let output = 1 - self.input;
        let ends_round = self.next + slots >= self.listed;
        GatherPart {
            round: Round {
                input: self.input,
                budget,
                stride,
                first: self.next,
            },
            slots,
            output,
            clear_output: self.next == 0,
            ends_round,
            next_list: (ends_round && budget != u32::MAX).then_some(COUNTER_LIST + output as usize),
        }
    }

    /// Moves on past `part`; `left` is the counter `part.next_list` names (0 when it names
    /// none). The gather is done once `listed` is 0.
    fn advance(&mut self, part: &GatherPart, left: u32) {
        self.next += part.slots;
        if part.ends_round {
            self.rounds += 1;
            self.next = 0;
            self.listed = left;
            self.input = part.output;
        }
    }
}

/// What `gather_mark` counted for an update (its counter words).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Marked {
    /// Segments listed to gather, afresh or from the changes (`COUNTER_SEGMENTS`).
    segments: u32,
    /// Of those, segments to update from the changed photons alone (`COUNTER_DELTA`).
    delta: u32,
    /// Of those, segments given a delta scatter slot (`COUNTER_SCATTER`; may pass its capacity).
    scatter: u32,
    /// Change-list entries the update wrote (`COUNTER_CHANGES`; may pass the list's length).
    changes: u32,
    /// Of the segments whose opacity changed, those whose last march ended at its
    /// transmittance cut-off (`COUNTER_CUT`): samples past it were never gathered.
    cut: u32,
}

impl Marked {
    fn from_words(words: &[u32]) -> Self {
        Self {
            segments: words[COUNTER_SEGMENTS],
            delta: words[COUNTER_DELTA],
            scatter: words[COUNTER_SCATTER],
            changes: words[COUNTER_CHANGES],
            cut: words[COUNTER_CUT],
        }
    }
}

/// The delta scatter's dispatches (`Photon::scatter`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ScatterPlan {
    /// The changes far outnumber the slots' segments (the delta gather's cost follows the
    /// segments, the scatter's the changes): `scatter_fallback` over the slots lists their
    /// segments for the delta gather at once.
    Fallback { slots: u32 },
    /// `scatter_weights` over the slots, `scatter_changes` over the change-list entries, then
    /// `scatter_apply` over the slots, or `scatter_fallback` where a change reached more
    /// pixels than one invocation may visit (one blocking read).
    Scatter { slots: u32, changes: u32 },
}

/// One grid build (`Photon::build_grid`): which grid, over how many items (records or
/// change-list entries).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct GridBuild {
    grid: u32,
    items: u32,
}

/// What a gather does between `gather_mark` and its rounds (`begin_gather`): the delta
/// scatter, and the grids its gather reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct GridPlan {
    /// Some segments are gathered afresh: they read the records' grid.
    records_grid: bool,
    scatter: Option<ScatterPlan>,
    /// Segments the delta gather takes from the change grid when the scatter keeps its slots.
    from_changes: u32,
    /// Every segment updated from the changes (all go to the delta gather when the scatter
    /// gives its slots back).
    delta: u32,
    /// Items of the two grids: the records in the map, the change list's length.
    records: u32,
    change_entries: u32,
}

impl GridPlan {
    /// A full gather: every segment afresh, from the records' grid.
    fn full(records: u32) -> Self {
        Self {
            records_grid: true,
            scatter: None,
            from_changes: 0,
            delta: 0,
            records,
            change_entries: 0,
        }
    }

    /// An update's gather with per-sample sums: segments recomposite from the sums, a sum
    /// not kept is gathered from the records' grid, and where the changes are not yet in
    /// the sums (`applied` false) the dirty samples add them from the change grid. A segment
    /// whose opacity did not change gathers the samples it gathered before, and so does one
    /// whose opacity only fell (no bin's rose: `opacity_rose` false) unless its last march
    /// ended at its cut-off (`Marked::cut`): a sample it gathers now had opacity then, and was
    /// gathered. So where every sample gathered since the last full gather holds a valid sum
    /// (`complete`), the records' grid is needed only for the segments whose opacity rose or
    /// that were cut off.
    fn summed(
        marked: Marked,
        applied: bool,
        complete: bool,
        opacity_rose: bool,
        records: u32,
        change_entries: u32,
    ) -> Self {
        let from_changes = if !applied && marked.changes <= change_entries {
            marked.segments
        } else {
            0
        };
        Self {
            records_grid: marked.segments > 0
                && (!complete
                    || (marked.segments > marked.delta && (opacity_rose || marked.cut > 0))),
            scatter: None,
            from_changes,
            delta: from_changes,
            records,
            change_entries,
        }
    }

    /// An update's gather from `gather_mark`'s counts, with slots for `scatter_capacity`
    /// segments and a change list of `change_entries`.
    fn update(marked: Marked, scatter_capacity: u32, records: u32, change_entries: u32) -> Self {
        let slots = marked.scatter.min(scatter_capacity);
        let changes = marked.changes.min(change_entries);
        let scatter = (slots > 0).then(|| {
            if changes as u64 > SCATTER_CHANGES_PER_SEGMENT * slots as u64 {
                ScatterPlan::Fallback { slots }
            } else {
                ScatterPlan::Scatter { slots, changes }
            }
        });
        Self {
            records_grid: marked.segments > marked.delta,
            scatter,
            from_changes: marked.delta.saturating_sub(slots),
            delta: marked.delta,
            records,
            change_entries,
        }
    }

    /// Segments the scatter updated; `gave_back`: it left its slots to the delta gather.
    fn scattered(&self, gave_back: bool) -> u32 {
        match self.scatter {
            Some(ScatterPlan::Scatter { slots, .. }) if !gave_back => slots,
            _ => 0,
        }
    }

    /// The grids to build once the scatter has run, the records' first.
    fn grids(&self, gave_back: bool) -> Vec<GridBuild> {
        let from_changes = if gave_back {
            self.delta
        } else {
            self.from_changes
        };
        let mut grids = Vec::new();
        if self.records_grid {
            grids.push(GridBuild {
                grid: GRID_RECORDS,
                items: self.records,
            });
        }
        if from_changes > 0 {
            grids.push(GridBuild {
                grid: GRID_CHANGES,
                items: self.change_entries,
            });
        }
        grids
    }
}

/// After an update's trace, the change-list entries `scatter_touch` marks segments from
/// (None: `gather_mark` marches every segment through the dirty cells instead, cheaper where
/// the changes are many for the segments).
fn touch_entries(changes: u64, segments: u64, change_entries: u64) -> Option<u32> {
    (changes * TOUCH_SEGMENTS_PER_CHANGE <= segments).then(|| changes.min(change_entries) as u32)
}

/// A part of a long gather takes about this long (one submission).
const GATHER_PART_TIME: Duration = Duration::from_millis(40);

/// List slots of a gather's first part, before the gather's rate is known.
const FIRST_PART_SLOTS: u32 = 16384;

/// List slots of `step`'s next gather part: `fixed` (tests), else as many as the last part's
/// `rate` (slots per second) gathers in `GATHER_PART_TIME`, else `FIRST_PART_SLOTS`.
fn part_slots(fixed: Option<u32>, rate: Option<f64>) -> u32 {
    match (fixed, rate) {
        (Some(slots), _) => slots,
        (None, Some(rate)) => {
            (rate * GATHER_PART_TIME.as_secs_f64()).clamp(1.0, u32::MAX as f64) as u32
        }
        (None, None) => FIRST_PART_SLOTS,
    }
}

/// Paths of a pass's first trace part, before the trace's rate is known.
const FIRST_TRACE_PATHS: u32 = 2048;

/// Paths of `step`'s next trace part: `fixed` (tests), else as many as the last part's `rate`
/// (paths per second) traces in `GATHER_PART_TIME` (at least a workgroup's), else
/// `FIRST_TRACE_PATHS`.
fn trace_part_paths(fixed: Option<u32>, rate: Option<f64>) -> u32 {
    match (fixed, rate) {
        (Some(paths), _) => paths.max(1),
        (None, Some(rate)) => {
            (rate * GATHER_PART_TIME.as_secs_f64()).clamp(WORKGROUP as f64, u32::MAX as f64) as u32
        }
        (None, None) => FIRST_TRACE_PATHS,
    }
}

/// What one submission's uniforms select besides the edit: the mode, the paths a trace
/// dispatch covers, the gather round and the grid the grid kernels build.
#[derive(Debug, Clone, Default)]
struct Dispatch {
    mode: u32,
    trace_paths: std::ops::Range<u32>,
    round: Round,
    grid_pass: u32,
}

/// An update's photon side from its counter words (the segments' side is the caller's).
fn photons_report(words: &[u32], paths: u32, segments: u64) -> UpdateReport {
    UpdateReport {
        paths: paths as u64,
        // trace_mark lists both kinds; the trace counts the recoloured ones.
        paths_retraced: words[COUNTER_RETRACED].saturating_sub(words[COUNTER_RECOLOURED]) as u64,
        paths_recoloured: words[COUNTER_RECOLOURED] as u64,
        records_changed: words[COUNTER_CHANGED] as u64,
        segments,
        changes: words[COUNTER_CHANGES] as u64,
        ..UpdateReport::default()
    }
}

/// The bins a TF edit changed (widened, see `update_tf`): any property, and opacity alone.
#[derive(Debug, Clone, Copy, Default)]
struct Query {
    any: u64,
    opacity: u64,
    /// Bins whose opacity rose (photon/common.wgsl: rejection_query).
    rejection: u64,
    /// Bins whose colour changed or opacity fell (collision_query).
    collision: u64,
}

/// What one incremental TF update did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct UpdateReport {
    pub paths: u64,
    /// Paths tracked again from a moved interaction on.
    pub paths_retraced: u64,
    /// Paths whose records only took new powers (a changed colour where they collided): no
    /// flight of theirs was tracked.
    pub paths_recoloured: u64,
    /// Records that differ from before (all of them when the edit touched every bin and the
    /// map was recomputed without comparing).
    pub records_changed: u64,
    pub segments: u64,
    pub segments_recomputed: u64,
    /// Of those, segments updated from the changed photons alone (their opacity unchanged).
    pub segments_delta: u64,
    /// Of those, segments the delta scatter updated (the rest were gathered from the change
    /// grid: past its capacity, or all of them where the changes far outnumbered them or one
    /// reached too many pixels).
    pub segments_scattered: u64,
    /// Entries of the change list (old and new versions of the changed records; one per record
    /// whose power alone changed).
    pub changes: u64,
    /// Spatial historygram after the update: x, y, z masks.
    pub spatial: [u64; 3],
}

impl UpdateReport {
    pub fn photons_retraced_pct(&self) -> f64 {
        100.0 * self.paths_retraced as f64 / self.paths.max(1) as f64
    }

    pub fn segments_recomputed_pct(&self) -> f64 {
        100.0 * self.segments_recomputed as f64 / self.segments.max(1) as f64
    }
}

/// The GPU state read back, for comparisons. The map is in path order: which slots a path's
/// records lie in depends on the order its pass's paths took chunks (`slots`), which no
/// result depends on.
#[derive(Debug, Clone, PartialEq)]
pub struct PhotonState {
    /// Every path's records in order, path after path (the slots past a path's end hold
    /// none).
    pub records: Vec<PhotonRecord>,
    /// The paths, with `chunk` zeroed.
    pub paths: Vec<PhotonPath>,
    pub segments: Vec<Segment>,
    /// Per pixel: radiance rgb, w = 1.
    pub hdr: Vec<[f32; 4]>,
    /// The hash grid's cell starts, then its records sorted by cell, as indices into
    /// `records` (`u32::MAX`: a slot that holds no path's record).
    pub grid_cells: Vec<u32>,
    pub grid_sorted: Vec<u32>,
}

/// Sizes of one session's buffers (bytes), computed before anything is allocated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotonBudget {
    pub paths: u64,
    /// Record slots (`layout`: paths · path_slots).
    pub records: u64,
    pub layout: RecordLayout,
    pub cells: u64,
    pub grid_dims: [u32; 3],
    pub radius: f32,
    pub record_bytes: u64,
    /// The records' resumes (`RecordResume`, one per slot).
    pub record_resume_bytes: u64,
    pub path_bytes: u64,
    pub grid_cell_bytes: u64,
    pub grid_sorted_bytes: u64,
    pub segment_bytes: u64,
    /// The segments one gather computes (indices), compacted by `gather_mark`.
    pub gather_list_bytes: u64,
    /// Where each unfinished segment's gather stands between rounds.
    pub gather_state_bytes: u64,
    /// The paths an update retraces (indices), compacted by `trace_mark`; in the second half,
    /// those the walk left to the trace.
    pub retrace_list_bytes: u64,
    /// Entries of the change list.
    pub change_entries: u64,
    /// The records an update changed, old and new versions (its change grid's items).
    pub change_bytes: u64,
    /// Segments the delta scatter can update per update (0: off) and the lattice samples it
    /// keeps per segment.
    pub scatter_capacity: u64,
    pub scatter_samples: u64,
    pub scatter_bytes: u64,
    /// Lattice samples per pixel whose photon sums are kept (0: off) and their bytes.
    pub sample_cache_samples: u64,
    pub sample_cache_bytes: u64,
    pub accum_bytes: u64,
    /// Counters plus one dirty bit per grid cell.
    pub counter_bytes: u64,
    /// The chunks' next pointers and per pass the chunks taken.
    pub chunk_bytes: u64,
    /// Rows of the `path_queries` texture (`gpu::PATH_QUERY_ROW` words each).
    pub path_query_rows: u32,
    pub total: u64,
}

/// Change-list entries per segment to update above which an update gathers those segments from
/// the change grid instead of scattering the changes. On lavapipe a change costs the scatter
/// ~4 µs and a segment the delta gather ~11 µs (engine and chest CT profiles, 2026-12-02): an
/// outer-layer edit of the engine, 18 136 changes for 3 800 segments, took 1.0× with the
/// scatter and 1.5× without; its colour edit, 3 393 for 13 000, 7.8× against 4.4×.
const SCATTER_CHANGES_PER_SEGMENT: u64 = 2;

/// Change-list entries per listed segment above which an update with per-sample sums adds its
/// changes to the sums in the gather (at each listed segment's dirty samples, from the change
/// grid) rather than by `scatter_sums`. The gather pays per dirty sample of every listed
/// segment, the scatter per change. On lavapipe (96², 2026-12-05) the outer-layer edits, where
/// the changes are many, took 777–781 ms (Cornell) and 118–156 ms (engine) with the gather
/// adding them and 209–223 ms and 65–70 ms with the scatter; 4 was not tuned further.
const SUMS_SCATTER_CHANGES_PER_SEGMENT: u64 = 4;

/// Segments per change-list entry below which an update marks the segments its changes reach
/// from the changes' side (`scatter_touch`) rather than by marching every segment through the
/// dirty cells. On lavapipe a change costs the marking ~2.3 µs and the march ~80 ns per
/// segment (engine CT, 96² × 8 segments, 2026-12-02); the marks are tighter, so they pay a
/// little beyond the break-even.
const TOUCH_SEGMENTS_PER_CHANGE: u64 = 16;

/// Largest hash grid (cells) a session may build.
pub const MAX_GRID_CELLS: u64 = 1 << 22;
/// Cells per workgroup of the grid's prefix sum (SCAN_BLOCK in photon/grid.wgsl).
const SCAN_BLOCK: u64 = 4096;
// Every block of the largest grid is one workgroup of one dispatch.
const _: () = assert!(MAX_GRID_CELLS.div_ceil(SCAN_BLOCK) <= 65535);

impl PhotonBudget {
    pub fn new(
        params: &PhotonParams,
        volume: &GpuVolume,
        width: u32,
        height: u32,
        max_passes: u32,
    ) -> Result<Self, EngineError> {
        let invalid = |m: String| Err(EngineError::InvalidScene(m));
        if params.photons_per_pass == 0
            || params.bounces == 0
            || params.record_slots == 0
            || params.segments == 0
        {
            return invalid(
                "photon: photons_per_pass, bounces, record_slots and segments must be positive"
                    .into(),
            );
        }
        let pool_least = slots::INLINE_SLOTS + gpu::CHUNK_SLOTS;
        if params.bounces > params.record_slots && params.record_slots < pool_least {
            return invalid(format!(
                "photon: record_slots must be at least {pool_least} where bounces ({}) exceeds it",
                params.bounces
            ));
        }
        if !(params.gather_step_voxels.is_finite() && params.gather_step_voxels > 0.0) {
            return invalid("photon: gather_step_voxels must be positive".into());
        }
        if !(params.radius_alpha > 0.0 && params.radius_alpha <= 1.0) {
            return invalid("photon: radius_alpha must be in (0, 1]".into());
        }
        if params.roulette_survival.is_nan() || params.roulette_survival <= 0.0 {
            return invalid(
                "photon: roulette_survival must be positive (>= 1: no roulette)".into(),
            );
        }
        let voxel = 2.0 * default_step(volume);
        let radius = if params.radius > 0.0 && params.radius.is_finite() {
            params.radius
        } else {
            (1.5 * voxel).max(volume.extent.iter().fold(0.0f32, |a, &e| a.max(e)) / 150.0)
        };
        let grid_dims = volume.extent.map(|e| ((e / radius).ceil() as u32).max(1));
        let cells = grid_dims.iter().map(|&d| d as u64).product::<u64>();
        if cells > MAX_GRID_CELLS {
            return invalid(format!(
                "photon: radius {radius} makes a {}×{}×{} grid, more than {MAX_GRID_CELLS} cells",
                grid_dims[0], grid_dims[1], grid_dims[2]
            ));
        }
        let passes = max_passes.max(1) as u64;
        let paths = params.photons_per_pass as u64 * passes;
        let layout =
            RecordLayout::new(params.photons_per_pass, params.bounces, params.record_slots);
        let records = paths * layout.path_slots as u64;
        let chunk_bytes = passes * (layout.chunks_per_pass as u64 + 1) * 4;
        let pixels = width as u64 * height as u64;
        let record_bytes = records * size_of::<PhotonRecord>() as u64;
        let record_resume_bytes = records * size_of::<RecordResume>() as u64;
        let path_bytes = paths * size_of::<PhotonPath>() as u64;
        let path_query_rows = (paths * gpu::PATH_QUERY_WORDS as u64)
            .div_ceil(gpu::PATH_QUERY_ROW as u64)
            .max(1);
        // Two grids (the records', an update's changes'), each cell starts then cursors.
        // After them, the scan's sum per block of cells (photon/grid.wgsl, block_sum_word).
        let grid_cell_bytes = (2 * (2 * cells + 1) + cells.div_ceil(SCAN_BLOCK)) * 4;
        let change_entries = match params.change_list {
            0 => records,
            n => (n as u64).min(records),
        };
        // The records' slots, then the changes'.
        let grid_sorted_bytes = (records + change_entries) * 4;
        let change_bytes = change_entries * size_of::<PhotonChange>() as u64;
        let segment_bytes = pixels * params.segments as u64 * size_of::<Segment>() as u64;
        // Two halves: a round's input and the segments left for the next.
        let gather_list_bytes = 2 * pixels * params.segments as u64 * 4;
        let gather_state_bytes = pixels * params.segments as u64 * size_of::<GatherState>() as u64;
        let retrace_list_bytes = 2 * paths * 4;
        let segment_count = pixels * params.segments as u64;
        // A segment spans at most the box diagonal / Vn; its first lattice index is one early,
        // and rounding may add one more at each end.
        let step = voxel * params.gather_step_voxels;
        let diagonal = volume.extent.iter().map(|e| e * e).sum::<f32>().sqrt();
        let scatter_samples = (diagonal / (params.segments as f32 * step)).ceil() as u64 + 4;
        let scatter_words = params.scatter_bytes / 4;
        let scatter_capacity = scatter_words
            .saturating_sub(segment_count)
            .checked_div(SLOT_WORDS as u64 + scatter_samples)
            .unwrap_or(0)
            .min(segment_count)
            .min(u32::MAX as u64 / 2);
        let scatter_bytes = if scatter_capacity == 0 {
            16
        } else {
            (segment_count + scatter_capacity * (SLOT_WORDS as u64 + scatter_samples)) * 4
        };
        // A view ray's lattice samples: the box diagonal in steps, one early, and rounding at
        // each end. Indexed by u32 words, behind the delta scatter's marks.
        let samples_per_ray = (diagonal / step).ceil() as u64 + 3;
        let cache_bytes = pixels * samples_per_ray * SAMPLE_WORDS as u64 * 4;
        let sample_cache_samples = if params.sample_cache_bytes > 0
            && cache_bytes <= params.sample_cache_bytes
            && cache_bytes / 4 < u32::MAX as u64
        {
            samples_per_ray
        } else {
            0
        };
        let sample_cache_bytes = if sample_cache_samples > 0 {
            cache_bytes
        } else {
            16
        };
        let accum_bytes = pixels * 16;
        // The dirty-cell bits are of half-size cells: 8 per hash cell; then a bit per pixel
        // (`pixel_mark` in photon/common.wgsl).
        let counter_bytes =
            (COUNTER_WORDS as u64 + (8 * cells).div_ceil(32) + pixels.div_ceil(32)) * 4;
        let small = TfTexture::BYTES
            + (size_of::<SceneUniforms>()
                + size_of::<PhotonUniforms>()
                + 8 * size_of::<PhotonEmitter>()) as u64;
        let total = counter_bytes
            + chunk_bytes
            + record_bytes
            + record_resume_bytes
            + path_bytes
            + grid_cell_bytes
            + grid_sorted_bytes
            + segment_bytes
            + gather_list_bytes
            + gather_state_bytes
            + retrace_list_bytes
            + change_bytes
            + scatter_bytes
            + sample_cache_bytes
            + accum_bytes
            + path_query_rows * gpu::PATH_QUERY_ROW as u64 * 4
            + small;
        Ok(Self {
            paths,
            records,
            layout,
            cells,
            grid_dims,
            radius,
            record_bytes,
            record_resume_bytes,
            path_bytes,
            grid_cell_bytes,
            grid_sorted_bytes,
            segment_bytes,
            gather_list_bytes,
            gather_state_bytes,
            retrace_list_bytes,
            change_entries,
            change_bytes,
            scatter_capacity,
            scatter_samples,
            scatter_bytes,
            sample_cache_samples,
            sample_cache_bytes,
            accum_bytes,
            counter_bytes,
            chunk_bytes,
            path_query_rows: path_query_rows.min(u32::MAX as u64) as u32,
            total,
        })
    }

    /// Refuses sizes this GPU or the session budget cannot hold (before any allocation).
    pub fn check(&self, engine: &Engine) -> Result<(), EngineError> {
        let limits = &engine.gpu.limits;
        let binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let largest = [
            self.record_bytes,
            self.record_resume_bytes,
            self.path_bytes,
            self.grid_cell_bytes,
            self.grid_sorted_bytes,
            self.segment_bytes,
            self.gather_list_bytes,
            self.gather_state_bytes,
            self.retrace_list_bytes,
            self.change_bytes,
            self.scatter_bytes,
            self.sample_cache_bytes,
            self.accum_bytes,
            self.counter_bytes,
            self.chunk_bytes,
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        if largest > binding {
            return Err(EngineError::OutOfMemory {
                needed: largest,
                available: binding,
            });
        }
        if self.path_query_rows > limits.max_texture_dimension_2d {
            return Err(EngineError::OutOfMemory {
                needed: self.path_query_rows as u64 * gpu::PATH_QUERY_ROW as u64 * 4,
                available: limits.max_texture_dimension_2d as u64 * gpu::PATH_QUERY_ROW as u64 * 4,
            });
        }
        if self.records > u32::MAX as u64 / 2 {
            return Err(EngineError::OutOfMemory {
                needed: self.record_bytes,
                available: binding,
            });
        }
        if self.total > engine.session_budget {
            return Err(EngineError::OutOfMemory {
                needed: self.total,
                available: engine.session_budget,
            });
        }
        Ok(())
    }
}

/// One session's buffers, named as `PhotonBindings` names them.
struct PhotonBuffers {
    scene: wgpu::Buffer,
    tf_lut: TfTexture,
    uniforms: wgpu::Buffer,
    emitters: wgpu::Buffer,
    records: wgpu::Buffer,
    paths: wgpu::Buffer,
    grid_cells: wgpu::Buffer,
    grid_sorted: wgpu::Buffer,
    segments: wgpu::Buffer,
    gather_list: wgpu::Buffer,
    gather_state: wgpu::Buffer,
    retrace_list: wgpu::Buffer,
    changes: wgpu::Buffer,
    /// The delta scatter's state; a census borrows it (a full pass does not use it).
    scatter: wgpu::Buffer,
    accum: wgpu::Buffer,
    counters: wgpu::Buffer,
    /// The record chunks' lists (`slots`).
    chunks: wgpu::Buffer,
    /// The per-sample photon sums (`PhotonParams::sample_cache_bytes`).
    sample_sums: wgpu::Buffer,
    /// The paths' query words (`path_queries` in photon/common.wgsl).
    path_queries: wgpu::TextureView,
    /// The records' resumes (`record_resumes`).
    record_resumes: wgpu::Buffer,
}

impl PhotonBuffers {
    fn new(engine: &Engine, budget: &PhotonBudget) -> Self {
        let buffer = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            engine.gpu.buffer(label, size, usage)
        };
        use wgpu::BufferUsages as U;
        let [records, grid_sorted, changes, chunks, record_resumes] =
            Self::slot_buffers(engine, budget);
        Self {
            scene: buffer(
                "photon scene",
                size_of::<SceneUniforms>() as u64,
                U::UNIFORM,
            ),
            tf_lut: engine.gpu.tf_texture("photon tf lut"),
            uniforms: buffer(
                "photon uniforms",
                size_of::<PhotonUniforms>() as u64,
                U::UNIFORM,
            ),
            emitters: buffer(
                "photon emitters",
                (8 * size_of::<PhotonEmitter>()) as u64,
                U::STORAGE,
            ),
            records,
            paths: buffer("photon paths", budget.path_bytes, U::STORAGE | U::COPY_SRC),
            grid_cells: buffer(
                "photon grid cells",
                budget.grid_cell_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            grid_sorted,
            segments: buffer(
                "photon segments",
                budget.segment_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            gather_list: buffer("photon gather list", budget.gather_list_bytes, U::STORAGE),
            gather_state: buffer("photon gather state", budget.gather_state_bytes, U::STORAGE),
            retrace_list: buffer("photon retrace list", budget.retrace_list_bytes, U::STORAGE),
            changes,
            scatter: buffer(
                "photon scatter",
                budget.scatter_bytes,
                U::STORAGE | U::COPY_SRC | U::COPY_DST,
            ),
            accum: buffer("photon accum", budget.accum_bytes, U::STORAGE | U::COPY_SRC),
            counters: buffer(
                "photon counters",
                budget.counter_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            chunks,
            sample_sums: buffer("photon sample sums", budget.sample_cache_bytes, U::STORAGE),
            path_queries: engine
                .gpu
                .device
                .create_texture(&wgpu::TextureDescriptor {
                    label: Some("photon path queries"),
                    size: wgpu::Extent3d {
                        width: gpu::PATH_QUERY_ROW,
                        height: budget.path_query_rows,
                        depth_or_array_layers: 1,
                    },
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: wgpu::TextureFormat::R32Uint,
                    usage: wgpu::TextureUsages::STORAGE_BINDING,
                    view_formats: &[],
                })
                .create_view(&wgpu::TextureViewDescriptor {
                    label: Some("photon path queries"),
                    ..Default::default()
                }),
            record_resumes,
        }
    }

    /// The buffers whose size follows the record slots: records, the grid's sorted slots,
    /// the change list, the chunk lists and the records' resumes.
    fn slot_buffers(engine: &Engine, budget: &PhotonBudget) -> [wgpu::Buffer; 5] {
        use wgpu::BufferUsages as U;
        let gpu = &engine.gpu;
        [
            gpu.buffer(
                "photon records",
                budget.record_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            gpu.buffer(
                "photon grid sorted",
                budget.grid_sorted_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            gpu.buffer("photon changes", budget.change_bytes, U::STORAGE),
            gpu.buffer(
                "photon chunks",
                budget.chunk_bytes,
                U::STORAGE | U::COPY_SRC,
            ),
            gpu.buffer(
                "photon record resumes",
                budget.record_resume_bytes,
                U::STORAGE,
            ),
        ]
    }

    /// Replaces the buffers `slot_buffers` names with ones of `budget`'s sizes.
    fn resize_slots(&mut self, engine: &Engine, budget: &PhotonBudget) {
        [
            self.records,
            self.grid_sorted,
            self.changes,
            self.chunks,
            self.record_resumes,
        ] = Self::slot_buffers(engine, budget);
    }

    fn bind_group(&self, engine: &Engine, volume: &GpuVolume) -> wgpu::BindGroup {
        engine.photon.bind_group(
            &engine.gpu,
            &PhotonBindings {
                scene: &self.scene,
                volume: &volume.view,
                tf_lut: &self.tf_lut.view,
                uniforms: &self.uniforms,
                emitters: &self.emitters,
                records: &self.records,
                paths: &self.paths,
                grid_cells: &self.grid_cells,
                grid_sorted: &self.grid_sorted,
                segments: &self.segments,
                gather_list: &self.gather_list,
                gather_state: &self.gather_state,
                retrace_list: &self.retrace_list,
                changes: &self.changes,
                scatter: &self.scatter,
                accum: &self.accum,
                counters: &self.counters,
                chunks: &self.chunks,
                sample_sums: &self.sample_sums,
                path_queries: &self.path_queries,
                record_resumes: &self.record_resumes,
            },
        )
    }
}

pub struct Photon {
    params: PhotonParams,
    budget: PhotonBudget,
    volume: Arc<GpuVolume>,
    buffers: PhotonBuffers,
    bind_group: wgpu::BindGroup,
    emitter_count: u32,
    width: u32,
    height: u32,
    /// Photon passes in the map.
    passes: u32,
    /// Passes the buffers hold.
    capacity: u32,
    photons_traced: u64,
    last_update: Option<UpdateReport>,
    /// Gather rounds the last grid and gather took.
    gather_rounds: u32,
    /// Segments the last update's delta scatter updated.
    scattered: u32,
    /// The generation of the per-sample photon sums: an entry formed in another is not valid
    /// (each full gather starts one, and so does an update whose changes could not all be
    /// added to the sums).
    cache_generation: Cell<u32>,
    /// Whether the update being gathered added its changes to the valid sums already
    /// (`scatter_sums`); if not, its gather adds them at the dirty samples.
    sums_applied: Cell<bool>,
    /// Whether every sample a segment gathered holds a valid sum (since the last full gather
    /// no update started a new generation): a segment whose opacity did not change then
    /// recomposites from sums alone, and needs no records' grid.
    sums_complete: Cell<bool>,
    /// Set by `sum_changes_in_gather`: updates never scatter their changes into the sums.
    sums_by_gather: bool,
    /// Where the update under way marked (and listed) the segments its changes reach (`touch`)
    /// and the marks stand for the dirty cells, how many segments they listed.
    marks: Cell<Option<u32>>,
    /// Whether the records' grid is older than the records (an update that gathered no
    /// segment afresh did not need it).
    records_grid_behind: Cell<bool>,
    /// Bumped by every submission and every write to the counters: a read of the counters
    /// (`counters_read`) stays current while this stands.
    epoch: Cell<u64>,
    /// The counter words as last read, and the epoch they were read in.
    counters_read: RefCell<Option<(u64, Vec<u32>)>>,
    last_uniforms: Cell<PhotonUniforms>,
    /// Whether the full pass being dispatched counts its work (`census`).
    census: Cell<bool>,
    /// The gather under way, if any; `step` carries it on in parts.
    gathering: Option<GatherInProgress>,
    /// Passes the composite in the output holds for the current camera (`iteration`): the
    /// passes in the map once their gather is done, 0 while a camera edit's gather runs.
    shown: u32,
    /// Gather list slots per second of the last part (sizes the next part).
    gather_rate: Option<f64>,
    /// Paths of the last pass traced so far, while its trace runs in parts (`step`).
    tracing: Option<u32>,
    /// Paths per second of the last trace part (sizes the next part).
    trace_rate: Option<f64>,
    /// Paths per trace part set by `fix_trace_part` instead of the measured rate.
    fixed_trace_part: Option<u32>,
    /// Slots per part set by `fix_gather_part` instead of the measured rate.
    fixed_part: Option<u32>,
    /// Whether a pass has run out of record chunks (logged once).
    warned_chunks: bool,
}

impl Photon {
    pub fn new(
        engine: &Engine,
        volume: Arc<GpuVolume>,
        scene: &Scene,
        params: PhotonParams,
    ) -> Result<Self, EngineError> {
        let (width, height) = (scene.viewport.width, scene.viewport.height);
        let capacity = params.max_passes.max(1).min(scene.target_iterations.max(1));
        let mut params = params;
        let mut budget = PhotonBudget::new(&params, &volume, width, height, capacity)?;
        if params.sample_cache_bytes > 0 && budget.check(engine).is_err() {
            // The sample sums, like the delta scatter, only save time.
            params.sample_cache_bytes = 0;
            budget = PhotonBudget::new(&params, &volume, width, height, capacity)?;
        }
        if params.scatter_bytes > 0 && budget.check(engine).is_err() {
            // The delta scatter only saves time: a session that fits without it goes without.
            params.scatter_bytes = 0;
            budget = PhotonBudget::new(&params, &volume, width, height, capacity)?;
        }
        budget.check(engine)?;
        let buffers = PhotonBuffers::new(engine, &budget);
        let bind_group = buffers.bind_group(engine, &volume);
        let mut technique = Self {
            params,
            budget,
            volume,
            buffers,
            bind_group,
            emitter_count: 0,
            width,
            height,
            passes: 0,
            capacity,
            photons_traced: 0,
            last_update: None,
            gather_rounds: 0,
            scattered: 0,
            cache_generation: Cell::new(0),
            sums_applied: Cell::new(false),
            sums_complete: Cell::new(false),
            sums_by_gather: false,
            marks: Cell::new(None),
            records_grid_behind: Cell::new(false),
            epoch: Cell::new(0),
            counters_read: RefCell::new(None),
            last_uniforms: Cell::new(bytemuck::Zeroable::zeroed()),
            census: Cell::new(false),
            gathering: None,
            shown: 0,
            gather_rate: None,
            tracing: None,
            trace_rate: None,
            fixed_trace_part: None,
            fixed_part: None,
            warned_chunks: false,
        };
        technique.write_tf(engine, scene);
        technique.write_emitters(engine, scene);
        // The picture before the first pass: the environment through the volume is not known
        // yet, so show black.
        engine.gpu.check()?;
        Ok(technique)
    }

    pub fn params(&self) -> &PhotonParams {
        &self.params
    }

    pub fn budget(&self) -> &PhotonBudget {
        &self.budget
    }

    /// Photon passes in the map.
    pub fn passes(&self) -> u32 {
        self.passes
    }

    /// Paths of the pass being traced traced so far (None: no trace under way).
    pub fn tracing(&self) -> Option<u32> {
        self.tracing
    }

    /// Gather rounds (dispatches over the unfinished segments) the last gather took.
    pub fn gather_rounds(&self) -> u32 {
        self.gather_rounds
    }

    pub fn last_update(&self) -> Option<UpdateReport> {
        self.last_update
    }

    fn target(&self, scene: &Scene) -> u32 {
        self.capacity.min(scene.target_iterations.max(1))
    }

    fn write_tf(&self, engine: &Engine, scene: &Scene) {
        let lut = bake(&scene.tf);
        self.buffers.tf_lut.write(&engine.gpu.queue, &lut);
    }

    /// A path's flights at most (`bounces`), or with Russian roulette about the expected
    /// number: `roulette_from` sure ones, then 1 / (1 − survival) on average.
    fn expected_flights(&self) -> f64 {
        let cap = self.params.bounces as f64;
        let q = self.params.roulette_survival as f64;
        if q >= 1.0 || q.is_nan() {
            return cap;
        }
        let sure = self.params.roulette_from.max(1) as f64;
        cap.min(sure + 1.0 / (1.0 - q.max(0.0)))
    }

    fn write_emitters(&mut self, engine: &Engine, scene: &Scene) {
        let emitters = emitters(&scene.lights, &self.volume, self.params.photons_per_pass);
        self.emitter_count = emitters.len() as u32;
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.emitters, 0, bytemuck::cast_slice(&emitters));
    }

    fn write_scene(&self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        // A photon path's delta tracking against the fixed majorant takes about density ×
        // length steps in one shader invocation; past the device's loop limit the path would
        // be cut short silently, so refuse instead. The limit counts a batch of lanes together,
        // so with Russian roulette a path's expected number of flights is what counts.
        let diagonal = self.volume.extent.iter().map(|e| e * e).sum::<f32>().sqrt() as f64;
        let steps = scene.params.density_scale as f64 * diagonal * (self.expected_flights() + 1.0);
        if let Some(budget) = engine.gpu.lane_loop_budget()
            && 2.0 * steps > budget as f64
        {
            return Err(EngineError::InvalidScene(format!(
                "photon: density scale {} needs ~{steps:.0} tracking steps per photon path, more \
                 than this device ({}) runs in one shader invocation; lower the density scale \
                 or use another technique",
                scene.params.density_scale,
                engine.gpu.adapter_name()
            )));
        }
        let uniforms = SceneUniforms::new(scene, &self.volume, self.passes)
            .map_err(EngineError::InvalidScene)?;
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.scene, 0, bytemuck::bytes_of(&uniforms));
        Ok(())
    }

    fn write_uniforms(&self, engine: &Engine, scene: &Scene, query: Query, dispatch: Dispatch) {
        let Dispatch {
            mode,
            trace_paths,
            round,
            grid_pass,
        } = dispatch;
        let r = self.budget.radius;
        let path_count = self.passes * self.params.photons_per_pass;
        let uniforms = PhotonUniforms {
            grid_dims: self.budget.grid_dims,
            cell_count: self.budget.cells as u32,
            radius: r,
            kernel_norm: 15.0
                / (8.0 * std::f32::consts::PI * r * r * r)
                / self.passes.max(1) as f32,
            majorant: scene.params.density_scale,
            gather_step: 2.0 * default_step(&self.volume) * self.params.gather_step_voxels,
            photons_per_pass: self.params.photons_per_pass,
            path_count,
            record_count: path_count * self.budget.layout.path_slots,
            bounces: self.params.bounces,
            path_offset: trace_paths.start,
            dispatch_paths: trace_paths.len() as u32,
            mode,
            segments: self.params.segments,
            rejection_query_lo: query.rejection as u32,
            rejection_query_hi: (query.rejection >> 32) as u32,
            emitter_count: self.emitter_count,
            spatial: self.params.invalidation.uniform(),
            round_input: round.input,
            round_budget: round.budget,
            round_stride: round.stride.max(1),
            opacity_query_lo: query.opacity as u32,
            opacity_query_hi: (query.opacity >> 32) as u32,
            grid_pass,
            change_capacity: self.budget.change_entries as u32,
            record_capacity: self.budget.records as u32,
            collision_query_lo: query.collision as u32,
            collision_query_hi: (query.collision >> 32) as u32,
            scatter_capacity: self.budget.scatter_capacity as u32,
            scatter_samples: self.budget.scatter_samples as u32,
            census: self.census.get() as u32,
            round_first: round.first,
            roulette_survival: self.params.roulette_survival,
            roulette_from: self.params.roulette_from,
            path_slots: self.budget.layout.path_slots,
            inline_slots: self.budget.layout.inline_slots,
            chunks_per_pass: self.budget.layout.chunks_per_pass,
            chunk_counts_at: self.capacity * self.budget.layout.chunks_per_pass,
            sample_cache_samples: self.budget.sample_cache_samples as u32,
            cache_generation: self.cache_generation.get(),
            sums_applied: self.sums_applied.get() as u32,
            marks_stand: self.marks.get().is_some() as u32,
            pass_kernels: pass_kernels(r, self.params.radius_alpha),
        };
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.uniforms, 0, bytemuck::bytes_of(&uniforms));
        self.last_uniforms.set(uniforms);
    }

    /// Builds the records' grid if an update left it behind (it builds it only where it
    /// gathers a segment afresh), with the last uniforms but its grid.
    fn catch_up_records_grid(&self, engine: &Engine) {
        if !self.records_grid_behind.replace(false) {
            return;
        }
        let uniforms = PhotonUniforms {
            grid_pass: GRID_RECORDS,
            ..self.last_uniforms.get()
        };
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.uniforms, 0, bytemuck::bytes_of(&uniforms));
        let mut encoder = Self::encoder(engine, "photon grid");
        self.build_grid(&mut encoder, &engine.photon, self.record_count());
        self.submit(engine, encoder);
    }

    fn encoder(engine: &Engine, label: &str) -> wgpu::CommandEncoder {
        engine
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) })
    }

    /// Submits `encoder`'s commands.
    fn submit(&self, engine: &Engine, encoder: wgpu::CommandEncoder) {
        self.epoch.set(self.epoch.get() + 1);
        engine.gpu.queue.submit([encoder.finish()]);
    }

    /// One dispatch of `pipeline` over `count` invocations, in its own submission.
    fn submit_linear(
        &self,
        engine: &Engine,
        label: &str,
        pipeline: &wgpu::ComputePipeline,
        count: u32,
    ) {
        let mut encoder = Self::encoder(engine, label);
        dispatch_linear(&mut encoder, label, pipeline, &self.bind_group, count);
        self.submit(engine, encoder);
    }

    /// Sets one counter word before the next submission.
    fn write_counter(&self, engine: &Engine, word: usize, value: u32) {
        self.write_counters(engine, word, bytemuck::bytes_of(&value));
    }

    /// Writes `bytes` into the counters from `word` on, before the next submission; a kept
    /// read of them (`counters_read`) is then stale.
    fn write_counters(&self, engine: &Engine, word: usize, bytes: &[u8]) {
        self.epoch.set(self.epoch.get() + 1);
        let offset = word as u64 * 4;
        engine
            .gpu
            .queue
            .write_buffer(&self.buffers.counters, offset, bytes);
    }

    /// Record slots in the map (`path_slots` per path, filled or not).
    fn record_count(&self) -> u32 {
        self.passes * self.params.photons_per_pass * self.budget.layout.path_slots
    }

    /// Empties the chunk pools of the passes paths `paths` (whole passes) belong to, before
    /// a full trace of them (`trace_clear`), in its own submission.
    fn clear_pools(&self, engine: &Engine, scene: &Scene, paths: std::ops::Range<u32>) {
        let pool = self.budget.layout.pool_slots();
        if pool == 0 || paths.is_empty() {
            return;
        }
        let slots = paths.len() as u32 / self.params.photons_per_pass * pool;
        let dispatch = Dispatch {
            mode: MODE_FULL,
            trace_paths: paths,
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, Query::default(), dispatch);
        let clear = &engine.photon.trace_clear;
        self.submit_linear(engine, "photon trace clear", clear, slots);
    }

    /// Traces paths [offset, offset + count) (MODE_FULL; their passes' pools emptied first,
    /// `clear_pools`) or retraces the first `count` paths of the retrace list (MODE_UPDATE),
    /// in its own submission (the uniforms differ from the gather's).
    fn trace(
        &self,
        engine: &Engine,
        scene: &Scene,
        mode: u32,
        offset: u32,
        count: u32,
        query: Query,
    ) {
        if count == 0 {
            return;
        }
        let dispatch = Dispatch {
            mode,
            trace_paths: offset..offset + count,
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, query, dispatch);
        let (label, pipeline) = if mode == MODE_UPDATE {
            ("photon trace update", &engine.photon.trace_update)
        } else {
            ("photon trace", &engine.photon.trace)
        };
        self.submit_linear(engine, label, pipeline, count);
    }

    /// An update's retrace of the `listed` paths: the walk finishes those that only take new
    /// colours (photon/trace.wgsl, TRACE_WALK), then the trace takes the rest (one blocking
    /// read between, for their number). Where the new TF is transparent in every bin of the
    /// collision query, every listed path's first changed collision is now rejected (or its
    /// flight met a bin whose opacity rose): the walk would finish none, and is skipped.
    fn retrace(
        &self,
        engine: &Engine,
        scene: &Scene,
        listed: u32,
        query: Query,
    ) -> Result<(), EngineError> {
        if listed == 0 {
            return Ok(());
        }
        if query.collision & opaque_bins(&scene.tf) == 0 {
            self.trace(engine, scene, MODE_UPDATE, 0, listed, query);
            return Ok(());
        }
        let dispatch = Dispatch {
            mode: MODE_UPDATE,
            trace_paths: 0..listed,
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, query, dispatch);
        let walk = &engine.photon.trace_walk;
        self.submit_linear(engine, "photon trace walk", walk, listed);
        let deferred = self.counter(engine, COUNTER_DEFERRED)?;
        // In the list's second half (defer_trace), from the map's path count.
        let paths = self.passes * self.params.photons_per_pass;
        self.trace(engine, scene, MODE_UPDATE, paths, deferred, query);
        Ok(())
    }

    /// Whether a pass's paths needed more chunks than its pool holds since its last full trace
    /// (blocks on the GPU): some were cut short, which a full trace with room would not do.
    pub fn chunks_exhausted(&self, engine: &Engine) -> Result<bool, EngineError> {
        let layout = &self.budget.layout;
        if layout.chunks_per_pass == 0 || self.passes == 0 {
            return Ok(false);
        }
        let at = self.capacity as u64 * layout.chunks_per_pass as u64 * 4;
        let bytes =
            engine
                .gpu
                .read_buffer_range(&self.buffers.chunks, at, self.passes as u64 * 4)?;
        Ok(bytes
            .chunks_exact(4)
            .any(|w| bytemuck::pod_read_unaligned::<u32>(w) > layout.chunks_per_pass))
    }

    /// Carries a gather under way to its end (composite included), at once. Does not wait.
    fn finish_gather(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        while !self.gather_part(engine, scene, u32::MAX)? {}
        Ok(())
    }

    /// Starts a gather (a gather under way is dropped): `gather_mark` lists the segments to
    /// gather (all in MODE_FULL, stale ones in MODE_UPDATE, so that the gather's SIMD lanes
    /// all work), then, as `GridPlan` says, an update's delta scatter runs and the grids are
    /// rebuilt (over every record, and in MODE_UPDATE over the changes). `gather_part` then
    /// gathers the listed segments in rounds within the device's loop limit, and composites.
    fn begin_gather(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        mode: u32,
        query: Query,
    ) -> Result<(), EngineError> {
        self.gathering = None;
        let segments = self.width * self.height * self.params.segments;
        if mode == MODE_FULL {
            self.new_sum_generation();
            self.sums_complete.set(true);
        }
        // The uniforms of the marks and of `remarch_from_sums`.
        let mode_only = Dispatch {
            mode,
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, query, mode_only.clone());
        // Where an update's marks stand for the dirty cells (`touch`: no change was too wide
        // for them and the change list holds every change), the segments they listed.
        let marked = if mode == MODE_UPDATE {
            self.marks.get()
        } else {
            None
        };
        let no_opacity = query.opacity == 0;
        // gather_mark lists afresh.
        self.write_counter(engine, COUNTER_LIST, 0);
        let pass = &engine.photon;
        match marked {
            // No opacity changed: the marked segments are all an update can change, and the
            // marks added the changes to the sums: most need only recompositing.
            Some(listed) if no_opacity && self.budget.sample_cache_samples > 0 => {
                let recomposite = &pass.recomposite_touched;
                let label = "photon recomposite touched";
                self.submit_linear(engine, label, recomposite, listed);
            }
            Some(listed) if no_opacity => {
                let mark = &pass.gather_mark_touched;
                self.submit_linear(engine, "photon gather mark touched", mark, listed);
            }
            // An opacity edit: the segments whose opacity changed, then those the marks listed;
            // no other needs anything.
            Some(listed) => {
                let stale = &pass.gather_mark_stale;
                let pixels = self.width * self.height;
                self.submit_linear(engine, "photon gather mark stale", stale, pixels);
                let mark = &pass.gather_mark_touched;
                self.submit_linear(engine, "photon gather mark touched", mark, listed);
            }
            None => self.submit_linear(engine, "photon gather mark", &pass.gather_mark, segments),
        }
        let records = self.record_count();
        let change_entries = self.budget.change_entries as u32;
        // With per-sample sums, the segments whose sums took the changes from the scatter.
        let (plan, summed) = if mode == MODE_FULL {
            (GridPlan::full(records), None)
        } else if self.budget.sample_cache_samples > 0 {
            let words = self.counter_words(engine)?;
            let applied = self.add_changes_to_sums(engine, scene, query, &words)?;
            let marked = Marked::from_words(&words);
            let scattered = if applied { marked.delta } else { 0 };
            let complete = self.sums_complete.get();
            let rose = query.rejection != 0;
            let plan = GridPlan::summed(marked, applied, complete, rose, records, change_entries);
            (plan, Some(scattered))
        } else {
            let marked = Marked::from_words(&self.counter_words(engine)?);
            let capacity = self.budget.scatter_capacity as u32;
            let plan = GridPlan::update(marked, capacity, records, change_entries);
            (plan, None)
        };
        let gave_back = match plan.scatter {
            Some(scatter) => self.scatter(engine, scene, query, scatter)?,
            None => false,
        };
        self.scattered = summed.unwrap_or_else(|| plan.scattered(gave_back));
        self.records_grid_behind.set(!plan.records_grid);
        for build in plan.grids(gave_back) {
            let dispatch = Dispatch {
                mode,
                grid_pass: build.grid,
                ..Dispatch::default()
            };
            self.write_uniforms(engine, scene, query, dispatch);
            let mut encoder = Self::encoder(engine, "photon grid");
            self.build_grid(&mut encoder, &engine.photon, build.items);
            self.submit(engine, encoder);
        }
        let mut listed = self.counter(engine, COUNTER_LIST)?;
        let mut input = 0;
        let mut composited = false;
        // Where every valid sum holds the changes, most listed segments need no photon: they
        // march (or recomposite) from the sums first, and the gather takes the rest.
        let summed = self.budget.sample_cache_samples > 0
            && self.sums_applied.get()
            && self.sums_complete.get();
        if mode == MODE_UPDATE && summed && listed > 0 {
            // After the grids' uniforms, and with this update's `sums_applied`.
            self.write_uniforms(engine, scene, query, mode_only);
            self.write_counter(engine, COUNTER_LIST + 1, 0);
            let pass = &engine.photon;
            let mut encoder = Self::encoder(engine, "photon remarch from sums");
            let bg = &self.bind_group;
            let remarch = &pass.remarch_from_sums;
            dispatch_linear(
                &mut encoder,
                "photon remarch from sums",
                remarch,
                bg,
                listed,
            );
            // The marked pixels' composite, in the same submission: the sums usually leave the
            // gather nothing, and the read below then ends the update. Where they do not, the
            // gather composites those pixels again after it (`composited` stays false).
            if marked.is_some() {
                let pixels = self.width * self.height;
                let composite = &pass.composite_changed;
                dispatch_linear(
                    &mut encoder,
                    "photon composite changed",
                    composite,
                    bg,
                    pixels,
                );
            }
            self.submit(engine, encoder);
            listed = self.counter(engine, COUNTER_LIST + 1)?;
            input = 1;
            composited = marked.is_some() && listed == 0;
        }
        self.gathering = Some(GatherInProgress {
            pixels_marked: marked.is_some(),
            composited,
            ..GatherInProgress::new(mode, query, listed, input)
        });
        Ok(())
    }

    /// Gathers at most `max_slots` more segments of the gather under way (one submission,
    /// `GatherInProgress::part`; a round's last part reads the next round's list, a blocking
    /// read, when the device's loop limit made rounds), then, once no segment is left,
    /// composites. Returns whether the gather is done (true also when none was under way).
    /// Does not wait otherwise.
    fn gather_part(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        max_slots: u32,
    ) -> Result<bool, EngineError> {
        let Some(mut gathering) = self.gathering.take() else {
            return Ok(true);
        };
        if gathering.listed > 0 {
            let lanes = engine.gpu.info.subgroup_max_size;
            let part = gathering.part(self.round_budget(engine), lanes, max_slots);
            let dispatch = Dispatch {
                mode: gathering.mode,
                round: part.round,
                ..Dispatch::default()
            };
            self.write_uniforms(engine, scene, gathering.query, dispatch);
            if part.clear_output {
                self.write_counter(engine, COUNTER_LIST + part.output as usize, 0);
            }
            let invocations = part.slots * part.round.stride;
            let (label, gather) = if self.budget.sample_cache_samples > 0 {
                ("photon gather sums", &engine.photon.gather_sums)
            } else {
                ("photon gather", &engine.photon.gather)
            };
            self.submit_linear(engine, label, gather, invocations);
            let left = match part.next_list {
                Some(word) => self.counter(engine, word)?,
                None => 0,
            };
            gathering.advance(&part, left);
            if gathering.listed > 0 {
                self.gathering = Some(gathering);
                return Ok(false);
            }
        }
        self.gather_rounds = gathering.rounds;
        let pixels = self.width * self.height;
        // An update whose marks passes marked its pixels recomposites only those.
        let (label, composite) = if gathering.pixels_marked {
            ("photon composite changed", &engine.photon.composite_changed)
        } else {
            ("photon composite", &engine.photon.composite)
        };
        if !gathering.composited {
            self.submit_linear(engine, label, composite, pixels);
        }
        self.shown = self.passes;
        Ok(true)
    }

    /// The delta scatter (photon/scatter.wgsl) as `plan` says, over the slots gather_mark gave
    /// it and the update's change list: the slots' sample weights, every change's terms, then
    /// either the sums added to their segments or, where a change reached more pixels than one
    /// invocation may visit, every slot's segment listed for the delta gather instead (one
    /// blocking read). Returns whether the segments were left to the delta gather.
    fn scatter(
        &self,
        engine: &Engine,
        scene: &Scene,
        query: Query,
        plan: ScatterPlan,
    ) -> Result<bool, EngineError> {
        let pass = &engine.photon;
        let (slots, changes) = match plan {
            ScatterPlan::Fallback { slots } => {
                self.submit_linear(
                    engine,
                    "photon scatter fallback",
                    &pass.scatter_fallback,
                    slots,
                );
                return Ok(true);
            }
            ScatterPlan::Scatter { slots, changes } => (slots, changes),
        };
        self.write_scatter_uniforms(engine, scene, query);
        let bg = &self.bind_group;
        let mut encoder = Self::encoder(engine, "photon scatter");
        let weights = &pass.scatter_weights;
        dispatch_linear(&mut encoder, "photon scatter weights", weights, bg, slots);
        let terms = &pass.scatter_changes;
        dispatch_linear(&mut encoder, "photon scatter changes", terms, bg, changes);
        self.submit(engine, encoder);
        let overflow = self.counter(engine, COUNTER_SCATTER_OVERFLOW)? > 0;
        let (label, pipeline) = if overflow {
            ("photon scatter fallback", &pass.scatter_fallback)
        } else {
            ("photon scatter apply", &pass.scatter_apply)
        };
        self.submit_linear(engine, label, pipeline, slots);
        Ok(overflow)
    }

    /// Marks and lists the segments the update's changes can reach (`scatter_touch`, over at
    /// most `entries` change-list entries), for the marks' passes to take instead of the dirty
    /// cells' march over every segment (`begin_gather`); with per-sample sums it
    /// adds the changes to them in the same visit (`scatter_touch_sums`). Then reads whether
    /// the marks stand for the dirty cells (`marks`; one blocking read): no change was too
    /// wide for them, and the list holds all `changes`.
    fn touch(
        &self,
        engine: &Engine,
        scene: &Scene,
        query: Query,
        entries: u32,
        changes: u64,
    ) -> Result<(), EngineError> {
        self.write_scatter_uniforms(engine, scene, query);
        self.write_counter(engine, COUNTER_TOUCH, 1);
        let pass = &engine.photon;
        let (label, pipeline) = if self.budget.sample_cache_samples > 0 {
            ("photon scatter touch sums", &pass.scatter_touch_sums)
        } else {
            ("photon scatter touch", &pass.scatter_touch)
        };
        self.submit_linear(engine, label, pipeline, entries);
        let words = self.counter_words(engine)?;
        let stand = words[COUNTER_SCATTER_OVERFLOW] == 0 && changes <= self.budget.change_entries;
        self.marks.set(stand.then_some(words[COUNTER_LIST + 1]));
        Ok(())
    }

    /// Starts a new generation of the per-sample photon sums: every kept sum is invalid.
    fn new_sum_generation(&self) {
        // 0 is what a new buffer holds, and what `sample_forget` writes.
        let next = self.cache_generation.get().wrapping_add(1).max(1);
        self.cache_generation.set(next);
        self.sums_applied.set(false);
        self.sums_complete.set(false);
    }

    /// With per-sample sums, after an update's `gather_mark` (its counter `words`): whether
    /// the update's changes are now in every valid sum. `touch` added them where its marks
    /// stand (where they do not, a new generation starts); otherwise, unless the changes far
    /// outnumber the listed segments, `scatter_sums` adds them now (one blocking read: a
    /// change too wide for it leaves the sums incomplete, and a new generation starts). Where
    /// the change list overflowed the sums cannot be updated: a new generation. Otherwise the
    /// gather adds the changes at the dirty samples of the segments it recomposites (false).
    fn add_changes_to_sums(
        &self,
        engine: &Engine,
        scene: &Scene,
        query: Query,
        words: &[u32],
    ) -> Result<bool, EngineError> {
        let changes = words[COUNTER_CHANGES];
        let applied = if changes == 0 {
            true
        } else if changes as u64 > self.budget.change_entries {
            self.new_sum_generation();
            false
        } else if words[COUNTER_TOUCH] != 0 {
            // A change too wide for the marks left the sums that `touch` added incomplete.
            let complete = words[COUNTER_SCATTER_OVERFLOW] == 0;
            if !complete {
                self.new_sum_generation();
            }
            complete
        } else if !self.sums_by_gather
            && changes as u64 <= SUMS_SCATTER_CHANGES_PER_SEGMENT * words[COUNTER_SEGMENTS] as u64
        {
            self.write_scatter_uniforms(engine, scene, query);
            let sums = &engine.photon.scatter_sums;
            self.submit_linear(engine, "photon scatter sums", sums, changes);
            if self.counter(engine, COUNTER_SCATTER_OVERFLOW)? > 0 {
                self.new_sum_generation();
                false
            } else {
                true
            }
        } else {
            false
        };
        self.sums_applied.set(applied);
        Ok(applied)
    }

    /// The uniforms of the scatter passes: an update's, with the loop budget of one invocation
    /// (`change_pixels` in photon/scatter.wgsl checks a change's pixels against it; the marks
    /// and the scatter must decide alike).
    fn write_scatter_uniforms(&self, engine: &Engine, scene: &Scene, query: Query) {
        let dispatch = Dispatch {
            mode: MODE_UPDATE,
            round: Round {
                budget: self.round_budget(engine),
                ..Round::default()
            },
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, query, dispatch);
    }

    /// The counter words (not the dirty bits). Blocks on the GPU, unless nothing was submitted
    /// or written to the counters since the last read (`epoch`).
    fn counter_words(&self, engine: &Engine) -> Result<Vec<u32>, EngineError> {
        let epoch = self.epoch.get();
        if let Some((read_in, words)) = self.counters_read.borrow().as_ref()
            && *read_in == epoch
        {
            return Ok(words.clone());
        }
        let bytes =
            engine
                .gpu
                .read_buffer_range(&self.buffers.counters, 0, (COUNTER_WORDS * 4) as u64)?;
        let words: Vec<u32> = bytes
            .chunks_exact(4)
            .map(bytemuck::pod_read_unaligned::<u32>)
            .collect();
        *self.counters_read.borrow_mut() = Some((epoch, words.clone()));
        Ok(words)
    }

    /// Lists the paths whose historygram meets the query (`trace_mark`) and returns how many
    /// (blocks on the GPU): the retrace then runs on them alone.
    fn list_retraced(
        &self,
        engine: &Engine,
        scene: &Scene,
        paths: u32,
        query: Query,
    ) -> Result<u32, EngineError> {
        let dispatch = Dispatch {
            mode: MODE_UPDATE,
            ..Dispatch::default()
        };
        self.write_uniforms(engine, scene, query, dispatch);
        let mark = &engine.photon.trace_mark;
        self.submit_linear(engine, "photon trace mark", mark, paths);
        self.counter(engine, COUNTER_RETRACED)
    }

    /// Clear, count, scan and scatter of the grid the uniforms' `grid_pass` names, over
    /// `items` records or change-list entries (those past the list's length return at once).
    fn build_grid(&self, encoder: &mut wgpu::CommandEncoder, pass: &PhotonPass, items: u32) {
        let bg = &self.bind_group;
        let cells = self.budget.cells as u32;
        dispatch_linear(encoder, "photon grid clear", &pass.grid_clear, bg, cells);
        dispatch_linear(encoder, "photon grid count", &pass.grid_count, bg, items);
        // MAX_GRID_CELLS / SCAN_BLOCK blocks at most: within one dispatch's x.
        let blocks = (cells as u64).div_ceil(SCAN_BLOCK) as u32;
        let (reduce, scan, apply) = (
            &pass.grid_scan_reduce,
            &pass.grid_scan_blocks,
            &pass.grid_scan_apply,
        );
        dispatch_groups(encoder, "photon grid scan reduce", reduce, bg, blocks);
        dispatch_groups(encoder, "photon grid scan blocks", scan, bg, 1);
        dispatch_groups(encoder, "photon grid scan apply", apply, bg, blocks);
        dispatch_linear(
            encoder,
            "photon grid scatter",
            &pass.grid_scatter,
            bg,
            items,
        );
    }

    /// One counter word (`counter_words`).
    fn counter(&self, engine: &Engine, word: usize) -> Result<u32, EngineError> {
        Ok(self.counter_words(engine)?[word])
    }

    /// Loop iterations one gather invocation may run per round, unbounded (one round) where
    /// the device has no loop limit. llvmpipe counts its limit per batch of SIMD lanes run in
    /// lockstep, and with nested loops a batch can run up to the sum of its lanes' counts; so
    /// each lane gets its share of the limit, less a tenth for the rest of the invocation.
    fn round_budget(&self, engine: &Engine) -> u32 {
        if self.params.gather_budget > 0 {
            return self.params.gather_budget;
        }
        engine.gpu.lane_loop_budget().unwrap_or(u32::MAX)
    }

    /// Has every update add its changes to the per-sample sums in its gather, at the dirty
    /// samples, never by the scatter (tests of that path, which the scatter's limits choose).
    pub fn sum_changes_in_gather(&mut self) {
        self.sums_by_gather = true;
    }

    /// Traces `paths` paths per part of `step`'s passes, whatever they take (tests of the
    /// parts).
    pub fn fix_trace_part(&mut self, paths: u32) {
        self.fixed_trace_part = Some(paths.max(1));
    }

    /// Gathers `slots` list slots per part of `step`'s gathers, whatever they take: for tests
    /// of the parts, which otherwise only long gathers take.
    pub fn fix_gather_part(&mut self, slots: u32) {
        self.fixed_part = Some(slots.max(1));
    }

    /// Starts one progressive pass: more photons, then (`gather_part`) every segment gathered
    /// from all of them.
    fn begin_pass(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        let p = self.params.photons_per_pass;
        let offset = self.passes * p;
        self.passes += 1;
        self.write_scene(engine, scene)?;
        self.clear_pools(engine, scene, offset..offset + p);
        self.tracing = Some(0);
        Ok(())
    }

    /// Traces the next part of the pass under way (sized to `GATHER_PART_TIME` by the last
    /// part's rate) and waits for it; after its last part, starts the pass's gather. Paths are
    /// independent, so the parts give one dispatch's records.
    fn trace_next_part(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        let paths = trace_part_paths(self.fixed_trace_part, self.trace_rate);
        self.trace_part(engine, scene, paths)
    }

    /// Traces at most `paths` more paths of the pass under way (`trace_next_part`).
    fn trace_part(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        paths: u32,
    ) -> Result<(), EngineError> {
        let Some(done) = self.tracing else {
            return Ok(());
        };
        let p = self.params.photons_per_pass;
        let count = paths.min(p - done);
        let offset = (self.passes - 1) * p + done;
        let started = Instant::now();
        self.trace(engine, scene, MODE_FULL, offset, count, Query::default());
        engine.gpu.wait_idle()?;
        let took = started.elapsed().as_secs_f64();
        if took > 0.0 {
            self.trace_rate = Some(count as f64 / took);
        }
        if done + count < p {
            self.tracing = Some(done + count);
            return Ok(());
        }
        self.tracing = None;
        self.photons_traced += p as u64;
        self.begin_gather(engine, scene, MODE_FULL, Query::default())?;
        // begin_gather has waited for the trace; the pass's chunk count is a word.
        self.make_room(engine, scene)
    }

    /// Traces what is left of the pass under way at once (before anything that reads the
    /// whole map), then starts its gather.
    fn finish_trace(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        self.trace_part(engine, scene, u32::MAX)
    }

    /// Where a pass ran out of record chunks (its last paths were cut short): doubles the
    /// record slots per path and recomputes the map until none does, as far as the session's
    /// memory allows (else it logs once; every TF update of such a map is a full recompute).
    /// Blocks on the GPU.
    fn make_room(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        while self.chunks_exhausted(engine)? {
            let mut params = self.params;
            params.record_slots = params.record_slots.saturating_mul(2);
            let (w, h) = (self.width, self.height);
            let budget = PhotonBudget::new(&params, &self.volume, w, h, self.capacity)?;
            if budget.check(engine).is_err() {
                if !self.warned_chunks {
                    self.warned_chunks = true;
                    tracing::warn!(
                        "photon: a pass needs more record slots than {} per path, and no more \
                         fit; some paths were cut short and every TF edit recomputes the map",
                        self.params.record_slots
                    );
                }
                return Ok(());
            }
            tracing::debug!(
                "photon: a pass ran out of record chunks; {} slots per path",
                params.record_slots
            );
            self.buffers.resize_slots(engine, &budget);
            self.bind_group = self.buffers.bind_group(engine, &self.volume);
            self.params = params;
            self.budget = budget;
            self.records_grid_behind.set(false);
            self.full_pass(engine, scene, self.passes, false)?;
        }
        Ok(())
    }

    /// Gathers the next part of the gather under way, sized to `GATHER_PART_TIME` by the last
    /// part's rate, and waits for it.
    fn gather_next_part(&mut self, engine: &Engine, scene: &Scene) -> Result<(), EngineError> {
        let slots = part_slots(self.fixed_part, self.gather_rate);
        let before = self.gathering.map_or(0, |g| g.listed - g.next);
        let started = Instant::now();
        self.gather_part(engine, scene, slots)?;
        engine.gpu.wait_idle()?;
        let took = started.elapsed().as_secs_f64();
        // A part that ended a round (a read-back, the composite) says less about the rate.
        if slots < before && took > 0.0 {
            self.gather_rate = Some(slots as f64 / took);
        }
        Ok(())
    }

    /// Recomputes everything from scratch with `passes` photon passes (the reference an
    /// incremental update is compared with). Blocks until the GPU is done.
    pub fn recompute(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        passes: u32,
    ) -> Result<(), EngineError> {
        self.full_pass(engine, scene, passes, false)?;
        self.make_room(engine, scene)
    }

    /// The full recompute, its trace and the rest (grids, gather, composite) timed apart with a
    /// wait between them: how a full recompute's time divides (`bench tf-edit --census`).
    pub fn recompute_split(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        passes: u32,
    ) -> Result<(Duration, Duration), EngineError> {
        self.full_pass(engine, scene, passes, true)
    }

    /// A full recompute (blocks until done); with `timed`, returns how long the trace and the
    /// rest took (zero otherwise).
    fn full_pass(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        passes: u32,
        timed: bool,
    ) -> Result<(Duration, Duration), EngineError> {
        self.gathering = None;
        self.tracing = None;
        self.passes = passes.min(self.capacity);
        self.write_tf(engine, scene);
        self.write_emitters(engine, scene);
        self.write_scene(engine, scene)?;
        let paths = self.passes * self.params.photons_per_pass;
        if timed {
            engine.gpu.wait_idle()?;
        }
        let started = Instant::now();
        self.clear_pools(engine, scene, 0..paths);
        self.trace(engine, scene, MODE_FULL, 0, paths, Query::default());
        let mut trace = Duration::ZERO;
        if timed {
            engine.gpu.wait_idle()?;
            trace = started.elapsed();
        }
        let started = Instant::now();
        self.begin_gather(engine, scene, MODE_FULL, Query::default())?;
        self.finish_gather(engine, scene)?;
        self.photons_traced += paths as u64;
        engine.gpu.wait_idle()?;
        let rest = if timed {
            started.elapsed()
        } else {
            Duration::ZERO
        };
        Ok((trace, rest))
    }

    /// A full recompute with `scene` that also counts its work per record: the gather terms
    /// each record gave and the tracking steps of the flight that stored it, and per path its
    /// last flight's (benchmarks: `WorkBound::between` two censuses bounds what an exact
    /// update between their TFs can save). The state afterwards is that of `recompute`. It
    /// borrows the delta scatter's buffer (two words per record slot and one per path), which
    /// a full pass does not use, and leaves it cleared.
    pub fn census(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        passes: u32,
    ) -> Result<Census, EngineError> {
        let slots = self.budget.records;
        // Terms and steps per slot, then the last flight's steps per path.
        let bytes = 8 * slots + 4 * self.budget.paths;
        if self.budget.scatter_bytes < bytes {
            return Err(EngineError::InvalidScene(format!(
                "photon census: needs {bytes} bytes of the delta scatter's buffer, which has {} \
                 (PhotonParams::scatter_bytes)",
                self.budget.scatter_bytes
            )));
        }
        let clear = |photon: &Self| {
            let mut encoder = Self::encoder(engine, "photon census clear");
            encoder.clear_buffer(&photon.buffers.scatter, 0, Some(bytes));
            photon.submit(engine, encoder);
        };
        clear(self);
        self.census.set(true);
        let done = self.full_pass(engine, scene, passes, false);
        self.census.set(false);
        done?;
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&engine.gpu.read_buffer_range(
            &self.buffers.scatter,
            0,
            bytes,
        )?);
        // Between updates the scatter's per-segment words read SEGMENT_UNTOUCHED (0); a
        // leftover count of 1 would pass for a mark (more work for the next update, same bits).
        clear(self);
        let (map, paths) = self.read_map(engine)?;
        let slots = slots as usize;
        let per_record = |offset: usize| -> Vec<u32> {
            let slot_words = map.canonical.slots.iter();
            slot_words.map(|&s| words[offset + s as usize]).collect()
        };
        Ok(Census {
            terms: per_record(0),
            steps: per_record(slots),
            records: map.records,
            path_starts: map.canonical.path_starts,
            end_steps: words[2 * slots..2 * slots + paths.len()].to_vec(),
        })
    }

    /// The incremental update after a TF edit from `old_tf` (`scene` holds the new TF).
    /// Blocks until done.
    pub fn update_tf(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        old_tf: &TransferFunction,
    ) -> Result<UpdateReport, EngineError> {
        // A full gather under way (a pass's, a camera edit's) gathers every segment anyway: it
        // starts again after the photons' update, with the new TF, instead of ending with the
        // old one for the update to correct (seconds at 512² on a software adapter). Any other
        // update starts from segments of the old TF: a gather under way ends first (with the
        // old TF's table, still bound).
        // A pass being traced is finished with the TF it started with (still in the LUT), so
        // that the update starts from a whole map; its full gather then runs with the new TF.
        self.finish_trace(engine, scene)?;
        let regather = self.gathering.is_some_and(|g| g.mode == MODE_FULL);
        if !regather {
            self.finish_gather(engine, scene)?;
        }
        let query_historygram = query_historygram(old_tf, &scene.tf);
        self.write_tf(engine, scene);
        let paths = self.passes * self.params.photons_per_pass;
        let segments = self.width as u64 * self.height as u64 * self.params.segments as u64;
        if query_historygram == 0 || self.passes == 0 {
            let report = UpdateReport {
                paths: paths as u64,
                segments,
                ..UpdateReport::default()
            };
            self.last_update = Some(report);
            return Ok(report);
        }
        // Interpolation between LUT entries can reach one bin further than the query's own
        // rounding; widening it by one bin on each side keeps the update exact at the edges.
        let widen = |q: u64| q | (q << 1) | (q >> 1);
        let query = Query {
            any: widen(query_historygram),
            opacity: widen(opacity_query_historygram(old_tf, &scene.tf)),
            rejection: widen(opacity_rise_historygram(old_tf, &scene.tf)),
            collision: widen(collision_query_historygram(old_tf, &scene.tf)),
        };
        if query.any == u64::MAX {
            // Every bin changed: every path would be retraced from its start and most segments
            // gathered again; the full recompute is that work without the checks.
            return self.update_by_recompute(engine, scene);
        }
        self.write_counters(engine, 0, &vec![0u8; self.budget.counter_bytes as usize]);
        self.marks.set(None);
        self.write_scene(engine, scene)?;
        let listed = self.list_retraced(engine, scene, paths, query)?;
        self.retrace(engine, scene, listed, query)?;
        if self.chunks_exhausted(engine)? {
            // A retraced path grew past what its pass's pool had left and was cut short, which
            // a full recompute (taking every chunk afresh) would not do.
            tracing::debug!("photon: an update ran out of record chunks; recomputing the map");
            return self.update_by_recompute(engine, scene);
        }
        if regather {
            let words = self.counter_words(engine)?;
            self.begin_gather(engine, scene, MODE_FULL, Query::default())?;
            self.shown = 0;
            return Ok(self.record_update(UpdateReport {
                segments_recomputed: segments,
                ..photons_report(&words, paths, segments)
            }));
        }
        let changes = self.counter(engine, COUNTER_CHANGES)? as u64;
        if self.params.invalidation == Invalidation::DirtyCells
            && self.budget.scatter_capacity > 0
            && !self.sums_by_gather
            && let Some(entries) = touch_entries(changes, segments, self.budget.change_entries)
        {
            self.touch(engine, scene, query, entries, changes)?;
        }
        // The dirty cells of the changes the list holds (the trace marked the rest); a full
        // regather needs none, and neither does an update whose marks stand with per-sample
        // sums: the marks added the changes to the sums, and gather_mark takes the marks.
        if self.marks.get().is_none() || self.budget.sample_cache_samples == 0 {
            self.submit_linear(
                engine,
                "photon trace mark changes",
                &engine.photon.trace_mark_changes,
                changes.min(self.budget.change_entries) as u32,
            );
        }
        self.begin_gather(engine, scene, MODE_UPDATE, query)?;
        self.finish_gather(engine, scene)?;
        let words = self.counter_words(engine)?;
        let mask = |axis: usize| {
            words[COUNTER_SPATIAL + 2 * axis] as u64
                | (words[COUNTER_SPATIAL + 2 * axis + 1] as u64) << 32
        };
        Ok(self.record_update(UpdateReport {
            segments_recomputed: words[COUNTER_SEGMENTS] as u64,
            segments_delta: words[COUNTER_DELTA] as u64,
            segments_scattered: self.scattered as u64,
            spatial: [mask(0), mask(1), mask(2)],
            ..photons_report(&words, paths, segments)
        }))
    }

    /// An update done as a full recompute (every path retraced, every segment gathered).
    fn update_by_recompute(
        &mut self,
        engine: &Engine,
        scene: &Scene,
    ) -> Result<UpdateReport, EngineError> {
        self.recompute(engine, scene, self.passes)?;
        let paths = (self.passes * self.params.photons_per_pass) as u64;
        let segments = self.width as u64 * self.height as u64 * self.params.segments as u64;
        let report = UpdateReport {
            paths,
            paths_retraced: paths,
            records_changed: self.record_count() as u64,
            segments,
            segments_recomputed: segments,
            spatial: [u64::MAX; 3],
            ..UpdateReport::default()
        };
        self.last_update = Some(report);
        Ok(report)
    }

    /// Keeps `report` as the last update's and counts its retraced photons.
    fn record_update(&mut self, report: UpdateReport) -> UpdateReport {
        self.photons_traced += report.paths_retraced;
        self.last_update = Some(report);
        report
    }

    /// Reads back the photon map, the segments and the picture, the map in path order
    /// (`PhotonState`).
    pub fn read_state(&self, engine: &Engine) -> Result<PhotonState, EngineError> {
        self.catch_up_records_grid(engine);
        let cast = odd_readback;
        let words = |buffer: &wgpu::Buffer, what: &str| -> Result<Vec<u32>, EngineError> {
            let bytes = engine.gpu.read_buffer(buffer)?;
            Ok(bytemuck::try_cast_slice::<u8, u32>(&bytes)
                .map_err(|_| cast(what))?
                .to_vec())
        };
        let (map, paths) = self.read_map(engine)?;
        let segments = engine.gpu.read_buffer(&self.buffers.segments)?;
        let hdr = engine.gpu.read_buffer(&self.buffers.accum)?;
        let cells = words(&self.buffers.grid_cells, "grid")?;
        let grid_sorted = words(&self.buffers.grid_sorted, "grid")?;
        let pixels = (self.width * self.height) as usize;
        let n_cells = self.budget.cells as usize;
        let slots = self.record_count() as usize;
        let total = (cells[n_cells] as usize).min(slots);
        // The grid's slots as path-order indices; the order within a cell is the atomics'
        // (the sums do not depend on it), so each cell's in index order, that equal grids
        // compare equal.
        let mut sorted: Vec<u32> = grid_sorted[..total]
            .iter()
            .map(|&slot| {
                map.canonical
                    .index_of
                    .get(slot as usize)
                    .copied()
                    .unwrap_or(u32::MAX)
            })
            .collect();
        for c in 0..n_cells {
            let (first, end) = (cells[c] as usize, (cells[c + 1] as usize).min(total));
            if first < end {
                sorted[first..end].sort_unstable();
            }
        }
        Ok(PhotonState {
            records: map.records,
            paths: paths
                .into_iter()
                .map(|p| PhotonPath { chunk: 0, ..p })
                .collect(),
            segments: bytemuck::try_cast_slice::<u8, Segment>(&segments)
                .map_err(|_| cast("segments"))?[..pixels * self.params.segments as usize]
                .to_vec(),
            hdr: bytemuck::try_cast_slice::<u8, [f32; 4]>(&hdr).map_err(|_| cast("image"))?
                [..pixels]
                .to_vec(),
            grid_cells: cells[..n_cells + 1].to_vec(),
            grid_sorted: sorted,
        })
    }

    /// The map's records in path order (and the paths as the GPU holds them).
    fn read_map(&self, engine: &Engine) -> Result<(PathOrder, Vec<PhotonPath>), EngineError> {
        let odd = odd_readback;
        let records = engine.gpu.read_buffer(&self.buffers.records)?;
        let records =
            bytemuck::try_cast_slice::<u8, PhotonRecord>(&records).map_err(|_| odd("records"))?;
        let paths = engine.gpu.read_buffer(&self.buffers.paths)?;
        let n_paths = (self.passes * self.params.photons_per_pass) as usize;
        let paths = bytemuck::try_cast_slice::<u8, PhotonPath>(&paths).map_err(|_| odd("paths"))?
            [..n_paths]
            .to_vec();
        let chunks = engine.gpu.read_buffer(&self.buffers.chunks)?;
        let next: &[u32] = bytemuck::try_cast_slice(&chunks).map_err(|_| odd("chunks"))?;
        let record_slots = self.record_count() as usize;
        let canonical = slots::canonical(&self.budget.layout, &paths, next, record_slots)
            .ok_or_else(|| {
                EngineError::Gpu("photon: a path's chunk list does not hold its records".into())
            })?;
        let records = canonical
            .slots
            .iter()
            .map(|&s| records[s as usize])
            .collect();
        Ok((PathOrder { canonical, records }, paths))
    }
}

/// A read-back buffer whose size is not a whole number of its records.
fn odd_readback(what: &str) -> EngineError {
    EngineError::Gpu(format!("photon {what} readback has an odd size"))
}

/// A map read back in path order (`Photon::read_map`).
struct PathOrder {
    canonical: slots::Canonical,
    records: Vec<PhotonRecord>,
}

/// The gather kernel of every pass (`PhotonUniforms::pass_kernels`): pass i's r_i² and
/// (r_0 / r_i)³ (its Epanechnikov normalisation relative to r_0's) for the radius schedule
/// r_i³ = r_0³ · Π_{k<i} (k + α) / (k + 1).
pub fn pass_kernels(r0: f32, alpha: f32) -> [[f32; 4]; PASS_KERNEL_ENTRIES] {
    let mut table = [[0.0f32; 4]; PASS_KERNEL_ENTRIES];
    let mut volume_ratio = 1.0f64;
    for i in 0..2 * PASS_KERNEL_ENTRIES {
        let r2 = (r0 as f64 * r0 as f64 * volume_ratio.powf(2.0 / 3.0)) as f32;
        let norm = (1.0 / volume_ratio) as f32;
        table[i / 2][2 * (i % 2)] = r2;
        table[i / 2][2 * (i % 2) + 1] = norm;
        volume_ratio *= (i as f64 + alpha as f64) / (i as f64 + 1.0);
    }
    table
}

/// Pass `pass`'s gather radius (world units) under `radius_alpha`'s schedule.
pub fn pass_radius(r0: f32, alpha: f32, pass: u32) -> f32 {
    let i = (pass as usize).min(2 * PASS_KERNEL_ENTRIES - 1);
    pass_kernels(r0, alpha)[i / 2][2 * (i % 2)].sqrt()
}

/// Photon emitters for the lights: selection by power (mean over rgb), each photon carrying
/// its light's power / (selection probability · photons per pass).
pub fn emitters(lights: &[Light], volume: &GpuVolume, photons_per_pass: u32) -> Vec<PhotonEmitter> {
    let extent = volume.extent;
    let radius = 0.5
        * (extent[0] * extent[0] + extent[1] * extent[1] + extent[2] * extent[2]).sqrt()
        * 1.001;
    let disk = std::f32::consts::PI * radius * radius;
    let four_pi = 4.0 * std::f32::consts::PI;
    let mut list: Vec<(u32, [f32; 3], [f32; 3])> = Vec::new();
    let mut env = [0.0f32; 3];
    for light in lights {
        match *light {
            Light::Directional {
                direction,
                irradiance,
            } => list.push((
                EMIT_DIRECTIONAL,
                crate::camera::normalize(direction).unwrap_or([0.0, 0.0, -1.0]),
                irradiance.map(|e| e * disk),
            )),
            Light::Point {
                position,
                intensity,
            } => list.push((EMIT_POINT, position, intensity.map(|i| i * four_pi))),
            Light::Environment { radiance } => {
                for k in 0..3 {
                    env[k] += radiance[k];
                }
            }
        }
    }
    if env.iter().any(|&e| e > 0.0) {
        // Uniform radiance L from every direction: L · 4π · πR² enters the bounding sphere.
        list.push((EMIT_ENVIRONMENT, [0.0; 3], env.map(|l| l * four_pi * disk)));
    }
    let weight = |p: &[f32; 3]| (p[0] + p[1] + p[2]) / 3.0;
    list.retain(|(_, _, p)| weight(p) > 0.0);
    let total: f32 = list.iter().map(|(_, _, p)| weight(p)).sum();
    if list.is_empty() {
        return vec![PhotonEmitter {
            vector: [0.0, 0.0, -1.0],
            kind: EMIT_DIRECTIONAL,
            power: [0.0; 3],
            cdf: 1.0,
        }];
    }
    let mut cdf = 0.0;
    let n = list.len();
    list.into_iter()
        .enumerate()
        .map(|(i, (kind, vector, power))| {
            let prob = weight(&power) / total;
            cdf += prob;
            PhotonEmitter {
                vector,
                kind,
                power: power.map(|p| p / (prob * photons_per_pass as f32)),
                cdf: if i + 1 == n { 1.0 } else { cdf },
            }
        })
        .collect()
}

impl Technique for Photon {
    fn name(&self) -> &'static str {
        "photon"
    }

    fn apply(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        change: &Change,
    ) -> Result<(), EngineError> {
        match change {
            Change::Tf { old, .. } => {
                self.update_tf(engine, scene, old)?;
            }
            Change::Camera => {
                // Photons do not depend on the camera: gather again (in parts, by `step`); a
                // gather under way, of the old view, is dropped.
                self.shown = 0;
                if self.passes > 0 {
                    self.write_scene(engine, scene)?;
                    // A pass being traced gathers everything, in this view, once its trace
                    // is done.
                    if self.tracing.is_none() {
                        self.begin_gather(engine, scene, MODE_FULL, Query::default())?;
                    }
                }
            }
            Change::Lights | Change::Params => {
                self.write_emitters(engine, scene);
                self.gathering = None;
                self.tracing = None;
                self.passes = 0;
                self.shown = 0;
            }
            Change::Viewport => {
                *self = Photon::new(engine, self.volume.clone(), scene, self.params)?;
            }
            Change::Iterations => {
                if scene.target_iterations.min(self.params.max_passes) > self.capacity {
                    let passes = self.passes;
                    *self = Photon::new(engine, self.volume.clone(), scene, self.params)?;
                    if passes > 0 {
                        self.recompute(engine, scene, passes)?;
                    }
                }
            }
        }
        Ok(())
    }

    fn step(
        &mut self,
        engine: &Engine,
        scene: &Scene,
        budget: Duration,
    ) -> Result<StepReport, EngineError> {
        let target = self.target(scene);
        let start = Instant::now();
        let shown = self.shown;
        loop {
            if self.tracing.is_some() {
                self.trace_next_part(engine, scene)?;
            } else if self.gathering.is_some() {
                self.gather_next_part(engine, scene)?;
            } else if self.passes < target {
                self.begin_pass(engine, scene)?;
            } else {
                break;
            }
            // A zero budget asks for the next part now.
            if budget.is_zero() || start.elapsed() >= budget {
                break;
            }
        }
        Ok(StepReport {
            iterations_done: self.shown.saturating_sub(shown),
            iteration: self.shown,
            converged: self.tracing.is_none() && self.gathering.is_none() && self.shown >= target,
            gpu_time: start.elapsed(),
        })
    }

    fn output(&self) -> &wgpu::Buffer {
        &self.buffers.accum
    }

    /// Passes in the picture shown (a pass counts once its gather is done).
    fn iteration(&self) -> u32 {
        self.shown
    }

    fn target_iterations(&self, scene: &Scene) -> u32 {
        self.target(scene)
    }

    fn stats(&self) -> TechniqueStats {
        let update = self.last_update.unwrap_or_default();
        TechniqueStats {
            name: self.name(),
            iteration: self.shown,
            memory_bytes: self.budget.total,
            details: TechniqueDetails {
                photons_traced: Some(self.photons_traced).filter(|&n| n > 0),
                photons_in_map: Some(self.passes as u64 * self.params.photons_per_pass as u64)
                    .filter(|&n| n > 0),
                photons_retraced_pct: self
                    .last_update
                    .map(|_| update.photons_retraced_pct() as f32),
                segments_recomputed_pct: self
                    .last_update
                    .map(|_| update.segments_recomputed_pct() as f32),
                ..TechniqueDetails::default()
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn marked(segments: u32, delta: u32, scatter: u32, changes: u32) -> Marked {
        Marked {
            segments,
            delta,
            scatter,
            changes,
            cut: 0,
        }
    }

    const RECORDS: GridBuild = GridBuild {
        grid: GRID_RECORDS,
        items: 900,
    };
    const CHANGES: GridBuild = GridBuild {
        grid: GRID_CHANGES,
        items: 50,
    };

    #[test]
    fn a_full_gather_builds_the_records_grid_and_scatters_nothing() {
        let plan = GridPlan::full(900);
        assert_eq!(plan.scatter, None);
        assert_eq!(plan.grids(false), vec![RECORDS]);
        assert_eq!(plan.scattered(false), 0);
    }

    #[test]
    fn an_update_with_sample_sums_builds_only_the_grids_its_samples_read() {
        // 40 segments listed, 30 of them from the changes alone (no opacity change), 35 changes
        // in a list of 50.
        let plan = |m, applied, complete| GridPlan::summed(m, applied, complete, true, 900, 50);
        // The changes are in the sums: a segment whose opacity rose may gather a sample
        // afresh; the others recomposite from valid sums.
        assert_eq!(
            plan(marked(40, 30, 0, 35), true, true).grids(false),
            vec![RECORDS]
        );
        // Where opacity only fell, only a segment that was cut off may.
        let fell = |m| GridPlan::summed(m, true, true, false, 900, 50).grids(false);
        assert_eq!(fell(marked(40, 30, 0, 35)), vec![]);
        assert_eq!(
            fell(Marked {
                cut: 1,
                ..marked(40, 30, 0, 35)
            }),
            vec![RECORDS]
        );
        assert_eq!(plan(marked(30, 30, 0, 35), true, true).grids(false), vec![]);
        // Unless the sums started anew since the last full gather.
        assert_eq!(
            plan(marked(30, 30, 0, 35), true, false).grids(false),
            vec![RECORDS]
        );
        // The gather adds the changes at the dirty samples.
        let from_gather = plan(marked(30, 30, 0, 35), false, true);
        assert_eq!(from_gather.grids(false), vec![CHANGES]);
        assert_eq!(from_gather.scatter, None);
        // A change list that overflowed cannot be added (the sums start anew instead).
        let overflowed = plan(marked(40, 30, 0, 60), false, false);
        assert_eq!(overflowed.grids(false), vec![RECORDS]);
        // Nothing listed: no grid.
        assert_eq!(plan(marked(0, 0, 0, 35), false, true).grids(false), vec![]);
    }

    #[test]
    fn an_update_scatters_into_its_slots_and_gathers_the_rest_from_the_change_grid() {
        // 40 segments listed, 30 from the changes alone, 25 asking for a slot; 20 slots.
        let plan = GridPlan::update(marked(40, 30, 25, 35), 20, 900, 50);
        assert_eq!(
            plan.scatter,
            Some(ScatterPlan::Scatter {
                slots: 20,
                changes: 35
            })
        );
        // 10 gathered afresh (records' grid), 10 past the slots from the change grid.
        assert_eq!(plan.grids(false), vec![RECORDS, CHANGES]);
        assert_eq!(plan.scattered(false), 20);
        // A change that reached too many pixels gives every slot back to the delta gather.
        assert_eq!(plan.grids(true), vec![RECORDS, CHANGES]);
        assert_eq!(plan.scattered(true), 0);

        // Every delta segment has a slot and none is gathered afresh: no grid at all, unless
        // the scatter gives its slots back.
        let plan = GridPlan::update(marked(30, 30, 30, 35), 64, 900, 50);
        assert_eq!(plan.grids(false), vec![]);
        assert_eq!(plan.scattered(false), 30);
        assert_eq!(plan.grids(true), vec![CHANGES]);
    }

    #[test]
    fn an_update_leaves_changes_that_far_outnumber_the_slots_to_the_delta_gather() {
        // The change list holds 50 of the 400 changes written: 50 > 2 × 20 slots.
        let plan = GridPlan::update(marked(20, 20, 20, 400), 64, 900, 50);
        assert_eq!(plan.scatter, Some(ScatterPlan::Fallback { slots: 20 }));
        // At twice the slots the scatter still pays (the list caps the changes it visits).
        let plan = GridPlan::update(marked(25, 25, 25, 400), 64, 900, 50);
        assert_eq!(
            plan.scatter,
            Some(ScatterPlan::Scatter {
                slots: 25,
                changes: 50
            })
        );
        // No slots (the scatter off, or nothing asked for one): no scatter.
        let plan = GridPlan::update(marked(20, 20, 20, 10), 0, 900, 50);
        assert_eq!(plan.scatter, None);
        assert_eq!(plan.grids(false), vec![CHANGES]);
        // Nothing stale: no grid, nothing to gather.
        let plan = GridPlan::update(Marked::default(), 64, 900, 50);
        assert_eq!((plan.scatter, plan.grids(false)), (None, vec![]));
    }

    #[test]
    fn touch_marks_from_the_changes_only_where_they_are_few_for_the_segments() {
        assert_eq!(touch_entries(10, 160, 1000), Some(10));
        assert_eq!(touch_entries(11, 160, 1000), None);
        // At most the list's entries (an overflowing list holds no more).
        assert_eq!(touch_entries(100, 1 << 20, 64), Some(64));
    }

    #[test]
    fn an_unbounded_gather_is_one_round_in_parts() {
        let mut gathering = GatherInProgress::new(MODE_FULL, Query::default(), 2500, 0);
        let mut parts = Vec::new();
        while gathering.listed > 0 {
            let part = gathering.part(u32::MAX, 32, 1000);
            gathering.advance(&part, 0);
            parts.push(part);
        }
        let slots: Vec<(u32, u32)> = parts.iter().map(|p| (p.round.first, p.slots)).collect();
        assert_eq!(slots, vec![(0, 1000), (1000, 1000), (2000, 500)]);
        assert!(parts.iter().all(|p| p.round.stride == 1
            && p.round.budget == u32::MAX
            && p.round.input == 0
            && p.output == 1));
        // The first part clears the list the round writes; the last ends it and reads nothing
        // (an unbounded round leaves no segment).
        assert_eq!(
            parts.iter().map(|p| p.clear_output).collect::<Vec<_>>(),
            vec![true, false, false]
        );
        assert_eq!(
            parts.iter().map(|p| p.ends_round).collect::<Vec<_>>(),
            vec![false, false, true]
        );
        assert!(parts.iter().all(|p| p.next_list.is_none()));
        assert_eq!(gathering.rounds, 1);
    }

    #[test]
    fn bounded_rounds_alternate_lists_and_give_the_rest_more_budget_on_fewer_lanes() {
        let mut gathering = GatherInProgress::new(MODE_UPDATE, Query::default(), 100, 0);
        let mut rounds = Vec::new();
        // Each round leaves half its segments, until one is left and it finishes.
        while gathering.listed > 0 {
            let part = gathering.part(200, 16, u32::MAX);
            assert!(part.ends_round && part.clear_output && part.slots == gathering.listed);
            assert_eq!(part.next_list, Some(COUNTER_LIST + part.output as usize));
            assert_eq!(part.output, 1 - part.round.input);
            gathering.advance(&part, part.slots / 2);
            rounds.push((part.round.input, part.round.stride, part.round.budget));
        }
        assert_eq!(
            rounds,
            vec![
                (0, 1, 200),
                (1, 2, 400),
                (0, 4, 800),
                (1, 8, 1600),
                (0, 16, 3200),
                // At most the lanes of a SIMD batch.
                (1, 16, 3200),
                (0, 16, 3200),
            ]
        );
        assert_eq!(gathering.rounds, 7);
        // Lanes are taken as at least 1 and at most 64; the doubling stops at 64.
        let mut late = GatherInProgress::new(MODE_FULL, Query::default(), 5, 0);
        late.rounds = 9;
        assert_eq!(late.part(200, 0, 2).round.stride, 1);
        assert_eq!(late.part(200, 128, 2).round.stride, 64);
        assert_eq!(late.part(u32::MAX / 2, 128, 2).round.budget, u32::MAX);
        assert_eq!(
            late.part(200, 128, 0).slots,
            1,
            "at least one slot per part"
        );
    }

    #[test]
    fn gather_parts_follow_the_last_rate() {
        assert_eq!(part_slots(Some(1000), Some(1.0)), 1000);
        assert_eq!(part_slots(None, None), FIRST_PART_SLOTS);
        // 40 ms at 100 000 slots per second.
        assert_eq!(part_slots(None, Some(100_000.0)), 4000);
        assert_eq!(part_slots(None, Some(0.0)), 1);
        assert_eq!(part_slots(None, Some(f64::INFINITY)), u32::MAX);
    }

    #[test]
    fn trace_parts_are_sized_by_the_last_parts_rate() {
        assert_eq!(trace_part_paths(None, None), FIRST_TRACE_PATHS);
        assert_eq!(trace_part_paths(Some(100), Some(1e9)), 100);
        // 40 ms at 100 000 paths per second.
        assert_eq!(trace_part_paths(None, Some(100_000.0)), 4000);
        // At least a workgroup's paths, however slow the last part was.
        assert_eq!(trace_part_paths(None, Some(10.0)), WORKGROUP);
    }

    #[test]
    fn the_radius_schedule_shrinks_by_the_3d_knaus_zwicker_rule() {
        let r0 = 0.05f32;
        let table = pass_kernels(r0, 2.0 / 3.0);
        // Pass 0 gathers with r_0 and the normalisation of r_0.
        assert!((table[0][0] - r0 * r0).abs() < 1e-9);
        assert_eq!(table[0][1], 1.0);
        // r_1³ = r_0³ · α, r_2³ = r_1³ · (1 + α) / 2; the normalisation is (r_0 / r_i)³.
        let r1 = pass_radius(r0, 2.0 / 3.0, 1);
        assert!((r1.powi(3) / r0.powi(3) - 2.0 / 3.0).abs() < 1e-5, "{r1}");
        let r2 = pass_radius(r0, 2.0 / 3.0, 2);
        assert!(
            (r2.powi(3) / r1.powi(3) - (5.0 / 3.0) / 2.0).abs() < 1e-5,
            "{r2}"
        );
        assert!((table[0][3] - 1.5).abs() < 1e-5);
        assert!((table[1][1] * (r2 / r0).powi(3) - 1.0).abs() < 1e-4);
        // Shrinking throughout, never to zero; past the table the last entry holds.
        let radii: Vec<f32> = (0..300).map(|i| pass_radius(r0, 2.0 / 3.0, i)).collect();
        assert!(radii.windows(2).all(|w| w[1] <= w[0]));
        assert!(
            radii[255] > 0.3 * r0 && radii[255] < 0.6 * r0,
            "{}",
            radii[255]
        );
        assert_eq!(radii[299], radii[255]);
        // α = 1 keeps one radius.
        let one = pass_kernels(r0, 1.0);
        assert!(one.iter().all(|e| e[0] == one[0][0] && e[2] == one[0][0]));
        assert!(one.iter().all(|e| e[1] == 1.0 && e[3] == 1.0));
    }
}
