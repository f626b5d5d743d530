//! Verification scores of a refined keyframe-to-keyframe estimate.
//!
//! - Residual: RMS point-to-plane distance of the source points that have a target point within
//!   the finest correspondence distance. Plane, not point, distance: the clouds sample the
//!   surfaces on different pixel grids, so even a perfect pose leaves point-to-point gaps of up to
//!   half the sampling step along the surface.
//! - Depth agreement: each keyframe's points are projected into the other keyframe's depth image.
//!   A point close to the measured depth agrees; a point clearly in front of it is a free-space
//!   violation (the other camera sees through where the estimate puts a surface); a point behind
//!   it may be occluded and says nothing. Agreement = agreeing / (agreeing + violations), in both
//!   directions, so a pose that merely matches one planar region but contradicts the rest of the
//!   views is refused.

use crate::covariance::smallest_eigenvector;
use crate::{PointTree, RegistrationTarget};
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::{Isometry3, Point3};

use crate::alignment::AlignmentConfig;

/// Projected comparisons of one direction of the depth check.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DepthComparison {
    /// Points within the tolerance of a measured depth around their projection.
    pub agreeing: usize,
    /// Points in front of the other camera's measured surface.
    pub violating: usize,
    /// Points behind it (possibly occluded: neither for nor against).
    pub occluded: usize,
}

impl DepthComparison {
    /// Agreeing over agreeing plus violating; 0 without comparisons.
    pub fn agreement(&self) -> f64 {
        let decisive = self.agreeing + self.violating;
        if decisive == 0 {
            0.0
        } else {
            self.agreeing as f64 / decisive as f64
        }
    }

    /// Comparisons that count for or against the estimate: agreeing plus violating.
    pub fn decisive(&self) -> usize {
        self.agreeing + self.violating
    }
}

/// RMS point-to-plane distance (metres) over the source points with a target point within
/// `max_distance_m` after `target_from_source`, and how many there are.
pub fn point_to_plane_rms(
    source: &PointTree,
    target: &PointTree,
    target_from_source: &Isometry3<f64>,
    max_distance_m: f64,
) -> (f64, usize) {
    let max_distance_sq = (max_distance_m * max_distance_m) as f32;
    let mut sum_sq = 0.0;
    let mut count = 0;
    for position in source.positions() {
        let moved = target_from_source * position.cast::<f64>();
        let Some((index, _)) = target.nearest_within(&moved.cast::<f32>(), max_distance_sq) else {
            continue;
        };
        let normal = smallest_eigenvector(&target.covariance(index).to_matrix());
        let offset = moved - target.position(index).cast::<f64>();
        sum_sq += offset.dot(&normal).powi(2);
        count += 1;
    }
    if count == 0 {
        (f64::INFINITY, 0)
    } else {
        ((sum_sq / count as f64).sqrt(), count)
    }
}

/// When a projected point agrees with a measured depth: within `metres + fraction * depth` of it
/// (depth noise grows with depth), measured depths at or beyond `truncation_m` ignored.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthTolerance {
    /// Fixed part of the tolerance, in metres.
    pub metres: f64,
    /// Part of the tolerance proportional to the measured depth (metres per metre).
    pub fraction: f64,
    /// Measured depths at or beyond this (metres) are not compared.
    pub truncation_m: f64,
    /// Pixels around the projection compared too: a point agrees when any of them agrees, and
    /// violates only when it lies in front of all of them. A point at an object's edge that
    /// lands a pixel off (depth edges are where noise, motion blur and rolling shutter move
    /// the measurement) then does not count as seeing through the object. 0: the pixel only.
    pub pixel_radius: u32,
}

impl DepthTolerance {
    /// The alignment's tolerance (`[consensus.alignment] depth_tolerance_*`, `truncation_m`).
    pub fn of(config: &AlignmentConfig) -> Self {
        Self {
            metres: config.depth_tolerance_m,
            fraction: config.depth_tolerance_fraction,
            truncation_m: config.truncation_m,
            pixel_radius: 0,
        }
    }
}

/// Projects `points` (camera frame of the first view) into the second view (`second_from_first`)
/// and compares with its depth image, with the alignment's tolerance.
pub fn compare_depth(
    points: &[Point3<f32>],
    second_from_first: &Isometry3<f64>,
    second_depth: &DepthImage,
    second_intrinsics: &Intrinsics,
    config: &AlignmentConfig,
) -> DepthComparison {
    compare_depth_within(
        points,
        second_from_first,
        second_depth,
        second_intrinsics,
        &DepthTolerance::of(config),
    )
}

/// [`compare_depth`] with an explicit tolerance.
pub fn compare_depth_within(
    points: &[Point3<f32>],
    second_from_first: &Isometry3<f64>,
    second_depth: &DepthImage,
    second_intrinsics: &Intrinsics,
    tolerance: &DepthTolerance,
) -> DepthComparison {
    let mut comparison = DepthComparison::default();
    let radius = i64::from(tolerance.pixel_radius);
    let (width, height) = (
        i64::from(second_intrinsics.width),
        i64::from(second_intrinsics.height),
    );
    for point in points {
        let in_second = second_from_first * point.cast::<f64>();
        let Some(pixel) = second_intrinsics.project(&in_second) else {
            continue;
        };
        if !second_intrinsics.contains(&pixel) {
            continue;
        }
        let (u, v) = (pixel.x.round() as i64, pixel.y.round() as i64);
        // Over the pixel's neighbourhood: does any measurement agree, and is the point in front
        // of every measurement (a violation)?
        let mut any_measured = false;
        let mut agrees = false;
        let mut in_front_of_all = true;
        for y in (v - radius).max(0)..=(v + radius).min(height - 1) {
            for x in (u - radius).max(0)..=(u + radius).min(width - 1) {
                let measured = second_depth.get(x as u32, y as u32) as f64;
                if !(measured > 0.0 && measured < tolerance.truncation_m) {
                    continue;
                }
                any_measured = true;
                let allowed = tolerance.metres + tolerance.fraction * measured;
                let difference = in_second.z - measured;
                agrees |= difference.abs() <= allowed;
                in_front_of_all &= difference < -allowed;
            }
        }
        if !any_measured {
            continue;
        }
        if agrees {
            comparison.agreeing += 1;
        } else if in_front_of_all {
            comparison.violating += 1;
        } else {
            comparison.occluded += 1;
        }
    }
    comparison
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_comparison_classifies_points() {
        let k = Intrinsics::new(10.0, 10.0, 4.5, 4.5, 10, 10);
        let mut depth = DepthImage::new(10, 10);
        depth.data.fill(2.0);
        let config = AlignmentConfig::default();
        let points = [
            Point3::new(0.0, 0.0, 2.01), // agrees
            Point3::new(0.0, 0.0, 1.5),  // in front: violation
            Point3::new(0.0, 0.0, 3.0),  // behind: occluded
            Point3::new(50.0, 0.0, 2.0), // outside the image
        ];
        let result = compare_depth(&points, &Isometry3::identity(), &depth, &k, &config);
        assert_eq!(
            result,
            DepthComparison {
                agreeing: 1,
                violating: 1,
                occluded: 1
            }
        );
        assert_eq!(result.agreement(), 0.5);
        assert_eq!(DepthComparison::default().agreement(), 0.0);
    }
}
