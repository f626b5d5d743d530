//! Keypoints with binary descriptors, lifted to 3-D with the keyframe's depth, and their matching.
//!
//! FAST-9 corners (imageproc's `oriented_fast`, strongest first) and 256-bit BRIEF descriptors
//! (imageproc's `brief`) on every level of an image pyramid: BRIEF compares fixed pixel pairs in a
//! 31x31 patch, so it is not scale-invariant by itself, and two agents see the same place from
//! different distances. The test pairs are drawn once from a fixed seed so that descriptors of
//! all keyframes are comparable. No orientation steering: hand-held and walking cameras keep the
//! horizon roughly level, and BRIEF tolerates the ~15 degrees of roll they show.
//!
//! A keypoint is kept only if its depth is trustworthy (see
//! [`AlignmentConfig::max_depth_spread_fraction`]); it is then a 3-D point in the camera frame.

use std::sync::OnceLock;

use image::imageops::FilterType;
use image::{GrayImage, RgbImage};
use imageproc::binary_descriptors::brief::{TestPair, brief};
use imageproc::corners::oriented_fast;
use imageproc::point::Point;
use nalgebra::Point3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use slam_core::camera::Intrinsics;
use slam_core::dataset::DepthImage;

use crate::config::AlignmentConfig;

/// Descriptor length in bits; imageproc stores descriptors as 128-bit words.
const DESCRIPTOR_BITS: usize = 256;
const DESCRIPTOR_WORDS: usize = DESCRIPTOR_BITS / 128;
/// BRIEF's patch is 31 x 31 pixels around the keypoint (imageproc's constant).
const BRIEF_PATCH_DIAMETER: u32 = 31;
const BRIEF_PATCH_RADIUS: u32 = BRIEF_PATCH_DIAMETER / 2;
/// Keypoints must lie farther than the patch radius from the border for BRIEF (imageproc refuses
/// closer ones); one extra pixel of margin for the patch smoothing.
const KEYPOINT_BORDER: u32 = BRIEF_PATCH_RADIUS + 2;
/// Spread of the test-pair coordinates around the patch centre: Calonder et al.'s isotropic
/// Gaussian with sigma = patch size / 5 (what imageproc draws).
const TEST_PAIR_SIGMA: f32 = BRIEF_PATCH_DIAMETER as f32 / 5.0;
/// Seed of the test pairs. Changing it changes every descriptor: keyframes described with
/// different pairs cannot be matched.
const TEST_PAIR_SEED: u64 = 0x0b51_ef00;
/// Seed of imageproc's FAST threshold estimate (a sample of random pixels): fixed for
/// reproducible keypoints.
const FAST_THRESHOLD_SEED: u64 = 7;
/// Half-width of the depth neighbourhood that must be valid and smooth around a keypoint.
const DEPTH_WINDOW_RADIUS: i64 = 1;

/// A 256-bit BRIEF descriptor.
pub type Descriptor = [u128; DESCRIPTOR_WORDS];

/// Keypoints of one keyframe with valid depth: 3-D positions in the camera frame and descriptors.
#[derive(Debug, Clone, Default)]
pub struct Features {
    pub camera_points: Vec<Point3<f64>>,
    pub descriptors: Vec<Descriptor>,
    /// Keypoints detected before the depth check (for diagnostics).
    pub detected: usize,
}

impl Features {
    pub fn len(&self) -> usize {
        self.camera_points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.camera_points.is_empty()
    }
}

/// The fixed BRIEF test pairs, drawn once from [`TEST_PAIR_SEED`].
fn test_pairs() -> &'static Vec<TestPair> {
    static PAIRS: OnceLock<Vec<TestPair>> = OnceLock::new();
    PAIRS.get_or_init(draw_test_pairs)
}

fn draw_test_pairs() -> Vec<TestPair> {
    let mut rng = ChaCha8Rng::seed_from_u64(TEST_PAIR_SEED);
    let centre = BRIEF_PATCH_RADIUS as f32;
    let normal = Normal::new(centre, TEST_PAIR_SIGMA).expect("finite positive sigma");
    let mut coordinate = || loop {
        let value = normal.sample(&mut rng).round();
        if (0.0..BRIEF_PATCH_DIAMETER as f32).contains(&value) {
            return value as u32;
        }
    };
    (0..DESCRIPTOR_BITS)
        .map(|_| TestPair {
            p0: Point::new(coordinate(), coordinate()),
            p1: Point::new(coordinate(), coordinate()),
        })
        .collect()
}

/// Detects, describes and lifts the keypoints of one RGB-D keyframe: FAST corners on every
/// pyramid level, each described on the level it was found on (ORB's scheme), so a corner seen
/// at another distance is found and described on another level.
pub fn extract(
    rgb: &RgbImage,
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    config: &AlignmentConfig,
) -> Features {
    let _span = tracing::debug_span!("features").entered();
    let grey = image::imageops::grayscale(rgb);
    let pyramid = pyramid(&grey, config);
    // Keypoints per level in proportion to the level's area, like ORB.
    let areas: Vec<f64> = pyramid
        .iter()
        .map(|level| level.width() as f64 * level.height() as f64)
        .collect();
    let total_area: f64 = areas.iter().sum();
    let mut features = Features::default();
    for (level, (image, area)) in pyramid.iter().zip(&areas).enumerate() {
        if image.width() <= 2 * KEYPOINT_BORDER + 1 || image.height() <= 2 * KEYPOINT_BORDER + 1 {
            break;
        }
        let wanted = (config.features_per_image as f64 * area / total_area).ceil() as usize;
        let corners = oriented_fast(
            image,
            None,
            wanted,
            KEYPOINT_BORDER,
            Some(FAST_THRESHOLD_SEED),
        );
        let keypoints: Vec<(u32, u32)> = corners.iter().map(|c| (c.corner.x, c.corner.y)).collect();
        describe_on_level(
            &pyramid,
            level,
            &keypoints,
            depth,
            intrinsics,
            config,
            &mut features,
        );
    }
    tracing::debug!(
        detected = features.detected,
        lifted = features.len(),
        "keypoints"
    );
    features
}

/// Image pyramid of `grey`: level `l` is `pyramid_scale_factor^l` times smaller.
fn pyramid(grey: &GrayImage, config: &AlignmentConfig) -> Vec<GrayImage> {
    let scale = config.pyramid_scale_factor.max(1.0);
    (0..config.pyramid_levels.max(1))
        .map(|level| {
            if level == 0 {
                return grey.clone();
            }
            let factor = scale.powi(level as i32);
            let width = (grey.width() as f64 / factor).round().max(1.0) as u32;
            let height = (grey.height() as f64 / factor).round().max(1.0) as u32;
            image::imageops::resize(grey, width, height, FilterType::Triangle)
        })
        .collect()
}

/// Describes keypoints given in pixels of pyramid level `level` and appends those with reliable
/// depth to `features`, lifted from their level-0 position.
#[allow(clippy::too_many_arguments)]
fn describe_on_level(
    pyramid: &[GrayImage],
    level: usize,
    keypoints: &[(u32, u32)],
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    config: &AlignmentConfig,
    features: &mut Features,
) {
    features.detected += keypoints.len();
    let image = &pyramid[level];
    let factor = config.pyramid_scale_factor.max(1.0).powi(level as i32);
    let inside = |x: u32, limit: u32| x >= KEYPOINT_BORDER && x + KEYPOINT_BORDER < limit;
    let mut positions = Vec::new();
    let mut points = Vec::new();
    for &(x, y) in keypoints {
        if !inside(x, image.width()) || !inside(y, image.height()) {
            continue;
        }
        // Pixel centres sit at integer coordinates: scale about pixel corners.
        let u = (x as f64 + 0.5) * factor - 0.5;
        let v = (y as f64 + 0.5) * factor - 0.5;
        let Some(z) = reliable_depth(depth, u.round() as i64, v.round() as i64, config) else {
            continue;
        };
        positions.push(Point::new(x, y));
        points.push(intrinsics.back_project(u, v, z as f64));
    }
    if positions.is_empty() {
        return;
    }
    let Ok((descriptors, _)) = brief(image, &positions, DESCRIPTOR_BITS, Some(test_pairs())) else {
        // BRIEF only refuses keypoints within its patch radius of the border, dropped above.
        tracing::warn!(level, "BRIEF refused this level's keypoints; level skipped");
        return;
    };
    for (point, descriptor) in points.into_iter().zip(descriptors) {
        let mut words = [0u128; DESCRIPTOR_WORDS];
        words.copy_from_slice(&descriptor.bits);
        features.camera_points.push(point);
        features.descriptors.push(words);
    }
}

/// The depth at pixel (u, v) when its whole neighbourhood is valid and smooth, else `None`.
fn reliable_depth(depth: &DepthImage, u: i64, v: i64, config: &AlignmentConfig) -> Option<f32> {
    let (width, height) = (depth.width as i64, depth.height as i64);
    let inside = |x: i64, y: i64| x >= 0 && y >= 0 && x < width && y < height;
    if !inside(u - DEPTH_WINDOW_RADIUS, v - DEPTH_WINDOW_RADIUS)
        || !inside(u + DEPTH_WINDOW_RADIUS, v + DEPTH_WINDOW_RADIUS)
    {
        return None;
    }
    let centre = depth.get(u as u32, v as u32);
    let truncation = config.truncation_m as f32;
    let (mut lowest, mut highest) = (f32::INFINITY, 0.0f32);
    for y in v - DEPTH_WINDOW_RADIUS..=v + DEPTH_WINDOW_RADIUS {
        for x in u - DEPTH_WINDOW_RADIUS..=u + DEPTH_WINDOW_RADIUS {
            let z = depth.get(x as u32, y as u32);
            // `z > 0.0` is false for NaN as well.
            if !(z > 0.0 && z < truncation) {
                return None;
            }
            lowest = lowest.min(z);
            highest = highest.max(z);
        }
    }
    (highest - lowest <= config.max_depth_spread_fraction as f32 * centre).then_some(centre)
}

fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

/// Best and second-best distance and the best index of `query` among `candidates`.
fn two_nearest(query: &Descriptor, candidates: &[Descriptor]) -> Option<(usize, u32, u32)> {
    let (mut best_index, mut best, mut second) = (None, u32::MAX, u32::MAX);
    for (index, candidate) in candidates.iter().enumerate() {
        let distance = hamming(query, candidate);
        if distance < best {
            second = best;
            best = distance;
            best_index = Some(index);
        } else if distance < second {
            second = distance;
        }
    }
    best_index.map(|index| (index, best, second))
}

/// Matches `(source index, target index)`: mutual nearest neighbours in Hamming distance that
/// pass the distance limit and Lowe's ratio test in both directions. Brute force: 1000 x 1000
/// descriptors are two million 256-bit comparisons, a few milliseconds.
pub fn match_features(
    source: &Features,
    target: &Features,
    config: &AlignmentConfig,
) -> Vec<(usize, usize)> {
    let passes = |best: u32, second: u32| {
        best <= config.max_hamming_distance && (best as f64) < config.match_ratio * second as f64
    };
    let backward: Vec<Option<usize>> = target
        .descriptors
        .iter()
        .map(|d| {
            two_nearest(d, &source.descriptors)
                .filter(|&(_, best, second)| passes(best, second))
                .map(|(index, _, _)| index)
        })
        .collect();
    source
        .descriptors
        .iter()
        .enumerate()
        .filter_map(|(i, d)| {
            let (j, best, second) = two_nearest(d, &target.descriptors)?;
            (passes(best, second) && backward[j] == Some(i)).then_some((i, j))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_pairs_are_fixed_and_inside_the_patch() {
        let a = test_pairs();
        assert_eq!(a, test_pairs());
        assert_eq!(a.len(), DESCRIPTOR_BITS);
        assert!(a.iter().all(|p| p.p0.x < BRIEF_PATCH_DIAMETER
            && p.p0.y < BRIEF_PATCH_DIAMETER
            && p.p1.x < BRIEF_PATCH_DIAMETER
            && p.p1.y < BRIEF_PATCH_DIAMETER));
    }

    #[test]
    fn two_nearest_and_mutual_matching() {
        let d = |v: u128| [v, 0];
        assert_eq!(
            two_nearest(&d(0b1111), &[d(0), d(0b111), d(0b1)]),
            Some((1, 1, 3))
        );
        let config = AlignmentConfig {
            max_hamming_distance: 10,
            ..AlignmentConfig::default()
        };
        let features = |values: &[u128]| Features {
            camera_points: vec![Point3::origin(); values.len()],
            descriptors: values.iter().map(|&v| d(v)).collect(),
            detected: values.len(),
        };
        // 0 <-> 0 is exact and unambiguous; u128::MAX has no partner within 10 bits.
        let source = features(&[0, u128::MAX]);
        let target = features(&[0, 0xffff_ffff]);
        assert_eq!(match_features(&source, &target, &config), vec![(0, 0)]);
    }

    /// Random 3x3-pixel blocks: plenty of corners with distinct surroundings.
    fn blocky_texture(width: u32, height: u32) -> RgbImage {
        use rand::RngExt;
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let blocks: Vec<u8> = (0..(width * height) as usize)
            .map(|_| rng.random_range(0..=255))
            .collect();
        RgbImage::from_fn(width, height, |x, y| {
            let v = blocks[((y / 3) * width + x / 3) as usize];
            image::Rgb([v, v, v])
        })
    }

    #[test]
    fn keypoints_of_a_shifted_view_match_their_originals() {
        let (width, height, shift) = (240u32, 180u32, (7u32, 4u32));
        let texture = blocky_texture(width + shift.0, height + shift.1);
        let source_image = image::imageops::crop_imm(&texture, 0, 0, width, height).to_image();
        let target_image =
            image::imageops::crop_imm(&texture, shift.0, shift.1, width, height).to_image();
        let mut depth = DepthImage::new(width, height);
        depth.data.fill(2.0);
        let k = Intrinsics::new(200.0, 200.0, 119.5, 89.5, width, height);
        let config = AlignmentConfig::default();
        let source = extract(&source_image, &depth, &k, &config);
        let target = extract(&target_image, &depth, &k, &config);
        assert!(source.len() > 100 && target.len() > 100);
        let matches = match_features(&source, &target, &config);
        // The target camera sees the same plane moved by the shift in pixels.
        let offset = nalgebra::Vector3::new(
            shift.0 as f64 * 2.0 / k.fx,
            shift.1 as f64 * 2.0 / k.fy,
            0.0,
        );
        let correct = matches
            .iter()
            .filter(|(i, j)| {
                (source.camera_points[*i] - offset - target.camera_points[*j]).norm() < 0.02
            })
            .count();
        assert!(
            matches.len() >= 50 && correct * 10 >= matches.len() * 9,
            "{correct} of {} matches correct",
            matches.len()
        );
    }

    #[test]
    fn depth_must_be_valid_and_smooth() {
        let mut depth = DepthImage::new(5, 5);
        depth.data.fill(2.0);
        let config = AlignmentConfig::default();
        assert_eq!(reliable_depth(&depth, 2, 2, &config), Some(2.0));
        assert_eq!(
            reliable_depth(&depth, 0, 2, &config),
            None,
            "window leaves the image"
        );
        depth.data[3 * 5 + 3] = 2.5; // a depth edge next to the centre
        assert_eq!(reliable_depth(&depth, 2, 2, &config), None);
        depth.data[3 * 5 + 3] = 0.0; // a hole
        assert_eq!(reliable_depth(&depth, 2, 2, &config), None);
    }
}
