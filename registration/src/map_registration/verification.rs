//! Stages 5 and 6: G-ICP refinement of the RANSAC transform, then the figures the verdict and the
//! pose graph need: overlap, residual and an information matrix of the estimate.
//!
//! **Refinement.** the registration crate's G-ICP, coarse to fine, with plane-like covariances from each map's
//! own neighbours (`PointTree::with_covariances`). G-ICP matches plane to plane, so two maps
//! sampled on different voxel grids align to a fraction of the voxel, which point-to-point
//! matching of centroids could not do. RANSAC's transform is typically within a voxel and a
//! degree or two; the coarse stages pull in from there on the feature-level maps (half their
//! points). The final stage runs on the refinement-level maps, which keep the finest voxel up to
//! their own, larger point budget: when a large map coarsened the feature level, the final
//! stage and the verification still see the finer surfaces, which cuts the rotation error by
//! about a factor of ten (docs/benchmarks.md).
//!
//! **Overlap and residual.** After alignment, a source point overlaps when a target point lies
//! within the finest refinement distance; the overlap fraction counts them relative to the
//! smaller map (two maps can share at most the smaller one's points; with the same voxel grid one
//! point per voxel on each side). The residual is the RMS point-to-plane distance of the
//! overlapping points to their target point's plane (target normals from the feature stage): a
//! point-to-point distance would also measure the half-voxel offset between two samplings of the
//! same surface.
//!
//! **Information.** With `r_i = n_i . (T a_i - b_i)` the point-to-plane residual of an overlapping
//! point and `T <- T Exp(delta)`, `delta = (omega, v)` (rotation first, a right perturbation: the
//! translation in the source frame, the convention of the registration crate's G-ICP and of the pose graph's
//! edge residual), `d r_i / d delta = n_i^T R [-[a_i]x, I]`, and the information is
//! `sum J_i^T J_i / sigma^2` with `sigma` the measured RMS residual (floored). It treats the
//! residuals as independent, which they are not (a map's error is correlated over metres: drift,
//! calibration), so it is an optimistic bound: its inverse is the least uncertainty the overlap
//! allows. It is honest about *which directions* are constrained, which is what the degeneracy
//! check uses: the marginal standard deviations of rotation and of translation at the centre of
//! the overlap (where rotation and translation errors do not mix through a lever arm).
//!
//! **Colour.** When both maps have colours, each overlapping source point is also compared with
//! its target point in chromaticity (`colour`: invariant to exposure): the fraction that agree
//! within a tolerance is the overlap's colour agreement. Surfaces laid onto the same surface
//! agree; a room turned onto itself lays walls, floor and furniture onto other ones, of other
//! colours, which geometry alone cannot see. How much agreement is telling depends on the
//! scene: real cameras' white balance and the offset between the colour and depth images leave
//! well under all points agreeing at the true pose (about half on 7-Scenes), while in a room of
//! few colours many points agree by chance at any pose. So the agreement is compared with the
//! *chance agreement*, that of the same overlapping points paired at random (each source point
//! with the target points of a few overlapping pairs drawn at random):
//! Cohen's kappa, `(agreement - chance) / (1 - chance)`, is 1 for perfect agreement and about 0
//! for colours unrelated to the pairing. A scene of one colour (chance near 1) cannot be judged
//! and is not.
//!
//! Two cameras also differ in white balance (a gain per channel), which moves every
//! chromaticity, greys included: 10 % more red in one agent's images put the true poses of
//! 7-Scenes crops at kappas of 0.02-0.22 (docs/benchmarks.md). So before comparing, the source
//! colours are multiplied by the two maps' relative white balance
//! ([`super::colour::relative_white_balance`], found once per pair of maps, whatever the pose).
//! Gains fitted to each pose's own colour pairs would not do: they bend the colours of a wrong
//! pose towards agreement (a red half of a floor laid onto a blue one agrees after a gain of
//! 1.35), which is what this check must refuse.

use crate::{GicpParams, PointCloud, PointTree, RegistrationResult, RegistrationTarget, register};
use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, RowVector6, Vector3};
use rayon::prelude::*;

use super::colour::{Rgb, chromaticity};

/// Source points per rayon task.
const POINTS_PER_TASK: usize = 512;

/// G-ICP parameters of the refinement (distances in metres).
#[derive(Debug, Clone, PartialEq)]
pub struct RefinementParams {
    /// Correspondence distances of the coarse stages, largest first (on the feature-level maps).
    pub coarse_distances_m: Vec<f64>,
    /// Correspondence distance of the final stage (on the refinement-level maps).
    pub fine_distance_m: f64,
    /// Levenberg-Marquardt iterations per stage at most.
    pub max_iterations: usize,
    /// The final stage converges when an update rotates less than this (radians)...
    pub rotation_epsilon_rad: f64,
    /// ...and translates less than this (metres); the coarse stages use ten times both
    /// (`COARSE_STAGE_EPSILON_FACTOR`).
    pub translation_epsilon_m: f64,
}

/// Source points used by the coarse stages: every n-th (the coarse stages only have to bring the
/// estimate within reach of the final one, which uses every point).
const COARSE_STAGE_POINT_STEP: usize = 2;
/// The coarse stages stop at this multiple of the final convergence thresholds.
const COARSE_STAGE_EPSILON_FACTOR: f64 = 10.0;

/// Coarse-to-fine G-ICP from `initial`: one G-ICP run (registration crate) per coarse distance on the
/// feature-level maps `coarse` (every [`COARSE_STAGE_POINT_STEP`]-th source point, looser
/// convergence thresholds), then one at the fine distance on the refinement-level maps `fine`
/// (every point; the same maps as `coarse` when the feature level was not coarsened). Each
/// stage starts where the previous one ended; a stage that fails with an unusable pose ends the
/// sequence with `initial`. Sources need covariances. No inlier minimum: the verification
/// judges the overlap itself. Iterations are summed over the stages.
pub fn refine(
    coarse: (&PointCloud, &PointTree),
    fine: (&PointCloud, &PointTree),
    initial: &Isometry3<f64>,
    params: &RefinementParams,
) -> RegistrationResult {
    let gicp = |distance: f64, epsilon_factor: f64| GicpParams {
        max_correspondence_m: distance,
        max_iterations: params.max_iterations,
        rotation_epsilon_rad: params.rotation_epsilon_rad * epsilon_factor,
        translation_epsilon_m: params.translation_epsilon_m * epsilon_factor,
        overlap_distance_m: params.fine_distance_m,
        min_inlier_fraction: 0.0,
    };
    let coarse_source = PointCloud {
        positions: coarse
            .0
            .positions
            .iter()
            .step_by(COARSE_STAGE_POINT_STEP)
            .copied()
            .collect(),
        covariances: coarse
            .0
            .covariances
            .iter()
            .step_by(COARSE_STAGE_POINT_STEP)
            .copied()
            .collect(),
        ..PointCloud::default()
    };
    let mut pose = *initial;
    let mut iterations = 0;
    for (stage, &distance) in params.coarse_distances_m.iter().enumerate() {
        let result = register(
            &coarse_source,
            coarse.1,
            &pose,
            &gicp(distance, COARSE_STAGE_EPSILON_FACTOR),
        );
        iterations += result.iterations;
        if result.failure.as_ref().is_some_and(|f| !f.pose_is_usable()) {
            tracing::debug!(stage, failure = ?result.failure, "coarse G-ICP stage failed");
            return RegistrationResult {
                iterations,
                target_from_source: *initial,
                ..result
            };
        }
        pose = result.target_from_source;
    }
    let result = register(fine.0, fine.1, &pose, &gicp(params.fine_distance_m, 1.0));
    let usable = result.failure.as_ref().is_none_or(|f| f.pose_is_usable());
    RegistrationResult {
        iterations: iterations + result.iterations,
        target_from_source: if usable {
            result.target_from_source
        } else {
            *initial
        },
        ..result
    }
}

/// Figures of an aligned pair of maps.
#[derive(Debug, Clone, PartialEq)]
pub struct Overlap {
    /// Source points with a target point within the overlap distance.
    pub overlapping: usize,
    /// `overlapping` over the smaller map's point count, at most 1.
    pub fraction: f64,
    /// RMS point-to-plane distance of the overlapping points with a target normal (metres).
    pub residual_m: f64,
    /// Information of `target_from_source` (6x6, rotation first, right perturbation; see the
    /// module documentation). Zero without overlap.
    pub information: Matrix6<f64>,
    /// Marginal standard deviations at the overlap's centre: the worst rotation direction
    /// (radians)...
    pub rotation_sigma_rad: f64,
    /// ...and the worst translation direction (metres); both infinite when the overlap leaves
    /// a direction unconstrained.
    pub translation_sigma_m: f64,
    /// Overlapping points compared in colour (both with a chromaticity; 0 without colours).
    pub colour_compared: usize,
    /// How many of them agree within the tolerance.
    pub colour_agreeing: usize,
    /// Fraction of the compared points that agree when paired at random (see the module
    /// documentation); NaN when nothing was compared.
    pub colour_chance: f64,
    /// The per-channel gains applied to the source colours before comparing (the maps' relative
    /// white balance; `[1, 1, 1]` without colours).
    pub colour_gains: [f64; 3],
}

/// Random partners per compared source point for the chance agreement.
const CHANCE_SAMPLES: usize = 4;
/// Above this chance agreement the colours cannot tell a right pairing from a random one (a
/// scene of one colour): [`Overlap::colour_kappa`] is NaN.
const UNINFORMATIVE_CHANCE: f64 = 0.9;

impl Overlap {
    /// `colour_agreeing / colour_compared`, NaN when nothing was compared.
    pub fn colour_agreement(&self) -> f64 {
        if self.colour_compared == 0 {
            f64::NAN
        } else {
            self.colour_agreeing as f64 / self.colour_compared as f64
        }
    }

    /// Cohen's kappa of the colour agreement against chance, `(agreement - chance) / (1 -
    /// chance)`: NaN when nothing was compared or chance agreement is above
    /// [`UNINFORMATIVE_CHANCE`].
    pub fn colour_kappa(&self) -> f64 {
        // NaN chance (nothing compared) and uninformative colours alike.
        if self.colour_chance.is_nan() || self.colour_chance > UNINFORMATIVE_CHANCE {
            return f64::NAN;
        }
        (self.colour_agreement() - self.colour_chance) / (1.0 - self.colour_chance)
    }
}

/// A well-mixed 64-bit hash (SplitMix64's finaliser): random partners without a generator.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Whether two chromaticities agree within `tolerance`.
#[inline]
fn agree(a: [f32; 2], b: [f32; 2], tolerance: f32) -> bool {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) <= tolerance * tolerance
}

/// Chromaticities of the colour pairs, the source's with `gains` applied; pairs either of
/// whose colours has none are left out.
fn chromaticity_pairs(pairs: &[(Rgb, Rgb)], gains: [f64; 3]) -> Vec<([f32; 2], [f32; 2])> {
    let gains = gains.map(|g| g as f32);
    pairs
        .iter()
        .filter_map(|(s, t)| {
            let balanced = [s[0] * gains[0], s[1] * gains[1], s[2] * gains[2]];
            Some((chromaticity(&balanced)?, chromaticity(t)?))
        })
        .collect()
}

/// Chance agreement of chromaticity pairs: each source chromaticity compared with the target
/// chromaticity of [`CHANCE_SAMPLES`] pairs drawn at random (a fixed hash of the indices, so
/// the result is deterministic). NaN without pairs.
fn chance_agreement(pairs: &[([f32; 2], [f32; 2])], tolerance: f32) -> f64 {
    let n = pairs.len();
    if n == 0 {
        return f64::NAN;
    }
    let agreeing = (0..n * CHANCE_SAMPLES)
        .into_par_iter()
        .with_min_len(POINTS_PER_TASK)
        .filter(|&k| {
            let a = pairs[k / CHANCE_SAMPLES].0;
            let b = pairs[(mix(k as u64) % n as u64) as usize].1;
            agree(a, b, tolerance)
        })
        .count();
    agreeing as f64 / (n * CHANCE_SAMPLES) as f64
}

/// The colours of both maps (per point, in the order of the points given to
/// [`measure_overlap`]), the chromaticity distance within which two points agree, and the
/// per-channel gains the source colours are multiplied by first (the maps' relative white
/// balance; `[1, 1, 1]` for none).
#[derive(Debug, Clone, Copy)]
pub struct ColourCheck<'a> {
    /// Per source point, its colour.
    pub source: &'a [Rgb],
    /// Per target point, its colour.
    pub target: &'a [Rgb],
    /// Chromaticity distance within which two colours agree.
    pub tolerance: f32,
    /// Per-channel gains applied to the source colours first.
    pub source_gains: [f64; 3],
}

/// Sums of one pass over the source points.
#[derive(Clone)]
struct Sums {
    overlapping: usize,
    planar: usize,
    residual_sq: f64,
    centre: Vector3<f64>,
    /// `sum J^T J` with the Jacobian about the source origin.
    hessian: Matrix6<f64>,
    /// Colours of the overlapping pairs (source, target), in source order.
    colour_pairs: Vec<(Rgb, Rgb)>,
}

impl Sums {
    fn zero() -> Self {
        Self {
            overlapping: 0,
            planar: 0,
            residual_sq: 0.0,
            centre: Vector3::zeros(),
            hessian: Matrix6::zeros(),
            colour_pairs: Vec::new(),
        }
    }

    fn add(mut self, other: Self) -> Self {
        self.overlapping += other.overlapping;
        self.planar += other.planar;
        self.residual_sq += other.residual_sq;
        self.centre += other.centre;
        self.hessian += other.hessian;
        self.colour_pairs.extend(other.colour_pairs);
        self
    }
}

/// Largest eigenvalue of a symmetric 3x3 block, `INFINITY` if it is not finite.
fn largest_eigenvalue(block: &Matrix3<f64>) -> f64 {
    if !block.iter().all(|v| v.is_finite()) {
        return f64::INFINITY;
    }
    block.symmetric_eigenvalues().max()
}

/// What one pass over the source points compares them with: the target map (and its normals)
/// and the colours, the transform placing the source, and the overlap distance.
struct Placement<'a> {
    target: &'a PointTree,
    target_normals: &'a [Option<Vector3<f32>>],
    target_from_source: &'a Isometry3<f64>,
    /// `target_from_source`'s rotation as a matrix.
    rotation: Matrix3<f64>,
    limit_sq: f32,
    colours: Option<ColourCheck<'a>>,
}

impl Placement<'_> {
    /// Adds source point `i` (`a`) to `sums`: whether it overlaps, its colour pair, and with a
    /// target normal its point-to-plane residual and Jacobian.
    fn add_point(&self, sums: &mut Sums, i: usize, a: &Point3<f32>) {
        let a = a.cast::<f64>();
        let moved = self.target_from_source * a;
        let Some((j, _)) = self
            .target
            .nearest_within(&moved.cast::<f32>(), self.limit_sq)
        else {
            return;
        };
        sums.overlapping += 1;
        if let Some(check) = &self.colours
            && let (Some(s), Some(t)) = (check.source.get(i), check.target.get(j as usize))
            && chromaticity(s).is_some()
            && chromaticity(t).is_some()
        {
            sums.colour_pairs.push((*s, *t));
        }
        let Some(normal) = self.target_normals.get(j as usize).copied().flatten() else {
            return;
        };
        let n = normal.cast::<f64>();
        let b = self.target.position(j).cast::<f64>();
        let r = n.dot(&(moved - b));
        sums.planar += 1;
        sums.residual_sq += r * r;
        sums.centre += a.coords;
        // J = n^T R [-[a]x, I] = [(a x R^T n)^T, (R^T n)^T].
        let m = self.rotation.transpose() * n;
        let rot = a.coords.cross(&m);
        let j_row = RowVector6::new(rot.x, rot.y, rot.z, m.x, m.y, m.z);
        sums.hessian += j_row.transpose() * j_row;
    }
}

/// Marginal standard deviations of rotation (radians) and translation (metres) of `information`
/// (about the source origin) re-expressed at `centre`; infinite when it is singular.
fn sigmas_at(information: &Matrix6<f64>, centre: &Vector3<f64>) -> (f64, f64) {
    // Re-expressed at the overlap's centre c: v_c = v + omega x c, so delta_c = A delta with
    // A = [[I, 0], [-[c]x, I]], and the information about c is A^-T H A^-1.
    let mut a_inverse = Matrix6::identity();
    a_inverse
        .fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&centre.cross_matrix());
    let at_centre = a_inverse.transpose() * information * a_inverse;
    let (rotation_sigma_rad, translation_sigma_m) = match at_centre.try_inverse() {
        Some(covariance) => (
            largest_eigenvalue(&covariance.fixed_view::<3, 3>(0, 0).into_owned()).sqrt(),
            largest_eigenvalue(&covariance.fixed_view::<3, 3>(3, 3).into_owned()).sqrt(),
        ),
        None => (f64::INFINITY, f64::INFINITY),
    };
    let sanitise = |s: f64| if s.is_finite() { s } else { f64::INFINITY };
    (sanitise(rotation_sigma_rad), sanitise(translation_sigma_m))
}

/// Overlap, residual and information of `source` placed onto `target` by `target_from_source`,
/// and with `colours` their colour agreement. `target_normals[j]` is target point j's normal
/// (`None`: not used for the residual).
pub fn measure_overlap(
    source: &[Point3<f32>],
    target: &PointTree,
    target_normals: &[Option<Vector3<f32>>],
    target_from_source: &Isometry3<f64>,
    overlap_distance_m: f64,
    sigma_floor_m: f64,
    colours: Option<ColourCheck<'_>>,
) -> Overlap {
    let placement = Placement {
        target,
        target_normals,
        target_from_source,
        rotation: target_from_source
            .rotation
            .to_rotation_matrix()
            .into_inner(),
        limit_sq: (overlap_distance_m * overlap_distance_m) as f32,
        colours,
    };
    let sums = source
        .par_chunks(POINTS_PER_TASK)
        .enumerate()
        .map(|(chunk_index, chunk)| {
            let mut sums = Sums::zero();
            for (offset, a) in chunk.iter().enumerate() {
                placement.add_point(&mut sums, chunk_index * POINTS_PER_TASK + offset, a);
            }
            sums
        })
        .reduce(Sums::zero, Sums::add);
    let colour_gains = colours.map_or([1.0; 3], |check| check.source_gains);
    let chromaticities = chromaticity_pairs(&sums.colour_pairs, colour_gains);
    let tolerance = colours.map_or(0.0, |check| check.tolerance);
    let colour_agreeing = chromaticities
        .iter()
        .filter(|(s, t)| agree(*s, *t, tolerance))
        .count();
    let colour_chance = colours.map_or(f64::NAN, |_| chance_agreement(&chromaticities, tolerance));
    let smaller = source.len().min(target.len());
    let fraction = if smaller == 0 {
        0.0
    } else {
        (sums.overlapping as f64 / smaller as f64).min(1.0)
    };
    let mut overlap = Overlap {
        overlapping: sums.overlapping,
        fraction,
        residual_m: f64::NAN,
        information: Matrix6::zeros(),
        rotation_sigma_rad: f64::INFINITY,
        translation_sigma_m: f64::INFINITY,
        colour_compared: chromaticities.len(),
        colour_agreeing,
        colour_chance,
        colour_gains,
    };
    if sums.planar == 0 {
        return overlap;
    }
    overlap.residual_m = (sums.residual_sq / sums.planar as f64).sqrt();
    let sigma = overlap.residual_m.max(sigma_floor_m);
    overlap.information = sums.hessian / (sigma * sigma);
    let centre = sums.centre / sums.planar as f64;
    (overlap.rotation_sigma_rad, overlap.translation_sigma_m) =
        sigmas_at(&overlap.information, &centre);
    overlap
}

#[cfg(test)]
mod tests {
    use super::super::colour::relative_white_balance;
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A grid of `n` x `n` points with 5 cm spacing on the plane through `origin` spanned by `u`
    /// and `v`.
    fn plane(origin: Vector3<f64>, u: Vector3<f64>, v: Vector3<f64>, n: usize) -> Vec<Point3<f32>> {
        let mut points = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let p = origin + u * (i as f64 * 0.05) + v * (j as f64 * 0.05);
                points.push(Point3::from(p.cast::<f32>()));
            }
        }
        points
    }

    fn normals_of(points: &[Point3<f32>]) -> Vec<Option<Vector3<f32>>> {
        let tree = PointTree::new(points.to_vec()).unwrap();
        let neighbourhoods = super::super::fpfh::radius_neighbours(&tree, 0.12);
        super::super::fpfh::estimate_normals(points, &neighbourhoods, 0.12, 5)
    }

    #[test]
    fn a_single_plane_is_degenerate_three_planes_are_not() {
        let floor = plane(Vector3::zeros(), Vector3::x(), Vector3::y(), 40);
        let mut corner = floor.clone();
        corner.extend(plane(
            Vector3::new(0.0, 0.0, 0.05),
            Vector3::x(),
            Vector3::z(),
            40,
        ));
        corner.extend(plane(
            Vector3::new(0.0, 0.05, 0.05),
            Vector3::y(),
            Vector3::z(),
            40,
        ));
        let pose = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        );
        for (points, degenerate) in [(&floor, true), (&corner, false)] {
            let moved: Vec<Point3<f32>> = points
                .iter()
                .map(|p| (pose * p.cast::<f64>()).cast::<f32>())
                .collect();
            let target = PointTree::new(moved.clone()).unwrap();
            let overlap = measure_overlap(
                points,
                &target,
                &normals_of(&moved),
                &pose,
                0.05,
                0.005,
                None,
            );
            assert_eq!(overlap.colour_compared, 0);
            assert!(overlap.colour_agreement().is_nan());
            assert_eq!(overlap.overlapping, points.len());
            assert!((overlap.fraction - 1.0).abs() < 1e-12);
            assert!(overlap.residual_m < 1e-5, "{}", overlap.residual_m);
            if degenerate {
                assert!(overlap.translation_sigma_m > 1.0, "{overlap:?}");
            } else {
                // 4800 points, 5 mm each: well below a millimetre and a tenth of a degree.
                assert!(overlap.translation_sigma_m < 1e-3, "{overlap:?}");
                assert!(overlap.rotation_sigma_rad < 1e-3, "{overlap:?}");
                assert!(overlap.information.determinant() > 0.0);
            }
        }
        // Placed 20 cm off: no overlap at 5 cm.
        let target = PointTree::new(floor.clone()).unwrap();
        let off = measure_overlap(
            &floor,
            &target,
            &normals_of(&floor),
            &Isometry3::translation(0.0, 0.0, 0.2),
            0.05,
            0.005,
            None,
        );
        assert_eq!(off.overlapping, 0);
        assert!(off.translation_sigma_m.is_infinite());
    }

    #[test]
    fn colour_agreement_sees_a_surface_laid_onto_another() {
        // A floor, red in its west half and blue in its east half, laid onto itself and onto
        // itself turned by 180 degrees about its centre (the same geometry, the colours swapped).
        let floor = plane(Vector3::zeros(), Vector3::x(), Vector3::y(), 40);
        let colours: Vec<Rgb> = floor
            .iter()
            .map(|p| {
                if p.x < 0.975 {
                    [0.6, 0.2, 0.2]
                } else {
                    [0.2, 0.2, 0.6]
                }
            })
            .collect();
        // The target is brighter (another exposure): chromaticity does not change.
        let brighter: Vec<Rgb> = colours.iter().map(|c| c.map(|v| v * 1.4)).collect();
        let target = PointTree::new(floor.clone()).unwrap();
        let check = ColourCheck {
            source: &colours,
            target: &brighter,
            tolerance: 0.05,
            source_gains: [1.0; 3],
        };
        let measure = |pose: &Isometry3<f64>| {
            measure_overlap(
                &floor,
                &target,
                &normals_of(&floor),
                pose,
                0.03,
                0.005,
                Some(check),
            )
        };
        let same = measure(&Isometry3::identity());
        assert_eq!(same.colour_compared, floor.len());
        assert_eq!(same.colour_agreement(), 1.0);
        // Half the points have each colour: half agree by chance.
        assert!((same.colour_chance - 0.5).abs() < 0.05, "{same:?}");
        assert!((same.colour_kappa() - 1.0).abs() < 1e-9);
        let turned = measure(&Isometry3::from_parts(
            Translation3::new(1.95, 1.95, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::PI),
        ));
        assert_eq!(turned.overlapping, floor.len());
        assert_eq!(turned.colour_agreement(), 0.0);
        assert!(turned.colour_kappa() < -0.8, "{turned:?}");
        // A floor of one colour cannot be judged.
        let plain = vec![[0.4f32, 0.3, 0.2]; floor.len()];
        let one_colour = measure_overlap(
            &floor,
            &target,
            &normals_of(&floor),
            &Isometry3::identity(),
            0.03,
            0.005,
            Some(ColourCheck {
                source: &plain,
                target: &plain,
                tolerance: 0.05,
                source_gains: [1.0; 3],
            }),
        );
        assert_eq!(one_colour.colour_agreement(), 1.0);
        assert!(one_colour.colour_kappa().is_nan());
        // Dark colours are not compared.
        let dark = vec![[0.01f32; 3]; floor.len()];
        let unlit = measure_overlap(
            &floor,
            &target,
            &normals_of(&floor),
            &Isometry3::identity(),
            0.03,
            0.005,
            Some(ColourCheck {
                source: &dark,
                ..check
            }),
        );
        assert_eq!(unlit.colour_compared, 0);
    }

    #[test]
    fn another_white_balance_is_corrected_before_colours_are_compared() {
        // A floor of four colours, greys among them; the target seen through another white
        // balance (more red, less blue).
        let floor = plane(Vector3::zeros(), Vector3::x(), Vector3::y(), 40);
        let palette: [Rgb; 4] = [
            [0.5, 0.5, 0.5],
            [0.6, 0.55, 0.45],
            [0.3, 0.45, 0.6],
            [0.55, 0.35, 0.3],
        ];
        let colours: Vec<Rgb> = floor
            .iter()
            .map(|p| palette[((p.x * 2.0) as usize + 2 * (p.y * 2.0) as usize) % 4])
            .collect();
        let balanced: Vec<Rgb> = colours
            .iter()
            .map(|c| [c[0] * 1.15, c[1], c[2] * 0.88])
            .collect();
        let target = PointTree::new(floor.clone()).unwrap();
        let measure = |source_gains: [f64; 3], pose: &Isometry3<f64>| {
            measure_overlap(
                &floor,
                &target,
                &normals_of(&floor),
                pose,
                0.03,
                0.005,
                Some(ColourCheck {
                    source: &colours,
                    target: &balanced,
                    tolerance: 0.05,
                    source_gains,
                }),
            )
        };
        let uncorrected = measure([1.0; 3], &Isometry3::identity());
        assert!(uncorrected.colour_kappa() < 0.5, "{uncorrected:?}");
        // The maps' relative white balance, found from their colours alone.
        let gains = relative_white_balance(&colours, &balanced, 0.3).map(f64::from);
        let [r, g, b] = gains;
        assert!(
            (r / g - 1.15).abs() < 0.03 && (b / g - 0.88).abs() < 0.03,
            "{gains:?}"
        );
        let corrected = measure(gains, &Isometry3::identity());
        assert_eq!(corrected.colour_gains, gains);
        assert!(corrected.colour_kappa() > 0.95, "{corrected:?}");
        // Shifted by a quarter of the floor (other colours laid onto each): still no agreement
        // beyond chance with the gains.
        let shifted = measure(gains, &Isometry3::translation(0.5, 0.0, 0.0));
        assert!(shifted.colour_kappa() < 0.2, "{shifted:?}");
    }
}
