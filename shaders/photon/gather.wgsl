// Technique `photon`, pass 3: radiance gathering along view rays split into Vn segments, and
// compositing. Each pixel's ray (through the pixel centre, one fixed jitter of the march
// lattice per pixel) is cut into `segments` equal pieces of its box interval; each segment
// marches its own samples with transmittance starting at 1 and stores the in-scattered
// radiance (an Epanechnikov density estimate of the photons within `radius`, from the
// 27-cell neighbourhood, summed in fixed point: fixed_hi), its transmittance and the
// historygram of its samples' data values. `gather_mark` lists the segments to compute: all in
// MODE_FULL; in MODE_UPDATE those whose historygram meets the opacity query, gathered afresh,
// and those that a changed photon can reach (dirty cells, the spatial historygram, or any
// changed photon), whose samples and weights are as before: they are updated by the change
// grid alone (DELTA_SEGMENT), each changed record's old term subtracted and its new one added,
// which in integer arithmetic gives the very bits of a full gather at the cost of the changed
// photons only; while the delta scatter has slots (photon/scatter.wgsl) it takes them instead,
// from the changed photons' side. Listing them keeps every SIMD lane of the gather busy (a
// sparse update would otherwise pay for whole idle batches).
//
// `gather` serves both formulations, as two pipelines that set SAMPLE_SUMS: segments that
// sum their photons' weighted terms (false), or samples that keep their photon sums and
// segments that weight them (true). Each pipeline compiles without the other's code: with
// the choice made at run time, llvmpipe's full gathers without the sums were 25–35% slower
// (CT volumes at 256²).
// `gather` counts its loop iterations and, after `round_budget` of them, keeps its place in
// `gather_state`; the host runs rounds over the segments still listed until none is left. The
// sums do not depend on the budget: llvmpipe silently ends an invocation's loops after 65535
// iterations in all, and dense cells exceed that.
// With per-sample sums, a segment whose opacity did not change recomposites from its samples'
// kept sums and weights (recomposite_from_sums): in the gather where gather_mark lists it, and,
// where an update's only segments to compute are those the marks listed, in
// `recomposite_touched` instead of gather_mark_touched and the gather.
// In an opacity edit whose marks stand, `gather_mark_stale` and `gather_mark_touched` list
// what gather_mark would, and with complete sums that hold the update's changes,
// `remarch_from_sums` computes the listed segments whose samples all have their sums before
// the gather takes the rest: llvmpipe runs every branch of a kernel, masked, for every SIMD
// batch, so the general kernels cost these cases as much as their hardest ones.
// `composite` multiplies the segments front to back.
// Rust twin: server/engine/src/techniques/photon/gpu.rs.

#import photon/common

// Whether this pipeline's gather keeps per-sample photon sums (the host's
// PhotonBudget::sample_cache_samples > 0); see the header.
override SAMPLE_SUMS: bool = false;

// Whether this `composite` pipeline ends an update whose segments the marks passes listed
// (gather_mark_stale, gather_mark_touched, recomposite_touched; not gather_mark, whose full
// gathers must not pay for the marking): it recomposites only the pixels whose segments the
// update computed (mark_pixel_changed); every other pixel's output and historygram union are
// what the last composite left. The composite reads every segment of each pixel it visits,
// which cost the chest CT's local edits 2.5–3.4 ms of ~13–33 on lavapipe.
override COMPOSITE_CHANGED: bool = false;

// Whether a photon change recorded in the spatial historygram can reach the segment a..b.
fn spatial_hit(a: vec3<f32>, b: vec3<f32>) -> bool {
    let lo = spatial_bins(min(a, b) - vec3<f32>(photon.radius));
    let hi = spatial_bins(max(a, b) + vec3<f32>(photon.radius));
    for (var axis = 0u; axis < 3u; axis++) {
        let m = range_mask(lo[axis], hi[axis]);
        let w0 = atomicLoad(&counters[COUNTER_SPATIAL + axis * 2u]);
        let w1 = atomicLoad(&counters[COUNTER_SPATIAL + axis * 2u + 1u]);
        if (((m.x & w0) | (m.y & w1)) == 0u) {
            return false;
        }
    }
    return true;
}

// Whether any sample of the segment lies in a dirty cell (SPATIAL_CELLS): every half-size cell
// that comes within the gather radius of a changed photon is marked, so this finds every
// change within the gather radius of a sample. Visits every lattice sample in [ta, tb) (a
// superset of those gathered).
fn cells_hit(pixel: u32, hit: vec2<f32>, ta: f32, tb: f32, dir: vec3<f32>) -> bool {
    let jitter = pixel_jitter(pixel);
    var k = first_lattice_index(hit, ta, jitter);
    loop {
        let t = hit.x + (k + jitter) * photon.gather_step;
        k += 1.0;
        if (t < ta) {
            continue;
        }
        if (t >= tb) {
            break;
        }
        if (dirty(scene.eye + dir * t)) {
            return true;
        }
    }
    return false;
}

// Whether a changed photon may lie within the gather radius of x.
fn dirty(x: vec3<f32>) -> bool {
    let cell = dirty_index(dirty_cell3(x));
    return (atomicLoad(&counters[COUNTER_DIRTY + cell / 32u]) & (1u << (cell % 32u))) != 0u;
}

@compute @workgroup_size(64)
fn gather_mark(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let id = linear_index(gid, groups);
    if (id >= scene.width * scene.height * photon.segments) {
        return;
    }
    mark_segment(id);
}

// gather_mark over the segments scatter_touch listed (in the second half of gather_list),
// where the marks stand for the dirty cells (the host checks): where no opacity changed, they
// are all an update can change, and the other segments need nothing; in an opacity edit,
// gather_mark_stale lists those whose opacity changed, so here they only lose their mark.
@compute @workgroup_size(64)
fn gather_mark_touched(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = linear_index(gid, groups);
    if (index >= atomicLoad(&counters[COUNTER_LIST + 1u])) {
        return;
    }
    let id = gather_list[scene.width * scene.height * photon.segments + index];
    if (hist_hits_opacity_query(segments[id].hist_lo, segments[id].hist_hi)) {
        atomicStore(&scatter[id], SEGMENT_UNTOUCHED);
        return;
    }
    // A marked segment is computed (mark_segment lists or slots it) unless its ray misses the
    // box, where recompositing the pixel changes nothing.
    mark_pixel_changed(id / photon.segments);
    mark_segment(id);
}

// gather_mark in an opacity edit whose marks stand (the host checks), with
// gather_mark_touched: lists the segments whose opacity changed, to be gathered afresh. The
// others need nothing unless the marks listed them. One invocation per pixel, which it skips
// by the union of its segments' historygrams (Segment.pixel_hist_lo/hi). A kernel of its own
// because llvmpipe runs every branch of a kernel's code for every SIMD batch, masked:
// gather_mark's other cases would cost every segment about as much as this does.
@compute @workgroup_size(64)
fn gather_mark_stale(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let pixel = linear_index(gid, groups);
    if (pixel >= scene.width * scene.height) {
        return;
    }
    let first = pixel * photon.segments;
    if (!hist_hits_opacity_query(segments[first].pixel_hist_lo, segments[first].pixel_hist_hi)) {
        return;
    }
    let hit = intersect_box(scene.eye, pixel_ray(pixel), scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        return;
    }
    var listed = false;
    for (var s = 0u; s < photon.segments; s++) {
        let id = first + s;
        let old = segments[id];
        if (!hist_hits_opacity_query(old.hist_lo, old.hist_hi)) {
            continue;
        }
        if (old.cut_off != 0u) {
            atomicAdd(&counters[COUNTER_CUT], 1u);
        }
        atomicAdd(&counters[COUNTER_SEGMENTS], 1u);
        list_from_start(id);
        listed = true;
    }
    if (listed) {
        mark_pixel_changed(pixel);
    }
}

// With per-sample sums, in place of gather_mark_touched and the gather where an update's
// segments to compute are those scatter_touch listed and its marks stand (the host checks: no
// opacity changed, and the marks added every change to the sums): recomposites each from its
// samples' kept sums and weights (recomposite_from_sums), and lists for the gather, as
// gather_mark would, the few it cannot (a sample without a valid sum). Counts each as
// gather_mark does.
@compute @workgroup_size(64)
fn recomposite_touched(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let index = linear_index(gid, groups);
    if (index >= atomicLoad(&counters[COUNTER_LIST + 1u])) {
        return;
    }
    let id = gather_list[scene.width * scene.height * photon.segments + index];
    atomicStore(&scatter[id], SEGMENT_UNTOUCHED);
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        return;
    }
    atomicAdd(&counters[COUNTER_DELTA], 1u);
    atomicAdd(&counters[COUNTER_SEGMENTS], 1u);
    mark_pixel_changed(pixel);
    let bounds = segment_bounds(hit, id % photon.segments);
    let jitter = pixel_jitter(pixel);
    // No budget: a segment holds at most a view ray's samples, far fewer than llvmpipe's
    // loop limit.
    var used = 0u;
    if (recomposite_from_sums(id, hit, bounds, jitter, 0xffffffffu, &used)) {
        return;
    }
    list_from_start(id);
}

// A segment's gather from its first lattice index k: nothing summed, full transmittance.
fn gather_start(k: f32) -> GatherState {
    return GatherState(vec3<u32>(0u), k, vec3<u32>(0u), 1.0, 0u, 0u, NEXT_SAMPLE, 0u);
}

// Lists segment id for the gather afresh, from its first lattice index (FRESH_SEGMENT).
fn list_from_start(id: u32) {
    gather_list[atomicAdd(&counters[COUNTER_LIST], 1u)] = id | FRESH_SEGMENT;
}

// The segment a gather_list entry names (without its flags).
fn entry_segment(entry: u32) -> u32 {
    return entry & ~(DELTA_SEGMENT | FRESH_SEGMENT);
}

// Lists segment id for the gather if it must be computed, as a full gather or an update
// needs, and leaves its delta-scatter mark cleared.
fn mark_segment(id: u32) {
    var touched = false;
    if (photon.mode == MODE_UPDATE && photon.scatter_capacity > 0u) {
        touched = atomicLoad(&scatter[id]) == SEGMENT_TOUCHED;
        atomicStore(&scatter[id], SEGMENT_UNTOUCHED);
    }
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    if (hit.x >= hit.y) {
        if (photon.mode == MODE_FULL) {
            segments[id] = Segment(vec3<u32>(0u), 1.0, vec3<u32>(0u), 0u, 0u, 0u, 0u, 0u);
        }
        return;
    }
    let bounds = segment_bounds(hit, id % photon.segments);
    var stale = true;
    var delta = false;
    var scattered = false;
    var start = gather_start(0.0);
    if (photon.mode == MODE_UPDATE) {
        let old = segments[id];
        stale = hist_hits_opacity_query(old.hist_lo, old.hist_hi);
        if (stale && old.cut_off != 0u) {
            atomicAdd(&counters[COUNTER_CUT], 1u);
        }
        if (!stale) {
            if (photon.spatial == SPATIAL_AXES) {
                stale = spatial_hit(scene.eye + dir * bounds.x, scene.eye + dir * bounds.y);
            } else if (photon.spatial == SPATIAL_CELLS) {
                if (photon.marks_stand != 0u) {
                    stale = touched;
                } else {
                    stale = cells_hit(pixel, hit, bounds.x, bounds.y, dir);
                }
            } else {
                stale = atomicLoad(&counters[COUNTER_CHANGED]) > 0u;
            }
            // Unless the change list overflowed, only the changed photons' terms differ.
            delta = stale && atomicLoad(&counters[COUNTER_CHANGES]) <= photon.change_capacity;
            if (delta && photon.sample_cache_samples > 0u) {
                // With per-sample sums the segment recomposites from them (counted as updated
                // by the changes alone: no photon of the records is visited), by their kept
                // weights where it can (recomposite_from_sums).
                atomicAdd(&counters[COUNTER_DELTA], 1u);
            } else if (delta) {
                start.color_lo = old.color_lo;
                start.color_hi = old.color_hi;
                atomicAdd(&counters[COUNTER_DELTA], 1u);
                // The delta scatter takes it while it has slots (photon/scatter.wgsl).
                if (photon.scatter_capacity > 0u && atomicLoad(&counters[COUNTER_SCATTER_OVERFLOW]) == 0u) {
                    let slot = atomicAdd(&counters[COUNTER_SCATTER], 1u);
                    if (slot < photon.scatter_capacity) {
                        atomicStore(&scatter[id], slot + 2u);
                        atomicStore(&scatter[slot_word(slot, 0u)], id);
                        scattered = true;
                    }
                }
            }
        }
        if (stale) {
            atomicAdd(&counters[COUNTER_SEGMENTS], 1u);
        }
    }
    if (stale) {
        start.k = first_lattice_index(hit, bounds.x, pixel_jitter(pixel));
        // Kept for a scattered segment too, in case the scatter overflows.
        gather_state[id] = start;
        if (!scattered) {
            gather_list[atomicAdd(&counters[COUNTER_LIST], 1u)] = select(id, id | DELTA_SEGMENT, delta);
        }
    }
}

// GatherState.cell: 0..26 = the neighbour cell being visited (dz, dy, dx from −1, dx fastest),
// NEXT_SAMPLE = take the next lattice sample.
const NEXT_SAMPLE: u32 = 28u;

// Keeps the segment's place for the next round and lists it there (its entry's DELTA_SEGMENT
// flag kept; no longer FRESH_SEGMENT, its state now being in gather_state).
fn defer_segment(entry: u32, st: GatherState, segment_count: u32) {
    gather_state[entry_segment(entry)] = st;
    let next = 1u - photon.round_input;
    gather_list[next * segment_count + atomicAdd(&counters[COUNTER_LIST + next], 1u)] = entry & ~FRESH_SEGMENT;
}

// GatherState.cell past the 27 neighbours: the segment's samples are done, and the march goes
// on past its transmittance cut-off only to forget the photon sums of dirty samples
// (forget_dirty_sums).
const FORGET_TAIL: u32 = 29u;
// GatherState.cell of a sample whose terms are all known without visiting a cell (its kept
// sum, or no change within the radius).
const SKIP_CELLS: u32 = 30u;

// With per-sample sums, the grid a sample's gather visits: the changes' where its kept sum is
// valid in an update, else the records' (every photon afresh). Decided alike when a sample
// begins and when its gather resumes in a later round (a partial sum leaves the generation
// as it was).
fn sample_grid(kept: u32) -> u32 {
    return select(GRID_RECORDS, GRID_CHANGES, photon.mode == MODE_UPDATE && sample_valid(kept));
}

// With per-sample sums, whether the samples a gather skips must forget their sums: the update's
// changes were not added to them (sums_applied = 0), and a dirty sample may hold a changed
// photon's old term.
fn forget_dirty_sums() -> bool {
    return SAMPLE_SUMS && photon.mode == MODE_UPDATE && photon.sums_applied == 0u;
}

// With per-sample sums, stores the radiance of segment id, whose samples' weights are as its
// last gather kept them (no opacity it meets changed), from their sums: Σ_k fixed(f32(P_k) ·
// w_k), the very terms the gather adds (photon/common.wgsl, sample_weight_word), over the same
// lattice samples, without sampling the volume. Returns false, storing nothing, where a sample
// lacks its kept sum or weight or the loop budget ran out (`budget`: the loop iterations `used`
// may reach): the segment is then gathered.
fn recomposite_from_sums(id: u32, hit: vec2<f32>, bounds: vec2<f32>, jitter: f32, budget: u32, used: ptr<function, u32>) -> bool {
    let pixel = id / photon.segments;
    var sum = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
    var k = first_lattice_index(hit, bounds.x, jitter);
    loop {
        if (*used >= budget) {
            return false;
        }
        *used += 1u;
        let t = hit.x + (k + jitter) * photon.gather_step;
        if (t >= bounds.y) {
            break;
        }
        if (t >= bounds.x) {
            let entry = sample_entry(pixel, k);
            if (entry == SAMPLE_NONE) {
                return false;
            }
            let weight = bitcast<f32>(atomicLoad(&sample_sums[sample_weight_word(entry)]));
            if (weight < 0.0) {
                break;
            }
            if (weight > 0.0) {
                if (!sample_valid(entry)) {
                    return false;
                }
                let acc = sample_read(entry);
                sum = accumulate(sum, fixed_to_f32(acc.lo, acc.hi) * (weight * FIXED_ONE), false);
            }
        }
        k += 1.0;
    }
    segments[id].color_lo = sum.lo;
    segments[id].color_hi = sum.hi;
    return true;
}

// With per-sample sums, where every valid sum holds the update's changes (sums_applied) and
// the sums are complete (the host checks both): before the gather's rounds, over the segments
// gather_mark listed (round 0's list). One whose opacity changed marches afresh, taking each
// sample's photons from its kept sum (march_from_sums), as the gather then does without
// visiting a cell; one listed as a delta recomposites from its samples' sums and weights. It
// lists for the gather, in the other half of gather_list, those it cannot (a sample without a
// valid sum), from the start gather_mark gave them. A kernel of its own: llvmpipe runs the
// gather's photon loops, masked, at every sample of every segment the gather marches.
@compute @workgroup_size(64)
fn remarch_from_sums(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    if (slot >= atomicLoad(&counters[COUNTER_LIST])) {
        return;
    }
    let entry = gather_list[slot];
    let id = entry_segment(entry);
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    let bounds = segment_bounds(hit, id % photon.segments);
    let jitter = pixel_jitter(pixel);
    if ((entry & DELTA_SEGMENT) != 0u) {
        var used = 0u;
        if (recomposite_from_sums(id, hit, bounds, jitter, 0xffffffffu, &used)) {
            return;
        }
    } else if (march_from_sums(id, pixel, dir, hit, bounds, jitter)) {
        return;
    }
    let segment_count = scene.width * scene.height * photon.segments;
    gather_list[segment_count + atomicAdd(&counters[COUNTER_LIST + 1u], 1u)] = id | (entry & FRESH_SEGMENT);
}

// With per-sample sums whose every valid one holds the update's changes: the gather of segment
// id from its start, where each sample its march weights has a valid kept sum: the same march
// (hist, transmittance, cut-off, the samples' weights) and the same terms, `Σ_k fixed(f32(P_k)
// · w_k)` in march order, without visiting a cell. Returns false where a sample lacks its sum:
// the segment is then gathered (the weights stored so far are the ones the gather stores).
fn march_from_sums(id: u32, pixel: u32, dir: vec3<f32>, hit: vec2<f32>, bounds: vec2<f32>, jitter: f32) -> bool {
    var k = first_lattice_index(hit, bounds.x, jitter);
    var transmit = 1.0;
    var hist = vec2<u32>(0u);
    var color = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
    loop {
        let t = hit.x + (k + jitter) * photon.gather_step;
        if (t < bounds.x) {
            k += 1.0;
            continue;
        }
        if (t >= bounds.y) {
            break;
        }
        let kept = sample_entry(pixel, k);
        if (transmit < SEGMENT_T_CUTOFF) {
            sample_set_weight(kept, SAMPLE_PAST_CUTOFF);
            break;
        }
        let v = data_at(scene.eye + dir * t);
        hist |= hist_bit(v);
        let sigma = classify_opacity(v) * scene.density_scale;
        if (sigma <= 0.0) {
            sample_set_weight(kept, 0.0);
            k += 1.0;
            continue;
        }
        if (!sample_valid(kept)) {
            return false;
        }
        let acc = sample_read(kept);
        let weight = transport(transmit, sigma);
        sample_set_weight(kept, weight);
        color = accumulate(color, fixed_to_f32(acc.lo, acc.hi) * (weight * FIXED_ONE), false);
        transmit *= exp(-sigma * photon.gather_step);
        k += 1.0;
    }
    let cut_off = select(0u, 1u, transmit < SEGMENT_T_CUTOFF);
    segments[id] = Segment(color.lo, transmit, color.hi, hist.x, hist.y, cut_off, 0u, 0u);
    return true;
}

@compute @workgroup_size(64)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let invocation = linear_index(gid, groups);
    let slot = photon.round_first + invocation / photon.round_stride;
    let segment_count = scene.width * scene.height * photon.segments;
    if (invocation % photon.round_stride != 0u || slot >= atomicLoad(&counters[COUNTER_LIST + photon.round_input])) {
        return;
    }
    let entry = gather_list[photon.round_input * segment_count + slot];
    let id = entry_segment(entry);
    let delta_entry = (entry & DELTA_SEGMENT) != 0u;
    let cached = SAMPLE_SUMS;
    // A delta segment visits the change grid, a fresh one the records'. With per-sample sums
    // each sample chooses (sample_grid), and its sum so far waits in its entry between
    // rounds.
    let segment_grid = select(GRID_RECORDS, GRID_CHANGES, delta_entry);
    let pixel = id / photon.segments;
    let dir = pixel_ray(pixel);
    let out_dir = -dir;
    let hit = intersect_box(scene.eye, dir, scene.box_min, scene.box_max);
    let bounds = segment_bounds(hit, id % photon.segments);
    let jitter = pixel_jitter(pixel);
    let step = photon.gather_step;
    let r2 = photon.radius * photon.radius;
    let dims = vec3<i32>(photon.grid_dims);
    let budget = photon.round_budget;
    // This invocation's loop iterations; each loop counts its own so that the sum stays
    // within the budget whatever the nesting.
    var used = 0u;
    var listed = entry;
    if (cached && delta_entry) {
        // A segment whose opacity did not change, with the update's changes in its samples'
        // sums (sums_applied): its kept weights are its samples' as they stand.
        if (photon.sums_applied != 0u) {
            if (recomposite_from_sums(id, hit, bounds, jitter, budget, &used)) {
                return;
            }
        }
        // Gathered as any other (a later round too).
        listed = id;
    }
    var st: GatherState;
    if ((entry & FRESH_SEGMENT) != 0u) {
        st = gather_start(first_lattice_index(hit, bounds.x, jitter));
    } else {
        st = gather_state[id];
    }
    // The current sample (recomputed when resuming inside one): position, extinction, the
    // factor its photons' terms start with, its kept sum's entry, the grid it visits, and the
    // sum its terms join (the segment's, or with per-sample sums the sample's).
    var x = scene.eye + dir * (hit.x + (st.k + jitter) * step);
    var sigma = 0.0;
    var lead = 0.0;
    var centre = grid_cell3(x);
    var kept = sample_entry(pixel, st.k);
    var grid = segment_grid;
    var acc = FixedSum(st.color_lo, st.color_hi);
    if (st.cell < NEXT_SAMPLE) {
        sigma = classify_opacity(data_at(x)) * scene.density_scale;
        lead = select(sample_weight(st.transmit, sigma), sum_lead(), cached);
        if (cached) {
            grid = sample_grid(kept);
            acc = sample_read(kept);
        }
    }
    loop {
        if (used >= budget) {
            defer_segment(listed, st, segment_count);
            return;
        }
        used += 1u;
        if (st.cell == FORGET_TAIL) {
            let t = hit.x + (st.k + jitter) * step;
            if (t >= bounds.y) {
                break;
            }
            if (t >= bounds.x && dirty(scene.eye + dir * t)) {
                sample_forget(sample_entry(pixel, st.k));
            }
            st.k += 1.0;
            continue;
        }
        if (st.cell == NEXT_SAMPLE) {
            let t = hit.x + (st.k + jitter) * step;
            if (t < bounds.x) {
                st.k += 1.0;
                continue;
            }
            if (t >= bounds.y) {
                break;
            }
            if (st.transmit < SEGMENT_T_CUTOFF) {
                if (cached) {
                    sample_set_weight(sample_entry(pixel, st.k), SAMPLE_PAST_CUTOFF);
                }
                if (forget_dirty_sums()) {
                    st.cell = FORGET_TAIL;
                    continue;
                }
                break;
            }
            x = scene.eye + dir * t;
            let v = data_at(x);
            let bit = hist_bit(v);
            st.hist_lo |= bit.x;
            st.hist_hi |= bit.y;
            sigma = classify_opacity(v) * scene.density_scale;
            kept = sample_entry(pixel, st.k);
            if (sigma <= 0.0) {
                if (cached) {
                    sample_set_weight(kept, 0.0);
                }
                if (forget_dirty_sums() && dirty(x)) {
                    sample_forget(kept);
                }
                st.k += 1.0;
                continue;
            }
            var visit = true;
            if (cached) {
                // Fresh where the sum is not kept; else the kept sum, plus the changes within
                // the radius where the scatter did not add them.
                grid = sample_grid(kept);
                if (grid == GRID_CHANGES) {
                    acc = sample_read(kept);
                    visit = photon.sums_applied == 0u && dirty(x);
                } else {
                    acc = FixedSum(vec3<u32>(0u), vec3<u32>(0u));
                }
            } else if (segment_grid == GRID_CHANGES && !dirty(x)) {
                // No changed photon within the radius: the sample's terms are as before.
                visit = false;
            }
            lead = select(sample_weight(st.transmit, sigma), sum_lead(), cached);
            centre = grid_cell3(x);
            st.rank = 0u;
            st.cell = select(SKIP_CELLS, 0u, visit);
        }
        let cells_base = grid_base(grid);
        let slots_base = sorted_base(grid);
        for (; st.cell < 27u; st.cell++) {
            used += 1u;
            let n = centre + vec3<i32>(i32(st.cell % 3u), i32(st.cell / 3u % 3u), i32(st.cell / 9u)) - 1;
            if (any(n < vec3<i32>(0)) || any(n >= dims)) {
                continue;
            }
            // A neighbour farther than the radius holds no photon that contributes (about a
            // quarter of the 27 for a uniformly placed sample).
            if (cube_distance2(scene.box_min + vec3<f32>(n) * photon.radius, photon.radius, x) >= r2) {
                continue;
            }
            let cell = cells_base + grid_index(n);
            let first = atomicLoad(&grid_cells[cell]);
            let end = atomicLoad(&grid_cells[cell + 1u]);
            let start = first + st.rank;
            // As many of the cell's photons as the budget allows (at least none).
            // (budget may be u32::MAX: no overflowing sum.)
            let stop = start + min(end - start, budget - min(used, budget));
            for (var i = start; i < stop; i++) {
                let item = grid_sorted[slots_base + i];
                // The position first, the rest only within the radius (about a fifth of the
                // photons visited): llvmpipe loads a storage buffer lane by lane, word by word.
                var position: vec3<f32>;
                var pass_index: u32;
                if (grid == GRID_CHANGES) {
                    position = changes[item].position;
                    pass_index = changes[item].pass_index;
                } else {
                    position = records[item].position;
                    pass_index = record_pass(item);
                }
                let d = x - position;
                let d2 = dot(d, d);
                let kernel = pass_kernel(pass_index);
                if (d2 < kernel.x) {
                    if (photon.census != 0u && grid == GRID_RECORDS) {
                        atomicAdd(&scatter[item], 1u);
                    }
                    var power: vec3<f32>;
                    var direction: vec3<f32>;
                    var kind = CHANGE_ADD;
                    var old_power = vec3<f32>(0.0);
                    if (grid == GRID_CHANGES) {
                        power = changes[item].power;
                        direction = changes[item].direction;
                        kind = changes[item].kind;
                        old_power = changes[item].old_power;
                    } else {
                        power = records[item].power;
                        direction = records[item].direction;
                    }
                    // A replaced photon's two terms share this factor (same position and
                    // direction), so they are the very terms two separate visits would give.
                    let s = lead * phase_hg(dot(direction, out_dir), scene.g) * (1.0 - d2 / kernel.x) * kernel.y;
                    acc = accumulate(acc, power * s, kind == CHANGE_SUBTRACT);
                    if (kind == CHANGE_REPLACE) {
                        acc = accumulate(acc, old_power * s, true);
                    }
                }
            }
            used += stop - start;
            if (stop < end) {
                st.rank = stop - first;
                if (cached) {
                    sample_keep(kept, acc);
                } else {
                    st.color_lo = acc.lo;
                    st.color_hi = acc.hi;
                }
                defer_segment(listed, st, segment_count);
                return;
            }
            st.rank = 0u;
        }
        if (cached) {
            // The sample's sum is kept, and joins the segment's weighted by its transport.
            if (st.cell == 27u) {
                sample_write(kept, acc);
            }
            let weight = transport(st.transmit, sigma);
            sample_set_weight(kept, weight);
            let radiance = fixed_to_f32(acc.lo, acc.hi) * (weight * FIXED_ONE);
            let sum = accumulate(FixedSum(st.color_lo, st.color_hi), radiance, false);
            st.color_lo = sum.lo;
            st.color_hi = sum.hi;
        } else {
            st.color_lo = acc.lo;
            st.color_hi = acc.hi;
        }
        st.transmit *= exp(-sigma * step);
        st.k += 1.0;
        st.cell = NEXT_SAMPLE;
    }
    let cut_off = select(0u, 1u, st.transmit < SEGMENT_T_CUTOFF);
    segments[id] = Segment(st.color_lo, st.transmit, st.color_hi, st.hist_lo, st.hist_hi, cut_off, 0u, 0u);
}

@compute @workgroup_size(64)
fn composite(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let pixel = linear_index(gid, groups);
    if (pixel >= scene.width * scene.height) {
        return;
    }
    if (COMPOSITE_CHANGED) {
        let m = pixel_mark(pixel);
        if ((atomicLoad(&counters[m.x]) & m.y) == 0u) {
            return;
        }
    }
    var radiance = vec3<f32>(0.0);
    var transmit = 1.0;
    var hist = vec2<u32>(0u);
    for (var s = 0u; s < photon.segments; s++) {
        let seg = segments[pixel * photon.segments + s];
        radiance += transmit * fixed_to_f32(seg.color_lo, seg.color_hi);
        transmit *= seg.transmittance;
        hist |= vec2<u32>(seg.hist_lo, seg.hist_hi);
    }
    segments[pixel * photon.segments].pixel_hist_lo = hist.x;
    segments[pixel * photon.segments].pixel_hist_hi = hist.y;
    radiance += transmit * scene.env_radiance;
    accum[pixel] = vec4<f32>(radiance, 1.0);
}
