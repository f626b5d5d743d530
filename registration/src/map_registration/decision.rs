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
//! One left of several distinct candidates is not chosen by elimination alone: the checks that
//! failed the others are the ones the turned copy of a symmetric room passes as well as the
//! true pose (7-Scenes-like rooms are boxes; the synthetic room is one exactly), so a wrong
//! turn that passes and a true pose that drifted or overlaps too little look alike. The
//! survivor must show colours that agree with a kappa of at least `ambiguity_colour_kappa`, or
//! the registration is refused as unconfirmed; a later attempt with more of the maps decides.
//!
//! G-ICP from a hypothesis can also slide away from it: on a thin overlap, the parts of each map
//! the other does not hold find wrong partners within the correspondence distance and pull the
//! estimate along a direction the overlap barely constrains (7-Scenes crops of 15 % overlap:
//! 20-30 cm from a RANSAC pose within 4 cm). A refined transform that keeps fewer than
//! `min_support_kept` of its hypothesis' supporting correspondences left what the features say,
//! and is refused.

use std::time::Instant;

use nalgebra::{Isometry3, Matrix6, Point3};

use super::consistency::{self, Hypothesis, transform_difference};
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
    /// Supporters of the hypothesis...
    support: usize,
    /// ...and its transform.
    hypothesis: Isometry3<f64>,
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
            hypothesis: coarse,
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
    for (k, j) in judged.iter().enumerate() {
        let (angle, distance) = transform_difference(&j.estimate, &judged[0].estimate, &centre);
        tracing::debug!(
            candidate = k,
            support = j.support,
            kept = j.support_kept,
            overlap = j.overlap.as_ref().map(|o| o.fraction),
            residual_m = j.overlap.as_ref().map(|o| o.residual_m),
            kappa = j.overlap.as_ref().map(|o| o.colour_kappa()),
            depth_agreement = j.free_space.as_ref().map(FreeSpace::agreement),
            from_best_deg = angle.to_degrees(),
            from_best_m = distance,
            verdict = ?j.verdict,
            "candidate verified"
        );
    }
    let same = |a: &Isometry3<f64>, b: &Isometry3<f64>| same_transform(a, b, &centre, config);
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
        [only] => {
            if let Some(refusal) = unconfirmed(&judged, *only, &centre, config) {
                fill_scores(&judged[*only], scores);
                return refusal;
            }
            *only
        }
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

/// Whether two transforms are one (the correspondences' `distinct_*` thresholds, at `centre`).
fn same_transform(
    a: &Isometry3<f64>,
    b: &Isometry3<f64>,
    centre: &Point3<f64>,
    config: &MapRegistrationConfig,
) -> bool {
    consistency::same_transform(
        a,
        b,
        centre,
        config.distinct_rotation_rad,
        config.distinct_translation_m,
    )
}

/// The refusal of `judged[only]`, the one candidate that passed, when distinct alternatives
/// failed beside it and its colours do not confirm it (`ambiguity_colour_kappa`; see the
/// module documentation). An alternative is distinct when neither its hypothesis nor its
/// refined transform is the candidate's estimate.
fn unconfirmed(
    judged: &[Judged],
    only: usize,
    centre: &Point3<f64>,
    config: &MapRegistrationConfig,
) -> Option<Outcome> {
    let winner = &judged[only];
    let apart = |pose: &Isometry3<f64>| !same_transform(pose, &winner.estimate, centre, config);
    let rivals: Vec<&Judged> = judged
        .iter()
        .enumerate()
        .filter(|&(k, j)| k != only && apart(&j.hypothesis) && apart(&j.estimate))
        .map(|(_, j)| j)
        .collect();
    let strongest = rivals.iter().max_by_key(|j| j.support)?;
    let overlap = winner.overlap.as_ref()?;
    let compared = overlap.colour_compared;
    let kappa = overlap.colour_kappa();
    if compared >= config.min_colour_comparisons && kappa >= config.ambiguity_colour_kappa {
        return None;
    }
    let (angle, distance) = transform_difference(&strongest.hypothesis, &winner.estimate, centre);
    Some(Outcome {
        target_from_source: winner.estimate,
        verdict: Err(MapRejection::Unconfirmed {
            rivals: rivals.len(),
            rival_support: strongest.support,
            support: winner.support,
            rotation_deg: angle.to_degrees(),
            translation_m: distance,
            kappa,
            compared,
            required: config.ambiguity_colour_kappa,
            required_compared: config.min_colour_comparisons,
        }),
        information: None,
    })
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    /// A candidate that passed with `compared` colours compared, `agreeing` of them agreeing
    /// against a chance agreement of 0.2.
    fn passed(
        estimate: Isometry3<f64>,
        support: usize,
        compared: usize,
        agreeing: usize,
    ) -> Judged {
        Judged {
            support,
            hypothesis: estimate,
            estimate,
            support_kept: support,
            gicp_iterations: 5,
            gicp_converged: true,
            overlap: Some(Overlap {
                overlapping: 5000,
                fraction: 0.3,
                residual_m: 0.004,
                information: Matrix6::identity(),
                rotation_sigma_rad: 1e-4,
                translation_sigma_m: 1e-4,
                colour_compared: compared,
                colour_agreeing: agreeing,
                colour_chance: 0.2,
                colour_gains: [1.0; 3],
            }),
            free_space: None,
            verdict: Ok(()),
        }
    }

    /// A candidate whose G-ICP slid from `hypothesis` to `estimate`.
    fn drifted(hypothesis: Isometry3<f64>, estimate: Isometry3<f64>, support: usize) -> Judged {
        Judged {
            hypothesis,
            estimate,
            support_kept: 1,
            overlap: None,
            verdict: Err(MapRejection::RefinementDrifted {
                kept: 1,
                support,
                required: support / 2,
                rotation_deg: 5.0,
                translation_m: 0.3,
            }),
            ..passed(estimate, support, 0, 0)
        }
    }

    fn turned(degrees: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(4.0, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), degrees.to_radians()),
        )
    }

    /// Kappa with a chance agreement of 0.2: (a - 0.2) / 0.8.
    fn agreeing_for_kappa(kappa: f64, compared: usize) -> usize {
        ((kappa * 0.8 + 0.2) * compared as f64).round() as usize
    }

    #[test]
    fn a_lone_survivor_of_distinct_candidates_needs_colour_that_confirms_it() {
        let config = MapRegistrationConfig::default();
        let centre = Point3::origin();
        let truth = turned(0.0);
        let turn = turned(180.0);
        let weak = agreeing_for_kappa(0.33, 1000);
        let strong = agreeing_for_kappa(0.68, 1000);
        // The better supported true pose drifted, its 180-degree turn passed with weak colour.
        let judged = [drifted(truth, truth, 22), passed(turn, 19, 1000, weak)];
        let refusal = unconfirmed(&judged, 1, &centre, &config).expect("refused");
        match refusal.verdict {
            Err(MapRejection::Unconfirmed {
                rivals: 1,
                rival_support: 22,
                support: 19,
                rotation_deg,
                kappa,
                ..
            }) => {
                assert!((rotation_deg - 180.0).abs() < 1e-6, "{rotation_deg}");
                assert!((kappa - 0.33).abs() < 0.01, "{kappa}");
            }
            other => panic!("{other:?}"),
        }
        // Colours that agree well confirm it.
        let judged = [drifted(truth, truth, 22), passed(turn, 19, 1000, strong)];
        assert!(unconfirmed(&judged, 1, &centre, &config).is_none());
        // So few points compared that colour cannot judge: refused whatever they show.
        let judged = [drifted(truth, truth, 22), passed(turn, 19, 50, 50)];
        assert!(unconfirmed(&judged, 1, &centre, &config).is_some());
        // No colour at all: refused.
        let judged = [drifted(truth, truth, 22), passed(turn, 19, 0, 0)];
        assert!(unconfirmed(&judged, 1, &centre, &config).is_some());
    }

    #[test]
    fn candidates_that_reach_the_survivors_transform_are_not_rivals() {
        let config = MapRegistrationConfig::default();
        let centre = Point3::origin();
        let truth = turned(0.0);
        let nearby = turned(3.0);
        // Another hypothesis that refined onto the survivor's transform but kept too few
        // supporters, and one whose hypothesis is the survivor's transform: neither is an
        // alternative, so weak colour is enough (as it is without any alternative).
        let judged = [
            passed(truth, 30, 1000, agreeing_for_kappa(0.3, 1000)),
            drifted(turned(90.0), nearby, 25),
            drifted(nearby, turned(90.0), 24),
        ];
        assert!(unconfirmed(&judged, 0, &centre, &config).is_none());
        // A distinct one makes the same survivor unconfirmed.
        let judged = [
            passed(truth, 30, 1000, agreeing_for_kappa(0.3, 1000)),
            drifted(turned(90.0), turned(95.0), 25),
        ];
        assert!(unconfirmed(&judged, 0, &centre, &config).is_some());
    }
}
