// rasterize_backward, shared part: bindings 6-9 and per-pixel gradient arithmetic of the
// backward rasterizer, between rasterize_tiles.wgsl and rasterize_backward.wgsl or
// rasterize_backward_subgroup.wgsl, which differ in how the splats reach the invocations and
// how the per-splat sums reach binding 10.
// Thread mapping (both variants, as in the forward pass, see rasterize_tiles.wgsl): invocation
// r owns tile row r as 4 PixelGradients groups of 4 pixels. The tile's
// splat list is walked BACK to front; each pixel only considers entries before its recorded
// last_entry, recomputes each splat's alpha exactly as the forward pass did, recovers the
// transmittance in front of it as T_before = T_after / (1 - alpha), and adds dL/d(mean2d,
// conic, opacity, colour, depth) of the splat over its pixels into a SplatPartials; the
// variants sum those over the tile and add them atomically into binding 10 (10 floats per
// Gaussian, or per tile/Gaussian pair: see add_splat_gradient).
// Invariants: the splat order and skip rules are identical to the forward pass; a splat whose
// alpha hit the cap gets no opacity/footprint gradient.
// `add_gradient` and binding 10 (gradient_sums) come from atomics_float.wgsl or
// atomics_cas.wgsl (compare-exchange fallback when float atomics are unavailable), which the
// launcher puts in front of this file.
@group(0) @binding(6) var<storage, read> pixel_transmittance: array<f32>;
@group(0) @binding(7) var<storage, read> pixel_last_entry: array<u32>;
// dL/d(r, g, b, depth) and dL/d(alpha) per pixel
@group(0) @binding(8) var<storage, read> v_rgbd: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read> v_alpha: array<f32>;
// Tile-list slot -> the pair's depth-order index (bin.wgsl), where the per-pair sums live.
@group(0) @binding(11) var<storage, read> slot_pairs: array<u32>;

// Backward state of 4 pixels of one row (vec4 components). Pixels outside the image have
// last_entry 0 and so consider no splat. `behind` is sum_c v_c * (channel c composited behind
// the current splat) - v_alpha * final transmittance, over c in (r, g, b, depth): all the
// pixel's gradient needs of what lies behind, in one vec4 instead of four.
struct PixelGradients {
    x: vec4<f32>,
    last_entry: vec4<u32>,
    transmittance: vec4<f32>,
    v_red: vec4<f32>,
    v_green: vec4<f32>,
    v_blue: vec4<f32>,
    v_depth: vec4<f32>,
    behind: vec4<f32>,
}

fn load_group(first_column: u32, row: u32) -> PixelGradients {
    let width = params.width;
    let columns = vec4<u32>(first_column) + GROUP_COLUMNS;
    var group: PixelGradients;
    group.x = vec4<f32>(columns);
    group.last_entry = vec4<u32>(0u);
    group.transmittance = vec4<f32>(1.0);
    group.v_red = vec4<f32>(0.0);
    group.v_green = vec4<f32>(0.0);
    group.v_blue = vec4<f32>(0.0);
    group.v_depth = vec4<f32>(0.0);
    group.behind = vec4<f32>(0.0);
    for (var k = 0u; k < 4u; k++) {
        if columns[k] < width && row < params.height {
            let pixel_index = row * width + columns[k];
            group.last_entry[k] = pixel_last_entry[pixel_index];
            let transmittance = pixel_transmittance[pixel_index];
            group.transmittance[k] = transmittance;
            let v = v_rgbd[pixel_index];
            group.v_red[k] = v.x;
            group.v_green[k] = v.y;
            group.v_blue[k] = v.z;
            group.v_depth[k] = v.w;
            // alpha = 1 - final transmittance: its gradient enters every splat's alpha
            // derivative like a channel composited behind everything, with value -1.
            group.behind[k] = -v_alpha[pixel_index] * transmittance;
        }
    }
    return group;
}

fn max_last_entry(group: PixelGradients) -> u32 {
    return max(max(group.last_entry.x, group.last_entry.y), max(group.last_entry.z, group.last_entry.w));
}

// dL/d(screen-space parameters) of one splat summed over some pixels, per vec4 component.
struct SplatPartials {
    colour_red: vec4<f32>,
    colour_green: vec4<f32>,
    colour_blue: vec4<f32>,
    depth: vec4<f32>,
    opacity: vec4<f32>,
    conic_a: vec4<f32>,
    conic_b: vec4<f32>,
    conic_c: vec4<f32>,
    mean_x: vec4<f32>,
    mean_y: vec4<f32>,
}

fn zero_partials() -> SplatPartials {
    let z = vec4<f32>(0.0);
    return SplatPartials(z, z, z, z, z, z, z, z, z, z);
}

// The 10 screen gradients of SplatPartials, each summed over its 4 components, in the
// screen_gradients layout: (mean2d x, y, conic a, b), (c, opacity, colour r, g), (b, depth).
struct SplatGradient {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec2<f32>,
}

fn sum4(values: vec4<f32>) -> f32 {
    return (values.x + values.y) + (values.z + values.w);
}

fn total(p: SplatPartials) -> SplatGradient {
    return SplatGradient(
        vec4<f32>(sum4(p.mean_x), sum4(p.mean_y), sum4(p.conic_a), sum4(p.conic_b)),
        vec4<f32>(sum4(p.conic_c), sum4(p.opacity), sum4(p.colour_red), sum4(p.colour_green)),
        vec2<f32>(sum4(p.colour_blue), sum4(p.depth)));
}

fn is_zero(g: SplatGradient) -> bool {
    return all(g.a == vec4<f32>(0.0)) && all(g.b == vec4<f32>(0.0)) && all(g.c == vec2<f32>(0.0));
}

// Adds a splat's gradient over some pixels of list slot `slot` (Gaussian `gaussian`) into
// binding 10: its pair's sums (at the pair's depth-order index, slot_pairs) when
// params.pair_gradient_sums (pair_gradients.wgsl then adds each Gaussian's pairs in a fixed
// order), the Gaussian's sums otherwise.
fn add_splat_gradient(slot: u32, gaussian: u32, g: SplatGradient) {
    var base = gaussian * SCREEN_GRADIENT_STRIDE;
    if params.pair_gradient_sums != 0u {
        base = slot_pairs[slot] * PAIR_SUM_STRIDE;
    }
    add_gradient(base + V_MEAN2D, g.a.x);
    add_gradient(base + V_MEAN2D + 1u, g.a.y);
    add_gradient(base + V_CONIC, g.a.z);
    add_gradient(base + V_CONIC + 1u, g.a.w);
    add_gradient(base + V_CONIC + 2u, g.b.x);
    add_gradient(base + V_OPACITY, g.b.y);
    add_gradient(base + V_COLOUR, g.b.z);
    add_gradient(base + V_COLOUR + 1u, g.b.w);
    add_gradient(base + V_COLOUR + 2u, g.c.x);
    add_gradient(base + V_DEPTH, g.c.y);
}

// Un-composites `splat` (list entry `entry` of the tile, walking back to front) from the
// group's pixels and adds its gradients into `partials`. Returns whether any pixel of the
// group saw the splat.
// `ratio_growth` is row_ratio_growth(splat.conic) (common.wgsl), computed once per splat.
fn accumulate(group: ptr<function, PixelGradients>, pixel_y: f32, splat: Splat,
              ratio_growth: f32, entry: u32, partials: ptr<function, SplatPartials>) -> bool {
    let in_list = vec4<u32>(entry) < (*group).last_entry;
    if !any(in_list) {
        return false;
    }
    let min_alpha = params.min_splat_alpha;
    let max_alpha = params.max_splat_alpha;
    let conic = splat.conic;
    let offset_x = (*group).x - splat.position.x;
    let offset_y = pixel_y - splat.position.y;
    // The forward pass's values (row_gaussian_values), so the same pixels see the splat.
    let gaussian_value = row_gaussian_values(conic, offset_x.x, offset_y, ratio_growth);
    let raw_alpha = splat.position.z * gaussian_value;
    let alpha = min(vec4<f32>(max_alpha), raw_alpha);
    let visible = in_list & gaussian_value <= vec4<f32>(1.0) & alpha >= vec4<f32>(min_alpha);
    if !any(visible) {
        return false;
    }
    let inverse = 1.0 / (1.0 - alpha);
    let transmittance = select((*group).transmittance, (*group).transmittance * inverse, visible);
    (*group).transmittance = transmittance;
    let weight = select(vec4<f32>(0.0), alpha * transmittance, visible);
    let colour = splat.colour;
    let depth = splat.position.w;
    // dL/d(this splat's value) per pixel: sum_c v_c * value_c.
    let v_value = (*group).v_red * colour.x + (*group).v_green * colour.y
        + (*group).v_blue * colour.z + (*group).v_depth * depth;
    // d(output)/d(alpha): own contribution minus the dimming of everything behind.
    let v_splat_alpha = select(vec4<f32>(0.0),
        v_value * transmittance - (*group).behind * inverse, visible);
    (*group).behind += v_value * weight;

    (*partials).colour_red += (*group).v_red * weight;
    (*partials).colour_green += (*group).v_green * weight;
    (*partials).colour_blue += (*group).v_blue * weight;
    (*partials).depth += (*group).v_depth * weight;
    // Pixels where alpha hit the cap pass no gradient to opacity and footprint.
    let unclamped = visible & raw_alpha <= vec4<f32>(max_alpha);
    let v_power = select(vec4<f32>(0.0), v_splat_alpha * alpha, unclamped);
    (*partials).opacity += select(vec4<f32>(0.0), v_splat_alpha * gaussian_value, unclamped);
    (*partials).conic_a += v_power * -0.5 * offset_x * offset_x;
    (*partials).conic_b += v_power * -offset_x * offset_y;
    (*partials).conic_c += v_power * -0.5 * offset_y * offset_y;
    (*partials).mean_x += v_power * (conic.x * offset_x + conic.y * offset_y);
    (*partials).mean_y += v_power * (conic.y * offset_x + conic.z * offset_y);
    return true;
}
