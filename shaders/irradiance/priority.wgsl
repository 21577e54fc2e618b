// Technique `irradiance`, rendering priorities (§6, "expected gain"): per 16 × 8 block, the mean
// over its pixels of ΔE = 1.96 (√(S²/N) − √(S²/(N + 1))), the reduction of the 95% error
// estimate one more sample would bring if the sample variance S² stayed the same (Eq. 12).
// Pixels with fewer than two samples get PRIORITY_UNSAMPLED. Rust twin:
// server/engine/src/techniques/irradiance/gpu.rs.

#import irradiance/common

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(7) var<uniform> dispatch: DispatchInfo;
@group(0) @binding(12) var<storage, read_write> pixel_aux: array<vec4<f32>>;
@group(0) @binding(13) var<storage, read_write> blocks: array<u32>;

const PRIORITY_UNSAMPLED: f32 = 1e30;

var<workgroup> gains: array<f32, 128>;
// Per thread: pixels inside the image (x) and those among them with fewer than two samples (y).
var<workgroup> counts: array<vec2<u32>, 128>;

@compute @workgroup_size(16, 8)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let block = dispatch.first + wid.x;
    let x = (block % params.blocks_x) * 16u + lid.x;
    let y = (block / params.blocks_x) * 8u + lid.y;
    var gain = 0.0;
    var count = vec2<u32>(0u);
    if (block < params.block_count && x < scene.width && y < scene.height) {
        let pixel = y * scene.width + x;
        let sum = accum[pixel];
        let n = sum.w;
        count.x = 1u;
        if (n < 2.0) {
            count.y = 1u;
        } else {
            let mean = luminance(sum.rgb) / n;
            let variance = max(0.0, (pixel_aux[pixel].w - n * mean * mean) / (n - 1.0));
            gain = 1.96 * (sqrt(variance / n) - sqrt(variance / (n + 1.0)));
        }
    }
    gains[li] = gain;
    counts[li] = count;
    workgroupBarrier();
    for (var offset = 64u; offset > 0u; offset >>= 1u) {
        if (li < offset) {
            gains[li] += gains[li + offset];
            counts[li] += counts[li + offset];
        }
        workgroupBarrier();
    }
    if (li == 0u && block < params.block_count) {
        var priority = gains[0] / f32(max(counts[0].x, 1u));
        if (counts[0].y > 0u) {
            priority = PRIORITY_UNSAMPLED;
        }
        blocks[params.priority_offset + block] = bitcast<u32>(priority);
    }
}
