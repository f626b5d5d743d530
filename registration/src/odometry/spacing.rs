//! A second correspondence distance for frames whose points lie far apart.
//!
//! The G-ICP correspondence distance is configured for the point spacing of full-resolution
//! RGB-D frames: at 640x480 with a pixel stride of 4, neighbouring points of a wall 2 m away are
//! about 1.5 cm apart, well inside the 2 cm gate. A low-resolution camera or a large stride
//! spreads the points further apart (160x120 with a stride of 5: about 17 cm at the synthetic
//! room's 4.4 m median depth), so after any motion most of a frame's points have no map point
//! within the gate even at the right pose, and tracking reports too few correspondences on every
//! frame. A point's nearest neighbour in a surface sampled `s` apart lies within `s / sqrt(2)`
//! (the centre of a square of samples). On the first frame the tracker measures the spacing at
//! the median depth (`depth x pixel_stride / focal length`); when `s / sqrt(2)` exceeds the
//! configured distance, a frame that finds too few correspondences at the configured distance is
//! registered again at `s / sqrt(2)`, at most the map's voxel size (the neighbour search's
//! reach). Frames that track at the configured distance are untouched, and so is everything on
//! frames dense enough (redkitchen and TUM at the shipped strides).

use geometry::camera::Intrinsics;

use crate::points::PointCloud;
use crate::voxel_map::VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE;

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

/// The correspondence distance for points `spacing_m` apart, when the configured one is
/// `max_correspondence_m`: the farthest a point lies from its nearest sample, `spacing_m /
/// sqrt(2)`, between the configured distance and the map's voxel size.
pub fn sparse_correspondence_m(spacing_m: f64, max_correspondence_m: f64) -> f64 {
    if !(spacing_m.is_finite() && max_correspondence_m > 0.0) {
        return max_correspondence_m;
    }
    (spacing_m * std::f64::consts::FRAC_1_SQRT_2).clamp(
        max_correspondence_m,
        VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE * max_correspondence_m,
    )
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
    fn dense_frames_keep_the_configured_distance_and_sparse_ones_stay_within_a_voxel() {
        assert_eq!(sparse_correspondence_m(0.015, 0.02), 0.02);
        assert_eq!(sparse_correspondence_m(0.028, 0.02), 0.02);
        assert!((sparse_correspondence_m(0.056, 0.02) - 0.056 / 2f64.sqrt()).abs() < 1e-12);
        assert!((sparse_correspondence_m(0.17, 0.02) - 0.06).abs() < 1e-12);
        assert_eq!(sparse_correspondence_m(f64::NAN, 0.02), 0.02);
    }
}
