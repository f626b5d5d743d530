//! Evaluation metrics (SPEC section 7): trajectory error ([`ate`]), image quality ([`image`]:
//! PSNR, SSIM; [`lpips`]: LPIPS AlexNet v0.1), depth error ([`depth`]), and the summary
//! statistics every run-time report uses ([`stats`]).

pub mod ate;
pub mod covisibility;
pub mod depth;
pub mod image;
pub mod lpips;
pub mod stats;

/// Errors of metric computations on well-formed but unusable input.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    #[error("images differ in size: {0}x{1} vs {2}x{3}")]
    SizeMismatch(u32, u32, u32, u32),
    #[error("image is {0}x{1}; at least {2}x{2} pixels are needed")]
    TooSmall(u32, u32, u32),
    #[error("{0}")]
    Trajectory(String),
}
