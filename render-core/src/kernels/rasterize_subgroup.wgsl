// rasterize (forward), subgroup variant (needs Features::SUBGROUP; see rasterize_pixels.wgsl
// for the thread mapping). Each subgroup walks its tile's depth-ordered splat list on its own,
// without workgroup memory or barriers: per step every lane loads a DIFFERENT splat (lane l
// loads entry start + l) and the subgroup composites them in list order, each broadcast from
// its lane with subgroupShuffle. On lavapipe a load costs the same per lane whether the lanes
// share the address or not, so this loads each splat once per subgroup instead of once per
// lane. The subgroup stops once all its pixels have stopped (subgroupAll).
// Skipping: each lane also tests its splat's visible ellipse against the subgroup's band (its
// rows x the tile's columns; ellipse_misses_box, common.wgsl, vectorised over the lanes), and
// the compositing loop runs only over the splats that reach it (a subgroupBallot, walked
// lowest lane first = list order). Exact: a skipped splat would have added exactly nothing to
// the band's pixels. It is a shorter loop
// rather than an `if` because SIMD CPU adapters (lavapipe) run straight-line code masked
// whatever the condition and only save loop trips (see render-core/README.md).
// Two splats per trip of the compositing loop: a SIMD CPU adapter (lavapipe) writes every
// value a loop carries (the pixel state) back through a blend with the execution mask once per
// trip, so two splats per trip halve that traffic (a measurably faster forward pass, see
// docs/benchmarks.md). Without a second splat, a copy of the first with zero opacity stands
// in: it touches no pixel. (The same in the backward pass was slower: its two splats'
// gradient sums do not fit the registers.)
// Invariants: the loop bounds and the shuffle source lane are subgroup-uniform; lanes are
// assumed to be numbered 0 .. active - 1 (active = number of invocations in the subgroup,
// which may be fewer than subgroup_size for a small workgroup); the subgroup size is never
// assumed.

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
    // The subgroup's band of pixel centres: its rows, the tile's columns.
    let band_low = vec2<f32>(f32(tile_origin.x), f32(subgroupMin(row)));
    let band_high = vec2<f32>(f32(tile_origin.x + TILE_SIZE - 1u), f32(subgroupMax(row)));
    var group0 = new_group(tile_origin.x, row);
    var group1 = new_group(tile_origin.x + 4u, row);
    var group2 = new_group(tile_origin.x + 8u, row);
    var group3 = new_group(tile_origin.x + 12u, row);
    for (var start = range.x; start < range.y; start += lanes) {
        if subgroupAll(all(group0.done & group1.done & group2.done & group3.done)) {
            break;
        }
        var mine = Splat(vec4<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
        var reaches_band = false;
        if start + lane < range.y {
            mine = load_splat(intersection_gaussians[start + lane]);
            reaches_band = !ellipse_misses_box(mine.position.xy, mine.position.z, mine.conic,
                                               params.min_splat_alpha, band_low, band_high);
        }
        // Only the loaded splats that reach the subgroup's band, in lane (= list) order.
        var pending = subgroupBallot(reaches_band);
        loop {
            let k = pop_lowest_lane(&pending);
            if k == NO_LANE {
                break;
            }
            // The next splat reaching the band, or the stand-in (zero opacity) when none is left.
            let next = pop_lowest_lane(&pending);
            let has_next = next != NO_LANE;
            let k2 = select(k, next, has_next);
            let splat = Splat(subgroupShuffle(mine.position, k), subgroupShuffle(mine.conic, k),
                              subgroupShuffle(mine.colour, k));
            var splat2 = Splat(subgroupShuffle(mine.position, k2), subgroupShuffle(mine.conic, k2),
                               subgroupShuffle(mine.colour, k2));
            splat2.position.z = select(0.0, splat2.position.z, has_next);
            let entry = start - range.x + k + 1u;
            let entry2 = start - range.x + k2 + 1u;
            let ratio_growth = row_ratio_growth(splat.conic);
            let ratio_growth2 = row_ratio_growth(splat2.conic);
            composite(&group0, pixel_y, splat, ratio_growth, entry);
            composite(&group1, pixel_y, splat, ratio_growth, entry);
            composite(&group2, pixel_y, splat, ratio_growth, entry);
            composite(&group3, pixel_y, splat, ratio_growth, entry);
            composite(&group0, pixel_y, splat2, ratio_growth2, entry2);
            composite(&group1, pixel_y, splat2, ratio_growth2, entry2);
            composite(&group2, pixel_y, splat2, ratio_growth2, entry2);
            composite(&group3, pixel_y, splat2, ratio_growth2, entry2);
        }
    }
    write_group(group0, row);
    write_group(group1, row);
    write_group(group2, row);
    write_group(group3, row);
}
