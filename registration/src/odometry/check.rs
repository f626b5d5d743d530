//! Divergence detection (docs/method.md, One agent: Tracking, "Checks"): is a tracked pose right?
//!
//! G-ICP reports success whenever enough of the frame's points found a map point within the
//! correspondence distance. That says nothing about a pose that slid along a surface: with the
//! camera several centimetres from where the prediction put it, the frame's points still lie
//! within 2 cm of *some* surface of a kitchen (counter, cabinet fronts, the floor), G-ICP
//! converges there, and tracking diverges without a single failure. What a wrong pose cannot
//! hide is free space: placed wrongly, the map's surfaces show up where the frame's depth image
//! sees through to something farther away. So the check moves a sample of the map's points in
//! the frame's view into the camera at the estimated pose and compares each with the measured
//! depth at its pixel (the keyframe alignment's depth test, registration/src/alignment):
//! - *agreeing*: within `depth_tolerance_m + depth_tolerance_fraction * depth` of it;
//! - *violating*: clearly in front of it: the camera sees through where the map has a surface;
//! - *occluded*: behind it (hidden by something nearer, or not seen from here): no evidence.
//!
//! The frame's *confidence* is the agreement `agreeing / (agreeing + violating)`; below
//! `min_depth_agreement`, or with too few decisive comparisons while the map has points in view,
//! the pose is flagged as diverged. A right pose scores near 1 on every sequence measured (depth
//! noise and moving objects take a few percent); a pose a few centimetres off, far less.

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::Isometry3;
use serde::Serialize;

use crate::alignment::verification::{DepthComparison, DepthTolerance, compare_depth_within};
use crate::config::TrackingConfig;
use crate::gicp::RegistrationResult;
use crate::voxel_map::VoxelMap;

/// What the check measured of one pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameCheck {
    /// Map points moved into the frame and compared with its depth: those within the depth
    /// tolerance of the measured depth at their pixel.
    pub agreeing: usize,
    /// Map points clearly in front of the measured depth (the camera sees through them).
    pub violating: usize,
    /// Map points behind the measured depth (hidden or not seen from here: no evidence).
    pub occluded: usize,
    /// `agreeing / (agreeing + violating)`; 0 without decisive comparisons.
    pub agreement: f64,
    /// Fraction of the frame's points with a map point within the correspondence distance.
    pub inlier_fraction: f64,
    /// Fraction of the frame's points with a map point within the keyframe overlap distance.
    pub overlap_fraction: f64,
}

/// Why a pose was judged wrong.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum Divergence {
    /// Too small a fraction of the decisive comparisons agree: the map shows surfaces where
    /// the frame sees free space.
    #[error(
        "the map disagrees with the frame's depth: {agreement:.3} of {decisive} map points agree, \
         at least {required:.3} needed"
    )]
    FreeSpaceViolated {
        /// `agreeing / (agreeing + violating)`.
        agreement: f64,
        /// Agreeing plus violating comparisons.
        decisive: usize,
        /// `tracking.min_depth_agreement`.
        required: f64,
    },
    /// Too few map points could be compared with the frame's depth (agreeing or violating) to
    /// judge the pose.
    #[error(
        "{decisive} map points could be compared with the frame's depth, at least {required} needed"
    )]
    TooFewComparisons {
        /// Agreeing plus violating comparisons.
        decisive: usize,
        /// `tracking.min_depth_comparisons`.
        required: usize,
    },
}

impl FrameCheck {
    /// Measures `result`'s pose (`world_from_camera`) against `map`'s points in the selected view
    /// (every n-th, about `tracking.check_points` of them).
    pub fn measure(
        map: &VoxelMap,
        result: &RegistrationResult,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        tracking: &TrackingConfig,
    ) -> Self {
        let sample = map.sample_view(tracking.check_points);
        Self::of_points(
            &sample,
            &result.target_from_source,
            depth,
            intrinsics,
            tracking,
        )
        .with_registration(result)
    }

    /// The depth comparison of world-frame `points` seen from `world_from_camera`.
    pub fn of_points(
        points: &[nalgebra::Point3<f32>],
        world_from_camera: &Isometry3<f64>,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        tracking: &TrackingConfig,
    ) -> Self {
        let comparison = compare_depth_within(
            points,
            &world_from_camera.inverse(),
            depth,
            intrinsics,
            &DepthTolerance {
                metres: tracking.depth_tolerance_m,
                fraction: tracking.depth_tolerance_fraction,
                truncation_m: tracking.truncation_m,
                pixel_radius: tracking.depth_check_pixel_radius,
            },
        );
        Self::from_comparison(comparison)
    }

    fn from_comparison(c: DepthComparison) -> Self {
        Self {
            agreeing: c.agreeing,
            violating: c.violating,
            occluded: c.occluded,
            agreement: c.agreement(),
            inlier_fraction: 0.0,
            overlap_fraction: 0.0,
        }
    }

    fn with_registration(self, result: &RegistrationResult) -> Self {
        Self {
            inlier_fraction: result.inlier_fraction(),
            overlap_fraction: result.overlap_fraction,
            ..self
        }
    }

    /// Comparisons that count for or against the pose: agreeing plus violating.
    pub fn decisive(&self) -> usize {
        self.agreeing + self.violating
    }

    /// The frame's confidence in [0, 1]: the depth agreement.
    pub fn confidence(&self) -> f64 {
        self.agreement
    }

    /// `Err` when the pose is judged wrong (see the module documentation).
    pub fn verdict(&self, tracking: &TrackingConfig) -> Result<(), Divergence> {
        let decisive = self.decisive();
        if decisive < tracking.min_depth_comparisons {
            return Err(Divergence::TooFewComparisons {
                decisive,
                required: tracking.min_depth_comparisons,
            });
        }
        if self.agreement < tracking.min_depth_agreement {
            return Err(Divergence::FreeSpaceViolated {
                agreement: self.agreement,
                decisive,
                required: tracking.min_depth_agreement,
            });
        }
        Ok(())
    }

    /// Orders two candidate poses of one frame: more of the frame's points on the map first
    /// (G-ICP's own evidence at the fine distance), then the depth agreement.
    pub fn better_than(&self, other: &FrameCheck) -> bool {
        (self.inlier_fraction, self.agreement) > (other.inlier_fraction, other.agreement)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3};

    /// A wall at 2 m facing the camera with a box sticking out of it at 1.5 m in the middle.
    fn scene() -> (DepthImage, Intrinsics, Vec<Point3<f32>>) {
        let k = Intrinsics::new(100.0, 100.0, 49.5, 39.5, 100, 80);
        let mut depth = DepthImage::new(100, 80);
        let mut points = Vec::new();
        for v in 0..80 {
            for u in 0..100 {
                let z = if (35..65).contains(&u) && (25..55).contains(&v) {
                    1.5
                } else {
                    2.0
                };
                depth.data[v * 100 + u] = z as f32;
                if (u + v) % 3 == 0 {
                    points.push(k.back_project(u as f64, v as f64, z).cast::<f32>());
                }
            }
        }
        (depth, k, points)
    }

    #[test]
    fn a_right_pose_agrees_and_a_shifted_one_violates_free_space() {
        let (depth, k, points) = scene();
        let tracking = TrackingConfig::default();
        let right = FrameCheck::of_points(&points, &Isometry3::identity(), &depth, &k, &tracking);
        assert!(right.agreement > 0.99, "{right:?}");
        assert_eq!(right.verdict(&tracking), Ok(()));
        // The camera believed 8 cm to the side: box points near its edge move onto pixels that
        // see the wall behind, and sit in front of it.
        let shifted = Isometry3::from_parts(Translation3::new(0.08, 0.0, 0.0), Default::default());
        let wrong = FrameCheck::of_points(&points, &shifted, &depth, &k, &tracking);
        assert!(wrong.violating > 0, "{wrong:?}");
        assert!(wrong.agreement < right.agreement);
        // Pushed forward by 10 cm, the whole map sits in front of the measured surfaces.
        let forward = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.1), Default::default());
        let wrong = FrameCheck::of_points(&points, &forward, &depth, &k, &tracking);
        assert!(matches!(
            wrong.verdict(&tracking),
            Err(Divergence::FreeSpaceViolated { .. })
        ));
    }

    #[test]
    fn without_comparisons_the_check_refuses() {
        let (depth, k, _) = scene();
        let tracking = TrackingConfig::default();
        let none = FrameCheck::of_points(&[], &Isometry3::identity(), &depth, &k, &tracking);
        assert_eq!(none.confidence(), 0.0);
        assert!(matches!(
            none.verdict(&tracking),
            Err(Divergence::TooFewComparisons { decisive: 0, .. })
        ));
    }
}
