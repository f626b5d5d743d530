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

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;

use crate::config::{KeyframeConfig, TrackingConfig};

use crate::covariance::Covariance;
use crate::points::PointCloud;

/// A rigid transform has six degrees of freedom: fewer points (or correspondences) than this can
/// never determine it, whatever the configured inlier fraction.
pub const MIN_POINTS_FOR_A_POSE: usize = 6;

/// Damping of the first Levenberg-Marquardt step (small_gicp's default).
pub const LM_INITIAL_LAMBDA: f64 = 1e-3;
/// Factor by which the damping grows after a rejected step and shrinks after an accepted one.
pub const LM_LAMBDA_FACTOR: f64 = 10.0;
/// Damped steps tried per iteration before the pose is declared a minimum.
pub const LM_MAX_INNER_ITERATIONS: usize = 10;

/// Source points per rayon task: big enough to amortise scheduling, small enough to balance.
const POINTS_PER_TASK: usize = 1024;

/// A source point's correspondence as found by the last linearisation: the target point and the
/// weight `W = (C_B + R C_A R^T)^-1` at that linearisation's rotation. `None` without one.
type Correspondence = Option<(Vector3<f64>, Matrix3<f64>)>;

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
    #[error("{found} source points, at least {required} needed")]
    TooFewSourcePoints { found: usize, required: usize },
    #[error("{found} target points, at least {required} needed")]
    TooFewTargetPoints { found: usize, required: usize },
    #[error("the source cloud has no covariances (estimate them first)")]
    MissingSourceCovariances,
    #[error("{found} correspondences, at least {required} needed")]
    TooFewCorrespondences { found: usize, required: usize },
    #[error("the optimisation diverged (non-finite error or update)")]
    Diverged,
    #[error("not converged after {iterations} iterations")]
    NotConverged { iterations: usize },
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
    pub converged: bool,
    /// Source points with a target point within the correspondence distance at the final pose.
    pub correspondences: usize,
    pub source_points: usize,
    /// Fraction of source points with a target point within `overlap_distance_m` at the final pose.
    pub overlap_fraction: f64,
    /// G-ICP cost `sum d^T (C_B + R C_A R^T)^-1 d` over the final correspondences.
    pub error: f64,
    /// `None` on success.
    pub failure: Option<RegistrationFailure>,
}

impl RegistrationResult {
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

/// A rival initial guess's score, as [`count_correspondences`] gave it: `matches` of every
/// `sample_step`-th source point within the correspondence distance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RivalGuess {
    pub sample_step: usize,
    pub matches: usize,
    /// Whether the rival wins when both guesses count the same.
    pub wins_ties: bool,
}

/// [`register`] from `initial`, unless a rival initial guess scores better: the first
/// correspondence search also counts what [`count_correspondences`] would count at `initial`
/// (the same points, the same distance test), and when that is below `rival.matches` (or equal
/// to it, with `rival.wins_ties`) the optimisation is given up (`None`) before its first step.
/// Choosing between two guesses then costs one sampled search (the rival's) instead of two,
/// because the chosen guess's count comes from a search G-ICP makes anyway; the choice is the
/// same as comparing two [`count_correspondences`]. Inputs G-ICP cannot use (too few points, no
/// covariances) fail at once, from `initial`, whatever the rival scored.
pub fn register_unless_outscored<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    params: &GicpParams,
    rival: Option<RivalGuess>,
) -> Option<RegistrationResult> {
    if let Some(failure) = check_inputs(source, target) {
        return Some(RegistrationResult::failed(initial, source.len(), failure));
    }
    let max_distance_sq = (params.max_correspondence_m * params.max_correspondence_m) as f32;
    let overlap_sq = (params.overlap_distance_m * params.overlap_distance_m) as f32;
    let mut correspondences: Vec<Correspondence> = vec![None; source.len()];
    let mut hints = vec![NO_HINT; source.len()];
    // Statistics of the latest linearisation: the result's when the next step is the converged
    // one (see `finish`).
    let mut linearized = None;
    let mut pose = *initial;
    let mut lambda = LM_INITIAL_LAMBDA;
    let mut converged = false;
    let mut iterations = 0;
    while iterations < params.max_iterations && !converged {
        iterations += 1;
        // The rival is judged on the first search only.
        let rival = rival.filter(|_| iterations == 1);
        let sample_step = rival.map_or(0, |r| r.sample_step.max(1));
        let system = linearize(
            source,
            target,
            &pose,
            (max_distance_sq, overlap_sq),
            sample_step,
            (&mut correspondences, &mut hints),
        );
        if let Some(rival) = rival
            && (system.sampled_within < rival.matches
                || (rival.wins_ties && system.sampled_within == rival.matches))
        {
            return None;
        }
        linearized = Some(FinalStatistics {
            inliers: system.inliers,
            overlapping: system.overlapping,
            error: system.error,
        });
        if system.inliers < MIN_POINTS_FOR_A_POSE {
            let failure = RegistrationFailure::TooFewCorrespondences {
                found: system.inliers,
                required: MIN_POINTS_FOR_A_POSE,
            };
            return Some(RegistrationResult {
                iterations,
                ..RegistrationResult::failed(initial, source.len(), failure)
            });
        }
        if !system.error.is_finite() {
            return Some(RegistrationResult {
                iterations,
                ..RegistrationResult::failed(initial, source.len(), RegistrationFailure::Diverged)
            });
        }
        let mut accepted = false;
        for _ in 0..LM_MAX_INNER_ITERATIONS {
            let damped = system.hessian + Matrix6::identity() * lambda;
            let Some(delta) = damped.cholesky().map(|c| -c.solve(&system.gradient)) else {
                lambda *= LM_LAMBDA_FACTOR;
                continue;
            };
            if !delta.iter().all(|v| v.is_finite()) {
                return Some(RegistrationResult {
                    iterations,
                    ..RegistrationResult::failed(
                        initial,
                        source.len(),
                        RegistrationFailure::Diverged,
                    )
                });
            }
            let rotation_change = delta.fixed_rows::<3>(0).into_owned();
            let translation_change = delta.fixed_rows::<3>(3).into_owned();
            let candidate = pose * Isometry3::new(translation_change, rotation_change);
            if evaluate(source, &candidate, &correspondences) <= system.error {
                pose = candidate;
                lambda /= LM_LAMBDA_FACTOR;
                accepted = true;
                converged = rotation_change.norm() < params.rotation_epsilon_rad
                    && translation_change.norm() < params.translation_epsilon_m;
                break;
            }
            lambda *= LM_LAMBDA_FACTOR;
        }
        if !accepted {
            // No damped step lowers the error: the pose is a minimum to numerical precision.
            converged = true;
        }
    }
    let linearized = linearized.filter(|_| converged);
    Some(finish(
        source, target, initial, pose, iterations, converged, params, linearized,
    ))
}

/// Coarse-to-fine G-ICP: one [`register`] per correspondence distance in `distances_m` (largest
/// first, e.g. `[0.1, 0.05, 0.02]`), each starting where the previous one ended. A coarse stage
/// that merely runs out of iterations hands its pose on; any other failure stops the sequence.
/// The result is the last stage's, with iterations summed over all stages. An empty list runs
/// once at `params.max_correspondence_m`.
///
/// A stage whose inlier fraction (at its own distance) ends below `give_up_below_fraction` also
/// ends the sequence: at a given pose a finer distance can only count fewer inliers, so a pair
/// that the caller would reject for too few inliers at the finest distance is rejected without
/// the finer stages' iterations (pairs that do not overlap are the ones that run every stage to
/// its iteration limit). 0 never gives up.
pub fn register_coarse_to_fine<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    distances_m: &[f64],
    params: &GicpParams,
    give_up_below_fraction: f64,
) -> RegistrationResult {
    let mut pose = *initial;
    let mut total_iterations = 0;
    let mut last = None;
    for &distance in distances_m {
        let stage = register(
            source,
            target,
            &pose,
            &params.with_max_correspondence(distance),
        );
        total_iterations += stage.iterations;
        let usable = stage.failure.as_ref().is_none_or(|f| f.pose_is_usable());
        let hopeless = stage.inlier_fraction() < give_up_below_fraction;
        pose = stage.target_from_source;
        last = Some(stage);
        if !usable || hopeless {
            break;
        }
    }
    match last {
        Some(result) => RegistrationResult {
            iterations: total_iterations,
            // A failed stage returns the pose it started from, not the caller's initial guess.
            target_from_source: if result.failure.as_ref().is_some_and(|f| !f.pose_is_usable()) {
                *initial
            } else {
                result.target_from_source
            },
            ..result
        },
        // No coarse stages given: a plain run at the configured distance.
        None => register(source, target, initial, params),
    }
}

/// Source points with a target point within `max_distance_m` when placed by
/// `target_from_source`, counted over every `sample_step`-th point (those whose index is a
/// multiple of it): a cheap score (one search of a sample, no optimisation) for choosing
/// between initial guesses.
pub fn count_correspondences<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    target_from_source: &Isometry3<f64>,
    max_distance_m: f64,
    sample_step: usize,
) -> usize {
    let parts = RigidParts::of(target_from_source);
    let max_distance_sq = (max_distance_m * max_distance_m) as f32;
    let step = sample_step.max(1);
    source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .enumerate()
        .map(|(chunk, positions)| {
            let first_index = chunk * POINTS_PER_TASK;
            positions
                .iter()
                .enumerate()
                .filter(|&(i, a)| {
                    in_sample(first_index + i, step) && {
                        let transformed = parts.transform(&a.coords.cast::<f64>()).cast::<f32>();
                        target.any_within(&Point3::from(transformed), max_distance_sq)
                    }
                })
                .count()
        })
        .sum()
}

/// Whether source point `index` (its index in the whole cloud) belongs to the every-`step`-th
/// sample that [`count_correspondences`] and the first search of
/// [`register_unless_outscored`] count: both must pick the same points for their counts to
/// compare.
fn in_sample(index: usize, step: usize) -> bool {
    index.is_multiple_of(step)
}

fn check_inputs<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
) -> Option<RegistrationFailure> {
    if source.len() < MIN_POINTS_FOR_A_POSE {
        return Some(RegistrationFailure::TooFewSourcePoints {
            found: source.len(),
            required: MIN_POINTS_FOR_A_POSE,
        });
    }
    if !source.has_covariances() {
        return Some(RegistrationFailure::MissingSourceCovariances);
    }
    if target.target_len() < MIN_POINTS_FOR_A_POSE {
        return Some(RegistrationFailure::TooFewTargetPoints {
            found: target.target_len(),
            required: MIN_POINTS_FOR_A_POSE,
        });
    }
    None
}

/// Final statistics and the failure classification. After convergence they are those of the
/// last linearisation (`linearized`): the returned pose is that linearisation's pose plus one
/// step below the convergence thresholds (or none at all), which moves no point by more than a
/// fraction of a millimetre, so a fresh search would count the same correspondences (small_gicp
/// reports its last linearisation's figures likewise) and costs a sixth of a frame's tracking.
/// Otherwise a fresh search at the final pose.
#[allow(clippy::too_many_arguments)]
fn finish<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    initial: &Isometry3<f64>,
    pose: Isometry3<f64>,
    iterations: usize,
    converged: bool,
    params: &GicpParams,
    linearized: Option<FinalStatistics>,
) -> RegistrationResult {
    let stats = linearized.unwrap_or_else(|| final_statistics(source, target, &pose, params));
    let required = MIN_POINTS_FOR_A_POSE
        .max((params.min_inlier_fraction * source.len() as f64).ceil() as usize);
    let failure =
        if !stats.error.is_finite() || !pose.to_homogeneous().iter().all(|v| v.is_finite()) {
            Some(RegistrationFailure::Diverged)
        } else if stats.inliers < required {
            Some(RegistrationFailure::TooFewCorrespondences {
                found: stats.inliers,
                required,
            })
        } else if !converged {
            Some(RegistrationFailure::NotConverged { iterations })
        } else {
            None
        };
    let pose_is_usable = failure.as_ref().is_none_or(|f| f.pose_is_usable());
    RegistrationResult {
        target_from_source: if pose_is_usable { pose } else { *initial },
        iterations,
        converged,
        correspondences: stats.inliers,
        source_points: source.len(),
        overlap_fraction: stats.overlapping as f64 / source.len() as f64,
        error: stats.error,
        failure,
    }
}

/// Normal equations of one linearisation, summed over correspondences.
#[derive(Clone, Copy)]
struct NormalEquations {
    hessian: Matrix6<f64>,
    gradient: Vector6<f64>,
    error: f64,
    inliers: usize,
    /// Source points with a target point within the overlap distance.
    overlapping: usize,
    /// Of every `sample_step`-th source point (index a multiple of it), those with a target
    /// point within the correspondence distance; 0 when no sample was asked for.
    sampled_within: usize,
}

impl NormalEquations {
    fn zero() -> Self {
        Self {
            hessian: Matrix6::zeros(),
            gradient: Vector6::zeros(),
            error: 0.0,
            inliers: 0,
            overlapping: 0,
            sampled_within: 0,
        }
    }

    fn add(mut self, other: Self) -> Self {
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
struct RigidParts {
    rotation: Matrix3<f64>,
    translation: Vector3<f64>,
}

impl RigidParts {
    fn of(pose: &Isometry3<f64>) -> Self {
        Self {
            rotation: pose.rotation.to_rotation_matrix().into_inner(),
            translation: pose.translation.vector,
        }
    }

    fn transform(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}

/// Residual `d = b - T a` and its weight `W = (C_B + R C_A R^T)^-1`; `None` if the combined
/// covariance is singular (both covariances are positive definite by construction, so only
/// corrupted input gets here).
#[inline]
fn residual_and_weight(
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
fn linearize<T: RegistrationTarget + ?Sized>(
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
fn evaluate(source: &PointCloud, pose: &Isometry3<f64>, correspondences: &[Correspondence]) -> f64 {
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
fn in_chunk_order<T: Send>(
    chunks: impl IndexedParallelIterator<Item = T>,
    zero: T,
    add: impl Fn(T, T) -> T,
) -> T {
    chunks.collect::<Vec<T>>().into_iter().fold(zero, add)
}

struct FinalStatistics {
    inliers: usize,
    overlapping: usize,
    error: f64,
}

/// Inliers, overlapping points and error at the final pose, from one search with the larger of
/// the correspondence and overlap distances.
fn final_statistics<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    pose: &Isometry3<f64>,
    params: &GicpParams,
) -> FinalStatistics {
    let parts = RigidParts::of(pose);
    let inlier_sq = (params.max_correspondence_m * params.max_correspondence_m) as f32;
    let overlap_sq = (params.overlap_distance_m * params.overlap_distance_m) as f32;
    let search_sq = inlier_sq.max(overlap_sq);
    let chunks = source
        .positions
        .par_chunks(POINTS_PER_TASK)
        .zip(source.covariances.par_chunks(POINTS_PER_TASK))
        .map(|(positions, covariances)| {
            let (mut inliers, mut overlapping, mut error) = (0usize, 0usize, 0.0f64);
            for (a, c_a) in positions.iter().zip(covariances) {
                let transformed = parts.transform(&a.coords.cast::<f64>());
                let Some((j, distance_sq)) =
                    target.nearest_within(&Point3::from(transformed.cast::<f32>()), search_sq)
                else {
                    continue;
                };
                if distance_sq <= overlap_sq {
                    overlapping += 1;
                }
                if distance_sq <= inlier_sq
                    && let Some((d, w)) = residual_and_weight(
                        &transformed,
                        c_a,
                        &target.position(j),
                        &target.covariance(j),
                        &parts.rotation,
                    )
                {
                    inliers += 1;
                    error += d.dot(&(w * d));
                }
            }
            (inliers, overlapping, error)
        });
    let (inliers, overlapping, error) = in_chunk_order(chunks, (0, 0, 0.0), |x, y| {
        (x.0 + y.0, x.1 + y.1, x.2 + y.2)
    });
    FinalStatistics {
        inliers,
        overlapping,
        error,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kdtree::PointTree;
    use nalgebra::{Translation3, UnitQuaternion};

    const EPSILON: f64 = 1e-3;
    const NEIGHBOURS: usize = 10;

    /// Points on three orthogonal walls of a room corner (2 cm grid, shifted by `phase` of a grid
    /// step): the smallest scene that pins down all six degrees of freedom.
    fn corner(phase: f32) -> Vec<Point3<f32>> {
        let step = 0.02f32;
        let cells = 40;
        let mut points = Vec::new();
        for i in 0..cells {
            for j in 0..cells {
                let (a, b) = ((i as f32 + phase) * step, (j as f32 + phase) * step);
                points.push(Point3::new(a, b, 0.0));
                points.push(Point3::new(a, 0.0, b + step));
                points.push(Point3::new(0.0, a + step, b + step));
            }
        }
        // Seen from a camera 1.5 m away, so coordinates look like a camera-frame cloud.
        points
            .into_iter()
            .map(|p| p + nalgebra::Vector3::new(-0.4, -0.4, 1.5))
            .collect()
    }

    fn with_covariances(points: Vec<Point3<f32>>) -> PointTree {
        PointTree::with_covariances(PointCloud::from_positions(points), NEIGHBOURS, EPSILON)
            .unwrap()
    }

    fn params(max_correspondence_m: f64) -> GicpParams {
        GicpParams {
            max_correspondence_m,
            ..GicpParams::tracking(&TrackingConfig::default(), &KeyframeConfig::default())
        }
    }

    /// Target = `truth` applied to a differently sampled corner, so G-ICP must find `truth`.
    fn source_and_target(truth: &Isometry3<f64>) -> (PointTree, PointTree) {
        let source = with_covariances(corner(0.0));
        let target = with_covariances(
            corner(0.5)
                .iter()
                .map(|p| (truth * p.cast::<f64>()).cast::<f32>())
                .collect(),
        );
        (source, target)
    }

    fn assert_close(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) {
        let error = estimate.inverse() * truth;
        let translation_mm = error.translation.vector.norm() * 1e3;
        let rotation_deg = error.rotation.angle().to_degrees();
        assert!(
            translation_mm < 1.0 && rotation_deg < 0.05,
            "off by {translation_mm:.3} mm, {rotation_deg:.4} deg"
        );
    }

    /// The first search's sampled count is exactly `count_correspondences`'s at the initial
    /// guess (so choosing between guesses does not change), for a kd-tree and a voxel-map
    /// target and for sample steps that do and do not divide the points per task: a rival with
    /// that many matches loses a tie it does not win and the result is `register`'s; a rival
    /// with one more, or a tie it wins, wins.
    #[test]
    fn a_rival_guess_is_judged_by_the_first_search_as_by_count_correspondences() {
        let truth = Isometry3::from_parts(
            Translation3::new(0.012, -0.008, 0.01),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
        );
        let (source, tree) = source_and_target(&truth);
        let voxels = crate::voxel_map::VoxelMap::from_cloud(tree.cloud(), 0.06);
        let params = params(0.02);
        let initial = Isometry3::identity();
        let targets: [&dyn RegistrationTarget; 2] = [&tree, &voxels];
        for (t, target) in targets.into_iter().enumerate() {
            for sample_step in [1, 3, 4] {
                let matches =
                    count_correspondences(source.cloud(), target, &initial, 0.02, sample_step);
                assert!(
                    matches > 0 && matches < source.len().div_ceil(sample_step),
                    "target {t}, step {sample_step}: {matches} matches, want some but not all"
                );
                let tied = RivalGuess {
                    sample_step,
                    matches,
                    wins_ties: false,
                };
                let kept = register_unless_outscored(
                    source.cloud(),
                    target,
                    &initial,
                    &params,
                    Some(tied),
                )
                .expect("a tie goes to the initial guess");
                let plain = register(source.cloud(), target, &initial, &params);
                assert_eq!(kept.target_from_source, plain.target_from_source);
                assert_eq!(kept.iterations, plain.iterations);
                let better = RivalGuess {
                    matches: matches + 1,
                    ..tied
                };
                let tie_to_rival = RivalGuess {
                    wins_ties: true,
                    ..tied
                };
                for (rival, why) in [(better, "more matches"), (tie_to_rival, "a tie it wins")] {
                    assert!(
                        register_unless_outscored(
                            source.cloud(),
                            target,
                            &initial,
                            &params,
                            Some(rival)
                        )
                        .is_none(),
                        "target {t}, step {sample_step}: a rival with {why} wins"
                    );
                }
            }
        }
    }

    #[test]
    fn recovers_a_known_transform() {
        let truth = Isometry3::from_parts(
            Translation3::new(0.012, -0.008, 0.01),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
        );
        let (source, target) = source_and_target(&truth);
        let result = register(
            source.cloud(),
            &target,
            &Isometry3::identity(),
            &params(0.05),
        );
        assert!(result.is_success(), "{:?}", result.failure);
        assert!(result.converged && result.iterations <= 64);
        assert_close(&result.target_from_source, &truth);
        assert!(
            result.inlier_fraction() > 0.9,
            "{}",
            result.inlier_fraction()
        );
        assert!(result.overlap_fraction > 0.9 && result.error.is_finite());
    }

    #[test]
    fn the_result_does_not_depend_on_the_thread_count() {
        // 4800 points: five chunks of POINTS_PER_TASK, which rayon may combine in any tree.
        let truth = Isometry3::from_parts(
            Translation3::new(0.012, -0.008, 0.01),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
        );
        let (source, target) = source_and_target(&truth);
        assert!(source.len() > 4 * POINTS_PER_TASK);
        let with_threads = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    register(
                        source.cloud(),
                        &target,
                        &Isometry3::identity(),
                        &params(0.05),
                    )
                })
        };
        let bits = |result: &RegistrationResult| {
            result
                .target_from_source
                .to_homogeneous()
                .iter()
                .map(|v| v.to_bits())
                .chain([result.error.to_bits()])
                .collect::<Vec<_>>()
        };
        let one = bits(&with_threads(1));
        for threads in [2, 3, 4] {
            for _ in 0..3 {
                assert_eq!(bits(&with_threads(threads)), one, "{threads} threads");
            }
        }
    }

    #[test]
    fn coarse_to_fine_converges_from_ten_centimetres_and_five_degrees() {
        let truth = Isometry3::from_parts(
            Translation3::new(0.06, -0.05, 0.065),
            UnitQuaternion::from_scaled_axis(
                nalgebra::Vector3::new(1.0, -2.0, 1.5).normalize() * 5f64.to_radians(),
            ),
        );
        assert!(truth.translation.vector.norm() > 0.099);
        let (source, target) = source_and_target(&truth);
        let at_identity = |distance_m: f64| {
            register(
                source.cloud(),
                &target,
                &Isometry3::identity(),
                &params(distance_m),
            )
        };
        let coarse_to_fine_giving_up_below = |fraction: f64| {
            register_coarse_to_fine(
                source.cloud(),
                &target,
                &Isometry3::identity(),
                &[0.1, 0.05, 0.02],
                &params(0.02),
                fraction,
            )
        };
        let fine_only = at_identity(0.02);
        let coarse_to_fine = coarse_to_fine_giving_up_below(0.0);
        assert!(coarse_to_fine.is_success(), "{:?}", coarse_to_fine.failure);
        // Giving up below a fraction no stage reaches stops after the first stage.
        let first_stage = at_identity(0.1);
        let given_up = coarse_to_fine_giving_up_below(1.01);
        assert_eq!(given_up.iterations, first_stage.iterations);
        assert!(given_up.iterations < coarse_to_fine.iterations);
        assert_close(&coarse_to_fine.target_from_source, &truth);
        // The fine distance alone cannot bridge 10 cm: the coarse stages are what make it work.
        let fine_error = (fine_only.target_from_source.inverse() * truth)
            .translation
            .vector
            .norm();
        assert!(!fine_only.is_success() || fine_error > 0.01, "{fine_error}");
    }

    #[test]
    fn degenerate_input_is_a_classified_failure() {
        let target = with_covariances(corner(0.0));
        let initial = Isometry3::translation(0.1, 0.2, 0.3);
        let p = params(0.02);
        // Empty source, and an all-NaN depth image (which yields no points).
        let empty = register(&PointCloud::default(), &target, &initial, &p);
        assert!(matches!(
            empty.failure,
            Some(RegistrationFailure::TooFewSourcePoints { found: 0, .. })
        ));
        assert_eq!(empty.target_from_source, initial);
        let k = geometry::camera::Intrinsics::new(50.0, 50.0, 15.5, 11.5, 32, 24);
        let mut nan_depth = geometry::depth::DepthImage::new(32, 24);
        nan_depth.data.fill(f32::NAN);
        let from_nan = crate::points_from_depth(&nan_depth, &k, 1, 10.0);
        assert!(!register(&from_nan, &target, &initial, &p).is_success());
        // Fewer than six points.
        let five = with_covariances(corner(0.0)[..5].to_vec());
        assert!(matches!(
            register(five.cloud(), &target, &initial, &p).failure,
            Some(RegistrationFailure::TooFewSourcePoints { found: 5, .. })
        ));
        // Missing covariances, empty target.
        let bare = PointCloud::from_positions(corner(0.0));
        assert_eq!(
            register(&bare, &target, &initial, &p).failure,
            Some(RegistrationFailure::MissingSourceCovariances)
        );
        let source = with_covariances(corner(0.0));
        let nothing = PointTree::new(Vec::new()).unwrap();
        assert!(matches!(
            register(source.cloud(), &nothing, &initial, &p).failure,
            Some(RegistrationFailure::TooFewTargetPoints { found: 0, .. })
        ));
        // A target out of reach: no correspondences, and the initial guess comes back untouched.
        let far = register(
            source.cloud(),
            &target,
            &Isometry3::translation(5.0, 0.0, 0.0),
            &p,
        );
        assert!(matches!(
            far.failure,
            Some(RegistrationFailure::TooFewCorrespondences { .. })
        ));
        assert_eq!(
            far.target_from_source,
            Isometry3::translation(5.0, 0.0, 0.0)
        );
        // Non-finite covariances (corrupted input) never produce a pose.
        let mut corrupted = source.cloud().clone();
        corrupted.covariances.fill(Covariance([f32::NAN; 6]));
        let result = register(&corrupted, &target, &Isometry3::identity(), &p);
        assert!(!result.is_success() && result.target_from_source == Isometry3::identity());
    }
}
