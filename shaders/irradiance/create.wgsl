// Technique `irradiance`, the cache-entry creation procedure (§4.2): one round per dispatch, one
// workgroup per pending request. 63 threads each take one irradiance sample at one of the seven
// estimation points (the centre and ± Δ along the axes of the entry's local frame), nine per
// point; the seven points of a sample share their random numbers (common random numbers make
// the ratios E_Δ / E_0 of Eq. 6 far less noisy than independent estimates) and neighbouring
// threads, so the lanes that run together trace nearly the same paths. When the centre estimate meets
// the error criterion of Eq. 5 (or has max_samples), the entry is finished: its virtual
// extinction coefficients per half-axis (Eq. 6); its radii follow from them when the requests
// pass stores it. Rust twin: server/engine/src/techniques/irradiance/gpu.rs.

#import irradiance/paths

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(14) var<storage, read_write> requests: array<Request>;
@group(0) @binding(15) var<storage, read> cell_bins: array<vec2<u32>>;

const SAMPLES_PER_ROUND: u32 = 9u;

var<workgroup> point_sums: array<vec4<f32>, 64>;
// FLAG_TRACED_DIRECT: the direct irradiance luminance of each centre sample.
var<workgroup> direct_sums: array<f32, SAMPLES_PER_ROUND>;
var<workgroup> hist: array<atomic<u32>, 4>;

@compute @workgroup_size(64)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    if (t < 4u) {
        atomicStore(&hist[t], 0u);
    }
    workgroupBarrier();
    let slot = wid.x;
    let req = requests[slot];
    let is_pending = req.state == REQUEST_PENDING;
    let point = t % 7u;
    let sample_index = t / 7u;
    var estimate = vec4<f32>(0.0);
    if (is_pending && sample_index < SAMPLES_PER_ROUND) {
        recording = true;
        recorded_opacity = vec2<u32>(0u);
        recorded_colour = vec2<u32>(0u);
        var rng = rng_new(scene.seed ^ CREATE_SALT, req.key, req.count + sample_index);
        var y = req.position;
        if (point > 0u) {
            let half_axis = point - 1u;
            let frame = orthonormal_basis(req.normal);
            let sign = select(1.0, -1.0, (half_axis & 1u) == 1u);
            y += frame[half_axis / 2u] * (sign * req.delta);
        }
        let e = irradiance_sample(y, &rng);
        let lum = luminance(e);
        estimate = vec4<f32>(e, lum * lum);
        if (point == 0u && traced_direct()) {
            // What the render pass adds to this entry's light: Eq. 5 bounds the entry's error
            // relative to the whole irradiance a pixel shows, not to its indirect share alone.
            // It only decides when the estimate may stop, so its rays are not recorded: the
            // entry's value is an estimate of the indirect light whatever they find.
            recording = false;
            marched_shadows = true;
            direct_sums[sample_index] = luminance(direct_irradiance(y, &rng));
            marched_shadows = false;
        }
        atomicOr(&hist[0], recorded_opacity.x);
        atomicOr(&hist[1], recorded_opacity.y);
        atomicOr(&hist[2], recorded_colour.x);
        atomicOr(&hist[3], recorded_colour.y);
    }
    point_sums[t] = estimate;
    workgroupBarrier();
    var total = vec4<f32>(0.0);
    if (t < 7u) {
        for (var k = 0u; k < SAMPLES_PER_ROUND; k++) {
            total += point_sums[k * 7u + t];
        }
    }
    workgroupBarrier();
    if (t < 7u) {
        point_sums[t] = total;
    }
    workgroupBarrier();
    if (t != 0u || !is_pending) {
        return;
    }
    var r = req;
    for (var p = 0u; p < 7u; p++) {
        r.sums[p] += point_sums[p];
    }
    if (traced_direct()) {
        for (var k = 0u; k < SAMPLES_PER_ROUND; k++) {
            r.direct_sum += direct_sums[k];
        }
    }
    r.count += SAMPLES_PER_ROUND;
    r.opacity_lo |= atomicLoad(&hist[0]);
    r.opacity_hi |= atomicLoad(&hist[1]);
    r.colour_lo |= atomicLoad(&hist[2]);
    r.colour_hi |= atomicLoad(&hist[3]);
    let n = f32(r.count);
    let mean = r.sums[0].rgb / n;
    let mean_lum = luminance(mean);
    let variance = max(0.0, (r.sums[0].w - n * mean_lum * mean_lum) / max(n - 1.0, 1.0));
    // Eq. 5: the 95% confidence interval within γ/(γ + 1) of the estimate (of the dark floor
    // where the estimate is darker: there the error is absolute, not relative). An indirect
    // entry's estimate is relative to all the light at its centre (direct_sum is 0 otherwise).
    let shown = mean_lum + r.direct_sum / n;
    let bound = params.gamma / (params.gamma + 1.0) * max(shown, params.dark_floor);
    let converged = 1.96 * sqrt(variance / n) <= bound;
    if ((r.count >= params.min_samples && converged) || r.count >= params.max_samples) {
        var entry: CacheEntry;
        entry.position = r.position;
        entry.key = r.key;
        entry.normal = r.normal;
        entry.samples = r.count;
        entry.irradiance = mean;
        let e0 = max(mean, vec3<f32>(IRRADIANCE_FLOOR));
        let lum0 = max(mean_lum, IRRADIANCE_FLOOR);
        // Coefficients beyond this would only extrapolate noise across a voxel or two.
        let limit = log(1e6) / r.delta;
        for (var h = 0u; h < 6u; h++) {
            let e = r.sums[1u + h].rgb / n;
            let rgb = -log(max(e, vec3<f32>(IRRADIANCE_FLOOR)) / e0) / r.delta;
            let lum = -log(max(luminance(e), IRRADIANCE_FLOOR) / lum0) / r.delta;
            entry.sigma[h] = clamp(vec4<f32>(rgb, lum), vec4<f32>(-limit), vec4<f32>(limit));
        }
        entry.opacity_lo = r.opacity_lo;
        entry.opacity_hi = r.opacity_hi;
        entry.colour_lo = r.colour_lo;
        entry.colour_hi = r.colour_hi;
        entry.delta = r.delta;
        r.entry = entry;
        r.state = REQUEST_DONE;
    }
    requests[slot] = r;
}
