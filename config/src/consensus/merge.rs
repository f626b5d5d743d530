//! The `[consensus.merge]` table: how the agents' maps become one world map (docs/method.md,
//! The consensus: the merged map).

use geometry::checks::{FieldError, positive};
use serde::{Deserialize, Serialize};

/// Building the merged world map from the agents' maps (docs/method.md, The consensus: the
/// merged map). Each agent's map is optimised for its own views; where two agents mapped the
/// same surface, both copies together blur and occlude each other from every view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MergeConfig {
    /// In merged maps that no joint refinement follows (mid-run snapshots, the live view, runs
    /// with refinement off or interrupted): where agents' maps overlap, keep each Gaussian only
    /// from the agent whose keyframes saw its place from nearest (its samples are the finest
    /// there); elsewhere keep every agent's. The refinement starts from every agent's whole map:
    /// from there it ended higher (docs/benchmarks.md). Off: always all maps together.
    pub nearest_observer: bool,
    /// A Gaussian is in the overlap when another agent has a Gaussian within this distance
    /// (metres): about the agents' residual misalignment after the pose graph (a few cm).
    pub overlap_radius_m: f64,
    /// In the merged map the joint refinement starts from: where agents' maps overlap, fuse
    /// each pair of duplicates (a Gaussian of each agent, each the other's nearest, closer than
    /// `fuse_radius_m`) into one Gaussian carrying both (their moment-matched mixture). Off: the
    /// refinement starts from every agent's whole map.
    pub fuse_duplicates: bool,
    /// Largest distance (metres) between two duplicates that are fused.
    pub fuse_radius_m: f64,
}

impl Default for MergeConfig {
    fn default() -> Self {
        Self {
            nearest_observer: true,
            overlap_radius_m: 0.05,
            fuse_duplicates: false,
            fuse_radius_m: 0.03,
        }
    }
}

impl MergeConfig {
    /// Checks ranges; returns the offending field (`consensus.merge.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        positive("consensus.merge.overlap_radius_m", self.overlap_radius_m)?;
        positive("consensus.merge.fuse_radius_m", self.fuse_radius_m)
    }
}
