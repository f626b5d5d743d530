//! Rendering quality of a map (docs/method.md, Metrics): the map rendered at the estimated camera poses of
//! evaluation frames, against the frames' images. PSNR over the whole image, SSIM zero-padded
//! (3DGS style), LPIPS (AlexNet) when weights are given, depth L1 in cm over valid ground-truth
//! pixels (a hole in the render counts its full error).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use alexnet::lpips::Lpips;
use datasets::Frame;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use metrics::depth::depth_l1_cm;
use metrics::image::image_quality;
use nalgebra::Isometry3;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::{DeviceGaussians, GpuRenderer};
use render_core::types::{Camera, RenderMode, RenderOutput};
use serde::Serialize;
use splats::{GaussianCloud, RigidTransform};

/// Pixels whose accumulated opacity is below this get no depth: there the map is mostly empty and
/// depth / alpha would be a guess.
pub const MIN_ALPHA_FOR_DEPTH: f32 = 0.5;

/// A rendered view as images.
pub struct RenderedView {
    /// Rendered colour, clamped to [0, 1] and rounded to 8 bits; black where the map is empty.
    pub rgb: RgbImage,
    /// Expected depth (composited depth / alpha) where alpha >= [`MIN_ALPHA_FOR_DEPTH`], else 0.
    pub depth: DepthImage,
}

impl RenderedView {
    /// Converts a render-core output (colour clamped to [0, 1] and rounded to 8 bits).
    pub fn from_output(output: &RenderOutput) -> Self {
        let (width, height) = (output.width, output.height);
        let rgb = match &output.rgb {
            Some(values) => RgbImage::from_fn(width, height, |x, y| {
                let c = values[(y * width + x) as usize];
                image::Rgb(c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
            }),
            None => RgbImage::new(width, height),
        };
        let data = match &output.depth {
            Some(composited) => composited
                .iter()
                .zip(&output.alpha)
                .map(|(&d, &a)| {
                    if a >= MIN_ALPHA_FOR_DEPTH && d > 0.0 && (d / a).is_finite() {
                        d / a
                    } else {
                        0.0
                    }
                })
                .collect(),
            None => vec![0.0; output.alpha.len()],
        };
        Self {
            rgb,
            depth: DepthImage {
                width,
                height,
                data,
            },
        }
    }
}

/// A map uploaded once and rendered from many poses.
pub struct MapRenderer {
    context: GpuContext,
    renderer: GpuRenderer,
    gaussians: Option<DeviceGaussians>,
    /// Set once a render was reported as cut short by the adapter's loop limit (warned once).
    warned_cut_short: AtomicBool,
}

impl MapRenderer {
    /// Opens a device and uploads `cloud` (nothing for an empty cloud). Fails when no usable
    /// adapter is found or the upload fails.
    pub fn new(cloud: &GaussianCloud) -> Result<Self, GpuError> {
        let context = GpuContext::new()?;
        let renderer = GpuRenderer::new(&context);
        let gaussians = if cloud.is_empty() {
            None
        } else {
            Some(DeviceGaussians::upload(&context, cloud)?)
        };
        Ok(Self {
            context,
            renderer,
            gaussians,
            warned_cut_short: AtomicBool::new(false),
        })
    }

    /// Renders the map from `world_from_camera` with `intrinsics` (full image size). An empty map
    /// renders black with no depth.
    pub fn render(
        &self,
        world_from_camera: &Isometry3<f64>,
        intrinsics: &Intrinsics,
    ) -> Result<RenderedView, GpuError> {
        let camera = Camera::new(RigidTransform::from(world_from_camera), intrinsics);
        let output = match &self.gaussians {
            Some(gaussians) => {
                let output =
                    self.renderer
                        .render(&self.context, gaussians, &camera, RenderMode::RgbD)?;
                if self.renderer.checks_cut_short() > 0
                    && !self.warned_cut_short.swap(true, Ordering::Relaxed)
                {
                    tracing::warn!(
                        gaussians = gaussians.len(),
                        "a tile's splat list is too long for the adapter's loop limit: this \
                         render lacks the rest of it (see render-core/README.md)"
                    );
                }
                output
            }
            None => RenderOutput {
                width: camera.width,
                height: camera.height,
                rgb: Some(vec![[0.0; 3]; camera.pixel_count()]),
                depth: Some(vec![0.0; camera.pixel_count()]),
                alpha: vec![0.0; camera.pixel_count()],
            },
        };
        Ok(RenderedView::from_output(&output))
    }
}

/// Per-frame quality.
#[derive(Debug, Clone, Serialize)]
pub struct FrameQuality {
    /// The frame's number in its sequence ([`Frame::index`]).
    pub frame: usize,
    /// PSNR in dB over the whole 8-bit RGB image, data range 1 (infinite for identical images).
    pub psnr: f64,
    /// SSIM with zero padding, every pixel averaged (the 3DGS convention).
    pub ssim: f64,
    /// LPIPS (AlexNet); `None` without the weights.
    pub lpips: Option<f64>,
    /// Mean |rendered expected depth - measured depth| in cm over valid measured pixels;
    /// `None` when the frame has no valid depth.
    pub depth_l1_cm: Option<f64>,
}

/// Means over the evaluated frames.
#[derive(Debug, Clone, Default, Serialize)]
pub struct QualitySummary {
    /// How many frames were evaluated.
    pub frames: usize,
    /// Mean PSNR in dB over the frames with a finite one; `None` when there is none.
    pub psnr: Option<f64>,
    /// Mean SSIM; `None` without frames.
    pub ssim: Option<f64>,
    /// Mean LPIPS over the frames that have one; `None` when none has.
    pub lpips: Option<f64>,
    /// Mean depth L1 in cm over the frames that have one; `None` when none has.
    pub depth_l1_cm: Option<f64>,
}

impl QualitySummary {
    /// Summarises per-frame figures: each mean skips the frames that lack that figure.
    pub fn of(frames: &[FrameQuality]) -> Self {
        fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
            let (sum, count) = values.fold((0.0, 0usize), |(s, c), v| (s + v, c + 1));
            (count > 0).then(|| sum / count as f64)
        }
        Self {
            frames: frames.len(),
            // Identical images have infinite PSNR; a mean over them would be meaningless.
            psnr: mean(frames.iter().map(|f| f.psnr).filter(|p| p.is_finite())),
            ssim: mean(frames.iter().map(|f| f.ssim)),
            lpips: mean(frames.iter().filter_map(|f| f.lpips)),
            depth_l1_cm: mean(frames.iter().filter_map(|f| f.depth_l1_cm)),
        }
    }
}

/// Evaluates one frame; optionally writes `[ground truth | render]` side by side to `comparison`.
pub fn evaluate_frame(
    renderer: &MapRenderer,
    frame: &Frame,
    world_from_camera: &Isometry3<f64>,
    lpips: Option<&Lpips>,
    comparison: Option<&Path>,
) -> anyhow::Result<FrameQuality> {
    let view = renderer.render(world_from_camera, &frame.intrinsics)?;
    let quality = image_quality(&frame.rgb, &view.rgb)?;
    let lpips = match lpips {
        Some(network) => Some(network.distance(&frame.rgb, &view.rgb)?),
        None => None,
    };
    let depth_l1_cm = depth_l1_cm(&frame.depth, &view.depth)?;
    if let Some(path) = comparison {
        side_by_side(&frame.rgb, &view.rgb)
            .save(path)
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
    }
    Ok(FrameQuality {
        frame: frame.index,
        psnr: quality.psnr,
        ssim: quality.ssim,
        lpips,
        depth_l1_cm,
    })
}

/// `left | right` in one image (same height).
pub fn side_by_side(left: &RgbImage, right: &RgbImage) -> RgbImage {
    let height = left.height().max(right.height());
    RgbImage::from_fn(left.width() + right.width(), height, |x, y| {
        let (image, x) = if x < left.width() {
            (left, x)
        } else {
            (right, x - left.width())
        };
        if y < image.height() {
            *image.get_pixel(x, y)
        } else {
            image::Rgb([0, 0, 0])
        }
    })
}

/// `DIR/renders/frame_NNNNNN.png`.
pub fn comparison_path(dir: &Path, frame: usize) -> PathBuf {
    dir.join(format!("frame_{frame:06}.png"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rendered_view_divides_depth_by_alpha_and_masks_thin_pixels() {
        let output = RenderOutput {
            width: 2,
            height: 1,
            rgb: Some(vec![[1.5, 0.5, -1.0], [0.0; 3]]),
            depth: Some(vec![1.0, 0.1]),
            alpha: vec![0.5, 0.2],
        };
        let view = RenderedView::from_output(&output);
        assert_eq!(view.rgb.get_pixel(0, 0).0, [255, 128, 0]);
        assert_eq!(view.depth.data, vec![2.0, 0.0]);
    }

    #[test]
    fn summary_skips_missing_values() {
        let frames = vec![
            FrameQuality {
                frame: 0,
                psnr: 20.0,
                ssim: 0.5,
                lpips: None,
                depth_l1_cm: Some(2.0),
            },
            FrameQuality {
                frame: 1,
                psnr: 30.0,
                ssim: 0.7,
                lpips: None,
                depth_l1_cm: None,
            },
        ];
        let summary = QualitySummary::of(&frames);
        assert_eq!(summary.psnr, Some(25.0));
        assert!((summary.ssim.unwrap() - 0.6).abs() < 1e-12);
        assert_eq!(summary.lpips, None);
        assert_eq!(summary.depth_l1_cm, Some(2.0));
    }
}
