// rasterize (forward), workgroup-memory variant (no subgroup operations; see
// rasterize_pixels.wgsl for the thread mapping). The workgroup walks its tile's depth-ordered
// splat list in batches of BATCH_SIZE splats, each invocation loading LOADS_PER_THREAD of them
// into workgroup memory; then every pixel composites the batch front to back. The workgroup
// stops once every pixel has stopped.
// Invariants: barriers are reached in uniform control flow (loop bounds come from
// workgroupUniformLoad); pixels outside the image take part in loading but write nothing.
// Per pixel it records the final transmittance and how many list entries it consumed up to
// its last contributing splat (for the backward pass).

const BATCH_SIZE: u32 = 64u;
const LOADS_PER_THREAD: u32 = BATCH_SIZE / THREADS_PER_TILE;

var<workgroup> batch_position: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_conic: array<vec3<f32>, BATCH_SIZE>;
var<workgroup> batch_colour: array<vec3<f32>, BATCH_SIZE>;
var<workgroup> tile_range: vec2<u32>;
var<workgroup> finished_threads: atomic<u32>;

@compute @workgroup_size(THREADS_PER_TILE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let tile_id = workgroup_id.y * params.tiles_x + workgroup_id.x;
    let tile_origin = workgroup_id.xy * TILE_SIZE;
    let row = tile_origin.y + local_index;
    if local_index == 0u {
        tile_range = tile_ranges[tile_id];
    }
    let range = workgroupUniformLoad(&tile_range);
    let batch_count = (range.y - range.x + BATCH_SIZE - 1u) / BATCH_SIZE;

    let pixel_y = f32(row);
    var group0 = new_group(tile_origin.x, row);
    var group1 = new_group(tile_origin.x + 4u, row);
    var group2 = new_group(tile_origin.x + 8u, row);
    var group3 = new_group(tile_origin.x + 12u, row);
    for (var batch = 0u; batch < batch_count; batch++) {
        if local_index == 0u {
            atomicStore(&finished_threads, 0u);
        }
        workgroupBarrier();
        if all(group0.done & group1.done & group2.done & group3.done) {
            atomicAdd(&finished_threads, 1u);
        }
        if workgroupUniformLoad(&finished_threads) == THREADS_PER_TILE {
            break;
        }
        let batch_start = range.x + batch * BATCH_SIZE;
        for (var k = 0u; k < LOADS_PER_THREAD; k++) {
            let slot = k * THREADS_PER_TILE + local_index;
            let load_index = batch_start + slot;
            if load_index < range.y {
                let splat = load_splat(intersection_gaussians[load_index]);
                batch_position[slot] = splat.position;
                batch_conic[slot] = splat.conic;
                batch_colour[slot] = splat.colour;
            }
        }
        workgroupBarrier();
        let batch_length = min(BATCH_SIZE, range.y - batch_start);
        for (var j = 0u; j < batch_length; j++) {
            let splat = Splat(batch_position[j], batch_conic[j], batch_colour[j]);
            let entry = batch * BATCH_SIZE + j + 1u;
            let ratio_growth = row_ratio_growth(splat.conic);
            composite(&group0, pixel_y, splat, ratio_growth, entry);
            composite(&group1, pixel_y, splat, ratio_growth, entry);
            composite(&group2, pixel_y, splat, ratio_growth, entry);
            composite(&group3, pixel_y, splat, ratio_growth, entry);
        }
        workgroupBarrier();
    }
    write_group(group0, row);
    write_group(group1, row);
    write_group(group2, row);
    write_group(group3, row);
    report_walk(STATUS_RASTERIZE_CUT_SHORT);
}
