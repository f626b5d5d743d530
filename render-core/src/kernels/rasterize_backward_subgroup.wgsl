// rasterize_backward, subgroup variant (needs Features::SUBGROUP; see
// rasterize_backward_pixels.wgsl for the thread mapping and the arithmetic). Each subgroup
// walks its tile's list back to front on its own, from the largest last_entry of its pixels
// (later entries affect none of them), without workgroup memory or barriers: per step lane l
// loads entry end - 1 - l (a different splat per lane) and the subgroup processes them in
// list order, each broadcast from its lane with subgroupShuffle. A splat's gradient sums over
// the subgroup's pixels (subgroup_sum, skipped when no pixel of the subgroup sees it) are kept
// by the lane that loaded the splat, which adds them to binding 10 after the step: one
// atomic add per component per subgroup instead of one per invocation.
// Skipping as in rasterize_subgroup.wgsl: the band is processed as two halves of 8 columns,
// each looping only over the loaded splats whose visible ellipse reaches it
// (ellipse_misses_box; a subgroupBallot); exact, a skipped splat touched none of the half's
// pixels in the forward pass either. A splat reaching both halves is summed over each half
// separately (two subgroup sums) and its lane adds both before the atomic add.
// Loops test at the end of the body, as in rasterize_subgroup.wgsl (`Loops`).
// Invariants: loop bounds and the splat shuffles' source lanes are subgroup-uniform; lanes are
// assumed to be numbered 0 .. active - 1; the subgroup size is never assumed.

// Columns of one half of the band: two pixel groups.
const HALF_TILE: u32 = TILE_SIZE / 2u;

fn add_gradients(a: SplatGradient, b: SplatGradient) -> SplatGradient {
    return SplatGradient(a.a + b.a, a.b + b.b, a.c + b.c);
}

// The sum of `own` over the subgroup's `lanes` active lanes, in every lane: a tree of
// subgroupShuffleDown steps into lane 0 (after the step of offset o, lane l holds the sum of
// lanes l .. l + 2o - 1 that exist, so any number of lanes works), then lane 0's sum
// broadcast. Not subgroupAdd: lavapipe turns each subgroupAdd into a loop over the lanes with
// a branch per lane, one loop per component, which cost more (docs/benchmarks.md). The order
// of the additions is fixed, so the sum is repeatable.
fn subgroup_sum(own: SplatGradient, lane: u32, lanes: u32) -> SplatGradient {
    var sum = own;
    var offset = 1u;
    if lanes > 1u {
        loop {
            let inside = lane + offset < lanes;
            sum.a += select(vec4<f32>(0.0), subgroupShuffleDown(sum.a, offset), inside);
            sum.b += select(vec4<f32>(0.0), subgroupShuffleDown(sum.b, offset), inside);
            sum.c += select(vec2<f32>(0.0), subgroupShuffleDown(sum.c, offset), inside);
            offset *= 2u;
            if offset >= lanes {
                break;
            }
        }
    }
    return SplatGradient(subgroupBroadcast(sum.a, 0u), subgroupBroadcast(sum.b, 0u),
                         subgroupBroadcast(sum.c, 0u));
}

// Un-composites the loaded splats of `ballot` (lanes, walked lowest first = list order back
// to front; `mine` is each lane's splat, `last_entry` the list entry of lane 0's) from two
// pixel groups of each invocation's row (one half of the band), and adds each splat's
// gradient summed over the subgroup's pixels of the half to `my_gradient` of the lane that
// loaded it.
fn accumulate_half(half0: ptr<function, PixelGradients>, half1: ptr<function, PixelGradients>,
                   ballot: vec4<u32>, mine: Splat, last_entry: u32, pixel_y: f32, lane: u32,
                   lanes: u32, my_gradient: ptr<function, SplatGradient>) {
    var pending = ballot;
    var k = pop_lowest_lane(&pending);
    if k == NO_LANE {
        return;
    }
    loop {
        let splat = Splat(subgroupShuffle(mine.position, k), subgroupShuffle(mine.conic, k),
                          subgroupShuffle(mine.colour, k));
        let entry = last_entry - k;
        var partials = zero_partials();
        let ratio_growth = row_ratio_growth(splat.conic);
        let hit0 = accumulate(half0, pixel_y, splat, ratio_growth, entry, &partials);
        let hit1 = accumulate(half1, pixel_y, splat, ratio_growth, entry, &partials);
        if subgroupAny(hit0 || hit1) {
            let summed = subgroup_sum(total(partials), lane, lanes);
            if lane == k {
                *my_gradient = add_gradients(*my_gradient, summed);
            }
        }
        k = pop_lowest_lane(&pending);
        if k == NO_LANE {
            break;
        }
    }
}

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
    // The two halves of the subgroup's band of pixel centres: its rows, the tile's left and
    // right 8 columns.
    let rows = vec2<f32>(f32(subgroupMin(row)), f32(subgroupMax(row)));
    let left_low = vec2<f32>(f32(tile_origin.x), rows.x);
    let left_high = vec2<f32>(f32(tile_origin.x + HALF_TILE - 1u), rows.y);
    let right_low = vec2<f32>(f32(tile_origin.x + HALF_TILE), rows.x);
    let right_high = vec2<f32>(f32(tile_origin.x + TILE_SIZE - 1u), rows.y);
    var group0 = load_group(tile_origin.x, row);
    var group1 = load_group(tile_origin.x + 4u, row);
    var group2 = load_group(tile_origin.x + 8u, row);
    var group3 = load_group(tile_origin.x + 12u, row);
    let start = tile_ranges[tile_id].x;
    let lanes = subgroupAdd(1u);
    var end = subgroupMax(max(max(max_last_entry(group0), max_last_entry(group1)),
                              max(max_last_entry(group2), max_last_entry(group3))));
    if end == 0u {
        return;
    }
    loop {
        let count = min(lanes, end);
        var mine = Splat(vec4<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        var my_gaussian = 0u;
        var reaches_left = false;
        var reaches_right = false;
        if lane < count {
            my_gaussian = intersection_gaussians[start + end - 1u - lane];
            mine = load_splat(my_gaussian);
            let min_alpha = params.min_splat_alpha;
            reaches_left = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                               min_alpha, left_low, left_high);
            reaches_right = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                                min_alpha, right_low, right_high);
        }
        var my_gradient = SplatGradient(vec4<f32>(0.0), vec4<f32>(0.0), vec2<f32>(0.0));
        // Each half un-composites only the loaded splats that reach it, in lane (= list) order;
        // the halves share no pixel.
        accumulate_half(&group0, &group1, subgroupBallot(reaches_left), mine, end - 1u, pixel_y,
                        lane, lanes, &my_gradient);
        accumulate_half(&group2, &group3, subgroupBallot(reaches_right), mine, end - 1u, pixel_y,
                        lane, lanes, &my_gradient);
        if lane < count && !is_zero(my_gradient) {
            add_splat_gradient(start + end - 1u - lane, my_gaussian, my_gradient);
        }
        end -= count;
        if end == 0u {
            break;
        }
    }
    report_walk(STATUS_RASTERIZE_BACKWARD_CUT_SHORT);
}
