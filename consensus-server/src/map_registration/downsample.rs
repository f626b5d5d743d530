//! Stage 1: voxel-grid downsampling, one point (the centroid) per occupied voxel.
//!
//! Maps come with wildly different densities (a Gaussian map is dense where the agent lingered,
//! sparse where it passed once); features computed on raw points would describe the sampling as
//! much as the geometry. A voxel grid gives both maps the same, nearly uniform sampling. The
//! centroid rather than the voxel centre keeps the point on the surface (a voxel centre can sit
//! half a voxel off a wall).
//!
//! The voxel grows when a map has more occupied voxels than the caller's budget: registration
//! cost grows with the points, not with the scene, so a large map is described at a coarser
//! scale instead of slowly. Both maps must then use the *same* voxel ([`common_voxel`]), because
//! feature radii are multiples of it.
//!
//! Before the cap is applied, isolated points are removed at the finest voxel: a point with fewer
//! than a plane's worth of neighbours within the normal radius can get no normal, so it can never
//! be described or matched, but it would still take its share of the point budget (in a map
//! with a fifth of its points floating in free space, half of the occupied voxels are such
//! points, and the cap would coarsen the surfaces to make room for them). This assumes the map
//! samples its surfaces at least as finely as the finest voxel, as dense SLAM maps do.
//!
//! Voxels are visited in the order of their integer coordinates, so the output does not depend on
//! the order of the input points.

use std::borrow::Cow;
use std::num::NonZeroUsize;

use kiddo::SquaredEuclidean;
use nalgebra::Point3;
use rayon::prelude::*;
use slam_core::registration::PointTree;

/// Each retry grows the voxel by at least this factor (the estimate from the point count alone
/// can undershoot on clouds that are not surfaces).
const MIN_GROWTH: f64 = 1.05;
/// Retries at most: every retry at least multiplies the voxel by [`MIN_GROWTH`] and, in practice,
/// by the square root of the excess, so two or three suffice.
const MAX_RETRIES: usize = 64;
/// Voxel coordinates are packed 21 bits per axis into one sort key.
const AXIS_BITS: u32 = 21;
const AXIS_CELLS: i64 = 1 << AXIS_BITS;

/// A downsampled cloud and the voxel it was made with.
#[derive(Debug, Clone, PartialEq)]
pub struct Downsampled {
    pub points: Vec<Point3<f32>>,
    pub voxel_m: f64,
}

/// Packed voxel key of every finite point (non-finite points are dropped), with the grid origin at
/// the cloud's minimum corner. `None` when the cloud spans more than 2^21 voxels along an axis
/// (kilometres at centimetre voxels); the caller grows the voxel.
fn voxel_keys(points: &[Point3<f32>], voxel_m: f64) -> Option<Vec<(u64, u32)>> {
    let finite = |p: &&Point3<f32>| p.iter().all(|v| v.is_finite());
    let mut min = [f64::INFINITY; 3];
    for p in points.iter().filter(finite) {
        for axis in 0..3 {
            min[axis] = min[axis].min(p[axis] as f64);
        }
    }
    let inverse = 1.0 / voxel_m;
    let mut keys = Vec::with_capacity(points.len());
    for (index, p) in points.iter().enumerate().filter(|(_, p)| finite(p)) {
        let mut key = 0u64;
        for axis in 0..3 {
            let cell = ((p[axis] as f64 - min[axis]) * inverse).floor() as i64;
            if !(0..AXIS_CELLS).contains(&cell) {
                return None;
            }
            key = (key << AXIS_BITS) | cell as u64;
        }
        keys.push((key, index as u32));
    }
    keys.par_sort_unstable();
    Some(keys)
}

/// Occupied voxels at this voxel size (`usize::MAX` when the grid would overflow its keys).
pub fn occupied_voxels(points: &[Point3<f32>], voxel_m: f64) -> usize {
    match voxel_keys(points, voxel_m) {
        Some(keys) => keys.chunk_by(|a, b| a.0 == b.0).count(),
        None => usize::MAX,
    }
}

/// One centroid per occupied voxel of edge `voxel_m` (metres), in voxel order. Non-finite input
/// points are ignored. Falls back to a larger voxel only when the grid would overflow (see
/// [`voxel_keys`]); use [`downsample_to_cap`] to bound the output size.
pub fn voxel_downsample(points: &[Point3<f32>], voxel_m: f64) -> Downsampled {
    let mut voxel = voxel_m;
    let keys = loop {
        if let Some(keys) = voxel_keys(points, voxel) {
            break keys;
        }
        voxel *= 2.0;
    };
    let centroids = keys
        .chunk_by(|a, b| a.0 == b.0)
        .map(|cell| {
            let sum = cell.iter().fold([0.0f64; 3], |mut sum, &(_, index)| {
                let p = &points[index as usize];
                for axis in 0..3 {
                    sum[axis] += p[axis] as f64;
                }
                sum
            });
            let n = cell.len() as f64;
            Point3::new(
                (sum[0] / n) as f32,
                (sum[1] / n) as f32,
                (sum[2] / n) as f32,
            )
        })
        .collect();
    Downsampled {
        points: centroids,
        voxel_m: voxel,
    }
}

/// The smallest voxel of the sequence `start_voxel_m`, then grown, at which the cloud occupies at
/// most `max_points` voxels. On a surface the count falls with the square of the voxel, so each
/// retry grows it by the square root of the excess (at least [`MIN_GROWTH`]).
pub fn capped_voxel(points: &[Point3<f32>], start_voxel_m: f64, max_points: usize) -> f64 {
    let mut voxel = start_voxel_m;
    for _ in 0..MAX_RETRIES {
        let count = occupied_voxels(points, voxel);
        if count <= max_points.max(1) {
            return voxel;
        }
        let excess = count as f64 / max_points.max(1) as f64;
        voxel *= excess.sqrt().max(MIN_GROWTH);
    }
    voxel
}

/// The voxel both clouds are downsampled with: the larger of their capped voxels, so each ends
/// up with at most `max_points` points and both are sampled alike.
pub fn common_voxel(
    a: &[Point3<f32>],
    b: &[Point3<f32>],
    start_voxel_m: f64,
    max_points: usize,
) -> f64 {
    let (va, vb) = rayon::join(
        || capped_voxel(a, start_voxel_m, max_points),
        || capped_voxel(b, start_voxel_m, max_points),
    );
    va.max(vb)
}

/// Downsamples to at most `max_points` points, growing the voxel from `start_voxel_m` as needed.
pub fn downsample_to_cap(
    points: &[Point3<f32>],
    start_voxel_m: f64,
    max_points: usize,
) -> Downsampled {
    voxel_downsample(points, capped_voxel(points, start_voxel_m, max_points))
}

/// Keeps the points that have at least `min_neighbours` points (themselves included) within
/// `radius_m`. Order is preserved.
pub fn remove_isolated(
    points: Vec<Point3<f32>>,
    radius_m: f64,
    min_neighbours: usize,
) -> Vec<Point3<f32>> {
    let Some(k) = NonZeroUsize::new(min_neighbours) else {
        return points;
    };
    if points.len() < k.get() {
        return Vec::new();
    }
    let tree = PointTree::new(points).expect("voxel centroids are finite");
    let radius_sq = (radius_m * radius_m) as f32;
    let keep: Vec<bool> = tree
        .positions()
        .par_iter()
        .with_min_len(512)
        .map(|p| {
            tree.kd_tree()
                .query(&[p.x, p.y, p.z])
                .nearest_n::<SquaredEuclidean<f32>>(k)
                .execute()
                .last()
                .is_some_and(|farthest| farthest.distance <= radius_sq)
        })
        .collect();
    tree.into_cloud()
        .positions
        .into_iter()
        .zip(keep)
        .filter_map(|(p, keep)| keep.then_some(p))
        .collect()
}

/// Both maps at `voxel_m` without isolated points (fewer than `min_neighbours` within
/// `isolation_radius_voxels` voxels). Returns the two clouds and the voxel used (`voxel_m`
/// unless a map spans too many voxels, see [`voxel_downsample`]).
pub fn clean_pair(
    a: &[Point3<f32>],
    b: &[Point3<f32>],
    voxel_m: f64,
    isolation_radius_voxels: f64,
    min_neighbours: usize,
) -> (Vec<Point3<f32>>, Vec<Point3<f32>>, f64) {
    let clean = |points: &[Point3<f32>]| {
        let fine = voxel_downsample(points, voxel_m);
        let radius = isolation_radius_voxels * fine.voxel_m;
        (
            remove_isolated(fine.points, radius, min_neighbours),
            fine.voxel_m,
        )
    };
    let ((a, voxel_a), (b, voxel_b)) = rayon::join(|| clean(a), || clean(b));
    (a, b, voxel_a.max(voxel_b))
}

/// Two clouds, borrowed or re-downsampled, and their voxel.
pub type CappedPair<'a> = (Cow<'a, [Point3<f32>]>, Cow<'a, [Point3<f32>]>, f64);

/// Both clouds (downsampled at `voxel_m` already) at the smallest common voxel, `voxel_m` or
/// larger, that leaves each with at most `max_points` points (re-downsampling the centroids).
/// Returns the clouds and that voxel; borrowed unchanged when `voxel_m` already does.
pub fn cap_pair<'a>(
    a: &'a [Point3<f32>],
    b: &'a [Point3<f32>],
    voxel_m: f64,
    max_points: usize,
) -> CappedPair<'a> {
    if a.len() <= max_points && b.len() <= max_points {
        return (Cow::Borrowed(a), Cow::Borrowed(b), voxel_m);
    }
    let voxel = common_voxel(a, b, voxel_m, max_points);
    let (a, b) = rayon::join(|| voxel_downsample(a, voxel), || voxel_downsample(b, voxel));
    let voxel = a.voxel_m.max(b.voxel_m);
    (Cow::Owned(a.points), Cow::Owned(b.points), voxel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn centroids_per_voxel_independent_of_input_order() {
        // Two points in one 1 m voxel, one in another, one NaN.
        let points = vec![
            Point3::new(0.1f32, 0.1, 0.1),
            Point3::new(2.5, 0.5, 0.5),
            Point3::new(0.3, 0.5, 0.7),
            Point3::new(f32::NAN, 0.0, 0.0),
        ];
        let down = voxel_downsample(&points, 1.0);
        assert_eq!(down.voxel_m, 1.0);
        assert_eq!(down.points.len(), 2);
        assert!((down.points[0] - Point3::new(0.2, 0.3, 0.4)).norm() < 1e-6);
        assert!((down.points[1] - Point3::new(2.5, 0.5, 0.5)).norm() < 1e-6);
        let mut reversed = points.clone();
        reversed.reverse();
        assert_eq!(voxel_downsample(&reversed, 1.0), down);
        assert!(voxel_downsample(&[], 0.05).points.is_empty());
    }

    #[test]
    fn the_voxel_grows_until_the_cap_holds() {
        // A 4 x 4 m plane sampled every centimetre: 160k points, 6400 voxels of 5 cm.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let points: Vec<Point3<f32>> = (0..160_000)
            .map(|_| {
                Point3::new(
                    rng.random_range(0.0..4.0),
                    rng.random_range(0.0..4.0),
                    rng.random_range(0.0..0.01),
                )
            })
            .collect();
        let fine = downsample_to_cap(&points, 0.05, 10_000);
        assert_eq!(fine.voxel_m, 0.05);
        assert!((6000..=6400).contains(&fine.points.len()));
        let capped = downsample_to_cap(&points, 0.05, 1000);
        assert!(capped.points.len() <= 1000, "{}", capped.points.len());
        // Not grown far beyond what the cap needs (a 4 m plane at 1000 voxels: ~12.6 cm).
        assert!(
            capped.voxel_m > 0.12 && capped.voxel_m < 0.16,
            "{}",
            capped.voxel_m
        );
        let small: Vec<Point3<f32>> = points[..1000].to_vec();
        assert_eq!(common_voxel(&small, &points, 0.05, 1000), capped.voxel_m);
    }

    #[test]
    fn isolated_points_are_removed_before_the_cap() {
        // A 2 x 2 m plane (1600 voxels of 5 cm) and as many points scattered in a 2 m cube.
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut points: Vec<Point3<f32>> = (0..40_000)
            .map(|_| Point3::new(rng.random_range(0.0..2.0), rng.random_range(0.0..2.0), 0.0))
            .collect();
        points.extend((0..1600).map(|_| {
            Point3::new(
                rng.random_range(0.0..2.0),
                rng.random_range(0.0..2.0),
                rng.random_range(0.2..2.2),
            )
        }));
        let (a, b, voxel) = clean_pair(&points, &points[..40_000], 0.05, 2.5, 6);
        assert_eq!(voxel, 0.05);
        assert_eq!(b.len(), 1600);
        // Almost all scattered points are gone (a few have neighbours by chance).
        assert!(a.len() >= 1600 && a.len() < 1700, "{}", a.len());
        // Under the cap nothing changes; below the plane's voxels both grow alike.
        let (same_a, _, same_voxel) = cap_pair(&a, &b, voxel, 2000);
        assert!(matches!(same_a, Cow::Borrowed(_)) && same_voxel == voxel);
        let (a, b, voxel) = cap_pair(&a, &b, voxel, 1000);
        assert!(
            voxel > 0.05 && a.len() <= 1000 && b.len() <= 1000,
            "{voxel}"
        );
        assert!(remove_isolated(vec![Point3::origin(); 3], 0.1, 6).is_empty());
    }
}
