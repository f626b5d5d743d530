//! The pose half of joint refinement: Adam over each keyframe pose's left perturbation, the
//! pose-consistency term over the pose graph's edges, and the bound on how far a pose may move.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3, Vector6};

use super::{PoseEdge, RefinementReport};
use crate::pose_graph::residual::residual;
use config::{ConsensusConfig, RefinementConfig};
use geometry::se3::pose_change;
use render_core::pose::{PoseAdam, pose_rates};

/// Step of the central differences of the pose-consistency term (radians / metres): far below
/// any pose change that matters, far above f64 round-off of poses a few metres from the origin.
const CONSISTENCY_DIFFERENCE_STEP: f64 = 1e-6;

/// Every view's pose as refinement moves it, with its optimiser state.
pub(super) struct PoseRefinement<'e> {
    pub poses: Vec<Isometry3<f64>>,
    adam: Vec<PoseAdam>,
    /// Adam step sizes, `[translation, rotation]`.
    rates: Vector6<f64>,
    edges: &'e [PoseEdge],
    consistency_weight: f64,
}

impl<'e> PoseRefinement<'e> {
    pub fn new(
        initial: Vec<Isometry3<f64>>,
        edges: &'e [PoseEdge],
        consensus: &ConsensusConfig,
    ) -> Self {
        let config = &consensus.refinement;
        Self {
            adam: vec![PoseAdam::default(); initial.len()],
            poses: initial,
            rates: pose_rates(config.lr_pose_translation_m, config.lr_pose_rotation_rad),
            edges,
            consistency_weight: consensus.weight_pose_consistency,
        }
    }

    /// One Adam step of `view`'s pose along its photometric gradient (render-core's, read back)
    /// plus the consistency term's; skipped when the gradient is not finite.
    pub fn step(&mut self, view: usize, photometric: &[f64; 6]) {
        let gradient = Vector6::from_column_slice(photometric)
            + consistency_gradient(&self.poses, self.edges, view, self.consistency_weight);
        if gradient.iter().all(|g| g.is_finite()) {
            let xi = self.adam[view].step(&gradient, &self.rates);
            self.poses[view] = perturbed(&self.poses[view], &xi);
        }
    }

    /// The refined poses, those that moved farther from `initial` than `max_pose_change_*` put
    /// back (counted in `report`, with the largest change kept).
    pub fn into_bounded(
        mut self,
        initial: &[Isometry3<f64>],
        config: &RefinementConfig,
        report: &mut RefinementReport,
    ) -> Vec<Isometry3<f64>> {
        for (pose, start) in self.poses.iter_mut().zip(initial) {
            let (moved_m, turned_rad) = pose_change(start, pose);
            if moved_m > config.max_pose_change_m || turned_rad > config.max_pose_change_rad {
                *pose = *start;
                report.poses_reverted += 1;
            } else {
                report.max_pose_change_m = report.max_pose_change_m.max(moved_m);
                report.max_pose_change_deg =
                    report.max_pose_change_deg.max(turned_rad.to_degrees());
            }
        }
        self.poses
    }
}

/// `camera_from_world` perturbed on the left by `xi = [translation, rotation]`, returned as
/// `world_from_camera`. First-order equal to render-core's SE(3) exponential, which is all a
/// gradient step (and its finite difference) needs.
fn perturbed(world_from_camera: &Isometry3<f64>, xi: &Vector6<f64>) -> Isometry3<f64> {
    let delta = Isometry3::from_parts(
        Translation3::from(Vector3::new(xi[0], xi[1], xi[2])),
        UnitQuaternion::from_scaled_axis(Vector3::new(xi[3], xi[4], xi[5])),
    );
    (delta * world_from_camera.inverse()).inverse()
}

/// `sum |r_ij|^2` over `edges`.
pub fn consistency_cost(poses: &[Isometry3<f64>], edges: &[PoseEdge]) -> f64 {
    edges
        .iter()
        .map(|e| residual(&poses[e.i], &poses[e.j], &e.camera_i_from_camera_j).norm_squared())
        .sum()
}

/// Gradient of `weight * sum |r_ij|^2` over the edges touching `view`, w.r.t. the left
/// perturbation of that view's `camera_from_world` (central differences: 12 residual evaluations
/// per edge, nothing next to a render).
fn consistency_gradient(
    poses: &[Isometry3<f64>],
    edges: &[PoseEdge],
    view: usize,
    weight: f64,
) -> Vector6<f64> {
    let touching: Vec<&PoseEdge> = edges
        .iter()
        .filter(|e| e.i == view || e.j == view)
        .collect();
    if touching.is_empty() || weight == 0.0 {
        return Vector6::zeros();
    }
    let cost_with = |pose: &Isometry3<f64>| -> f64 {
        touching
            .iter()
            .map(|e| {
                let (x_i, x_j) = if e.i == view {
                    (pose, &poses[e.j])
                } else {
                    (&poses[e.i], pose)
                };
                residual(x_i, x_j, &e.camera_i_from_camera_j).norm_squared()
            })
            .sum()
    };
    Vector6::from_fn(|k, _| {
        let mut step = Vector6::zeros();
        step[k] = CONSISTENCY_DIFFERENCE_STEP;
        let plus = cost_with(&perturbed(&poses[view], &step));
        let minus = cost_with(&perturbed(&poses[view], &(-step)));
        weight * (plus - minus) / (2.0 * CONSISTENCY_DIFFERENCE_STEP)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: [f64; 3], axis_angle: [f64; 3]) -> Isometry3<f64> {
        Isometry3::new(Vector3::from(t), Vector3::from(axis_angle))
    }

    #[test]
    fn consistency_gradient_matches_the_cost_and_vanishes_at_agreement() {
        let poses = vec![
            pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
            pose([1.0, 0.2, -0.1], [0.05, -0.1, 0.2]),
            pose([1.5, 0.9, 0.3], [0.1, 0.3, -0.2]),
        ];
        // Measurements that agree with the poses: zero cost, zero gradient.
        let agreeing: Vec<PoseEdge> = [(0, 1), (1, 2), (0, 2)]
            .iter()
            .map(|&(i, j)| PoseEdge {
                i,
                j,
                camera_i_from_camera_j: poses[i].inverse() * poses[j],
            })
            .collect();
        assert!(consistency_cost(&poses, &agreeing) < 1e-20);
        for view in 0..3 {
            assert!(consistency_gradient(&poses, &agreeing, view, 1.0).norm() < 1e-8);
        }
        // A disagreeing edge: a small step against the gradient lowers the cost.
        let mut edges = agreeing.clone();
        edges[1].camera_i_from_camera_j =
            pose([0.02, -0.01, 0.03], [0.01, 0.0, -0.02]) * edges[1].camera_i_from_camera_j;
        let before = consistency_cost(&poses, &edges);
        for view in 1..3 {
            let gradient = consistency_gradient(&poses, &edges, view, 1.0);
            assert!(gradient.norm() > 1e-4, "view {view}: {gradient}");
            let mut moved = poses.clone();
            moved[view] = perturbed(&poses[view], &(-1e-2 * gradient));
            assert!(consistency_cost(&moved, &edges) < before, "view {view}");
        }
    }

    #[test]
    fn perturbation_moves_the_camera_from_world_on_the_left() {
        let world_from_camera = pose([0.5, -0.2, 1.0], [0.1, 0.2, 0.3]);
        let xi = Vector6::new(0.01, 0.0, 0.0, 0.0, 0.0, 0.0);
        let moved = perturbed(&world_from_camera, &xi);
        // A left translation of camera_from_world shifts the camera-frame coordinates of every
        // world point by the same vector.
        let point = nalgebra::Point3::new(0.3, 0.4, 2.0);
        let before = world_from_camera.inverse() * point;
        let after = moved.inverse() * point;
        assert!(((after - before) - Vector3::new(0.01, 0.0, 0.0)).norm() < 1e-12);
    }
}
