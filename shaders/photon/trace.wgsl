// Technique `photon`, pass 1: photon tracing. One invocation per photon path: emission from a
// light chosen by power (directional: a disk covering the volume's bounding sphere; point: a
// uniform direction; environment: a uniform direction and such a disk), delta tracking against
// a fixed, TF-independent majorant, a record at every real collision (power × albedo there),
// Henyey-Greenstein scattering, at most `bounces` records. Every data value a tentative
// collision reads is added to the path's historygram. A path's first `inline_slots` records
// have slots of their own; further ones go into chunks the path takes from its pass's pool as
// it grows (record_slot), so a path's length is not bounded by a fixed number of slots.
//
// Randomness is keyed by (seed, path, interaction k): the flight to interaction k and the
// scattering that starts it draw from rng_new(seed, path, k) only, and the state it starts
// from (position, direction, power, historygram) is exactly what record k − 1 stores. So
// MODE_UPDATE can restart a path after its last record the edit cannot have changed and
// produce bit for bit the path a full trace (MODE_FULL) would. A record is changed when its
// flight's historygram meets the rejection query (opacity rose) or its collision's bin, or an
// earlier one's, meets the collision query (colour changed or opacity fell); see
// PhotonUniforms. Where a resumed flight collides where it did, the record is the old one but
// for its colour, and so is every flight after it up to the next record the edit changes:
// the update walks the old records again from there instead of tracking them. In
// MODE_UPDATE, `trace_mark` first lists the paths the edit affects, and `main` runs one
// invocation per listed path: a sparse update then keeps every SIMD lane busy instead of
// paying for whole batches whose one affected path runs while the others idle.
// Rust twin: server/engine/src/techniques/photon/gpu.rs.

#import photon/common

// `main` is compiled twice: for full traces and for updates (TRACE_UPDATE), each without the
// other's code. llvmpipe runs every branch of a kernel for every SIMD batch, masked, so with
// the mode a uniform the full trace paid for the update's walk, resume and change list, and
// the update for the census.
override TRACE_UPDATE: bool = false;

// With TRACE_UPDATE, whether this pipeline is the update's walk (`trace_walk`): it runs first
// on every listed path and finishes those that only take new colours, where each flight the
// edit could move (its collision's opacity fell) still collides where it did: its acceptance
// draw, tested against the new opacity, decides that without tracking, and the record keeps
// its place and takes the colour the walk gives it (the same operations as the resumed flight,
// so the same bits). Every other path it lists for the update's trace (COUNTER_DEFERRED), which
// walks it again from its start: the powers the walk already gave are found unchanged. llvmpipe
// runs a kernel's code for every SIMD batch, masked, whatever its lanes need (the update's trace
// over chest CT's 3 851 listed paths cost ~0.7 ms with every lane returning at once), so the
// paths that need only the walk are kept out of the trace's batches.
override TRACE_WALK: bool = false;

// Whether this pipeline updates a map (MODE_UPDATE); `main` and what it calls ask this.
fn updating() -> bool {
    return TRACE_UPDATE;
}

// Whether a full trace counts its work (PhotonUniforms::census).
fn counting() -> bool {
    return !TRACE_UPDATE && photon.census != 0u;
}

// Marks the spatial historygram (3×64 bits) at world position p.
fn mark_axes(p: vec3<f32>) {
    let b = spatial_bins(p);
    for (var axis = 0u; axis < 3u; axis++) {
        let bin = b[axis];
        let word = COUNTER_SPATIAL + axis * 2u + bin / 32u;
        atomicOr(&counters[word], 1u << (bin % 32u));
    }
}

// Marks the dirty bits of the half-size cells that come within the gather radius of p (of the
// 5 × 5 × 5 around p's, about two thirds: those whose box lies within the radius, with 1% to
// spare for rounding), every one a sample within the radius of p can lie in: SPATIAL_CELLS finds
// stale segments by them, and every delta gather skips the samples outside them. A bit already
// set is not written again (dense edits mark the same cells many times).
fn mark_cells(p: vec3<f32>) {
    {
        let c = dirty_cell3(p);
        let dims = vec3<i32>(2u * photon.grid_dims);
        let half = 0.5 * photon.radius;
        let reach = 1.01 * photon.radius;
        for (var dz = -2; dz <= 2; dz++) {
            for (var dy = -2; dy <= 2; dy++) {
                for (var dx = -2; dx <= 2; dx++) {
                    let n = c + vec3<i32>(dx, dy, dz);
                    let near = cube_distance2(scene.box_min + vec3<f32>(n) * half, half, p) <= reach * reach;
                    if (all(n >= vec3<i32>(0)) && all(n < dims) && near) {
                        let cell = dirty_index(n);
                        let word = COUNTER_DIRTY + cell / 32u;
                        let bit = 1u << (cell % 32u);
                        if ((atomicLoad(&counters[word]) & bit) == 0u) {
                            atomicOr(&counters[word], bit);
                        }
                    }
                }
            }
        }
    }
}

// Whether two records are at the same position with the same direction, bit for bit.
fn same_place(a: PhotonRecord, b: PhotonRecord) -> bool {
    return all(bitcast<vec3<u32>>(a.position) == bitcast<vec3<u32>>(b.position))
        && all(bitcast<vec3<u32>>(a.direction) == bitcast<vec3<u32>>(b.direction));
}

fn same_record(a: PhotonRecord, b: PhotonRecord) -> bool {
    return same_place(a, b) && all(bitcast<vec3<u32>>(a.power) == bitcast<vec3<u32>>(b.power))
        && a.cell == b.cell && a.hist_lo == b.hist_lo && a.hist_hi == b.hist_hi;
}

// Appends a version of a changed record to the change list and marks its position (dropped
// past the list's capacity: the host then sees COUNTER_CHANGES over it and regathers instead).
// The dirty cells of a listed change are marked afterwards, by `trace_mark_changes`: the 125
// neighbours' loop would otherwise hold up the other lanes of a retraced path's SIMD batch
// while they track their flights. A change the list cannot hold is marked here.
fn append_change(index: u32, r: PhotonRecord, kind: u32, old_power: vec3<f32>) {
    mark_axes(r.position);
    let slot = atomicAdd(&counters[COUNTER_CHANGES], 1u);
    if (slot < photon.change_capacity) {
        changes[slot] = PhotonChange(r.position, r.cell, r.power, kind, r.direction, record_pass(index), old_power, 0u);
    } else {
        mark_cells(r.position);
    }
}

// MODE_UPDATE, after `main`: marks the dirty cells of every change the list holds
// (append_change).
@compute @workgroup_size(64)
fn trace_mark_changes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    if (i >= min(atomicLoad(&counters[COUNTER_CHANGES]), photon.change_capacity)) {
        return;
    }
    mark_cells(changes[i].position);
}

// Writes record `index`; in MODE_UPDATE a record that differs from the one it replaces marks
// both positions as changed and lists both versions as changes.
fn store_record(index: u32, record: PhotonRecord) {
    if (updating()) {
        let old = records[index];
        if (!same_record(old, record)) {
            atomicAdd(&counters[COUNTER_CHANGED], 1u);
            let had = old.cell != CELL_NONE;
            let has = record.cell != CELL_NONE;
            let replace = had && has && same_place(old, record);
            // One entry for a replaced record, else one per version that holds a photon: the
            // old one's first. A loop with one call site, not a call per case: llvmpipe runs
            // every branch's code for every SIMD batch, masked, and a loop only as often as
            // its busiest lane needs.
            let entries = select(u32(had) + u32(has), 1u, replace);
            for (var e = 0u; e < entries; e++) {
                var r = record;
                var kind = CHANGE_ADD;
                var old_power = vec3<f32>(0.0);
                if (replace) {
                    kind = CHANGE_REPLACE;
                    old_power = old.power;
                } else if (e == 0u && had) {
                    r = old;
                    kind = CHANGE_SUBTRACT;
                }
                append_change(index, r, kind, old_power);
            }
        }
    }
    records[index] = record;
}

// MODE_UPDATE, the walk: gives record `index` (r, as loaded, which holds a photon) a new power,
// a CHANGE_REPLACE where it differs. Writes only the power: llvmpipe loads and stores a storage
// buffer one lane at a time, each word behind its own loop over the SIMD batch's lanes.
fn store_power(index: u32, r: PhotonRecord, power: vec3<f32>) {
    if (any(bitcast<vec3<u32>>(power) != bitcast<vec3<u32>>(r.power))) {
        atomicAdd(&counters[COUNTER_CHANGED], 1u);
        append_change(index, PhotonRecord(r.position, r.cell, power, r.hist_lo, r.direction, r.hist_hi), CHANGE_REPLACE, r.power);
        records[index].power = power;
    }
}

// MODE_UPDATE, past the new end of a path: empties record `index`, which held a photon of the
// old path (a CHANGE_SUBTRACT of its old version).
fn clear_record(index: u32) {
    let old = records[index];
    atomicAdd(&counters[COUNTER_CHANGED], 1u);
    append_change(index, old, CHANGE_SUBTRACT, vec3<f32>(0.0));
    records[index] = empty_record();
}

fn uniform_sphere(u1: f32, u2: f32) -> vec3<f32> {
    let z = 1.0 - 2.0 * u1;
    let r = sqrt(max(0.0, 1.0 - z * z));
    let phi = 2.0 * PI * u2;
    return vec3<f32>(r * cos(phi), r * sin(phi), z);
}

struct Emission {
    origin: vec3<f32>,
    direction: vec3<f32>,
    power: vec3<f32>,
}

fn emit(rng: ptr<function, Rng>) -> Emission {
    let u = rng_next(rng);
    var e = emitters[photon.emitter_count - 1u];
    for (var i = 0u; i < photon.emitter_count; i++) {
        if (u < emitters[i].cdf) {
            e = emitters[i];
            break;
        }
    }
    let u1 = rng_next(rng);
    let u2 = rng_next(rng);
    if (e.kind == EMIT_POINT) {
        return Emission(e.vector, uniform_sphere(u1, u2), e.power);
    }
    var dir = e.vector;
    if (e.kind == EMIT_ENVIRONMENT) {
        dir = uniform_sphere(u1, u2);
    }
    // A disk of the bounding sphere's radius, perpendicular to dir, before the volume.
    let u3 = rng_next(rng);
    let u4 = rng_next(rng);
    let radius = bounding_radius();
    let centre = 0.5 * (scene.box_min + scene.box_max);
    let basis = orthonormal_basis(dir);
    let r = radius * sqrt(u3);
    let phi = 2.0 * PI * u4;
    let origin = centre - dir * (2.0 * radius) + basis * vec3<f32>(r * cos(phi), r * sin(phi), 0.0);
    return Emission(origin, dir, e.power);
}

fn empty_record() -> PhotonRecord {
    return PhotonRecord(vec3<f32>(0.0), CELL_NONE, vec3<f32>(0.0), 0u, vec3<f32>(0.0), 0u);
}

fn pass_of(p: u32) -> u32 {
    return p / photon.photons_per_pass;
}

// Path p's own slot for interaction k < inline_slots.
fn inline_slot(p: u32, k: u32) -> u32 {
    let pass_index = pass_of(p);
    let block = pass_index * photon.photons_per_pass * photon.path_slots;
    return block + (p - pass_index * photon.photons_per_pass) * photon.inline_slots + k;
}

// Slot j of chunk c (its index within p's pass) of p's pass's pool.
fn chunk_slot(p: u32, c: u32, j: u32) -> u32 {
    let block = pass_of(p) * photon.photons_per_pass * photon.path_slots;
    return block + photon.photons_per_pass * photon.inline_slots + c * CHUNK_SLOTS + j;
}

// The word of chunk c's next pointer in `chunks`.
fn chunk_word(p: u32, c: u32) -> u32 {
    return pass_of(p) * photon.chunks_per_pass + c;
}

// The chunk that holds interaction k >= inline_slots of path p, whose list starts at `head`
// (CHUNK_NONE where the list is shorter).
fn chain_chunk(p: u32, head: u32, k: u32) -> u32 {
    var c = head;
    let hops = (k - photon.inline_slots) / CHUNK_SLOTS;
    for (var i = 0u; i < hops && c != CHUNK_NONE; i++) {
        c = atomicLoad(&chunks[chunk_word(p, c)]);
    }
    return c;
}

// The slot of interaction k of path p, one the path holds (k below its count).
fn record_slot(p: u32, head: u32, k: u32) -> u32 {
    if (k < photon.inline_slots) {
        return inline_slot(p, k);
    }
    return chunk_slot(p, chain_chunk(p, head, k), (k - photon.inline_slots) % CHUNK_SLOTS);
}

// Walks a path's slots in order (interaction k, then k + 1, ...) with one next-pointer read
// per chunk, where record_slot walks the list from its head for every interaction.
struct SlotCursor {
    k: u32,
    // The chunk that holds interaction k − 1 (CHUNK_NONE while k − 1 is an inline slot).
    chunk: u32,
}

// The slot of interaction cursor.k (one the path holds), and the cursor moved past it.
fn cursor_slot(p: u32, head: u32, cursor: ptr<function, SlotCursor>) -> u32 {
    let k = (*cursor).k;
    (*cursor).k = k + 1u;
    if (k < photon.inline_slots) {
        return inline_slot(p, k);
    }
    let j = (k - photon.inline_slots) % CHUNK_SLOTS;
    if (j == 0u) {
        if (k == photon.inline_slots) {
            (*cursor).chunk = head;
        } else if ((*cursor).chunk != CHUNK_NONE) {
            (*cursor).chunk = atomicLoad(&chunks[chunk_word(p, (*cursor).chunk)]);
        }
    }
    return chunk_slot(p, (*cursor).chunk, j);
}

// A cursor at interaction k of path p (list starting at head).
fn slot_cursor(p: u32, head: u32, k: u32) -> SlotCursor {
    var chunk = CHUNK_NONE;
    if (k > photon.inline_slots) {
        chunk = chain_chunk(p, head, k - 1u);
    }
    return SlotCursor(k, chunk);
}

// Takes the next free chunk of p's pass as the last of p's list (CHUNK_NONE: none is left).
fn take_chunk(p: u32) -> u32 {
    let c = atomicAdd(&chunks[photon.chunk_counts_at + pass_of(p)], 1u);
    if (c >= photon.chunks_per_pass) {
        return CHUNK_NONE;
    }
    atomicStore(&chunks[chunk_word(p, c)], CHUNK_NONE);
    return c;
}

// MODE_FULL, before `main`: empties the chunk pools of the passes that paths [path_offset,
// + dispatch_paths) belong to and sets their counts to none taken. A full trace takes its
// chunks afresh, and a slot no path takes must hold no photon for the grid.
@compute @workgroup_size(64)
fn trace_clear(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    let pool = photon.photons_per_pass * (photon.path_slots - photon.inline_slots);
    let passes = photon.dispatch_paths / photon.photons_per_pass;
    if (i >= passes * pool) {
        return;
    }
    let pass_index = photon.path_offset / photon.photons_per_pass + i / pool;
    let local = i % pool;
    let block = pass_index * photon.photons_per_pass * photon.path_slots;
    records[block + photon.photons_per_pass * photon.inline_slots + local] = empty_record();
    if (local == 0u) {
        atomicStore(&chunks[photon.chunk_counts_at + pass_index], 0u);
    }
}

// MODE_UPDATE: lists every path of the map whose historygram meets the query.
@compute @workgroup_size(64)
fn trace_mark(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let p = linear_index(gid, groups);
    if (p >= photon.path_count) {
        return;
    }
    let q = path_query_load(p);
    if (hist_hits_rejection_query(q.x, q.y) || hist_hits_collision_query(q.z, q.w)) {
        retrace_list[atomicAdd(&counters[COUNTER_RETRACED], 1u)] = p;
    }
}

// Opacity at v for delta tracking, interpolated as a weighted sum rather than mix's
// a + f·(b − a): each term rounds monotonically, so where an edit lowers LUT entries the
// result cannot rise, and a rejected tentative collision stays rejected (what the collision
// query's exemption of rejected points relies on).
fn tracking_opacity(v: f32) -> f32 {
    let x = clamp(v, 0.0, 1.0) * f32(TF_LUT_SIZE - 1u);
    let i = min(u32(x), TF_LUT_SIZE - 2u);
    let f = x - f32(i);
    return tf_entry(i).a * (1.0 - f) + tf_entry(i + 1u).a * f;
}

// Whether delta tracking takes a tentative point of data value v, with acceptance draw
// `accept`, as a real collision. The update's walk (TRACE_WALK) asks it of an old collision
// under the new TF: the very test the tracking loop would make there.
fn tracking_accepts(accept: f32, v: f32) -> bool {
    return accept * photon.majorant < tracking_opacity(v) * scene.density_scale;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    if (i >= photon.dispatch_paths) {
        return;
    }
    // An update's paths are listed, from path_offset: trace_mark's list for the walk, the
    // walk's (or, where the host skips the walk, trace_mark's) for the trace.
    var p = photon.path_offset + i;
    if (updating()) {
        p = retrace_list[photon.path_offset + i];
    }
    let bounces = photon.bounces;
    // The path's chunk list: a full trace takes chunks afresh; an update keeps the ones the
    // path has (their slots past its end are empty) and takes more only where it grows.
    var head = CHUNK_NONE;
    var old_count = 0u;
    // The historygram of the flight that left the volume after the old path's last record.
    var old_end = vec2<u32>(0u);
    if (updating()) {
        let path = paths[p];
        old_count = path.count;
        head = path.chunk;
        old_end = vec2<u32>(path.end_lo, path.end_hi);
    }
    // The bins of the path's collisions (kept ones, then new ones).
    var collisions = vec2<u32>(0u);
    // An update's walk over the old records: whether one took a new colour (so every later
    // one does), the power of the record before the next it looks at, and that next one.
    var recolour = false;
    var power_before = vec3<f32>(0.0);
    var j = 0;
    var position = vec3<f32>(0.0);
    var direction = vec3<f32>(0.0, 0.0, 1.0);
    var power = vec3<f32>(0.0);
    var hist = vec2<u32>(0u);
    var k = 0u;
    var count = 0u;
    // The tracking steps of the last flight, which stored no record (census).
    var last_steps = 0u;
    // A full trace runs this once. An update walks the old records, tracks from the first one
    // the edit moves, and where that flight collides where it did, walks on from there.
    loop {
        var start = -1;
        // Where an update resumes the first moved flight: at its old collision, whose opacity
        // fell (from the record's RecordResume, just before that point), with the path's
        // historygram up to there (the old record's) and the old record's power.
        var resume = false;
        var resume_from = RecordResume(0.0, 0u);
        var resume_position = vec3<f32>(0.0);
        var resume_hist = vec2<u32>(0u);
        var resume_power = vec3<f32>(0.0);
        if (updating()) {
            // Start after the last interaction the edit did not move: the first moved one is
            // the first whose flight met the rejection query or whose collision's opacity fell.
            // A collision whose colour alone changed stays where it is (the tracking never
            // reads the albedo): it and every record after it only take a new power, formed
            // here as the trace forms it (power × albedo), with no flight tracked. Should that
            // decide whether the path goes on (a power that is now, or was, all zero), the
            // trace resumes there.
            var ends_differently = false;
            var cursor = slot_cursor(p, head, u32(j));
            loop {
                if (j >= i32(old_count)) {
                    break;
                }
                let slot = cursor_slot(p, head, &cursor);
                let r = records[slot];
                // The data value of the record's collision, recomputed from its position: the
                // very point the tracker classified.
                let value = data_at(r.position);
                let bit = hist_bit(value);
                let opacity_fell_here = hist_hits_collision_query(bit.x, bit.y) && hist_hits_opacity_query(bit.x, bit.y);
                if (hist_hits_rejection_query(r.hist_lo, r.hist_hi)) {
                    break;
                }
                if (opacity_fell_here && TRACE_WALK) {
                    // The resumed flight's first draw gives the old collision's t again, its
                    // second the acceptance there (below).
                    var rng = rng_new(scene.seed, p, u32(j));
                    rng.dim = record_resumes[slot].draws + 1u;
                    if (!tracking_accepts(rng_next(&rng), value)) {
                        defer_trace(p);
                        return;
                    }
                } else if (opacity_fell_here) {
                    // No tentative point of this flight met a bin whose opacity rose, so every
                    // one before the collision stays rejected (tracking_opacity cannot rise
                    // where the LUT fell): the flight resumes at the collision (`resume`).
                    resume = true;
                    resume_from = record_resumes[slot];
                    resume_position = r.position;
                    resume_hist = vec2<u32>(r.hist_lo, r.hist_hi);
                    resume_power = r.power;
                    break;
                }
                collisions |= bit;
                recolour = recolour || hist_hits_collision_query(bit.x, bit.y);
                if (!recolour) {
                    power_before = r.power;
                    j += 1;
                    continue;
                }
                if (j == 0) {
                    var rng = rng_new(scene.seed, p, 0u);
                    power_before = emit(&rng).power;
                }
                let power = roulette_carry(power_before, u32(j)) * classify(value).rgb;
                // The trace goes on after a record only while its power is not all zero.
                let ends_here_differently = all(power <= vec3<f32>(0.0)) != all(r.power <= vec3<f32>(0.0));
                if (TRACE_WALK && ends_here_differently) {
                    // Left to the trace before its power is stored: the trace's walk finds this
                    // record's old power, and so that the path ends differently here.
                    defer_trace(p);
                    return;
                }
                store_power(slot, r, power);
                power_before = power;
                j += 1;
                if (ends_here_differently) {
                    ends_differently = true;
                    break;
                }
            }
            start = j - 1;
            // Every record stayed in place and the flight that left the volume after the last
            // one cannot collide now: nothing to track.
            let escape_may_collide = old_count < bounces && hist_hits_rejection_query(old_end.x, old_end.y);
            if (recolour && j == i32(old_count) && !ends_differently && !escape_may_collide) {
                atomicAdd(&counters[COUNTER_RECOLOURED], 1u);
                return;
            }
            if (TRACE_WALK) {
                defer_trace(p);
                return;
            }
        }

        k = 0u;
        if (start >= 0) {
            let r = records[record_slot(p, head, u32(start))];
            position = r.position;
            direction = r.direction;
            power = r.power;
            hist = vec2<u32>(r.hist_lo, r.hist_hi);
            k = u32(start) + 1u;
        }
        // The chunk that holds interaction k − 1 (past the inline slots).
        let chunk_at_start = slot_cursor(p, head, k);
        var chunk = chunk_at_start.chunk;
        count = k;
        // Whether the resumed flight collided where it did: the walk goes on after it.
        var walk_on = false;
        loop {
            if (k >= bounces) {
                break;
            }
            var rng = rng_new(scene.seed, p, k);
            var origin: vec3<f32>;
            var dir: vec3<f32>;
            if (k == 0u) {
                let e = emit(&rng);
                origin = e.origin;
                dir = e.direction;
                power = e.power;
            } else {
                if (all(power <= vec3<f32>(0.0))) {
                    break;
                }
                if (roulette_applies(k)) {
                    if (rng_next(&rng) >= photon.roulette_survival) {
                        break;
                    }
                    power = roulette_carry(power, k);
                }
                let u1 = rng_next(&rng);
                let u2 = rng_next(&rng);
                dir = sample_hg(direction, scene.g, u1, u2);
                origin = position;
            }
            let hit = intersect_box(origin, dir, scene.box_min, scene.box_max);
            if (hit.x >= hit.y || photon.majorant <= 0.0) {
                break;
            }
            var t = hit.x;
            var collided = false;
            var albedo = vec3<f32>(0.0);
            var steps = 0u;
            // Where the collision's flight stood before its point (the record's resume).
            var resume_at = RecordResume(0.0, 0u);
            // Only the first flight an update tracks resumes: at the t and with the draws the
            // flight that stored the old record had just before its collision point, so the
            // tracking loop decides that point again and goes on as a full trace would, with
            // the path's historygram up to there. The points before it were rejected and stay
            // rejected (their opacity cannot have risen), so they are not replayed.
            let resumed = resume;
            if (resume) {
                resume = false;
                rng.dim = resume_from.draws;
                t = resume_from.t;
                hist = resume_hist;
            }
            loop {
                steps += 1u;
                resume_at = RecordResume(t, rng.dim);
                t += -log(1.0 - rng_next(&rng)) / photon.majorant;
                if (t >= hit.y) {
                    break;
                }
                let x = origin + dir * t;
                let accept = rng_next(&rng);
                let v = data_at(x);
                hist |= hist_bit(v);
                if (tracking_accepts(accept, v)) {
                    collided = true;
                    albedo = classify(v).rgb;
                    position = x;
                    collisions |= hist_bit(v);
                    break;
                }
            }
            if (!collided) {
                last_steps = steps;
                break;
            }
            // Interaction k's slot: its own, or the next in the path's chunks, taking a chunk
            // where its list ends.
            var slot = 0u;
            if (k < photon.inline_slots) {
                slot = inline_slot(p, k);
            } else {
                let j = (k - photon.inline_slots) % CHUNK_SLOTS;
                if (j == 0u) {
                    var next = head;
                    if (k > photon.inline_slots) {
                        next = atomicLoad(&chunks[chunk_word(p, chunk)]);
                    }
                    if (next == CHUNK_NONE) {
                        next = take_chunk(p);
                        // None left: the path ends here, shorter than a trace with room would
                        // make it; the host sees the pass's count past its chunks.
                        if (next == CHUNK_NONE) {
                            last_steps = steps;
                            break;
                        }
                        if (k == photon.inline_slots) {
                            head = next;
                        } else {
                            atomicStore(&chunks[chunk_word(p, chunk)], next);
                        }
                    }
                    chunk = next;
                }
                slot = chunk_slot(p, chunk, j);
            }
            if (counting()) {
                atomicStore(&scatter[photon.record_capacity + slot], steps);
            }
            direction = dir;
            power *= albedo;
            store_record(slot, PhotonRecord(position, grid_index(grid_cell3(position)), power, hist.x, direction, hist.y));
            record_resumes[slot] = resume_at;
            k += 1u;
            count = k;
            // Collided where it did (the same draws; no earlier point accepted now): the
            // record is the old one but for its colour, and the flights after it start as they
            // did, so the walk takes the old records again, unless whether the path goes on
            // changed with the power.
            if (resumed && all(bitcast<vec3<u32>>(position) == bitcast<vec3<u32>>(resume_position))
                && all(power <= vec3<f32>(0.0)) == all(resume_power <= vec3<f32>(0.0))) {
                walk_on = true;
                break;
            }
        }
        if (!walk_on) {
            break;
        }
        j = i32(k);
        power_before = power;
        recolour = true;
    }
    if (counting()) {
        atomicStore(&scatter[2u * photon.record_capacity + p], last_steps);
    }
    // Interactions past the end of the path hold no photon: in a full trace its inline slots
    // (trace_clear emptied the chunks), in an update the slots the old path filled.
    if (!updating()) {
        for (var r = count; r < photon.inline_slots; r++) {
            store_record(inline_slot(p, r), empty_record());
        }
    } else {
        var tail = slot_cursor(p, head, count);
        for (var r = count; r < old_count; r++) {
            clear_record(cursor_slot(p, head, &tail));
        }
    }
    paths[p] = PhotonPath(count, hist.x, hist.y, collisions.x, collisions.y, head, 0u, 0u);
    path_query_store(p, hist, collisions);
}

// TRACE_WALK: leaves path p to the update's trace (`main`), in the retrace list's second half.
fn defer_trace(p: u32) {
    retrace_list[photon.path_count + atomicAdd(&counters[COUNTER_DEFERRED], 1u)] = p;
}

// Whether interaction k (k >= 1: a scattering) plays Russian roulette first (PhotonUniforms).
fn roulette_applies(k: u32) -> bool {
    return k >= max(photon.roulette_from, 1u) && photon.roulette_survival < 1.0;
}

// The power that goes on to interaction k, from the power of record k − 1: divided by the
// survival probability where k played the roulette. The trace and an update's recolouring
// both form a record's power as roulette_carry(previous, k) × albedo, the same operations,
// so the same bits.
fn roulette_carry(power: vec3<f32>, k: u32) -> vec3<f32> {
    if (roulette_applies(k)) {
        return power / photon.roulette_survival;
    }
    return power;
}

fn bounding_radius() -> f32 {
    return 0.5 * length(scene.box_max - scene.box_min) * 1.001;
}
