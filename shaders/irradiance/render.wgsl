// Technique `irradiance`, the rendering procedure: one 16 × 8 pixel block per workgroup (the
// paper's §7), one sample per pixel. A camera ray finds its first scattering event (delta
// tracked, or picked along a jittered march: FLAG_MARCHED_VIEW); where
// the cache covers that point its irradiance is used (isotropic phase function: radiance =
// albedo · E / 4π), elsewhere the path tracer continues from one of them (plain MCVR) and
// that miss claims the creation of a new entry there: the deepest octree node holding the
// point (object-space locking) or the block (screen-space locking, after a rejection test on
// the block's share of misses). With FLAG_TRACED_DIRECT (beyond the paper) the directional and
// point lights' direct light is traced at every event and the cache holds only the rest.
// Rust twin: server/engine/src/techniques/irradiance/gpu.rs.

#import irradiance/paths
#import irradiance/cache

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(7) var<uniform> dispatch: DispatchInfo;
@group(0) @binding(8) var<storage, read_write> entries: array<CacheEntry>;
@group(0) @binding(9) var<storage, read_write> radii: array<atomic<u32>>;
@group(0) @binding(10) var<storage, read> octree: array<u32>;
@group(0) @binding(11) var<storage, read_write> words: array<atomic<u32>>;
@group(0) @binding(12) var<storage, read_write> pixel_aux: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> blocks: array<u32>;
@group(0) @binding(15) var<storage, read> cell_bins: array<vec2<u32>>;
@group(0) @binding(16) var<storage, read_write> bounds: array<vec4<f32>>;

var<workgroup> block_rays: atomic<u32>;
var<workgroup> block_misses: atomic<u32>;
// The block's claim: its miss with the smallest key, and that miss's deepest octree node.
var<workgroup> block_claim: atomic<u32>;
var<workgroup> block_claim_node: u32;

// A sample's scattering events (view_picks_along), and the octree node of each that missed.
const MAX_VIEW_PICKS: u32 = 16u;
var<private> picked_position: array<vec3<f32>, MAX_VIEW_PICKS>;
var<private> picked_albedo: array<vec3<f32>, MAX_VIEW_PICKS>;
var<private> miss_node_of: array<u32, MAX_VIEW_PICKS>;

// The jittered view march of shared/march.wgsl (same lattice, empty cells skipped, same cut-off):
// the total weight Σ T·(1 − e^(−σt·dt)) and the transmittance through it.
fn view_weight(origin: vec3<f32>, dir: vec3<f32>, t0: f32, t1: f32, jitter: f32) -> vec2<f32> {
    var weight = 0.0;
    var transmit = 1.0;
    var k = 0.0;
    loop {
        let t = t0 + (k + jitter) * scene.step;
        if (t >= t1 || transmit < VIEW_T_CUTOFF) {
            break;
        }
        let p = origin + dir * t;
        let cell = cell_of(box_relative(p));
        if (cell_is_empty(cell)) {
            k = skip_empty_cell(origin, dir, cell, t0, scene.step, jitter, k);
            continue;
        }
        let alpha = 1.0 - exp(-extinction_at(p) * scene.step);
        weight += transmit * alpha;
        transmit *= 1.0 - alpha;
        k += 1.0;
    }
    return vec2<f32>(weight, transmit);
}

// The same march again, taking `count` points at the cumulative weights (u + j)/count · total
// (systematic resampling: point j stands for total / count of the weight).
fn view_picks_along(
    origin: vec3<f32>,
    dir: vec3<f32>,
    t0: f32,
    t1: f32,
    jitter: f32,
    total: f32,
    count: u32,
    u: f32,
) {
    var cumulative = 0.0;
    var transmit = 1.0;
    var next = 0u;
    var k = 0.0;
    var last = origin + dir * t0;
    loop {
        let t = t0 + (k + jitter) * scene.step;
        if (t >= t1 || transmit < VIEW_T_CUTOFF || next >= count) {
            break;
        }
        let p = origin + dir * t;
        let cell = cell_of(box_relative(p));
        if (cell_is_empty(cell)) {
            k = skip_empty_cell(origin, dir, cell, t0, scene.step, jitter, k);
            continue;
        }
        let m = medium_at(p);
        let alpha = 1.0 - exp(-m.a * scene.step);
        cumulative += transmit * alpha;
        if (alpha > 0.0) {
            last = p;
        }
        loop {
            if (next >= count || (u + f32(next)) / f32(count) * total >= cumulative) {
                break;
            }
            picked_position[next] = p;
            picked_albedo[next] = m.rgb;
            next += 1u;
        }
        transmit *= 1.0 - alpha;
        k += 1.0;
    }
    // Rounding can leave the last threshold a hair above the sum: the last point takes it.
    for (var j = next; j < count; j++) {
        picked_position[j] = last;
        picked_albedo[j] = medium_at(last).rgb;
    }
}

// The cache at event j, counted as one of the block's lookups; a miss keeps the octree node
// its claim would lock.
fn look_up(j: u32) -> Lookup {
    let cached = cache_lookup(picked_position[j]);
    atomicAdd(&block_rays, 1u);
    if (cached.weight <= 0.0) {
        miss_node_of[j] = cached.node;
    }
    return cached;
}

@compute @workgroup_size(16, 8)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    if (li == 0u) {
        atomicStore(&block_rays, 0u);
        atomicStore(&block_misses, 0u);
        atomicStore(&block_claim, NO_CLAIM);
    }
    workgroupBarrier();
    let block = blocks[dispatch.first + wid.x];
    let x = (block % params.blocks_x) * 16u + lid.x;
    let y = (block / params.blocks_x) * 8u + lid.y;
    let cache_on = (params.flags & FLAG_CACHE) != 0u;
    let screen_locking = (params.flags & FLAG_SCREEN_LOCKING) != 0u;
    var my_claim = NO_CLAIM;
    var my_node = 0u;
    if (x < scene.width && y < scene.height) {
        let pixel = y * scene.width + x;
        let before = accum[pixel];
        var aux = pixel_aux[pixel];
        // The pixel's own sample count numbers its samples (blocks render at their own pace).
        var rng = rng_new(scene.seed, pixel, u32(before.w));
        let px = vec2<f32>(f32(x) + rng_next(&rng), f32(y) + rng_next(&rng));
        let dir = camera_ray_dir(scene, px);
        let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
        // The scattering events of this sample: one delta-tracked collision (Exposure Render),
        // or `view_picks` points drawn along a jittered march in proportion to
        // T·(1 − e^(−σt·dt)) by systematic resampling, each standing for weight / view_picks of
        // the march's exact total weight (no variance from whether the ray collides, and the
        // cached part of the in-scattering nearly noise-free).
        var weight = 0.0;
        var transmit = 1.0;
        var picks = 0u;
        if (hit.x < hit.y) {
            if ((params.flags & FLAG_MARCHED_VIEW) != 0u) {
                let jitter = rng_next(&rng);
                let total = view_weight(scene.eye, dir, hit.x, hit.y, jitter);
                weight = total.x;
                transmit = total.y;
                if (weight > 0.0) {
                    picks = max(params.view_picks, 1u);
                    view_picks_along(scene.eye, dir, hit.x, hit.y, jitter, weight, picks, rng_next(&rng));
                }
            } else {
                let event = delta_track(scene.eye, dir, hit.x, hit.y, &rng);
                if (event.y > 0.0) {
                    weight = 1.0;
                    transmit = 0.0;
                    picks = 1u;
                    picked_position[0] = scene.eye + dir * event.x;
                    picked_albedo[0] = medium_at(picked_position[0]).rgb;
                }
            }
        }
        var radiance = scene.env_radiance * transmit;
        var scattered = vec3<f32>(0.0);
        var misses = 0u;
        var miss = 0u;
        if (traced_direct()) {
            // The directional and point lights' direct light is traced at every event (a shadow
            // ray per light each: cheap next to the march, and it removes most of the variance
            // of where along the ray the event lies); the rest, from one event chosen uniformly
            // for all of them, comes from the cache (which holds only that) or a traced path.
            for (var j = 0u; j < picks; j++) {
                if (any(picked_albedo[j] > vec3<f32>(0.0))) {
                    scattered += picked_albedo[j] * direct_light(picked_position[j], dir, &rng);
                }
            }
            if (picks > 0u) {
                miss = min(u32(rng_next(&rng) * f32(picks)), picks - 1u);
                misses = 1u;
                if (cache_on) {
                    let cached = look_up(miss);
                    if (cached.weight > 0.0) {
                        scattered += f32(picks) * picked_albedo[miss] * cached.irradiance * INV_4PI;
                        misses = 0u;
                    }
                }
            }
        } else {
            for (var j = 0u; j < picks; j++) {
                var found = false;
                if (cache_on) {
                    let cached = look_up(j);
                    if (cached.weight > 0.0) {
                        scattered += picked_albedo[j] * cached.irradiance * INV_4PI;
                        found = true;
                    }
                }
                if (!found) {
                    // One miss, chosen uniformly, is path traced for all of them.
                    misses += 1u;
                    if (rng_next(&rng) * f32(misses) < 1.0) {
                        miss = j;
                    }
                }
            }
        }
        if (misses > 0u) {
            let p = picked_position[miss];
            let albedo = picked_albedo[miss];
            var traced = vec3<f32>(0.0);
            if (any(albedo > vec3<f32>(0.0))) {
                if (!traced_direct()) {
                    traced = albedo * direct_light(p, dir, &rng);
                }
                // With single scattering and no environment the scattered path's one flight
                // can only find darkness (trace_radiance returns exactly 0): skip it.
                if (params.bounces > 1u || any(scene.env_radiance > vec3<f32>(0.0))) {
                    let u1 = rng_next(&rng);
                    let u2 = rng_next(&rng);
                    let next = sample_hg(dir, scene.g, u1, u2);
                    traced += trace_radiance(p, next, albedo, 1u, params.bounces, &rng);
                }
            }
            // A traced event stands for `misses` events (FLAG_TRACED_DIRECT: for all of them).
            scattered += f32(select(misses, picks, traced_direct())) * traced;
            if (cache_on) {
                atomicAdd(&block_misses, misses);
                aux = vec4<f32>(p, aux.w);
                // Claims are ordered by a per-frame random byte, then the pixel; a block puts
                // forward one (one global atomic per block, not per miss).
                my_claim = (pcg_hash(pixel ^ pcg_hash(params.frame)) & 0xff000000u) | pixel;
                my_node = miss_node_of[miss];
                atomicMin(&block_claim, my_claim);
            }
        }
        if (picks > 0u) {
            radiance += weight / f32(picks) * scattered;
        }
        accum[pixel] = before + vec4<f32>(radiance, 1.0);
        let lum = luminance(radiance);
        aux.w += lum * lum;
        pixel_aux[pixel] = aux;
    }
    workgroupBarrier();
    let best = atomicLoad(&block_claim);
    if (my_claim != NO_CLAIM && my_claim == best) {
        block_claim_node = my_node;
    }
    workgroupBarrier();
    if (li == 0u && cache_on) {
        let rays = atomicLoad(&block_rays);
        let misses = atomicLoad(&block_misses);
        atomicAdd(&words[COUNTER_HITS], rays - misses);
        atomicAdd(&words[COUNTER_MISSES], misses);
        if (misses > 0u && screen_locking) {
            // §5.2: a block asks for a new entry with probability equal to its share of misses.
            let u = f32(pcg_hash(block ^ pcg_hash(params.frame ^ UPDATE_SALT)) >> 8u) / 16777216.0;
            if (u * f32(rays) < f32(misses)
                && atomicLoad(&words[params.block_held_offset + block]) == 0u) {
                atomicMin(&words[params.block_claim_offset + block], best);
            }
        } else if (misses > 0u) {
            let node = block_claim_node;
            if (atomicLoad(&words[params.node_held_offset + node]) == 0u) {
                atomicMin(&words[params.node_claim_offset + node], best);
            }
        }
    }
}
