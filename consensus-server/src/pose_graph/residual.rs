//! The residual of one relative-pose edge and its Jacobians.
//!
//! Node poses are `world_from_camera = (R, t)`. An edge from node i to node j measures
//! `Z = camera_i_from_camera_j`; the error transform is `E = Z^-1 x_i^-1 x_j` (identity when the
//! poses agree with the measurement) and the residual is
//!
//! ```text
//!     r = [ Log(R_z^T R_i^T R_j) ;  R_z^T (R_i^T (t_j - t_i) - t_z) ]      (rotation first)
//! ```
//!
//! that is, E's rotation vector and translation. Updates perturb a node as
//! `R <- R Exp(phi)`, `t <- t + dt` (rotation in the body frame, translation in the world frame),
//! which keeps every Jacobian block a closed form:
//!
//! ```text
//!     d r_rot   / d phi_i = -Jr^-1(r_rot) R_j^T R_i      d r_rot   / d phi_j = Jr^-1(r_rot)
//!     d r_trans / d phi_i = R_z^T [R_i^T (t_j - t_i)]x    d r_trans / d dt_i  = -R_z^T R_i^T
//!     d r_trans / d dt_j  =  R_z^T R_i^T                  (the other blocks are zero)
//! ```
//!
//! with `Jr^-1` the inverse right Jacobian of SO(3). The unit test checks them against finite
//! differences.

use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

/// Rotation residuals beyond this angle (radians) use the inverse right Jacobian of this angle:
/// the exact one diverges at pi, and only gross outliers (down-weighted by GNC) get there.
const MAX_JACOBIAN_ANGLE: f64 = 3.0;
/// Below this angle (radians) the inverse right Jacobian's series coefficient is used: the
/// closed form divides by sin(theta).
const SMALL_ANGLE: f64 = 1e-5;
/// The closed form's coefficient of [theta]x^2 as theta -> 0.
const SMALL_ANGLE_COEFFICIENT: f64 = 1.0 / 12.0;

/// Applies an update `(phi, dt)` to a pose (see the module documentation).
pub fn retract(pose: &Isometry3<f64>, delta: &Vector6<f64>) -> Isometry3<f64> {
    let phi: Vector3<f64> = delta.fixed_rows::<3>(0).into_owned();
    let dt: Vector3<f64> = delta.fixed_rows::<3>(3).into_owned();
    Isometry3::from_parts(
        Translation3::from(pose.translation.vector + dt),
        pose.rotation * UnitQuaternion::from_scaled_axis(phi),
    )
}

/// Residual of edge `Z = camera_i_from_camera_j` at poses `x_i`, `x_j`.
pub fn residual(
    x_i: &Isometry3<f64>,
    x_j: &Isometry3<f64>,
    measured: &Isometry3<f64>,
) -> Vector6<f64> {
    let error = measured.inverse() * x_i.inverse() * x_j;
    let mut r = Vector6::zeros();
    r.fixed_rows_mut::<3>(0)
        .copy_from(&error.rotation.scaled_axis());
    r.fixed_rows_mut::<3>(3)
        .copy_from(&error.translation.vector);
    r
}

/// Residual and its Jacobians with respect to the updates of node i and node j.
pub struct Linearised {
    /// The residual `r` (rotation first, then translation).
    pub residual: Vector6<f64>,
    /// `d r / d (phi_i, dt_i)`: rows as `r`, columns rotation update first.
    pub jacobian_i: Matrix6<f64>,
    /// `d r / d (phi_j, dt_j)`: rows as `r`, columns rotation update first.
    pub jacobian_j: Matrix6<f64>,
}

/// The residual of edge `Z = camera_i_from_camera_j` at poses `x_i`, `x_j`, with its closed-form
/// Jacobians (see the module documentation).
pub fn linearise(
    x_i: &Isometry3<f64>,
    x_j: &Isometry3<f64>,
    measured: &Isometry3<f64>,
) -> Linearised {
    let r = residual(x_i, x_j, measured);
    let r_i = x_i.rotation.to_rotation_matrix().into_inner();
    let r_j = x_j.rotation.to_rotation_matrix().into_inner();
    let r_z = measured.rotation.to_rotation_matrix().into_inner();
    let jr_inv = inverse_right_jacobian(&r.fixed_rows::<3>(0).into_owned());
    let rz_t_ri_t = r_z.transpose() * r_i.transpose();
    let relative_position = r_i.transpose() * (x_j.translation.vector - x_i.translation.vector);

    let mut jacobian_i = Matrix6::zeros();
    jacobian_i
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-jr_inv * r_j.transpose() * r_i));
    jacobian_i
        .fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(r_z.transpose() * relative_position.cross_matrix()));
    jacobian_i
        .fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(-rz_t_ri_t));

    let mut jacobian_j = Matrix6::zeros();
    jacobian_j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jr_inv);
    jacobian_j
        .fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&rz_t_ri_t);
    Linearised {
        residual: r,
        jacobian_i,
        jacobian_j,
    }
}

/// Inverse right Jacobian of SO(3):
/// `I + [theta]x / 2 + (1 / |theta|^2 - (1 + cos|theta|) / (2 |theta| sin|theta|)) [theta]x^2`.
fn inverse_right_jacobian(theta: &Vector3<f64>) -> Matrix3<f64> {
    let skew = theta.cross_matrix();
    let angle = theta.norm();
    let coefficient = if angle < SMALL_ANGLE {
        SMALL_ANGLE_COEFFICIENT
    } else {
        let a = angle.min(MAX_JACOBIAN_ANGLE);
        1.0 / (a * a) - (1.0 + a.cos()) / (2.0 * a * a.sin())
    };
    Matrix3::identity() + 0.5 * skew + coefficient * skew * skew
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: [f64; 3], euler: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_euler_angles(euler[0], euler[1], euler[2]),
        )
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let x_i = pose([0.3, -1.2, 0.8], [0.2, -0.4, 1.1]);
        let x_j = pose([1.1, 0.4, 0.2], [-0.3, 0.5, 2.0]);
        // A measurement that does not agree with the poses, so the residual is far from zero.
        let measured = pose([0.5, 0.2, -0.4], [0.6, 0.1, 0.7]);
        let lin = linearise(&x_i, &x_j, &measured);
        let step = 1e-6;
        for k in 0..6 {
            let delta = Vector6::ith(k, step);
            let d_i = (residual(&retract(&x_i, &delta), &x_j, &measured)
                - residual(&retract(&x_i, &-delta), &x_j, &measured))
                / (2.0 * step);
            let d_j = (residual(&x_i, &retract(&x_j, &delta), &measured)
                - residual(&x_i, &retract(&x_j, &-delta), &measured))
                / (2.0 * step);
            assert!(
                (d_i - lin.jacobian_i.column(k)).norm() < 1e-6,
                "d/d node i, column {k}: {d_i} vs {}",
                lin.jacobian_i.column(k)
            );
            assert!(
                (d_j - lin.jacobian_j.column(k)).norm() < 1e-6,
                "d/d node j, column {k}: {d_j} vs {}",
                lin.jacobian_j.column(k)
            );
        }
    }

    #[test]
    fn consistent_poses_have_zero_residual() {
        let x_i = pose([0.3, -1.2, 0.8], [0.2, -0.4, 1.1]);
        let x_j = pose([1.1, 0.4, 0.2], [-0.3, 0.5, 2.0]);
        assert!(residual(&x_i, &x_j, &(x_i.inverse() * x_j)).norm() < 1e-12);
    }
}
