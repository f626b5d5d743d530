//! Stage 2: surface normals and FPFH-style local descriptors (after Rusu, Blodow and Beetz, "Fast
//! Point Feature Histograms (FPFH) for 3D registration", ICRA 2009).
//!
//! **Normals.** The normal of a point is the smallest principal axis of its neighbours within
//! the normal radius (a plane fitted by PCA); points with too few neighbours get none and take
//! no further part in matching (isolated outliers, the frayed edge of a scan).
//!
//! **Why the histograms here ignore the normal's sign.** PCA gives a normal up to sign. Rusu's
//! angles (alpha, phi, theta of the Darboux frame) change when a normal flips, so PCL orients
//! every normal towards the sensor first. A merged map has no single sensor position, and the
//! usual substitutes differ between the two maps being registered: orienting towards each map's
//! centroid agrees for the walls of a room seen from inside (the centroid of points on the
//! boundary of a convex room lies inside it) but not for furniture, whose sides face the
//! centroid of one partial map and turn away from another's. Features that disagree on the
//! same surface cannot match. So every angle below is one between *lines*, unchanged by either
//! normal's sign: for a point `p` with normal `n_p` and a neighbour `q` with `n_q`, `d = (q - p)
//! / |q - p|`,
//!
//! ```text
//!     f1 = acos |n_p . d|     angle between p's normal and the line to q   (Rusu's phi)
//!     f2 = acos |n_q . d|     angle between q's normal and that line        (~ alpha)
//!     f3 = acos |n_p . n_q|   angle between the two normals                 (~ theta)
//! ```
//!
//! each in [0, pi/2], binned into 11 equal bins: three 11-bin histograms, 33 values, as in FPFH.
//! What is lost is the distinction between a convex and a concave edge of the same angle (the
//! normal's sign is exactly what says which side is free space); RANSAC copes with the extra
//! ambiguity, and nothing is lost to inconsistent orientation. Angles rather than cosines keep
//! the bins equally sensitive at 0 (coplanar normals) and at pi/2 (the line lies in the plane),
//! where cosines flatten.
//!
//! **SPFH and FPFH.** The simplified histogram (SPFH) of `p` bins the pairs of `p` with every
//! neighbour within the feature radius; each of its three parts is normalised to sum 1. The
//! descriptor (FPFH) is `(SPFH(p) + N(p)) / 2`, where `N(p)` is the sum of the neighbours' SPFHs
//! weighted by `1 / |q - p|`, each part normalised to sum 1 again (PCL's normalisation; Rusu's
//! `1/k` scaling differs only in how much the own histogram weighs). Folding in the neighbours'
//! histograms makes the descriptor see twice the radius for the cost of one radius search.
//!
//! Neighbour lists are sorted by index, so every sum runs in the same order whatever search
//! produced them: the descriptors are bit-identical between runs, thread counts and the
//! kd-tree and brute-force searches (the unit test's reference).

use crate::PointTree;
use crate::covariance::smallest_eigenvector;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

/// Bins per angle.
pub const BINS: usize = 11;
/// Length of a descriptor: three angles times [`BINS`].
pub const DESCRIPTOR_LEN: usize = 3 * BINS;
/// One point's descriptor.
pub type Descriptor = [f32; DESCRIPTOR_LEN];

/// Points per rayon task.
const POINTS_PER_TASK: usize = 256;

/// Every point's neighbours within a radius (the point itself included), indices ascending, in
/// one flat list (compressed rows).
#[derive(Debug, Clone, PartialEq)]
pub struct Neighbourhoods {
    offsets: Vec<usize>,
    indices: Vec<u32>,
}

impl Neighbourhoods {
    /// Builds the rows from per-point lists (each sorted here).
    fn from_lists(lists: Vec<Vec<u32>>) -> Self {
        let mut offsets = Vec::with_capacity(lists.len() + 1);
        offsets.push(0);
        let mut indices = Vec::with_capacity(lists.iter().map(Vec::len).sum());
        for mut list in lists {
            list.sort_unstable();
            indices.extend_from_slice(&list);
            offsets.push(indices.len());
        }
        Self { offsets, indices }
    }

    /// Neighbours of point `i`, ascending.
    pub fn of(&self, i: usize) -> &[u32] {
        &self.indices[self.offsets[i]..self.offsets[i + 1]]
    }

    /// Number of points (rows).
    pub fn len(&self) -> usize {
        self.offsets.len() - 1
    }

    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Neighbourhoods within `radius_m` from the kd-tree of `tree`.
pub fn radius_neighbours(tree: &PointTree, radius_m: f64) -> Neighbourhoods {
    if tree.is_empty() {
        return Neighbourhoods::from_lists(Vec::new());
    }
    let radius_sq = (radius_m * radius_m) as f32;
    let lists = tree
        .positions()
        .par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(|p| {
            tree.kd_tree()
                .query(&[p.x, p.y, p.z])
                .within::<SquaredEuclidean<f32>>(radius_sq)
                .unsorted()
                .execute()
                .iter()
                .map(|n| n.item)
                .collect()
        })
        .collect();
    Neighbourhoods::from_lists(lists)
}

/// Squared distance as the kd-tree computes it (test reference and radius filters).
fn distance_sq(a: &Point3<f32>, b: &Point3<f32>) -> f32 {
    let d = a - b;
    d.x * d.x + d.y * d.y + d.z * d.z
}

/// Neighbourhoods within `radius_m` by comparing every pair: the reference the kd-tree search is
/// tested against.
pub fn brute_force_neighbours(points: &[Point3<f32>], radius_m: f64) -> Neighbourhoods {
    let radius_sq = (radius_m * radius_m) as f32;
    let lists = points
        .par_iter()
        .map(|p| {
            (0..points.len() as u32)
                .filter(|&j| distance_sq(p, &points[j as usize]) <= radius_sq)
                .collect()
        })
        .collect();
    Neighbourhoods::from_lists(lists)
}

/// Unit normal of every point from the neighbours within `radius_m` (taken from `neighbourhoods`,
/// whose radius must be at least as large); `None` with fewer than `min_neighbours` of them.
pub fn estimate_normals(
    points: &[Point3<f32>],
    neighbourhoods: &Neighbourhoods,
    radius_m: f64,
    min_neighbours: usize,
) -> Vec<Option<Vector3<f32>>> {
    let radius_sq = (radius_m * radius_m) as f32;
    (0..points.len())
        .into_par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(|i| {
            let centre = &points[i];
            let near = || {
                neighbourhoods
                    .of(i)
                    .iter()
                    .map(|&j| &points[j as usize])
                    .filter(|q| distance_sq(centre, q) <= radius_sq)
            };
            let count = near().count();
            if count < min_neighbours.max(3) {
                return None;
            }
            let mean = near().fold(Vector3::zeros(), |sum, q| {
                sum + (q.coords - centre.coords).cast::<f64>()
            }) / count as f64;
            let scatter = near().fold(Matrix3::zeros(), |sum, q| {
                let d = (q.coords - centre.coords).cast::<f64>() - mean;
                sum + d * d.transpose()
            });
            if !scatter.iter().all(|v| v.is_finite()) || scatter.trace() <= 0.0 {
                return None;
            }
            Some(smallest_eigenvector(&scatter).cast::<f32>())
        })
        .collect()
}

/// Bin of an angle in [0, pi/2].
#[inline]
fn bin(angle: f32) -> usize {
    ((angle * (BINS as f32 / std::f32::consts::FRAC_PI_2)) as usize).min(BINS - 1)
}

/// The three sign-invariant angles of the pair (p, q); see the module documentation. `None` for
/// coincident points.
#[inline]
pub fn pair_angles(
    p: &Point3<f32>,
    n_p: &Vector3<f32>,
    q: &Point3<f32>,
    n_q: &Vector3<f32>,
) -> Option<[f32; 3]> {
    let d = q - p;
    let length = d.norm();
    if length <= f32::EPSILON {
        return None;
    }
    let d = d / length;
    let line_angle = |c: f32| c.abs().min(1.0).acos();
    Some([
        line_angle(n_p.dot(&d)),
        line_angle(n_q.dot(&d)),
        line_angle(n_p.dot(n_q)),
    ])
}

/// Scales each of the three parts of a histogram to sum 1 (parts that are all zero stay so).
fn normalise_parts(h: &mut Descriptor) {
    for part in h.chunks_exact_mut(BINS) {
        let sum: f32 = part.iter().sum();
        if sum > 0.0 {
            part.iter_mut().for_each(|v| *v /= sum);
        }
    }
}

/// Descriptors of a cloud: which points have one, and the descriptors in the same order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Features {
    /// Indices (into the cloud) of the points with a descriptor, ascending.
    pub indices: Vec<u32>,
    /// One per entry of `indices`: that point's FPFH descriptor (see the module documentation).
    pub descriptors: Vec<Descriptor>,
}

impl Features {
    /// Points with a descriptor.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// True when no point has a descriptor.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }
}

/// SPFH of every point: `None` without a normal or with fewer than `min_neighbours` neighbours
/// with normals within the radius of `neighbourhoods`.
fn simplified_histograms(
    points: &[Point3<f32>],
    normals: &[Option<Vector3<f32>>],
    neighbourhoods: &Neighbourhoods,
    min_neighbours: usize,
) -> Vec<Option<Descriptor>> {
    (0..points.len())
        .into_par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(|i| {
            let n_p = normals[i].as_ref()?;
            let mut h = [0.0f32; DESCRIPTOR_LEN];
            let mut pairs = 0usize;
            for &j in neighbourhoods.of(i) {
                let j = j as usize;
                let Some(n_q) = normals[j].as_ref().filter(|_| j != i) else {
                    continue;
                };
                let Some(angles) = pair_angles(&points[i], n_p, &points[j], n_q) else {
                    continue;
                };
                for (part, angle) in angles.into_iter().enumerate() {
                    h[part * BINS + bin(angle)] += 1.0;
                }
                pairs += 1;
            }
            if pairs < min_neighbours.max(1) {
                return None;
            }
            normalise_parts(&mut h);
            Some(h)
        })
        .collect()
}

/// FPFH descriptors of every point that has an SPFH (see the module documentation).
/// `neighbourhoods` must hold the neighbours within the feature radius.
pub fn compute_features(
    points: &[Point3<f32>],
    normals: &[Option<Vector3<f32>>],
    neighbourhoods: &Neighbourhoods,
    min_neighbours: usize,
) -> Features {
    let spfh = simplified_histograms(points, normals, neighbourhoods, min_neighbours);
    let described: Vec<Option<Descriptor>> = (0..points.len())
        .into_par_iter()
        .with_min_len(POINTS_PER_TASK)
        .map(|i| {
            let own = spfh[i].as_ref()?;
            let mut around = [0.0f32; DESCRIPTOR_LEN];
            let mut weight_sum = 0.0f32;
            for &j in neighbourhoods.of(i) {
                let j = j as usize;
                let Some(theirs) = spfh[j].as_ref().filter(|_| j != i) else {
                    continue;
                };
                let distance = distance_sq(&points[i], &points[j]).sqrt();
                if distance <= f32::EPSILON {
                    continue;
                }
                let weight = 1.0 / distance;
                weight_sum += weight;
                for (sum, v) in around.iter_mut().zip(theirs) {
                    *sum += weight * v;
                }
            }
            let mut descriptor = *own;
            if weight_sum > 0.0 {
                normalise_parts(&mut around);
                for (d, a) in descriptor.iter_mut().zip(&around) {
                    *d = 0.5 * (*d + a);
                }
            }
            Some(descriptor)
        })
        .collect();
    let mut features = Features::default();
    for (i, descriptor) in described.into_iter().enumerate() {
        if let Some(descriptor) = descriptor {
            features.indices.push(i as u32);
            features.descriptors.push(descriptor);
        }
    }
    features
}

/// Normals and descriptors of a downsampled cloud in one go: one radius search at the larger of
/// the two radii serves both.
pub fn describe(
    tree: &PointTree,
    normal_radius_m: f64,
    min_normal_neighbours: usize,
    feature_radius_m: f64,
    min_feature_neighbours: usize,
) -> (Vec<Option<Vector3<f32>>>, Features) {
    let neighbourhoods = radius_neighbours(tree, normal_radius_m.max(feature_radius_m));
    describe_with(
        tree.positions(),
        &neighbourhoods,
        (normal_radius_m, min_normal_neighbours),
        (feature_radius_m, min_feature_neighbours),
    )
}

/// [`describe`] from precomputed neighbourhoods (at the larger radius).
pub fn describe_with(
    points: &[Point3<f32>],
    neighbourhoods: &Neighbourhoods,
    (normal_radius_m, min_normal_neighbours): (f64, usize),
    (feature_radius_m, min_feature_neighbours): (f64, usize),
) -> (Vec<Option<Vector3<f32>>>, Features) {
    let normals = estimate_normals(
        points,
        neighbourhoods,
        normal_radius_m,
        min_normal_neighbours,
    );
    let features = if feature_radius_m >= normal_radius_m {
        compute_features(points, &normals, neighbourhoods, min_feature_neighbours)
    } else {
        // The shared search used the normal radius: narrow it for the histograms.
        let radius_sq = (feature_radius_m * feature_radius_m) as f32;
        let narrowed = Neighbourhoods::from_lists(
            (0..points.len())
                .map(|i| {
                    neighbourhoods
                        .of(i)
                        .iter()
                        .copied()
                        .filter(|&j| distance_sq(&points[i], &points[j as usize]) <= radius_sq)
                        .collect()
                })
                .collect(),
        );
        compute_features(points, &normals, &narrowed, min_feature_neighbours)
    };
    (normals, features)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Isometry3;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points on a bumpy surface plus a box corner: varied normals, a few isolated points.
    fn cloud(seed: u64, n: usize) -> Vec<Point3<f32>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|k| {
                let (x, y): (f32, f32) = (rng.random_range(0.0..1.0), rng.random_range(0.0..1.0));
                match k % 10 {
                    0..=5 => Point3::new(x, y, 0.1 * (4.0 * x).sin() * (3.0 * y).cos()),
                    6 | 7 => Point3::new(x, 0.0, 0.5 * y),
                    8 => Point3::new(0.0, x, 0.5 * y),
                    _ => Point3::new(
                        rng.random_range(-1.0..2.0),
                        rng.random_range(-1.0..2.0),
                        rng.random_range(-1.0..2.0),
                    ),
                }
            })
            .collect()
    }

    #[test]
    fn kd_tree_features_equal_brute_force_features() {
        let points = cloud(3, 3000);
        let tree = PointTree::new(points.clone()).unwrap();
        let (normal_radius, feature_radius) = (0.06, 0.12);
        let searched = radius_neighbours(&tree, feature_radius);
        let brute = brute_force_neighbours(&points, feature_radius);
        assert_eq!(searched, brute);
        let (normals, features) = describe(&tree, normal_radius, 6, feature_radius, 10);
        let (brute_normals, brute_features) =
            describe_with(&points, &brute, (normal_radius, 6), (feature_radius, 10));
        assert_eq!(normals, brute_normals);
        assert_eq!(features, brute_features);
        // Most surface points are described; isolated ones are not.
        assert!(features.len() > 2000, "{}", features.len());
        let scattered = features.indices.iter().filter(|&&i| i % 10 == 9).count();
        assert!(
            scattered < 15,
            "{scattered} of 300 scattered points described"
        );
        // Each part of a descriptor sums to 1.
        for d in &features.descriptors {
            for part in d.chunks_exact(BINS) {
                assert!((part.iter().sum::<f32>() - 1.0).abs() < 1e-4);
            }
        }
        // The narrowed path (feature radius below the normal radius) agrees with a direct
        // search at the feature radius.
        let (_, narrow) = describe(&tree, feature_radius, 6, normal_radius, 10);
        let direct = radius_neighbours(&tree, normal_radius);
        let normals_wide = estimate_normals(&points, &searched, feature_radius, 6);
        assert_eq!(
            narrow,
            compute_features(&points, &normals_wide, &direct, 10)
        );
    }

    #[test]
    fn descriptors_are_invariant_to_rigid_motion_and_normal_sign() {
        let points = cloud(5, 2000);
        let motion = Isometry3::new(
            nalgebra::Vector3::new(3.0, -2.0, 1.0),
            nalgebra::Vector3::new(0.4, -1.2, 2.0),
        );
        let moved: Vec<Point3<f32>> = points
            .iter()
            .map(|p| (motion * p.cast::<f64>()).cast::<f32>())
            .collect();
        let tree = PointTree::new(points.clone()).unwrap();
        let moved_tree = PointTree::new(moved).unwrap();
        let (normals, features) = describe(&tree, 0.06, 6, 0.12, 10);
        let (_, moved_features) = describe(&moved_tree, 0.06, 6, 0.12, 10);
        assert_eq!(features.indices, moved_features.indices);
        let mut largest_difference = 0.0f32;
        for (a, b) in features.descriptors.iter().zip(&moved_features.descriptors) {
            for (x, y) in a.iter().zip(b) {
                largest_difference = largest_difference.max((x - y).abs());
            }
        }
        // Only rounding can move an angle across a bin edge.
        assert!(largest_difference < 0.05, "{largest_difference}");
        // Flipping every other normal changes nothing at all.
        let flipped: Vec<Option<Vector3<f32>>> = normals
            .iter()
            .enumerate()
            .map(|(i, n)| n.map(|n| if i % 2 == 0 { -n } else { n }))
            .collect();
        let neighbourhoods = radius_neighbours(&tree, 0.12);
        assert_eq!(
            compute_features(&points, &flipped, &neighbourhoods, 10),
            features
        );
    }
}
