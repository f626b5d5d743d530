//! The mac-ego3d consensus process (SPEC section 4): selection (place recognition over keyframe
//! descriptors), association and alignment between agents, robust pose-graph and joint map
//! optimisation, corrections back to the agents.
//!
//! Built so far:
//! - [`place_recognition`]: the descriptor database that proposes loop closures;
//! - [`alignment`]: verified relative pose of two keyframes (features + RANSAC, G-ICP, checks);
//! - [`pose_graph`]: robust (GNC) pose graph over all agents' keyframes, giving each agent's
//!   frame in the world and corrected keyframe poses;
//! - [`config`]: their parameters.
//!
//! The joint photometric refinement and the process itself follow (issue 6).

pub mod alignment;
pub mod config;
pub mod place_recognition;
pub mod pose_graph;

// The wire format and the extractor must agree on the descriptor length.
const _: () =
    assert!(protocol::messages::DESCRIPTOR_LEN == slam_core::descriptor::GLOBAL_DESCRIPTOR_LEN);
