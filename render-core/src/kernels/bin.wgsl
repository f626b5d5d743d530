// bin: turns depth-sorted Gaussians into per-tile lists, front to back within each tile,
// without sorting the tile/Gaussian pairs. The depth-sorted Gaussians are split into blocks
// of bin_params.block_size; the table holds one counter per (tile, block), tile-major
// (table[tile * block_count + block]).
// - `gather_counts` (one invocation per element, WORKGROUP_SIZE per workgroup):
//   sorted_tile_counts[k] = tile_counts[sorted_gaussians[k]] (inclusive-scanned next, which
//   gives every Gaussian the depth-order index of its first pair).
// - `pair_status_from_scan` (ONE invocation): frame_status' pair counts (kept, needed); the
//   needed count is the last scan entry, the kept count is capped at the capacity.
// - `count_pairs` (one invocation per block, BIN_WORKGROUP_SIZE per workgroup, walking its
//   block serially):
//   adds 1 to (tile, block) for every kept pair of the block's Gaussians: the tiles of the
//   Gaussian's rectangle (tile_rects: first tile, columns | rows << 16, and for rectangles
//   of up to 32 tiles a row-major mask of the tiles the splat reaches, see project.wgsl).
//   A pair is kept iff its depth-order index is below the capacity, so an overflowing frame
//   keeps exactly its first `capacity` pairs in depth order (it loses the pairs of its
//   farthest Gaussians). It sets frame_status' STATUS_BINNING_CUT_SHORT when it binned fewer
//   pairs than the scan counts for its block: the adapter's loop limit cut its walk short
//   (see walk_block).
// - the launcher exclusive-scans the table: (tile, block) then holds the first list slot of
//   the block's pairs in that tile, and tiles' lists are contiguous in tile order.
// - `emit_pairs` (same walk): writes each kept pair's Gaussian at the next slot of its
//   (tile, block) entry, so each tile's list is in depth order (blocks in order, Gaussians in
//   order within a block), and the pair's depth-order index at its slot in slot_pairs (a
//   Gaussian's pairs are contiguous in depth order: the backward rasterizer adds each slot's
//   gradient into the sum at that index, where pair_gradients.wgsl reads a Gaussian's sums as
//   one run). Afterwards (tile, last block) holds the end of the tile's list.
// - `tile_ranges_from_table` (one invocation per tile, WORKGROUP_SIZE per workgroup):
//   [start, end) of each tile's list: end from (tile, last block), start from the previous tile's end (0 first).
// On CPU adapters (lavapipe) one serial walk per block costs a few memory accesses per pair,
// where a radix sort of the pairs costs dozens.
// Invariants: only this block's invocation touches a (tile, block) entry (no atomics); the
// table is zeroed by the launcher before `count_pairs`.

@group(0) @binding(0) var<uniform> bin_params: BinParams;
@group(0) @binding(1) var<storage, read> sorted_gaussians: array<u32>;
@group(0) @binding(2) var<storage, read> tile_counts: array<u32>;
@group(0) @binding(3) var<storage, read_write> sorted_tile_counts: array<u32>;
@group(0) @binding(4) var<storage, read> tile_rects: array<vec4<u32>>;
@group(0) @binding(5) var<storage, read_write> table: array<u32>;
@group(0) @binding(6) var<storage, read_write> intersection_gaussians: array<u32>;
// Tile-list slot -> the pair's depth-order index.
@group(0) @binding(7) var<storage, read_write> slot_pairs: array<u32>;
@group(0) @binding(8) var<storage, read_write> tile_ranges: array<vec2<u32>>;
// FRAME_STATUS_WORDS words, indexed by the STATUS_* constants (the rasterizers set their own).
@group(0) @binding(9) var<storage, read_write> frame_status: array<u32>;

@compute @workgroup_size(1)
fn pair_status_from_scan() {
    var needed = 0u;
    if bin_params.gaussian_count > 0u {
        needed = sorted_tile_counts[bin_params.gaussian_count - 1u];
    }
    frame_status[STATUS_PAIRS_KEPT] = min(needed, bin_params.pair_capacity);
    frame_status[STATUS_PAIRS_NEEDED] = needed;
}

fn linear_index(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>, local_index: u32,
                workgroup_size: u32) -> u32 {
    return linear_workgroup(workgroup_id, workgroup_count) * workgroup_size + local_index;
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn gather_counts(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let k = linear_index(workgroup_id, workgroup_count, local_index, WORKGROUP_SIZE);
    if k < bin_params.gaussian_count {
        sorted_tile_counts[k] = tile_counts[sorted_gaussians[k]];
    }
}

// Walks the kept pairs of block `block` in depth order; `emit` selects the pass.
fn walk_block(block: u32, emit: bool) {
    let block_count = bin_params.block_count;
    let first = block * bin_params.block_size;
    let last = min(first + bin_params.block_size, bin_params.gaussian_count);
    // Pairs binned so far, checked against the scan at the end.
    var walked = 0u;
    for (var k = first; k < last; k++) {
        let gaussian = sorted_gaussians[k];
        let count = tile_counts[gaussian];
        if count == 0u {
            // Only culled Gaussians bin no tile, and their depth key sorts them behind every
            // visible one (project.wgsl): the rest of the block is culled too.
            break;
        }
        // The inclusive scan holds the end of this Gaussian's pairs in depth order.
        let first_pair = sorted_tile_counts[k] - count;
        if first_pair >= bin_params.pair_capacity {
            // Every later Gaussian of the block starts even later: nothing more is kept.
            break;
        }
        let kept = min(count, bin_params.pair_capacity - first_pair);
        let rect = tile_rects[gaussian];
        let columns = rect.z & 0xffffu;
        let area = columns * (rect.z >> 16u);
        let masked = area <= MAX_MASKED_TILES;
        var binned = 0u;
        // One trip per binned tile: a masked rectangle's i walks the set bits of its mask,
        // a larger one every tile. (Walking every tile of a masked rectangle too cost a trip
        // per tile it does not reach, and the lanes wait for the one with the most trips.)
        var pending = select(ALL_TILES, rect.w, masked);
        var i = firstTrailingBit(pending);
        let first_tile = rect.y * bin_params.tiles_x + rect.x;
        let inverse_columns = 1.0 / f32(columns);
        while i < area && binned < kept {
            // Row and column of tile i of the rectangle. The row comes from a float product
            // (SIMD CPU adapters divide integers lane by lane, at dozens of cycles each),
            // corrected by one if rounding put it off.
            var row = u32((f32(i) + 0.5) * inverse_columns);
            row = select(row, row - 1u, row * columns > i);
            row = select(row, row + 1u, (row + 1u) * columns <= i);
            let tile = first_tile + row * bin_params.tiles_x + (i - row * columns);
            pending &= pending - 1u;
            i = select(i + 1u, select(firstTrailingBit(pending), area, pending == 0u), masked);
            let entry = tile * block_count + block;
            let slot = table[entry];
            table[entry] = slot + 1u;
            if emit {
                intersection_gaussians[slot] = gaussian;
                slot_pairs[slot] = first_pair + binned;
            }
            binned += 1u;
        }
        walked += binned;
    }
    if !emit {
        // lavapipe ends every loop of an invocation once they have made 65535 trips in all
        // (render-core/README.md): a walk cut short bins fewer pairs than the scan counts for
        // the block. Flag it; check_pairs then makes later frames' blocks small enough.
        var before = 0u;
        if first > 0u {
            before = sorted_tile_counts[first - 1u];
        }
        let capacity = bin_params.pair_capacity;
        let expected = min(sorted_tile_counts[last - 1u], capacity) - min(before, capacity);
        if last > first && walked != expected {
            frame_status[STATUS_BINNING_CUT_SHORT] = 1u;
        }
    }
}

@compute @workgroup_size(BIN_WORKGROUP_SIZE)
fn count_pairs(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = linear_index(workgroup_id, workgroup_count, local_index, BIN_WORKGROUP_SIZE);
    if block < bin_params.block_count {
        walk_block(block, false);
    }
}

@compute @workgroup_size(BIN_WORKGROUP_SIZE)
fn emit_pairs(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let block = linear_index(workgroup_id, workgroup_count, local_index, BIN_WORKGROUP_SIZE);
    if block < bin_params.block_count {
        walk_block(block, true);
    }
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn tile_ranges_from_table(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let tile = linear_index(workgroup_id, workgroup_count, local_index, WORKGROUP_SIZE);
    if tile >= bin_params.tile_count {
        return;
    }
    let last_block = bin_params.block_count - 1u;
    var start = 0u;
    if tile > 0u {
        start = table[(tile - 1u) * bin_params.block_count + last_block];
    }
    tile_ranges[tile] = vec2<u32>(start, table[tile * bin_params.block_count + last_block]);
}
