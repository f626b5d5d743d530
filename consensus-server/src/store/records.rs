//! What the store holds: the run's identity and the accepted inputs, as serde types (bincode on
//! disk).

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::se3::{isometry_from_tum, isometry_to_tum};
use image::RgbImage;
use protocol::messages::GaussianRecord;
use serde::{Deserialize, Serialize};

use crate::alignment::Keyframe;
use crate::engine::{ExactIsometry, KeyframeArrival};
use crate::place_recognition::KeyframeRef;

/// Which run a store belongs to: a consensus resumes only its own run's store.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunIdentity {
    /// `mac-consensus --run-id` (the namespace when not given).
    pub run_id: String,
    /// [`config::Config::hash`] of the consensus's configuration.
    pub config_hash: u64,
    /// `--agents N`, the agents the run waits for (`None`: until stopped).
    pub agents: Option<u32>,
}

impl RunIdentity {
    /// What differs from `other`, in words (stored value first); empty when the same run.
    pub fn differences(&self, other: &RunIdentity) -> Vec<String> {
        let mut differences = Vec::new();
        if self.run_id != other.run_id {
            differences.push(format!(
                "run id '{}' there, '{}' here",
                self.run_id, other.run_id
            ));
        }
        if self.config_hash != other.config_hash {
            differences.push(format!(
                "configuration hash {:016x} there, {:016x} here",
                self.config_hash, other.config_hash
            ));
        }
        if self.agents != other.agents {
            let count = |agents: Option<u32>| agents.map_or("any".to_string(), |n| n.to_string());
            differences.push(format!(
                "{} agents there, {} here",
                count(self.agents),
                count(other.agents)
            ));
        }
        differences
    }
}

/// One accepted input, as the consensus received it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub enum StoredInput {
    /// Incarnation `epoch` of an agent said hello with its run anchor and configuration hash.
    Hello {
        /// The agent that said hello.
        agent_id: u32,
        /// The process's incarnation: nanoseconds since the Unix epoch at its start-up.
        epoch: u64,
        /// Identifies the frame the agent tracks in (a hash of its dataset and first frame): a
        /// restart on other frames sends another value.
        run_anchor: u64,
        /// Hash of the agent's configuration.
        config_hash: u64,
    },
    /// An agent said goodbye: it is done until it says hello again.
    Goodbye {
        /// The agent that said goodbye.
        agent_id: u32,
    },
    /// A keyframe whose descriptor and image are both there.
    Keyframe(Box<StoredKeyframe>),
    /// A keyframe's Gaussians, or an agent's final map
    /// (`protocol::messages::FINAL_MAP_KEYFRAME_ID`).
    Patch {
        /// The agent that sent the patch.
        agent_id: u32,
        /// The keyframe the Gaussians came with, or `FINAL_MAP_KEYFRAME_ID` for the final map.
        keyframe_id: u64,
        /// The sending process's incarnation.
        epoch: u64,
        /// The Gaussians as received, in the agent's own frame.
        records: Vec<GaussianRecord>,
    },
}

/// A complete keyframe: what [`KeyframeArrival`] holds besides Gaussians, and the incarnation
/// that sent it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StoredKeyframe {
    /// The agent that made the keyframe.
    pub agent_id: u32,
    /// The keyframe's number on its agent.
    pub keyframe_id: u64,
    /// The incarnation of the agent's process that sent it.
    pub epoch: u64,
    /// Index of the keyframe's frame in its agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// The L2-normalised global descriptor.
    pub descriptor: Vec<f32>,
    /// The pinhole camera of the images, in pixels.
    pub intrinsics: Intrinsics,
    /// The tracked pose, camera to the agent's own frame: `[tx, ty, tz, qx, qy, qz, qw]` (TUM
    /// order).
    pub agent_from_camera: [f64; 7],
    /// Image width, pixels (of both `rgb` and `depth_m`).
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Row-major RGB, 3 bytes a pixel.
    pub rgb: Vec<u8>,
    /// Row-major metres, 0 = invalid.
    pub depth_m: Vec<f32>,
}

impl StoredKeyframe {
    /// The keyframe of `arrival` (its Gaussians are stored apart, as patches), sent by
    /// incarnation `epoch`.
    pub fn new(arrival: &KeyframeArrival, epoch: u64) -> Self {
        let keyframe = &arrival.keyframe;
        Self {
            agent_id: keyframe.id.agent_id,
            keyframe_id: keyframe.id.keyframe_id,
            epoch,
            frame_index: arrival.frame_index,
            timestamp_s: arrival.timestamp_s,
            descriptor: arrival.descriptor.clone(),
            intrinsics: keyframe.intrinsics,
            agent_from_camera: isometry_to_tum(&keyframe.agent_from_camera),
            width: keyframe.rgb.width(),
            height: keyframe.rgb.height(),
            rgb: keyframe.rgb.as_raw().clone(),
            depth_m: keyframe.depth.data.clone(),
        }
    }

    /// The keyframe's identity in the swarm.
    pub fn id(&self) -> KeyframeRef {
        KeyframeRef {
            agent_id: self.agent_id,
            keyframe_id: self.keyframe_id,
        }
    }

    /// The keyframe as the inbox takes it; an error names the keyframe when the stored image
    /// or pose is inconsistent.
    pub fn keyframe(&self) -> anyhow::Result<Keyframe> {
        let name = || {
            format!(
                "stored keyframe {} of agent {}",
                self.keyframe_id, self.agent_id
            )
        };
        let rgb = RgbImage::from_raw(self.width, self.height, self.rgb.clone())
            .ok_or_else(|| anyhow::anyhow!("{}: RGB size does not match", name()))?;
        if self.depth_m.len() != self.width as usize * self.height as usize {
            anyhow::bail!("{}: depth size does not match", name());
        }
        let agent_from_camera = isometry_from_tum(&self.agent_from_camera)
            .map_err(|error| anyhow::anyhow!("{}: pose: {error}", name()))?;
        Ok(Keyframe {
            id: self.id(),
            rgb,
            depth: DepthImage {
                width: self.width,
                height: self.height,
                data: self.depth_m.clone(),
            },
            intrinsics: self.intrinsics,
            agent_from_camera,
        })
    }
}

/// One correction as it was sent to an agent: its frame in the world and its keyframes' poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoredCorrection {
    /// The agent the correction was sent to.
    pub agent_id: u32,
    /// The agent's corrections in the order they were sent, from 0, across the run's consensus
    /// processes.
    pub sequence: u64,
    /// Maps the agent's own frame into the world frame (agent 0's).
    pub world_from_agent: ExactIsometry,
    /// `(keyframe id, world_from_camera)` of each of the agent's placed keyframes.
    pub world_from_camera: Vec<(u64, ExactIsometry)>,
}
