//! Reading what a swarm run left in its directory, tolerantly: the report shows whatever is
//! there and says what is not, so every reader here returns the reason something is missing
//! instead of failing the whole report.

use std::path::{Path, PathBuf};

use geometry::trajectory::Trajectory;
use metrics::ate::{Alignment, DEFAULT_MAX_DT, associate, ate, joint_ate};
use nalgebra::Point3;
use serde::Deserialize;
use serde_json::Value;

/// A JSON file, or why it cannot be used.
pub fn read_json(path: &Path) -> Result<Value, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Agents of the run: those the consensus heard from, and those metrics.json has a per-agent
/// entry for (a run whose consensus crashed still has the agents' figures).
pub fn agent_ids(metrics: Option<&Value>, consensus: Option<&Value>) -> Vec<u32> {
    let mut ids: Vec<u32> = consensus
        .and_then(|c| c["agents"].as_object())
        .map(|agents| agents.keys().filter_map(|k| k.parse().ok()).collect())
        .unwrap_or_default();
    let listed = metrics
        .and_then(|m| m["ate_per_agent_rmse_m"].as_array())
        .map_or(0, Vec::len);
    ids.extend((0..listed).filter_map(|k| u32::try_from(k).ok()));
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// One agent's trajectories under the joint alignment.
pub struct AgentTrack {
    pub id: u32,
    /// Every estimated world position (file order), mapped by the joint alignment into the
    /// ground-truth frame.
    pub estimate: Vec<Point3<f64>>,
    pub ground_truth: Vec<Point3<f64>>,
    /// (seconds since the agent's first matched frame, translation error in metres) per pose
    /// pair, exactly the errors the joint ATE sums for this agent.
    pub errors: Vec<(f64, f64)>,
}

/// The agents whose trajectories can be drawn, and a line for each one that cannot.
pub struct Trajectories {
    pub tracks: Vec<AgentTrack>,
    pub notes: Vec<String>,
}

/// An agent's (ground truth, world-frame estimate), or why there is none.
fn read_pair(dir: &Path, id: u32) -> Result<(Trajectory, Trajectory), String> {
    let world = dir.join(format!("agent_{id}.tum"));
    let truth = dir.join(format!("agent_{id}")).join("groundtruth.tum");
    if !world.exists() {
        return Err(format!(
            "agent {id}: not linked to the world frame (the consensus wrote no {}); its trajectory is not drawn",
            world.display()
        ));
    }
    if !truth.exists() {
        return Err(format!(
            "agent {id}: no ground truth ({} is missing); its trajectory is not drawn",
            truth.display()
        ));
    }
    let read = |path: &Path| Trajectory::read_tum(path).map_err(|e| format!("agent {id}: {e}"));
    let pair = (read(&truth)?, read(&world)?);
    if associate(&pair.0, &pair.1, DEFAULT_MAX_DT).is_empty() {
        return Err(format!(
            "agent {id}: no estimated pose has a ground-truth pose within {DEFAULT_MAX_DT} s; not drawn"
        ));
    }
    Ok(pair)
}

fn positions(trajectory: &Trajectory) -> Vec<Point3<f64>> {
    trajectory
        .poses
        .iter()
        .map(|pose| Point3::from(pose.translation.vector))
        .collect()
}

/// Every agent's trajectories after the one SE(3) alignment the joint ATE uses
/// (`metrics::ate::joint_ate`), so the plots show what the figure measures.
pub fn load_trajectories(dir: &Path, ids: &[u32]) -> Trajectories {
    let mut notes = Vec::new();
    let mut linked = Vec::new();
    let mut pairs = Vec::new();
    for &id in ids {
        match read_pair(dir, id) {
            Ok(pair) => {
                linked.push(id);
                pairs.push(pair);
            }
            Err(note) => notes.push(note),
        }
    }
    if pairs.is_empty() {
        return Trajectories {
            tracks: Vec::new(),
            notes,
        };
    }
    let alignment = match joint_ate(&pairs, Alignment::Se3, DEFAULT_MAX_DT) {
        Ok(joint) => joint.alignment,
        Err(e) => {
            notes.push(format!("the joint alignment failed: {e}"));
            return Trajectories {
                tracks: Vec::new(),
                notes,
            };
        }
    };
    let mut tracks = Vec::new();
    for (id, (truth, estimate)) in linked.into_iter().zip(pairs) {
        let aligned = Trajectory::from_pairs(
            estimate
                .stamps
                .iter()
                .zip(&estimate.poses)
                .map(|(t, pose)| (*t, alignment.transform_pose(pose))),
        );
        // Already aligned: `Alignment::None` measures the same pairs and errors as the joint ATE.
        let errors = match ate(&truth, &aligned, Alignment::None, DEFAULT_MAX_DT) {
            Ok(result) => result.errors,
            Err(e) => {
                notes.push(format!("agent {id}: {e}"));
                continue;
            }
        };
        let first = errors.first().map_or(0.0, |e| e.0);
        tracks.push(AgentTrack {
            id,
            estimate: positions(&aligned),
            ground_truth: positions(&truth),
            errors: errors.into_iter().map(|(t, e)| (t - first, e)).collect(),
        });
    }
    Trajectories { tracks, notes }
}

/// A keyframe named in a closure event.
#[derive(Debug, Clone, Copy, Deserialize)]
pub struct KeyframeRef {
    pub agent_id: u32,
    pub keyframe_id: u64,
}

/// One alignment decision of consensus.json's `events` (mac-consensus's `ClosureEvent`; fields
/// this report does not show are ignored).
#[derive(Debug, Clone, Deserialize)]
pub struct ClosureEvent {
    /// Seconds since the consensus started.
    pub at_s: f64,
    pub source: KeyframeRef,
    pub target: KeyframeRef,
    #[serde(default)]
    pub origin: Option<String>,
    pub inter_agent: bool,
    #[serde(default)]
    pub score: Option<f64>,
    pub verified: bool,
    #[serde(default)]
    pub rejection: Option<String>,
    #[serde(default)]
    pub accepted_by_pose_graph: Option<bool>,
}

/// What became of a proposed closure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Verified and kept by the robust pose graph.
    Accepted,
    /// Verified, then dropped by the pose graph as an outlier.
    RejectedByPoseGraph,
    /// Verified; no pose-graph solve came after it.
    VerifiedUnsolved,
    /// Alignment could not verify the pair.
    RejectedByAlignment,
}

impl Outcome {
    pub const ALL: [Outcome; 4] = [
        Outcome::Accepted,
        Outcome::RejectedByPoseGraph,
        Outcome::VerifiedUnsolved,
        Outcome::RejectedByAlignment,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Outcome::Accepted => "accepted by the pose graph",
            Outcome::RejectedByPoseGraph => "verified, pose graph rejected it",
            Outcome::VerifiedUnsolved => "verified, before any solve",
            Outcome::RejectedByAlignment => "rejected by alignment",
        }
    }
}

impl ClosureEvent {
    pub fn outcome(&self) -> Outcome {
        match (self.verified, self.accepted_by_pose_graph) {
            (false, _) => Outcome::RejectedByAlignment,
            (true, Some(true)) => Outcome::Accepted,
            (true, Some(false)) => Outcome::RejectedByPoseGraph,
            (true, None) => Outcome::VerifiedUnsolved,
        }
    }
}

/// consensus.json's closure events, or why there are none to show.
pub fn closure_events(consensus: &Value) -> Result<Vec<ClosureEvent>, String> {
    match consensus.get("events") {
        None | Some(Value::Null) => Err("consensus.json has no `events` list".into()),
        Some(events) => serde_json::from_value(events.clone())
            .map_err(|e| format!("consensus.json: `events`: {e}")),
    }
}

/// The side-by-side PNGs eval swarm wrote to DIR/renders/, in name order (agent, then frame).
pub fn render_files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let renders = dir.join("renders");
    let entries = std::fs::read_dir(&renders).map_err(|e| format!("{}: {e}", renders.display()))?;
    let mut files: Vec<PathBuf> = entries
        .flatten()
        .map(|entry| entry.path())
        .filter(|path| {
            path.extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("png"))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// "agent 0, frame 20" from eval swarm's `agent_0_frame_000020.png`; the file name otherwise.
pub fn render_caption(path: &Path) -> String {
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let parsed = name.strip_prefix("agent_").and_then(|rest| {
        let (agent, frame) = rest.split_once("_frame_")?;
        Some((agent.parse::<u32>().ok()?, frame.parse::<u64>().ok()?))
    });
    match parsed {
        Some((agent, frame)) => format!("agent {agent}, frame {frame}"),
        None => name,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agent_ids_merge_consensus_and_metrics() {
        let consensus = serde_json::json!({"agents": {"0": {}, "2": {}}});
        let metrics = serde_json::json!({"ate_per_agent_rmse_m": [0.1, null]});
        assert_eq!(agent_ids(Some(&metrics), Some(&consensus)), [0, 1, 2]);
        assert_eq!(agent_ids(None, None), Vec::<u32>::new());
    }

    #[test]
    fn outcomes_follow_verification_and_pose_graph() {
        let event = |verified, accepted| ClosureEvent {
            at_s: 1.0,
            source: KeyframeRef {
                agent_id: 0,
                keyframe_id: 1,
            },
            target: KeyframeRef {
                agent_id: 1,
                keyframe_id: 2,
            },
            origin: None,
            inter_agent: true,
            score: None,
            verified,
            rejection: None,
            accepted_by_pose_graph: accepted,
        };
        assert_eq!(event(false, None).outcome(), Outcome::RejectedByAlignment);
        assert_eq!(event(true, Some(true)).outcome(), Outcome::Accepted);
        assert_eq!(
            event(true, Some(false)).outcome(),
            Outcome::RejectedByPoseGraph
        );
        assert_eq!(event(true, None).outcome(), Outcome::VerifiedUnsolved);
    }

    #[test]
    fn render_captions_name_agent_and_frame() {
        assert_eq!(
            render_caption(Path::new("r/agent_1_frame_000040.png")),
            "agent 1, frame 40"
        );
        assert_eq!(render_caption(Path::new("r/other.png")), "other");
    }
}
