//! The embedded synthetic multi-agent RGB-D dataset: needs no download and is the default
//! everywhere (SPEC section 6).
//!
//! A procedural room (6 x 5 x 3 m: textured floor, ceiling and walls, a table with objects on
//! it, a cabinet, a shelf, a bench, a pillar, a bin, a ball, stacked boxes, posters) is ray-cast
//! analytically (rays against planes, boxes, spheres and cylinders; no mesh files) to RGB and
//! exact depth. Textures are procedural (multi-octave value noise, checkers, stripes, tiles,
//! planks, each with colour variation) and filtered by the pixel footprint so they do not alias;
//! shading is Lambertian with fixed point lights, so a surface point has the same colour from
//! every viewpoint (what photometric map optimisation assumes).
//!
//! `agents` cameras walk smooth loops around the table, alternating direction, looking towards
//! the room's interior with slow gaze wander, head-bob and roll; consecutive agents cover
//! overlapping stretches of the same loop, so their views overlap. Ground truth is exact. The
//! world frame is the room frame (x east, y north, z up, floor at z = 0, origin in the middle of
//! the floor), so no agent starts at the identity: the SLAM system must find the inter-agent
//! transforms.
//!
//! Depth is the camera-frame z in metres (not the ray length), quantised to whole millimetres
//! exactly as the 7-Scenes depth PNG reader decodes them (`raw_mm as f32 * (1/1000 as f32)`), so
//! a frame written with [`write_seven_scenes`] and read back has bit-identical colour, depth,
//! timestamp and pose translation; the pose rotation differs by ~1e-13 rad because the pose
//! reader re-orthonormalises the stored matrix. Depth beyond 65.534 m, or rays that leave the
//! scene, is 0 (invalid); inside the closed room every pixel has valid depth.
//!
//! Everything is a pure function of [`SyntheticSpec`]: textures, object placement and trajectory
//! jitter come from ChaCha RNGs seeded from `seed`, and pixels are computed independently, so the
//! output is bit-identical across runs and rayon thread counts.

use std::f64::consts::{PI, TAU};
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use image::RgbImage;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::files::DatasetError;
use geometry::trajectory::NO_CLOCK_FRAMES_PER_SECOND;

use crate::seven_scenes::{DEPTH_UNITS_PER_METRE, INVALID_DEPTH_RAW, SevenScenesWriter};
use crate::{Dataset, Frame, FrameRange};

// ---------------------------------------------------------------------------------------------
// Spec
// ---------------------------------------------------------------------------------------------

/// The word that selects this dataset in `--dataset` arguments and configs.
pub const SPEC_PREFIX: &str = "synthetic";
pub const DEFAULT_AGENTS: usize = 3;
pub const DEFAULT_FRAMES: usize = 300;
pub const DEFAULT_SEED: u64 = 0;
pub const DEFAULT_WIDTH: u32 = 640;
pub const DEFAULT_HEIGHT: u32 = 480;
/// Limits that keep a typo from asking for terabytes or a degenerate camera.
pub const MAX_AGENTS: usize = 64;
pub const MAX_FRAMES: usize = 1_000_000;
pub const MIN_IMAGE_SIDE: u32 = 16;
pub const MAX_IMAGE_SIDE: u32 = 8192;

/// Focal length in pixels at the reference width (a Kinect-like 525 px at 640 px); other widths
/// scale it so the horizontal field of view stays the same.
const REFERENCE_FOCAL_PX: f64 = 525.0;
const REFERENCE_WIDTH_PX: f64 = 640.0;
/// Camera rate. The same rate the 7-Scenes reader assumes for its clock-less frames, so written
/// and read-back timestamps agree.
pub const FRAMES_PER_SECOND: f64 = NO_CLOCK_FRAMES_PER_SECOND;

/// Which synthetic sequence to produce: `synthetic` or
/// `synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240` (any subset of keys, any
/// order; missing keys take the defaults).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SyntheticSpec {
    /// Number of agents sharing the scene (the trajectories depend on it: agents are spread
    /// evenly around the loop).
    pub agents: usize,
    /// Which agent this sequence is (0-based, < agents).
    pub agent: usize,
    /// Frames per agent, 30 per second.
    pub frames: usize,
    /// Seed of textures, object placement and trajectory jitter.
    pub seed: u64,
    pub width: u32,
    pub height: u32,
}

impl Default for SyntheticSpec {
    fn default() -> Self {
        Self {
            agents: DEFAULT_AGENTS,
            agent: 0,
            frames: DEFAULT_FRAMES,
            seed: DEFAULT_SEED,
            width: DEFAULT_WIDTH,
            height: DEFAULT_HEIGHT,
        }
    }
}

impl SyntheticSpec {
    /// The same sequence for another agent.
    pub fn with_agent(self, agent: usize) -> Self {
        Self { agent, ..self }
    }

    /// Pinhole intrinsics: fx = fy = 525 px at 640 px width (scaled with the width), principal
    /// point in the image centre. 640x480 gives fx = fy = 525, cx = 319.5, cy = 239.5.
    pub fn intrinsics(&self) -> Intrinsics {
        let focal = REFERENCE_FOCAL_PX * self.width as f64 / REFERENCE_WIDTH_PX;
        Intrinsics::new(
            focal,
            focal,
            (self.width as f64 - 1.0) / 2.0,
            (self.height as f64 - 1.0) / 2.0,
            self.width,
            self.height,
        )
    }

    /// Checks every field; the message names the offending key.
    pub fn validate(&self) -> Result<(), String> {
        if self.agents == 0 || self.agents > MAX_AGENTS {
            return Err(format!(
                "agents={} is out of range 1..={MAX_AGENTS}",
                self.agents
            ));
        }
        if self.agent >= self.agents {
            return Err(format!(
                "agent={} is out of range: with agents={} the agent must be 0..={}",
                self.agent,
                self.agents,
                self.agents - 1
            ));
        }
        if self.frames == 0 || self.frames > MAX_FRAMES {
            return Err(format!(
                "frames={} is out of range 1..={MAX_FRAMES}",
                self.frames
            ));
        }
        for (key, value) in [("width", self.width), ("height", self.height)] {
            if !(MIN_IMAGE_SIDE..=MAX_IMAGE_SIDE).contains(&value) {
                return Err(format!(
                    "{key}={value} is out of range {MIN_IMAGE_SIDE}..={MAX_IMAGE_SIDE}"
                ));
            }
        }
        Ok(())
    }
}

impl FromStr for SyntheticSpec {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let text = text.trim();
        let rest = text
            .strip_prefix(SPEC_PREFIX)
            .ok_or_else(|| format!("{text:?} is not a synthetic spec: expected `{SPEC_PREFIX}` or `{SPEC_PREFIX}:key=value,...`"))?;
        let mut spec = Self::default();
        let options = match rest.strip_prefix(':') {
            Some(options) => options,
            None if rest.is_empty() => "",
            None => {
                return Err(format!(
                    "{text:?} is not a synthetic spec: expected `:` after `{SPEC_PREFIX}`"
                ));
            }
        };
        let mut seen: Vec<&str> = Vec::new();
        for item in options
            .split(',')
            .map(str::trim)
            .filter(|item| !item.is_empty())
        {
            let (key, value) = item
                .split_once('=')
                .map(|(k, v)| (k.trim(), v.trim()))
                .ok_or_else(|| format!("{item:?} in synthetic spec {text:?} is not key=value"))?;
            if seen.contains(&key) {
                return Err(format!(
                    "key {key:?} appears twice in synthetic spec {text:?}"
                ));
            }
            seen.push(key);
            let bad = |expected: &str| {
                format!(
                    "bad value {value:?} for key {key:?} in synthetic spec {text:?}: expected {expected}"
                )
            };
            match key {
                "agents" => spec.agents = value.parse().map_err(|_| bad("a positive integer"))?,
                "agent" => spec.agent = value.parse().map_err(|_| bad("an agent number from 0"))?,
                "frames" => spec.frames = value.parse().map_err(|_| bad("a positive integer"))?,
                "seed" => {
                    spec.seed = value
                        .parse()
                        .map_err(|_| bad("an unsigned 64-bit integer"))?
                }
                "width" => spec.width = value.parse().map_err(|_| bad("a width in pixels"))?,
                "height" => spec.height = value.parse().map_err(|_| bad("a height in pixels"))?,
                _ => {
                    return Err(format!(
                        "unknown key {key:?} in synthetic spec {text:?}: expected agents, agent, frames, seed, width or height"
                    ));
                }
            }
        }
        spec.validate()
            .map_err(|reason| format!("synthetic spec {text:?}: {reason}"))?;
        Ok(spec)
    }
}

impl fmt::Display for SyntheticSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{SPEC_PREFIX}:agents={},agent={},frames={},seed={},width={},height={}",
            self.agents, self.agent, self.frames, self.seed, self.width, self.height
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Scene geometry
// ---------------------------------------------------------------------------------------------

/// Room corners in the world (room) frame, metres: 6 x 5 x 3 m, floor at z = 0.
pub const ROOM_MIN: [f64; 3] = [-3.0, -2.5, 0.0];
pub const ROOM_MAX: [f64; 3] = [3.0, 2.5, 3.0];

/// Intersections closer than this along the ray (in camera-z metres) are ignored, so a ray never
/// re-hits the surface it starts on.
const MIN_HIT_DISTANCE: f64 = 1e-6;
/// Ray direction components below this are treated as parallel to a slab.
const PARALLEL_EPSILON: f64 = 1e-12;
/// Texture coordinates of the six faces of a box are shifted apart by this much (metres) so that
/// faces do not repeat each other's pattern, which would confuse keypoint matching.
const FACE_UV_OFFSET: f64 = 17.3;

#[derive(Debug, Clone, Copy)]
struct Ray {
    origin: Vector3<f64>,
    /// Not normalised: its camera-frame z component is 1, so the hit parameter t is the
    /// camera-frame depth directly.
    direction: Vector3<f64>,
}

impl Ray {
    fn at(&self, t: f64) -> Vector3<f64> {
        self.origin + self.direction * t
    }
}

#[derive(Debug, Clone, Copy)]
struct Hit {
    /// Ray parameter = camera-frame z of the hit point.
    t: f64,
    /// Unit surface normal in the world frame (not yet oriented towards the viewer).
    normal: Vector3<f64>,
    /// Surface texture coordinates in metres.
    uv: [f64; 2],
    material: usize,
}

#[derive(Debug, Clone, Copy)]
enum Shape {
    /// A box rotated by `yaw` about the vertical axis.
    Cuboid {
        center: Vector3<f64>,
        half_size: Vector3<f64>,
        cos_yaw: f64,
        sin_yaw: f64,
    },
    Sphere {
        center: Vector3<f64>,
        radius: f64,
    },
    /// A vertical cylinder standing on `base` (centre of its bottom cap), caps included.
    Cylinder {
        base: Vector3<f64>,
        radius: f64,
        height: f64,
    },
}

#[derive(Debug, Clone, Copy)]
struct Primitive {
    shape: Shape,
    material: usize,
    /// Bounding sphere: most rays miss most objects, and a sphere test rejects them in a few
    /// multiplications before the exact test.
    bound_center: Vector3<f64>,
    bound_radius_squared: f64,
}

/// Rotates a world-frame vector into a box's yawed frame.
fn to_yawed(v: &Vector3<f64>, cos_yaw: f64, sin_yaw: f64) -> Vector3<f64> {
    Vector3::new(
        cos_yaw * v.x + sin_yaw * v.y,
        -sin_yaw * v.x + cos_yaw * v.y,
        v.z,
    )
}

/// Rotates a vector from a box's yawed frame into the world frame.
fn from_yawed(v: &Vector3<f64>, cos_yaw: f64, sin_yaw: f64) -> Vector3<f64> {
    Vector3::new(
        cos_yaw * v.x - sin_yaw * v.y,
        sin_yaw * v.x + cos_yaw * v.y,
        v.z,
    )
}

/// Slab test of a ray against an axis-aligned box centred at the origin. Returns
/// (t_enter, t_exit, axis of the entry face, axis of the exit face), or None when the ray misses.
fn slabs(
    origin: &Vector3<f64>,
    direction: &Vector3<f64>,
    half_size: &Vector3<f64>,
) -> Option<(f64, f64, usize, usize)> {
    let (mut t_enter, mut t_exit) = (f64::NEG_INFINITY, f64::INFINITY);
    let (mut enter_axis, mut exit_axis) = (0, 0);
    for axis in 0..3 {
        let (o, d, h) = (origin[axis], direction[axis], half_size[axis]);
        if d.abs() < PARALLEL_EPSILON {
            if o.abs() > h {
                return None;
            }
            continue;
        }
        let (t0, t1) = ((-h - o) / d, (h - o) / d);
        let (near, far) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
        if near > t_enter {
            t_enter = near;
            enter_axis = axis;
        }
        if far < t_exit {
            t_exit = far;
            exit_axis = axis;
        }
    }
    (t_enter <= t_exit).then_some((t_enter, t_exit, enter_axis, exit_axis))
}

/// Texture coordinates on the face of a box (or the room) perpendicular to `axis`, with faces
/// offset from each other.
fn face_uv(point: &Vector3<f64>, axis: usize, positive_side: bool) -> [f64; 2] {
    let face = (2 * axis + usize::from(positive_side)) as f64 * FACE_UV_OFFSET;
    match axis {
        0 => [point.y + face, point.z],
        1 => [point.x + face, point.z],
        _ => [point.x + face, point.y],
    }
}

impl Primitive {
    fn new(shape: Shape, material: usize) -> Self {
        let (bound_center, bound_radius) = match shape {
            Shape::Cuboid {
                center, half_size, ..
            } => (center, half_size.norm()),
            Shape::Sphere { center, radius } => (center, radius),
            Shape::Cylinder {
                base,
                radius,
                height,
            } => (
                base + Vector3::new(0.0, 0.0, height / 2.0),
                radius.hypot(height / 2.0),
            ),
        };
        Self {
            shape,
            material,
            bound_center,
            bound_radius_squared: bound_radius * bound_radius,
        }
    }

    /// False when the ray certainly misses the primitive, or can only hit it at or beyond
    /// `t_limit`.
    fn may_hit(&self, ray: &Ray, t_limit: f64) -> bool {
        let to_center = self.bound_center - ray.origin;
        let direction_length = ray.direction.norm();
        // Distance along the ray (metres) to the point closest to the bounding sphere's centre.
        let along = to_center.dot(&ray.direction) / direction_length;
        let miss_distance_squared = to_center.norm_squared() - along * along;
        if miss_distance_squared > self.bound_radius_squared {
            return false;
        }
        let half_chord = (self.bound_radius_squared - miss_distance_squared).sqrt();
        along + half_chord > 0.0 && (along - half_chord) / direction_length < t_limit
    }

    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        match self.shape {
            Shape::Cuboid {
                center,
                half_size,
                cos_yaw,
                sin_yaw,
            } => {
                let origin = to_yawed(&(ray.origin - center), cos_yaw, sin_yaw);
                let direction = to_yawed(&ray.direction, cos_yaw, sin_yaw);
                let (t_enter, _, axis, _) = slabs(&origin, &direction, &half_size)?;
                // t_enter <= MIN_HIT_DISTANCE means the camera is inside or behind the box: no hit.
                if t_enter <= MIN_HIT_DISTANCE {
                    return None;
                }
                let positive_side = direction[axis] < 0.0;
                let mut local_normal = Vector3::zeros();
                local_normal[axis] = if positive_side { 1.0 } else { -1.0 };
                let point = origin + direction * t_enter;
                Some(Hit {
                    t: t_enter,
                    normal: from_yawed(&local_normal, cos_yaw, sin_yaw),
                    uv: face_uv(&point, axis, positive_side),
                    material: self.material,
                })
            }
            Shape::Sphere { center, radius } => {
                let offset = ray.origin - center;
                let a = ray.direction.norm_squared();
                let half_b = offset.dot(&ray.direction);
                let c = offset.norm_squared() - radius * radius;
                let discriminant = half_b * half_b - a * c;
                if discriminant < 0.0 {
                    return None;
                }
                let t = (-half_b - discriminant.sqrt()) / a;
                if t <= MIN_HIT_DISTANCE {
                    return None;
                }
                let local = ray.at(t) - center;
                let normal = local / radius;
                // Longitude/latitude in metres of arc, so texture scale matches the other surfaces.
                let longitude = normal.y.atan2(normal.x) * radius;
                let colatitude = normal.z.clamp(-1.0, 1.0).acos() * radius;
                Some(Hit {
                    t,
                    normal,
                    uv: [longitude, colatitude],
                    material: self.material,
                })
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => {
                let o = ray.origin - base;
                let d = ray.direction;
                let mut best: Option<Hit> = None;
                let mut consider = |hit: Hit| {
                    if hit.t > MIN_HIT_DISTANCE && best.is_none_or(|b| hit.t < b.t) {
                        best = Some(hit);
                    }
                };
                let a = d.x * d.x + d.y * d.y;
                if a > PARALLEL_EPSILON {
                    let half_b = o.x * d.x + o.y * d.y;
                    let c = o.x * o.x + o.y * o.y - radius * radius;
                    let discriminant = half_b * half_b - a * c;
                    if discriminant >= 0.0 {
                        let t = (-half_b - discriminant.sqrt()) / a;
                        let p = o + d * t;
                        if (0.0..=height).contains(&p.z) {
                            let normal = Vector3::new(p.x / radius, p.y / radius, 0.0);
                            consider(Hit {
                                t,
                                normal,
                                uv: [p.y.atan2(p.x) * radius, p.z],
                                material: self.material,
                            });
                        }
                    }
                }
                if d.z.abs() > PARALLEL_EPSILON {
                    for (cap_z, normal_z) in [(height, 1.0), (0.0, -1.0)] {
                        let t = (cap_z - o.z) / d.z;
                        let p = o + d * t;
                        if p.x * p.x + p.y * p.y <= radius * radius {
                            let uv = [p.x + FACE_UV_OFFSET * normal_z, p.y];
                            consider(Hit {
                                t,
                                normal: Vector3::new(0.0, 0.0, normal_z),
                                uv,
                                material: self.material,
                            });
                        }
                    }
                }
                best
            }
        }
    }

    /// Distance from a point outside the primitive to its surface (negative inside); used to
    /// prove that cameras keep clear of objects.
    #[cfg(test)]
    fn distance(&self, p: &Vector3<f64>) -> f64 {
        fn box_distance(q: &Vector3<f64>, half_size: &Vector3<f64>) -> f64 {
            let outside = Vector3::new(
                (q.x.abs() - half_size.x).max(0.0),
                (q.y.abs() - half_size.y).max(0.0),
                (q.z.abs() - half_size.z).max(0.0),
            );
            let inside = (q.x.abs() - half_size.x)
                .max(q.y.abs() - half_size.y)
                .max(q.z.abs() - half_size.z)
                .min(0.0);
            outside.norm() + inside
        }
        match self.shape {
            Shape::Cuboid {
                center,
                half_size,
                cos_yaw,
                sin_yaw,
            } => box_distance(&to_yawed(&(p - center), cos_yaw, sin_yaw), &half_size),
            Shape::Sphere { center, radius } => (p - center).norm() - radius,
            Shape::Cylinder {
                base,
                radius,
                height,
            } => {
                let q = p - base;
                let radial = (q.x * q.x + q.y * q.y).sqrt() - radius;
                let vertical = (q.z - height / 2.0).abs() - height / 2.0;
                let outside = Vector3::new(radial.max(0.0), vertical.max(0.0), 0.0).norm();
                outside + radial.max(vertical).min(0.0)
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Procedural textures
// ---------------------------------------------------------------------------------------------

/// Octaves of the value-noise sum (see [`fbm_bands`]); each doubles the frequency and scales the
/// amplitude by [`NOISE_GAIN`].
const COARSE_OCTAVES: usize = 4;
const FINE_OCTAVES: usize = 4;
const NOISE_GAIN: f64 = 0.55;
/// Texture detail whose period spans fewer than `FADE_END` pixels on screen is replaced by its
/// mean (fully so below [`FADE_START`] pixels): a cheap pre-filter that keeps far or grazing
/// surfaces from aliasing into flicker, which would break photometric consistency between views.
const FADE_START_PX: f64 = 2.0;
const FADE_END_PX: f64 = 5.0;
/// How far value-noise contrast is stretched around 0.5 (raw sums cluster near the middle).
const NOISE_CONTRAST: f64 = 2.6;
/// Warm/cool colour shift driven by the base noise, for colour variation inside a pattern.
const COLOUR_SHIFT: f64 = 0.22;
/// Floor planks: half width of the joints (m), their relative brightness, the wood grain's line
/// spacing (m) and how many grain periods the noise bends it by.
const PLANK_GAP_HALF_WIDTH: f64 = 0.004;
const PLANK_GAP_BRIGHTNESS: f64 = 0.45;
const WOOD_GRAIN_PERIOD: f64 = 0.02;
const WOOD_GRAIN_WARP: f64 = 6.0;
/// Smallest cosine between the viewing ray and a surface used to stretch the pixel footprint
/// (grazing angles would otherwise blow it up without bound).
const MIN_FOOTPRINT_COSINE: f64 = 0.15;

/// splitmix64 finaliser: a fast, well-mixed integer hash.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform value in [0, 1) for an integer lattice point.
fn lattice_value(ix: i64, iy: i64, seed: u64) -> f64 {
    // Distinct odd multipliers and a rotation keep (ix, iy) and (iy, ix) apart; one finaliser
    // round then mixes every input bit into the output.
    let key = (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (iy as u64)
            .wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            .rotate_left(29);
    let h = mix64(seed ^ key);
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Quintic fade: C2-continuous interpolation, so the noise has no visible grid creases.
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// `x.floor()` without the libm call (x86-64's baseline has no rounding instruction); exact for
/// |x| < 2^53, far beyond any texture coordinate here.
fn fast_floor(x: f64) -> f64 {
    let truncated = x as i64 as f64;
    if truncated > x {
        truncated - 1.0
    } else {
        truncated
    }
}

fn value_noise(x: f64, y: f64, seed: u64) -> f64 {
    let (fx, fy) = (fast_floor(x), fast_floor(y));
    let (ix, iy) = (fx as i64, fy as i64);
    let (sx, sy) = (fade(x - fx), fade(y - fy));
    let v00 = lattice_value(ix, iy, seed);
    let v10 = lattice_value(ix + 1, iy, seed);
    let v01 = lattice_value(ix, iy + 1, seed);
    let v11 = lattice_value(ix + 1, iy + 1, seed);
    let bottom = v00 + (v10 - v00) * sx;
    let top = v01 + (v11 - v01) * sx;
    bottom + (top - bottom) * sy
}

/// 0 when a feature of `period` covers fewer than FADE_START_PX pixels of `footprint`, 1 when it
/// covers more than FADE_END_PX, smooth in between.
fn visibility(period: f64, footprint: f64) -> f64 {
    let pixels = period / footprint.max(f64::MIN_POSITIVE);
    ((pixels - FADE_START_PX) / (FADE_END_PX - FADE_START_PX)).clamp(0.0, 1.0)
}

/// Multi-octave value noise, band-limited to the pixel footprint (same units as x, y), split
/// into two bands that are each normalised to [0, 1] around 0.5: the first [`COARSE_OCTAVES`]
/// (large blotches that modulate patterns and colour) and the next [`FINE_OCTAVES`] (grain that
/// modulates brightness). One pass for both bands costs less than two separate sums.
fn fbm_bands(x: f64, y: f64, seed: u64, footprint: f64) -> (f64, f64) {
    let mut bands = [(0.0, 0.0); 2];
    let (mut amplitude, mut frequency) = (1.0, 1.0);
    for octave in 0..COARSE_OCTAVES + FINE_OCTAVES {
        if octave == COARSE_OCTAVES {
            amplitude = 1.0;
        }
        let band = &mut bands[usize::from(octave >= COARSE_OCTAVES)];
        let weight = visibility(1.0 / frequency, footprint);
        let value = if weight > 0.0 {
            // Offsets decorrelate octaves that share lattice points at the origin.
            let noise = value_noise(
                x * frequency + 31.7 * octave as f64,
                y * frequency - 17.3 * octave as f64,
                seed.wrapping_add(octave as u64),
            );
            0.5 + weight * (noise - 0.5)
        } else {
            0.5
        };
        band.0 += amplitude * value;
        band.1 += amplitude;
        amplitude *= NOISE_GAIN;
        frequency *= 2.0;
    }
    (bands[0].0 / bands[0].1, bands[1].0 / bands[1].1)
}

/// Anti-aliased square wave of `period` in [-1, 1]: +1 on the first half-period, -1 on the
/// second, ramping linearly over one footprint at each edge and fading to its mean 0 when the
/// period is too small to resolve.
fn square_wave(x: f64, period: f64, footprint: f64) -> f64 {
    let phase = x / period - fast_floor(x / period);
    let sign = if phase < 0.5 { 1.0 } else { -1.0 };
    let edge_distance = period * phase.min((phase - 0.5).abs()).min(1.0 - phase);
    sign * (edge_distance / footprint.max(f64::MIN_POSITIVE)).min(1.0)
        * visibility(period, footprint)
}

/// Anti-aliased grid line mask: 1 within `half_width` of a multiple of `period`, 0 elsewhere,
/// fading to the line's area fraction when the period is too small to resolve.
fn grid_line(x: f64, period: f64, half_width: f64, footprint: f64) -> f64 {
    let phase = x / period - fast_floor(x / period);
    let distance = period * phase.min(1.0 - phase);
    let sharp = ((half_width + footprint - distance) / (2.0 * footprint).max(f64::MIN_POSITIVE))
        .clamp(0.0, 1.0);
    let mean = (2.0 * half_width / period).min(1.0);
    mean + (sharp - mean) * visibility(period, footprint)
}

type Rgb = [f64; 3];

fn mix_rgb(a: &Rgb, b: &Rgb, t: f64) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

fn hsv_to_rgb(hue: f64, saturation: f64, value: f64) -> Rgb {
    let h = (hue - hue.floor()) * 6.0;
    let chroma = value * saturation;
    let x = chroma * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (chroma, x, 0.0),
        1 => (x, chroma, 0.0),
        2 => (0.0, chroma, x),
        3 => (0.0, x, chroma),
        4 => (x, 0.0, chroma),
        _ => (chroma, 0.0, x),
    };
    let m = value - chroma;
    [r + m, g + m, b + m]
}

#[derive(Debug, Clone, Copy)]
enum Pattern {
    /// Contrast-stretched multi-octave noise (plaster, stone).
    Marble,
    /// Two-colour checkerboard of `period` (one light and one dark square per period).
    Checker { period: f64 },
    /// Stripes of `period` along direction `angle` (wallpaper).
    Stripes {
        period: f64,
        cos_angle: f64,
        sin_angle: f64,
    },
    /// Square tiles with grout lines; each tile gets its own tint.
    Tiles { period: f64, grout_half_width: f64 },
    /// Floor planks with wood grain, staggered joints and a tint per plank.
    Planks { width: f64, length: f64 },
}

#[derive(Debug, Clone, Copy)]
struct Material {
    pattern: Pattern,
    primary: Rgb,
    secondary: Rgb,
    /// Seed of this material's noise, so no two surfaces share a texture.
    noise_seed: u64,
    /// Frequency of the lowest noise octave, cycles per metre.
    noise_frequency: f64,
    /// Relative brightness variation from fine noise.
    detail_strength: f64,
    /// Relative brightness variation between tiles or planks.
    cell_tint: f64,
}

impl Material {
    /// Reflectance (linear, 0..1) at surface coordinates `uv` (metres), filtered for a pixel
    /// footprint of `footprint` metres.
    fn albedo(&self, uv: [f64; 2], footprint: f64) -> Rgb {
        let [u, v] = uv;
        let f = self.noise_frequency;
        let (base, detail) = fbm_bands(u * f, v * f, self.noise_seed, footprint * f);
        let stretched = ((base - 0.5) * NOISE_CONTRAST + 0.5).clamp(0.0, 1.0);
        let (mix, cell_brightness) = match self.pattern {
            Pattern::Marble => (stretched, 1.0),
            Pattern::Checker { period } => {
                let checker = square_wave(u, period, footprint) * square_wave(v, period, footprint);
                (0.5 + 0.4 * checker + 0.2 * (stretched - 0.5), 1.0)
            }
            Pattern::Stripes {
                period,
                cos_angle,
                sin_angle,
            } => {
                let along = u * cos_angle + v * sin_angle;
                let stripe = square_wave(along, period, footprint);
                // A thinner stripe at a third of the period makes the pattern non-repetitive within
                // one period, which helps matching along the stripes.
                let fine = square_wave(along + 0.37 * period, period / 3.0, footprint);
                (
                    0.5 + 0.3 * stripe + 0.1 * fine + 0.25 * (stretched - 0.5),
                    1.0,
                )
            }
            Pattern::Tiles {
                period,
                grout_half_width,
            } => {
                let grout = grid_line(u, period, grout_half_width, footprint).max(grid_line(
                    v,
                    period,
                    grout_half_width,
                    footprint,
                ));
                let cell = lattice_value(
                    (u / period).floor() as i64,
                    (v / period).floor() as i64,
                    self.noise_seed ^ 0x7A11,
                );
                // The per-tile tint jumps at tile edges, which the grout hides; fade it with the
                // grout's own visibility so far tiles do not shimmer.
                let tint =
                    1.0 + self.cell_tint * (cell - 0.5) * 2.0 * visibility(period, footprint);
                (
                    grout + (1.0 - grout) * 0.35 * stretched,
                    tint * (1.0 - grout) + grout,
                )
            }
            Pattern::Planks { width, length } => {
                let row = (v / width).floor();
                let stagger = lattice_value(row as i64, 0, self.noise_seed ^ 0x9A4C) * length;
                let plank = ((u + stagger) / length).floor();
                let gap = grid_line(v, width, PLANK_GAP_HALF_WIDTH, footprint).max(grid_line(
                    u + stagger,
                    length,
                    PLANK_GAP_HALF_WIDTH,
                    footprint,
                ));
                let cell = lattice_value(row as i64, plank as i64, self.noise_seed ^ 0x51D3);
                let tint = 1.0 + self.cell_tint * (cell - 0.5) * 2.0 * visibility(width, footprint);
                // Grain: lines along the plank, warped by the noise; fades out below pixel size.
                let grain = 0.5
                    + 0.5
                        * (TAU * (v / WOOD_GRAIN_PERIOD + WOOD_GRAIN_WARP * base)).sin()
                        * visibility(WOOD_GRAIN_PERIOD, footprint);
                // Mostly grain, some blotches, kept away from both ends of the colour ramp.
                let wood = 0.25 + 0.3 * grain + 0.2 * stretched;
                // Gaps are dark: the mix goes to the primary colour at reduced brightness.
                (
                    wood * (1.0 - gap),
                    tint * (1.0 - gap) + PLANK_GAP_BRIGHTNESS * gap,
                )
            }
        };
        let mut colour = mix_rgb(&self.primary, &self.secondary, mix.clamp(0.0, 1.0));
        let brightness = cell_brightness * (1.0 + self.detail_strength * (detail - 0.5) * 2.0);
        let shift = COLOUR_SHIFT * (base - 0.5);
        colour[0] *= brightness * (1.0 + shift);
        colour[1] *= brightness;
        colour[2] *= brightness * (1.0 - shift);
        colour
    }
}

// ---------------------------------------------------------------------------------------------
// Scene
// ---------------------------------------------------------------------------------------------

/// Diffuse light that reaches every surface (fraction of albedo).
const AMBIENT_LIGHT: f64 = 0.32;
/// Ceiling lamps: position (m) and diffuse strength.
const LAMPS: [([f64; 3], f64); 2] = [([1.1, -0.7, 2.8], 0.55), ([-1.3, 0.9, 2.8], 0.5)];
/// Distance (m) at which a lamp's light has fallen to half.
const LAMP_FALLOFF_DISTANCE: f64 = 3.2;
/// Display gamma applied when converting linear radiance to 8-bit values.
const DISPLAY_GAMMA: f64 = 2.2;

/// Surfaces of the room shell, in the order of [`Scene::room_materials`].
const ROOM_SURFACES: usize = 6;

/// The procedural room: a shell (6 faces) and a list of objects.
#[derive(Debug, Clone)]
struct Scene {
    /// Materials of the faces -x, +x, -y, +y (walls), -z (floor), +z (ceiling).
    room_materials: [usize; ROOM_SURFACES],
    primitives: Vec<Primitive>,
    materials: Vec<Material>,
}

/// Salts that give each part of the generator its own RNG stream for a seed, so changing one
/// part (e.g. the number of agents) never moves another (e.g. the furniture).
const SCENE_STREAM: u64 = 0x5CE4_E000_0000_0001;
const TRAJECTORY_STREAM: u64 = 0x7A4E_C700_0000_0002;

fn stream_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(mix64(seed ^ mix64(stream)))
}

fn symmetric(rng: &mut ChaCha8Rng, amplitude: f64) -> f64 {
    rng.random_range(-amplitude..=amplitude)
}

fn random_colour(rng: &mut ChaCha8Rng, saturation: (f64, f64), value: (f64, f64)) -> Rgb {
    hsv_to_rgb(
        rng.random_range(0.0..1.0),
        rng.random_range(saturation.0..=saturation.1),
        rng.random_range(value.0..=value.1),
    )
}

fn random_material(rng: &mut ChaCha8Rng, pattern: Pattern, value_range: (f64, f64)) -> Material {
    let primary = random_colour(rng, (0.15, 0.7), value_range);
    // The second colour differs in hue and clearly in brightness, so patterns have contrast in
    // grey-level too (trackers often work on intensity).
    let hsv_hue_shift = rng.random_range(0.08..0.5);
    let secondary_value = if rng.random_bool(0.5) {
        value_range.0 * 0.45
    } else {
        (value_range.1 * 1.15).min(1.0)
    };
    let base_hue = rng.random_range(0.0..1.0);
    let secondary = hsv_to_rgb(
        base_hue + hsv_hue_shift,
        rng.random_range(0.2..0.8),
        secondary_value,
    );
    Material {
        pattern,
        primary,
        secondary,
        noise_seed: rng.random(),
        noise_frequency: rng.random_range(1.5..3.5),
        detail_strength: rng.random_range(0.18..0.32),
        cell_tint: rng.random_range(0.08..0.2),
    }
}

fn random_object_pattern(rng: &mut ChaCha8Rng) -> Pattern {
    match rng.random_range(0..4u32) {
        0 => Pattern::Marble,
        1 => Pattern::Checker {
            period: rng.random_range(0.08..0.2),
        },
        2 => {
            let angle: f64 = rng.random_range(0.0..PI);
            Pattern::Stripes {
                period: rng.random_range(0.06..0.16),
                cos_angle: angle.cos(),
                sin_angle: angle.sin(),
            }
        }
        _ => Pattern::Tiles {
            period: rng.random_range(0.06..0.15),
            grout_half_width: 0.005,
        },
    }
}

impl Scene {
    fn generate(seed: u64) -> Self {
        let mut rng = stream_rng(seed, SCENE_STREAM);
        let mut materials = Vec::new();
        let mut add_material = |material: Material| {
            materials.push(material);
            materials.len() - 1
        };
        // Room shell: each wall a different kind of pattern, floor planks, ceiling panels.
        let wall_value = (0.55, 0.9);
        let stripe_angle: f64 = PI / 2.0 + symmetric(&mut rng, 0.05);
        let west = add_material(random_material(&mut rng, Pattern::Marble, wall_value));
        let east = add_material(random_material(
            &mut rng,
            Pattern::Stripes {
                period: 0.21,
                cos_angle: stripe_angle.cos(),
                sin_angle: stripe_angle.sin(),
            },
            wall_value,
        ));
        let south = add_material(random_material(
            &mut rng,
            Pattern::Checker { period: 0.5 },
            wall_value,
        ));
        let north = add_material(random_material(
            &mut rng,
            Pattern::Tiles {
                period: 0.3,
                grout_half_width: 0.008,
            },
            wall_value,
        ));
        let floor = add_material(random_material(
            &mut rng,
            Pattern::Planks {
                width: 0.16,
                length: 1.1,
            },
            (0.45, 0.75),
        ));
        let ceiling = add_material(random_material(
            &mut rng,
            Pattern::Tiles {
                period: 0.6,
                grout_half_width: 0.012,
            },
            (0.7, 0.95),
        ));
        let room_materials = [west, east, south, north, floor, ceiling];

        let mut primitives = Vec::new();
        let mut add = |shape: Shape, rng: &mut ChaCha8Rng, materials: &mut Vec<Material>| {
            let pattern = random_object_pattern(rng);
            materials.push(random_material(rng, pattern, (0.35, 0.9)));
            primitives.push(Primitive::new(shape, materials.len() - 1));
        };
        let cuboid = |center: Vector3<f64>, half_size: Vector3<f64>, yaw: f64| Shape::Cuboid {
            center,
            half_size,
            cos_yaw: yaw.cos(),
            sin_yaw: yaw.sin(),
        };

        // Table in the middle of the room, with a box, a ball and a vase on it.
        let table_center = Vector3::new(symmetric(&mut rng, 0.15), symmetric(&mut rng, 0.1), 0.0);
        let table_yaw = symmetric(&mut rng, 0.25);
        let (top_half, top_height, top_thickness) = (
            Vector3::new(0.6, 0.4, 0.02),
            rng.random_range(0.72..0.78),
            0.04,
        );
        let on_table = |x: f64, y: f64, z: f64| {
            table_center
                + from_yawed(&Vector3::new(x, y, 0.0), table_yaw.cos(), table_yaw.sin())
                + Vector3::new(0.0, 0.0, z)
        };
        add(
            cuboid(
                on_table(0.0, 0.0, top_height - top_half.z),
                top_half,
                table_yaw,
            ),
            &mut rng,
            &mut materials,
        );
        let leg_half = Vector3::new(0.03, 0.03, (top_height - top_thickness) / 2.0);
        let leg_material_shape = |sx: f64, sy: f64| {
            cuboid(
                on_table(
                    sx * (top_half.x - 0.07),
                    sy * (top_half.y - 0.07),
                    leg_half.z,
                ),
                leg_half,
                table_yaw,
            )
        };
        for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            add(leg_material_shape(sx, sy), &mut rng, &mut materials);
        }
        let box_half = Vector3::new(0.16, 0.12, 0.1);
        let box_center = on_table(
            -0.25 + symmetric(&mut rng, 0.05),
            0.1 + symmetric(&mut rng, 0.05),
            top_height + box_half.z,
        );
        add(
            cuboid(box_center, box_half, table_yaw + symmetric(&mut rng, 0.6)),
            &mut rng,
            &mut materials,
        );
        let ball_radius = 0.11;
        add(
            Shape::Sphere {
                center: on_table(
                    0.3 + symmetric(&mut rng, 0.05),
                    -0.12,
                    top_height + ball_radius,
                ),
                radius: ball_radius,
            },
            &mut rng,
            &mut materials,
        );
        add(
            Shape::Cylinder {
                base: on_table(0.05, -0.22 + symmetric(&mut rng, 0.04), top_height),
                radius: 0.06,
                height: 0.22,
            },
            &mut rng,
            &mut materials,
        );

        // Furniture along the walls, outside the agents' walking loop.
        let cabinet_y = -0.2 + symmetric(&mut rng, 0.2);
        add(
            cuboid(
                Vector3::new(2.775, cabinet_y, 0.95),
                Vector3::new(0.225, 0.7, 0.95),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );
        let shelf_x = -0.6 + symmetric(&mut rng, 0.2);
        add(
            cuboid(
                Vector3::new(shelf_x, -2.3, 0.6),
                Vector3::new(0.8, 0.2, 0.6),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );
        let bench_y = 0.3 + symmetric(&mut rng, 0.2);
        add(
            cuboid(
                Vector3::new(-2.75, bench_y, 0.22),
                Vector3::new(0.25, 0.6, 0.22),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );
        let big_ball_radius = 0.4;
        add(
            Shape::Sphere {
                center: Vector3::new(
                    2.35 + symmetric(&mut rng, 0.1),
                    1.85 + symmetric(&mut rng, 0.1),
                    big_ball_radius,
                ),
                radius: big_ball_radius,
            },
            &mut rng,
            &mut materials,
        );
        add(
            Shape::Cylinder {
                base: Vector3::new(-2.6, -2.1, 0.0),
                radius: 0.22,
                height: ROOM_MAX[2],
            },
            &mut rng,
            &mut materials,
        );
        add(
            Shape::Cylinder {
                base: Vector3::new(
                    -2.45 + symmetric(&mut rng, 0.08),
                    1.95 + symmetric(&mut rng, 0.08),
                    0.0,
                ),
                radius: 0.22,
                height: 0.65,
            },
            &mut rng,
            &mut materials,
        );
        let stack_x = 0.8 + symmetric(&mut rng, 0.2);
        let lower_half = Vector3::new(0.4, 0.25, 0.25);
        add(
            cuboid(
                Vector3::new(stack_x, 2.2, lower_half.z),
                lower_half,
                symmetric(&mut rng, 0.15),
            ),
            &mut rng,
            &mut materials,
        );
        let upper_half = Vector3::new(0.25, 0.2, 0.18);
        add(
            cuboid(
                Vector3::new(
                    stack_x + symmetric(&mut rng, 0.1),
                    2.22,
                    2.0 * lower_half.z + upper_half.z,
                ),
                upper_half,
                symmetric(&mut rng, 0.4),
            ),
            &mut rng,
            &mut materials,
        );
        // Posters: thin boards on three walls.
        add(
            cuboid(
                Vector3::new(-2.99, bench_y, 1.5),
                Vector3::new(0.01, 0.5, 0.35),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );
        add(
            cuboid(
                Vector3::new(-0.8, 2.49, 1.55),
                Vector3::new(0.45, 0.01, 0.3),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );
        add(
            cuboid(
                Vector3::new(1.5, -2.49, 1.6),
                Vector3::new(0.4, 0.01, 0.5),
                0.0,
            ),
            &mut rng,
            &mut materials,
        );

        Self {
            room_materials,
            primitives,
            materials,
        }
    }

    /// Nearest surface along the ray: the closest object, else the room shell.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let mut best = self.intersect_room(ray);
        for primitive in &self.primitives {
            if !primitive.may_hit(ray, best.map_or(f64::INFINITY, |b| b.t)) {
                continue;
            }
            if let Some(hit) = primitive.intersect(ray)
                && best.is_none_or(|b| hit.t < b.t)
            {
                best = Some(hit);
            }
        }
        best
    }

    /// Where a ray from inside the room leaves it.
    fn intersect_room(&self, ray: &Ray) -> Option<Hit> {
        let min = Vector3::from(ROOM_MIN);
        let max = Vector3::from(ROOM_MAX);
        let center = (min + max) / 2.0;
        let half_size = (max - min) / 2.0;
        let origin = ray.origin - center;
        let (_, t_exit, _, axis) = slabs(&origin, &ray.direction, &half_size)?;
        if t_exit <= MIN_HIT_DISTANCE {
            return None;
        }
        let positive_side = ray.direction[axis] > 0.0;
        let mut normal = Vector3::zeros();
        normal[axis] = if positive_side { -1.0 } else { 1.0 };
        let point = ray.at(t_exit);
        Some(Hit {
            t: t_exit,
            normal,
            uv: face_uv(&point, axis, positive_side),
            material: self.room_materials[2 * axis + usize::from(positive_side)],
        })
    }

    /// Lambertian radiance (linear) of a hit seen along `ray`, with `pixel_angle` the angular size
    /// of one pixel along the optical axis (1 / focal length).
    fn shade(&self, ray: &Ray, hit: &Hit, pixel_angle: f64) -> Rgb {
        let ray_length_per_t = ray.direction.norm();
        let view = ray.direction / ray_length_per_t;
        // Two-sided surfaces: face the normal towards the viewer.
        let normal = if hit.normal.dot(&view) > 0.0 {
            -hit.normal
        } else {
            hit.normal
        };
        let cosine = (-normal.dot(&view)).max(MIN_FOOTPRINT_COSINE);
        // Pixel footprint on the surface: lateral size at this depth, stretched by obliquity. Off-axis
        // pixels subtend a smaller angle by the factor 1/|direction|^2, and the ray is |direction|
        // times longer than t.
        let footprint = hit.t * pixel_angle / ray_length_per_t / cosine;
        let albedo = self.materials[hit.material].albedo(hit.uv, footprint);
        let point = ray.at(hit.t);
        let mut light = AMBIENT_LIGHT;
        for (position, strength) in LAMPS {
            let to_lamp = Vector3::from(position) - point;
            let distance = to_lamp.norm();
            let incidence = normal.dot(&to_lamp) / distance;
            if incidence > 0.0 {
                let ratio = distance / LAMP_FALLOFF_DISTANCE;
                light += strength * incidence / (1.0 + ratio * ratio);
            }
        }
        [albedo[0] * light, albedo[1] * light, albedo[2] * light]
    }
}

/// Entries of the linear-to-display table: fine enough that the 8-bit output matches an exact
/// `powf` to within one level for radiance above 1e-4 (the ambient light keeps every pixel
/// well above that).
const GAMMA_TABLE_SIZE: usize = 1 << 16;

/// Linear radiance -> 8-bit display value by table lookup (three `powf` per pixel were a
/// noticeable share of the rendering time).
fn to_display_u8(linear: f64) -> u8 {
    static TABLE: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let last = (GAMMA_TABLE_SIZE - 1) as f64;
        (0..GAMMA_TABLE_SIZE)
            .map(|i| ((i as f64 / last).powf(1.0 / DISPLAY_GAMMA) * 255.0).round() as u8)
            .collect()
    });
    table[(linear.clamp(0.0, 1.0) * (GAMMA_TABLE_SIZE - 1) as f64).round() as usize]
}

/// Largest depth the 16-bit millimetre format can hold (65535 is the 7-Scenes hole marker).
const MAX_DEPTH_RAW: u16 = INVALID_DEPTH_RAW - 1;

/// Camera z (metres) -> whole millimetres, 0 when invalid or out of range.
fn depth_to_raw(z: f64) -> u16 {
    let millimetres = (z * DEPTH_UNITS_PER_METRE).round();
    if millimetres.is_finite() && millimetres >= 1.0 && millimetres <= MAX_DEPTH_RAW as f64 {
        millimetres as u16
    } else {
        0
    }
}

/// Ray-casts one view: 8-bit RGB and millimetre-quantised depth decoded exactly as the 7-Scenes
/// reader decodes a depth PNG.
fn render(
    scene: &Scene,
    intrinsics: &Intrinsics,
    world_from_camera: &Isometry3<f64>,
) -> (RgbImage, DepthImage) {
    let (width, height) = (intrinsics.width as usize, intrinsics.height as usize);
    let rotation = world_from_camera.rotation.to_rotation_matrix();
    let origin = world_from_camera.translation.vector;
    let pixel_angle = 1.0 / intrinsics.fx.min(intrinsics.fy);
    let mut rgb = vec![0u8; width * height * 3];
    let mut raw_depth = vec![0u16; width * height];
    rgb.par_chunks_mut(width * 3)
        .zip(raw_depth.par_chunks_mut(width))
        .enumerate()
        .for_each(|(row, (rgb_row, depth_row))| {
            let y = (row as f64 - intrinsics.cy) / intrinsics.fy;
            for column in 0..width {
                let x = (column as f64 - intrinsics.cx) / intrinsics.fx;
                let ray = Ray {
                    origin,
                    direction: rotation * Vector3::new(x, y, 1.0),
                };
                let Some(hit) = scene.intersect(&ray) else {
                    continue;
                };
                depth_row[column] = depth_to_raw(hit.t);
                let radiance = scene.shade(&ray, &hit, pixel_angle);
                for channel in 0..3 {
                    rgb_row[3 * column + channel] = to_display_u8(radiance[channel]);
                }
            }
        });
    let rgb = RgbImage::from_raw(intrinsics.width, intrinsics.height, rgb)
        .expect("buffer sized width * height * 3");
    let depth = DepthImage::from_raw_u16(
        intrinsics.width,
        intrinsics.height,
        &raw_depth,
        DEPTH_UNITS_PER_METRE,
        Some(INVALID_DEPTH_RAW),
    );
    (rgb, depth)
}

// ---------------------------------------------------------------------------------------------
// Trajectories
// ---------------------------------------------------------------------------------------------

/// The agents' walking loop: an ellipse around the table, radii in metres.
const LOOP_RADII: [f64; 2] = [1.85, 1.35];
/// Per-agent scale of the loop (agents walk slightly different loops) and its slow wobble.
const LOOP_SCALE_JITTER: f64 = 0.05;
const LOOP_WOBBLE: f64 = 0.05;
/// Walking speed: metres per frame at 30 Hz (0.6 m/s), varying by +-SPEED_VARIATION.
const STEP_LENGTH: f64 = 0.02;
const SPEED_VARIATION: f64 = 0.25;
const SPEED_PERIOD_FRAMES: f64 = 210.0;
/// Eye height, its slow variation and the walking head-bob (one bob per step, ~2 steps/s).
const EYE_HEIGHT: f64 = 1.45;
const EYE_HEIGHT_SWAY: f64 = 0.1;
const EYE_HEIGHT_PERIOD_FRAMES: f64 = 420.0;
const HEAD_BOB: f64 = 0.006;
const HEAD_BOB_PERIOD_FRAMES: f64 = 16.0;
/// The gaze point wanders around the table so views sweep over different parts of the room.
const GAZE_CENTER_HEIGHT: f64 = 0.8;
/// The gaze point lies beyond the room's centre by this fraction of the camera's horizontal
/// distance to the centre: the camera looks across the room (more walls in view) and, the gaze
/// point being farther, walking turns the view more gently.
const GAZE_BEYOND_CENTER: f64 = 0.4;
const GAZE_WANDER: [f64; 3] = [0.55, 0.45, 0.3];
const GAZE_PERIOD_FRAMES: [f64; 3] = [400.0, 330.0, 280.0];
/// Slow camera roll (radians) of a hand-held camera.
const ROLL_AMPLITUDE: f64 = 0.04;
const ROLL_PERIOD_FRAMES: f64 = 300.0;
/// Start-angle jitter around the evenly spread starting points (radians).
const START_ANGLE_JITTER: f64 = 0.1;
/// Angle step for the numerical derivative of the loop.
const LOOP_DERIVATIVE_STEP: f64 = 1e-5;

/// Smooth, seeded parameters of one agent's walk.
struct Walk {
    start_angle: f64,
    /// +1 counter-clockwise, -1 clockwise; agents alternate so neighbours walk towards each
    /// other's stretches and see the same places from similar viewpoints.
    direction: f64,
    scale: f64,
    wobble_phase: f64,
    speed_phase: f64,
    height_phase: f64,
    bob_phase: f64,
    gaze_phases: [f64; 3],
    roll_phase: f64,
}

impl Walk {
    fn new(seed: u64, agents: usize, agent: usize) -> Self {
        let mut rng = stream_rng(seed, TRAJECTORY_STREAM.wrapping_add(agent as u64));
        let mut phase = || rng.random_range(0.0..TAU);
        let gaze_phases = [phase(), phase(), phase()];
        let (wobble_phase, speed_phase, height_phase, bob_phase, roll_phase) =
            (phase(), phase(), phase(), phase(), phase());
        let start_angle =
            TAU * agent as f64 / agents as f64 + symmetric(&mut rng, START_ANGLE_JITTER);
        let scale = 1.0 + symmetric(&mut rng, LOOP_SCALE_JITTER);
        let direction = if agent.is_multiple_of(2) { 1.0 } else { -1.0 };
        Self {
            start_angle,
            direction,
            scale,
            wobble_phase,
            speed_phase,
            height_phase,
            bob_phase,
            gaze_phases,
            roll_phase,
        }
    }

    /// Horizontal position on the loop at `angle`.
    fn loop_point(&self, angle: f64) -> [f64; 2] {
        let radius_scale =
            self.scale * (1.0 + LOOP_WOBBLE * (2.0 * angle + self.wobble_phase).sin());
        [
            radius_scale * LOOP_RADII[0] * angle.cos(),
            radius_scale * LOOP_RADII[1] * angle.sin(),
        ]
    }

    /// Metres walked per radian of loop angle at `angle`.
    fn loop_speed(&self, angle: f64) -> f64 {
        let a = self.loop_point(angle - LOOP_DERIVATIVE_STEP);
        let b = self.loop_point(angle + LOOP_DERIVATIVE_STEP);
        (b[0] - a[0]).hypot(b[1] - a[1]) / (2.0 * LOOP_DERIVATIVE_STEP)
    }

    fn pose(&self, angle: f64, frame: f64) -> Isometry3<f64> {
        let [x, y] = self.loop_point(angle);
        let z = EYE_HEIGHT
            + EYE_HEIGHT_SWAY * (TAU * frame / EYE_HEIGHT_PERIOD_FRAMES + self.height_phase).sin()
            + HEAD_BOB * (TAU * frame / HEAD_BOB_PERIOD_FRAMES + self.bob_phase).sin();
        let position = Vector3::new(x, y, z);
        let wander = |axis: usize| {
            GAZE_WANDER[axis]
                * (TAU * frame / GAZE_PERIOD_FRAMES[axis] + self.gaze_phases[axis]).sin()
        };
        let gaze = Vector3::new(
            wander(0) - GAZE_BEYOND_CENTER * x,
            wander(1) - GAZE_BEYOND_CENTER * y,
            GAZE_CENTER_HEIGHT + wander(2),
        );
        let roll = ROLL_AMPLITUDE * (TAU * frame / ROLL_PERIOD_FRAMES + self.roll_phase).sin();
        Isometry3::from_parts(
            Translation3::from(position),
            look_at(&position, &gaze, roll),
        )
    }
}

/// Camera orientation (x right, y down, z forward) looking from `eye` to `target` with the world
/// z axis up, then rolled about the optical axis.
fn look_at(eye: &Vector3<f64>, target: &Vector3<f64>, roll: f64) -> UnitQuaternion<f64> {
    let forward = (target - eye).normalize();
    let right = forward.cross(&Vector3::z()).normalize();
    let down = forward.cross(&right);
    let world_from_camera = Matrix3::from_columns(&[right, down, forward]);
    let rolled =
        world_from_camera * Rotation3::from_axis_angle(&Vector3::z_axis(), roll).into_inner();
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rolled))
}

/// Ground-truth `world_from_camera` of every frame of one agent.
fn trajectory(spec: &SyntheticSpec) -> Vec<Isometry3<f64>> {
    let walk = Walk::new(spec.seed, spec.agents, spec.agent);
    let mut angle = walk.start_angle;
    let mut poses = Vec::with_capacity(spec.frames);
    for frame in 0..spec.frames {
        let frame = frame as f64;
        poses.push(walk.pose(angle, frame));
        let step = STEP_LENGTH
            * (1.0
                + SPEED_VARIATION * (TAU * frame / SPEED_PERIOD_FRAMES + walk.speed_phase).sin());
        angle += walk.direction * step / walk.loop_speed(angle);
    }
    poses
}

// ---------------------------------------------------------------------------------------------
// Dataset
// ---------------------------------------------------------------------------------------------

/// One agent's synthetic sequence, rendered on demand.
pub struct SyntheticDataset {
    spec: SyntheticSpec,
    intrinsics: Intrinsics,
    scene: Scene,
    /// Ground truth of every frame 0..frames (not only the selected ones).
    trajectory: Vec<Isometry3<f64>>,
    /// Frame numbers selected by the range.
    numbers: Vec<usize>,
}

impl SyntheticDataset {
    pub fn new(spec: SyntheticSpec, range: FrameRange) -> Result<Self, DatasetError> {
        spec.validate()
            .map_err(|reason| DatasetError::Invalid(format!("synthetic spec {spec}: {reason}")))?;
        let numbers: Vec<usize> = (0..spec.frames).filter(|&n| range.contains(n)).collect();
        if numbers.is_empty() {
            return Err(DatasetError::Invalid(format!(
                "{spec}: frame range {range} selects none of its frames 0..{}",
                spec.frames
            )));
        }
        Ok(Self {
            spec,
            intrinsics: spec.intrinsics(),
            scene: Scene::generate(spec.seed),
            trajectory: trajectory(&spec),
            numbers,
        })
    }

    pub fn spec(&self) -> &SyntheticSpec {
        &self.spec
    }

    /// Renders an arbitrary view of the scene (e.g. for visual checks), returning RGB and depth.
    pub fn render_view(&self, world_from_camera: &Isometry3<f64>) -> (RgbImage, DepthImage) {
        render(&self.scene, &self.intrinsics, world_from_camera)
    }
}

impl Dataset for SyntheticDataset {
    fn describe(&self) -> String {
        format!("synthetic scene ({})", self.spec)
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn len(&self) -> usize {
        self.numbers.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.numbers[position]
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.numbers[position] as f64 / FRAMES_PER_SECOND
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(Some(self.trajectory[self.numbers[position]]))
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let number = self.numbers[position];
        let pose = self.trajectory[number];
        let (rgb, depth) = render(&self.scene, &self.intrinsics, &pose);
        Ok(Frame {
            index: number,
            timestamp: self.timestamp(position),
            rgb,
            depth,
            world_from_camera_gt: Some(pose),
            intrinsics: self.intrinsics,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Writing to disk
// ---------------------------------------------------------------------------------------------

/// Description of a written dataset, saved as `scene.json` next to the agent folders.
pub const SCENE_FILE: &str = "scene.json";

/// Folder of agent `agent` inside an output folder.
pub fn agent_folder(out_dir: &Path, agent: usize) -> PathBuf {
    out_dir.join(format!("agent_{agent}"))
}

#[derive(Debug, Serialize, Deserialize)]
struct SceneDescription {
    generator: String,
    spec: String,
    agents: usize,
    frames_per_agent: usize,
    seed: u64,
    intrinsics: Intrinsics,
    frames_per_second: f64,
    depth_units_per_metre: f64,
    room_min: [f64; 3],
    room_max: [f64; 3],
    agent_folders: Vec<String>,
}

/// Frames rendered ahead of the writer: rendering and PNG encoding run concurrently.
const WRITE_QUEUE_DEPTH: usize = 4;

/// Writes every agent of `spec` (its `agent` field is ignored) into `out_dir/agent_K/` in the
/// 7-Scenes layout (PNG colour, millimetre depth PNG, pose files, `camera-intrinsics.txt`,
/// `groundtruth_tum.txt`) plus `out_dir/scene.json`. `progress(done, total)` is called after each
/// frame. Refuses to write into an agent folder that already holds files, so frames of an
/// earlier, longer run cannot mix in (see [`remove_written`]). Returns the agent folders.
pub fn write_seven_scenes(
    spec: &SyntheticSpec,
    out_dir: &Path,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<PathBuf>, DatasetError> {
    let spec = spec.with_agent(0);
    spec.validate()
        .map_err(|reason| DatasetError::Invalid(format!("synthetic spec {spec}: {reason}")))?;
    let folders: Vec<PathBuf> = (0..spec.agents)
        .map(|agent| agent_folder(out_dir, agent))
        .collect();
    for folder in &folders {
        if let Ok(mut entries) = std::fs::read_dir(folder)
            && entries.next().is_some()
        {
            return Err(DatasetError::Invalid(format!(
                "{}: folder is not empty; remove it (or use --overwrite) so frames of an earlier run do not mix in",
                folder.display()
            )));
        }
    }
    std::fs::create_dir_all(out_dir).map_err(|e| DatasetError::io(out_dir, e))?;
    let description = SceneDescription {
        generator: "mac-ego3d synthetic scene".into(),
        spec: spec.to_string(),
        agents: spec.agents,
        frames_per_agent: spec.frames,
        seed: spec.seed,
        intrinsics: spec.intrinsics(),
        frames_per_second: FRAMES_PER_SECOND,
        depth_units_per_metre: DEPTH_UNITS_PER_METRE,
        room_min: ROOM_MIN,
        room_max: ROOM_MAX,
        agent_folders: folders
            .iter()
            .map(|f| {
                f.file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect(),
    };
    let scene_path = out_dir.join(SCENE_FILE);
    let json = serde_json::to_string_pretty(&description)
        .map_err(|e| DatasetError::Invalid(format!("{}: {e}", scene_path.display())))?;
    std::fs::write(&scene_path, json + "\n").map_err(|e| DatasetError::io(&scene_path, e))?;

    let total = spec.agents * spec.frames;
    let (sender, receiver) =
        std::sync::mpsc::sync_channel::<Result<(usize, Frame), DatasetError>>(WRITE_QUEUE_DEPTH);
    std::thread::scope(|scope| {
        scope.spawn(move || {
            for agent in 0..spec.agents {
                let dataset = match SyntheticDataset::new(spec.with_agent(agent), FrameRange::ALL) {
                    Ok(dataset) => dataset,
                    Err(e) => {
                        let _ = sender.send(Err(e));
                        return;
                    }
                };
                for position in 0..dataset.len() {
                    // A send error means the writer stopped on an error of its own: stop too.
                    if sender
                        .send(dataset.load(position).map(|frame| (agent, frame)))
                        .is_err()
                    {
                        return;
                    }
                }
            }
        });
        let mut writer: Option<(usize, SevenScenesWriter)> = None;
        let mut done = 0;
        for message in receiver {
            let (agent, frame) = message?;
            if writer.as_ref().is_none_or(|(current, _)| *current != agent) {
                if let Some((_, finished)) = writer.take() {
                    finished.finish()?;
                }
                writer = Some((
                    agent,
                    SevenScenesWriter::create(&folders[agent], &frame.intrinsics)?,
                ));
            }
            if let Some((_, current)) = writer.as_mut() {
                current.write(&frame)?;
            }
            done += 1;
            progress(done, total);
        }
        if let Some((_, finished)) = writer.take() {
            finished.finish()?;
        }
        Ok::<(), DatasetError>(())
    })?;
    Ok(folders)
}

/// Removes what [`write_seven_scenes`] writes (the `agent_K` folders' frame, intrinsics and
/// ground-truth files, then the folders if empty, and `scene.json`), touching nothing else.
/// Returns the number of files removed.
pub fn remove_written(out_dir: &Path) -> Result<usize, DatasetError> {
    let mut removed = 0;
    let Ok(entries) = std::fs::read_dir(out_dir) else {
        return Ok(0);
    };
    for entry in entries.flatten() {
        let folder = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        let is_agent_folder = name
            .strip_prefix("agent_")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !is_agent_folder || !folder.is_dir() {
            continue;
        }
        for file in std::fs::read_dir(&folder)
            .map_err(|e| DatasetError::io(&folder, e))?
            .flatten()
        {
            let file_name = file.file_name().to_string_lossy().into_owned();
            let ours = (file_name.starts_with("frame-")
                && (file_name.ends_with(".color.png")
                    || file_name.ends_with(".depth.png")
                    || file_name.ends_with(".pose.txt")))
                || file_name == crate::seven_scenes::INTRINSICS_FILE
                || file_name == "groundtruth_tum.txt";
            if ours {
                std::fs::remove_file(file.path()).map_err(|e| DatasetError::io(&file.path(), e))?;
                removed += 1;
            }
        }
        // Leave a folder that still holds someone else's files.
        let _ = std::fs::remove_dir(&folder);
    }
    let scene = out_dir.join(SCENE_FILE);
    if scene.is_file() {
        std::fs::remove_file(&scene).map_err(|e| DatasetError::io(&scene, e))?;
        removed += 1;
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    /// Small images keep the rendering tests fast in the lightly optimised test build.
    const TEST_WIDTH: u32 = 160;
    const TEST_HEIGHT: u32 = 120;

    /// How far a rotation may move through the pose file's re-orthonormalisation.
    const POSE_FILE_ROTATION_TOLERANCE_RAD: f64 = 1e-10;

    fn small_spec(agents: usize, agent: usize, frames: usize, seed: u64) -> SyntheticSpec {
        SyntheticSpec {
            agents,
            agent,
            frames,
            seed,
            width: TEST_WIDTH,
            height: TEST_HEIGHT,
        }
    }

    fn camera_looking(eye: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(eye), look_at(&eye, &target, 0.0))
    }

    #[test]
    fn spec_parses_defaults_keys_and_round_trips() {
        let default: SyntheticSpec = "synthetic".parse().unwrap();
        assert_eq!(default, SyntheticSpec::default());
        assert_eq!(
            (default.agents, default.agent, default.frames, default.seed),
            (3, 0, 300, 0)
        );
        assert_eq!((default.width, default.height), (640, 480));
        let spec: SyntheticSpec =
            "synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240"
                .parse()
                .unwrap();
        assert_eq!(
            spec,
            SyntheticSpec {
                agents: 3,
                agent: 1,
                frames: 300,
                seed: 7,
                width: 320,
                height: 240
            }
        );
        assert_eq!(
            spec.to_string(),
            "synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240"
        );
        assert_eq!(spec.to_string().parse::<SyntheticSpec>().unwrap(), spec);
        let partial: SyntheticSpec = "synthetic: seed=9 , agent=2".parse().unwrap();
        assert_eq!(
            (partial.seed, partial.agent, partial.frames),
            (9, 2, DEFAULT_FRAMES)
        );
    }

    #[test]
    fn spec_errors_name_the_bad_key() {
        let cases = [
            ("synthetic:agnets=3", "agnets"),
            ("synthetic:frames=many", "frames"),
            ("synthetic:seed=-1", "seed"),
            ("synthetic:width=12", "width"),
            ("synthetic:height=0", "height"),
            ("synthetic:agents=2,agent=2", "agent=2"),
            ("synthetic:agents=0", "agents=0"),
            ("synthetic:frames=0", "frames=0"),
            ("synthetic:seed=1,seed=2", "seed"),
            ("synthetic:seed", "seed"),
        ];
        for (text, key) in cases {
            let err = text.parse::<SyntheticSpec>().unwrap_err();
            assert!(
                err.contains(key),
                "{text}: error {err:?} does not name {key:?}"
            );
        }
        assert!("synthetics".parse::<SyntheticSpec>().is_err());
        assert!("replica".parse::<SyntheticSpec>().is_err());
    }

    #[test]
    fn intrinsics_follow_the_resolution() {
        let k = SyntheticSpec::default().intrinsics();
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
            (525.0, 525.0, 319.5, 239.5, 640, 480)
        );
        let half = small_spec(1, 0, 1, 0).intrinsics();
        let expected = k.scaled(0.25);
        assert!(
            (half.fx - expected.fx).abs() < 1e-12
                && (half.cx - expected.cx).abs() < 1e-12
                && (half.cy - expected.cy).abs() < 1e-12
        );
    }

    #[test]
    fn frames_are_deterministic_for_a_seed_and_thread_count() {
        let spec = small_spec(2, 1, 40, 5);
        let a = SyntheticDataset::new(spec, FrameRange::ALL)
            .unwrap()
            .load(17)
            .unwrap();
        let single_thread = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let b = single_thread.install(|| {
            SyntheticDataset::new(spec, FrameRange::ALL)
                .unwrap()
                .load(17)
                .unwrap()
        });
        assert_eq!(a.rgb, b.rgb);
        assert_eq!(a.depth, b.depth);
        assert_eq!(a.world_from_camera_gt, b.world_from_camera_gt);
        let other_seed = SyntheticDataset::new(SyntheticSpec { seed: 6, ..spec }, FrameRange::ALL)
            .unwrap()
            .load(17)
            .unwrap();
        assert_ne!(a.rgb, other_seed.rgb);
        assert_ne!(a.world_from_camera_gt, other_seed.world_from_camera_gt);
    }

    #[test]
    fn range_selects_frame_numbers_and_timestamps() {
        let ds = SyntheticDataset::new(small_spec(3, 2, 50, 0), "10..20".parse().unwrap()).unwrap();
        assert_eq!(ds.len(), 10);
        assert_eq!(ds.frame_index(0), 10);
        assert_eq!(ds.timestamp(3), 13.0 / 30.0);
        let all = SyntheticDataset::new(small_spec(3, 2, 50, 0), FrameRange::ALL).unwrap();
        assert_eq!(ds.ground_truth(3).unwrap(), all.ground_truth(13).unwrap());
        let err = SyntheticDataset::new(small_spec(3, 2, 50, 0), "60..".parse().unwrap())
            .err()
            .unwrap();
        assert!(err.to_string().contains("60.."), "{err}");
        assert!(SyntheticDataset::new(small_spec(3, 3, 50, 0), FrameRange::ALL).is_err());
    }

    #[test]
    fn depth_is_exact_camera_z_on_known_planes() {
        let scene = Scene::generate(0);
        let k = small_spec(1, 0, 1, 0).intrinsics();
        let eye = Vector3::new(0.1, -0.2, 1.5);
        let ceiling = ROOM_MAX[2];
        // Straight up at the ceiling: every pixel's camera z is the height difference.
        // The identity rotation looks along world +z: camera x = east, y = north, z = up.
        let up = Isometry3::translation(eye.x, eye.y, eye.z);
        let (_, depth) = render(&scene, &k, &up);
        let expected = ((ceiling - eye.z) * 1000.0).round() as f32 / 1000.0;
        assert!(
            depth.data.iter().all(|&d| (d - expected).abs() < 1e-6),
            "ceiling depth should be {expected} everywhere"
        );

        // Obliquely at the ceiling: z = (ceiling - eye_z) / (world-z component of the ray with
        // unit camera z), exact up to millimetre quantisation.
        let oblique = camera_looking(eye, eye + Vector3::new(1.0, 0.6, 1.2));
        let (_, depth) = render(&scene, &k, &oblique);
        let rotation = oblique.rotation.to_rotation_matrix();
        let mut checked = 0;
        for v in 0..k.height {
            for u in 0..k.width {
                let ray = rotation
                    * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                if ray.z <= 0.0 {
                    continue;
                }
                let z = (ceiling - eye.z) / ray.z;
                let hit = eye + ray * z;
                // Only rays that reach the ceiling well inside the walls.
                let margin = 0.05;
                if hit.x.abs() > ROOM_MAX[0] - margin || hit.y.abs() > ROOM_MAX[1] - margin {
                    continue;
                }
                let got = depth.get(u, v) as f64;
                assert!(
                    (got - z).abs() <= 0.0005 + 1e-6,
                    "pixel ({u}, {v}): depth {got}, expected {z}"
                );
                checked += 1;
            }
        }
        assert!(
            checked > (k.width * k.height / 2) as usize,
            "only {checked} pixels reached the ceiling"
        );

        // The optical axis through the centre of a sphere hits it at distance - radius.
        let (center, radius) = scene
            .primitives
            .iter()
            .find_map(|p| match p.shape {
                Shape::Sphere { center, radius } if radius > 0.3 => Some((center, radius)),
                _ => None,
            })
            .unwrap();
        let square = SyntheticSpec {
            width: 81,
            height: 61,
            ..small_spec(1, 0, 1, 0)
        }
        .intrinsics();
        let viewer = Vector3::new(0.5, 0.3, 1.2);
        let (_, depth) = render(&scene, &square, &camera_looking(viewer, center));
        let expected = (center - viewer).norm() - radius;
        let got = depth.get(40, 30) as f64;
        assert!(
            (got - expected).abs() <= 0.0005 + 1e-6,
            "sphere depth {got}, expected {expected}"
        );
    }

    #[test]
    fn depth_quantisation_matches_the_png_reader() {
        for z in [
            0.0004,
            0.0006,
            1.2344,
            1.2346,
            3.0,
            65.534,
            65.5346,
            f64::INFINITY,
            f64::NAN,
            -1.0,
        ] {
            let raw = depth_to_raw(z);
            let streamed = DepthImage::from_raw_u16(
                1,
                1,
                &[raw],
                DEPTH_UNITS_PER_METRE,
                Some(INVALID_DEPTH_RAW),
            );
            let written = streamed.to_raw_u16(DEPTH_UNITS_PER_METRE);
            assert_eq!(written, vec![raw], "z = {z}");
            let valid = z.is_finite() && (0.0005..65.5345).contains(&z);
            assert_eq!(raw > 0, valid, "z = {z} gave raw {raw}");
        }
    }

    #[test]
    fn frames_have_valid_depth_and_texture() {
        let ds = SyntheticDataset::new(small_spec(3, 0, 300, 0), FrameRange::ALL).unwrap();
        for position in [0, 150, 299] {
            let frame = ds.load(position).unwrap();
            let pixels = frame.depth.data.len();
            assert!(frame.depth.valid_count() as f64 >= 0.95 * pixels as f64);
            let min_depth = frame
                .depth
                .data
                .iter()
                .copied()
                .filter(|&d| d > 0.0)
                .fold(f32::INFINITY, f32::min);
            assert!(
                min_depth > 0.3,
                "frame {position}: something {min_depth} m from the camera"
            );
            // Texture: grey-level gradients are present over most of the image.
            let grey: Vec<f64> = frame
                .rgb
                .pixels()
                .map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0)
                .collect();
            let w = frame.rgb.width() as usize;
            let textured = (0..grey.len() - w - 1)
                .filter(|&i| (grey[i + 1] - grey[i]).abs() + (grey[i + w] - grey[i]).abs() > 2.0)
                .count();
            assert!(
                textured as f64 > 0.3 * pixels as f64,
                "frame {position}: only {textured} textured pixels"
            );
            let mean = grey.iter().sum::<f64>() / grey.len() as f64;
            assert!(
                (50.0..210.0).contains(&mean),
                "frame {position}: mean grey {mean}"
            );
        }
    }

    /// Per-frame translation (m) and rotation (rad) of a trajectory, maxima.
    fn max_steps(poses: &[Isometry3<f64>]) -> (f64, f64) {
        poses.windows(2).fold((0.0, 0.0), |(t, r), w| {
            let delta = w[0].inverse() * w[1];
            (
                t.max(delta.translation.vector.norm()),
                r.max(delta.rotation.angle()),
            )
        })
    }

    #[test]
    fn trajectories_are_smooth_and_stay_clear_of_walls_and_objects() {
        const MAX_STEP_M: f64 = 0.03;
        const MAX_TURN_RAD: f64 = 2.0 * PI / 180.0;
        const CLEARANCE_M: f64 = 0.3;
        for seed in 0..4 {
            let scene = Scene::generate(seed);
            for agents in [1, 3, 5] {
                for agent in 0..agents {
                    let spec = SyntheticSpec {
                        agents,
                        agent,
                        frames: 1200,
                        seed,
                        ..SyntheticSpec::default()
                    };
                    let poses = trajectory(&spec);
                    let (step, turn) = max_steps(&poses);
                    assert!(
                        step <= MAX_STEP_M,
                        "seed {seed} agent {agent}/{agents}: step {step} m"
                    );
                    assert!(
                        turn <= MAX_TURN_RAD,
                        "seed {seed} agent {agent}/{agents}: turn {} deg",
                        turn.to_degrees()
                    );
                    for (frame, pose) in poses.iter().enumerate() {
                        let p = pose.translation.vector;
                        for axis in 0..3 {
                            assert!(
                                p[axis] > ROOM_MIN[axis] + CLEARANCE_M
                                    && p[axis] < ROOM_MAX[axis] - CLEARANCE_M,
                                "seed {seed} agent {agent} frame {frame}: {p:?} too close to the room's walls"
                            );
                        }
                        for primitive in &scene.primitives {
                            let distance = primitive.distance(&p);
                            assert!(
                                distance > CLEARANCE_M,
                                "seed {seed} agent {agent} frame {frame}: {distance} m from {primitive:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn agents_start_apart_and_revisit_each_others_places() {
        const NEAR_M: f64 = 0.5;
        const SIMILAR_VIEW_RAD: f64 = 30.0 * PI / 180.0;
        let agents = 3;
        let trajectories: Vec<Vec<Isometry3<f64>>> = (0..agents)
            .map(|agent| {
                trajectory(&SyntheticSpec {
                    agent,
                    ..SyntheticSpec::default()
                })
            })
            .collect();
        for a in 0..agents {
            for b in a + 1..agents {
                let start_gap = (trajectories[a][0].translation.vector
                    - trajectories[b][0].translation.vector)
                    .norm();
                assert!(
                    start_gap > 1.0,
                    "agents {a} and {b} start only {start_gap} m apart"
                );
            }
        }
        // Every agent shares at least one place (near, looking the same way) with another agent.
        let mut best_pair = None;
        for a in 0..agents {
            let mut overlaps = 0;
            for b in (0..agents).filter(|&b| b != a) {
                for (i, pa) in trajectories[a].iter().enumerate() {
                    for (j, pb) in trajectories[b].iter().enumerate() {
                        let gap = (pa.translation.vector - pb.translation.vector).norm();
                        let view_angle =
                            (pa.rotation * Vector3::z()).angle(&(pb.rotation * Vector3::z()));
                        if gap < NEAR_M && view_angle < SIMILAR_VIEW_RAD {
                            overlaps += 1;
                            if best_pair.is_none() {
                                best_pair = Some((a, i, b, j));
                            }
                        }
                    }
                }
            }
            assert!(overlaps > 0, "agent {a} never sees what another agent sees");
        }

        // Geometric and photometric consistency of one such pair: agent a's depth, moved into
        // agent b's camera with the ground-truth poses, agrees with b's depth, and the colours of
        // corresponding pixels agree (Lambertian shading is view independent).
        let (a, i, b, j) = best_pair.unwrap();
        let frame_a = SyntheticDataset::new(small_spec(agents, a, 300, 0), FrameRange::ALL)
            .unwrap()
            .load(i)
            .unwrap();
        let frame_b = SyntheticDataset::new(small_spec(agents, b, 300, 0), FrameRange::ALL)
            .unwrap()
            .load(j)
            .unwrap();
        let k = frame_a.intrinsics;
        let b_from_a =
            frame_b.world_from_camera_gt.unwrap().inverse() * frame_a.world_from_camera_gt.unwrap();
        let (mut visible, mut consistent, mut colour_error) = (0usize, 0usize, 0.0);
        for v in 0..k.height {
            for u in 0..k.width {
                let z = frame_a.depth.get(u, v) as f64;
                if z <= 0.0 {
                    continue;
                }
                let p_b = b_from_a * Point3::from(k.back_project(u as f64, v as f64, z).coords);
                let Some(pixel) = k.project(&p_b) else {
                    continue;
                };
                if !k.contains(&pixel) {
                    continue;
                }
                visible += 1;
                let (ub, vb) = (pixel.x.round() as u32, pixel.y.round() as u32);
                // One pixel of rounding at a slanted surface moves depth by up to a few cm.
                if (frame_b.depth.get(ub, vb) as f64 - p_b.z).abs() < 0.03 * p_b.z {
                    consistent += 1;
                    let (ca, cb) = (frame_a.rgb.get_pixel(u, v), frame_b.rgb.get_pixel(ub, vb));
                    colour_error += (0..3)
                        .map(|c| (ca[c] as f64 - cb[c] as f64).abs())
                        .sum::<f64>()
                        / 3.0;
                }
            }
        }
        let pixels = (k.width * k.height) as usize;
        assert!(
            visible as f64 > 0.5 * pixels as f64,
            "agents {a}/{b}: only {visible} of {pixels} pixels co-visible"
        );
        assert!(
            consistent as f64 > 0.85 * visible as f64,
            "agents {a}/{b}: {consistent} of {visible} depths agree"
        );
        let mean_colour_error = colour_error / consistent as f64;
        assert!(
            mean_colour_error < 12.0,
            "agents {a}/{b}: mean colour difference {mean_colour_error}"
        );
    }

    #[test]
    fn written_dataset_reads_back_identical() {
        let dir = tempfile::tempdir().unwrap();
        let spec = SyntheticSpec {
            width: 64,
            height: 48,
            ..small_spec(2, 0, 4, 3)
        };
        let mut calls = Vec::new();
        let folders =
            write_seven_scenes(&spec, dir.path(), |done, total| calls.push((done, total))).unwrap();
        assert_eq!(
            folders,
            vec![dir.path().join("agent_0"), dir.path().join("agent_1")]
        );
        assert_eq!(calls.last(), Some(&(8, 8)));
        assert!(dir.path().join(SCENE_FILE).is_file());
        for (agent, folder) in folders.iter().enumerate() {
            let streamed = SyntheticDataset::new(spec.with_agent(agent), FrameRange::ALL).unwrap();
            let read = crate::open(folder.to_str().unwrap(), FrameRange::ALL).unwrap();
            assert_eq!(read.len(), streamed.len());
            let (ki, ks) = (read.intrinsics(), streamed.intrinsics());
            assert_eq!((ki.width, ki.height), (ks.width, ks.height));
            for (x, y) in [
                (ki.fx, ks.fx),
                (ki.fy, ks.fy),
                (ki.cx, ks.cx),
                (ki.cy, ks.cy),
            ] {
                assert!(
                    (x - y).abs() <= 1e-12 * y.abs().max(1.0),
                    "intrinsics {ki:?} vs {ks:?}"
                );
            }
            for position in 0..streamed.len() {
                let (a, b) = (
                    streamed.load(position).unwrap(),
                    read.load(position).unwrap(),
                );
                assert_eq!(a.index, b.index);
                assert_eq!(a.timestamp, b.timestamp);
                assert_eq!(
                    a.rgb, b.rgb,
                    "agent {agent} frame {position}: colour differs"
                );
                assert_eq!(
                    a.depth, b.depth,
                    "agent {agent} frame {position}: depth differs"
                );
                // Translations survive the 17-digit pose file exactly; the reader re-orthonormalises
                // the rotation matrix iteratively (to 1e-12), which moves the last bits.
                let (pa, pb) = (
                    a.world_from_camera_gt.unwrap(),
                    b.world_from_camera_gt.unwrap(),
                );
                assert_eq!(
                    pa.translation, pb.translation,
                    "agent {agent} frame {position}"
                );
                let rotation_error = pa.rotation.angle_to(&pb.rotation);
                assert!(
                    rotation_error < POSE_FILE_ROTATION_TOLERANCE_RAD,
                    "agent {agent} frame {position}: rotation differs by {rotation_error} rad"
                );
            }
        }
        // A second write into the same folder is refused; after remove_written it works again.
        let err = write_seven_scenes(&spec, dir.path(), |_, _| {})
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("agent_0") && err.contains("not empty"),
            "{err}"
        );
        let removed = remove_written(dir.path()).unwrap();
        assert_eq!(removed, 2 * (4 * 3 + 2) + 1);
        assert!(!dir.path().join("agent_0").exists());
        write_seven_scenes(&spec, dir.path(), |_, _| {}).unwrap();
    }

    #[test]
    fn open_streams_the_synthetic_spec() {
        let ds = crate::open(
            "synthetic:agents=2,agent=1,frames=5,width=32,height=24",
            "2..".parse().unwrap(),
        )
        .unwrap();
        assert_eq!(ds.len(), 3);
        assert_eq!(ds.frame_index(0), 2);
        let frame = ds.load(0).unwrap();
        assert_eq!((frame.rgb.width(), frame.depth.height), (32, 24));
        assert!(ds.describe().contains("agent=1"));
    }
}

/// Rendering throughput, for the record: `cargo test --release -p slam-core render_speed --
/// --ignored --nocapture`.
#[cfg(test)]
mod speed {
    use super::*;

    #[test]
    #[ignore = "timing, not a check; run with --release"]
    fn render_speed() {
        let ds = SyntheticDataset::new(SyntheticSpec::default(), FrameRange::ALL).unwrap();
        let frames = 30;
        let started = std::time::Instant::now();
        for position in 0..frames {
            std::hint::black_box(ds.load(position * 10).unwrap());
        }
        let seconds = started.elapsed().as_secs_f64();
        println!(
            "rendered {frames} frames at 640x480 in {seconds:.2} s: {:.1} frames/s on {} threads",
            frames as f64 / seconds,
            rayon::current_num_threads()
        );
    }
}
