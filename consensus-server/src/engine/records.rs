//! What the engine records: every attempt's decision and each keyframe's tracked pose
//! (consensus.json).

use serde::Serialize;

use super::CandidateSource;
use crate::map_links::MapAttemptScores;
use crate::place_recognition::KeyframeRef;

/// What was compared to decide an attempt (consensus.json).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AttemptKind {
    /// Two keyframes' images and depth.
    Keyframe,
    /// Two agents' maps.
    Map,
}

/// One alignment decision (consensus.json).
#[derive(Debug, Clone, Serialize)]
pub struct ClosureEvent {
    /// Seconds since the engine started.
    pub at_s: f64,
    pub source: KeyframeRef,
    pub target: KeyframeRef,
    pub origin: CandidateSource,
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
    pub alignment_ms: f64,
}

/// What the engine knows about one keyframe besides its images.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct KeyframeInfo {
    pub frame_index: u64,
    pub timestamp_s: f64,
    /// `[tx, ty, tz, qx, qy, qz, qw]` (TUM order).
    pub agent_from_camera: [f64; 7],
}
