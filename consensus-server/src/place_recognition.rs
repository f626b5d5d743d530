//! Selection (docs/method.md, The consensus: selection): the consensus keeps every keyframe
//! descriptor it has received and scores each new one against all stored ones by dot product. A
//! score above tau proposes a loop closure: tau_same_agent (0.80) within one agent,
//! tau_other_agent (0.85) between agents. Proposals are only candidates: association and alignment verify or reject them.

use config::ConsensusConfig;
use protocol::messages::descriptor_score;
use serde::{Deserialize, Serialize};

/// Identifies one keyframe in the swarm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct KeyframeRef {
    /// The agent that made the keyframe.
    pub agent_id: u32,
    /// The keyframe's number on its agent: keyframes are numbered from 0 in the order the agent
    /// makes them. `protocol::messages::FINAL_MAP_KEYFRAME_ID` names the agent's final map
    /// instead.
    pub keyframe_id: u64,
}

/// A loop-closure candidate between a new keyframe and a stored one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LoopCandidate {
    /// The keyframe whose descriptor was just inserted.
    pub query: KeyframeRef,
    /// The stored keyframe it resembles.
    pub matched: KeyframeRef,
    /// Dot product of the two unit descriptors (their cosine, at most 1); above the threshold
    /// that applies.
    pub score: f32,
    /// Whether the two keyframes come from different agents (`tau_other_agent` applied) or the
    /// same one (`tau_same_agent`).
    pub inter_agent: bool,
}

struct Entry {
    keyframe: KeyframeRef,
    frame_index: u64,
    descriptor: Vec<f32>,
}

/// Thresholds of [`PlaceDatabase`], taken from the consensus configuration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelectionThresholds {
    /// Minimum score (exclusive) for a candidate between two keyframes of one agent.
    pub tau_same_agent: f32,
    /// Minimum score (exclusive) for a candidate between keyframes of two agents.
    pub tau_other_agent: f32,
    /// Same-agent keyframes closer than this many frames are not compared: they are neighbours
    /// on the agent's own trajectory, already linked by odometry, and trivially similar.
    pub same_agent_min_frame_gap: u64,
}

impl SelectionThresholds {
    /// The thresholds of the `[consensus]` section.
    pub fn from_config(config: &ConsensusConfig) -> Self {
        Self {
            tau_same_agent: config.tau_same_agent as f32,
            tau_other_agent: config.tau_other_agent as f32,
            same_agent_min_frame_gap: config.same_agent_min_frame_gap as u64,
        }
    }
}

/// Every descriptor received so far, in arrival order.
pub struct PlaceDatabase {
    thresholds: SelectionThresholds,
    entries: Vec<Entry>,
}

impl PlaceDatabase {
    /// An empty database that proposes candidates by `thresholds`.
    pub fn new(thresholds: SelectionThresholds) -> Self {
        Self {
            thresholds,
            entries: Vec::new(),
        }
    }

    /// How many keyframes' descriptors are stored.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no descriptor has been stored yet.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Scores `descriptor` against every stored keyframe, stores it, and returns the proposals
    /// above threshold, best first. A keyframe already stored (a message that arrived twice) is
    /// not stored again and proposes nothing new.
    pub fn insert_and_query(
        &mut self,
        keyframe: KeyframeRef,
        frame_index: u64,
        descriptor: &[f32],
    ) -> Vec<LoopCandidate> {
        if self.entries.iter().any(|e| e.keyframe == keyframe) {
            tracing::debug!(
                ?keyframe,
                "descriptor already stored: duplicate message ignored"
            );
            return Vec::new();
        }
        let mut proposals: Vec<LoopCandidate> = self
            .entries
            .iter()
            .filter_map(|stored| {
                let inter_agent = stored.keyframe.agent_id != keyframe.agent_id;
                if !inter_agent
                    && stored.frame_index.abs_diff(frame_index)
                        < self.thresholds.same_agent_min_frame_gap
                {
                    return None;
                }
                let s = descriptor_score(descriptor, &stored.descriptor);
                let tau = if inter_agent {
                    self.thresholds.tau_other_agent
                } else {
                    self.thresholds.tau_same_agent
                };
                (s > tau).then_some(LoopCandidate {
                    query: keyframe,
                    matched: stored.keyframe,
                    score: s,
                    inter_agent,
                })
            })
            .collect();
        proposals.sort_by(|a, b| b.score.total_cmp(&a.score));
        self.entries.push(Entry {
            keyframe,
            frame_index,
            descriptor: descriptor.to_vec(),
        });
        proposals
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(values: &[f32]) -> Vec<f32> {
        let n = values.iter().map(|v| v * v).sum::<f32>().sqrt();
        values.iter().map(|v| v / n).collect()
    }

    fn kf(agent_id: u32, keyframe_id: u64) -> KeyframeRef {
        KeyframeRef {
            agent_id,
            keyframe_id,
        }
    }

    fn database() -> PlaceDatabase {
        PlaceDatabase::new(SelectionThresholds {
            tau_same_agent: 0.80,
            tau_other_agent: 0.85,
            same_agent_min_frame_gap: 100,
        })
    }

    #[test]
    fn thresholds_differ_for_same_and_other_agent() {
        let mut db = database();
        let base = unit(&[1.0, 0.0, 0.0]);
        // cos = 0.83: above tau_same (0.80), below tau_other (0.85).
        let similar = unit(&[0.83, (1.0f32 - 0.83 * 0.83).sqrt(), 0.0]);
        assert!(db.insert_and_query(kf(0, 0), 0, &base).is_empty());
        let same = db.insert_and_query(kf(0, 1), 500, &similar);
        assert_eq!(same.len(), 1);
        assert!(!same[0].inter_agent && same[0].matched == kf(0, 0));
        let other = db.insert_and_query(kf(1, 0), 0, &similar);
        // Scores 0.83 against agent 0's first keyframe (rejected, other agent) and 1.0 against its
        // second (accepted).
        assert_eq!(other.len(), 1);
        assert!(other[0].inter_agent && other[0].matched == kf(0, 1));
        assert!((other[0].score - 1.0).abs() < 1e-6);
    }

    #[test]
    fn neighbours_on_one_trajectory_and_duplicates_propose_nothing() {
        let mut db = database();
        let d = unit(&[0.0, 1.0, 1.0]);
        db.insert_and_query(kf(2, 0), 1000, &d);
        assert!(
            db.insert_and_query(kf(2, 1), 1060, &d).is_empty(),
            "60 frames apart on one agent"
        );
        assert_eq!(db.insert_and_query(kf(2, 2), 1200, &d).len(), 2);
        assert!(
            db.insert_and_query(kf(2, 2), 1200, &d).is_empty(),
            "duplicate message"
        );
        assert_eq!(db.len(), 3);
    }
}
