//! Every conversion between the wire types of [`crate::messages`] and the in-memory types the
//! processes compute with, both directions, in one place: poses and nalgebra isometries,
//! intrinsics, keyframe RGB-D images, Gaussian patches. The agent uses the "to the wire" half
//! (building messages in place in shared memory), the consensus the "from the wire" half.
//!
//! The in-memory types come from geometry (camera intrinsics, depth images) and splats (the
//! Gaussian cloud); those crates know nothing of the wire.

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use splats::GaussianCloud;

use crate::messages::{GaussianRecord, Intrinsics as WireIntrinsics, Pose, RgbdPixel};

impl From<&Isometry3<f64>> for Pose {
    fn from(isometry: &Isometry3<f64>) -> Self {
        let t = isometry.translation.vector;
        let q = isometry.rotation.quaternion();
        Pose {
            translation: [t.x, t.y, t.z],
            rotation_wxyz: [q.w, q.i, q.j, q.k],
        }
    }
}

impl Pose {
    /// The isometry this pose describes. The quaternion is renormalised: senders validate it to
    /// unit norm within a tolerance, and geometry downstream wants an exact rotation.
    pub fn to_isometry(&self) -> Isometry3<f64> {
        let [w, x, y, z] = self.rotation_wxyz;
        let [tx, ty, tz] = self.translation;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }
}

impl From<&Intrinsics> for WireIntrinsics {
    fn from(k: &Intrinsics) -> Self {
        WireIntrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            width: k.width,
            height: k.height,
        }
    }
}

impl From<&WireIntrinsics> for Intrinsics {
    fn from(k: &WireIntrinsics) -> Self {
        Intrinsics::new(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    }
}

/// Row-major pixel `i` of a keyframe as an RGB-D wire pixel; invalid or out-of-range depth
/// becomes 0 (invalid). Both images must have the same size.
pub fn rgbd_pixel(rgb: &RgbImage, depth: &DepthImage, i: usize) -> RgbdPixel {
    let colour = &rgb.as_raw()[3 * i..3 * i + 3];
    RgbdPixel::new([colour[0], colour[1], colour[2]], depth.data[i])
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

/// Gaussian `i` of `cloud` as a wire record.
pub fn gaussian_record(cloud: &GaussianCloud, i: usize) -> GaussianRecord {
    GaussianRecord {
        mean: cloud.means[i],
        log_scale: cloud.log_scales[i],
        rotation_wxyz: cloud.quaternions[i],
        opacity_logit: cloud.opacity_logits[i],
        colour: cloud.colours[i],
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn round_trip_keeps_the_transform() {
        let isometry = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.3, -0.2, 1.1));
        let back = Pose::from(&isometry).to_isometry();
        assert!(
            (back.to_homogeneous() - isometry.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
    }

    #[test]
    fn depth_out_of_range_or_invalid_is_sent_as_zero() {
        let rgb = RgbImage::from_pixel(4, 1, image::Rgb([1, 2, 3]));
        let depth = DepthImage {
            width: 4,
            height: 1,
            data: vec![1.2345, f32::NAN, -1.0, 100.0],
        };
        let pixels: Vec<RgbdPixel> = (0..4).map(|i| rgbd_pixel(&rgb, &depth, i)).collect();
        let mm: Vec<u16> = pixels.iter().map(|p| p.depth_mm).collect();
        assert_eq!(mm, vec![1235, 0, 0, 0]);
        assert_eq!(pixels[0].rgb, [1, 2, 3]);
    }
}
