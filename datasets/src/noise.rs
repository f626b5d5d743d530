//! Sensor-noise perturbation for the robustness protocol (docs/method.md, Metrics): zero-mean Gaussian
//! noise with sigma 10/255 on RGB and 5 mm on depth, on RGB, depth or both. Seeded per frame
//! (seed and frame number), so the same frame gets the same noise whatever order frames are
//! decoded in.

use geometry::checks::{FieldError, non_negative};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::Frame;

/// Which channels receive noise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NoiseTarget {
    /// Colour only.
    Rgb,
    /// Depth only.
    Depth,
    /// Colour and depth.
    Rgbd,
}

impl std::str::FromStr for NoiseTarget {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "rgb" => Ok(Self::Rgb),
            "depth" => Ok(Self::Depth),
            "rgbd" => Ok(Self::Rgbd),
            other => Err(format!(
                "unknown noise target {other:?}: expected rgb, depth or rgbd"
            )),
        }
    }
}

/// Noise parameters; the defaults are the robustness protocol's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseConfig {
    /// Which channels receive noise: `rgb`, `depth` or `rgbd` (default `rgbd`).
    pub target: NoiseTarget,
    /// Standard deviation of RGB noise on the [0, 1] intensity scale.
    pub rgb_sigma: f64,
    /// Standard deviation of depth noise in metres.
    pub depth_sigma_m: f64,
    /// Seed of the noise (default 0). Each frame draws from a stream of its own, made from this
    /// seed and its frame number.
    pub seed: u64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        Self {
            target: NoiseTarget::Rgbd,
            rgb_sigma: 10.0 / 255.0,
            depth_sigma_m: 0.005,
            seed: 0,
        }
    }
}

impl NoiseConfig {
    /// The protocol's default noise, on the channels `target` names.
    pub fn with_target(target: NoiseTarget) -> Self {
        Self {
            target,
            ..Self::default()
        }
    }

    /// Adds noise to a frame in place. RGB values are rounded and clamped to 0..=255. Depth noise
    /// touches only valid pixels; a pixel pushed to or below zero becomes invalid (0) rather than
    /// negative.
    pub fn apply(&self, frame: &mut Frame) {
        // Distinct streams per frame; the golden-ratio multiplier spreads consecutive seeds.
        let stream = self.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ frame.index as u64;
        let mut rng = ChaCha8Rng::seed_from_u64(stream);
        if matches!(self.target, NoiseTarget::Rgb | NoiseTarget::Rgbd) && self.rgb_sigma > 0.0 {
            let normal = Normal::new(0.0, self.rgb_sigma * 255.0).expect("finite positive sigma");
            for v in frame.rgb.iter_mut() {
                let noisy = *v as f64 + normal.sample(&mut rng);
                *v = noisy.round().clamp(0.0, 255.0) as u8;
            }
        }
        if matches!(self.target, NoiseTarget::Depth | NoiseTarget::Rgbd) && self.depth_sigma_m > 0.0
        {
            let normal = Normal::new(0.0, self.depth_sigma_m).expect("finite positive sigma");
            for d in frame.depth.data.iter_mut().filter(|d| **d > 0.0) {
                let noisy = *d as f64 + normal.sample(&mut rng);
                *d = if noisy > 0.0 { noisy as f32 } else { 0.0 };
            }
        }
    }
}

impl NoiseConfig {
    /// Checks ranges; returns the offending field (`noise.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        non_negative("noise.rgb_sigma", self.rgb_sigma)?;
        non_negative("noise.depth_sigma_m", self.depth_sigma_m)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::camera::Intrinsics;
    use geometry::depth::DepthImage;

    fn flat_frame(index: usize) -> Frame {
        let (w, h) = (64, 64);
        let mut depth = DepthImage::new(w, h);
        depth
            .data
            .iter_mut()
            .enumerate()
            .for_each(|(i, d)| *d = if i % 10 == 0 { 0.0 } else { 2.0 });
        Frame {
            index,
            timestamp: 0.0,
            rgb: image::RgbImage::from_pixel(w, h, image::Rgb([128, 128, 128])),
            depth,
            world_from_camera_gt: None,
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: Intrinsics::new(50.0, 50.0, 31.5, 31.5, w, h),
        }
    }

    fn std_dev(values: impl Iterator<Item = f64>) -> f64 {
        let v: Vec<f64> = values.collect();
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
    }

    #[test]
    fn noise_has_the_protocol_sigmas_and_is_seeded() {
        let cfg = NoiseConfig::default();
        let mut a = flat_frame(7);
        cfg.apply(&mut a);
        let rgb_sd = std_dev(a.rgb.iter().map(|&v| v as f64 / 255.0));
        assert!((rgb_sd - 10.0 / 255.0).abs() < 0.004, "rgb sigma {rgb_sd}");
        let depth_sd = std_dev(a.depth.data.iter().filter(|d| **d > 0.0).map(|&d| d as f64));
        assert!((depth_sd - 0.005).abs() < 0.0005, "depth sigma {depth_sd}");
        // Invalid pixels stay invalid.
        assert!(a.depth.data.iter().step_by(10).all(|&d| d == 0.0));
        let mut b = flat_frame(7);
        cfg.apply(&mut b);
        assert_eq!(a.rgb, b.rgb);
        assert_eq!(a.depth, b.depth);
        let mut c = flat_frame(8);
        cfg.apply(&mut c);
        assert_ne!(a.rgb, c.rgb);
    }

    #[test]
    fn targets_are_respected() {
        let clean = flat_frame(1);
        let mut rgb_only = flat_frame(1);
        NoiseConfig::with_target(NoiseTarget::Rgb).apply(&mut rgb_only);
        assert_eq!(rgb_only.depth, clean.depth);
        assert_ne!(rgb_only.rgb, clean.rgb);
        let mut depth_only = flat_frame(1);
        NoiseConfig::with_target(NoiseTarget::Depth).apply(&mut depth_only);
        assert_eq!(depth_only.rgb, clean.rgb);
        assert_ne!(depth_only.depth, clean.depth);
    }
}
