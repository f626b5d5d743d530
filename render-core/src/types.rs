//! CPU-side scene description shared by the CPU reference and the wgpu renderer.
//!
//! Conventions (they hold at every public boundary of this crate):
//! - Quaternions are `[w, x, y, z]` (w first). They need not be unit length; the renderer
//!   normalises them. A quaternion of (near) zero length culls its Gaussian.
//! - Camera frame is the OpenCV one: x right, y down, z forward (the viewing direction).
//! - Pixel `(col, row)` has its centre at image coordinate `(col, row)`, so a principal point
//!   `cx = (width - 1) / 2` is the image centre (Replica: `cx = 599.5` for width 1200).
//! - Colours are SH degree 0 already converted to linear RGB in `[0, 1]` (not `f_dc`); see
//!   [`crate::ply`] for the `f_dc` conversion used in files.

use geometry::camera::Intrinsics;
use glam::{DMat3, DQuat, DVec3, Mat3, Quat, Vec3};

/// Activation and rasterisation constants of the image model (docs/method.md, The map) and the
/// 3DGS reference.
pub mod constants {
    /// Side of a square screen tile in pixels.
    pub const TILE_SIZE: u32 = 16;
    /// Largest alpha a single splat may contribute (keeps `1 - alpha` invertible in backward).
    pub const MAX_SPLAT_ALPHA: f32 = 0.99;
    /// Splats whose alpha at a pixel falls below this are skipped there.
    pub const MIN_SPLAT_ALPHA: f32 = 1.0 / 255.0;
    /// A pixel stops compositing once its transmittance would drop below this.
    pub const MIN_TRANSMITTANCE: f32 = 1e-4;
    /// Isotropic variance (pixels^2) added to every projected 2D covariance: a low-pass filter
    /// so that a splat covers at least about one pixel (standard 3DGS value).
    pub const LOW_PASS_VARIANCE: f32 = 0.3;
    /// Gaussians closer to the camera than this (camera z, metres) are culled.
    pub const NEAR_PLANE: f32 = 0.01;
    /// Gaussians whose mean projects further outside the image than this fraction of the
    /// image's width (or height) are culled. The projection linearises around the mean (EWA);
    /// far off-axis (a mean beside the camera, `x/z` large) the linearisation explodes into a
    /// splat that covers the whole image with a wrong colour. 3DGS clamps `x/z` at 1.3 times
    /// the half field of view in the Jacobian for the same reason; culling instead keeps the
    /// gradients of every splat that is drawn exact.
    pub const FRUSTUM_GUARD_BAND: f32 = 0.3;
    /// Screen-space extent of a splat, in standard deviations of its largest axis.
    pub const SPLAT_EXTENT_SIGMAS: f32 = 3.0;
    /// Quaternions with squared norm below this are treated as invalid and culled.
    pub const MIN_QUATERNION_NORM_SQUARED: f32 = 1e-12;
    /// Largest log-scale accepted; larger values (exp overflow territory) cull the Gaussian.
    pub const MAX_LOG_SCALE: f32 = 20.0;
    /// Bits of a splat's depth sort key (see [`super::depth_sort_key`]): three 8-bit radix
    /// passes instead of four for the full f32.
    pub const DEPTH_KEY_BITS: u32 = 24;
    /// Low mantissa bits of the camera z the depth sort key drops.
    pub const DEPTH_KEY_DROPPED_BITS: u32 = 4;
    /// The largest depth sort key of a visible splat, one below the culled key's
    /// [`DEPTH_KEY_BITS`] low bits.
    pub const LARGEST_VISIBLE_DEPTH_KEY: u32 = (1 << DEPTH_KEY_BITS) - 2;
    /// The depth sort key of a culled splat: above every visible key, so culled splats sort
    /// last.
    pub const CULLED_DEPTH_KEY: u32 = u32::MAX;
}

/// The key splats are depth-sorted by (ascending; ties keep the Gaussian order): camera z's
/// f32 bit pattern relative to the near plane's, without its
/// [`constants::DEPTH_KEY_DROPPED_BITS`] lowest mantissa bits, in [`constants::DEPTH_KEY_BITS`]
/// bits. Positive floats order like their bit patterns, so the key orders like z. Dropping 4 of
/// the 23 mantissa bits merges depths closer than 2^-19 of z (6 um at 3 m) into one key; 24
/// bits then span 2^(24+4-23) = 32 binades above the near plane (0.01 m to 4.3e7 m). Farther
/// splats share the largest key; [`constants::CULLED_DEPTH_KEY`] stays above every visible key.
/// project.wgsl computes the same key.
pub fn depth_sort_key(camera_z: f32) -> u32 {
    let above_near = camera_z
        .to_bits()
        .saturating_sub(constants::NEAR_PLANE.to_bits());
    (above_near >> constants::DEPTH_KEY_DROPPED_BITS).min(constants::LARGEST_VISIBLE_DEPTH_KEY)
}

/// A set of 3D Gaussians in structure-of-arrays layout, all vectors of equal length.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    /// World-space centres.
    pub means: Vec<[f32; 3]>,
    /// Natural-log standard deviations along the Gaussian's local axes.
    pub log_scales: Vec<[f32; 3]>,
    /// Rotations as quaternions `[w, x, y, z]`, not necessarily normalised.
    pub quaternions: Vec<[f32; 4]>,
    /// Opacities before the sigmoid (`opacity = 1 / (1 + exp(-logit))`).
    pub opacity_logits: Vec<f32>,
    /// Linear RGB colours in `[0, 1]` (SH degree 0 after `0.5 + C0 * f_dc`).
    pub colours: Vec<[f32; 3]>,
}

impl GaussianCloud {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Appends one Gaussian.
    pub fn push(
        &mut self,
        mean: [f32; 3],
        log_scale: [f32; 3],
        quaternion: [f32; 4],
        opacity_logit: f32,
        colour: [f32; 3],
    ) {
        self.means.push(mean);
        self.log_scales.push(log_scale);
        self.quaternions.push(quaternion);
        self.opacity_logits.push(opacity_logit);
        self.colours.push(colour);
    }

    /// Appends every Gaussian of `other` (same order).
    pub fn extend_from(&mut self, other: &GaussianCloud) {
        self.means.extend_from_slice(&other.means);
        self.log_scales.extend_from_slice(&other.log_scales);
        self.quaternions.extend_from_slice(&other.quaternions);
        self.opacity_logits.extend_from_slice(&other.opacity_logits);
        self.colours.extend_from_slice(&other.colours);
    }

    /// The Gaussians whose `keep` entry is true, in their original order (the host
    /// counterpart of the device compaction). Panics if `keep` and the cloud differ in length.
    pub fn select(&self, keep: &[bool]) -> GaussianCloud {
        assert_eq!(keep.len(), self.len(), "one keep flag per Gaussian");
        fn pick<T: Copy>(values: &[T], keep: &[bool]) -> Vec<T> {
            values
                .iter()
                .zip(keep)
                .filter_map(|(value, &kept)| kept.then_some(*value))
                .collect()
        }
        GaussianCloud {
            means: pick(&self.means, keep),
            log_scales: pick(&self.log_scales, keep),
            quaternions: pick(&self.quaternions, keep),
            opacity_logits: pick(&self.opacity_logits, keep),
            colours: pick(&self.colours, keep),
        }
    }

    /// Applies `transform` to every Gaussian: means are mapped, quaternions left-multiplied
    /// by the rotation's quaternion (so covariances become `R Sigma R^T`); scales, opacities
    /// and colours are frame-independent and unchanged. The host counterpart of
    /// `DeviceGaussians::transform_rigid`.
    pub fn transform_rigid(&mut self, transform: &RigidTransform) {
        let rotation = transform.rotation_quaternion();
        for mean in &mut self.means {
            *mean = transform.transform_point(*mean);
        }
        for quaternion in &mut self.quaternions {
            *quaternion = quaternion_multiply(rotation, *quaternion);
        }
    }

    /// Applies `transforms[group_of[i]]` to Gaussian `i` as [`Self::transform_rigid`] does; a
    /// group index past the end of `transforms` leaves that Gaussian unchanged. The host
    /// counterpart of `DeviceGaussians::transform_groups`.
    ///
    /// # Panics
    /// When `group_of` does not have one entry per Gaussian.
    pub fn transform_groups(&mut self, group_of: &[u32], transforms: &[RigidTransform]) {
        assert_eq!(group_of.len(), self.len(), "one group index per Gaussian");
        let rotations: Vec<[f32; 4]> = transforms
            .iter()
            .map(RigidTransform::rotation_quaternion)
            .collect();
        for (i, &group) in group_of.iter().enumerate() {
            let Some(transform) = transforms.get(group as usize) else {
                continue;
            };
            self.means[i] = transform.transform_point(self.means[i]);
            self.quaternions[i] =
                quaternion_multiply(rotations[group as usize], self.quaternions[i]);
        }
    }

    /// Largest distance of a mean from the centroid of all means (metres; 0 when empty): the
    /// scene scale mean learning rates are multiplied by (3DGS normalises by the camera extent;
    /// a map's own radius is the stand-in before cameras are known).
    pub fn radius_around_centroid(&self) -> f64 {
        if self.is_empty() {
            return 0.0;
        }
        let count = self.len() as f64;
        let centroid = self.means.iter().fold([0.0f64; 3], |acc, m| {
            [0, 1, 2].map(|k| acc[k] + f64::from(m[k]) / count)
        });
        self.means
            .iter()
            .map(|m| {
                (0..3)
                    .map(|k| (f64::from(m[k]) - centroid[k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(0.0, f64::max)
    }

    /// Checks that all attribute vectors have the same length.
    pub fn validate_lengths(&self) -> Result<(), String> {
        let n = self.means.len();
        let lengths = [
            ("log_scales", self.log_scales.len()),
            ("quaternions", self.quaternions.len()),
            ("opacity_logits", self.opacity_logits.len()),
            ("colours", self.colours.len()),
        ];
        for (name, len) in lengths {
            if len != n {
                return Err(format!(
                    "GaussianCloud: {name} has {len} entries, means has {n}"
                ));
            }
        }
        Ok(())
    }
}

/// A rigid transform `p_to = rotation * p_from + translation`; `rotation` is row-major.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidTransform {
    pub rotation: [[f32; 3]; 3],
    pub translation: [f32; 3],
}

impl RigidTransform {
    pub const IDENTITY: Self = Self {
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0, 0.0, 0.0],
    };

    /// Builds a transform from a quaternion `[w, x, y, z]` (normalised here) and a translation.
    pub fn from_quaternion_translation(quaternion: [f32; 4], translation: [f32; 3]) -> Self {
        let q = quaternion.map(f64::from);
        let rotation = rotation_from_quaternion_f64(q).map(|row| row.map(|v| v as f32));
        Self {
            rotation,
            translation,
        }
    }

    /// The rotation as a glam matrix (glam is column-major, `rotation` row-major).
    fn matrix(&self) -> Mat3 {
        Mat3::from_cols_array_2d(&self.rotation).transpose()
    }

    fn from_parts(rotation: Mat3, translation: Vec3) -> Self {
        Self {
            rotation: rotation.transpose().to_cols_array_2d(),
            translation: translation.to_array(),
        }
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rotation_t = self.matrix().transpose();
        Self::from_parts(rotation_t, -(rotation_t * Vec3::from(self.translation)))
    }

    /// `self * inner`: applies `inner` first, then `self`.
    pub fn compose(&self, inner: &RigidTransform) -> Self {
        Self::from_parts(
            self.matrix() * inner.matrix(),
            Vec3::from(self.transform_point(inner.translation)),
        )
    }

    /// The unit quaternion `[w, x, y, z]` of the rotation (with `w >= 0`), computed in f64
    /// (glam's `from_mat3` pivots on the largest component, so it is stable for every angle)
    /// and normalised.
    pub fn rotation_quaternion(&self) -> [f32; 4] {
        let q = DQuat::from_mat3(&self.matrix().as_dmat3()).normalize();
        let q = if q.w < 0.0 { -q } else { q };
        [q.w, q.x, q.y, q.z].map(|v| v as f32)
    }

    /// Applies the transform to a point.
    pub fn transform_point(&self, p: [f32; 3]) -> [f32; 3] {
        (self.matrix() * Vec3::from(p) + Vec3::from(self.translation)).to_array()
    }

    /// Left perturbation `exp(xi) * self` with `xi = [translation (3), rotation (3)]` (see
    /// [`PoseGradient`]); used by finite-difference tests and by pose optimisers.
    pub fn left_perturbed(&self, xi: [f64; 6]) -> Self {
        let (delta_rotation, delta_translation) = se3_exp(xi);
        let rotation = delta_rotation * self.matrix().as_dmat3();
        let translation =
            delta_rotation * DVec3::from(self.translation.map(f64::from)) + delta_translation;
        Self::from_parts(rotation.as_mat3(), translation.as_vec3())
    }
}

/// The workspace's poses are nalgebra `Isometry3<f64>`; this is their one conversion into
/// render-core's f32 form (rounded to f32, rotation taken from the unit quaternion).
impl From<&nalgebra::Isometry3<f64>> for RigidTransform {
    fn from(pose: &nalgebra::Isometry3<f64>) -> Self {
        let rotation = pose.rotation.to_rotation_matrix();
        let matrix = rotation.matrix();
        Self {
            rotation: [0, 1, 2].map(|row| [0, 1, 2].map(|col| matrix[(row, col)] as f32)),
            translation: [0, 1, 2].map(|i| pose.translation.vector[i] as f32),
        }
    }
}

/// And back, for poses render-core moved (a refined keyframe pose): the rotation re-orthonormalised
/// through its quaternion.
impl From<&RigidTransform> for nalgebra::Isometry3<f64> {
    fn from(transform: &RigidTransform) -> Self {
        let [w, x, y, z] = transform.rotation_quaternion().map(f64::from);
        let [tx, ty, tz] = transform.translation.map(f64::from);
        nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::new(tx, ty, tz),
            nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
        )
    }
}

/// Hamilton product `a * b` of quaternions `[w, x, y, z]` (rotation `b` first, then `a`).
pub fn quaternion_multiply(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    let quaternion = |[w, x, y, z]: [f32; 4]| Quat::from_xyzw(x, y, z, w);
    let product = quaternion(a) * quaternion(b);
    [product.w, product.x, product.y, product.z]
}

/// Rotation matrix (row-major) of a quaternion `[w, x, y, z]`, normalised here.
pub(crate) fn rotation_from_quaternion_f64(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [w, x, y, z] = q;
    let matrix = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
    matrix.transpose().to_cols_array_2d()
}

/// SE(3) exponential with `xi = [rho, phi]`: returns (rotation, translation) where the
/// translation is `V(phi) * rho` (the exact group exponential).
pub(crate) fn se3_exp(xi: [f64; 6]) -> (DMat3, DVec3) {
    let rho = DVec3::new(xi[0], xi[1], xi[2]);
    let phi = DVec3::new(xi[3], xi[4], xi[5]);
    let theta = phi.length();
    let skew = DMat3::from_cols(
        DVec3::new(0.0, phi.z, -phi.y),
        DVec3::new(-phi.z, 0.0, phi.x),
        DVec3::new(phi.y, -phi.x, 0.0),
    );
    let skew2 = skew * skew;
    // Taylor expansions below this angle avoid 0/0 in the closed forms.
    const SMALL_ANGLE: f64 = 1e-8;
    let (a, b, c) = if theta < SMALL_ANGLE {
        (1.0, 0.5, 1.0 / 6.0)
    } else {
        (
            theta.sin() / theta,
            (1.0 - theta.cos()) / (theta * theta),
            (theta - theta.sin()) / (theta * theta * theta),
        )
    };
    let rotation = DMat3::IDENTITY + skew * a + skew2 * b;
    let v = DMat3::IDENTITY + skew * b + skew2 * c;
    (rotation, v * rho)
}

/// A pinhole camera (OpenCV axes, no distortion).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Maps world points into the camera frame (the "view" matrix).
    pub camera_from_world: RigidTransform,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// Camera at `world_from_camera` (camera-to-world) with a pinhole's intrinsics and image
    /// size (geometry's definition; the device takes them as f32).
    pub fn new(world_from_camera: RigidTransform, intrinsics: &Intrinsics) -> Self {
        Self::from_world_from_camera(
            world_from_camera,
            [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy].map(|v| v as f32),
            intrinsics.width,
            intrinsics.height,
        )
    }

    /// Camera from its pose in the world (`world_from_camera`, i.e. camera-to-world) and f32
    /// intrinsics `[fx, fy, cx, cy]` (synthetic test and benchmark cameras).
    pub fn from_world_from_camera(
        world_from_camera: RigidTransform,
        intrinsics: [f32; 4],
        width: u32,
        height: u32,
    ) -> Self {
        let [fx, fy, cx, cy] = intrinsics;
        Self {
            camera_from_world: world_from_camera.inverse(),
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// The camera's pose in the world (camera-to-world).
    pub fn world_from_camera(&self) -> RigidTransform {
        self.camera_from_world.inverse()
    }

    /// Number of 16x16 tiles horizontally and vertically.
    pub fn tile_counts(&self) -> (u32, u32) {
        (
            self.width.div_ceil(constants::TILE_SIZE),
            self.height.div_ceil(constants::TILE_SIZE),
        )
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Which images a render produces. Alpha is always produced (it is needed to interpret depth:
/// expected depth = depth / alpha).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RenderMode {
    Rgb,
    Depth,
    #[default]
    RgbD,
}

impl RenderMode {
    pub fn has_rgb(self) -> bool {
        matches!(self, RenderMode::Rgb | RenderMode::RgbD)
    }
    pub fn has_depth(self) -> bool {
        matches!(self, RenderMode::Depth | RenderMode::RgbD)
    }
}

/// Rendered images, row-major, `width * height` pixels.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    /// Alpha-composited colour (not divided by alpha; background is black). `None` in Depth mode.
    pub rgb: Option<Vec<[f32; 3]>>,
    /// Alpha-composited camera z (metres). `None` in Rgb mode. Expected depth = depth / alpha.
    pub depth: Option<Vec<f32>>,
    /// Accumulated opacity `1 - final transmittance`.
    pub alpha: Vec<f32>,
}

/// Tangent-space gradient of a scalar loss w.r.t. the camera pose, for the LEFT perturbation
/// of `camera_from_world`: `camera_from_world' = exp(xi) * camera_from_world` with
/// `xi = [translation (3), rotation (3)]` (rotation as an axis-angle vector in the camera
/// frame), evaluated at `xi = 0`.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct PoseGradient {
    pub v_translation: [f32; 3],
    pub v_rotation: [f32; 3],
}

impl PoseGradient {
    /// As one vector `[translation, rotation]`.
    pub fn as_array(&self) -> [f32; 6] {
        let t = self.v_translation;
        let r = self.v_rotation;
        [t[0], t[1], t[2], r[0], r[1], r[2]]
    }
}

/// Gradients of a scalar loss w.r.t. every Gaussian parameter and the camera pose.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct GaussianGradients {
    pub v_means: Vec<[f32; 3]>,
    pub v_log_scales: Vec<[f32; 3]>,
    /// W.r.t. the raw (unnormalised) quaternion `[w, x, y, z]`.
    pub v_quaternions: Vec<[f32; 4]>,
    pub v_opacity_logits: Vec<f32>,
    pub v_colours: Vec<[f32; 3]>,
    pub v_pose: PoseGradient,
}

/// Gradient of a loss w.r.t. the rendered images (same layout as [`RenderOutput`]).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ImageGradients {
    pub v_rgb: Vec<[f32; 3]>,
    pub v_depth: Vec<f32>,
    pub v_alpha: Vec<f32>,
}

/// Rasterisation thresholds. [`RasterConfig::default`] holds the image model's thresholds
/// (docs/method.md, The map: [`constants::MIN_SPLAT_ALPHA`], [`constants::MAX_SPLAT_ALPHA`],
/// [`constants::MIN_TRANSMITTANCE`]) and is what the wgpu renderer uses; the smooth variant exists for finite-difference tests only.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterConfig {
    pub min_splat_alpha: f32,
    pub max_splat_alpha: f32,
    pub min_transmittance: f32,
    /// Restrict each splat to the tiles its 3-sigma box overlaps (as the GPU binning does).
    pub restrict_to_tiles: bool,
}

impl Default for RasterConfig {
    fn default() -> Self {
        Self {
            min_splat_alpha: constants::MIN_SPLAT_ALPHA,
            max_splat_alpha: constants::MAX_SPLAT_ALPHA,
            min_transmittance: constants::MIN_TRANSMITTANCE,
            restrict_to_tiles: true,
        }
    }
}

impl RasterConfig {
    /// No alpha skip, no early termination, no tile cut-off: the image is then a smooth
    /// function of every parameter, so central differences converge (test-only use).
    pub fn smooth_for_gradient_checks() -> Self {
        Self {
            min_splat_alpha: 0.0,
            max_splat_alpha: constants::MAX_SPLAT_ALPHA,
            min_transmittance: 0.0,
            restrict_to_tiles: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Point3, Vector3};

    #[test]
    fn depth_sort_keys_order_like_depth_and_stay_below_the_culled_key() {
        // The culled key (u32::MAX) as the sort sees it: its low DEPTH_KEY_BITS bits.
        let culled_key = (1u32 << constants::DEPTH_KEY_BITS) - 1;
        assert_eq!(depth_sort_key(constants::NEAR_PLANE), 0);
        let depths = [0.01f32, 0.02, 0.5, 1.0, 1.0001, 2.0, 3.5, 10.0, 1e3, 4e7];
        for pair in depths.windows(2) {
            let (near, far) = (depth_sort_key(pair[0]), depth_sort_key(pair[1]));
            assert!(near < far, "{} -> {near}, {} -> {far}", pair[0], pair[1]);
        }
        // Depths within 2^-19 of each other may share a key; the farthest depths saturate
        // below the culled key.
        assert_eq!(
            depth_sort_key(3.0),
            depth_sort_key(3.0 + 3.0 * 2f32.powi(-21))
        );
        assert!(depth_sort_key(f32::MAX) < culled_key);
        assert!(depth_sort_key(1e30) < culled_key);
        assert_eq!(depth_sort_key(0.0), 0);
    }

    #[test]
    fn converted_isometry_maps_points_the_same_way() {
        let pose = Isometry3::new(Vector3::new(0.5, -1.0, 2.0), Vector3::new(0.3, -0.2, 1.1));
        let rigid = RigidTransform::from(&pose);
        let p = Point3::new(0.25, 0.75, -1.5);
        let expected = pose * p;
        let got = rigid.transform_point([p.x as f32, p.y as f32, p.z as f32]);
        for k in 0..3 {
            assert!((f64::from(got[k]) - expected[k]).abs() < 1e-6);
        }
        // And back: the same pose, to f32 precision.
        let back = Isometry3::from(&rigid);
        assert!(((back * p) - expected).norm() < 1e-6);
        assert!(back.rotation.angle_to(&pose.rotation) < 1e-6);
        // The same rotation as built from the quaternion.
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        let from_quaternion = RigidTransform::from_quaternion_translation(
            [q.w, q.i, q.j, q.k].map(|v| v as f32),
            [t.x, t.y, t.z].map(|v| v as f32),
        );
        for (a, b) in rigid.rotation.iter().zip(&from_quaternion.rotation) {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() < 1e-6);
            }
        }
    }
}
