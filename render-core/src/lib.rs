//! render-core: the wgpu Gaussian-splat kernels shared by agents (mapping) and the consensus
//! (joint refinement). Of this workspace it depends on geometry (pinhole intrinsics, SSIM's
//! definition) and splats, the map as data: [`splats::GaussianCloud`], [`splats::RigidTransform`]
//! and the PLY format are splats' (a crate without a GPU), and this crate's functions take them.
//!
//! - [`types`]: the CPU scene description ([`Camera`], [`RenderMode`], [`RasterConfig`], ...)
//!   and the conventions every boundary follows (quaternions `[w, x, y, z]`, OpenCV camera axes,
//!   pixel centres at integer coordinates, colours as RGB in `[0, 1]`, pose gradients as a left
//!   perturbation of `camera_from_world` ordered `[translation, rotation]`).
//! - [`reference`](mod@reference): the scalar CPU renderer (forward and backward), the test oracle.
//! - [`context`]: the wgpu adapter/device and its capabilities (float atomics, subgroups,
//!   storage-binding limit).
//! - [`gpu`]: device-resident Gaussians ([`gpu::DeviceGaussians`]) and the forward renderer
//!   (project, radix sort, tile binning, rasterize; the steps of one frame are in `forward.rs`,
//!   the radix sort in `sort.rs`, pipeline and dispatch helpers in `passes.rs`).
//! - [`map`]: in-place edits of the device map (append with amortised growth, prune/retain by
//!   stable compaction, rigid transform) and [`map::DeviceMap`], which keeps the Adam state in
//!   step with them.
//! - [`backward`]: per-Gaussian and camera-pose gradients on the device.
//! - [`pose`]: Adam over a camera pose on the host, stepped with the read-back pose gradient.
//! - `wgsl.rs`: the WGSL/Rust contract: every constant and uniform struct shared with the
//!   kernels, defined once in Rust and prepended to every kernel as a generated WGSL prelude.
//! - [`training`]: L1 / SSIM / depth-L1 loss with gradients and Adam on the device, plus the CPU
//!   reference loss.
//!
//! Typical iteration (no host read-back; `GpuRenderer::check_pairs` outside the loop sizes
//! the pair buffers, see [`gpu`]):
//! `render_frame` -> `TrainingKernels::image_loss` -> `GpuRenderer::backward` ->
//! `TrainingKernels::adam_step`.

pub mod backward;
pub mod context;
mod forward;
mod gaussians;
pub mod gpu;
pub mod map;
mod passes;
pub mod pose;
mod profile;
pub mod reference;
mod sort;
pub mod training;
pub mod types;
mod wgsl;

pub use types::{
    Camera, GaussianGradients, ImageGradients, PoseGradient, RasterConfig, RenderMode,
    RenderOutput, constants, depth_sort_key,
};
