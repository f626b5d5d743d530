//! Global image descriptors for place recognition (docs/method.md, The consensus:
//! selection): every T_comm frames an
//! agent describes its latest keyframe image with one L2-normalised vector; the consensus scores
//! descriptors by dot product and proposes loop closures above a threshold.
//!
//! Two kinds, same length so they share one wire type:
//! - [`GlobalDescriptorExtractor::AlexNetGem`]: pretrained AlexNet relu5 features (the LPIPS
//!   weights) with generalised-mean (GeM) pooling per channel, L2-normalised;
//! - [`GlobalDescriptorExtractor::Thumbnail`]: the classical fallback when no weights are
//!   configured, a zero-mean grey thumbnail, L2-normalised (weaker under viewpoint change).

use std::path::Path;

use candle_core::{D, Tensor};
use image::RgbImage;
use image::imageops::FilterType;

use crate::lpips::{Lpips, LpipsError};

/// Descriptor length: AlexNet's relu5 has 256 channels; the thumbnail is 16 x 16.
pub const GLOBAL_DESCRIPTOR_LEN: usize = 256;
/// AlexNet layer whose activations are pooled (relu5: the most view-invariant).
pub const ALEXNET_LAYER: usize = 5;
/// GeM exponent: 1 is average pooling, large values approach max pooling; 3 is the usual choice.
pub const GEM_POWER: f64 = 3.0;
/// Activations are clamped to at least this before the power (GeM is undefined at 0).
const GEM_EPSILON: f64 = 1e-6;
/// Images are resized to this width (aspect kept) before AlexNet: place recognition needs the
/// layout of the scene, not its fine texture, and it is 4x cheaper than full 640x480.
pub const ALEXNET_INPUT_WIDTH: u32 = 320;
/// Side of the grey thumbnail of the classical fallback (16 x 16 = GLOBAL_DESCRIPTOR_LEN).
const THUMBNAIL_SIDE: u32 = 16;
const _: () = assert!((THUMBNAIL_SIDE * THUMBNAIL_SIDE) as usize == GLOBAL_DESCRIPTOR_LEN);

/// Computes a keyframe's global descriptor ([`GLOBAL_DESCRIPTOR_LEN`] values, L2-normalised);
/// built by [`Self::from_weights`], which picks the kind.
pub enum GlobalDescriptorExtractor {
    /// GeM-pooled relu5 features of the pretrained AlexNet (the LPIPS network, whose weights it
    /// holds), on the image resized to [`ALEXNET_INPUT_WIDTH`] pixels wide.
    AlexNetGem(Box<Lpips>),
    /// The classical fallback without weights: a zero-mean 16 x 16 grey thumbnail.
    Thumbnail,
}

impl GlobalDescriptorExtractor {
    /// The pretrained descriptor when `weights` is given and loads; otherwise the thumbnail
    /// fallback. Logs which one runs; a file that does not load is a warning. (No weights at all
    /// is an info line: [`crate::weights::default_alexnet_weights`] has already warned, naming
    /// the path it looked for and how to fetch the weights.)
    pub fn from_weights(weights: Option<&Path>) -> Self {
        match weights {
            Some(path) => match Lpips::load(path) {
                Ok(net) => {
                    tracing::info!(weights = %path.display(), "global descriptor: alexnet-gem");
                    Self::AlexNetGem(Box::new(net))
                }
                Err(error) => {
                    tracing::warn!(%error, "cannot load descriptor weights: using the classical thumbnail descriptor");
                    Self::Thumbnail
                }
            },
            None => {
                tracing::info!(
                    "global descriptor: classical thumbnail (no AlexNet weights configured)"
                );
                Self::Thumbnail
            }
        }
    }

    /// Short name for logs and reports.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::AlexNetGem(_) => "alexnet-gem",
            Self::Thumbnail => "thumbnail",
        }
    }

    /// The L2-normalised descriptor of an image.
    pub fn describe(&self, image: &RgbImage) -> Result<Vec<f32>, LpipsError> {
        let raw = match self {
            Self::AlexNetGem(net) => {
                let height = (image.height() as u64 * ALEXNET_INPUT_WIDTH as u64
                    / image.width().max(1) as u64) as u32;
                let small = image::imageops::resize(
                    image,
                    ALEXNET_INPUT_WIDTH,
                    height.max(1),
                    FilterType::Triangle,
                );
                gem_pool(&net.conv_features(&small, ALEXNET_LAYER)?)?
            }
            Self::Thumbnail => thumbnail(image),
        };
        Ok(l2_normalised(raw))
    }
}

/// GeM pooling of a `(1, channels, h, w)` activation: (mean over h, w of x^p)^(1/p) per channel.
fn gem_pool(features: &Tensor) -> Result<Vec<f64>, LpipsError> {
    let pooled = features
        .to_dtype(candle_core::DType::F64)?
        .clamp(GEM_EPSILON, f64::MAX)?
        .powf(GEM_POWER)?
        .flatten_from(2)?
        .mean(D::Minus1)?
        .powf(1.0 / GEM_POWER)?
        .flatten_all()?;
    Ok(pooled.to_vec1::<f64>()?)
}

/// Zero-mean grey thumbnail.
fn thumbnail(image: &RgbImage) -> Vec<f64> {
    let grey = image::imageops::grayscale(image);
    let small =
        image::imageops::resize(&grey, THUMBNAIL_SIDE, THUMBNAIL_SIDE, FilterType::Triangle);
    let values: Vec<f64> = small.as_raw().iter().map(|&v| v as f64).collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    values.into_iter().map(|v| v - mean).collect()
}

/// Unit-length f32 vector; an all-zero input (a uniform image) stays zero and scores 0 with
/// everything, so it never proposes a loop closure.
fn l2_normalised(values: Vec<f64>) -> Vec<f32> {
    let norm = values.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(norm.is_finite() && norm > 0.0) {
        return vec![0.0; values.len()];
    }
    values.into_iter().map(|v| (v / norm) as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The consensus's similarity (protocol::messages::descriptor_score): a dot product.
    fn score(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    /// A diagonal ramp with a bright disc: distinct layout, smooth enough for a thumbnail.
    fn textured(shift: u32) -> RgbImage {
        RgbImage::from_fn(160, 120, |x, y| {
            let x = x + shift;
            let disc = if (x as i32 - 50).pow(2) + (y as i32 - 40).pow(2) < 400 {
                120
            } else {
                0
            };
            let v = (x + y) / 2 + disc;
            image::Rgb([v.min(255) as u8, (v / 2) as u8, 40])
        })
    }

    #[test]
    fn thumbnail_descriptor_is_unit_length_and_discriminates() {
        let extractor = GlobalDescriptorExtractor::from_weights(None);
        assert_eq!(extractor.kind(), "thumbnail");
        let a = extractor.describe(&textured(0)).unwrap();
        assert_eq!(a.len(), GLOBAL_DESCRIPTOR_LEN);
        assert!((score(&a, &a) - 1.0).abs() < 1e-5);
        let near = extractor.describe(&textured(2)).unwrap();
        let flipped = extractor
            .describe(&image::imageops::flip_vertical(&textured(0)))
            .unwrap();
        assert!(score(&a, &near) > score(&a, &flipped));
        let uniform = extractor
            .describe(&RgbImage::from_pixel(64, 48, image::Rgb([9, 9, 9])))
            .unwrap();
        assert!(uniform.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn missing_weights_fall_back_to_thumbnail() {
        let extractor =
            GlobalDescriptorExtractor::from_weights(Some(Path::new("/nonexistent/alexnet.npz")));
        assert_eq!(extractor.kind(), "thumbnail");
    }

    #[test]
    fn real_data_alexnet_descriptor_scores_nearby_views_higher() {
        let weights = datasets::shared_data::require("weights/lpips/alexnet.npz");
        let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
        let extractor = GlobalDescriptorExtractor::from_weights(Some(&weights));
        assert_eq!(extractor.kind(), "alexnet-gem");
        let describe = |n: usize| {
            let img = image::open(dir.join(format!("frame-{n:06}.color.jpg")))
                .unwrap()
                .to_rgb8();
            extractor.describe(&img).unwrap()
        };
        let d0 = describe(0);
        assert_eq!(d0.len(), GLOBAL_DESCRIPTOR_LEN);
        let (near, far) = (score(&d0, &describe(10)), score(&d0, &describe(300)));
        eprintln!("score(0, 10) = {near}, score(0, 300) = {far}");
        assert!(
            near > far,
            "a view 1/3 s later must score higher than one 10 s later"
        );
    }
}
