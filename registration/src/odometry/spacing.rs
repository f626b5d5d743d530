//! A correspondence distance that follows the frame's point spacing.
//!
//! The G-ICP correspondence distance is configured for the point spacing of full-resolution
//! RGB-D frames: at 640x480 with a pixel stride of 4, neighbouring points of a wall 2 m away are
//! about 1.5 cm apart, well inside the 2 cm gate. A low-resolution camera or a large stride
//! spreads the points further apart (160x120 with a stride of 5: about 8 cm at 2 m), so after any
//! motion most of a frame's points have no map point within the gate even at the right pose, and
//! tracking reports too few correspondences on every frame. A point's nearest neighbour in a map
//! sampled `s` apart lies within `s / sqrt(2)` (the centre of a square of samples), so on the
//! first frame the tracker measures the spacing at the median depth (`depth x pixel_stride /
//! focal length`) and widens the gate to `s / sqrt(2)` when that is larger. The keyframe
//! distances (overlap, trackable-new) keep their configured values: they decide how much of the
//! scene a keyframe must add, which the sampling does not change. Frames whose points are dense
//! enough keep the configuration exactly as it is.

use geometry::camera::Intrinsics;

use crate::points::PointCloud;

/// How far apart neighbouring points of `cloud` are at its median depth (metres), for points
/// back-projected every `pixel_stride` pixels through `intrinsics`; `None` for an empty cloud.
pub fn median_point_spacing_m(
    cloud: &PointCloud,
    intrinsics: &Intrinsics,
    pixel_stride: usize,
) -> Option<f64> {
    let mut depths: Vec<f32> = cloud
        .positions
        .iter()
        .map(|p| p.z)
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    if depths.is_empty() {
        return None;
    }
    let middle = depths.len() / 2;
    let (_, median, _) = depths.select_nth_unstable_by(middle, f32::total_cmp);
    let focal = intrinsics.fx.min(intrinsics.fy);
    (focal > 0.0).then(|| f64::from(*median) * pixel_stride.max(1) as f64 / focal)
}

/// The factor (>= 1) the correspondence distance `max_correspondence_m` is widened by for points
/// `spacing_m` apart: to the farthest a point lies from its nearest sample, `spacing_m / sqrt(2)`.
pub fn distance_scale(spacing_m: f64, max_correspondence_m: f64) -> f64 {
    if max_correspondence_m > 0.0 && spacing_m.is_finite() {
        (spacing_m * std::f64::consts::FRAC_1_SQRT_2 / max_correspondence_m).max(1.0)
    } else {
        1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn intrinsics(fx: f64) -> Intrinsics {
        Intrinsics {
            fx,
            fy: fx,
            cx: 80.0,
            cy: 60.0,
            width: 160,
            height: 120,
        }
    }

    #[test]
    fn spacing_is_the_median_depth_times_the_stride_over_the_focal_length() {
        let cloud = PointCloud::from_positions(
            [1.0, 2.0, 2.0, 3.0, 10.0]
                .iter()
                .map(|&z| Point3::new(0.0, 0.0, z))
                .collect(),
        );
        let spacing = median_point_spacing_m(&cloud, &intrinsics(125.0), 5).unwrap();
        assert!((spacing - 0.08).abs() < 1e-9, "{spacing}");
        assert_eq!(
            median_point_spacing_m(&PointCloud::from_positions(Vec::new()), &intrinsics(1.0), 1),
            None
        );
    }

    #[test]
    fn dense_frames_keep_the_configured_distances() {
        assert_eq!(distance_scale(0.015, 0.02), 1.0);
        assert_eq!(distance_scale(0.028, 0.02), 1.0);
        assert!((distance_scale(0.08, 0.02) - 4.0 / 2f64.sqrt()).abs() < 1e-12);
        assert_eq!(distance_scale(f64::NAN, 0.02), 1.0);
    }
}
