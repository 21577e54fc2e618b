// Shared pieces: delta (Woodcock) tracking against the macrocell majorants. A pass that
// includes this also includes shared/macrocell.wgsl, declares its bindings and defines
// `fn track_visit(cell: vec3<u32>)`, called for every macrocell the tracking enters (the
// virtual lights record the data bins their paths depended on there), and
// `fn track_sample(p: vec3<f32>)`, called at every tentative collision.

// Step past a cell face so the next lookup lands in the next cell.
const CELL_NUDGE: f32 = 1e-5;

// Distance along origin + t·dir to the first real collision in [t0, t1]; w = 1 when one
// happened, 0 when the ray left the interval.
fn delta_track(origin: vec3<f32>, dir: vec3<f32>, t0: f32, t1: f32, rng: ptr<function, Rng>) -> vec2<f32> {
    var t = t0;
    loop {
        if (t >= t1) {
            return vec2<f32>(t1, 0.0);
        }
        let cell = cell_of(box_relative(origin + dir * (t + CELL_NUDGE)));
        track_visit(cell);
        let t_exit = min(cell_exit(origin, dir, cell), t1);
        let majorant = cell_majorant(cell);
        if (majorant <= 0.0) {
            t = max(t_exit, t + CELL_NUDGE);
            continue;
        }
        let free_flight = -log(1.0 - rng_next(rng)) / majorant;
        if (t + free_flight >= t_exit) {
            // Memoryless: restart at the face with the next cell's majorant.
            t = max(t_exit, t + CELL_NUDGE);
            continue;
        }
        t += free_flight;
        track_sample(origin + dir * t);
        if (rng_next(rng) * majorant < extinction_at(origin + dir * t)) {
            return vec2<f32>(t, 1.0);
        }
    }
    return vec2<f32>(t1, 0.0);
}
