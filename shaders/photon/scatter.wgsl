// Technique `photon`, pass 4: the delta scatter. After a TF edit, a segment whose opacity did
// not change but that a changed photon can reach (gather_mark's delta segments) differs from
// before only by the changed photons' terms. The delta gather (photon/gather.wgsl) finds them
// from the segment's side: every dirty sample visits the change grid's 27 cells, and most of
// what it visits lies beyond the radius. The scatter goes from the photon's side instead:
//
// - `scatter_touch` (where the changes are few; the host decides) marks the segments that the
//   rays through each change's ball cross within it, for gather_mark to take in place of the
//   dirty cells;
// - `scatter_weights` marches each slot's segment once, exactly as the gather does, and keeps
//   each lattice sample's weight (sample_weight; −1 where the gather takes no photons: σ = 0,
//   before the segment or past its transmittance cut-off);
// - `scatter_changes` runs one invocation per change-list entry: the pixels whose rays can pass
//   within the radius (row spans of the photon's cone within the projection of its cube:
//   ChangeCone), on each ray the lattice samples within the radius, and for each the term the
//   gather would form (the same expressions on the same bits), summed per segment in 64-bit
//   fixed point and added to the slot's sum with two 32-bit atomics and a carry. Integer sums
//   do not depend on order, so segment + sum is bit for bit what a gather gives;
// - `scatter_apply` adds each slot's sum to its segment.
//
// A change whose pixels would take more loop iterations than one invocation may run (llvmpipe
// ends loops silently past its limit) sets COUNTER_SCATTER_OVERFLOW instead. Found by
// scatter_touch, gather_mark then gives out no slots (and uses the dirty cells); found by
// scatter_changes, the host runs `scatter_fallback`, which lists every slot's segment for the
// delta gather, and no sum is applied. Segments past scatter_capacity are gathered as before
// (gather_mark), and so are all of them where the changes far outnumber the segments (the host
// then runs scatter_fallback alone: the scatter's cost follows the changes, the gather's the
// segments).
// Rust twin: server/engine/src/techniques/photon/gpu.rs.

#import photon/common

fn weight_word(slot: u32, j: u32) -> u32 {
    return slot_word(photon.scatter_capacity, 0u) + slot * photon.scatter_samples + j;
}

fn scatter_slots() -> u32 {
    return min(atomicLoad(&counters[COUNTER_SCATTER]), photon.scatter_capacity);
}

@compute @workgroup_size(64)
fn scatter_weights(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    if (slot >= scatter_slots()) {
        return;
    }
    let id = atomicLoad(&scatter[slot_word(slot, 0u)]);
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    let bounds = segment_bounds(hit, id % photon.segments);
    let jitter = pixel_jitter(pixel);
    // The gather's march (photon/gather.wgsl), sample for sample.
    var k = first_lattice_index(hit, bounds.x, jitter);
    var transmit = 1.0;
    var j = 0u;
    loop {
        let t = hit.x + (k + jitter) * photon.gather_step;
        var weight = -1.0;
        if (t >= bounds.x) {
            if (t >= bounds.y || transmit < SEGMENT_T_CUTOFF) {
                break;
            }
            let x = scene.eye + dir * t;
            let sigma = classify_opacity(data_at(x)) * scene.density_scale;
            if (sigma > 0.0) {
                weight = sample_weight(transmit, sigma);
                transmit *= exp(-sigma * photon.gather_step);
            }
        }
        if (j >= photon.scatter_samples) {
            // More samples than the host sized for: gather instead.
            atomicAdd(&counters[COUNTER_SCATTER_OVERFLOW], 1u);
            break;
        }
        atomicStore(&scatter[weight_word(slot, j)], bitcast<u32>(weight));
        j += 1u;
        k += 1.0;
    }
    atomicStore(&scatter[slot_word(slot, 1u)], j);
    for (var w = 2u; w < SLOT_WORDS; w++) {
        atomicStore(&scatter[slot_word(slot, w)], 0u);
    }
}

// Adds a 64-bit fixed-point sum to a slot's (wrapping; the final sum is non-negative).
fn add_to_slot(slot: u32, sum: FixedSum) {
    if (slot == SLOT_NONE) {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        let lo = sum.lo[c];
        let hi = sum.hi[c];
        if ((lo | hi) == 0u) {
            continue;
        }
        let old = atomicAdd(&scatter[slot_word(slot, 2u + c)], lo);
        let carry = select(0u, 1u, old + lo < old);
        // Most terms are small: hi + carry wraps to 0 for a negative one (hi all ones, a
        // carry) and is 0 for a positive one without a carry; adding it would change nothing.
        if (hi + carry != 0u) {
            atomicAdd(&scatter[slot_word(slot, 5u + c)], hi + carry);
        }
    }
}

// The segment of ray sample t, by the comparisons the gather's membership uses.
fn segment_of(hit: vec2<f32>, t: f32) -> u32 {
    let len = (hit.y - hit.x) / f32(photon.segments);
    var s = min(u32(max((t - hit.x) / len, 0.0)), photon.segments - 1u);
    loop {
        let b = segment_bounds(hit, s);
        if (s > 0u && t < b.x) {
            s -= 1u;
        } else if (s + 1u < photon.segments && t >= b.y) {
            s += 1u;
        } else {
            return s;
        }
    }
    return s;
}

// The pixels whose rays can pass within the radius of p: the projection of p's cube (every
// ray through the ball crosses the cube), rounded outwards. `fits` is false where there are
// none, or more than one invocation should visit (COUNTER_SCATTER_OVERFLOW is then set).
struct ChangePixels {
    first: vec2<i32>,
    last: vec2<i32>,
    fits: bool,
}

fn change_pixels(p: vec3<f32>) -> ChangePixels {
    let r = photon.radius;
    let size = vec2<f32>(f32(scene.width), f32(scene.height));
    var lo = size;
    var hi = vec2<f32>(-1.0);
    var behind = false;
    for (var c = 0u; c < 8u; c++) {
        let corner = p + vec3<f32>(
            select(-r, r, (c & 1u) != 0u),
            select(-r, r, (c & 2u) != 0u),
            select(-r, r, (c & 4u) != 0u),
        );
        let v = corner - scene.eye;
        let z = dot(v, scene.forward);
        if (z <= 0.0) {
            behind = true;
            break;
        }
        let ndc = vec2<f32>(
            dot(v, scene.right) / (z * scene.aspect * scene.tan_half_fov),
            dot(v, scene.up) / (z * scene.tan_half_fov),
        );
        let px = vec2<f32>(ndc.x + 1.0, 1.0 - ndc.y) * 0.5 * size;
        lo = min(lo, px);
        hi = max(hi, px);
    }
    if (behind) {
        lo = vec2<f32>(0.0);
        hi = size;
    }
    // Pixel i's centre is at i + 0.5; rounding outwards leaves a pixel's margin on each side.
    let first = vec2<i32>(clamp(floor(lo - 0.5), vec2<f32>(0.0), size - 1.0));
    let last = vec2<i32>(clamp(ceil(hi - 0.5), vec2<f32>(-1.0), size - 1.0));
    if (any(last < first)) {
        return ChangePixels(first, last, false);
    }
    let pixels = u32(last.x - first.x + 1) * u32(last.y - first.y + 1);
    let per_pixel = u32(ceil(2.1 * r / photon.gather_step)) + 8u;
    // At most 2^16 iterations even where the device has no loop limit: a photon by the eye
    // would have one invocation visit the whole screen.
    if (pixels * per_pixel > min(photon.round_budget, 65536u)) {
        atomicAdd(&counters[COUNTER_SCATTER_OVERFLOW], 1u);
        return ChangePixels(first, last, false);
    }
    return ChangePixels(first, last, true);
}

// The pixels of a change's box whose rays can pass within reach of it, row by row: the rays
// within `reach` of p form a cone from the eye, which meets the image plane in an ellipse;
// each row of pixel centres crosses it in one span. `reach` is the radius and 1% besides,
// plus 1e-5 of p's distance from the eye: a ray whose rounded sample lies within the radius
// passes far nearer p than that (ball_reach2's larger margin is for the difference of squares
// that ray_near_change rounds). Visiting the spans instead of the whole box matters on
// llvmpipe: a pixel's work runs masked for all lanes of a SIMD batch where any lane's ray
// passes near, and about 70% of a box's pixels pass too far (the projection of the photon's
// cube, rounded outwards, for a ball a pixel or two across).
// In camera coordinates (right, up, forward), with p − eye = (X, Y, Z), the pixel's ray
// direction d = (u, v, 1) and its offsets δu = u − X/Z, δv = v − Y/Z from p's projection, the
// squared distance of p from the ray is Z² (δu² + δv² + (u₀δv − v₀δu)²) / |d|²: small terms
// only, so the span is found to a rounding far below reach's margin, and it is widened by a
// few hundredths of a pixel besides. Each visited pixel still takes the exact tests
// (ray_near_change, then each sample's distance).
struct ChangeCone {
    // p's projection (u₀, v₀) on the image plane at distance 1.
    centre: vec2<f32>,
    // reach² / Z².
    q: f32,
    // False where the ball reaches near the eye's plane: every pixel of the box's rows.
    narrow: bool,
}

fn change_cone(e: vec3<f32>, e2: f32) -> ChangeCone {
    let z = dot(e, scene.forward);
    let reach = 1.01 * photon.radius + 1e-5 * sqrt(e2);
    let q = reach * reach / max(z * z, 1e-30);
    let narrow = z > 0.0 && q < 0.25;
    return ChangeCone(vec2<f32>(dot(e, scene.right), dot(e, scene.up)) / z, q, narrow);
}

// Pixel columns first..=last of row py whose rays can pass within reach (first > last: none),
// within the box's columns.
fn cone_row(cone: ChangeCone, py: i32, box: ChangePixels) -> vec2<i32> {
    if (!cone.narrow) {
        return vec2<i32>(box.first.x, box.last.x);
    }
    // The row's v as camera_ray_dir forms it.
    let v = (1.0 - 2.0 * (f32(py) + 0.5) / f32(scene.height)) * scene.tan_half_fov;
    let u0 = cone.centre.x;
    let v0 = cone.centre.y;
    let dv = v - v0;
    let q = cone.q;
    // a·δu² − 2b·δu + c <= 0.
    let a = 1.0 + v0 * v0 - q;
    let b = u0 * (v0 * dv + q);
    let c = dv * dv * (1.0 + u0 * u0) - q * (u0 * u0 + v * v + 1.0);
    let disc = b * b - a * c;
    if (disc < 0.0) {
        return vec2<i32>(1, 0);
    }
    let root = sqrt(disc);
    // Column x's centre is at u = (2 (x + 0.5) / width − 1) · aspect · tan_half_fov.
    let to_px = 0.5 * f32(scene.width) / (scene.aspect * scene.tan_half_fov);
    let lo = (u0 + (b - root) / a) * to_px + 0.5 * f32(scene.width) - 0.5;
    let hi = (u0 + (b + root) / a) * to_px + 0.5 * f32(scene.width) - 0.5;
    let margin = 0.05;
    let first = max(i32(ceil(max(lo - margin, -1.0))), box.first.x);
    let last = min(i32(floor(min(hi + margin, f32(scene.width)))), box.last.x);
    return vec2<i32>(first, last);
}

// A change's visit of its pixels: its box (change_pixels, which also decides whether it fits
// the loop budget), its offset e = p − eye (e2 = |e|²), the reach ray_near_change tests, its cone,
// and the walk over the cone's row spans (next_pixel), row by row.
struct PixelWalk {
    box: ChangePixels,
    cone: ChangeCone,
    e: vec3<f32>,
    e2: f32,
    reach2: f32,
    x: i32,
    y: i32,
    row_last: i32,
}

fn pixel_walk(p: vec3<f32>) -> PixelWalk {
    let box = change_pixels(p);
    let e = p - scene.eye;
    let e2 = dot(e, e);
    return PixelWalk(box, change_cone(e, e2), e, e2, ball_reach2(e2), 0, box.first.y - 1, -1);
}

// Moves to the next pixel of the spans; false past the last. One loop visits them all, so a
// SIMD batch iterates as often as its lane with the most pixels, not its widest span times its
// most rows.
fn next_pixel(walk: ptr<function, PixelWalk>) -> bool {
    (*walk).x += 1;
    loop {
        if ((*walk).x <= (*walk).row_last) {
            return true;
        }
        (*walk).y += 1;
        if ((*walk).y > (*walk).box.last.y) {
            return false;
        }
        let span = cone_row((*walk).cone, (*walk).y, (*walk).box);
        (*walk).x = span.x;
        (*walk).row_last = span.y;
    }
    return false;
}

// The current pixel's ray as the change sees it.
fn walk_ray(walk: PixelWalk) -> RayNearChange {
    return ray_near_change(walk_pixel(walk), walk.e, walk.e2, walk.reach2);
}

fn walk_pixel(walk: PixelWalk) -> u32 {
    return u32(walk.y) * scene.width + u32(walk.x);
}

// The squared distance from p within which a ray may pass near enough (e2: p's squared
// distance from the eye). It is found by a difference of squares; its rounding stays far below
// this margin, and the exact test is the gather's own (d2 < r2).
fn ball_reach2(e2: f32) -> f32 {
    return 1.02 * photon.radius * photon.radius + 1e-5 * e2;
}

// A pixel's ray as seen from a change at e = p − eye (e2 = |e|²): its direction, box interval,
// distance along the ray to p's foot (tc), and whether it passes within reach2 of p and meets
// the box.
struct RayNearChange {
    dir: vec3<f32>,
    hit: vec2<f32>,
    tc: f32,
    perp2: f32,
    near: bool,
}

fn ray_near_change(pixel: u32, e: vec3<f32>, e2: f32, reach2: f32) -> RayNearChange {
    let dir = pixel_ray(pixel);
    let tc = dot(e, dir);
    let perp2 = max(e2 - tc * tc, 0.0);
    if (perp2 >= reach2) {
        return RayNearChange(dir, vec2<f32>(0.0), tc, perp2, false);
    }
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    return RayNearChange(dir, hit, tc, perp2, hit.x < hit.y);
}

// A pixel's ray as a change's scatter visits it: the ray near the change, the pixel's jitter,
// the phase towards the eye, and the lattice indices that can lie within reach (none where
// the ray passes too far).
struct ChangeRay {
    near: RayNearChange,
    jitter: f32,
    phase: f32,
    k_first: f32,
    k_last: f32,
}

fn change_ray(pixel: u32, change: PhotonChange, ray: RayNearChange, reach2: f32) -> ChangeRay {
    var out = ChangeRay(ray, 0.0, 0.0, 0.0, -1.0);
    if (!ray.near) {
        return out;
    }
    let half = sqrt(reach2 - ray.perp2);
    let step = photon.gather_step;
    out.jitter = pixel_jitter(pixel);
    out.phase = phase_hg(dot(change.direction, -ray.dir), scene.g);
    // Exactly the lattice indices within `half` of the foot: reach2's margin (at least 1% of
    // the radius on each side) is far beyond the rounding of these few operations, so no
    // sample within the radius falls outside (the loops test each sample exactly).
    out.k_first = max(0.0, ceil((ray.tc - half - ray.hit.x) / step - out.jitter));
    out.k_last = floor((ray.tc + half - ray.hit.x) / step - out.jitter);
    return out;
}

// Lattice sample k of the ray, as the gather places it: its distance t along the ray and its
// squared distance from p.
fn change_sample(ray: ChangeRay, k: f32, p: vec3<f32>) -> vec2<f32> {
    let t = ray.near.hit.x + (k + ray.jitter) * photon.gather_step;
    let d = scene.eye + ray.near.dir * t - p;
    return vec2<f32>(t, dot(d, d));
}

// The change-list entries the update listed (past the list's capacity they were dropped).
fn change_entries() -> u32 {
    return min(atomicLoad(&counters[COUNTER_CHANGES]), photon.change_capacity);
}

// Whether scatter_touch also adds the changes to the per-sample sums (scatter_sums' work, in the
// same visit of each change's pixels): its pipeline `scatter_touch_sums`. A change too wide for
// the marks then leaves the sums partly added, and the host starts them anew.
override TOUCH_SUMS: bool = false;

// Marks (SEGMENT_TOUCHED) and lists every segment that holds a lattice sample within the radius
// of a changed photon, or may: the segments of each ray through the photon's ball that overlap the
// ray's interval within the ball (with TOUCH_SUMS, exactly those that hold such a sample, found
// by the samples the sums visit). gather_mark takes these as the segments the changes reach,
// in place of the dirty cells' march over every segment (COUNTER_TOUCH).
@compute @workgroup_size(64)
fn scatter_touch(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = linear_index(gid, groups);
    if (index >= change_entries()) {
        return;
    }
    let change = changes[index];
    var walk = pixel_walk(change.position);
    if (!walk.box.fits) {
        return;
    }
    let reach2 = walk.reach2;
    let kernel = pass_kernel(change.pass_index);
    let lead = sum_lead();
    loop {
        if (!next_pixel(&walk)) {
            break;
        }
        let pixel = walk_pixel(walk);
        let ray = walk_ray(walk);
        if (!ray.near) {
            continue;
        }
        let hit = ray.hit;
        if (TOUCH_SUMS) {
            // The samples the sums visit give the segments exactly: those with a lattice
            // sample within the radius, the only ones whose terms the change alters.
            let within = add_to_sums(pixel, change, change_ray(pixel, change, ray, reach2), kernel, lead);
            if (within.x <= within.y) {
                touch_segments(pixel, segment_of(hit, within.x), segment_of(hit, within.y));
            }
            continue;
        }
        // A step's margin at each end for the rounding of the samples' positions.
        let half = sqrt(reach2 - ray.perp2) + photon.gather_step;
        let ta = max(ray.tc - half, hit.x);
        let tb = min(ray.tc + half, hit.y);
        if (ta >= tb) {
            continue;
        }
        touch_segments(pixel, segment_of(hit, ta), segment_of(hit, tb));
    }
}

// Marks and lists the pixel's segments first..=last (scatter_touch).
fn touch_segments(pixel: u32, first: u32, last: u32) {
    for (var s = first; s <= last; s++) {
        // Each segment marked once is also listed once, in the second half of gather_list,
        // free until the gather's rounds (gather_mark_touched).
        let id = pixel * photon.segments + s;
        if (atomicExchange(&scatter[id], SEGMENT_TOUCHED) != SEGMENT_TOUCHED) {
            let listed = atomicAdd(&counters[COUNTER_LIST + 1u], 1u);
            gather_list[scene.width * scene.height * photon.segments + listed] = id;
        }
    }
}

@compute @workgroup_size(64)
fn scatter_changes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = linear_index(gid, groups);
    if (index >= change_entries()) {
        return;
    }
    let change = changes[index];
    let p = change.position;
    let kernel = pass_kernel(change.pass_index);
    let r2 = kernel.x;
    var walk = pixel_walk(p);
    if (!walk.box.fits) {
        return;
    }
    var current = SLOT_NONE;
    var sum = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
    loop {
        if (!next_pixel(&walk)) {
            break;
        }
        let pixel = walk_pixel(walk);
        let ray = change_ray(pixel, change, walk_ray(walk), walk.reach2);
        let hit = ray.near.hit;
        let jitter = ray.jitter;
        // The segment of the samples being visited: its slot, first lattice index and
        // samples marched (SLOT_NONE: none yet).
        var segment = SLOT_NONE;
        var slot = SLOT_NONE;
        var k0 = 0.0;
        var marched = 0u;
        for (var k = ray.k_first; k <= ray.k_last; k += 1.0) {
            let sample = change_sample(ray, k, p);
            let t = sample.x;
            let d2 = sample.y;
            if (t < hit.x) {
                continue;
            }
            if (t >= hit.y) {
                break;
            }
            if (d2 >= r2) {
                continue;
            }
            let s = segment_of(hit, t);
            if (s != segment) {
                segment = s;
                slot = segment_slot(pixel * photon.segments + s);
                if (slot != SLOT_NONE) {
                    k0 = first_lattice_index(hit, segment_bounds(hit, s).x, jitter);
                    marched = atomicLoad(&scatter[slot_word(slot, 1u)]);
                }
            }
            // SLOT_NONE: a fresh segment (gathered whole), one gathered from the change
            // grid, or one no change reaches.
            if (slot == SLOT_NONE || k < k0 || u32(k - k0) >= marched) {
                continue;
            }
            let j = u32(k - k0);
            let weight = bitcast<f32>(atomicLoad(&scatter[weight_word(slot, j)]));
            if (weight < 0.0) {
                continue;
            }
            if (slot != current) {
                add_to_slot(current, sum);
                current = slot;
                sum = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
            }
            // The gather's term (photon/gather.wgsl), factor for factor.
            let factor = weight * ray.phase * (1.0 - d2 / r2) * kernel.y;
            sum = accumulate(sum, change.power * factor, change.kind == CHANGE_SUBTRACT);
            if (change.kind == CHANGE_REPLACE) {
                sum = accumulate(sum, change.old_power * factor, true);
            }
        }
    }
    add_to_slot(current, sum);
}

// With per-sample photon sums (sample_cache_samples > 0; photon/common.wgsl, sample_sums):
// one invocation per change-list entry adds the change's term to the sum of every lattice
// sample within its radius that holds a valid sum (the gather's term without the sample's
// weight: the same expressions on the same bits), so that the gather recomposites the
// segments the changes reach from their sums alone. It runs where the marks did not
// (`scatter_touch_sums` adds the sums as it marks); where it finds a change that reaches too
// many pixels, the sums it added are incomplete and the host starts a new generation of them.
@compute @workgroup_size(64)
fn scatter_sums(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = linear_index(gid, groups);
    if (index >= change_entries() || atomicLoad(&counters[COUNTER_SCATTER_OVERFLOW]) != 0u) {
        return;
    }
    let change = changes[index];
    let kernel = pass_kernel(change.pass_index);
    var walk = pixel_walk(change.position);
    if (!walk.box.fits) {
        return;
    }
    let lead = sum_lead();
    loop {
        if (!next_pixel(&walk)) {
            break;
        }
        let pixel = walk_pixel(walk);
        let near = walk_ray(walk);
        add_to_sums(pixel, change, change_ray(pixel, change, near, walk.reach2), kernel, lead);
    }
}

// Adds the change's terms to the valid sums of the pixel's lattice samples within its radius.
// Returns the distances along the ray of the first and last such sample, valid sum or not
// (first > last: none).
fn add_to_sums(pixel: u32, change: PhotonChange, ray: ChangeRay, kernel: vec2<f32>, lead: f32) -> vec2<f32> {
    let r2 = kernel.x;
    var within = vec2<f32>(1.0, 0.0);
    for (var k = ray.k_first; k <= ray.k_last; k += 1.0) {
        let sample = change_sample(ray, k, change.position);
        let d2 = sample.y;
        if (sample.x < ray.near.hit.x) {
            continue;
        }
        if (sample.x >= ray.near.hit.y) {
            break;
        }
        if (d2 >= r2) {
            continue;
        }
        within = vec2<f32>(select(within.x, sample.x, within.x > within.y), sample.x);
        let kept = sample_entry(pixel, k);
        if (!sample_valid(kept)) {
            continue;
        }
        // The gather's term (photon/gather.wgsl), factor for factor.
        let factor = lead * ray.phase * (1.0 - d2 / r2) * kernel.y;
        var sum = accumulate(FixedSum(vec3<u32>(0u), vec3<u32>(0u)), change.power * factor, change.kind == CHANGE_SUBTRACT);
        if (change.kind == CHANGE_REPLACE) {
            sum = accumulate(sum, change.old_power * factor, true);
        }
        sample_add(kept, sum);
    }
    return within;
}

@compute @workgroup_size(64)
fn scatter_apply(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    if (slot >= scatter_slots()) {
        return;
    }
    let id = atomicLoad(&scatter[slot_word(slot, 0u)]);
    var seg = segments[id];
    let lo = vec3<u32>(
        atomicLoad(&scatter[slot_word(slot, 2u)]),
        atomicLoad(&scatter[slot_word(slot, 3u)]),
        atomicLoad(&scatter[slot_word(slot, 4u)]),
    );
    let hi = vec3<u32>(
        atomicLoad(&scatter[slot_word(slot, 5u)]),
        atomicLoad(&scatter[slot_word(slot, 6u)]),
        atomicLoad(&scatter[slot_word(slot, 7u)]),
    );
    let sum_lo = seg.color_lo + lo;
    seg.color_hi = seg.color_hi + hi + select(vec3<u32>(0u), vec3<u32>(1u), sum_lo < lo);
    seg.color_lo = sum_lo;
    segments[id] = seg;
    // Between updates every segment's word reads SEGMENT_UNTOUCHED: the next update's marks
    // list only what they mark, and gather_mark_touched visits only those.
    atomicStore(&scatter[id], SEGMENT_UNTOUCHED);
}

// After an overflow: every slot's segment goes to the delta gather (gather_mark left its
// state ready), and no slot sum is applied.
@compute @workgroup_size(64)
fn scatter_fallback(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    if (slot >= scatter_slots()) {
        return;
    }
    let id = atomicLoad(&scatter[slot_word(slot, 0u)]);
    gather_list[atomicAdd(&counters[COUNTER_LIST], 1u)] = id | DELTA_SEGMENT;
    atomicStore(&scatter[id], SEGMENT_UNTOUCHED);
}
