// project: one invocation per Gaussian (WORKGROUP_SIZE per workgroup, linear id over a 2D grid).
// Transforms the Gaussian into the camera, builds its 2D covariance J W J^T + low-pass, inverts
// it (conic), and its tile rectangle: the bounding box of the splat's support, i.e. of the
// 3-sigma square of the reference (radius = 3 sqrt(largest eigenvalue)) intersected with the
// ellipse outside which opacity * exp(-0.5 d^T conic d) < min splat alpha (those pixels skip
// the splat anyway). Rectangles of up to 32 tiles also get a mask of the tiles the ellipse
// actually reaches (exact box/ellipse test with a small margin), and only those are binned:
// like the tighter box, this changes no pixel, it only saves tile/splat pairs (a thin tilted
// ellipse misses most tiles of its bounding box). Invariants: every Gaussian index < count
// writes all outputs; tile_counts is the number of binned tiles (mask bits, or the whole
// rectangle); a culled Gaussian (non-finite input or result, zero quaternion, behind the near
// plane, degenerate footprint, no tile reached) gets tile_count 0 and depth key 0xffffffff so
// it sorts last and is never binned (visible keys stay below it: see depth_sort_key).
// sort_values is initialised to the identity permutation.

@group(0) @binding(0) var<uniform> params: RenderParams;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> log_scales: array<f32>;
@group(0) @binding(3) var<storage, read> quaternions: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(5) var<storage, read> colours: array<f32>;
// mean2d.x, mean2d.y, opacity, camera z
@group(0) @binding(6) var<storage, read_write> splat_position: array<vec4<f32>>;
// conic a, b, c (matrix [[a, b], [b, c]]), radius in pixels
@group(0) @binding(7) var<storage, read_write> splat_conic: array<vec4<f32>>;
@group(0) @binding(8) var<storage, read_write> splat_colour: array<vec4<f32>>;
// first tile x, first tile y, columns | rows << 16, mask of the rectangle's tiles (row-major)
// the splat reaches
@group(0) @binding(9) var<storage, read_write> tile_rects: array<vec4<u32>>;
@group(0) @binding(10) var<storage, read_write> tile_counts: array<u32>;
@group(0) @binding(11) var<storage, read_write> depth_keys: array<u32>;
@group(0) @binding(12) var<storage, read_write> sort_values: array<u32>;

fn cull(index: u32) {
    splat_position[index] = vec4<f32>(0.0);
    splat_conic[index] = vec4<f32>(0.0);
    splat_colour[index] = vec4<f32>(0.0);
    tile_rects[index] = vec4<u32>(0u);
    tile_counts[index] = 0u;
    depth_keys[index] = CULLED_DEPTH_KEY;
}

fn quaternion_to_rotation(q: vec4<f32>) -> mat3x3<f32> {
    let n = q / sqrt(dot(q, q));
    let w = n.x;
    let x = n.y;
    let y = n.z;
    let z = n.w;
    // Column-major constructor: each vec3 is a column.
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

@compute @workgroup_size(WORKGROUP_SIZE)
fn main(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let index = linear_workgroup(workgroup_id, workgroup_count) * WORKGROUP_SIZE + local_index;
    if index >= params.gaussian_count {
        return;
    }
    sort_values[index] = index;
    let mean = vec3<f32>(means[3u * index], means[3u * index + 1u], means[3u * index + 2u]);
    let log_scale = vec3<f32>(
        log_scales[3u * index], log_scales[3u * index + 1u], log_scales[3u * index + 2u]);
    let quaternion = quaternions[index];
    let opacity_logit = opacity_logits[index];
    let colour = vec3<f32>(colours[3u * index], colours[3u * index + 1u], colours[3u * index + 2u]);
    var inputs_finite = is_finite(opacity_logit);
    for (var k = 0u; k < 3u; k++) {
        inputs_finite = inputs_finite && is_finite(mean[k]) && is_finite(log_scale[k])
            && is_finite(colour[k]) && is_finite(quaternion[k]);
    }
    inputs_finite = inputs_finite && is_finite(quaternion.w);
    if !inputs_finite {
        cull(index);
        return;
    }
    let max_log_scale = params.max_log_scale;
    if dot(quaternion, quaternion) < params.min_quaternion_norm_squared || log_scale.x > max_log_scale
        || log_scale.y > max_log_scale || log_scale.z > max_log_scale {
        cull(index);
        return;
    }
    let camera_rotation = transpose(mat3x3<f32>(
        params.camera_row0.xyz, params.camera_row1.xyz, params.camera_row2.xyz));
    let camera_translation = vec3<f32>(params.camera_row0.w, params.camera_row1.w, params.camera_row2.w);
    let p = camera_rotation * mean + camera_translation;
    if !(is_finite(p.x) && is_finite(p.y) && is_finite(p.z)) || p.z < params.near_plane {
        cull(index);
        return;
    }
    // Far off-axis the linearised projection is meaningless (see FRUSTUM_GUARD_BAND).
    let u = p.x / p.z;
    let v = p.y / p.z;
    if u < params.frustum_min_x || u > params.frustum_max_x || v < params.frustum_min_y || v > params.frustum_max_y {
        cull(index);
        return;
    }
    let rotation = quaternion_to_rotation(quaternion);
    let scale = exp(log_scale);
    let scaled_rotation = mat3x3<f32>(rotation[0] * scale.x, rotation[1] * scale.y, rotation[2] * scale.z);
    let world_covariance = scaled_rotation * transpose(scaled_rotation);
    let camera_covariance = camera_rotation * world_covariance * transpose(camera_rotation);
    let fx = params.fx;
    let fy = params.fy;
    // J is 2x3; as a WGSL mat3x2 it has 3 columns of vec2.
    let jacobian = mat3x2<f32>(
        vec2<f32>(fx / p.z, 0.0),
        vec2<f32>(0.0, fy / p.z),
        vec2<f32>(-fx * p.x / (p.z * p.z), -fy * p.y / (p.z * p.z)),
    );
    let cov2d = jacobian * camera_covariance * transpose(jacobian);
    let low_pass = params.low_pass_variance;
    let cov_xx = cov2d[0][0] + low_pass;
    let cov_xy = cov2d[1][0];
    let cov_yy = cov2d[1][1] + low_pass;
    let det = cov_xx * cov_yy - cov_xy * cov_xy;
    if !(is_finite(det) && det > 0.0) {
        cull(index);
        return;
    }
    let conic = vec3<f32>(cov_yy / det, -cov_xy / det, cov_xx / det);
    let mid = 0.5 * (cov_xx + cov_yy);
    let largest_eigenvalue = mid + sqrt(max(mid * mid - det, 0.0));
    let radius = ceil(params.extent_sigmas * sqrt(largest_eigenvalue));
    let mean2d = vec2<f32>(fx * p.x / p.z + params.cx, fy * p.y / p.z + params.cy);
    if !(is_finite(mean2d.x) && is_finite(mean2d.y) && is_finite(radius) && is_finite(conic.x)
        && is_finite(conic.y) && is_finite(conic.z)) {
        cull(index);
        return;
    }
    let clamped_logit = clamp(opacity_logit, -MAX_ABS_OPACITY_LOGIT, MAX_ABS_OPACITY_LOGIT);
    let opacity = 1.0 / (1.0 + exp(-clamped_logit));
    // Half extents of the support per axis: the 3-sigma square, cut to the bounding box of the
    // ellipse d^T conic d <= 2 ln(opacity / min_alpha) (half extent sqrt(r^2 * cov_xx) in x).
    var half_extent = vec2<f32>(radius);
    let min_alpha = params.min_splat_alpha;
    if min_alpha > 0.0 {
        if opacity < min_alpha {
            cull(index);
            return;
        }
        half_extent = min(half_extent,
            sqrt(visible_radius_squared(opacity, min_alpha) * vec2<f32>(cov_xx, cov_yy)));
    }
    // Tile t covers pixel centres t*16 ..= t*16 + 15 (pixel centres at integer coordinates).
    let tile = f32(TILE_SIZE);
    let last_tile = vec2<f32>(f32(params.tiles_x) - 1.0, f32(params.tiles_y) - 1.0);
    let rect_min = max(ceil((mean2d - half_extent - (tile - 1.0)) / tile), vec2<f32>(0.0));
    let rect_max = min(floor((mean2d + half_extent) / tile), last_tile);
    if rect_min.x > rect_max.x || rect_min.y > rect_max.y {
        cull(index);
        return;
    }
    let first_tile = vec2<u32>(rect_min);
    let columns = u32(rect_max.x) - first_tile.x + 1u;
    let rows = u32(rect_max.y) - first_tile.y + 1u;
    // Tiles of the rectangle the visible ellipse actually reaches (row-major bit mask); the
    // test is skipped (all tiles kept) for rectangles of more than 32 tiles or without an
    // alpha cut-off.
    var tile_mask = ALL_TILES;
    var tile_count = columns * rows;
    if min_alpha > 0.0 && tile_count <= MAX_MASKED_TILES {
        let radius_squared = visible_radius_squared(opacity, min_alpha);
        tile_mask = 0u;
        tile_count = 0u;
        // The tile's column and row advance with i (no integer division: SIMD CPU adapters
        // divide lane by lane, at dozens of cycles each).
        var cell = vec2<u32>(0u);
        for (var i = 0u; i < columns * rows; i++) {
            let tile_origin = vec2<f32>(first_tile + cell) * tile;
            let low = tile_origin - mean2d;
            let nearest = box_min_quadratic(low, low + (tile - 1.0), conic);
            // NaN compares false: such a tile is kept.
            if !(nearest > radius_squared) {
                tile_mask |= 1u << i;
                tile_count += 1u;
            }
            let row_ends = cell.x + 1u == columns;
            cell = select(vec2<u32>(cell.x + 1u, cell.y), vec2<u32>(0u, cell.y + 1u), row_ends);
        }
        if tile_count == 0u {
            cull(index);
            return;
        }
    }
    splat_position[index] = vec4<f32>(mean2d, opacity, p.z);
    splat_conic[index] = vec4<f32>(conic, radius);
    splat_colour[index] = vec4<f32>(colour, 0.0);
    tile_rects[index] = vec4<u32>(first_tile, columns | (rows << 16u), tile_mask);
    tile_counts[index] = tile_count;
    // render_core::depth_sort_key (p.z >= the near plane here).
    let above_near = bitcast<u32>(p.z) - bitcast<u32>(params.near_plane);
    depth_keys[index] = min(above_near >> DEPTH_KEY_DROPPED_BITS, LARGEST_VISIBLE_DEPTH_KEY);
}
