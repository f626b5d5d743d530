//! The free-space test of a map registration: the check that catches what the maps' geometry
//! and colours cannot.
//!
//! A depth camera measures more than surfaces: the space between the camera and each measured
//! surface is empty. Two maps laid onto each other wrongly (two rooms, or two walls of one room
//! that look alike, or a room turned by the symmetry of its shape) put each map's surfaces where
//! the other agent's cameras saw through: in front of the surfaces they measured. So each map's
//! points (at most `max_points`, evenly spread), moved by the estimate into every depth view of
//! the other map (its keyframes), are compared with what that view measured (the keyframe
//! alignment's depth test, [`compare_depth`]: agreeing, in front = violating, behind = occluded
//! and neither for nor against), both ways, at pixels off depth edges (a pixel that mixes a
//! foreground rim with the background says nothing about free space). The registration passes
//! when both directions have enough decisive comparisons and each one's agreement (agreeing over
//! decisive) reaches `min_agreement`. Real maps do not agree everywhere at the true transform:
//! depth noise, and each map's own drift, which no rigid transform undoes, leave 7-Scenes maps
//! of the whole sequence (ground-truth poses) at 0.75-0.81 and pairs of 100-frame stretches at
//! 0.86, while the synthetic scene agrees fully (docs/benchmarks.md); a wrong transform lays
//! surfaces into open space (0.24 on the synthetic room, 0.44 for a 7-Scenes pose 10 degrees
//! off).
//!
//! The registration ([`super::register_maps_checked`]) applies it to the result it accepts and
//! uses it to choose between hypotheses that the correspondences and the geometry leave nearly
//! tied; the consensus gives it the agents' keyframes (consensus-server/src/map_links.rs).

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::alignment::AlignmentConfig;
use crate::alignment::verification::DepthComparison;

use super::MapRejection;

/// One depth image of a map (a keyframe), placed in the map's frame.
#[derive(Debug, Clone, Copy)]
pub struct DepthView<'a> {
    /// The keyframe's depth image (metres).
    pub depth: &'a DepthImage,
    /// Its camera.
    pub intrinsics: &'a Intrinsics,
    /// Its pose: maps the camera's coordinates into the map's frame.
    pub map_from_camera: Isometry3<f64>,
}

/// Both maps' depth views and the thresholds of the test.
#[derive(Debug, Clone)]
pub struct FreeSpaceCheck<'a> {
    /// The source map's depth views, in the source map's frame.
    pub source_views: Vec<DepthView<'a>>,
    /// The target map's depth views, in the target map's frame.
    pub target_views: Vec<DepthView<'a>>,
    /// The depth tolerances and the minimum of decisive comparisons (`[consensus.alignment]`).
    pub config: &'a AlignmentConfig,
    /// Each direction's agreement at least (`[consensus.map_registration] min_depth_agreement`).
    pub min_agreement: f64,
    /// Points of each map moved into the other's views, at most.
    pub max_points: usize,
}

/// The test's counts, both ways.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FreeSpace {
    /// The source map's points in the target map's views, summed over the views.
    pub source_in_target: DepthComparison,
    /// The target map's points in the source map's views, summed over the views.
    pub target_in_source: DepthComparison,
}

impl FreeSpace {
    /// The smaller of the two directions' agreements.
    pub fn agreement(&self) -> f64 {
        self.source_in_target
            .agreement()
            .min(self.target_in_source.agreement())
    }

    /// The smaller of the two directions' decisive comparisons.
    pub fn decisive(&self) -> usize {
        self.source_in_target
            .decisive()
            .min(self.target_in_source.decisive())
    }
}

/// At most `max_points` of `points`, evenly spread through the list.
fn spread(points: &[Point3<f32>], max_points: usize) -> Vec<Point3<f32>> {
    let step = points.len().div_ceil(max_points.max(1)).max(1);
    points.iter().step_by(step).copied().collect()
}

/// The measured depth at `(u, v)` when the 3 x 3 pixels around it all hold depths within
/// `tolerance_m` of each other: a depth edge (a foreground object's rim, where a pixel mixes two
/// surfaces and the map's points of the far one lie in front of the near one's measurement, or
/// the reverse) cannot say whether a point lies in free space.
fn smooth_depth(
    depth: &DepthImage,
    u: u32,
    v: u32,
    tolerance_m: f64,
    truncation_m: f64,
) -> Option<f64> {
    if u == 0 || v == 0 || u + 1 >= depth.width || v + 1 >= depth.height {
        return None;
    }
    let centre = f64::from(depth.get(u, v));
    if !(centre > 0.0 && centre < truncation_m) {
        return None;
    }
    for (du, dv) in (0..9).map(|k| (k % 3, k / 3)) {
        let d = f64::from(depth.get(u + du - 1, v + dv - 1));
        if d.is_nan() || d <= 0.0 || (d - centre).abs() > tolerance_m {
            return None;
        }
    }
    Some(centre)
}

/// The keyframe alignment's depth test (agreeing within `depth_tolerance_m +
/// depth_tolerance_fraction * depth`, in front: violating, behind: occluded) of `points` in one
/// view, at pixels off depth edges ([`smooth_depth`]).
fn compare_in_view(
    points: &[Point3<f32>],
    camera_from_points: &Isometry3<f64>,
    view: &DepthView<'_>,
    config: &AlignmentConfig,
) -> DepthComparison {
    let mut comparison = DepthComparison::default();
    for point in points {
        let in_camera = camera_from_points * point.cast::<f64>();
        let Some(pixel) = view.intrinsics.project(&in_camera) else {
            continue;
        };
        if !view.intrinsics.contains(&pixel) {
            continue;
        }
        let (u, v) = (pixel.x.round() as u32, pixel.y.round() as u32);
        let Some(measured) = smooth_depth(
            view.depth,
            u,
            v,
            config.depth_tolerance_m + config.depth_tolerance_fraction * in_camera.z.abs(),
            config.truncation_m,
        ) else {
            continue;
        };
        let tolerance = config.depth_tolerance_m + config.depth_tolerance_fraction * measured;
        let difference = in_camera.z - measured;
        if difference.abs() <= tolerance {
            comparison.agreeing += 1;
        } else if difference < 0.0 {
            comparison.violating += 1;
        } else {
            comparison.occluded += 1;
        }
    }
    comparison
}

/// The depth test of `points` (in the views' map frame after `views_map_from_points`) summed over
/// every view.
fn in_views(
    points: &[Point3<f32>],
    views_map_from_points: &Isometry3<f64>,
    views: &[DepthView<'_>],
    config: &AlignmentConfig,
) -> DepthComparison {
    views
        .par_iter()
        .map(|view| {
            let camera_from_points = view.map_from_camera.inverse() * views_map_from_points;
            compare_in_view(points, &camera_from_points, view, config)
        })
        .reduce(DepthComparison::default, |a, b| DepthComparison {
            agreeing: a.agreeing + b.agreeing,
            violating: a.violating + b.violating,
            occluded: a.occluded + b.occluded,
        })
}

impl FreeSpaceCheck<'_> {
    /// The counts of the source map's `source` points and the target map's `target` points under
    /// `target_from_source`.
    pub fn measure(
        &self,
        source: &[Point3<f32>],
        target: &[Point3<f32>],
        target_from_source: &Isometry3<f64>,
    ) -> FreeSpace {
        let (source, target) = (
            spread(source, self.max_points),
            spread(target, self.max_points),
        );
        let (source_in_target, target_in_source) = rayon::join(
            || in_views(&source, target_from_source, &self.target_views, self.config),
            || {
                in_views(
                    &target,
                    &target_from_source.inverse(),
                    &self.source_views,
                    self.config,
                )
            },
        );
        FreeSpace {
            source_in_target,
            target_in_source,
        }
    }

    /// Passed, or why not (the keyframe alignment's thresholds): refused when either direction
    /// with enough decisive comparisons agrees too little (a wrong pose can leave the other
    /// direction nothing but occluded points), then when either has too few.
    pub fn verdict(&self, free_space: &FreeSpace) -> Result<(), MapRejection> {
        let required = self.config.min_depth_comparisons;
        for direction in [free_space.source_in_target, free_space.target_in_source] {
            if direction.decisive() >= required && direction.agreement() < self.min_agreement {
                return Err(MapRejection::FreeSpaceViolated {
                    agreement: direction.agreement(),
                    required: self.min_agreement,
                });
            }
        }
        let comparisons = free_space.decisive();
        if comparisons < required {
            return Err(MapRejection::TooFewDepthComparisons {
                comparisons,
                required,
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at the origin looking along +z at a wall 2 m away.
    fn wall_view(depth: &mut DepthImage) -> Intrinsics {
        depth.data.fill(2.0);
        Intrinsics::new(50.0, 50.0, 31.5, 23.5, 64, 48)
    }

    #[test]
    fn points_in_front_of_a_measured_wall_violate_it() {
        let mut depth = DepthImage::new(64, 48);
        let intrinsics = wall_view(&mut depth);
        let config = AlignmentConfig::default();
        let view = DepthView {
            depth: &depth,
            intrinsics: &intrinsics,
            map_from_camera: Isometry3::identity(),
        };
        let check = FreeSpaceCheck {
            source_views: vec![view],
            target_views: vec![view],
            config: &config,
            min_agreement: 0.7,
            max_points: 1000,
        };
        // The wall itself, seen by both maps.
        let wall: Vec<Point3<f32>> = (0..600)
            .map(|k| {
                Point3::new(
                    (k % 30) as f32 * 0.03 - 0.45,
                    (k / 30) as f32 * 0.03 - 0.3,
                    2.0,
                )
            })
            .collect();
        let right = check.measure(&wall, &wall, &Isometry3::identity());
        assert_eq!(right.decisive(), 600);
        assert!((right.agreement() - 1.0).abs() < 1e-12);
        assert_eq!(check.verdict(&right), Ok(()));
        // Moved 0.5 m towards the camera: the wall floats in the other camera's free space.
        let wrong = check.measure(&wall, &wall, &Isometry3::translation(0.0, 0.0, -0.5));
        assert_eq!(wrong.source_in_target.violating, 600);
        assert!(matches!(
            check.verdict(&wrong),
            Err(MapRejection::FreeSpaceViolated { .. })
        ));
        // Nothing in view: too few comparisons.
        let away = check.measure(&wall, &wall, &Isometry3::translation(50.0, 0.0, 0.0));
        assert!(matches!(
            check.verdict(&away),
            Err(MapRejection::TooFewDepthComparisons { .. })
        ));
    }
}
