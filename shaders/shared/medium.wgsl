// Shared pieces: the medium at a world point, and the 8³ macrocell that holds it. A pass that
// includes this also includes shared/volume.wgsl and declares `scene: SceneUniforms`.

// Box-relative position of world point p.
fn box_relative(p: vec3<f32>) -> vec3<f32> {
    return (p - scene.box_min) / (scene.box_max - scene.box_min);
}

// Albedo (rgb) and extinction sigma_t (a) at world position p.
fn medium_at(p: vec3<f32>) -> vec4<f32> {
    let c = classify(sample_volume(box_relative(p)));
    return vec4<f32>(c.rgb, c.a * scene.density_scale);
}

// Extinction sigma_t at world position p: medium_at(p).a.
fn extinction_at(p: vec3<f32>) -> f32 {
    return classify_opacity(sample_volume(box_relative(p))) * scene.density_scale;
}

// Macrocell containing box-relative position u.
fn cell_of(u: vec3<f32>) -> vec3<u32> {
    let dims = vec3<f32>(textureDimensions(volume_tex));
    let voxel = vec3<u32>(max(u * dims, vec3<f32>(0.0)));
    return min(voxel / scene.cell_voxels, scene.cell_dims - vec3<u32>(1u));
}
