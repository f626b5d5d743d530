//! The Gaussian-splat map as data, without a GPU: [`GaussianCloud`] (3D Gaussians in
//! structure-of-arrays layout, with the host-side edits the device map mirrors),
//! [`RigidTransform`] (the f32 pose of Gaussians and cameras) and the 3DGS PLY format
//! ([`ply`]). The messages that carry Gaussians between processes (protocol, mac-bridge), the
//! consensus's merged map and render-core's device map all use these; only render-core adds
//! wgpu.
//!
//! Conventions: quaternions are `[w, x, y, z]` (w first, not necessarily unit length); colours
//! are linear RGB in `[0, 1]` (SH degree 0 already converted from `f_dc`; [`ply`] converts in
//! files); opacities are logits; scales are natural logs.

mod cloud;
pub mod ply;
mod transform;

pub use cloud::GaussianCloud;
pub use transform::{RigidTransform, quaternion_multiply, rotation_from_quaternion_f64};
