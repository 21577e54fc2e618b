// Shared pieces: the unbiased multiple-scattering path estimator of `pathtrace`, also used by
// `irradiance` (its cache-miss shading and its cache entries' irradiance samples). Delta
// tracking against the macrocell majorants (shared/tracking.wgsl), real collisions scatter with
// probability albedo (the path weight is multiplied by it), next-event estimation to every
// directional and point light with ratio-tracked transmittance (shared/lights.wgsl), Henyey-Greenstein
// phase sampling, the environment reached by escaping paths (it is not sampled by next-event
// estimation, so nothing is counted twice), Russian roulette on the path weight. A pass that
// includes this declares the estimator bindings, its shadow-ray estimator
// `fn shadow_transmittance(p, dir, t_max, rng) -> f32` (shared/lights.wgsl; `ratio_transmittance`
// below, or another) and three hooks: `fn track_visit(cell: vec3<u32>)` (every macrocell a
// tracking or ratio-tracked ray enters), `fn track_sample(p: vec3<f32>)` (every tentative
// collision they look at) and `fn track_vertex(p: vec3<f32>)` (every real collision a path
// scatters at).

// Paths longer than this are cut (only reached in very dense, almost white media).
const MAX_BOUNCES: u32 = 1024u;
// Russian roulette on the path weight starts after this many scattering events.
const ROULETTE_START: u32 = 3u;
// Ratio tracking plays roulette once the transmittance estimate falls below this.
const RATIO_ROULETTE: f32 = 0.05;

// Transmittance from p along dir over at most t_max, by ratio tracking (unbiased).
fn ratio_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, rng: ptr<function, Rng>) -> f32 {
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t1 = min(hit.y, t_max);
    var t = hit.x;
    var tr = 1.0;
    loop {
        if (t >= t1) {
            break;
        }
        let cell = cell_of(box_relative(p + dir * (t + CELL_NUDGE)));
        track_visit(cell);
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
        track_sample(p + dir * t);
        tr *= max(0.0, 1.0 - extinction_at(p + dir * t) / majorant);
        if (tr < RATIO_ROULETTE) {
            if (rng_next(rng) < 0.5) {
                return 0.0;
            }
            tr *= 2.0;
        }
    }
    return tr;
}

// Radiance arriving at `origin` from direction `dir` (the light travels along −dir), times
// `weight`, for a path whose scattering events so far number `first_bounce`: the loop of
// `pathtrace` from that event on. Scatters at most `max_bounces` times in all.
fn trace_radiance(
    origin_in: vec3<f32>,
    dir_in: vec3<f32>,
    weight_in: vec3<f32>,
    first_bounce: u32,
    max_bounces: u32,
    rng: ptr<function, Rng>,
) -> vec3<f32> {
    var origin = origin_in;
    var dir = dir_in;
    var weight = weight_in;
    var radiance = vec3<f32>(0.0);
    for (var bounce = first_bounce; bounce < max_bounces + 1u; bounce++) {
        let hit = intersect_box(origin, dir, scene.box_min, scene.box_max);
        var event = vec2<f32>(0.0, 0.0);
        if (hit.x < hit.y) {
            event = delta_track(origin, dir, hit.x, hit.y, rng);
        }
        if (event.y == 0.0) {
            radiance += weight * scene.env_radiance;
            break;
        }
        if (bounce == max_bounces) {
            // The path may not scatter again: what lies beyond this collision is cut.
            break;
        }
        let p = origin + dir * event.x;
        track_vertex(p);
        weight *= medium_at(p).rgb;
        if (all(weight <= vec3<f32>(0.0))) {
            break;
        }
        radiance += weight * direct_light(p, dir, rng);
        if (bounce >= ROULETTE_START) {
            let survive = min(max(weight.x, max(weight.y, weight.z)), 1.0);
            if (rng_next(rng) >= survive) {
                break;
            }
            weight /= survive;
        }
        let u1 = rng_next(rng);
        let u2 = rng_next(rng);
        dir = sample_hg(dir, scene.g, u1, u2);
        origin = p;
    }
    return radiance;
}
