// Technique `photon`, pass 3: radiance gathering along view rays split into Vn segments, and
// compositing. Each pixel's ray (through the pixel centre, one fixed jitter of the march
// lattice per pixel) is cut into `segments` equal pieces of its box interval; each segment
// marches its own samples with transmittance starting at 1 and stores the in-scattered
// radiance (an Epanechnikov density estimate of the photons within `radius`, from the
// 27-cell neighbourhood, in record order), its transmittance and the historygram of its
// samples' data values. `gather_mark` lists the segments to compute in gather_list: all in
// MODE_FULL; in MODE_UPDATE those whose historygram meets the query or that a changed photon
// can reach (spatial historygram; without it, any changed photon). Listing them keeps every
// SIMD lane of the gather busy (a sparse update would otherwise pay for whole idle batches).
// `gather` then runs over the list once per chunk of photon ranks (PhotonUniforms.chunk_*),
// adding each chunk's radiance. `composite` multiplies the segments front to back.
// Rust twin: server/engine/src/passes/photon.rs.

// Below this transmittance inside a segment its march stops.
const SEGMENT_T_CUTOFF: f32 = 1e-4;

// In-scattered radiance per unit length at x toward out_dir (propagation direction), from the
// photons of this dispatch's rank chunk in each cell.
fn gather_at(x: vec3<f32>, out_dir: vec3<f32>) -> vec3<f32> {
    let c = grid_cell3(x);
    let r2 = photon.radius * photon.radius;
    let dims = vec3<i32>(photon.grid_dims);
    var s = vec3<f32>(0.0);
    for (var dz = -1; dz <= 1; dz++) {
        for (var dy = -1; dy <= 1; dy++) {
            for (var dx = -1; dx <= 1; dx++) {
                let n = c + vec3<i32>(dx, dy, dz);
                if (any(n < vec3<i32>(0)) || any(n >= dims)) {
                    continue;
                }
                let cell = grid_index(n);
                let cell_first = atomicLoad(&grid_cells[cell]);
                let cell_end = atomicLoad(&grid_cells[cell + 1u]);
                let first = min(cell_first + photon.chunk_first, cell_end);
                // (chunk_count may be u32::MAX: no overflowing sum.)
                let end = first + min(photon.chunk_count, cell_end - first);
                for (var i = first; i < end; i++) {
                    let rec = records[grid_sorted[i]];
                    let d = x - rec.position;
                    let d2 = dot(d, d);
                    if (d2 < r2) {
                        s += rec.power * (phase_hg(dot(rec.direction, out_dir), scene.g) * (1.0 - d2 / r2));
                    }
                }
            }
        }
    }
    return s * photon.kernel_norm;
}

// Whether a photon change recorded in the spatial historygram can reach the segment a..b.
fn spatial_hit(a: vec3<f32>, b: vec3<f32>) -> bool {
    let lo = spatial_bins(min(a, b) - vec3<f32>(photon.radius));
    let hi = spatial_bins(max(a, b) + vec3<f32>(photon.radius));
    for (var axis = 0u; axis < 3u; axis++) {
        let m = range_mask(lo[axis], hi[axis]);
        let w0 = atomicLoad(&counters[COUNTER_SPATIAL + axis * 2u]);
        let w1 = atomicLoad(&counters[COUNTER_SPATIAL + axis * 2u + 1u]);
        if (((m.x & w0) | (m.y & w1)) == 0u) {
            return false;
        }
    }
    return true;
}

// Whether any sample of the segment lies in a dirty cell (SPATIAL_CELLS): the cells of changed
// photons are marked with their 26 neighbours, so this finds every change within the gather
// radius of a sample. Visits every lattice sample in [ta, tb) (a superset of those gathered).
fn cells_hit(pixel: u32, hit: vec2<f32>, ta: f32, tb: f32, dir: vec3<f32>) -> bool {
    var rng = rng_new(scene.seed, pixel, 0xffffffffu);
    let jitter = rng_next(&rng);
    let step = photon.gather_step;
    var k = max(0.0, ceil((ta - hit.x) / step - jitter) - 1.0);
    loop {
        let t = hit.x + (k + jitter) * step;
        k += 1.0;
        if (t < ta) {
            continue;
        }
        if (t >= tb) {
            break;
        }
        let cell = grid_index(grid_cell3(scene.eye + dir * t));
        if ((atomicLoad(&counters[COUNTER_DIRTY + cell / 32u]) & (1u << (cell % 32u))) != 0u) {
            return true;
        }
    }
    return false;
}

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

@compute @workgroup_size(64)
fn gather_mark(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let id = linear_index(gid, groups);
    if (id >= scene.width * scene.height * photon.segments) {
        return;
    }
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        if (photon.mode == MODE_FULL) {
            segments[id] = Segment(vec3<f32>(0.0), 1.0, 0u, 0u, 0u, 0u);
        }
        return;
    }
    var stale = true;
    if (photon.mode == MODE_UPDATE) {
        let bounds = segment_bounds(hit, id % photon.segments);
        let old = segments[id];
        stale = hist_hits_query(old.hist_lo, old.hist_hi);
        if (!stale) {
            if (photon.spatial == SPATIAL_AXES) {
                stale = spatial_hit(scene.eye + dir * bounds.x, scene.eye + dir * bounds.y);
            } else if (photon.spatial == SPATIAL_CELLS) {
                stale = cells_hit(pixel, hit, bounds.x, bounds.y, dir);
            } else {
                stale = atomicLoad(&counters[COUNTER_CHANGED]) > 0u;
            }
        }
        if (stale) {
            atomicAdd(&counters[COUNTER_SEGMENTS], 1u);
        }
    }
    if (stale) {
        gather_list[atomicAdd(&counters[COUNTER_LIST], 1u)] = id;
    }
}

@compute @workgroup_size(64)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    if (slot >= atomicLoad(&counters[COUNTER_LIST])) {
        return;
    }
    let id = gather_list[slot];
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    let bounds = segment_bounds(hit, id % photon.segments);
    let ta = bounds.x;
    let tb = bounds.y;
    var rng = rng_new(scene.seed, pixel, 0xffffffffu);
    let jitter = rng_next(&rng);
    let step = photon.gather_step;
    // One sample before the first that can fall in [ta, tb), so that the membership of a
    // sample is decided by the same comparison in neighbouring segments.
    var k = max(0.0, ceil((ta - hit.x) / step - jitter) - 1.0);
    var transmit = 1.0;
    var color = vec3<f32>(0.0);
    var hist = vec2<u32>(0u);
    loop {
        let t = hit.x + (k + jitter) * step;
        k += 1.0;
        if (t < ta) {
            continue;
        }
        if (t >= tb || transmit < SEGMENT_T_CUTOFF) {
            break;
        }
        let x = scene.eye + dir * t;
        let v = data_at(x);
        hist |= hist_bit(v);
        let sigma = classify(v).a * scene.density_scale;
        if (sigma > 0.0) {
            let w = (1.0 - exp(-sigma * step)) / sigma;
            color += transmit * w * gather_at(x, -dir);
            transmit *= exp(-sigma * step);
        }
    }
    if (photon.chunk_first > 0u) {
        color = segments[id].color + color;
    }
    segments[id] = Segment(color, transmit, hist.x, hist.y, 0u, 0u);
}

@compute @workgroup_size(64)
fn composite(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let pixel = linear_index(gid, groups);
    if (pixel >= scene.width * scene.height) {
        return;
    }
    var radiance = vec3<f32>(0.0);
    var transmit = 1.0;
    for (var s = 0u; s < photon.segments; s++) {
        let seg = segments[pixel * photon.segments + s];
        radiance += transmit * seg.color;
        transmit *= seg.transmittance;
    }
    radiance += transmit * scene.env_radiance;
    accum[pixel] = vec4<f32>(radiance, 1.0);
}
