// scan: inclusive prefix sum of u32 values, 256 values per workgroup (one per invocation,
// linear workgroup id over a 2D grid). `scan_blocks` scans each block in workgroup memory
// (Hillis-Steele, no subgroup operations) and writes the block total to block_sums;
// the launcher scans block_sums recursively, then `add_block_offsets` adds the inclusive sum
// of all preceding blocks. Invariant: only indices < count are read or written.

struct ScanParams {
    count: u32,
    padding0: u32,
    padding1: u32,
    padding2: u32,
}

@group(0) @binding(0) var<uniform> scan_params: ScanParams;
@group(0) @binding(1) var<storage, read_write> values: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

const BLOCK_SIZE: u32 = 256u;
var<workgroup> partial_sums: array<u32, BLOCK_SIZE>;

@compute @workgroup_size(256)
fn scan_blocks(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = workgroup_id.y * workgroup_count.x + workgroup_id.x;
    let index = block * BLOCK_SIZE + local_index;
    var value = 0u;
    if index < scan_params.count {
        value = values[index];
    }
    partial_sums[local_index] = value;
    workgroupBarrier();
    for (var offset = 1u; offset < BLOCK_SIZE; offset = offset * 2u) {
        var addend = 0u;
        if local_index >= offset {
            addend = partial_sums[local_index - offset];
        }
        workgroupBarrier();
        partial_sums[local_index] += addend;
        workgroupBarrier();
    }
    if index < scan_params.count {
        values[index] = partial_sums[local_index];
    }
    // Surplus workgroups of a 2D grid must not write past the block table.
    if local_index == BLOCK_SIZE - 1u && block * BLOCK_SIZE < scan_params.count {
        block_sums[block] = partial_sums[local_index];
    }
}

@compute @workgroup_size(256)
fn add_block_offsets(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = workgroup_id.y * workgroup_count.x + workgroup_id.x;
    let index = block * BLOCK_SIZE + local_index;
    if block > 0u && index < scan_params.count {
        values[index] += block_sums[block - 1u];
    }
}
