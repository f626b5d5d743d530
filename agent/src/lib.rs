//! The mac-ego3d agent (docs/method.md, One agent): one OS process per agent running
//! frame source -> G-ICP tracking -> keyframes -> Gaussian map optimisation.
//!
//! - [`source`]: frames in order, decoded ahead, sanitised, missing ones skipped and counted;
//! - tracking: frame-to-model G-ICP odometry; its model is a voxel map of the points tracking
//!   keyframes marked trackable, with their G-ICP covariances (the mapper's optimisation does
//!   not move them; the consensus's corrections do);
//! - [`seeding`]: new Gaussians from keyframe points;
//! - [`mapper`]: the mapping thread (render-core on the device; render-core's `DeviceMap` keeps
//!   Gaussians and Adam state together through appends and pruning);
//! - [`evaluation`]: rendering quality at the estimated poses;
//! - [`pipeline`]: the per-frame stages (track, decide keyframe, seed, publish, hand to the
//!   mapper, apply corrections);
//! - [`pace`]: the camera clock of the sensor pace (frames at their timestamps, late ones dropped);
//! - [`run`]: one run: the frame loop over those stages, then its outputs; [`report`]: its
//!   metrics.json;
//! - [`swarm`]: the link to the consensus, [`describer`]: keyframe descriptors computed beside
//!   the frame loop, [`local_corrections`]: the consensus's corrections applied to the local
//!   maps, and [`link_schedule`]: simulated intermittent links;
//! - [`progress`]: progress.json for the swarm launcher's progress line;
//! - [`views`]: keyframes.csv and trajectory_map.tum, what held-out evaluation needs of a run.

pub mod describer;
pub mod evaluation;
pub mod link_schedule;
pub mod local_corrections;
pub mod mapper;
pub mod pace;
pub mod pipeline;
pub mod progress;
pub mod report;
pub mod ros2_live;
pub mod ros2_outputs;
pub mod run;
pub mod seeding;
pub mod segments;
pub mod source;
pub mod spool;
pub mod swarm;
pub mod views;

// The extractor the agent runs and the wire format it publishes in must agree on the
// descriptor length.
const _: () =
    assert!(protocol::messages::DESCRIPTOR_LEN == alexnet::descriptor::GLOBAL_DESCRIPTOR_LEN);
