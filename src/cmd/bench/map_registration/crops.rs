//! Pairs of maps cropped to a controlled overlap.
//!
//! Two maps of one scene (both in the world frame: made from different frames of one sequence,
//! or by two agents of the synthetic scene) are cut by a vertical slab: map A keeps what lies
//! before the slab's far side, map B what lies beyond its near side, so the two share the slab.
//! The slab's direction is random in the scene's horizontal plane (its two largest principal
//! axes), its centre a random quantile (0.3-0.7) of the scene along that direction, and its width
//! is found by bisection so that the true overlap, the fraction of the smaller crop's points
//! with a point of the other crop within 5 cm, is the bin's target (within 3 points of percent).
//! A disjoint pair leaves a gap of 0.5 m between the two crops instead (and is checked to share
//! nothing). Each crop keeps at least a fifth of its map, and the views (depth images) that see
//! mostly what it kept.

use nalgebra::{Matrix3, Point3, Vector3};
use registration::PointTree;

use super::maps::{Map, SplitMix};

/// Two points overlap within this distance (metres).
pub const TRUE_OVERLAP_DISTANCE_M: f64 = 0.05;
/// A cropped pair's true overlap is within this of its target.
const OVERLAP_TOLERANCE: f64 = 0.03;
/// Half the gap between the two crops of a disjoint pair (metres).
const DISJOINT_HALF_GAP_M: f64 = 0.25;
/// A disjoint pair's true overlap is below this (a few stray points across the gap).
const DISJOINT_MAX_OVERLAP: f64 = 0.005;
/// Each crop keeps at least this fraction of its map's points.
const MIN_KEPT_FRACTION: f64 = 0.2;
/// A view belongs to a crop when this fraction of its sampled points lies in it.
const VIEW_IN_CROP_FRACTION: f64 = 0.3;
/// Slabs tried per pair before giving up (an overlap the scene cannot give).
const ATTEMPTS: u64 = 64;
const BISECTION_STEPS: usize = 40;

/// One side of a slab: the points whose coordinate along `direction` is below `limit`
/// (`below`), or above it.
#[derive(Debug, Clone, Copy)]
struct HalfSpace {
    direction: Vector3<f32>,
    limit: f32,
    below: bool,
}

impl HalfSpace {
    fn contains(&self, p: &Point3<f32>) -> bool {
        let s = p.coords.dot(&self.direction);
        if self.below {
            s < self.limit
        } else {
            s > self.limit
        }
    }
}

/// Two maps of one scene in the world frame, prepared for cropping.
pub struct CropScene {
    a: Map,
    b: Map,
    /// Each point's nearest point of the other map within [`TRUE_OVERLAP_DISTANCE_M`].
    a_partner: Vec<Option<u32>>,
    b_partner: Vec<Option<u32>>,
    /// The scene's two largest principal axes (its horizontal plane, for a room).
    axes: [Vector3<f32>; 2],
    /// Natural overlap of the whole maps.
    pub full_overlap: f64,
}

/// A cropped pair (both in the world frame) and its true overlap.
pub struct CroppedPair {
    pub a: Map,
    pub b: Map,
    pub true_overlap: f64,
}

fn partners(from: &[Point3<f32>], to: &[Point3<f32>]) -> Vec<Option<u32>> {
    let Ok(tree) = PointTree::new(to.to_vec()) else {
        return vec![None; from.len()];
    };
    let limit = (TRUE_OVERLAP_DISTANCE_M * TRUE_OVERLAP_DISTANCE_M) as f32;
    from.iter()
        .map(|p| tree.nearest(p).filter(|&(_, d)| d <= limit).map(|(j, _)| j))
        .collect()
}

fn principal_axes(points: &[Point3<f32>]) -> [Vector3<f32>; 2] {
    let n = points.len().max(1) as f64;
    let mean = points
        .iter()
        .fold(Vector3::zeros(), |s, p| s + p.coords.cast::<f64>())
        / n;
    let mut scatter = Matrix3::zeros();
    for p in points {
        let d = p.coords.cast::<f64>() - mean;
        scatter += d * d.transpose();
    }
    let eigen = scatter.symmetric_eigen();
    let mut order = [0, 1, 2];
    order.sort_by(|&i, &j| eigen.eigenvalues[j].total_cmp(&eigen.eigenvalues[i]));
    [0, 1].map(|k| {
        eigen
            .eigenvectors
            .column(order[k])
            .into_owned()
            .cast::<f32>()
    })
}

impl CropScene {
    pub fn new(a: Map, b: Map) -> Self {
        let (a_partner, b_partner) = (
            partners(&a.points, &b.points),
            partners(&b.points, &a.points),
        );
        let mut union = a.points.clone();
        union.extend_from_slice(&b.points);
        let axes = principal_axes(&union);
        let mut scene = Self {
            a,
            b,
            a_partner,
            b_partner,
            axes,
            full_overlap: 0.0,
        };
        let everything = |below| HalfSpace {
            direction: Vector3::x(),
            limit: if below {
                f32::INFINITY
            } else {
                f32::NEG_INFINITY
            },
            below,
        };
        scene.full_overlap = scene.overlap(&everything(true), &everything(false));
        scene
    }

    /// True overlap of the crops `a_side` of A and `b_side` of B, over the smaller crop, from
    /// the partners (a point overlaps when its partner is kept too).
    fn overlap(&self, a_side: &HalfSpace, b_side: &HalfSpace) -> f64 {
        let count = |points: &[Point3<f32>],
                     partner: &[Option<u32>],
                     own: &HalfSpace,
                     other: &[Point3<f32>],
                     other_side: &HalfSpace| {
            let mut kept = 0usize;
            let mut overlapping = 0usize;
            for (p, partner) in points.iter().zip(partner) {
                if !own.contains(p) {
                    continue;
                }
                kept += 1;
                if partner.is_some_and(|j| other_side.contains(&other[j as usize])) {
                    overlapping += 1;
                }
            }
            (kept, overlapping)
        };
        let (na, oa) = count(
            &self.a.points,
            &self.a_partner,
            a_side,
            &self.b.points,
            b_side,
        );
        let (nb, ob) = count(
            &self.b.points,
            &self.b_partner,
            b_side,
            &self.a.points,
            a_side,
        );
        let (kept, overlapping) = if na <= nb { (na, oa) } else { (nb, ob) };
        overlapping as f64 / kept.max(1) as f64
    }

    fn kept(&self, map: &Map, side: &HalfSpace) -> usize {
        map.points.iter().filter(|p| side.contains(p)).count()
    }

    /// A pair with true overlap `target` (0: disjoint), from slabs drawn with `seed`; `None` when
    /// no slab of [`ATTEMPTS`] gives it.
    pub fn pair(&self, target: f64, seed: u64) -> Option<CroppedPair> {
        for attempt in 0..ATTEMPTS {
            let mut rng = SplitMix(seed.wrapping_mul(0x1000).wrapping_add(attempt) ^ 0xc509);
            let angle = std::f64::consts::TAU * rng.unit();
            let direction =
                (self.axes[0] * angle.cos() as f32 + self.axes[1] * angle.sin() as f32).normalize();
            let mut along: Vec<f32> = self
                .a
                .points
                .iter()
                .chain(&self.b.points)
                .map(|p| p.coords.dot(&direction))
                .collect();
            along.sort_by(f32::total_cmp);
            let quantile = |q: f64| along[((along.len() - 1) as f64 * q) as usize];
            let centre = quantile(0.3 + 0.4 * rng.unit());
            let span = quantile(1.0) - quantile(0.0);
            let sides = |half_width: f32| {
                (
                    HalfSpace {
                        direction,
                        limit: centre + half_width,
                        below: true,
                    },
                    HalfSpace {
                        direction,
                        limit: centre - half_width,
                        below: false,
                    },
                )
            };
            let (a_side, b_side, overlap) = if target <= 0.0 {
                let (a_side, b_side) = sides(-DISJOINT_HALF_GAP_M as f32);
                let overlap = self.overlap(&a_side, &b_side);
                if overlap > DISJOINT_MAX_OVERLAP {
                    continue;
                }
                (a_side, b_side, overlap)
            } else {
                let (mut low, mut high) = (0.0f32, span);
                if self.overlap(&sides(high).0, &sides(high).1) < target - OVERLAP_TOLERANCE {
                    continue;
                }
                for _ in 0..BISECTION_STEPS {
                    let middle = 0.5 * (low + high);
                    let (a_side, b_side) = sides(middle);
                    if self.overlap(&a_side, &b_side) < target {
                        low = middle;
                    } else {
                        high = middle;
                    }
                }
                let (a_side, b_side) = sides(high);
                let overlap = self.overlap(&a_side, &b_side);
                if (overlap - target).abs() > OVERLAP_TOLERANCE {
                    continue;
                }
                (a_side, b_side, overlap)
            };
            let enough = |map: &Map, side: &HalfSpace| {
                self.kept(map, side) as f64 >= MIN_KEPT_FRACTION * map.points.len() as f64
            };
            if !enough(&self.a, &a_side) || !enough(&self.b, &b_side) {
                continue;
            }
            return Some(CroppedPair {
                a: crop(&self.a, &a_side),
                b: crop(&self.b, &b_side),
                true_overlap: overlap,
            });
        }
        None
    }
}

/// The points of `map` on `side`, with the views that mostly see them.
fn crop(map: &Map, side: &HalfSpace) -> Map {
    let mut cropped = map.filtered(|p| side.contains(p));
    cropped.views = map
        .views
        .iter()
        .filter(|view| {
            let inside = view.sample.iter().filter(|p| side.contains(p)).count();
            inside as f64 >= VIEW_IN_CROP_FRACTION * view.sample.len().max(1) as f64
        })
        .cloned()
        .collect();
    cropped
}
