// Shared pieces of technique `manylight` (Weber et al. 2013): the parameters, the virtual
// lights, the cube-map layout of their adaptive volumetric shadow maps (AVSMs) and the virtual
// spherical light's geometry term. Rust twin: server/engine/src/techniques/manylight/gpu.rs.

#import shared/common
#import shared/volume
#import shared/scene
#import shared/macrocell

struct ManylightParams {
    // Virtual-light slots, and how many hold a light.
    capacity: u32,
    count: u32,
    // First path index of a light-tracing dispatch (paths are traced in batches until the
    // slots are full), and the most virtual lights one path leaves.
    first_path: u32,
    max_bounces: u32,
    // Texels per cube-face edge and nodes per texel of every AVSM.
    face_res: u32,
    nodes: u32,
    // Transmittance from virtual lights: 0 AVSM point sampling, 1 AVSM trilinear, 2 ray marched.
    mode: u32,
    seed: u32,
    // Radius of the virtual spherical lights (world units).
    vsl_radius: f32,
    // Density scale the AVSMs were built with: lookups rescale T^(density/built) (paper §5).
    built_density: f32,
    // 1 / light paths traced: a virtual light's power is its path's share of the emission.
    power_scale: f32,
    // When non-zero, the light tracing traces the paths work_list[0..list_count] and the
    // shadow-map build builds the maps of the slots work_list[0..list_count] (a TF edit's
    // partial rebuild); when zero, paths first_path.. and every slot.
    list_count: u32,
    // 1: light paths are tracked against the fixed majorant density_scale (their historygram
    // then holds exactly the values they read); 0: against the macrocell majorants (for dense
    // media, where the fixed one would take too many steps; the historygram then holds every
    // bin of the cells they crossed).
    fixed_majorant: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const MODE_AVSM_POINT: u32 = 0u;
const MODE_AVSM_TRILINEAR: u32 = 1u;
const MODE_RAY_MARCHED: u32 = 2u;

// Most nodes one AVSM texel may hold.
const MAX_NODES: u32 = 12u;

// A virtual light: a scattering event of a light path. It re-emits `power` (W, albedo
// applied) with the phase function around `direction` (the light's travel direction there).
// `tau` is the optical depth of its path from the light per unit density scale, `vertices` the
// scattering events on that path including this one: together they re-weight the light
// exactly when only the density scale changes (the paper's Eq. 6 with fixed positions).
// `path` is the light path it belongs to. The path's historygrams (the same in each of its
// lights, and in slot 0 of a path that left none): `opacity_*` the data bins of every
// macrocell its flights crossed (majorants, tentative collisions, optical depth), `colour_*`
// the bins at its scattering vertices (albedo, and with it the roulette). A TF edit changes
// the path only if its opacity query meets the first or its query meets the second.
struct VirtualLight {
    position: vec3<f32>,
    tau: f32,
    power: vec3<f32>,
    vertices: f32,
    direction: vec3<f32>,
    path: u32,
    opacity_lo: u32,
    opacity_hi: u32,
    colour_lo: u32,
    colour_hi: u32,
    // The data value at this vertex: the immediate re-weighting after a TF edit (the paper's
    // Eq. 6) changes the albedo there.
    value: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

// Historygram bit (lo, hi words) of data value v: bin floor(v·63) of 64.
fn value_bin_bits(v: f32) -> vec2<u32> {
    let bin = min(u32(clamp(v, 0.0, 1.0) * 63.0), 63u);
    if (bin < 32u) {
        return vec2<u32>(1u << bin, 0u);
    }
    return vec2<u32>(0u, 1u << (bin - 32u));
}

// Data bins per macrocell (lo, hi words; RangeGrid::bin_masks), shared by the passes.
@group(0) @binding(11) var<storage, read> cell_bins: array<vec2<u32>>;

// Data bins of macrocell c.
fn cell_bin_bits(c: vec3<u32>) -> vec2<u32> {
    return cell_bins[(c.z * scene.cell_dims.y + c.y) * scene.cell_dims.x + c.x];
}

// Power of virtual light `vl` at density scale `density` when traced at `built`:
// per vertex (s/s_b)·exp(−(s − s_b)·τ_unit) (σs and the segment's transmittance).
fn reweighted_power(vl: VirtualLight, density: f32, built: f32) -> vec3<f32> {
    if (density == built || built <= 0.0) {
        return vl.power;
    }
    return vl.power * pow(density / built, vl.vertices) * exp(-(density - built) * vl.tau);
}

// Cube face (0..5: +x −x +y −y +z −z) and face coordinates in [−1, 1]² of direction d.
fn cube_face(d: vec3<f32>) -> vec3<f32> {
    let a = abs(d);
    if (a.x >= a.y && a.x >= a.z) {
        return vec3<f32>(select(1.0, 0.0, d.x > 0.0), d.y / a.x, d.z / a.x);
    }
    if (a.y >= a.z) {
        return vec3<f32>(select(3.0, 2.0, d.y > 0.0), d.x / a.y, d.z / a.y);
    }
    return vec3<f32>(select(5.0, 4.0, d.z > 0.0), d.x / a.z, d.y / a.z);
}

// The direction through face coordinates (u, v) of `face` (inverse of cube_face).
fn cube_direction(face: u32, u: f32, v: f32) -> vec3<f32> {
    let s = select(-1.0, 1.0, face % 2u == 0u);
    let axis = face / 2u;
    if (axis == 0u) {
        return normalize(vec3<f32>(s, u, v));
    }
    if (axis == 1u) {
        return normalize(vec3<f32>(u, s, v));
    }
    return normalize(vec3<f32>(u, v, s));
}

// First node of texel (x, y) of `face` in the AVSM of virtual light `vl`.
fn avsm_base(vl: u32, face: u32, x: u32, y: u32) -> u32 {
    let r = ml.face_res;
    return (((vl * 6u + face) * r + y) * r + x) * ml.nodes;
}

// The virtual spherical light's replacement for 1/d²: 1/d² beyond the radius r, inside it the
// constant 3/r², which carries the same power as 1/d² does inside the sphere. The power a
// light leaves thus stays within r of it. (The sphere's solid angle over π r², used before,
// conserves power too, but only over all space: it takes from inside r what it adds at
// 1–3 r, so that thin dense structure lost power to the empty space beside it, −3% in the
// CT's volume blocks at r = 0.02; see docs/validation.md.)
fn vsl_geometry(d: f32, r: f32) -> f32 {
    return select(1.0 / max(d * d, 1e-12), 3.0 / (r * r), d < r);
}
