//! The `[consensus]` section and its tables: what the consensus process reads (place
//! recognition, alignment, pose graph, refinement, map registration) and what agents read of it
//! too (`t_comm`, the descriptor weights, `[consensus.resend]`, `[consensus.local_corrections]`).
//! Every field has a serde default, so a configuration file names only what it changes; the
//! defaults suit a 640x480 RGB-D sensor (7-Scenes, TUM, the synthetic scene).

mod false_closures;
mod merge;
mod pose_graph;
mod refinement;

use std::path::PathBuf;

use geometry::checks::{FieldError, at_least_one, fraction, nice_value, non_negative, positive};
use serde::{Deserialize, Serialize};

pub use false_closures::FalseClosureConfig;
pub use merge::MergeConfig;
pub use pose_graph::PoseGraphConfig;
pub use refinement::RefinementConfig;
pub use registration::alignment::AlignmentConfig;
pub use registration::map_registration::MapRegistrationConfig;

/// Inter-agent consensus (docs/method.md, The consensus).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConsensusConfig {
    /// Agents publish a keyframe descriptor every T_comm frames (60 for 7-Scenes, 150 Replica).
    pub t_comm: usize,
    /// Descriptor score above which two keyframes of the same agent propose a loop closure.
    pub tau_same_agent: f64,
    /// Descriptor score above which keyframes of different agents propose a loop closure.
    pub tau_other_agent: f64,
    /// Same-agent keyframes closer than this many frames are never proposed as loop closures:
    /// odometry already links them and their images are trivially alike (the method does not say; 10 s at 30 Hz).
    pub same_agent_min_frame_gap: usize,
    /// Place-recognition proposals aligned per new keyframe at most (the best-scoring ones):
    /// alignment costs about a second on a CPU, and the best few carry the overlap.
    pub max_candidates_per_keyframe: usize,
    /// Sensor pace (`mapping.pace`): nice value (0-19) of the consensus process. On one host
    /// with its agents (a simulated swarm) it then takes the cores their tracking leaves, as the
    /// agents' mappers do; on a host of its own it changes nothing. 0: the same priority.
    pub sensor_niceness: i32,
    /// Joint refinement weights.
    pub weight_l1: f64,
    /// Weight of the (1 - SSIM) colour term of the joint refinement loss (default 0.2).
    pub weight_ssim: f64,
    /// Weight of the depth L1 term of the joint refinement loss, errors in metres (default 0.1).
    pub weight_depth: f64,
    /// alpha: weight of the pose-consistency term.
    pub weight_pose_consistency: f64,
    /// AlexNet weights for the global descriptor; without them a classical descriptor is used.
    pub descriptor_weights: Option<PathBuf>,
    /// Keyframe-to-keyframe alignment (association, G-ICP, verification): `[consensus.alignment]`.
    pub alignment: AlignmentConfig,
    /// Robust pose graph: `[consensus.pose_graph]`.
    pub pose_graph: PoseGraphConfig,
    /// How the agents' maps become one world map: `[consensus.merge]`.
    pub merge: MergeConfig,
    /// Joint photometric refinement of the merged map: `[consensus.refinement]`.
    pub refinement: RefinementConfig,
    /// How agents apply corrections to their local maps: `[consensus.local_corrections]`.
    pub local_corrections: LocalCorrectionConfig,
    /// Re-requesting keyframes that arrived incomplete: `[consensus.resend]`.
    pub resend: ResendConfig,
    /// Map-to-map global registration without an initial guess: `[consensus.map_registration]`.
    pub map_registration: MapRegistrationConfig,
    /// Deliberately wrong closures for robustness measurements (off by default):
    /// `[consensus.false_closures]`.
    pub false_closures: FalseClosureConfig,
}

impl Default for ConsensusConfig {
    fn default() -> Self {
        Self {
            t_comm: 60,
            tau_same_agent: 0.80,
            tau_other_agent: 0.85,
            same_agent_min_frame_gap: 300,
            max_candidates_per_keyframe: 3,
            sensor_niceness: 19,
            weight_l1: 0.8,
            weight_ssim: 0.2,
            weight_depth: 0.1,
            weight_pose_consistency: 1.0,
            descriptor_weights: None,
            alignment: AlignmentConfig::default(),
            pose_graph: PoseGraphConfig::default(),
            merge: MergeConfig::default(),
            refinement: RefinementConfig::default(),
            local_corrections: LocalCorrectionConfig::default(),
            resend: ResendConfig::default(),
            map_registration: MapRegistrationConfig::default(),
            false_closures: FalseClosureConfig::default(),
        }
    }
}

impl ConsensusConfig {
    /// Checks ranges of this section and its tables; returns the offending field
    /// (`consensus.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        at_least_one("consensus.t_comm", self.t_comm)?;
        nice_value("consensus.sensor_niceness", self.sensor_niceness)?;
        at_least_one(
            "consensus.max_candidates_per_keyframe",
            self.max_candidates_per_keyframe,
        )?;
        fraction("consensus.tau_same_agent", self.tau_same_agent)?;
        fraction("consensus.tau_other_agent", self.tau_other_agent)?;
        for (field, v) in [
            ("consensus.weight_l1", self.weight_l1),
            ("consensus.weight_ssim", self.weight_ssim),
            ("consensus.weight_depth", self.weight_depth),
            (
                "consensus.weight_pose_consistency",
                self.weight_pose_consistency,
            ),
        ] {
            non_negative(field, v)?;
        }
        self.alignment.validate()?;
        self.merge.validate()?;
        self.refinement.validate()?;
        self.local_corrections.validate()?;
        self.resend.validate()?;
        self.false_closures.validate()?;
        self.pose_graph.validate()?;
        self.map_registration.validate()
    }
}

/// How an agent applies the consensus's corrections to its local maps (docs/method.md, The
/// consensus: pose graph: corrections go back to agents, which apply them to their local maps
/// between frames): the
/// `[consensus.local_corrections]` table.
///
/// A correction carries the corrected pose of every keyframe the agent published. The agent
/// moves each part of its mapping map, its keyframe poses and its coverage index (and, with
/// `move_tracking_map`, its tracking map) with the correction blended at the time that part was
/// made (the consensus's own rule for per-frame trajectories), so a drift the pose graph
/// removed is also removed from the map the agent builds. What it publishes stays in its
/// tracked (uncorrected) frame, which the consensus's odometry edges are built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalCorrectionConfig {
    /// Apply corrections to the local maps at all (false: they are only recorded).
    pub apply: bool,
    /// Whether the tracking map moves with the corrections too (the mapping map, keyframe poses
    /// and coverage index always do when `apply` is on). Off (the default), the tracker is plain
    /// odometry: its poses are the tracked frame by construction, and each is carried into the
    /// corrected frame for seeding and mapping. On, tracking runs in the corrected frame and its
    /// poses are converted back for publishing; but a non-rigid correction leaves parts of the
    /// tracking map that carry different corrections side by side, a frame that sees several
    /// of them lands between them, and part of the correction leaks into the tracked poses as
    /// motion the odometry never made. On redkitchen (two agents, 0..600 and 400..1000, T_comm
    /// 30 frames) that doubled the agents' own ATE and raised the joint ATE by 0.6 cm with the
    /// same pose-graph settings (docs/benchmarks.md, "the tracking map stays out of the
    /// corrections").
    pub move_tracking_map: bool,
    /// A correction is applied only when it would move some keyframe by at least this much
    /// (metres) or `min_rotation_rad`. Smaller changes are mostly pose-graph noise: every solve
    /// moves every keyframe by a millimetre or two. On redkitchen (two agents, 0..600 and
    /// 400..1000) applying every change of 2 mm / 0.1 degrees moved the maps 14-18 times per
    /// agent, cost up to 6 s of tracking time and raised the joint ATE from 2.89 to 3.25 cm (the
    /// small moves of overlapping parts blur the surfaces G-ICP aligns to); 1 cm / 0.5 degrees
    /// applied 6-8 corrections (the real drift fixes) for 2.95 cm.
    pub min_translation_m: f64,
    /// Radians (0.5 degrees).
    pub min_rotation_rad: f64,
    /// Within an applied correction, a part of the tracking map or coverage index (the points
    /// one frame added) moves only when its own move reaches this (metres) or
    /// `part_min_rotation_rad`; a part that waits keeps its correction and moves the whole way
    /// later. Moving a point costs a removal and an insertion in the index, and most of the map
    /// (far from where the pose graph changed) moves by far less than the depth noise.
    pub part_min_translation_m: f64,
    /// Radians (0.1 degrees).
    pub part_min_rotation_rad: f64,
}

impl Default for LocalCorrectionConfig {
    fn default() -> Self {
        Self {
            apply: true,
            move_tracking_map: false,
            min_translation_m: 0.01,
            min_rotation_rad: 0.5_f64.to_radians(),
            part_min_translation_m: 0.002,
            part_min_rotation_rad: 0.1_f64.to_radians(),
        }
    }
}

impl LocalCorrectionConfig {
    /// Checks ranges; returns the offending field (`consensus.local_corrections.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        for (field, v) in [
            (
                "consensus.local_corrections.min_translation_m",
                self.min_translation_m,
            ),
            (
                "consensus.local_corrections.min_rotation_rad",
                self.min_rotation_rad,
            ),
            (
                "consensus.local_corrections.part_min_translation_m",
                self.part_min_translation_m,
            ),
            (
                "consensus.local_corrections.part_min_rotation_rad",
                self.part_min_rotation_rad,
            ),
        ] {
            non_negative(field, v)?;
        }
        Ok(())
    }
}

/// Re-requesting keyframes that arrived incomplete: the `[consensus.resend]` table.
///
/// A published keyframe is three messages (descriptor, RGB-D image, Gaussian patch). One can be
/// lost: a full queue, an agent that restarted between them, a sample iceoryx2 dropped. The
/// consensus notices a keyframe with some parts and not others, waits `after_s` (the parts of
/// one keyframe go out back to back, so a longer wait means loss, not delay) and asks the agent
/// to publish it again (`ControlMessage::ResendKeyframe`), at most `max_requests` times. The
/// agent keeps its last `agent_keeps` published keyframes in memory for that, and older ones it
/// delivered on disk (up to `agent_spool_bytes`) until the consensus confirms it stored them (a
/// correction naming them, or a resumed consensus's list of held keyframes); one gone from both
/// is answered by nothing (counted on both sides).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResendConfig {
    /// Seconds an incomplete keyframe waits before (and between) requests.
    pub after_s: f64,
    /// Requests per keyframe before the consensus gives up on it (0: never ask).
    pub max_requests: usize,
    /// Published keyframes an agent keeps for re-sending (each holds its RGB-D image and its
    /// Gaussians: ~2.5 MB at 640x480 plus 56 bytes per Gaussian).
    pub agent_keeps: usize,
    /// Bytes of older published keyframes an agent keeps on disk (its output folder's
    /// `keyframe_spool/`) until the consensus confirms it stored them, so a consensus restarted
    /// on its store can be given every one again; beyond it the oldest are dropped.
    pub agent_spool_bytes: u64,
}

impl Default for ResendConfig {
    fn default() -> Self {
        Self {
            after_s: 2.0,
            max_requests: 3,
            agent_keeps: 8,
            agent_spool_bytes: 2 << 30,
        }
    }
}

impl ResendConfig {
    /// Checks ranges; returns the offending field (`consensus.resend.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        positive("consensus.resend.after_s", self.after_s)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partial_config_keeps_defaults() {
        let config: ConsensusConfig =
            toml::from_str("[alignment]\nmax_residual_m = 0.02\n").unwrap();
        assert_eq!(config.alignment.max_residual_m, 0.02);
        assert_eq!(
            config.alignment.correspondence_distances_m,
            vec![0.1, 0.05, 0.02]
        );
        assert_eq!(config.pose_graph, PoseGraphConfig::default());
        assert!(toml::from_str::<AlignmentConfig>("typo = 1").is_err());
    }
}
