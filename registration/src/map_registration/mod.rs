//! Map-level global registration: the rigid transform between two agents' maps (point clouds,
//! e.g. downsampled map points or Gaussian means, each in its agent's frame) with no initial
//! guess, verified, with an information matrix for the pose graph.
//!
//! Keyframe-to-keyframe alignment ([`crate::alignment`]) needs two images of the same place from
//! similar viewpoints; agents that crossed the same room in opposite directions, or metres apart,
//! never produce such a pair. Their maps still share surfaces, and the shape and colour of those
//! surfaces are viewpoint-independent. The input is a [`MapPoints`] per map: points and,
//! optionally, a colour per point; colour is used when both maps have it. The pipeline, one
//! stage per file:
//!
//! 1. [`downsample`]: one centroid per voxel (and the mean colour), isolated points removed, the
//!    same voxel for both maps, grown until both fit `max_points` (the cost bound). Uniform
//!    sampling makes the local descriptors describe the geometry rather than how long the agent
//!    looked at it.
//! 2. [`fpfh`]: a PCA normal per point and a 33-bin FPFH-style histogram of the angles between
//!    the normals of neighbouring points and the lines joining them: a description of the local
//!    shape that is invariant to rigid motion. The angles are taken between lines, so the
//!    unknowable sign of a map normal does not matter (the reason is in that file). With colour,
//!    [`colour`] appends the neighbourhood's hue histogram (exposure-invariant chromaticity),
//!    weighted by `colour_weight`.
//! 3. [`correspondences`]: mutual nearest neighbours in descriptor space, plus one-way matches
//!    that pass Lowe's ratio test (`match_ratio`), topped up with the best one-way matches when
//!    too few are mutual.
//! 4. [`compatibility`] (when `clique_seeds` > 0) and [`consistency`]: cliques of mutually
//!    distance-compatible correspondences (SC^2-scored seeds) as hypotheses, then RANSAC over
//!    three correspondences with distance-preservation pre-checks and local least-squares
//!    refits: the transform most correspondences agree on, and the best *distinct* runner-up,
//!    whose relative support measures ambiguity (symmetric rooms, repeated shelves).
//! 5. [`verification`]: coarse-to-fine G-ICP from the hypothesis (slam_core's, plane to plane,
//!    with each map's covariances), then overlap, point-to-plane residual, the information
//!    matrix of the estimate and, with colour, how far the overlap's colours agree beyond chance
//!    (Cohen's kappa of chromaticity agreement, after the maps' relative white balance).
//! 6. [`decision`] and [`free_space`]: when the correspondences leave alternatives nearly tied,
//!    each is refined and verified and the free-space test of the maps' depth views (when
//!    given), else the residual, chooses; the accepted result must pass the free-space test.
//!
//! The verdict refuses, with the numbers, every estimate that is not trustworthy: too few points,
//! descriptors or consistent correspondences; ambiguous (verified alternatives that neither the
//! free-space test nor the residual tells apart: `Tied`); G-ICP failure or drift away from the
//! correspondences; too little overlap (below `min_overlap_fraction`, or below the smaller
//! `colour_confirmed_overlap_fraction` when colour agrees with a kappa of at least
//! `colour_confirmed_kappa`); a high residual; a degenerate overlap (one plane, a corridor: a
//! direction the overlap does not constrain); colours that agree no better than chance; or map
//! points in the free space of the other map's depth views.
//!
//! Lengths of the configuration ending in `_voxels` scale with the voxel actually used. Every
//! stage is parallel (rayon) except RANSAC, which is sequential so that the result depends on
//! the seed only; timings per stage go to `tracing` at debug level and into the scores.
//!
//! **Why colour.** Geometry alone cannot tell a box-shaped room from itself turned by 90 or 180
//! degrees: with little true overlap the turned room often overlaps *more* than the true pose,
//! so neither the overlap nor the residual can refuse it, and only the correspondence evidence
//! does (enough supporters, twice the best distinct alternative's), at the cost of recall. The
//! walls of a room differ in colour, and the hue part of the descriptors lets the true
//! correspondences find each other. The verification's colour kappa refuses poses whose colours
//! are unrelated (another room), not a turned room whose floor matches; those are left to the
//! correspondence evidence and, between agents, to the free-space check of the consensus (consensus-server/src/map_links.rs).
//! A kappa well above anything a wrong pose reaches confirms a pose enough to accept a small
//! overlap (`colour_confirmed_*`). Colour also raises chance support (matches concentrate in
//! regions of distinctive colour), which the ambiguity test absorbs. The measurements behind
//! these choices, per stage and per variant tried, are in docs/benchmarks.md
//! (`mac-ego3d bench map-registration`).
//!
//! The information matrix treats residuals as independent and is therefore optimistic.

pub mod colour;
pub mod compatibility;
mod config;
pub mod consistency;
pub mod correspondences;
mod decision;
pub mod downsample;
pub mod fpfh;
pub mod free_space;
mod maps;
mod outcome;
pub mod verification;

#[cfg(test)]
mod tests;

use std::borrow::Cow;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix6, Point3};

use compatibility::CliqueParams;
pub use config::MapRegistrationConfig;
use consistency::{Consensus, Hypothesis, RansacParams, find_consensus, transform_difference};
use correspondences::{FeatureMatch, MatchParams};
use decision::{FineLevel, Judge, decide};
use downsample::Cloud;
pub use downsample::MapPoints;
pub use free_space::{DepthView, FreeSpace, FreeSpaceCheck};
use maps::{PreparedMap, RefinementMap, prepare};
pub use outcome::{MapRegistration, MapRegistrationScores, MapRejection, StageTimings};

/// A map needs at least this many points after downsampling, and descriptors, to be registered:
/// fewer cannot describe a scene that fixes six degrees of freedom.
pub const MIN_POINTS: usize = 30;

fn elapsed_ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

/// Registers the `source` map onto the `target` map (see the module documentation). Colours
/// are used when both maps have them.
pub fn register_maps<'a, 'b>(
    source: impl Into<MapPoints<'a>>,
    target: impl Into<MapPoints<'b>>,
    config: &MapRegistrationConfig,
) -> MapRegistration {
    register_maps_checked(source, target, config, None)
}

/// [`register_maps`] with the free-space test of the maps' depth views ([`free_space`]): the
/// accepted result must pass it, and it judges between candidates the correspondences leave
/// nearly tied.
pub fn register_maps_checked<'a, 'b>(
    source: impl Into<MapPoints<'a>>,
    target: impl Into<MapPoints<'b>>,
    config: &MapRegistrationConfig,
    free_space: Option<&FreeSpaceCheck<'_>>,
) -> MapRegistration {
    let start = Instant::now();
    let (mut source, mut target) = (source.into(), target.into());
    let use_colour = source.colours.is_some() && target.colours.is_some();
    if !use_colour {
        source.colours = None;
        target.colours = None;
    }
    let _span = tracing::debug_span!(
        "register_maps",
        source = source.points.len(),
        target = target.points.len(),
        colour = use_colour
    )
    .entered();
    let mut scores = MapRegistrationScores::new(source.points.len(), target.points.len());
    scores.colour = use_colour;
    let outcome =
        run_stages(source, target, config, free_space, &mut scores).unwrap_or_else(Outcome::from);
    match &outcome.verdict {
        Ok(()) => tracing::debug!("map registration accepted"),
        Err(reason) => tracing::debug!(%reason, "map registration refused"),
    }
    MapRegistration {
        target_from_source: outcome.target_from_source,
        scores,
        verdict: outcome.verdict,
        information: outcome.information,
        elapsed_ms: elapsed_ms(start),
    }
}

/// Where the stages ended: the estimate, the verdict and the information matrix of the
/// verification.
struct Outcome {
    target_from_source: Isometry3<f64>,
    verdict: Result<(), MapRejection>,
    information: Option<Matrix6<f64>>,
}

/// A registration a stage refused before the verification: the estimate so far and why.
struct Refusal {
    target_from_source: Isometry3<f64>,
    /// Boxed: a rejection carries its numbers, and every stage's `Result` would otherwise be as
    /// large as the largest of them.
    reason: Box<MapRejection>,
}

impl Refusal {
    fn new(target_from_source: Isometry3<f64>, reason: MapRejection) -> Self {
        Self {
            target_from_source,
            reason: Box::new(reason),
        }
    }
}

impl From<Refusal> for Outcome {
    fn from(refusal: Refusal) -> Self {
        Self {
            target_from_source: refusal.target_from_source,
            verdict: Err(*refusal.reason),
            information: None,
        }
    }
}

/// A stage's result, or the registration it refused.
type Stage<T> = Result<T, Refusal>;

/// The stages of the module documentation, in order; each fills its part of `scores`.
fn run_stages(
    source: MapPoints<'_>,
    target: MapPoints<'_>,
    config: &MapRegistrationConfig,
    free_space: Option<&FreeSpaceCheck<'_>>,
    scores: &mut MapRegistrationScores,
) -> Stage<Outcome> {
    let started = Instant::now();
    let inputs = (source.points, target.points);
    let clean = downsample::clean_pair(
        source,
        target,
        config.voxel_m,
        config.normal_radius_voxels,
        config.min_normal_neighbours,
    );
    let levels = Levels::new(&clean, started, config, scores)?;
    let voxel = levels.voxel;
    let (source_map, target_map) = describe(levels.source, levels.target, voxel, config, scores)?;
    let matches = match_features(&source_map, &target_map, config, scores)?;
    let candidates =
        consistent_hypotheses(&source_map, &target_map, &matches, voxel, config, scores)?;

    let stage = Instant::now();
    let fine_maps = levels.refinement.map(|(source_fine, target_fine)| {
        rayon::join(
            || RefinementMap::new(source_fine.into_owned(), config),
            || RefinementMap::new(target_fine.into_owned(), config),
        )
    });
    let (fine_source, fine_target) = match &fine_maps {
        Some((s, t)) => (s.fine_view(), t.fine_view()),
        None => (source_map.fine_view(), target_map.fine_view()),
    };
    let judge = Judge {
        source_map: &source_map,
        target_map: &target_map,
        fine: FineLevel {
            source: fine_source,
            target: fine_target,
            distance_m: config
                .refine_distances_voxels
                .last()
                .copied()
                .unwrap_or(1.0)
                * scores.refine_voxel_m,
        },
        matched: (&candidates.source_points, &candidates.target_points),
        voxel_m: voxel,
        free_space,
        inputs,
        colour_gains: scores.source_colour_gains,
        config,
    };
    scores.timings.refinement_ms = elapsed_ms(stage);
    Ok(decide(&judge, &candidates.hypotheses, scores))
}

/// Stage 1's output: the feature level (the cheaper, for descriptors, matching and the coarse
/// G-ICP stages) and, when finer, the refinement level (the final G-ICP stage and the
/// verification), both borrowed from the cleaned maps when already within their point budget.
struct Levels<'c> {
    source: Cow<'c, Cloud>,
    target: Cow<'c, Cloud>,
    voxel: f64,
    /// `None` when a refinement level would be no finer than the feature level.
    refinement: Option<(Cow<'c, Cloud>, Cow<'c, Cloud>)>,
}

impl<'c> Levels<'c> {
    /// Stage 1, downsampling: from the clean finest level `clean`, the feature level and the
    /// refinement level.
    fn new(
        clean: &'c (Cloud, Cloud, f64),
        started: Instant,
        config: &MapRegistrationConfig,
        scores: &mut MapRegistrationScores,
    ) -> Stage<Self> {
        let (source_clean, target_clean, finest) = clean;
        let (source_down, target_down, voxel) =
            downsample::cap_pair(source_clean, target_clean, *finest, config.max_points);
        let (source_fine, target_fine, refine_voxel) = downsample::cap_pair(
            source_clean,
            target_clean,
            *finest,
            config.refine_max_points,
        );
        // A refinement level no finer than the feature level is the feature level.
        let separate_refinement_level = refine_voxel < voxel;
        scores.voxel_m = voxel;
        scores.source_points = source_down.len();
        scores.target_points = target_down.len();
        scores.refine_voxel_m = refine_voxel.min(voxel);
        scores.refine_source_points = source_fine.len();
        scores.refine_target_points = target_fine.len();
        if !separate_refinement_level {
            scores.refine_source_points = source_down.len();
            scores.refine_target_points = target_down.len();
        }
        scores.timings.downsample_ms = elapsed_ms(started);
        tracing::debug!(
            voxel_m = voxel,
            refine_voxel_m = scores.refine_voxel_m,
            source = scores.source_points,
            target = scores.target_points,
            ms = scores.timings.downsample_ms,
            "downsampled"
        );
        if scores.source_points < MIN_POINTS || scores.target_points < MIN_POINTS {
            let reason = MapRejection::TooFewPoints {
                source_points: scores.source_points,
                target_points: scores.target_points,
                required: MIN_POINTS,
            };
            return Err(Refusal::new(Isometry3::identity(), reason));
        }
        Ok(Self {
            source: source_down,
            target: target_down,
            voxel,
            refinement: separate_refinement_level.then_some((source_fine, target_fine)),
        })
    }
}

/// Stage 2: normals and descriptors of both feature-level maps.
fn describe(
    source: Cow<'_, Cloud>,
    target: Cow<'_, Cloud>,
    voxel: f64,
    config: &MapRegistrationConfig,
    scores: &mut MapRegistrationScores,
) -> Stage<(PreparedMap, PreparedMap)> {
    let stage = Instant::now();
    let gains = match (&source.colours, &target.colours) {
        (Some(s), Some(t)) if config.balance_colours => {
            colour::relative_white_balance(s, t, config.max_white_balance_gain.ln())
        }
        _ => [1.0; 3],
    };
    scores.source_colour_gains = gains.map(f64::from);
    let (source_map, target_map) = rayon::join(
        || prepare(source.into_owned(), voxel, gains, config),
        || prepare(target.into_owned(), voxel, [1.0; 3], config),
    );
    scores.source_features = source_map.features.len();
    scores.target_features = target_map.features.len();
    scores.timings.features_ms = elapsed_ms(stage);
    tracing::debug!(
        source = scores.source_features,
        target = scores.target_features,
        ms = scores.timings.features_ms,
        "described"
    );
    if scores.source_features < MIN_POINTS || scores.target_features < MIN_POINTS {
        let reason = MapRejection::TooFewFeatures {
            source_features: scores.source_features,
            target_features: scores.target_features,
            required: MIN_POINTS,
        };
        return Err(Refusal::new(Isometry3::identity(), reason));
    }
    Ok((source_map, target_map))
}

/// Stage 3: correspondences between the two maps' descriptors.
fn match_features(
    source_map: &PreparedMap,
    target_map: &PreparedMap,
    config: &MapRegistrationConfig,
    scores: &mut MapRegistrationScores,
) -> Stage<Vec<FeatureMatch>> {
    let stage = Instant::now();
    let matches = correspondences::match_descriptors(
        &source_map.descriptors,
        &target_map.descriptors,
        &MatchParams {
            max_per_map: config.max_matched_features,
            max_ratio: config.match_ratio as f32,
            max_correspondences: config.max_correspondences,
            min_correspondences: config.min_correspondences,
        },
    );
    scores.correspondences = matches.len();
    scores.mutual_correspondences = matches.iter().filter(|m| m.mutual).count();
    scores.timings.matching_ms = elapsed_ms(stage);
    tracing::debug!(
        correspondences = scores.correspondences,
        mutual = scores.mutual_correspondences,
        ms = scores.timings.matching_ms,
        "matched"
    );
    if matches.len() < config.min_consistent_correspondences {
        let reason = MapRejection::TooFewCorrespondences {
            found: matches.len(),
            required: config.min_consistent_correspondences,
        };
        return Err(Refusal::new(Isometry3::identity(), reason));
    }
    Ok(matches)
}

/// Stage 4's output: the candidate transforms (the best hypothesis first, then the distinct
/// alternatives nearly as well supported), and the matched points.
struct Candidates {
    hypotheses: Vec<Hypothesis>,
    source_points: Vec<Point3<f64>>,
    target_points: Vec<Point3<f64>>,
}

/// Stage 4, the consistent subset: the best transform of the cliques and RANSAC, refused when
/// too few correspondences support it, and the distinct alternatives whose own supporters reach
/// `max_ambiguity_ratio` of its (up to `max_verified_hypotheses` in all), which
/// [`decision`] verifies too.
fn consistent_hypotheses(
    source_map: &PreparedMap,
    target_map: &PreparedMap,
    matches: &[FeatureMatch],
    voxel: f64,
    config: &MapRegistrationConfig,
    scores: &mut MapRegistrationScores,
) -> Stage<Candidates> {
    let stage = Instant::now();
    let point_of = |map: &PreparedMap, feature: u32| {
        map.tree.positions()[map.features.indices[feature as usize] as usize].cast::<f64>()
    };
    let (source_points, target_points): (Vec<Point3<f64>>, Vec<Point3<f64>>) = matches
        .iter()
        .map(|m| {
            (
                point_of(source_map, m.source),
                point_of(target_map, m.target),
            )
        })
        .unzip();
    let ransac = RansacParams {
        inlier_distance_m: config.inlier_distance_voxels * voxel,
        edge_tolerance_m: config.edge_tolerance_voxels * voxel,
        min_sample_spread_m: config.min_sample_spread_voxels * voxel,
        max_samples: config.ransac_max_samples,
        min_samples: config.ransac_min_samples,
        confidence: config.ransac_confidence,
        seed: config.ransac_seed,
        distinct_rotation_rad: config.distinct_rotation_rad,
        distinct_translation_m: config.distinct_translation_m,
        cliques: (config.clique_seeds > 0).then_some(CliqueParams {
            tolerance_m: config.edge_tolerance_voxels * voxel,
            max_seeds: config.clique_seeds,
            max_clique: config.max_clique_size,
        }),
    };
    let consensus = find_consensus(&source_points, &target_points, &ransac);
    scores.ransac_samples = consensus.samples;
    scores.ransac_fitted = consensus.fitted;
    scores.timings.consistency_ms = elapsed_ms(stage);
    score_support(&consensus, &source_points, scores);
    let best_support = scores.consistent_correspondences;
    tracing::debug!(
        best = best_support,
        runner_up = scores.runner_up_support,
        samples = consensus.samples,
        fitted = consensus.fitted,
        ms = scores.timings.consistency_ms,
        "consensus"
    );
    let Some(best) = consensus.best else {
        let reason = MapRejection::TooFewConsistent {
            found: 0,
            required: config.min_consistent_correspondences,
        };
        return Err(Refusal::new(Isometry3::identity(), reason));
    };
    let coarse = best.target_from_source;
    if best_support < config.min_consistent_correspondences {
        let reason = MapRejection::TooFewConsistent {
            found: best_support,
            required: config.min_consistent_correspondences,
        };
        return Err(Refusal::new(coarse, reason));
    }
    let mut hypotheses = vec![best.clone()];
    if scores.ambiguity_ratio > config.max_ambiguity_ratio {
        // The alternatives, by their own supporters (those the best does not also have).
        let mut alternatives: Vec<(usize, &Hypothesis)> = consensus.pool[1..]
            .iter()
            .map(|h| {
                let own = h
                    .inliers
                    .iter()
                    .filter(|k| best.inliers.binary_search(k).is_err())
                    .count();
                (own, h)
            })
            .filter(|&(own, _)| own as f64 > config.max_ambiguity_ratio * best_support as f64)
            .collect();
        alternatives.sort_by_key(|a| std::cmp::Reverse(a.0));
        hypotheses.extend(
            alternatives
                .into_iter()
                .take(config.max_verified_hypotheses.saturating_sub(1))
                .map(|(_, h)| h.clone()),
        );
    }
    Ok(Candidates {
        hypotheses,
        source_points,
        target_points,
    })
}

/// The support of RANSAC's best and runner-up hypotheses, their ratio and how far apart they
/// are (at the centre of the matched source points).
fn score_support(
    consensus: &Consensus,
    source_points: &[Point3<f64>],
    scores: &mut MapRegistrationScores,
) {
    let best_support = consensus.best.as_ref().map_or(0, |h| h.support());
    scores.consistent_correspondences = best_support;
    scores.runner_up_support = consensus.runner_up.as_ref().map_or(0, |h| h.support());
    if best_support > 0 {
        scores.ambiguity_ratio = scores.runner_up_support as f64 / best_support as f64;
    }
    if let (Some(best), Some(runner_up)) = (&consensus.best, &consensus.runner_up) {
        let centre = Point3::from(
            source_points
                .iter()
                .fold(nalgebra::Vector3::zeros(), |sum, p| sum + p.coords)
                / source_points.len() as f64,
        );
        let (angle, distance) = transform_difference(
            &best.target_from_source,
            &runner_up.target_from_source,
            &centre,
        );
        scores.runner_up_rotation_deg = angle.to_degrees();
        scores.runner_up_translation_m = distance;
    }
}
