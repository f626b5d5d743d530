//! The maps the bench registers: built from a dataset's frames and their ground-truth poses,
//! coloured by their pixels, with the depth views that made them (for the free-space test), and
//! written as Gaussian maps for the peers.

use std::path::Path;

use anyhow::Context;
use datasets::FrameRange;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use registration::covariance::smallest_eigenvector;
use registration::map_registration::colour::Rgb;
use registration::{PointCloud, PointTree, points_from_depth};
use splats::GaussianCloud;

/// Depth beyond this is not used (metres).
const TRUNCATION_M: f64 = 8.0;
/// Largest distance of the random frame's origin (metres).
const RANDOM_FRAME_RADIUS_M: f64 = 5.0;
/// Pixels between the points of a view's sample (in x and y): what says which crop a view
/// belongs to.
const VIEW_SAMPLE_STRIDE: usize = 16;
/// Neighbours of a map point whose spread gives its Gaussian's normal.
const GAUSSIAN_NEIGHBOURS: usize = 10;
/// Flatness of a Gaussian (normal axis over tangent axes), the G-ICP plane shape the agents seed.
const GAUSSIAN_FLATNESS: f64 = 0.03;
/// Opacity of the written Gaussians.
const GAUSSIAN_OPACITY: f64 = 0.9;

/// SplitMix64: a few seeded random numbers without a dependency.
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A uniformly random rotation (Shoemake's method) and a translation uniform in a ball.
pub fn random_frame(seed: u64) -> Isometry3<f64> {
    let mut rng = SplitMix(seed ^ 0x006d_6170_5f72_6567);
    let (u1, u2, u3) = (rng.unit(), rng.unit(), rng.unit());
    let tau = std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let q = nalgebra::Quaternion::new(
        b * (tau * u3).cos(),
        a * (tau * u2).sin(),
        a * (tau * u2).cos(),
        b * (tau * u3).sin(),
    );
    let direction = loop {
        let v = Vector3::new(rng.unit(), rng.unit(), rng.unit()) * 2.0 - Vector3::repeat(1.0);
        if v.norm() <= 1.0 && v.norm() > 1e-3 {
            break v;
        }
    };
    Isometry3::from_parts(
        Translation3::from(direction * RANDOM_FRAME_RADIUS_M),
        UnitQuaternion::from_quaternion(q),
    )
}

/// One depth image that built a map, placed in the map's frame.
#[derive(Clone)]
pub struct View {
    /// Shared by every crop and pair that keeps the view: a run holds each image once (100
    /// pairs of redkitchen crops held 20 GB when each pair had copies).
    pub depth: std::sync::Arc<DepthImage>,
    pub intrinsics: Intrinsics,
    pub map_from_camera: Isometry3<f64>,
    /// Every [`VIEW_SAMPLE_STRIDE`]-th pixel's point in the map frame.
    pub sample: Vec<Point3<f32>>,
}

/// A map's points with their colours, and the views they came from.
#[derive(Clone, Default)]
pub struct Map {
    pub points: Vec<Point3<f32>>,
    pub colours: Vec<Rgb>,
    pub views: Vec<View>,
}

impl Map {
    /// The points (with their colours) `keep` keeps, and no views.
    pub fn filtered(&self, keep: impl Fn(&Point3<f32>) -> bool) -> Self {
        let (points, colours) = self
            .points
            .iter()
            .zip(&self.colours)
            .filter(|(p, _)| keep(p))
            .map(|(p, c)| (*p, *c))
            .unzip();
        Self {
            points,
            colours,
            views: Vec::new(),
        }
    }

    /// The map moved by `frame_from_map` (points and views).
    pub fn moved(mut self, frame_from_map: &Isometry3<f64>) -> Self {
        let move_point = |p: &mut Point3<f32>| *p = (frame_from_map * p.cast::<f64>()).cast();
        self.points.iter_mut().for_each(move_point);
        for view in &mut self.views {
            view.map_from_camera = frame_from_map * view.map_from_camera;
            view.sample.iter_mut().for_each(move_point);
        }
        self
    }

    /// At most `max_points` points: a seeded random subset above (partial Fisher-Yates).
    pub fn capped(mut self, max_points: usize, seed: u64) -> Self {
        if self.points.len() > max_points {
            let mut rng = SplitMix(seed ^ 0x0000_7375_6273_6574);
            for i in 0..max_points {
                let j = i + (rng.next_u64() % (self.points.len() - i) as u64) as usize;
                self.points.swap(i, j);
                self.colours.swap(i, j);
            }
            self.points.truncate(max_points);
            self.colours.truncate(max_points);
        }
        self
    }

    /// One point per cell of `spacing_m` (centroids and mean colours), without views.
    pub fn resampled(&self, spacing_m: f64) -> Self {
        let down = registration::map_registration::downsample::voxel_downsample_coloured(
            &self.points,
            Some(&self.colours),
            spacing_m,
        );
        Self {
            points: down.points,
            colours: down.colours.expect("coloured input"),
            views: Vec::new(),
        }
    }

    /// Map colours multiplied per channel by `gains` (another white balance), clamped to 1.
    pub fn white_balanced(mut self, gains: [f32; 3]) -> Self {
        for c in &mut self.colours {
            for (v, g) in c.iter_mut().zip(gains) {
                *v = (*v * g).min(1.0);
            }
        }
        self
    }
}

/// How a map is made from a dataset (see the bench's module documentation).
pub struct MapRecipe<'a> {
    pub spec: &'a str,
    pub frames: FrameRange,
    /// Back-project every n-th frame of `frames`, starting at the `offset`-th.
    pub every: usize,
    pub offset: usize,
    pub pixel_stride: usize,
    /// One point per cell of this size (metres).
    pub map_voxel_m: f64,
}

/// The world-frame map of a dataset's frames, with colours and views.
pub fn build_map(recipe: &MapRecipe<'_>) -> anyhow::Result<Map> {
    let spec = recipe.spec;
    let ds = datasets::open(spec, recipe.frames).with_context(|| format!("opening {spec}"))?;
    anyhow::ensure!(!ds.is_empty(), "{spec}: no frames in {}", recipe.frames);
    let mut points = Vec::new();
    let mut colours = Vec::new();
    let mut views = Vec::new();
    for position in (recipe.offset..ds.len()).step_by(recipe.every.max(1)) {
        let frame = ds.load(position)?;
        let pose = frame
            .world_from_camera_gt
            .with_context(|| format!("{spec}: frame {} has no ground-truth pose", frame.index))?;
        let cloud = points_from_depth(
            &frame.depth,
            &frame.intrinsics,
            recipe.pixel_stride,
            TRUNCATION_M,
        );
        let world = |p: &Point3<f32>| (pose * p.cast::<f64>()).cast::<f32>();
        points.extend(cloud.positions.iter().map(world));
        let width = frame.rgb.width();
        colours.extend(cloud.pixels.iter().map(|&pixel| {
            let rgb = frame.rgb.get_pixel(pixel % width, pixel / width).0;
            rgb.map(|c| f32::from(c) / 255.0)
        }));
        let sparse = points_from_depth(
            &frame.depth,
            &frame.intrinsics,
            VIEW_SAMPLE_STRIDE,
            TRUNCATION_M,
        );
        views.push(View {
            sample: sparse.positions.iter().map(world).collect(),
            depth: std::sync::Arc::new(frame.depth),
            intrinsics: frame.intrinsics,
            map_from_camera: pose,
        });
    }
    let down = registration::map_registration::downsample::voxel_downsample_coloured(
        &points,
        Some(&colours),
        recipe.map_voxel_m,
    );
    Ok(Map {
        points: down.points,
        colours: down.colours.expect("coloured input"),
        views,
    })
}

/// Fraction of `b`'s points with a point of `a` within `distance_m`, over the smaller map.
pub fn overlap_of_smaller(a: &[Point3<f32>], b: &[Point3<f32>], distance_m: f64) -> f64 {
    let Ok(tree) = PointTree::new(a.to_vec()) else {
        return f64::NAN;
    };
    let limit = (distance_m * distance_m) as f32;
    let near = b
        .iter()
        .filter(|p| tree.nearest(p).is_some_and(|(_, d)| d <= limit))
        .count();
    (near as f64 / a.len().min(b.len()).max(1) as f64).min(1.0)
}

/// The map as Gaussians, as an agent seeds them from depth: mean and colour of each point,
/// flattened along the normal of its neighbourhood (the G-ICP plane shape), tangent standard
/// deviation half the map's spacing, opacity 0.9.
pub fn gaussian_map(map: &Map, spacing_m: f64) -> anyhow::Result<GaussianCloud> {
    let tree = PointTree::with_covariances(
        PointCloud::from_positions(map.points.clone()),
        GAUSSIAN_NEIGHBOURS,
        1e-3,
    )
    .context("map points for the Gaussian map")?;
    let tangent = (0.5 * spacing_m).ln() as f32;
    let normal = (0.5 * spacing_m * GAUSSIAN_FLATNESS).ln() as f32;
    let opacity_logit = (GAUSSIAN_OPACITY / (1.0 - GAUSSIAN_OPACITY)).ln() as f32;
    let mut cloud = GaussianCloud::default();
    for (i, (p, colour)) in map.points.iter().zip(&map.colours).enumerate() {
        let n = smallest_eigenvector(&tree.cloud().covariances[i].to_matrix());
        let n = if n.iter().all(|v| v.is_finite()) && n.norm() > 0.0 {
            n.normalize()
        } else {
            Vector3::z()
        };
        let q = UnitQuaternion::from_rotation_matrix(&frame_with_third_axis(&n));
        cloud.push(
            [p.x, p.y, p.z],
            [tangent, tangent, normal],
            [q.w, q.i, q.j, q.k].map(|v| v as f32),
            opacity_logit,
            *colour,
        );
    }
    Ok(cloud)
}

/// A rotation whose third column is `axis` (unit).
fn frame_with_third_axis(axis: &Vector3<f64>) -> Rotation3<f64> {
    let helper = if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = helper.cross(axis).normalize();
    let v = axis.cross(&u);
    Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[u, v, *axis]))
}

/// Writes the Gaussian map of `map` to `path`.
pub fn write_gaussian_map(path: &Path, map: &Map, spacing_m: f64) -> anyhow::Result<()> {
    let cloud = gaussian_map(map, spacing_m)?;
    splats::ply::save_ply(path, &cloud).with_context(|| format!("writing {}", path.display()))
}
