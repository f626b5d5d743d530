//! The `[consensus.refinement]` table: joint photometric refinement of the merged map
//! (docs/method.md, The consensus: joint refinement).

use geometry::checks::{FieldError, at_least_one, fraction, non_negative, positive};
use serde::{Deserialize, Serialize};

/// Joint photometric refinement of the merged world map (docs/method.md, The consensus: joint
/// refinement):
/// the merged map and the keyframe poses are optimised against every placed keyframe's RGB-D
/// image with `weight_l1`, `weight_ssim`, `weight_depth` and `weight_pose_consistency` of
/// `[consensus]`. It runs when the agents are done, before the world map and trajectories are
/// written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefinementConfig {
    /// Adam iterations per keyframe view (0 turns refinement off): one iteration fits one view,
    /// and every view is visited in turn, in a shuffled order per pass, so this is how often
    /// each view is fitted. The views, not a total, set the budget: too few visits leave the
    /// merged map blurred, too many fit the few views the consensus holds images of at the
    /// expense of every other frame (docs/method.md, The consensus: joint refinement).
    pub iterations_per_view: usize,
    /// At most this many iterations in all (0 turns refinement off), whatever the views.
    pub max_iterations: usize,
    /// Stop earlier when refinement has run this long (seconds): on a CPU Vulkan device an
    /// iteration over a few hundred thousand Gaussians costs about a second.
    pub max_seconds: f64,
    /// Views are rendered at their resolution divided by this (as `[mapping] image_downscale`).
    pub image_downscale: u32,
    /// Learning rates of the Gaussians (the mapping rates of docs/method.md, One agent: Map
    /// optimisation; the mean rate is
    /// multiplied by the map's radius, as the mapper does).
    pub lr_means: f64,
    /// Adam learning rate of the Gaussians' RGB colours, on the [0, 1] scale (default 2.5e-3).
    pub lr_colours: f64,
    /// Adam learning rate of the opacity logits, the opacities before the sigmoid (default 0.05).
    pub lr_opacity: f64,
    /// Adam learning rate of the natural-log scales (default 0.01).
    pub lr_log_scales: f64,
    /// Adam learning rate of the rotation quaternions (default 0: the optimisation leaves the
    /// orientations as they are).
    pub lr_rotations: f64,
    /// Optimise the keyframe poses too (photometric gradient plus the pose-consistency term over
    /// the pose graph's odometry and accepted loop edges). Agent 0's first keyframe stays fixed:
    /// it defines the world frame.
    pub refine_poses: bool,
    /// Poses stay fixed for this fraction of the iterations: the photometric pose gradient of
    /// a blurred map points nowhere useful (on the synthetic swarm, refining poses from the first
    /// iteration moved exact poses by up to 1.1 cm and 0.5 degrees).
    pub pose_warmup_fraction: f64,
    /// The first this fraction of the iterations (or of the time bound) moves the poses only,
    /// the map held as the agents sent it (default 0: none). Each agent's map fits its own final
    /// keyframe poses, and the pose graph's lie a centimetre or two from those: poses that reach
    /// their maps first are not paid for by a map refitted to the wrong poses. The map-only
    /// warm-up (`pose_warmup_fraction`) then runs until its own fraction, counted from the first
    /// iteration, and both move after it.
    pub poses_first_fraction: f64,
    /// Adam step sizes of the pose (metres and radians per step; an Adam step is about this
    /// size whatever the gradient's scale): 0.2 mm and 0.01 degrees.
    pub lr_pose_translation_m: f64,
    /// Rotation step size of the pose, radians (default 2e-4).
    pub lr_pose_rotation_rad: f64,
    /// A refined pose may move at most this far from the pose graph's (metres, radians);
    /// farther means the photometric term pulled it into a wrong basin, and the pose graph's
    /// pose is kept.
    pub max_pose_change_m: f64,
    /// Rotation limit of the refined pose, radians (default 2 degrees).
    pub max_pose_change_rad: f64,
    /// Seed of the view order (runs are repeatable).
    pub random_seed: u64,
    /// The Gaussians' learning rates decay exponentially from the `lr_*` values at the first
    /// iteration to this fraction of them at the last (1: constant). A fine-tuning of maps that
    /// are already fitted gains from smaller steps at its end: the last iterations, each on one
    /// view, would otherwise leave the map tilted towards whichever views came last.
    pub lr_final_fraction: f64,
    /// After the refinement, Gaussians whose opacity it brought below this are removed (0: none
    /// is): where agents' maps overlap, the refinement fades the copies it does not need.
    pub prune_min_opacity: f64,
}

impl Default for RefinementConfig {
    fn default() -> Self {
        Self {
            iterations_per_view: 40,
            max_iterations: 4000,
            max_seconds: 120.0,
            image_downscale: 2,
            lr_means: 5e-6,
            lr_colours: 2.5e-3,
            lr_opacity: 0.05,
            lr_log_scales: 0.01,
            lr_rotations: 0.0,
            refine_poses: true,
            pose_warmup_fraction: 0.5,
            poses_first_fraction: 0.0,
            lr_pose_translation_m: 2e-4,
            lr_pose_rotation_rad: 2e-4,
            max_pose_change_m: 0.05,
            max_pose_change_rad: 2f64.to_radians(),
            random_seed: 0,
            lr_final_fraction: 1.0,
            prune_min_opacity: 0.0,
        }
    }
}

impl RefinementConfig {
    /// The iterations of a refinement over `views` keyframe views (0: off).
    pub fn iterations_for(&self, views: usize) -> usize {
        views
            .saturating_mul(self.iterations_per_view)
            .min(self.max_iterations)
    }

    /// Whether a refinement runs at all.
    pub fn enabled(&self) -> bool {
        self.iterations_per_view > 0 && self.max_iterations > 0
    }

    /// Checks ranges; returns the offending field (`consensus.refinement.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        positive("consensus.refinement.max_seconds", self.max_seconds)?;
        fraction(
            "consensus.refinement.pose_warmup_fraction",
            self.pose_warmup_fraction,
        )?;
        fraction(
            "consensus.refinement.poses_first_fraction",
            self.poses_first_fraction,
        )?;
        positive(
            "consensus.refinement.lr_final_fraction",
            self.lr_final_fraction,
        )?;
        fraction(
            "consensus.refinement.prune_min_opacity",
            self.prune_min_opacity,
        )?;
        at_least_one(
            "consensus.refinement.image_downscale",
            self.image_downscale as usize,
        )?;
        for (field, v) in [
            ("consensus.refinement.lr_means", self.lr_means),
            ("consensus.refinement.lr_colours", self.lr_colours),
            ("consensus.refinement.lr_opacity", self.lr_opacity),
            ("consensus.refinement.lr_log_scales", self.lr_log_scales),
            ("consensus.refinement.lr_rotations", self.lr_rotations),
            (
                "consensus.refinement.lr_pose_translation_m",
                self.lr_pose_translation_m,
            ),
            (
                "consensus.refinement.lr_pose_rotation_rad",
                self.lr_pose_rotation_rad,
            ),
            (
                "consensus.refinement.max_pose_change_m",
                self.max_pose_change_m,
            ),
            (
                "consensus.refinement.max_pose_change_rad",
                self.max_pose_change_rad,
            ),
        ] {
            non_negative(field, v)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_is_per_view_up_to_the_cap_and_zero_turns_it_off() {
        let config = RefinementConfig {
            iterations_per_view: 40,
            max_iterations: 1000,
            ..RefinementConfig::default()
        };
        assert_eq!(config.iterations_for(12), 480);
        assert_eq!(config.iterations_for(30), 1000, "capped");
        assert_eq!(config.iterations_for(0), 0);
        assert!(config.enabled());
        let huge = RefinementConfig {
            iterations_per_view: usize::MAX,
            ..config.clone()
        };
        assert_eq!(huge.iterations_for(3), 1000, "no overflow");
        for off in [
            RefinementConfig {
                iterations_per_view: 0,
                ..config.clone()
            },
            RefinementConfig {
                max_iterations: 0,
                ..config.clone()
            },
        ] {
            assert!(!off.enabled());
            assert_eq!(off.iterations_for(12), 0);
        }
    }
}
