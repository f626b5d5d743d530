//! Keypoints with binary descriptors, lifted to 3-D with the keyframe's depth, and their matching.
//!
//! ORB-like, with the depth put to use: FAST-9 corners on every level of an image pyramid,
//! thinned to local maxima of the FAST score, those with reliable depth spread over the image
//! with a grid; each is described by 256 BRIEF intensity tests on a patch of the surface under it
//! (a square [`AlignmentConfig::descriptor_radius_m`] in radius, laid onto the surface with the
//! normal from depth and sampled from the pyramid level whose pixels match), the pattern turned by
//! the patch's intensity-centroid orientation (steered BRIEF). The same place seen from another
//! distance, another angle or with the camera rolled then gives nearly the same descriptor.
//!
//! Why each part: unsteered BRIEF does not survive in-plane rotation (views of a room from metres
//! apart differ by tens of degrees locally even without roll); strongest-first corners without
//! non-maximum suppression pile up on a few spots, so a region the other view sees often has
//! none; choosing corners before the depth check spends the budget on corners that cannot be
//! lifted; image patches change with distance and viewing angle, surface patches much less.
//! Views metres apart whose directions differ by more than ~50 degrees still mostly give fewer
//! matches than RANSAC needs: such pairs are linked by map-level registration
//! ([`crate::map_registration`]). The measurements (`examples/keyframe_matching`) are in
//! docs/benchmarks.md.
//!
//! A keypoint is kept only if its depth is trustworthy (see
//! [`AlignmentConfig::max_depth_spread_fraction`]); it is then a 3-D point in the camera frame.

mod detection;
mod matching;
mod patch;
#[cfg(test)]
mod tests;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Point3;

use crate::alignment::AlignmentConfig;
use detection::{local_maxima, pyramid, spread};
pub use matching::{hamming, match_features};
use patch::{Patch, PatchSampler, SAMPLING_LEVELS, descriptor, orientation};

/// Descriptor length in bits, stored as 128-bit words.
const DESCRIPTOR_BITS: usize = 256;
const DESCRIPTOR_WORDS: usize = DESCRIPTOR_BITS / 128;
/// The tests and the orientation use a disc of this radius around the keypoint (ORB's 31-pixel
/// patch): a disc turns into itself, so a steered pattern needs no larger border.
const PATCH_RADIUS: i32 = 15;
/// Each test compares the mean of a (2r+1)^2 box around its two points (r = 2: 5x5), which
/// smooths the pixel noise BRIEF is sensitive to.
const BOX_RADIUS: i32 = 2;
/// Keypoints must lie farther than the patch and its boxes from the border.
const KEYPOINT_BORDER: u32 = (PATCH_RADIUS + BOX_RADIUS + 1) as u32;
/// Spread of the test-point coordinates around the patch centre: Calonder et al.'s isotropic
/// Gaussian with sigma = patch size / 5.
const TEST_POINT_SIGMA: f64 = (2 * PATCH_RADIUS + 1) as f64 / 5.0;
/// Seed of the test pattern. Changing it changes every descriptor: keyframes described with
/// different patterns cannot be matched.
const TEST_PAIR_SEED: u64 = 0x0b51_ef00;
/// Half-width of the depth neighbourhood that must be valid and smooth around a keypoint.
const DEPTH_WINDOW_RADIUS: i64 = 1;

/// A 256-bit descriptor.
pub type Descriptor = [u128; DESCRIPTOR_WORDS];

/// Where a lifted keypoint was found (for diagnostics).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Level-0 pixel coordinates: column...
    pub u: f64,
    /// ...and row.
    pub v: f64,
    /// Pyramid level it was detected and described on.
    pub level: usize,
    /// Orientation (radians) in image coordinates: from +x towards +y (y points down), so
    /// turning the image by `a` that way adds `a`. 0 when descriptors are not steered.
    pub angle: f32,
    /// FAST score (the largest threshold at which it is still a corner).
    pub score: u8,
}

/// Keypoints of one keyframe with valid depth: 3-D positions in the camera frame and descriptors.
#[derive(Debug, Clone, Default)]
pub struct Features {
    /// Per lifted keypoint, its 3-D position in the camera frame (metres).
    pub camera_points: Vec<Point3<f64>>,
    /// Per lifted keypoint, parallel to `camera_points`, its BRIEF descriptor.
    pub descriptors: Vec<Descriptor>,
    /// Per lifted keypoint, parallel to `camera_points`.
    pub keypoints: Vec<Keypoint>,
    /// Corners detected (local maxima of the FAST score) before the depth check and the
    /// per-level budget (for diagnostics).
    pub detected: usize,
}

impl Features {
    /// Number of lifted keypoints.
    pub fn len(&self) -> usize {
        self.camera_points.len()
    }

    /// True when no keypoint could be lifted.
    pub fn is_empty(&self) -> bool {
        self.camera_points.is_empty()
    }
}

/// A FAST corner of one pyramid level that can be lifted.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    x: u32,
    y: u32,
    score: u8,
    /// Level-0 pixel and depth.
    u: f64,
    v: f64,
    z: f32,
}

/// Detects, describes and lifts the keypoints of one RGB-D keyframe: on every pyramid level,
/// FAST corners thinned to local maxima, those with reliable depth spread over a grid
/// ([`AlignmentConfig::keypoint_cell_px`]) up to the level's share of
/// [`AlignmentConfig::features_per_image`], oriented and described on that level.
pub fn extract(
    rgb: &RgbImage,
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    config: &AlignmentConfig,
) -> Features {
    let _span = tracing::debug_span!("features").entered();
    let grey = image::imageops::grayscale(rgb);
    let levels = config.pyramid_levels.max(1);
    // Metric patches may need coarser levels than detection does (a near surface).
    let sampling_levels = if config.descriptor_radius_m > 0.0 {
        levels.max(SAMPLING_LEVELS)
    } else {
        levels
    };
    let pyramid = pyramid(&grey, config.pyramid_scale_factor, sampling_levels);
    let sampler = PatchSampler {
        pyramid: &pyramid,
        scale: config.pyramid_scale_factor.max(1.0),
        depth,
        intrinsics,
        config,
    };
    // Keypoints per level in proportion to the level's area, like ORB.
    let areas: Vec<f64> = pyramid[..levels.min(pyramid.len())]
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
        let factor = config.pyramid_scale_factor.max(1.0).powi(level as i32);
        let corners = local_maxima(image, config.fast_threshold);
        features.detected += corners.len();
        let candidates: Vec<Candidate> = corners
            .into_iter()
            .filter_map(|(x, y, score)| {
                // Pixel centres sit at integer coordinates: scale about pixel corners.
                let u = (x as f64 + 0.5) * factor - 0.5;
                let v = (y as f64 + 0.5) * factor - 0.5;
                let z = reliable_depth(depth, u.round() as i64, v.round() as i64, config)?;
                Some(Candidate {
                    x,
                    y,
                    score,
                    u,
                    v,
                    z,
                })
            })
            .collect();
        let chosen = spread(candidates, wanted, config.keypoint_cell_px, image);
        for candidate in &chosen {
            if let Some(patch) = sampler.patch(level, candidate) {
                features.push(&patch, level, candidate, intrinsics, config);
            }
        }
    }
    tracing::debug!(
        detected = features.detected,
        lifted = features.len(),
        "keypoints"
    );
    features
}

/// Descriptors at given places as if keypoints had been found there (for diagnostics: what a
/// descriptor of the true corresponding point looks like): `(u, v, level)` in level-0 pixels;
/// `None` where the depth is unreliable or the patch leaves the image.
pub fn describe_at(
    rgb: &RgbImage,
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    config: &AlignmentConfig,
    places: &[(f64, f64, usize)],
) -> Vec<Option<Descriptor>> {
    let grey = image::imageops::grayscale(rgb);
    let levels = config.pyramid_levels.max(1).max(SAMPLING_LEVELS);
    let pyramid = pyramid(&grey, config.pyramid_scale_factor, levels);
    let scale = config.pyramid_scale_factor.max(1.0);
    let sampler = PatchSampler {
        pyramid: &pyramid,
        scale,
        depth,
        intrinsics,
        config,
    };
    places
        .iter()
        .map(|&(u, v, level)| {
            let level = level.min(pyramid.len() - 1);
            let factor = scale.powi(level as i32);
            let (x, y) = ((u + 0.5) / factor - 0.5, (v + 0.5) / factor - 0.5);
            let (x, y) = (x.round(), y.round());
            let image = &pyramid[level];
            let border = KEYPOINT_BORDER as f64;
            if x < border
                || y < border
                || x + border >= image.width() as f64
                || y + border >= image.height() as f64
            {
                return None;
            }
            let z = reliable_depth(depth, u.round() as i64, v.round() as i64, config)?;
            let candidate = Candidate {
                x: x as u32,
                y: y as u32,
                score: 0,
                u,
                v,
                z,
            };
            let patch = sampler.patch(level, &candidate)?;
            let angle = if config.steer_descriptors {
                orientation(&patch)
            } else {
                0.0
            };
            Some(descriptor(&patch, angle))
        })
        .collect()
}

impl Features {
    /// Orients and describes a keypoint's patch and appends it, lifted from its level-0
    /// position.
    fn push(
        &mut self,
        patch: &Patch,
        level: usize,
        c: &Candidate,
        intrinsics: &Intrinsics,
        config: &AlignmentConfig,
    ) {
        let angle = if config.steer_descriptors {
            orientation(patch)
        } else {
            0.0
        };
        self.keypoints.push(Keypoint {
            u: c.u,
            v: c.v,
            level,
            angle,
            score: c.score,
        });
        self.camera_points
            .push(intrinsics.back_project(c.u, c.v, c.z as f64));
        self.descriptors.push(descriptor(patch, angle));
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
