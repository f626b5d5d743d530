//! Keyframe-to-keyframe alignment (docs/method.md, The consensus: association and alignment):
//! the relative pose of two RGB-D views with no initial guess, from the same agent or from two
//! agents whose frames are unrelated. The consensus aligns keyframe pairs with it, and an agent
//! relocalises against its own keyframes with it.
//!
//! 1. Coarse ([`features`], [`ransac`]): FAST + BRIEF keypoints on both images, mutual ratio-test
//!    matches, lifted to 3-D with depth, RANSAC over 3-point rigid fits. Needs no initial guess, so
//!    it works when the cameras are metres and tens of degrees apart.
//! 2. Refinement: G-ICP between the two views' point clouds with both covariances
//!    (`Sigma_k + Sigma_l`), coarse-to-fine correspondence distances
//!    ([`crate::register_coarse_to_fine`]).
//! 3. Verification ([`verification`]): inlier fraction, point-to-plane residual and depth
//!    agreement in both directions against [`AlignmentConfig`] thresholds. The result always says
//!    why an estimate was rejected.
//!
//! The estimate is `target_camera_from_source_camera`: it maps points of the source view's
//! camera frame into the target view's camera frame.

mod config;
pub mod features;
pub mod ransac;
pub mod verification;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

use crate::{
    GicpParams, PointTree, RegistrationFailure, points_from_depth, register_coarse_to_fine,
};
pub use config::AlignmentConfig;
use features::Features;
use verification::DepthComparison;

/// What alignment computes once per view, however many others it is paired with: lifted
/// keypoints and the point cloud with G-ICP covariances.
pub struct PreparedView {
    /// Keypoints lifted to 3-D in the camera frame, with descriptors.
    pub features: Features,
    /// Camera-frame points with covariances: G-ICP source and target.
    pub cloud: PointTree,
}

impl PreparedView {
    /// Extracts the features and back-projects the depth (every `config.pixel_stride`-th pixel,
    /// up to `config.truncation_m`) into a cloud with covariances. Never fails: a cloud that
    /// cannot be indexed is replaced by an empty one, so every alignment with the view is
    /// rejected.
    pub fn new(
        rgb: &RgbImage,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        config: &AlignmentConfig,
    ) -> Self {
        let features = features::extract(rgb, depth, intrinsics, config);
        let points = points_from_depth(depth, intrinsics, config.pixel_stride, config.truncation_m);
        let cloud = PointTree::with_covariances(
            points,
            config.covariance_neighbours,
            config.covariance_epsilon,
        )
        // Points back-projected with valid intrinsics are finite; if not, the view simply
        // has no cloud and every alignment with it is rejected as a refinement failure.
        .unwrap_or_else(|error| {
            tracing::warn!(%error, "view points cannot be indexed");
            PointTree::new(Vec::new()).expect("an empty cloud always indexes")
        });
        Self { features, cloud }
    }
}

/// One side of an alignment: a prepared view with the depth image it was made from (the depth
/// agreement test projects the other side's points into it).
#[derive(Clone, Copy)]
pub struct AlignmentInput<'a> {
    /// The view's features and cloud.
    pub prepared: &'a PreparedView,
    /// The depth image (metres) the view was prepared from.
    pub depth: &'a DepthImage,
    /// The view's camera.
    pub intrinsics: &'a Intrinsics,
}

/// Scores of the coarse registration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CoarseScores {
    /// Keypoints of the source view lifted to 3-D.
    pub source_keypoints: usize,
    /// Keypoints of the target view lifted to 3-D.
    pub target_keypoints: usize,
    /// Descriptor matches between them.
    pub matches: usize,
    /// Matches consistent with the RANSAC estimate (0 when no hypothesis could be formed).
    pub inliers: usize,
    /// RANSAC hypotheses drawn.
    pub ransac_iterations: usize,
}

/// Scores of the refined estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RefinementScores {
    /// G-ICP correspondence searches, summed over the coarse-to-fine stages.
    pub gicp_iterations: usize,
    /// Whether the last G-ICP stage run converged.
    pub converged: bool,
    /// Source points with a target point within the finest correspondence distance.
    pub inlier_fraction: f64,
    /// RMS point-to-plane distance of those points (metres).
    pub residual_m: f64,
    /// Depth agreement of the source projected into the target, and the reverse.
    pub source_in_target: DepthCounts,
    /// Depth agreement of the target's points projected into the source's depth image.
    pub target_in_source: DepthCounts,
}

/// [`DepthComparison`] as reported.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DepthCounts {
    /// Points within the depth tolerance of the other view's measured depth.
    pub agreeing: usize,
    /// Points clearly in front of the other view's measured surface.
    pub violating: usize,
    /// Points behind it (possibly occluded: neither for nor against).
    pub occluded: usize,
    /// `agreeing / (agreeing + violating)`; 0 without decisive comparisons.
    pub agreement: f64,
}

impl From<DepthComparison> for DepthCounts {
    fn from(c: DepthComparison) -> Self {
        Self {
            agreeing: c.agreeing,
            violating: c.violating,
            occluded: c.occluded,
            agreement: c.agreement(),
        }
    }
}

/// Why an alignment was not accepted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RejectionReason {
    /// Fewer descriptor matches than the coarse estimate needs inliers; RANSAC was not run.
    #[error("{found} descriptor matches, at least {required} needed")]
    TooFewMatches {
        /// Descriptor matches.
        found: usize,
        /// `min_coarse_inliers`.
        required: usize,
    },
    /// RANSAC found no estimate with enough inlier matches.
    #[error("coarse registration found {found} inlier matches, at least {required} needed")]
    TooFewCoarseInliers {
        /// Inliers of the best hypothesis (0 when none could be formed).
        found: usize,
        /// `min_coarse_inliers`.
        required: usize,
    },
    /// G-ICP gave no usable pose from the coarse estimate.
    #[error("G-ICP refinement failed: {0}")]
    RefinementFailed(RegistrationFailure),
    /// Too few source points have a target point within the correspondence distance.
    #[error("inlier fraction {found:.3} below {required:.3}")]
    LowInlierFraction {
        /// The refinement's inlier fraction.
        found: f64,
        /// `min_inlier_fraction`.
        required: f64,
    },
    /// The point-to-plane residual is too large, or NaN (nothing to measure it on).
    #[error("point-to-plane residual {found_m:.4} m above {allowed_m:.4} m")]
    HighResidual {
        /// RMS point-to-plane distance, metres.
        found_m: f64,
        /// `max_residual_m`.
        allowed_m: f64,
    },
    /// Too few decisive depth comparisons in one of the two directions to vouch for the pose.
    #[error("{comparisons} depth comparisons, at least {required} needed")]
    TooFewDepthComparisons {
        /// Agreeing plus violating points, the smaller of the two directions.
        comparisons: usize,
        /// `min_depth_comparisons`.
        required: usize,
    },
    /// The views' depths contradict the pose: too small an agreement in one direction.
    #[error("depth agreement {found:.3} below {required:.3}")]
    DepthDisagreement {
        /// The smaller agreement of the two directions.
        found: f64,
        /// `min_depth_agreement`.
        required: f64,
    },
}

/// Accepted, or rejected with the reason.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Every verification threshold passed.
    Accepted,
    /// The first check that failed.
    Rejected(RejectionReason),
}

/// The outcome of aligning a source view to a target view.
#[derive(Debug, Clone)]
pub struct Alignment {
    /// The estimate: refined when refinement ran, the coarse one when refinement failed,
    /// identity when there were too few matches to estimate anything.
    pub target_camera_from_source_camera: Isometry3<f64>,
    /// `None` when there were too few matches to try.
    pub coarse: Option<CoarseScores>,
    /// `None` when refinement did not run or failed.
    pub refinement: Option<RefinementScores>,
    /// Whether the estimate passed verification, and why not if it did not.
    pub verdict: Verdict,
}

impl Alignment {
    /// True when the verdict is [`Verdict::Accepted`].
    pub fn is_accepted(&self) -> bool {
        self.verdict == Verdict::Accepted
    }
}

/// Aligns two prepared views; see the module documentation.
pub fn align(
    source: AlignmentInput<'_>,
    target: AlignmentInput<'_>,
    config: &AlignmentConfig,
) -> Alignment {
    let mut result = Alignment {
        target_camera_from_source_camera: Isometry3::identity(),
        coarse: None,
        refinement: None,
        verdict: Verdict::Accepted,
    };
    let reject = |mut result: Alignment, reason: RejectionReason| {
        tracing::debug!(%reason, "alignment rejected");
        result.verdict = Verdict::Rejected(reason);
        result
    };

    let coarse = match coarse_estimate(source.prepared, target.prepared, config, &mut result) {
        Ok(coarse) => coarse,
        Err(reason) => return reject(result, reason),
    };
    result.target_camera_from_source_camera = coarse.target_from_source;

    let refined = {
        let _span = tracing::debug_span!("gicp").entered();
        register_coarse_to_fine(
            source.prepared.cloud.cloud(),
            &target.prepared.cloud,
            &coarse.target_from_source,
            &config.correspondence_distances_m,
            &gicp_params(config),
            // `verify` rejects pairs below this fraction at the finest distance; a coarser
            // stage already below it cannot get there.
            config.min_inlier_fraction,
        )
    };
    if let Some(failure) = refined.failure.clone().filter(|f| !f.pose_is_usable()) {
        return reject(result, RejectionReason::RefinementFailed(failure));
    }
    let estimate = refined.target_from_source;
    result.target_camera_from_source_camera = estimate;

    let _span = tracing::debug_span!("verify").entered();
    let measured = Measured::of(source, target, &estimate, config);
    let scores = RefinementScores {
        gicp_iterations: refined.iterations,
        converged: refined.converged,
        inlier_fraction: refined.inlier_fraction(),
        residual_m: measured.residual_m,
        source_in_target: measured.source_in_target.into(),
        target_in_source: measured.target_in_source.into(),
    };
    result.refinement = Some(scores);
    tracing::debug!(?scores, "refined");
    match verify(
        &scores,
        measured.source_in_target,
        measured.target_in_source,
        config,
    ) {
        Some(reason) => reject(result, reason),
        None => result,
    }
}

/// Coarse stage: descriptor matches lifted to 3-D, then RANSAC; its scores go into `result`.
fn coarse_estimate(
    source: &PreparedView,
    target: &PreparedView,
    config: &AlignmentConfig,
    result: &mut Alignment,
) -> Result<ransac::CoarseEstimate, RejectionReason> {
    let matches = features::match_features(&source.features, &target.features, config);
    if matches.len() < config.min_coarse_inliers {
        return Err(RejectionReason::TooFewMatches {
            found: matches.len(),
            required: config.min_coarse_inliers,
        });
    }
    let (source_points, target_points): (Vec<Point3<f64>>, Vec<Point3<f64>>) = matches
        .iter()
        .map(|&(i, j)| {
            (
                source.features.camera_points[i],
                target.features.camera_points[j],
            )
        })
        .unzip();
    let coarse = ransac::register(&source_points, &target_points, config);
    let inliers = coarse.as_ref().map_or(0, |c| c.inliers.len());
    result.coarse = Some(CoarseScores {
        source_keypoints: source.features.len(),
        target_keypoints: target.features.len(),
        matches: matches.len(),
        inliers,
        ransac_iterations: coarse.as_ref().map_or(0, |c| c.iterations),
    });
    match coarse {
        Some(coarse) if inliers >= config.min_coarse_inliers => Ok(coarse),
        _ => Err(RejectionReason::TooFewCoarseInliers {
            found: inliers,
            required: config.min_coarse_inliers,
        }),
    }
}

/// What the verification measures of a refined estimate: the point-to-plane residual at the
/// finest distance and the depth agreement in both directions.
struct Measured {
    residual_m: f64,
    source_in_target: DepthComparison,
    target_in_source: DepthComparison,
}

impl Measured {
    fn of(
        source: AlignmentInput<'_>,
        target: AlignmentInput<'_>,
        estimate: &Isometry3<f64>,
        config: &AlignmentConfig,
    ) -> Self {
        let finest = finest_distance(config);
        let (residual_m, _) = verification::point_to_plane_rms(
            &source.prepared.cloud,
            &target.prepared.cloud,
            estimate,
            finest,
        );
        let source_in_target = verification::compare_depth(
            source.prepared.cloud.positions(),
            estimate,
            target.depth,
            target.intrinsics,
            config,
        );
        let target_in_source = verification::compare_depth(
            target.prepared.cloud.positions(),
            &estimate.inverse(),
            source.depth,
            source.intrinsics,
            config,
        );
        Self {
            residual_m,
            source_in_target,
            target_in_source,
        }
    }
}

/// The first threshold the scores fail, if any.
fn verify(
    scores: &RefinementScores,
    source_in_target: DepthComparison,
    target_in_source: DepthComparison,
    config: &AlignmentConfig,
) -> Option<RejectionReason> {
    if scores.inlier_fraction < config.min_inlier_fraction {
        return Some(RejectionReason::LowInlierFraction {
            found: scores.inlier_fraction,
            required: config.min_inlier_fraction,
        });
    }
    // A NaN residual (no correspondences to measure) fails as well.
    if scores.residual_m.is_nan() || scores.residual_m > config.max_residual_m {
        return Some(RejectionReason::HighResidual {
            found_m: scores.residual_m,
            allowed_m: config.max_residual_m,
        });
    }
    let comparisons = source_in_target.decisive().min(target_in_source.decisive());
    if comparisons < config.min_depth_comparisons {
        return Some(RejectionReason::TooFewDepthComparisons {
            comparisons,
            required: config.min_depth_comparisons,
        });
    }
    let agreement = source_in_target
        .agreement()
        .min(target_in_source.agreement());
    if agreement < config.min_depth_agreement {
        return Some(RejectionReason::DepthDisagreement {
            found: agreement,
            required: config.min_depth_agreement,
        });
    }
    None
}

/// The last (finest) coarse-to-fine distance: the one the final statistics are measured at.
fn finest_distance(config: &AlignmentConfig) -> f64 {
    config
        .correspondence_distances_m
        .last()
        .copied()
        .unwrap_or(DEFAULT_FINEST_DISTANCE_M)
}

/// Correspondence distance when the configuration lists none: the agent's tracking distance
/// (docs/method.md, One agent: Tracking), 2 cm.
const DEFAULT_FINEST_DISTANCE_M: f64 = 0.02;

fn gicp_params(config: &AlignmentConfig) -> GicpParams {
    GicpParams {
        max_correspondence_m: finest_distance(config),
        max_iterations: config.gicp_max_iterations,
        rotation_epsilon_rad: config.gicp_rotation_epsilon_rad,
        translation_epsilon_m: config.gicp_translation_epsilon_m,
        overlap_distance_m: finest_distance(config),
        // The inlier fraction is judged by `verify`, with a reason; G-ICP only needs enough
        // correspondences for a pose.
        min_inlier_fraction: 0.0,
    }
}
