// Technique `manylight`, pass 1: virtual lights. One invocation per light path (Weber et al.
// 2013, §3.1): a light chosen by power, an emitted ray (directional: a disk covering the
// volume's bounding sphere; point: a uniform direction; environment: an inward cosine-weighted
// ray from the bounding sphere), then delta tracking (fixed majorant) to each real collision, where a virtual
// light is stored with the path's power × albedo (before the 1/paths normalisation, which
// the gather applies), Russian roulette on the throughput, and Henyey-Greenstein scattering.
// Each path writes `max_bounces` slots of a batch's scratch buffer (unused ones with zero
// power); the CPU keeps whole paths in order until N virtual lights are stored, so the set is
// the same on every run ("spawn paths until N virtual lights"). Each path also records its
// historygrams (VirtualLight), so that a TF edit retraces only the paths it can change; with
// a work list, exactly those paths are traced again (the same random numbers per path).
// Rust twin: server/engine/src/techniques/manylight/gpu.rs.

#import shared/tracking
#import manylight/common

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> ml: ManylightParams;
@group(0) @binding(10) var<storage, read_write> scratch: array<VirtualLight>;
@group(0) @binding(12) var<storage, read> work_list: array<u32>;

// The data bins of every value this path's flights read (tentative collisions and the
// optical-depth march), or with macrocell majorants of every cell they crossed.
var<private> opacity_bins: vec2<u32>;

// The tracking hook (shared/tracking.wgsl): a macrocell majorant depends on every bin of the cell.
fn track_visit(cell: vec3<u32>) {
    opacity_bins |= cell_bin_bits(cell);
}

// Tentative collisions add nothing: their cells' bins are recorded.
fn track_sample(p: vec3<f32>) {}

// Delta tracking against the fixed majorant density_scale · 1 (opacity ≤ 1): unlike the
// macrocell majorants (shared/tracking.wgsl), it does not depend on the TF, so the path depends on
// the TF only through the values it reads, which opacity_bins records. (A few more null
// collisions per path; light paths are few.)
fn delta_track_fixed(origin: vec3<f32>, dir: vec3<f32>, t0: f32, t1: f32, rng: ptr<function, Rng>) -> vec2<f32> {
    let majorant = scene.density_scale;
    if (majorant <= 0.0) {
        return vec2<f32>(t1, 0.0);
    }
    var t = t0;
    loop {
        t += -log(1.0 - rng_next(rng)) / majorant;
        if (t >= t1) {
            return vec2<f32>(t1, 0.0);
        }
        let v = sample_volume(box_relative(origin + dir * t));
        opacity_bins |= value_bin_bits(v);
        if (rng_next(rng) * majorant < classify_opacity(v) * scene.density_scale) {
            return vec2<f32>(t, 1.0);
        }
    }
    return vec2<f32>(t1, 0.0);
}

fn uniform_direction(u1: f32, u2: f32) -> vec3<f32> {
    let z = 1.0 - 2.0 * u1;
    let r = sqrt(max(0.0, 1.0 - z * z));
    let phi = 2.0 * PI * u2;
    return vec3<f32>(r * cos(phi), r * sin(phi), z);
}

// Optical depth per unit density scale along origin + t·dir for t in [t0, t1] (midpoint rule
// at the shadow step), for re-weighting under density-scale edits.
fn unit_optical_depth(origin: vec3<f32>, dir: vec3<f32>, t0: f32, t1: f32) -> f32 {
    let step = scene.step * 2.0;
    let full = u32(max(0.0, floor((t1 - t0) / step)));
    var tau = 0.0;
    for (var k = 0u; k < full; k++) {
        let v = sample_volume(box_relative(origin + dir * (t0 + (f32(k) + 0.5) * step)));
        opacity_bins |= value_bin_bits(v);
        tau += classify_opacity(v);
    }
    tau *= step;
    // The last partial step.
    let covered = f32(full) * step;
    let rest = t1 - t0 - covered;
    if (rest > 0.0) {
        let v = sample_volume(box_relative(origin + dir * (t0 + covered + 0.5 * rest)));
        opacity_bins |= value_bin_bits(v);
        tau += classify_opacity(v) * rest;
    }
    return tau;
}

fn luminance(c: vec3<f32>) -> f32 {
    return dot(c, vec3<f32>(0.2126, 0.7152, 0.0722));
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    var path = ml.first_path + gid.x;
    if (ml.list_count > 0u) {
        if (gid.x >= ml.list_count) {
            return;
        }
        path = work_list[gid.x];
    }
    opacity_bins = vec2<u32>(0u);
    var colour_bins = vec2<u32>(0u);
    var rng = rng_new(ml.seed, path, 0x7f4a7c15u);
    let center = 0.5 * (scene.box_min + scene.box_max);
    let radius = 0.5 * length(scene.box_max - scene.box_min);
    let disk_area = PI * radius * radius;

    // Emitted power of every light, and one chosen in proportion to it.
    let env_power = scene.env_radiance * PI * 4.0 * PI * radius * radius;
    var total = luminance(env_power);
    for (var i = 0u; i < scene.light_count; i++) {
        let l = lights[i];
        total += luminance(select(l.color * 4.0 * PI, l.color * disk_area, l.kind == LIGHT_DIRECTIONAL));
    }
    var origin = center;
    var dir = vec3<f32>(0.0, 0.0, 1.0);
    var power = vec3<f32>(0.0);
    if (total > 0.0) {
        var pick = rng_next(&rng) * total;
        let u1 = rng_next(&rng);
        let u2 = rng_next(&rng);
        let u3 = rng_next(&rng);
        let u4 = rng_next(&rng);
        var chosen = false;
        for (var i = 0u; i < scene.light_count; i++) {
            let l = lights[i];
            let p = select(l.color * 4.0 * PI, l.color * disk_area, l.kind == LIGHT_DIRECTIONAL);
            let lum = luminance(p);
            if (!chosen && lum > 0.0 && pick < lum) {
                chosen = true;
                power = p * (total / lum);
                if (l.kind == LIGHT_DIRECTIONAL) {
                    dir = normalize(l.vector);
                    let basis = orthonormal_basis(dir);
                    let r = radius * sqrt(u1);
                    let phi = 2.0 * PI * u2;
                    origin = center - dir * 2.0 * radius + basis * vec3<f32>(r * cos(phi), r * sin(phi), 0.0);
                } else {
                    origin = l.vector;
                    dir = uniform_direction(u1, u2);
                }
            }
            pick -= lum;
        }
        if (!chosen) {
            // The environment: a point on the bounding sphere, a cosine-weighted inward ray.
            let lum = luminance(env_power);
            power = env_power * (total / max(lum, 1e-20));
            let n = uniform_direction(u1, u2);
            origin = center + n * radius;
            let r = sqrt(u3);
            let phi = 2.0 * PI * u4;
            let local = vec3<f32>(r * cos(phi), r * sin(phi), sqrt(max(0.0, 1.0 - u3)));
            dir = normalize(orthonormal_basis(-n) * local);
        }
    }
    var weight = power;
    var tau = 0.0;
    let start = max(weight.x, max(weight.y, weight.z));
    var alive = start > 0.0;
    for (var k = 0u; k < ml.max_bounces; k++) {
        var vl = VirtualLight(vec3<f32>(0.0), 0.0, vec3<f32>(0.0), 0.0, dir, path, 0u, 0u, 0u, 0u, 0.0, 0u, 0u, 0u);
        if (alive) {
            let hit = intersect_box(origin, dir, scene.box_min, scene.box_max);
            var event = vec2<f32>(0.0, 0.0);
            if (hit.x < hit.y) {
                if (ml.fixed_majorant != 0u) {
                    event = delta_track_fixed(origin, dir, max(hit.x, 0.0), hit.y, &rng);
                } else {
                    event = delta_track(origin, dir, max(hit.x, 0.0), hit.y, &rng);
                }
            }
            if (event.y == 0.0) {
                alive = false;
            } else {
                let p = origin + dir * event.x;
                let value = sample_volume(box_relative(p));
                weight *= classify(value).rgb;
                colour_bins |= value_bin_bits(value);
                tau += unit_optical_depth(origin, dir, max(hit.x, 0.0), event.x);
                vl = VirtualLight(p, tau, weight, f32(k + 1u), dir, path, 0u, 0u, 0u, 0u, value, 0u, 0u, 0u);
                // Roulette on the throughput relative to the emitted power.
                let survive = min(1.0, max(weight.x, max(weight.y, weight.z)) / start);
                if (rng_next(&rng) >= survive) {
                    alive = false;
                } else {
                    weight /= survive;
                    let u1 = rng_next(&rng);
                    let u2 = rng_next(&rng);
                    dir = sample_hg(dir, scene.g, u1, u2);
                    origin = p;
                }
            }
        }
        scratch[gid.x * ml.max_bounces + k] = vl;
    }
    for (var k = 0u; k < ml.max_bounces; k++) {
        let slot = gid.x * ml.max_bounces + k;
        scratch[slot].opacity_lo = opacity_bins.x;
        scratch[slot].opacity_hi = opacity_bins.y;
        scratch[slot].colour_lo = colour_bins.x;
        scratch[slot].colour_hi = colour_bins.y;
    }
}
