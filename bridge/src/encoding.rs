//! How an agent's bulk messages (Gaussian patches, keyframe images) are written on the network
//! when a bandwidth budget is set (docs/method.md, Across hosts: bandwidth budget). Every
//! encoding keeps the message's header as laid out in shared memory at the front, so the stamp
//! (and with it acknowledgements and ordering) reads the same; the consumer host's bridge decodes
//! back to the shared-memory layout before publishing, so the consensus never sees the
//! difference. The encoding travels in the zenoh attachment (one byte); no attachment is
//! [`Encoding::Raw`].
//!
//! From exact to smallest:
//! - `Raw`: the shared-memory bytes (no budget).
//! - `Lossless`: patches as byte planes of their records, zstd-compressed; images as a colour PNG
//!   and a 16-bit depth PNG. Decodes to the same bytes.
//! - `Compact`: patches without the Gaussians no pixel can show (opacity below 1/255, which the
//!   rasteriser never blends), the rest quantised to 25 bytes (mean as 16 bits per axis within
//!   the patch's bounding box, log-scales and opacity as f16, rotation as 16-bit snorm, colour
//!   as 8 bits), as byte planes, zstd-compressed; images with JPEG colour and lossless depth.
//! - `Reduced`: as `Compact`, and the image binned to half resolution (colour averaged over 2x2,
//!   depth averaged where the block is one surface and its nearest value where it is not), with
//!   the intrinsics binned to match (the header says the size the consensus gets).

use anyhow::{Context, Result, anyhow, bail, ensure};
use half::f16;
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ExtendedColorType, ImageEncoder, ImageFormat};
use protocol::messages::{
    GaussianRecord, Intrinsics, KeyframeImageHeader, PatchHeader, RgbdPixel, Stamp,
};
use protocol::services::Topic;
use protocol::transport::relay::RelayedMessage;
use serde::Serialize;

/// zstd level for the patch encodings: fast (hundreds of MB/s), most of the gain.
const ZSTD_LEVEL: i32 = 3;

/// Gaussians whose opacity is below this are never blended by the rasteriser (it skips alphas
/// below 1/255), so `Compact` and `Reduced` leave them out.
pub const NEAR_TRANSPARENT_OPACITY: f32 = 1.0 / 255.0;

/// An encoding of a message on the network, from exact to smallest.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Encoding {
    Raw = 0,
    Lossless = 1,
    Compact = 2,
    Reduced = 3,
}

impl Encoding {
    /// The encodings a capped agent's bulk messages choose from, least lossy first.
    pub const UNDER_A_CAP: [Encoding; 3] =
        [Encoding::Lossless, Encoding::Compact, Encoding::Reduced];

    pub fn tag(self) -> u8 {
        self as u8
    }

    pub fn from_tag(tag: u8) -> Result<Self> {
        match tag {
            0 => Ok(Self::Raw),
            1 => Ok(Self::Lossless),
            2 => Ok(Self::Compact),
            3 => Ok(Self::Reduced),
            _ => bail!("unknown network encoding tag {tag}"),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Raw => "raw",
            Self::Lossless => "lossless",
            Self::Compact => "compact",
            Self::Reduced => "reduced",
        }
    }

    /// Topics whose messages have encodings other than `Raw`.
    pub fn applies_to(topic: Topic) -> bool {
        matches!(topic, Topic::Patch | Topic::KeyframeImage)
    }
}

/// A relayed message as it goes on the network.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WireMessage {
    pub agent_id: u32,
    pub topic: Topic,
    /// The stamp the agent gave it (acknowledgements name it).
    pub stamp: Stamp,
    pub encoding: Encoding,
    pub bytes: Vec<u8>,
}

impl WireMessage {
    /// A message that crosses as laid out in shared memory.
    pub fn raw(message: RelayedMessage) -> Self {
        Self {
            agent_id: message.agent_id,
            topic: message.topic,
            stamp: message.stamp,
            encoding: Encoding::Raw,
            bytes: message.bytes,
        }
    }
}

/// What an encoding did to one message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Encoded {
    pub encoding: Encoding,
    pub bytes: Vec<u8>,
    /// Near-transparent Gaussians left out (patches under `Compact` and `Reduced`).
    pub gaussians_dropped: u64,
}

/// Encodes the shared-memory bytes `raw` of a `topic` message. Topics without encodings, and
/// `Encoding::Raw`, are returned as they are.
pub fn encode(topic: Topic, raw: &[u8], encoding: Encoding, jpeg_quality: u8) -> Result<Encoded> {
    let unchanged = || Encoded {
        encoding: Encoding::Raw,
        bytes: raw.to_vec(),
        gaussians_dropped: 0,
    };
    if encoding == Encoding::Raw || !Encoding::applies_to(topic) {
        return Ok(unchanged());
    }
    match topic {
        Topic::Patch => encode_patch(raw, encoding),
        Topic::KeyframeImage => encode_image(raw, encoding, jpeg_quality),
        _ => Ok(unchanged()),
    }
}

/// Decodes a message of `topic` received in `encoding` back to its shared-memory bytes.
pub fn decode(topic: Topic, encoding: Encoding, wire: &[u8]) -> Result<Vec<u8>> {
    if encoding == Encoding::Raw {
        return Ok(wire.to_vec());
    }
    match topic {
        Topic::Patch => decode_patch(wire, encoding),
        Topic::KeyframeImage => decode_image(wire),
        _ => bail!(
            "a {topic} message arrived in encoding {}, which it has not",
            encoding.name()
        ),
    }
}

// ---- Gaussian patches ----

/// Bytes of one quantised record (`Compact`, `Reduced`).
const QUANTISED_RECORD: usize = 6 + 6 + 8 + 2 + 3;

fn split_header<'a, H: bytemuck::Pod>(bytes: &'a [u8], what: &str) -> Result<(H, &'a [u8])> {
    let (header, rest) = bytes
        .split_at_checked(size_of::<H>())
        .ok_or_else(|| anyhow!("{what} of {} bytes is shorter than its header", bytes.len()))?;
    Ok((bytemuck::pod_read_unaligned(header), rest))
}

fn patch_records(raw: &[u8]) -> Result<(PatchHeader, Vec<GaussianRecord>)> {
    let (header, payload) = split_header::<PatchHeader>(raw, "patch")?;
    let record = size_of::<GaussianRecord>();
    ensure!(
        payload.len() % record == 0,
        "patch payload of {} bytes is not a whole number of {record}-byte records",
        payload.len()
    );
    let records = payload
        .chunks_exact(record)
        .map(bytemuck::pod_read_unaligned)
        .collect();
    Ok((header, records))
}

/// Byte `b` of every `record_size`-byte record together: the same byte of neighbouring records
/// is alike (exponents, high bytes), which is what the compressor finds.
fn to_planes(bytes: &[u8], record_size: usize) -> Vec<u8> {
    let count = bytes.len() / record_size;
    let mut planes = vec![0u8; bytes.len()];
    for (i, record) in bytes.chunks_exact(record_size).enumerate() {
        for (b, &byte) in record.iter().enumerate() {
            planes[b * count + i] = byte;
        }
    }
    planes
}

fn from_planes(planes: &[u8], record_size: usize) -> Vec<u8> {
    let count = planes.len() / record_size;
    let mut bytes = vec![0u8; planes.len()];
    for (b, plane) in planes
        .chunks_exact(count.max(1))
        .enumerate()
        .take(record_size)
    {
        for (i, &byte) in plane.iter().enumerate() {
            bytes[i * record_size + b] = byte;
        }
    }
    bytes
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn encode_patch(raw: &[u8], encoding: Encoding) -> Result<Encoded> {
    let (mut header, records) = patch_records(raw)?;
    let header_len = size_of::<PatchHeader>();
    if encoding == Encoding::Lossless {
        let planes = to_planes(&raw[header_len..], size_of::<GaussianRecord>());
        let mut bytes = raw[..header_len].to_vec();
        bytes.extend(zstd::bulk::compress(&planes, ZSTD_LEVEL).context("zstd")?);
        return Ok(Encoded {
            encoding,
            bytes,
            gaussians_dropped: 0,
        });
    }
    let kept: Vec<&GaussianRecord> = records
        .iter()
        .filter(|r| sigmoid(r.opacity_logit) >= NEAR_TRANSPARENT_OPACITY)
        .collect();
    let (mut low, mut high) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for record in &kept {
        for axis in 0..3 {
            low[axis] = low[axis].min(record.mean[axis]);
            high[axis] = high[axis].max(record.mean[axis]);
        }
    }
    if kept.is_empty() {
        (low, high) = ([0.0; 3], [0.0; 3]);
    }
    ensure!(
        low.iter().chain(&high).all(|v| v.is_finite()),
        "patch of keyframe {} has a non-finite mean",
        header.keyframe_id
    );
    let mut quantised = Vec::with_capacity(kept.len() * QUANTISED_RECORD);
    for record in &kept {
        for axis in 0..3 {
            let extent = high[axis] - low[axis];
            let unit = if extent > 0.0 {
                (record.mean[axis] - low[axis]) / extent
            } else {
                0.0
            };
            quantised.extend(((unit * 65535.0).round() as u16).to_le_bytes());
        }
        for &log_scale in &record.log_scale {
            quantised.extend(f16::from_f32(log_scale).to_le_bytes());
        }
        let norm = record
            .rotation_wxyz
            .iter()
            .map(|q| q * q)
            .sum::<f32>()
            .sqrt()
            .max(f32::MIN_POSITIVE);
        for &q in &record.rotation_wxyz {
            quantised.extend((((q / norm) * 32767.0).round() as i16).to_le_bytes());
        }
        quantised.extend(f16::from_f32(record.opacity_logit).to_le_bytes());
        for &c in &record.colour {
            quantised.push((c.clamp(0.0, 1.0) * 255.0).round() as u8);
        }
    }
    let gaussians_dropped = (records.len() - kept.len()) as u64;
    header.count = kept.len() as u64;
    let mut bytes = bytemuck::bytes_of(&header).to_vec();
    for v in low.iter().chain(&high) {
        bytes.extend(v.to_le_bytes());
    }
    let planes = to_planes(&quantised, QUANTISED_RECORD);
    bytes.extend(zstd::bulk::compress(&planes, ZSTD_LEVEL).context("zstd")?);
    Ok(Encoded {
        encoding,
        bytes,
        gaussians_dropped,
    })
}

fn decode_patch(wire: &[u8], encoding: Encoding) -> Result<Vec<u8>> {
    let (header, body) = split_header::<PatchHeader>(wire, "encoded patch")?;
    let count = usize::try_from(header.count).context("patch count")?;
    let mut raw = bytemuck::bytes_of(&header).to_vec();
    if encoding == Encoding::Lossless {
        let expected = count * size_of::<GaussianRecord>();
        let planes = zstd::bulk::decompress(body, expected).context("patch: zstd")?;
        ensure!(
            planes.len() == expected,
            "patch announces {count} records but decodes to {} bytes",
            planes.len()
        );
        raw.extend(from_planes(&planes, size_of::<GaussianRecord>()));
        return Ok(raw);
    }
    ensure!(body.len() >= 24, "encoded patch without its bounding box");
    let (bounds, compressed) = body.split_at(24);
    let bound = |i: usize| f32::from_le_bytes(bounds[i * 4..i * 4 + 4].try_into().unwrap());
    let (low, high) = (
        [bound(0), bound(1), bound(2)],
        [bound(3), bound(4), bound(5)],
    );
    let expected = count * QUANTISED_RECORD;
    let planes = zstd::bulk::decompress(compressed, expected).context("patch: zstd")?;
    ensure!(
        planes.len() == expected,
        "patch announces {count} records but decodes to {} bytes",
        planes.len()
    );
    let quantised = from_planes(&planes, QUANTISED_RECORD);
    raw.reserve(count * size_of::<GaussianRecord>());
    for q in quantised.chunks_exact(QUANTISED_RECORD) {
        let u16_at = |at: usize| u16::from_le_bytes([q[at], q[at + 1]]);
        let f16_at = |at: usize| f16::from_bits(u16_at(at)).to_f32();
        let mut record = GaussianRecord::default();
        for axis in 0..3 {
            let unit = f32::from(u16_at(axis * 2)) / 65535.0;
            record.mean[axis] = low[axis] + unit * (high[axis] - low[axis]);
            record.log_scale[axis] = f16_at(6 + axis * 2);
        }
        let rotation: Vec<f32> = (0..4)
            .map(|i| f32::from(u16_at(12 + i * 2) as i16) / 32767.0)
            .collect();
        let norm = rotation.iter().map(|v| v * v).sum::<f32>().sqrt();
        for (i, v) in rotation.iter().enumerate() {
            record.rotation_wxyz[i] = if norm > 0.0 {
                v / norm
            } else {
                f32::from(i == 0)
            };
        }
        record.opacity_logit = f16_at(20);
        for c in 0..3 {
            record.colour[c] = f32::from(q[22 + c]) / 255.0;
        }
        raw.extend(bytemuck::bytes_of(&record));
    }
    Ok(raw)
}

// ---- keyframe images ----

fn image_pixels(raw: &[u8]) -> Result<(KeyframeImageHeader, Vec<RgbdPixel>)> {
    let (header, payload) = split_header::<KeyframeImageHeader>(raw, "keyframe image")?;
    let pixel = size_of::<RgbdPixel>();
    let expected = usize::try_from(header.pixel_count()).context("image size")? * pixel;
    ensure!(
        payload.len() == expected,
        "keyframe image {} announces {}x{} pixels but carries {} bytes",
        header.keyframe_id,
        header.width,
        header.height,
        payload.len()
    );
    Ok((
        header,
        payload
            .chunks_exact(pixel)
            .map(bytemuck::pod_read_unaligned)
            .collect(),
    ))
}

/// Colour averaged over 2x2 blocks; depth averaged where the block's valid depths lie within
/// 2 % of each other (one surface), else its nearest valid depth (no value between two
/// surfaces); a partial last row or column dropped, as `Intrinsics` binning does.
fn binned(width: u32, height: u32, pixels: &[RgbdPixel]) -> (u32, u32, Vec<RgbdPixel>) {
    let (w, h) = (width / 2, height / 2);
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let block = [(0, 0), (1, 0), (0, 1), (1, 1)]
                .map(|(dx, dy)| pixels[((2 * y + dy) * width + 2 * x + dx) as usize]);
            let mut rgb = [0u8; 3];
            for (c, value) in rgb.iter_mut().enumerate() {
                let sum: u32 = block.iter().map(|p| u32::from(p.rgb[c])).sum();
                *value = ((sum + 2) / 4) as u8;
            }
            let depths: Vec<u16> = block
                .iter()
                .map(|p| p.depth_mm)
                .filter(|&d| d != RgbdPixel::INVALID_DEPTH_MM)
                .collect();
            let depth_mm = match (depths.iter().min(), depths.iter().max()) {
                (Some(&near), Some(&far)) if f32::from(far - near) <= 0.02 * f32::from(near) => {
                    let sum: u32 = depths.iter().map(|&d| u32::from(d)).sum();
                    ((sum as f32) / depths.len() as f32).round() as u16
                }
                (Some(&near), _) => near,
                _ => RgbdPixel::INVALID_DEPTH_MM,
            };
            out.push(RgbdPixel {
                rgb,
                reserved: 0,
                depth_mm,
            });
        }
    }
    (w, h, out)
}

fn binned_intrinsics(k: &Intrinsics, width: u32, height: u32) -> Intrinsics {
    Intrinsics {
        fx: k.fx / 2.0,
        fy: k.fy / 2.0,
        cx: (k.cx + 0.5) / 2.0 - 0.5,
        cy: (k.cy + 0.5) / 2.0 - 0.5,
        width,
        height,
    }
}

fn encode_image(raw: &[u8], encoding: Encoding, jpeg_quality: u8) -> Result<Encoded> {
    let (mut header, mut pixels) = image_pixels(raw)?;
    if encoding == Encoding::Reduced && header.width >= 2 && header.height >= 2 {
        let (w, h, half) = binned(header.width, header.height, &pixels);
        header.intrinsics = binned_intrinsics(&header.intrinsics, w, h);
        (header.width, header.height, pixels) = (w, h, half);
    }
    let (width, height) = (header.width, header.height);
    let rgb: Vec<u8> = pixels.iter().flat_map(|p| p.rgb).collect();
    let depth: Vec<u8> = pixels
        .iter()
        .flat_map(|p| p.depth_mm.to_ne_bytes())
        .collect();
    let mut colour = Vec::new();
    if encoding == Encoding::Lossless {
        PngEncoder::new_with_quality(&mut colour, CompressionType::Fast, FilterType::Adaptive)
            .write_image(&rgb, width, height, ExtendedColorType::Rgb8)
            .context("keyframe colour as PNG")?;
    } else {
        JpegEncoder::new_with_quality(&mut colour, jpeg_quality)
            .write_image(&rgb, width, height, ExtendedColorType::Rgb8)
            .context("keyframe colour as JPEG")?;
    }
    let mut depth_png = Vec::new();
    PngEncoder::new_with_quality(&mut depth_png, CompressionType::Fast, FilterType::Adaptive)
        .write_image(&depth, width, height, ExtendedColorType::L16)
        .context("keyframe depth as PNG")?;
    let mut bytes = bytemuck::bytes_of(&header).to_vec();
    bytes.extend(u32::try_from(colour.len())?.to_le_bytes());
    bytes.extend(colour);
    bytes.extend(depth_png);
    Ok(Encoded {
        encoding,
        bytes,
        gaussians_dropped: 0,
    })
}

fn decode_image(wire: &[u8]) -> Result<Vec<u8>> {
    let (header, body) = split_header::<KeyframeImageHeader>(wire, "encoded keyframe image")?;
    let id = header.keyframe_id;
    ensure!(
        body.len() >= 4,
        "encoded keyframe image {id} without its colour length"
    );
    let colour_len = u32::from_le_bytes(body[..4].try_into().unwrap()) as usize;
    let (colour, depth) = body[4..].split_at_checked(colour_len).ok_or_else(|| {
        anyhow!("encoded keyframe image {id}: colour of {colour_len} bytes is cut short")
    })?;
    let colour = image::load_from_memory(colour)
        .with_context(|| format!("keyframe image {id}: colour"))?
        .to_rgb8();
    let depth = image::load_from_memory_with_format(depth, ImageFormat::Png)
        .with_context(|| format!("keyframe image {id}: depth"))?
        .to_luma16();
    for (what, (w, h)) in [
        ("colour", colour.dimensions()),
        ("depth", depth.dimensions()),
    ] {
        ensure!(
            (w, h) == (header.width, header.height),
            "keyframe image {id}: {what} is {w}x{h}, the header says {}x{}",
            header.width,
            header.height
        );
    }
    let mut raw = bytemuck::bytes_of(&header).to_vec();
    raw.reserve(colour.len() * 2);
    for (rgb, depth) in colour.pixels().zip(depth.pixels()) {
        raw.extend(bytemuck::bytes_of(&RgbdPixel {
            rgb: rgb.0,
            reserved: 0,
            depth_mm: depth.0[0],
        }));
    }
    Ok(raw)
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::messages::Pose;

    fn stamp() -> Stamp {
        Stamp {
            agent_id: 3,
            epoch: 1,
            sequence: 7,
            ..Stamp::default()
        }
    }

    fn patch(records: &[GaussianRecord]) -> Vec<u8> {
        let header = PatchHeader {
            stamp: stamp(),
            keyframe_id: 12,
            count: records.len() as u64,
            frame: 0,
            reserved: 0,
        };
        let mut raw = bytemuck::bytes_of(&header).to_vec();
        raw.extend_from_slice(bytemuck::cast_slice(records));
        raw
    }

    fn record(i: usize) -> GaussianRecord {
        let t = i as f32;
        GaussianRecord {
            mean: [0.37 * t.sin() - 1.0, 2.5 + 0.001 * t, (0.3 * t).cos()],
            log_scale: [-4.0 + 0.001 * t, -3.5, -5.0],
            rotation_wxyz: [0.9, 0.1 * t.sin(), 0.2, -0.3],
            opacity_logit: 2.0 - 0.001 * t,
            colour: [(0.01 * t) % 1.0, 0.5, 0.25],
        }
    }

    fn records_of(raw: &[u8]) -> (PatchHeader, Vec<GaussianRecord>) {
        patch_records(raw).unwrap()
    }

    #[test]
    fn lossless_patches_decode_to_the_same_bytes_and_are_smaller() {
        let records: Vec<_> = (0..5000).map(record).collect();
        let raw = patch(&records);
        let encoded = encode(Topic::Patch, &raw, Encoding::Lossless, 90).unwrap();
        assert!(
            encoded.bytes.len() < raw.len() * 3 / 4,
            "{} of {}",
            encoded.bytes.len(),
            raw.len()
        );
        assert_eq!(
            decode(Topic::Patch, Encoding::Lossless, &encoded.bytes).unwrap(),
            raw
        );
    }

    #[test]
    fn compact_patches_drop_only_invisible_gaussians_and_stay_within_quantisation() {
        let mut records: Vec<_> = (0..3000).map(record).collect();
        // Opacity 1/300 and 1/200: only the first is below what the rasteriser blends.
        records[10].opacity_logit = (1.0f32 / 300.0 / (1.0 - 1.0 / 300.0)).ln();
        records[11].opacity_logit = (1.0f32 / 200.0 / (1.0 - 1.0 / 200.0)).ln();
        let raw = patch(&records);
        let encoded = encode(Topic::Patch, &raw, Encoding::Compact, 90).unwrap();
        assert_eq!(encoded.gaussians_dropped, 1);
        assert!(
            encoded.bytes.len() < raw.len() / 3,
            "{} of {}",
            encoded.bytes.len(),
            raw.len()
        );
        let (header, decoded) =
            records_of(&decode(Topic::Patch, Encoding::Compact, &encoded.bytes).unwrap());
        assert_eq!(
            (header.keyframe_id, header.count, header.stamp),
            (12, 2999, stamp())
        );
        let kept: Vec<_> = records
            .iter()
            .enumerate()
            .filter(|(i, _)| *i != 10)
            .map(|(_, r)| r)
            .collect();
        for (a, b) in kept.iter().zip(&decoded) {
            for axis in 0..3 {
                // 16 bits over a bounding box of a few metres: well under a millimetre.
                assert!((a.mean[axis] - b.mean[axis]).abs() < 1e-4, "{a:?} {b:?}");
                assert!((a.log_scale[axis] - b.log_scale[axis]).abs() < 5e-3);
                assert!((a.colour[axis] - b.colour[axis]).abs() <= 0.5 / 255.0 + 1e-6);
            }
            let norm = a.rotation_wxyz.iter().map(|q| q * q).sum::<f32>().sqrt();
            for i in 0..4 {
                assert!((a.rotation_wxyz[i] / norm - b.rotation_wxyz[i]).abs() < 1e-4);
            }
            assert!((a.opacity_logit - b.opacity_logit).abs() < 2e-3);
        }
    }

    #[test]
    fn an_empty_patch_crosses_in_every_encoding() {
        let raw = patch(&[]);
        for encoding in Encoding::UNDER_A_CAP {
            let encoded = encode(Topic::Patch, &raw, encoding, 90).unwrap();
            let (header, records) =
                records_of(&decode(Topic::Patch, encoding, &encoded.bytes).unwrap());
            assert_eq!((header.count, records.len()), (0, 0));
        }
    }

    fn image(width: u32, height: u32) -> Vec<u8> {
        let header = KeyframeImageHeader {
            stamp: stamp(),
            keyframe_id: 4,
            frame_index: 40,
            timestamp_s: 1.5,
            camera_to_agent_world: Pose::default(),
            intrinsics: Intrinsics {
                fx: 525.0,
                fy: 520.0,
                cx: 319.5,
                cy: 239.5,
                width,
                height,
            },
            width,
            height,
        };
        let mut raw = bytemuck::bytes_of(&header).to_vec();
        for y in 0..height {
            for x in 0..width {
                // A smooth wall with a step (two surfaces) at x = 20, and a hole.
                let depth_mm = if (x, y) == (5, 5) {
                    0
                } else if x < 20 {
                    1500 + y as u16
                } else {
                    3000
                };
                let rgb = [(x * 4) as u8, (y * 3) as u8, ((x + y) % 7 * 30) as u8];
                raw.extend(bytemuck::bytes_of(&RgbdPixel {
                    rgb,
                    reserved: 0,
                    depth_mm,
                }));
            }
        }
        raw
    }

    #[test]
    fn lossless_images_decode_to_the_same_bytes() {
        let raw = image(48, 32);
        let encoded = encode(Topic::KeyframeImage, &raw, Encoding::Lossless, 90).unwrap();
        assert_eq!(
            decode(Topic::KeyframeImage, Encoding::Lossless, &encoded.bytes).unwrap(),
            raw
        );
    }

    #[test]
    fn compact_images_keep_depth_exact_and_colour_close() {
        let raw = image(48, 32);
        let encoded = encode(Topic::KeyframeImage, &raw, Encoding::Compact, 95).unwrap();
        let (header, pixels) =
            image_pixels(&decode(Topic::KeyframeImage, Encoding::Compact, &encoded.bytes).unwrap())
                .unwrap();
        let (original_header, original) = image_pixels(&raw).unwrap();
        assert_eq!(header, original_header);
        let mut colour_error = 0.0;
        for (a, b) in original.iter().zip(&pixels) {
            assert_eq!(a.depth_mm, b.depth_mm);
            colour_error += (0..3)
                .map(|c| (f64::from(a.rgb[c]) - f64::from(b.rgb[c])).abs())
                .sum::<f64>();
        }
        assert!(
            colour_error / ((pixels.len() * 3) as f64) < 6.0,
            "{colour_error}"
        );
    }

    #[test]
    fn reduced_images_are_binned_with_their_intrinsics_and_never_mix_two_surfaces() {
        let raw = image(49, 32);
        let encoded = encode(Topic::KeyframeImage, &raw, Encoding::Reduced, 90).unwrap();
        let (header, pixels) =
            image_pixels(&decode(Topic::KeyframeImage, Encoding::Reduced, &encoded.bytes).unwrap())
                .unwrap();
        assert_eq!(
            (header.width, header.height, pixels.len()),
            (24, 16, 24 * 16)
        );
        assert_eq!(
            (header.intrinsics.width, header.intrinsics.height),
            (24, 16)
        );
        assert_eq!((header.intrinsics.fx, header.intrinsics.cx), (262.5, 159.5));
        // Block (2, 2) holds the hole and three valid pixels (1504, 1504, 1505): their mean.
        assert_eq!(pixels[2 * 24 + 2].depth_mm, 1504);
        for (i, p) in pixels.iter().enumerate() {
            assert!(
                p.depth_mm == 3000 || (1500..1540).contains(&p.depth_mm),
                "pixel {i}: {}",
                p.depth_mm
            );
        }
    }

    #[test]
    fn corrupt_or_mislabelled_messages_are_refused_with_a_reason() {
        let raw = image(16, 8);
        let encoded = encode(Topic::KeyframeImage, &raw, Encoding::Compact, 90).unwrap();
        let cut = &encoded.bytes[..encoded.bytes.len() - 40];
        assert!(decode(Topic::KeyframeImage, Encoding::Compact, cut).is_err());
        let patch = encode(Topic::Patch, &patch(&[record(0)]), Encoding::Lossless, 90).unwrap();
        let error = decode(Topic::Descriptor, Encoding::Lossless, &patch.bytes).unwrap_err();
        assert!(error.to_string().contains("descriptor"), "{error}");
        assert!(Encoding::from_tag(9).is_err());
        // Small topics and the raw encoding cross unchanged.
        let descriptor = vec![1u8; 40];
        let unchanged = encode(Topic::Descriptor, &descriptor, Encoding::Reduced, 90).unwrap();
        assert_eq!(
            (unchanged.encoding, unchanged.bytes),
            (Encoding::Raw, descriptor)
        );
    }
}
