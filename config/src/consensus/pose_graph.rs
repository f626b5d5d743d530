//! The `[consensus.pose_graph]` table: the robust pose graph over every agent's keyframes
//! (docs/method.md, The consensus: pose graph). No value of it has been range-checked so far, so
//! it has no `validate()`.

use serde::{Deserialize, Serialize};

/// Robust pose graph over all agents' keyframes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseGraphConfig {
    /// Standard deviation of an odometry edge (consecutive keyframes of one agent, from
    /// tracking): rotation (radians) and translation (metres). Measured on redkitchen with
    /// keyframes 20 frames apart: frame-to-model tracking errs by a median 24 mm and 0.9 degrees
    /// per step (90th percentile 50-90 mm, 2 degrees).
    pub odometry_rotation_sigma_rad: f64,
    pub odometry_translation_sigma_m: f64,
    /// Standard deviation of a verified loop closure: alignments on redkitchen differ from the
    /// (KinectFusion) ground truth by a median 17 mm and 0.6 degrees, part of it the ground
    /// truth's own error.
    pub loop_rotation_sigma_rad: f64,
    pub loop_translation_sigma_m: f64,
    /// Truncated least squares: a loop edge whose squared Mahalanobis residual exceeds this is an
    /// outlier (16.81: the 99 % quantile of chi-square with 6 degrees of freedom).
    pub outlier_threshold_chi2: f64,
    /// Graduated non-convexity: the control parameter mu grows by this factor per step
    /// (Yang et al. 2020 use 1.4).
    pub gnc_mu_factor: f64,
    /// GNC steps at most.
    pub gnc_max_steps: usize,
    /// Levenberg-Marquardt iterations per GNC step and for the final solve.
    pub lm_max_iterations: usize,
    /// LM stops when the largest update component falls below this (radians or metres).
    pub lm_step_tolerance: f64,
    /// Initial guess of each agent's frame: two inter-agent loop closures vote for each other
    /// when the agent-to-agent transforms they imply differ by less than this translation
    /// (metres) and rotation (radians). Generous: odometry drift between the two closures
    /// separates even correct votes.
    pub vote_translation_m: f64,
    pub vote_rotation_rad: f64,
}

impl Default for PoseGraphConfig {
    fn default() -> Self {
        Self {
            odometry_rotation_sigma_rad: 0.02,
            odometry_translation_sigma_m: 0.03,
            loop_rotation_sigma_rad: 0.01,
            loop_translation_sigma_m: 0.02,
            outlier_threshold_chi2: 16.81,
            gnc_mu_factor: 1.4,
            gnc_max_steps: 100,
            lm_max_iterations: 30,
            lm_step_tolerance: 1e-7,
            vote_translation_m: 0.3,
            vote_rotation_rad: 10f64.to_radians(),
        }
    }
}
