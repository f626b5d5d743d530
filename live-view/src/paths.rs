//! The entity paths of the live view, defined once (the crate documentation lists what each
//! holds).

/// The world frame: every agent and the consensus log under it.
pub const WORLD: &str = "world";

/// Agent `K`'s frame: its transform is `world_from_agent`.
pub fn agent(agent_id: u32) -> String {
    format!("world/agent_{agent_id}")
}

pub fn agent_camera(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/camera")
}

pub fn agent_trajectory(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/trajectory")
}

pub fn agent_keyframes(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/keyframes")
}

pub fn agent_map(agent_id: u32) -> String {
    format!("world/agent_{agent_id}/map")
}

pub const CONSENSUS_CLOSURES: &str = "world/consensus/closures";

pub fn consensus_trajectory(agent_id: u32) -> String {
    format!("world/consensus/trajectories/agent_{agent_id}")
}

pub const CONSENSUS_MAP: &str = "world/consensus/map";

pub const CONSENSUS_LATENCY_MS: &str = "consensus/latency_ms";

pub const CONSENSUS_CLOSURES_ACCEPTED: &str = "consensus/closures/accepted";

pub const CONSENSUS_CLOSURES_REJECTED: &str = "consensus/closures/rejected";

pub fn consensus_agent_kbps(agent_id: u32) -> String {
    format!("consensus/agent_{agent_id}/kbps")
}

/// The joint refinement's quality before and after (its loss stays on the device).
pub const CONSENSUS_REFINEMENT_PSNR_DB: &str = "consensus/refinement/psnr_db";

/// The sequence timeline of agents' frames (the frame's index in its sequence).
pub const FRAME_TIMELINE: &str = "frame";
