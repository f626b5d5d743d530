// Shared by the forward and backward rasterizers (all four variants), in front of
// rasterize_pixels.wgsl or rasterize_backward_pixels.wgsl: the frame's bindings 0-5 and 12, the
// thread mapping's constants, the splat as the per-pixel code sees it and the loop-limit check.
// Thread mapping: one workgroup per 16x16 tile, THREADS_PER_TILE = 16 invocations; invocation
// r owns tile row r, 16 pixels held as 4 groups of 4 pixels (columns 4g .. 4g + 3 of the tile,
// as vec4 components).

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> tile_ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> intersection_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> splat_position: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> splat_conic: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> splat_colour: array<vec4<f32>>;
// The frame's status words (wgsl.rs FRAME_STATUS_WORDS), where report_walk flags a walk cut
// short; binding 12 in all four rasterizers (the forward ones leave 10 and 11 unused).
@group(0) @binding(12) var<storage, read_write> frame_status: array<u32>;

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

// Whether lavapipe's loop limit cut this invocation's loops short (render-core/README.md).
// gallivm (lavapipe's compiler) counts the trips of all loops of an invocation against one
// budget of 65535, and once it is spent every loop ends after its first trip, silently. So a
// loop that needs two trips and makes one says the budget ran out somewhere before it. Called
// after every other loop of a rasterizer: it vouches for all of them, at the cost of two trips
// per invocation (flags in the loops themselves were carried through the inner loops at a
// measurable cost). The trip count comes from a uniform so that the compiler cannot unroll
// the loop away. A walk that ended exactly on the budget's last trip is reported too.
// Adapters without such a budget always make both trips.
fn loop_limit_reached() -> bool {
    let trips = min(params.tiles_x, 1u) + 1u;
    var made = 0u;
    loop {
        made += 1u;
        if made >= trips {
            break;
        }
    }
    return made < trips;
}

// Sets the frame's status word `status_word` (STATUS_RASTERIZE_CUT_SHORT or
// STATUS_RASTERIZE_BACKWARD_CUT_SHORT) when the loop limit cut this invocation's walk short.
// Called last by every rasterizer.
fn report_walk(status_word: u32) {
    if loop_limit_reached() {
        frame_status[status_word] = 1u;
    }
}
