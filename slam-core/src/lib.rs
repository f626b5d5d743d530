//! Code shared by the mac-ego3d processes (agent, consensus) and the user CLI.
//!
//! One concept, one place: the SE(3) helpers, the pinhole camera model, the dataset readers, the
//! embedded synthetic scene and the evaluation metrics are defined here once.
//!
//! Conventions used across the workspace:
//! - Poses are `world_from_camera` (camera-to-world) rigid transforms unless a name says otherwise.
//! - Camera frame: x right, y down, z forward (OpenCV / 7-Scenes / TUM convention).
//! - Depth is metres as `f32`; an invalid depth pixel is exactly `0.0`.
//! - Quaternions at file boundaries follow the file's order (TUM: qx qy qz qw); in memory they are
//!   nalgebra `UnitQuaternion`s.

pub mod camera;
pub mod config;
pub mod correction;
pub mod dataset;
pub mod descriptor;
pub mod metrics;
pub mod process;
pub mod registration;
pub mod se3;
pub mod shared_data;
pub mod trajectory;
pub mod weights;
