// Technique `irradiance`, once per frame after the creation rounds: one workgroup stores the
// finished entries and turns this frame's claims into requests. First, the finished requests'
// entries are appended to the cache in request order (with the radii of Eq. 9–10, cut where
// the medium changes), their locks released a frame later, and the pending requests moved
// together. Then every lock (octree node or image block) claimed by a cache miss and not held
// gets a request, in lock order, while fewer than max_pending are pending; its local frame is
// oriented along the extinction gradient there (§4.2). Everything is in a fixed order, so a
// run is repeatable.
// Rust twin: server/engine/src/techniques/irradiance/gpu.rs.

#import shared/volume
#import shared/medium
#import irradiance/common

@group(0) @binding(0) var<uniform> scene: SceneUniforms;
@group(0) @binding(1) var volume_tex: texture_3d<f32>;
@group(0) @binding(2) var tf_lut: texture_2d<f32>;
@group(0) @binding(6) var<uniform> params: IrradianceParams;
@group(0) @binding(8) var<storage, read_write> entries: array<CacheEntry>;
@group(0) @binding(9) var<storage, read_write> radii: array<atomic<u32>>;
@group(0) @binding(11) var<storage, read_write> words: array<atomic<u32>>;
@group(0) @binding(12) var<storage, read_write> pixel_aux: array<vec4<f32>>;
@group(0) @binding(14) var<storage, read_write> requests: array<Request>;
@group(0) @binding(15) var<storage, read> cell_bins: array<vec2<u32>>;
@group(0) @binding(16) var<storage, read_write> bounds: array<vec4<f32>>;

const WG: u32 = 256u;
// Lock states (words at node_held_offset / block_held_offset).
const LOCK_HELD: u32 = 1u;
const LOCK_COOLING: u32 = 2u;

var<workgroup> scan_buf: array<u32, 256>;
var<workgroup> start_entries: u32;

// Δ for an entry centred at p: params.delta, or less where a mean free path is shorter.
fn entry_delta(p: vec3<f32>) -> f32 {
    let sigma_t = extinction_at(p);
    if (params.delta_free_paths <= 0.0 || sigma_t <= 0.0) {
        return params.delta;
    }
    return clamp(params.delta_free_paths / sigma_t, 0.25 * params.voxel, params.delta);
}

// Direction of the extinction gradient at p by central differences one voxel apart: the axis
// an entry's local frame is oriented along (the paper's §4.2). +z where the medium is flat.
fn extinction_normal(p: vec3<f32>) -> vec3<f32> {
    let h = params.voxel;
    let gradient = vec3<f32>(
        extinction_at(p + vec3<f32>(h, 0.0, 0.0)) - extinction_at(p - vec3<f32>(h, 0.0, 0.0)),
        extinction_at(p + vec3<f32>(0.0, h, 0.0)) - extinction_at(p - vec3<f32>(0.0, h, 0.0)),
        extinction_at(p + vec3<f32>(0.0, 0.0, h)) - extinction_at(p - vec3<f32>(0.0, 0.0, h)),
    );
    let len = length(gradient);
    if (len <= 1e-12) {
        return vec3<f32>(0.0, 0.0, 1.0);
    }
    return gradient / len;
}

// How far along one half-axis an entry's zone may reach before the medium differs from its
// centre's: the extrapolation's log-irradiance gradient is the centre's, the true one changes
// with the extinction, so the walk stops where ∫|σt(x) − σt(x0)| dx exceeds ln(1 + ε) (a
// zone in soft tissue does not reach into the bone beside it). Half-voxel steps.
fn extinction_reach(x0: vec3<f32>, axis: vec3<f32>, limit: f32) -> f32 {
    let sigma0 = extinction_at(x0);
    let tolerance = log(1.0 + params.epsilon);
    let step = 0.5 * params.voxel;
    var excess = 0.0;
    var s = 0.0;
    loop {
        if (s >= limit) {
            return limit;
        }
        s += step;
        excess += abs(extinction_at(x0 + axis * s) - sigma0) * step;
        if (excess > tolerance) {
            return max(s - step, params.min_radius);
        }
    }
    return limit;
}

// Exclusive prefix sum of `value` over the workgroup, and the total (uniform).
fn exclusive_scan(t: u32, value: u32) -> vec2<u32> {
    scan_buf[t] = value;
    workgroupBarrier();
    for (var offset = 1u; offset < WG; offset <<= 1u) {
        var add = 0u;
        if (t >= offset) {
            add = scan_buf[t - offset];
        }
        workgroupBarrier();
        scan_buf[t] += add;
        workgroupBarrier();
    }
    let inclusive = scan_buf[t];
    let total = workgroupUniformLoad(&scan_buf[WG - 1u]);
    return vec2<u32>(inclusive - value, total);
}

@compute @workgroup_size(256)
fn main(@builtin(local_invocation_index) t: u32) {
    if (t == 0u) {
        start_entries = atomicLoad(&words[COUNTER_ENTRIES]);
    }
    var entry_count = workgroupUniformLoad(&start_entries);
    let screen_locking = (params.flags & FLAG_SCREEN_LOCKING) != 0u;
    var slots = params.node_count;
    var claim_base = params.node_claim_offset;
    var held_base = params.node_held_offset;
    if (screen_locking) {
        slots = params.block_count;
        claim_base = params.block_claim_offset;
        held_base = params.block_held_offset;
    }
    let may_create = (params.flags & FLAG_NO_CREATION) == 0u;

    // Finished requests → entries; the rest move together. A finished request's lock cools
    // for a frame (LOCK_COOLING): its entry is in the octree only from the next frame on, so
    // this frame's claims near it are not taken.
    var kept = 0u;
    for (var base = 0u; base < params.pending; base += WG) {
        let i = base + t;
        var r: Request;
        var done = 0u;
        var keep = 0u;
        if (i < params.pending) {
            r = requests[i];
            done = select(0u, 1u, r.state == REQUEST_DONE);
            keep = 1u - done;
        }
        let done_scan = exclusive_scan(t, done);
        let keep_scan = exclusive_scan(t, keep);
        storageBarrier();
        workgroupBarrier();
        if (done == 1u) {
            let e = entry_count + done_scan.x;
            if (e < params.entry_capacity) {
                entries[e] = r.entry;
                let frame = orthonormal_basis(r.entry.normal);
                var reach = 0.0;
                for (var h = 0u; h < 6u; h++) {
                    let sign = select(1.0, -1.0, (h & 1u) == 1u);
                    let radius = extinction_reach(
                        r.entry.position,
                        frame[h / 2u] * sign,
                        validity_radius(r.entry.sigma[h].w, r.entry.delta),
                    );
                    atomicStore(&radii[e * 6u + h], bitcast<u32>(radius));
                    reach = max(reach, radius);
                }
                bounds[e] = vec4<f32>(r.entry.position, reach);
                atomicAdd(&words[COUNTER_CREATED], 1u);
            } else {
                atomicAdd(&words[COUNTER_LOST], 1u);
            }
            atomicStore(&words[held_base + r.lock], LOCK_COOLING);
        }
        if (keep == 1u) {
            requests[kept + keep_scan.x] = r;
        }
        entry_count = min(entry_count + done_scan.y, params.entry_capacity);
        kept += keep_scan.y;
        storageBarrier();
        workgroupBarrier();
    }
    storageBarrier();
    workgroupBarrier();

    // Claims → requests, while both the pending list and the cache have room.
    var pending = kept;
    var limit = pending;
    if (may_create) {
        let room_left = params.entry_capacity - min(entry_count, params.entry_capacity);
        limit = max(pending, min(params.max_pending, room_left));
    }
    for (var base = 0u; base < slots; base += WG) {
        let lock = base + t;
        var claim = NO_CLAIM;
        var wanted = 0u;
        if (lock < slots) {
            claim = atomicExchange(&words[claim_base + lock], NO_CLAIM);
            let held = atomicLoad(&words[held_base + lock]);
            if (held == LOCK_COOLING) {
                atomicStore(&words[held_base + lock], 0u);
            } else if (claim != NO_CLAIM && held == 0u) {
                wanted = 1u;
            }
        }
        let scan = exclusive_scan(t, wanted);
        let slot = pending + scan.x;
        if (wanted == 1u) {
            if (slot < limit) {
                let position = pixel_aux[claim & 0x00ffffffu].xyz;
                var r: Request;
                r.position = position;
                r.key = pcg_hash(claim ^ pcg_hash(params.frame ^ CREATE_SALT));
                r.normal = extinction_normal(position);
                r.lock = lock;
                for (var p = 0u; p < 7u; p++) {
                    r.sums[p] = vec4<f32>(0.0);
                }
                r.count = 0u;
                r.state = REQUEST_PENDING;
                // The frame depends on the extinction around the centre.
                let cell = cell_of(box_relative(position));
                let bins = cell_bins[cell_index(cell)];
                r.opacity_lo = bins.x;
                r.opacity_hi = bins.y;
                r.colour_lo = 0u;
                r.colour_hi = 0u;
                r.delta = entry_delta(position);
                r.direct_sum = 0.0;
                requests[slot] = r;
                atomicStore(&words[held_base + lock], LOCK_HELD);
                atomicAdd(&words[COUNTER_ISSUED], 1u);
            } else {
                atomicAdd(&words[COUNTER_DROPPED], 1u);
            }
        }
        pending = min(pending + scan.y, limit);
    }
    storageBarrier();
    workgroupBarrier();
    if (t == 0u) {
        atomicStore(&words[COUNTER_PENDING], pending);
        atomicStore(&words[COUNTER_ENTRIES], entry_count);
    }
}
