// Shared pieces: counter-based random numbers, Henyey-Greenstein phase function, constants.
// Prepended to every pass that needs them (see server/engine/src/shaders.rs).

const PI: f32 = 3.14159265358979;
const INV_4PI: f32 = 0.0795774715459477;

// PCG hash (Jarzynski & Olano 2020): a good 32-bit mix with no state.
fn pcg_hash(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Counter-based random stream: the same (seed, path, sample, dimension) always gives the same
// number, whatever was drawn before (DESIGN.md "Randomness is counter-based").
struct Rng {
    key: u32,
    dim: u32,
}

fn rng_new(seed: u32, path: u32, sample: u32) -> Rng {
    return Rng(pcg_hash(path ^ pcg_hash(sample ^ pcg_hash(seed + 0x9e3779b9u))), 0u);
}

// Uniform in [0, 1).
fn rng_next(rng: ptr<function, Rng>) -> f32 {
    let bits = pcg_hash((*rng).key + pcg_hash((*rng).dim));
    (*rng).dim += 1u;
    return f32(bits >> 8u) * (1.0 / 16777216.0);
}

// Henyey-Greenstein phase function; cos_theta is between the propagation directions
// (incoming light's travel direction and outgoing direction).
fn phase_hg(cos_theta: f32, g: f32) -> f32 {
    let denom = 1.0 + g * g - 2.0 * g * cos_theta;
    return INV_4PI * (1.0 - g * g) / (denom * sqrt(denom));
}

fn orthonormal_basis(n: vec3<f32>) -> mat3x3<f32> {
    let s = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    let t = vec3<f32>(1.0 + s * n.x * n.x * a, s * b, -s * n.x);
    let bt = vec3<f32>(b, s + n.y * n.y * a, -n.y);
    return mat3x3<f32>(t, bt, n);
}

// Samples a propagation direction after scattering of light travelling along `dir`;
// pdf equals phase_hg, so the phase/pdf weight is 1.
fn sample_hg(dir: vec3<f32>, g: f32, u1: f32, u2: f32) -> vec3<f32> {
    var cos_theta: f32;
    if (abs(g) < 1e-3) {
        cos_theta = 1.0 - 2.0 * u1;
    } else {
        let sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1);
        cos_theta = (1.0 + g * g - sq * sq) / (2.0 * g);
    }
    let sin_theta = sqrt(max(0.0, 1.0 - cos_theta * cos_theta));
    let phi = 2.0 * PI * u2;
    let local = vec3<f32>(sin_theta * cos(phi), sin_theta * sin(phi), cos_theta);
    return normalize(orthonormal_basis(dir) * local);
}

// Image row of invocation row `y` in band `band` of `bands` (a long pass runs as bands, one
// submission each; engine::techniques::progressive, engine::preview): the band holds the 8-row
// blocks band, band + bands, …, so that every band costs about the same and each 8×8 workgroup
// still covers adjacent rows. One band (0 of 1) is the identity.
fn band_row(y: u32, band: u32, bands: u32) -> u32 {
    return ((y / 8u) * bands + band) * 8u + y % 8u;
}
