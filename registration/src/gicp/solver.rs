//! The Levenberg-Marquardt loop (see the module documentation of [`super`]) and the
//! classification of its result.

use nalgebra::{Isometry3, Matrix6, Point3};
use rayon::prelude::*;

use super::correspondences::{
    Correspondence, POINTS_PER_TASK, RigidParts, evaluate, in_chunk_order, linearize,
    residual_and_weight,
};
use super::{
    GicpParams, JointTerm, LM_INITIAL_LAMBDA, LM_LAMBDA_FACTOR, LM_MAX_INNER_ITERATIONS,
    MIN_POINTS_FOR_A_POSE, NO_HINT, RegistrationFailure, RegistrationResult, RegistrationTarget,
};
use crate::points::PointCloud;

/// A rival initial guess's score, as [`count_correspondences`] gave it: `matches` of every
/// `sample_step`-th source point within the correspondence distance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RivalGuess {
    /// Every `sample_step`-th source point was counted (0 counts as 1).
    pub sample_step: usize,
    /// Counted points with a target point within the correspondence distance at the rival.
    pub matches: usize,
    /// Whether the rival wins when both guesses count the same.
    pub wins_ties: bool,
}

/// [`register`] from `initial`, unless a rival initial guess scores better: the first
/// correspondence search also counts what [`count_correspondences`] would count at `initial`
/// (the same points, the same distance test), and when that is below `rival.matches` (or equal
/// to it, with `rival.wins_ties`) the optimisation is given up (`None`) before its first step.
/// Choosing between two guesses then costs one sampled search (the rival's) instead of two,
/// because the chosen guess's count comes from a search G-ICP makes anyway; the choice is the
/// same as comparing two [`count_correspondences`]. Inputs G-ICP cannot use (too few points, no
/// covariances) fail at once, from `initial`, whatever the rival scored.
pub fn register_unless_outscored<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    params: &GicpParams,
    rival: Option<RivalGuess>,
) -> Option<RegistrationResult> {
    register_joint_unless_outscored(source, target, initial, params, rival, None)
}

/// [`register_unless_outscored`] minimising G-ICP's cost plus `term`'s (when given): `term` is
/// linearised at every correspondence search, its normal equations are added to G-ICP's, and a
/// damped step is judged by the sum of both costs. The result's statistics (`error`,
/// correspondences, overlap) are G-ICP's alone, so the checks that read them mean what they
/// mean without the term.
pub fn register_joint_unless_outscored<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    params: &GicpParams,
    rival: Option<RivalGuess>,
    mut term: Option<&mut dyn JointTerm>,
) -> Option<RegistrationResult> {
    if let Some(failure) = check_inputs(source, target) {
        return Some(RegistrationResult::failed(initial, source.len(), failure));
    }
    let max_distance_sq = (params.max_correspondence_m * params.max_correspondence_m) as f32;
    let overlap_sq = (params.overlap_distance_m * params.overlap_distance_m) as f32;
    let mut correspondences: Vec<Correspondence> = vec![None; source.len()];
    let mut hints = vec![NO_HINT; source.len()];
    // Statistics of the latest linearisation: the result's when the next step is the converged
    // one (see `finish`).
    let mut linearized = None;
    let mut pose = *initial;
    let mut lambda = LM_INITIAL_LAMBDA;
    let mut converged = false;
    let mut iterations = 0;
    while iterations < params.max_iterations && !converged {
        iterations += 1;
        // The rival is judged on the first search only.
        let rival = rival.filter(|_| iterations == 1);
        let sample_step = rival.map_or(0, |r| r.sample_step.max(1));
        let system = linearize(
            source,
            target,
            &pose,
            (max_distance_sq, overlap_sq),
            sample_step,
            (&mut correspondences, &mut hints),
        );
        if let Some(rival) = rival
            && (system.sampled_within < rival.matches
                || (rival.wins_ties && system.sampled_within == rival.matches))
        {
            return None;
        }
        linearized = Some(FinalStatistics {
            inliers: system.inliers,
            overlapping: system.overlapping,
            error: system.error,
        });
        if system.inliers < MIN_POINTS_FOR_A_POSE {
            let failure = RegistrationFailure::TooFewCorrespondences {
                found: system.inliers,
                required: MIN_POINTS_FOR_A_POSE,
            };
            return Some(RegistrationResult {
                iterations,
                ..RegistrationResult::failed(initial, source.len(), failure)
            });
        }
        if !system.error.is_finite() {
            return Some(RegistrationResult {
                iterations,
                ..RegistrationResult::failed(initial, source.len(), RegistrationFailure::Diverged)
            });
        }
        let (mut hessian, mut gradient, mut error) =
            (system.hessian, system.gradient, system.error);
        if let Some(term) = term.as_deref_mut() {
            let joint = term.linearize(&pose);
            if joint.error.is_finite() {
                hessian += joint.hessian;
                gradient += joint.gradient;
                error += joint.error;
            }
        }
        let mut accepted = false;
        for _ in 0..LM_MAX_INNER_ITERATIONS {
            let damped = hessian + Matrix6::identity() * lambda;
            let Some(delta) = damped.cholesky().map(|c| -c.solve(&gradient)) else {
                lambda *= LM_LAMBDA_FACTOR;
                continue;
            };
            if !delta.iter().all(|v| v.is_finite()) {
                return Some(RegistrationResult {
                    iterations,
                    ..RegistrationResult::failed(
                        initial,
                        source.len(),
                        RegistrationFailure::Diverged,
                    )
                });
            }
            let rotation_change = delta.fixed_rows::<3>(0).into_owned();
            let translation_change = delta.fixed_rows::<3>(3).into_owned();
            let candidate = pose * Isometry3::new(translation_change, rotation_change);
            let term_error = term.as_deref().map_or(0.0, |t| t.evaluate(&candidate));
            if evaluate(source, &candidate, &correspondences) + term_error <= error {
                pose = candidate;
                lambda /= LM_LAMBDA_FACTOR;
                accepted = true;
                converged = rotation_change.norm() < params.rotation_epsilon_rad
                    && translation_change.norm() < params.translation_epsilon_m;
                break;
            }
            lambda *= LM_LAMBDA_FACTOR;
        }
        if !accepted {
            // No damped step lowers the error: the pose is a minimum to numerical precision.
            converged = true;
        }
    }
    let linearized = linearized.filter(|_| converged);
    Some(finish(
        source, target, initial, pose, iterations, converged, params, linearized,
    ))
}

fn check_inputs<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
) -> Option<RegistrationFailure> {
    if source.len() < MIN_POINTS_FOR_A_POSE {
        return Some(RegistrationFailure::TooFewSourcePoints {
            found: source.len(),
            required: MIN_POINTS_FOR_A_POSE,
        });
    }
    if !source.has_covariances() {
        return Some(RegistrationFailure::MissingSourceCovariances);
    }
    if target.target_len() < MIN_POINTS_FOR_A_POSE {
        return Some(RegistrationFailure::TooFewTargetPoints {
            found: target.target_len(),
            required: MIN_POINTS_FOR_A_POSE,
        });
    }
    None
}

/// Final statistics and the failure classification. After convergence they are those of the
/// last linearisation (`linearized`): the returned pose is that linearisation's pose plus one
/// step below the convergence thresholds (or none at all), which moves no point by more than a
/// fraction of a millimetre, so a fresh search would count the same correspondences (small_gicp
/// reports its last linearisation's figures likewise) and costs a sixth of a frame's tracking.
/// Otherwise a fresh search at the final pose.
#[allow(
    clippy::too_many_arguments,
    reason = "the solver's state at its end, handed over once"
)]
fn finish<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    pose: Isometry3<f64>,
    iterations: usize,
    converged: bool,
    params: &GicpParams,
    linearized: Option<FinalStatistics>,
) -> RegistrationResult {
    let stats = linearized.unwrap_or_else(|| final_statistics(source, target, &pose, params));
    let required = MIN_POINTS_FOR_A_POSE
        .max((params.min_inlier_fraction * source.len() as f64).ceil() as usize);
    let failure =
        if !stats.error.is_finite() || !pose.to_homogeneous().iter().all(|v| v.is_finite()) {
            Some(RegistrationFailure::Diverged)
        } else if stats.inliers < required {
            Some(RegistrationFailure::TooFewCorrespondences {
                found: stats.inliers,
                required,
            })
        } else if !converged {
            Some(RegistrationFailure::NotConverged { iterations })
        } else {
            None
        };
    let pose_is_usable = failure.as_ref().is_none_or(|f| f.pose_is_usable());
    RegistrationResult {
        target_from_source: if pose_is_usable { pose } else { *initial },
        iterations,
        converged,
        correspondences: stats.inliers,
        source_points: source.len(),
        overlap_fraction: stats.overlapping as f64 / source.len() as f64,
        error: stats.error,
        failure,
    }
}

struct FinalStatistics {
    inliers: usize,
    overlapping: usize,
    error: f64,
}

/// Inliers, overlapping points and error at the final pose, from one search with the larger of
/// the correspondence and overlap distances.
fn final_statistics<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    pose: &Isometry3<f64>,
    params: &GicpParams,
) -> FinalStatistics {
    let parts = RigidParts::of(pose);
    let inlier_sq = (params.max_correspondence_m * params.max_correspondence_m) as f32;
    let overlap_sq = (params.overlap_distance_m * params.overlap_distance_m) as f32;
    let search_sq = inlier_sq.max(overlap_sq);
    let chunks = source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .zip(source.covariances.par_chunks(POINTS_PER_TASK))
        .map(|(positions, covariances)| {
            let (mut inliers, mut overlapping, mut error) = (0usize, 0usize, 0.0f64);
            for (a, c_a) in positions.iter().zip(covariances) {
                let transformed = parts.transform(&a.coords.cast::<f64>());
                let Some((j, distance_sq)) =
                    target.nearest_within(&Point3::from(transformed.cast::<f32>()), search_sq)
                else {
                    continue;
                };
                if distance_sq <= overlap_sq {
                    overlapping += 1;
                }
                if distance_sq <= inlier_sq
                    && let Some((d, w)) = residual_and_weight(
                        &transformed,
                        c_a,
                        &target.position(j),
                        &target.covariance(j),
                        &parts.rotation,
                    )
                {
                    inliers += 1;
                    error += d.dot(&(w * d));
                }
            }
            (inliers, overlapping, error)
        });
    let (inliers, overlapping, error) = in_chunk_order(chunks, (0, 0, 0.0), |x, y| {
        (x.0 + y.0, x.1 + y.1, x.2 + y.2)
    });
    FinalStatistics {
        inliers,
        overlapping,
        error,
    }
}
