//! What the odometry takes and reports per frame, and its counters.

use std::fmt;
use std::str::FromStr;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;
use serde::Serialize;

use crate::gicp::{RegistrationFailure, RegistrationResult};
use crate::points::PointCloud;

use super::check::{Divergence, FrameCheck};
use super::recovery::Guess;
use super::segments::{SegmentId, SegmentJoin};

/// What the odometry aligns each frame against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OdometryMode {
    /// The previous frame's points.
    FrameToFrame,
    /// The map of keyframe points (what the agent does with its Gaussians).
    #[default]
    FrameToModel,
}

impl FromStr for OdometryMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "frame-to-frame" => Ok(Self::FrameToFrame),
            "frame-to-model" => Ok(Self::FrameToModel),
            other => Err(format!(
                "unknown tracking mode {other:?}: expected frame-to-frame or frame-to-model"
            )),
        }
    }
}

impl fmt::Display for OdometryMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::FrameToFrame => "frame-to-frame",
            Self::FrameToModel => "frame-to-model",
        })
    }
}

/// One frame as the tracker takes it.
#[derive(Debug, Clone, Copy)]
pub struct FrameInput<'a> {
    /// Seconds, any origin.
    pub timestamp_s: f64,
    /// Depth in metres, invalid pixels 0 (see [`crate::points`]).
    pub depth: &'a DepthImage,
    /// Colour, for the image-feature guesses (recovery and relocalisation); without it those
    /// are geometric only.
    pub rgb: Option<&'a RgbImage>,
    /// The depth image's camera; a colour image is expected registered to it (same size).
    pub intrinsics: &'a Intrinsics,
    /// When the colour image was taken relative to the depth image (seconds, colour minus
    /// depth; `datasets::Frame::colour_offset_s`): the photometric term compares the colour
    /// image from the pose the camera had then, predicted by the constant-velocity motion.
    pub colour_offset_s: f64,
    /// The frame came from a live camera or a sensor-paced replay, which do not wait for the
    /// tracker: the expensive recovery work is rationed (`recovery_time_share`).
    pub real_time: bool,
}

/// Why a frame was not placed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrackingFailure {
    /// No registration gave a usable pose: G-ICP failed (or the frame had too few points for
    /// any guess to run).
    #[error("{0}")]
    Registration(RegistrationFailure),
    /// The chosen registration's pose was refused by the depth-agreement check.
    #[error("{0}")]
    Diverged(Divergence),
}

/// How a frame's pose was obtained.
#[derive(Debug, Clone, PartialEq)]
pub enum TrackingOutcome {
    /// First frame of a segment (the run's first, or the first after repeated failures): the
    /// frame starts the segment's map at its origin.
    Initialised,
    /// The ordinary path's G-ICP converged and passed the check.
    Tracked,
    /// The ordinary path's G-ICP used all its iterations while still lowering the error and
    /// passed the check; its pose is used.
    TrackedNotConverged,
    /// A wide-baseline guess gave the pose (see [`recovery`]).
    Recovered(Guess),
    /// No guess placed the frame; the pose is the prediction and must not be trusted.
    Lost(TrackingFailure),
}

impl TrackingOutcome {
    /// The pose came from a registration that passed the check.
    pub fn is_tracked(&self) -> bool {
        matches!(
            self,
            Self::Tracked | Self::TrackedNotConverged | Self::Recovered(_)
        )
    }
}

/// Which frame a pose is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Placement {
    /// The root frame: the first segment's, into which joined segments were moved.
    Root,
    /// The frame of a segment not joined (yet): its first camera is its origin.
    Unjoined(SegmentId),
}

/// One frame's result.
#[derive(Debug, Clone)]
pub struct TrackedFrame {
    /// In the frame [`Self::placement`] names.
    pub world_from_camera: Isometry3<f64>,
    /// The frame `world_from_camera` maps into: the root or an unjoined segment's.
    pub placement: Placement,
    /// How the pose was obtained (and, for a lost frame, why it could not be).
    pub outcome: TrackingOutcome,
    /// The final G-ICP run, when there was one.
    pub registration: Option<RegistrationResult>,
    /// The check of the final pose, when there was one (frame-to-model).
    pub check: Option<FrameCheck>,
    /// At this frame a segment was joined to the root (its earlier poses move by the join's
    /// transform; this frame's pose is already in the root).
    pub join: Option<SegmentJoin>,
    /// Points back-projected from the frame.
    pub points: usize,
    /// The frame added points to the map (frame-to-model tracking keyframe or initialisation).
    pub keyframe: bool,
    /// The frame's points in its camera frame, with covariances and source pixels (the agent
    /// seeds Gaussians from them).
    pub frame_points: PointCloud,
    /// At a keyframe: per point of `frame_points`, whether it joined the tracking map (the
    /// trackable flag of docs/method.md, One agent: Keyframes). `None` on other frames.
    pub trackable: Option<Vec<bool>>,
    /// Wall time spent on this frame, per stage.
    pub timings: StageTimings,
}

impl TrackedFrame {
    /// The frame's confidence in [0, 1]: the check's depth agreement; 1 for a segment's first
    /// frame (it defines its frame), 0 for a lost frame.
    pub fn confidence(&self) -> f64 {
        match &self.outcome {
            TrackingOutcome::Initialised => 1.0,
            TrackingOutcome::Lost(_) => 0.0,
            _ => self.check.map_or(1.0, |c| c.confidence()),
        }
    }
}

/// Wall time of the stages of [`Odometry::track`], milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimings {
    /// Points from depth, kd-tree and covariances.
    pub points_ms: f64,
    /// View selection, initial-guess check, G-ICP and the check.
    pub registration_ms: f64,
    /// Wide-baseline guesses (0 when the ordinary path passed).
    pub recovery_ms: f64,
    /// Keyframe insertion into the map, and relocalisation attempts.
    pub map_update_ms: f64,
}

/// Counters over a run.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct OdometryStats {
    /// Frames passed to [`super::Odometry::track`].
    pub frames: usize,
    /// Frames that added at least one point to the map (frame-to-model only; a segment's first
    /// frame included).
    pub keyframes: usize,
    /// Frames no guess placed (pose = prediction).
    pub failures: usize,
    /// Frames whose ordinary G-ICP result the check refused (divergence detected).
    pub divergences: usize,
    /// Frames placed by a wide-baseline guess.
    pub recoveries: usize,
    /// Frames tracked without meeting the convergence thresholds.
    pub not_converged: usize,
    /// Segments started after the first (after `max_consecutive_failures` lost frames).
    pub segments_started: usize,
    /// Segments joined to the root by relocalisation.
    pub segments_joined: usize,
    /// Image-feature or geometry guesses and relocalisation attempts not started at sensor
    /// pace because their share of the time was spent (`recovery_time_share`).
    pub searches_rationed: usize,
    /// Frames whose ordinary G-ICP started from the previous pose: the constant-velocity
    /// prediction found fewer correspondences, or there was no motion to predict.
    pub still_starts: usize,
}
