// scan: prefix sum of u32 values in place, inclusive or exclusive. One invocation per chunk of
// SCAN_CHUNK consecutive values (64 invocations per workgroup, linear workgroup id over a 2D grid),
// each walking its chunk serially: on CPU adapters (lavapipe) this costs 3 memory accesses per
// value and no barriers, where a tree scan in workgroup memory costs dozens.
// - `scan_blocks`: block_sums[c] = sum of chunk c.
// - the launcher scans block_sums (inclusive, recursively),
// - `add_block_offsets`: rewrites chunk c as its running sum starting from the inclusive sum
//   of all preceding chunks (block_sums[c - 1]); exclusive when scan_params.exclusive != 0.
// Invariant: only indices < count are read or written.

@group(0) @binding(0) var<uniform> scan_params: ScanParams;
@group(0) @binding(1) var<storage, read_write> values: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

fn chunk_index(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>, local_index: u32) -> u32 {
    return linear_workgroup(workgroup_id, workgroup_count) * SERIAL_WORKGROUP_SIZE + local_index;
}

@compute @workgroup_size(SERIAL_WORKGROUP_SIZE)
fn scan_blocks(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let chunk = chunk_index(workgroup_id, workgroup_count, local_index);
    let first = chunk * SCAN_CHUNK;
    if first >= scan_params.count {
        return;
    }
    let last = min(first + SCAN_CHUNK, scan_params.count);
    var total = 0u;
    for (var i = first; i < last; i++) {
        total += values[i];
    }
    block_sums[chunk] = total;
}

@compute @workgroup_size(SERIAL_WORKGROUP_SIZE)
fn add_block_offsets(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let chunk = chunk_index(workgroup_id, workgroup_count, local_index);
    let first = chunk * SCAN_CHUNK;
    if first >= scan_params.count {
        return;
    }
    let last = min(first + SCAN_CHUNK, scan_params.count);
    var running = 0u;
    if chunk > 0u {
        running = block_sums[chunk - 1u];
    }
    let exclusive = scan_params.exclusive != 0u;
    for (var i = first; i < last; i++) {
        let value = values[i];
        values[i] = select(running + value, running, exclusive);
        running += value;
    }
}
