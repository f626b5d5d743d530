//! Step 3 of the pipeline: Generalized-ICP (Segal, Haehnel, Thrun, RSS 2009) solved with
//! Levenberg-Marquardt on SE(3).
//!
//! Given source points `a_i` with covariances `C_A,i` and a target with points `b_j` and
//! covariances `C_B,j`, find `T = target_from_source` minimising
//!
//! ```text
//!     E(T) = sum_i  d_i^T (C_B,j(i) + R C_A,i R^T)^-1 d_i,     d_i = b_j(i) - T a_i
//! ```
//!
//! where `j(i)` is the single nearest target point to `T a_i` within the correspondence distance
//! (re-searched at every iteration). The same formula with both covariances is the consensus's
//! two-keyframe alignment (docs/method.md, The consensus: association and alignment:
//! `Sigma_k + Sigma_l`): it is this function with a [`crate::kdtree::PointTree`] target.
//!
//! **Perturbation:** right (body-frame), `T <- T * (Exp(omega), v)`, the update `delta = (omega, v)`
//! with `omega` a rotation vector and `v` a translation in the *source* frame. Then
//! `d(d_i)/d(delta) = [R [a_i]x, -R]`, the form small_gicp uses, and the update's size is directly
//! the "rotation change" and "translation change" of the convergence test (docs/method.md, One
//! agent: Tracking; |R v| = |v|).
//!
//! **Levenberg-Marquardt:** each iteration searches correspondences and builds the normal
//! equations `H = sum J^T W J`, `b = sum J^T W d` at the current pose; then up to
//! [`LM_MAX_INNER_ITERATIONS`] damped steps `(H + lambda I) delta = -b` are tried, each judged with
//! the *same* correspondences and the *same* weights `W` (no new search, no new 3x3 inverse): a
//! step that does not lower the error is rejected and `lambda` grows by [`LM_LAMBDA_FACTOR`]; an
//! accepted step shrinks it. These are small_gicp's defaults, and so is keeping `W` from the
//! linearisation (the rotation a damped step adds changes `R C_A R^T` by far less than it changes
//! the residuals, and recomputing `W` per point doubled the cost of judging a step). When no damped step lowers the error the pose is a minimum to numerical precision,
//! which counts as converged.

//!
//! The code: `solver.rs` runs the Levenberg-Marquardt loop and classifies the result,
//! `correspondences.rs` searches correspondences and builds the normal equations, and
//! `coarse_to_fine.rs` chains runs over shrinking distances and scores initial guesses.

use nalgebra::{Isometry3, Point3};

use crate::config::{KeyframeConfig, TrackingConfig};
use crate::covariance::Covariance;
use crate::points::PointCloud;

mod coarse_to_fine;
mod correspondences;
mod solver;
#[cfg(test)]
mod tests;

pub use coarse_to_fine::{count_correspondences, register_coarse_to_fine};
pub use solver::{RivalGuess, register_joint_unless_outscored, register_unless_outscored};

/// A rigid transform has six degrees of freedom: fewer points (or correspondences) than this can
/// never determine it, whatever the configured inlier fraction.
pub const MIN_POINTS_FOR_A_POSE: usize = 6;

/// Damping of the first Levenberg-Marquardt step (small_gicp's default).
pub const LM_INITIAL_LAMBDA: f64 = 1e-3;
/// Factor by which the damping grows after a rejected step and shrinks after an accepted one.
pub const LM_LAMBDA_FACTOR: f64 = 10.0;
/// Damped steps tried per iteration before the pose is declared a minimum.
pub const LM_MAX_INNER_ITERATIONS: usize = 10;

/// A search hint that points nowhere (see [`RegistrationTarget::nearest_within_hinted`]).
pub const NO_HINT: u32 = u32::MAX;

/// What G-ICP aligns against: a searchable set of points with covariances. Implemented by the
/// static [`super::kdtree::PointTree`] and the incremental [`super::voxel_map::VoxelMap`].
pub trait RegistrationTarget: Sync {
    /// Index and squared distance of the nearest target point no farther than
    /// `sqrt(max_distance_sq)` from `query`, if any.
    fn nearest_within(&self, query: &Point3<f32>, max_distance_sq: f32) -> Option<(u32, f32)>;
    /// [`Self::nearest_within`] for a query that repeats, moved a little, the one that last used
    /// `hint` (the same source point at the next G-ICP iteration). A target may keep in `hint`
    /// where it found that query's answer and look there first; the answer is the same as
    /// [`Self::nearest_within`]'s. Start each source point with [`NO_HINT`].
    fn nearest_within_hinted(
        &self,
        query: &Point3<f32>,
        max_distance_sq: f32,
        _hint: &mut u32,
    ) -> Option<(u32, f32)> {
        self.nearest_within(query, max_distance_sq)
    }
    /// Whether any target point is within `sqrt(max_distance_sq)` of `query`. Targets that can
    /// answer this faster than a nearest search override it.
    fn any_within(&self, query: &Point3<f32>, max_distance_sq: f32) -> bool {
        self.nearest_within(query, max_distance_sq).is_some()
    }
    /// Position of the target point with that index.
    fn position(&self, index: u32) -> Point3<f32>;
    /// G-ICP covariance of the target point with that index.
    fn covariance(&self, index: u32) -> Covariance;
    /// Number of points that can be matched.
    fn target_len(&self) -> usize;
}

/// Normal equations of a [`JointTerm`] at one pose, in G-ICP's perturbation (right, `(omega,
/// v)`): `hessian = sum J^T w J`, `gradient = sum J^T w r` for residuals `r` with Jacobians `J`
/// and weights `w`, and `error = sum w r^2`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointSystem {
    /// `sum J^T w J`, added to G-ICP's Hessian approximation.
    pub hessian: nalgebra::Matrix6<f64>,
    /// `sum J^T w r`, added to G-ICP's gradient.
    pub gradient: nalgebra::Vector6<f64>,
    /// `sum w r^2` at the linearisation pose; when not finite the system is left out of the
    /// step.
    pub error: f64,
}

/// A second cost minimised together with G-ICP's ([`register_joint_unless_outscored`]), such as
/// the photometric term of tracking ([`crate::photometric`]).
pub trait JointTerm {
    /// Linearises the term at `pose` (`target_from_source`). It may refresh per-linearisation
    /// state here (robust weights, brightness), which [`Self::evaluate`] then keeps, as G-ICP
    /// keeps its correspondences and weights while judging damped steps.
    fn linearize(&mut self, pose: &Isometry3<f64>) -> JointSystem;
    /// The cost at `pose` with the last linearisation's weights.
    fn evaluate(&self, pose: &Isometry3<f64>) -> f64;
}

/// Parameters of one G-ICP run. Build them from the configuration with [`GicpParams::tracking`];
/// the consensus overrides `max_correspondence_m` per coarse-to-fine stage.
#[derive(Debug, Clone, PartialEq)]
pub struct GicpParams {
    /// Largest source-to-target distance accepted as a correspondence (metres).
    pub max_correspondence_m: f64,
    /// Levenberg-Marquardt iterations (correspondence searches) at most.
    pub max_iterations: usize,
    /// Converged when an accepted update rotates less than this (radians)...
    pub rotation_epsilon_rad: f64,
    /// ...and translates less than this (metres).
    pub translation_epsilon_m: f64,
    /// A source point "overlaps" the target when a target point is within this distance of it
    /// at the final pose (metres; the keyframe criterion of docs/method.md, One agent: Keyframes, sqrt(5e-4)).
    pub overlap_distance_m: f64,
    /// The result is a failure when fewer than this fraction of the source points have a
    /// correspondence at the final pose.
    pub min_inlier_fraction: f64,
}

impl GicpParams {
    /// The tracking parameters (docs/method.md, One agent: Tracking).
    pub fn tracking(tracking: &TrackingConfig, keyframes: &KeyframeConfig) -> Self {
        Self {
            max_correspondence_m: tracking.max_correspondence_m,
            max_iterations: tracking.max_iterations,
            rotation_epsilon_rad: tracking.rotation_epsilon_rad,
            translation_epsilon_m: tracking.translation_epsilon_m,
            overlap_distance_m: keyframes.overlap_distance_sq_m2.sqrt(),
            min_inlier_fraction: tracking.min_inlier_fraction,
        }
    }

    /// The same parameters with another correspondence distance (coarse-to-fine stages).
    pub fn with_max_correspondence(&self, max_correspondence_m: f64) -> Self {
        Self {
            max_correspondence_m,
            ..self.clone()
        }
    }
}

/// Why a registration cannot be trusted. Every failure is reported; none is silently accepted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RegistrationFailure {
    /// The source cloud has fewer points than a pose needs; checked before the first iteration.
    #[error("{found} source points, at least {required} needed")]
    TooFewSourcePoints {
        /// Points in the source cloud.
        found: usize,
        /// [`MIN_POINTS_FOR_A_POSE`].
        required: usize,
    },
    /// The target has fewer points than a pose needs; checked before the first iteration.
    #[error("{found} target points, at least {required} needed")]
    TooFewTargetPoints {
        /// Points in the target ([`RegistrationTarget::target_len`]).
        found: usize,
        /// [`MIN_POINTS_FOR_A_POSE`].
        required: usize,
    },
    /// The source cloud lacks one covariance per point.
    #[error("the source cloud has no covariances (estimate them first)")]
    MissingSourceCovariances,
    /// Too few source points found a target point within the correspondence distance, during
    /// the optimisation or at the final pose.
    #[error("{found} correspondences, at least {required} needed")]
    TooFewCorrespondences {
        /// Source points with a correspondence.
        found: usize,
        /// During the optimisation [`MIN_POINTS_FOR_A_POSE`]; at the final pose the larger of
        /// that and `min_inlier_fraction` of the source points (rounded up).
        required: usize,
    },
    /// The error, an update or the final pose is not finite.
    #[error("the optimisation diverged (non-finite error or update)")]
    Diverged,
    /// `max_iterations` ran out before an update fell below both convergence thresholds. The
    /// pose is still usable ([`RegistrationFailure::pose_is_usable`]).
    #[error("not converged after {iterations} iterations")]
    NotConverged {
        /// Correspondence searches performed.
        iterations: usize,
    },
}

impl RegistrationFailure {
    /// True when the returned pose is still the best estimate available (the optimisation only
    /// ran out of iterations while lowering the error); false when the pose must not be used.
    pub fn pose_is_usable(&self) -> bool {
        matches!(self, Self::NotConverged { .. })
    }
}

/// Outcome of a G-ICP run.
#[derive(Debug, Clone, PartialEq)]
pub struct RegistrationResult {
    /// The estimate: maps source points into the target frame (for tracking against a world
    /// map, `world_from_camera`). On a failure whose pose is not usable, the initial guess.
    pub target_from_source: Isometry3<f64>,
    /// Correspondence searches performed (summed over coarse-to-fine stages).
    pub iterations: usize,
    /// Whether the optimisation converged: an accepted update fell below both thresholds of
    /// [`GicpParams`], or no damped step lowered the error. False when it stopped early on a
    /// failure or ran out of iterations.
    pub converged: bool,
    /// Source points with a target point within the correspondence distance at the final pose.
    pub correspondences: usize,
    /// Points in the source cloud.
    pub source_points: usize,
    /// Fraction of source points with a target point within `overlap_distance_m` at the final pose.
    pub overlap_fraction: f64,
    /// G-ICP cost `sum d^T (C_B + R C_A R^T)^-1 d` over the final correspondences.
    pub error: f64,
    /// `None` on success.
    pub failure: Option<RegistrationFailure>,
}

impl RegistrationResult {
    /// True when no failure was reported.
    pub fn is_success(&self) -> bool {
        self.failure.is_none()
    }

    /// Fraction of source points with a correspondence at the final pose.
    pub fn inlier_fraction(&self) -> f64 {
        if self.source_points == 0 {
            0.0
        } else {
            self.correspondences as f64 / self.source_points as f64
        }
    }

    fn failed(
        initial: &Isometry3<f64>,
        source_points: usize,
        failure: RegistrationFailure,
    ) -> Self {
        Self {
            target_from_source: *initial,
            iterations: 0,
            converged: false,
            correspondences: 0,
            source_points,
            overlap_fraction: 0.0,
            error: f64::NAN,
            failure: Some(failure),
        }
    }
}

/// Aligns `source` (points with covariances) to `target`, starting from `initial`
/// (`target_from_source`). See the module documentation for the method.
pub fn register<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    params: &GicpParams,
) -> RegistrationResult {
    register_unless_outscored(source, target, initial, params, None)
        .expect("no rival guess: never given up")
}
