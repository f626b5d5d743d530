//! The `[mapping]` section: map optimisation and pruning, read by the agent's mapper.

use geometry::checks::{FieldError, at_least_one, fraction, nice_value, non_negative, positive};
use serde::{Deserialize, Serialize};

/// How an agent's frame loop is timed against the camera clock and its mapper (docs/method.md,
/// One agent: Pace).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pace {
    /// Frames arrive at the dataset's own timestamps, as from a live camera; an agent that falls
    /// behind skips the frames a live driver would have overwritten, and counts them. The honest
    /// real-time figure.
    #[default]
    Sensor,
    /// The agent takes the next frame only once its mapper has spent
    /// `iterations_per_keyframe` iterations on the newest keyframe: the same map on any machine
    /// for a given seed.
    Paced,
    /// Every frame, as fast as the agent goes; the mapper iterates while the tracker works
    /// (batch processing).
    Unthrottled,
}

/// Map optimisation and pruning.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MappingConfig {
    /// `sensor` (default), `paced` or `unthrottled`: see [`Pace`].
    pub pace: Pace,
    /// Paced: mapping iterations after each keyframe before the agent takes its next frame. They
    /// go to the newest keyframe first, then to random earlier ones (the mapper's usual order).
    pub iterations_per_keyframe: usize,
    /// Extra wall time per mapping iteration, to see what a slower machine would get (sensor
    /// pace drops more frames; paced runs take longer and give the same map). 0: none.
    pub simulated_iteration_delay_ms: f64,
    /// Sensor pace: nice value (0-19) of the agent's work that tracking must not wait for: the
    /// mapping thread (and the renderer's worker threads it starts) and the keyframe descriptor.
    /// Tracking, which must keep up with the camera, gets the cores first; the rest runs on what
    /// is left. 0: the same priority as tracking. Other paces ignore it (there tracking either
    /// waits for the mapper or runs a batch).
    pub sensor_background_niceness: i32,
    /// Weight of the colour L1 term of the mapping loss (default 0.8).
    pub weight_l1: f64,
    /// Weight of the (1 - SSIM) colour term of the mapping loss (default 0.2).
    pub weight_ssim: f64,
    /// Weight of L1(depth / truncation).
    pub weight_depth: f64,
    /// Learning rate of means, multiplied by the scene scale.
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
    /// Prune every n mapper iterations.
    pub prune_every: usize,
    /// Pruning removes Gaussians whose opacity (after the sigmoid) is below this; in [0, 1]
    /// (default 0.005).
    pub prune_min_opacity: f64,
    /// tau_s: largest allowed scale (metres; 1.0, or 0.25 for Replica-like scenes).
    pub prune_max_scale_m: f64,
    /// Largest allowed max scale / (sum of the other two).
    pub prune_max_elongation: f64,
    /// Keyframes are optimised at their resolution divided by this (1 = full resolution, as
    /// docs/method.md, One agent: Map optimisation, describes it). On a CPU Vulkan device (lavapipe) a 640x480 iteration costs seconds; a factor of 2
    /// or 4 buys 4x or 16x more iterations for the same time.
    pub image_downscale: u32,
    /// Seed of the mapper's choice of earlier keyframes (runs are repeatable).
    pub random_seed: u64,
    /// Optimise each keyframe's pose with the map, photometrically, as the consensus's joint
    /// refinement does (docs/method.md, One agent: Map optimisation). The first keyframe stays
    /// (it fixes the map's frame). The tracked trajectory is not changed; the agent's evaluation
    /// renders each frame where the refinement of its neighbouring keyframes moved it. A swarm
    /// agent sends its final map as fitted, at the refined poses; the consensus, which knows the
    /// tracked ones, closes the gap in its joint refinement.
    pub refine_keyframe_poses: bool,
    /// Adam step sizes of a keyframe pose (metres and radians per step).
    pub lr_pose_translation_m: f64,
    /// Rotation step size of a keyframe pose, radians (default 2e-4).
    pub lr_pose_rotation_rad: f64,
    /// A keyframe pose stays within this distance of its tracked pose (metres, radians): a step
    /// that would take it farther is not taken.
    pub max_pose_change_m: f64,
    /// Rotation limit of a keyframe pose, radians (default 2 degrees).
    pub max_pose_change_rad: f64,
    /// Read the pair count back every n iterations (one blocking read) to grow the binning
    /// buffers when the map outgrows them.
    pub check_pairs_every: usize,
}

impl Default for MappingConfig {
    fn default() -> Self {
        Self {
            pace: Pace::Sensor,
            iterations_per_keyframe: 100,
            simulated_iteration_delay_ms: 0.0,
            sensor_background_niceness: 19,
            weight_l1: 0.8,
            weight_ssim: 0.2,
            weight_depth: 2.0,
            lr_means: 5e-6,
            lr_colours: 2.5e-3,
            lr_opacity: 0.05,
            lr_log_scales: 0.01,
            lr_rotations: 0.0,
            prune_every: 200,
            prune_min_opacity: 0.005,
            prune_max_scale_m: 1.0,
            prune_max_elongation: 10.0,
            image_downscale: 1,
            random_seed: 0,
            refine_keyframe_poses: false,
            lr_pose_translation_m: 2e-4,
            lr_pose_rotation_rad: 2e-4,
            max_pose_change_m: 0.05,
            max_pose_change_rad: 2f64.to_radians(),
            check_pairs_every: 50,
        }
    }
}

impl MappingConfig {
    /// The nice value of the agent's background work (mapper, descriptor) under this pace:
    /// `sensor_background_niceness` at the sensor pace, 0 otherwise.
    pub fn background_niceness(&self) -> i32 {
        match self.pace {
            Pace::Sensor => self.sensor_background_niceness,
            Pace::Paced | Pace::Unthrottled => 0,
        }
    }

    /// Checks ranges; returns the offending field (`mapping.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        for (field, v) in [
            ("mapping.weight_l1", self.weight_l1),
            ("mapping.weight_ssim", self.weight_ssim),
            ("mapping.weight_depth", self.weight_depth),
            ("mapping.lr_means", self.lr_means),
            ("mapping.lr_colours", self.lr_colours),
            ("mapping.lr_opacity", self.lr_opacity),
            ("mapping.lr_log_scales", self.lr_log_scales),
            ("mapping.lr_rotations", self.lr_rotations),
            ("mapping.lr_pose_translation_m", self.lr_pose_translation_m),
            ("mapping.lr_pose_rotation_rad", self.lr_pose_rotation_rad),
        ] {
            non_negative(field, v)?;
        }
        at_least_one("mapping.prune_every", self.prune_every)?;
        non_negative(
            "mapping.simulated_iteration_delay_ms",
            self.simulated_iteration_delay_ms,
        )?;
        nice_value(
            "mapping.sensor_background_niceness",
            self.sensor_background_niceness,
        )?;
        if self.pace == Pace::Paced {
            at_least_one(
                "mapping.iterations_per_keyframe",
                self.iterations_per_keyframe,
            )?;
        }
        fraction("mapping.prune_min_opacity", self.prune_min_opacity)?;
        positive("mapping.prune_max_scale_m", self.prune_max_scale_m)?;
        positive("mapping.prune_max_elongation", self.prune_max_elongation)?;
        positive("mapping.max_pose_change_m", self.max_pose_change_m)?;
        positive("mapping.max_pose_change_rad", self.max_pose_change_rad)?;
        at_least_one("mapping.image_downscale", self.image_downscale as usize)?;
        at_least_one("mapping.check_pairs_every", self.check_pairs_every)?;
        Ok(())
    }
}
