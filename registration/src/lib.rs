//! RGB-D tracking core shared by the agent (frame-to-model tracking, docs/method.md, One agent)
//! and the consensus (keyframe-to-keyframe alignment, docs/method.md, The consensus: association
//! and alignment): a pipeline small enough to read in
//! one sitting, in the spirit of KISS-ICP.
//!
//! 1. [`points`]: back-project every `pixel_stride`-th depth pixel (camera frame), dropping
//!    invalid and truncated depth.
//! 2. [`covariance`]: one G-ICP covariance per point from its k nearest neighbours (the depth
//!    image's pixel grid where it certifies them, else the kd-tree of [`kdtree::PointTree`]),
//!    regularised to a plane-like ellipse; map Gaussians get theirs from scale and rotation
//!    ([`covariance::Covariance::from_gaussian`]).
//! 3. [`gicp`]: Generalized-ICP with Levenberg-Marquardt on SE(3) against any
//!    [`gicp::RegistrationTarget`]; coarse-to-fine correspondence distances for the consensus.
//! 4. [`voxel_map`]: the incremental target map (insert / replace / remove by id, view-frustum
//!    selection of candidates).
//! 5. [`odometry`]: the driver that strings them together with a constant-velocity prediction,
//!    keyframes and failure recovery; used by `mac-ego3d bench tracking`.
//!
//! Registration without an initial guess, shared by the consensus (linking agents) and the agent
//! (relocalising after tracking failed):
//! - [`alignment`]: two RGB-D views, by image features lifted to 3-D, RANSAC, G-ICP and a
//!   depth-agreement verification;
//! - [`map_registration`]: two point maps, by FPFH-style features, RANSAC, G-ICP and a
//!   verification of overlap, residual, degeneracy and colour.
//!
//! Every parameter comes from [`crate::config::TrackingConfig`] / [`crate::config::KeyframeConfig`]
//! or is a named constant next to the code that uses it, with the reason for its value.

pub mod alignment;
pub mod config;
pub mod covariance;
pub mod gicp;
pub mod kdtree;
pub mod map_registration;
pub mod odometry;
pub mod photometric;
pub mod points;
pub mod voxel_map;
mod voxel_points;

pub use covariance::{Covariance, estimate_covariances};
pub use gicp::{
    GicpParams, RegistrationFailure, RegistrationResult, RegistrationTarget, register,
    register_coarse_to_fine,
};
pub use kdtree::{PointTree, PointTreeError};
pub use odometry::{
    FrameInput, Odometry, OdometryMode, OdometryStats, Placement, StageTimings, TrackedFrame,
    TrackingFailure, TrackingOutcome,
};
pub use points::{PointCloud, points_from_depth};
pub use voxel_map::{MapPoint, MapPointId, ViewFrustum, VoxelMap};

/// Threads the parallel steps (covariances, G-ICP) run on: rayon's global pool, sized by
/// `RAYON_NUM_THREADS` or the number of cores.
pub fn worker_threads() -> usize {
    rayon::current_num_threads()
}
