// Shared pieces: the per-session scene uniforms (camera, box, medium, lights) that every
// technique binds, and the primary camera ray. Rust twin: server/engine/src/scene_gpu.rs.

struct SceneUniforms {
    eye: vec3<f32>,
    tan_half_fov: f32,
    right: vec3<f32>,
    aspect: f32,
    up: vec3<f32>,
    step: f32,
    forward: vec3<f32>,
    density_scale: f32,
    box_min: vec3<f32>,
    g: f32,
    box_max: vec3<f32>,
    light_count: u32,
    env_radiance: vec3<f32>,
    seed: u32,
    width: u32,
    height: u32,
    iteration: u32,
    // A dispatch of the progressive estimators is band row_offset of row_stride (shared/common.wgsl
    // band_row; techniques/progressive.rs: a long iteration runs as bands); 0 and 1 for every
    // other pass.
    row_offset: u32,
    // Macrocells per axis and their edge in voxels (shared/macrocell.wgsl).
    cell_dims: vec3<u32>,
    cell_voxels: u32,
    row_stride: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const LIGHT_DIRECTIONAL: u32 = 0u;
const LIGHT_POINT: u32 = 1u;

// Directional: `vector` is the direction the light travels, `color` its irradiance.
// Point: `vector` is its position, `color` its radiant intensity.
// Lights a scene may hold: protocol::MAX_LIGHTS. Passes bind them as a uniform array: lavapipe
// (llvmpipe) treats a value read from a storage buffer as varying per invocation even at a
// uniform index, and a march along a direction read that way ran ~30× slower.
const MAX_LIGHTS: u32 = 16u;

struct GpuLight {
    vector: vec3<f32>,
    kind: u32,
    color: vec3<f32>,
    pad0: f32,
}

// Direction of the primary ray through continuous pixel position `px` (row 0 at the top).
fn camera_ray_dir(s: SceneUniforms, px: vec2<f32>) -> vec3<f32> {
    let ndc_x = (2.0 * px.x / f32(s.width) - 1.0) * s.aspect * s.tan_half_fov;
    let ndc_y = (1.0 - 2.0 * px.y / f32(s.height)) * s.tan_half_fov;
    return normalize(s.forward + ndc_x * s.right + ndc_y * s.up);
}
