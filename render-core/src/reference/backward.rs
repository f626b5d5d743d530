//! The reference's analytic backward pass: per-pixel compositing gradients, then through the
//! projection to every Gaussian parameter and the camera pose.

use crate::types::{
    Camera, GaussianCloud, GaussianGradients, ImageGradients, PoseGradient, RasterConfig,
};

use super::{
    Mat3, PixelResult, ProjectedGaussian, composite_pixel, cross, mat_mul, mat_vec,
    project_and_sort, transpose,
};

/// Per-splat gradients w.r.t. the screen-space quantities, accumulated over pixels.
#[derive(Clone, Copy, Default)]
pub(super) struct ScreenGradient {
    pub(super) v_mean2d: [f64; 2],
    pub(super) v_conic: [f64; 3],
    pub(super) v_opacity: f64,
    pub(super) v_colour: [f64; 3],
    pub(super) v_depth: f64,
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

pub(super) fn backward_pixel(
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
pub(super) fn project_backward(
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
pub(super) fn quaternion_backward(raw: [f64; 4], v_r: &Mat3) -> [f64; 4] {
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
