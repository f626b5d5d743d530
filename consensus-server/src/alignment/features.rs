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

use std::sync::OnceLock;

use image::GrayImage;
use image::RgbImage;
use image::imageops::FilterType;
use imageproc::corners::corners_fast9;
use nalgebra::{Matrix3, Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use slam_core::camera::Intrinsics;
use slam_core::dataset::DepthImage;

use crate::config::AlignmentConfig;

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
    /// Level-0 pixel coordinates.
    pub u: f64,
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
    pub camera_points: Vec<Point3<f64>>,
    pub descriptors: Vec<Descriptor>,
    /// Per lifted keypoint, parallel to `camera_points`.
    pub keypoints: Vec<Keypoint>,
    /// Corners detected (local maxima of the FAST score) before the depth check and the
    /// per-level budget (for diagnostics).
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

/// One intensity test: offsets of its two points from the keypoint (pixels, image axes).
#[derive(Debug, Clone, Copy, PartialEq)]
struct TestPair {
    p0: [f32; 2],
    p1: [f32; 2],
}

/// The fixed test pattern, drawn once from [`TEST_PAIR_SEED`].
fn test_pairs() -> &'static [TestPair] {
    static PAIRS: OnceLock<Vec<TestPair>> = OnceLock::new();
    PAIRS.get_or_init(draw_test_pairs)
}

/// Gaussian points inside the patch disc, rounded to whole pixels.
fn draw_test_pairs() -> Vec<TestPair> {
    let mut rng = ChaCha8Rng::seed_from_u64(TEST_PAIR_SEED);
    let normal = Normal::new(0.0, TEST_POINT_SIGMA).expect("finite positive sigma");
    let mut point = || loop {
        let (x, y): (f64, f64) = (
            normal.sample(&mut rng).round(),
            normal.sample(&mut rng).round(),
        );
        if x * x + y * y <= (PATCH_RADIUS * PATCH_RADIUS) as f64 {
            return [x as f32, y as f32];
        }
    };
    let mut pairs = Vec::with_capacity(DESCRIPTOR_BITS);
    while pairs.len() < DESCRIPTOR_BITS {
        let (p0, p1) = (point(), point());
        // A test of a point against itself is always false.
        if p0 != p1 {
            pairs.push(TestPair { p0, p1 });
        }
    }
    pairs
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

/// Image pyramid of `grey`: level `l` is `scale^l` times smaller; levels stop before the image
/// gets smaller than a patch.
fn pyramid(grey: &GrayImage, scale: f64, levels: usize) -> Vec<GrayImage> {
    let scale = scale.max(1.0);
    (0..levels.max(1))
        .take_while(|&level| {
            let factor = scale.powi(level as i32);
            level == 0 || grey.width().min(grey.height()) as f64 / factor > PATCH_SIZE as f64
        })
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

/// FAST-9 corners at `threshold` inside the keypoint border that are local maxima of the FAST
/// score in their 3x3 neighbourhood (ties go to the first in raster order): a corner makes a
/// blob of adjacent detections, of which one is kept. `(x, y, score)`, raster order.
fn local_maxima(image: &GrayImage, threshold: u8) -> Vec<(u32, u32, u8)> {
    let (width, height) = image.dimensions();
    let mut scores = vec![0u8; (width * height) as usize];
    let mut corners = Vec::new();
    for corner in corners_fast9(image, threshold) {
        let inside = |c: u32, limit: u32| c >= KEYPOINT_BORDER && c + KEYPOINT_BORDER < limit;
        if !inside(corner.x, width) || !inside(corner.y, height) {
            continue;
        }
        // The score is at least the threshold; store it + 1 so that 0 means "no corner".
        let score = (corner.score as u8).saturating_add(1);
        scores[(corner.y * width + corner.x) as usize] = score;
        corners.push((corner.x, corner.y, score));
    }
    corners.retain(|&(x, y, score)| {
        let mut keep = true;
        for ny in y - 1..=y + 1 {
            for nx in x - 1..=x + 1 {
                let other = scores[(ny * width + nx) as usize];
                let earlier = (ny, nx) < (y, x);
                keep &= other < score || (other == score && !earlier);
            }
        }
        keep
    });
    corners
        .into_iter()
        .map(|(x, y, score)| (x, y, score - 1))
        .collect()
}

/// Up to `wanted` candidates spread over a grid of `cell_px`-pixel cells: the strongest of every
/// cell first (strongest cells first), then the second of every cell, and so on. With `cell_px`
/// 0, the strongest overall. Deterministic: ties keep raster order.
fn spread(
    mut candidates: Vec<Candidate>,
    wanted: usize,
    cell_px: u32,
    image: &GrayImage,
) -> Vec<Candidate> {
    // Stable: equal scores keep raster order.
    candidates.sort_by_key(|c| std::cmp::Reverse(c.score));
    if cell_px == 0 || candidates.len() <= wanted {
        candidates.truncate(wanted);
        return candidates;
    }
    let columns = image.width().div_ceil(cell_px) as usize;
    let cell = |c: &Candidate| (c.y / cell_px) as usize * columns + (c.x / cell_px) as usize;
    // Rank of each candidate within its cell, in the strongest-first order.
    let mut seen = vec![0usize; columns * image.height().div_ceil(cell_px) as usize];
    let mut ranked: Vec<(usize, Candidate)> = candidates
        .into_iter()
        .map(|c| {
            let slot = &mut seen[cell(&c)];
            *slot += 1;
            (*slot - 1, c)
        })
        .collect();
    // Stable again: within a rank, strongest first.
    ranked.sort_by_key(|&(rank, _)| rank);
    ranked.truncate(wanted);
    ranked.into_iter().map(|(_, c)| c).collect()
}

/// Side of a sampled patch: the test disc plus the boxes around its points.
const PATCH_SIZE: usize = (2 * (PATCH_RADIUS + BOX_RADIUS) + 1) as usize;
/// Centre index of a patch.
const PATCH_CENTRE: i32 = PATCH_RADIUS + BOX_RADIUS;
/// Pyramid levels available to metric patches (1.25^11 = 11.6: a 10 cm patch at 0.5 m).
const SAMPLING_LEVELS: usize = 12;
/// Surface normals from a grid of this many depth samples per side over the patch.
const NORMAL_GRID: i32 = 9;
/// A normal needs this many of the grid's samples on the keypoint's surface.
const MIN_NORMAL_SAMPLES: usize = 20;
/// Surfaces seen more obliquely than this (cosine between the normal and the viewing ray) are
/// described fronto-parallel: the rectification would stretch a few pixels over the patch.
const MIN_VIEW_COSINE: f64 = 0.3;

/// The grey values of a keypoint's patch, `PATCH_SIZE` x `PATCH_SIZE`, centred on it.
type Patch = [[f32; PATCH_SIZE]; PATCH_SIZE];

/// Cuts keypoint patches out of a keyframe: either the pixels around the corner on its level
/// (`descriptor_radius_m` 0), or a metric patch on the surface under it, sampled from the level
/// whose pixels match the sample spacing.
struct PatchSampler<'a> {
    pyramid: &'a [GrayImage],
    scale: f64,
    depth: &'a DepthImage,
    intrinsics: &'a Intrinsics,
    config: &'a AlignmentConfig,
}

impl PatchSampler<'_> {
    fn patch(&self, level: usize, c: &Candidate) -> Option<Patch> {
        if self.config.descriptor_radius_m <= 0.0 {
            return Some(self.pixel_patch(level, c));
        }
        self.metric_patch(c)
    }

    /// Pixels of the detection level around the corner (inside the keypoint border).
    fn pixel_patch(&self, level: usize, c: &Candidate) -> Patch {
        let image = &self.pyramid[level];
        let mut patch = [[0.0; PATCH_SIZE]; PATCH_SIZE];
        for (row, line) in patch.iter_mut().enumerate() {
            for (column, value) in line.iter_mut().enumerate() {
                let x = c.x as i32 + column as i32 - PATCH_CENTRE;
                let y = c.y as i32 + row as i32 - PATCH_CENTRE;
                *value = image.get_pixel(x as u32, y as u32).0[0] as f32;
            }
        }
        patch
    }

    /// A square of the surface under the keypoint, `2 descriptor_radius_m` across the test
    /// disc, on the plane through the keypoint normal to the surface (`rectify_patches`) or
    /// facing the camera. The same place seen from another distance or angle gives nearly the
    /// same patch. `None` when the patch leaves the image.
    fn metric_patch(&self, c: &Candidate) -> Option<Patch> {
        let k = self.intrinsics;
        let centre = k.back_project(c.u, c.v, c.z as f64).coords;
        let towards_camera = -centre.normalize();
        let normal = if self.config.rectify_patches {
            self.surface_normal(c, &centre)
                .filter(|n| n.dot(&towards_camera) >= MIN_VIEW_COSINE)
                .unwrap_or(towards_camera)
        } else {
            towards_camera
        };
        // In-plane axes: the camera's x axis laid onto the plane, and the one completing a
        // right-handed frame with the normal (the image's y for a plane facing the camera).
        let x_axis = Vector3::x();
        let e1 = (x_axis - normal * x_axis.dot(&normal)).try_normalize(1e-9)?;
        let e2 = e1.cross(&normal);
        let step = self.config.descriptor_radius_m / PATCH_RADIUS as f64;
        // Pick the level whose pixels are as large as the projected sample spacing.
        let spacing_px = [e1, e2]
            .iter()
            .filter_map(|axis| {
                let a = k.project(&Point3::from(centre))?;
                let b = k.project(&Point3::from(centre + axis * step))?;
                Some((b - a).norm())
            })
            .fold(0.0f64, f64::max);
        if spacing_px <= 0.0 {
            return None;
        }
        let level = ((spacing_px.ln() / self.scale.ln()).round().max(0.0) as usize)
            .min(self.pyramid.len() - 1);
        let image = &self.pyramid[level];
        let factor = self.scale.powi(level as i32);
        let mut patch = [[0.0; PATCH_SIZE]; PATCH_SIZE];
        for (row, line) in patch.iter_mut().enumerate() {
            for (column, value) in line.iter_mut().enumerate() {
                let a = (column as i32 - PATCH_CENTRE) as f64 * step;
                let b = (row as i32 - PATCH_CENTRE) as f64 * step;
                let point = Point3::from(centre + e1 * a + e2 * b);
                let pixel = k.project(&point)?;
                *value = bilinear(
                    image,
                    (pixel.x + 0.5) / factor - 0.5,
                    (pixel.y + 0.5) / factor - 0.5,
                )?;
            }
        }
        Some(patch)
    }

    /// The normal (towards the camera) of the depth surface around the keypoint: smallest
    /// principal axis of the points on a grid over the patch that lie within the patch radius
    /// of the keypoint in 3-D.
    fn surface_normal(&self, c: &Candidate, centre: &Vector3<f64>) -> Option<Vector3<f64>> {
        let k = self.intrinsics;
        let radius = self.config.descriptor_radius_m;
        let reach_px = k.fx * radius / c.z as f64;
        let mut points = Vec::with_capacity((NORMAL_GRID * NORMAL_GRID) as usize);
        let half = NORMAL_GRID / 2;
        for gy in -half..=half {
            for gx in -half..=half {
                let u = (c.u + gx as f64 * reach_px / half as f64).round();
                let v = (c.v + gy as f64 * reach_px / half as f64).round();
                if u < 0.0
                    || v < 0.0
                    || u >= self.depth.width as f64
                    || v >= self.depth.height as f64
                {
                    continue;
                }
                let z = self.depth.get(u as u32, v as u32) as f64;
                if !(z > 0.0 && z < self.config.truncation_m) {
                    continue;
                }
                let p = k.back_project(u, v, z).coords;
                if (p - centre).norm() <= radius {
                    points.push(p);
                }
            }
        }
        if points.len() < MIN_NORMAL_SAMPLES {
            return None;
        }
        let mean = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let covariance = points
            .iter()
            .map(|p| (p - mean) * (p - mean).transpose())
            .sum::<Matrix3<f64>>();
        let eigen = covariance.symmetric_eigen();
        let smallest = eigen.eigenvalues.imin();
        let normal = eigen.eigenvectors.column(smallest).into_owned();
        Some(if normal.dot(centre) > 0.0 {
            -normal
        } else {
            normal
        })
    }
}

/// Bilinear interpolation of `image` at (x, y) (pixel centres at integers); `None` outside.
fn bilinear(image: &GrayImage, x: f64, y: f64) -> Option<f32> {
    let (width, height) = (image.width() as f64, image.height() as f64);
    if !(x >= 0.0 && y >= 0.0 && x <= width - 1.0 && y <= height - 1.0) {
        return None;
    }
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
    let (x0, y0) = (x0 as u32, y0 as u32);
    let (x1, y1) = (
        (x0 + 1).min(image.width() - 1),
        (y0 + 1).min(image.height() - 1),
    );
    let at = |x: u32, y: u32| image.get_pixel(x, y).0[0] as f32;
    let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
    let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

/// Orientation of the patch disc: the direction from the centre to the intensity centroid
/// (Rosin's moments, as ORB), radians in image coordinates.
fn orientation(patch: &Patch) -> f32 {
    let (mut m10, mut m01) = (0.0f64, 0.0f64);
    for dy in -PATCH_RADIUS..=PATCH_RADIUS {
        // Half-width of the disc on this row.
        let half = ((PATCH_RADIUS * PATCH_RADIUS - dy * dy) as f64).sqrt() as i32;
        let row = &patch[(PATCH_CENTRE + dy) as usize];
        for dx in -half..=half {
            let value = row[(PATCH_CENTRE + dx) as usize] as f64;
            m10 += dx as f64 * value;
            m01 += dy as f64 * value;
        }
    }
    m01.atan2(m10) as f32
}

/// Box means of a patch: `sums[y][x]` is the sum of the (2 BOX_RADIUS + 1)^2 box centred on
/// (x, y), for centres at least BOX_RADIUS inside the patch.
fn box_sums(patch: &Patch) -> Patch {
    // Summed-area table with a zero first row and column.
    let mut table = [[0.0f32; PATCH_SIZE + 1]; PATCH_SIZE + 1];
    for y in 0..PATCH_SIZE {
        let mut row = 0.0;
        for x in 0..PATCH_SIZE {
            row += patch[y][x];
            table[y + 1][x + 1] = table[y][x + 1] + row;
        }
    }
    let mut sums = [[0.0f32; PATCH_SIZE]; PATCH_SIZE];
    let r = BOX_RADIUS as usize;
    for (y, line) in sums.iter_mut().enumerate().take(PATCH_SIZE - r).skip(r) {
        for (x, sum) in line.iter_mut().enumerate().take(PATCH_SIZE - r).skip(r) {
            let (x0, y0, x1, y1) = (x - r, y - r, x + r + 1, y + r + 1);
            *sum = table[y1][x1] + table[y0][x0] - table[y0][x1] - table[y1][x0];
        }
    }
    sums
}

/// The steered BRIEF descriptor of a patch whose pattern is turned by `angle`.
fn descriptor(patch: &Patch, angle: f32) -> Descriptor {
    let sums = box_sums(patch);
    let (sin, cos) = angle.sin_cos();
    // A pattern offset turned by `angle` and rounded to a patch sample.
    let at = |[dx, dy]: [f32; 2]| {
        let rx = (cos * dx - sin * dy).round() as i32;
        let ry = (sin * dx + cos * dy).round() as i32;
        sums[(PATCH_CENTRE + ry) as usize][(PATCH_CENTRE + rx) as usize]
    };
    let mut descriptor = [0u128; DESCRIPTOR_WORDS];
    for (bit, pair) in test_pairs().iter().enumerate() {
        if at(pair.p0) < at(pair.p1) {
            descriptor[bit / 128] |= 1u128 << (bit % 128);
        }
    }
    descriptor
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

/// Bits in which two descriptors differ.
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
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
///
/// Mutual only: every keypoint's nearest neighbour in either direction keeps about twice the
/// correct matches but four times the wrong ones, which uniform 3-point RANSAC cannot sort out
/// within its budget (on the synthetic pairs of `examples/keyframe_matching`, fewer pairs aligned:
/// docs/benchmarks.md).
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
    fn test_pairs_are_fixed_and_inside_the_patch_disc() {
        let a = test_pairs();
        assert_eq!(a, draw_test_pairs().as_slice());
        assert_eq!(a.len(), DESCRIPTOR_BITS);
        let radius = PATCH_RADIUS as f32;
        assert!(a.iter().all(|p| {
            p.p0 != p.p1
                && [p.p0, p.p1]
                    .iter()
                    .all(|[x, y]| x * x + y * y <= radius * radius)
        }));
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
            keypoints: Vec::new(),
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

    /// Correct matches between `source` and `target` when a source keypoint at level-0 pixel
    /// `p` should be found at `map(p)` in the target (within 1.5 pixels), and all matches.
    fn correct_matches(
        source: &Features,
        target: &Features,
        config: &AlignmentConfig,
        map: impl Fn(f64, f64) -> (f64, f64),
    ) -> (usize, usize) {
        let matches = match_features(source, target, config);
        let correct = matches
            .iter()
            .filter(|&&(i, j)| {
                let (u, v) = map(source.keypoints[i].u, source.keypoints[i].v);
                let (tu, tv) = (target.keypoints[j].u, target.keypoints[j].v);
                (u - tu).hypot(v - tv) <= 1.5
            })
            .count();
        (correct, matches.len())
    }

    #[test]
    fn steered_descriptors_match_a_view_turned_by_90_degrees() {
        // The camera rolled by 90 degrees about its optical axis: the image turns clockwise,
        // pixel (x, y) moves to (height - 1 - y, x).
        let (width, height) = (240u32, 180u32);
        let source_image = blocky_texture(width, height);
        let target_image = image::imageops::rotate90(&source_image);
        let mut depth = DepthImage::new(width, height);
        depth.data.fill(2.0);
        let mut turned_depth = DepthImage::new(height, width);
        turned_depth.data.fill(2.0);
        let k = Intrinsics::new(200.0, 200.0, 119.5, 89.5, width, height);
        let turned_k = Intrinsics::new(200.0, 200.0, 89.5, 119.5, height, width);
        let turn = |u: f64, v: f64| (height as f64 - 1.0 - v, u);
        for radius in [0.0, 0.08] {
            let steered = AlignmentConfig {
                descriptor_radius_m: radius,
                ..AlignmentConfig::default()
            };
            let unsteered = AlignmentConfig {
                steer_descriptors: false,
                ..steered.clone()
            };
            let count = |config: &AlignmentConfig| {
                let source = extract(&source_image, &depth, &k, config);
                let target = extract(&target_image, &turned_depth, &turned_k, config);
                correct_matches(&source, &target, config, turn)
            };
            let (correct, all) = count(&steered);
            let (unsteered_correct, _) = count(&unsteered);
            eprintln!(
                "patch radius {radius} m: steered {correct} of {all} correct, unsteered {unsteered_correct}"
            );
            assert!(
                correct >= 100 && correct * 10 >= all * 8,
                "patch radius {radius} m: {correct} of {all} matches correct"
            );
            assert!(unsteered_correct * 4 < correct);
        }
    }

    #[test]
    fn keypoints_spread_over_the_image() {
        // Strong texture in the left quarter, faint texture elsewhere.
        let (width, height) = (320u32, 240u32);
        let texture = blocky_texture(width, height);
        let image = RgbImage::from_fn(width, height, |x, y| {
            let v = texture.get_pixel(x, y).0[0];
            let v = if x < width / 4 { v } else { 100 + v / 8 };
            image::Rgb([v, v, v])
        });
        let mut depth = DepthImage::new(width, height);
        depth.data.fill(2.0);
        let k = Intrinsics::new(260.0, 260.0, 159.5, 119.5, width, height);
        let in_strong_part = |cell_px: u32| {
            let config = AlignmentConfig {
                keypoint_cell_px: cell_px,
                features_per_image: 300,
                ..AlignmentConfig::default()
            };
            let features = extract(&image, &depth, &k, &config);
            let strong = features
                .keypoints
                .iter()
                .filter(|p| p.u < (width / 4) as f64)
                .count();
            strong as f64 / features.len() as f64
        };
        let (spread, strongest_first) = (in_strong_part(32), in_strong_part(0));
        eprintln!(
            "in the textured quarter: {spread:.2} spread, {strongest_first:.2} strongest first"
        );
        assert!(strongest_first > 0.9 && spread < 0.5);
    }

    #[test]
    fn one_corner_per_blob() {
        let mut image = GrayImage::new(80, 80);
        for y in 30..50 {
            for x in 30..50 {
                image.put_pixel(x, y, image::Luma([200]));
            }
        }
        image.put_pixel(60, 60, image::Luma([255]));
        let corners = local_maxima(&image, 20);
        assert!(!corners.is_empty());
        for (a, &(xa, ya, _)) in corners.iter().enumerate() {
            for &(xb, yb, _) in &corners[a + 1..] {
                assert!(xa.abs_diff(xb) > 1 || ya.abs_diff(yb) > 1, "{corners:?}");
            }
        }
        // The four corners of the square and the single bright pixel, nothing else.
        assert!(corners.len() <= 5 * 2, "{corners:?}");
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
