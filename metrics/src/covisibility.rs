//! Co-visibility of two RGB-D frames with known poses: the fraction of the surface one frame
//! measured that the other frame measured too. It characterises how hard it is to relate two
//! views (keyframe matching needs shared surface; a multi-agent scenario is "wide-baseline" when
//! no cross-agent pair of frames shares much), and is computed from ground truth only.

use nalgebra::Isometry3;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;

/// How two frames' depth must agree for a point to count as seen by both: within
/// `tolerance_m + tolerance_fraction * depth` of the other frame's depth at its pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CovisibilityParams {
    /// Use every n-th pixel of the first frame in both directions.
    pub pixel_stride: u32,
    /// Fixed part of the tolerance, metres (default 0.03).
    pub tolerance_m: f64,
    /// Part of the tolerance proportional to the other frame's measured depth (default 0.02, 2 %).
    pub tolerance_fraction: f64,
}

impl Default for CovisibilityParams {
    fn default() -> Self {
        Self {
            pixel_stride: 4,
            tolerance_m: 0.03,
            tolerance_fraction: 0.02,
        }
    }
}

/// One frame for [`covisibility`]: depth in metres (0 = invalid), intrinsics and pose.
#[derive(Debug, Clone, Copy)]
pub struct PosedDepth<'a> {
    /// Depth image in metres, `0.0` invalid.
    pub depth: &'a DepthImage,
    /// Intrinsics of the depth image.
    pub intrinsics: &'a Intrinsics,
    /// Camera-to-world pose of the frame.
    pub world_from_camera: &'a Isometry3<f64>,
}

/// The fraction of `a`'s valid depth pixels (every `pixel_stride`-th) whose 3-D point lies inside
/// `b`'s image and agrees with `b`'s depth there (seen by `b`, not hidden behind what `b` sees).
/// `None` when `a` has no valid depth. Not symmetric: use the larger of both directions for "how
/// much two frames share".
pub fn covisibility(
    a: PosedDepth<'_>,
    b: PosedDepth<'_>,
    params: &CovisibilityParams,
) -> Option<f64> {
    covisibility_with_any(a, &[b], params)
}

/// The fraction of `a`'s valid depth pixels seen by at least one of `others` (see
/// [`covisibility`]): with the frames of another agent's whole run, how much of what `a` saw
/// that agent's map holds.
pub fn covisibility_with_any(
    a: PosedDepth<'_>,
    others: &[PosedDepth<'_>],
    params: &CovisibilityParams,
) -> Option<f64> {
    let others_from_a: Vec<Isometry3<f64>> = others
        .iter()
        .map(|b| b.world_from_camera.inverse() * a.world_from_camera)
        .collect();
    let stride = params.pixel_stride.max(1) as usize;
    let (mut valid, mut shared) = (0usize, 0usize);
    for v in (0..a.depth.height).step_by(stride) {
        for u in (0..a.depth.width).step_by(stride) {
            let z = a.depth.get(u, v) as f64;
            if !(z > 0.0 && z.is_finite()) {
                continue;
            }
            valid += 1;
            let point = a.intrinsics.back_project(u as f64, v as f64, z);
            if others
                .iter()
                .zip(&others_from_a)
                .any(|(b, b_from_a)| seen_by(b, &(b_from_a * point), params))
            {
                shared += 1;
            }
        }
    }
    (valid > 0).then(|| shared as f64 / valid as f64)
}

/// Whether a point in `b`'s camera frame is inside `b`'s image and agrees with its depth.
fn seen_by(b: &PosedDepth<'_>, in_b: &nalgebra::Point3<f64>, params: &CovisibilityParams) -> bool {
    let Some(pixel) = b.intrinsics.project(in_b) else {
        return false;
    };
    if !b.intrinsics.contains(&pixel) {
        return false;
    }
    let measured = b.depth.get(pixel.x.round() as u32, pixel.y.round() as u32) as f64;
    measured > 0.0
        && (in_b.z - measured).abs() <= params.tolerance_m + params.tolerance_fraction * measured
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall(depth_m: f32) -> DepthImage {
        let mut depth = DepthImage::new(40, 30);
        depth.data.fill(depth_m);
        depth
    }

    #[test]
    fn a_frame_shares_everything_with_itself_and_nothing_with_the_opposite_view() {
        let k = Intrinsics::new(40.0, 40.0, 19.5, 14.5, 40, 30);
        let depth = wall(2.0);
        let here = Isometry3::identity();
        let params = CovisibilityParams::default();
        let same = PosedDepth {
            depth: &depth,
            intrinsics: &k,
            world_from_camera: &here,
        };
        assert_eq!(covisibility(same, same, &params), Some(1.0));
        // Turned around: the wall is behind the second camera.
        let turned = Isometry3::rotation(nalgebra::Vector3::y() * std::f64::consts::PI);
        let opposite = PosedDepth {
            world_from_camera: &turned,
            ..same
        };
        assert_eq!(covisibility(same, opposite, &params), Some(0.0));
        // Shifted sideways by half the wall's width at 2 m: about half is shared.
        let shifted = Isometry3::translation(1.0, 0.0, 0.0);
        let half = covisibility(
            same,
            PosedDepth {
                world_from_camera: &shifted,
                ..same
            },
            &params,
        )
        .unwrap();
        assert!((half - 0.5).abs() < 0.1, "{half}");
        let empty = DepthImage::new(40, 30);
        let nothing = PosedDepth {
            depth: &empty,
            ..same
        };
        assert_eq!(covisibility(nothing, same, &params), None);
    }
}
