// Tone map: mean of the accumulated HDR samples × exposure, clamped, sRGB-encoded, packed
// RGBA8 (alpha 255) for readback. Display only: linear radiance stays in `accum`.
// Rust twin: server/engine/src/passes/tonemap.rs.

struct ToneParams {
    width: u32,
    height: u32,
    exposure: f32,
    pad0: u32,
}

@group(0) @binding(0) var<uniform> params: ToneParams;
@group(0) @binding(1) var<storage, read> accum: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read_write> rgba: array<u32>;

fn srgb_encode(x: f32) -> f32 {
    if (x <= 0.0031308) {
        return 12.92 * x;
    }
    return 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}

fn to_byte(x: f32) -> u32 {
    return u32(clamp(srgb_encode(clamp(x, 0.0, 1.0)), 0.0, 1.0) * 255.0 + 0.5);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let pixel = gid.y * params.width + gid.x;
    let a = accum[pixel];
    let c = a.rgb / max(a.w, 1.0) * params.exposure;
    rgba[pixel] = to_byte(c.r) | (to_byte(c.g) << 8u) | (to_byte(c.b) << 16u) | (255u << 24u);
}
