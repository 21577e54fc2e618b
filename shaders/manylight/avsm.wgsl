// Technique `manylight`, pass 2: an adaptive volumetric shadow map (Salvi et al. 2010) per
// virtual light. One invocation per (texel of the six faces, light): a ray from the light through the
// texel centre is marched to the end of the volume, and its transmittance curve is kept as at
// most `nodes` (depth, transmittance) nodes, dropping the interior node whose removal changes
// the area under the curve least whenever there is one too many. Nodes are packed as two
// half floats. Rust twin: server/engine/src/techniques/manylight/gpu.rs.

#import manylight/common

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(5) var<storage, read> cell_max_opacity: array<f32>;
@group(0) @binding(6) var<uniform> ml: ManylightParams;
@group(0) @binding(7) var<storage, read_write> vls: array<VirtualLight>;
@group(0) @binding(8) var<storage, read_write> avsm: array<u32>;
@group(0) @binding(12) var<storage, read> work_list: array<u32>;
// Per light, the data bins of every macrocell its map's rays crossed (lo, hi): the map can
// change only under a TF edit whose opacity query meets them.
@group(0) @binding(13) var<storage, read_write> avsm_hist: array<atomic<u32>>;

// Build step in view steps (2 voxel edges): shadow maps are low frequency (the paper uses
// 40–48² texels), and with a new set of lights every iteration their errors average out; the
// maps were ~60% of an iteration at 1 voxel edge (the CT of the Mitsuba comparison).
const BUILD_STEP_SCALE: f32 = 4.0;

var<private> nodes: array<vec2<f32>, 13>;
var<private> count: u32;

// Appends a node; past the budget, removes the interior node of least area change.
fn push_node(node: vec2<f32>) {
    nodes[count] = node;
    count += 1u;
    if (count <= ml.nodes) {
        return;
    }
    var best = 1u;
    var best_area = 1e30;
    for (var i = 1u; i + 1u < count; i++) {
        let a = nodes[i - 1u];
        let b = nodes[i];
        let c = nodes[i + 1u];
        let area = abs((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y));
        if (area < best_area) {
            best_area = area;
            best = i;
        }
    }
    for (var i = best; i + 1u < count; i++) {
        nodes[i] = nodes[i + 1u];
    }
    count -= 1u;
}

// Texels are numbered through all six faces (not an 8×8 tile per face row), so that a face
// edge that is not a multiple of 8 leaves no idle invocations beside the busy ones.
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let r = ml.face_res;
    if (gid.x >= 6u * r * r) {
        return;
    }
    let face = gid.x / (r * r);
    let row = (gid.x / r) % r;
    let column = gid.x % r;
    var vl_index = gid.z;
    if (ml.list_count > 0u) {
        if (gid.z >= ml.list_count) {
            return;
        }
        vl_index = work_list[gid.z];
    }
    if (vl_index >= ml.count) {
        return;
    }
    let vl = vls[vl_index];
    let base = avsm_base(vl_index, face, column, row);
    if (all(vl.power <= vec3<f32>(0.0))) {
        // An empty slot: never read.
        return;
    }
    let u = (f32(column) + 0.5) / f32(r) * 2.0 - 1.0;
    let v = (f32(row) + 0.5) / f32(r) * 2.0 - 1.0;
    let dir = cube_direction(face, u, v);
    let p = vl.position;
    let hit = intersect_box(p, dir, scene.box_min, scene.box_max);
    let t_end = max(hit.y, 0.0);
    let step = scene.step * BUILD_STEP_SCALE;

    count = 0u;
    push_node(vec2<f32>(0.0, 1.0));
    var tau = 0.0;
    var last_t = 1.0;
    var k = 0.0;
    var bins = vec2<u32>(0u);
    loop {
        let t = (k + 0.5) * step;
        if (t >= t_end || last_t < 1e-4) {
            break;
        }
        let x = p + dir * t;
        let cell = cell_of(box_relative(x));
        if (cell_is_empty(cell)) {
            // Every value the skipped cell holds: a TF edit can make it non-empty.
            bins |= cell_bin_bits(cell);
            k = skip_empty_cell(p, dir, cell, 0.0, step, 0.5, k);
            continue;
        }
        let v = sample_volume(box_relative(x));
        bins |= value_bin_bits(v);
        let sigma = classify_opacity(v) * scene.density_scale;
        if (sigma > 0.0) {
            // The curve is flat up to the start of this step: keep its corner.
            if (tau == 0.0 || nodes[count - 1u].x < t - 0.5 * step - 1e-6) {
                push_node(vec2<f32>(t - 0.5 * step, exp(-tau)));
            }
            tau += sigma * step;
            last_t = exp(-tau);
            push_node(vec2<f32>(t + 0.5 * step, last_t));
        }
        k += 1.0;
    }
    atomicOr(&avsm_hist[2u * vl_index], bins.x);
    atomicOr(&avsm_hist[2u * vl_index + 1u], bins.y);
    // Pad with the final value far away.
    let final_t = exp(-tau);
    for (var i = 0u; i < ml.nodes; i++) {
        var node = vec2<f32>(1e4, final_t);
        if (i < count) {
            node = nodes[i];
        }
        avsm[base + i] = pack2x16float(node);
    }
}
