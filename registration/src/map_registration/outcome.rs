//! What [`super::register_maps`] returns: the estimate, the verdict with the numbers that decided
//! it, and everything measured on the way.

use crate::RegistrationFailure;
use nalgebra::{Isometry3, Matrix6};
use serde::Serialize;

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
    #[error(
        "two verified transforms {rotation_deg:.1} degrees and {translation_m:.2} m apart tie: residuals {:.4} / {:.4} m, overlaps {:.3} / {:.3}, depth agreements {:.3} / {:.3}",
        residuals_m[0], residuals_m[1], overlaps[0], overlaps[1], depth_agreements[0], depth_agreements[1]
    )]
    Tied {
        rotation_deg: f64,
        translation_m: f64,
        /// Of the better supported first (depth agreements NaN without the free-space test).
        residuals_m: [f64; 2],
        overlaps: [f64; 2],
        depth_agreements: [f64; 2],
    },
    #[error("G-ICP refinement failed: {0}")]
    RefinementFailed(RegistrationFailure),
    #[error(
        "G-ICP moved {rotation_deg:.1} degrees and {translation_m:.2} m from the correspondences' transform and keeps {kept} of its {support} supporters, at least {required} needed"
    )]
    RefinementDrifted {
        kept: usize,
        support: usize,
        required: usize,
        rotation_deg: f64,
        translation_m: f64,
    },
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
        "map points lie in the free space of the other map's depth views: depth agreement {agreement:.3} below {required:.3}"
    )]
    FreeSpaceViolated { agreement: f64, required: f64 },
    #[error(
        "{comparisons} depth comparisons against the other map's depth views, at least {required} needed"
    )]
    TooFewDepthComparisons { comparisons: usize, required: usize },
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
    /// Per-channel gains of the source's colours for its colour signatures: the two maps'
    /// relative white balance (`colour::relative_white_balance`).
    pub source_colour_gains: [f64; 3],
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
    /// Candidate transforms refined and verified (more than one when the correspondences left
    /// them nearly tied), and whether the verification chose between them.
    pub hypotheses_verified: usize,
    pub ambiguity_resolved: bool,
    /// Supporting correspondences of the refined transform.
    pub support_kept: usize,
    pub gicp_iterations: usize,
    pub gicp_converged: bool,
    /// Source points with a target point within the finest refinement distance.
    pub overlapping_points: usize,
    /// `overlapping_points` over the smaller map's points.
    pub overlap_fraction: f64,
    /// RMS point-to-plane distance of the overlapping points (metres).
    pub residual_m: f64,
    /// Marginal standard deviations of the estimate (see [`verification`](super::verification)).
    pub rotation_sigma_deg: f64,
    pub translation_sigma_m: f64,
    /// Overlapping points compared in colour, the fraction of them that agree, the fraction that
    /// agree when paired at random, and Cohen's kappa of the two (see [`verification`](super::verification); NaN when
    /// none were compared, the kappa also when the colours cannot tell).
    pub colour_compared: usize,
    pub colour_agreement: f64,
    pub colour_chance: f64,
    pub colour_kappa: f64,
    /// Per-channel gains applied to the source's colours before comparing (white balance).
    pub colour_gains: [f64; 3],
    /// The free-space test of the result, when the maps' depth views were given: the smaller
    /// direction's depth agreement and decisive comparisons (NaN and 0 without).
    pub depth_agreement: f64,
    pub depth_comparisons: usize,
    pub timings: StageTimings,
}

impl MapRegistrationScores {
    pub(super) fn new(source_input_points: usize, target_input_points: usize) -> Self {
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
            source_colour_gains: [1.0; 3],
            correspondences: 0,
            mutual_correspondences: 0,
            ransac_samples: 0,
            ransac_fitted: 0,
            consistent_correspondences: 0,
            runner_up_support: 0,
            ambiguity_ratio: f64::NAN,
            runner_up_rotation_deg: f64::NAN,
            runner_up_translation_m: f64::NAN,
            hypotheses_verified: 0,
            ambiguity_resolved: false,
            support_kept: 0,
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
            colour_gains: [1.0; 3],
            depth_agreement: f64::NAN,
            depth_comparisons: 0,
            timings: StageTimings::default(),
        }
    }
}

/// The outcome of [`register_maps`](super::register_maps).
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
    /// [`verification`](super::verification).
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
