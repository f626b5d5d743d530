// sort: one pass of a stable least-significant-digit radix sort on u32 keys with u32 values,
// RADIX_BITS bits per pass, 256 elements per workgroup (one per invocation, linear workgroup id
// over a 2D grid). `histogram` counts each block's digits into block_histograms laid out
// digit-major ([digit * block_count + block]) so that an inclusive scan of that table gives
// every (digit, block) its output range in key order. `scatter` ranks each element among the
// equal digits before it in its block (a plain loop over workgroup memory: no subgroup
// operations, and the rank keeps equal keys in input order, which makes the sort stable).

struct SortParams {
    shift: u32,
    count: u32,
    block_count: u32,
    padding: u32,
}

@group(0) @binding(0) var<uniform> sort_params: SortParams;
@group(0) @binding(1) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read> values_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> block_histograms: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;

const BLOCK_SIZE: u32 = 256u;
const RADIX_BITS: u32 = 4u;
const RADIX: u32 = 16u;
const DIGIT_MASK: u32 = 15u;
// Marks padding lanes of the last block; never equal to a real digit.
const NO_DIGIT: u32 = 0xffffffffu;

var<workgroup> digit_counts: array<atomic<u32>, RADIX>;
var<workgroup> block_digits: array<u32, BLOCK_SIZE>;

@compute @workgroup_size(256)
fn histogram(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = workgroup_id.y * workgroup_count.x + workgroup_id.x;
    if local_index < RADIX {
        atomicStore(&digit_counts[local_index], 0u);
    }
    workgroupBarrier();
    let index = block * BLOCK_SIZE + local_index;
    if index < sort_params.count {
        let digit = (keys_in[index] >> sort_params.shift) & DIGIT_MASK;
        atomicAdd(&digit_counts[digit], 1u);
    }
    workgroupBarrier();
    if local_index < RADIX && block < sort_params.block_count {
        block_histograms[local_index * sort_params.block_count + block] =
            atomicLoad(&digit_counts[local_index]);
    }
}

@compute @workgroup_size(256)
fn scatter(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = workgroup_id.y * workgroup_count.x + workgroup_id.x;
    let index = block * BLOCK_SIZE + local_index;
    let valid = index < sort_params.count;
    var key = 0u;
    var digit = NO_DIGIT;
    if valid {
        key = keys_in[index];
        digit = (key >> sort_params.shift) & DIGIT_MASK;
    }
    block_digits[local_index] = digit;
    workgroupBarrier();
    if !valid {
        return;
    }
    var rank = 0u;
    for (var earlier = 0u; earlier < local_index; earlier++) {
        if block_digits[earlier] == digit {
            rank += 1u;
        }
    }
    let table_index = digit * sort_params.block_count + block;
    var base = 0u;
    if table_index > 0u {
        base = block_histograms[table_index - 1u];
    }
    keys_out[base + rank] = key;
    values_out[base + rank] = values_in[index];
}
