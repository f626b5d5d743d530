// rasterize (forward): one workgroup per 16x16 tile, 64 invocations; each invocation shades
// PIXELS_PER_THREAD = 4 pixels of one tile row (columns local_x + k * THREADS_PER_ROW, k < 4,
// held as the components of vec4s), so every splat loaded from memory serves 4 pixels and the
// per-pixel arithmetic is plain vector code (on CPU adapters such as lavapipe, loads dominate).
// The workgroup walks its tile's depth-ordered splat list in batches of THREADS_PER_TILE: each
// invocation loads one splat into workgroup memory, then every pixel composites the batch
// front to back. A pixel stops when the next splat would bring its transmittance below the
// floor (early termination); the whole workgroup stops once every pixel has stopped.
// Invariants: barriers are reached in uniform control flow (loop bounds come from
// workgroupUniformLoad); pixels outside the image take part in loading but write nothing; the
// arithmetic per (pixel, splat) is that of the CPU reference in the same order (a skipped
// splat adds exactly 0). Per pixel it records the final transmittance and how many list
// entries it consumed up to its last contributing splat (for the backward pass).

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> tile_ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> intersection_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> splat_position: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> splat_conic: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> splat_colour: array<vec4<f32>>;
// r, g, b, depth (alpha-composited, not normalised)
@group(0) @binding(6) var<storage, read_write> out_rgbd: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read_write> out_alpha: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_transmittance: array<f32>;
@group(0) @binding(9) var<storage, read_write> out_last_entry: array<u32>;

const PIXELS_PER_THREAD: u32 = 4u;
const THREADS_PER_ROW: u32 = TILE_SIZE / PIXELS_PER_THREAD;
const THREADS_PER_TILE: u32 = THREADS_PER_ROW * TILE_SIZE;
const BATCH_SIZE: u32 = THREADS_PER_TILE;
// Column offsets of a thread's 4 pixels relative to its first one.
const PIXEL_COLUMN_STEPS: vec4<u32> = vec4<u32>(0u, 1u, 2u, 3u) * THREADS_PER_ROW;

var<workgroup> batch_position: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_conic: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_colour: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> tile_range: vec2<u32>;
var<workgroup> finished_threads: atomic<u32>;

@compute @workgroup_size(THREADS_PER_ROW, TILE_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_id) local_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let width = params.image_size.x;
    let height = params.image_size.y;
    let tile_id = workgroup_id.y * params.image_size.z + workgroup_id.x;
    let tile_origin = workgroup_id.xy * TILE_SIZE;
    let row = tile_origin.y + local_id.y;
    if local_index == 0u {
        tile_range = tile_ranges[tile_id];
    }
    let range = workgroupUniformLoad(&tile_range);
    let batch_count = (range.y - range.x + BATCH_SIZE - 1u) / BATCH_SIZE;

    let min_alpha = params.thresholds.x;
    let max_alpha = params.thresholds.y;
    let min_transmittance = params.thresholds.z;
    let columns = vec4<u32>(tile_origin.x + local_id.x) + PIXEL_COLUMN_STEPS;
    let pixel_x = vec4<f32>(columns);
    let pixel_y = f32(row);
    var done = columns >= vec4<u32>(width) | vec4<bool>(row >= height);
    var transmittance = vec4<f32>(1.0);
    var red = vec4<f32>(0.0);
    var green = vec4<f32>(0.0);
    var blue = vec4<f32>(0.0);
    var depth = vec4<f32>(0.0);
    var last_entry = vec4<u32>(0u);
    for (var batch = 0u; batch < batch_count; batch++) {
        if local_index == 0u {
            atomicStore(&finished_threads, 0u);
        }
        workgroupBarrier();
        if all(done) {
            atomicAdd(&finished_threads, 1u);
        }
        if workgroupUniformLoad(&finished_threads) == THREADS_PER_TILE {
            break;
        }
        let batch_start = range.x + batch * BATCH_SIZE;
        let load_index = batch_start + local_index;
        if load_index < range.y {
            let gaussian = intersection_gaussians[load_index];
            batch_position[local_index] = splat_position[gaussian];
            batch_conic[local_index] = splat_conic[gaussian];
            batch_colour[local_index] = splat_colour[gaussian];
        }
        workgroupBarrier();
        let batch_length = min(BATCH_SIZE, range.y - batch_start);
        for (var j = 0u; j < batch_length && !all(done); j++) {
            let position = batch_position[j];
            let conic = batch_conic[j].xyz;
            let splat_rgb = batch_colour[j].xyz;
            let offset_x = pixel_x - position.x;
            let offset_y = pixel_y - position.y;
            let power = -0.5 * (conic.x * offset_x * offset_x + conic.z * offset_y * offset_y)
                - conic.y * offset_x * offset_y;
            let alpha = min(vec4<f32>(max_alpha), position.z * exp(power));
            let visible = !done & power <= vec4<f32>(0.0) & alpha >= vec4<f32>(min_alpha);
            let next_transmittance = transmittance * (1.0 - alpha);
            let terminates = visible & next_transmittance < vec4<f32>(min_transmittance);
            done = done | terminates;
            let contributes = visible & !terminates;
            let weight = select(vec4<f32>(0.0), alpha * transmittance, contributes);
            red += splat_rgb.x * weight;
            green += splat_rgb.y * weight;
            blue += splat_rgb.z * weight;
            depth += position.w * weight;
            transmittance = select(transmittance, next_transmittance, contributes);
            last_entry = select(last_entry, vec4<u32>(batch * BATCH_SIZE + j + 1u), contributes);
        }
        workgroupBarrier();
    }
    for (var k = 0u; k < PIXELS_PER_THREAD; k++) {
        let column = columns[k];
        if column < width && row < height {
            let pixel_index = row * width + column;
            out_rgbd[pixel_index] = vec4<f32>(red[k], green[k], blue[k], depth[k]);
            out_alpha[pixel_index] = 1.0 - transmittance[k];
            out_transmittance[pixel_index] = transmittance[k];
            out_last_entry[pixel_index] = last_entry[k];
        }
    }
}
