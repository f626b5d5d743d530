// rasterize, shared part: output bindings and the per-pixel compositing of the forward
// rasterizer, between rasterize_tiles.wgsl and rasterize.wgsl or rasterize_subgroup.wgsl,
// which differ only in how the splats of a tile reach the invocations.
// Thread mapping (both variants, see rasterize_tiles.wgsl): invocation r shades tile row r,
// 16 pixels held as 4 PixelGroups of 4 pixels. On CPU adapters (lavapipe) every
// load inside a loop is a per-lane scalar gather costing as much as dozens of arithmetic
// operations, paid per invocation: 16 pixels per invocation pay one splat load for 16 pixels.
// Per (pixel, splat) the arithmetic is that of the CPU reference in the same order (a skipped
// splat adds exactly 0), so both variants give bit-identical images.

// r, g, b, depth (alpha-composited, not normalised)
@group(0) @binding(6) var<storage, read_write> out_rgbd: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> out_alpha: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_transmittance: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_last_entry: array<u32>;

// Compositing state of 4 pixels of one row.
struct PixelGroup {
    columns: vec4<u32>,
    x: vec4<f32>,
    done: vec4<bool>,
    transmittance: vec4<f32>,
    red: vec4<f32>,
    green: vec4<f32>,
    blue: vec4<f32>,
    depth: vec4<f32>,
    last_entry: vec4<u32>,
}

fn new_group(first_column: u32, row: u32) -> PixelGroup {
    let columns = vec4<u32>(first_column) + GROUP_COLUMNS;
    var group: PixelGroup;
    group.columns = columns;
    group.x = vec4<f32>(columns);
    group.done = columns >= vec4<u32>(params.width) | vec4<bool>(row >= params.height);
    group.transmittance = vec4<f32>(1.0);
    group.red = vec4<f32>(0.0);
    group.green = vec4<f32>(0.0);
    group.blue = vec4<f32>(0.0);
    group.depth = vec4<f32>(0.0);
    group.last_entry = vec4<u32>(0u);
    return group;
}

// Composites `splat`, list entry `entry - 1` of the tile, behind the group's pixels. A pixel
// stops when the splat would bring its transmittance below the floor (early termination).
// `ratio_growth` is row_ratio_growth(splat.conic) (common.wgsl), computed once per splat.
fn composite(group: ptr<function, PixelGroup>, pixel_y: f32, splat: Splat, ratio_growth: f32,
             entry: u32) {
    let min_alpha = params.min_splat_alpha;
    let max_alpha = params.max_splat_alpha;
    let min_transmittance = params.min_transmittance;
    let value = row_gaussian_values(splat.conic, (*group).x.x - splat.position.x,
                                    pixel_y - splat.position.y, ratio_growth);
    let alpha = min(vec4<f32>(max_alpha), splat.position.z * value);
    let visible = !(*group).done & value <= vec4<f32>(1.0) & alpha >= vec4<f32>(min_alpha);
    let transmittance = (*group).transmittance;
    let next_transmittance = transmittance * (1.0 - alpha);
    let terminates = visible & next_transmittance < vec4<f32>(min_transmittance);
    (*group).done = (*group).done | terminates;
    let contributes = visible & !terminates;
    let weight = select(vec4<f32>(0.0), alpha * transmittance, contributes);
    (*group).red += splat.colour.x * weight;
    (*group).green += splat.colour.y * weight;
    (*group).blue += splat.colour.z * weight;
    (*group).depth += splat.position.w * weight;
    (*group).transmittance = select(transmittance, next_transmittance, contributes);
    (*group).last_entry = select((*group).last_entry, vec4<u32>(entry), contributes);
}

// Writes the final colour, depth, alpha, transmittance and last entry of the group's pixels
// inside the image.
fn write_group(group: PixelGroup, row: u32) {
    let width = params.width;
    for (var k = 0u; k < 4u; k++) {
        let column = group.columns[k];
        if column < width && row < params.height {
            let pixel_index = row * width + column;
            out_rgbd[pixel_index] = vec4<f32>(group.red[k], group.green[k], group.blue[k], group.depth[k]);
            out_alpha[pixel_index] = 1.0 - group.transmittance[k];
            out_transmittance[pixel_index] = group.transmittance[k];
            out_last_entry[pixel_index] = group.last_entry[k];
        }
    }
}
