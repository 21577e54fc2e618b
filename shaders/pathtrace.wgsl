// Technique `pathtrace`: the unbiased reference. One path per pixel and dispatch: delta
// (Woodcock) tracking against the piecewise-constant majorant of the 8³ macrocells, real
// collisions scatter with probability albedo (the path weight is multiplied by it), next-event
// estimation to every directional and point light with ratio-tracked transmittance,
// Henyey-Greenstein phase sampling for the next direction, the environment reached by escaping
// paths (it is not sampled by next-event estimation, so nothing is counted twice), Russian
// roulette on the path weight. Rust twin: server/engine/src/passes/pathtrace.rs.

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var<storage, read> tf_lut: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> lights: array<GpuLight>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;

// The tracking hook (tracking.wgsl): nothing to record here.
fn track_visit(cell: vec3<u32>) {}

// Paths longer than this are cut (only reached in very dense, almost white media).
const MAX_BOUNCES: u32 = 1024u;
// Russian roulette on the path weight starts after this many scattering events.
const ROULETTE_START: u32 = 3u;
// Ratio tracking plays roulette once the transmittance estimate falls below this.
const RATIO_ROULETTE: f32 = 0.05;
// Transmittance from p along dir over at most t_max, by ratio tracking (unbiased); the
// shadow-ray estimator of lights.wgsl.
fn shadow_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, rng: ptr<function, Rng>) -> f32 {
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t1 = min(hit.y, t_max);
    var t = hit.x;
    var tr = 1.0;
    loop {
        if (t >= t1) {
            break;
        }
        let cell = cell_of(box_relative(p + dir * (t + CELL_NUDGE)));
        let t_exit = min(cell_exit(p, dir, cell), t1);
        let majorant = cell_majorant(cell);
        if (majorant <= 0.0) {
            t = max(t_exit, t + CELL_NUDGE);
            continue;
        }
        let free_flight = -log(1.0 - rng_next(rng)) / majorant;
        if (t + free_flight >= t_exit) {
            t = max(t_exit, t + CELL_NUDGE);
            continue;
        }
        t += free_flight;
        tr *= max(0.0, 1.0 - medium_at(p + dir * t).a / majorant);
        if (tr < RATIO_ROULETTE) {
            if (rng_next(rng) < 0.5) {
                return 0.0;
            }
            tr *= 2.0;
        }
    }
    return tr;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= scene.width || gid.y >= scene.height) {
        return;
    }
    let pixel = gid.y * scene.width + gid.x;
    var rng = rng_new(scene.seed, pixel, scene.iteration);
    let px = vec2<f32>(f32(gid.x) + rng_next(&rng), f32(gid.y) + rng_next(&rng));
    var dir = camera_ray_dir(scene, px);
    var origin = scene.eye;
    var weight = vec3<f32>(1.0);
    var radiance = vec3<f32>(0.0);

    for (var bounce = 0u; bounce < MAX_BOUNCES; bounce++) {
        let hit = intersect_box(origin, dir, scene.box_min, scene.box_max);
        var event = vec2<f32>(0.0, 0.0);
        if (hit.x < hit.y) {
            event = delta_track(origin, dir, hit.x, hit.y, &rng);
        }
        if (event.y == 0.0) {
            radiance += weight * scene.env_radiance;
            break;
        }
        let p = origin + dir * event.x;
        weight *= medium_at(p).rgb;
        if (all(weight <= vec3<f32>(0.0))) {
            break;
        }
        radiance += weight * direct_light(p, dir, &rng);
        if (bounce >= ROULETTE_START) {
            let survive = min(max(weight.x, max(weight.y, weight.z)), 1.0);
            if (rng_next(&rng) >= survive) {
                break;
            }
            weight /= survive;
        }
        let u1 = rng_next(&rng);
        let u2 = rng_next(&rng);
        dir = sample_hg(dir, scene.g, u1, u2);
        origin = p;
    }

    let estimate = vec4<f32>(radiance, 1.0);
    if (scene.iteration == 0u) {
        accum[pixel] = estimate;
    } else {
        accum[pixel] += estimate;
    }
}
