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
        agent_id: u32,
        epoch: u64,
        run_anchor: u64,
        config_hash: u64,
    },
    Goodbye {
        agent_id: u32,
    },
    /// A keyframe whose descriptor and image are both there.
    Keyframe(Box<StoredKeyframe>),
    /// A keyframe's Gaussians, or an agent's final map
    /// (`protocol::messages::FINAL_MAP_KEYFRAME_ID`).
    Patch {
        agent_id: u32,
        keyframe_id: u64,
        epoch: u64,
        records: Vec<GaussianRecord>,
    },
}

/// A complete keyframe: what [`KeyframeArrival`] holds besides Gaussians, and the incarnation
/// that sent it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StoredKeyframe {
    pub agent_id: u32,
    pub keyframe_id: u64,
    pub epoch: u64,
    pub frame_index: u64,
    pub timestamp_s: f64,
    pub descriptor: Vec<f32>,
    pub intrinsics: Intrinsics,
    /// `[tx, ty, tz, qx, qy, qz, qw]` (TUM order).
    pub agent_from_camera: [f64; 7],
    pub width: u32,
    pub height: u32,
    /// Row-major RGB, 3 bytes a pixel.
    pub rgb: Vec<u8>,
    /// Row-major metres, 0 = invalid.
    pub depth_m: Vec<f32>,
}

impl StoredKeyframe {
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
    pub agent_id: u32,
    /// The agent's corrections in the order they were sent, from 0, across the run's consensus
    /// processes.
    pub sequence: u64,
    pub world_from_agent: ExactIsometry,
    /// `(keyframe id, world_from_camera)` of each of the agent's placed keyframes.
    pub world_from_camera: Vec<(u64, ExactIsometry)>,
}
