//! CPU-side scene description shared by the CPU reference and the wgpu renderer.
//!
//! Conventions (they hold at every public boundary of this crate):
//! - Quaternions are `[w, x, y, z]` (w first). They need not be unit length; the renderer
//!   normalises them. A quaternion of (near) zero length culls its Gaussian.
//! - Camera frame is the OpenCV one: x right, y down, z forward (the viewing direction).
//! - Pixel `(col, row)` has its centre at image coordinate `(col, row)`, so a principal point
//!   `cx = (width - 1) / 2` is the image centre (Replica: `cx = 599.5` for width 1200).
//! - Colours are SH degree 0 already converted to linear RGB in `[0, 1]` (not `f_dc`); see
//!   [`splats::ply`] for the `f_dc` conversion used in files.

use geometry::camera::Intrinsics;
// The map as data is the splats crate's (one definition for the GPU-free crates and this one);
// the modules of this crate name it through here.
pub(crate) use splats::{GaussianCloud, RigidTransform, rotation_from_quaternion_f64};

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

/// A pinhole camera (OpenCV axes, no distortion).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Maps world points into the camera frame (the "view" matrix).
    pub camera_from_world: RigidTransform,
    /// Horizontal focal length, in pixels.
    pub fx: f32,
    /// Vertical focal length, in pixels.
    pub fy: f32,
    /// Principal point's column, in pixels (pixel centres at integer coordinates).
    pub cx: f32,
    /// Principal point's row, in pixels (pixel centres at integer coordinates).
    pub cy: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
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

    /// Number of pixels, `width * height`.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Which images a render produces. Alpha is always produced (it is needed to interpret depth:
/// expected depth = depth / alpha).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RenderMode {
    /// Colour and alpha.
    Rgb,
    /// Depth and alpha.
    Depth,
    /// Colour, depth and alpha.
    #[default]
    RgbD,
}

impl RenderMode {
    /// True when the render produces colour ([`RenderOutput::rgb`] is `Some`).
    pub fn has_rgb(self) -> bool {
        matches!(self, RenderMode::Rgb | RenderMode::RgbD)
    }
    /// True when the render produces depth ([`RenderOutput::depth`] is `Some`).
    pub fn has_depth(self) -> bool {
        matches!(self, RenderMode::Depth | RenderMode::RgbD)
    }
}

/// Rendered images, row-major, `width * height` pixels.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct RenderOutput {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
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
    /// dL/d(translation part of `xi`), in the camera frame (loss units per metre).
    pub v_translation: [f32; 3],
    /// dL/d(rotation part of `xi`, axis-angle in the camera frame; loss units per radian).
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
    /// W.r.t. the world-space means, one per Gaussian (as are all the per-Gaussian vectors).
    pub v_means: Vec<[f32; 3]>,
    /// W.r.t. the natural-log scales.
    pub v_log_scales: Vec<[f32; 3]>,
    /// W.r.t. the raw (unnormalised) quaternion `[w, x, y, z]`.
    pub v_quaternions: Vec<[f32; 4]>,
    /// W.r.t. the opacity logits (before the sigmoid).
    pub v_opacity_logits: Vec<f32>,
    /// W.r.t. the linear RGB colours.
    pub v_colours: Vec<[f32; 3]>,
    /// W.r.t. the camera pose (see [`PoseGradient`] for the convention).
    pub v_pose: PoseGradient,
}

/// Gradient of a loss w.r.t. the rendered images (same layout as [`RenderOutput`]).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ImageGradients {
    /// W.r.t. the composited colour ([`RenderOutput::rgb`]), one per pixel; empty means zero.
    pub v_rgb: Vec<[f32; 3]>,
    /// W.r.t. the composited depth ([`RenderOutput::depth`], not divided by alpha), one per
    /// pixel; empty means zero.
    pub v_depth: Vec<f32>,
    /// W.r.t. the accumulated opacity ([`RenderOutput::alpha`]), one per pixel; empty means
    /// zero.
    pub v_alpha: Vec<f32>,
}

/// Rasterisation thresholds. [`RasterConfig::default`] holds the image model's thresholds
/// (docs/method.md, The map: [`constants::MIN_SPLAT_ALPHA`], [`constants::MAX_SPLAT_ALPHA`],
/// [`constants::MIN_TRANSMITTANCE`]) and is what the wgpu renderer uses; the smooth variant exists for finite-difference tests only.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterConfig {
    /// A splat whose alpha at a pixel falls below this is skipped at that pixel.
    pub min_splat_alpha: f32,
    /// A splat's alpha at a pixel is clamped to at most this (keeps `1 - alpha` invertible in
    /// the backward pass).
    pub max_splat_alpha: f32,
    /// A pixel stops compositing before a splat that would bring its transmittance below this.
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
}
