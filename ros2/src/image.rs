//! Camera images from ROS 2 messages: colour as 8-bit RGB, depth in metres (0 = no depth), from
//! raw `sensor_msgs/Image` or from `sensor_msgs/CompressedImage` (JPEG or PNG colour; PNG depth
//! in compressed_depth_image_transport's `compressedDepth` format).
//!
//! Colour encodings: rgb8, bgr8, rgba8, bgra8, mono8. Depth encodings: 16UC1 (and mono16) in
//! millimetres, 32FC1 in metres (NaN and infinities become "no depth"). Any other encoding, a
//! buffer shorter than `step * height`, or a `step` shorter than a row is refused with a message
//! that says which.

use geometry::depth::DepthImage;
use image::RgbImage;

use crate::msg::{CompressedImage, Image};

/// Why an image message cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImageError {
    /// A raw colour image in another encoding (the message's `encoding`).
    #[error(
        "encoding {0:?} is not a colour encoding this reader knows (rgb8, bgr8, rgba8, bgra8, mono8)"
    )]
    ColourEncoding(String),
    /// A raw depth image in another encoding (the message's `encoding`).
    #[error(
        "encoding {0:?} is not a depth encoding this reader knows (16UC1 or mono16 in millimetres, 32FC1 in metres)"
    )]
    DepthEncoding(String),
    /// `step` is shorter than one row of pixels.
    #[error("{width}x{height} {encoding} needs rows of at least {row} bytes, but step is {step}")]
    Step {
        /// The message's width, pixels.
        width: u32,
        /// The message's height, pixels.
        height: u32,
        /// The message's encoding.
        encoding: String,
        /// Bytes one row of pixels takes: width times the encoding's pixel size.
        row: usize,
        /// The message's row length, bytes.
        step: u32,
    },
    /// `data` is too short for the rows: a message cut short, or a wrong size or step.
    #[error("{width}x{height} with step {step} needs {needed} bytes, the message carries {found}")]
    DataLength {
        /// The message's width, pixels.
        width: u32,
        /// The message's height, pixels.
        height: u32,
        /// The message's row length, bytes.
        step: u32,
        /// Bytes the rows need: `step` per row but the last, which need not carry its padding.
        needed: usize,
        /// Bytes in `data`.
        found: usize,
    },
    /// A width or a height of 0: an image without pixels.
    #[error("an image of size 0x0")]
    Empty,
    /// A compressed image whose `format` this reader does not decode for the kind asked:
    /// colour takes JPEG or PNG, depth compressedDepth or a 16-bit PNG (the message's
    /// `format`).
    #[error(
        "compressed format {0:?} is not one this reader knows (jpeg, png, or '16UC1; compressedDepth png')"
    )]
    Format(String),
    /// The compressed bytes do not decode (the decoder's message, or why they were refused:
    /// a JPEG cut short, compressedDepth without its 12-byte header, a depth PNG that is not
    /// 16-bit grey).
    #[error("cannot decode the compressed image: {0}")]
    Codec(String),
}

/// Reads one pixel of a colour encoding as RGB.
type ColourPixel = fn(&[u8]) -> [u8; 3];
/// Reads one depth pixel as metres, given the message's byte order (true: big endian).
type DepthPixel = fn(&[u8], bool) -> f32;

/// Bytes per pixel of a colour encoding, and how to read one pixel as RGB.
fn colour_layout(encoding: &str) -> Option<(usize, ColourPixel)> {
    Some(match encoding {
        "rgb8" => (3, |p| [p[0], p[1], p[2]]),
        "bgr8" => (3, |p| [p[2], p[1], p[0]]),
        "rgba8" => (4, |p| [p[0], p[1], p[2]]),
        "bgra8" => (4, |p| [p[2], p[1], p[0]]),
        "mono8" => (1, |p| [p[0], p[0], p[0]]),
        _ => return None,
    })
}

/// Checks that `step` holds a row and `data` holds `height` rows; the first row's byte count.
fn check_rows(image: &Image, bytes_per_pixel: usize) -> Result<usize, ImageError> {
    if image.width == 0 || image.height == 0 {
        return Err(ImageError::Empty);
    }
    let row = image.width as usize * bytes_per_pixel;
    if (image.step as usize) < row {
        return Err(ImageError::Step {
            width: image.width,
            height: image.height,
            encoding: image.encoding.clone(),
            row,
            step: image.step,
        });
    }
    // The last row need not carry its padding.
    let needed = image.step as usize * (image.height as usize - 1) + row;
    if image.data.len() < needed {
        return Err(ImageError::DataLength {
            width: image.width,
            height: image.height,
            step: image.step,
            needed,
            found: image.data.len(),
        });
    }
    Ok(row)
}

/// A raw colour image as RGB.
pub fn colour_from_image(image: &Image) -> Result<RgbImage, ImageError> {
    let (bytes_per_pixel, pixel) = colour_layout(&image.encoding)
        .ok_or_else(|| ImageError::ColourEncoding(image.encoding.clone()))?;
    let row = check_rows(image, bytes_per_pixel)?;
    let mut rgb = Vec::with_capacity(image.width as usize * image.height as usize * 3);
    for y in 0..image.height as usize {
        let start = y * image.step as usize;
        let pixels = &image.data[start..start + row];
        if image.encoding == "rgb8" {
            // Already the layout wanted: one copy per row.
            rgb.extend_from_slice(pixels);
        } else {
            rgb.extend(pixels.chunks_exact(bytes_per_pixel).flat_map(pixel));
        }
    }
    Ok(RgbImage::from_raw(image.width, image.height, rgb).expect("buffer sized above"))
}

/// A raw depth image in metres.
pub fn depth_from_image(image: &Image) -> Result<DepthImage, ImageError> {
    let big_endian = image.is_bigendian != 0;
    let (bytes_per_pixel, to_metres): (usize, DepthPixel) = match image.encoding.as_str() {
        "16UC1" | "mono16" => (2, |p, big| {
            let raw = if big {
                u16::from_be_bytes([p[0], p[1]])
            } else {
                u16::from_le_bytes([p[0], p[1]])
            };
            (raw as f64 / 1000.0) as f32
        }),
        "32FC1" => (4, |p, big| {
            let bytes = [p[0], p[1], p[2], p[3]];
            let metres = if big {
                f32::from_be_bytes(bytes)
            } else {
                f32::from_le_bytes(bytes)
            };
            if metres.is_finite() && metres > 0.0 {
                metres
            } else {
                0.0
            }
        }),
        other => return Err(ImageError::DepthEncoding(other.to_string())),
    };
    let row = check_rows(image, bytes_per_pixel)?;
    let mut depth = Vec::with_capacity(image.width as usize * image.height as usize);
    for y in 0..image.height as usize {
        let start = y * image.step as usize;
        for p in image.data[start..start + row].chunks_exact(bytes_per_pixel) {
            depth.push(to_metres(p, big_endian));
        }
    }
    Ok(DepthImage {
        width: image.width,
        height: image.height,
        data: depth,
    })
}

/// A JPEG or PNG colour image (the `format` string names the codec; the bytes decide).
pub fn colour_from_compressed(image: &CompressedImage) -> Result<RgbImage, ImageError> {
    let format = image.format.to_ascii_lowercase();
    if format.contains("compresseddepth") {
        return Err(ImageError::Format(image.format.clone()));
    }
    if !(format.contains("jpeg") || format.contains("jpg") || format.contains("png")) {
        return Err(ImageError::Format(image.format.clone()));
    }
    if is_truncated_jpeg(&image.data) {
        return Err(ImageError::Codec(
            "JPEG without its end-of-image marker: the message is cut short".into(),
        ));
    }
    let decoded =
        image::load_from_memory(&image.data).map_err(|e| ImageError::Codec(e.to_string()))?;
    Ok(decoded.to_rgb8())
}

/// A depth image from compressed_depth_image_transport: a 12-byte header (the format enum and
/// two quantisation parameters) then a PNG. `16UC1` depth is the PNG's millimetres; `32FC1`
/// depth was stored as quantised inverse depth, `metres = a / (value - b)`.
pub fn depth_from_compressed(image: &CompressedImage) -> Result<DepthImage, ImageError> {
    let format = image.format.to_ascii_lowercase();
    if !format.contains("compresseddepth") {
        if format.contains("png") {
            // A plain 16-bit PNG of millimetres (image_transport's png plugin).
            return depth_from_png(&image.data, None);
        }
        return Err(ImageError::Format(image.format.clone()));
    }
    const HEADER: usize = 12;
    const PNG_MAGIC: &[u8] = &[0x89, b'P', b'N', b'G'];
    if image.data.len() < HEADER + PNG_MAGIC.len() || &image.data[HEADER..HEADER + 4] != PNG_MAGIC {
        return Err(ImageError::Codec(
            "compressedDepth data is not a 12-byte header followed by a PNG".into(),
        ));
    }
    let quantisation = if format.starts_with("32fc1") {
        let a = f32::from_le_bytes(image.data[4..8].try_into().expect("4 bytes"));
        let b = f32::from_le_bytes(image.data[8..12].try_into().expect("4 bytes"));
        Some((a, b))
    } else {
        None
    };
    depth_from_png(&image.data[HEADER..], quantisation)
}

fn depth_from_png(bytes: &[u8], inverse: Option<(f32, f32)>) -> Result<DepthImage, ImageError> {
    let decoded = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| ImageError::Codec(e.to_string()))?;
    let image::DynamicImage::ImageLuma16(raw) = decoded else {
        return Err(ImageError::Codec(format!(
            "depth PNG must be 16-bit single channel, found {:?}",
            decoded.color()
        )));
    };
    let (width, height) = raw.dimensions();
    let data = raw
        .into_raw()
        .into_iter()
        .map(|value| match (value, inverse) {
            (0, _) => 0.0,
            (value, None) => (value as f64 / 1000.0) as f32,
            (value, Some((a, b))) => {
                let metres = a / (value as f32 - b);
                if metres.is_finite() && metres > 0.0 {
                    metres
                } else {
                    0.0
                }
            }
        })
        .collect();
    Ok(DepthImage {
        width,
        height,
        data,
    })
}

/// A JPEG (starts with the SOI marker) that does not end with the EOI marker `FF D9` (trailing
/// zero padding allowed). The JPEG decoder fills a cut-short file's missing rows with grey
/// instead of failing, which would hand tracking and mapping an image that is partly made up.
/// The one check of this, for dataset files and image messages alike.
pub fn is_truncated_jpeg(bytes: &[u8]) -> bool {
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return false;
    }
    let end = bytes.iter().rposition(|b| *b != 0).map_or(0, |i| i + 1);
    !bytes[..end].ends_with(&[0xFF, 0xD9])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::Header;

    fn raw(encoding: &str, width: u32, height: u32, step: u32, data: &[u8]) -> Image {
        Image {
            header: Header::default(),
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data: data.to_vec(),
        }
    }

    #[test]
    fn colour_encodings_give_the_same_rgb() {
        // 2x1 pixels: red-ish then blue-ish, rows padded to 8 bytes.
        let rgb =
            colour_from_image(&raw("rgb8", 2, 1, 8, &[10, 20, 30, 40, 50, 60, 0, 0])).unwrap();
        let bgr = colour_from_image(&raw("bgr8", 2, 1, 6, &[30, 20, 10, 60, 50, 40])).unwrap();
        let bgra =
            colour_from_image(&raw("bgra8", 2, 1, 8, &[30, 20, 10, 255, 60, 50, 40, 255])).unwrap();
        assert_eq!(rgb, bgr);
        assert_eq!(rgb, bgra);
        assert_eq!(rgb.get_pixel(1, 0).0, [40, 50, 60]);
        let mono = colour_from_image(&raw("mono8", 2, 1, 2, &[7, 9])).unwrap();
        assert_eq!(mono.get_pixel(1, 0).0, [9, 9, 9]);
    }

    #[test]
    fn depth_encodings_are_metres() {
        let mm = 1234u16.to_le_bytes();
        let d16 = depth_from_image(&raw("16UC1", 2, 1, 4, &[mm[0], mm[1], 0, 0])).unwrap();
        assert_eq!(d16.data, vec![1.234, 0.0]);
        let mut bytes = 1.5f32.to_le_bytes().to_vec();
        bytes.extend_from_slice(&f32::NAN.to_le_bytes());
        let d32 = depth_from_image(&raw("32FC1", 2, 1, 8, &bytes)).unwrap();
        assert_eq!(d32.data, vec![1.5, 0.0]);
    }

    #[test]
    fn inconsistent_images_are_refused_with_the_reason() {
        let error = colour_from_image(&raw("yuv422", 2, 1, 4, &[0; 4])).unwrap_err();
        assert!(error.to_string().contains("yuv422"), "{error}");
        let error = colour_from_image(&raw("rgb8", 4, 2, 12, &[0; 20])).unwrap_err();
        assert!(
            matches!(
                error,
                ImageError::DataLength {
                    needed: 24,
                    found: 20,
                    ..
                }
            ),
            "{error}"
        );
        let error = depth_from_image(&raw("16UC1", 4, 2, 6, &[0; 16])).unwrap_err();
        assert!(
            matches!(
                error,
                ImageError::Step {
                    row: 8,
                    step: 6,
                    ..
                }
            ),
            "{error}"
        );
        let error = depth_from_image(&raw("rgb8", 1, 1, 3, &[0; 3])).unwrap_err();
        assert!(error.to_string().contains("rgb8"), "{error}");
    }

    #[test]
    fn compressed_depth_png_decodes_millimetres() {
        let png_depth: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
            image::ImageBuffer::from_raw(2, 1, vec![2500, 0]).unwrap();
        let mut png = Vec::new();
        png_depth
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let mut data = vec![0u8; 12];
        data.extend_from_slice(&png);
        let message = CompressedImage {
            header: Header::default(),
            format: "16UC1; compressedDepth png".into(),
            data: data.clone(),
        };
        assert_eq!(
            depth_from_compressed(&message).unwrap().data,
            vec![2.5, 0.0]
        );
        let cut = CompressedImage {
            data: data[..data.len() - 10].to_vec(),
            ..message.clone()
        };
        assert!(matches!(
            depth_from_compressed(&cut),
            Err(ImageError::Codec(_))
        ));
        let jpeg = CompressedImage {
            format: "jpeg".into(),
            data: vec![0xFF, 0xD8, 1, 2, 3],
            ..message
        };
        assert!(
            colour_from_compressed(&jpeg)
                .unwrap_err()
                .to_string()
                .contains("cut short")
        );
    }
}
