// Shared pieces: the volume box, trilinear sampling (post-classification) and the transfer
// function lookup. A pass that includes this declares `volume_tex: texture_3d<f32>` and
// `tf_lut: texture_2d<f32>` (one row of TF_LUT_SIZE rgba32float texels: albedo rgb + opacity;
// a texture because llvmpipe loads a storage buffer's entry lane by lane, each lane behind a
// bounds check, and a texel of every lane in one gather).

const TF_LUT_SIZE: u32 = 1024u;

// Ray/box intersection; returns (t_near, t_far), empty when t_near >= t_far.
fn intersect_box(origin: vec3<f32>, dir: vec3<f32>, box_min: vec3<f32>, box_max: vec3<f32>) -> vec2<f32> {
    let inv = 1.0 / dir;
    let t0 = (box_min - origin) * inv;
    let t1 = (box_max - origin) * inv;
    let tmin = min(t0, t1);
    let tmax = max(t0, t1);
    let t_near = max(max(tmin.x, tmin.y), max(tmin.z, 0.0));
    let t_far = min(min(tmax.x, tmax.y), tmax.z);
    return vec2<f32>(t_near, t_far);
}

// Data value at box-relative position u in [0,1]^3: voxel i's centre is at (i + 0.5) / n,
// trilinear between centres, clamped to the edge voxels.
fn sample_volume(u: vec3<f32>) -> f32 {
    let dims = vec3<i32>(textureDimensions(volume_tex));
    let p = u * vec3<f32>(dims) - 0.5;
    let base = floor(p);
    let f = p - base;
    let i0 = clamp(vec3<i32>(base), vec3<i32>(0), dims - 1);
    let i1 = clamp(vec3<i32>(base) + 1, vec3<i32>(0), dims - 1);
    let c000 = textureLoad(volume_tex, vec3<i32>(i0.x, i0.y, i0.z), 0).r;
    let c100 = textureLoad(volume_tex, vec3<i32>(i1.x, i0.y, i0.z), 0).r;
    let c010 = textureLoad(volume_tex, vec3<i32>(i0.x, i1.y, i0.z), 0).r;
    let c110 = textureLoad(volume_tex, vec3<i32>(i1.x, i1.y, i0.z), 0).r;
    let c001 = textureLoad(volume_tex, vec3<i32>(i0.x, i0.y, i1.z), 0).r;
    let c101 = textureLoad(volume_tex, vec3<i32>(i1.x, i0.y, i1.z), 0).r;
    let c011 = textureLoad(volume_tex, vec3<i32>(i0.x, i1.y, i1.z), 0).r;
    let c111 = textureLoad(volume_tex, vec3<i32>(i1.x, i1.y, i1.z), 0).r;
    let x00 = mix(c000, c100, f.x);
    let x10 = mix(c010, c110, f.x);
    let x01 = mix(c001, c101, f.x);
    let x11 = mix(c011, c111, f.x);
    return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}

// Albedo (rgb) and opacity (a) of data value v: the piecewise-linear TF baked into the LUT at
// TF_LUT_SIZE evenly spaced values, linear between entries.
fn classify(v: f32) -> vec4<f32> {
    let x = clamp(v, 0.0, 1.0) * f32(TF_LUT_SIZE - 1u);
    let i = min(u32(x), TF_LUT_SIZE - 2u);
    return mix(tf_entry(i), tf_entry(i + 1u), x - f32(i));
}

// Entry i of the LUT.
fn tf_entry(i: u32) -> vec4<f32> {
    return textureLoad(tf_lut, vec2<u32>(i, 0u), 0);
}

// The opacity alone, for the marches that need no albedo. Since the LUT became a texture a
// texel is loaded whole, so this is classify(v).a (llvmpipe keeps each component in a vector
// of its own, and the unused ones' interpolation is dropped as dead code).
fn classify_opacity(v: f32) -> f32 {
    return classify(v).a;
}
