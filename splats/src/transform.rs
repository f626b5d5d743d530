//! [`RigidTransform`]: the f32 rigid transform of Gaussians and cameras, its conversions from
//! and to the workspace's nalgebra poses, and the quaternion and SE(3) maths it needs.

use glam::{DMat3, DQuat, DVec3, Mat3, Quat, Vec3};

/// A rigid transform `p_to = rotation * p_from + translation`; `rotation` is row-major.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidTransform {
    /// Rotation matrix, row-major (`rotation[row][column]`), from the `from` frame's axes to
    /// the `to` frame's.
    pub rotation: [[f32; 3]; 3],
    /// Translation, in the `to` frame (where the `from` frame's origin lands), in the
    /// points' units (metres for the workspace's maps and poses).
    pub translation: [f32; 3],
}

impl RigidTransform {
    /// The transform that maps every point to itself.
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
    /// render-core's `PoseGradient`); used by finite-difference tests and by pose optimisers.
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
pub fn rotation_from_quaternion_f64(q: [f64; 4]) -> [[f64; 3]; 3] {
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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Point3, Vector3};

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
