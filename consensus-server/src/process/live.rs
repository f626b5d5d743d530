//! What the consensus shows in the rerun live view (entity paths in `live_view::paths`): every
//! closure attempt as a line between its keyframes, each agent's keyframe positions after a
//! solve, the kB/s received per agent, the merged map. Each call only queues (the live view
//! drops what it cannot take), and builds nothing when the view is disabled.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use live_view::{ClosureLine, ClosureOutcome, LiveView, paths};
use nalgebra::Isometry3;
use protocol::transport::{ConsumerLink, Direction};

use crate::engine::{CandidateSource, Engine};
use crate::place_recognition::KeyframeRef;

/// Every loop-closure attempt so far (place recognition and map registration; not the odometry
/// pairs, not injected wrong closures), and how many were accepted and rejected.
pub(super) fn show_closures(view: &LiveView, engine: &Engine) {
    if !view.is_enabled() {
        return;
    }
    let mut lines = Vec::new();
    for event in engine.events() {
        if matches!(
            event.origin,
            CandidateSource::Odometry | CandidateSource::Injected
        ) {
            continue;
        }
        let (Some(from), Some(to)) = (
            keyframe_position(engine, &event.source),
            keyframe_position(engine, &event.target),
        ) else {
            continue;
        };
        let outcome = match (event.verified, event.accepted_by_pose_graph) {
            (false, _) => ClosureOutcome::Rejected,
            (true, Some(false)) => ClosureOutcome::DroppedByPoseGraph,
            (true, _) => ClosureOutcome::Accepted,
        };
        lines.push(ClosureLine { from, to, outcome });
    }
    let count = |outcome| lines.iter().filter(|l| l.outcome == outcome).count() as f64;
    view.scalar(
        paths::CONSENSUS_CLOSURES_ACCEPTED,
        count(ClosureOutcome::Accepted),
    );
    view.scalar(
        paths::CONSENSUS_CLOSURES_REJECTED,
        count(ClosureOutcome::Rejected),
    );
    view.closures(lines);
}

/// Every linked agent's keyframe positions in the world, after a solve.
pub(super) fn show_solution(
    view: &LiveView,
    world_from_camera: &BTreeMap<KeyframeRef, Isometry3<f64>>,
) {
    if !view.is_enabled() {
        return;
    }
    let mut trajectories: BTreeMap<u32, Vec<[f64; 3]>> = BTreeMap::new();
    // KeyframeRef orders by agent, then keyframe id: each agent's keyframes in order.
    for (keyframe, pose) in world_from_camera {
        trajectories
            .entry(keyframe.agent_id)
            .or_default()
            .push(pose.translation.vector.into());
    }
    view.consensus_trajectories(trajectories);
}

/// A keyframe's position: in the world where the latest solution placed it, else in its
/// agent's frame.
fn keyframe_position(engine: &Engine, keyframe: &KeyframeRef) -> Option<[f64; 3]> {
    if let Some(pose) = engine
        .solution()
        .and_then(|solution| solution.world_from_camera.get(keyframe))
    {
        return Some(pose.translation.vector.into());
    }
    let tum = engine.keyframes().get(keyframe)?.agent_from_camera;
    Some([tum[0], tum[1], tum[2]])
}

/// The kB/s received from each agent, sampled about once a second from the transport's byte
/// counts.
pub(super) struct BandwidthProbe {
    last: Option<(Instant, BTreeMap<u32, u64>)>,
}

const BANDWIDTH_INTERVAL: Duration = Duration::from_secs(1);

impl BandwidthProbe {
    pub fn new() -> Self {
        Self { last: None }
    }

    pub fn sample(&mut self, view: &LiveView, link: &ConsumerLink) {
        if !view.is_enabled()
            || self
                .last
                .as_ref()
                .is_some_and(|(at, _)| at.elapsed() < BANDWIDTH_INTERVAL)
        {
            return;
        }
        let mut bytes: BTreeMap<u32, u64> = BTreeMap::new();
        for entry in link.bandwidth().entries {
            if entry.direction != Direction::Received {
                continue;
            }
            *bytes.entry(entry.agent_id).or_default() += entry.traffic.bytes;
        }
        let now = Instant::now();
        if let Some((at, before)) = &self.last {
            let seconds = now.duration_since(*at).as_secs_f64();
            for (agent_id, total) in &bytes {
                let earlier = before.get(agent_id).copied().unwrap_or(0);
                let kbps = total.saturating_sub(earlier) as f64 / 1e3 / seconds;
                view.scalar(paths::consensus_agent_kbps(*agent_id), kbps);
            }
        }
        self.last = Some((now, bytes));
    }
}
