//! The geometric vocabulary every other crate of mac-ego3d speaks: rigid and similarity
//! transforms ([`se3`]), the pinhole camera model ([`camera`]) and its lens distortion
//! ([`distortion`]), depth images ([`depth`]),
//! timestamped trajectories and their file formats ([`trajectory`]), pose corrections
//! ([`correction`]), the errors and number parsing of the text files these are read from
//! ([`files`]), and the range checks configuration sections share ([`checks`]).
//!
//! It depends on nalgebra, serde and thiserror only, so the readers, the tracker, the metrics and
//! both processes can share these types without pulling in image decoding or a network.
//! Colour images are `image::RgbImage` wherever they appear; this crate does not wrap them.
//!
//! Conventions used across the workspace:
//! - Poses are `world_from_camera` (camera-to-world) rigid transforms unless a name says otherwise.
//! - Camera frame: x right, y down, z forward (OpenCV / 7-Scenes / TUM convention).
//! - Depth is metres as `f32`; an invalid depth pixel is exactly `0.0`.
//! - Quaternions at file boundaries follow the file's order (TUM: qx qy qz qw); in memory they are
//!   nalgebra `UnitQuaternion`s.

pub mod camera;
pub mod checks;
pub mod correction;
pub mod depth;
pub mod distortion;
pub mod files;
pub mod se3;
pub mod ssim;
pub mod trajectory;
