//! The definition of SSIM (Wang et al. 2004, as 3DGS and scikit-image use it): an 11x11
//! Gaussian window of standard deviation 1.5 pixels and the stabilisers `K1 = 0.01`,
//! `K2 = 0.03` for data range 1. One definition for the evaluation metric (`metrics::image`)
//! and the training loss (render-core), so the maps are optimised for the SSIM they are scored
//! with.

/// Gaussian window side, pixels.
pub const SSIM_WINDOW: usize = 11;
/// Gaussian window standard deviation, pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// Stabiliser of the means' term, as a fraction of the data range (`C1 = K1^2`).
pub const SSIM_K1: f64 = 0.01;
/// Stabiliser of the variances' term, as a fraction of the data range (`C2 = K2^2`).
pub const SSIM_K2: f64 = 0.03;

/// The window's normalised 1-D Gaussian weights (the 2-D window is their outer product).
pub fn gaussian_window() -> [f64; SSIM_WINDOW] {
    let radius = (SSIM_WINDOW / 2) as f64;
    let mut w = [0.0; SSIM_WINDOW];
    for (i, v) in w.iter_mut().enumerate() {
        let x = i as f64 - radius;
        *v = (-x * x / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}
