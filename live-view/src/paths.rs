//! The entity paths of the live view, defined once (the crate documentation lists what each
//! holds).

/// The world frame: every agent and the consensus log under it.
pub const WORLD: &str = "world";

/// Agent `K`'s frame: its transform is `world_from_agent`.
pub fn agent(agent_id: u32) -> String {
    format!("world/agent_{agent_id}")
}

/// Agent `K`'s camera: its pose in the agent's frame, the Pinhole and the colour image, per
/// frame on [`FRAME_TIMELINE`].
pub fn agent_camera(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/camera")
}

/// Agent `K`'s tracked path so far, one line through its camera positions.
pub fn agent_trajectory(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/trajectory")
}

/// Agent `K`'s keyframes, as points at their camera positions.
pub fn agent_keyframes(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/keyframes")
}

/// Agent `K`'s map: its Gaussians as coloured points (at most `map_points_max`), the final map
/// at the end.
pub fn agent_map(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/map")
}

/// Every closure attempt so far, one line between its two keyframes, coloured by its
/// [`crate::ClosureOutcome`].
pub const CONSENSUS_CLOSURES: &str = "world/consensus/closures";

/// Agent `K`'s keyframe positions in the world after the latest pose-graph solve, one line.
pub fn consensus_trajectory(agent_id: u32) -> String {
    format!("world/consensus/trajectories/agent_{agent_id}")
}

/// The merged world map as coloured points, each time the consensus writes it.
pub const CONSENSUS_MAP: &str = "world/consensus/map";

/// Time series: milliseconds from a keyframe's arrival at the consensus to the first solve that
/// placed it.
pub const CONSENSUS_LATENCY_MS: &str = "consensus/latency_ms";

/// Time series: closure attempts accepted so far (verified and kept by the pose graph).
pub const CONSENSUS_CLOSURES_ACCEPTED: &str = "consensus/closures/accepted";

/// Time series: closure attempts refused by alignment so far (those the pose graph dropped
/// count in neither series).
pub const CONSENSUS_CLOSURES_REJECTED: &str = "consensus/closures/rejected";

/// Time series: kB/s received from agent `K` (1 kB = 1000 bytes), sampled about once a second.
pub fn consensus_agent_kbps(agent_id: u32) -> String {
    format!("consensus/agent_{agent_id}/kbps")
}

/// The joint refinement's quality before and after (its loss stays on the device).
pub const CONSENSUS_REFINEMENT_PSNR_DB: &str = "consensus/refinement/psnr_db";

/// The sequence timeline of agents' frames (the frame's index in its sequence).
pub const FRAME_TIMELINE: &str = "frame";
