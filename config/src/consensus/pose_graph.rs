//! The `[consensus.pose_graph]` table: the robust pose graph over every agent's keyframes
//! (docs/method.md, The consensus: pose graph).

use geometry::checks::{FieldError, at_least_one};
use serde::{Deserialize, Serialize};

/// Robust pose graph over all agents' keyframes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseGraphConfig {
    /// Standard deviation of an odometry edge (consecutive keyframes of one agent, from
    /// tracking) between keyframes `odometry_sigma_span_frames` frames apart: rotation (radians)
    /// and translation (metres). Tracking drift accumulates frame by frame like a random walk,
    /// so an edge spanning `n` frames gets these times `sqrt(n / odometry_sigma_span_frames)`:
    /// a shorter `consensus.t_comm` (keyframes published closer together) then trusts each edge
    /// more, and the chain over a stretch of frames as much as before. The sigmas are the best
    /// of a sweep on paced redkitchen swarms at `t_comm = 60`; the span they are for (10 frames:
    /// an edge of 30 frames gets 1.7 times them, one of 60 frames 2.4 times) was chosen by
    /// re-solving finished swarms at `t_comm` 30 and 60 offline, where it lowered the joint ATE
    /// by 0.1-0.3 cm against 60 frames (the run also refined again kept its map's PSNR;
    /// docs/benchmarks.md).
    pub odometry_rotation_sigma_rad: f64,
    /// Translation part of the odometry sigma above, metres (default 0.03).
    pub odometry_translation_sigma_m: f64,
    /// Frames between two keyframes that the odometry sigmas above are for (at least 1).
    pub odometry_sigma_span_frames: usize,
    /// Standard deviation of a verified loop closure: alignments on redkitchen differ from the
    /// (KinectFusion) ground truth by a median 17 mm and 0.6 degrees, part of it the ground
    /// truth's own error.
    pub loop_rotation_sigma_rad: f64,
    /// Translation part of the loop-closure sigma above, metres (default 0.02).
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
    /// Rotation part of the vote tolerance above, radians (default 10 degrees).
    pub vote_rotation_rad: f64,
}

impl Default for PoseGraphConfig {
    fn default() -> Self {
        Self {
            odometry_rotation_sigma_rad: 0.02,
            odometry_translation_sigma_m: 0.03,
            odometry_sigma_span_frames: 10,
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

impl PoseGraphConfig {
    /// Checks ranges; returns the offending field (`consensus.pose_graph.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        at_least_one(
            "consensus.pose_graph.odometry_sigma_span_frames",
            self.odometry_sigma_span_frames,
        )
    }

    /// Standard deviations (rotation radians, translation metres) of an odometry edge between
    /// keyframes `span_frames` frames apart (see [`Self::odometry_translation_sigma_m`]). A span
    /// of 0 (two keyframes from one frame) counts as 1.
    pub fn odometry_sigmas(&self, span_frames: u64) -> (f64, f64) {
        let scale =
            (span_frames.max(1) as f64 / self.odometry_sigma_span_frames.max(1) as f64).sqrt();
        (
            self.odometry_rotation_sigma_rad * scale,
            self.odometry_translation_sigma_m * scale,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn odometry_sigmas_grow_with_the_square_root_of_the_span() {
        let config = PoseGraphConfig::default();
        let span = config.odometry_sigma_span_frames as u64;
        let (rotation, translation) = config.odometry_sigmas(span);
        assert_eq!(
            (rotation, translation),
            (
                config.odometry_rotation_sigma_rad,
                config.odometry_translation_sigma_m
            )
        );
        // Four times the span, twice the sigmas.
        let (rotation, translation) = config.odometry_sigmas(4 * span);
        assert!((rotation - config.odometry_rotation_sigma_rad * 2.0).abs() < 1e-12);
        assert!((translation - config.odometry_translation_sigma_m * 2.0).abs() < 1e-12);
        assert_eq!(config.odometry_sigmas(0), config.odometry_sigmas(1));
        let zero_span = PoseGraphConfig {
            odometry_sigma_span_frames: 0,
            ..PoseGraphConfig::default()
        };
        assert_eq!(
            zero_span.validate().unwrap_err().0,
            "consensus.pose_graph.odometry_sigma_span_frames"
        );
        assert!(config.validate().is_ok());
    }
}
