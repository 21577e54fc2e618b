// Technique `irradiance`, the cache update procedure (§4.3): one thread per 16 × 8 block picks
// a random pixel of it, finds the first collision of a camera ray through it as the rendering
// does, and evaluates every entry whose zone holds that point. While the predictions of two of
// them differ by more than the update threshold, the entry with the lowest weight loses the
// point: its radii in the point's octant shrink, each in proportion to the point's coordinate
// along it (Fig. 6), until the point lies on its zone's edge. With FLAG_VALIDATE_HITS (beyond the
// paper) the point's irradiance is first estimated afresh, and every entry predicting outside
// that estimate's 95% interval (widened by the threshold) loses the point too. A validation
// round (DispatchInfo.validate, a budget of its own) does only that check, at points of its
// own. Rust twin: server/engine/src/techniques/irradiance/gpu.rs.

#import irradiance/paths
#import irradiance/cache

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(7) var<uniform> dispatch: DispatchInfo;
@group(0) @binding(8) var<storage, read_write> entries: array<CacheEntry>;
@group(0) @binding(9) var<storage, read_write> radii: array<atomic<u32>>;
@group(0) @binding(10) var<storage, read> octree: array<u32>;
@group(0) @binding(11) var<storage, read_write> words: array<atomic<u32>>;
@group(0) @binding(15) var<storage, read> cell_bins: array<vec2<u32>>;
@group(0) @binding(16) var<storage, read_write> bounds: array<vec4<f32>>;

// Shrinks entry e's radii in the octant of x so that x lies just outside its zone: r_i − s·|l_i|
// for the smallest s with Σ l_i² / (r_i − s·|l_i|)² ≥ 1 (bisection).
fn exclude_point(e: u32, x: vec3<f32>) {
    let local = local_coordinates(entries[e], x);
    let h = local.half_axes;
    let r = vec3<f32>(radius_of(e, h.x), radius_of(e, h.y), radius_of(e, h.z));
    let a = abs(local.l);
    // s < s_max keeps every radius positive.
    var s_max = 1e30;
    for (var i = 0u; i < 3u; i++) {
        if (a[i] > 0.0) {
            s_max = min(s_max, r[i] / a[i]);
        }
    }
    if (s_max >= 1e30) {
        return;
    }
    var lo = 0.0;
    var hi = s_max;
    for (var step = 0u; step < 24u; step++) {
        let mid = 0.5 * (lo + hi);
        let shrunk = r - mid * a;
        if (dot(a * a, 1.0 / (shrunk * shrunk)) >= 1.0) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let shrunk = max(r - hi * a, vec3<f32>(params.min_radius));
    atomicMin(&radii[e * 6u + h.x], bitcast<u32>(shrunk.x));
    atomicMin(&radii[e * 6u + h.y], bitcast<u32>(shrunk.y));
    atomicMin(&radii[e * 6u + h.z], bitcast<u32>(shrunk.z));
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let block = gid.x;
    if (block >= params.block_count) {
        return;
    }
    let validation_round = dispatch.validate != 0u;
    var rng = rng_new(
        scene.seed ^ select(UPDATE_SALT, VALIDATE_SALT, validation_round),
        block,
        dispatch.round,
    );
    let x = (block % params.blocks_x) * 16u + min(u32(rng_next(&rng) * 16.0), 15u);
    let y = (block / params.blocks_x) * 8u + min(u32(rng_next(&rng) * 8.0), 7u);
    if (x >= scene.width || y >= scene.height) {
        return;
    }
    let px = vec2<f32>(f32(x) + rng_next(&rng), f32(y) + rng_next(&rng));
    let dir = camera_ray_dir(scene, px);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        return;
    }
    let event = delta_track(scene.eye, dir, hit.x, hit.y, &rng);
    if (event.y == 0.0) {
        return;
    }
    let p = scene.eye + dir * event.x;

    // Every entry whose zone holds p, with its weight and log-luminance prediction.
    var ids: array<u32, MAX_OVERLAP>;
    var weights: array<f32, MAX_OVERLAP>;
    var predictions: array<f32, MAX_OVERLAP>;
    var n = 0u;
    var node = 0u;
    var lo = params.root_min;
    var edge = params.root_edge;
    for (var depth = 0u; depth < MAX_DEPTH; depth++) {
        let base = node * 4u;
        let first = params.refs_offset + octree[base + 1u];
        let count = octree[base + 2u];
        for (var i = 0u; i < count && n < MAX_OVERLAP; i++) {
            let e = octree[first + i];
            let prediction = entry_predict(e, p);
            if (prediction.weight > 0.0) {
                ids[n] = e;
                weights[n] = prediction.weight;
                predictions[n] = log(max(luminance(exp(prediction.log_irradiance)), IRRADIANCE_FLOOR));
                n++;
            }
        }
        let child = octree[base];
        if (child == 0u) {
            break;
        }
        edge *= 0.5;
        let next = descend(child, lo, edge, p);
        node = next.child;
        lo = next.lo;
    }

    let tolerance = log(1.0 + params.update_threshold);
    if (n > 0u && (validation_round || (params.flags & FLAG_VALIDATE_HITS) != 0u)) {
        let samples = select(VALIDATION_SAMPLES, max(params.validation_samples, 2u), validation_round);
        let allowed = select(
            tolerance,
            log(1.0 + params.validation_threshold),
            validation_round,
        );
        var sum = 0.0;
        var sum_sq = 0.0;
        for (var s = 0u; s < samples; s++) {
            let l = luminance(irradiance_sample(p, &rng));
            sum += l;
            sum_sq += l * l;
        }
        let k = f32(samples);
        let mean = sum / k;
        let half_width = 1.96 * sqrt(max(0.0, (sum_sq - k * mean * mean) / (k - 1.0)) / k);
        let high = log(max(mean + half_width, IRRADIANCE_FLOOR)) + allowed;
        let low = log(max(mean - half_width, IRRADIANCE_FLOOR)) - allowed;
        for (var i = 0u; i < n; i++) {
            if (predictions[i] > high || predictions[i] < low) {
                exclude_point(ids[i], p);
                weights[i] = 0.0;
                atomicAdd(&words[COUNTER_REDUCTIONS], 1u);
            }
        }
    }
    if (validation_round) {
        return;
    }
    for (var remaining = n; remaining >= 2u; remaining--) {
        var low = 1e30;
        var high = -1e30;
        var weakest = 0u;
        for (var i = 0u; i < n; i++) {
            if (weights[i] > 0.0) {
                low = min(low, predictions[i]);
                high = max(high, predictions[i]);
                if (weights[weakest] <= 0.0 || weights[i] < weights[weakest]) {
                    weakest = i;
                }
            }
        }
        if (high - low <= tolerance) {
            break;
        }
        exclude_point(ids[weakest], p);
        weights[weakest] = 0.0;
        atomicAdd(&words[COUNTER_REDUCTIONS], 1u);
    }
}
