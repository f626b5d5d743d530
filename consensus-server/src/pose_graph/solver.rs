//! Weighted Levenberg-Marquardt over all node poses of the graph.
//!
//! Minimises `sum_e w_e r_e^T Omega_e r_e` ([`super::residual`]) with dense normal equations: the
//! consensus's graphs have tens to a few hundred keyframes (6 unknowns each), where a dense
//! Cholesky takes milliseconds. One node is held fixed: it defines the world frame (gauge).
//!
//! Damping follows Marquardt: `(H + lambda diag(H)) delta = -g`, a step is kept only if it lowers
//! the cost, and lambda shrinks after a kept step and grows after a refused one.

use nalgebra::{DMatrix, DVector, Isometry3, Matrix6, Vector6};

use super::residual::{linearise, residual, retract};

/// Damping of the first step, relative to the Hessian's diagonal.
const INITIAL_LAMBDA: f64 = 1e-4;
/// Factor by which lambda grows after a refused step and shrinks after a kept one.
const LAMBDA_FACTOR: f64 = 10.0;
/// Damped steps tried per iteration before the estimate counts as a minimum.
const MAX_DAMPED_STEPS: usize = 10;
/// Lower bound of each diagonal entry in the damping term: a node whose every edge is weighted
/// out (an agent whose only loop closures were rejected) has a zero Hessian block, and the floor
/// keeps the system solvable with that node left where it is.
const DIAGONAL_FLOOR: f64 = 1e-6;

/// A relative-pose constraint between two nodes.
#[derive(Debug, Clone)]
pub struct Edge {
    /// Index of node i in the poses: the camera whose coordinates `measured` maps into.
    pub from: usize,
    /// Index of node j in the poses: the camera whose coordinates `measured` maps from.
    pub to: usize,
    /// `camera_from_from_camera_to`.
    pub measured: Isometry3<f64>,
    /// Inverse variances of the rotation and translation residual components.
    pub rotation_information: f64,
    /// Inverse variance of each translation residual component, 1/m^2.
    pub translation_information: f64,
}

impl Edge {
    fn information(&self) -> Matrix6<f64> {
        let r = self.rotation_information;
        let t = self.translation_information;
        Matrix6::from_diagonal(&Vector6::new(r, r, r, t, t, t))
    }

    /// Squared Mahalanobis norm of the residual at `poses`.
    pub fn chi2(&self, poses: &[Isometry3<f64>]) -> f64 {
        let r = residual(&poses[self.from], &poses[self.to], &self.measured);
        r.dot(&(self.information() * r))
    }
}

/// What one optimisation did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverReport {
    /// Levenberg-Marquardt iterations run (each builds the normal equations once).
    pub iterations: usize,
    /// Weighted cost ([`cost`]) of the starting poses.
    pub initial_cost: f64,
    /// Weighted cost of the poses returned; never above `initial_cost`, as only steps that lower
    /// the cost are kept.
    pub final_cost: f64,
}

/// Weighted cost of all edges at `poses`.
pub fn cost(poses: &[Isometry3<f64>], edges: &[Edge], weights: &[f64]) -> f64 {
    edges
        .iter()
        .zip(weights)
        .filter(|(_, w)| **w > 0.0)
        .map(|(e, w)| w * e.chi2(poses))
        .sum()
}

/// Optimises `poses` in place; `fixed` is the gauge node. `weights[e]` scales edge e (GNC).
pub fn optimise(
    poses: &mut [Isometry3<f64>],
    fixed: usize,
    edges: &[Edge],
    weights: &[f64],
    max_iterations: usize,
    step_tolerance: f64,
) -> SolverReport {
    let column = |node: usize| -> Option<usize> {
        match node.cmp(&fixed) {
            std::cmp::Ordering::Less => Some(6 * node),
            std::cmp::Ordering::Equal => None,
            std::cmp::Ordering::Greater => Some(6 * (node - 1)),
        }
    };
    let unknowns = 6 * (poses.len() - 1);
    let initial_cost = cost(poses, edges, weights);
    let mut current_cost = initial_cost;
    let mut lambda = INITIAL_LAMBDA;
    let mut iterations = 0;
    while iterations < max_iterations && unknowns > 0 {
        iterations += 1;
        let (hessian, gradient) = normal_equations(poses, edges, weights, unknowns, &column);
        let mut improved = false;
        let mut step_size = f64::INFINITY;
        for _ in 0..MAX_DAMPED_STEPS {
            let mut damped = hessian.clone();
            for k in 0..unknowns {
                damped[(k, k)] += lambda * hessian[(k, k)].max(DIAGONAL_FLOOR);
            }
            let Some(cholesky) = damped.cholesky() else {
                lambda *= LAMBDA_FACTOR;
                continue;
            };
            let delta = -cholesky.solve(&gradient);
            let candidate: Vec<Isometry3<f64>> = poses
                .iter()
                .enumerate()
                .map(|(node, pose)| match column(node) {
                    Some(c) => retract(pose, &delta.fixed_rows::<6>(c).into_owned()),
                    None => *pose,
                })
                .collect();
            let candidate_cost = cost(&candidate, edges, weights);
            if candidate_cost < current_cost {
                poses.copy_from_slice(&candidate);
                current_cost = candidate_cost;
                step_size = delta.amax();
                lambda /= LAMBDA_FACTOR;
                improved = true;
                break;
            }
            lambda *= LAMBDA_FACTOR;
        }
        // No damped step lowers the cost: a minimum to numerical precision.
        if !improved || step_size < step_tolerance {
            break;
        }
    }
    SolverReport {
        iterations,
        initial_cost,
        final_cost: current_cost,
    }
}

/// `H = sum w J^T Omega J` and `g = sum w J^T Omega r` over the free nodes.
fn normal_equations(
    poses: &[Isometry3<f64>],
    edges: &[Edge],
    weights: &[f64],
    unknowns: usize,
    column: &dyn Fn(usize) -> Option<usize>,
) -> (DMatrix<f64>, DVector<f64>) {
    let mut hessian = DMatrix::zeros(unknowns, unknowns);
    let mut gradient = DVector::zeros(unknowns);
    for (edge, &weight) in edges.iter().zip(weights) {
        if weight <= 0.0 {
            continue;
        }
        let lin = linearise(&poses[edge.from], &poses[edge.to], &edge.measured);
        let weighted_information = edge.information() * weight;
        let blocks = [
            (column(edge.from), lin.jacobian_i),
            (column(edge.to), lin.jacobian_j),
        ];
        for (row, jacobian_row) in &blocks {
            let Some(row) = row else { continue };
            let jt_omega = jacobian_row.transpose() * weighted_information;
            let mut g = gradient.fixed_rows_mut::<6>(*row);
            g += jt_omega * lin.residual;
            for (col, jacobian_col) in &blocks {
                let Some(col) = col else { continue };
                let mut h = hessian.fixed_view_mut::<6, 6>(*row, *col);
                h += jt_omega * jacobian_col;
            }
        }
    }
    (hessian, gradient)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A square of four poses with consistent odometry, started from a perturbed guess.
    #[test]
    fn recovers_a_consistent_loop_from_a_perturbed_start() {
        let truth: Vec<Isometry3<f64>> = (0..4)
            .map(|k| {
                let angle = k as f64 * std::f64::consts::FRAC_PI_2;
                Isometry3::from_parts(
                    Translation3::new(angle.cos(), angle.sin(), 0.1 * k as f64),
                    UnitQuaternion::from_euler_angles(0.1, -0.2, angle),
                )
            })
            .collect();
        let edges: Vec<Edge> = (0..4)
            .map(|k| {
                let (from, to) = (k, (k + 1) % 4);
                Edge {
                    from,
                    to,
                    measured: truth[from].inverse() * truth[to],
                    rotation_information: 1e4,
                    translation_information: 1e4,
                }
            })
            .collect();
        let mut poses: Vec<Isometry3<f64>> = truth
            .iter()
            .enumerate()
            .map(|(k, p)| {
                if k == 0 {
                    *p
                } else {
                    retract(p, &Vector6::new(0.2, -0.1, 0.3, 0.3, -0.2, 0.1))
                }
            })
            .collect();
        let report = optimise(&mut poses, 0, &edges, &[1.0; 4], 50, 1e-10);
        assert!(report.final_cost < 1e-12, "{report:?}");
        for (estimate, expected) in poses.iter().zip(&truth) {
            let error = estimate.inverse() * expected;
            assert!(error.translation.vector.norm() < 1e-6 && error.rotation.angle() < 1e-6);
        }
    }
}
