// Technique `irradiance` (Khlebnikov et al. 2014): what its five passes share. Monte Carlo
// volume rendering in the style of Exposure Render, whose first scattering event reads the
// irradiance from a cache of entries with ellipsoidal influence zones, stored in a
// multi-reference octree. Rust twin: server/engine/src/techniques/irradiance/gpu.rs.
//
// - Here: the structs the passes bind, flags, counters, and helpers that read only `scene` and
//   `params` (every pass declares both). irradiance/cache.wgsl: the cache lookup;
//   irradiance/paths.wgsl: the path tracer's hooks and an entry's irradiance samples.
// - Bindings: each pass declares the ones it reads, always under these numbers and access
//   modes, and gets a bind group layout of exactly those (gpu.rs `binding`, `Pass::bindings`):
//   0–5 the estimator's: scene, volume_tex, tf_lut, lights, accum, cell_max_opacity
//       (server/engine/src/passes/estimator.rs);
//   6   params: IrradianceParams;
//   7   dispatch: DispatchInfo, one per dispatch, at a dynamic offset;
//   8   entries: array<CacheEntry>;
//   9   radii: six radii (f32 bits, world units) per entry, in half-axis order; shrunk with
//       atomicMin;
//   10  octree: nodes (child, first reference, references, depth; 4 words each), then the
//       references;
//   11  words: counters, then per node and per block the claim of this frame and whether it
//       is locked;
//   12  pixel_aux: per pixel, the last cache miss's position (xyz) and the sum of squared
//       luminance (w);
//   13  blocks: the blocks to render, then (at priority_offset) each block's priority (f32
//       bits);
//   14  requests: array<Request>;
//   15  cell_bins: the data bins each macrocell's values can fall in (lo, hi words);
//   16  bounds: per entry, its centre and a radius its zone lies within (a lookup rejects far
//       entries without reading them; the update only shrinks zones, so the radius stays an
//       upper bound).

#import shared/common
#import shared/scene

struct IrradianceParams {
    // The octree's root cube.
    root_min: vec3<f32>,
    root_edge: f32,
    // Δ (world units): offset of the six extra estimation points.
    delta: f32,
    // γ: accepted relative error of an irradiance estimate (Eq. 5).
    gamma: f32,
    // ε: accepted relative extrapolation error at a zone's edge (Eq. 9–10).
    epsilon: f32,
    // Influence-zone radius bounds (world units).
    min_radius: f32,
    max_radius: f32,
    // Relative difference between overlapping predictions that the update resolves.
    update_threshold: f32,
    // Frames rendered since the session started (randomizes claims).
    frame: u32,
    // FLAG_* bits.
    flags: u32,
    // 16 × 8 pixel blocks across and down the image, and in all.
    blocks_x: u32,
    blocks_y: u32,
    block_count: u32,
    // Octree nodes in use.
    node_count: u32,
    // Word offsets: references in `octree`; claims and locks in `words`.
    refs_offset: u32,
    node_claim_offset: u32,
    node_held_offset: u32,
    block_claim_offset: u32,
    block_held_offset: u32,
    entry_capacity: u32,
    // Most cache entries being created at once, and how many are (CPU's last reading).
    max_pending: u32,
    pending: u32,
    // Samples per estimation point before the error criterion may stop, and at most.
    min_samples: u32,
    max_samples: u32,
    // Most scattering events on a camera path (1: single scattering, as in the paper).
    bounces: u32,
    // Word offset of the block priorities in `blocks`.
    priority_offset: u32,
    // Smallest voxel edge (world units).
    voxel: f32,
    // Irradiance (luminance) below which Eq. 5's error bound stops shrinking: an absolute
    // floor for dark regions, a fraction of the scene's brightest unshadowed irradiance.
    dark_floor: f32,
    // Δ of an entry is at most this many mean free paths at its centre (0: always delta): in
    // dense media the irradiance changes within a free path, far below two voxels.
    delta_free_paths: f32,
    // Scattering events per camera sample along the marched view ray (FLAG_MARCHED_VIEW).
    view_picks: u32,
    // Validation rounds (DispatchInfo.validate): the relative disagreement beyond a fresh
    // estimate's 95% interval that shrinks an entry, and that estimate's samples.
    validation_threshold: f32,
    validation_samples: u32,
    pad0: u32,
    pad1: u32,
}

// A cache entry: the irradiance at `position` and, per half-axis of its local frame (+t, −t,
// +b, −b, +n, −n, with n along the extinction gradient), the virtual extinction coefficient
// (Eq. 6) it extrapolates with: rgb per channel, w for the luminance (which gives the zone's
// radii, Eq. 9–10). The radii themselves live in `radii` (the update shrinks them).
struct CacheEntry {
    position: vec3<f32>,
    key: u32,
    normal: vec3<f32>,
    samples: u32,
    irradiance: vec3<f32>,
    // Historygrams of the data bins the estimate depended on: through extinction (every
    // macrocell its rays crossed) and through albedo (the vertices its paths scattered at).
    opacity_lo: u32,
    sigma: array<vec4<f32>, 6>,
    opacity_hi: u32,
    colour_lo: u32,
    colour_hi: u32,
    // The entry's Δ (world units).
    delta: f32,
}

// A cache entry being created: per estimation point (the centre, then ± Δ along t, b, n), the
// rgb sum of its irradiance samples and (w) the sum of their squared luminance.
struct Request {
    position: vec3<f32>,
    key: u32,
    normal: vec3<f32>,
    // The octree node or image block it locks.
    lock: u32,
    sums: array<vec4<f32>, 7>,
    count: u32,
    state: u32,
    opacity_lo: u32,
    opacity_hi: u32,
    colour_lo: u32,
    colour_hi: u32,
    delta: f32,
    // FLAG_TRACED_DIRECT: the sum of the centre's direct irradiance luminance (the lights'
    // share the render pass traces itself), which only sets Eq. 5's bound.
    direct_sum: f32,
    // The finished entry (state REQUEST_DONE).
    entry: CacheEntry,
}

// One dispatch's share of a frame (bound with a dynamic offset).
struct DispatchInfo {
    // First element of `blocks` this dispatch renders.
    first: u32,
    count: u32,
    // Round of the creation or update procedure (random numbers).
    round: u32,
    // Update dispatches: 1 for a validation round (its own budget, beyond the paper): the
    // update pass only checks the entries at its points against fresh estimates there.
    validate: u32,
}

const FLAG_CACHE: u32 = 1u;
const FLAG_SCREEN_LOCKING: u32 = 2u;
const FLAG_NO_CREATION: u32 = 4u;
// Historygrams of the values sampled (and of the cells skipped as empty) instead of the
// whole value range of every macrocell crossed.
const FLAG_SAMPLED_HISTORYGRAMS: u32 = 8u;
// Camera rays pick their scattering event along a jittered march (shared/march.wgsl) instead of
// delta tracking it.
const FLAG_MARCHED_VIEW: u32 = 16u;
// The update also checks the entries holding its point against a fresh estimate there.
const FLAG_VALIDATE_HITS: u32 = 32u;
// Irradiance samples of that fresh estimate (validation rounds: params.validation_samples).
const VALIDATION_SAMPLES: u32 = 8u;
// Validation rounds (DispatchInfo.validate) draw their points with a salt of their own.
const VALIDATE_SALT: u32 = 0x2c1b3c6du;
// The render pass traces the directional and point lights' direct light at every event (a
// shadow ray each), and entries hold only the rest of the irradiance (the environment and light
// scattered by the medium): no shadow edge is ever interpolated.
const FLAG_TRACED_DIRECT: u32 = 64u;

const REQUEST_PENDING: u32 = 0u;
const REQUEST_DONE: u32 = 1u;

// Counters at the start of `words`.
const COUNTER_HITS: u32 = 0u;
const COUNTER_MISSES: u32 = 1u;
const COUNTER_PENDING: u32 = 2u;
const COUNTER_ENTRIES: u32 = 3u;
const COUNTER_CREATED: u32 = 4u;
const COUNTER_ISSUED: u32 = 5u;
const COUNTER_DROPPED: u32 = 6u;
const COUNTER_REDUCTIONS: u32 = 7u;
const COUNTER_LOST: u32 = 8u;

const NO_CLAIM: u32 = 0xffffffffu;
// Octree nodes along one branch at most.
const MAX_DEPTH: u32 = 16u;
// Irradiance below this is treated as this (the log-space average needs E > 0).
const IRRADIANCE_FLOOR: f32 = 1e-8;
// Entries evaluated by one update sample at most.
const MAX_OVERLAP: u32 = 16u;

const CREATE_SALT: u32 = 0x5bd1e995u;
const UPDATE_SALT: u32 = 0x68e31da4u;

fn cell_index(cell: vec3<u32>) -> u32 {
    return (cell.z * scene.cell_dims.y + cell.y) * scene.cell_dims.x + cell.x;
}

fn luminance(c: vec3<f32>) -> f32 {
    return dot(c, vec3<f32>(0.2126, 0.7152, 0.0722));
}

// The validity radius of Eq. 9–10 for a virtual extinction coefficient along one axis: the
// distance at which the extrapolation from E0 differs by ε from E_Δ, i.e. Δ + c/|σ| with
// c = ln(1 + ε) where the irradiance grows and −ln(1 − ε) where it falls; clamped.
fn validity_radius(sigma: f32, delta: f32) -> f32 {
    var r = params.max_radius;
    let magnitude = abs(sigma);
    if (magnitude > 0.0) {
        let c = select(-log(1.0 - params.epsilon), log(1.0 + params.epsilon), sigma < 0.0);
        r = min(delta + c / magnitude, params.max_radius);
    }
    return max(r, params.min_radius);
}

fn traced_direct() -> bool {
    return (params.flags & FLAG_TRACED_DIRECT) != 0u;
}
