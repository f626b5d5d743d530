// rasterize_backward: one workgroup per 16x16 tile, one invocation per pixel (same mapping as
// rasterize). The workgroup walks the tile's splat list BACK to front in batches of 256 loaded
// into workgroup memory; each pixel only considers entries before its recorded last_entry,
// recomputes each splat's alpha exactly as the forward pass did, recovers the transmittance in
// front of it as T_before = T_after / (1 - alpha), and accumulates dL/d(mean2d, conic, opacity,
// colour, depth) of the splat into screen_gradients (10 floats per Gaussian) with atomic adds.
// Invariants: barriers in uniform control flow; the splat order and skip rules are identical
// to the forward pass; a splat whose alpha hit the cap gets no opacity/footprint gradient.
// The `#gradient_atomics` line is replaced by the launcher with atomics_float.wgsl or
// atomics_cas.wgsl (compare-exchange fallback when float atomics are unavailable).

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> tile_ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> intersection_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> splat_position: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> splat_conic: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read> splat_colour: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> pixel_transmittance: array<f32>;
@group(0) @binding(7) var<storage, read> pixel_last_entry: array<u32>;
// dL/d(r, g, b, depth) and dL/d(alpha) per pixel
@group(0) @binding(8) var<storage, read> v_rgbd: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read> v_alpha: array<f32>;

#gradient_atomics

const BATCH_SIZE: u32 = 256u;
// Per-Gaussian layout of screen_gradients.
const SCREEN_GRADIENT_STRIDE: u32 = 10u;
const V_MEAN2D: u32 = 0u;
const V_CONIC: u32 = 2u;
const V_OPACITY: u32 = 5u;
const V_COLOUR: u32 = 6u;
const V_DEPTH: u32 = 9u;

var<workgroup> batch_gaussian: array<u32, BATCH_SIZE>;
var<workgroup> batch_position: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_conic: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> batch_colour: array<vec4<f32>, BATCH_SIZE>;
var<workgroup> tile_range: vec2<u32>;

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
    let list_length = range.y - range.x;
    let batch_count = (list_length + BATCH_SIZE - 1u) / BATCH_SIZE;

    let min_alpha = params.thresholds.x;
    let max_alpha = params.thresholds.y;
    var last_entry = 0u;
    var transmittance = 1.0;
    var v_colour_pixel = vec3<f32>(0.0);
    var v_depth_pixel = 0.0;
    var v_alpha_pixel = 0.0;
    if inside {
        let pixel_index = pixel.y * width + pixel.x;
        last_entry = pixel_last_entry[pixel_index];
        transmittance = pixel_transmittance[pixel_index];
        let v = v_rgbd[pixel_index];
        v_colour_pixel = v.xyz;
        v_depth_pixel = v.w;
        v_alpha_pixel = v_alpha[pixel_index];
    }
    let final_transmittance = transmittance;
    var colour_behind = vec3<f32>(0.0);
    var depth_behind = 0.0;

    for (var batch = 0u; batch < batch_count; batch++) {
        // Entries are loaded in reverse: slot j of batch b is list entry length-1-(b*256+j).
        let first_reversed = batch * BATCH_SIZE;
        let reversed_index = first_reversed + local_index;
        if reversed_index < list_length {
            let gaussian = intersection_gaussians[range.y - 1u - reversed_index];
            batch_gaussian[local_index] = gaussian;
            batch_position[local_index] = splat_position[gaussian];
            batch_conic[local_index] = splat_conic[gaussian];
            batch_colour[local_index] = splat_colour[gaussian];
        }
        workgroupBarrier();
        let batch_length = min(BATCH_SIZE, list_length - first_reversed);
        for (var j = 0u; j < batch_length; j++) {
            let entry = list_length - 1u - (first_reversed + j);
            if entry >= last_entry {
                continue;
            }
            let position = batch_position[j];
            let conic = batch_conic[j].xyz;
            let offset = pixel_position - position.xy;
            let power = -0.5 * (conic.x * offset.x * offset.x + conic.z * offset.y * offset.y)
                - conic.y * offset.x * offset.y;
            if power > 0.0 {
                continue;
            }
            let gaussian_value = exp(power);
            let raw_alpha = position.z * gaussian_value;
            let alpha = min(max_alpha, raw_alpha);
            if alpha < min_alpha {
                continue;
            }
            let one_minus_alpha = 1.0 - alpha;
            transmittance = transmittance / one_minus_alpha;
            let weight = alpha * transmittance;
            let colour = batch_colour[j].xyz;
            let depth = position.w;
            // d(output)/d(alpha): own contribution minus the dimming of everything behind.
            let v_splat_alpha = dot(v_colour_pixel, colour * transmittance - colour_behind / one_minus_alpha)
                + v_depth_pixel * (depth * transmittance - depth_behind / one_minus_alpha)
                + v_alpha_pixel * final_transmittance / one_minus_alpha;
            colour_behind += colour * weight;
            depth_behind += depth * weight;

            let base = batch_gaussian[j] * SCREEN_GRADIENT_STRIDE;
            add_gradient(base + V_COLOUR, v_colour_pixel.x * weight);
            add_gradient(base + V_COLOUR + 1u, v_colour_pixel.y * weight);
            add_gradient(base + V_COLOUR + 2u, v_colour_pixel.z * weight);
            add_gradient(base + V_DEPTH, v_depth_pixel * weight);
            if raw_alpha > max_alpha {
                continue;
            }
            let v_power = v_splat_alpha * alpha;
            add_gradient(base + V_OPACITY, v_splat_alpha * gaussian_value);
            add_gradient(base + V_CONIC, v_power * -0.5 * offset.x * offset.x);
            add_gradient(base + V_CONIC + 1u, v_power * -offset.x * offset.y);
            add_gradient(base + V_CONIC + 2u, v_power * -0.5 * offset.y * offset.y);
            add_gradient(base + V_MEAN2D, v_power * (conic.x * offset.x + conic.y * offset.y));
            add_gradient(base + V_MEAN2D + 1u, v_power * (conic.y * offset.x + conic.z * offset.y));
        }
        workgroupBarrier();
    }
}
