//! Stages 5 and 6 for each candidate transform, then the choice between them.
//!
//! The correspondences usually single out one transform: the best hypothesis, with no distinct
//! alternative holding more than `max_ambiguity_ratio` of its support. It is refined (G-ICP) and
//! verified, and its verdict is the registration's.
//!
//! When alternatives come near (a room whose shape repeats when turned, shelves in a row, or a
//! small overlap whose right transform has few more supporters than chance ones), the
//! correspondences cannot decide, but the maps can: every such candidate (the best and up to
//! `max_verified_hypotheses - 1` alternatives) is refined and verified in full, and the
//! free-space test of the agents' depth views (when given) judges each. Candidates that fail are
//! dropped; candidates that converge to the same transform are one. One left: it is the answer.
//! Several: one must beat every other, first by the free-space test (an agreement higher by
//! `ambiguity_free_space_margin`), else by geometry (a residual below `ambiguity_residual_ratio`
//! of the other's with an overlap at least that fraction of the other's); when none does, the
//! registration is refused as ambiguous, with the numbers of the two that tie.
//!
//! G-ICP from a hypothesis can also slide away from it: on a thin overlap, the parts of each map
//! the other does not hold find wrong partners within the correspondence distance and pull the
//! estimate along a direction the overlap barely constrains (7-Scenes crops of 15 % overlap:
//! 20-30 cm from a RANSAC pose within 4 cm). A refined transform that keeps fewer than
//! `min_support_kept` of its hypothesis' supporting correspondences left what the features say,
//! and is refused.

use std::time::Instant;

use nalgebra::{Isometry3, Matrix6, Point3};

use super::consistency::{Hypothesis, transform_difference};
use super::free_space::{FreeSpace, FreeSpaceCheck};
use super::maps::{FineView, PreparedMap};
use super::verification::{ColourCheck, Overlap, RefinementParams, measure_overlap, refine};
use super::{MapRegistrationConfig, MapRegistrationScores, MapRejection, Outcome, elapsed_ms};

/// The maps the final G-ICP stage and the verification work on, and the finest refinement
/// distance (also the overlap distance).
pub(super) struct FineLevel<'m> {
    pub source: FineView<'m>,
    pub target: FineView<'m>,
    pub distance_m: f64,
}

/// What the candidates are judged with: the feature-level maps (coarse G-ICP stages), the fine
/// level, the correspondences (support kept), the free-space test.
pub(super) struct Judge<'a> {
    pub source_map: &'a PreparedMap,
    pub target_map: &'a PreparedMap,
    pub fine: FineLevel<'a>,
    /// Matched points of the correspondences, source and target.
    pub matched: (&'a [Point3<f64>], &'a [Point3<f64>]),
    pub voxel_m: f64,
    pub free_space: Option<&'a FreeSpaceCheck<'a>>,
    /// The maps' points as given (the free-space test moves them, not voxel centroids, which at
    /// a depth edge float between the two surfaces).
    pub inputs: (&'a [Point3<f32>], &'a [Point3<f32>]),
    /// The source's colours times these gains are compared with the target's (the maps'
    /// relative white balance).
    pub colour_gains: [f64; 3],
    pub config: &'a MapRegistrationConfig,
}

/// One candidate after refinement and verification.
struct Judged {
    /// Supporters of the hypothesis.
    support: usize,
    estimate: Isometry3<f64>,
    /// Supporting correspondences of the refined transform.
    support_kept: usize,
    gicp_iterations: usize,
    gicp_converged: bool,
    overlap: Option<Overlap>,
    free_space: Option<FreeSpace>,
    verdict: Result<(), MapRejection>,
}

impl Judge<'_> {
    /// The centre of the fine source map, where transforms are compared (a translation compared
    /// at the origin would depend on where the map's frame lies).
    fn source_centre(&self) -> Point3<f64> {
        let points = self.fine.source.tree.positions();
        let sum = points.iter().fold(nalgebra::Vector3::zeros(), |sum, p| {
            sum + p.coords.cast::<f64>()
        });
        Point3::from(sum / points.len().max(1) as f64)
    }

    /// Correspondences within the inlier distance under `pose`.
    fn supporters(&self, pose: &Isometry3<f64>) -> usize {
        let limit = self.config.inlier_distance_voxels * self.voxel_m;
        let (source, target) = self.matched;
        source
            .iter()
            .zip(target)
            .filter(|(s, t)| (pose * *s - *t).norm() <= limit)
            .count()
    }

    /// G-ICP from `coarse`: the coarse distances on the feature level, the finest on the fine one.
    fn refine(&self, coarse: &Isometry3<f64>) -> crate::RegistrationResult {
        let config = self.config;
        let distances = &config.refine_distances_voxels;
        refine(
            (self.source_map.tree.cloud(), &self.target_map.tree),
            (self.fine.source.tree.cloud(), self.fine.target.tree),
            coarse,
            &RefinementParams {
                coarse_distances_m: distances[..distances.len().saturating_sub(1)]
                    .iter()
                    .map(|d| d * self.voxel_m)
                    .collect(),
                fine_distance_m: self.fine.distance_m,
                max_iterations: config.gicp_max_iterations,
                rotation_epsilon_rad: config.gicp_rotation_epsilon_rad,
                translation_epsilon_m: config.gicp_translation_epsilon_m,
            },
        )
    }

    /// Overlap, residual, information and colour of `estimate` on the fine level.
    fn overlap(&self, estimate: &Isometry3<f64>) -> Overlap {
        let config = self.config;
        let colour_check = match (self.fine.source.colours, self.fine.target.colours) {
            (Some(source), Some(target)) => Some(ColourCheck {
                source,
                target,
                tolerance: config.colour_tolerance as f32,
                source_gains: self.colour_gains,
            }),
            _ => None,
        };
        measure_overlap(
            self.fine.source.tree.positions(),
            self.fine.target.tree,
            self.fine.target.normals,
            estimate,
            self.fine.distance_m,
            config.residual_sigma_floor_m,
            colour_check,
        )
    }

    /// Refines and verifies one hypothesis.
    fn judge(&self, hypothesis: &Hypothesis) -> Judged {
        let coarse = hypothesis.target_from_source;
        let refined = self.refine(&coarse);
        let mut judged = Judged {
            support: hypothesis.support(),
            estimate: refined.target_from_source,
            support_kept: 0,
            gicp_iterations: refined.iterations,
            gicp_converged: refined.converged,
            overlap: None,
            free_space: None,
            verdict: Ok(()),
        };
        if let Some(failure) = refined.failure.clone().filter(|f| !f.pose_is_usable()) {
            judged.estimate = coarse;
            judged.verdict = Err(MapRejection::RefinementFailed(failure));
            return judged;
        }
        judged.support_kept = self.supporters(&judged.estimate);
        let required = (self.config.min_support_kept * judged.support as f64).ceil() as usize;
        if judged.support_kept < required {
            let (angle, distance) =
                transform_difference(&judged.estimate, &coarse, &self.source_centre());
            judged.verdict = Err(MapRejection::RefinementDrifted {
                kept: judged.support_kept,
                support: judged.support,
                required,
                rotation_deg: angle.to_degrees(),
                translation_m: distance,
            });
            return judged;
        }
        let overlap = self.overlap(&judged.estimate);
        judged.verdict = verdict(&overlap, self.config);
        judged.overlap = Some(overlap);
        if judged.verdict.is_ok()
            && let Some(check) = self.free_space
        {
            let free_space = check.measure(self.inputs.0, self.inputs.1, &judged.estimate);
            judged.verdict = check.verdict(&free_space);
            judged.free_space = Some(free_space);
        }
        judged
    }
}

/// Accepted, or the first check `overlap` fails (see the module documentation of the parent).
pub(super) fn verdict(
    overlap: &Overlap,
    config: &MapRegistrationConfig,
) -> Result<(), MapRejection> {
    let colour_judged = overlap.colour_compared >= config.min_colour_comparisons;
    let colour_confirms = colour_judged
        && overlap.colour_kappa() >= config.colour_confirmed_kappa
        && overlap.fraction >= config.colour_confirmed_overlap_fraction;
    if overlap.fraction < config.min_overlap_fraction && !colour_confirms {
        Err(MapRejection::LowOverlap {
            found: overlap.fraction,
            required: config.min_overlap_fraction,
            confirmed: config.colour_confirmed_overlap_fraction,
            required_kappa: config.colour_confirmed_kappa,
            kappa: overlap.colour_kappa(),
        })
    } else if overlap.residual_m.is_nan() || overlap.residual_m > config.max_residual_m {
        Err(MapRejection::HighResidual {
            found_m: overlap.residual_m,
            allowed_m: config.max_residual_m,
        })
    } else if overlap.rotation_sigma_rad > config.max_rotation_sigma_rad
        || overlap.translation_sigma_m > config.max_translation_sigma_m
    {
        Err(MapRejection::Degenerate {
            rotation_deg: overlap.rotation_sigma_rad.to_degrees(),
            translation_m: overlap.translation_sigma_m,
            allowed_rotation_deg: config.max_rotation_sigma_rad.to_degrees(),
            allowed_translation_m: config.max_translation_sigma_m,
        })
    } else if colour_judged && overlap.colour_kappa() < config.min_colour_kappa {
        Err(MapRejection::ColourDisagreement {
            compared: overlap.colour_compared,
            agreement: overlap.colour_agreement(),
            chance: overlap.colour_chance,
            kappa: overlap.colour_kappa(),
            required: config.min_colour_kappa,
        })
    } else {
        Ok(())
    }
}

/// Whether `a` beats `b` (both verified): by the free-space test when both were measured, else
/// by geometry (see the module documentation).
fn beats(a: &Judged, b: &Judged, config: &MapRegistrationConfig) -> bool {
    if let (Some(fa), Some(fb)) = (&a.free_space, &b.free_space) {
        let difference = fa.agreement() - fb.agreement();
        if difference.abs() >= config.ambiguity_free_space_margin {
            return difference > 0.0;
        }
    }
    let (Some(oa), Some(ob)) = (&a.overlap, &b.overlap) else {
        return false;
    };
    let ratio = config.ambiguity_residual_ratio;
    oa.residual_m <= ratio * ob.residual_m && oa.fraction >= ratio * ob.fraction
}

/// Refines and verifies the candidates (best first) and chooses (see the module documentation);
/// fills the chosen candidate's figures into `scores`.
pub(super) fn decide(
    judge: &Judge<'_>,
    candidates: &[Hypothesis],
    scores: &mut MapRegistrationScores,
) -> Outcome {
    let stage = Instant::now();
    let config = judge.config;
    let judged: Vec<Judged> = candidates.iter().map(|h| judge.judge(h)).collect();
    scores.hypotheses_verified = judged.len();
    scores.timings.verification_ms = elapsed_ms(stage);
    let centre = judge.source_centre();
    let same = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
        let (angle, distance) = transform_difference(a, b, &centre);
        angle <= config.distinct_rotation_rad && distance <= config.distinct_translation_m
    };
    // The verified candidates, one per refined transform (the better supported first).
    let mut passed: Vec<usize> = Vec::new();
    for (k, j) in judged.iter().enumerate() {
        if j.verdict.is_ok()
            && !passed
                .iter()
                .any(|&p| same(&judged[p].estimate, &j.estimate))
        {
            passed.push(k);
        }
    }
    let chosen = match passed.as_slice() {
        [] => 0,
        [only] => *only,
        _ => match passed.iter().copied().find(|&a| {
            passed
                .iter()
                .all(|&b| a == b || beats(&judged[a], &judged[b], config))
        }) {
            Some(winner) => winner,
            None => {
                let (a, b) = (&judged[passed[0]], &judged[passed[1]]);
                fill_scores(a, scores);
                return tied(a, b, &centre);
            }
        },
    };
    scores.ambiguity_resolved = judged.len() > 1 && judged[chosen].verdict.is_ok();
    let winner = &judged[chosen];
    fill_scores(winner, scores);
    Outcome {
        target_from_source: winner.estimate,
        verdict: winner.verdict.clone(),
        information: winner.overlap.as_ref().map(|o| o.information),
    }
}

/// The refusal of two verified candidates that neither the free-space test nor geometry tells
/// apart.
fn tied(a: &Judged, b: &Judged, centre: &Point3<f64>) -> Outcome {
    let (angle, distance) = transform_difference(&a.estimate, &b.estimate, centre);
    let residual = |j: &Judged| j.overlap.as_ref().map_or(f64::NAN, |o| o.residual_m);
    let fraction = |j: &Judged| j.overlap.as_ref().map_or(f64::NAN, |o| o.fraction);
    let agreement = |j: &Judged| j.free_space.as_ref().map_or(f64::NAN, FreeSpace::agreement);
    Outcome {
        target_from_source: a.estimate,
        verdict: Err(MapRejection::Tied {
            rotation_deg: angle.to_degrees(),
            translation_m: distance,
            residuals_m: [residual(a), residual(b)],
            overlaps: [fraction(a), fraction(b)],
            depth_agreements: [agreement(a), agreement(b)],
        }),
        information: None::<Matrix6<f64>>,
    }
}

/// The figures of the candidate the registration ends with.
fn fill_scores(j: &Judged, scores: &mut MapRegistrationScores) {
    scores.consistent_correspondences = j.support;
    scores.support_kept = j.support_kept;
    scores.gicp_iterations = j.gicp_iterations;
    scores.gicp_converged = j.gicp_converged;
    if let Some(overlap) = &j.overlap {
        scores.overlapping_points = overlap.overlapping;
        scores.overlap_fraction = overlap.fraction;
        scores.residual_m = overlap.residual_m;
        scores.rotation_sigma_deg = overlap.rotation_sigma_rad.to_degrees();
        scores.translation_sigma_m = overlap.translation_sigma_m;
        scores.colour_compared = overlap.colour_compared;
        scores.colour_agreement = overlap.colour_agreement();
        scores.colour_chance = overlap.colour_chance;
        scores.colour_kappa = overlap.colour_kappa();
        scores.colour_gains = overlap.colour_gains;
    }
    if let Some(free_space) = &j.free_space {
        scores.depth_agreement = free_space.agreement();
        scores.depth_comparisons = free_space.decisive();
    }
}
