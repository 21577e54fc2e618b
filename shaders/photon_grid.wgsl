// Technique `photon`, pass 2: the spatial hash grid (cell edge = gather radius), rebuilt from
// the photon records by a counting sort: clear, count (atomics), exclusive prefix sum (one
// workgroup), scatter (atomic cursors) into scratch, then each record placed at its rank by
// record index within its cell, so that the gather visits photons in an order that does not
// depend on atomic timing (bit-exact sums). Entry points grid_clear, grid_count, grid_scan, grid_scatter, grid_sort.
// Rust twin: server/engine/src/passes/photon.rs.

const SCAN_THREADS: u32 = 256u;

var<workgroup> scan_sums: array<u32, SCAN_THREADS>;
var<workgroup> scan_max: array<u32, SCAN_THREADS>;

fn cursor(c: u32) -> u32 {
    return photon.cell_count + 1u + c;
}

@compute @workgroup_size(64)
fn grid_clear(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let c = linear_index(gid, groups);
    if (c == 0u) {
        // gather_mark lists afresh after every grid build.
        atomicStore(&counters[COUNTER_LIST], 0u);
    }
    if (c < photon.cell_count) {
        atomicStore(&grid_cells[cursor(c)], 0u);
    }
}

@compute @workgroup_size(64)
fn grid_count(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = linear_index(gid, groups);
    if (r >= photon.record_count) {
        return;
    }
    let cell = records[r].cell;
    if (cell != CELL_NONE) {
        atomicAdd(&grid_cells[cursor(cell)], 1u);
    }
}

@compute @workgroup_size(256)
fn grid_scan(@builtin(local_invocation_id) lid: vec3<u32>) {
    let n = photon.cell_count;
    let chunk = (n + SCAN_THREADS - 1u) / SCAN_THREADS;
    let first = min(lid.x * chunk, n);
    let end = min(first + chunk, n);
    var sum = 0u;
    var most = 0u;
    for (var c = first; c < end; c++) {
        let count = atomicLoad(&grid_cells[cursor(c)]);
        sum += count;
        most = max(most, count);
    }
    scan_sums[lid.x] = sum;
    scan_max[lid.x] = most;
    workgroupBarrier();
    if (lid.x == 0u) {
        var running = 0u;
        var fullest = 0u;
        for (var t = 0u; t < SCAN_THREADS; t++) {
            let s = scan_sums[t];
            scan_sums[t] = running;
            running += s;
            fullest = max(fullest, scan_max[t]);
        }
        atomicStore(&grid_cells[n], running);
        // The host checks it against the device's loop limit (the sort's rank loop).
        atomicStore(&counters[COUNTER_MAX_CELL], fullest);
    }
    workgroupBarrier();
    var offset = scan_sums[lid.x];
    for (var c = first; c < end; c++) {
        let count = atomicLoad(&grid_cells[cursor(c)]);
        atomicStore(&grid_cells[c], offset);
        atomicStore(&grid_cells[cursor(c)], offset);
        offset += count;
    }
}

// Scatter into the scratch half of grid_sorted (after the first record_count entries), in
// whatever order the atomics give.
@compute @workgroup_size(64)
fn grid_scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = linear_index(gid, groups);
    if (r >= photon.record_count) {
        return;
    }
    let cell = records[r].cell;
    if (cell != CELL_NONE) {
        let slot = atomicAdd(&grid_cells[cursor(cell)], 1u);
        grid_sorted[photon.record_count + slot] = r;
    }
}

// Each scattered record finds its rank among its cell's records by index and writes itself
// there: every cell ends up ordered by record index whatever the atomic order was, and every
// output slot is written exactly once from read-only scratch.
@compute @workgroup_size(64)
fn grid_sort(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let slot = linear_index(gid, groups);
    let total = atomicLoad(&grid_cells[photon.cell_count]);
    if (slot >= total) {
        return;
    }
    let scratch = photon.record_count;
    let r = grid_sorted[scratch + slot];
    let cell = records[r].cell;
    let first = atomicLoad(&grid_cells[cell]);
    let end = atomicLoad(&grid_cells[cell + 1u]);
    var rank = 0u;
    for (var i = first; i < end; i++) {
        if (grid_sorted[scratch + i] < r) {
            rank += 1u;
        }
    }
    grid_sorted[first + rank] = r;
}
