//! The reference's textured points and the photometric term (see the module documentation of
//! [`super`]).

use geometry::depth::DepthImage;
use nalgebra::{Isometry3, Matrix3, Matrix6, RowVector6, Vector3, Vector6};

use super::PhotometricFrame;
use crate::config::PhotometricConfig;
use crate::gicp::{JointSystem, JointTerm};

/// Points visible in the current image that a linearisation needs before the term counts: with
/// fewer, the brightness fit and the six pose directions are not determined by the images.
const MIN_POINTS_USED: usize = 50;
/// Brightness gains outside this range are not exposure changes but a wrong fit (too few
/// points, or points that do not correspond): the fit falls back to an offset alone.
const GAIN_RANGE: (f64, f64) = (0.5, 2.0);
/// Residuals the brightness fit's second pass keeps, in Huber thresholds from its first pass.
const BRIGHTNESS_INLIER_THRESHOLDS: f64 = 2.0;

/// A textured pixel of the reference frame lifted to the world.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ReferencePoint {
    world: Vector3<f64>,
    intensity: f32,
}

/// The previous placed frame's textured points with valid depth, in world coordinates.
#[derive(Debug, Clone, Default)]
pub struct PhotometricReference {
    points: Vec<ReferencePoint>,
}

impl PhotometricReference {
    /// Selects `frame`'s pixels with an intensity gradient of at least `config.min_gradient`
    /// whose depth block (the full-resolution pixels the level pixel bins) is valid, nearer than
    /// `truncation_m` and spreads by at most `config.max_depth_spread_fraction` of its mean;
    /// lifts them with that mean to the world at `world_from_camera` (the depth image's pose),
    /// evenly thinned to `config.max_points`. Each point's intensity is the colour image's where
    /// the colour camera saw it ([`PhotometricFrame::colour_from_depth`]); points it saw outside
    /// its image are left out.
    pub fn select(
        frame: &PhotometricFrame,
        depth: &DepthImage,
        world_from_camera: &Isometry3<f64>,
        config: &PhotometricConfig,
        truncation_m: f64,
    ) -> Self {
        let f = frame.factor;
        let (w, h) = (frame.intensity.width, frame.intensity.height);
        let min_gradient_sq = (config.min_gradient * config.min_gradient) as f32;
        let mut candidates = Vec::new();
        if depth.width < w * f || depth.height < h * f {
            return Self::default();
        }
        let colour_from_depth =
            (frame.colour_from_depth != Isometry3::identity()).then_some(frame.colour_from_depth);
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                let (gx, gy) = (frame.gradient_x.at(x, y), frame.gradient_y.at(x, y));
                if gx * gx + gy * gy < min_gradient_sq {
                    continue;
                }
                let Some(z) = block_depth(depth, x, y, f, truncation_m, config) else {
                    continue;
                };
                let camera = frame.intrinsics.back_project(f64::from(x), f64::from(y), z);
                let intensity = match &colour_from_depth {
                    None => frame.intensity.at(x, y),
                    Some(colour_from_depth) => {
                        let Some(pixel) = frame.intrinsics.project(&(colour_from_depth * camera))
                        else {
                            continue;
                        };
                        let Some(intensity) = frame.intensity.bilinear(pixel.x, pixel.y) else {
                            continue;
                        };
                        intensity
                    }
                };
                candidates.push(ReferencePoint {
                    world: (world_from_camera * camera).coords,
                    intensity,
                });
            }
        }
        let points = if candidates.len() <= config.max_points {
            candidates
        } else {
            let step = candidates.len() as f64 / config.max_points as f64;
            (0..config.max_points)
                .map(|i| candidates[(i as f64 * step) as usize])
                .collect()
        };
        Self { points }
    }

    /// Number of selected reference points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when no pixel was selected (the term then has nothing to compare).
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Moves the points with the map (a consensus correction at the reference's pose).
    pub fn transform(&mut self, correction: &Isometry3<f64>) {
        for point in &mut self.points {
            point.world = (correction * nalgebra::Point3::from(point.world)).coords;
        }
    }
}

/// Mean depth of the `f` x `f` full-resolution block of level pixel (x, y), when every depth in
/// it is valid and they spread by at most `max_depth_spread_fraction` of the mean.
fn block_depth(
    depth: &DepthImage,
    x: u32,
    y: u32,
    f: u32,
    truncation_m: f64,
    config: &PhotometricConfig,
) -> Option<f64> {
    let (mut low, mut high, mut sum) = (f32::INFINITY, 0.0f32, 0.0f32);
    for dy in 0..f {
        for dx in 0..f {
            let d = depth.get(x * f + dx, y * f + dy);
            if !(d.is_finite() && d > 0.0 && f64::from(d) < truncation_m) {
                return None;
            }
            low = low.min(d);
            high = high.max(d);
            sum += d;
        }
    }
    let mean = f64::from(sum) / f64::from(f * f);
    (f64::from(high - low) <= config.max_depth_spread_fraction * mean).then_some(mean)
}

/// One reference point seen from the current pose.
struct Projection {
    /// The point in the current depth camera (the pose being estimated).
    camera: Vector3<f64>,
    /// The point in the current colour camera (`camera` where colour and depth were taken
    /// together).
    colour_camera: Vector3<f64>,
    /// Current intensity and gradient (level pixels) at its projection.
    intensity: f64,
    gradient: (f64, f64),
}

/// The photometric cost of the current frame against a reference, for
/// [`crate::gicp::register_joint_unless_outscored`].
pub struct PhotometricTerm<'a> {
    reference: &'a PhotometricReference,
    current: &'a PhotometricFrame,
    /// The current frame's depth, for the occlusion test.
    depth: &'a DepthImage,
    config: &'a PhotometricConfig,
    /// Per reference point, `weight x Huber weight` of the last linearisation (0: not used).
    weights: Vec<f64>,
    /// Per reference point, its weighted squared residual at the last linearisation: what it
    /// costs in [`JointTerm::evaluate`] at a pose that projects it out of the image.
    costs: Vec<f64>,
    /// Brightness `(a, b)`: the reference's intensities as the current image sees them.
    brightness: (f64, f64),
    used: usize,
    /// The current frame's `colour_from_depth` as (rotation, translation), `None` for the
    /// identity (colour and depth taken together), unless `colour_motion` moves it with the pose.
    colour_from_depth: Option<(Matrix3<f64>, Vector3<f64>)>,
    colour_motion: Option<ColourMotion>,
}

/// Where the current frame's colour camera is while its depth camera's pose is estimated: its
/// colour image was taken `steps` frame intervals after its depth image (negative: before), and
/// the camera moves at the velocity the pose tried implies, from the previous frame's pose.
/// Better than the previous step's velocity where the motion turns (a camera rolled back and
/// forth), at no cost: the term is relinearised at every pose anyway.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourMotion {
    /// The previous frame's pose.
    pub world_from_previous: Isometry3<f64>,
    /// The colour-to-depth offset over the time since the previous frame.
    pub steps: f64,
}

impl ColourMotion {
    /// `colour_from_depth` for the depth camera at `world_from_camera`.
    pub fn colour_from_depth(&self, world_from_camera: &Isometry3<f64>) -> Isometry3<f64> {
        // `previous_from_current` over one interval; at a constant velocity also `now_from_later`.
        let motion = self.world_from_previous.inverse() * world_from_camera;
        let now_from_later = Isometry3::from_parts(
            (motion.translation.vector * self.steps).into(),
            motion.rotation.powf(self.steps),
        );
        now_from_later.inverse()
    }
}

/// An isometry as (rotation matrix, translation), `None` for the identity.
fn matrix_parts(transform: &Isometry3<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    (*transform != Isometry3::identity()).then(|| {
        (
            transform.rotation.to_rotation_matrix().into_inner(),
            transform.translation.vector,
        )
    })
}

impl<'a> PhotometricTerm<'a> {
    /// The term of `current` (the frame being tracked, at the term's level) against
    /// `reference`; `depth` is the current frame's full-resolution depth image, used to skip
    /// reference points occluded in it. Nothing is computed until the first linearisation.
    pub fn new(
        reference: &'a PhotometricReference,
        current: &'a PhotometricFrame,
        depth: &'a DepthImage,
        config: &'a PhotometricConfig,
    ) -> Self {
        Self {
            reference,
            current,
            depth,
            config,
            weights: vec![0.0; reference.len()],
            costs: vec![0.0; reference.len()],
            brightness: (1.0, 0.0),
            used: 0,
            colour_from_depth: matrix_parts(&current.colour_from_depth),
            colour_motion: None,
        }
    }

    /// The term with the current colour camera moving with the pose tried (see
    /// [`ColourMotion`]) instead of the frame's fixed `colour_from_depth`.
    pub fn with_colour_motion(mut self, motion: ColourMotion) -> Self {
        self.colour_motion = Some(motion);
        self
    }

    /// The current frame's `colour_from_depth` at `pose` (see [`Self::colour_from_depth`]).
    fn colour_parts(&self, pose: &Isometry3<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)> {
        match &self.colour_motion {
            Some(motion) => matrix_parts(&motion.colour_from_depth(pose)),
            None => self.colour_from_depth,
        }
    }

    /// Reference points visible and unoccluded at the last linearisation (0 when too few for
    /// the term to count).
    pub fn points_used(&self) -> usize {
        self.used
    }

    /// The brightness change `(a, b)` of the last linearisation.
    pub fn brightness(&self) -> (f64, f64) {
        self.brightness
    }

    fn project(
        &self,
        camera_from_world: &(Matrix3<f64>, Vector3<f64>),
        colour_from_depth: Option<&(Matrix3<f64>, Vector3<f64>)>,
        point: &ReferencePoint,
    ) -> Option<Projection> {
        let camera = camera_from_world.0 * point.world + camera_from_world.1;
        let colour_camera = match colour_from_depth {
            Some(colour_from_depth) => colour_from_depth.0 * camera + colour_from_depth.1,
            None => camera,
        };
        let k = &self.current.intrinsics;
        let pixel = k.project(&colour_camera.into())?;
        let (intensity, gx, gy) = self.current.sample(pixel.x, pixel.y)?;
        // The full-resolution depth pixel nearest the level pixel's projection, in the depth
        // image's camera.
        let (u, v) = match colour_from_depth {
            Some(_) => k.project(&camera.into()).map(|p| (p.x, p.y))?,
            None => (pixel.x, pixel.y),
        };
        let f = f64::from(self.current.factor);
        let (du, dv) = (((u + 0.5) * f - 0.5).round(), ((v + 0.5) * f - 0.5).round());
        if du >= 0.0
            && dv >= 0.0
            && du < f64::from(self.depth.width)
            && dv < f64::from(self.depth.height)
        {
            let measured = f64::from(self.depth.get(du as u32, dv as u32));
            if measured.is_finite()
                && measured > 0.0
                && measured < camera.z - self.config.occlusion_m
            {
                return None;
            }
        }
        Some(Projection {
            camera,
            colour_camera,
            intensity: f64::from(intensity),
            gradient: (f64::from(gx), f64::from(gy)),
        })
    }

    fn residual(&self, projection: &Projection, point: &ReferencePoint) -> f64 {
        let (a, b) = self.brightness;
        projection.intensity - (a * f64::from(point.intensity) + b)
    }

    /// Least-squares `(a, b)` with `I_cur = a I_ref + b` over `pairs`, twice: the second pass
    /// keeps the pairs the first explains within [`BRIGHTNESS_INLIER_THRESHOLDS`] Huber
    /// thresholds. An offset alone when the gain is out of [`GAIN_RANGE`].
    fn fit_brightness(&self, pairs: &[(f64, f64)]) -> (f64, f64) {
        let fit = |keep: &dyn Fn(&(f64, f64)) -> bool| -> Option<(f64, f64)> {
            let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for &(x, y) in pairs.iter().filter(|p| keep(p)) {
                n += 1.0;
                sx += x;
                sy += y;
                sxx += x * x;
                sxy += x * y;
            }
            if n < MIN_POINTS_USED as f64 {
                return None;
            }
            let variance = sxx - sx * sx / n;
            let gain = if variance > 1e-9 {
                (sxy - sx * sy / n) / variance
            } else {
                1.0
            };
            if (GAIN_RANGE.0..=GAIN_RANGE.1).contains(&gain) {
                Some((gain, (sy - gain * sx) / n))
            } else {
                Some((1.0, (sy - sx) / n))
            }
        };
        let Some(first) = fit(&|_| true) else {
            return (1.0, 0.0);
        };
        let bound = BRIGHTNESS_INLIER_THRESHOLDS * self.config.huber_threshold;
        fit(&|&(x, y)| (y - (first.0 * x + first.1)).abs() <= bound).unwrap_or(first)
    }
}

fn camera_from_world(pose: &Isometry3<f64>) -> (Matrix3<f64>, Vector3<f64>) {
    let inverse = pose.inverse();
    (
        inverse.rotation.to_rotation_matrix().into_inner(),
        inverse.translation.vector,
    )
}

impl JointTerm for PhotometricTerm<'_> {
    fn linearize(&mut self, pose: &Isometry3<f64>) -> JointSystem {
        let parts = camera_from_world(pose);
        // Held fixed in the Jacobian: it moves with the pose a fraction `steps` as much.
        let colour = self.colour_parts(pose);
        let projections: Vec<Option<Projection>> = self
            .reference
            .points
            .iter()
            .map(|point| self.project(&parts, colour.as_ref(), point))
            .collect();
        let pairs: Vec<(f64, f64)> = projections
            .iter()
            .zip(&self.reference.points)
            .filter_map(|(p, point)| {
                p.as_ref()
                    .map(|p| (f64::from(point.intensity), p.intensity))
            })
            .collect();
        let mut system = JointSystem {
            hessian: Matrix6::zeros(),
            gradient: Vector6::zeros(),
            error: 0.0,
        };
        self.weights.fill(0.0);
        self.costs.fill(0.0);
        self.used = 0;
        if pairs.len() < MIN_POINTS_USED {
            return system;
        }
        self.brightness = self.fit_brightness(&pairs);
        let k = self.current.intrinsics;
        let huber = self.config.huber_threshold;
        for (i, (projection, point)) in projections.iter().zip(&self.reference.points).enumerate() {
            let Some(p) = projection else {
                continue;
            };
            let r = self.residual(p, point);
            let weight = self.config.weight
                * if r.abs() <= huber {
                    1.0
                } else {
                    huber / r.abs()
                };
            let colour_rotation = colour.as_ref().map(|(rotation, _)| rotation);
            let jacobian = residual_jacobian(
                &p.camera,
                &p.colour_camera,
                colour_rotation,
                p.gradient,
                (k.fx, k.fy),
            );
            system.hessian += jacobian.transpose() * jacobian * weight;
            system.gradient += jacobian.transpose() * (weight * r);
            self.weights[i] = weight;
            self.costs[i] = weight * r * r;
            system.error += self.costs[i];
            self.used += 1;
        }
        system
    }

    fn evaluate(&self, pose: &Isometry3<f64>) -> f64 {
        let parts = camera_from_world(pose);
        let colour = self.colour_parts(pose);
        let mut error = 0.0;
        for (i, point) in self.reference.points.iter().enumerate() {
            let weight = self.weights[i];
            if weight == 0.0 {
                continue;
            }
            error += match self.project(&parts, colour.as_ref(), point) {
                Some(p) => {
                    let r = self.residual(&p, point);
                    weight * r * r
                }
                None => self.costs[i],
            };
        }
        error
    }
}

/// `dr/d(omega, v)` of a residual `I(pi(A c)) - const` for `c = T^-1 q` (`camera`) and the
/// colour camera's point `A c` (`colour_camera`; `A` = colour_from_depth, whose rotation is
/// `colour_rotation`, `None` for the identity) under the right perturbation `T <- T (Exp(omega),
/// v)`: then `c <- c - omega x c - v`, so `d(A c)/d(omega, v) = R_A [[c]x, -I]`, chained with
/// the pinhole's `dpi/dc` at `A c` and the image gradient.
pub(super) fn residual_jacobian(
    camera: &Vector3<f64>,
    colour_camera: &Vector3<f64>,
    colour_rotation: Option<&Matrix3<f64>>,
    gradient: (f64, f64),
    (fx, fy): (f64, f64),
) -> RowVector6<f64> {
    let inverse_z = 1.0 / colour_camera.z;
    // grad I^T dpi/dc at the colour camera's point, a row of three.
    let gu = gradient.0 * fx * inverse_z;
    let gv = gradient.1 * fy * inverse_z;
    let d_colour = Vector3::new(
        gu,
        gv,
        -(gu * colour_camera.x + gv * colour_camera.y) * inverse_z,
    );
    // Back in the depth camera: a^T R_A = (R_A^T a)^T.
    let d_camera = match colour_rotation {
        Some(rotation) => rotation.transpose() * d_colour,
        None => d_colour,
    };
    // a^T [c]x = (a x c)^T (the scalar triple product).
    let rotation = d_camera.cross(camera);
    RowVector6::new(
        rotation.x,
        rotation.y,
        rotation.z,
        -d_camera.x,
        -d_camera.y,
        -d_camera.z,
    )
}
