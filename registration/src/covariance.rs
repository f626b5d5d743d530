//! Step 2 of the pipeline: one G-ICP covariance per point.
//!
//! Generalized-ICP (Segal, Haehnel, Thrun 2009) models every point as a sample of a locally planar
//! surface: a covariance that is wide along the surface and thin along its normal. Following the
//! paper (and fast_gicp / small_gicp's "plane" regularisation, which MAC-Ego3D's reference code
//! uses) the covariance of a point's k nearest neighbours is decomposed, C = U S U^T, and its
//! singular values S are replaced by (1, 1, epsilon). Only the *shape* survives: the result is
//! `I - (1 - epsilon) n n^T`, with n the direction of least spread (the surface normal). For a
//! symmetric positive semi-definite matrix the SVD is the eigen-decomposition, so we compute the
//! eigenvector of the smallest eigenvalue.
//!
//! Map Gaussians carry their own shape (rotation and scales); [`Covariance::from_gaussian`] turns
//! them into the same normalised form so that source and target covariances weigh equally in
//! G-ICP's combined covariance `C_target + R C_source R^T`.

use std::num::NonZeroUsize;

use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Point3, Quaternion, SymmetricEigen, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::kdtree::PointTree;
use crate::points::{PixelGrid, PointCloud};

/// Points per rayon task when estimating covariances: large enough that scheduling costs nothing
/// next to the k-NN queries, small enough to balance two to sixteen threads on ~10k points.
const COVARIANCE_CHUNK: usize = 512;

/// A symmetric 3x3 covariance stored as its upper triangle `[xx, xy, xz, yy, yz, zz]` (`f32`:
/// a shape, not a measurement, and half the memory traffic of `f64` in the G-ICP inner loop).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Covariance(pub [f32; 6]);

/// A map Gaussian's parameters that cannot describe a covariance.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GaussianCovarianceError {
    /// A log-scale component is NaN or infinite.
    #[error("log-scale {0:?} is not finite")]
    NonFiniteScale([f32; 3]),
    /// The rotation quaternion (w, x, y, z) is zero, nearly zero or not finite, so it has no
    /// direction to normalise.
    #[error("rotation quaternion (w, x, y, z) = {0:?} has zero or non-finite norm")]
    InvalidRotation([f32; 4]),
}

impl Covariance {
    /// The identity matrix: unit variance in every direction, no preferred shape.
    pub const IDENTITY: Covariance = Covariance([1.0, 0.0, 0.0, 1.0, 0.0, 1.0]);

    /// Stores the upper triangle of `m`; the lower triangle is ignored, so `m` should be
    /// symmetric.
    pub fn from_matrix(m: &Matrix3<f64>) -> Self {
        Self([
            m[(0, 0)] as f32,
            m[(0, 1)] as f32,
            m[(0, 2)] as f32,
            m[(1, 1)] as f32,
            m[(1, 2)] as f32,
            m[(2, 2)] as f32,
        ])
    }

    /// The full symmetric 3x3 matrix.
    pub fn to_matrix(&self) -> Matrix3<f64> {
        let [xx, xy, xz, yy, yz, zz] = self.0.map(f64::from);
        Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz)
    }

    /// The G-ICP plane covariance `I - (1 - epsilon) n n^T` for a surface with unit normal `n`:
    /// variance 1 along the surface, `epsilon` across it.
    pub fn plane(normal: &Vector3<f64>, epsilon: f64) -> Self {
        let n = normal.normalize();
        Self::from_matrix(&(Matrix3::identity() - (1.0 - epsilon) * n * n.transpose()))
    }

    /// G-ICP regularisation of a neighbourhood's scatter matrix: its eigenvalues are replaced by
    /// (1, 1, epsilon), keeping the eigenvectors. `None` when the scatter is not finite.
    pub fn regularised(scatter: &Matrix3<f64>, epsilon: f64) -> Option<Self> {
        if !scatter.iter().all(|v| v.is_finite()) {
            return None;
        }
        Some(Self::plane(&smallest_eigenvector(scatter), epsilon))
    }

    /// Covariance of a map Gaussian, `R diag(exp(log_scale))^2 R^T`, brought to the normalised
    /// G-ICP form: variances divided by the largest one, the smallest floored at
    /// `min_variance_ratio` (pass the tracking `covariance_epsilon`). The floor keeps flat
    /// Gaussians (one scale optimised towards zero) from producing a singular combined covariance.
    ///
    /// `rotation_wxyz` is the quaternion in (w, x, y, z) order, the order of our Gaussian records;
    /// it need not be normalised.
    pub fn from_gaussian(
        log_scale: [f32; 3],
        rotation_wxyz: [f32; 4],
        min_variance_ratio: f64,
    ) -> Result<Self, GaussianCovarianceError> {
        if !log_scale.iter().all(|s| s.is_finite()) {
            return Err(GaussianCovarianceError::NonFiniteScale(log_scale));
        }
        let [w, x, y, z] = rotation_wxyz.map(f64::from);
        let q = Quaternion::new(w, x, y, z);
        let norm = q.norm();
        if !norm.is_finite() || norm < f64::EPSILON {
            return Err(GaussianCovarianceError::InvalidRotation(rotation_wxyz));
        }
        let rotation = UnitQuaternion::from_quaternion(q).to_rotation_matrix();
        // Subtracting the largest log-scale before exponentiating normalises without overflow.
        let largest = log_scale.iter().copied().fold(f32::MIN, f32::max) as f64;
        let variances = Vector3::from(log_scale.map(|s| (2.0 * (s as f64 - largest)).exp()))
            .map(|v| v.max(min_variance_ratio));
        let m =
            rotation.matrix() * Matrix3::from_diagonal(&variances) * rotation.matrix().transpose();
        Ok(Self::from_matrix(&m))
    }
}

/// Relative size below which the closed-form eigenvector is not trusted: the smallest eigenvalue
/// is (nearly) repeated, so its eigenvector is ill-defined by cross products and the iterative
/// solver decides.
const REPEATED_EIGENVALUE_TOLERANCE: f64 = 1e-9;

/// Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix. Closed form (about ten
/// times faster than the iterative solver, which matters at 10k points per frame): the eigenvalue
/// by the trigonometric method (Smith 1961), the eigenvector as the largest cross product of two
/// rows of `A - lambda I` (each row is orthogonal to the eigenvector).
pub fn smallest_eigenvector(a: &Matrix3<f64>) -> Vector3<f64> {
    let off_diagonal = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    if off_diagonal == 0.0 {
        return Vector3::ith(a.diagonal().imin(), 1.0);
    }
    let mean = a.trace() / 3.0;
    let spread = ((a[(0, 0)] - mean).powi(2)
        + (a[(1, 1)] - mean).powi(2)
        + (a[(2, 2)] - mean).powi(2)
        + 2.0 * off_diagonal)
        / 6.0;
    let spread = spread.sqrt();
    let smallest = smallest_eigenvalue_by_newton(a).unwrap_or_else(|| {
        let b = (a - Matrix3::identity() * mean) / spread;
        let half_det = (b.determinant() / 2.0).clamp(-1.0, 1.0);
        let angle = half_det.acos() / 3.0;
        mean + 2.0 * spread * (angle + 2.0 * std::f64::consts::FRAC_PI_3).cos()
    });
    let shifted = a - Matrix3::identity() * smallest;
    let rows = [
        shifted.row(0).transpose(),
        shifted.row(1).transpose(),
        shifted.row(2).transpose(),
    ];
    let best = [
        rows[0].cross(&rows[1]),
        rows[0].cross(&rows[2]),
        rows[1].cross(&rows[2]),
    ]
    .into_iter()
    .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))
    .expect("three candidates");
    let scale = (spread * spread).max(mean * mean);
    if best.norm() > REPEATED_EIGENVALUE_TOLERANCE * scale {
        return best.normalize();
    }
    let eigen = SymmetricEigen::new(*a);
    eigen
        .eigenvectors
        .column(eigen.eigenvalues.imin())
        .into_owned()
}

/// Newton steps allowed before [`smallest_eigenvalue_by_newton`] gives the answer up to the
/// trigonometric method. A surface's scatter (smallest eigenvalue far below the others) needs 3
/// to 5; a nearly isotropic one converges slowly and is better served by the closed form.
const NEWTON_MAX_STEPS: usize = 8;

/// The smallest eigenvalue of a symmetric 3x3 matrix whose eigenvalues are all positive, by
/// Newton's method on the characteristic polynomial from 0; `None` when the eigenvalues are not
/// all positive or Newton has not converged within [`NEWTON_MAX_STEPS`].
///
/// Why: the trigonometric method's `acos` and `cos` were a fifth of the covariance stage. Why it
/// is safe: the characteristic polynomial `p(l) = l^3 - c2 l^2 + c1 l - c0` of a symmetric matrix
/// has three real roots; with `c0, c1, c2 > 0` none is negative (Descartes' rule of signs), and
/// left of its smallest root `p` is increasing and concave, so Newton's steps from 0 approach
/// that root from below without overshooting it.
fn smallest_eigenvalue_by_newton(a: &Matrix3<f64>) -> Option<f64> {
    let c2 = a.trace();
    let c1 = a[(0, 0)] * a[(1, 1)] - a[(0, 1)] * a[(1, 0)] + a[(0, 0)] * a[(2, 2)]
        - a[(0, 2)] * a[(2, 0)]
        + a[(1, 1)] * a[(2, 2)]
        - a[(1, 2)] * a[(2, 1)];
    let c0 = a.determinant();
    if !(c0 > 0.0 && c1 > 0.0 && c2 > 0.0) {
        return None;
    }
    let tolerance = 1e-13 * c2;
    let mut lambda = 0.0f64;
    for _ in 0..NEWTON_MAX_STEPS {
        let value = ((lambda - c2) * lambda + c1) * lambda - c0;
        let slope = (3.0 * lambda - 2.0 * c2) * lambda + c1;
        let step = value / slope;
        lambda -= step;
        if step.abs() <= tolerance {
            return lambda.is_finite().then_some(lambda);
        }
    }
    None
}

/// Estimates every point's G-ICP covariance from its `neighbours` nearest neighbours (the point
/// itself included, as fast_gicp / small_gicp count it), in parallel with rayon.
///
/// A point of a cloud smaller than `neighbours` uses the whole cloud. Neighbourhoods whose scatter
/// is degenerate (fewer than 3 distinct points) still get a valid, positive-definite covariance: the
/// eigen-decomposition picks some direction as the "normal", and the regularisation keeps the
/// result invertible, so G-ICP never divides by zero.
///
/// **Image-grid search.** For a cloud back-projected from a depth image
/// ([`super::points::PointCloud::grid`]), the candidates are first taken from the
/// `(2 radius + 1)^2` grid cells around the point, for each radius of
/// [`GRID_WINDOW_RADII_CELLS`] until one answer is *certified* exact: a point outside the
/// window lies on a camera ray at least `(radius + 1) stride` pixels away, and every point on
/// such a ray is at least `z (radius + 1) stride / (f_max |m|_max)` from the query (z: the
/// query's depth, f_max: the larger focal length, |m|_max: the longest normalised ray, at an
/// image corner; see [`outside_window_distance`]). When the k-th candidate is no farther than
/// that bound, no point outside the window can be among the k nearest, so the result equals
/// the kd-tree's (up to ties); otherwise (grazing surfaces, sparse depth) the kd-tree answers.
/// The semantics are exactly k-NN; the grid only makes the common case cheap.
pub fn estimate_covariances(tree: &PointTree, neighbours: usize, epsilon: f64) -> Vec<Covariance> {
    let from_grid = covariances_from_grid(tree.cloud(), neighbours, epsilon);
    complete_from_tree(tree, from_grid, neighbours, epsilon)
}

/// The image-grid half of [`estimate_covariances`]: the covariance of every point whose k
/// nearest neighbours the grid certifies, `None` for the others (and for every point of a cloud
/// without a grid). It needs no kd-tree, so [`PointTree::with_covariances`] runs it while the
/// tree is being built.
pub(crate) fn covariances_from_grid(
    cloud: &PointCloud,
    neighbours: usize,
    epsilon: f64,
) -> Vec<Option<Covariance>> {
    let positions = &cloud.positions;
    let mut covariances = vec![None; positions.len()];
    let k = neighbours.min(positions.len());
    let Some(grid) = cloud
        .grid
        .filter(|_| k > 0 && cloud.pixels.len() == positions.len())
        .map(|grid| GridIndex::new(grid, &cloud.pixels))
    else {
        return covariances;
    };
    covariances
        .par_chunks_mut(COVARIANCE_CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| {
            let mut candidates: Vec<(f32, u32)> = Vec::new();
            for (offset, covariance) in out.iter_mut().enumerate() {
                let index = chunk * COVARIANCE_CHUNK + offset;
                if grid.nearest(index, positions, &cloud.pixels, k, &mut candidates) {
                    *covariance = Some(of_neighbourhood(
                        positions,
                        &positions[index],
                        candidates.iter().map(|&(_, index)| index),
                        epsilon,
                    ));
                }
            }
        });
    covariances
}

/// The kd-tree half of [`estimate_covariances`]: `partial` (from [`covariances_from_grid`]) with
/// each missing covariance estimated from the tree's k nearest neighbours.
pub(crate) fn complete_from_tree(
    tree: &PointTree,
    partial: Vec<Option<Covariance>>,
    neighbours: usize,
    epsilon: f64,
) -> Vec<Covariance> {
    let positions = tree.positions();
    let Some(k) = NonZeroUsize::new(neighbours.min(positions.len())) else {
        return Vec::new();
    };
    partial
        .into_par_iter()
        .with_min_len(COVARIANCE_CHUNK)
        .enumerate()
        .map(|(index, covariance)| {
            covariance.unwrap_or_else(|| {
                let centre = positions[index];
                let found = tree
                    .kd_tree()
                    .query(&[centre.x, centre.y, centre.z])
                    .nearest_n::<SquaredEuclidean<f32>>(k)
                    .execute();
                of_neighbourhood(positions, &centre, found.iter().map(|n| n.item), epsilon)
            })
        })
        .collect()
}

/// The regularised covariance of `centre`'s neighbourhood (indices into `positions`).
fn of_neighbourhood(
    positions: &[Point3<f32>],
    centre: &Point3<f32>,
    neighbours: impl Iterator<Item = u32>,
    epsilon: f64,
) -> Covariance {
    let neighbourhood = neighbours.map(|i| &positions[i as usize]);
    Covariance::regularised(&scatter(centre, neighbourhood), epsilon)
        .unwrap_or(Covariance::IDENTITY)
}

/// Half-widths of the image-grid windows searched before the kd-tree, in grid cells, smallest
/// first. With k = 10 the 10th neighbour on a surface facing the camera is 2 cells away: the
/// certificate of a radius-2 window reaches about 2.5 cells at the image centre for a 640x480,
/// f = 585 camera, which answers most points of frontal surfaces from 25 candidates; radius 3
/// (49 candidates, certificate ~3.3 cells) answers surfaces up to roughly 50 degrees from
/// frontal. Trying the small window first makes the points + covariances stage about a quarter
/// faster than radius 3 alone (timings: docs/benchmarks.md).
pub const GRID_WINDOW_RADII_CELLS: [usize; 2] = [2, 3];

/// Lower bound on the distance from a point at depth `z` to any point seen through a pixel at
/// least `pixel_gap` pixels away (Chebyshev distance in the image), for a camera whose longest
/// normalised ray `(x/z, y/z, 1)` has length `longest_ray`.
///
/// Derivation: for normalised rays m1, m2 (z-component 1), |m1 x m2| >= |m2 - m1| because m2 - m1
/// lies in the plane z = 0; so sin(angle) >= |m2 - m1| / (|m1| |m2|). A point p on ray m1 is at
/// least |p| sin(angle) = z |m1| sin(angle) >= z |m2 - m1| / |m2| from the whole ray m2 (for
/// angles below 90 degrees, true for any real camera), and |m2 - m1| >= pixel_gap / f_max.
pub fn outside_window_distance(z: f32, pixel_gap: f32, max_focal: f32, longest_ray: f32) -> f32 {
    z * pixel_gap / (max_focal * longest_ray)
}

/// Grid cell -> point index of a cloud sampled on a pixel grid.
struct GridIndex {
    grid: PixelGrid,
    columns: usize,
    rows: usize,
    point_at: Vec<u32>,
    /// `outside_window_distance` per metre of depth, per window of `GRID_WINDOW_RADII_CELLS`.
    certificate_per_metre: [f32; GRID_WINDOW_RADII_CELLS.len()],
}

impl GridIndex {
    const EMPTY: u32 = u32::MAX;

    fn new(grid: PixelGrid, pixels: &[u32]) -> Self {
        let (columns, rows) = grid.dimensions();
        let mut point_at = vec![Self::EMPTY; columns * rows];
        for (index, &pixel) in pixels.iter().enumerate() {
            let (column, row) = grid.cell_of_pixel(pixel);
            point_at[row * columns + column] = index as u32;
        }
        let k = &grid.intrinsics;
        let corner_offsets = [(-0.5 - k.cx) / k.fx, (k.width as f64 - 0.5 - k.cx) / k.fx];
        let row_offsets = [(-0.5 - k.cy) / k.fy, (k.height as f64 - 0.5 - k.cy) / k.fy];
        let longest_ray = corner_offsets
            .iter()
            .flat_map(|x| {
                row_offsets
                    .iter()
                    .map(move |y| (x * x + y * y + 1.0).sqrt())
            })
            .fold(1.0, f64::max);
        let certificate_per_metre = GRID_WINDOW_RADII_CELLS.map(|radius| {
            outside_window_distance(
                1.0,
                ((radius + 1) * grid.stride) as f32,
                k.fx.max(k.fy) as f32,
                longest_ray as f32,
            )
        });
        Self {
            grid,
            columns,
            rows,
            point_at,
            certificate_per_metre,
        }
    }

    /// Fills `found` with the k nearest neighbours of point `index` from the smallest grid window
    /// that certifies them and returns true; false when no window does (see
    /// [`estimate_covariances`]).
    fn nearest(
        &self,
        index: usize,
        positions: &[Point3<f32>],
        pixels: &[u32],
        k: usize,
        found: &mut Vec<(f32, u32)>,
    ) -> bool {
        GRID_WINDOW_RADII_CELLS
            .iter()
            .zip(self.certificate_per_metre)
            .any(|(&radius, certificate)| {
                self.nearest_in_window(index, positions, pixels, k, radius, certificate, found)
            })
    }

    /// Fills `found` with the k nearest neighbours of point `index` within `radius` cells and
    /// returns true when the answer is certified exact by `certificate_per_metre`.
    #[allow(
        clippy::too_many_arguments,
        reason = "the inner neighbour search: its inputs and the reused output buffer"
    )]
    fn nearest_in_window(
        &self,
        index: usize,
        positions: &[Point3<f32>],
        pixels: &[u32],
        k: usize,
        radius: usize,
        certificate_per_metre: f32,
        found: &mut Vec<(f32, u32)>,
    ) -> bool {
        let centre = positions[index];
        let (column, row) = self.grid.cell_of_pixel(pixels[index]);
        // The answer is certified when k candidates lie within the bound: then the k nearest in
        // the window are the k nearest overall. So only candidates within it are kept.
        let bound = certificate_per_metre * centre.z;
        let bound_sq = bound * bound;
        found.clear();
        for r in row.saturating_sub(radius)..(row + radius + 1).min(self.rows) {
            let cells = &self.point_at[r * self.columns..(r + 1) * self.columns];
            for &other in
                &cells[column.saturating_sub(radius)..(column + radius + 1).min(self.columns)]
            {
                if other != Self::EMPTY {
                    let distance_sq = (positions[other as usize] - centre).norm_squared();
                    if distance_sq <= bound_sq {
                        found.push((distance_sq, other));
                    }
                }
            }
        }
        if found.len() < k {
            return false;
        }
        keep_nearest(found, k);
        true
    }
}

/// Keeps the `k` nearest of `(squared distance, index)` candidates. Squared distances are
/// non-negative, and the bits of non-negative floats order as the floats do: comparing the bits
/// as integers makes the same comparisons as a float comparison (so the same selection, in the
/// same order: the covariance sums its neighbours in that order) and costs less.
fn keep_nearest(found: &mut Vec<(f32, u32)>, k: usize) {
    if found.len() > k {
        found.select_nth_unstable_by_key(k - 1, |&(distance_sq, _)| distance_sq.to_bits());
        found.truncate(k);
    }
}

/// Scatter (sample covariance times count) of a neighbourhood, accumulated in `f64` relative to
/// `centre` so that points metres from the origin keep their millimetre differences.
fn scatter<'a>(
    centre: &Point3<f32>,
    neighbourhood: impl Iterator<Item = &'a Point3<f32>>,
) -> Matrix3<f64> {
    let mut count = 0.0;
    let mut sum = Vector3::<f64>::zeros();
    let mut sum_outer = Matrix3::<f64>::zeros();
    for p in neighbourhood {
        let d = (p - centre).cast::<f64>();
        count += 1.0;
        sum += d;
        sum_outer += d * d.transpose();
    }
    if count == 0.0 {
        return Matrix3::zeros();
    }
    let mean = sum / count;
    sum_outer - count * mean * mean.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;

    fn eigenvalues(c: &Covariance) -> Vector3<f64> {
        let mut e = SymmetricEigen::new(c.to_matrix()).eigenvalues;
        e.as_mut_slice().sort_by(f64::total_cmp);
        e
    }

    #[test]
    fn covariances_of_a_plane_are_plane_like() {
        // A tilted, slightly noisy plane: every covariance must be thin along the plane normal.
        let normal = Vector3::new(0.2, -0.3, 1.0).normalize();
        let tangent_u = normal.cross(&Vector3::x()).normalize();
        let tangent_v = normal.cross(&tangent_u);
        let positions: Vec<Point3<f32>> = (0..30)
            .flat_map(|i| (0..30).map(move |j| (i, j)))
            .map(|(i, j)| {
                let wobble = 1e-4 * ((i * 7 + j * 13) % 5) as f64;
                let p = Vector3::new(0.5, -0.2, 2.0)
                    + tangent_u * (i as f64 * 0.01)
                    + tangent_v * (j as f64 * 0.01)
                    + normal * wobble;
                Point3::from(p.cast::<f32>())
            })
            .collect();
        let tree = PointTree::new(positions).unwrap();
        let epsilon = 1e-3;
        let covariances = estimate_covariances(&tree, 10, epsilon);
        assert_eq!(covariances.len(), 900);
        for c in &covariances {
            let e = eigenvalues(c);
            assert!((e[0] - epsilon).abs() < 1e-5, "eigenvalues {e:?}");
            assert!((e[1] - 1.0).abs() < 1e-5 && (e[2] - 1.0).abs() < 1e-5);
            let along_normal = normal.dot(&(c.to_matrix() * normal));
            assert!(along_normal < 2.0 * epsilon, "{along_normal}");
        }
    }

    #[test]
    fn closed_form_eigenvector_matches_the_iterative_solver() {
        for (i, values) in [
            [1e-4, 2e-4, 3e-4],
            [1.0, 1.0, 1e-3],
            [5e-3, 5e-3, 5e-3],
            [0.0, 1.0, 2.0],
        ]
        .into_iter()
        .enumerate()
        {
            let rotation = Rotation3::from_euler_angles(0.3 * i as f64, -0.7, 1.1);
            let a = rotation.matrix()
                * Matrix3::from_diagonal(&Vector3::from(values))
                * rotation.matrix().transpose();
            let v = smallest_eigenvector(&a);
            assert!((v.norm() - 1.0).abs() < 1e-9);
            let smallest = values.iter().copied().fold(f64::INFINITY, f64::min);
            // Rayleigh quotient: the vector lies in the smallest eigenvalue's eigenspace.
            assert!(
                (v.dot(&(a * v)) - smallest).abs() < 1e-9 * (1.0 + smallest),
                "{values:?}"
            );
        }
        assert_eq!(
            smallest_eigenvector(&Matrix3::from_diagonal(&Vector3::new(2.0, 1.0, 3.0))),
            Vector3::y()
        );
    }

    /// Newton's smallest eigenvalue agrees with the iterative solver on surface-like scatters
    /// (where it must answer: that is the fast path), and declines what it cannot answer safely
    /// (a zero or negative eigenvalue, a nearly isotropic scatter it may not finish in time).
    #[test]
    fn newton_smallest_eigenvalue_matches_the_iterative_solver() {
        let scatter = |values: [f64; 3], i: usize| {
            let rotation =
                Rotation3::from_euler_angles(0.37 * i as f64, -0.7 + 0.1 * i as f64, 1.1);
            rotation.matrix()
                * Matrix3::from_diagonal(&Vector3::from(values))
                * rotation.matrix().transpose()
        };
        let surfaces = [
            [1e-6, 2e-3, 3e-3],
            [2e-5, 1e-3, 1e-3],
            [1e-4, 0.5, 0.9],
            [3e-9, 4e-4, 9e-4],
            [1e-3, 4e-3, 2e-2],
        ];
        for (i, values) in surfaces.into_iter().enumerate() {
            let a = scatter(values, i);
            let newton = smallest_eigenvalue_by_newton(&a)
                .unwrap_or_else(|| panic!("{values:?}: a surface's scatter takes the fast path"));
            let truth = SymmetricEigen::new(a).eigenvalues.min();
            assert!(
                (newton - truth).abs() <= 1e-12 * a.trace(),
                "{values:?}: newton {newton:e}, solver {truth:e}"
            );
            let v = smallest_eigenvector(&a);
            assert!(
                (v.dot(&(a * v)) - truth).abs() <= 1e-9 * a.trace(),
                "{values:?}"
            );
        }
        // A zero eigenvalue: rounding may leave the determinant either side of zero; an answer,
        // if any, is that zero.
        let zero = smallest_eigenvalue_by_newton(&scatter([0.0, 1.0, 2.0], 1));
        assert!(zero.is_none_or(|l| l.abs() <= 1e-12 * 3.0), "{zero:?}");
        for values in [[-1e-6, 1.0, 2.0], [0.0, 0.0, 0.0]] {
            assert_eq!(
                smallest_eigenvalue_by_newton(&scatter(values, 1)),
                None,
                "{values:?}"
            );
        }
        // A nearly isotropic scatter converges too slowly and is left to the closed form, which
        // still gives an eigenvector of the smallest eigenvalue.
        let a = scatter([1.0, 1.0 + 1e-7, 1.0 + 2e-7], 2);
        assert_eq!(smallest_eigenvalue_by_newton(&a), None);
        let v = smallest_eigenvector(&a);
        assert!((v.norm() - 1.0).abs() < 1e-9);
    }

    /// The selection keeps what a float comparison keeps, in the same order, ties included
    /// (distances repeat, and zero and subnormal distances occur): the covariance sums the
    /// neighbours in that order, so any other order would change its last bits.
    #[test]
    fn keep_nearest_selects_as_a_float_comparison_would() {
        let levels = [0.0f32, 1e-45, 1e-38, 2.5e-5, 4e-4, 1.0, 3.0e7];
        for (n, k) in [
            (5, 10),
            (10, 10),
            (16, 10),
            (25, 10),
            (49, 10),
            (49, 1),
            (30, 29),
        ] {
            for seed in 0..20u32 {
                let candidates: Vec<(f32, u32)> = (0..n as u32)
                    .map(|i| {
                        let pick = i.wrapping_mul(2_654_435_761).wrapping_add(seed * 97) >> 7;
                        (levels[pick as usize % levels.len()], i)
                    })
                    .collect();
                let mut by_float = candidates.clone();
                if by_float.len() > k {
                    by_float.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
                    by_float.truncate(k);
                }
                let mut kept = candidates;
                keep_nearest(&mut kept, k);
                assert_eq!(kept, by_float, "n {n} k {k} seed {seed}");
            }
        }
    }

    #[test]
    fn image_grid_neighbours_match_the_kd_tree() {
        use crate::points::points_from_depth;
        let k = geometry::camera::Intrinsics::new(585.0, 585.0, 320.0, 240.0, 640, 480);
        // A wavy surface with a step and a grazing slope: grid answers and fallbacks both occur.
        let mut depth = geometry::depth::DepthImage::new(640, 480);
        for v in 0..480 {
            for u in 0..640 {
                let (x, y) = (u as f32 / 640.0, v as f32 / 480.0);
                let z = if u < 200 {
                    1.0 + 3.0 * x
                } else {
                    2.0 + 0.1 * (9.0 * y).sin()
                };
                depth.data[v * 640 + u] = if (u * 7 + v * 13) % 29 == 0 { 0.0 } else { z };
            }
        }
        let cloud = points_from_depth(&depth, &k, 5, 10.0);
        let tree = PointTree::from_cloud(cloud.clone()).unwrap();
        let grid = GridIndex::new(cloud.grid.unwrap(), &cloud.pixels);
        let (mut certified, mut found) = (0, Vec::new());
        let neighbours = NonZeroUsize::new(10).unwrap();
        for (index, p) in cloud.positions.iter().enumerate() {
            if !grid.nearest(index, &cloud.positions, &cloud.pixels, 10, &mut found) {
                continue;
            }
            certified += 1;
            // Same neighbour distances as the kd-tree (the sets may differ only among ties).
            let mut from_grid: Vec<f32> = found.iter().map(|f| f.0).collect();
            from_grid.sort_by(f32::total_cmp);
            let from_tree: Vec<f32> = tree
                .kd_tree()
                .query(&[p.x, p.y, p.z])
                .nearest_n::<SquaredEuclidean<f32>>(neighbours)
                .execute()
                .iter()
                .map(|n| n.distance)
                .collect();
            assert_eq!(from_grid, from_tree, "point {index}");
        }
        // Most points are answered by the grid, and the grazing slope needs the fallback.
        assert!(
            certified * 10 > cloud.len() * 7,
            "{certified} of {}",
            cloud.len()
        );
        assert!(certified < cloud.len());
    }

    #[test]
    fn gaussian_covariance_is_normalised_floored_and_rotated() {
        let rotation = Rotation3::from_euler_angles(0.3, -0.5, 1.1);
        let q = UnitQuaternion::from_rotation_matrix(&rotation);
        let wxyz = [q.w as f32, q.i as f32, q.j as f32, q.k as f32];
        // Scales 4 cm, 2 cm and 0.01 mm: the last must be floored.
        let log_scale = [0.04f32.ln(), 0.02f32.ln(), 1e-5f32.ln()];
        let c = Covariance::from_gaussian(log_scale, wxyz, 1e-3).unwrap();
        let local = rotation.matrix().transpose() * c.to_matrix() * rotation.matrix();
        let expected = Matrix3::from_diagonal(&Vector3::new(1.0, 0.25, 1e-3));
        assert!((local - expected).abs().max() < 1e-5, "{local}");
        assert!(Covariance::from_gaussian([0.0; 3], [0.0; 4], 1e-3).is_err());
        assert!(Covariance::from_gaussian([f32::NAN, 0.0, 0.0], wxyz, 1e-3).is_err());
    }

    #[test]
    fn tiny_clouds_still_get_invertible_covariances() {
        let tree =
            PointTree::new(vec![Point3::new(0.0, 0.0, 1.0), Point3::new(0.1, 0.0, 1.0)]).unwrap();
        let covariances = estimate_covariances(&tree, 10, 1e-3);
        assert_eq!(covariances.len(), 2);
        for c in &covariances {
            assert!(c.to_matrix().determinant() > 1e-4);
        }
    }
}
