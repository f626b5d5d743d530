// loss: image loss  w_l1 * L1(rgb) + w_ssim * (1 - SSIM(rgb)) + w_depth * L1(depth / truncation)
// and its gradient w.r.t. the rendered rgb and depth. One invocation per pixel (16x16
// workgroups over the image). The 11x11 Gaussian window (sigma 1.5) is separable and the
// padding is ZERO (3DGS convention), so every windowed sum is a horizontal pass (`*_rows`,
// writing per-pixel row sums to row_sums) followed by a vertical pass over those row sums;
// this reads 22 instead of 121 neighbours per pixel.
// - `ssim_rows`: row sums of x, y, x^2, y^2, xy (rgb each) -> row_sums[5 * pixel + k].
// - `loss_forward`: per pixel and channel, the windowed statistics of rendered x and target y
//   (vertical pass over row_sums), the SSIM value, and the three
//   coefficient maps the SSIM gradient needs; per-pixel loss terms go to pixel_losses
//   (l1, 1 - ssim, depth, 0), already divided by their normalisers so that their sum is the
//   loss.
// - `coefficient_rows`: row sums of the (a, b, c) coefficient maps -> row_sums[5 * pixel + k],
//   k < 3 (a rgb, b rgb, c rgb).
// - `loss_backward`: dL/dx(q) = x(q) * (G * b)(q) + y(q) * (G * c)(q) + (G * a)(q) for SSIM
//   (G symmetric, same zero padding), plus the L1 and depth terms; writes v_rgbd and zeroes
//   v_alpha. Depth pixels whose target depth is not > 0 are ignored (validity mask).
// Invariants: every in-image pixel writes all of its outputs; no atomics (deterministic).

struct LossParams {
    // width, height, unused, unused
    image_size: vec4<u32>,
    // w_l1, w_ssim, w_depth, 1 / depth_truncation
    weights: vec4<f32>,
    // 1 / (3 * pixels), 1 / valid depth pixels (0 if none), unused, unused
    normalisers: vec4<f32>,
}

@group(0) @binding(0) var<uniform> loss_params: LossParams;
@group(0) @binding(1) var<storage, read> rendered: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> target_rgbd: array<vec4<f32>>;
// Per pixel 3 channels x (a, b, c) coefficients.
@group(0) @binding(3) var<storage, read_write> ssim_coefficients: array<f32>;
@group(0) @binding(4) var<storage, read_write> pixel_losses: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> v_rgbd: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> v_alpha: array<f32>;
// Horizontal-pass results, ROW_SUMS_PER_PIXEL vec4 per pixel.
@group(0) @binding(7) var<storage, read_write> row_sums: array<vec4<f32>>;

const WINDOW_RADIUS: i32 = 5;
const WINDOW_SIGMA: f32 = 1.5;
const SSIM_C1: f32 = 0.0001; // (0.01 * data range 1)^2
const SSIM_C2: f32 = 0.0009; // (0.03 * data range 1)^2
const COEFFICIENTS_PER_PIXEL: u32 = 9u;
const ROW_SUMS_PER_PIXEL: u32 = 5u;
// Slots of row_sums: statistics in the forward pass, coefficients in the backward pass.
const ROW_MU_X: u32 = 0u;
const ROW_MU_Y: u32 = 1u;
const ROW_XX: u32 = 2u;
const ROW_YY: u32 = 3u;
const ROW_XY: u32 = 4u;
const ROW_A: u32 = 0u;
const ROW_B: u32 = 1u;
const ROW_C: u32 = 2u;

// Sum of the unnormalised 1D Gaussian window over its taps (computed once per invocation:
// exp is expensive on CPU adapters).
fn window_total() -> f32 {
    var total = 0.0;
    for (var d = -WINDOW_RADIUS; d <= WINDOW_RADIUS; d++) {
        total += exp(-f32(d * d) / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA));
    }
    return total;
}

// Normalised 1D window weight at `offset` given window_total().
fn window_weight_1d(offset: i32, total: f32) -> f32 {
    return exp(-f32(offset * offset) / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA)) / total;
}

fn sign_or_zero(value: f32) -> f32 {
    return select(select(0.0, -1.0, value < 0.0), 1.0, value > 0.0);
}

@compute @workgroup_size(16, 16)
fn loss_forward(@builtin(global_invocation_id) global_id: vec3<u32>) {
    let width = loss_params.image_size.x;
    let height = loss_params.image_size.y;
    if global_id.x >= width || global_id.y >= height {
        return;
    }
    let pixel_index = global_id.y * width + global_id.x;
    let x_centre = rendered[pixel_index];
    let y_centre = target_rgbd[pixel_index];
    let total_weight = window_total();
    var mu_x = vec3<f32>(0.0);
    var mu_y = vec3<f32>(0.0);
    var xx = vec3<f32>(0.0);
    var yy = vec3<f32>(0.0);
    var xy = vec3<f32>(0.0);
    for (var dy = -WINDOW_RADIUS; dy <= WINDOW_RADIUS; dy++) {
        let row = i32(global_id.y) + dy;
        if row < 0 || row >= i32(height) {
            continue;
        }
        let weight = window_weight_1d(dy, total_weight);
        let base = (u32(row) * width + global_id.x) * ROW_SUMS_PER_PIXEL;
        mu_x += weight * row_sums[base + ROW_MU_X].xyz;
        mu_y += weight * row_sums[base + ROW_MU_Y].xyz;
        xx += weight * row_sums[base + ROW_XX].xyz;
        yy += weight * row_sums[base + ROW_YY].xyz;
        xy += weight * row_sums[base + ROW_XY].xyz;
    }
    let v_ssim = -loss_params.weights.y * loss_params.normalisers.x;
    var one_minus_ssim = 0.0;
    for (var c = 0u; c < 3u; c++) {
        let sigma_xx = xx[c] - mu_x[c] * mu_x[c];
        let sigma_yy = yy[c] - mu_y[c] * mu_y[c];
        let sigma_xy = xy[c] - mu_x[c] * mu_y[c];
        let n1 = 2.0 * mu_x[c] * mu_y[c] + SSIM_C1;
        let n2 = 2.0 * sigma_xy + SSIM_C2;
        let d1 = mu_x[c] * mu_x[c] + mu_y[c] * mu_y[c] + SSIM_C1;
        let d2 = sigma_xx + sigma_yy + SSIM_C2;
        let ssim = (n1 * n2) / (d1 * d2);
        one_minus_ssim += 1.0 - ssim;
        // Partial derivatives of SSIM w.r.t. mu_x, sigma_xx and sigma_xy.
        let d_mu = 2.0 * mu_y[c] * n2 / (d1 * d2) - 2.0 * mu_x[c] * ssim / d1;
        let d_sigma_xx = -ssim / d2;
        let d_sigma_xy = 2.0 * n1 / (d1 * d2);
        let base = pixel_index * COEFFICIENTS_PER_PIXEL + 3u * c;
        ssim_coefficients[base] = v_ssim * (d_mu - 2.0 * d_sigma_xx * mu_x[c] - d_sigma_xy * mu_y[c]);
        ssim_coefficients[base + 1u] = v_ssim * 2.0 * d_sigma_xx;
        ssim_coefficients[base + 2u] = v_ssim * d_sigma_xy;
    }
    let l1 = dot(abs(x_centre.xyz - y_centre.xyz), vec3<f32>(1.0));
    var depth_term = 0.0;
    if y_centre.w > 0.0 {
        depth_term = abs(x_centre.w - y_centre.w) * loss_params.weights.w;
    }
    pixel_losses[pixel_index] = vec4<f32>(
        loss_params.weights.x * l1 * loss_params.normalisers.x,
        loss_params.weights.y * one_minus_ssim * loss_params.normalisers.x,
        loss_params.weights.z * depth_term * loss_params.normalisers.y,
        0.0,
    );
}

@compute @workgroup_size(16, 16)
fn loss_backward(@builtin(global_invocation_id) global_id: vec3<u32>) {
    let width = loss_params.image_size.x;
    let height = loss_params.image_size.y;
    if global_id.x >= width || global_id.y >= height {
        return;
    }
    let pixel_index = global_id.y * width + global_id.x;
    let x = rendered[pixel_index];
    let y = target_rgbd[pixel_index];
    let total_weight = window_total();
    var sum_a = vec3<f32>(0.0);
    var sum_b = vec3<f32>(0.0);
    var sum_c = vec3<f32>(0.0);
    for (var dy = -WINDOW_RADIUS; dy <= WINDOW_RADIUS; dy++) {
        let row = i32(global_id.y) + dy;
        if row < 0 || row >= i32(height) {
            continue;
        }
        let weight = window_weight_1d(dy, total_weight);
        let base = (u32(row) * width + global_id.x) * ROW_SUMS_PER_PIXEL;
        sum_a += weight * row_sums[base + ROW_A].xyz;
        sum_b += weight * row_sums[base + ROW_B].xyz;
        sum_c += weight * row_sums[base + ROW_C].xyz;
    }
    var v_rgb = x.xyz * sum_b + y.xyz * sum_c + sum_a;
    let l1_scale = loss_params.weights.x * loss_params.normalisers.x;
    for (var c = 0u; c < 3u; c++) {
        v_rgb[c] += l1_scale * sign_or_zero(x[c] - y[c]);
    }
    var v_depth = 0.0;
    if y.w > 0.0 {
        v_depth = loss_params.weights.z * loss_params.weights.w * loss_params.normalisers.y
            * sign_or_zero(x.w - y.w);
    }
    v_rgbd[pixel_index] = vec4<f32>(v_rgb, v_depth);
    v_alpha[pixel_index] = 0.0;
}

@compute @workgroup_size(16, 16)
fn ssim_rows(@builtin(global_invocation_id) global_id: vec3<u32>) {
    let width = loss_params.image_size.x;
    let height = loss_params.image_size.y;
    if global_id.x >= width || global_id.y >= height {
        return;
    }
    let total_weight = window_total();
    var mu_x = vec3<f32>(0.0);
    var mu_y = vec3<f32>(0.0);
    var xx = vec3<f32>(0.0);
    var yy = vec3<f32>(0.0);
    var xy = vec3<f32>(0.0);
    for (var dx = -WINDOW_RADIUS; dx <= WINDOW_RADIUS; dx++) {
        let column = i32(global_id.x) + dx;
        if column < 0 || column >= i32(width) {
            continue;
        }
        let weight = window_weight_1d(dx, total_weight);
        let neighbour = global_id.y * width + u32(column);
        let x = rendered[neighbour].xyz;
        let y = target_rgbd[neighbour].xyz;
        mu_x += weight * x;
        mu_y += weight * y;
        xx += weight * x * x;
        yy += weight * y * y;
        xy += weight * x * y;
    }
    let base = (global_id.y * width + global_id.x) * ROW_SUMS_PER_PIXEL;
    row_sums[base + ROW_MU_X] = vec4<f32>(mu_x, 0.0);
    row_sums[base + ROW_MU_Y] = vec4<f32>(mu_y, 0.0);
    row_sums[base + ROW_XX] = vec4<f32>(xx, 0.0);
    row_sums[base + ROW_YY] = vec4<f32>(yy, 0.0);
    row_sums[base + ROW_XY] = vec4<f32>(xy, 0.0);
}

@compute @workgroup_size(16, 16)
fn coefficient_rows(@builtin(global_invocation_id) global_id: vec3<u32>) {
    let width = loss_params.image_size.x;
    let height = loss_params.image_size.y;
    if global_id.x >= width || global_id.y >= height {
        return;
    }
    let total_weight = window_total();
    var sum_a = vec3<f32>(0.0);
    var sum_b = vec3<f32>(0.0);
    var sum_c = vec3<f32>(0.0);
    for (var dx = -WINDOW_RADIUS; dx <= WINDOW_RADIUS; dx++) {
        let column = i32(global_id.x) + dx;
        if column < 0 || column >= i32(width) {
            continue;
        }
        let weight = window_weight_1d(dx, total_weight);
        let base = (global_id.y * width + u32(column)) * COEFFICIENTS_PER_PIXEL;
        for (var c = 0u; c < 3u; c++) {
            sum_a[c] += weight * ssim_coefficients[base + 3u * c];
            sum_b[c] += weight * ssim_coefficients[base + 3u * c + 1u];
            sum_c[c] += weight * ssim_coefficients[base + 3u * c + 2u];
        }
    }
    let base = (global_id.y * width + global_id.x) * ROW_SUMS_PER_PIXEL;
    row_sums[base + ROW_A] = vec4<f32>(sum_a, 0.0);
    row_sums[base + ROW_B] = vec4<f32>(sum_b, 0.0);
    row_sums[base + ROW_C] = vec4<f32>(sum_c, 0.0);
}
