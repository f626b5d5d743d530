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
    /// Two images (or depth images) differ in size: the first's width and height, then the
    /// second's.
    #[error("images differ in size: {0}x{1} vs {2}x{3}")]
    SizeMismatch(u32, u32, u32, u32),
    /// An image is smaller than the SSIM window: its width and height, then the window's side (11).
    #[error("image is {0}x{1}; at least {2}x{2} pixels are needed")]
    TooSmall(u32, u32, u32),
    /// Other unusable input, with the message saying what: trajectories with no pose pairs within
    /// the time tolerance, or whose pairs cannot be aligned (too few, all positions identical),
    /// and (despite the name) image buffers whose length does not match their size.
    #[error("{0}")]
    Trajectory(String),
}
