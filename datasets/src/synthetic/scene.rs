//! The procedural room as the renderer sees it: materials and primitives, intersection of a ray
//! with the whole scene, and Lambertian shading with fixed lamps (so a surface point has the same
//! colour from every viewpoint). [`super::layout`] builds it.

use nalgebra::Vector3;

use super::shapes::{Hit, MIN_HIT_DISTANCE, Primitive, ROOM_MAX, ROOM_MIN, Ray, face_uv, slabs};
use super::texture::{MIN_FOOTPRINT_COSINE, Material, Rgb};

/// Diffuse light that reaches every surface (fraction of albedo).
const AMBIENT_LIGHT: f64 = 0.32;
/// Ceiling lamps: position (m) and diffuse strength.
const LAMPS: [([f64; 3], f64); 2] = [([1.1, -0.7, 2.8], 0.55), ([-1.3, 0.9, 2.8], 0.5)];
/// Distance (m) at which a lamp's light has fallen to half.
const LAMP_FALLOFF_DISTANCE: f64 = 3.2;
/// Display gamma applied when converting linear radiance to 8-bit values.
pub(super) const DISPLAY_GAMMA: f64 = 2.2;

/// Surfaces of the room shell, in the order of [`Scene::room_materials`].
pub(super) const ROOM_SURFACES: usize = 6;

/// The procedural room: a shell (6 faces) and a list of objects.
#[derive(Debug, Clone)]
pub(super) struct Scene {
    /// Materials of the faces -x, +x, -y, +y (walls), -z (floor), +z (ceiling).
    pub(super) room_materials: [usize; ROOM_SURFACES],
    pub(super) primitives: Vec<Primitive>,
    pub(super) materials: Vec<Material>,
}

impl Scene {
    /// Nearest surface along the ray: the closest object, else the room shell.
    pub(super) fn intersect(&self, ray: &Ray) -> Option<Hit> {
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
    pub(super) fn shade(&self, ray: &Ray, hit: &Hit, pixel_angle: f64) -> Rgb {
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
