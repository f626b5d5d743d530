// rasterize (forward): one workgroup per 16x16 tile, one invocation per pixel. The workgroup
// walks its tile's depth-ordered splat list in batches of 256: each invocation loads one splat
// into workgroup memory, then every pixel composites the batch front to back. A pixel stops
// when the next splat would bring its transmittance below the floor (early termination), and
// the whole workgroup stops once every pixel has stopped. Invariants: barriers are reached in
// uniform control flow (loop bounds come from workgroupUniformLoad); pixels outside the image
// take part in loading but write nothing. Per pixel it records the final transmittance and how
// many list entries it consumed up to its last contributing splat (for the backward pass).

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

const BATCH_SIZE: u32 = 256u;

var<workgroup> batch_position: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_conic: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_colour: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> tile_range: vec2<u32>;
var<workgroup> finished_pixels: atomic<u32>;

@compute @workgroup_size(16, 16)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(local_invocation_id) local_id: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let width = params.image_size.x;
    let height = params.image_size.y;
    let tile_id = workgroup_id.y * params.image_size.z + workgroup_id.x;
    let pixel = workgroup_id.xy * TILE_SIZE + local_id.xy;
    let inside = pixel.x < width && pixel.y < height;
    let pixel_position = vec2<f32>(f32(pixel.x), f32(pixel.y));
    if local_index == 0u {
        tile_range = tile_ranges[tile_id];
    }
    let range = workgroupUniformLoad(&tile_range);
    let batch_count = (range.y - range.x + BATCH_SIZE - 1u) / BATCH_SIZE;

    let min_alpha = params.thresholds.x;
    let max_alpha = params.thresholds.y;
    let min_transmittance = params.thresholds.z;
    var done = !inside;
    var transmittance = 1.0;
    var colour = vec3<f32>(0.0);
    var depth = 0.0;
    var last_entry = 0u;
    for (var batch = 0u; batch < batch_count; batch++) {
        if local_index == 0u {
            atomicStore(&finished_pixels, 0u);
        }
        workgroupBarrier();
        if done {
            atomicAdd(&finished_pixels, 1u);
        }
        if workgroupUniformLoad(&finished_pixels) == TILE_SIZE * TILE_SIZE {
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
        for (var j = 0u; j < batch_length && !done; j++) {
            let position = batch_position[j];
            let conic = batch_conic[j].xyz;
            let offset = pixel_position - position.xy;
            let power = -0.5 * (conic.x * offset.x * offset.x + conic.z * offset.y * offset.y)
                - conic.y * offset.x * offset.y;
            if power > 0.0 {
                continue;
            }
            let alpha = min(max_alpha, position.z * exp(power));
            if alpha < min_alpha {
                continue;
            }
            let next_transmittance = transmittance * (1.0 - alpha);
            if next_transmittance < min_transmittance {
                done = true;
                break;
            }
            let weight = alpha * transmittance;
            colour += batch_colour[j].xyz * weight;
            depth += position.w * weight;
            transmittance = next_transmittance;
            last_entry = batch * BATCH_SIZE + j + 1u;
        }
        workgroupBarrier();
    }
    if inside {
        let pixel_index = pixel.y * width + pixel.x;
        out_rgbd[pixel_index] = vec4<f32>(colour, depth);
        out_alpha[pixel_index] = 1.0 - transmittance;
        out_transmittance[pixel_index] = transmittance;
        out_last_entry[pixel_index] = last_entry;
    }
}
