//! Keypoint description: the patch under a keypoint (pixels on its level, or a metric patch on
//! the surface under it), its intensity-centroid orientation, and the steered BRIEF tests.

use std::sync::OnceLock;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::GrayImage;
use nalgebra::{Matrix3, Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::{
    BOX_RADIUS, Candidate, DESCRIPTOR_BITS, DESCRIPTOR_WORDS, Descriptor, PATCH_RADIUS,
    TEST_PAIR_SEED, TEST_POINT_SIGMA,
};
use crate::alignment::AlignmentConfig;

/// One intensity test: offsets of its two points from the keypoint (pixels, image axes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct TestPair {
    pub(super) p0: [f32; 2],
    pub(super) p1: [f32; 2],
}

/// The fixed test pattern, drawn once from [`TEST_PAIR_SEED`].
pub(super) fn test_pairs() -> &'static [TestPair] {
    static PAIRS: OnceLock<Vec<TestPair>> = OnceLock::new();
    PAIRS.get_or_init(draw_test_pairs)
}

/// Gaussian points inside the patch disc, rounded to whole pixels.
pub(super) fn draw_test_pairs() -> Vec<TestPair> {
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

/// Side of a sampled patch: the test disc plus the boxes around its points.
pub(super) const PATCH_SIZE: usize = (2 * (PATCH_RADIUS + BOX_RADIUS) + 1) as usize;
/// Centre index of a patch.
pub(super) const PATCH_CENTRE: i32 = PATCH_RADIUS + BOX_RADIUS;
/// Pyramid levels available to metric patches (1.25^11 = 11.6: a 10 cm patch at 0.5 m).
pub(super) const SAMPLING_LEVELS: usize = 12;
/// Surface normals from a grid of this many depth samples per side over the patch.
pub(super) const NORMAL_GRID: i32 = 9;
/// A normal needs this many of the grid's samples on the keypoint's surface.
pub(super) const MIN_NORMAL_SAMPLES: usize = 20;
/// Surfaces seen more obliquely than this (cosine between the normal and the viewing ray) are
/// described fronto-parallel: the rectification would stretch a few pixels over the patch.
pub(super) const MIN_VIEW_COSINE: f64 = 0.3;

/// The grey values of a keypoint's patch, `PATCH_SIZE` x `PATCH_SIZE`, centred on it.
pub(super) type Patch = [[f32; PATCH_SIZE]; PATCH_SIZE];

/// Cuts keypoint patches out of a keyframe: either the pixels around the corner on its level
/// (`descriptor_radius_m` 0), or a metric patch on the surface under it, sampled from the level
/// whose pixels match the sample spacing.
pub(super) struct PatchSampler<'a> {
    pub(super) pyramid: &'a [GrayImage],
    pub(super) scale: f64,
    pub(super) depth: &'a DepthImage,
    pub(super) intrinsics: &'a Intrinsics,
    pub(super) config: &'a AlignmentConfig,
}

impl PatchSampler<'_> {
    pub(super) fn patch(&self, level: usize, c: &Candidate) -> Option<Patch> {
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
pub(super) fn bilinear(image: &GrayImage, x: f64, y: f64) -> Option<f32> {
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
pub(super) fn orientation(patch: &Patch) -> f32 {
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
pub(super) fn box_sums(patch: &Patch) -> Patch {
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
pub(super) fn descriptor(patch: &Patch, angle: f32) -> Descriptor {
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
