// rasterize_backward, subgroup variant (needs Features::SUBGROUP; see
// rasterize_backward_pixels.wgsl for the thread mapping and the arithmetic). Each subgroup
// walks its tile's list back to front on its own, from the largest last_entry of its pixels
// (later entries affect none of them), without workgroup memory or barriers: per step lane l
// loads entry end - 1 - l (a different splat per lane) and the subgroup processes them in
// list order, each broadcast from its lane with subgroupShuffle. A splat's gradient sums over
// the subgroup's pixels (subgroupAdd, skipped when no pixel of the subgroup sees it) are kept
// by the lane that loaded the splat, which adds them to screen_gradients after the step: one
// atomic add per component per subgroup instead of one per invocation.
// Skipping as in rasterize_subgroup.wgsl: the loop runs only over the loaded splats whose
// visible ellipse reaches the subgroup's band (ellipse_misses_box; a subgroupBallot); exact, a
// skipped splat touched none of these pixels in the forward pass either.
// Invariants: loop bounds and shuffle source lanes are subgroup-uniform; lanes are assumed to
// be numbered 0 .. active - 1; the subgroup size is never assumed.

@compute @workgroup_size(THREADS_PER_TILE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
    @builtin(subgroup_invocation_id) lane: u32,
) {
    let tile_id = workgroup_id.y * params.tiles_x + workgroup_id.x;
    let tile_origin = workgroup_id.xy * TILE_SIZE;
    let row = tile_origin.y + local_index;
    let pixel_y = f32(row);
    // The subgroup's band of pixel centres: its rows, the tile's columns.
    let band_low = vec2<f32>(f32(tile_origin.x), f32(subgroupMin(row)));
    let band_high = vec2<f32>(f32(tile_origin.x + TILE_SIZE - 1u), f32(subgroupMax(row)));
    var group0 = load_group(tile_origin.x, row);
    var group1 = load_group(tile_origin.x + 4u, row);
    var group2 = load_group(tile_origin.x + 8u, row);
    var group3 = load_group(tile_origin.x + 12u, row);
    let start = tile_ranges[tile_id].x;
    let lanes = subgroupAdd(1u);
    var end = subgroupMax(max(max(max_last_entry(group0), max_last_entry(group1)),
                              max(max_last_entry(group2), max_last_entry(group3))));
    while end > 0u {
        let count = min(lanes, end);
        var mine = Splat(vec4<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        var my_gaussian = 0u;
        var reaches_band = false;
        if lane < count {
            my_gaussian = intersection_gaussians[start + end - 1u - lane];
            mine = load_splat(my_gaussian);
            reaches_band = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                               params.min_splat_alpha, band_low, band_high);
        }
        var my_gradient = SplatGradient(vec4<f32>(0.0), vec4<f32>(0.0), vec2<f32>(0.0));
        // Only the loaded splats that reach the subgroup's band, in lane (= list) order.
        var pending = subgroupBallot(reaches_band);
        loop {
            let k = pop_lowest_lane(&pending);
            if k == NO_LANE {
                break;
            }
            let splat = Splat(subgroupShuffle(mine.position, k), subgroupShuffle(mine.conic, k),
                              subgroupShuffle(mine.colour, k));
            let entry = end - 1u - k;
            var partials = zero_partials();
            let ratio_growth = row_ratio_growth(splat.conic);
            let hit0 = accumulate(&group0, pixel_y, splat, ratio_growth, entry, &partials);
            let hit1 = accumulate(&group1, pixel_y, splat, ratio_growth, entry, &partials);
            let hit2 = accumulate(&group2, pixel_y, splat, ratio_growth, entry, &partials);
            let hit3 = accumulate(&group3, pixel_y, splat, ratio_growth, entry, &partials);
            if subgroupAny(hit0 || hit1 || hit2 || hit3) {
                let own = total(partials);
                let summed = SplatGradient(subgroupAdd(own.a), subgroupAdd(own.b), subgroupAdd(own.c));
                if lane == k {
                    my_gradient = summed;
                }
            }
        }
        if lane < count && !is_zero(my_gradient) {
            add_splat_gradient(my_gaussian, my_gradient);
        }
        end -= count;
    }
}
