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
//!
//! This file holds the forward pass (projection, sorting, compositing); `backward.rs` the
//! analytic backward pass.

use crate::types::{
    Camera, GaussianCloud, RasterConfig, RenderMode, RenderOutput, constants, depth_sort_key,
    rotation_from_quaternion_f64,
};

mod backward;
#[cfg(test)]
mod tests;

pub use backward::render_backward;

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
    /// Opacity in `[0, 1]`: the sigmoid of the opacity logit.
    pub opacity: f64,
    /// Linear RGB colour, as in the [`GaussianCloud`].
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
