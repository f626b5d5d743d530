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
//! 3. [`correspondences`]: mutual nearest neighbours in descriptor space, topped up with the best
//!    one-way matches when too few are mutual.
//! 4. [`consistency`]: RANSAC over three correspondences with distance-preservation pre-checks
//!    and local least-squares refits: the transform most correspondences agree on, and the best
//!    *distinct* runner-up, whose relative support measures ambiguity (symmetric rooms,
//!    repeated shelves).
//! 5. [`verification`]: coarse-to-fine G-ICP from the RANSAC transform (the registration crate's, plane to
//!    plane, with each map's covariances), then overlap, point-to-plane residual, the
//!    information matrix of the estimate and, with colour, how far the overlap's colours agree
//!    beyond chance (Cohen's kappa of chromaticity agreement).
//!
//! The verdict refuses, with the numbers, every estimate that is not trustworthy: too few points,
//! descriptors or consistent correspondences; ambiguous (the runner-up nearly as well supported);
//! G-ICP failure; too little overlap (below `min_overlap_fraction`, or below the smaller
//! `colour_confirmed_overlap_fraction` when colour agrees with a kappa of at least
//! `colour_confirmed_kappa`); a high residual; a degenerate overlap (one plane, a corridor: a
//! direction the overlap does not constrain); or colours that agree no better than chance.
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
//! correspondence evidence and, between agents, to the free-space check of [`crate::map_links`].
//! A kappa well above anything a wrong pose reaches confirms a pose enough to accept a small
//! overlap (`colour_confirmed_*`). Colour also raises chance support (matches concentrate in
//! regions of distinctive colour), which the ambiguity test absorbs. The measurements behind
//! these choices, per stage and per variant tried, are in docs/benchmarks.md
//! (`mac-ego3d bench map-registration`).
//!
//! The information matrix treats residuals as independent and is therefore optimistic.

pub mod colour;
pub mod consistency;
pub mod correspondences;
pub mod downsample;
pub mod fpfh;
pub mod verification;

#[cfg(test)]
mod tests;

use std::time::Instant;

use config::MapRegistrationConfig;
use nalgebra::{Isometry3, Matrix6, Point3};
use registration::covariance::smallest_eigenvector;
use registration::{PointCloud, PointTree, RegistrationFailure};
use serde::Serialize;

use colour::Rgb;
use consistency::{RansacParams, find_consensus, transform_difference};
use correspondences::{MATCH_LEN, MatchDescriptor};
use downsample::Cloud;
pub use downsample::MapPoints;
use verification::{ColourCheck, RefinementParams, measure_overlap, refine};

/// Why a map registration is refused. Each names the numbers that decided it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapRejection {
    #[error(
        "{source_points} source and {target_points} target points after downsampling, at least {required} each needed"
    )]
    TooFewPoints {
        source_points: usize,
        target_points: usize,
        required: usize,
    },
    #[error(
        "{source_features} source and {target_features} target descriptors, at least {required} each needed"
    )]
    TooFewFeatures {
        source_features: usize,
        target_features: usize,
        required: usize,
    },
    #[error("{found} descriptor correspondences, at least {required} needed")]
    TooFewCorrespondences { found: usize, required: usize },
    #[error("{found} geometrically consistent correspondences, at least {required} needed")]
    TooFewConsistent { found: usize, required: usize },
    #[error(
        "ambiguous: a transform {rotation_deg:.1} degrees and {translation_m:.2} m from the best has {runner_up} supporters against {best} (ratio {ratio:.2}, at most {allowed:.2} allowed)"
    )]
    Ambiguous {
        best: usize,
        runner_up: usize,
        ratio: f64,
        allowed: f64,
        rotation_deg: f64,
        translation_m: f64,
    },
    #[error("G-ICP refinement failed: {0}")]
    RefinementFailed(RegistrationFailure),
    #[error(
        "overlap {found:.3} of the smaller map below {required:.3} (or {confirmed:.3} with a colour kappa of {required_kappa:.2}; found {kappa:.2})"
    )]
    LowOverlap {
        found: f64,
        required: f64,
        /// The smaller overlap allowed when colour confirms the pose, the kappa that takes and
        /// the kappa found (NaN without colour).
        confirmed: f64,
        required_kappa: f64,
        kappa: f64,
    },
    #[error("point-to-plane residual {found_m:.4} m above {allowed_m:.4} m")]
    HighResidual { found_m: f64, allowed_m: f64 },
    #[error(
        "degenerate overlap: standard deviation {rotation_deg:.2} degrees / {translation_m:.3} m along the worst direction, at most {allowed_rotation_deg:.2} degrees / {allowed_translation_m:.3} m allowed"
    )]
    Degenerate {
        rotation_deg: f64,
        translation_m: f64,
        allowed_rotation_deg: f64,
        allowed_translation_m: f64,
    },
    #[error(
        "colours disagree: {agreement:.3} of {compared} overlapping points agree in chromaticity, {chance:.3} by chance: kappa {kappa:.3} below {required:.3}"
    )]
    ColourDisagreement {
        compared: usize,
        agreement: f64,
        chance: f64,
        kappa: f64,
        required: f64,
    },
}

/// Wall time of each stage (milliseconds).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StageTimings {
    pub downsample_ms: f64,
    /// Kd-trees, G-ICP covariances, normals and descriptors of both maps.
    pub features_ms: f64,
    pub matching_ms: f64,
    pub consistency_ms: f64,
    /// G-ICP, and the refinement level's covariances when it is a separate level.
    pub refinement_ms: f64,
    pub verification_ms: f64,
}

/// Everything measured on the way; fields of stages that did not run stay at their defaults
/// (0, or NaN for ratios and distances).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MapRegistrationScores {
    pub source_input_points: usize,
    pub target_input_points: usize,
    /// Voxel edge both maps were downsampled with (metres).
    pub voxel_m: f64,
    pub source_points: usize,
    pub target_points: usize,
    /// Voxel and points of the refinement level (the final G-ICP stage and the verification);
    /// the feature level's when that is already fine enough.
    pub refine_voxel_m: f64,
    pub refine_source_points: usize,
    pub refine_target_points: usize,
    pub source_features: usize,
    pub target_features: usize,
    /// Whether colour was used (both maps have colours).
    pub colour: bool,
    /// Putative correspondences, and how many of them are mutual nearest neighbours.
    pub correspondences: usize,
    pub mutual_correspondences: usize,
    pub ransac_samples: usize,
    pub ransac_fitted: usize,
    /// Support of the best hypothesis.
    pub consistent_correspondences: usize,
    /// Support of the best hypothesis distinct from it, not counting correspondences the best
    /// one also explains (0 without one).
    pub runner_up_support: usize,
    /// `runner_up_support / consistent_correspondences`.
    pub ambiguity_ratio: f64,
    /// How far the runner-up is from the best (NaN without one).
    pub runner_up_rotation_deg: f64,
    pub runner_up_translation_m: f64,
    pub gicp_iterations: usize,
    pub gicp_converged: bool,
    /// Source points with a target point within the finest refinement distance.
    pub overlapping_points: usize,
    /// `overlapping_points` over the smaller map's points.
    pub overlap_fraction: f64,
    /// RMS point-to-plane distance of the overlapping points (metres).
    pub residual_m: f64,
    /// Marginal standard deviations of the estimate (see [`verification`]).
    pub rotation_sigma_deg: f64,
    pub translation_sigma_m: f64,
    /// Overlapping points compared in colour, the fraction of them that agree, the fraction that
    /// agree when paired at random, and Cohen's kappa of the two (see [`verification`]; NaN when
    /// none were compared, the kappa also when the colours cannot tell).
    pub colour_compared: usize,
    pub colour_agreement: f64,
    pub colour_chance: f64,
    pub colour_kappa: f64,
    pub timings: StageTimings,
}

impl MapRegistrationScores {
    fn new(source_input_points: usize, target_input_points: usize) -> Self {
        Self {
            source_input_points,
            target_input_points,
            voxel_m: f64::NAN,
            source_points: 0,
            target_points: 0,
            refine_voxel_m: f64::NAN,
            refine_source_points: 0,
            refine_target_points: 0,
            source_features: 0,
            target_features: 0,
            colour: false,
            correspondences: 0,
            mutual_correspondences: 0,
            ransac_samples: 0,
            ransac_fitted: 0,
            consistent_correspondences: 0,
            runner_up_support: 0,
            ambiguity_ratio: f64::NAN,
            runner_up_rotation_deg: f64::NAN,
            runner_up_translation_m: f64::NAN,
            gicp_iterations: 0,
            gicp_converged: false,
            overlapping_points: 0,
            overlap_fraction: f64::NAN,
            residual_m: f64::NAN,
            rotation_sigma_deg: f64::NAN,
            translation_sigma_m: f64::NAN,
            colour_compared: 0,
            colour_agreement: f64::NAN,
            colour_chance: f64::NAN,
            colour_kappa: f64::NAN,
            timings: StageTimings::default(),
        }
    }
}

/// The outcome of [`register_maps`].
#[derive(Debug, Clone, PartialEq)]
pub struct MapRegistration {
    /// The estimate: maps source-map points into the target map's frame. The refined one when
    /// refinement ran, RANSAC's when it did not, identity when there was nothing to estimate from.
    pub target_from_source: Isometry3<f64>,
    pub scores: MapRegistrationScores,
    /// Accepted, or why not.
    pub verdict: Result<(), MapRejection>,
    /// Information matrix of `target_from_source` (6x6; rotation first, then translation; a right
    /// perturbation `T Exp(delta)`, the pose graph's edge convention), from the point-to-plane
    /// residuals at the solution; `None` when refinement did not run. Optimistic: see
    /// [`verification`].
    pub information: Option<Matrix6<f64>>,
    pub elapsed_ms: f64,
}

impl MapRegistration {
    pub fn is_accepted(&self) -> bool {
        self.verdict.is_ok()
    }

    /// Covariance of `target_from_source` (inverse of [`Self::information`]), `None` when there
    /// is no information or it is singular (a degenerate overlap).
    pub fn covariance(&self) -> Option<Matrix6<f64>> {
        self.information?.try_inverse()
    }
}

/// A map needs at least this many points after downsampling, and descriptors, to be registered:
/// fewer cannot describe a scene that fixes six degrees of freedom.
pub const MIN_POINTS: usize = 30;

fn elapsed_ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

/// A downsampled map with everything the later stages need.
struct PreparedMap {
    tree: PointTree,
    normals: Vec<Option<nalgebra::Vector3<f32>>>,
    features: fpfh::Features,
    /// Per feature: the FPFH descriptor and the weighted colour signature.
    descriptors: Vec<MatchDescriptor>,
    /// Per point, when colour is used.
    colours: Option<Vec<Rgb>>,
}

/// Normals, descriptors and, with `colours`, colour signatures of a downsampled map.
fn prepare(cloud: Cloud, voxel_m: f64, config: &MapRegistrationConfig) -> PreparedMap {
    let tree = PointTree::with_covariances(
        PointCloud::from_positions(cloud.points),
        config.covariance_neighbours,
        config.covariance_epsilon,
    )
    .expect("downsampled points are finite and few");
    let normal_radius = config.normal_radius_voxels * voxel_m;
    let feature_radius = config.feature_radius_voxels * voxel_m;
    let neighbourhoods = fpfh::radius_neighbours(&tree, normal_radius.max(feature_radius));
    let (normals, features) = fpfh::describe_with(
        tree.positions(),
        &neighbourhoods,
        (normal_radius, config.min_normal_neighbours),
        (feature_radius, config.min_feature_neighbours),
    );
    let signatures = cloud
        .colours
        .as_ref()
        .map(|colours| colour::signatures(colours, &neighbourhoods, &features.indices));
    let weight = config.colour_weight as f32;
    let descriptors = (0..features.len())
        .map(|k| {
            let mut d = [0.0f32; MATCH_LEN];
            d[..fpfh::DESCRIPTOR_LEN].copy_from_slice(&features.descriptors[k]);
            if let Some(signature) = signatures.as_ref().and_then(|s| s[k].as_ref()) {
                for (to, from) in d[fpfh::DESCRIPTOR_LEN..].iter_mut().zip(signature) {
                    *to = weight * from;
                }
            }
            d
        })
        .collect();
    PreparedMap {
        tree,
        normals,
        features,
        descriptors,
        colours: cloud.colours,
    }
}

/// A refinement-level map: covariances for G-ICP, normals (the covariances' normal directions)
/// for the verification.
struct RefinementMap {
    tree: PointTree,
    normals: Vec<Option<nalgebra::Vector3<f32>>>,
    colours: Option<Vec<Rgb>>,
}

impl RefinementMap {
    fn new(cloud: Cloud, config: &MapRegistrationConfig) -> Self {
        let tree = PointTree::with_covariances(
            PointCloud::from_positions(cloud.points),
            config.covariance_neighbours,
            config.covariance_epsilon,
        )
        .expect("downsampled points are finite and few");
        // The plane covariance I - (1 - eps) n n^T has n as its smallest eigenvector.
        let normals = tree
            .cloud()
            .covariances
            .iter()
            .map(|c| Some(smallest_eigenvector(&c.to_matrix()).cast::<f32>()))
            .collect();
        Self {
            tree,
            normals,
            colours: cloud.colours,
        }
    }
}

/// Registers the `source` map onto the `target` map (see the module documentation). Colours
/// are used when both maps have them.
pub fn register_maps<'a, 'b>(
    source: impl Into<MapPoints<'a>>,
    target: impl Into<MapPoints<'b>>,
    config: &MapRegistrationConfig,
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
    let finish = |target_from_source: Isometry3<f64>,
                  scores: MapRegistrationScores,
                  verdict: Result<(), MapRejection>,
                  information: Option<Matrix6<f64>>| {
        match &verdict {
            Ok(()) => tracing::debug!("map registration accepted"),
            Err(reason) => tracing::debug!(%reason, "map registration refused"),
        }
        MapRegistration {
            target_from_source,
            scores,
            verdict,
            information,
            elapsed_ms: elapsed_ms(start),
        }
    };

    // 1. Downsampling: the clean finest level, the feature level and the refinement level.
    let stage = Instant::now();
    let (source_clean, target_clean, finest) = downsample::clean_pair(
        source,
        target,
        config.voxel_m,
        config.normal_radius_voxels,
        config.min_normal_neighbours,
    );
    let (source_down, target_down, voxel) =
        downsample::cap_pair(&source_clean, &target_clean, finest, config.max_points);
    let (source_fine, target_fine, refine_voxel) = downsample::cap_pair(
        &source_clean,
        &target_clean,
        finest,
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
    scores.timings.downsample_ms = elapsed_ms(stage);
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
        return finish(Isometry3::identity(), scores, Err(reason), None);
    }

    // 2. Normals and descriptors.
    let stage = Instant::now();
    let (source_map, target_map) = rayon::join(
        || prepare(source_down.into_owned(), voxel, config),
        || prepare(target_down.into_owned(), voxel, config),
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
        return finish(Isometry3::identity(), scores, Err(reason), None);
    }

    // 3. Correspondences.
    let stage = Instant::now();
    let matches = correspondences::match_descriptors(
        &source_map.descriptors,
        &target_map.descriptors,
        config.max_matched_features,
        config.min_correspondences,
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
        return finish(Isometry3::identity(), scores, Err(reason), None);
    }

    // 4. Consistent subset: best and runner-up.
    let stage = Instant::now();
    let point_of = |map: &PreparedMap, feature: u32| {
        map.tree.positions()[map.features.indices[feature as usize] as usize].cast::<f64>()
    };
    let (source_points, target_points): (Vec<Point3<f64>>, Vec<Point3<f64>>) = matches
        .iter()
        .map(|m| {
            (
                point_of(&source_map, m.source),
                point_of(&target_map, m.target),
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
    };
    let consensus = find_consensus(&source_points, &target_points, &ransac);
    scores.ransac_samples = consensus.samples;
    scores.ransac_fitted = consensus.fitted;
    scores.timings.consistency_ms = elapsed_ms(stage);
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
        return finish(Isometry3::identity(), scores, Err(reason), None);
    };
    let coarse = best.target_from_source;
    if best_support < config.min_consistent_correspondences {
        let reason = MapRejection::TooFewConsistent {
            found: best_support,
            required: config.min_consistent_correspondences,
        };
        return finish(coarse, scores, Err(reason), None);
    }
    if scores.ambiguity_ratio > config.max_ambiguity_ratio {
        let reason = MapRejection::Ambiguous {
            best: best_support,
            runner_up: scores.runner_up_support,
            ratio: scores.ambiguity_ratio,
            allowed: config.max_ambiguity_ratio,
            rotation_deg: scores.runner_up_rotation_deg,
            translation_m: scores.runner_up_translation_m,
        };
        return finish(coarse, scores, Err(reason), None);
    }

    // 5. G-ICP refinement.
    let stage = Instant::now();
    let fine_maps = separate_refinement_level.then(|| {
        rayon::join(
            || RefinementMap::new(source_fine.into_owned(), config),
            || RefinementMap::new(target_fine.into_owned(), config),
        )
    });
    let (fine_source, fine_target) = match &fine_maps {
        Some((s, t)) => (
            (&s.tree, &s.normals, &s.colours),
            (&t.tree, &t.normals, &t.colours),
        ),
        None => (
            (&source_map.tree, &source_map.normals, &source_map.colours),
            (&target_map.tree, &target_map.normals, &target_map.colours),
        ),
    };
    let distances = &config.refine_distances_voxels;
    let fine_distance_m = distances.last().copied().unwrap_or(1.0) * scores.refine_voxel_m;
    let refined = refine(
        (source_map.tree.cloud(), &target_map.tree),
        (fine_source.0.cloud(), fine_target.0),
        &coarse,
        &RefinementParams {
            coarse_distances_m: distances[..distances.len().saturating_sub(1)]
                .iter()
                .map(|d| d * voxel)
                .collect(),
            fine_distance_m,
            max_iterations: config.gicp_max_iterations,
            rotation_epsilon_rad: config.gicp_rotation_epsilon_rad,
            translation_epsilon_m: config.gicp_translation_epsilon_m,
        },
    );
    scores.gicp_iterations = refined.iterations;
    scores.gicp_converged = refined.converged;
    scores.timings.refinement_ms = elapsed_ms(stage);
    tracing::debug!(
        iterations = refined.iterations,
        converged = refined.converged,
        ms = scores.timings.refinement_ms,
        "refined"
    );
    if let Some(failure) = refined.failure.clone().filter(|f| !f.pose_is_usable()) {
        return finish(
            coarse,
            scores,
            Err(MapRejection::RefinementFailed(failure)),
            None,
        );
    }
    let estimate = refined.target_from_source;

    // 6. Verification.
    let stage = Instant::now();
    let colour_check = match (fine_source.2, fine_target.2) {
        (Some(source), Some(target)) => Some(ColourCheck {
            source,
            target,
            tolerance: config.colour_tolerance as f32,
        }),
        _ => None,
    };
    let overlap = measure_overlap(
        fine_source.0.positions(),
        fine_target.0,
        fine_target.1,
        &estimate,
        fine_distance_m,
        config.residual_sigma_floor_m,
        colour_check,
    );
    scores.overlapping_points = overlap.overlapping;
    scores.overlap_fraction = overlap.fraction;
    scores.residual_m = overlap.residual_m;
    scores.rotation_sigma_deg = overlap.rotation_sigma_rad.to_degrees();
    scores.translation_sigma_m = overlap.translation_sigma_m;
    scores.colour_compared = overlap.colour_compared;
    scores.colour_agreement = overlap.colour_agreement();
    scores.colour_chance = overlap.colour_chance;
    scores.colour_kappa = overlap.colour_kappa();
    scores.timings.verification_ms = elapsed_ms(stage);
    tracing::debug!(
        overlap = overlap.fraction,
        residual_m = overlap.residual_m,
        colour_agreement = scores.colour_agreement,
        colour_kappa = scores.colour_kappa,
        ms = scores.timings.verification_ms,
        "verified"
    );
    let information = Some(overlap.information);
    let colour_judged = overlap.colour_compared >= config.min_colour_comparisons;
    let colour_confirms = colour_judged
        && overlap.colour_kappa() >= config.colour_confirmed_kappa
        && overlap.fraction >= config.colour_confirmed_overlap_fraction;
    let verdict = if overlap.fraction < config.min_overlap_fraction && !colour_confirms {
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
    };
    finish(estimate, scores, verdict, information)
}
