// Technique `photon`, pass 2: the spatial hash grid (cell edge = gather radius) by a counting
// sort: clear, count (atomics), exclusive prefix sum (by blocks), scatter (atomic cursors).
// The order within a cell is whatever the atomics give: the gather's fixed-point sums do not
// depend on it. `grid_pass` picks the grid: the records' (every build), or, in an update, the
// change list's (the old and new versions of the records it changed, see PhotonChange). Entry points grid_clear,
// grid_count, grid_scan_reduce, grid_scan_blocks, grid_scan_apply, grid_scatter.
// Rust twin: server/engine/src/techniques/photon/gpu.rs.

#import photon/common

const SCAN_THREADS: u32 = 256u;
const CELLS_PER_THREAD: u32 = 16u;
// Cells per workgroup of the scan (SCAN_BLOCK in photon/mod.rs).
const SCAN_BLOCK: u32 = SCAN_THREADS * CELLS_PER_THREAD;

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

// The exclusive prefix sum of the cells' counts runs in three steps, so that it spreads over
// the device instead of one workgroup walking up to MAX_GRID_CELLS cells: each workgroup sums
// a block of SCAN_BLOCK cells (grid_scan_reduce), one workgroup scans the blocks' sums
// (grid_scan_blocks), and each workgroup scans its block from its offset (grid_scan_apply).
fn block_sum_word(block: u32) -> u32 {
    // After both grids (PhotonBudget::grid_cell_bytes).
    return 2u * (2u * photon.cell_count + 1u) + block;
}

// This thread's cells of block `block`: [first, end).
fn thread_cells(block: u32, thread: u32) -> vec2<u32> {
    let first = min(block * SCAN_BLOCK + thread * CELLS_PER_THREAD, photon.cell_count);
    return vec2<u32>(first, min(first + CELLS_PER_THREAD, photon.cell_count));
}

fn count_cells(cells: vec2<u32>) -> u32 {
    var sum = 0u;
    for (var c = cells.x; c < cells.y; c++) {
        sum += atomicLoad(&grid_cells[cursor(c)]);
    }
    return sum;
}

// Replaces scan_sums[0..n) by its exclusive prefix sum and returns the total (thread 0 only).
fn scan_shared(n: u32) -> u32 {
    var running = 0u;
    for (var t = 0u; t < n; t++) {
        let s = scan_sums[t];
        scan_sums[t] = running;
        running += s;
    }
    return running;
}

@compute @workgroup_size(256)
fn grid_scan_reduce(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    scan_sums[lid.x] = count_cells(thread_cells(wid.x, lid.x));
    workgroupBarrier();
    if (lid.x == 0u) {
        atomicStore(&grid_cells[block_sum_word(wid.x)], scan_shared(SCAN_THREADS));
    }
}

@compute @workgroup_size(256)
fn grid_scan_blocks(@builtin(local_invocation_id) lid: vec3<u32>) {
    let blocks = (photon.cell_count + SCAN_BLOCK - 1u) / SCAN_BLOCK;
    let chunk = (blocks + SCAN_THREADS - 1u) / SCAN_THREADS;
    let first = min(lid.x * chunk, blocks);
    let end = min(first + chunk, blocks);
    var sum = 0u;
    for (var b = first; b < end; b++) {
        sum += atomicLoad(&grid_cells[block_sum_word(b)]);
    }
    scan_sums[lid.x] = sum;
    workgroupBarrier();
    if (lid.x == 0u) {
        let total = scan_shared(SCAN_THREADS);
        atomicStore(&grid_cells[grid_base(photon.grid_pass) + photon.cell_count], total);
    }
    workgroupBarrier();
    var offset = scan_sums[lid.x];
    for (var b = first; b < end; b++) {
        let sum = atomicLoad(&grid_cells[block_sum_word(b)]);
        atomicStore(&grid_cells[block_sum_word(b)], offset);
        offset += sum;
    }
}

@compute @workgroup_size(256)
fn grid_scan_apply(@builtin(local_invocation_id) lid: vec3<u32>, @builtin(workgroup_id) wid: vec3<u32>) {
    let cells = thread_cells(wid.x, lid.x);
    scan_sums[lid.x] = count_cells(cells);
    workgroupBarrier();
    if (lid.x == 0u) {
        scan_shared(SCAN_THREADS);
    }
    workgroupBarrier();
    let base = grid_base(photon.grid_pass);
    var offset = atomicLoad(&grid_cells[block_sum_word(wid.x)]) + scan_sums[lid.x];
    for (var c = cells.x; c < cells.y; c++) {
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
