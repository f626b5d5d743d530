// project: one invocation per Gaussian (WORKGROUP_SIZE per workgroup, linear id over a 2D grid).
// Transforms the Gaussian into the camera, builds its 2D covariance J W J^T + low-pass, inverts
// it (conic), and its tile rectangle: the bounding box of the splat's support, i.e. of the
// 3-sigma square of the reference (radius = 3 sqrt(largest eigenvalue)) intersected with the
// ellipse outside which opacity * exp(-0.5 d^T conic d) < min splat alpha (those pixels skip
// the splat anyway). Rectangles of up to 32 tiles also get a mask of the tiles the ellipse
// actually reaches (exact per tile row, with a small margin: ellipse_tile_mask), and only those are binned:
// like the tighter box, this changes no pixel, it only saves tile/splat pairs (a thin tilted
// ellipse misses most tiles of its bounding box). Invariants: every Gaussian index < count
// writes its depth key (the depth sort takes the Gaussians' indices as its values); a kept
// Gaussian writes all outputs, tile_counts being the number of binned tiles (mask bits, or
// the whole rectangle); a culled Gaussian (non-finite input or result, zero quaternion,
// behind the near plane, degenerate footprint, no tile reached) writes only the depth key
// 0xffffffff, so it sorts last (visible keys stay below it: see depth_sort_key), and leaves
// its other outputs the zeros of the launcher's fresh buffers: tile_count 0 (never binned)
// and radius 0 (project_backward skips it).

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

// A culled Gaussian's other outputs stay the zeros of the launcher's fresh (zero-filled)
// buffers: on CPU adapters (lavapipe) each store is a loop over the SIMD lanes, and most of a
// large map's Gaussians are culled in any one view.
fn cull(index: u32) {
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

// Pixel margin of ellipse_tile_mask's column ranges: absorbs the f32 rounding of its square
// roots (visible_radius_squared's margins already absorb the rasterizer's own rounding).
const TILE_MASK_MARGIN: f32 = 0.01;

// Row-major mask of the tiles of a `columns` x `rows` rectangle (at most 32 tiles) that the
// ellipse d^T cov^-1 d <= radius_squared reaches, for the 2D covariance (xx, xy, yy) of
// determinant `det` (the one the conic was divided by); `mean` is the ellipse's centre
// relative to the rectangle's first pixel centre. One trip per tile row: the ellipse's points
// in the row's strip of pixel centres span an interval of x (both are convex), and the row's
// tiles whose pixel columns meet that interval are the ones it reaches. At height dy the
// ellipse spans x = (xy / yy) dy +- sqrt(det / yy (r^2 - dy^2 / yy)), a concave right end
// that peaks at the ellipse's rightmost point, dy = r xy / sqrt(xx) (the left end mirrors
// it), so over the strip each end is extreme at that point clamped to the strip.
// (A box test per tile cost one trip per tile; tile rows are fewer.)
fn ellipse_tile_mask(mean: vec2<f32>, covariance: vec3<f32>, det: f32, radius_squared: f32,
                     columns: u32, rows: u32) -> u32 {
    let xx = covariance.x;
    let xy = covariance.y;
    let yy = covariance.z;
    let half_height = sqrt(radius_squared * yy);
    let rightmost_dy = sqrt(radius_squared / xx) * xy;
    let slope = xy / yy;
    let spread = det / yy;
    let tile = f32(TILE_SIZE);
    let last_column = f32(columns) - 1.0;
    var mask = 0u;
    var row = 0u;
    loop {
        // dy over the row's pixel centres, cut to the ellipse's own extent.
        let strip_low = max(f32(row) * tile - mean.y, -half_height);
        let strip_high = min(f32(row) * tile + (tile - 1.0) - mean.y, half_height);
        let dy_right = clamp(rightmost_dy, strip_low, strip_high);
        let dy_left = clamp(-rightmost_dy, strip_low, strip_high);
        let right = mean.x + slope * dy_right
            + sqrt(max(spread * (radius_squared - dy_right * dy_right / yy), 0.0));
        let left = mean.x + slope * dy_left
            - sqrt(max(spread * (radius_squared - dy_left * dy_left / yy), 0.0));
        // Tile columns whose pixel centres (t * 16 .. t * 16 + 15) meet [left, right].
        var first = max(ceil((left - TILE_MASK_MARGIN - (tile - 1.0)) / tile), 0.0);
        var last = min(floor((right + TILE_MASK_MARGIN) / tile), last_column);
        var reached = strip_low <= strip_high && first <= last;
        // Huge covariances (a splat far larger than the image, its rectangle cut to it) can
        // overflow: such a row keeps all its tiles.
        if !(is_finite(left) && is_finite(right) && is_finite(strip_low) && is_finite(strip_high)) {
            first = 0.0;
            last = last_column;
            reached = true;
        }
        let count = u32(last - first) + 1u;
        let bits = (ALL_TILES >> (32u - count)) << (row * columns + u32(first));
        mask |= select(0u, bits, reached);
        row += 1u;
        if row >= rows {
            break;
        }
    }
    return mask;
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
    // Position and scale first: most culled Gaussians are culled by them, before the other
    // inputs are loaded (a load costs a loop over the SIMD lanes that are still active).
    let mean = vec3<f32>(means[3u * index], means[3u * index + 1u], means[3u * index + 2u]);
    let log_scale = vec3<f32>(
        log_scales[3u * index], log_scales[3u * index + 1u], log_scales[3u * index + 2u]);
    let max_log_scale = params.max_log_scale;
    if !(all_finite3(mean) && all_finite3(log_scale)) || log_scale.x > max_log_scale
        || log_scale.y > max_log_scale || log_scale.z > max_log_scale {
        cull(index);
        return;
    }
    let camera_rotation = transpose(mat3x3<f32>(
        params.camera_row0.xyz, params.camera_row1.xyz, params.camera_row2.xyz));
    let camera_translation = vec3<f32>(params.camera_row0.w, params.camera_row1.w, params.camera_row2.w);
    let p = camera_rotation * mean + camera_translation;
    if !all_finite3(p) || p.z < params.near_plane {
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
    let quaternion = quaternions[index];
    let opacity_logit = opacity_logits[index];
    let colour = vec3<f32>(colours[3u * index], colours[3u * index + 1u], colours[3u * index + 2u]);
    if !(all_finite3(colour) && all_finite3(quaternion.xyz) && is_finite(quaternion.w)
        && is_finite(opacity_logit)) || dot(quaternion, quaternion) < params.min_quaternion_norm_squared {
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
        tile_mask = ellipse_tile_mask(mean2d - vec2<f32>(first_tile) * tile,
                                      vec3<f32>(cov_xx, cov_xy, cov_yy), det,
                                      visible_radius_squared(opacity, min_alpha), columns, rows);
        tile_count = countOneBits(tile_mask);
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
