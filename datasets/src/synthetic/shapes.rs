//! Scene geometry: rays, hits, and the analytic primitives (planes of the room shell, yawed boxes,
//! spheres, upright cylinders) they are intersected with.

use nalgebra::Vector3;

/// Room corners in the world (room) frame, metres: 6 x 5 x 3 m, floor at z = 0.
pub const ROOM_MIN: [f64; 3] = [-3.0, -2.5, 0.0];
/// The room's corner opposite [`ROOM_MIN`], metres: walls at x = 3 and y = 2.5, ceiling at z = 3.
pub const ROOM_MAX: [f64; 3] = [3.0, 2.5, 3.0];

/// Intersections closer than this along the ray (in camera-z metres) are ignored, so a ray never
/// re-hits the surface it starts on.
pub(super) const MIN_HIT_DISTANCE: f64 = 1e-6;
/// Ray direction components below this are treated as parallel to a slab.
const PARALLEL_EPSILON: f64 = 1e-12;
/// Texture coordinates of the six faces of a box are shifted apart by this much (metres) so that
/// faces do not repeat each other's pattern, which would confuse keypoint matching.
const FACE_UV_OFFSET: f64 = 17.3;

#[derive(Debug, Clone, Copy)]
pub(super) struct Ray {
    pub(super) origin: Vector3<f64>,
    /// Not normalised: its camera-frame z component is 1, so the hit parameter t is the
    /// camera-frame depth directly.
    pub(super) direction: Vector3<f64>,
}

impl Ray {
    pub(super) fn at(&self, t: f64) -> Vector3<f64> {
        self.origin + self.direction * t
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Hit {
    /// Ray parameter = camera-frame z of the hit point.
    pub(super) t: f64,
    /// Unit surface normal in the world frame (not yet oriented towards the viewer).
    pub(super) normal: Vector3<f64>,
    /// Surface texture coordinates in metres.
    pub(super) uv: [f64; 2],
    pub(super) material: usize,
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Shape {
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
pub(super) struct Primitive {
    pub(super) shape: Shape,
    pub(super) material: usize,
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
pub(super) fn from_yawed(v: &Vector3<f64>, cos_yaw: f64, sin_yaw: f64) -> Vector3<f64> {
    Vector3::new(
        cos_yaw * v.x - sin_yaw * v.y,
        sin_yaw * v.x + cos_yaw * v.y,
        v.z,
    )
}

/// Slab test of a ray against an axis-aligned box centred at the origin. Returns
/// (t_enter, t_exit, axis of the entry face, axis of the exit face), or None when the ray misses.
pub(super) fn slabs(
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
pub(super) fn face_uv(point: &Vector3<f64>, axis: usize, positive_side: bool) -> [f64; 2] {
    let face = (2 * axis + usize::from(positive_side)) as f64 * FACE_UV_OFFSET;
    match axis {
        0 => [point.y + face, point.z],
        1 => [point.x + face, point.z],
        _ => [point.x + face, point.y],
    }
}

impl Primitive {
    pub(super) fn new(shape: Shape, material: usize) -> Self {
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
    pub(super) fn may_hit(&self, ray: &Ray, t_limit: f64) -> bool {
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

    pub(super) fn intersect(&self, ray: &Ray) -> Option<Hit> {
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
    pub(super) fn distance(&self, p: &Vector3<f64>) -> f64 {
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
