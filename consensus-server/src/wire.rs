//! Received messages turned into the consensus's own types (the agent owns the other direction).

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use render_core::types::GaussianCloud;

use protocol::messages::{GaussianRecord, Intrinsics as WireIntrinsics, RgbdPixel};

pub fn intrinsics(wire: &WireIntrinsics) -> Intrinsics {
    Intrinsics::new(wire.fx, wire.fy, wire.cx, wire.cy, wire.width, wire.height)
}

/// Colour and metric depth (0 = invalid) of a keyframe image; `pixels` is row-major and holds
/// `width * height` entries (the transport checked the count).
pub fn rgbd_images(width: u32, height: u32, pixels: &[RgbdPixel]) -> (RgbImage, DepthImage) {
    let rgb = RgbImage::from_fn(width, height, |x, y| {
        image::Rgb(pixels[(y * width + x) as usize].rgb)
    });
    let mut depth = DepthImage::new(width, height);
    for (metres, pixel) in depth.data.iter_mut().zip(pixels) {
        *metres = pixel.depth_m().unwrap_or(0.0);
    }
    (rgb, depth)
}

/// Gaussian records as a cloud. Records with non-finite values are dropped (a corrupt sender
/// must not poison the merged map); the count dropped is returned.
pub fn gaussian_cloud(records: &[GaussianRecord]) -> (GaussianCloud, usize) {
    let mut cloud = GaussianCloud::default();
    let mut dropped = 0;
    for r in records {
        let values = r
            .mean
            .iter()
            .chain(&r.log_scale)
            .chain(&r.rotation_wxyz)
            .chain(&r.colour)
            .chain(std::iter::once(&r.opacity_logit));
        if values.into_iter().all(|v| v.is_finite()) {
            cloud.means.push(r.mean);
            cloud.log_scales.push(r.log_scale);
            cloud.quaternions.push(r.rotation_wxyz);
            cloud.opacity_logits.push(r.opacity_logit);
            cloud.colours.push(r.colour);
        } else {
            dropped += 1;
        }
    }
    (cloud, dropped)
}
