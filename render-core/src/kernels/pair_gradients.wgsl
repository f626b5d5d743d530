// pair_gradients: each Gaussian's screen-space gradient as the sum of its tile/Gaussian pairs'
// gradients, added in the pair's depth order (the order bin.wgsl emitted them), so the result
// does not depend on which thread finished first.
// Why: with RenderParams.pair_gradient_sums the backward rasterizer adds a splat's gradient
// into its pair's sum (found from the pair's entry in the tile's list through slot_pairs)
// instead of into the Gaussian's sum. Only the tile's own workgroup touches that sum, and with
// subgroups of at least 8 lanes at most two subgroups (the tile's two bands of 8 rows) add to
// it; float addition is commutative, so two adds onto zero give the same bits in either order.
// What remains is the sum across tiles, done here in a fixed order. Float atomics straight
// into the Gaussian's sum (pair_gradient_sums = 0) add tiles in the order threads arrive: runs
// differ in the last bits, and an optimisation drifts apart from there.
// Thread mapping: one invocation per depth-ordered Gaussian k (WORKGROUP_SIZE per workgroup);
// its pairs are [first, end) with end = sorted_tile_counts[k] (inclusive scan of the tile
// counts) and first the previous Gaussian's end (0 for k = 0), cut at the pair capacity as
// bin.wgsl cut them. Both come from neighbouring scan entries: the only scattered access left
// per Gaussian is its screen_gradients entry.
// The sums are stored in that depth order, so an invocation reads one contiguous run and
// neighbouring invocations neighbouring runs (stored in list order, each pair's sum would be
// a scattered read).
// Invariants: screen_gradients is zero-filled by the launcher; a culled Gaussian (no pair)
// keeps zeros; every kept pair's slot_pairs entry was written by emit_pairs. pair_sums is all
// zeros between backward passes (the launcher keeps it from one pass to the next rather than
// allocating and clearing PAIR_SUM_STRIDE floats per pair of capacity every time): the
// backward rasterizer only adds into sums of kept pairs, and this pass reads each kept pair's
// sum once and zeroes it.

@group(0) @binding(0) var<uniform> bin_params: BinParams;
@group(0) @binding(1) var<storage, read> sorted_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> sorted_tile_counts: array<u32>;
// PAIR_SUM_STRIDE floats (three vec4, the last two padding) per pair in depth order, written
// by the backward rasterizer in the screen_gradients order.
@group(0) @binding(5) var<storage, read_write> pair_sums: array<vec4<f32>>;
// SCREEN_GRADIENT_STRIDE floats per Gaussian, read by project_backward.wgsl.
@group(0) @binding(6) var<storage, read_write> screen_gradients: array<f32>;

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let k = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if k >= bin_params.gaussian_count {
        return;
    }
    var first = 0u;
    if k > 0u {
        first = sorted_tile_counts[k - 1u];
    }
    let end = min(sorted_tile_counts[k], bin_params.pair_capacity);
    if first >= end {
        // No pair (culled), or none kept.
        return;
    }
    let gaussian = sorted_gaussians[k];
    // The SCREEN_GRADIENT_STRIDE (10) components in three vectors: no local array, which
    // CPU adapters would keep in memory.
    var sum_a = vec4<f32>(0.0);
    var sum_b = vec4<f32>(0.0);
    var sum_c = vec4<f32>(0.0);
    let zero = vec4<f32>(0.0);
    for (var pair = first; pair < end; pair++) {
        let base = pair * (PAIR_SUM_STRIDE / 4u);
        sum_a += pair_sums[base];
        sum_b += pair_sums[base + 1u];
        sum_c += pair_sums[base + 2u];
        pair_sums[base] = zero;
        pair_sums[base + 1u] = zero;
        pair_sums[base + 2u] = zero;
    }
    let out = gaussian * SCREEN_GRADIENT_STRIDE;
    for (var c = 0u; c < 4u; c++) {
        screen_gradients[out + c] = sum_a[c];
        screen_gradients[out + 4u + c] = sum_b[c];
    }
    screen_gradients[out + 8u] = sum_c.x;
    screen_gradients[out + 9u] = sum_c.y;
}
