//! What the engine records: every attempt's decision and each keyframe's tracked pose
//! (consensus.json).

use serde::{Deserialize, Serialize};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::CandidateSource;
use crate::map_links::MapAttemptScores;
use crate::place_recognition::KeyframeRef;
use crate::pose_graph::EdgeSigmas;

/// What was compared to decide an attempt (consensus.json).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttemptKind {
    /// Two keyframes' images and depth.
    Keyframe,
    /// Two agents' maps.
    Map,
}

/// One alignment decision (consensus.json).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ClosureEvent {
    /// Seconds since the engine started.
    pub at_s: f64,
    /// The keyframe whose camera frame the measurement maps from (for a map attempt, the source
    /// agent's end of the link, or its newest keyframe when no closure came of it).
    pub source: KeyframeRef,
    /// The keyframe whose camera frame the measurement maps into (for a map attempt, the target
    /// agent's end of the link, or its newest keyframe).
    pub target: KeyframeRef,
    /// Why the pair was attempted.
    pub origin: CandidateSource,
    /// Whether `source` and `target` belong to different agents.
    pub inter_agent: bool,
    /// Descriptor score (place-recognition candidates only).
    pub score: Option<f32>,
    /// Alignment verified the pair.
    pub verified: bool,
    /// Keyframe pair or agents' maps.
    pub kind: AttemptKind,
    /// Inlier correspondences of the coarse registration (features or map points).
    pub inliers: Option<usize>,
    /// Overlap after alignment: the fraction of source points with a target point within the
    /// finest correspondence distance.
    pub overlap: Option<f64>,
    /// The map registration's figures (map attempts only).
    pub map: Option<MapAttemptScores>,
    /// Why alignment rejected it.
    pub rejection: Option<String>,
    /// Whether the latest pose-graph solve kept it (verified pairs only; `None` before a solve).
    pub accepted_by_pose_graph: Option<bool>,
    /// Wall-clock time of the alignment or map registration, milliseconds (0 for an injected
    /// closure).
    pub alignment_ms: f64,
    /// What joined the pose graph (verified and injected closures; `None` otherwise).
    pub measurement: Option<ClosureMeasurement>,
}

/// A closure's relative pose and uncertainty, as the pose graph takes it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClosureMeasurement {
    /// Maps the source keyframe's camera coordinates into the target keyframe's (metres).
    pub target_camera_from_source_camera: ExactIsometry,
    /// The measurement's own standard deviations; `None`: the configured loop-closure ones.
    pub sigmas: Option<EdgeSigmas>,
}

/// A rigid transform kept bit for bit: `[tx, ty, tz, qx, qy, qz, qw]` (TUM order) with the
/// quaternion as computed, neither renormalised nor sign-flipped, so that a stored closure or
/// correction reads back as exactly the transform that was used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct ExactIsometry(pub [f64; 7]);

impl From<&Isometry3<f64>> for ExactIsometry {
    fn from(pose: &Isometry3<f64>) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        Self([t.x, t.y, t.z, q.i, q.j, q.k, q.w])
    }
}

impl ExactIsometry {
    /// The transform, with the stored quaternion taken as is (not renormalised).
    pub fn isometry(&self) -> Isometry3<f64> {
        let [tx, ty, tz, qx, qy, qz, qw] = self.0;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            // Written from a unit quaternion, so unit already; renormalising could change bits.
            UnitQuaternion::new_unchecked(Quaternion::new(qw, qx, qy, qz)),
        )
    }
}

/// What the engine knows about one keyframe besides its images.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct KeyframeInfo {
    /// Index of the keyframe's frame in its agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// The keyframe's pose as its agent tracked it (camera to the agent's own frame):
    /// `[tx, ty, tz, qx, qy, qz, qw]` (TUM order).
    pub agent_from_camera: [f64; 7],
}
