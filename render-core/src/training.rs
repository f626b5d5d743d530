//! Image losses (L1, SSIM, depth L1) with gradients, and Adam, on the device; plus the CPU
//! reference of the loss used as the test oracle.
//!
//! Loss (docs/method.md, One agent: Map optimisation; the consensus's joint refinement uses the
//! same loss):
//! `w_l1 * mean|rgb - target| + w_ssim * (1 - mean SSIM) + w_depth * mean_valid |d - d*| / truncation`
//! where rgb and d are the rendered (alpha-composited) colour and depth, the means run over
//! pixels and channels, and the depth mean over pixels whose target depth is > 0 (the validity
//! mask). SSIM uses an 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2, and ZERO
//! padding at the image border (the 3DGS convention: windows are not renormalised).

use crate::backward::{DeviceGradients, DeviceImageGradients};
use crate::context::{GpuContext, GpuError};
use crate::gaussians::{PARAMETER_GROUP_WIDTHS, PARAMETER_GROUPS};
use crate::gpu::{DeviceFrame, DeviceGaussians, GpuRenderer, LayoutId};
use crate::passes::{U32_BYTES, VEC4_BYTES, bind_group, compute_pipeline, dispatch_linear};
use crate::types::{Camera, GaussianCloud, ImageGradients, RenderOutput};
use crate::wgsl::{
    AdamParams, LOSS_RUN, LOSS_WORKGROUP_SIZE, LossParams, ROW_SUMS_VEC4S_PER_PIXEL,
    SSIM_COEFFICIENT_VEC4S_PER_PIXEL, WORKGROUP_SIZE, source,
};
use bytemuck::Zeroable;
use geometry::ssim;

// SSIM is defined once (geometry::ssim), for the evaluation metric and this loss: the maps are
// optimised for the SSIM they are scored with.
/// SSIM window half-width in pixels: 5, for the 11x11 window.
pub const SSIM_WINDOW_RADIUS: i32 = (ssim::SSIM_WINDOW / 2) as i32;
/// Standard deviation of the SSIM window's Gaussian weights, in pixels (1.5).
pub const SSIM_WINDOW_SIGMA: f64 = ssim::SSIM_SIGMA;
/// SSIM stabiliser of the means' term for data range 1: `C1 = K1^2 = 0.01^2`.
pub const SSIM_C1: f64 = ssim::SSIM_K1 * ssim::SSIM_K1;
/// SSIM stabiliser of the (co)variances' term for data range 1: `C2 = K2^2 = 0.03^2`.
pub const SSIM_C2: f64 = ssim::SSIM_K2 * ssim::SSIM_K2;

/// Loss weights; [`Default`] is the mapping loss (docs/method.md, One agent: Map optimisation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossWeights {
    /// Weight of the colour L1 term, `mean |rgb - target|` over pixels and channels.
    pub l1: f32,
    /// Weight of the SSIM term, `1 - mean SSIM` over pixels and channels.
    pub ssim: f32,
    /// Weight of the depth term, `mean |d - d*| / depth_truncation` over valid-depth pixels.
    pub depth: f32,
    /// Depth errors are divided by this (metres; 12 Replica, 10 7-Scenes).
    pub depth_truncation: f32,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            l1: 0.8,
            ssim: 0.2,
            depth: 2.0,
            depth_truncation: 10.0,
        }
    }
}

/// A ground-truth image. `depth` entries `<= 0` (or a missing depth image) are invalid.
#[derive(Clone, Debug, PartialEq)]
pub struct TargetImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Linear RGB in `[0, 1]` per pixel, row-major, `width * height` entries.
    pub rgb: Vec<[f32; 3]>,
    /// Depth in metres (camera z) per pixel, row-major, `width * height` entries; `None` when
    /// there is no depth image (the depth term is then zero).
    pub depth: Option<Vec<f32>>,
}

impl TargetImage {
    /// A target `factor` x smaller than an 8-bit RGB image (`rgb8`: `width * height * 3` bytes,
    /// row-major) and its depth in metres (`depth_m`, the same size; `<= 0` or non-finite is
    /// invalid). Colour is box-filtered (u8 -> [0, 1]); a depth block averages its valid pixels
    /// and is invalid (0) when none is valid. Partial blocks at the right and bottom edges are
    /// dropped, as a camera whose intrinsics are scaled by `1 / factor` expects. Panics when the
    /// slices do not match the size.
    pub fn downscaled(width: u32, height: u32, rgb8: &[u8], depth_m: &[f32], factor: u32) -> Self {
        let pixels = width as usize * height as usize;
        assert_eq!(
            rgb8.len(),
            pixels * 3,
            "rgb8 holds width * height * 3 bytes"
        );
        assert_eq!(depth_m.len(), pixels, "depth_m holds width * height values");
        let factor = factor.max(1);
        let (out_width, out_height) = (width / factor, height / factor);
        let block = (factor * factor) as f32;
        let mut colours = Vec::with_capacity(out_width as usize * out_height as usize);
        let mut depths = Vec::with_capacity(out_width as usize * out_height as usize);
        for y in 0..out_height {
            for x in 0..out_width {
                let mut sum = [0.0f32; 3];
                let (mut depth_sum, mut depth_count) = (0.0f32, 0u32);
                for dy in 0..factor {
                    for dx in 0..factor {
                        let index = ((y * factor + dy) * width + x * factor + dx) as usize;
                        for (c, total) in sum.iter_mut().enumerate() {
                            *total += f32::from(rgb8[index * 3 + c]);
                        }
                        let d = depth_m[index];
                        if d.is_finite() && d > 0.0 {
                            depth_sum += d;
                            depth_count += 1;
                        }
                    }
                }
                colours.push(sum.map(|s| s / (255.0 * block)));
                depths.push(if depth_count > 0 {
                    depth_sum / depth_count as f32
                } else {
                    0.0
                });
            }
        }
        Self {
            width: out_width,
            height: out_height,
            rgb: colours,
            depth: Some(depths),
        }
    }

    fn valid_depth_count(&self) -> usize {
        self.depth
            .as_ref()
            .map_or(0, |d| d.iter().filter(|&&v| v > 0.0).count())
    }
}

/// CPU reference of the loss and of dL/d(rendered rgb, depth) (alpha gradient is zero).
pub fn reference_image_loss(
    rendered: &RenderOutput,
    target: &TargetImage,
    weights: &LossWeights,
) -> (f64, ImageGradients) {
    let (width, height) = (target.width as usize, target.height as usize);
    let pixels = width * height;
    let rgb = rendered.rgb.as_ref().expect("loss needs the rendered rgb");
    let zero_depth = vec![0.0f32; pixels];
    let depth = rendered.depth.as_ref().unwrap_or(&zero_depth);
    let window = ssim::gaussian_window();
    let radius = SSIM_WINDOW_RADIUS as isize;
    let colour_normaliser = 1.0 / (3.0 * pixels as f64);
    let mut loss = 0.0;
    let mut v_rgb = vec![[0.0f64; 3]; pixels];
    for c in 0..3 {
        let x: Vec<f64> = rgb.iter().map(|v| f64::from(v[c])).collect();
        let y: Vec<f64> = target.rgb.iter().map(|v| f64::from(v[c])).collect();
        // SSIM gradient coefficients per pixel (see loss.wgsl for the derivation).
        let mut coefficients = vec![[0.0f64; 3]; pixels];
        for py in 0..height as isize {
            for px in 0..width as isize {
                let (mut mu_x, mut mu_y, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dy in -radius..=radius {
                    for dx in -radius..=radius {
                        let (qx, qy) = (px + dx, py + dy);
                        if qx < 0 || qy < 0 || qx >= width as isize || qy >= height as isize {
                            continue;
                        }
                        let w = window[(dy + radius) as usize] * window[(dx + radius) as usize];
                        let q = qy as usize * width + qx as usize;
                        mu_x += w * x[q];
                        mu_y += w * y[q];
                        xx += w * x[q] * x[q];
                        yy += w * y[q] * y[q];
                        xy += w * x[q] * y[q];
                    }
                }
                let sigma_xx = xx - mu_x * mu_x;
                let sigma_yy = yy - mu_y * mu_y;
                let sigma_xy = xy - mu_x * mu_y;
                let (n1, n2) = (2.0 * mu_x * mu_y + SSIM_C1, 2.0 * sigma_xy + SSIM_C2);
                let (d1, d2) = (
                    mu_x * mu_x + mu_y * mu_y + SSIM_C1,
                    sigma_xx + sigma_yy + SSIM_C2,
                );
                let ssim = n1 * n2 / (d1 * d2);
                loss += f64::from(weights.ssim) * (1.0 - ssim) * colour_normaliser;
                let v = -f64::from(weights.ssim) * colour_normaliser;
                let d_mu = 2.0 * mu_y * n2 / (d1 * d2) - 2.0 * mu_x * ssim / d1;
                let d_sigma_xx = -ssim / d2;
                let d_sigma_xy = 2.0 * n1 / (d1 * d2);
                let p = py as usize * width + px as usize;
                coefficients[p] = [
                    v * (d_mu - 2.0 * d_sigma_xx * mu_x - d_sigma_xy * mu_y),
                    v * 2.0 * d_sigma_xx,
                    v * d_sigma_xy,
                ];
                let difference = x[p] - y[p];
                loss += f64::from(weights.l1) * difference.abs() * colour_normaliser;
                v_rgb[p][c] += f64::from(weights.l1) * colour_normaliser * sign_or_zero(difference);
            }
        }
        for py in 0..height as isize {
            for px in 0..width as isize {
                let q = py as usize * width + px as usize;
                let mut sums = [0.0f64; 3];
                for dy in -radius..=radius {
                    for dx in -radius..=radius {
                        let (sx, sy) = (px + dx, py + dy);
                        if sx < 0 || sy < 0 || sx >= width as isize || sy >= height as isize {
                            continue;
                        }
                        let w = window[(dy + radius) as usize] * window[(dx + radius) as usize];
                        let p = sy as usize * width + sx as usize;
                        for k in 0..3 {
                            sums[k] += w * coefficients[p][k];
                        }
                    }
                }
                v_rgb[q][c] += x[q] * sums[1] + y[q] * sums[2] + sums[0];
            }
        }
    }
    let mut v_depth = vec![0.0f32; pixels];
    let valid = target.valid_depth_count();
    if let (Some(target_depth), true) = (&target.depth, valid > 0) {
        let scale = f64::from(weights.depth) / (f64::from(weights.depth_truncation) * valid as f64);
        for p in 0..pixels {
            if target_depth[p] > 0.0 {
                let difference = f64::from(depth[p]) - f64::from(target_depth[p]);
                loss += scale * difference.abs();
                v_depth[p] = (scale * sign_or_zero(difference)) as f32;
            }
        }
    }
    let gradients = ImageGradients {
        v_rgb: v_rgb.iter().map(|v| v.map(|g| g as f32)).collect(),
        v_depth,
        v_alpha: vec![0.0; pixels],
    };
    (loss, gradients)
}

fn sign_or_zero(value: f64) -> f64 {
    if value > 0.0 {
        1.0
    } else if value < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// A target image on the device: per pixel (r, g, b, depth), depth 0 where invalid.
pub struct DeviceTarget {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Per pixel, row-major: `vec4<f32>` (r, g, b, depth in metres).
    pub rgbd: wgpu::Buffer,
    /// Number of pixels with valid depth (computed on upload, so no read-back later).
    pub valid_depth_pixels: u32,
}

impl DeviceTarget {
    /// Copies `target` to the device; invalid depths (`<= 0`, NaN, or no depth image) become
    /// 0. Fails with [`GpuError::InvalidInput`] when `rgb` or `depth` does not hold
    /// `width * height` pixels.
    pub fn upload(context: &GpuContext, target: &TargetImage) -> Result<Self, GpuError> {
        let pixels = target.width as usize * target.height as usize;
        if target.rgb.len() != pixels || target.depth.as_ref().is_some_and(|d| d.len() != pixels) {
            return Err(GpuError::InvalidInput(
                "target image sizes do not match width x height".into(),
            ));
        }
        let rgbd: Vec<[f32; 4]> = (0..pixels)
            .map(|p| {
                let [r, g, b] = target.rgb[p];
                let d = target.depth.as_ref().map_or(0.0, |d| d[p]);
                [r, g, b, if d > 0.0 { d } else { 0.0 }]
            })
            .collect();
        Ok(Self {
            width: target.width,
            height: target.height,
            rgbd: context.storage_buffer_init(
                "target rgbd",
                bytemuck::cast_slice(&rgbd),
                VEC4_BYTES as usize,
            ),
            valid_depth_pixels: target.valid_depth_count() as u32,
        })
    }
}

/// The loss kernels' parameters for `camera`'s image: run counts (runs of LOSS_RUN pixels per
/// row and per column), weights, and the normalisers that turn sums into means.
fn loss_params(camera: &Camera, target: &DeviceTarget, weights: &LossWeights) -> LossParams {
    let pixels = camera.pixel_count() as u64;
    let depth_normaliser = if target.valid_depth_pixels > 0 {
        1.0 / target.valid_depth_pixels as f32
    } else {
        0.0
    };
    let runs_per_column = camera.height.div_ceil(LOSS_RUN);
    LossParams {
        width: camera.width,
        height: camera.height,
        runs_per_row: camera.width.div_ceil(LOSS_RUN),
        runs_per_column,
        w_l1: weights.l1,
        w_ssim: weights.ssim,
        w_depth: weights.depth,
        inverse_depth_truncation: 1.0 / weights.depth_truncation,
        rgb_normaliser: 1.0 / (3.0 * pixels as f32),
        depth_normaliser,
        column_run_count: runs_per_column * camera.width,
        ..Zeroable::zeroed()
    }
}

/// A loss evaluated on the device; the value stays there until [`DeviceLoss::read`].
pub struct DeviceLoss {
    /// vec4: (L1 term, SSIM term, depth term, 0), already weighted.
    pub terms: wgpu::Buffer,
}

impl DeviceLoss {
    /// Reads the weighted terms (l1, ssim, depth) back; their sum is the loss.
    pub fn read(&self, context: &GpuContext) -> Result<[f32; 3], GpuError> {
        let terms: Vec<[f32; 4]> = context.read_vec(&self.terms, 1)?;
        Ok([terms[0][0], terms[0][1], terms[0][2]])
    }
}

/// Learning rates per parameter group (a rate of 0 freezes the group) and Adam constants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Learning rate of the means, in metres (an Adam step moves a value by about its rate);
    /// the default is to be multiplied by the scene scale.
    pub means: f32,
    /// Learning rate of the natural-log scales.
    pub log_scales: f32,
    /// Learning rate of the raw quaternions `[w, x, y, z]` (0 by default: rotations frozen).
    pub quaternions: f32,
    /// Learning rate of the opacity logits.
    pub opacity_logits: f32,
    /// Learning rate of the linear RGB colours.
    pub colours: f32,
    /// Decay of the first moment (the gradients' running mean).
    pub beta1: f32,
    /// Decay of the second moment (the squared gradients' running mean).
    pub beta2: f32,
    /// Added to the square root of the bias-corrected second moment before dividing by it.
    pub epsilon: f32,
}

impl Default for AdamConfig {
    /// The mapping rates of docs/method.md, One agent: Map optimisation (the mean rate is to be multiplied by the scene scale).
    fn default() -> Self {
        Self {
            means: 5e-6,
            log_scales: 0.01,
            quaternions: 0.0,
            opacity_logits: 0.05,
            colours: 2.5e-3,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-15,
        }
    }
}

/// Adam moments for every parameter group of one [`DeviceGaussians`].
///
/// The state follows one arrangement of the Gaussians: after an append, prune or retain done
/// on the Gaussians alone, [`TrainingKernels::adam_step`] refuses the stale state. Edit the
/// map through [`crate::map::DeviceMap`], which moves the moments with the Gaussians.
pub struct DeviceAdam {
    /// Learning rates and constants the next steps use (may be changed between steps).
    pub config: AdamConfig,
    step: u32,
    /// (first, second) moments per parameter group, in `PARAMETER_GROUP_WIDTHS` order, each
    /// with room for `capacity` Gaussians.
    pub(crate) moments: [(wgpu::Buffer, wgpu::Buffer); PARAMETER_GROUPS],
    pub(crate) count: u32,
    pub(crate) capacity: u32,
    /// Layout of the Gaussians the moments belong to.
    pub(crate) gaussian_layout: LayoutId,
}

/// First and second Adam moments on the host, each laid out like the parameters it belongs
/// to (e.g. `first.means[i]` is the first moment of Gaussian i's mean).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct AdamMoments {
    /// First moments (running means of the gradients), not bias-corrected.
    pub first: GaussianCloud,
    /// Second moments (running means of the squared gradients), not bias-corrected.
    pub second: GaussianCloud,
}

impl DeviceAdam {
    /// Zero moments for every Gaussian of `gaussians` (step count 0).
    pub fn new(
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        config: AdamConfig,
    ) -> Result<Self, GpuError> {
        Ok(Self {
            config,
            step: 0,
            moments: zero_moments(context, gaussians.capacity)?,
            count: gaussians.count,
            capacity: gaussians.capacity,
            gaussian_layout: gaussians.layout,
        })
    }

    /// Adam steps taken so far (the `t` of the bias correction); 0 for a fresh state.
    pub fn step_count(&self) -> u32 {
        self.step
    }

    /// Number of Gaussians the moments describe.
    pub fn len(&self) -> usize {
        self.count as usize
    }

    /// True when the moments describe no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Copies the moments back to the host (tests, checkpoints).
    pub fn download_moments(&self, context: &GpuContext) -> Result<AdamMoments, GpuError> {
        let n = self.len();
        let read = |moment: usize| -> Result<GaussianCloud, GpuError> {
            let buffer = |group: usize| {
                let (first, second) = &self.moments[group];
                if moment == 0 { first } else { second }
            };
            Ok(GaussianCloud {
                means: context.read_vec(buffer(0), n)?,
                log_scales: context.read_vec(buffer(1), n)?,
                quaternions: context.read_vec(buffer(2), n)?,
                opacity_logits: context.read_vec(buffer(3), n)?,
                colours: context.read_vec(buffer(4), n)?,
            })
        };
        Ok(AdamMoments {
            first: read(0)?,
            second: read(1)?,
        })
    }
}

/// Zeroed (first, second) moment buffers for `capacity` Gaussians.
pub(crate) fn zero_moments(
    context: &GpuContext,
    capacity: u32,
) -> Result<[(wgpu::Buffer, wgpu::Buffer); PARAMETER_GROUPS], GpuError> {
    let make = |width: u32| -> Result<(wgpu::Buffer, wgpu::Buffer), GpuError> {
        let bytes = u64::from(capacity) * u64::from(width) * U32_BYTES;
        Ok((
            context.storage_buffer("adam m", bytes)?,
            context.storage_buffer("adam v", bytes)?,
        ))
    };
    Ok([
        make(PARAMETER_GROUP_WIDTHS[0])?,
        make(PARAMETER_GROUP_WIDTHS[1])?,
        make(PARAMETER_GROUP_WIDTHS[2])?,
        make(PARAMETER_GROUP_WIDTHS[3])?,
        make(PARAMETER_GROUP_WIDTHS[4])?,
    ])
}

/// Compiled loss and Adam kernels.
pub struct TrainingKernels {
    ssim_rows: wgpu::ComputePipeline,
    ssim_columns: wgpu::ComputePipeline,
    loss_rows: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    adam_tail: wgpu::ComputePipeline,
}

impl TrainingKernels {
    /// Compiles the loss (SSIM rows and columns, per-pixel loss) and Adam kernels for
    /// `context`.
    pub fn new(context: &GpuContext) -> Self {
        let device = &context.device;
        Self {
            ssim_rows: compute_pipeline(device, "ssim_rows", &[source::LOSS], "ssim_rows"),
            ssim_columns: compute_pipeline(device, "ssim_columns", &[source::LOSS], "ssim_columns"),
            loss_rows: compute_pipeline(device, "loss_rows", &[source::LOSS], "loss_rows"),
            adam: compute_pipeline(device, "adam", &[source::ADAM], "main"),
            adam_tail: compute_pipeline(device, "adam tail", &[source::ADAM], "tail"),
        }
    }

    /// Evaluates the loss of `frame` against `target` and writes dL/d(image) into
    /// `image_gradients`. Submits work; reads nothing back.
    pub fn image_loss(
        &self,
        context: &GpuContext,
        renderer: &GpuRenderer,
        frame: &DeviceFrame,
        target: &DeviceTarget,
        weights: &LossWeights,
        image_gradients: &DeviceImageGradients,
    ) -> Result<DeviceLoss, GpuError> {
        let camera: &Camera = &frame.camera;
        if (target.width, target.height) != (camera.width, camera.height)
            || (image_gradients.width, image_gradients.height) != (camera.width, camera.height)
        {
            return Err(GpuError::InvalidInput(
                "target, gradients and frame differ in size".into(),
            ));
        }
        let pixels = camera.pixel_count() as u64;
        let params = loss_params(camera, target, weights);
        let row_runs = params.runs_per_row * camera.height;
        let column_runs = params.column_run_count;
        let params_buffer = context.uniform_buffer("loss params", bytemuck::bytes_of(&params));
        let coefficients = context.storage_buffer(
            "ssim coefficients",
            pixels * u64::from(SSIM_COEFFICIENT_VEC4S_PER_PIXEL) * VEC4_BYTES,
        )?;
        let partial_count = column_runs + row_runs;
        let loss_partials =
            context.storage_buffer("loss partials", u64::from(partial_count) * VEC4_BYTES)?;
        let row_sums = context.storage_buffer(
            "ssim row sums",
            pixels * u64::from(ROW_SUMS_VEC4S_PER_PIXEL) * VEC4_BYTES,
        )?;
        let mut encoder = context.device.create_command_encoder(&Default::default());
        let ssim_rows_group = bind_group(
            context,
            &self.ssim_rows,
            &[
                (0, &params_buffer),
                (1, &frame.rgbd),
                (2, &target.rgbd),
                (7, &row_sums),
            ],
        );
        let columns_group = bind_group(
            context,
            &self.ssim_columns,
            &[
                (0, &params_buffer),
                (3, &coefficients),
                (4, &loss_partials),
                (7, &row_sums),
            ],
        );
        let rows_group = bind_group(
            context,
            &self.loss_rows,
            &[
                (0, &params_buffer),
                (1, &frame.rgbd),
                (2, &target.rgbd),
                (3, &coefficients),
                (4, &loss_partials),
                (5, &image_gradients.v_rgbd),
                (6, &image_gradients.v_alpha),
            ],
        );
        for (pipeline, group, runs) in [
            (&self.ssim_rows, &ssim_rows_group, row_runs),
            (&self.ssim_columns, &columns_group, column_runs),
            (&self.loss_rows, &rows_group, row_runs),
        ] {
            dispatch_linear(
                &mut encoder,
                pipeline,
                group,
                runs.div_ceil(LOSS_WORKGROUP_SIZE),
            );
        }
        let terms = renderer.reduce_vec4(context, &mut encoder, loss_partials, partial_count)?;
        context.queue.submit([encoder.finish()]);
        Ok(DeviceLoss { terms })
    }

    /// One Adam step on every group with a non-zero learning rate, over every Gaussian (plain
    /// Adam: one the frame did not see still moves by its momentum). Not a "selective" step over
    /// the Gaussians in view only: it is slightly cheaper but mapped measurably worse (see
    /// docs/benchmarks.md): with so few iterations per keyframe the momentum carries the
    /// Gaussians on in the right direction. Submits work; reads nothing back.
    pub fn adam_step(
        &self,
        context: &GpuContext,
        adam: &mut DeviceAdam,
        gaussians: &DeviceGaussians,
        gradients: &DeviceGradients,
    ) -> Result<(), GpuError> {
        if adam.gaussian_layout != gaussians.layout || gaussians.count != adam.count {
            return Err(GpuError::InvalidInput(
                "the Adam state does not follow the Gaussians (appended to, pruned or retained \
                 without it): edit the map through DeviceMap"
                    .into(),
            ));
        }
        if gradients.gaussian_layout != gaussians.layout {
            return Err(GpuError::InvalidInput(
                "the gradients belong to an earlier arrangement of the Gaussians".into(),
            ));
        }
        adam.step += 1;
        let config = adam.config;
        let t = adam.step as i32;
        let bias_correction1 = 1.0 / (1.0 - config.beta1.powi(t));
        let bias_correction2 = 1.0 / (1.0 - config.beta2.powi(t));
        let groups = [
            (config.means, &gaussians.means, &gradients.v_means),
            (
                config.log_scales,
                &gaussians.log_scales,
                &gradients.v_log_scales,
            ),
            (
                config.quaternions,
                &gaussians.quaternions,
                &gradients.v_quaternions,
            ),
            (
                config.opacity_logits,
                &gaussians.opacity_logits,
                &gradients.v_opacity_logits,
            ),
            (config.colours, &gaussians.colours, &gradients.v_colours),
        ];
        let mut encoder = context.device.create_command_encoder(&Default::default());
        for (group, (learning_rate, parameters, group_gradients)) in groups.into_iter().enumerate()
        {
            let elements = adam.count * PARAMETER_GROUP_WIDTHS[group];
            if learning_rate == 0.0 || elements == 0 {
                continue;
            }
            let params = AdamParams {
                count: elements,
                learning_rate,
                beta1: config.beta1,
                beta2: config.beta2,
                epsilon: config.epsilon,
                bias_correction1,
                bias_correction2,
                ..Zeroable::zeroed()
            };
            let params_buffer = context.uniform_buffer("adam params", bytemuck::bytes_of(&params));
            let (m, v) = &adam.moments[group];
            // adam.wgsl: vectors of 4 elements, then the last elements % 4 one by one.
            let vectors = elements / 4;
            if vectors > 0 {
                let bind = bind_group(
                    context,
                    &self.adam,
                    &[
                        (0, &params_buffer),
                        (1, parameters),
                        (2, group_gradients),
                        (3, m),
                        (4, v),
                    ],
                );
                dispatch_linear(
                    &mut encoder,
                    &self.adam,
                    &bind,
                    vectors.div_ceil(WORKGROUP_SIZE),
                );
            }
            if !elements.is_multiple_of(4) {
                let bind = bind_group(
                    context,
                    &self.adam_tail,
                    &[
                        (0, &params_buffer),
                        (5, parameters),
                        (6, group_gradients),
                        (7, m),
                        (8, v),
                    ],
                );
                dispatch_linear(&mut encoder, &self.adam_tail, &bind, 1);
            }
        }
        context.queue.submit([encoder.finish()]);
        Ok(())
    }
}
