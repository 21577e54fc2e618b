// Interactive preview, pass 1: the light volume (preview/common.wgsl). One invocation per grid
// point marches toward every light (midpoint rule at half a grid cell per step, so the volume is
// deterministic and cheap), empty cells skipped; the environment
// channels hold ENV_DIRECTIONS Fibonacci-sphere directions' mean and first moment. Run once per opacity, density or
// light edit; camera moves and colour edits reuse it.

#import preview/common

const ENV_DIRECTIONS: u32 = 8u;

// Transmittance from p along dir over at most t_max (shared/march.wgsl): the midpoint rule at half a
// light-volume cell per step (coarser steps miss walls two voxels thick).
fn light_transmittance(p: vec3<f32>, dir: vec3<f32>, t_max: f32) -> f32 {
    let cell = (scene.box_max - scene.box_min) / vec3<f32>(params.light_dims);
    return transmittance_with_step(p, dir, t_max, 0.5, 0.5 * min(min(cell.x, cell.y), cell.z));
}

// Direction k of ENV_DIRECTIONS, evenly spread over the sphere (Fibonacci lattice).
fn env_direction(k: u32) -> vec3<f32> {
    let z = 1.0 - (2.0 * f32(k) + 1.0) / f32(ENV_DIRECTIONS);
    let r = sqrt(max(0.0, 1.0 - z * z));
    let phi = f32(k) * 2.399963229728653;
    return vec3<f32>(r * cos(phi), r * sin(phi), z);
}

// One grid plane per workgroup layer, so that a build can run a few planes at a time.
@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let gid = vec3<u32>(id.xy, id.z + params.z_offset);
    if (any(gid >= params.light_dims)) {
        return;
    }
    let u = (vec3<f32>(gid) + 0.5) / vec3<f32>(params.light_dims);
    let p = scene.box_min + u * (scene.box_max - scene.box_min);
    for (var l = 0u; l < scene.light_count; l++) {
        let light = lights[l];
        var tr = 0.0;
        if (light.kind == LIGHT_DIRECTIONAL) {
            tr = light_transmittance(p, -light.vector, 1e30);
        } else {
            let offset = light.vector - p;
            let dist = length(offset);
            tr = light_transmittance(p, offset / max(dist, 1e-6), dist);
        }
        light_volume[light_index(l, gid)] = tr;
    }
    // The environment's transmittance as a function of direction to first order,
    // T(ω) ≈ mean + lobe·ω (spherical harmonics l ≤ 1): the view pass weights the lobe
    // by the phase function's mean cosine g.
    var mean = 0.0;
    var lobe = vec3<f32>(0.0);
    // The approximate multiple scattering needs the mean even without an environment.
    if (any(scene.env_radiance > vec3<f32>(0.0)) || params.multiple != 0u) {
        for (var k = 0u; k < ENV_DIRECTIONS; k++) {
            let w = env_direction(k);
            let tr = light_transmittance(p, w, 1e30);
            mean += tr;
            lobe += tr * w;
        }
        mean /= f32(ENV_DIRECTIONS);
        lobe *= 3.0 / f32(ENV_DIRECTIONS);
    }
    let env = scene.light_count;
    light_volume[light_index(env, gid)] = mean;
    light_volume[light_index(env + 1u, gid)] = lobe.x;
    light_volume[light_index(env + 2u, gid)] = lobe.y;
    light_volume[light_index(env + 3u, gid)] = lobe.z;
}
