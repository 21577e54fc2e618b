// Shared pieces: 8³ macrocells for empty-space skipping and majorants. A pass that includes
// this also includes shared/volume.wgsl and declares `scene: SceneUniforms` and
// `cell_max_opacity: array<f32>` (the largest opacity any trilinear sample in each cell can
// classify to under the current TF; server/engine/src/macrocell.rs).

#import shared/medium

// Majorant of sigma_t over cell c (delta and ratio tracking).
fn cell_majorant(c: vec3<u32>) -> f32 {
    let index = (c.z * scene.cell_dims.y + c.y) * scene.cell_dims.x + c.x;
    return cell_max_opacity[index] * scene.density_scale;
}

// True when nothing in cell c can scatter or absorb: samples there contribute exactly zero.
fn cell_is_empty(c: vec3<u32>) -> bool {
    let index = (c.z * scene.cell_dims.y + c.y) * scene.cell_dims.x + c.x;
    return cell_max_opacity[index] == 0.0;
}

// Ray parameter at which origin + t·dir leaves cell c.
fn cell_exit(origin: vec3<f32>, dir: vec3<f32>, c: vec3<u32>) -> f32 {
    let dims = vec3<f32>(textureDimensions(volume_tex));
    let size = scene.box_max - scene.box_min;
    let lo = scene.box_min + vec3<f32>(c * scene.cell_voxels) / dims * size;
    let hi = scene.box_min + min(vec3<f32>((c + vec3<u32>(1u)) * scene.cell_voxels), dims) / dims * size;
    let inv = 1.0 / dir;
    let t_far = max((lo - origin) * inv, (hi - origin) * inv);
    return min(min(t_far.x, t_far.y), t_far.z);
}

// Index of the next sample of the jittered lattice t = t0 + (k + jitter)·step at or after the
// exit of the empty cell c that holds sample k: samples inside it are skipped, the rest of the
// lattice (and so every estimate) is unchanged.
fn skip_empty_cell(origin: vec3<f32>, dir: vec3<f32>, c: vec3<u32>, t0: f32, step: f32, jitter: f32, k: f32) -> f32 {
    let t_exit = cell_exit(origin, dir, c);
    return max(k + 1.0, ceil((t_exit - t0) / step - jitter));
}
