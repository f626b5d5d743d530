// Shared by the forward and backward rasterizers (all four variants), in front of
// rasterize_pixels.wgsl or rasterize_backward_pixels.wgsl: the frame's bindings 0-5, the thread
// mapping's constants and the splat as the per-pixel code sees it.
// Thread mapping: one workgroup per 16x16 tile, THREADS_PER_TILE = 16 invocations; invocation
// r owns tile row r, 16 pixels held as 4 groups of 4 pixels (columns 4g .. 4g + 3 of the tile,
// as vec4 components).

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> tile_ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> intersection_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> splat_position: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> splat_conic: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> splat_colour: array<vec4<f32>>;

const THREADS_PER_TILE: u32 = TILE_SIZE;
// Column offsets of the 4 pixels of a group relative to its first column.
const GROUP_COLUMNS: vec4<u32> = vec4<u32>(0u, 1u, 2u, 3u);

// One splat as the per-pixel code needs it.
struct Splat {
    // mean2d.x, mean2d.y, opacity, camera z
    position: vec4<f32>,
    conic: vec3<f32>,
    colour: vec3<f32>,
}

fn load_splat(gaussian: u32) -> Splat {
    return Splat(splat_position[gaussian], splat_conic[gaussian].xyz, splat_colour[gaussian].xyz);
}
