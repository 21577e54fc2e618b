// Shared pieces: transmittance by a jittered march with empty-space skipping. A pass that
// includes this also includes macrocell.wgsl and declares its bindings.

// Above this optical depth a shadow ray counts as blocked (exp(-16) ≈ 1e-7).
const SHADOW_TAU_CUTOFF: f32 = 16.0;

// Shadow rays march with this multiple of the view step: the estimate of the optical depth
// stays unbiased, only its variance grows, and shadow rays are most of the cost.
const SHADOW_STEP_SCALE: f32 = 2.0;

// Transmittance from p along dir over at most t_max, by a jittered Riemann sum of the optical
// depth (an unbiased estimate of it for a jitter uniform over one step).
fn transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, jitter: f32) -> f32 {
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t_end = min(hit.y, t_max);
    let step = scene.step * SHADOW_STEP_SCALE;
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
        tau += medium_at(x).a * step;
        if (tau > SHADOW_TAU_CUTOFF) {
            return 0.0;
        }
        k += 1.0;
    }
    return exp(-tau);
}
