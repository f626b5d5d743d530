// bin: turns depth-sorted Gaussians into per-tile lists. One invocation per element (256 per
// workgroup, linear workgroup id over a 2D grid).
// - `gather_counts`: sorted_tile_counts[k] = tile_counts[sorted_gaussians[k]] (scanned next).
// - `emit`: the k-th nearest Gaussian writes one (tile id, Gaussian index) pair per tile of its
//   rectangle, at the offset given by the inclusive scan; pairs therefore come out in depth
//   order, and the stable sort by tile id that follows keeps that order within each tile.
// - `pair_status`: ONE invocation; pair_status = [pairs kept, pairs needed]: the needed count
//   is the last inclusive-scan entry, the kept count is capped at the buffers' capacity. The
//   sort and `tile_ranges` read the kept count on the device (no host read-back).
// - `emit`: pairs at offsets >= capacity are dropped. Since pairs are emitted in depth order,
//   an overflowing frame loses only the pairs of its farthest Gaussians.
// - `tile_ranges`: for the tile-sorted pairs, records [start, end) of each tile's run. Tiles
//   without pairs keep the [0, 0) the launcher cleared them to.

struct BinParams {
    gaussian_count: u32,
    pair_capacity: u32,
    tiles_x: u32,
    padding: u32,
}

@group(0) @binding(0) var<uniform> bin_params: BinParams;
@group(0) @binding(1) var<storage, read> sorted_gaussians: array<u32>;
@group(0) @binding(2) var<storage, read> tile_counts: array<u32>;
@group(0) @binding(3) var<storage, read_write> sorted_tile_counts: array<u32>;
@group(0) @binding(4) var<storage, read> tile_rects: array<vec4<u32>>;
@group(0) @binding(5) var<storage, read_write> intersection_tiles: array<u32>;
@group(0) @binding(6) var<storage, read_write> intersection_gaussians: array<u32>;
@group(0) @binding(7) var<storage, read> sorted_tiles: array<u32>;
@group(0) @binding(8) var<storage, read_write> tile_ranges: array<vec2<u32>>;
// [pairs kept, pairs needed]
@group(0) @binding(9) var<storage, read_write> pair_status: array<u32>;

@compute @workgroup_size(1)
fn pair_status_from_scan() {
    var needed = 0u;
    if bin_params.gaussian_count > 0u {
        needed = sorted_tile_counts[bin_params.gaussian_count - 1u];
    }
    pair_status[0] = min(needed, bin_params.pair_capacity);
    pair_status[1] = needed;
}

fn element_index(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>, local_index: u32) -> u32 {
    return (workgroup_id.y * workgroup_count.x + workgroup_id.x) * 256u + local_index;
}

@compute @workgroup_size(256)
fn gather_counts(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let k = element_index(workgroup_id, workgroup_count, local_index);
    if k < bin_params.gaussian_count {
        sorted_tile_counts[k] = tile_counts[sorted_gaussians[k]];
    }
}

@compute @workgroup_size(256)
fn emit(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let k = element_index(workgroup_id, workgroup_count, local_index);
    if k >= bin_params.gaussian_count {
        return;
    }
    let gaussian = sorted_gaussians[k];
    let count = tile_counts[gaussian];
    if count == 0u {
        return;
    }
    // The inclusive scan holds the end of this Gaussian's range.
    var cursor = sorted_tile_counts[k] - count;
    let rect = tile_rects[gaussian];
    for (var tile_y = rect.y; tile_y <= rect.w; tile_y++) {
        for (var tile_x = rect.x; tile_x <= rect.z; tile_x++) {
            if cursor >= bin_params.pair_capacity {
                return;
            }
            intersection_tiles[cursor] = tile_y * bin_params.tiles_x + tile_x;
            intersection_gaussians[cursor] = gaussian;
            cursor += 1u;
        }
    }
}

@compute @workgroup_size(256)
fn tile_ranges_from_sorted(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let i = element_index(workgroup_id, workgroup_count, local_index);
    let n = pair_status[0];
    if i >= n {
        return;
    }
    let tile = sorted_tiles[i];
    if i == 0u || sorted_tiles[i - 1u] != tile {
        tile_ranges[tile].x = i;
    }
    if i + 1u == n || sorted_tiles[i + 1u] != tile {
        tile_ranges[tile].y = i + 1u;
    }
}
