//! The mac-ego3d consensus process (docs/method.md, The consensus): selection (place recognition
//! over keyframe descriptors), association and alignment between agents, robust pose-graph and
//! joint map optimisation, corrections back to the agents.
//!
//! Modules, in the order a keyframe meets them:
//! - [`process`]: the `mac-consensus` process (iceoryx2 on the main thread, a worker thread for
//!   the engine, an aligner thread, the outputs);
//! - [`inbox`]: joins each keyframe's messages, drops repeats, says what to re-request;
//! - [`engine`]: the consensus state (keyframes, candidates, decisions), free of transport;
//! - [`place_recognition`]: the descriptor database that proposes loop closures;
//! - [`alignment`]: verified relative pose of two keyframes (features + RANSAC, G-ICP, checks);
//! - [`registration::map_registration`] (in the registration crate): verified transform between
//!   two agents' maps without an initial guess (voxel downsampling, FPFH-style descriptors,
//!   RANSAC with a runner-up, G-ICP, checks);
//! - [`map_links`]: when two agents' maps are registered, the free-space check of a result, and
//!   the pose-graph edge it becomes;
//! - [`pose_graph`]: robust (GNC) pose graph over all agents' keyframes, giving each agent's
//!   frame in the world and corrected keyframe poses;
//! - [`refinement`]: joint photometric refinement of the merged world map and the keyframe
//!   poses through render-core, with the pose-consistency term over the pose graph's edges;
//! - [`store`]: every accepted input, committed to a crash-safe database in the run folder
//!   before it is acted on, so a consensus started again on the folder resumes the run;
//! - [`rebuild`]: a finished run's end (merged map, refinement, outputs) built again from its
//!   store with another configuration;
//!
//! Their parameters are the config crate's `[consensus.*]` sections.
//!
//! Refinement runs once the agents are done (before the outputs are written); during the run the
//! agents receive the pose graph's corrections.

pub mod alignment;
pub mod engine;
pub mod inbox;
pub mod map_links;
pub mod place_recognition;
pub mod pose_graph;
pub mod process;
pub mod rebuild;
pub mod refinement;
pub mod store;
