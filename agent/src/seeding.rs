//! Seeding (docs/method.md, Seeding): new Gaussians from a keyframe's points.
//!
//! A keyframe's back-projected points (camera frame, each with its G-ICP covariance and the pixel
//! it came from) become Gaussians in the agent's world frame:
//! - mean: the point in the world frame;
//! - colour: the point's pixel;
//! - opacity: `keyframes.initial_opacity` (stored as its logit);
//! - rotation: the eigenvectors of the point's covariance (surface tangents and normal);
//! - scale: see [`SeedScale`]; the normal axis is `sqrt(covariance_epsilon)` times the tangent
//!   axes, the G-ICP plane shape.
//!
//! Which points seed (the method's rule, applied by [`crate::mapper`]'s caller): every point at a
//! tracking keyframe; at a mapping keyframe only the points no Gaussian covers yet
//! ([`CoverageIndex`]).

use geometry::camera::Intrinsics;
use image::RgbImage;
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use registration::config::{KeyframeConfig, SeedScale, TrackingConfig};
use registration::covariance::{Covariance, smallest_eigenvector};
use registration::points::PointCloud;
use registration::voxel_map::{MapPoint, MapPointId, VoxelMap};
use splats::GaussianCloud;

/// The published seeding scale (docs/method.md, Seeding):
/// `sqrt(eigenvalue) / max(1, PUBLISHED_DEPTH_FACTOR * z^PUBLISHED_DEPTH_EXPONENT)`.
const PUBLISHED_DEPTH_FACTOR: f64 = 2.0;
const PUBLISHED_DEPTH_EXPONENT: f64 = 1.5;

fn logit(probability: f64) -> f32 {
    (probability / (1.0 - probability)).ln() as f32
}

/// Everything seeding needs about the keyframe.
pub struct SeedFrame<'a> {
    /// Points in the camera frame, with covariances and source pixels.
    pub points: &'a PointCloud,
    /// The keyframe's camera in the agent's local-map frame, where the Gaussians are placed.
    pub world_from_camera: &'a Isometry3<f64>,
    /// The keyframe's colour image: each Gaussian takes its point's pixel.
    pub rgb: &'a RgbImage,
    /// The keyframe's intrinsics: their mean focal length sets the `sample_footprint` scale.
    pub intrinsics: &'a Intrinsics,
}

/// Gaussians for the points of `frame` selected by `selected` (one flag per point).
pub fn seed_gaussians(
    frame: &SeedFrame<'_>,
    selected: &[bool],
    tracking: &TrackingConfig,
    keyframes: &KeyframeConfig,
) -> GaussianCloud {
    let points = frame.points;
    let mut cloud = GaussianCloud::default();
    let opacity_logit = logit(keyframes.initial_opacity);
    let focal = 0.5 * (frame.intrinsics.fx + frame.intrinsics.fy);
    let normal_ratio = tracking.covariance_epsilon.sqrt();
    let world_rotation = frame.world_from_camera.rotation.to_rotation_matrix();
    let width = frame.rgb.width();
    for (index, position) in points.positions.iter().enumerate() {
        if !selected.get(index).copied().unwrap_or(false) {
            continue;
        }
        let camera_point = position.cast::<f64>();
        let depth = camera_point.z;
        if !(depth.is_finite() && depth > 0.0) {
            continue;
        }
        let normal = match points.covariances.get(index) {
            Some(covariance) => surface_normal(covariance, &camera_point),
            None => -camera_point.coords.normalize(),
        };
        let tangent_sigma = match keyframes.seed_scale {
            SeedScale::Published => {
                1.0 / (PUBLISHED_DEPTH_FACTOR * depth.powf(PUBLISHED_DEPTH_EXPONENT)).max(1.0)
            }
            SeedScale::SampleFootprint => {
                keyframes.footprint_sigma_per_spacing * tracking.pixel_stride as f64 * depth / focal
            }
        };
        let normal_sigma = tangent_sigma * normal_ratio;
        let rotation = world_rotation * frame_with_normal(&normal);
        let quaternion = UnitQuaternion::from_rotation_matrix(&rotation);
        let world_point = frame.world_from_camera * camera_point;
        let colour = points
            .pixels
            .get(index)
            .map(|&pixel| {
                let rgb = frame.rgb.get_pixel(pixel % width, pixel / width).0;
                rgb.map(|c| f32::from(c) / 255.0)
            })
            .unwrap_or([0.5; 3]);
        cloud.push(
            [world_point.x, world_point.y, world_point.z].map(|v| v as f32),
            [tangent_sigma, tangent_sigma, normal_sigma].map(|s| s.ln() as f32),
            [quaternion.w, quaternion.i, quaternion.j, quaternion.k].map(|v| v as f32),
            opacity_logit,
            colour,
        );
    }
    cloud
}

/// The surface normal of a point's G-ICP covariance (the direction of least spread), turned to
/// face the camera (the sign is arbitrary in the eigenvector).
fn surface_normal(covariance: &Covariance, camera_point: &Point3<f64>) -> Vector3<f64> {
    let normal = smallest_eigenvector(&covariance.to_matrix());
    let normal = if normal.iter().all(|v| v.is_finite()) && normal.norm() > 0.0 {
        normal.normalize()
    } else {
        -camera_point.coords.normalize()
    };
    if normal.dot(&camera_point.coords) > 0.0 {
        -normal
    } else {
        normal
    }
}

/// A right-handed rotation whose third axis is `normal` (the Gaussian's local z carries the thin
/// scale).
fn frame_with_normal(normal: &Vector3<f64>) -> Rotation3<f64> {
    let helper = if normal.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let first = helper.cross(normal).normalize();
    let second = normal.cross(&first);
    Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[first, second, *normal]))
}

/// Where the map already has Gaussians: a voxel hash of every seeded mean, answering "is there a
/// Gaussian within r of this point" for the mapping-keyframe seeding rule.
pub struct CoverageIndex {
    map: VoxelMap,
    next_id: u64,
}

impl CoverageIndex {
    /// Index for queries up to `radius_m`.
    pub fn new(radius_m: f64) -> Self {
        Self {
            map: VoxelMap::for_correspondence_distance(radius_m.max(f64::EPSILON)),
            next_id: 0,
        }
    }

    /// Number of means indexed.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// Whether no mean is indexed.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// Per point of `frame`: true when no indexed Gaussian lies within sqrt(`radius_sq_m2`).
    pub fn uncovered(&self, frame: &SeedFrame<'_>, radius_sq_m2: f64) -> Vec<bool> {
        frame
            .points
            .positions
            .iter()
            .map(|p| {
                let world = (frame.world_from_camera * p.cast::<f64>()).cast::<f32>();
                self.map
                    .nearest_in_map(&world, radius_sq_m2 as f32)
                    .is_none()
            })
            .collect()
    }

    /// Adds the means of `cloud`.
    pub fn insert(&mut self, cloud: &GaussianCloud) {
        for mean in &cloud.means {
            let point = MapPoint {
                id: self.next_id,
                position: Point3::from(*mean),
                covariance: Covariance::IDENTITY,
            };
            self.next_id += 1;
            // Seeded means are finite (finite points under a finite pose).
            let _ = self.map.insert(point);
        }
    }

    /// Id the next inserted mean gets (ids count up in insertion order).
    pub fn next_id(&self) -> MapPointId {
        self.next_id
    }

    /// Moves the indexed means with a correction ([`VoxelMap::transform_points`]).
    pub fn transform_points(
        &mut self,
        transform_of: impl FnMut(MapPointId) -> Option<Isometry3<f64>>,
    ) -> usize {
        self.map.transform_points(transform_of)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use registration::covariance::Covariance;

    fn one_point_frame(z: f32) -> (PointCloud, RgbImage, Intrinsics) {
        let mut points = PointCloud::from_positions(vec![Point3::new(0.0, 0.0, z)]);
        // A wall facing the camera: normal along z.
        points.covariances = vec![Covariance::plane(&Vector3::z(), 1e-3)];
        points.pixels = vec![5];
        let rgb = RgbImage::from_fn(4, 4, |x, y| image::Rgb([(x * 60) as u8, (y * 60) as u8, 7]));
        (points, rgb, Intrinsics::new(500.0, 500.0, 1.5, 1.5, 4, 4))
    }

    #[test]
    fn a_seeded_gaussian_sits_on_the_point_with_its_pixel_colour_and_a_thin_disc() {
        let (points, rgb, intrinsics) = one_point_frame(2.0);
        let world_from_camera = Isometry3::translation(1.0, 0.0, 0.0);
        let frame = SeedFrame {
            points: &points,
            world_from_camera: &world_from_camera,
            rgb: &rgb,
            intrinsics: &intrinsics,
        };
        let tracking = TrackingConfig::default();
        let keyframes = KeyframeConfig {
            footprint_sigma_per_spacing: 0.5,
            ..KeyframeConfig::default()
        };
        let cloud = seed_gaussians(&frame, &[true], &tracking, &keyframes);
        assert_eq!(cloud.len(), 1);
        assert_eq!(cloud.means[0], [1.0, 0.0, 2.0]);
        // Pixel 5 of a 4-wide image is (1, 1).
        assert_eq!(cloud.colours[0], [60.0 / 255.0, 60.0 / 255.0, 7.0 / 255.0]);
        let opacity = 1.0 / (1.0 + (-cloud.opacity_logits[0]).exp());
        assert!((opacity - 0.1).abs() < 1e-6);
        let scales = cloud.log_scales[0].map(f32::exp);
        // Stride 5 at 2 m with f = 500: samples 2 cm apart, sigma 1 cm.
        assert!((scales[0] - 0.01).abs() < 1e-6, "{scales:?}");
        assert!((scales[2] / scales[0] - 1e-3f32.sqrt()).abs() < 1e-6);
        // The thin axis (local z) is the wall normal (world z).
        let [w, x, y, z] = cloud.quaternions[0].map(f64::from);
        let rotation = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        let thin_axis = rotation * Vector3::z();
        assert!(thin_axis.z.abs() > 0.999, "{thin_axis:?}");

        let spec = KeyframeConfig {
            seed_scale: SeedScale::Published,
            ..KeyframeConfig::default()
        };
        let cloud = seed_gaussians(&frame, &[true], &tracking, &spec);
        let expected = 1.0 / (2.0 * 2.0f64.powf(1.5));
        assert!((f64::from(cloud.log_scales[0][0].exp()) - expected).abs() < 1e-6);
        // Unselected points seed nothing.
        assert!(seed_gaussians(&frame, &[false], &tracking, &keyframes).is_empty());
    }

    #[test]
    fn coverage_finds_points_near_seeded_gaussians_only() {
        let (points, rgb, intrinsics) = one_point_frame(2.0);
        let identity = Isometry3::identity();
        let frame = SeedFrame {
            points: &points,
            world_from_camera: &identity,
            rgb: &rgb,
            intrinsics: &intrinsics,
        };
        let mut coverage = CoverageIndex::new(0.02);
        assert_eq!(coverage.uncovered(&frame, 4e-4), vec![true]);
        let mut near = GaussianCloud::default();
        near.push(
            [0.0, 0.01, 2.0],
            [0.0; 3],
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            [0.0; 3],
        );
        coverage.insert(&near);
        assert_eq!(coverage.uncovered(&frame, 4e-4), vec![false]);
        assert_eq!(coverage.uncovered(&frame, 1e-5), vec![true]);
    }
}
