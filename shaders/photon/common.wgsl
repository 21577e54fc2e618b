// Shared pieces of technique `photon` (volumetric photon mapping with historygrams, Jönsson et
// al. 2012): the bindings every photon pass shares (one layout, server/engine/src/techniques/photon/gpu.rs),
// the photon, path and view-ray-segment records, historygram helpers and the medium.
// Prepended to photon/trace.wgsl, photon/grid.wgsl, photon/gather.wgsl and photon/scatter.wgsl.

#import shared/common
#import shared/volume
#import shared/scene

struct PhotonUniforms {
    // Hash grid: cell edge = gather radius, over the volume box.
    grid_dims: vec3<u32>,
    cell_count: u32,
    radius: f32,
    // Epanechnikov normalisation 15 / (8π r³) divided by the number of photon passes.
    kernel_norm: f32,
    // Fixed majorant of delta tracking: density_scale · 1 (opacity ≤ 1), independent of the TF.
    majorant: f32,
    // View-ray march step in world units.
    gather_step: f32,
    photons_per_pass: u32,
    // Paths in the map (passes · photons_per_pass) and record slots (paths · path_slots).
    path_count: u32,
    record_count: u32,
    // The most interactions a path may store (1 = single scattering).
    bounces: u32,
    // First path of this trace dispatch and how many.
    path_offset: u32,
    dispatch_paths: u32,
    // MODE_FULL or MODE_UPDATE. The trace kernel does not read it: the host picks its pipeline
    // by the mode instead (photon/trace.wgsl, TRACE_UPDATE).
    mode: u32,
    // View-ray segments per pixel (Vn).
    segments: u32,
    // The edit's query split by what it can change on a photon path (64 bits each). Rejection
    // query: bins whose opacity rose, where a rejected tentative collision may become a real
    // one; it meets the historygram of every tentative point. Collision query: bins whose
    // colour changed or opacity fell, where a real collision may change its albedo or be
    // rejected; it meets the bins of the path's collisions only (a rejected point stays
    // rejected when the opacity falls, and its colour is never used).
    rejection_query_lo: u32,
    rejection_query_hi: u32,
    emitter_count: u32,
    // How segments learn of changed photons: SPATIAL_NONE (any change invalidates every
    // segment), SPATIAL_AXES (the 3×64-bit spatial historygram), SPATIAL_CELLS (a dirty bit per
    // half-size hash cell, dilated by two).
    spatial: u32,
    // Gather rounds: which half of gather_list (and COUNTER_LIST word) is this round's input,
    // and the loop iterations an invocation may run before it keeps its place for the next.
    round_input: u32,
    round_budget: u32,
    // Only every round_stride-th invocation gathers (one per SIMD batch in the last rounds,
    // so that one lane may take the whole budget).
    round_stride: u32,
    // Bins whose opacity changed (a subset of the query): all that a segment depends on
    // directly; colour reaches it only through the photons.
    opacity_query_lo: u32,
    opacity_query_hi: u32,
    // Which grid the grid kernels build: GRID_RECORDS or GRID_CHANGES.
    grid_pass: u32,
    // Entries the change list holds.
    change_capacity: u32,
    // Records the map holds; the change grid's slots start there in grid_sorted.
    record_capacity: u32,
    collision_query_lo: u32,
    collision_query_hi: u32,
    // Segments the delta scatter can hold (0: off, every delta segment is gathered from the
    // change grid) and the lattice samples it keeps per segment (photon/scatter.wgsl).
    scatter_capacity: u32,
    scatter_samples: u32,
    // 1: this full pass also counts its work per record slot into `scatter`, which a full pass
    // does not otherwise use (the work census of `bench tf-edit --census`): words
    // [0, record_capacity) the gather terms each record gave, words
    // [record_capacity, 2 · record_capacity) the tracking steps of the flight that stored
    // each slot's record, words [2 · record_capacity, + path_count) those of each path's
    // last flight, which stored none (it left the volume). 0 in every other pass.
    census: u32,
    // The first list slot of this gather dispatch: a round runs as parts, one submission each,
    // so that a long gather gives way between them (techniques/photon: GatherInProgress).
    round_first: u32,
    // Russian roulette: from interaction `roulette_from` on, a path goes on to its next
    // interaction with probability `roulette_survival` (a constant, not the albedo: so whether
    // a path survives does not depend on the TF, and a recoloured record's path keeps its
    // length) and its power is divided by it. survival >= 1: off.
    roulette_survival: f32,
    roulette_from: u32,
    // Record slots (record_slot): each pass owns a block of photons_per_pass · path_slots
    // slots, in it first inline_slots per path (a path's first interactions), then a pool of
    // chunks of CHUNK_SLOTS slots that the paths of that pass take as they grow past their
    // inline slots (chunks_per_pass of them). A path's chunks form a list, from
    // PhotonPath::chunk through `chunks` (next pointers; from chunk_counts_at on, the chunks
    // each pass has taken). So a path has any length up to `bounces`, while the memory is
    // path_slots per path on average.
    path_slots: u32,
    inline_slots: u32,
    chunks_per_pass: u32,
    chunk_counts_at: u32,
    // The per-sample photon sums (`sample_sums`): lattice samples kept per pixel (0: off, the
    // segment sums each photon's weighted term), the generation an entry must carry to be
    // valid (each full gather starts a new one), and whether this update's changes were
    // already added to the valid entries (scatter_sums; 0: the gather adds them from the
    // change grid at the dirty samples it visits).
    sample_cache_samples: u32,
    cache_generation: u32,
    sums_applied: u32,
    // Whether the update's marks (scatter_touch) stand for the dirty cells: no change was too
    // wide for them, and the change list holds every change (the host reads it after them).
    marks_stand: u32,
    // Progressive radius reduction (Knaus & Zwicker 2011): the photons of pass i are gathered
    // with their own radius r_i <= radius (the grid's cell edge), r_i³ = r_0³ · Π_{k<i} (k + α)
    // / (k + 1). Entry i / 2 holds pass i's (r_i², (r_0 / r_i)³) in .xy (even i) or .zw (odd
    // i); passes past the table use its last entry. The picture is the mean of the passes'
    // estimates, so both noise and kernel blur fall as passes are added.
    pass_kernels: array<vec4<f32>, PASS_KERNEL_ENTRIES>,
}

const PASS_KERNEL_ENTRIES: u32 = 128u;

// Pass `pass_index`'s kernel: (r², normalisation relative to radius's).
fn pass_kernel(pass_index: u32) -> vec2<f32> {
    let i = min(pass_index, 2u * PASS_KERNEL_ENTRIES - 1u);
    let e = photon.pass_kernels[i / 2u];
    if (i % 2u == 0u) {
        return e.xy;
    }
    return e.zw;
}

// The pass that traced the record in slot `index` (inline or in a chunk: both lie in the
// pass's block).
fn record_pass(index: u32) -> u32 {
    return index / (photon.path_slots * photon.photons_per_pass);
}

// A stored photon interaction (a real collision): where, the direction it arrived from (travel
// direction), its power after the albedo there, its hash cell (CELL_NONE = no photon) and the
// historygram of every data value its path sampled up to here.
struct PhotonRecord {
    position: vec3<f32>,
    cell: u32,
    power: vec3<f32>,
    hist_lo: u32,
    direction: vec3<f32>,
    hist_hi: u32,
}

// Per record slot, where its flight stood just before the collision point: the flight's t
// there and the draws its Rng had taken (Rng.dim). An update resumes a flight whose collision's
// opacity fell from there, where it would otherwise replay every tentative point before it.
struct RecordResume {
    t: f32,
    draws: u32,
}

// Per path: stored interactions, the historygram of the whole path (including the flight
// that left the volume) and that of its collisions' data values alone, so that a path the
// edit affects is found by two tests (trace_mark), and the first chunk of slots past its
// inline ones (CHUNK_NONE: none; photon/trace.wgsl, record_slot).
struct PhotonPath {
    count: u32,
    end_lo: u32,
    end_hi: u32,
    collisions_lo: u32,
    collisions_hi: u32,
    chunk: u32,
    pad1: u32,
    pad2: u32,
}

// A light as photons see it. kind: EMIT_DIRECTIONAL (vector = travel direction), EMIT_POINT
// (vector = position), EMIT_ENVIRONMENT. power: the power of one photon (light power / its
// selection probability / photons per pass). cdf: cumulative selection probability.
struct PhotonEmitter {
    vector: vec3<f32>,
    kind: u32,
    power: vec3<f32>,
    cdf: f32,
}

// A photon record that an update changed, for the change grid: kind CHANGE_SUBTRACT (its old
// version), CHANGE_ADD (its new version), or CHANGE_REPLACE where only the power changed (a
// colour edit's usual case): one entry that subtracts old_power's term and adds power's, so a
// delta gather visits the photon once.
struct PhotonChange {
    position: vec3<f32>,
    cell: u32,
    power: vec3<f32>,
    kind: u32,
    direction: vec3<f32>,
    // The pass that traced the record (its gather radius: pass_kernel).
    pass_index: u32,
    old_power: vec3<f32>,
    pad1: u32,
}

// A segment's gather between rounds: its radiance so far (fixed point, see fixed_hi), the
// current sample's lattice index k, the transmittance and historygram so far, and the place in
// the 27-cell neighbourhood (cell, see photon/gather.wgsl; rank within that cell). With
// per-sample sums, the current sample's sum so far waits in its own entry of sample_sums.
struct GatherState {
    color_lo: vec3<u32>,
    k: f32,
    color_hi: vec3<u32>,
    transmit: f32,
    hist_lo: u32,
    hist_hi: u32,
    cell: u32,
    rank: u32,
}

// One view-ray segment: in-scattered radiance (rgb, 64-bit fixed point as lo/hi words;
// transmittance inside the segment starts at 1), the segment's transmittance and the
// historygram of its samples' data values.
struct Segment {
    color_lo: vec3<u32>,
    transmittance: f32,
    color_hi: vec3<u32>,
    hist_lo: u32,
    hist_hi: u32,
    // 1 where the segment's march ended at its transmittance cut-off (samples past it were
    // never gathered); gather_mark counts the opacity-stale ones (COUNTER_CUT).
    cut_off: u32,
    // In each pixel's first segment: the union of its segments' historygrams as the last
    // `composite` found them (every update's marks come after a finished gather, whose
    // composite ran); gather_mark_stale skips a pixel by it. 0 in every other segment.
    pixel_hist_lo: u32,
    pixel_hist_hi: u32,
}

const MODE_FULL: u32 = 0u;
const MODE_UPDATE: u32 = 1u;
const EMIT_DIRECTIONAL: u32 = 0u;
const EMIT_POINT: u32 = 1u;
const EMIT_ENVIRONMENT: u32 = 2u;
const CELL_NONE: u32 = 0xffffffffu;
const HIST_BINS: u32 = 64u;

// Counters written by the passes: listed paths (retraced or recoloured), changed photon
// records, recomputed segments, the spatial historygram (x lo/hi, y lo/hi, z lo/hi), the
// segments listed in each half of gather_list, change-list entries, segments updated from the
// changes alone.
const COUNTER_RETRACED: u32 = 0u;
const COUNTER_CHANGED: u32 = 1u;
const COUNTER_SEGMENTS: u32 = 2u;
const COUNTER_SPATIAL: u32 = 3u;
// Segments in the two halves of gather_list (two words).
const COUNTER_LIST: u32 = 9u;
// Entries an update appended to the change list (more than change_capacity: it overflowed).
const COUNTER_CHANGES: u32 = 11u;
// Segments an update recomputed from the changes alone (by the change grid, DELTA_SEGMENT, or
// by the delta scatter).
const COUNTER_DELTA: u32 = 12u;
// Segments the delta scatter updates (its slots; past scatter_capacity the rest are gathered).
const COUNTER_SCATTER: u32 = 13u;
// Set when a change reaches more pixels than one scatter invocation may visit: the update then
// gathers every delta segment from the change grid instead (photon/scatter.wgsl).
const COUNTER_SCATTER_OVERFLOW: u32 = 14u;
// Set by the host where `scatter_touch` ran: gather_mark then finds the segments the changes
// reach by its marks instead of the dirty cells (unless the change list or the scatter
// overflowed).
const COUNTER_TOUCH: u32 = 15u;
// Listed paths an update only recoloured (photon/trace.wgsl): no flight of theirs was tracked.
const COUNTER_RECOLOURED: u32 = 16u;
// Opacity-stale segments whose last march ended at its cut-off (Segment::cut_off).
const COUNTER_CUT: u32 = 17u;
// Listed paths the walk (photon/trace.wgsl, TRACE_WALK) left to the update's trace.
const COUNTER_DEFERRED: u32 = 18u;
// Dirty-cell bits follow the counters (8 per hash cell), then one bit per pixel that an
// update changed a segment of (mark_pixel_changed).
const COUNTER_DIRTY: u32 = 19u;
const GRID_RECORDS: u32 = 0u;
const GRID_CHANGES: u32 = 1u;
const CHANGE_ADD: u32 = 0u;
const CHANGE_SUBTRACT: u32 = 1u;
const CHANGE_REPLACE: u32 = 2u;
// A gather_list entry with this bit updates its segment by the change grid's photons only.
const DELTA_SEGMENT: u32 = 0x80000000u;
// A gather_list entry with this bit starts its segment's gather from its first lattice index
// (gather_start) instead of its gather_state, which the lister did not write: most segments an
// opacity edit lists are marched from the sums (remarch_from_sums) and never gathered. Segment
// ids stay below this bit: the segments buffer (48 bytes each) fits one storage binding.
const FRESH_SEGMENT: u32 = 0x40000000u;
const SPATIAL_NONE: u32 = 0u;
const SPATIAL_AXES: u32 = 1u;
const SPATIAL_CELLS: u32 = 2u;

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> photon: PhotonUniforms;
@group(0) @binding(4) var<storage, read> emitters: array<PhotonEmitter>;
@group(0) @binding(5) var<storage, read_write> records: array<PhotonRecord>;
@group(0) @binding(6) var<storage, read_write> paths: array<PhotonPath>;
// Two grids, each over the same cells: the records' at grid_base(GRID_RECORDS), the change
// list's at grid_base(GRID_CHANGES). In each, [0, cell_count]: first slot of each cell
// (exclusive prefix sum, total at the end); [cell_count + 1, 2·cell_count + 1): per-cell
// counters and scatter cursors. grid_sorted holds the records' slots, then from
// record_capacity on the changes'.
@group(0) @binding(7) var<storage, read_write> grid_cells: array<atomic<u32>>;
@group(0) @binding(8) var<storage, read_write> grid_sorted: array<u32>;
@group(0) @binding(9) var<storage, read_write> segments: array<Segment>;
@group(0) @binding(10) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> counters: array<atomic<u32>>;
// The segments the gather computes: two halves of width·height·segments, this round's input
// and the unfinished ones for the next (COUNTER_LIST + half of them each).
@group(0) @binding(12) var<storage, read_write> gather_list: array<u32>;
// Where an unfinished segment's gather stands, by segment.
@group(0) @binding(13) var<storage, read_write> gather_state: array<GatherState>;
// The paths an update retraces (COUNTER_RETRACED of them), listed by `trace_mark`.
@group(0) @binding(14) var<storage, read_write> retrace_list: array<u32>;
// The records an update changed, old and new versions (or one entry for both where only the
// power changed; COUNTER_CHANGES of them).
@group(0) @binding(15) var<storage, read_write> changes: array<PhotonChange>;
// The delta scatter's state (photon/scatter.wgsl): per segment a word (SEGMENT_UNTOUCHED between
// updates: gather_mark clears the marks, scatter_apply and scatter_fallback the slots;
// SEGMENT_TOUCHED, set by scatter_touch before gather_mark; or the segment's slot + 2, set by
// gather_mark), then per slot SLOT_WORDS words (segment, samples marched, the change sum's lo
// and hi words), then per slot scatter_samples sample weights (f32 bits, < 0: not gathered).
@group(0) @binding(16) var<storage, read_write> scatter: array<atomic<u32>>;
// The record chunks' list (PhotonUniforms::path_slots): per chunk (pass · chunks_per_pass +
// its index in the pass) the next chunk of its path (CHUNK_NONE: the last), then from
// chunk_counts_at on per pass the chunks taken (more than chunks_per_pass: a path found
// none and was cut short; the host sees it).
@group(0) @binding(17) var<storage, read_write> chunks: array<atomic<u32>>;
// The per-sample photon sums (sample_cache_samples > 0): per pixel and lattice index k, the sum
// of fixed(power · sum_lead() · phase · kernel) over the photons within the radius
// (64-bit fixed point, lo then hi words per channel), the generation it was formed in, and the
// weight its segment's last gather gave it (SAMPLE_WORDS words; sample_weight_word). A segment
// is then Σ_k fixed(f32(P_k) · transport(T_k, σ_k)), so a segment whose opacity changed
// recomposites from its samples' sums instead of gathering its photons again, one whose
// opacity did not from their sums and weights, and a changed photon updates the sums it
// reaches (integer sums, exact).
@group(0) @binding(18) var<storage, read_write> sample_sums: array<atomic<u32>>;
// Per path p, its end and collision historygrams (PhotonPath::end_lo/hi, collisions_lo/hi) as
// words 4p..4p+3, PATH_QUERY_ROW to a row: what `trace_mark` reads of every path in each
// update. llvmpipe reads a storage buffer's words lane by lane behind bounds checks, a
// storage texture's in one gather.
@group(0) @binding(19) var path_queries: texture_storage_2d<r32uint, read_write>;
// Per record slot, its RecordResume (written with the record by photon/trace.wgsl).
@group(0) @binding(20) var<storage, read_write> record_resumes: array<RecordResume>;
const PATH_QUERY_ROW: u32 = 4096u;

fn path_query_texel(p: u32, w: u32) -> vec2<i32> {
    let i = p * 4u + w;
    return vec2<i32>(i32(i % PATH_QUERY_ROW), i32(i / PATH_QUERY_ROW));
}

// Path p's end (xy) and collision (zw) historygrams.
fn path_query_load(p: u32) -> vec4<u32> {
    return vec4<u32>(
        textureLoad(path_queries, path_query_texel(p, 0u)).x,
        textureLoad(path_queries, path_query_texel(p, 1u)).x,
        textureLoad(path_queries, path_query_texel(p, 2u)).x,
        textureLoad(path_queries, path_query_texel(p, 3u)).x,
    );
}

fn path_query_store(p: u32, end: vec2<u32>, collisions: vec2<u32>) {
    textureStore(path_queries, path_query_texel(p, 0u), vec4<u32>(end.x));
    textureStore(path_queries, path_query_texel(p, 1u), vec4<u32>(end.y));
    textureStore(path_queries, path_query_texel(p, 2u), vec4<u32>(collisions.x));
    textureStore(path_queries, path_query_texel(p, 3u), vec4<u32>(collisions.y));
}

const CHUNK_SLOTS: u32 = 4u;
const CHUNK_NONE: u32 = 0xffffffffu;

const SLOT_NONE: u32 = 0xffffffffu;
const SLOT_WORDS: u32 = 8u;
const SEGMENT_UNTOUCHED: u32 = 0u;
const SEGMENT_TOUCHED: u32 = 1u;

const SAMPLE_WORDS: u32 = 8u;
const SAMPLE_NONE: u32 = 0xffffffffu;

// The first word of the photon sum of pixel's lattice sample k (SAMPLE_NONE: not kept; the
// host keeps as many per pixel as a view ray through the box can hold, so with per-sample sums
// on every sample has one).
fn sample_entry(pixel: u32, k: f32) -> u32 {
    if (k >= f32(photon.sample_cache_samples)) {
        return SAMPLE_NONE;
    }
    return (pixel * photon.sample_cache_samples + u32(k)) * SAMPLE_WORDS;
}

fn sample_valid(entry: u32) -> bool {
    return entry != SAMPLE_NONE && atomicLoad(&sample_sums[entry + 6u]) == photon.cache_generation;
}

fn sample_read(entry: u32) -> FixedSum {
    if (entry == SAMPLE_NONE) {
        return FixedSum(vec3<u32>(0u), vec3<u32>(0u));
    }
    var sum = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
    for (var c = 0u; c < 3u; c++) {
        sum.lo[c] = atomicLoad(&sample_sums[entry + c]);
        sum.hi[c] = atomicLoad(&sample_sums[entry + 3u + c]);
    }
    return sum;
}

// Keeps the sum (not its generation: a partial sum of a gather that resumes later keeps the
// validity the entry had when the sample began).
fn sample_keep(entry: u32, sum: FixedSum) {
    if (entry == SAMPLE_NONE) {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        atomicStore(&sample_sums[entry + c], sum.lo[c]);
        atomicStore(&sample_sums[entry + 3u + c], sum.hi[c]);
    }
}

fn sample_write(entry: u32, sum: FixedSum) {
    sample_keep(entry, sum);
    atomicStore(&sample_sums[entry + 6u], photon.cache_generation);
}

// A sample's weight in its segment as the segment's last gather found it (f32 bits):
// transport(T_k, σ_k) where it was gathered, 0 where it was empty (σ ≤ 0), SAMPLE_PAST_CUTOFF
// at the first sample past the segment's transmittance cut-off (the march ended there). Where
// no opacity the segment meets changed, its samples' weights are as before, so a colour edit
// recomposites the segment from sums and weights alone (gather.wgsl, recomposite_from_sums).
fn sample_weight_word(entry: u32) -> u32 {
    return entry + 7u;
}

const SAMPLE_PAST_CUTOFF: f32 = -1.0;

fn sample_set_weight(entry: u32, weight: f32) {
    if (entry != SAMPLE_NONE) {
        atomicStore(&sample_sums[sample_weight_word(entry)], bitcast<u32>(weight));
    }
}

fn sample_forget(entry: u32) {
    if (entry != SAMPLE_NONE) {
        atomicStore(&sample_sums[entry + 6u], 0u);
    }
}

// Adds a 64-bit fixed-point sum (wrapping) to the entry's, atomically per word with a carry.
fn sample_add(entry: u32, sum: FixedSum) {
    for (var c = 0u; c < 3u; c++) {
        let lo = sum.lo[c];
        let hi = sum.hi[c];
        if ((lo | hi) == 0u) {
            continue;
        }
        let old = atomicAdd(&sample_sums[entry + c], lo);
        let carry = select(0u, 1u, old + lo < old);
        // Most terms are small: hi + carry wraps to 0 for a negative one (hi all ones, a
        // carry) and is 0 for a positive one without a carry; adding it would change nothing.
        if (hi + carry != 0u) {
            atomicAdd(&sample_sums[entry + 3u + c], hi + carry);
        }
    }
}

// The factor a photon's term in a per-sample sum starts with: the kernel's normalisation and
// the fixed point's scale (the sample's weight comes in with its transport).
fn sum_lead() -> f32 {
    return photon.kernel_norm * FIXED_ONE;
}

// What a sample's photon sum is weighted by in a segment (sample_weight without the kernel's
// normalisation, which the sum holds): the transmittance to it and the integral of the
// extinction over its step.
fn transport(transmit: f32, sigma: f32) -> f32 {
    return transmit * (1.0 - exp(-sigma * photon.gather_step)) / sigma;
}

// The delta-scatter slot of segment id (SLOT_NONE: none).
fn segment_slot(id: u32) -> u32 {
    let word = atomicLoad(&scatter[id]);
    return select(SLOT_NONE, word - 2u, word >= 2u);
}

// Word w of a delta-scatter slot: 0 its segment, 1 the samples scatter_weights marched, 2..4 and
// 5..7 the lo and hi words of its sum (rgb).
fn slot_word(slot: u32, w: u32) -> u32 {
    return scene.width * scene.height * photon.segments + slot * SLOT_WORDS + w;
}

fn grid_base(grid: u32) -> u32 {
    return select(0u, 2u * photon.cell_count + 1u, grid == GRID_CHANGES);
}

fn sorted_base(grid: u32) -> u32 {
    return select(0u, photon.record_capacity, grid == GRID_CHANGES);
}

// Radiance sums are 64-bit fixed point with 40 fraction bits, per channel (lo, hi words): an
// integer sum does not depend on the order of its terms, so the grid needs no sort, and an
// update can subtract a changed photon's old contribution and add its new one and land on the
// bits a full gather forms. A term x arrives already scaled by 2^40 (FIXED_ONE) and is
// truncated to an integer: its high word, then its low word.
const FIXED_ONE: f32 = 1099511627776.0;

fn fixed_hi(x: vec3<f32>) -> vec3<u32> {
    return vec3<u32>(x * (1.0 / 4294967296.0));
}

// Exact: above 2^32 an f32 is a multiple of 2^9, and so is its remainder below 2^32.
fn fixed_lo(x: vec3<f32>, hi: vec3<u32>) -> vec3<u32> {
    return vec3<u32>(x - vec3<f32>(hi) * 4294967296.0);
}

fn fixed_to_f32(lo: vec3<u32>, hi: vec3<u32>) -> vec3<f32> {
    return (vec3<f32>(hi) + vec3<f32>(lo) * (1.0 / 4294967296.0)) * (1.0 / 256.0);
}

// Linear invocation index of a 1D problem dispatched as a 2D grid of 64-wide workgroups.
fn linear_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.y * groups.x * 64u + gid.x;
}

// Historygram bit of data value v: d(x) = 1 << floor(x·(p − 1)), p = 64, as (lo, hi) words.
fn hist_bit(v: f32) -> vec2<u32> {
    let bin = min(u32(clamp(v, 0.0, 1.0) * f32(HIST_BINS - 1u)), HIST_BINS - 1u);
    if (bin < 32u) {
        return vec2<u32>(1u << bin, 0u);
    }
    return vec2<u32>(0u, 1u << (bin - 32u));
}

fn hist_hits_rejection_query(lo: u32, hi: u32) -> bool {
    return ((lo & photon.rejection_query_lo) | (hi & photon.rejection_query_hi)) != 0u;
}

fn hist_hits_opacity_query(lo: u32, hi: u32) -> bool {
    return ((lo & photon.opacity_query_lo) | (hi & photon.opacity_query_hi)) != 0u;
}

// Whether the edit may change what happened at collisions in these bins: their albedo, or
// whether they were collisions at all (the collision query).
fn hist_hits_collision_query(lo: u32, hi: u32) -> bool {
    return ((lo & photon.collision_query_lo) | (hi & photon.collision_query_hi)) != 0u;
}

// Squared distance from p to the cube of edge `edge` whose lowest corner is `lo` (0 inside).
fn cube_distance2(lo: vec3<f32>, edge: f32, p: vec3<f32>) -> f32 {
    let gap = max(max(lo - p, p - (lo + vec3<f32>(edge))), vec3<f32>(0.0));
    return dot(gap, gap);
}

// Bits first..=last of a 64-bit mask as (lo, hi).
fn range_mask(first: u32, last: u32) -> vec2<u32> {
    var m = vec2<u32>(0u);
    for (var b = first; b <= last; b++) {
        if (b < 32u) {
            m.x |= 1u << b;
        } else {
            m.y |= 1u << (b - 32u);
        }
    }
    return m;
}

// Spatial historygram bin (per axis, 64 over the box) of world position p.
fn spatial_bins(p: vec3<f32>) -> vec3<u32> {
    let u = (p - scene.box_min) / (scene.box_max - scene.box_min);
    return min(vec3<u32>(clamp(u, vec3<f32>(0.0), vec3<f32>(1.0)) * 64.0), vec3<u32>(63u));
}

// Hash-grid cell of world position p (cell edge = radius).
fn grid_cell3(p: vec3<f32>) -> vec3<i32> {
    let c = vec3<i32>(floor((p - scene.box_min) / photon.radius));
    return clamp(c, vec3<i32>(0), vec3<i32>(photon.grid_dims) - 1);
}

// Dirty-cell grid (SPATIAL_CELLS, and every delta gather): half the hash cell's edge, so that
// marking the cells within the gather radius of a changed photon (mark_cells) covers its
// reach more tightly than whole cells.
fn dirty_cell3(p: vec3<f32>) -> vec3<i32> {
    let c = vec3<i32>(floor((p - scene.box_min) / (0.5 * photon.radius)));
    return clamp(c, vec3<i32>(0), vec3<i32>(2u * photon.grid_dims) - 1);
}

fn dirty_index(c: vec3<i32>) -> u32 {
    let d = 2u * photon.grid_dims;
    return (u32(c.z) * d.y + u32(c.y)) * d.x + u32(c.x);
}

fn grid_index(c: vec3<i32>) -> u32 {
    let d = photon.grid_dims;
    return (u32(c.z) * d.y + u32(c.y)) * d.x + u32(c.x);
}

// The counter word and bit of pixel `pixel`'s changed mark (after the dirty-cell bits).
fn pixel_mark(pixel: u32) -> vec2<u32> {
    let at = COUNTER_DIRTY + (8u * photon.cell_count + 31u) / 32u;
    return vec2<u32>(at + pixel / 32u, 1u << (pixel % 32u));
}

// An update's marks passes: marks a pixel one of whose segments the update computes, so that
// its composite runs (`composite` with COMPOSITE_CHANGED); the update clears the counters
// first. A bit already set is not written again.
fn mark_pixel_changed(pixel: u32) {
    let m = pixel_mark(pixel);
    if ((atomicLoad(&counters[m.x]) & m.y) == 0u) {
        atomicOr(&counters[m.x], m.y);
    }
}

// Data value at world position p (trilinear, shared/volume.wgsl).
fn data_at(p: vec3<f32>) -> f32 {
    return sample_volume((p - scene.box_min) / (scene.box_max - scene.box_min));
}

// Below this transmittance inside a segment its march stops.
const SEGMENT_T_CUTOFF: f32 = 1e-4;

fn pixel_ray(pixel: u32) -> vec3<f32> {
    let px = vec2<f32>(f32(pixel % scene.width) + 0.5, f32(pixel / scene.width) + 0.5);
    return camera_ray_dir(scene, px);
}

// The box interval [ta, tb) of segment s of a ray that meets the box in hit.
fn segment_bounds(hit: vec2<f32>, s: u32) -> vec2<f32> {
    let len = (hit.y - hit.x) / f32(photon.segments);
    let ta = hit.x + f32(s) * len;
    var tb = hit.x + f32(s + 1u) * len;
    if (s + 1u == photon.segments) {
        tb = hit.y;
    }
    return vec2<f32>(ta, tb);
}

// Lattice index of the first sample that can fall in [ta, tb), less one, so that the
// membership of a sample is decided by the same comparison in neighbouring segments.
fn first_lattice_index(hit: vec2<f32>, ta: f32, jitter: f32) -> f32 {
    return max(0.0, ceil((ta - hit.x) / photon.gather_step - jitter) - 1.0);
}

fn pixel_jitter(pixel: u32) -> f32 {
    var rng = rng_new(scene.seed, pixel, 0xffffffffu);
    return rng_next(&rng);
}

// A 64-bit fixed-point sum per channel (see fixed_hi).
struct FixedSum {
    lo: vec3<u32>,
    hi: vec3<u32>,
}

// sum + x or sum − x, with x truncated to fixed point, wrapping (only the final sum is known
// to be non-negative).
fn accumulate(sum: FixedSum, x: vec3<f32>, negative: bool) -> FixedSum {
    let x_hi = fixed_hi(x);
    let x_lo = fixed_lo(x, x_hi);
    if (negative) {
        let borrow = select(vec3<u32>(0u), vec3<u32>(1u), sum.lo < x_lo);
        return FixedSum(sum.lo - x_lo, sum.hi - x_hi - borrow);
    }
    let lo = sum.lo + x_lo;
    let carry = select(vec3<u32>(0u), vec3<u32>(1u), lo < x_lo);
    return FixedSum(lo, sum.hi + x_hi + carry);
}

// What a sample's photons are weighted by: the transmittance to it, the integral of the
// extinction over its step, the kernel's normalisation, and the fixed point's scale.
fn sample_weight(transmit: f32, sigma: f32) -> f32 {
    return transmit * (1.0 - exp(-sigma * photon.gather_step)) / sigma * photon.kernel_norm * FIXED_ONE;
}
