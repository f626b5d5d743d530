//! LPIPS v0.1 with the AlexNet backbone: a learned perceptual distance between two RGB images
//! (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric").
//!
//! The computation matches torchmetrics `LPIPS(net_type='alex', normalize=True)`:
//! 1. pixels in `[0, 1]` are mapped to `[-1, 1]`, then through LPIPS' scaling layer
//!    `(x - shift) / scale`;
//! 2. torchvision AlexNet `features` is run and its five ReLU outputs (relu1..relu5) are tapped;
//! 3. per tap, each spatial feature vector is scaled to unit length over channels, the two
//!    images' vectors are subtracted and squared, a learned 1x1 linear head weighs the channels,
//!    and the result is averaged over the feature map;
//! 4. the five per-layer values are summed.
//!
//! The weights live outside the repository (`alexnet.npz`, torchvision names, OIHW layout);
//! `scripts/get_lpips_weights.sh` produces the file on a user's machine.
//!
//! The same AlexNet activations are exposed through [`Lpips::conv_features`] so that they can be
//! reused as a pretrained image descriptor (e.g. for place recognition).

use std::fmt;
use std::path::{Path, PathBuf};

use candle_core::npy::NpzTensors;
use candle_core::{DType, Device, Tensor};
use image::RgbImage;

/// Number of AlexNet ReLU outputs LPIPS compares (relu1..relu5).
pub const FEATURE_LAYER_COUNT: usize = 5;

/// Smallest width and height AlexNet's `features` stack accepts: below it a max-pool window no
/// longer fits in the feature map. Derived from [`ALEXNET_CONVS`]; a test checks it.
pub const MIN_IMAGE_SIDE: u32 = 31;

/// Largest 8-bit channel value; pixels are divided by it to land in `[0, 1]`.
const PIXEL_MAX: f32 = 255.0;

/// LPIPS' `ScalingLayer` (per RGB channel, applied to pixels already in `[-1, 1]`): it maps the
/// LPIPS input range onto the ImageNet statistics AlexNet was trained with.
const SCALING_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALING_SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// LPIPS' `normalize_tensor` epsilon: keeps an all-zero feature vector (dead ReLUs) at zero
/// instead of dividing by zero.
const UNIT_NORMALIZE_EPS: f64 = 1e-10;

/// AlexNet's max-pool (torchvision `MaxPool2d(kernel_size=3, stride=2)`, floor mode).
const MAX_POOL_KERNEL: usize = 3;
const MAX_POOL_STRIDE: usize = 2;

/// RGB input channels of AlexNet's first convolution.
const INPUT_CHANNELS: usize = 3;

/// One convolution of torchvision AlexNet `features`, each followed by a ReLU that LPIPS taps.
struct ConvSpec {
    /// Index of the layer in torchvision's `features` Sequential: names the weight/bias keys.
    features_index: usize,
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    /// Whether a max-pool sits between the previous tap and this convolution.
    max_pool_before: bool,
}

/// torchvision AlexNet `features` (convolutions 1..5, in order).
const ALEXNET_CONVS: [ConvSpec; FEATURE_LAYER_COUNT] = [
    ConvSpec {
        features_index: 0,
        in_channels: INPUT_CHANNELS,
        out_channels: 64,
        kernel: 11,
        stride: 4,
        padding: 2,
        max_pool_before: false,
    },
    ConvSpec {
        features_index: 3,
        in_channels: 64,
        out_channels: 192,
        kernel: 5,
        stride: 1,
        padding: 2,
        max_pool_before: true,
    },
    ConvSpec {
        features_index: 6,
        in_channels: 192,
        out_channels: 384,
        kernel: 3,
        stride: 1,
        padding: 1,
        max_pool_before: true,
    },
    ConvSpec {
        features_index: 8,
        in_channels: 384,
        out_channels: 256,
        kernel: 3,
        stride: 1,
        padding: 1,
        max_pool_before: false,
    },
    ConvSpec {
        features_index: 10,
        in_channels: 256,
        out_channels: 256,
        kernel: 3,
        stride: 1,
        padding: 1,
        max_pool_before: false,
    },
];

impl ConvSpec {
    fn weight_key(&self) -> String {
        format!("features.{}.weight", self.features_index)
    }

    fn bias_key(&self) -> String {
        format!("features.{}.bias", self.features_index)
    }

    fn weight_shape(&self) -> Vec<usize> {
        vec![
            self.out_channels,
            self.in_channels,
            self.kernel,
            self.kernel,
        ]
    }
}

/// Key of the LPIPS linear head for tap `tap_index` (0-based), as in the LPIPS state dict
/// (`lin{i}.model` is `Sequential(Dropout, Conv2d 1x1)`, hence `.1.`).
fn linear_head_key(tap_index: usize) -> String {
    format!("lin{tap_index}.model.1.weight")
}

/// Side length of the relu5 feature map for an input side, or `None` when some layer's window
/// no longer fits (the image is smaller than AlexNet's receptive field).
fn final_feature_side(image_side: usize) -> Option<usize> {
    let mut side = image_side;
    for conv in &ALEXNET_CONVS {
        if conv.max_pool_before {
            side = side.checked_sub(MAX_POOL_KERNEL)? / MAX_POOL_STRIDE + 1;
        }
        side = (side + 2 * conv.padding).checked_sub(conv.kernel)? / conv.stride + 1;
    }
    Some(side)
}

/// Why LPIPS could not be loaded or evaluated.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    /// The weights file is absent, unreadable, not a zip/npz, or an array in it is corrupt.
    #[error("cannot read LPIPS weights file {}: {source}", path.display())]
    ReadWeights {
        /// The weights file.
        path: PathBuf,
        /// candle's error from opening or decoding it.
        #[source]
        source: candle_core::Error,
    },
    /// A required array is not in the weights file.
    #[error("LPIPS weights file {} has no array named `{key}`", path.display())]
    MissingKey {
        /// The weights file.
        path: PathBuf,
        /// The array's name (e.g. `features.0.weight`, `lin0.model.1.weight`).
        key: String,
    },
    /// A required array has the wrong shape (e.g. weights of another network).
    #[error(
        "LPIPS weights file {}: array `{key}` has shape {found:?}, expected {expected:?}",
        path.display()
    )]
    WrongShape {
        /// The weights file.
        path: PathBuf,
        /// The array's name.
        key: String,
        /// The shape this network needs (kernels OIHW, biases `[out]`, heads `[1, C, 1, 1]`).
        expected: Vec<usize>,
        /// The shape in the file.
        found: Vec<usize>,
    },
    /// A required array does not hold floating-point numbers.
    #[error(
        "LPIPS weights file {}: array `{key}` has element type {dtype:?}, expected floats",
        path.display()
    )]
    WrongElementType {
        /// The weights file.
        path: PathBuf,
        /// The array's name.
        key: String,
        /// The element type in the file.
        dtype: DType,
    },
    /// The two images given to [`Lpips::distance`] differ in size.
    #[error(
        "LPIPS compares images of the same size, got {first_width}x{first_height} and \
         {second_width}x{second_height}"
    )]
    SizeMismatch {
        /// Width of the first image, in pixels.
        first_width: u32,
        /// Height of the first image, in pixels.
        first_height: u32,
        /// Width of the second image, in pixels.
        second_width: u32,
        /// Height of the second image, in pixels.
        second_height: u32,
    },
    /// The image is smaller than AlexNet's receptive field.
    #[error(
        "image {width}x{height} is too small for LPIPS/AlexNet: both sides must be at least \
         {min_side} pixels"
    )]
    ImageTooSmall {
        /// The image's width, in pixels.
        width: u32,
        /// The image's height, in pixels.
        height: u32,
        /// The smallest side accepted, [`MIN_IMAGE_SIDE`] pixels.
        min_side: u32,
    },
    /// [`Lpips::conv_features`] was asked for a layer outside relu1..relu5.
    #[error(
        "AlexNet has no feature layer {layer}: layers are 1..={FEATURE_LAYER_COUNT} (relu1..relu5)"
    )]
    NoSuchLayer {
        /// The 1-based layer asked for.
        layer: usize,
    },
    /// A tensor operation failed while evaluating the network.
    #[error("LPIPS evaluation failed: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// Weights of one AlexNet convolution.
struct ConvWeights {
    /// `(out, in, kh, kw)`.
    kernel: Tensor,
    /// `(1, out, 1, 1)`, ready to broadcast over a `(batch, out, h, w)` feature map.
    bias: Tensor,
}

/// LPIPS v0.1 (AlexNet) perceptual distance, evaluated on the CPU with candle.
pub struct Lpips {
    convs: Vec<ConvWeights>,
    /// Per tap, the linear head's channel weights `(1, C, 1, 1)`.
    linear_heads: Vec<Tensor>,
    device: Device,
}

impl fmt::Debug for Lpips {
    // Tensor's Debug prints every value; a summary is what a log needs.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Lpips")
            .field("backbone", &"alexnet")
            .field("feature_layers", &self.convs.len())
            .field("device", &self.device)
            .finish()
    }
}

impl Lpips {
    /// Loads the AlexNet and linear-head weights from an `.npz` file with the keys
    /// `features.{0,3,6,8,10}.weight` / `.bias` (torchvision AlexNet, OIHW) and
    /// `lin{0..4}.model.1.weight` (`1 x C x 1 x 1`), as written by `scripts/get_lpips_weights.sh`.
    ///
    /// Errors name the file and, where it applies, the missing or mis-shaped array; a corrupt
    /// file gives [`LpipsError::ReadWeights`].
    pub fn load(weights: &Path) -> Result<Lpips, LpipsError> {
        let read_error = |source| LpipsError::ReadWeights {
            path: weights.to_path_buf(),
            source,
        };
        let archive = NpzTensors::new(weights).map_err(read_error)?;
        let device = Device::Cpu;

        let load_array =
            |key: &str, expected: &[usize]| -> Result<Tensor, LpipsError> {
                if !archive.names().iter().any(|name| name.as_str() == key) {
                    return Err(LpipsError::MissingKey {
                        path: weights.to_path_buf(),
                        key: key.to_owned(),
                    });
                }
                // Check the header before reading the data: a damaged header could otherwise ask
                // for an arbitrarily large allocation.
                let (shape, dtype) = archive.get_shape_and_dtype(key).map_err(read_error)?;
                if shape.dims() != expected {
                    return Err(LpipsError::WrongShape {
                        path: weights.to_path_buf(),
                        key: key.to_owned(),
                        expected: expected.to_vec(),
                        found: shape.dims().to_vec(),
                    });
                }
                if !dtype.is_float() {
                    return Err(LpipsError::WrongElementType {
                        path: weights.to_path_buf(),
                        key: key.to_owned(),
                        dtype,
                    });
                }
                let tensor = archive.get(key).map_err(read_error)?.ok_or_else(|| {
                    LpipsError::MissingKey {
                        path: weights.to_path_buf(),
                        key: key.to_owned(),
                    }
                })?;
                Ok(tensor.to_dtype(DType::F32)?.to_device(&device)?)
            };

        let mut convs = Vec::with_capacity(FEATURE_LAYER_COUNT);
        let mut linear_heads = Vec::with_capacity(FEATURE_LAYER_COUNT);
        for (tap_index, conv) in ALEXNET_CONVS.iter().enumerate() {
            let kernel = load_array(&conv.weight_key(), &conv.weight_shape())?;
            let bias = load_array(&conv.bias_key(), &[conv.out_channels])?;
            let bias = bias.reshape((1, conv.out_channels, 1, 1))?;
            convs.push(ConvWeights { kernel, bias });
            linear_heads.push(load_array(
                &linear_head_key(tap_index),
                &[1, conv.out_channels, 1, 1],
            )?);
        }
        Ok(Lpips {
            convs,
            linear_heads,
            device,
        })
    }

    /// LPIPS distance between two images of the same size (0 for identical images; about 0.1
    /// for a slight distortion, 0.7 for a strong one). Both sides must be at least
    /// [`MIN_IMAGE_SIDE`] pixels.
    pub fn distance(&self, a: &RgbImage, b: &RgbImage) -> Result<f64, LpipsError> {
        if a.dimensions() != b.dimensions() {
            return Err(LpipsError::SizeMismatch {
                first_width: a.width(),
                first_height: a.height(),
                second_width: b.width(),
                second_height: b.height(),
            });
        }
        check_image_size(a)?;

        // One batch of two: a single pass through the network for both images.
        let batch = self.network_input(&[a, b])?;
        let taps = self.relu_taps(&batch, FEATURE_LAYER_COUNT)?;
        let mut distance = 0.0_f64;
        for (tap, linear_head) in taps.iter().zip(&self.linear_heads) {
            let unit = unit_normalize_channels(tap)?;
            let squared_difference = (unit.narrow(0, 0, 1)? - unit.narrow(0, 1, 1)?)?.sqr()?;
            // The 1x1 head is a weighted sum over channels; its spatial mean is the layer's share.
            let layer_distance = squared_difference
                .broadcast_mul(linear_head)?
                .sum_keepdim(1)?
                .mean_all()?
                .to_scalar::<f32>()?;
            distance += f64::from(layer_distance);
        }
        Ok(distance)
    }

    /// The relu`layer` activation of AlexNet (`layer` is 1-based, 1..=5) for one image, shaped
    /// `(1, channels, h, w)` (channels 64, 192, 384, 256, 256), computed on the same LPIPS-scaled
    /// input as [`Lpips::distance`]. Meant as a pretrained image descriptor; pooling is up to the
    /// caller.
    pub fn conv_features(&self, img: &RgbImage, layer: usize) -> Result<Tensor, LpipsError> {
        if !(1..=FEATURE_LAYER_COUNT).contains(&layer) {
            return Err(LpipsError::NoSuchLayer { layer });
        }
        check_image_size(img)?;
        let input = self.network_input(&[img])?;
        let mut taps = self.relu_taps(&input, layer)?;
        Ok(taps.swap_remove(layer - 1))
    }

    /// Images as a `(batch, 3, h, w)` tensor in AlexNet's input space: `[0, 255]` -> `[-1, 1]`
    /// -> LPIPS scaling layer. All images must have the same size.
    fn network_input(&self, images: &[&RgbImage]) -> Result<Tensor, LpipsError> {
        let (width, height) = images[0].dimensions();
        let plane = width as usize * height as usize;
        let mut values = vec![0.0_f32; images.len() * INPUT_CHANNELS * plane];
        for (image, image_values) in images
            .iter()
            .zip(values.chunks_exact_mut(INPUT_CHANNELS * plane))
        {
            for (pixel_index, pixel) in image.pixels().enumerate() {
                for channel in 0..INPUT_CHANNELS {
                    let unit_range = f32::from(pixel[channel]) / PIXEL_MAX;
                    let symmetric_range = 2.0 * unit_range - 1.0;
                    image_values[channel * plane + pixel_index] =
                        (symmetric_range - SCALING_SHIFT[channel]) / SCALING_SCALE[channel];
                }
            }
        }
        let shape = (
            images.len(),
            INPUT_CHANNELS,
            height as usize,
            width as usize,
        );
        Ok(Tensor::from_vec(values, shape, &self.device)?)
    }

    /// Runs AlexNet `features` up to relu`last_layer` and returns relu1..relu`last_layer`.
    fn relu_taps(&self, input: &Tensor, last_layer: usize) -> Result<Vec<Tensor>, LpipsError> {
        let mut taps = Vec::with_capacity(last_layer);
        let mut activation = input.clone();
        for (spec, weights) in ALEXNET_CONVS.iter().zip(&self.convs).take(last_layer) {
            if spec.max_pool_before {
                activation = activation.max_pool2d_with_stride(MAX_POOL_KERNEL, MAX_POOL_STRIDE)?;
            }
            // dilation 1, groups 1: plain torchvision Conv2d.
            activation = activation
                .conv2d(&weights.kernel, spec.padding, spec.stride, 1, 1)?
                .broadcast_add(&weights.bias)?
                .relu()?;
            taps.push(activation.clone());
        }
        Ok(taps)
    }
}

/// Refuses images smaller than AlexNet's receptive field, before candle reports it obscurely.
fn check_image_size(image: &RgbImage) -> Result<(), LpipsError> {
    let (width, height) = image.dimensions();
    if final_feature_side(width as usize).is_none() || final_feature_side(height as usize).is_none()
    {
        return Err(LpipsError::ImageTooSmall {
            width,
            height,
            min_side: MIN_IMAGE_SIDE,
        });
    }
    Ok(())
}

/// Scales each spatial feature vector of a `(batch, C, h, w)` map to unit length over `C`
/// (LPIPS `normalize_tensor`: `x / (|x| + eps)`).
fn unit_normalize_channels(features: &Tensor) -> Result<Tensor, LpipsError> {
    let norm = features
        .sqr()?
        .sum_keepdim(1)?
        .sqrt()?
        .affine(1.0, UNIT_NORMALIZE_EPS)?;
    Ok(features.broadcast_div(&norm)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use datasets::shared_data;

    /// Every array `alexnet.npz` must hold, with its shape (the keys and shapes `load` checks).
    fn expected_weight_arrays() -> Vec<(String, Vec<usize>)> {
        let mut arrays = Vec::with_capacity(3 * FEATURE_LAYER_COUNT);
        for (tap_index, conv) in ALEXNET_CONVS.iter().enumerate() {
            arrays.push((conv.weight_key(), conv.weight_shape()));
            arrays.push((conv.bias_key(), vec![conv.out_channels]));
            arrays.push((linear_head_key(tap_index), vec![1, conv.out_channels, 1, 1]));
        }
        arrays
    }

    /// LPIPS project's example images and the distances it publishes for them (AlexNet, v0.1).
    const GOLDEN_TOLERANCE: f64 = 1e-3;
    const GOLDEN_REF_VS_P0: f64 = 0.722;
    const GOLDEN_REF_VS_P1: f64 = 0.138;

    fn real_weights() -> Lpips {
        let path = shared_data::require("weights/lpips/alexnet.npz");
        Lpips::load(&path).expect("load the shared LPIPS weights")
    }

    fn example_image(name: &str) -> RgbImage {
        let path = shared_data::require(&format!("weights/lpips/imgs/{name}.png"));
        image::open(&path)
            .unwrap_or_else(|e| panic!("decode {}: {e}", path.display()))
            .to_rgb8()
    }

    /// A deterministic, non-uniform test image.
    fn pattern_image(width: u32, height: u32, seed: u32) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| {
            let v = x.wrapping_mul(31) ^ y.wrapping_mul(17) ^ seed.wrapping_mul(101);
            image::Rgb([
                (v % 256) as u8,
                ((v / 3) % 256) as u8,
                ((v * 7) % 256) as u8,
            ])
        })
    }

    /// Small deterministic values of the given shape (not a trained network).
    fn synthetic_array(shape: &[usize]) -> Tensor {
        let count: usize = shape.iter().product();
        let values: Vec<f32> = (0..count).map(|i| ((i % 13) as f32 - 6.0) * 1e-3).collect();
        Tensor::from_vec(values, shape, &Device::Cpu).unwrap()
    }

    /// The first `count` arrays `load` reads, with synthetic values. Test files hold only a few
    /// arrays because candle's npz writer issues one write per element: a full 2.5M-parameter
    /// file takes seconds to write.
    fn leading_weight_arrays(count: usize) -> Vec<(String, Tensor)> {
        expected_weight_arrays()
            .into_iter()
            .take(count)
            .map(|(key, shape)| (key, synthetic_array(&shape)))
            .collect()
    }

    /// A network with synthetic weights, built in memory, for tests of the forward pass and its
    /// input checks.
    fn synthetic_lpips() -> Lpips {
        let convs = ALEXNET_CONVS
            .iter()
            .map(|conv| ConvWeights {
                kernel: synthetic_array(&conv.weight_shape()),
                bias: synthetic_array(&[1, conv.out_channels, 1, 1]),
            })
            .collect();
        let linear_heads = ALEXNET_CONVS
            .iter()
            .map(|conv| {
                synthetic_array(&[1, conv.out_channels, 1, 1])
                    .abs()
                    .unwrap()
            })
            .collect();
        Lpips {
            convs,
            linear_heads,
            device: Device::Cpu,
        }
    }

    #[test]
    fn real_data_lpips_matches_published_golden_values() {
        let lpips = real_weights();
        let reference = example_image("ex_ref");
        let p0 = lpips.distance(&reference, &example_image("ex_p0")).unwrap();
        let p1 = lpips.distance(&reference, &example_image("ex_p1")).unwrap();
        println!("LPIPS(ex_ref, ex_p0) = {p0:.4}, LPIPS(ex_ref, ex_p1) = {p1:.4}");
        assert!(
            (p0 - GOLDEN_REF_VS_P0).abs() <= GOLDEN_TOLERANCE,
            "ex_p0: {p0}"
        );
        assert!(
            (p1 - GOLDEN_REF_VS_P1).abs() <= GOLDEN_TOLERANCE,
            "ex_p1: {p1}"
        );
    }

    #[test]
    fn real_data_lpips_of_identical_images_is_zero_and_distance_is_symmetric() {
        let lpips = real_weights();
        let reference = example_image("ex_ref");
        let distorted = example_image("ex_p1");
        let same = lpips.distance(&reference, &reference.clone()).unwrap();
        assert!(same.abs() < 1e-6, "LPIPS(x, x) = {same}");
        let forward = lpips.distance(&reference, &distorted).unwrap();
        let backward = lpips.distance(&distorted, &reference).unwrap();
        assert!((forward - backward).abs() < 1e-6, "{forward} vs {backward}");
    }

    #[test]
    fn real_data_lpips_conv_features_are_relu_activations() {
        let lpips = real_weights();
        let features = lpips.conv_features(&example_image("ex_ref"), 3).unwrap();
        assert_eq!(features.dims(), &[1, 384, 3, 3]);
        let min = features.flatten_all().unwrap().min(0).unwrap();
        assert!(
            min.to_scalar::<f32>().unwrap() >= 0.0,
            "ReLU output is never negative"
        );
        let max = features.flatten_all().unwrap().max(0).unwrap();
        assert!(
            max.to_scalar::<f32>().unwrap() > 0.0,
            "a real image activates some unit"
        );
    }

    #[test]
    fn load_names_the_missing_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing.npz");
        // features.0.{weight,bias} and lin0 are present; features.3.weight, read next, is not.
        Tensor::write_npz(&leading_weight_arrays(3), &path).unwrap();
        let error = Lpips::load(&path).unwrap_err();
        assert!(
            matches!(&error, LpipsError::MissingKey { key, .. } if key == "features.3.weight"),
            "{error:?}"
        );
        let message = error.to_string();
        assert!(message.contains("`features.3.weight`"), "{message}");
        assert!(message.contains("missing.npz"), "{message}");
    }

    #[test]
    fn load_names_the_mis_shaped_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("misshaped.npz");
        let mut arrays = leading_weight_arrays(2);
        arrays.push((
            "lin0.model.1.weight".to_owned(),
            synthetic_array(&[1, 63, 1, 1]),
        ));
        Tensor::write_npz(&arrays, &path).unwrap();
        let error = Lpips::load(&path).unwrap_err();
        match &error {
            LpipsError::WrongShape {
                key,
                expected,
                found,
                ..
            } => {
                assert_eq!(key, "lin0.model.1.weight");
                assert_eq!(expected, &[1, 64, 1, 1]);
                assert_eq!(found, &[1, 63, 1, 1]);
            }
            other => panic!("expected WrongShape, got {other:?}"),
        }
        let message = error.to_string();
        assert!(message.contains("`lin0.model.1.weight`"), "{message}");
        assert!(message.contains("misshaped.npz"), "{message}");
    }

    #[test]
    fn load_rejects_integer_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("integers.npz");
        let (key, shape) = expected_weight_arrays().swap_remove(0);
        let integers = Tensor::zeros(shape, DType::U8, &Device::Cpu).unwrap();
        Tensor::write_npz(&[(key, integers)], &path).unwrap();
        let error = Lpips::load(&path).unwrap_err();
        assert!(
            matches!(&error, LpipsError::WrongElementType { key, .. } if key == "features.0.weight"),
            "{error:?}"
        );
    }

    #[test]
    fn load_reports_corrupt_and_absent_files_without_panicking() {
        let dir = tempfile::tempdir().unwrap();

        let garbage = dir.path().join("garbage.npz");
        std::fs::write(&garbage, b"this is not a zip archive at all").unwrap();
        let error = Lpips::load(&garbage).unwrap_err();
        assert!(matches!(error, LpipsError::ReadWeights { .. }), "{error:?}");
        assert!(error.to_string().contains("garbage.npz"), "{error}");

        // A valid archive cut short: the directory at the end of the zip is gone.
        let complete = dir.path().join("complete.npz");
        Tensor::write_npz(&leading_weight_arrays(3), &complete).unwrap();
        let bytes = std::fs::read(&complete).unwrap();
        let truncated = dir.path().join("truncated.npz");
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
        let error = Lpips::load(&truncated).unwrap_err();
        assert!(matches!(error, LpipsError::ReadWeights { .. }), "{error:?}");

        // Damaged array headers and data behind an intact zip directory.
        let mut scrambled_bytes = bytes.clone();
        scrambled_bytes[40..4096].fill(0xA5);
        let scrambled = dir.path().join("scrambled.npz");
        std::fs::write(&scrambled, &scrambled_bytes).unwrap();
        assert!(Lpips::load(&scrambled).is_err());

        let absent = dir.path().join("absent.npz");
        let error = Lpips::load(&absent).unwrap_err();
        assert!(matches!(error, LpipsError::ReadWeights { .. }), "{error:?}");
        assert!(error.to_string().contains("absent.npz"), "{error}");
    }

    #[test]
    fn min_image_side_is_the_smallest_side_alexnet_accepts() {
        let min_side = MIN_IMAGE_SIDE as usize;
        assert!(final_feature_side(min_side).is_some());
        assert!((1..min_side).all(|side| final_feature_side(side).is_none()));
    }

    #[test]
    fn distance_rejects_images_of_different_sizes() {
        let lpips = synthetic_lpips();
        let error = lpips
            .distance(&pattern_image(64, 48, 1), &pattern_image(48, 64, 1))
            .unwrap_err();
        assert!(
            matches!(error, LpipsError::SizeMismatch { .. }),
            "{error:?}"
        );
        assert!(error.to_string().contains("64x48 and 48x64"), "{error}");
    }

    #[test]
    fn distance_rejects_images_smaller_than_the_receptive_field() {
        let lpips = synthetic_lpips();
        let narrow = pattern_image(MIN_IMAGE_SIDE - 1, 64, 1);
        let error = lpips.distance(&narrow, &narrow).unwrap_err();
        assert!(
            matches!(error, LpipsError::ImageTooSmall { .. }),
            "{error:?}"
        );
        assert!(error.to_string().contains("at least 31 pixels"), "{error}");

        let smallest = pattern_image(MIN_IMAGE_SIDE, MIN_IMAGE_SIDE, 1);
        let other = pattern_image(MIN_IMAGE_SIDE, MIN_IMAGE_SIDE, 2);
        let distance = lpips.distance(&smallest, &other).unwrap();
        assert!(distance.is_finite() && distance >= 0.0, "{distance}");
    }

    #[test]
    fn conv_features_have_alexnet_shapes_and_reject_unknown_layers() {
        let lpips = synthetic_lpips();
        let image = pattern_image(64, 64, 3);
        let expected = [
            [1, 64, 15, 15],
            [1, 192, 7, 7],
            [1, 384, 3, 3],
            [1, 256, 3, 3],
            [1, 256, 3, 3],
        ];
        for (layer, shape) in (1..=FEATURE_LAYER_COUNT).zip(expected) {
            let features = lpips.conv_features(&image, layer).unwrap();
            assert_eq!(features.dims(), &shape, "relu{layer}");
        }
        for layer in [0, FEATURE_LAYER_COUNT + 1] {
            let error = lpips.conv_features(&image, layer).unwrap_err();
            assert!(matches!(error, LpipsError::NoSuchLayer { .. }), "{error:?}");
        }
        let error = lpips
            .conv_features(&pattern_image(20, 64, 3), 1)
            .unwrap_err();
        assert!(
            matches!(error, LpipsError::ImageTooSmall { .. }),
            "{error:?}"
        );
    }
}
