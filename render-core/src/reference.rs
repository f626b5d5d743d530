//! Scalar CPU reference renderer: the test oracle for the wgpu kernels.
//!
//! Deliberately simple and slow: every pixel walks the full depth-sorted list of projected
//! Gaussians, and all arithmetic is `f64`. It implements exactly the image model of the GPU
//! path (same culling, same 3-sigma tile restriction, same thresholds), so the two can be
//! compared pixel by pixel, and it provides the analytic backward pass that the GPU backward is
//! checked against and that finite differences check here.
//!
//! Image model (docs/method.md, The map), per pixel `p` with splats sorted front to back by camera z
//! (ties broken by Gaussian index):
//! `alpha_i = min(max_alpha, opacity_i * exp(-0.5 d^T conic_i d))`, `d = p - mean2d_i`,
//! splats with `alpha_i < min_alpha` skipped, compositing stops before a splat that would
//! bring the transmittance below `min_transmittance`,
//! `rgb = sum c_i alpha_i T_i`, `depth = sum z_i alpha_i T_i`, `alpha = 1 - T_final`.
//! The 2D covariance is `J W J^T + LOW_PASS_VARIANCE * I` (the standard 3DGS 0.3 low-pass),
//! without 3DGS's clamping of off-screen means in the Jacobian (no clamp: exact gradients).

use crate::types::{
    Camera, GaussianCloud, GaussianGradients, ImageGradients, PoseGradient, RasterConfig,
    RenderMode, RenderOutput, constants, depth_sort_key, rotation_from_quaternion_f64,
};

type Mat3 = [[f64; 3]; 3];

fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            *value = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

fn transpose(a: &Mat3) -> Mat3 {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            *value = a[j][i];
        }
    }
    out
}

fn mat_vec(a: &Mat3, v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// One Gaussian after projection into a camera, with the intermediates its backward needs.
#[derive(Clone, Debug)]
pub struct ProjectedGaussian {
    /// Index into the [`GaussianCloud`].
    pub index: usize,
    /// Camera-space centre.
    pub camera_point: [f64; 3],
    /// Pixel coordinates of the centre.
    pub mean2d: [f64; 2],
    /// Inverse 2D covariance `[a, b, c]` for the matrix `[[a, b], [b, c]]`.
    pub conic: [f64; 3],
    pub opacity: f64,
    pub colour: [f64; 3],
    /// Screen extent in pixels (3 sigma of the largest axis, rounded up).
    pub radius: f64,
    /// Inclusive tile rectangle `[x_min, y_min, x_max, y_max]` the splat is binned into.
    pub tile_rect: [u32; 4],
    rotation: Mat3,
    scales: [f64; 3],
    world_covariance: Mat3,
    camera_covariance: Mat3,
    jacobian: [[f64; 3]; 2],
}

fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Projects Gaussian `index`; `None` when it is culled (invalid values, behind the near
/// plane, degenerate footprint, or no tile overlap).
pub fn project_gaussian(
    cloud: &GaussianCloud,
    index: usize,
    camera: &Camera,
) -> Option<ProjectedGaussian> {
    let mean = cloud.means[index];
    let log_scale = cloud.log_scales[index];
    let quaternion = cloud.quaternions[index];
    let opacity_logit = cloud.opacity_logits[index];
    let colour = cloud.colours[index];
    if !(all_finite(&mean)
        && all_finite(&log_scale)
        && all_finite(&quaternion)
        && opacity_logit.is_finite()
        && all_finite(&colour))
    {
        return None;
    }
    let quaternion_norm_sq: f32 = quaternion.iter().map(|v| v * v).sum();
    if quaternion_norm_sq < constants::MIN_QUATERNION_NORM_SQUARED
        || log_scale.iter().any(|&s| s > constants::MAX_LOG_SCALE)
    {
        return None;
    }
    let camera_rotation = camera.camera_from_world.rotation.map(|r| r.map(f64::from));
    let camera_translation = camera.camera_from_world.translation.map(f64::from);
    let world_mean = mean.map(f64::from);
    let rotated = mat_vec(&camera_rotation, world_mean);
    let camera_point = [0, 1, 2].map(|i| rotated[i] + camera_translation[i]);
    let [x, y, z] = camera_point;
    // NaN-safe: a NaN depth is culled too.
    if z.is_nan() || z < f64::from(constants::NEAR_PLANE) {
        return None;
    }
    // Far off-axis the linearised projection is meaningless (see FRUSTUM_GUARD_BAND). The
    // bounds are the GPU's f32 ones, compared in f32 as the kernel does.
    let [min_u, max_u, min_v, max_v] = crate::gpu::frustum_bounds(camera);
    let (u, v) = ((x / z) as f32, (y / z) as f32);
    if u < min_u || u > max_u || v < min_v || v > max_v {
        return None;
    }
    let rotation = rotation_from_quaternion_f64(quaternion.map(f64::from));
    let scales = log_scale.map(|s| f64::from(s).exp());
    let mut scaled_rotation = rotation;
    for row in scaled_rotation.iter_mut() {
        for (j, value) in row.iter_mut().enumerate() {
            *value *= scales[j];
        }
    }
    let world_covariance = mat_mul(&scaled_rotation, &transpose(&scaled_rotation));
    let camera_covariance = mat_mul(
        &mat_mul(&camera_rotation, &world_covariance),
        &transpose(&camera_rotation),
    );
    let (fx, fy) = (f64::from(camera.fx), f64::from(camera.fy));
    let jacobian = [
        [fx / z, 0.0, -fx * x / (z * z)],
        [0.0, fy / z, -fy * y / (z * z)],
    ];
    let mut cov2d = [[0.0; 2]; 2];
    for (i, row) in cov2d.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            for k in 0..3 {
                for l in 0..3 {
                    sum += jacobian[i][k] * camera_covariance[k][l] * jacobian[j][l];
                }
            }
            *value = sum;
        }
    }
    let low_pass = f64::from(constants::LOW_PASS_VARIANCE);
    let (p, q, r) = (cov2d[0][0] + low_pass, cov2d[0][1], cov2d[1][1] + low_pass);
    let det = p * r - q * q;
    if !(det > 0.0 && det.is_finite()) {
        return None;
    }
    let conic = [r / det, -q / det, p / det];
    let mid = 0.5 * (p + r);
    let largest_eigenvalue = mid + (mid * mid - det).max(0.0).sqrt();
    let radius = (f64::from(constants::SPLAT_EXTENT_SIGMAS) * largest_eigenvalue.sqrt()).ceil();
    let mean2d = [
        fx * x / z + f64::from(camera.cx),
        fy * y / z + f64::from(camera.cy),
    ];
    let tile_rect = tile_rect(mean2d, radius, camera)?;
    Some(ProjectedGaussian {
        index,
        camera_point,
        mean2d,
        conic,
        opacity: sigmoid(f64::from(opacity_logit)),
        colour: colour.map(f64::from),
        radius,
        tile_rect,
        rotation,
        scales,
        world_covariance,
        camera_covariance,
        jacobian,
    })
}

/// Inclusive range of tiles whose pixel centres the box `mean +- radius` can touch.
fn tile_rect(mean2d: [f64; 2], radius: f64, camera: &Camera) -> Option<[u32; 4]> {
    let tile = f64::from(constants::TILE_SIZE);
    let (tiles_x, tiles_y) = camera.tile_counts();
    if !(mean2d[0].is_finite() && mean2d[1].is_finite()) || tiles_x == 0 || tiles_y == 0 {
        return None;
    }
    // Tile t covers pixel centres t*16 ..= t*16 + 15.
    let x_min = ((mean2d[0] - radius - (tile - 1.0)) / tile).ceil().max(0.0);
    let y_min = ((mean2d[1] - radius - (tile - 1.0)) / tile).ceil().max(0.0);
    let x_max = ((mean2d[0] + radius) / tile)
        .floor()
        .min(f64::from(tiles_x - 1));
    let y_max = ((mean2d[1] + radius) / tile)
        .floor()
        .min(f64::from(tiles_y - 1));
    if x_min > x_max || y_min > y_max {
        return None;
    }
    Some([x_min as u32, y_min as u32, x_max as u32, y_max as u32])
}

/// Projects all Gaussians and sorts the survivors front to back (camera z, then index).
pub fn project_and_sort(cloud: &GaussianCloud, camera: &Camera) -> Vec<ProjectedGaussian> {
    let mut projected: Vec<ProjectedGaussian> = (0..cloud.len())
        .filter_map(|i| project_gaussian(cloud, i, camera))
        .collect();
    // The GPU sorts by the same key (and keeps the Gaussian order on ties).
    projected.sort_by_key(|p| (depth_sort_key(p.camera_point[2] as f32), p.index));
    projected
}

/// One splat's contribution at a pixel, kept for the backward pass.
struct Contribution {
    splat: usize,
    alpha: f64,
    /// Transmittance before this splat.
    transmittance: f64,
    gaussian_value: f64,
    /// True when alpha hit `max_splat_alpha` (its gradient w.r.t. opacity and footprint is 0).
    clamped: bool,
    offset: [f64; 2],
}

struct PixelResult {
    rgb: [f64; 3],
    depth: f64,
    final_transmittance: f64,
    contributions: Vec<Contribution>,
}

/// A splat evaluated at a pixel centre, where it reaches the pixel.
pub struct SplatAtPixel {
    /// Pixel centre minus the splat's mean.
    pub offset: [f64; 2],
    /// exp(power), before the opacity.
    pub gaussian_value: f64,
    /// opacity x gaussian_value, capped at `max_splat_alpha`.
    pub alpha: f64,
    /// True when the cap applied (no opacity or footprint gradient then).
    pub clamped: bool,
}

/// `splat` at pixel centre `pixel`, as the CPU reference defines it (the device rasterizers
/// match it to a few ulps: they step exp along rows, see `row_gaussian_values` in
/// common.wgsl); `None` where it adds nothing (positive power, or alpha below
/// `min_splat_alpha`).
pub fn splat_at_pixel(
    splat: &ProjectedGaussian,
    pixel: [f64; 2],
    config: &RasterConfig,
) -> Option<SplatAtPixel> {
    let offset = [pixel[0] - splat.mean2d[0], pixel[1] - splat.mean2d[1]];
    let [a, b, c] = splat.conic;
    let power =
        -0.5 * (a * offset[0] * offset[0] + c * offset[1] * offset[1]) - b * offset[0] * offset[1];
    if power > 0.0 {
        return None;
    }
    let gaussian_value = power.exp();
    let raw_alpha = splat.opacity * gaussian_value;
    let max_alpha = f64::from(config.max_splat_alpha);
    let alpha = raw_alpha.min(max_alpha);
    if alpha < f64::from(config.min_splat_alpha) {
        return None;
    }
    Some(SplatAtPixel {
        offset,
        gaussian_value,
        alpha,
        clamped: raw_alpha > max_alpha,
    })
}

fn composite_pixel(
    splats: &[ProjectedGaussian],
    col: u32,
    row: u32,
    config: &RasterConfig,
    keep_contributions: bool,
) -> PixelResult {
    let tile_x = col / constants::TILE_SIZE;
    let tile_y = row / constants::TILE_SIZE;
    let pixel = [f64::from(col), f64::from(row)];
    let mut transmittance = 1.0f64;
    let mut rgb = [0.0f64; 3];
    let mut depth = 0.0f64;
    let mut contributions = Vec::new();
    for (splat_index, splat) in splats.iter().enumerate() {
        let [tx0, ty0, tx1, ty1] = splat.tile_rect;
        if config.restrict_to_tiles
            && !(tile_x >= tx0 && tile_x <= tx1 && tile_y >= ty0 && tile_y <= ty1)
        {
            continue;
        }
        let Some(SplatAtPixel {
            offset,
            gaussian_value,
            alpha,
            clamped,
        }) = splat_at_pixel(splat, pixel, config)
        else {
            continue;
        };
        let next_transmittance = transmittance * (1.0 - alpha);
        if next_transmittance < f64::from(config.min_transmittance) {
            break;
        }
        let weight = alpha * transmittance;
        for (channel, value) in rgb.iter_mut().enumerate() {
            *value += splat.colour[channel] * weight;
        }
        depth += splat.camera_point[2] * weight;
        if keep_contributions {
            contributions.push(Contribution {
                splat: splat_index,
                alpha,
                transmittance,
                gaussian_value,
                clamped,
                offset,
            });
        }
        transmittance = next_transmittance;
    }
    PixelResult {
        rgb,
        depth,
        final_transmittance: transmittance,
        contributions,
    }
}

/// Images in `f64`: (rgb, depth, alpha), row-major.
type ImagesF64 = (Vec<[f64; 3]>, Vec<f64>, Vec<f64>);

fn render_f64(cloud: &GaussianCloud, camera: &Camera, config: &RasterConfig) -> ImagesF64 {
    let splats = project_and_sort(cloud, camera);
    let pixels = camera.pixel_count();
    let mut rgb = Vec::with_capacity(pixels);
    let mut depth = Vec::with_capacity(pixels);
    let mut alpha = Vec::with_capacity(pixels);
    for row in 0..camera.height {
        for col in 0..camera.width {
            let result = composite_pixel(&splats, col, row, config, false);
            rgb.push(result.rgb);
            depth.push(result.depth);
            alpha.push(1.0 - result.final_transmittance);
        }
    }
    (rgb, depth, alpha)
}

/// Renders `cloud` from `camera`.
pub fn render(
    cloud: &GaussianCloud,
    camera: &Camera,
    mode: RenderMode,
    config: &RasterConfig,
) -> RenderOutput {
    let (rgb, depth, alpha) = render_f64(cloud, camera, config);
    RenderOutput {
        width: camera.width,
        height: camera.height,
        rgb: mode
            .has_rgb()
            .then(|| rgb.iter().map(|c| c.map(|v| v as f32)).collect()),
        depth: mode
            .has_depth()
            .then(|| depth.iter().map(|&v| v as f32).collect()),
        alpha: alpha.iter().map(|&v| v as f32).collect(),
    }
}

/// Per-splat gradients w.r.t. the screen-space quantities, accumulated over pixels.
#[derive(Clone, Copy, Default)]
struct ScreenGradient {
    v_mean2d: [f64; 2],
    v_conic: [f64; 3],
    v_opacity: f64,
    v_colour: [f64; 3],
    v_depth: f64,
}

/// Backward pass: gradients of `L` given `dL/d(image)` for every Gaussian parameter and the
/// camera pose (see [`PoseGradient`] for the tangent convention). Images absent from the
/// render mode are simply zero gradients; `image_gradients` vectors may be empty to mean zero.
pub fn render_backward(
    cloud: &GaussianCloud,
    camera: &Camera,
    config: &RasterConfig,
    image_gradients: &ImageGradients,
) -> GaussianGradients {
    let splats = project_and_sort(cloud, camera);
    let mut screen = vec![ScreenGradient::default(); splats.len()];
    let pixel_gradient = |values: &Vec<f32>, i: usize| values.get(i).copied().unwrap_or(0.0);
    for row in 0..camera.height {
        for col in 0..camera.width {
            let pixel_index = (row * camera.width + col) as usize;
            let v_rgb = image_gradients
                .v_rgb
                .get(pixel_index)
                .copied()
                .unwrap_or([0.0; 3])
                .map(f64::from);
            let v_depth = f64::from(pixel_gradient(&image_gradients.v_depth, pixel_index));
            let v_alpha = f64::from(pixel_gradient(&image_gradients.v_alpha, pixel_index));
            let result = composite_pixel(&splats, col, row, config, true);
            backward_pixel(&splats, &result, v_rgb, v_depth, v_alpha, &mut screen);
        }
    }
    let n = cloud.len();
    let mut gradients = GaussianGradients {
        v_means: vec![[0.0; 3]; n],
        v_log_scales: vec![[0.0; 3]; n],
        v_quaternions: vec![[0.0; 4]; n],
        v_opacity_logits: vec![0.0; n],
        v_colours: vec![[0.0; 3]; n],
        v_pose: PoseGradient::default(),
    };
    let mut v_pose = [0.0f64; 6];
    for (splat, screen_gradient) in splats.iter().zip(&screen) {
        project_backward(
            cloud,
            camera,
            splat,
            screen_gradient,
            &mut gradients,
            &mut v_pose,
        );
    }
    gradients.v_pose = PoseGradient {
        v_translation: [v_pose[0] as f32, v_pose[1] as f32, v_pose[2] as f32],
        v_rotation: [v_pose[3] as f32, v_pose[4] as f32, v_pose[5] as f32],
    };
    gradients
}

fn backward_pixel(
    splats: &[ProjectedGaussian],
    result: &PixelResult,
    v_rgb: [f64; 3],
    v_depth: f64,
    v_alpha: f64,
    screen: &mut [ScreenGradient],
) {
    // Colour and depth accumulated by the splats behind the current one (back-to-front walk).
    let mut rgb_behind = [0.0f64; 3];
    let mut depth_behind = 0.0f64;
    for contribution in result.contributions.iter().rev() {
        let splat = &splats[contribution.splat];
        let alpha = contribution.alpha;
        let transmittance = contribution.transmittance;
        let weight = alpha * transmittance;
        let one_minus_alpha = 1.0 - alpha;
        let z = splat.camera_point[2];
        // d(output)/d(alpha_i): own term minus the dimming of everything behind it.
        let mut v_splat_alpha = 0.0;
        for channel in 0..3 {
            v_splat_alpha += v_rgb[channel]
                * (splat.colour[channel] * transmittance - rgb_behind[channel] / one_minus_alpha);
        }
        v_splat_alpha += v_depth * (z * transmittance - depth_behind / one_minus_alpha);
        v_splat_alpha += v_alpha * result.final_transmittance / one_minus_alpha;

        let gradient = &mut screen[contribution.splat];
        for channel in 0..3 {
            gradient.v_colour[channel] += v_rgb[channel] * weight;
            rgb_behind[channel] += splat.colour[channel] * weight;
        }
        gradient.v_depth += v_depth * weight;
        depth_behind += z * weight;
        if contribution.clamped {
            continue;
        }
        gradient.v_opacity += v_splat_alpha * contribution.gaussian_value;
        let v_power = v_splat_alpha * alpha;
        let [dx, dy] = contribution.offset;
        let [a, b, c] = splat.conic;
        gradient.v_conic[0] += v_power * -0.5 * dx * dx;
        gradient.v_conic[1] += v_power * -dx * dy;
        gradient.v_conic[2] += v_power * -0.5 * dy * dy;
        // power depends on the mean through offset = pixel - mean2d.
        gradient.v_mean2d[0] += v_power * (a * dx + b * dy);
        gradient.v_mean2d[1] += v_power * (b * dx + c * dy);
    }
}

/// Chains screen-space gradients of one splat back to its 3D parameters and the pose.
fn project_backward(
    cloud: &GaussianCloud,
    camera: &Camera,
    splat: &ProjectedGaussian,
    screen: &ScreenGradient,
    gradients: &mut GaussianGradients,
    v_pose: &mut [f64; 6],
) {
    let index = splat.index;
    let [x, y, z] = splat.camera_point;
    let (fx, fy) = (f64::from(camera.fx), f64::from(camera.fy));
    let camera_rotation = camera.camera_from_world.rotation.map(|r| r.map(f64::from));

    // Conic K = inverse(cov2d): dL/dcov2d = -K V_K K, with V_K the symmetric matrix gradient
    // (the off-diagonal coefficient b appears twice in K, hence the halving).
    let [a, b, c] = splat.conic;
    let conic = [[a, b], [b, c]];
    let v_conic = [
        [screen.v_conic[0], 0.5 * screen.v_conic[1]],
        [0.5 * screen.v_conic[1], screen.v_conic[2]],
    ];
    let mut v_cov2d = [[0.0f64; 2]; 2];
    for (i, row) in v_cov2d.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            for k in 0..2 {
                for l in 0..2 {
                    sum -= conic[i][k] * v_conic[k][l] * conic[l][j];
                }
            }
            *value = sum;
        }
    }
    // cov2d = J W J^T (+ const): V_W = J^T V J, V_J = 2 V J W.
    let jacobian = &splat.jacobian;
    let w = &splat.camera_covariance;
    let mut v_camera_covariance = [[0.0f64; 3]; 3];
    for (k, row) in v_camera_covariance.iter_mut().enumerate() {
        for (l, value) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            for i in 0..2 {
                for j in 0..2 {
                    sum += jacobian[i][k] * v_cov2d[i][j] * jacobian[j][l];
                }
            }
            *value = sum;
        }
    }
    let mut v_jacobian = [[0.0f64; 3]; 2];
    for (i, row) in v_jacobian.iter_mut().enumerate() {
        for (k, value) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            for j in 0..2 {
                for l in 0..3 {
                    sum += v_cov2d[i][j] * jacobian[j][l] * w[l][k];
                }
            }
            *value = 2.0 * sum;
        }
    }
    let z2 = z * z;
    let z3 = z2 * z;
    let mut v_camera_point = [0.0f64; 3];
    v_camera_point[0] += v_jacobian[0][2] * (-fx / z2);
    v_camera_point[1] += v_jacobian[1][2] * (-fy / z2);
    v_camera_point[2] += v_jacobian[0][0] * (-fx / z2)
        + v_jacobian[0][2] * (2.0 * fx * x / z3)
        + v_jacobian[1][1] * (-fy / z2)
        + v_jacobian[1][2] * (2.0 * fy * y / z3);
    let [v_u, v_v] = screen.v_mean2d;
    v_camera_point[0] += v_u * fx / z;
    v_camera_point[1] += v_v * fy / z;
    v_camera_point[2] += -v_u * fx * x / z2 - v_v * fy * y / z2 + screen.v_depth;

    // camera_point = R_cw mean + t_cw.
    let rotation_t = transpose(&camera_rotation);
    let v_mean = mat_vec(&rotation_t, v_camera_point);
    gradients.v_means[index] = v_mean.map(|v| v as f32);

    // W = R_cw Sigma R_cw^T.
    let v_world_covariance = mat_mul(
        &mat_mul(&rotation_t, &v_camera_covariance),
        &camera_rotation,
    );
    // Sigma = M M^T with M = R S: V_M = 2 V_Sigma M.
    let mut scaled_rotation = splat.rotation;
    for row in scaled_rotation.iter_mut() {
        for (j, value) in row.iter_mut().enumerate() {
            *value *= splat.scales[j];
        }
    }
    let v_scaled_rotation =
        mat_mul(&v_world_covariance, &scaled_rotation).map(|r| r.map(|v| 2.0 * v));
    let mut v_rotation = [[0.0f64; 3]; 3];
    let mut v_log_scale = [0.0f64; 3];
    for i in 0..3 {
        for j in 0..3 {
            v_rotation[i][j] = v_scaled_rotation[i][j] * splat.scales[j];
            v_log_scale[j] += v_scaled_rotation[i][j] * splat.rotation[i][j];
        }
    }
    // d scale / d log_scale = scale.
    gradients.v_log_scales[index] = [0, 1, 2].map(|j| (v_log_scale[j] * splat.scales[j]) as f32);
    gradients.v_quaternions[index] =
        quaternion_backward(cloud.quaternions[index].map(f64::from), &v_rotation).map(|v| v as f32);

    let opacity = splat.opacity;
    gradients.v_opacity_logits[index] = (screen.v_opacity * opacity * (1.0 - opacity)) as f32;
    gradients.v_colours[index] = screen.v_colour.map(|v| v as f32);

    // Pose, left perturbation: d camera_point = rho + phi x camera_point, and
    // d R_cw = [phi]x R_cw inside W (vee of the skew part of V_Rcw R_cw^T).
    let v_phi_point = cross(splat.camera_point, v_camera_point);
    let v_camera_rotation = mat_mul(
        &mat_mul(&v_camera_covariance, &camera_rotation),
        &splat.world_covariance,
    )
    .map(|r| r.map(|v| 2.0 * v));
    let p = mat_mul(&v_camera_rotation, &rotation_t);
    let v_phi_covariance = [p[2][1] - p[1][2], p[0][2] - p[2][0], p[1][0] - p[0][1]];
    for i in 0..3 {
        v_pose[i] += v_camera_point[i];
        v_pose[3 + i] += v_phi_point[i] + v_phi_covariance[i];
    }
}

/// Gradient w.r.t. the raw quaternion `[w, x, y, z]` given dL/dR of the normalised rotation.
fn quaternion_backward(raw: [f64; 4], v_r: &Mat3) -> [f64; 4] {
    let norm = raw.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = raw.map(|v| v / norm);
    let v_w = 2.0
        * (-z * v_r[0][1] + y * v_r[0][2] + z * v_r[1][0] - x * v_r[1][2] - y * v_r[2][0]
            + x * v_r[2][1]);
    let v_x = 2.0
        * (y * v_r[0][1] + z * v_r[0][2] + y * v_r[1][0] - 2.0 * x * v_r[1][1] - w * v_r[1][2]
            + z * v_r[2][0]
            + w * v_r[2][1]
            - 2.0 * x * v_r[2][2]);
    let v_y = 2.0
        * (-2.0 * y * v_r[0][0] + x * v_r[0][1] + w * v_r[0][2] + x * v_r[1][0] + z * v_r[1][2]
            - w * v_r[2][0]
            + z * v_r[2][1]
            - 2.0 * y * v_r[2][2]);
    let v_z = 2.0
        * (-2.0 * z * v_r[0][0] - w * v_r[0][1] + x * v_r[0][2] + w * v_r[1][0]
            - 2.0 * z * v_r[1][1]
            + y * v_r[1][2]
            + x * v_r[2][0]
            + y * v_r[2][1]);
    let v_normalised = [v_w, v_x, v_y, v_z];
    let normalised = [w, x, y, z];
    let radial: f64 = (0..4).map(|i| normalised[i] * v_normalised[i]).sum();
    [0, 1, 2, 3].map(|i| (v_normalised[i] - normalised[i] * radial) / norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::RigidTransform;

    /// A small deterministic pseudo-random generator (keeps the oracle free of dependencies).
    struct Lcg(u64);
    impl Lcg {
        fn uniform(&mut self, low: f32, high: f32) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let unit = (self.0 >> 40) as f32 / (1u64 << 24) as f32;
            low + (high - low) * unit
        }
    }

    fn test_camera(width: u32, height: u32) -> Camera {
        let world_from_camera = RigidTransform::from_quaternion_translation(
            [0.98, 0.05, -0.12, 0.1],
            [0.1, -0.05, -0.2],
        );
        Camera::from_world_from_camera(
            world_from_camera,
            [40.0, 42.0, width as f32 * 0.45, height as f32 * 0.55],
            width,
            height,
        )
    }

    /// Gaussians scattered in front of `camera`, footprints of a few pixels.
    fn test_scene(camera: &Camera, count: usize, seed: u64) -> GaussianCloud {
        let mut rng = Lcg(seed);
        let world_from_camera = camera.world_from_camera();
        let mut cloud = GaussianCloud::default();
        for _ in 0..count {
            let z = rng.uniform(1.5, 3.0);
            let u = rng.uniform(0.0, camera.width as f32);
            let v = rng.uniform(0.0, camera.height as f32);
            let camera_point = [
                (u - camera.cx) * z / camera.fx,
                (v - camera.cy) * z / camera.fy,
                z,
            ];
            cloud.push(
                world_from_camera.transform_point(camera_point),
                [
                    rng.uniform(-2.8, -1.6),
                    rng.uniform(-2.8, -1.6),
                    rng.uniform(-2.8, -1.6),
                ],
                [
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                    rng.uniform(-1.0, 1.0),
                ],
                rng.uniform(-1.0, 1.5),
                [
                    rng.uniform(0.0, 1.0),
                    rng.uniform(0.0, 1.0),
                    rng.uniform(0.0, 1.0),
                ],
            );
        }
        cloud
    }

    struct LinearLoss {
        w_rgb: Vec<[f64; 3]>,
        w_depth: Vec<f64>,
        w_alpha: Vec<f64>,
    }

    impl LinearLoss {
        fn random(pixels: usize, seed: u64) -> Self {
            let mut rng = Lcg(seed);
            let mut sample = || f64::from(rng.uniform(-1.0, 1.0));
            Self {
                w_rgb: (0..pixels)
                    .map(|_| [sample(), sample(), sample()])
                    .collect(),
                w_depth: (0..pixels).map(|_| sample()).collect(),
                w_alpha: (0..pixels).map(|_| sample()).collect(),
            }
        }
        fn evaluate(&self, cloud: &GaussianCloud, camera: &Camera, config: &RasterConfig) -> f64 {
            let (rgb, depth, alpha) = render_f64(cloud, camera, config);
            let mut loss = 0.0;
            for i in 0..rgb.len() {
                loss += (0..3).map(|c| self.w_rgb[i][c] * rgb[i][c]).sum::<f64>()
                    + self.w_depth[i] * depth[i]
                    + self.w_alpha[i] * alpha[i];
            }
            loss
        }
        fn image_gradients(&self) -> ImageGradients {
            ImageGradients {
                v_rgb: self.w_rgb.iter().map(|w| w.map(|v| v as f32)).collect(),
                v_depth: self.w_depth.iter().map(|&v| v as f32).collect(),
                v_alpha: self.w_alpha.iter().map(|&v| v as f32).collect(),
            }
        }
    }

    const STEP: f32 = 1e-3;
    const RELATIVE_TOLERANCE: f64 = 1e-2;
    /// Absolute slack as a fraction of the largest gradient of the same parameter group.
    const GROUP_TOLERANCE: f64 = 2e-3;

    /// Central difference of `loss` in one f32 parameter, using the exactly representable
    /// step actually taken.
    fn central_difference(
        cloud: &GaussianCloud,
        set: impl Fn(&mut GaussianCloud, f32),
        get: impl Fn(&GaussianCloud) -> f32,
        loss: impl Fn(&GaussianCloud) -> f64,
    ) -> f64 {
        let original = get(cloud);
        let mut plus = cloud.clone();
        set(&mut plus, original + STEP);
        let mut minus = cloud.clone();
        set(&mut minus, original - STEP);
        let span = f64::from(get(&plus)) - f64::from(get(&minus));
        (loss(&plus) - loss(&minus)) / span
    }

    fn assert_close(name: &str, analytic: &[f64], numeric: &[f64]) {
        let scale = numeric.iter().fold(1e-6f64, |m, v| m.max(v.abs()));
        assert!(
            scale > 1e-4,
            "{name}: gradients vanish, the test would not test anything"
        );
        for (i, (a, f)) in analytic.iter().zip(numeric).enumerate() {
            let tolerance = RELATIVE_TOLERANCE * f.abs() + GROUP_TOLERANCE * scale;
            assert!(
                (a - f).abs() <= tolerance,
                "{name}[{i}]: analytic {a} vs numeric {f} (tolerance {tolerance})"
            );
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let camera = test_camera(32, 24);
        let cloud = test_scene(&camera, 8, 7);
        let config = RasterConfig::smooth_for_gradient_checks();
        let loss = LinearLoss::random(camera.pixel_count(), 11);
        let gradients = render_backward(&cloud, &camera, &config, &loss.image_gradients());
        let evaluate = |c: &GaussianCloud| loss.evaluate(c, &camera, &config);

        let (mut analytic, mut numeric) = (Vec::new(), Vec::new());
        macro_rules! check_group {
            ($name:expr, $field:ident, $grad:ident, $dims:expr) => {{
                analytic.clear();
                numeric.clear();
                for i in 0..cloud.len() {
                    for d in 0..$dims {
                        numeric.push(central_difference(
                            &cloud,
                            |c, v| c.$field[i][d] = v,
                            |c| c.$field[i][d],
                            evaluate,
                        ));
                        analytic.push(f64::from(gradients.$grad[i][d]));
                    }
                }
                assert_close($name, &analytic, &numeric);
            }};
        }
        check_group!("v_means", means, v_means, 3);
        check_group!("v_log_scales", log_scales, v_log_scales, 3);
        check_group!("v_quaternions", quaternions, v_quaternions, 4);
        check_group!("v_colours", colours, v_colours, 3);
        analytic.clear();
        numeric.clear();
        for i in 0..cloud.len() {
            numeric.push(central_difference(
                &cloud,
                |c, v| c.opacity_logits[i] = v,
                |c| c.opacity_logits[i],
                evaluate,
            ));
            analytic.push(f64::from(gradients.v_opacity_logits[i]));
        }
        assert_close("v_opacity_logits", &analytic, &numeric);

        let pose_step = f64::from(STEP);
        let pose_numeric: Vec<f64> = (0..6)
            .map(|k| {
                let mut xi = [0.0; 6];
                xi[k] = pose_step;
                let mut plus = camera;
                plus.camera_from_world = camera.camera_from_world.left_perturbed(xi);
                xi[k] = -pose_step;
                let mut minus = camera;
                minus.camera_from_world = camera.camera_from_world.left_perturbed(xi);
                (loss.evaluate(&cloud, &plus, &config) - loss.evaluate(&cloud, &minus, &config))
                    / (2.0 * pose_step)
            })
            .collect();
        let pose_analytic: Vec<f64> = gradients
            .v_pose
            .as_array()
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        assert_close("v_pose", &pose_analytic, &pose_numeric);
    }

    #[test]
    fn clamped_and_skipped_splats_get_consistent_gradients() {
        // Default thresholds: a nearly opaque splat (alpha clamped at 0.99) in front of others.
        // Away from the discontinuities the gradients must still match finite differences of
        // the colour and depth (which are smooth in the colour and the mean's z).
        let camera = test_camera(32, 24);
        let mut cloud = test_scene(&camera, 6, 3);
        cloud.opacity_logits[0] = 8.0;
        let config = RasterConfig::default();
        let loss = LinearLoss::random(camera.pixel_count(), 5);
        let gradients = render_backward(&cloud, &camera, &config, &loss.image_gradients());
        let evaluate = |c: &GaussianCloud| loss.evaluate(c, &camera, &config);
        let mut analytic = Vec::new();
        let mut numeric = Vec::new();
        for i in 0..cloud.len() {
            for d in 0..3 {
                numeric.push(central_difference(
                    &cloud,
                    |c, v| c.colours[i][d] = v,
                    |c| c.colours[i][d],
                    evaluate,
                ));
                analytic.push(f64::from(gradients.v_colours[i][d]));
            }
        }
        assert_close("v_colours (default thresholds)", &analytic, &numeric);
    }

    #[test]
    fn depth_is_alpha_weighted_camera_z() {
        // A single large flat splat facing the camera: expected depth = depth / alpha = its z.
        let camera = test_camera(32, 24);
        let point = camera.world_from_camera().transform_point([0.0, 0.0, 2.0]);
        let mut cloud = GaussianCloud::default();
        cloud.push(
            point,
            [0.0, 0.0, -6.0],
            [1.0, 0.0, 0.0, 0.0],
            2.0,
            [0.2, 0.4, 0.6],
        );
        let out = render(&cloud, &camera, RenderMode::RgbD, &RasterConfig::default());
        let centre = (camera.cy.round() as u32 * camera.width + camera.cx.round() as u32) as usize;
        let alpha = out.alpha[centre];
        assert!(alpha > 0.5, "centre alpha {alpha}");
        let depth = out.depth.as_ref().unwrap()[centre];
        let camera_z = project_gaussian(&cloud, 0, &camera).unwrap().camera_point[2] as f32;
        assert!(
            (depth / alpha - camera_z).abs() < 1e-4,
            "expected depth {} vs z {camera_z}",
            depth / alpha
        );
        let rgb = out.rgb.as_ref().unwrap()[centre];
        assert!((rgb[2] / alpha - 0.6).abs() < 1e-5);
    }

    #[test]
    fn principal_point_shifts_the_image() {
        let mut camera = test_camera(32, 24);
        let point = camera.world_from_camera().transform_point([0.0, 0.0, 2.0]);
        let mut cloud = GaussianCloud::default();
        cloud.push(point, [-3.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, [1.0; 3]);
        let brightest = |camera: &Camera| {
            let out = render(&cloud, camera, RenderMode::Rgb, &RasterConfig::default());
            let index = (0..out.alpha.len())
                .max_by(|&a, &b| out.alpha[a].total_cmp(&out.alpha[b]))
                .unwrap();
            (index as u32 % camera.width, index as u32 / camera.width)
        };
        camera.cx = 10.0;
        camera.cy = 7.0;
        assert_eq!(brightest(&camera), (10, 7));
        camera.cx = 20.0;
        camera.cy = 15.0;
        assert_eq!(brightest(&camera), (20, 15));
    }
}
