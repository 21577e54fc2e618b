// Interactive preview, pass 2: one deterministic view ray per preview pixel (its centre),
// composited front to back at one voxel per step (twice raymarch's), with empty-space
// skipping and early ray termination; the light at each sample comes from the light volume
// (trilinear), so no sample casts a shadow ray. The same single-scattering sum as raymarch's
// estimator, Σ T·(1 − exp(−σt·dt))·albedo·S(p) + T·L_env, without its noise.

#import preview/common

// Preview steps are this multiple of scene.step (half a voxel).
const PREVIEW_STEP_SCALE: f32 = 2.0;

// Below this view transmittance the ray stops: it can miss at most this share of the light.
const PREVIEW_T_CUTOFF: f32 = 1e-3;

// Channel c of the light volume at box-relative u, trilinear between grid points (clamped).
fn light_at(c: u32, u: vec3<f32>) -> f32 {
    let dims = vec3<i32>(params.light_dims);
    let q = u * vec3<f32>(dims) - 0.5;
    let base = floor(q);
    let f = q - base;
    let i0 = vec3<u32>(clamp(vec3<i32>(base), vec3<i32>(0), dims - 1));
    let i1 = vec3<u32>(clamp(vec3<i32>(base) + 1, vec3<i32>(0), dims - 1));
    let c000 = light_volume[light_index(c, vec3<u32>(i0.x, i0.y, i0.z))];
    let c100 = light_volume[light_index(c, vec3<u32>(i1.x, i0.y, i0.z))];
    let c010 = light_volume[light_index(c, vec3<u32>(i0.x, i1.y, i0.z))];
    let c110 = light_volume[light_index(c, vec3<u32>(i1.x, i1.y, i0.z))];
    let c001 = light_volume[light_index(c, vec3<u32>(i0.x, i0.y, i1.z))];
    let c101 = light_volume[light_index(c, vec3<u32>(i1.x, i0.y, i1.z))];
    let c011 = light_volume[light_index(c, vec3<u32>(i0.x, i1.y, i1.z))];
    let c111 = light_volume[light_index(c, vec3<u32>(i1.x, i1.y, i1.z))];
    let x00 = mix(c000, c100, f.x);
    let x10 = mix(c010, c110, f.x);
    let x01 = mix(c001, c101, f.x);
    let x11 = mix(c011, c111, f.x);
    return mix(mix(x00, x10, f.y), mix(x01, x11, f.y), f.z);
}

// The light volume's transmittance toward a light travelling `travel` at p, looked up one grid
// cell toward the light: a surface lit from outside then reads the grid points outside it,
// not the dark ones inside the material it is the surface of (the grid is coarser than a
// wall is thick); shadow edges move by at most one cell.
const LIGHT_OFFSET_CELLS: f32 = 0.25;

fn light_toward(l: u32, p: vec3<f32>, travel: vec3<f32>) -> f32 {
    let cell = (scene.box_max - scene.box_min) / vec3<f32>(params.light_dims);
    return light_at(l, box_relative(p - travel * cell * LIGHT_OFFSET_CELLS));
}

// Octaves of the approximate multiple scattering (below).
const MS_OCTAVES: u32 = 3u;

// Light reaching p, per unit albedo of the sample: `single` toward −view_dir as raymarch's
// in_scattered estimates it, with every transmittance looked up; `multiple` (only when
// params.multiple is set) an approximation of the light scattered more than once, for the GI
// techniques' previews. It follows Wrenninge's octaves ("Oz: The Great and Volumetric", 2013):
// order i + 1 sees the lights through softened shadows T^(2^-i), isotropically, weighted by
// (albedo·√(1 − escape))^i, where `escape` is the environment channel's mean transmittance at
// p, the share of scattered light that leaves without meeting the medium again. Its scale is
// fitted per session to the technique's still (engine::preview::BrightnessMatch), so only how
// it changes with the view and the TF matters; docs/architecture.md has the measurements.
struct Lit {
    single: vec3<f32>,
    multiple: vec3<f32>,
}

// Σ over the octaves i = 1.. of weight^i · transmittance^(2^-i).
fn octaves(transmittance: f32, weight: vec3<f32>) -> vec3<f32> {
    var sum = vec3<f32>(0.0);
    var w = vec3<f32>(1.0);
    var soften = 1.0;
    for (var i = 0u; i < MS_OCTAVES; i++) {
        w *= weight;
        soften *= 0.5;
        sum += w * pow(transmittance, soften);
    }
    return sum;
}

fn lit(p: vec3<f32>, view_dir: vec3<f32>, albedo: vec3<f32>) -> Lit {
    var out = Lit(vec3<f32>(0.0), vec3<f32>(0.0));
    let u = box_relative(p);
    let env = scene.light_count;
    var ms_weight = vec3<f32>(0.0);
    if (params.multiple != 0u) {
        let escape = clamp(light_at(env, u), 0.0, 1.0);
        ms_weight = albedo * sqrt(1.0 - escape);
    }
    for (var l = 0u; l < scene.light_count; l++) {
        let light = lights[l];
        var travel = light.vector;
        var color = light.color;
        if (light.kind != LIGHT_DIRECTIONAL) {
            let offset = light.vector - p;
            let dist2 = max(dot(offset, offset), 1e-8);
            travel = -offset / sqrt(dist2);
            color = light.color / dist2;
        }
        let tr = light_toward(l, p, travel);
        out.single += color * tr * phase_hg(dot(travel, -view_dir), scene.g);
        if (params.multiple != 0u) {
            out.multiple += color * INV_4PI * octaves(tr, ms_weight);
        }
    }
    if (any(scene.env_radiance > vec3<f32>(0.0))) {
        // ∫ phase(ω)·(mean + lobe·ω) dω = mean + g·(lobe·view_dir): Henyey-Greenstein's
        // mean cosine about the ray's direction is g.
        let mean = clamp(light_at(env, u), 0.0, 1.0);
        var tr = mean;
        if (scene.g != 0.0) {
            let lobe = vec3<f32>(light_at(env + 1u, u), light_at(env + 2u, u), light_at(env + 3u, u));
            tr += scene.g * dot(lobe, view_dir);
        }
        out.single += scene.env_radiance * clamp(tr, 0.0, 1.0);
        if (params.multiple != 0u) {
            out.multiple += scene.env_radiance * octaves(mean, ms_weight);
        }
    }
    return out;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let y = band_row(gid.y, params.row_offset, params.row_stride);
    if (gid.x >= params.width || y >= params.height) {
        return;
    }
    let pixel = y * params.width + gid.x;
    let dir = camera_ray_dir(scene, vec2<f32>(f32(gid.x) + 0.5, f32(y) + 0.5));
    var single = vec3<f32>(0.0);
    var multiple = vec3<f32>(0.0);
    var transmit = 1.0;
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x < hit.y) {
        let step = scene.step * PREVIEW_STEP_SCALE;
        // One fixed offset per pixel breaks up the lattice's wood-grain bands.
        var rng = rng_new(scene.seed, pixel, 0u);
        let jitter = rng_next(&rng);
        var k = 0.0;
        loop {
            let t = hit.x + (k + jitter) * step;
            if (t >= hit.y || transmit < PREVIEW_T_CUTOFF) {
                break;
            }
            let p = scene.eye + dir * t;
            let cell = cell_of(box_relative(p));
            if (cell_is_empty(cell)) {
                k = skip_empty_cell(scene.eye, dir, cell, hit.x, step, jitter, k);
                continue;
            }
            let m = medium_at(p);
            if (m.a > 0.0) {
                let alpha = 1.0 - exp(-m.a * step);
                if (any(m.rgb > vec3<f32>(0.0))) {
                    let light = lit(p, dir, m.rgb);
                    single += transmit * alpha * m.rgb * light.single;
                    multiple += transmit * alpha * m.rgb * light.multiple;
                }
                transmit *= 1.0 - alpha;
            }
            k += 1.0;
        }
    }
    let radiance = single * params.gain + multiple * params.multiple_weight;
    image[pixel] = vec4<f32>(radiance + scene.env_radiance * transmit, transmit);
    if (params.multiple != 0u) {
        image_multiple[pixel] = vec2<u32>(pack2x16float(multiple.rg), pack2x16float(vec2<f32>(multiple.b, 0.0)));
    }
}
