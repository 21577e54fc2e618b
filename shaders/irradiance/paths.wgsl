// Technique `irradiance`: the paths its passes trace. The hooks of shared/path.wgsl (a cache
// entry's estimate records the data bins it depended on), its shadow rays, and one irradiance
// sample of an entry. A pass that imports this declares `scene`, `volume_tex`, `tf_lut`, `lights`,
// `cell_max_opacity`, `params` and `cell_bins` (irradiance/common.wgsl lists the bindings).

#import shared/volume
#import shared/macrocell
#import shared/tracking
#import shared/march
#import shared/lights
#import shared/path
#import irradiance/common

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
        tau += extinction_at(x) * step;
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

fn uniform_sphere(u1: f32, u2: f32) -> vec3<f32> {
    let z = 1.0 - 2.0 * u1;
    let s = sqrt(max(0.0, 1.0 - z * z));
    let phi = 2.0 * PI * u2;
    return vec3<f32>(s * cos(phi), s * sin(phi), z);
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
