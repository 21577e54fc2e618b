// Technique `irradiance`: the cache lookup (Eq. 7–11) that rendering and the update share. A
// pass that imports this declares `entries`, `radii`, `octree` and `bounds` (irradiance/common.wgsl
// lists the bindings).

#import irradiance/common

fn radius_of(entry: u32, half_axis: u32) -> f32 {
    return bitcast<f32>(atomicLoad(&radii[entry * 6u + half_axis]));
}

// Coordinates of world point x in entry e's local frame, and the half-axes of its octant.
struct Local {
    l: vec3<f32>,
    half_axes: vec3<u32>,
}

fn local_coordinates(entry: CacheEntry, x: vec3<f32>) -> Local {
    let frame = orthonormal_basis(entry.normal);
    let d = x - entry.position;
    let l = vec3<f32>(dot(d, frame[0]), dot(d, frame[1]), dot(d, frame[2]));
    let half_axes = vec3<u32>(
        select(0u, 1u, l.x < 0.0),
        select(2u, 3u, l.y < 0.0),
        select(4u, 5u, l.z < 0.0),
    );
    return Local(l, half_axes);
}

// What one entry predicts at x: its weight w(d) = 3d² − 2d³ (zero outside its zone) and the
// log of the extrapolated irradiance (Eq. 7 with the barycentric coefficient of Eq. 8).
struct Prediction {
    weight: f32,
    log_irradiance: vec3<f32>,
}

fn entry_predict(e: u32, x: vec3<f32>) -> Prediction {
    let none = Prediction(0.0, vec3<f32>(0.0));
    let bound = bounds[e];
    let offset = x - bound.xyz;
    if (dot(offset, offset) >= bound.w * bound.w) {
        return none;
    }
    let entry = entries[e];
    let local = local_coordinates(entry, x);
    let h = local.half_axes;
    let r = vec3<f32>(radius_of(e, h.x), radius_of(e, h.y), radius_of(e, h.z));
    if (any(r <= vec3<f32>(0.0))) {
        return none;
    }
    let l = local.l;
    // ‖x‖ / r(x) with the ellipsoid radius r(x) = ‖x‖ (Σ x_i² / r_i²)^−½ of the octant.
    let q = dot(l * l, 1.0 / (r * r));
    if (q >= 1.0) {
        return none;
    }
    let dist = length(l);
    let a = abs(l);
    let a_sum = a.x + a.y + a.z;
    var sigma = vec4<f32>(0.0);
    if (a_sum > 0.0) {
        sigma = (a.x * entry.sigma[h.x] + a.y * entry.sigma[h.y] + a.z * entry.sigma[h.z]) / a_sum;
    }
    // Fig. 4: beyond the radius the interpolated coefficient gives, the entry is not used.
    if (dist > validity_radius(sigma.w, entry.delta)) {
        return none;
    }
    let d = 1.0 - sqrt(q);
    let weight = d * d * (3.0 - 2.0 * d);
    let log_e = log(max(entry.irradiance, vec3<f32>(IRRADIANCE_FLOOR))) - sigma.rgb * dist;
    return Prediction(weight, log_e);
}

// The cache's answer at x (Eq. 11: the log-space weighted average of every entry whose zone
// holds x; weight 0 when none does), and the deepest octree node on x's branch (the lock of
// object-space locking).
struct Lookup {
    weight: f32,
    irradiance: vec3<f32>,
    node: u32,
}

// Child of an octree node (children are stored together, in x, y, z bit order) that holds x,
// and its cube.
struct Descent {
    child: u32,
    lo: vec3<f32>,
}

fn descend(first_child: u32, lo: vec3<f32>, half: f32, x: vec3<f32>) -> Descent {
    let centre = lo + vec3<f32>(half);
    let upper = x >= centre;
    let octant = select(0u, 1u, upper.x) + select(0u, 2u, upper.y) + select(0u, 4u, upper.z);
    return Descent(first_child + octant, select(lo, centre, upper));
}

fn cache_lookup(x: vec3<f32>) -> Lookup {
    var node = 0u;
    var lo = params.root_min;
    var edge = params.root_edge;
    var weight_sum = 0.0;
    var log_sum = vec3<f32>(0.0);
    for (var depth = 0u; depth < MAX_DEPTH; depth++) {
        let base = node * 4u;
        let first = params.refs_offset + octree[base + 1u];
        let count = octree[base + 2u];
        for (var i = 0u; i < count; i++) {
            let p = entry_predict(octree[first + i], x);
            weight_sum += p.weight;
            log_sum += p.weight * p.log_irradiance;
        }
        let child = octree[base];
        if (child == 0u) {
            break;
        }
        edge *= 0.5;
        let next = descend(child, lo, edge, x);
        node = next.child;
        lo = next.lo;
    }
    var irradiance = vec3<f32>(0.0);
    if (weight_sum > 0.0) {
        irradiance = exp(log_sum / weight_sum);
    }
    return Lookup(weight_sum, irradiance, node);
}
