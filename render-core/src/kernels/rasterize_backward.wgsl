// rasterize_backward, workgroup-memory variant (no subgroup operations; see
// rasterize_backward_pixels.wgsl for the thread mapping and the arithmetic). The workgroup
// walks its tile's list back to front in batches of BATCH_SIZE splats loaded into workgroup
// memory (LOADS_PER_THREAD per invocation), starting at the largest last_entry of the tile's
// pixels (later entries affect no pixel). Each invocation sums a splat's gradients over its
// 16 pixels and adds them to binding 10 with one atomic add per component.
// Invariants: barriers in uniform control flow (bounds from workgroupUniformLoad).

const BATCH_SIZE: u32 = 64u;
const LOADS_PER_THREAD: u32 = BATCH_SIZE / THREADS_PER_TILE;

var<workgroup> batch_gaussian: array<u32, BATCH_SIZE>;
var<workgroup> batch_position: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_conic: array<vec3<f32>, BATCH_SIZE>;
var<workgroup> batch_colour: array<vec3<f32>, BATCH_SIZE>;
var<workgroup> tile_start: u32;
var<workgroup> tile_entries: atomic<u32>;

@compute @workgroup_size(THREADS_PER_TILE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let tile_id = workgroup_id.y * params.tiles_x + workgroup_id.x;
    let tile_origin = workgroup_id.xy * TILE_SIZE;
    let row = tile_origin.y + local_index;
    let pixel_y = f32(row);
    var group0 = load_group(tile_origin.x, row);
    var group1 = load_group(tile_origin.x + 4u, row);
    var group2 = load_group(tile_origin.x + 8u, row);
    var group3 = load_group(tile_origin.x + 12u, row);
    if local_index == 0u {
        tile_start = tile_ranges[tile_id].x;
        atomicStore(&tile_entries, 0u);
    }
    workgroupBarrier();
    atomicMax(&tile_entries, max(max(max_last_entry(group0), max_last_entry(group1)),
                                 max(max_last_entry(group2), max_last_entry(group3))));
    // Entries at or past the largest last_entry of the tile affect none of its pixels.
    let list_length = workgroupUniformLoad(&tile_entries);
    let start = workgroupUniformLoad(&tile_start);
    let batch_count = (list_length + BATCH_SIZE - 1u) / BATCH_SIZE;

    for (var batch = 0u; batch < batch_count; batch++) {
        // Slot j of batch b is list entry list_length - 1 - (b * BATCH_SIZE + j).
        let first_reversed = batch * BATCH_SIZE;
        for (var k = 0u; k < LOADS_PER_THREAD; k++) {
            let slot = k * THREADS_PER_TILE + local_index;
            let reversed_index = first_reversed + slot;
            if reversed_index < list_length {
                let gaussian = intersection_gaussians[start + list_length - 1u - reversed_index];
                let splat = load_splat(gaussian);
                batch_gaussian[slot] = gaussian;
                batch_position[slot] = splat.position;
                batch_conic[slot] = splat.conic;
                batch_colour[slot] = splat.colour;
            }
        }
        workgroupBarrier();
        let batch_length = min(BATCH_SIZE, list_length - first_reversed);
        for (var j = 0u; j < batch_length; j++) {
            let entry = list_length - 1u - (first_reversed + j);
            let splat = Splat(batch_position[j], batch_conic[j], batch_colour[j]);
            var partials = zero_partials();
            let ratio_growth = row_ratio_growth(splat.conic);
            let hit0 = accumulate(&group0, pixel_y, splat, ratio_growth, entry, &partials);
            let hit1 = accumulate(&group1, pixel_y, splat, ratio_growth, entry, &partials);
            let hit2 = accumulate(&group2, pixel_y, splat, ratio_growth, entry, &partials);
            let hit3 = accumulate(&group3, pixel_y, splat, ratio_growth, entry, &partials);
            if hit0 || hit1 || hit2 || hit3 {
                add_splat_gradient(start + entry, batch_gaussian[j], total(partials));
            }
        }
        workgroupBarrier();
    }
    report_walk(STATUS_RASTERIZE_BACKWARD_CUT_SHORT);
}
