// sort: one pass of a stable least-significant-digit radix sort on u32 keys with u32 values,
// RADIX_BITS bits per pass. Needs no subgroup operations. Three entry points per pass:
// - `histogram`: one workgroup per block of BLOCK_SIZE keys (linear workgroup id over a 2D
//   grid), THREADS invocations, counts the block's digits with workgroup atomics (counts do
//   not depend on atomic order) into block_histograms, laid out digit-major
//   ([digit * block_count + block]).
// - `scan_histograms`: ONE workgroup; exclusive prefix sum of the whole digit-major table, so
//   every (digit, block) gets the first output slot of its keys. Each invocation scans a
//   contiguous chunk serially; the chunk totals are scanned in workgroup memory.
// - `scatter`: one workgroup per block; invocation t owns the KEYS_PER_THREAD consecutive keys
//   t * KEYS_PER_THREAD ..; the per-(digit, invocation) counts, stored digit-major in
//   workgroup memory and exclusive-scanned as one flat array, give every key its rank among
//   the block's keys in (digit, input position) order. Equal digits therefore keep their input
//   order (stability); the output slot is the table offset of (digit, block) plus the rank
//   within the digit.
// The key count is read from the device (sort_count[0], written by an earlier kernel or the
// launcher), so the sort needs no host read-back: the launcher dispatches enough blocks for
// the largest possible count (the buffers' capacity) and blocks past the real count exit at
// once (a workgroup-uniform test, before any barrier).
// Invariants: only indices < count are read or written; block_count = ceil(count / BLOCK_SIZE)
// in every kernel, so the table layout agrees between them; barriers are in uniform control
// flow.

struct SortParams {
    shift: u32,
    // RADIX - 1, or fewer bits on a last pass that covers the remaining key bits only.
    digit_mask: u32,
    padding0: u32,
    padding1: u32,
}

@group(0) @binding(0) var<uniform> sort_params: SortParams;
@group(0) @binding(1) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read> values_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> block_histograms: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;
// [0]: number of keys to sort.
@group(0) @binding(6) var<storage, read> sort_count: array<u32>;

const THREADS: u32 = 128u;
const KEYS_PER_THREAD: u32 = 8u;
const BLOCK_SIZE: u32 = THREADS * KEYS_PER_THREAD;
const RADIX_BITS: u32 = 4u;
const RADIX: u32 = 1u << RADIX_BITS;
// Entries of the per-(digit, invocation) count matrix each invocation scans serially.
const MATRIX_ENTRIES_PER_THREAD: u32 = RADIX;

var<workgroup> digit_counts: array<atomic<u32>, RADIX>;
// [digit * THREADS + thread]: counts, then their flat exclusive prefix sums.
var<workgroup> thread_digit_offsets: array<u32, RADIX * THREADS>;
var<workgroup> chunk_sums: array<u32, THREADS>;
var<workgroup> block_digit_start: array<u32, RADIX>;

fn block_index(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>) -> u32 {
    return workgroup_id.y * workgroup_count.x + workgroup_id.x;
}

fn block_count_of(count: u32) -> u32 {
    return (count + BLOCK_SIZE - 1u) / BLOCK_SIZE;
}

// Inclusive Hillis-Steele scan of chunk_sums (THREADS entries) in workgroup memory.
fn scan_chunk_sums(local_index: u32) {
    for (var offset = 1u; offset < THREADS; offset = offset * 2u) {
        var addend = 0u;
        if local_index >= offset {
            addend = chunk_sums[local_index - offset];
        }
        workgroupBarrier();
        chunk_sums[local_index] += addend;
        workgroupBarrier();
    }
}

@compute @workgroup_size(THREADS)
fn histogram(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = block_index(workgroup_id, workgroup_count);
    let count = sort_count[0];
    let block_count = block_count_of(count);
    if block >= block_count {
        return;
    }
    if local_index < RADIX {
        atomicStore(&digit_counts[local_index], 0u);
    }
    workgroupBarrier();
    for (var i = 0u; i < KEYS_PER_THREAD; i++) {
        let index = block * BLOCK_SIZE + i * THREADS + local_index;
        if index < count {
            let digit = (keys_in[index] >> sort_params.shift) & sort_params.digit_mask;
            atomicAdd(&digit_counts[digit], 1u);
        }
    }
    workgroupBarrier();
    if local_index < RADIX {
        block_histograms[local_index * block_count + block] =
            atomicLoad(&digit_counts[local_index]);
    }
}

@compute @workgroup_size(THREADS)
fn scan_histograms(@builtin(local_invocation_index) local_index: u32) {
    let table_size = RADIX * block_count_of(sort_count[0]);
    let chunk = (table_size + THREADS - 1u) / THREADS;
    let first = local_index * chunk;
    let last = min(first + chunk, table_size);
    var total = 0u;
    for (var i = first; i < last; i++) {
        total += block_histograms[i];
    }
    chunk_sums[local_index] = total;
    workgroupBarrier();
    scan_chunk_sums(local_index);
    var running = chunk_sums[local_index] - total;
    for (var i = first; i < last; i++) {
        let value = block_histograms[i];
        block_histograms[i] = running;
        running += value;
    }
}

@compute @workgroup_size(THREADS)
fn scatter(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = block_index(workgroup_id, workgroup_count);
    let count = sort_count[0];
    let block_count = block_count_of(count);
    if block >= block_count {
        return;
    }
    let first_key = block * BLOCK_SIZE + local_index * KEYS_PER_THREAD;
    for (var digit = 0u; digit < RADIX; digit++) {
        thread_digit_offsets[digit * THREADS + local_index] = 0u;
    }
    // Each invocation touches only its own column of the matrix here: no races.
    for (var i = 0u; i < KEYS_PER_THREAD; i++) {
        let index = first_key + i;
        if index < count {
            let digit = (keys_in[index] >> sort_params.shift) & sort_params.digit_mask;
            thread_digit_offsets[digit * THREADS + local_index] += 1u;
        }
    }
    workgroupBarrier();
    // Flat exclusive scan of the digit-major matrix: chunk of this invocation first.
    let chunk_first = local_index * MATRIX_ENTRIES_PER_THREAD;
    var total = 0u;
    for (var i = 0u; i < MATRIX_ENTRIES_PER_THREAD; i++) {
        total += thread_digit_offsets[chunk_first + i];
    }
    chunk_sums[local_index] = total;
    workgroupBarrier();
    scan_chunk_sums(local_index);
    var running = chunk_sums[local_index] - total;
    for (var i = 0u; i < MATRIX_ENTRIES_PER_THREAD; i++) {
        let value = thread_digit_offsets[chunk_first + i];
        thread_digit_offsets[chunk_first + i] = running;
        running += value;
    }
    workgroupBarrier();
    if local_index < RADIX {
        block_digit_start[local_index] = thread_digit_offsets[local_index * THREADS];
    }
    workgroupBarrier();
    for (var i = 0u; i < KEYS_PER_THREAD; i++) {
        let index = first_key + i;
        if index < count {
            let key = keys_in[index];
            let digit = (key >> sort_params.shift) & sort_params.digit_mask;
            let slot = digit * THREADS + local_index;
            let rank_in_block = thread_digit_offsets[slot];
            thread_digit_offsets[slot] = rank_in_block + 1u;
            let destination = block_histograms[digit * block_count + block]
                + rank_in_block - block_digit_start[digit];
            keys_out[destination] = key;
            values_out[destination] = values_in[index];
        }
    }
}
