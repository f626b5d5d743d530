// sort: one pass of a stable least-significant-digit radix sort on u32 keys with u32 values,
// RADIX_BITS = 8 bits per pass, without subgroup operations or workgroup memory. The keys are
// split into blocks of sort_params.block_size consecutive keys; ONE invocation owns one block
// (64 invocations per workgroup, linear id over a 2D grid) and walks it serially, which on CPU
// adapters (lavapipe) is far cheaper than ranking keys across invocations in workgroup memory.
// - `histogram`: invocation b zeroes its column of the digit-major table
//   (table[digit * block_count + b], block_count = sort_params.block_count) and counts its
//   block's digits into it.
// - the launcher turns the table into an exclusive prefix sum (scan.wgsl), so that every
//   (digit, block) holds the first output slot of its keys.
// - `scatter`: invocation b walks its block in order and sends each key (and value) to the
//   next slot of its (digit, b) entry. Keys of equal digit keep their input order (stable).
// A depth sort's first pass (sort_params.depth_first_pass) takes each key's index, its
// Gaussian, as the value (values_in is not read, so project need not write an identity
// permutation) and splits the culled keys off: keys
// equal to CULLED_DEPTH_KEY go to one more bucket, RADIX, after every digit, so the pass
// leaves them behind the others in input order, where the whole sort would leave them too
// (the culled key sorts above every visible one, and the sort is stable). `count_kept`
// (ONE invocation, between the scan and `scatter`) writes the number of the other keys,
// the first slot of bucket RADIX, to kept_count[0], and the later passes sort only those:
// in a large map most Gaussians are culled in any one view.
// The key count is read from the device (sort_count[0], written by an earlier kernel or the
// launcher), so the sort needs no host read-back: the launcher sizes block_count for the
// largest possible count, and blocks past the real count only zero their column.
// Invariants: only keys < count are read or written; every table entry is written by
// `histogram` before the scan; later passes never move the culled keys a split left behind.

@group(0) @binding(0) var<uniform> sort_params: SortParams;
@group(0) @binding(1) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read> values_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> table: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;
// [0]: number of keys to sort.
@group(0) @binding(6) var<storage, read> sort_count: array<u32>;
// [0]: number of keys that are not culled (written by `count_kept`).
@group(0) @binding(7) var<storage, read_write> kept_count: array<u32>;

const RADIX: u32 = 1u << RADIX_BITS;

// Table rows (buckets) of this pass.
fn bucket_count() -> u32 {
    return RADIX + sort_params.depth_first_pass;
}

fn bucket_of(key: u32) -> u32 {
    let digit = (key >> sort_params.shift) & sort_params.digit_mask;
    return select(digit, RADIX, sort_params.depth_first_pass != 0u && key == CULLED_DEPTH_KEY);
}

fn block_index(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>, local_index: u32) -> u32 {
    return linear_workgroup(workgroup_id, workgroup_count) * SERIAL_WORKGROUP_SIZE + local_index;
}

@compute @workgroup_size(SERIAL_WORKGROUP_SIZE)
fn histogram(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = block_index(workgroup_id, workgroup_count, local_index);
    let block_count = sort_params.block_count;
    if block >= block_count {
        return;
    }
    for (var bucket = 0u; bucket < bucket_count(); bucket++) {
        table[bucket * block_count + block] = 0u;
    }
    let first = block * sort_params.block_size;
    let last = min(first + sort_params.block_size, sort_count[0]);
    for (var i = first; i < last; i++) {
        let entry = bucket_of(keys_in[i]) * block_count + block;
        table[entry] += 1u;
    }
}

@compute @workgroup_size(SERIAL_WORKGROUP_SIZE)
fn scatter(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = block_index(workgroup_id, workgroup_count, local_index);
    let block_count = sort_params.block_count;
    if block >= block_count {
        return;
    }
    let first = block * sort_params.block_size;
    let last = min(first + sort_params.block_size, sort_count[0]);
    for (var i = first; i < last; i++) {
        let key = keys_in[i];
        let entry = bucket_of(key) * block_count + block;
        let slot = table[entry];
        table[entry] = slot + 1u;
        keys_out[slot] = key;
        var value = i;
        if sort_params.depth_first_pass == 0u {
            value = values_in[i];
        }
        values_out[slot] = value;
    }
}

@compute @workgroup_size(1)
fn count_kept() {
    kept_count[0] = table[RADIX * sort_params.block_count];
}
