//! The engine's decisions: what a finished alignment or map registration means for the pose
//! graph, made in two steps so that the process can commit each decision to its store between
//! them ([`Engine::decide`], then [`Engine::apply`]). An engine resuming a run takes the stored
//! decisions ([`Engine::resume_decisions`]) and applies each one as soon as both its keyframes
//! are back, through the same [`Engine::apply`]: the pair is not aligned again, and the pose
//! graph gets the very closure it had. Pairs without a stored decision are aligned as live.
//!
//! Wrong closures injected for robustness measurements (`[consensus.false_closures]`) are not
//! decisions: applying a verified decision draws them again from the seed, live or resumed.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::{
    AttemptKind, CandidateSource, ClosureEvent, ClosureMeasurement, Engine, Finished,
    FinishedAlignment,
};
use crate::map_links::FinishedMapJob;
use crate::place_recognition::KeyframeRef;
use crate::pose_graph::{EdgeSigmas, LoopClosure};
use registration::alignment::Verdict;

/// One attempt's outcome, as consensus.json reports it and the store keeps it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Decision {
    /// The attempt as recorded; its `measurement` joins the pose graph when it is `verified`.
    pub event: ClosureEvent,
    /// Map registrations: the two agents (source, target) and the keyframes each had published
    /// when their maps were taken.
    pub map_attempt: Option<MapAttempt>,
}

/// Which agents' maps a registration compared, and how far each had grown.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapAttempt {
    /// The source and the target agent.
    pub agents: (u32, u32),
    /// Keyframes the source and the target agent had published when their maps were taken.
    pub keyframes_at_attempt: (usize, usize),
}

impl Engine {
    /// What a finished job decided, without acting on it (see the module documentation).
    /// `None` for a map registration with no keyframe to file it under.
    pub fn decide(&self, done: Finished) -> Option<Decision> {
        match done {
            Finished::Keyframes(done) => Some(self.decide_alignment(*done)),
            Finished::Maps(done) => self.decide_map_job(*done),
        }
    }

    /// Acts on a decision: a closure joins the pose graph (solved at the next
    /// [`Self::solve_if_changed`]), the pair counts as attempted, and the event is recorded for
    /// consensus.json.
    pub fn apply(&mut self, decision: Decision) {
        let Decision {
            mut event,
            map_attempt,
        } = decision;
        if event.kind == AttemptKind::Keyframe {
            self.attempted.insert((event.source, event.target));
        }
        if let Some(attempt) = map_attempt {
            self.map_scheduler
                .record_attempt(attempt.agents, attempt.keyframes_at_attempt);
        }
        let Some(measurement) = event.measurement.filter(|_| event.verified) else {
            self.events.push(event);
            return;
        };
        let closure = LoopClosure {
            source: event.source,
            target: event.target,
            target_camera_from_source_camera: measurement
                .target_camera_from_source_camera
                .isometry(),
            sigmas: measurement.sigmas,
        };
        match self.graph.add_loop(closure) {
            Ok(_) => {
                if let Some(attempt) = map_attempt {
                    self.map_scheduler
                        .mark_linked(attempt.agents.0, attempt.agents.1);
                }
                tracing::info!(
                    source = ?event.source,
                    target = ?event.target,
                    inter_agent = event.inter_agent,
                    kind = ?event.kind,
                    "closure verified"
                );
                self.closure_events.push(self.events.len());
                self.events.push(event);
                self.dirty = true;
                self.inject_false_closures();
            }
            Err(error) => {
                tracing::error!(%error, "verified closure not added");
                event.verified = false;
                event.rejection = Some(error.to_string());
                self.events.push(event);
            }
        }
    }

    /// Takes the decisions stored by an earlier process of this run, oldest first: each is
    /// applied once both its keyframes are known (those known now at once), instead of
    /// aligning the pair again.
    pub fn resume_decisions(&mut self, decisions: Vec<Decision>) {
        self.stored_decisions.extend(decisions);
        self.apply_stored_decisions();
    }

    /// Stored decisions still waiting for one of their keyframes.
    pub fn stored_decisions_waiting(&self) -> usize {
        self.stored_decisions.len()
    }

    /// Applies, in stored order, every stored decision whose keyframes are both known.
    pub(super) fn apply_stored_decisions(&mut self) {
        let known = |id: &KeyframeRef| self.prepared.contains_key(id);
        let (due, waiting): (Vec<Decision>, Vec<Decision>) =
            std::mem::take(&mut self.stored_decisions)
                .into_iter()
                .partition(|d| known(&d.event.source) && known(&d.event.target));
        self.stored_decisions = waiting;
        for decision in due {
            self.apply(decision);
        }
    }

    fn decide_alignment(&self, done: FinishedAlignment) -> Decision {
        let FinishedAlignment {
            candidate,
            result,
            alignment_ms,
        } = done;
        let verified = result.is_accepted();
        let event = ClosureEvent {
            at_s: self.started.elapsed().as_secs_f64(),
            source: candidate.source,
            target: candidate.target,
            origin: candidate.origin,
            inter_agent: candidate.source.agent_id != candidate.target.agent_id,
            score: candidate.score,
            verified,
            kind: AttemptKind::Keyframe,
            inliers: result.coarse.map(|c| c.inliers),
            overlap: result.refinement.map(|r| r.inlier_fraction),
            map: None,
            rejection: match &result.verdict {
                Verdict::Accepted => None,
                Verdict::Rejected(reason) => Some(reason.to_string()),
            },
            accepted_by_pose_graph: None,
            alignment_ms,
            measurement: verified.then(|| ClosureMeasurement {
                target_camera_from_source_camera: (&result.target_camera_from_source_camera).into(),
                sigmas: None,
            }),
        };
        if let Some(reason) = &event.rejection {
            tracing::debug!(source = ?event.source, target = ?event.target, %reason, "closure rejected");
        }
        Decision {
            event,
            map_attempt: None,
        }
    }

    fn decide_map_job(&self, done: FinishedMapJob) -> Option<Decision> {
        let (Some(source), Some(target)) = (done.source_keyframe, done.target_keyframe) else {
            return None;
        };
        let scores = &done.registration.scores;
        // The registration's own uncertainty, never tighter than a keyframe closure's: the
        // maps it compares carry each agent's tracking drift.
        let sigmas = EdgeSigmas {
            rotation_rad: scores
                .rotation_sigma_deg
                .to_radians()
                .max(self.config.pose_graph.loop_rotation_sigma_rad),
            translation_m: scores
                .translation_sigma_m
                .max(self.config.pose_graph.loop_translation_sigma_m),
        };
        let attempt_scores = done.scores();
        let event = ClosureEvent {
            at_s: self.started.elapsed().as_secs_f64(),
            source,
            target,
            origin: CandidateSource::MapRegistration,
            inter_agent: true,
            score: None,
            verified: done.closure.is_some(),
            kind: AttemptKind::Map,
            inliers: Some(attempt_scores.consistent_correspondences),
            overlap: Some(attempt_scores.overlap_fraction),
            map: Some(attempt_scores),
            rejection: done.rejection.as_ref().map(ToString::to_string),
            accepted_by_pose_graph: None,
            alignment_ms: done.elapsed_ms,
            measurement: done.closure.map(|measured| ClosureMeasurement {
                target_camera_from_source_camera: (&measured).into(),
                sigmas: Some(sigmas),
            }),
        };
        Some(Decision {
            event,
            map_attempt: Some(MapAttempt {
                agents: (done.source_agent, done.target_agent),
                keyframes_at_attempt: done.keyframes_at_attempt,
            }),
        })
    }

    /// Adds the wrong closures due beside the verified ones (`[consensus.false_closures]`),
    /// each recorded as an event of origin `injected`.
    fn inject_false_closures(&mut self) {
        let Some(injector) = self.false_closures.as_mut() else {
            return;
        };
        let mut keyframes_per_agent: BTreeMap<u32, Vec<KeyframeRef>> = BTreeMap::new();
        for id in self.info.keys() {
            keyframes_per_agent
                .entry(id.agent_id)
                .or_default()
                .push(*id);
        }
        for closure in injector.after_verified(&keyframes_per_agent) {
            let event = ClosureEvent {
                at_s: self.started.elapsed().as_secs_f64(),
                source: closure.source,
                target: closure.target,
                origin: CandidateSource::Injected,
                inter_agent: closure.source.agent_id != closure.target.agent_id,
                score: None,
                verified: true,
                kind: AttemptKind::Keyframe,
                inliers: None,
                overlap: None,
                map: None,
                rejection: None,
                accepted_by_pose_graph: None,
                alignment_ms: 0.0,
                measurement: Some(ClosureMeasurement {
                    target_camera_from_source_camera: (&closure.target_camera_from_source_camera)
                        .into(),
                    sigmas: closure.sigmas,
                }),
            };
            tracing::debug!(source = ?event.source, target = ?event.target, "wrong closure injected");
            // Both ends are known keyframes, so this cannot fail.
            if self.graph.add_loop(closure).is_ok() {
                self.closure_events.push(self.events.len());
                self.events.push(event);
                self.dirty = true;
            }
        }
    }
}

#[cfg(test)]
mod tests;
