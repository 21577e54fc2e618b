// Technique `pathtrace`: the unbiased reference. One path per pixel and dispatch, traced by
// the shared path estimator (shared/path.wgsl): delta tracking against the macrocell majorants,
// next-event estimation with ratio tracking, Henyey-Greenstein phase sampling, the environment
// reached by escaping paths, Russian roulette. Rust twin: server/engine/src/passes/pathtrace.rs.

#import shared/common
#import shared/volume
#import shared/scene
#import shared/macrocell
#import shared/tracking
#import shared/lights
#import shared/path

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;

// The hooks of shared/path.wgsl: nothing to record here.
fn track_visit(cell: vec3<u32>) {}
fn track_sample(p: vec3<f32>) {}
fn track_vertex(p: vec3<f32>) {}

// Shadow rays of shared/lights.wgsl: ratio tracking.
fn shadow_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, rng: ptr<function, Rng>) -> f32 {
    return ratio_transmittance(p, dir, t_max, rng);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let y = band_row(gid.y, scene.row_offset, scene.row_stride);
    if (gid.x >= scene.width || y >= scene.height) {
        return;
    }
    let pixel = y * scene.width + gid.x;
    var rng = rng_new(scene.seed, pixel, scene.iteration);
    let px = vec2<f32>(f32(gid.x) + rng_next(&rng), f32(y) + rng_next(&rng));
    let dir = camera_ray_dir(scene, px);
    let radiance = trace_radiance(scene.eye, dir, vec3<f32>(1.0), 0u, MAX_BOUNCES, &rng);
    let estimate = vec4<f32>(radiance, 1.0);
    if (scene.iteration == 0u) {
        accum[pixel] = estimate;
    } else {
        accum[pixel] += estimate;
    }
}
