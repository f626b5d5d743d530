//! Evaluation metrics (docs/method.md, Metrics): trajectory error ([`ate`]), how much two posed
//! depth images see of the same surfaces ([`covisibility`]), image quality ([`image`]: PSNR,
//! SSIM), depth error ([`depth`]), and the summary statistics every run-time report uses
//! ([`stats`]).
//!
//! LPIPS, the learned image metric, is in the `alexnet` crate with the network it runs: these
//! metrics are plain arithmetic and build without candle.

pub mod ate;
pub mod covisibility;
pub mod depth;
pub mod image;
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
