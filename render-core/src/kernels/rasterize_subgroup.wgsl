// rasterize (forward), subgroup variant (needs Features::SUBGROUP; see rasterize_pixels.wgsl
// for the thread mapping). Each subgroup walks its tile's depth-ordered splat list on its own,
// without workgroup memory or barriers: per step every lane loads a DIFFERENT splat (lane l
// loads entry start + l) and the subgroup composites them in list order, each broadcast from
// its lane with subgroupShuffle. On lavapipe a load costs the same per lane whether the lanes
// share the address or not, so this loads each splat once per subgroup instead of once per
// lane. The subgroup stops once all its pixels have stopped (subgroupAll).
// Skipping: the subgroup's band (its rows x the tile's 16 columns) is composited as two
// halves of 8 columns (each invocation's pixel groups 0-1 and 2-3), one loop each. Each lane
// tests its splat's visible ellipse against both halves (ellipse_misses_box, common.wgsl,
// vectorised over the lanes), and each half's loop runs only over the splats that reach it (a
// subgroupBallot, walked lowest lane first = list order). Exact: a skipped splat would have
// added exactly nothing to the half's pixels, and the halves share no pixel, so compositing
// one before the other changes nothing. A splat reaching both is broadcast twice. It is a shorter loop
// rather than an `if` because SIMD CPU adapters (lavapipe) run straight-line code masked
// whatever the condition and only save loop trips (see render-core/README.md).
// Two splats per trip of the compositing loop: a SIMD CPU adapter (lavapipe) writes every
// value a loop carries (the pixel state) back through a blend with the execution mask once per
// trip, so two splats per trip halve that traffic (a measurably faster forward pass, see
// docs/benchmarks.md). Without a second splat, a copy of the first with zero opacity stands
// in: it touches no pixel. (The same in the backward pass was slower: its two splats'
// gradient sums do not fit the registers.)
// Loops: every loop tests at the end of its body. On SIMD CPU adapters a loop tested at the
// top runs its body once more than its trips (render-core/README.md), and with a handful of
// splats per half and batch that extra pass was a large share of the rasterizer's time
// (docs/benchmarks.md). The `if` or `return` in front of a loop does not spare lavapipe the
// empty case: it runs them masked, so an empty ballot still costs the half one masked pass.
// Invariants: the loop bounds and the shuffle source lane are subgroup-uniform; lanes are
// assumed to be numbered 0 .. active - 1 (active = number of invocations in the subgroup,
// which may be fewer than subgroup_size for a small workgroup); the subgroup size is never
// assumed.

// Composites the loaded splats of `ballot` (lanes, walked lowest first = list order; `mine`
// is each lane's splat, `first_entry` the list entry of lane 0's) behind two pixel groups of
// each invocation's row: one half of the band. Two splats per trip (see above).
fn composite_half(half0: ptr<function, PixelGroup>, half1: ptr<function, PixelGroup>,
                  ballot: vec4<u32>, mine: Splat, first_entry: u32, pixel_y: f32) {
    var pending = ballot;
    var k = pop_lowest_lane(&pending);
    if k == NO_LANE {
        return;
    }
    // Tested at the end of the body: see `Loops` above.
    loop {
        // The next splat reaching the half, or the stand-in (zero opacity) when none is left.
        let next = pop_lowest_lane(&pending);
        let has_next = next != NO_LANE;
        let k2 = select(k, next, has_next);
        let splat = Splat(subgroupShuffle(mine.position, k), subgroupShuffle(mine.conic, k),
                          subgroupShuffle(mine.colour, k));
        var splat2 = Splat(subgroupShuffle(mine.position, k2), subgroupShuffle(mine.conic, k2),
                           subgroupShuffle(mine.colour, k2));
        splat2.position.z = select(0.0, splat2.position.z, has_next);
        let entry = first_entry + k;
        let entry2 = first_entry + k2;
        let ratio_growth = row_ratio_growth(splat.conic);
        let ratio_growth2 = row_ratio_growth(splat2.conic);
        composite(half0, pixel_y, splat, ratio_growth, entry);
        composite(half1, pixel_y, splat, ratio_growth, entry);
        composite(half0, pixel_y, splat2, ratio_growth2, entry2);
        composite(half1, pixel_y, splat2, ratio_growth2, entry2);
        k = pop_lowest_lane(&pending);
        if k == NO_LANE {
            break;
        }
    }
}

// Columns of one half of the band: two pixel groups.
const HALF_TILE: u32 = TILE_SIZE / 2u;

@compute @workgroup_size(THREADS_PER_TILE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
    @builtin(subgroup_invocation_id) lane: u32,
) {
    let tile_id = workgroup_id.y * params.tiles_x + workgroup_id.x;
    let tile_origin = workgroup_id.xy * TILE_SIZE;
    let row = tile_origin.y + local_index;
    let range = tile_ranges[tile_id];
    let lanes = subgroupAdd(1u);
    let pixel_y = f32(row);
    // The two halves of the subgroup's band of pixel centres: its rows, the tile's left and
    // right 8 columns.
    let rows = vec2<f32>(f32(subgroupMin(row)), f32(subgroupMax(row)));
    let left_low = vec2<f32>(f32(tile_origin.x), rows.x);
    let left_high = vec2<f32>(f32(tile_origin.x + HALF_TILE - 1u), rows.y);
    let right_low = vec2<f32>(f32(tile_origin.x + HALF_TILE), rows.x);
    let right_high = vec2<f32>(f32(tile_origin.x + TILE_SIZE - 1u), rows.y);
    var group0 = new_group(tile_origin.x, row);
    var group1 = new_group(tile_origin.x + 4u, row);
    var group2 = new_group(tile_origin.x + 8u, row);
    var group3 = new_group(tile_origin.x + 12u, row);
    var start = range.x;
    // Tested at the end of the body, entered under an `if`: see `Loops` above.
    if start < range.y
        && !subgroupAll(all(group0.done & group1.done & group2.done & group3.done)) {
        loop {
            var mine = Splat(vec4<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
            var reaches_left = false;
            var reaches_right = false;
            if start + lane < range.y {
                mine = load_splat(intersection_gaussians[start + lane]);
                let min_alpha = params.min_splat_alpha;
                reaches_left = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                                   min_alpha, left_low, left_high);
                reaches_right = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                                    min_alpha, right_low, right_high);
            }
            // Each half composites only the loaded splats that reach it, in lane (= list) order.
            // The halves share no pixel, so their order relative to each other does not matter.
            let first_entry = start - range.x + 1u;
            composite_half(&group0, &group1, subgroupBallot(reaches_left), mine, first_entry,
                           pixel_y);
            composite_half(&group2, &group3, subgroupBallot(reaches_right), mine, first_entry,
                           pixel_y);
            start += lanes;
            if start >= range.y
                || subgroupAll(all(group0.done & group1.done & group2.done & group3.done)) {
                break;
            }
        }
    }
    write_group(group0, row);
    write_group(group1, row);
    write_group(group2, row);
    write_group(group3, row);
    report_walk(STATUS_RASTERIZE_CUT_SHORT);
}
