//! What the process writes: consensus.json (the per-agent records and the tally of every
//! attempt), the merged world map (jointly refined at the end of a run), and each agent's world
//! trajectory.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use geometry::trajectory::Trajectory;
use metrics::stats::median;
use nalgebra::Isometry3;
use serde::Serialize;
use splats::GaussianCloud;

use super::ConsensusOptions;
use crate::engine::{AttemptKind, CandidateSource, ClosureEvent, Engine, KeyframeInfo};
use crate::place_recognition::KeyframeRef;
use crate::refinement::{self, RefinementReport};

/// Per agent, what the process saw of it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct AgentRecord {
    /// Hellos received: one per start of the agent's process (more than one after restarts).
    pub hellos: usize,
    /// Goodbye messages: the agent said it was done.
    pub goodbyes: usize,
    /// Hash of the agent's configuration from its latest hello (0 before any; a change on a
    /// restart is logged).
    pub config_hash: u64,
    /// Keyframes whose descriptor and image both arrived, handed to the engine.
    pub keyframes: usize,
    /// Gaussians received in patches (keyframes' and the final map), without the records
    /// dropped for non-finite values.
    pub gaussians_received: usize,
    /// Sequence gaps on any of the agent's topics: each is one or more lost messages.
    pub gaps: usize,
    /// `ResendKeyframe` requests sent for keyframes that arrived incomplete.
    pub resend_requests: usize,
    /// `MessagesLost` reports sent after a sequence gap on a keyframe topic (the agent then
    /// publishes again the keyframes of which nothing arrived).
    pub loss_reports: usize,
    /// Keyframes still missing a part at the end (descriptor, image or patch).
    pub keyframes_incomplete: usize,
    /// Keyframe parts that arrived more than once (ignored).
    pub duplicate_parts: usize,
    /// Keyframe images whose id this agent had already used for another frame (ignored): a
    /// restart that did not re-run the same frames numbers its keyframes from 0 again.
    pub keyframe_id_conflicts: usize,
    /// Restarts found to run on other frames (their hello's run anchor differs from the
    /// agent's first run's): each tracks in a frame of its own, which the consensus cannot
    /// place, so everything such a run publishes is ignored (see `KeyframeInbox`).
    pub restarts_on_other_frames: usize,
    /// Keyframe parts (descriptors, images, patches, final map) of those restarts, ignored.
    pub restart_parts_ignored: usize,
    /// Whether the agent's last run was such a restart: its corrections are withheld (they
    /// would name keyframes it does not have) and its trajectory file, written in its own
    /// frame, is not turned into a world trajectory.
    pub last_run_on_other_frames: bool,
    /// Corrections not sent because the agent's running process is such a restart.
    pub corrections_withheld: usize,
    /// Corrections delivered to the agent.
    pub corrections_sent: usize,
    /// Corrections whose send failed (the agent had left or crashed); the final outputs carry
    /// them anyway.
    pub corrections_undelivered: usize,
    /// `world_from_agent` as `[tx, ty, tz, qx, qy, qz, qw]` (TUM order); absent when the agent
    /// was never linked to the world.
    pub world_from_agent: Option<[f64; 7]>,
    /// Bytes received from the agent over the transport, all topics together.
    pub bytes_received: u64,
    /// Seconds from the agent's first message to when the record was completed (end of run or
    /// snapshot); 0 for an agent never heard from.
    pub seconds_seen: f64,
}

/// consensus.json.
#[derive(Debug, Clone, Serialize)]
pub struct ConsensusReport {
    /// Per agent id, what the process saw of it.
    pub agents: BTreeMap<u32, AgentRecord>,
    /// Keyframes the engine received, of all agents.
    pub keyframes: usize,
    /// Attempts made: keyframe pairs aligned and agent maps registered.
    pub closures_proposed: usize,
    /// Attempts that alignment or map registration verified.
    pub closures_verified: usize,
    /// Attempts not verified: refused by alignment or map registration, or verified but not
    /// taken by the pose graph.
    pub closures_rejected_by_alignment: usize,
    /// Attempts the latest pose-graph solve kept.
    pub loop_closures_accepted: usize,
    /// Attempts not kept by the latest solve, those refused before the pose graph included.
    pub loop_closures_rejected: usize,
    /// Kept attempts whose two keyframes belong to different agents.
    pub inter_agent_closures_accepted: usize,
    /// Deliberately wrong closures (`[consensus.false_closures]`, 0 when off): how many joined
    /// the pose graph and how many of them it kept. The `closures_*` and `*_accepted` counts
    /// above are of the real closures only.
    pub false_closures_injected: usize,
    /// Injected wrong closures that the latest pose-graph solve kept.
    pub false_closures_accepted: usize,
    /// From a keyframe's arrival to the first correction that includes it.
    pub consensus_latency_ms_median: Option<f64>,
    /// Each placed keyframe's latency, milliseconds, in the order they were placed; a keyframe
    /// the pose graph never placed has none.
    pub consensus_latency_ms: Vec<f64>,
    /// Median wall-clock time of a pose-graph solve, milliseconds; `None` before any solve.
    pub pose_graph_solve_ms_median: Option<f64>,
    /// Gaussians in the written map.ply.
    pub merged_gaussians: usize,
    /// Gaussians left out of map.ply because their agent (or keyframe) is not placed in the
    /// world.
    pub unplaced_gaussians: usize,
    /// The joint photometric refinement of the merged map (`null`: not run).
    pub refinement: Option<RefinementReport>,
    /// Seconds from the consensus's start to these outputs (the final refinement included; for
    /// a snapshot, to its request).
    pub wall_s: f64,
    /// A stop was requested (SIGINT / SIGTERM) before the run ended by itself; the joint
    /// refinement is then skipped.
    pub interrupted: bool,
    /// Written on request while the run went on (no refinement; later outputs replace it).
    pub snapshot: bool,
    /// Per pair of agents (`"A-B"`, A < B), what linking them took: every attempt is in
    /// `events` (with its kind, inliers, overlap and reason); this is their tally.
    pub agent_pairs: BTreeMap<String, PairAttempts>,
    /// Every attempt and injected closure, in the order the engine applied them
    /// ([`Engine::events`]).
    pub events: Vec<ClosureEvent>,
    /// Every keyframe with its frame index, capture time and tracked pose, by agent then
    /// keyframe id.
    pub keyframe_info: Vec<(KeyframeRef, KeyframeInfo)>,
}

/// The inter-agent attempts of one pair of agents (consensus.json `agent_pairs`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct PairAttempts {
    /// Keyframe pairs of the two agents aligned.
    pub keyframe_attempts: usize,
    /// Registrations of the two agents' maps.
    pub map_attempts: usize,
    /// Attempts that alignment or map registration verified.
    pub verified: usize,
    /// Verified attempts the robust pose graph kept.
    pub accepted: usize,
    /// Why the most recent refused attempt was refused.
    pub last_rejection: Option<String>,
}

/// Tallies the inter-agent attempts of `events` per pair of agents.
fn pair_attempts(events: &[ClosureEvent]) -> BTreeMap<String, PairAttempts> {
    let mut pairs: BTreeMap<(u32, u32), PairAttempts> = BTreeMap::new();
    // Real attempts only: injected wrong closures were never attempted.
    let real = events
        .iter()
        .filter(|e| e.inter_agent && e.origin != CandidateSource::Injected);
    for event in real {
        let (a, b) = (event.source.agent_id, event.target.agent_id);
        let pair = pairs.entry((a.min(b), a.max(b))).or_default();
        match event.kind {
            AttemptKind::Keyframe => pair.keyframe_attempts += 1,
            AttemptKind::Map => pair.map_attempts += 1,
        }
        pair.verified += usize::from(event.verified);
        pair.accepted += usize::from(event.accepted_by_pose_graph == Some(true));
        if let Some(reason) = &event.rejection {
            pair.last_rejection = Some(reason.clone());
        }
    }
    pairs
        .into_iter()
        .map(|((a, b), attempts)| (format!("{a}-{b}"), attempts))
        .collect()
}

/// The agent's own per-frame trajectory (its frame), written by the agent next to ours.
pub fn agent_trajectory_path(out: &Path, agent_id: u32) -> PathBuf {
    out.join(format!("agent_{agent_id}")).join("trajectory.tum")
}

/// The merged world map as written.
pub(super) struct WorldMap {
    pub map: GaussianCloud,
    /// Gaussians of agents not placed in the world (left out of `map`).
    pub unplaced: usize,
    pub refinement: Option<RefinementReport>,
}

/// The joint photometric refinement of the merged map when `refinement_follows` (not when it is
/// turned off or the run was interrupted; also skipped before any solution); the refined keyframe poses go into the engine, so the
/// world trajectories follow them. The unrefined map is kept as map_realtime.ply. A refinement
/// that fails is logged and the unrefined map is used: nothing computed is lost.
pub(super) fn refine_world_map(
    options: &ConsensusOptions,
    engine: &mut Engine,
    map: GaussianCloud,
    refinement_follows: bool,
) -> anyhow::Result<(GaussianCloud, Option<RefinementReport>)> {
    let consensus = &options.config.consensus;
    if !refinement_follows || map.is_empty() {
        return Ok((map, None));
    }
    let Some(problem) = engine.refinement_problem(map.clone()) else {
        return Ok((map, None));
    };
    let realtime_path = options.out.join("map_realtime.ply");
    splats::ply::save_ply(&realtime_path, &map)
        .with_context(|| format!("writing {}", realtime_path.display()))?;
    // Paced runs give the same map on any machine: the refinement runs all its iterations,
    // however long they take (docs/method.md, Pace).
    let mut consensus = consensus.clone();
    if options.config.mapping.pace == config::Pace::Paced {
        consensus.refinement.max_seconds = f64::INFINITY;
    }
    match refinement::refine(problem, &consensus) {
        Ok(outcome) => {
            // The loss stays on the device; the refined views' PSNR before and after is what
            // the refinement reads back.
            let report = &outcome.report;
            for psnr in [report.psnr_views_before, report.psnr_views_after]
                .into_iter()
                .flatten()
            {
                options
                    .live_view
                    .scalar(live_view::paths::CONSENSUS_REFINEMENT_PSNR_DB, psnr);
            }
            if consensus.refinement.refine_poses {
                engine.apply_refined_poses(&outcome.world_from_camera);
            }
            Ok((outcome.map, Some(outcome.report)))
        }
        Err(error) => {
            tracing::error!(%error, "joint refinement failed: writing the unrefined map");
            Ok((map, None))
        }
    }
}

/// Why outputs are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum OutputKind {
    /// Every expected agent said goodbye.
    Final,
    /// SIGINT / SIGTERM.
    Interrupted,
    /// On request while the run goes on.
    Snapshot,
}

/// Writes map.ply, every linked agent's world trajectory, the ROS 2 bag of both (ros2_bag/)
/// and consensus.json.
pub(super) fn write_outputs(
    options: &ConsensusOptions,
    engine: &Engine,
    world: WorldMap,
    agents: BTreeMap<u32, AgentRecord>,
    latencies: Vec<f64>,
    wall_s: f64,
    kind: OutputKind,
) -> anyhow::Result<ConsensusReport> {
    let out = &options.out;
    let WorldMap {
        map,
        unplaced,
        refinement,
    } = world;
    let map_path = out.join("map.ply");
    splats::ply::save_ply(&map_path, &map)
        .with_context(|| format!("writing {}", map_path.display()))?;
    options.live_view.merged_map(&map.means, &map.colours);
    write_world_trajectories(out, engine, &agents)?;
    let messages =
        super::ros2_outputs::consensus_messages(out, &agents, &map, &options.config.ros2)?;
    super::ros2_outputs::write_consensus_bag(out, &messages)?;
    super::ros2_outputs::publish(
        &messages,
        &options.config.ros2,
        kind != OutputKind::Snapshot,
    );
    let events = engine.events().to_vec();
    let (injected, real): (Vec<&ClosureEvent>, Vec<&ClosureEvent>) = events
        .iter()
        .partition(|e| e.origin == CandidateSource::Injected);
    let kept = |e: &&&ClosureEvent| e.accepted_by_pose_graph == Some(true);
    let accepted = real.iter().filter(kept).count();
    let report = ConsensusReport {
        keyframes: engine.keyframes().len(),
        closures_proposed: real.len(),
        closures_verified: real.iter().filter(|e| e.verified).count(),
        closures_rejected_by_alignment: real.iter().filter(|e| !e.verified).count(),
        loop_closures_accepted: accepted,
        loop_closures_rejected: real.len() - accepted,
        inter_agent_closures_accepted: real.iter().filter(|e| e.inter_agent).filter(kept).count(),
        false_closures_injected: injected.len(),
        false_closures_accepted: injected.iter().filter(kept).count(),
        consensus_latency_ms_median: median(&latencies),
        consensus_latency_ms: latencies,
        pose_graph_solve_ms_median: median(engine.solve_ms()),
        merged_gaussians: map.len(),
        unplaced_gaussians: unplaced,
        refinement,
        wall_s,
        interrupted: kind == OutputKind::Interrupted,
        snapshot: kind == OutputKind::Snapshot,
        agents,
        agent_pairs: pair_attempts(&events),
        events,
        keyframe_info: engine.keyframes().iter().map(|(k, v)| (*k, *v)).collect(),
    };
    let path = out.join("consensus.json");
    let json = serde_json::to_string_pretty(&report)?;
    geometry::files::write_whole(&path, |file| file.write_all(json.as_bytes()))
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(report)
}

/// OUT/agent_K.tum: each agent's own trajectory (written by the agent) moved into the world
/// frame, for every agent linked to it whose last run tracked in the frame the consensus knows.
fn write_world_trajectories(
    out: &Path,
    engine: &Engine,
    agents: &BTreeMap<u32, AgentRecord>,
) -> anyhow::Result<()> {
    for (agent_id, record) in agents {
        if record.last_run_on_other_frames {
            tracing::warn!(
                agent_id,
                "the agent's last run restarted on other frames, in a frame of its own: no world \
                 trajectory written from its trajectory file"
            );
            continue;
        }
        let path = agent_trajectory_path(out, *agent_id);
        if !path.exists() {
            tracing::warn!(agent_id, path = %path.display(), "no agent trajectory to correct");
            continue;
        }
        let tracked = Trajectory::read_tum(&path)
            .with_context(|| format!("reading agent {agent_id}'s trajectory"))?;
        let pairs: Vec<(f64, Isometry3<f64>)> = tracked
            .stamps
            .iter()
            .copied()
            .zip(tracked.poses.iter().copied())
            .collect();
        match engine.world_trajectory(*agent_id, &pairs) {
            Some(world) => {
                let target = out.join(format!("agent_{agent_id}.tum"));
                Trajectory::from_pairs(world)
                    .write_tum(&target)
                    .with_context(|| format!("writing {}", target.display()))?;
            }
            None => tracing::warn!(
                agent_id,
                "agent not linked to the world frame: no world trajectory written"
            ),
        }
    }
    Ok(())
}
