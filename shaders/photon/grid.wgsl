// Technique `photon`, pass 2: the spatial hash grid (cell edge = gather radius) by a counting
// sort: clear, count (atomics), exclusive prefix sum (one workgroup), scatter (atomic cursors).
// The order within a cell is whatever the atomics give: the gather's fixed-point sums do not
// depend on it. `grid_pass` picks the grid: the records' (every build), or, in an update, the
// change list's (the old and new versions of the records it changed, see PhotonChange). Entry points grid_clear,
// grid_count, grid_scan, grid_scatter.
// Rust twin: server/engine/src/techniques/photon/gpu.rs.

#import photon/common

const SCAN_THREADS: u32 = 256u;

var<workgroup> scan_sums: array<u32, SCAN_THREADS>;

fn cursor(c: u32) -> u32 {
    return grid_base(photon.grid_pass) + photon.cell_count + 1u + c;
}

// Items the grid indexes: the records, or the change list's entries.
fn item_count() -> u32 {
    if (photon.grid_pass == GRID_CHANGES) {
        return min(atomicLoad(&counters[COUNTER_CHANGES]), photon.change_capacity);
    }
    return photon.record_count;
}

fn item_cell(i: u32) -> u32 {
    if (photon.grid_pass == GRID_CHANGES) {
        return changes[i].cell;
    }
    return records[i].cell;
}

@compute @workgroup_size(64)
fn grid_clear(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let c = linear_index(gid, groups);
    if (c < photon.cell_count) {
        atomicStore(&grid_cells[cursor(c)], 0u);
    }
}

@compute @workgroup_size(64)
fn grid_count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    if (i >= item_count()) {
        return;
    }
    let cell = item_cell(i);
    if (cell != CELL_NONE) {
        atomicAdd(&grid_cells[cursor(cell)], 1u);
    }
}

@compute @workgroup_size(256)
fn grid_scan(@builtin(local_invocation_id) lid: vec3<u32>) {
    let n = photon.cell_count;
    let base = grid_base(photon.grid_pass);
    let chunk = (n + SCAN_THREADS - 1u) / SCAN_THREADS;
    let first = min(lid.x * chunk, n);
    let end = min(first + chunk, n);
    var sum = 0u;
    for (var c = first; c < end; c++) {
        sum += atomicLoad(&grid_cells[cursor(c)]);
    }
    scan_sums[lid.x] = sum;
    workgroupBarrier();
    if (lid.x == 0u) {
        var running = 0u;
        for (var t = 0u; t < SCAN_THREADS; t++) {
            let s = scan_sums[t];
            scan_sums[t] = running;
            running += s;
        }
        atomicStore(&grid_cells[base + n], running);
    }
    workgroupBarrier();
    var offset = scan_sums[lid.x];
    for (var c = first; c < end; c++) {
        let count = atomicLoad(&grid_cells[cursor(c)]);
        atomicStore(&grid_cells[base + c], offset);
        atomicStore(&grid_cells[cursor(c)], offset);
        offset += count;
    }
}

@compute @workgroup_size(64)
fn grid_scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    if (i >= item_count()) {
        return;
    }
    let cell = item_cell(i);
    if (cell != CELL_NONE) {
        let slot = atomicAdd(&grid_cells[cursor(cell)], 1u);
        grid_sorted[sorted_base(photon.grid_pass) + slot] = i;
    }
}
