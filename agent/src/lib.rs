//! The mac-ego3d agent (SPEC section 3): one OS process per agent running
//! frame source -> G-ICP tracking -> keyframes -> Gaussian map optimisation.
//!
//! - [`source`]: frames in order, decoded ahead, sanitised, missing ones skipped and counted;
//! - tracking: the registration crate's frame-to-model G-ICP odometry (its map is the trackable Gaussians'
//!   means with their G-ICP covariances);
//! - [`seeding`]: new Gaussians from keyframe points;
//! - [`mapper`]: the mapping thread (render-core on the device; render-core's `DeviceMap` keeps
//!   Gaussians and Adam state together through appends and pruning);
//! - [`evaluation`]: rendering quality at the estimated poses;
//! - [`run`]: the standalone run and its outputs;
//! - [`swarm`]: the link to the consensus, [`corrections`]: its corrections applied to the local
//!   maps, and [`link_schedule`]: simulated intermittent links;
//! - [`progress`]: progress.json for the swarm launcher's progress line.

pub mod corrections;
pub mod evaluation;
pub mod link_schedule;
pub mod mapper;
pub mod progress;
pub mod run;
pub mod seeding;
pub mod source;
pub mod swarm;
