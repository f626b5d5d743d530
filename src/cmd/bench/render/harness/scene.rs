//! The benchmark's synthetic indoor scene and camera (deterministic per seed).

use render_core::Camera;

use splats::{GaussianCloud, RigidTransform};

/// Focal length of the benchmark camera at 640 pixels of width (a Kinect-like sensor);
/// other widths scale it so that the field of view stays the same.
pub(super) const FOCAL_AT_640: f32 = 525.0;
pub(super) const REFERENCE_WIDTH: f32 = 640.0;
/// Camera z range of the synthetic surfaces (metres).
pub(super) const NEAREST_SURFACE: f32 = 1.0;
pub(super) const FARTHEST_SURFACE: f32 = 4.0;
/// Typical depth of the back wall the camera looks at (metres).
pub(super) const WALL_DEPTH: f32 = 3.0;
/// The wall bulges by up to this much (metres) along sin/cos waves over the image, with these
/// spatial frequencies (radians per pixel), and each Gaussian sits up to WALL_JITTER off it.
pub(super) const WALL_WAVE_AMPLITUDE: f32 = 0.3;
pub(super) const WALL_WAVE_FREQUENCY_U: f32 = 0.02;
pub(super) const WALL_WAVE_FREQUENCY_V: f32 = 0.015;
pub(super) const WALL_JITTER: f32 = 0.01;
/// Colours: red and green vary smoothly over the image around mid-grey (frequencies in
/// radians per pixel), blue is random within [MIN_BLUE, MAX_BLUE).
pub(super) const MID_GREY: f32 = 0.5;
pub(super) const COLOUR_WAVE_AMPLITUDE: f32 = 0.4;
pub(super) const RED_WAVE_FREQUENCY: f32 = 0.01;
pub(super) const GREEN_WAVE_FREQUENCY: f32 = 0.013;
pub(super) const MIN_BLUE: f32 = 0.1;
pub(super) const MAX_BLUE: f32 = 0.9;
/// Fraction of Gaussians on objects in front of the wall (the rest cover the wall).
pub(super) const OBJECT_FRACTION: f32 = 0.4;
/// Standard deviations of the Gaussians' two large axes: 1 to 4 cm; the third axis is
/// flattened (surfels on surfaces).
pub(super) const MIN_SCALE: f32 = 0.01;
pub(super) const MAX_SCALE: f32 = 0.04;
pub(super) const FLAT_AXIS_FACTOR: f32 = 0.2;
/// Opacity logits: sigmoid(-1) = 0.27 to sigmoid(4) = 0.98, like a trained map.
pub(super) const MIN_OPACITY_LOGIT: f32 = -1.0;
pub(super) const MAX_OPACITY_LOGIT: f32 = 4.0;
/// Gaussians may sit this many pixels outside the image (partial splats on border tiles).
pub(super) const MARGIN_PIXELS: f32 = 24.0;

/// The benchmark camera: `width x height`, principal point at the image centre, at the
/// world origin looking along +z (world = camera frame).
pub fn bench_camera(width: u32, height: u32) -> Camera {
    let focal = FOCAL_AT_640 * width as f32 / REFERENCE_WIDTH;
    Camera::from_world_from_camera(
        RigidTransform::IDENTITY,
        [
            focal,
            focal,
            (width as f32 - 1.0) / 2.0,
            (height as f32 - 1.0) / 2.0,
        ],
        width,
        height,
    )
}

/// A small deterministic generator (SplitMix64) so that the scene needs no RNG dependency
/// and is identical on every machine.
pub(super) struct SplitMix64(pub(super) u64);

impl SplitMix64 {
    pub(super) fn next_u64(&mut self) -> u64 {
        // The published SplitMix64 increment and finaliser multipliers (Steele et al. 2014).
        const GOLDEN_GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;
        self.0 = self.0.wrapping_add(GOLDEN_GAMMA);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[low, high)`.
    pub(super) fn uniform(&mut self, low: f32, high: f32) -> f32 {
        const MANTISSA_BITS: u32 = 24;
        let unit = (self.next_u64() >> (u64::BITS - MANTISSA_BITS)) as f32
            / (1u64 << MANTISSA_BITS) as f32;
        low + (high - low) * unit
    }
}

/// `count` Gaussians of an indoor-map-like scene in front of [`bench_camera`]: a wavy back
/// wall plus objects scattered in front of it, colours varying smoothly over the image.
pub fn realistic_scene(camera: &Camera, count: usize, seed: u64) -> GaussianCloud {
    let mut rng = SplitMix64(seed);
    let world_from_camera = camera.world_from_camera();
    let mut cloud = GaussianCloud::default();
    for _ in 0..count {
        let u = rng.uniform(-MARGIN_PIXELS, camera.width as f32 + MARGIN_PIXELS);
        let v = rng.uniform(-MARGIN_PIXELS, camera.height as f32 + MARGIN_PIXELS);
        let wall = WALL_DEPTH
            + WALL_WAVE_AMPLITUDE
                * (u * WALL_WAVE_FREQUENCY_U).sin()
                * (v * WALL_WAVE_FREQUENCY_V).cos()
            + rng.uniform(-WALL_JITTER, WALL_JITTER);
        let z = if rng.uniform(0.0, 1.0) < OBJECT_FRACTION {
            rng.uniform(NEAREST_SURFACE, wall)
        } else {
            wall
        }
        .clamp(NEAREST_SURFACE, FARTHEST_SURFACE);
        let point = [
            (u - camera.cx) * z / camera.fx,
            (v - camera.cy) * z / camera.fy,
            z,
        ];
        let large = [
            rng.uniform(MIN_SCALE, MAX_SCALE),
            rng.uniform(MIN_SCALE, MAX_SCALE),
        ];
        let log_scale = [
            large[0].ln(),
            large[1].ln(),
            (FLAT_AXIS_FACTOR * large[0].min(large[1])).ln(),
        ];
        let quaternion = [
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ];
        let colour = [
            MID_GREY + COLOUR_WAVE_AMPLITUDE * (u * RED_WAVE_FREQUENCY).sin(),
            MID_GREY + COLOUR_WAVE_AMPLITUDE * (v * GREEN_WAVE_FREQUENCY).cos(),
            rng.uniform(MIN_BLUE, MAX_BLUE),
        ];
        cloud.push(
            world_from_camera.transform_point(point),
            log_scale,
            quaternion,
            rng.uniform(MIN_OPACITY_LOGIT, MAX_OPACITY_LOGIT),
            colour,
        );
    }
    cloud
}
