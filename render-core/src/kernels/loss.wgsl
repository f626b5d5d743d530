// loss: image loss  w_l1 * L1(rgb) + w_ssim * (1 - SSIM(rgb)) + w_depth * L1(depth / truncation)
// and its gradient w.r.t. the rendered rgb and depth. The 11x11 Gaussian window (sigma 1.5)
// is separable and the padding is ZERO (3DGS convention), so every windowed sum is a
// horizontal pass over rows and a vertical pass over columns, in either order.
// Thread mapping: every kernel is one invocation per LOSS_RUN = 64 consecutive pixels of one row
// (horizontal passes) or one column (vertical pass), 64 invocations per workgroup, linear run
// index over a 2D grid. An invocation streams its run through an 11-entry window held in
// registers (s0 .. s10, shifted by one pixel per step), so each input is loaded about once per
// output instead of 11 times: on CPU adapters (lavapipe) every load is a per-lane scalar
// gather and dominates the cost.
// - `ssim_rows`: row sums of x, y, x^2, y^2, xy (rgb each) -> row_sums (15 floats per pixel,
//   in 4 vec4s).
// - `ssim_columns`: walks rows y0 - 5 .. y0 + LOSS_RUN + 5 of its column: the windowed statistics
//   of rendered x and target y (vertical pass over row_sums), the SSIM value and the three
//   coefficient maps (a, b, c) the SSIM gradient needs, then at once the vertical pass of
//   those coefficients (a second window over the coefficients just computed; the 5 rows on
//   either side of the run are computed too, so no other invocation's output is needed) ->
//   ssim_coefficients (9 floats per pixel in 3 vec4s: column sums of a rgb, b rgb, c rgb). The
//   SSIM loss term of the run's own pixels goes to loss_partials[run].
// - `loss_rows`: the horizontal pass of those coefficient sums gives (G * a), (G * b),
//   (G * c) and dL/dx(q) = x(q) * (G * b)(q) + y(q) * (G * c)(q) + (G * a)(q) for SSIM (G
//   symmetric, same zero padding), plus the L1 and depth terms; writes v_rgbd, zeroes v_alpha
//   and puts the run's L1 and depth loss terms in loss_partials[column runs + run]. Depth
//   pixels whose target depth is not > 0 are ignored (validity mask).
// Loss terms are (l1, 1 - ssim, depth, 0), already divided by their normalisers, so that the
// sum of loss_partials (reduce.wgsl) is the weighted loss.
// Invariants: every in-image pixel writes all of its outputs; pixels outside the image read
// as zero and are never written; no atomics (deterministic).

@group(0) @binding(0) var<uniform> loss_params: LossParams;
@group(0) @binding(1) var<storage, read> rendered: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> target_rgbd: array<vec4<f32>>;
// Per pixel the column sums of the 3 channels x (a, b, c) coefficients, packed in
// SSIM_COEFFICIENT_VEC4S_PER_PIXEL vec4s: (a rgb, b r), (b gb, c rg), (c b, unused).
@group(0) @binding(3) var<storage, read_write> ssim_coefficients: array<vec4<f32>>;
// One vec4 of loss terms per column run, then one per row run.
@group(0) @binding(4) var<storage, read_write> loss_partials: array<vec4<f32>>;
@group(0) @binding(5) var<storage, read_write> v_rgbd: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> v_alpha: array<f32>;
// Horizontal-pass results: the 15 statistics of a pixel packed in ROW_SUMS_VEC4S_PER_PIXEL
// vec4s: (mu_x rgb, mu_y r), (mu_y gb, xx rg), (xx b, yy rgb), (xy rgb, unused). Packed
// because on lavapipe a vec4 load or store costs about what an f32 one does.
@group(0) @binding(7) var<storage, read_write> row_sums: array<vec4<f32>>;

// Normalised 1D window weights by distance from the centre (0 .. 5).
struct Weights {
    w0: f32,
    w1: f32,
    w2: f32,
    w3: f32,
    w4: f32,
    w5: f32,
}

fn window_weights() -> Weights {
    // Sum of the unnormalised window over its taps; exp is computed once per invocation.
    var total = 0.0;
    for (var d = -SSIM_WINDOW_RADIUS; d <= SSIM_WINDOW_RADIUS; d++) {
        total += raw_weight(d);
    }
    return Weights(raw_weight(0) / total, raw_weight(1) / total, raw_weight(2) / total,
                   raw_weight(3) / total, raw_weight(4) / total, raw_weight(5) / total);
}

fn raw_weight(offset: i32) -> f32 {
    return exp(-f32(offset * offset) / (2.0 * SSIM_WINDOW_SIGMA * SSIM_WINDOW_SIGMA));
}

fn sign_or_zero(value: f32) -> f32 {
    return select(select(0.0, -1.0, value < 0.0), 1.0, value > 0.0);
}

// The run of this invocation: its first pixel (x, y) and whether it lies inside the image;
// pixel k of the run is start + k along the row (horizontal passes) or column (vertical).
struct Run {
    start: vec2<u32>,
    valid: bool,
}

fn run_of(workgroup_id: vec3<u32>, workgroup_count: vec3<u32>, local_index: u32,
          along_rows: bool) -> Run {
    let index = linear_workgroup(workgroup_id, workgroup_count) * LOSS_WORKGROUP_SIZE + local_index;
    let width = loss_params.width;
    let height = loss_params.height;
    if along_rows {
        let runs_per_row = loss_params.runs_per_row;
        let row = index / runs_per_row;
        return Run(vec2<u32>((index % runs_per_row) * LOSS_RUN, row), row < height);
    }
    let runs_per_column = loss_params.runs_per_column;
    let column = index / runs_per_column;
    return Run(vec2<u32>(column, (index % runs_per_column) * LOSS_RUN), column < width);
}

// Pixel index of window position `offset` (may be outside the run) or -1 outside the image.
fn pixel_at(run: Run, offset: i32, along_rows: bool) -> i32 {
    let width = i32(loss_params.width);
    let height = i32(loss_params.height);
    var x = i32(run.start.x);
    var y = i32(run.start.y);
    if along_rows {
        x += offset;
    } else {
        y += offset;
    }
    if x < 0 || y < 0 || x >= width || y >= height {
        return -1;
    }
    return y * width + x;
}

// ---- statistics (x, y, x^2, y^2, xy per channel) ----

struct Stats {
    mu_x: vec3<f32>,
    mu_y: vec3<f32>,
    xx: vec3<f32>,
    yy: vec3<f32>,
    xy: vec3<f32>,
}

fn zero_stats() -> Stats {
    let z = vec3<f32>(0.0);
    return Stats(z, z, z, z, z);
}

fn add_stats(a: Stats, b: Stats) -> Stats {
    return Stats(a.mu_x + b.mu_x, a.mu_y + b.mu_y, a.xx + b.xx, a.yy + b.yy, a.xy + b.xy);
}

fn scale_stats(a: Stats, w: f32) -> Stats {
    return Stats(w * a.mu_x, w * a.mu_y, w * a.xx, w * a.yy, w * a.xy);
}

fn window_stats(w: Weights, s0: Stats, s1: Stats, s2: Stats, s3: Stats, s4: Stats, s5: Stats,
                s6: Stats, s7: Stats, s8: Stats, s9: Stats, s10: Stats) -> Stats {
    var sum = scale_stats(s5, w.w0);
    sum = add_stats(sum, scale_stats(add_stats(s4, s6), w.w1));
    sum = add_stats(sum, scale_stats(add_stats(s3, s7), w.w2));
    sum = add_stats(sum, scale_stats(add_stats(s2, s8), w.w3));
    sum = add_stats(sum, scale_stats(add_stats(s1, s9), w.w4));
    return add_stats(sum, scale_stats(add_stats(s0, s10), w.w5));
}

// Products of one pixel (zero outside the image).
fn pixel_stats(pixel: i32) -> Stats {
    if pixel < 0 {
        return zero_stats();
    }
    let x = rendered[pixel].xyz;
    let y = target_rgbd[pixel].xyz;
    return Stats(x, y, x * x, y * y, x * y);
}

fn load_row_stats(pixel: i32) -> Stats {
    if pixel < 0 {
        return zero_stats();
    }
    let b = u32(pixel) * ROW_SUMS_VEC4S_PER_PIXEL;
    let p = row_sums[b];
    let q = row_sums[b + 1u];
    let r = row_sums[b + 2u];
    let t = row_sums[b + 3u];
    return Stats(p.xyz, vec3<f32>(p.w, q.xy), vec3<f32>(q.zw, r.x), r.yzw, t.xyz);
}

fn store_row_stats(pixel: u32, s: Stats) {
    let b = pixel * ROW_SUMS_VEC4S_PER_PIXEL;
    row_sums[b] = vec4<f32>(s.mu_x, s.mu_y.x);
    row_sums[b + 1u] = vec4<f32>(s.mu_y.yz, s.xx.xy);
    row_sums[b + 2u] = vec4<f32>(s.xx.z, s.yy);
    row_sums[b + 3u] = vec4<f32>(s.xy, 0.0);
}

// ---- SSIM gradient coefficients (a, b, c per channel) ----

struct Coefficients {
    a: vec3<f32>,
    b: vec3<f32>,
    c: vec3<f32>,
}

fn zero_coefficients() -> Coefficients {
    let z = vec3<f32>(0.0);
    return Coefficients(z, z, z);
}

fn add_coefficients(p: Coefficients, q: Coefficients) -> Coefficients {
    return Coefficients(p.a + q.a, p.b + q.b, p.c + q.c);
}

fn scale_coefficients(p: Coefficients, w: f32) -> Coefficients {
    return Coefficients(w * p.a, w * p.b, w * p.c);
}

fn window_coefficients(w: Weights, s0: Coefficients, s1: Coefficients, s2: Coefficients,
                       s3: Coefficients, s4: Coefficients, s5: Coefficients, s6: Coefficients,
                       s7: Coefficients, s8: Coefficients, s9: Coefficients,
                       s10: Coefficients) -> Coefficients {
    var sum = scale_coefficients(s5, w.w0);
    sum = add_coefficients(sum, scale_coefficients(add_coefficients(s4, s6), w.w1));
    sum = add_coefficients(sum, scale_coefficients(add_coefficients(s3, s7), w.w2));
    sum = add_coefficients(sum, scale_coefficients(add_coefficients(s2, s8), w.w3));
    sum = add_coefficients(sum, scale_coefficients(add_coefficients(s1, s9), w.w4));
    return add_coefficients(sum, scale_coefficients(add_coefficients(s0, s10), w.w5));
}

fn load_coefficients(pixel: i32) -> Coefficients {
    if pixel < 0 {
        return zero_coefficients();
    }
    let b = u32(pixel) * SSIM_COEFFICIENT_VEC4S_PER_PIXEL;
    let p = ssim_coefficients[b];
    let q = ssim_coefficients[b + 1u];
    let r = ssim_coefficients[b + 2u];
    return Coefficients(p.xyz, vec3<f32>(p.w, q.xy), vec3<f32>(q.zw, r.x));
}

@compute @workgroup_size(LOSS_WORKGROUP_SIZE)
fn ssim_rows(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let run = run_of(workgroup_id, workgroup_count, local_index, true);
    if !run.valid {
        return;
    }
    let w = window_weights();
    var s0 = pixel_stats(pixel_at(run, -5, true));
    var s1 = pixel_stats(pixel_at(run, -4, true));
    var s2 = pixel_stats(pixel_at(run, -3, true));
    var s3 = pixel_stats(pixel_at(run, -2, true));
    var s4 = pixel_stats(pixel_at(run, -1, true));
    var s5 = pixel_stats(pixel_at(run, 0, true));
    var s6 = pixel_stats(pixel_at(run, 1, true));
    var s7 = pixel_stats(pixel_at(run, 2, true));
    var s8 = pixel_stats(pixel_at(run, 3, true));
    var s9 = pixel_stats(pixel_at(run, 4, true));
    var s10 = pixel_stats(pixel_at(run, 5, true));
    for (var step = 0; step < i32(LOSS_RUN); step++) {
        let pixel = pixel_at(run, step, true);
        if pixel < 0 {
            break;
        }
        store_row_stats(u32(pixel), window_stats(w, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10));
        s0 = s1; s1 = s2; s2 = s3; s3 = s4; s4 = s5; s5 = s6; s6 = s7; s7 = s8; s8 = s9; s9 = s10;
        s10 = pixel_stats(pixel_at(run, step + 6, true));
    }
}

// SSIM gradient coefficients of one pixel from its windowed statistics, and its 1 - SSIM
// summed over the channels.
struct PixelSsim {
    coefficients: Coefficients,
    one_minus_ssim: f32,
}

fn pixel_ssim(stats: Stats) -> PixelSsim {
    let v_ssim = -loss_params.w_ssim * loss_params.rgb_normaliser;
    let mu_x = stats.mu_x;
    let mu_y = stats.mu_y;
    let sigma_xx = stats.xx - mu_x * mu_x;
    let sigma_yy = stats.yy - mu_y * mu_y;
    let sigma_xy = stats.xy - mu_x * mu_y;
    let n1 = 2.0 * mu_x * mu_y + SSIM_C1;
    let n2 = 2.0 * sigma_xy + SSIM_C2;
    let d1 = mu_x * mu_x + mu_y * mu_y + SSIM_C1;
    let d2 = sigma_xx + sigma_yy + SSIM_C2;
    let ssim = (n1 * n2) / (d1 * d2);
    // Partial derivatives of SSIM w.r.t. mu_x, sigma_xx and sigma_xy.
    let d_mu = 2.0 * mu_y * n2 / (d1 * d2) - 2.0 * mu_x * ssim / d1;
    let d_sigma_xx = -ssim / d2;
    let d_sigma_xy = 2.0 * n1 / (d1 * d2);
    return PixelSsim(
        Coefficients(v_ssim * (d_mu - 2.0 * d_sigma_xx * mu_x - d_sigma_xy * mu_y),
                     v_ssim * 2.0 * d_sigma_xx, v_ssim * d_sigma_xy),
        dot(vec3<f32>(1.0) - ssim, vec3<f32>(1.0)));
}

@compute @workgroup_size(LOSS_WORKGROUP_SIZE)
fn ssim_columns(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let run_index = linear_workgroup(workgroup_id, workgroup_count) * LOSS_WORKGROUP_SIZE + local_index;
    let run = run_of(workgroup_id, workgroup_count, local_index, false);
    if !run.valid {
        return;
    }
    let w = window_weights();
    // Statistics window centred on row y0 + step (step starts 5 rows above the run).
    var s0 = load_row_stats(pixel_at(run, -10, false));
    var s1 = load_row_stats(pixel_at(run, -9, false));
    var s2 = load_row_stats(pixel_at(run, -8, false));
    var s3 = load_row_stats(pixel_at(run, -7, false));
    var s4 = load_row_stats(pixel_at(run, -6, false));
    var s5 = load_row_stats(pixel_at(run, -5, false));
    var s6 = load_row_stats(pixel_at(run, -4, false));
    var s7 = load_row_stats(pixel_at(run, -3, false));
    var s8 = load_row_stats(pixel_at(run, -2, false));
    var s9 = load_row_stats(pixel_at(run, -1, false));
    var s10 = load_row_stats(pixel_at(run, 0, false));
    // Coefficient window: c10 is the newest row (y0 + step), c5 the row being output.
    var c0 = zero_coefficients();
    var c1 = zero_coefficients();
    var c2 = zero_coefficients();
    var c3 = zero_coefficients();
    var c4 = zero_coefficients();
    var c5 = zero_coefficients();
    var c6 = zero_coefficients();
    var c7 = zero_coefficients();
    var c8 = zero_coefficients();
    var c9 = zero_coefficients();
    var c10 = zero_coefficients();
    var ssim_term = 0.0;
    for (var step = -SSIM_WINDOW_RADIUS; step < i32(LOSS_RUN) + SSIM_WINDOW_RADIUS; step++) {
        c0 = c1; c1 = c2; c2 = c3; c3 = c4; c4 = c5; c5 = c6; c6 = c7; c7 = c8; c8 = c9; c9 = c10;
        c10 = zero_coefficients();
        if pixel_at(run, step, false) >= 0 {
            let ssim = pixel_ssim(window_stats(w, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10));
            c10 = ssim.coefficients;
            if step >= 0 && step < i32(LOSS_RUN) {
                ssim_term += ssim.one_minus_ssim;
            }
        }
        s0 = s1; s1 = s2; s2 = s3; s3 = s4; s4 = s5; s5 = s6; s6 = s7; s7 = s8; s8 = s9; s9 = s10;
        s10 = load_row_stats(pixel_at(run, step + 6, false));
        // Row y0 + step - 5 now has its whole coefficient window.
        let output = pixel_at(run, step - 5, false);
        if step >= 5 && output >= 0 {
            let sums = window_coefficients(w, c0, c1, c2, c3, c4, c5, c6, c7, c8, c9, c10);
            let base = u32(output) * SSIM_COEFFICIENT_VEC4S_PER_PIXEL;
            ssim_coefficients[base] = vec4<f32>(sums.a, sums.b.x);
            ssim_coefficients[base + 1u] = vec4<f32>(sums.b.yz, sums.c.xy);
            ssim_coefficients[base + 2u] = vec4<f32>(sums.c.z, 0.0, 0.0, 0.0);
        }
    }
    loss_partials[run_index] =
        vec4<f32>(0.0, loss_params.w_ssim * ssim_term * loss_params.rgb_normaliser, 0.0, 0.0);
}

@compute @workgroup_size(LOSS_WORKGROUP_SIZE)
fn loss_rows(
    @builtin(workgroup_id) workgroup_id: vec3<u32>,
    @builtin(num_workgroups) workgroup_count: vec3<u32>,
    @builtin(local_invocation_index) local_index: u32,
) {
    let run_index = linear_workgroup(workgroup_id, workgroup_count) * LOSS_WORKGROUP_SIZE + local_index;
    let run = run_of(workgroup_id, workgroup_count, local_index, true);
    if !run.valid {
        return;
    }
    let w = window_weights();
    var s0 = load_coefficients(pixel_at(run, -5, true));
    var s1 = load_coefficients(pixel_at(run, -4, true));
    var s2 = load_coefficients(pixel_at(run, -3, true));
    var s3 = load_coefficients(pixel_at(run, -2, true));
    var s4 = load_coefficients(pixel_at(run, -1, true));
    var s5 = load_coefficients(pixel_at(run, 0, true));
    var s6 = load_coefficients(pixel_at(run, 1, true));
    var s7 = load_coefficients(pixel_at(run, 2, true));
    var s8 = load_coefficients(pixel_at(run, 3, true));
    var s9 = load_coefficients(pixel_at(run, 4, true));
    var s10 = load_coefficients(pixel_at(run, 5, true));
    let l1_scale = loss_params.w_l1 * loss_params.rgb_normaliser;
    let depth_scale = loss_params.w_depth * loss_params.inverse_depth_truncation * loss_params.depth_normaliser;
    var l1_term = 0.0;
    var depth_term = 0.0;
    for (var step = 0; step < i32(LOSS_RUN); step++) {
        let pixel = pixel_at(run, step, true);
        if pixel < 0 {
            break;
        }
        let sums = window_coefficients(w, s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10);
        let x = rendered[pixel];
        let y = target_rgbd[pixel];
        var v_rgb = x.xyz * sums.b + y.xyz * sums.c + sums.a;
        for (var c = 0u; c < 3u; c++) {
            v_rgb[c] += l1_scale * sign_or_zero(x[c] - y[c]);
        }
        l1_term += dot(abs(x.xyz - y.xyz), vec3<f32>(1.0));
        var v_depth = 0.0;
        if y.w > 0.0 {
            v_depth = depth_scale * sign_or_zero(x.w - y.w);
            depth_term += abs(x.w - y.w) * loss_params.inverse_depth_truncation;
        }
        v_rgbd[pixel] = vec4<f32>(v_rgb, v_depth);
        v_alpha[pixel] = 0.0;
        s0 = s1; s1 = s2; s2 = s3; s3 = s4; s4 = s5; s5 = s6; s6 = s7; s7 = s8; s8 = s9; s9 = s10;
        s10 = load_coefficients(pixel_at(run, step + 6, true));
    }
    loss_partials[loss_params.column_run_count + run_index] = vec4<f32>(
        loss_params.w_l1 * l1_term * loss_params.rgb_normaliser,
        0.0,
        loss_params.w_depth * depth_term * loss_params.depth_normaliser,
        0.0,
    );
}
