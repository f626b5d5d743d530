//! Image quality: PSNR over the whole image (data range 1) and SSIM with an 11x11 Gaussian window
//! (sigma 1.5, K1 = 0.01, K2 = 0.03) in two variants:
//! - `ssim`: the 3DGS variant: local statistics with zero padding, averaged over every pixel;
//! - `ssim_valid`: scikit-image's variant (`structural_similarity(gaussian_weights=True,
//!   sigma=1.5, use_sample_covariance=False, data_range=1)`): averaged only over pixels whose
//!   window lies inside the image.
//!
//! Both average over the colour channels. Inputs are interleaved RGB in [0, 1].

use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::MetricError;

// SSIM's window and constants are geometry's, shared with the training loss (render-core).
use geometry::ssim::{SSIM_K1, SSIM_K2, SSIM_WINDOW, gaussian_window};
const CHANNELS: usize = 3;

/// PSNR and both SSIM variants of one image pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImageQuality {
    /// dB; infinite for identical images.
    pub psnr: f64,
    /// SSIM, the 3DGS variant: zero padding, averaged over every pixel (see the module
    /// documentation).
    pub ssim: f64,
    /// SSIM, scikit-image's variant: averaged over the pixels whose window lies inside the image.
    pub ssim_valid: f64,
}

/// Interleaved RGB u8 -> interleaved f64 in [0, 1].
fn to_unit(img: &RgbImage) -> Vec<f64> {
    img.as_raw().iter().map(|&v| v as f64 / 255.0).collect()
}

fn check_sizes(a: (u32, u32), b: (u32, u32)) -> Result<(), MetricError> {
    if a != b {
        return Err(MetricError::SizeMismatch(a.0, a.1, b.0, b.1));
    }
    if a.0 < SSIM_WINDOW as u32 || a.1 < SSIM_WINDOW as u32 {
        return Err(MetricError::TooSmall(a.0, a.1, SSIM_WINDOW as u32));
    }
    Ok(())
}

/// PSNR and SSIM of 8-bit images.
pub fn image_quality(
    reference: &RgbImage,
    rendered: &RgbImage,
) -> Result<ImageQuality, MetricError> {
    check_sizes(reference.dimensions(), rendered.dimensions())?;
    let (w, h) = reference.dimensions();
    image_quality_unit(
        &to_unit(reference),
        &to_unit(rendered),
        w as usize,
        h as usize,
    )
}

/// PSNR and SSIM of interleaved RGB images with values in [0, 1] (renders, before quantisation).
pub fn image_quality_unit(
    reference: &[f64],
    rendered: &[f64],
    width: usize,
    height: usize,
) -> Result<ImageQuality, MetricError> {
    check_sizes((width as u32, height as u32), (width as u32, height as u32))?;
    let n = width * height * CHANNELS;
    if reference.len() != n || rendered.len() != n {
        return Err(MetricError::Trajectory(format!(
            "image buffers hold {} and {} values, expected {n} for {width}x{height} RGB",
            reference.len(),
            rendered.len()
        )));
    }
    let (ssim, ssim_valid) = ssim(reference, rendered, width, height);
    Ok(ImageQuality {
        psnr: psnr(reference, rendered),
        ssim,
        ssim_valid,
    })
}

/// PSNR in dB with data range 1.
pub fn psnr(reference: &[f64], rendered: &[f64]) -> f64 {
    let mse = reference
        .iter()
        .zip(rendered)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        / reference.len() as f64;
    -10.0 * mse.log10()
}

/// Separable Gaussian filter of one plane with zero padding (same-size output).
fn blur(plane: &[f64], width: usize, height: usize, window: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let r = (SSIM_WINDOW / 2) as isize;
    let mut rows = vec![0.0; plane.len()];
    for y in 0..height {
        let line = &plane[y * width..(y + 1) * width];
        for x in 0..width {
            let mut acc = 0.0;
            for (k, wk) in window.iter().enumerate() {
                let xx = x as isize + k as isize - r;
                if xx >= 0 && (xx as usize) < width {
                    acc += wk * line[xx as usize];
                }
            }
            rows[y * width + x] = acc;
        }
    }
    let mut out = vec![0.0; plane.len()];
    for y in 0..height {
        for (k, wk) in window.iter().enumerate() {
            let yy = y as isize + k as isize - r;
            if yy < 0 || yy as usize >= height {
                continue;
            }
            let src = &rows[yy as usize * width..(yy as usize + 1) * width];
            let dst = &mut out[y * width..(y + 1) * width];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += wk * s;
            }
        }
    }
    out
}

/// (zero-padded mean SSIM, valid-region mean SSIM) over all channels; channels in parallel.
fn ssim(a: &[f64], b: &[f64], width: usize, height: usize) -> (f64, f64) {
    use rayon::prelude::*;
    let r = SSIM_WINDOW / 2;
    let sums: Vec<(f64, f64)> = (0..CHANNELS)
        .into_par_iter()
        .map(|c| {
            let pa: Vec<f64> = a.iter().skip(c).step_by(CHANNELS).copied().collect();
            let pb: Vec<f64> = b.iter().skip(c).step_by(CHANNELS).copied().collect();
            ssim_channel_sums(&pa, &pb, width, height)
        })
        .collect();
    let (sum_all, sum_valid) = sums
        .iter()
        .fold((0.0, 0.0), |acc, s| (acc.0 + s.0, acc.1 + s.1));
    let valid_pixels = (width - 2 * r) * (height - 2 * r);
    (
        sum_all / (width * height * CHANNELS) as f64,
        sum_valid / (valid_pixels * CHANNELS) as f64,
    )
}

/// Sums of the SSIM map of one channel plane: (over every pixel, over the valid region).
fn ssim_channel_sums(pa: &[f64], pb: &[f64], width: usize, height: usize) -> (f64, f64) {
    let window = gaussian_window();
    let c1 = SSIM_K1 * SSIM_K1;
    let c2 = SSIM_K2 * SSIM_K2;
    let r = SSIM_WINDOW / 2;
    let mu_a = blur(pa, width, height, &window);
    let mu_b = blur(pb, width, height, &window);
    let aa = blur(
        &pa.iter().map(|v| v * v).collect::<Vec<_>>(),
        width,
        height,
        &window,
    );
    let bb = blur(
        &pb.iter().map(|v| v * v).collect::<Vec<_>>(),
        width,
        height,
        &window,
    );
    let ab = blur(
        &pa.iter().zip(pb).map(|(x, y)| x * y).collect::<Vec<_>>(),
        width,
        height,
        &window,
    );
    let (mut sum_all, mut sum_valid) = (0.0, 0.0);
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            let (ma, mb) = (mu_a[i], mu_b[i]);
            let var_a = aa[i] - ma * ma;
            let var_b = bb[i] - mb * mb;
            let cov = ab[i] - ma * mb;
            let s = ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (var_a + var_b + c2));
            sum_all += s;
            if x >= r && y >= r && x < width - r && y < height - r {
                sum_valid += s;
            }
        }
    }
    (sum_all, sum_valid)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: u32, h: u32, seed: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| {
            let v = (x * 7 + y * 13 + seed * 31) ^ (x * y + seed);
            image::Rgb([
                (v % 256) as u8,
                ((v / 3) % 256) as u8,
                ((v * 5) % 256) as u8,
            ])
        })
    }

    #[test]
    fn identical_images() {
        let a = pattern(40, 30, 1);
        let q = image_quality(&a, &a).unwrap();
        assert!(q.psnr.is_infinite());
        assert!((q.ssim - 1.0).abs() < 1e-12 && (q.ssim_valid - 1.0).abs() < 1e-12);
    }

    #[test]
    fn psnr_of_a_known_error() {
        let a = RgbImage::from_pixel(20, 20, image::Rgb([100, 100, 100]));
        let b = RgbImage::from_pixel(20, 20, image::Rgb([110, 110, 110]));
        let q = image_quality(&a, &b).unwrap();
        let expected = -10.0 * ((10.0f64 / 255.0).powi(2)).log10();
        assert!((q.psnr - expected).abs() < 1e-9);
        // Constant images: SSIM reduces to the luminance term in the valid region.
        let (ma, mb) = (100.0 / 255.0, 110.0 / 255.0);
        let lum = (2.0 * ma * mb + 1e-4) / (ma * ma + mb * mb + 1e-4);
        assert!(
            (q.ssim_valid - lum).abs() < 1e-9,
            "{} vs {lum}",
            q.ssim_valid
        );
    }

    #[test]
    fn ssim_drops_with_noise_and_refuses_bad_sizes() {
        let a = pattern(64, 48, 2);
        let b = pattern(64, 48, 3);
        let q = image_quality(&a, &b).unwrap();
        assert!(q.ssim < 0.9 && q.ssim_valid < 0.9);
        assert_eq!(
            image_quality(&a, &pattern(64, 47, 2)).unwrap_err(),
            MetricError::SizeMismatch(64, 48, 64, 47)
        );
        assert!(image_quality(&pattern(8, 8, 0), &pattern(8, 8, 0)).is_err());
    }

    /// scikit-image 0.26.0 (ssim_valid, psnr) and scipy.ndimage (zero-padded ssim) on redkitchen
    /// frames 0 and 10 as decoded by our reader (scripts/golden_image_metrics.py).
    const GOLDEN_REDKITCHEN_0_10: ImageQuality = ImageQuality {
        psnr: 19.2064414110,
        ssim: 0.5279206426,
        ssim_valid: 0.5194726662,
    };

    #[test]
    fn real_data_psnr_ssim_match_scikit_image() {
        let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
        let a = image::open(dir.join("frame-000000.color.jpg"))
            .unwrap()
            .to_rgb8();
        let b = image::open(dir.join("frame-000010.color.jpg"))
            .unwrap()
            .to_rgb8();
        let q = image_quality(&a, &b).unwrap();
        let golden = GOLDEN_REDKITCHEN_0_10;
        assert!(
            (q.psnr - golden.psnr).abs() < 1e-6,
            "psnr {} vs {}",
            q.psnr,
            golden.psnr
        );
        assert!(
            (q.ssim_valid - golden.ssim_valid).abs() < 1e-6,
            "ssim_valid {} vs {}",
            q.ssim_valid,
            golden.ssim_valid
        );
        assert!(
            (q.ssim - golden.ssim).abs() < 1e-6,
            "ssim {} vs {}",
            q.ssim,
            golden.ssim
        );
    }
}
