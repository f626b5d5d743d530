// rasterize_backward: one workgroup per 16x16 tile with the thread mapping of rasterize: 64
// invocations, each owning PIXELS_PER_THREAD = 4 pixels of one tile row (columns
// local_x + k * THREADS_PER_ROW, held as vec4 components). The workgroup walks the tile's
// splat list BACK to front in batches of THREADS_PER_TILE loaded into workgroup memory; each
// pixel only considers entries before its recorded last_entry, recomputes each splat's alpha
// exactly as the forward pass did, recovers the transmittance in front of it as
// T_before = T_after / (1 - alpha), and the invocation sums dL/d(mean2d, conic, opacity,
// colour, depth) of the splat over its 4 pixels before one atomic add per component into
// screen_gradients (10 floats per Gaussian).
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

const PIXELS_PER_THREAD: u32 = 4u;
const THREADS_PER_ROW: u32 = TILE_SIZE / PIXELS_PER_THREAD;
const THREADS_PER_TILE: u32 = THREADS_PER_ROW * TILE_SIZE;
const BATCH_SIZE: u32 = THREADS_PER_TILE;
// Column offsets of a thread's 4 pixels relative to its first one.
const PIXEL_COLUMN_STEPS: vec4<u32> = vec4<u32>(0u, 1u, 2u, 3u) * THREADS_PER_ROW;
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
    let columns = vec4<u32>(tile_origin.x + local_id.x) + PIXEL_COLUMN_STEPS;
    let pixel_x = vec4<f32>(columns);
    let pixel_y = f32(row);
    if local_index == 0u {
        tile_range = tile_ranges[tile_id];
    }
    let range = workgroupUniformLoad(&tile_range);
    let list_length = range.y - range.x;
    let batch_count = (list_length + BATCH_SIZE - 1u) / BATCH_SIZE;

    let min_alpha = params.thresholds.x;
    let max_alpha = params.thresholds.y;
    // Per pixel (vec4 component): entries considered, transmittance and dL/d(outputs).
    var last_entry = vec4<u32>(0u);
    var transmittance = vec4<f32>(1.0);
    var v_red = vec4<f32>(0.0);
    var v_green = vec4<f32>(0.0);
    var v_blue = vec4<f32>(0.0);
    var v_depth_pixel = vec4<f32>(0.0);
    var v_alpha_pixel = vec4<f32>(0.0);
    for (var k = 0u; k < PIXELS_PER_THREAD; k++) {
        if columns[k] < width && row < height {
            let pixel_index = row * width + columns[k];
            last_entry[k] = pixel_last_entry[pixel_index];
            transmittance[k] = pixel_transmittance[pixel_index];
            let v = v_rgbd[pixel_index];
            v_red[k] = v.x;
            v_green[k] = v.y;
            v_blue[k] = v.z;
            v_depth_pixel[k] = v.w;
            v_alpha_pixel[k] = v_alpha[pixel_index];
        }
    }
    let final_transmittance = transmittance;
    var red_behind = vec4<f32>(0.0);
    var green_behind = vec4<f32>(0.0);
    var blue_behind = vec4<f32>(0.0);
    var depth_behind = vec4<f32>(0.0);

    for (var batch = 0u; batch < batch_count; batch++) {
        // Entries are loaded in reverse: slot j of batch b is list entry
        // length-1-(b*BATCH_SIZE+j).
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
            let in_list = vec4<u32>(entry) < last_entry;
            if !any(in_list) {
                continue;
            }
            let position = batch_position[j];
            let conic = batch_conic[j].xyz;
            let offset_x = pixel_x - position.x;
            let offset_y = pixel_y - position.y;
            let power = -0.5 * (conic.x * offset_x * offset_x + conic.z * offset_y * offset_y)
                - conic.y * offset_x * offset_y;
            let gaussian_value = exp(power);
            let raw_alpha = position.z * gaussian_value;
            let alpha = min(vec4<f32>(max_alpha), raw_alpha);
            let visible = in_list & power <= vec4<f32>(0.0) & alpha >= vec4<f32>(min_alpha);
            if !any(visible) {
                continue;
            }
            let one_minus_alpha = 1.0 - alpha;
            transmittance = select(transmittance, transmittance / one_minus_alpha, visible);
            let weight = select(vec4<f32>(0.0), alpha * transmittance, visible);
            let colour = batch_colour[j].xyz;
            let depth = position.w;
            // d(output)/d(alpha): own contribution minus the dimming of everything behind.
            let v_splat_alpha = select(vec4<f32>(0.0),
                v_red * (colour.x * transmittance - red_behind / one_minus_alpha)
                + v_green * (colour.y * transmittance - green_behind / one_minus_alpha)
                + v_blue * (colour.z * transmittance - blue_behind / one_minus_alpha)
                + v_depth_pixel * (depth * transmittance - depth_behind / one_minus_alpha)
                + v_alpha_pixel * final_transmittance / one_minus_alpha,
                visible);
            red_behind += colour.x * weight;
            green_behind += colour.y * weight;
            blue_behind += colour.z * weight;
            depth_behind += depth * weight;

            let base = batch_gaussian[j] * SCREEN_GRADIENT_STRIDE;
            add_gradient(base + V_COLOUR, sum4(v_red * weight));
            add_gradient(base + V_COLOUR + 1u, sum4(v_green * weight));
            add_gradient(base + V_COLOUR + 2u, sum4(v_blue * weight));
            add_gradient(base + V_DEPTH, sum4(v_depth_pixel * weight));
            // Pixels where alpha hit the cap pass no gradient to opacity and footprint.
            let unclamped = visible & raw_alpha <= vec4<f32>(max_alpha);
            let v_power = select(vec4<f32>(0.0), v_splat_alpha * alpha, unclamped);
            add_gradient(base + V_OPACITY,
                sum4(select(vec4<f32>(0.0), v_splat_alpha * gaussian_value, unclamped)));
            add_gradient(base + V_CONIC, sum4(v_power * -0.5 * offset_x * offset_x));
            add_gradient(base + V_CONIC + 1u, sum4(v_power * -offset_x * offset_y));
            add_gradient(base + V_CONIC + 2u, sum4(v_power * -0.5 * offset_y * offset_y));
            add_gradient(base + V_MEAN2D, sum4(v_power * (conic.x * offset_x + conic.y * offset_y)));
            add_gradient(base + V_MEAN2D + 1u,
                sum4(v_power * (conic.y * offset_x + conic.z * offset_y)));
        }
        workgroupBarrier();
    }
}

fn sum4(values: vec4<f32>) -> f32 {
    return (values.x + values.y) + (values.z + values.w);
}
