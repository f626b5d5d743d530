//! Coarse-to-fine G-ICP (one run per correspondence distance, largest first) and the cheap
//! correspondence count that chooses between initial guesses.

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use super::correspondences::{POINTS_PER_TASK, RigidParts, in_sample};
use super::{GicpParams, RegistrationResult, RegistrationTarget, register};
use crate::points::PointCloud;

/// Coarse-to-fine G-ICP: one [`register`] per correspondence distance in `distances_m` (largest
/// first, e.g. `[0.1, 0.05, 0.02]`), each starting where the previous one ended. A coarse stage
/// that merely runs out of iterations hands its pose on; any other failure stops the sequence.
/// The result is the last stage's, with iterations summed over all stages. An empty list runs
/// once at `params.max_correspondence_m`.
///
/// A stage whose inlier fraction (at its own distance) ends below `give_up_below_fraction` also
/// ends the sequence: at a given pose a finer distance can only count fewer inliers, so a pair
/// that the caller would reject for too few inliers at the finest distance is rejected without
/// the finer stages' iterations (pairs that do not overlap are the ones that run every stage to
/// its iteration limit). 0 never gives up.
pub fn register_coarse_to_fine<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    distances_m: &[f64],
    params: &GicpParams,
    give_up_below_fraction: f64,
) -> RegistrationResult {
    let mut pose = *initial;
    let mut total_iterations = 0;
    let mut last = None;
    for &distance in distances_m {
        let stage = register(
            source,
            target,
            &pose,
            &params.with_max_correspondence(distance),
        );
        total_iterations += stage.iterations;
        let usable = stage.failure.as_ref().is_none_or(|f| f.pose_is_usable());
        let hopeless = stage.inlier_fraction() < give_up_below_fraction;
        pose = stage.target_from_source;
        last = Some(stage);
        if !usable || hopeless {
            break;
        }
    }
    match last {
        Some(result) => RegistrationResult {
            iterations: total_iterations,
            // A failed stage returns the pose it started from, not the caller's initial guess.
            target_from_source: if result.failure.as_ref().is_some_and(|f| !f.pose_is_usable()) {
                *initial
            } else {
                result.target_from_source
            },
            ..result
        },
        // No coarse stages given: a plain run at the configured distance.
        None => register(source, target, initial, params),
    }
}

/// Source points with a target point within `max_distance_m` when placed by
/// `target_from_source`, counted over every `sample_step`-th point (those whose index is a
/// multiple of it): a cheap score (one search of a sample, no optimisation) for choosing
/// between initial guesses.
pub fn count_correspondences<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    target_from_source: &Isometry3<f64>,
    max_distance_m: f64,
    sample_step: usize,
) -> usize {
    let parts = RigidParts::of(target_from_source);
    let max_distance_sq = (max_distance_m * max_distance_m) as f32;
    let step = sample_step.max(1);
    source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .enumerate()
        .map(|(chunk, positions)| {
            let first_index = chunk * POINTS_PER_TASK;
            positions
                .iter()
                .enumerate()
                .filter(|&(i, a)| {
                    in_sample(first_index + i, step) && {
                        let transformed = parts.transform(&a.coords.cast::<f64>()).cast::<f32>();
                        target.any_within(&Point3::from(transformed), max_distance_sq)
                    }
                })
                .count()
        })
        .sum()
}
