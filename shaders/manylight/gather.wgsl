// Technique `manylight`, pass 3: multiple scattering gathered from the virtual lights, added to
// the single scattering the `raymarch` pass just wrote for this iteration. A jittered march
// along the view ray picks one scattering location with probability proportional to
// T·(1 − exp(−σt·dt)) (weighted reservoir, as raymarch does); there every virtual spherical
// light contributes power · phase · geometry · transmittance · phase. The transmittance from
// the light comes from its AVSM (point or trilinear lookup) or, as the baseline, from a
// ray march. Rust twin: server/engine/src/techniques/manylight/gpu.rs.

#import shared/march
#import manylight/common

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(4) var<storage, read_write> accum: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> ml: ManylightParams;
@group(0) @binding(7) var<storage, read_write> vls: array<VirtualLight>;
@group(0) @binding(8) var<storage, read_write> avsm: array<u32>;
@group(0) @binding(9) var<uniform> chunk: GatherChunk;

// The virtual lights one dispatch gathers. Splitting them keeps every invocation's loop
// iterations bounded (llvmpipe stops a shader invocation's loops after 65535 iterations).
struct GatherChunk {
    first: u32,
    count: u32,
    pad0: u32,
    pad1: u32,
}


// Transmittance at `depth` along the piecewise-linear curve of one texel.
fn texel_transmittance(base: u32, depth: f32) -> f32 {
    var prev = unpack2x16float(avsm[base]);
    for (var i = 1u; i < ml.nodes; i++) {
        let node = unpack2x16float(avsm[base + i]);
        if (depth <= node.x) {
            let span = node.x - prev.x;
            let f = select(1.0, clamp((depth - prev.x) / span, 0.0, 1.0), span > 1e-8);
            return mix(prev.y, node.y, f);
        }
        prev = node;
    }
    return prev.y;
}

// Transmittance from virtual light `j` to x through its AVSM.
fn avsm_transmittance(j: u32, light_pos: vec3<f32>, x: vec3<f32>) -> f32 {
    let offset = x - light_pos;
    let depth = length(offset);
    let fc = cube_face(offset / max(depth, 1e-8));
    let face = u32(fc.x);
    let r = f32(ml.face_res);
    let s = (vec2<f32>(fc.y, fc.z) * 0.5 + 0.5) * r;
    if (ml.mode == MODE_AVSM_POINT) {
        let texel = min(vec2<u32>(s), vec2<u32>(ml.face_res - 1u));
        return texel_transmittance(avsm_base(j, face, texel.x, texel.y), depth);
    }
    // Trilinear: bilinear over the face's texels (clamped at its edges), linear in depth.
    let c = clamp(s - 0.5, vec2<f32>(0.0), vec2<f32>(r - 1.0));
    let i0 = vec2<u32>(c);
    let i1 = min(i0 + vec2<u32>(1u), vec2<u32>(ml.face_res - 1u));
    let f = c - vec2<f32>(i0);
    let t00 = texel_transmittance(avsm_base(j, face, i0.x, i0.y), depth);
    let t10 = texel_transmittance(avsm_base(j, face, i1.x, i0.y), depth);
    let t01 = texel_transmittance(avsm_base(j, face, i0.x, i1.y), depth);
    let t11 = texel_transmittance(avsm_base(j, face, i1.x, i1.y), depth);
    return mix(mix(t00, t10, f.x), mix(t01, t11, f.x), f.y);
}

// Radiance scattered at x toward −view_dir from every virtual light, per unit albedo at x.
fn gather(x: vec3<f32>, view_dir: vec3<f32>, jitter: f32) -> vec3<f32> {
    var s = vec3<f32>(0.0);
    let end = min(chunk.first + chunk.count, ml.count);
    let rescale = scene.density_scale / max(ml.built_density, 1e-12);
    for (var j = chunk.first; j < end; j++) {
        let vl = vls[j];
        if (all(vl.power <= vec3<f32>(0.0))) {
            continue;
        }
        let offset = x - vl.position;
        let d = length(offset);
        let toward = offset / max(d, 1e-8);
        var tr: f32;
        if (ml.mode == MODE_RAY_MARCHED) {
            tr = transmittance(vl.position, toward, d, jitter);
        } else {
            tr = pow(avsm_transmittance(j, vl.position, x), rescale);
        }
        if (tr <= 0.0) {
            continue;
        }
        let power = reweighted_power(vl, scene.density_scale, ml.built_density);
        let emitted = power * ml.power_scale * phase_hg(dot(vl.direction, toward), scene.g);
        s += emitted * vsl_geometry(d, ml.vsl_radius) * tr * phase_hg(dot(toward, -view_dir), scene.g);
    }
    return s;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    // The same band of rows as the raymarch pass of this iteration (manylight.rs).
    let y = band_row(gid.y, scene.row_offset, scene.row_stride);
    if (gid.x >= scene.width || y >= scene.height) {
        return;
    }
    let pixel = y * scene.width + gid.x;
    // Its own stream, independent of the raymarch pass's; every chunk of an iteration picks
    // the same scattering location (same stream), so the chunks sum to one estimate.
    var rng = rng_new(scene.seed ^ 0x5bd1e995u, pixel, scene.iteration);
    let px = vec2<f32>(f32(gid.x) + rng_next(&rng), f32(y) + rng_next(&rng));
    let dir = camera_ray_dir(scene, px);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        return;
    }
    let s = pick_scattering(scene.eye, dir, hit.x, hit.y, &rng);
    if (s.weight_sum > 0.0 && any(s.albedo > vec3<f32>(0.0))) {
        let radiance = s.weight_sum * s.albedo * gather(s.position, dir, rng_next(&rng));
        accum[pixel] += vec4<f32>(radiance, 0.0);
    }
}
