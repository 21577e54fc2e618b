// Shared pieces: transmittance by a jittered march with empty-space skipping. A pass that
// includes this also includes shared/macrocell.wgsl and declares its bindings.

// Above this optical depth a shadow ray counts as blocked (exp(-16) ≈ 1e-7).
const SHADOW_TAU_CUTOFF: f32 = 16.0;

// Shadow rays march with this multiple of the view step: the estimate of the optical depth
// stays unbiased, only its variance grows, and shadow rays are most of the cost.
const SHADOW_STEP_SCALE: f32 = 2.0;

// Transmittance from p along dir over at most t_max, by a jittered Riemann sum of the optical
// depth (an unbiased estimate of it for a jitter uniform over one step).
fn transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, jitter: f32) -> f32 {
    return transmittance_with_step(p, dir, t_max, jitter, scene.step * SHADOW_STEP_SCALE);
}

// The same at a given step.
fn transmittance_with_step(p: vec3<f32>, dir: vec3<f32>, t_max: f32, jitter: f32, step: f32) -> f32 {
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t_end = min(hit.y, t_max);
    var tau = 0.0;
    var k = 0.0;
    loop {
        let t = hit.x + (k + jitter) * step;
        if (t >= t_end) {
            break;
        }
        let x = p + dir * t;
        let cell = cell_of((x - scene.box_min) / (scene.box_max - scene.box_min));
        if (cell_is_empty(cell)) {
            k = skip_empty_cell(p, dir, cell, hit.x, step, jitter, k);
            continue;
        }
        tau += extinction_at(x) * step;
        if (tau > SHADOW_TAU_CUTOFF) {
            return 0.0;
        }
        k += 1.0;
    }
    return exp(-tau);
}

// Below this view transmittance the march stops (relative bias at most 1e-4).
const VIEW_T_CUTOFF: f32 = 1e-4;

// One scattering location on a view ray, picked with probability proportional to its weight
// T·(1 − exp(−σt·dt)) among the jittered march's samples (weighted reservoir), with the sum of
// the weights and the transmittance through the whole march.
struct ViewSample {
    weight_sum: f32,
    transmit: f32,
    position: vec3<f32>,
    albedo: vec3<f32>,
}

// Marches origin + t·dir over [t0, t1] at the view step (one jitter for the lattice; empty
// cells skipped without moving it).
fn pick_scattering(origin: vec3<f32>, dir: vec3<f32>, t0: f32, t1: f32, rng: ptr<function, Rng>) -> ViewSample {
    var out = ViewSample(0.0, 1.0, vec3<f32>(0.0), vec3<f32>(0.0));
    let jitter = rng_next(rng);
    var k = 0.0;
    loop {
        let t = t0 + (k + jitter) * scene.step;
        if (t >= t1 || out.transmit < VIEW_T_CUTOFF) {
            break;
        }
        let p = origin + dir * t;
        let cell = cell_of(box_relative(p));
        if (cell_is_empty(cell)) {
            k = skip_empty_cell(origin, dir, cell, t0, scene.step, jitter, k);
            continue;
        }
        let m = medium_at(p);
        if (m.a > 0.0) {
            let alpha = 1.0 - exp(-m.a * scene.step);
            let w = out.transmit * alpha;
            out.weight_sum += w;
            // Weighted reservoir: keep this location with probability w / weight_sum.
            if (rng_next(rng) * out.weight_sum < w) {
                out.position = p;
                out.albedo = m.rgb;
            }
            out.transmit *= 1.0 - alpha;
        }
        k += 1.0;
    }
    return out;
}
