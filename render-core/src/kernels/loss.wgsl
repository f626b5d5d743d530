// loss: image loss  w_l1 * L1(rgb) + w_ssim * (1 - SSIM(rgb)) + w_depth * L1(depth / truncation)
// and its gradient w.r.t. the rendered rgb and depth. One invocation per pixel (16x16
// workgroups over the image).
// - `loss_forward`: per pixel and channel, the 11x11 Gaussian-window (sigma 1.5) statistics of
//   rendered x and target y with ZERO padding (3DGS convention), the SSIM value, and the three
//   coefficient maps the SSIM gradient needs; per-pixel loss terms go to pixel_losses
//   (l1, 1 - ssim, depth, 0), already divided by their normalisers so that their sum is the
//   loss.
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

const WINDOW_RADIUS: i32 = 5;
const WINDOW_SIGMA: f32 = 1.5;
const SSIM_C1: f32 = 0.0001; // (0.01 * data range 1)^2
const SSIM_C2: f32 = 0.0009; // (0.03 * data range 1)^2
const COEFFICIENTS_PER_PIXEL: u32 = 9u;

fn window_weight_1d(offset: i32) -> f32 {
    var total = 0.0;
    for (var d = -WINDOW_RADIUS; d <= WINDOW_RADIUS; d++) {
        total += exp(-f32(d * d) / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA));
    }
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
        let weight_y = window_weight_1d(dy);
        for (var dx = -WINDOW_RADIUS; dx <= WINDOW_RADIUS; dx++) {
            let column = i32(global_id.x) + dx;
            if column < 0 || column >= i32(width) {
                continue;
            }
            let weight = weight_y * window_weight_1d(dx);
            let neighbour = u32(row) * width + u32(column);
            let x = rendered[neighbour].xyz;
            let y = target_rgbd[neighbour].xyz;
            mu_x += weight * x;
            mu_y += weight * y;
            xx += weight * x * x;
            yy += weight * y * y;
            xy += weight * x * y;
        }
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
    var sum_a = vec3<f32>(0.0);
    var sum_b = vec3<f32>(0.0);
    var sum_c = vec3<f32>(0.0);
    for (var dy = -WINDOW_RADIUS; dy <= WINDOW_RADIUS; dy++) {
        let row = i32(global_id.y) + dy;
        if row < 0 || row >= i32(height) {
            continue;
        }
        let weight_y = window_weight_1d(dy);
        for (var dx = -WINDOW_RADIUS; dx <= WINDOW_RADIUS; dx++) {
            let column = i32(global_id.x) + dx;
            if column < 0 || column >= i32(width) {
                continue;
            }
            let weight = weight_y * window_weight_1d(dx);
            let base = (u32(row) * width + u32(column)) * COEFFICIENTS_PER_PIXEL;
            for (var c = 0u; c < 3u; c++) {
                sum_a[c] += weight * ssim_coefficients[base + 3u * c];
                sum_b[c] += weight * ssim_coefficients[base + 3u * c + 1u];
                sum_c[c] += weight * ssim_coefficients[base + 3u * c + 2u];
            }
        }
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
