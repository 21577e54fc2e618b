// Technique `irradiance`, the rendering procedure: one 16 × 8 pixel block per workgroup (the
// paper's §7), one sample per pixel. A camera ray finds its first scattering event (delta
// tracked, or picked along a jittered march: FLAG_MARCHED_VIEW); where
// the cache covers that point its irradiance is used (isotropic phase function: radiance =
// albedo · E / 4π), elsewhere the path tracer continues from it (plain MCVR) and the miss
// claims the creation of a new entry there: the deepest octree node holding the point
// (object-space locking) or the block (screen-space locking, after a rejection test on the
// block's share of misses). Rust twin: server/engine/src/passes/irradiance.rs.

var<workgroup> block_rays: atomic<u32>;
var<workgroup> block_misses: atomic<u32>;
var<workgroup> block_claim: atomic<u32>;

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
    if (x < scene.width && y < scene.height) {
        let pixel = y * scene.width + x;
        let before = accum[pixel];
        var aux = pixel_aux[pixel];
        // The pixel's own sample count numbers its samples (blocks render at their own pace).
        var rng = rng_new(scene.seed, pixel, u32(before.w));
        let px = vec2<f32>(f32(x) + rng_next(&rng), f32(y) + rng_next(&rng));
        let dir = camera_ray_dir(scene, px);
        let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
        // The first scattering event: delta tracked (Exposure Render), or picked among a
        // jittered march's samples in proportion to T·(1 − e^(−σt·dt)) with the march's total
        // weight and transmittance exact (no variance from whether the ray collides).
        var weight = 0.0;
        var transmit = 1.0;
        var p = vec3<f32>(0.0);
        if (hit.x < hit.y) {
            if ((params.flags & FLAG_MARCHED_VIEW) != 0u) {
                let picked = pick_scattering(scene.eye, dir, hit.x, hit.y, &rng);
                weight = picked.weight_sum;
                transmit = picked.transmit;
                p = picked.position;
            } else {
                let event = delta_track(scene.eye, dir, hit.x, hit.y, &rng);
                weight = event.y;
                transmit = 1.0 - event.y;
                p = scene.eye + dir * event.x;
            }
        }
        var radiance = scene.env_radiance * transmit;
        if (weight > 0.0) {
            let albedo = medium_at(p).rgb;
            var cached = Lookup(0.0, vec3<f32>(0.0), 0u);
            if (cache_on) {
                cached = cache_lookup(p);
                atomicAdd(&block_rays, 1u);
            }
            var scattered = vec3<f32>(0.0);
            if (cached.weight > 0.0) {
                scattered = albedo * cached.irradiance * INV_4PI;
            } else {
                if (any(albedo > vec3<f32>(0.0))) {
                    scattered = albedo * direct_light(p, dir, &rng);
                    let u1 = rng_next(&rng);
                    let u2 = rng_next(&rng);
                    let next = sample_hg(dir, scene.g, u1, u2);
                    scattered += trace_radiance(p, next, albedo, 1u, params.bounces, &rng);
                }
                if (cache_on) {
                    atomicAdd(&block_misses, 1u);
                    aux = vec4<f32>(p, aux.w);
                    // Claims are ordered by a per-frame random byte, then the pixel.
                    let claim = (pcg_hash(pixel ^ pcg_hash(params.frame)) & 0xff000000u) | pixel;
                    if (screen_locking) {
                        atomicMin(&block_claim, claim);
                    } else if (atomicLoad(&words[params.node_held_offset + cached.node]) == 0u) {
                        atomicMin(&words[params.node_claim_offset + cached.node], claim);
                    }
                }
            }
            radiance += weight * scattered;
        }
        accum[pixel] = before + vec4<f32>(radiance, 1.0);
        let lum = luminance(radiance);
        aux.w += lum * lum;
        pixel_aux[pixel] = aux;
    }
    workgroupBarrier();
    if (li == 0u && cache_on) {
        let rays = atomicLoad(&block_rays);
        let misses = atomicLoad(&block_misses);
        atomicAdd(&words[COUNTER_HITS], rays - misses);
        atomicAdd(&words[COUNTER_MISSES], misses);
        if (screen_locking && misses > 0u) {
            // §5.2: a block asks for a new entry with probability equal to its share of misses.
            let u = f32(pcg_hash(block ^ pcg_hash(params.frame ^ UPDATE_SALT)) >> 8u) / 16777216.0;
            if (u * f32(rays) < f32(misses)
                && atomicLoad(&words[params.block_held_offset + block]) == 0u) {
                atomicMin(&words[params.block_claim_offset + block], atomicLoad(&block_claim));
            }
        }
    }
}
