// Technique `raymarch`: single scattering with shadow rays to every light and the environment.
// One progressive sample per pixel and dispatch: a jittered march along the view ray picks one
// scattering location with probability proportional to its weight T·(1 − exp(−σt·dt))
// (weighted reservoir), where shadow rays to every light and one phase-sampled environment ray
// estimate the in-scattered radiance. Transmittance to the background is computed exactly for
// the march, so an absorbing-only medium is noise-free up to the jitter of the step.
// Rust twin: server/engine/src/passes/raymarch.rs.

#import shared/common
#import shared/volume
#import shared/scene
#import shared/macrocell
#import shared/march
#import shared/lights

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(3) var<uniform> lights: array<GpuLight, MAX_LIGHTS>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;

// Shadow rays of shared/lights.wgsl: the jittered march with a fresh jitter.
fn shadow_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32, rng: ptr<function, Rng>) -> f32 {
    return transmittance(p, dir, t_max, rng_next(rng));
}

// Radiance scattered toward -view_dir at p per unit scattering albedo.
fn in_scattered(p: vec3<f32>, view_dir: vec3<f32>, rng: ptr<function, Rng>) -> vec3<f32> {
    var s = direct_light(p, view_dir, rng);
    if (any(scene.env_radiance > vec3<f32>(0.0))) {
        // Direction toward the environment sampled by the phase function: weight 1.
        let u1 = rng_next(rng);
        let u2 = rng_next(rng);
        let toward_env = sample_hg(view_dir, scene.g, u1, u2);
        s += scene.env_radiance * transmittance(p, toward_env, 1e30, rng_next(rng));
    }
    return s;
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

    var radiance = scene.env_radiance;
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x < hit.y) {
        let s = pick_scattering(scene.eye, dir, hit.x, hit.y, &rng);
        radiance = scene.env_radiance * s.transmit;
        if (s.weight_sum > 0.0 && any(s.albedo > vec3<f32>(0.0))) {
            radiance += s.weight_sum * s.albedo * in_scattered(s.position, dir, &rng);
        }
    }

    let estimate = vec4<f32>(radiance, 1.0);
    if (scene.iteration == 0u) {
        accum[pixel] = estimate;
    } else {
        accum[pixel] += estimate;
    }
}
