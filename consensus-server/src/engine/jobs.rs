//! The work the engine hands to the aligner thread, and what comes back.

use std::sync::Arc;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::alignment::{AlignmentResult, PreparedKeyframe, align_prepared};
use crate::map_links::{FinishedMapJob, MapJob};
use crate::place_recognition::KeyframeRef;
use config::AlignmentConfig;

/// Why a pair was aligned.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CandidateSource {
    /// Consecutive published keyframes of one agent.
    Odometry,
    /// Proposed by place recognition.
    PlaceRecognition,
    /// Two agents' maps registered with each other ([`crate::map_links`]); the keyframes are
    /// the link's ends (or each agent's newest keyframe when the registration was not used).
    MapRegistration,
    /// A deliberately wrong closure (`[consensus.false_closures]`), never aligned.
    Injected,
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Candidate {
    pub(super) source: KeyframeRef,
    pub(super) target: KeyframeRef,
    pub(super) score: Option<f32>,
    pub(super) origin: CandidateSource,
}

/// One queued alignment with what it needs, free of the engine (see
/// [`Engine::next_alignment`](super::Engine::next_alignment)).
pub struct AlignmentJob {
    pub(super) candidate: Candidate,
    pub(super) source: Arc<PreparedKeyframe>,
    pub(super) target: Arc<PreparedKeyframe>,
    pub(super) config: AlignmentConfig,
}

impl AlignmentJob {
    /// Aligns the pair (about a second on a CPU).
    pub fn run(self) -> FinishedAlignment {
        let clock = Instant::now();
        let result = align_prepared(&self.source, &self.target, &self.config);
        FinishedAlignment {
            candidate: self.candidate,
            result,
            alignment_ms: clock.elapsed().as_secs_f64() * 1e3,
        }
    }
}

/// An [`AlignmentJob`]'s outcome.
pub struct FinishedAlignment {
    pub(super) candidate: Candidate,
    pub(super) result: AlignmentResult,
    pub(super) alignment_ms: f64,
}

/// Work for the aligner thread: a keyframe pair or two agents' maps.
/// Boxed: a job is made a few times a second and moved across threads.
pub enum Job {
    /// Align a queued keyframe candidate.
    Keyframes(Box<AlignmentJob>),
    /// Register two agents' maps.
    Maps(Box<MapJob>),
}

impl Job {
    /// Does the work on the calling thread (the aligner thread in the process).
    pub fn run(self) -> Finished {
        match self {
            Job::Keyframes(job) => Finished::Keyframes(Box::new(job.run())),
            Job::Maps(job) => Finished::Maps(Box::new(job.run())),
        }
    }
}

/// A [`Job`]'s outcome, for [`Engine::record`](super::Engine::record).
pub enum Finished {
    /// A keyframe pair's alignment.
    Keyframes(Box<FinishedAlignment>),
    /// Two agents' map registration, with its checks.
    Maps(Box<FinishedMapJob>),
}
