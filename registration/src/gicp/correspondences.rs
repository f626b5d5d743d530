//! Correspondence search and linearisation: for each source point the nearest target point
//! within the correspondence distance, its residual and weight, summed into the normal equations
//! of the right-perturbed residuals; and the error of a damped step with those correspondences.

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;

use super::RegistrationTarget;
use crate::covariance::Covariance;
use crate::points::PointCloud;

/// Source points per rayon task: big enough to amortise scheduling, small enough to balance.
pub(super) const POINTS_PER_TASK: usize = 1024;

/// A source point's correspondence as found by the last linearisation: the target point and the
/// weight `W = (C_B + R C_A R^T)^-1` at that linearisation's rotation. `None` without one.
pub(super) type Correspondence = Option<(Vector3<f64>, Matrix3<f64>)>;

/// Normal equations of one linearisation, summed over correspondences.
#[derive(Clone, Copy)]
pub(super) struct NormalEquations {
    pub(super) hessian: Matrix6<f64>,
    pub(super) gradient: Vector6<f64>,
    pub(super) error: f64,
    pub(super) inliers: usize,
    /// Source points with a target point within the overlap distance.
    pub(super) overlapping: usize,
    /// Of every `sample_step`-th source point (index a multiple of it), those with a target
    /// point within the correspondence distance; 0 when no sample was asked for.
    pub(super) sampled_within: usize,
}

impl NormalEquations {
    pub(super) fn zero() -> Self {
        Self {
            hessian: Matrix6::zeros(),
            gradient: Vector6::zeros(),
            error: 0.0,
            inliers: 0,
            overlapping: 0,
            sampled_within: 0,
        }
    }

    pub(super) fn add(mut self, other: Self) -> Self {
        self.hessian += other.hessian;
        self.gradient += other.gradient;
        self.error += other.error;
        self.inliers += other.inliers;
        self.overlapping += other.overlapping;
        self.sampled_within += other.sampled_within;
        self
    }
}

/// The pose's rotation and translation as plain matrices for the inner loops.
pub(super) struct RigidParts {
    pub(super) rotation: Matrix3<f64>,
    pub(super) translation: Vector3<f64>,
}

impl RigidParts {
    pub(super) fn of(pose: &Isometry3<f64>) -> Self {
        Self {
            rotation: pose.rotation.to_rotation_matrix().into_inner(),
            translation: pose.translation.vector,
        }
    }

    pub(super) fn transform(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}

/// Residual `d = b - T a` and its weight `W = (C_B + R C_A R^T)^-1`; `None` if the combined
/// covariance is singular (both covariances are positive definite by construction, so only
/// corrupted input gets here).
#[inline]
pub(super) fn residual_and_weight(
    transformed_source: &Vector3<f64>,
    source_covariance: &Covariance,
    target_position: &Point3<f32>,
    target_covariance: &Covariance,
    rotation: &Matrix3<f64>,
) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let combined = target_covariance.to_matrix()
        + rotation * source_covariance.to_matrix() * rotation.transpose();
    let weight = combined.try_inverse()?;
    Some((
        target_position.coords.cast::<f64>() - transformed_source,
        weight,
    ))
}

/// Searches correspondences at `pose` (stored with their weights into `correspondences`) and
/// builds the normal equations of the right-perturbed residuals. `(correspondence, overlap)`
/// squared distances: one search with the larger also counts the overlapping points, and with a
/// `sample_step` above 0 the sampled points within the correspondence distance.
pub(super) fn linearize<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    pose: &Isometry3<f64>,
    (max_distance_sq, overlap_sq): (f32, f32),
    sample_step: usize,
    (correspondences, hints): (&mut [Correspondence], &mut [u32]),
) -> NormalEquations {
    let parts = RigidParts::of(pose);
    let search_sq = max_distance_sq.max(overlap_sq);
    let chunks = source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .zip(source.covariances.par_chunks(POINTS_PER_TASK))
        .zip(correspondences.par_chunks_mut(POINTS_PER_TASK))
        .zip(hints.par_chunks_mut(POINTS_PER_TASK))
        .enumerate()
        .map(|(chunk, (((positions, covariances), matches), hints))| {
            let mut sum = NormalEquations::zero();
            let first_index = chunk * POINTS_PER_TASK;
            for (i, (((a, c_a), found), hint)) in positions
                .iter()
                .zip(covariances)
                .zip(matches.iter_mut())
                .zip(hints.iter_mut())
                .enumerate()
            {
                let a = a.coords.cast::<f64>();
                let transformed = parts.transform(&a);
                *found = None;
                let Some((j, distance_sq)) = target.nearest_within_hinted(
                    &Point3::from(transformed.cast::<f32>()),
                    search_sq,
                    hint,
                ) else {
                    continue;
                };
                if distance_sq <= overlap_sq {
                    sum.overlapping += 1;
                }
                if distance_sq > max_distance_sq {
                    continue;
                }
                if sample_step > 0 && in_sample(first_index + i, sample_step) {
                    sum.sampled_within += 1;
                }
                let target_position = target.position(j);
                let Some((d, w)) = residual_and_weight(
                    &transformed,
                    c_a,
                    &target_position,
                    &target.covariance(j),
                    &parts.rotation,
                ) else {
                    continue;
                };
                *found = Some((target_position.coords.cast::<f64>(), w));
                // J = [R [a]x, -R] = [[r]x, -I] B with r = R a and B = diag(R, R), so
                // J^T W J = B^T K^T W K B with the sparse K = [[r]x, -I]: K's blocks are summed
                // here (the lower-left one is the transpose of the upper-right, filled once) and B
                // is applied once to the sums, a third of the arithmetic of the dense product.
                let r = transformed - parts.translation;
                let skew = r.cross_matrix();
                let skew_t_w = skew.transpose() * w;
                let w_d = w * d;
                let mut block = sum.hessian.fixed_view_mut::<3, 3>(0, 0);
                block += skew_t_w * skew;
                let mut block = sum.hessian.fixed_view_mut::<3, 3>(0, 3);
                block -= skew_t_w;
                let mut block = sum.hessian.fixed_view_mut::<3, 3>(3, 3);
                block += w;
                let mut rows = sum.gradient.fixed_rows_mut::<3>(0);
                rows += skew.transpose() * w_d;
                let mut rows = sum.gradient.fixed_rows_mut::<3>(3);
                rows -= w_d;
                sum.error += d.dot(&w_d);
                sum.inliers += 1;
            }
            sum
        });
    let mut world = in_chunk_order(chunks, NormalEquations::zero(), NormalEquations::add);
    // Lower-left block from the upper-right, then from K's frame to the perturbation's.
    let upper_right = world.hessian.fixed_view::<3, 3>(0, 3).transpose();
    world
        .hessian
        .fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&upper_right);
    let mut to_body = Matrix6::zeros();
    to_body
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&parts.rotation);
    to_body
        .fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&parts.rotation);
    NormalEquations {
        hessian: to_body.transpose() * world.hessian * to_body,
        gradient: to_body.transpose() * world.gradient,
        ..world
    }
}

/// G-ICP error at `pose` with the correspondences and weights of the last linearisation (judging
/// a damped step needs no new search).
pub(super) fn evaluate(
    source: &PointCloud,
    pose: &Isometry3<f64>,
    correspondences: &[Correspondence],
) -> f64 {
    let parts = RigidParts::of(pose);
    let errors = source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .zip(correspondences.par_chunks(POINTS_PER_TASK))
        .map(|(positions, matches)| {
            let mut error = 0.0;
            for (a, found) in positions.iter().zip(matches) {
                if let Some((b, w)) = found {
                    let d = b - parts.transform(&a.coords.cast::<f64>());
                    error += d.dot(&(w * d));
                }
            }
            error
        });
    in_chunk_order(errors, 0.0, |x, y| x + y)
}

/// Combines per-chunk results in chunk order. Rayon's `reduce` and `sum` combine them in a tree
/// whose shape depends on which thread stole which work, and float addition is not
/// associative: the same frame would get a pose that differs in the last bits from run to run
/// and with the thread count, and odometry carries such differences on. The chunks themselves
/// are fixed (`POINTS_PER_TASK` points each, summed in order), so this makes the sums repeat.
pub(super) fn in_chunk_order<T: Send>(
    chunks: impl IndexedParallelIterator<Item = T>,
    zero: T,
    add: impl Fn(T, T) -> T,
) -> T {
    chunks.collect::<Vec<T>>().into_iter().fold(zero, add)
}

/// Whether source point `index` (its index in the whole cloud) belongs to the every-`step`-th
/// sample that [`super::count_correspondences`] and the first search of
/// [`super::register_unless_outscored`] count: both must pick the same points for their counts to
/// compare.
pub(super) fn in_sample(index: usize, step: usize) -> bool {
    index.is_multiple_of(step)
}
