//! SE(3) / Sim(3) helpers on nalgebra types (f64). Poses are `Isometry3<f64>`; names say which
//! frames they map between (`world_from_camera` maps camera-frame points into the world).

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

/// How far a 3x3 matrix may be from orthonormal before it is refused as a rotation.
const ROTATION_TOLERANCE: f64 = 1e-3;

/// Builds a rigid pose from a rotation matrix and a translation. The rotation is re-orthonormalised
/// (files store rounded decimals) but refused when it is clearly not a rotation (scaled, sheared,
/// reflected).
pub fn isometry_from_rt(
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
) -> Result<Isometry3<f64>, String> {
    let should_be_identity = rotation.transpose() * rotation;
    let error = (should_be_identity - Matrix3::identity()).abs().max();
    if !error.is_finite() || error > ROTATION_TOLERANCE || rotation.determinant() <= 0.0 {
        return Err(format!(
            "rotation part is not orthonormal (|R^T R - I| = {error:.2e}, det = {:.4})",
            rotation.determinant()
        ));
    }
    let rot = nearest_rotation(rotation)
        .ok_or_else(|| "rotation part has no singular value decomposition".to_string())?;
    Ok(Isometry3::from_parts(
        Translation3::from(*translation),
        UnitQuaternion::from_rotation_matrix(&rot),
    ))
}

/// Iterations the singular value decomposition of [`nearest_rotation`] may take (3x3 matrices
/// converge in a handful).
const NEAREST_ROTATION_MAX_ITERATIONS: usize = 100;

/// The rotation nearest to `m` in the Frobenius norm: `U diag(1, 1, det(U V^T)) V^T` from the
/// singular value decomposition `m = U S V^T` (the orthogonal Procrustes solution; for a sum of
/// rotation matrices, their chordal L2 mean). `None` when `m` is not finite or the
/// decomposition does not converge.
///
/// Why not nalgebra's `Rotation3::from_matrix`: it iterates from the identity until a step
/// falls below machine epsilon, with no iteration limit, and some perfectly ordinary inputs
/// never get there (a uniform multiple of a rotation, which a sum of nearly equal rotations
/// is; nalgebra issues 1177, 1529 and 1583): a consensus hung in it. From the identity it can
/// also stop at the identity for a rotation by 180 degrees (issue 1078).
pub fn nearest_rotation(m: &Matrix3<f64>) -> Option<Rotation3<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = m.try_svd(true, true, f64::EPSILON, NEAREST_ROTATION_MAX_ITERATIONS)?;
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut flip = Matrix3::identity();
    flip[(2, 2)] = (u * v_t).determinant().signum();
    Some(Rotation3::from_matrix_unchecked(u * flip * v_t))
}

/// Pose from TUM's `tx ty tz qx qy qz qw` (Hamilton quaternion, normalised here).
pub fn isometry_from_tum(values: &[f64; 7]) -> Result<Isometry3<f64>, String> {
    let [tx, ty, tz, qx, qy, qz, qw] = *values;
    let q = nalgebra::Quaternion::new(qw, qx, qy, qz);
    let norm = q.norm();
    if !norm.is_finite() || norm < 1e-6 {
        return Err(format!(
            "quaternion ({qx} {qy} {qz} {qw}) has zero or non-finite norm"
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// Pose -> TUM's `tx ty tz qx qy qz qw`, with qw >= 0 for a canonical sign.
pub fn isometry_to_tum(pose: &Isometry3<f64>) -> [f64; 7] {
    let t = pose.translation.vector;
    let mut q = *pose.rotation.quaternion();
    if q.w < 0.0 {
        q = -q;
    }
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// Row-major 4x4 homogeneous matrix of a pose.
pub fn to_matrix(pose: &Isometry3<f64>) -> Matrix4<f64> {
    pose.to_homogeneous()
}

/// How far the camera of `world_from_camera` is from that of `reference` (both camera-to-world):
/// the distance between the camera centres (metres) and the angle between the orientations
/// (radians).
pub fn pose_change(reference: &Isometry3<f64>, world_from_camera: &Isometry3<f64>) -> (f64, f64) {
    let change = reference.inverse() * world_from_camera;
    (change.translation.vector.norm(), change.rotation.angle())
}

/// Rotation angle of a pose in radians.
pub fn rotation_angle(pose: &Isometry3<f64>) -> f64 {
    pose.rotation.angle()
}

/// Similarity transform `x -> scale * R x + t` (used by Sim(3) trajectory alignment).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// The rotation R.
    pub rotation: UnitQuaternion<f64>,
    /// The translation t, added after scaling and rotating.
    pub translation: Vector3<f64>,
    /// The scale factor s (1 for a rigid transform).
    pub scale: f64,
}

impl Similarity {
    /// The identity: no rotation, no translation, scale 1.
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// Maps a point: `scale * R p + t`.
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.scale * (self.rotation * p.coords) + self.translation)
    }

    /// Applies the similarity to a pose: rotation composed, position transformed.
    pub fn transform_pose(&self, pose: &Isometry3<f64>) -> Isometry3<f64> {
        let position = self.transform_point(&Point3::from(pose.translation.vector));
        Isometry3::from_parts(
            Translation3::from(position.coords),
            self.rotation * pose.rotation,
        )
    }

    /// The rigid part (scale dropped), as an isometry.
    pub fn rigid(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(self.translation), self.rotation)
    }
}

/// Least-squares similarity (Umeyama 1991) mapping `source` points onto `target` points:
/// minimises sum |target_i - (s R source_i + t)|^2. With `with_scale = false` s is fixed to 1
/// (SE(3) alignment, right for metric RGB-D trajectories). Needs at least 3 non-collinear pairs
/// for a unique rotation; returns `None` with fewer than 2 pairs or degenerate input.
pub fn umeyama(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    with_scale: bool,
) -> Option<Similarity> {
    let n = source.len();
    if n < 2 || n != target.len() {
        return None;
    }
    let inv_n = 1.0 / n as f64;
    let mean_s = source
        .iter()
        .fold(Vector3::zeros(), |acc, p| acc + p.coords)
        * inv_n;
    let mean_t = target
        .iter()
        .fold(Vector3::zeros(), |acc, p| acc + p.coords)
        * inv_n;
    let mut cov = Matrix3::zeros();
    let mut var_s = 0.0;
    for (s, t) in source.iter().zip(target) {
        let ds = s.coords - mean_s;
        let dt = t.coords - mean_t;
        cov += dt * ds.transpose();
        var_s += ds.norm_squared();
    }
    cov *= inv_n;
    var_s *= inv_n;
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    let scale = if with_scale {
        if var_s <= 0.0 {
            return None;
        }
        (svd.singular_values.component_mul(&d.diagonal())).sum() / var_s
    } else {
        1.0
    };
    let t = mean_t - scale * r * mean_s;
    if !r.iter().chain(t.iter()).all(|v| v.is_finite()) || !scale.is_finite() {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Some(Similarity {
        rotation,
        translation: t,
        scale,
    })
}

/// Row-major 4x4 matrix (16 numbers) -> rigid pose, refusing matrices that are not rigid.
pub fn pose_from_row_major(values: &[f64]) -> Result<Isometry3<f64>, String> {
    if values.len() != 16 && values.len() != 12 {
        return Err(format!(
            "expected 12 or 16 numbers for a pose matrix, found {}",
            values.len()
        ));
    }
    let m = nalgebra::Matrix3x4::from_row_slice(&values[..12]);
    if values.len() == 16 {
        let last = &values[12..16];
        if (last[0].abs() + last[1].abs() + last[2].abs()) > 1e-6 || (last[3] - 1.0).abs() > 1e-6 {
            return Err(format!(
                "last row of the pose matrix must be 0 0 0 1, found {last:?}"
            ));
        }
    }
    isometry_from_rt(
        &m.fixed_view::<3, 3>(0, 0).into_owned(),
        &m.column(3).into_owned(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_change_is_the_distance_between_cameras_and_their_turn() {
        let reference = Isometry3::new(Vector3::new(1.0, 2.0, 0.5), Vector3::new(0.0, 0.3, 0.0));
        let moved = Isometry3::new(Vector3::new(1.03, 2.04, 0.5), Vector3::new(0.0, 0.32, 0.0));
        let (metres, radians) = pose_change(&reference, &moved);
        assert!((metres - 0.05).abs() < 1e-12, "{metres}");
        assert!((radians - 0.02).abs() < 1e-12, "{radians}");
        assert_eq!(pose_change(&moved, &moved), (0.0, 0.0));
    }

    #[test]
    fn nearest_rotation_recovers_scaled_and_half_turn_rotations() {
        let rotations = [
            UnitQuaternion::identity(),
            UnitQuaternion::from_euler_angles(0.3, -0.7, 1.9),
            // Half turns, where an iteration from the identity can stop at the identity.
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
            UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(1.0, 2.0, -0.5)),
                std::f64::consts::PI,
            ),
        ];
        for rotation in rotations {
            let r = rotation.to_rotation_matrix().into_inner();
            // Uniform multiples, as a sum of equal rotations is; nalgebra's from_matrix never
            // returns for some (e.g. 0.11823407 I in f32).
            for scale in [1.0, 0.118_234_07, 0.077_000_05, 0.125, 2.0, 7.0, 64.0, 1e-6] {
                let nearest = nearest_rotation(&(r * scale)).expect("finite input");
                assert!(
                    (nearest.into_inner() - r).abs().max() < 1e-12,
                    "{rotation:?} x {scale}"
                );
            }
        }
        // A noisy sum: still a proper rotation, close to the mean.
        let noisy = rotations[1].to_rotation_matrix().into_inner() * 3.0
            + Matrix3::new(0.01, -0.02, 0.0, 0.0, 0.015, 0.01, -0.01, 0.0, 0.02);
        let nearest = nearest_rotation(&noisy).unwrap().into_inner();
        assert!(
            (nearest.transpose() * nearest - Matrix3::identity())
                .abs()
                .max()
                < 1e-12
        );
        assert!((nearest.determinant() - 1.0).abs() < 1e-12);
        let nearest_quaternion =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(nearest));
        assert!(nearest_quaternion.angle_to(&rotations[1]) < 0.02);
        // A reflection gets the nearest proper rotation, not a reflection.
        let reflected = nearest_rotation(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0)))
            .unwrap()
            .into_inner();
        assert!((reflected.determinant() - 1.0).abs() < 1e-12);
        assert_eq!(nearest_rotation(&Matrix3::from_element(f64::NAN)), None);
    }

    #[test]
    fn umeyama_recovers_known_similarity() {
        let truth = Similarity {
            rotation: UnitQuaternion::from_euler_angles(0.3, -0.7, 1.9),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 1.7,
        };
        let source: Vec<_> = (0..20)
            .map(|i| {
                let f = i as f64;
                Point3::new(f.sin() * 3.0, (f * 0.7).cos(), f * 0.1)
            })
            .collect();
        let target: Vec<_> = source.iter().map(|p| truth.transform_point(p)).collect();
        let est = umeyama(&source, &target, true).unwrap();
        assert!((est.scale - 1.7).abs() < 1e-9);
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-9);
        assert!((est.translation - truth.translation).norm() < 1e-9);
        let rigid = umeyama(
            &source,
            &source.iter().map(|p| truth.rigid() * p).collect::<Vec<_>>(),
            false,
        )
        .unwrap();
        assert_eq!(rigid.scale, 1.0);
        assert!(rigid.rotation.angle_to(&truth.rotation) < 1e-9);
        assert!(umeyama(&source[..1], &target[..1], false).is_none());
    }

    #[test]
    fn refuses_non_rotations() {
        let t = Vector3::zeros();
        assert!(isometry_from_rt(&(Matrix3::identity() * 2.0), &t).is_err());
        assert!(
            isometry_from_rt(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0)), &t).is_err()
        );
        assert!(isometry_from_rt(&Matrix3::identity(), &t).is_ok());
        assert!(isometry_from_tum(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).is_err());
    }

    #[test]
    fn tum_round_trip() {
        let pose = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 2.9),
        );
        let back = isometry_from_tum(&isometry_to_tum(&pose)).unwrap();
        assert!((back.to_homogeneous() - pose.to_homogeneous()).abs().max() < 1e-12);
    }

    #[test]
    fn pose_matrix_must_be_rigid() {
        let id = [
            1., 0., 0., 1., 0., 1., 0., 2., 0., 0., 1., 3., 0., 0., 0., 1.,
        ];
        let p = pose_from_row_major(&id).unwrap();
        assert_eq!(p.translation.vector, nalgebra::Vector3::new(1.0, 2.0, 3.0));
        let mut scaled = id;
        scaled[0] = 2.0;
        assert!(pose_from_row_major(&scaled).is_err());
        assert!(pose_from_row_major(&id[..15]).is_err());
    }
}
