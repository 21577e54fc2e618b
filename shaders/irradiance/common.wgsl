// Technique `irradiance` (Khlebnikov et al. 2014): shared declarations of its passes. Monte
// Carlo volume rendering in the style of Exposure Render, whose first scattering event reads
// the irradiance from a cache of entries with ellipsoidal influence zones, stored in a
// multi-reference octree. Every pass binds the estimator bindings (0–5) and these (6–16), one
// bind group layout. Rust twin: server/engine/src/techniques/irradiance/gpu.rs.

#import shared/common
#import shared/volume
#import shared/scene
#import shared/macrocell
#import shared/tracking
#import shared/march
#import shared/lights
#import shared/path

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
    pad0: u32,
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
// Irradiance samples of that fresh estimate.
const VALIDATION_SAMPLES: u32 = 8u;
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

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var<storage, read> tf_lut: array<vec4<f32>>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(7) var<uniform> dispatch: DispatchInfo;
@group(0) @binding(8) var<storage, read_write> entries: array<CacheEntry>;
// Six radii (f32 bits, world units) per entry, in half-axis order; shrunk with atomicMin.
@group(0) @binding(9) var<storage, read_write> radii: array<atomic<u32>>;
// Nodes (child, first reference, references, depth; 4 words each), then the references.
@group(0) @binding(10) var<storage, read> octree: array<u32>;
// Counters, then per node and per block: the claim of this frame and whether it is locked.
@group(0) @binding(11) var<storage, read_write> words: array<atomic<u32>>;
// Per pixel: the last cache miss's position (xyz) and the sum of squared luminance (w).
@group(0) @binding(12) var<storage, read_write> pixel_aux: array<vec4<f32>>;
// The blocks to render, then (at priority_offset) each block's priority (f32 bits).
@group(0) @binding(13) var<storage, read_write> blocks: array<u32>;
@group(0) @binding(14) var<storage, read_write> requests: array<Request>;
// Data bins each macrocell's values can fall in (lo, hi words).
@group(0) @binding(15) var<storage, read> cell_bins: array<vec2<u32>>;
// Per entry: its centre and a radius its zone lies within (a lookup rejects far entries
// without reading them; the update only shrinks zones, so the radius stays an upper bound).
@group(0) @binding(16) var<storage, read_write> bounds: array<vec4<f32>>;

// The hooks of shared/path.wgsl: a cache entry's estimate records what it depended on.
var<private> recording: bool = false;
var<private> recorded_opacity: vec2<u32>;
var<private> recorded_colour: vec2<u32>;
// Shadow rays of the entry's own point march (low variance); those of its multiply
// scattered paths are ratio tracked.
var<private> marched_shadows: bool = false;

fn sampled_historygrams() -> bool {
    return (params.flags & FLAG_SAMPLED_HISTORYGRAMS) != 0u;
}

fn cell_index(cell: vec3<u32>) -> u32 {
    return (cell.z * scene.cell_dims.y + cell.y) * scene.cell_dims.x + cell.x;
}

// Every macrocell a ray enters: all values it holds, or (sampled historygrams) only where
// nothing in it is visible now, since no sample there is taken.
fn track_visit(cell: vec3<u32>) {
    if (recording && (!sampled_historygrams() || cell_is_empty(cell))) {
        recorded_opacity |= cell_bins[cell_index(cell)];
    }
}

fn track_sample(p: vec3<f32>) {
    if (recording && sampled_historygrams()) {
        recorded_opacity |= bin_mask(value_bin(sample_volume(box_relative(p))));
    }
}

fn track_vertex(p: vec3<f32>) {
    if (recording) {
        recorded_colour |= bin_mask(value_bin(sample_volume(box_relative(p))));
    }
}

// Shadow rays of shared/lights.wgsl.
fn shadow_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, rng: ptr<function, Rng>) -> f32 {
    if (marched_shadows) {
        return recorded_march(p, dir, t_max, rng_next(rng));
    }
    return ratio_transmittance(p, dir, t_max, rng);
}

// Transmittance by the jittered march of shared/march.wgsl (same step and cut-off), recording what
// it sampled through the hooks.
fn recorded_march(p: vec3<f32>, dir: vec3<f32>, t_max: f32, jitter: f32) -> f32 {
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t_end = min(hit.y, t_max);
    let step = scene.step * SHADOW_STEP_SCALE;
    var tau = 0.0;
    var k = 0.0;
    var last_cell = vec3<u32>(0xffffffffu);
    loop {
        let t = hit.x + (k + jitter) * step;
        if (t >= t_end) {
            break;
        }
        let x = p + dir * t;
        let cell = cell_of(box_relative(x));
        if (any(cell != last_cell)) {
            track_visit(cell);
            last_cell = cell;
        }
        if (cell_is_empty(cell)) {
            k = skip_empty_cell(p, dir, cell, hit.x, step, jitter, k);
            continue;
        }
        track_sample(x);
        tau += medium_at(x).a * step;
        if (tau > SHADOW_TAU_CUTOFF) {
            return 0.0;
        }
        k += 1.0;
    }
    return exp(-tau);
}

// Bin of data value v: floor(v·(p − 1)) with p = 64 (server/engine/src/tf.rs value_bin).
fn value_bin(v: f32) -> u32 {
    return min(u32(clamp(v, 0.0, 1.0) * 63.0), 63u);
}

fn bin_mask(bin: u32) -> vec2<u32> {
    if (bin < 32u) {
        return vec2<u32>(1u << bin, 0u);
    }
    return vec2<u32>(0u, 1u << (bin - 32u));
}

fn luminance(c: vec3<f32>) -> f32 {
    return dot(c, vec3<f32>(0.2126, 0.7152, 0.0722));
}

// Δ for an entry centred at p: params.delta, or less where a mean free path is shorter.
fn entry_delta(p: vec3<f32>) -> f32 {
    let sigma_t = medium_at(p).a;
    if (params.delta_free_paths <= 0.0 || sigma_t <= 0.0) {
        return params.delta;
    }
    return clamp(params.delta_free_paths / sigma_t, 0.25 * params.voxel, params.delta);
}

// Direction of the extinction gradient at p by central differences one voxel apart: the axis
// an entry's local frame is oriented along (the paper's §4.2). +z where the medium is flat.
fn extinction_normal(p: vec3<f32>) -> vec3<f32> {
    let h = params.voxel;
    let gradient = vec3<f32>(
        medium_at(p + vec3<f32>(h, 0.0, 0.0)).a - medium_at(p - vec3<f32>(h, 0.0, 0.0)).a,
        medium_at(p + vec3<f32>(0.0, h, 0.0)).a - medium_at(p - vec3<f32>(0.0, h, 0.0)).a,
        medium_at(p + vec3<f32>(0.0, 0.0, h)).a - medium_at(p - vec3<f32>(0.0, 0.0, h)).a,
    );
    let len = length(gradient);
    if (len <= 1e-12) {
        return vec3<f32>(0.0, 0.0, 1.0);
    }
    return gradient / len;
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

// How far along one half-axis an entry's zone may reach before the medium differs from its
// centre's: the extrapolation's log-irradiance gradient is the centre's, the true one changes
// with the extinction, so the walk stops where ∫|σt(x) − σt(x0)| dx exceeds ln(1 + ε) (a
// zone in soft tissue does not reach into the bone beside it). Half-voxel steps.
fn extinction_reach(x0: vec3<f32>, axis: vec3<f32>, limit: f32) -> f32 {
    let sigma0 = medium_at(x0).a;
    let tolerance = log(1.0 + params.epsilon);
    let step = 0.5 * params.voxel;
    var excess = 0.0;
    var s = 0.0;
    loop {
        if (s >= limit) {
            return limit;
        }
        s += step;
        excess += abs(medium_at(x0 + axis * s).a - sigma0) * step;
        if (excess > tolerance) {
            return max(s - step, params.min_radius);
        }
    }
    return limit;
}

fn radius_of(entry: u32, half_axis: u32) -> f32 {
    return bitcast<f32>(atomicLoad(&radii[entry * 6u + half_axis]));
}

// Coordinates of world point x in entry e's local frame, and the half-axes of its octant.
struct Local {
    l: vec3<f32>,
    half_axes: vec3<u32>,
}

fn local_coordinates(entry: CacheEntry, x: vec3<f32>) -> Local {
    let frame = orthonormal_basis(entry.normal);
    let d = x - entry.position;
    let l = vec3<f32>(dot(d, frame[0]), dot(d, frame[1]), dot(d, frame[2]));
    let half_axes = vec3<u32>(
        select(0u, 1u, l.x < 0.0),
        select(2u, 3u, l.y < 0.0),
        select(4u, 5u, l.z < 0.0),
    );
    return Local(l, half_axes);
}

// What one entry predicts at x: its weight w(d) = 3d² − 2d³ (zero outside its zone) and the
// log of the extrapolated irradiance (Eq. 7 with the barycentric coefficient of Eq. 8).
struct Prediction {
    weight: f32,
    log_irradiance: vec3<f32>,
}

fn entry_predict(e: u32, x: vec3<f32>) -> Prediction {
    let none = Prediction(0.0, vec3<f32>(0.0));
    let bound = bounds[e];
    let offset = x - bound.xyz;
    if (dot(offset, offset) >= bound.w * bound.w) {
        return none;
    }
    let entry = entries[e];
    let local = local_coordinates(entry, x);
    let h = local.half_axes;
    let r = vec3<f32>(radius_of(e, h.x), radius_of(e, h.y), radius_of(e, h.z));
    if (any(r <= vec3<f32>(0.0))) {
        return none;
    }
    let l = local.l;
    // ‖x‖ / r(x) with the ellipsoid radius r(x) = ‖x‖ (Σ x_i² / r_i²)^−½ of the octant.
    let q = dot(l * l, 1.0 / (r * r));
    if (q >= 1.0) {
        return none;
    }
    let dist = length(l);
    let a = abs(l);
    let a_sum = a.x + a.y + a.z;
    var sigma = vec4<f32>(0.0);
    if (a_sum > 0.0) {
        sigma = (a.x * entry.sigma[h.x] + a.y * entry.sigma[h.y] + a.z * entry.sigma[h.z]) / a_sum;
    }
    // Fig. 4: beyond the radius the interpolated coefficient gives, the entry is not used.
    if (dist > validity_radius(sigma.w, entry.delta)) {
        return none;
    }
    let d = 1.0 - sqrt(q);
    let weight = d * d * (3.0 - 2.0 * d);
    let log_e = log(max(entry.irradiance, vec3<f32>(IRRADIANCE_FLOOR))) - sigma.rgb * dist;
    return Prediction(weight, log_e);
}

// The cache's answer at x (Eq. 11: the log-space weighted average of every entry whose zone
// holds x; weight 0 when none does), and the deepest octree node on x's branch (the lock of
// object-space locking).
struct Lookup {
    weight: f32,
    irradiance: vec3<f32>,
    node: u32,
}

// Child of an octree node (children are stored together, in x, y, z bit order) that holds x,
// and its cube.
struct Descent {
    child: u32,
    lo: vec3<f32>,
}

fn descend(first_child: u32, lo: vec3<f32>, half: f32, x: vec3<f32>) -> Descent {
    let centre = lo + vec3<f32>(half);
    let upper = x >= centre;
    let octant = select(0u, 1u, upper.x) + select(0u, 2u, upper.y) + select(0u, 4u, upper.z);
    return Descent(first_child + octant, select(lo, centre, upper));
}

fn cache_lookup(x: vec3<f32>) -> Lookup {
    var node = 0u;
    var lo = params.root_min;
    var edge = params.root_edge;
    var weight_sum = 0.0;
    var log_sum = vec3<f32>(0.0);
    for (var depth = 0u; depth < MAX_DEPTH; depth++) {
        let base = node * 4u;
        let first = params.refs_offset + octree[base + 1u];
        let count = octree[base + 2u];
        for (var i = 0u; i < count; i++) {
            let p = entry_predict(octree[first + i], x);
            weight_sum += p.weight;
            log_sum += p.weight * p.log_irradiance;
        }
        let child = octree[base];
        if (child == 0u) {
            break;
        }
        edge *= 0.5;
        let next = descend(child, lo, edge, x);
        node = next.child;
        lo = next.lo;
    }
    var irradiance = vec3<f32>(0.0);
    if (weight_sum > 0.0) {
        irradiance = exp(log_sum / weight_sum);
    }
    return Lookup(weight_sum, irradiance, node);
}

fn uniform_sphere(u1: f32, u2: f32) -> vec3<f32> {
    let z = 1.0 - 2.0 * u1;
    let s = sqrt(max(0.0, 1.0 - z * z));
    let phi = 2.0 * PI * u2;
    return vec3<f32>(s * cos(phi), s * sin(phi), z);
}

fn traced_direct() -> bool {
    return (params.flags & FLAG_TRACED_DIRECT) != 0u;
}

// One sample of the irradiance E(y) = ∫ L(y, ω) dω (Eq. 4) that entries hold: the directional
// and point lights by next-event estimation with marched shadow rays (not with
// FLAG_TRACED_DIRECT), everything else (the environment and, with more than one bounce,
// light scattered by the medium) along one uniformly chosen direction, weight 4π.
fn irradiance_sample(y: vec3<f32>, rng: ptr<function, Rng>) -> vec3<f32> {
    marched_shadows = true;
    var e = vec3<f32>(0.0);
    if (!traced_direct()) {
        e = direct_irradiance(y, rng);
    }
    let u1 = rng_next(rng);
    let u2 = rng_next(rng);
    let w = uniform_sphere(u1, u2);
    if (params.bounces <= 1u) {
        if (any(scene.env_radiance > vec3<f32>(0.0))) {
            e += 4.0 * PI * scene.env_radiance * shadow_transmittance(y, w, 1e30, rng);
        }
        marched_shadows = false;
    } else {
        marched_shadows = false;
        e += 4.0 * PI * trace_radiance(y, w, vec3<f32>(1.0), 0u, params.bounces - 1u, rng);
    }
    return e;
}
