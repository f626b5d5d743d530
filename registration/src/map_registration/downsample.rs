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
//!
//! Colours, when a map has them, travel with their points: a voxel's colour is the mean of its
//! points' colours (as its position is their centroid), and removing a point removes its colour.

use std::borrow::Cow;
use std::num::NonZeroUsize;

use crate::PointTree;
use kiddo::SquaredEuclidean;
use nalgebra::Point3;
use rayon::prelude::*;

use super::colour::Rgb;

/// Each retry grows the voxel by at least this factor (the estimate from the point count alone
/// can undershoot on clouds that are not surfaces).
const MIN_GROWTH: f64 = 1.05;
/// Retries at most: every retry at least multiplies the voxel by [`MIN_GROWTH`] and, in practice,
/// by the square root of the excess, so two or three suffice.
const MAX_RETRIES: usize = 64;
/// Voxel coordinates are packed 21 bits per axis into one sort key.
const AXIS_BITS: u32 = 21;
const AXIS_CELLS: i64 = 1 << AXIS_BITS;

/// Points and, optionally, one colour per point.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Cloud {
    /// Positions in metres, in the map's frame.
    pub points: Vec<Point3<f32>>,
    /// As many as `points` when present.
    pub colours: Option<Vec<Rgb>>,
}

impl Cloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the cloud has no points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points whose entry of `keep` is true, with their colours.
    pub fn filtered(self, keep: &[bool]) -> Self {
        fn pick<T>(items: Vec<T>, keep: &[bool]) -> Vec<T> {
            items
                .into_iter()
                .zip(keep)
                .filter_map(|(item, &keep)| keep.then_some(item))
                .collect()
        }
        Self {
            points: pick(self.points, keep),
            colours: self.colours.map(|c| pick(c, keep)),
        }
    }
}

/// A downsampled cloud and the voxel it was made with.
#[derive(Debug, Clone, PartialEq)]
pub struct Downsampled {
    /// One centroid per occupied voxel, in the order of the voxels' integer coordinates.
    pub points: Vec<Point3<f32>>,
    /// Mean colour per voxel, when the input had colours.
    pub colours: Option<Vec<Rgb>>,
    /// Voxel edge used (metres).
    pub voxel_m: f64,
}

impl Downsampled {
    /// The points and colours, without the voxel size.
    pub fn into_cloud(self) -> Cloud {
        Cloud {
            points: self.points,
            colours: self.colours,
        }
    }
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
    voxel_downsample_coloured(points, None, voxel_m)
}

/// [`voxel_downsample`] with a colour per point (`colours`, as many as `points`): each voxel
/// also gets the mean colour of its points.
///
/// # Panics
/// When `colours` and `points` differ in length.
pub fn voxel_downsample_coloured(
    points: &[Point3<f32>],
    colours: Option<&[Rgb]>,
    voxel_m: f64,
) -> Downsampled {
    if let Some(colours) = colours {
        assert_eq!(colours.len(), points.len(), "one colour per point");
    }
    let mut voxel = voxel_m;
    let keys = loop {
        if let Some(keys) = voxel_keys(points, voxel) {
            break keys;
        }
        voxel *= 2.0;
    };
    let cells = || keys.chunk_by(|a, b| a.0 == b.0);
    let mean = |cell: &[(u64, u32)], value: &dyn Fn(usize) -> [f32; 3]| {
        let sum = cell.iter().fold([0.0f64; 3], |mut sum, &(_, index)| {
            let v = value(index as usize);
            for axis in 0..3 {
                sum[axis] += v[axis] as f64;
            }
            sum
        });
        let n = cell.len() as f64;
        sum.map(|s| (s / n) as f32)
    };
    let centroids = cells()
        .map(|cell| Point3::from(mean(cell, &|i| points[i].coords.into())))
        .collect();
    let colours = colours.map(|colours| cells().map(|cell| mean(cell, &|i| colours[i])).collect());
    Downsampled {
        points: centroids,
        colours,
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

/// Whether each point has at least `min_neighbours` points (itself included) within `radius_m`.
pub fn not_isolated(points: &[Point3<f32>], radius_m: f64, min_neighbours: usize) -> Vec<bool> {
    let Some(k) = NonZeroUsize::new(min_neighbours) else {
        return vec![true; points.len()];
    };
    if points.len() < k.get() {
        return vec![false; points.len()];
    }
    let tree = PointTree::new(points.to_vec()).expect("voxel centroids are finite");
    let radius_sq = (radius_m * radius_m) as f32;
    tree.positions()
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
        .collect()
}

/// Keeps the points that have at least `min_neighbours` points (themselves included) within
/// `radius_m`. Order is preserved.
pub fn remove_isolated(
    points: Vec<Point3<f32>>,
    radius_m: f64,
    min_neighbours: usize,
) -> Vec<Point3<f32>> {
    let keep = not_isolated(&points, radius_m, min_neighbours);
    Cloud {
        points,
        colours: None,
    }
    .filtered(&keep)
    .points
}

/// A map to register: its points and, optionally, a colour per point (RGB in `[0, 1]`, see
/// `colour`). Plain point slices convert into it without colours.
#[derive(Debug, Clone, Copy)]
pub struct MapPoints<'a> {
    /// Positions in metres, in the map's own frame.
    pub points: &'a [Point3<f32>],
    /// As many as `points` when present (see [`MapPoints::coloured`]).
    pub colours: Option<&'a [Rgb]>,
}

impl<'a> MapPoints<'a> {
    /// Points without colours.
    pub fn new(points: &'a [Point3<f32>]) -> Self {
        Self {
            points,
            colours: None,
        }
    }

    /// Points with their colours; colours of another length than the points are ignored (with
    /// a warning), so the map is registered on its geometry alone.
    pub fn coloured(points: &'a [Point3<f32>], colours: Option<&'a [Rgb]>) -> Self {
        let colours = colours.filter(|c| {
            let matches = c.len() == points.len();
            if !matches {
                tracing::warn!(
                    points = points.len(),
                    colours = c.len(),
                    "map colours ignored: not one per point"
                );
            }
            matches
        });
        Self { points, colours }
    }
}

impl<'a> From<&'a [Point3<f32>]> for MapPoints<'a> {
    fn from(points: &'a [Point3<f32>]) -> Self {
        Self::new(points)
    }
}

impl<'a> From<&'a Vec<Point3<f32>>> for MapPoints<'a> {
    fn from(points: &'a Vec<Point3<f32>>) -> Self {
        Self::new(points)
    }
}

/// Both maps at `voxel_m` without isolated points (fewer than `min_neighbours` within
/// `isolation_radius_voxels` voxels), colours averaged per voxel. Returns the two clouds and the
/// voxel used (`voxel_m` unless a map spans too many voxels, see [`voxel_downsample`]).
pub fn clean_pair(
    a: MapPoints<'_>,
    b: MapPoints<'_>,
    voxel_m: f64,
    isolation_radius_voxels: f64,
    min_neighbours: usize,
) -> (Cloud, Cloud, f64) {
    let clean = |input: MapPoints<'_>| {
        let fine = voxel_downsample_coloured(input.points, input.colours, voxel_m);
        let radius = isolation_radius_voxels * fine.voxel_m;
        let voxel = fine.voxel_m;
        let keep = not_isolated(&fine.points, radius, min_neighbours);
        (fine.into_cloud().filtered(&keep), voxel)
    };
    let ((a, voxel_a), (b, voxel_b)) = rayon::join(|| clean(a), || clean(b));
    (a, b, voxel_a.max(voxel_b))
}

/// Two clouds, borrowed or re-downsampled, and their voxel.
pub type CappedPair<'a> = (Cow<'a, Cloud>, Cow<'a, Cloud>, f64);

/// Both clouds (downsampled at `voxel_m` already) at the smallest common voxel, `voxel_m` or
/// larger, that leaves each with at most `max_points` points (re-downsampling the centroids and
/// averaging their colours). Returns the clouds and that voxel; borrowed unchanged when `voxel_m`
/// already does.
pub fn cap_pair<'a>(a: &'a Cloud, b: &'a Cloud, voxel_m: f64, max_points: usize) -> CappedPair<'a> {
    if a.len() <= max_points && b.len() <= max_points {
        return (Cow::Borrowed(a), Cow::Borrowed(b), voxel_m);
    }
    let voxel = common_voxel(&a.points, &b.points, voxel_m, max_points);
    let down = |c: &Cloud| voxel_downsample_coloured(&c.points, c.colours.as_deref(), voxel);
    let (a, b) = rayon::join(|| down(a), || down(b));
    let voxel = a.voxel_m.max(b.voxel_m);
    (
        Cow::Owned(a.into_cloud()),
        Cow::Owned(b.into_cloud()),
        voxel,
    )
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
    fn colours_are_averaged_per_voxel_and_follow_their_points() {
        let points = vec![
            Point3::new(0.1f32, 0.1, 0.1),
            Point3::new(2.5, 0.5, 0.5),
            Point3::new(0.3, 0.5, 0.7),
            Point3::new(f32::NAN, 0.0, 0.0),
        ];
        let colours = vec![
            [0.2f32, 0.4, 0.6],
            [1.0, 0.0, 0.5],
            [0.4, 0.0, 0.2],
            [9.0, 9.0, 9.0],
        ];
        let down = voxel_downsample_coloured(&points, Some(&colours), 1.0);
        assert_eq!(down.points, voxel_downsample(&points, 1.0).points);
        let averaged = down.colours.clone().expect("colours");
        assert_eq!(averaged.len(), 2);
        for (found, expected) in averaged.iter().zip([[0.3, 0.2, 0.4], [1.0, 0.0, 0.5]]) {
            assert!(
                found
                    .iter()
                    .zip(&expected)
                    .all(|(a, b)| (a - b).abs() < 1e-6),
                "{found:?}"
            );
        }
        assert_eq!(voxel_downsample(&points, 1.0).colours, None);
        // Re-downsampling and isolated-point removal keep each colour with its point.
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let plane: Vec<Point3<f32>> = (0..20_000)
            .map(|_| Point3::new(rng.random_range(0.0..2.0), rng.random_range(0.0..2.0), 0.0))
            .chain([Point3::new(1.0, 1.0, 1.5)])
            .collect();
        // Red left of x = 1, blue right of it; the isolated point green.
        let colours: Vec<Rgb> = plane
            .iter()
            .map(|p| match (p.z > 0.0, p.x < 1.0) {
                (true, _) => [0.0, 1.0, 0.0],
                (false, true) => [1.0, 0.0, 0.0],
                (false, false) => [0.0, 0.0, 1.0],
            })
            .collect();
        let input = MapPoints::coloured(&plane, Some(&colours));
        let (a, _, voxel) = clean_pair(input, input, 0.05, 2.5, 6);
        assert_eq!(a.len(), 1600);
        let (capped, _, capped_voxel) = cap_pair(&a, &a, voxel, 500);
        assert!(capped.len() <= 500 && capped_voxel > voxel);
        for (cloud, voxel) in [(&a, voxel), (&*capped, capped_voxel)] {
            let colours = cloud.colours.as_ref().unwrap();
            assert_eq!(colours.len(), cloud.len());
            for (p, c) in cloud.points.iter().zip(colours) {
                assert_eq!(c[1], 0.0, "the isolated green point is gone");
                // A voxel wholly on one side has that side's colour; one straddling x = 1, a mix.
                if (p.x - 1.0).abs() > voxel as f32 {
                    assert_eq!(c[0] > 0.5, p.x < 1.0, "{p:?} {c:?}");
                }
                assert!((c[0] + c[2] - 1.0).abs() < 1e-5);
            }
        }
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
        let (a, b, voxel) = clean_pair(
            MapPoints::new(&points),
            MapPoints::new(&points[..40_000]),
            0.05,
            2.5,
            6,
        );
        assert!(a.colours.is_none() && b.colours.is_none());
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
