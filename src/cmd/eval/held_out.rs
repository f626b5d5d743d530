//! Which frames a swarm run's maps are scored on, and the scoring (docs/method.md, Metrics).
//!
//! Two protocols, each applied the same way to every map (an agent's own map and the merged
//! world map) and to every agent's frames:
//! - **all frames**: every `every`-th frame of the agent's sequence, the paper's protocol. Some of
//!   them are keyframes, views a map was optimised on, which flatters whichever map saw them;
//! - **held out**: in each window of `every` frames from a multiple of `every` on, the first frame
//!   that no map used as an optimisation view: not a keyframe of any agent that ran on the same
//!   sequence (the merged map starts from every agent's map and is refined on published
//!   keyframes, a subset of those), so no map has seen it as a view. Needs each agent's
//!   keyframes.csv.
//!
//! Either way a frame counts only where every trajectory scored against it has a pose: a frame
//! the agent never tracked (dropped at sensor pace, lost) is skipped for all maps alike.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use alexnet::lpips::Lpips;
use anyhow::{Context, bail};
use datasets::{Dataset, FrameRange};
use geometry::trajectory::Trajectory;
use mac_agent::evaluation::{FrameQuality, MapRenderer, QualitySummary, evaluate_frame};
use mac_agent::views::{KEYFRAMES_FILE, MAP_TRAJECTORY_FILE};
use nalgebra::Isometry3;
use serde::Serialize;
use serde_json::Value;

/// Largest difference between a trajectory stamp and its frame's timestamp (agents write them
/// with microsecond precision).
pub const TIMESTAMP_TOLERANCE_S: f64 = 1e-5;

/// How an agent's frames are picked (module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    AllFrames,
    HeldOut,
}

/// What scoring needs of one agent of a run.
pub struct AgentFrames {
    pub agent_id: u32,
    /// The dataset argument it ran on (agents with the same one share frames).
    pub dataset_spec: String,
    pub dataset: Box<dyn Dataset>,
    /// Its frames in the world frame (DIR/agent_K.tum, by the consensus).
    pub world: Trajectory,
    /// Its frames in its own map's frame (agent_K/trajectory_map.tum); `None` for runs of
    /// agents that did not write it.
    pub own_map_poses: Option<Trajectory>,
    /// Timestamps (microseconds) of its keyframes (agent_K/keyframes.csv); `None` when absent.
    pub keyframes_us: Option<BTreeSet<i64>>,
}

fn microseconds(seconds: f64) -> i64 {
    (seconds * 1e6).round() as i64
}

impl AgentFrames {
    /// Reopens agent `agent_id`'s frames from what its metrics.json says it ran on; `None` when
    /// that is not recorded or the agent has no world trajectory.
    pub fn open(dir: &Path, agent_id: u32, metrics: &Value) -> anyhow::Result<Option<Self>> {
        let (Some(spec), Some(range)) = (
            metrics["dataset_spec"].as_str(),
            metrics["frame_range"].as_str(),
        ) else {
            return Ok(None);
        };
        let world_path = dir.join(format!("agent_{agent_id}.tum"));
        // A live camera's frames cannot be read again: nothing to score a map against.
        if !world_path.exists() || datasets::live::is_live(spec) {
            return Ok(None);
        }
        let range: FrameRange = range
            .parse()
            .map_err(|e| anyhow::anyhow!("agent {agent_id}: frame range {range:?}: {e}"))?;
        let dataset = datasets::open(spec, range)
            .with_context(|| format!("reopening agent {agent_id}'s frames ({spec})"))?;
        let own = dir.join(format!("agent_{agent_id}"));
        let own_map_path = own.join(MAP_TRAJECTORY_FILE);
        let own_map_poses = own_map_path
            .exists()
            .then(|| Trajectory::read_tum(&own_map_path))
            .transpose()?;
        let keyframes_path = own.join(KEYFRAMES_FILE);
        let keyframes_us = keyframes_path
            .exists()
            .then(|| read_keyframe_times(&keyframes_path))
            .transpose()?;
        Ok(Some(Self {
            agent_id,
            dataset_spec: spec.to_string(),
            dataset,
            world: Trajectory::read_tum(&world_path)?,
            own_map_poses,
            keyframes_us,
        }))
    }

    /// This agent's frame positions under `protocol`, every `every`-th; the keyframes of every
    /// agent of `run` on the same sequence are left out of the held-out ones. Fails when an
    /// agent on the same sequence did not record its keyframes.
    pub fn positions(
        &self,
        run: &[AgentFrames],
        every: usize,
        protocol: Protocol,
    ) -> anyhow::Result<Vec<usize>> {
        let every = every.max(1);
        let mut views = BTreeSet::new();
        if protocol == Protocol::HeldOut {
            for agent in run.iter().filter(|a| a.dataset_spec == self.dataset_spec) {
                let Some(keyframes) = &agent.keyframes_us else {
                    bail!(
                        "agent {} wrote no {KEYFRAMES_FILE}: the views its map was optimised on \
                         are unknown, so no frame of its sequence can be called held out",
                        agent.agent_id
                    );
                };
                views.extend(keyframes.iter().copied());
            }
        }
        let scored = |position: usize| {
            let t = self.dataset.timestamp(position);
            !views.contains(&microseconds(t))
                && pose_at(&self.world, t).is_some()
                && self
                    .own_map_poses
                    .as_ref()
                    .is_none_or(|own| pose_at(own, t).is_some())
        };
        let len = self.dataset.len();
        Ok((0..len)
            .step_by(every)
            .filter_map(|start| match protocol {
                Protocol::AllFrames => scored(start).then_some(start),
                Protocol::HeldOut => (start..(start + every).min(len)).find(|&p| scored(p)),
            })
            .collect())
    }
}

/// agent_K/keyframes.csv's timestamps, in microseconds.
fn read_keyframe_times(path: &Path) -> anyhow::Result<BTreeSet<i64>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or_default();
    let column = header
        .split(',')
        .position(|name| name == "timestamp")
        .with_context(|| format!("{}: no timestamp column", path.display()))?;
    lines
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty())
        .map(|(row, line)| {
            let field = line.split(',').nth(column).unwrap_or_default();
            field.parse::<f64>().map(microseconds).with_context(|| {
                format!("{} line {}: timestamp {field:?}", path.display(), row + 2)
            })
        })
        .collect()
}

/// The pose stamped with `t` in `trajectory`, if any.
pub fn pose_at(trajectory: &Trajectory, t: f64) -> Option<Isometry3<f64>> {
    let k = trajectory
        .stamps
        .partition_point(|&stamp| stamp < t - TIMESTAMP_TOLERANCE_S);
    (k < trajectory.len() && (trajectory.stamps[k] - t).abs() < TIMESTAMP_TOLERANCE_S)
        .then(|| trajectory.poses[k])
}

/// Scores `renderer`'s map on `agent`'s frames at `positions`, each rendered from its pose in
/// `poses`; `comparisons` names a PNG per frame to write side by side (`None`: none).
pub fn score(
    renderer: &MapRenderer,
    agent: &AgentFrames,
    poses: &Trajectory,
    positions: &[usize],
    lpips: Option<&Lpips>,
    comparisons: &dyn Fn(usize, usize) -> Option<PathBuf>,
) -> anyhow::Result<Vec<FrameQuality>> {
    let mut qualities = Vec::with_capacity(positions.len());
    for (i, &position) in positions.iter().enumerate() {
        let frame = match agent.dataset.load(position) {
            Ok(frame) => frame,
            Err(error) => {
                tracing::warn!(agent = agent.agent_id, %error, "frame skipped");
                continue;
            }
        };
        let Some(pose) = pose_at(poses, frame.timestamp) else {
            continue;
        };
        let comparison = comparisons(i, frame.index);
        qualities.push(evaluate_frame(
            renderer,
            &frame,
            &pose,
            lpips,
            comparison.as_deref(),
        )?);
    }
    Ok(qualities)
}

/// The mean figures of `qualities`, `None` when there are none.
pub fn summary(qualities: &[FrameQuality]) -> Option<QualitySummary> {
    (!qualities.is_empty()).then(|| QualitySummary::of(qualities))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn agent(id: u32, spec: &str, frames: usize, keyframes: &[usize]) -> AgentFrames {
        let dataset = datasets::open(
            &format!("synthetic:frames={frames},width=32,height=24"),
            FrameRange::default(),
        )
        .expect("synthetic scene");
        let stamps: Vec<f64> = (0..frames).map(|p| dataset.timestamp(p)).collect();
        let world = Trajectory {
            poses: vec![Isometry3::identity(); stamps.len()],
            stamps: stamps.clone(),
        };
        AgentFrames {
            agent_id: id,
            dataset_spec: spec.to_string(),
            keyframes_us: Some(keyframes.iter().map(|&p| microseconds(stamps[p])).collect()),
            dataset,
            own_map_poses: Some(world.clone()),
            world,
        }
    }

    #[test]
    fn held_out_frames_skip_every_agents_keyframes_on_the_same_sequence() {
        let run = [
            agent(0, "seq", 40, &[0, 10, 11, 25]),
            agent(1, "seq", 40, &[20, 30]),
            agent(2, "other", 40, &[1, 2, 3]),
        ];
        let all = run[0].positions(&run, 10, Protocol::AllFrames).unwrap();
        assert_eq!(all, vec![0, 10, 20, 30]);
        let held_out = run[0].positions(&run, 10, Protocol::HeldOut).unwrap();
        // 0 and 10, 11 are agent 0's keyframes, 20 and 30 agent 1's; agent 2's frames are
        // another sequence's.
        assert_eq!(held_out, vec![1, 12, 21, 31]);
        // The same rule for agent 1's frames (the same sequence here).
        assert_eq!(
            run[1].positions(&run, 10, Protocol::HeldOut).unwrap(),
            held_out
        );
    }

    #[test]
    fn frames_without_a_pose_are_skipped_and_unknown_keyframes_are_an_error() {
        let mut lost = agent(0, "seq", 20, &[0]);
        // Frames 1..=4 were never tracked (no pose in the world trajectory).
        lost.world.stamps.drain(1..5);
        lost.world.poses.drain(1..5);
        let run = [lost];
        assert_eq!(
            run[0].positions(&run, 10, Protocol::HeldOut).unwrap(),
            vec![5, 10]
        );
        let mut unknown = agent(1, "seq", 20, &[]);
        unknown.keyframes_us = None;
        let run = [agent(0, "seq", 20, &[0]), unknown];
        let error = run[0]
            .positions(&run, 10, Protocol::HeldOut)
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("agent 1") && error.contains(KEYFRAMES_FILE),
            "{error}"
        );
        // All frames need no keyframes.
        assert_eq!(
            run[0].positions(&run, 10, Protocol::AllFrames).unwrap(),
            vec![0, 10]
        );
    }

    #[test]
    fn poses_are_found_by_timestamp() {
        let trajectory = Trajectory {
            stamps: vec![0.0, 1.0 / 30.0, 2.0 / 30.0],
            poses: vec![Isometry3::identity(); 3],
        };
        assert!(pose_at(&trajectory, 1.0 / 30.0 + 4e-6).is_some());
        assert!(pose_at(&trajectory, 0.5).is_none());
        assert!(pose_at(&trajectory, -1.0).is_none());
        assert!(pose_at(&trajectory, 1.0).is_none());
    }
}
