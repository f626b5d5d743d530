//! What [`super::register_maps`] returns: the estimate, the verdict with the numbers that decided
//! it, and everything measured on the way.

use crate::RegistrationFailure;
use nalgebra::{Isometry3, Matrix6};
use serde::Serialize;

/// Why a map registration is refused. Each names the numbers that decided it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapRejection {
    /// After downsampling a map has fewer points than [`super::MIN_POINTS`].
    #[error(
        "{source_points} source and {target_points} target points after downsampling, at least {required} each needed"
    )]
    TooFewPoints {
        /// Source map points after downsampling (feature level).
        source_points: usize,
        /// Target map points after downsampling (feature level).
        target_points: usize,
        /// [`super::MIN_POINTS`].
        required: usize,
    },
    /// A map has fewer points with a descriptor than [`super::MIN_POINTS`].
    #[error(
        "{source_features} source and {target_features} target descriptors, at least {required} each needed"
    )]
    TooFewFeatures {
        /// Source map points with a descriptor.
        source_features: usize,
        /// Target map points with a descriptor.
        target_features: usize,
        /// [`super::MIN_POINTS`].
        required: usize,
    },
    /// Fewer descriptor correspondences than a hypothesis needs supporters.
    #[error("{found} descriptor correspondences, at least {required} needed")]
    TooFewCorrespondences {
        /// Correspondences found.
        found: usize,
        /// `min_consistent_correspondences`.
        required: usize,
    },
    /// The best hypothesis has too few supporting correspondences (or none could be formed).
    #[error("{found} geometrically consistent correspondences, at least {required} needed")]
    TooFewConsistent {
        /// Supporters of the best hypothesis; 0 when there was none.
        found: usize,
        /// `min_consistent_correspondences`.
        required: usize,
    },
    /// A distinct alternative is nearly as well supported as the best hypothesis. Not returned
    /// by the current pipeline: near-tied alternatives are refined and verified instead, and
    /// two that still tie are refused as [`MapRejection::Tied`].
    #[error(
        "ambiguous: a transform {rotation_deg:.1} degrees and {translation_m:.2} m from the best has {runner_up} supporters against {best} (ratio {ratio:.2}, at most {allowed:.2} allowed)"
    )]
    Ambiguous {
        /// Supporters of the best hypothesis.
        best: usize,
        /// Supporters of the runner-up that the best does not also have.
        runner_up: usize,
        /// `runner_up / best`.
        ratio: f64,
        /// `max_ambiguity_ratio`.
        allowed: f64,
        /// Rotation between the two transforms (degrees)...
        rotation_deg: f64,
        /// ...and the distance between where they put the matched source points' centre
        /// (metres).
        translation_m: f64,
    },
    /// Two verified candidates that neither the free-space test nor the geometry tells apart.
    #[error(
        "two verified transforms {rotation_deg:.1} degrees and {translation_m:.2} m apart tie: residuals {:.4} / {:.4} m, overlaps {:.3} / {:.3}, depth agreements {:.3} / {:.3}",
        residuals_m[0], residuals_m[1], overlaps[0], overlaps[1], depth_agreements[0], depth_agreements[1]
    )]
    Tied {
        /// Rotation between the two refined transforms (degrees)...
        rotation_deg: f64,
        /// ...and the distance between where they put the fine source map's centre (metres).
        translation_m: f64,
        /// Point-to-plane residuals (metres), of the better supported first (the same order for
        /// `overlaps` and `depth_agreements`).
        residuals_m: [f64; 2],
        /// Overlap fractions of the smaller map.
        overlaps: [f64; 2],
        /// Free-space depth agreements, the smaller direction's; NaN without the free-space
        /// test.
        depth_agreements: [f64; 2],
    },
    /// The correspondences left distinct alternatives nearly tied, only this candidate passed
    /// the verification, and the overlap's colours do not confirm it: geometry that passes
    /// while the alternatives fail does not choose between symmetric fits.
    #[error(
        "unconfirmed: {rivals} distinct alternative(s) near in support failed the verification beside it (the strongest {rival_support} supporters against {support}, {rotation_deg:.1} degrees and {translation_m:.2} m away), and colour does not confirm it: kappa {kappa:.3} of {compared} points compared, at least {required:.3} over {required_compared} needed"
    )]
    Unconfirmed {
        /// Distinct alternatives verified beside it (all failed).
        rivals: usize,
        /// Supporters of the best supported of them...
        rival_support: usize,
        /// ...and of the accepted candidate.
        support: usize,
        /// Rotation between that alternative's hypothesis and the candidate's estimate
        /// (degrees)...
        rotation_deg: f64,
        /// ...and the distance between where they put the fine source map's centre (metres).
        translation_m: f64,
        /// The candidate's colour kappa (NaN without colour, or when the colours cannot tell).
        kappa: f64,
        /// Overlapping points compared in colour.
        compared: usize,
        /// `ambiguity_colour_kappa`.
        required: f64,
        /// `min_colour_comparisons`.
        required_compared: usize,
    },
    /// G-ICP from the hypothesis gave no usable pose; the estimate is the hypothesis.
    #[error("G-ICP refinement failed: {0}")]
    RefinementFailed(RegistrationFailure),
    /// G-ICP slid away from the hypothesis: the refined transform keeps too few of its
    /// supporting correspondences.
    #[error(
        "G-ICP moved {rotation_deg:.1} degrees and {translation_m:.2} m from the correspondences' transform and keeps {kept} of its {support} supporters, at least {required} needed"
    )]
    RefinementDrifted {
        /// Supporters still within the inlier distance after refinement.
        kept: usize,
        /// Supporters of the hypothesis.
        support: usize,
        /// `min_support_kept` of `support`, rounded up.
        required: usize,
        /// Rotation between the refined transform and the hypothesis (degrees)...
        rotation_deg: f64,
        /// ...and the distance between where they put the fine source map's centre (metres).
        translation_m: f64,
    },
    /// Too small a fraction of the smaller map overlaps the other, and colour does not confirm
    /// the pose.
    #[error(
        "overlap {found:.3} of the smaller map below {required:.3} (or {confirmed:.3} with a colour kappa of {required_kappa:.2}; found {kappa:.2})"
    )]
    LowOverlap {
        /// Overlap fraction of the smaller map.
        found: f64,
        /// `min_overlap_fraction`.
        required: f64,
        /// The smaller overlap allowed when colour confirms the pose
        /// (`colour_confirmed_overlap_fraction`).
        confirmed: f64,
        /// The kappa that confirms it (`colour_confirmed_kappa`).
        required_kappa: f64,
        /// The colour kappa found (NaN without colour, or when the colours cannot tell).
        kappa: f64,
    },
    /// The overlapping points lie too far from the other map's surfaces, or no residual could
    /// be measured (NaN).
    #[error("point-to-plane residual {found_m:.4} m above {allowed_m:.4} m")]
    HighResidual {
        /// RMS point-to-plane distance of the overlapping points (metres).
        found_m: f64,
        /// `max_residual_m`.
        allowed_m: f64,
    },
    /// The overlap leaves a direction (nearly) unconstrained: a plane, a corridor.
    #[error(
        "degenerate overlap: standard deviation {rotation_deg:.2} degrees / {translation_m:.3} m along the worst direction, at most {allowed_rotation_deg:.2} degrees / {allowed_translation_m:.3} m allowed"
    )]
    Degenerate {
        /// Marginal standard deviation along the worst rotation direction (degrees).
        rotation_deg: f64,
        /// Marginal standard deviation along the worst translation direction (metres).
        translation_m: f64,
        /// `max_rotation_sigma_rad`, in degrees.
        allowed_rotation_deg: f64,
        /// `max_translation_sigma_m`.
        allowed_translation_m: f64,
    },
    /// One direction of the free-space test, with enough decisive comparisons, agrees too
    /// little: a map's points lie where the other map's cameras saw through.
    #[error(
        "map points lie in the free space of the other map's depth views: depth agreement {agreement:.3} below {required:.3}"
    )]
    FreeSpaceViolated {
        /// That direction's depth agreement.
        agreement: f64,
        /// `min_depth_agreement`.
        required: f64,
    },
    /// The free-space test had too few decisive comparisons in one direction to vouch for the
    /// pose.
    #[error(
        "{comparisons} depth comparisons against the other map's depth views, at least {required} needed"
    )]
    TooFewDepthComparisons {
        /// The smaller direction's decisive (agreeing plus violating) comparisons.
        comparisons: usize,
        /// The keyframe alignment's `min_depth_comparisons`.
        required: usize,
    },
    /// The overlap's colours agree no better than chance (kappa below `min_colour_kappa`).
    #[error(
        "colours disagree: {agreement:.3} of {compared} overlapping points agree in chromaticity, {chance:.3} by chance: kappa {kappa:.3} below {required:.3}"
    )]
    ColourDisagreement {
        /// Overlapping points compared in colour.
        compared: usize,
        /// Fraction of them whose chromaticities agree.
        agreement: f64,
        /// Fraction that agree when paired at random.
        chance: f64,
        /// Cohen's kappa, `(agreement - chance) / (1 - chance)`.
        kappa: f64,
        /// `min_colour_kappa`.
        required: f64,
    },
}

/// Wall time of each stage (milliseconds).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StageTimings {
    /// Cleaning both maps (isolated points removed) and downsampling them to both levels.
    pub downsample_ms: f64,
    /// Kd-trees, G-ICP covariances, normals and descriptors of both maps.
    pub features_ms: f64,
    /// Descriptor matching.
    pub matching_ms: f64,
    /// Cliques and RANSAC: the hypotheses.
    pub consistency_ms: f64,
    /// The refinement level's kd-trees, covariances and normals, when it is a separate level
    /// (the G-ICP runs count in `verification_ms`).
    pub refinement_ms: f64,
    /// G-ICP refinement and verification of every candidate, the free-space test included.
    pub verification_ms: f64,
}

/// Everything measured on the way; fields of stages that did not run stay at their defaults
/// (0, or NaN for ratios and distances).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MapRegistrationScores {
    /// Source map points as given.
    pub source_input_points: usize,
    /// Target map points as given.
    pub target_input_points: usize,
    /// Voxel edge both maps were downsampled with (metres).
    pub voxel_m: f64,
    /// Source map points at the feature level.
    pub source_points: usize,
    /// Target map points at the feature level.
    pub target_points: usize,
    /// Voxel of the refinement level (the final G-ICP stage and the verification), metres; the
    /// feature level's when that is already fine enough.
    pub refine_voxel_m: f64,
    /// Source map points at the refinement level.
    pub refine_source_points: usize,
    /// Target map points at the refinement level.
    pub refine_target_points: usize,
    /// Source map points with a descriptor.
    pub source_features: usize,
    /// Target map points with a descriptor.
    pub target_features: usize,
    /// Whether colour was used (both maps have colours).
    pub colour: bool,
    /// Per-channel gains of the source's colours for its colour signatures: the two maps'
    /// relative white balance (`colour::relative_white_balance`).
    pub source_colour_gains: [f64; 3],
    /// Putative correspondences (descriptor matches).
    pub correspondences: usize,
    /// How many of them are mutual nearest neighbours.
    pub mutual_correspondences: usize,
    /// RANSAC samples drawn.
    pub ransac_samples: usize,
    /// RANSAC samples that passed the edge checks and were fitted.
    pub ransac_fitted: usize,
    /// Support of the best hypothesis; at the end, of the candidate the registration ends with.
    pub consistent_correspondences: usize,
    /// Support of the best hypothesis distinct from it, not counting correspondences the best
    /// one also explains (0 without one).
    pub runner_up_support: usize,
    /// `runner_up_support / consistent_correspondences`, as RANSAC found them.
    pub ambiguity_ratio: f64,
    /// How far the runner-up is from the best (NaN without one): rotation in degrees...
    pub runner_up_rotation_deg: f64,
    /// ...and the distance between where they put the matched source points' centre (metres).
    pub runner_up_translation_m: f64,
    /// Candidate transforms refined and verified (more than one when the correspondences left
    /// them nearly tied).
    pub hypotheses_verified: usize,
    /// Whether the verification chose between several candidates and the chosen one passed.
    pub ambiguity_resolved: bool,
    /// Supporting correspondences of the refined transform.
    pub support_kept: usize,
    /// G-ICP correspondence searches, summed over the coarse-to-fine stages.
    pub gicp_iterations: usize,
    /// Whether the final G-ICP stage converged.
    pub gicp_converged: bool,
    /// Source points with a target point within the finest refinement distance.
    pub overlapping_points: usize,
    /// `overlapping_points` over the smaller map's points.
    pub overlap_fraction: f64,
    /// RMS point-to-plane distance of the overlapping points (metres).
    pub residual_m: f64,
    /// Marginal standard deviations of the estimate (see [`verification`](super::verification)):
    /// the worst rotation direction's (degrees)...
    pub rotation_sigma_deg: f64,
    /// ...and the worst translation direction's (metres); infinite when the overlap leaves a
    /// direction unconstrained.
    pub translation_sigma_m: f64,
    /// Overlapping points compared in colour.
    pub colour_compared: usize,
    /// Fraction of them whose chromaticities agree (NaN when none were compared).
    pub colour_agreement: f64,
    /// Fraction that agree when paired at random (NaN when none were compared).
    pub colour_chance: f64,
    /// Cohen's kappa of the two (see [`verification`](super::verification)): NaN when none
    /// were compared or the colours cannot tell.
    pub colour_kappa: f64,
    /// Per-channel gains applied to the source's colours before comparing (white balance).
    pub colour_gains: [f64; 3],
    /// The free-space test of the result, when the maps' depth views were given: the smaller
    /// direction's depth agreement (NaN without)...
    pub depth_agreement: f64,
    /// ...and the smaller direction's decisive comparisons (0 without).
    pub depth_comparisons: usize,
    /// Wall time of each stage.
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
    /// Everything measured on the way.
    pub scores: MapRegistrationScores,
    /// Accepted, or why not.
    pub verdict: Result<(), MapRejection>,
    /// Information matrix of `target_from_source` (6x6; rotation first, then translation; a right
    /// perturbation `T Exp(delta)`, the pose graph's edge convention), from the point-to-plane
    /// residuals at the solution; `None` when refinement did not run. Optimistic: see
    /// [`verification`](super::verification).
    pub information: Option<Matrix6<f64>>,
    /// Wall time of the whole registration (milliseconds).
    pub elapsed_ms: f64,
}

impl MapRegistration {
    /// True when the verdict is `Ok`.
    pub fn is_accepted(&self) -> bool {
        self.verdict.is_ok()
    }

    /// Covariance of `target_from_source` (inverse of [`Self::information`]), `None` when there
    /// is no information or it is singular (a degenerate overlap).
    pub fn covariance(&self) -> Option<Matrix6<f64>> {
        self.information?.try_inverse()
    }
}
