//! The `[consensus.alignment]` table: keyframe-to-keyframe alignment (docs/method.md, The
//! consensus: association and alignment). Every field has a serde default, so a configuration
//! file names only what it changes; the defaults suit a 640x480 RGB-D sensor.

use geometry::checks::FieldError;
use serde::{Deserialize, Serialize};

/// Keyframe-to-keyframe alignment: coarse feature registration, G-ICP refinement, verification.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignmentConfig {
    // --- Features (coarse registration) ---
    /// Keypoints kept per image over all pyramid levels (1000: enough for a few hundred matches
    /// between overlapping views, cheap to match by brute force; on synthetic pairs 1.5-2.5 m
    /// apart 1500 gave 1.5x the correct matches for 1.2x the extraction time, but aligned about
    /// as many pairs).
    pub features_per_image: usize,
    /// Image pyramid levels for FAST + BRIEF (BRIEF is not scale-invariant; levels let a view
    /// taken twice as far away still match). 5 levels of 1.25 span a 2.4x scale change.
    pub pyramid_levels: usize,
    /// Size ratio between consecutive pyramid levels.
    pub pyramid_scale_factor: f64,
    /// FAST-9 threshold (grey levels): a corner's arc must be this much brighter or darker than
    /// its centre. Low, so that plain surfaces still offer corners; the grid and the FAST score
    /// choose among them.
    pub fast_threshold: u8,
    /// Keypoints are spread over a grid of cells this many pixels wide (on each pyramid level):
    /// the strongest corner of every cell before the second of any. 0: strongest first over the
    /// whole image, which piles the keypoints onto a few high-contrast spots.
    pub keypoint_cell_px: u32,
    /// Turn the BRIEF pattern by each keypoint's intensity-centroid orientation (steered BRIEF),
    /// so that descriptors survive in-plane rotation between the views.
    pub steer_descriptors: bool,
    /// Radius (metres) of the surface patch a descriptor describes, sampled from the pyramid
    /// level whose pixels match it: the same place seen from 1 m and from 3 m gives the same
    /// patch. 0: the 31-pixel patch around the corner on its detection level.
    pub descriptor_radius_m: f64,
    /// Lay the metric patch onto the surface (normal from depth) instead of facing the camera:
    /// a surface seen obliquely by one camera and head-on by the other still gives one patch.
    pub rectify_patches: bool,
    /// Largest Hamming distance (of 256 bits) accepted for a descriptor match.
    pub max_hamming_distance: u32,
    /// Lowe's ratio test: the best match must be closer than this fraction of the second best.
    /// 1.0 only refuses ties. Views metres apart change BRIEF descriptors so much that the second
    /// best is often nearly as close as the best: on a synthetic pair 0.8 m and 11 degrees apart
    /// a ratio of 0.8 kept 6 correct matches, 1.0 kept 35 of 111. Mutual nearest neighbours and
    /// RANSAC do the filtering instead.
    pub match_ratio: f64,
    /// A keypoint lifts to 3-D only when the depths of its 3x3 neighbourhood are all valid and
    /// spread by less than this fraction of the centre depth (corners often sit on depth edges,
    /// where the depth of the pixel may belong to the background).
    pub max_depth_spread_fraction: f64,
    /// Depth at or beyond this is not used (metres; 10 for 7-Scenes, as in tracking).
    pub truncation_m: f64,

    // --- RANSAC over 3-point rigid fits ---
    /// A match is an inlier when the transformed source point lies within this distance of the
    /// target point (metres; covers Kinect depth noise of 1-2 cm at 2-3 m on both points).
    pub ransac_inlier_distance_m: f64,
    /// Hypotheses at most.
    pub ransac_max_iterations: usize,
    /// Stop early once a hypothesis with this probability of being all-inlier has been drawn.
    pub ransac_confidence: f64,
    /// Sampled points closer together than this (metres) make an ill-conditioned rotation.
    pub ransac_min_sample_spread_m: f64,
    /// Seed of the sampler: alignment is deterministic for the same inputs.
    pub ransac_seed: u64,
    /// The coarse estimate needs at least this many inlier matches.
    pub min_coarse_inliers: usize,

    // --- G-ICP refinement ---
    /// Back-project every n-th pixel of each keyframe's depth (as tracking does).
    pub pixel_stride: usize,
    /// Neighbours per G-ICP covariance and its plane regularisation (as tracking does).
    pub covariance_neighbours: usize,
    /// ...and the regularisation: a covariance's singular values become (1, 1, epsilon).
    pub covariance_epsilon: f64,
    /// Coarse-to-fine correspondence distances (metres, largest first; docs/method.md, The
    /// consensus: association and alignment).
    pub correspondence_distances_m: Vec<f64>,
    /// Levenberg-Marquardt iterations per stage.
    pub gicp_max_iterations: usize,
    /// Converged when an update rotates less than this (radians) and translates less than
    /// `gicp_translation_epsilon_m`: tighter than tracking's, a loop closure is used for long.
    pub gicp_rotation_epsilon_rad: f64,
    /// ...and translates less than this (metres).
    pub gicp_translation_epsilon_m: f64,

    // --- Verification ---
    /// Fraction of the source keyframe's points with a target point within the finest
    /// correspondence distance after refinement. Low values mean little overlap or a wrong pose.
    pub min_inlier_fraction: f64,
    /// RMS point-to-plane distance of those correspondences (metres) at most.
    pub max_residual_m: f64,
    /// Depth agreement: a point projected into the other keyframe agrees with its depth image
    /// when it lies within `depth_tolerance_m + depth_tolerance_fraction * depth` of it.
    pub depth_tolerance_m: f64,
    /// The tolerance's part that grows with the measured depth (a fraction of it), as depth
    /// noise does.
    pub depth_tolerance_fraction: f64,
    /// Agreeing points over agreeing plus free-space violations (a point in front of what the
    /// other camera sees) at least this fraction, in both directions.
    pub min_depth_agreement: f64,
    /// Fewer projected comparisons than this cannot vouch for a pose.
    pub min_depth_comparisons: usize,
}

impl Default for AlignmentConfig {
    fn default() -> Self {
        Self {
            features_per_image: 1000,
            pyramid_levels: 5,
            pyramid_scale_factor: 1.25,
            fast_threshold: 12,
            keypoint_cell_px: 32,
            steer_descriptors: true,
            descriptor_radius_m: 0.08,
            rectify_patches: true,
            max_hamming_distance: 80,
            match_ratio: 1.0,
            max_depth_spread_fraction: 0.05,
            truncation_m: 10.0,
            ransac_inlier_distance_m: 0.05,
            ransac_max_iterations: 5000,
            ransac_confidence: 0.999,
            ransac_min_sample_spread_m: 0.1,
            ransac_seed: 0,
            min_coarse_inliers: 15,
            pixel_stride: 5,
            covariance_neighbours: 10,
            covariance_epsilon: 1e-3,
            correspondence_distances_m: vec![0.1, 0.05, 0.02],
            gicp_max_iterations: 64,
            gicp_rotation_epsilon_rad: 1e-4,
            gicp_translation_epsilon_m: 1e-4,
            min_inlier_fraction: 0.2,
            max_residual_m: 0.01,
            depth_tolerance_m: 0.02,
            depth_tolerance_fraction: 0.01,
            min_depth_agreement: 0.8,
            min_depth_comparisons: 500,
        }
    }
}

impl AlignmentConfig {
    /// Checks ranges; returns the offending field (`consensus.alignment.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.correspondence_distances_m.is_empty()
            || self
                .correspondence_distances_m
                .iter()
                .any(|d| !(d.is_finite() && *d > 0.0))
        {
            return Err((
                "consensus.alignment.correspondence_distances_m",
                "must be a non-empty list of positive distances".into(),
            ));
        }
        if self
            .correspondence_distances_m
            .windows(2)
            .any(|w| w[1] > w[0])
        {
            return Err((
                "consensus.alignment.correspondence_distances_m",
                "must go from coarse to fine (decreasing)".into(),
            ));
        }
        Ok(())
    }
}
