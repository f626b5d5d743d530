//! Stage 4: robust pruning of the correspondences, keeping the best hypothesis *and* the best
//! distinct runner-up. Hypotheses come from two sources: the cliques of the compatibility graph
//! ([`super::compatibility`], which finds the right transform however few the right
//! correspondences are), then RANSAC over rigid 3-point fits with edge-length pre-checks (which
//! samples everything else, so that a well-supported alternative, such as a symmetric room's
//! turn, is not missed by a clique search that covered it with a larger one).
//!
//! Descriptor correspondences between two partial maps are mostly wrong (a few percent right is
//! typical: every flat wall point looks like every other, and the part of a map the other never
//! saw matches only by chance). Three right ones determine the transform. RANSAC draws three at
//! random; a rigid motion preserves distances, so a sample whose three pairwise distances differ
//! between the maps by more than the edge tolerance is dropped before any fit (three
//! subtractions that discard nearly every wrong sample; the fit and the inlier count, which cost
//! a pass over all correspondences, run for the rest only). That makes a million samples cost tens
//! of milliseconds, enough for an inlier ratio of a few percent.
//!
//! Every fitted hypothesis is locally optimised (refitted by least squares to its inliers until
//! the support stops growing, "LO-RANSAC"): three noisy points give a transform a few degrees
//! off, the refit gives the one all inliers agree on. Hypotheses are then pooled by *distinct
//! transforms*: two count as the same when their rotations differ by at most
//! `distinct_rotation_rad` and they place the centre of the source correspondences within
//! `distinct_translation_m` of each other (a translation compared at the origin would depend on
//! where the map's frame happens to be). The pool keeps the best of each distinct transform.
//!
//! The result is the best hypothesis and the best one distinct from it. On a scene with a
//! symmetry (a square room, a row of identical shelves) several distinct transforms explain the
//! correspondences about equally well; the ratio of their supports is the ambiguity the
//! verification refuses. The runner-up's support counts only correspondences the best does not
//! also explain: a variant of the best transform a little beyond the distinctness thresholds
//! (noise on a small overlap can leave one after the refits) shares most of its supporters with
//! it and is no alternative, while the transforms of a symmetry are supported by different
//! correspondences (each correspondence fits one of them). RANSAC's stopping rule (enough samples to have drawn an all-inlier
//! sample of the best hypothesis with `confidence`) also finds, with about that probability, any
//! hypothesis as well supported, which is what the ambiguity test needs.
//!
//! Deterministic: one ChaCha stream seeded from the configuration, one thread.

use geometry::se3::umeyama;
use nalgebra::{Isometry3, Point3, Vector3};

use super::compatibility::{CliqueParams, clique_hypotheses};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Distinct hypotheses kept while sampling.
const POOL_SIZE: usize = 32;
/// Least-squares refits per local optimisation at most (each stops early when the support stops
/// growing).
const LOCAL_REFITS: usize = 4;

/// Parameters of the search (lengths in metres).
#[derive(Debug, Clone, PartialEq)]
pub struct RansacParams {
    /// A correspondence supports a transform that puts its source point within this distance
    /// of its target point.
    pub inlier_distance_m: f64,
    /// A sample is fitted only when its three pairwise distances agree between the maps within
    /// this tolerance.
    pub edge_tolerance_m: f64,
    /// A sample is fitted only when its source points are at least this far apart pairwise and
    /// its triangle's height over its longest side is at least half of this (not collinear).
    pub min_sample_spread_m: f64,
    /// Samples drawn at most.
    pub max_samples: usize,
    /// Samples drawn at least, whatever the confidence reached.
    pub min_samples: usize,
    /// Sampling stops (after `min_samples`) once an all-inlier sample of the best hypothesis
    /// would have been drawn with this probability.
    pub confidence: f64,
    /// Seed of the sampler.
    pub seed: u64,
    /// Two transforms are distinct when their rotations differ by more than this (radians)...
    pub distinct_rotation_rad: f64,
    /// ...or they put the centre of the source correspondences farther apart than this.
    pub distinct_translation_m: f64,
    /// The clique search over the compatibility graph (`None`: RANSAC alone).
    pub cliques: Option<CliqueParams>,
}

/// A transform and the correspondences it explains.
#[derive(Debug, Clone, PartialEq)]
pub struct Hypothesis {
    /// Maps source points onto their target partners (after the local least-squares refits).
    pub target_from_source: Isometry3<f64>,
    /// Indices of the supporting correspondences, ascending.
    pub inliers: Vec<u32>,
}

impl Hypothesis {
    /// Supporting correspondences.
    pub fn support(&self) -> usize {
        self.inliers.len()
    }
}

/// What the search found.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Consensus {
    /// The hypothesis with the most supporters; `None` when no clique or sample gave a fit
    /// with at least three supporters (or there were fewer than three correspondences).
    pub best: Option<Hypothesis>,
    /// The hypothesis distinct from `best` with the most supporters that `best` does not also
    /// have; `inliers` holds only those (see the module documentation).
    pub runner_up: Option<Hypothesis>,
    /// Every hypothesis kept, best first (at most one per distinct transform, up to 32).
    pub pool: Vec<Hypothesis>,
    /// RANSAC samples drawn.
    pub samples: usize,
    /// Samples that passed the edge checks and were fitted.
    pub fitted: usize,
    /// Cliques of the compatibility graph tried.
    pub cliques: usize,
    /// Correspondences in the largest of them.
    pub largest_clique: usize,
}

/// How far apart two transforms are: the rotation angle between them (radians) and the distance
/// between the places they put `centre` (metres).
pub fn transform_difference(
    a: &Isometry3<f64>,
    b: &Isometry3<f64>,
    centre: &Point3<f64>,
) -> (f64, f64) {
    let angle = a.rotation.angle_to(&b.rotation);
    let distance = (a * centre - b * centre).norm();
    (angle, distance)
}

/// Whether two transforms are one: rotations at most `rotation_rad` apart and `centre` put at
/// most `translation_m` apart (the module documentation's distinct transforms, negated).
pub fn same_transform(
    a: &Isometry3<f64>,
    b: &Isometry3<f64>,
    centre: &Point3<f64>,
    rotation_rad: f64,
    translation_m: f64,
) -> bool {
    let (angle, distance) = transform_difference(a, b, centre);
    angle <= rotation_rad && distance <= translation_m
}

/// The search over correspondences `source[k] <-> target[k]`.
struct Search<'a> {
    source: &'a [Point3<f64>],
    target: &'a [Point3<f64>],
    params: &'a RansacParams,
    centre: Point3<f64>,
    pool: Vec<Hypothesis>,
}

impl Search<'_> {
    fn inliers(&self, pose: &Isometry3<f64>) -> Vec<u32> {
        let limit = self.params.inlier_distance_m * self.params.inlier_distance_m;
        self.source
            .iter()
            .zip(self.target)
            .enumerate()
            .filter(|(_, (s, t))| (pose * *s - *t).norm_squared() <= limit)
            .map(|(k, _)| k as u32)
            .collect()
    }

    fn fit(&self, indices: &[u32]) -> Option<Isometry3<f64>> {
        let (s, t): (Vec<Point3<f64>>, Vec<Point3<f64>>) = indices
            .iter()
            .map(|&k| (self.source[k as usize], self.target[k as usize]))
            .unzip();
        Some(umeyama(&s, &t, false)?.rigid())
    }

    /// Refits to the inliers while the support grows.
    fn locally_optimise(&self, mut best: Hypothesis) -> Hypothesis {
        for _ in 0..LOCAL_REFITS {
            let Some(pose) = self.fit(&best.inliers) else {
                break;
            };
            let inliers = self.inliers(&pose);
            if inliers.len() <= best.support() {
                break;
            }
            best = Hypothesis {
                target_from_source: pose,
                inliers,
            };
        }
        best
    }

    fn same_transform(&self, a: &Isometry3<f64>, b: &Isometry3<f64>) -> bool {
        same_transform(
            a,
            b,
            &self.centre,
            self.params.distinct_rotation_rad,
            self.params.distinct_translation_m,
        )
    }

    /// Whether a hypothesis of this support could change the pool.
    fn could_enter(&self, support: usize) -> bool {
        self.pool.len() < POOL_SIZE || self.pool.last().is_some_and(|h| support > h.support())
    }

    /// Adds a hypothesis, keeping the better one of each distinct transform, the pool sorted by
    /// support (best first) and at most [`POOL_SIZE`] long.
    fn offer(&mut self, hypothesis: Hypothesis) {
        if let Some(same) = self.pool.iter().position(|h| {
            self.same_transform(&h.target_from_source, &hypothesis.target_from_source)
        }) {
            if self.pool[same].support() >= hypothesis.support() {
                return;
            }
            self.pool.remove(same);
        }
        let at = self
            .pool
            .partition_point(|h| h.support() >= hypothesis.support());
        self.pool.insert(at, hypothesis);
        self.pool.truncate(POOL_SIZE);
    }

    fn best_support(&self) -> usize {
        self.pool.first().map_or(0, Hypothesis::support)
    }

    /// Fits the correspondences `indices`, counts the fit's supporters, locally optimises it and
    /// offers it to the pool; a new best updates the samples RANSAC still needs (`required`).
    fn try_sample(&mut self, indices: &[u32], required: &mut f64) {
        let Some(pose) = self.fit(indices) else {
            return;
        };
        let inliers = self.inliers(&pose);
        if inliers.len() < 3 || !self.could_enter(inliers.len()) {
            return;
        }
        let hypothesis = self.locally_optimise(Hypothesis {
            target_from_source: pose,
            inliers,
        });
        let previous_best = self.best_support();
        self.offer(hypothesis);
        if self.best_support() > previous_best {
            *required = required_samples(
                self.best_support() as f64 / self.source.len() as f64,
                self.params.confidence,
            );
        }
    }

    /// Whether three sampled correspondences can come from one rigid motion and are spread enough
    /// to fit one.
    fn plausible(&self, sample: [usize; 3]) -> bool {
        let p = self.params;
        let pairs = [(0, 1), (0, 2), (1, 2)];
        for (a, b) in pairs {
            let (i, j) = (sample[a], sample[b]);
            let ds = (self.source[i] - self.source[j]).norm();
            let dt = (self.target[i] - self.target[j]).norm();
            if (ds - dt).abs() > p.edge_tolerance_m || ds < p.min_sample_spread_m {
                return false;
            }
        }
        // Not collinear: the triangle's height over its longest side at least half the spread.
        let [a, b, c] = sample.map(|k| self.source[k]);
        let area2 = (b - a).cross(&(c - a)).norm();
        let longest = (b - a).norm().max((c - a).norm()).max((c - b).norm());
        area2 / longest >= 0.5 * p.min_sample_spread_m
    }
}

/// Samples needed to draw one all-inlier sample of 3 with probability `confidence`, at this
/// inlier ratio.
fn required_samples(inlier_ratio: f64, confidence: f64) -> f64 {
    let all_inliers = inlier_ratio.powi(3);
    if all_inliers <= 0.0 {
        return f64::INFINITY;
    }
    if all_inliers >= 1.0 {
        return 1.0;
    }
    (1.0 - confidence).ln() / (1.0 - all_inliers).ln()
}

/// Finds the best and runner-up rigid transforms explaining `source[k] <-> target[k]` (see the
/// module documentation).
pub fn find_consensus(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    params: &RansacParams,
) -> Consensus {
    let n = source.len().min(target.len());
    let mut consensus = Consensus::default();
    if n < 3 {
        return consensus;
    }
    let centre = Point3::from(
        source[..n]
            .iter()
            .fold(Vector3::zeros(), |sum, p| sum + p.coords)
            / n as f64,
    );
    let mut search = Search {
        source: &source[..n],
        target: &target[..n],
        params,
        centre,
        pool: Vec::new(),
    };
    let mut required = params.max_samples as f64;
    if let Some(clique_params) = &params.cliques {
        for clique in clique_hypotheses(&source[..n], &target[..n], clique_params) {
            consensus.cliques += 1;
            consensus.largest_clique = consensus.largest_clique.max(clique.len());
            search.try_sample(&clique, &mut required);
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    while consensus.samples < params.max_samples
        && (consensus.samples < params.min_samples || (consensus.samples as f64) < required)
    {
        consensus.samples += 1;
        let sample = [
            rng.random_range(0..n),
            rng.random_range(0..n),
            rng.random_range(0..n),
        ];
        if sample[0] == sample[1] || sample[0] == sample[2] || sample[1] == sample[2] {
            continue;
        }
        if !search.plausible(sample) {
            continue;
        }
        consensus.fitted += 1;
        search.try_sample(&sample.map(|k| k as u32), &mut required);
    }
    consensus.pool = search.pool.clone();
    let mut pool = std::mem::take(&mut search.pool).into_iter();
    consensus.best = pool.next();
    if let Some(best) = &consensus.best {
        consensus.runner_up = pool
            .filter(|h| !search.same_transform(&h.target_from_source, &best.target_from_source))
            .map(|h| Hypothesis {
                inliers: h
                    .inliers
                    .iter()
                    .copied()
                    .filter(|k| best.inliers.binary_search(k).is_err())
                    .collect(),
                ..h
            })
            // The first of the largest: the pool is in order of full support.
            .fold(None, |found: Option<Hypothesis>, h| match found {
                Some(f) if f.support() >= h.support() => Some(f),
                _ => Some(h),
            });
    }
    consensus
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use rand_distr::{Distribution, Normal};

    fn params() -> RansacParams {
        RansacParams {
            inlier_distance_m: 0.1,
            edge_tolerance_m: 0.15,
            min_sample_spread_m: 0.2,
            max_samples: 200_000,
            min_samples: 20_000,
            confidence: 0.9999,
            seed: 7,
            distinct_rotation_rad: 10f64.to_radians(),
            distinct_translation_m: 0.3,
            cliques: None,
        }
    }

    /// `inliers` noisy correspondences under `truth`, then `outliers` random ones, shuffled.
    fn correspondences(
        truth: &Isometry3<f64>,
        inliers: usize,
        outliers: usize,
        seed: u64,
    ) -> (Vec<Point3<f64>>, Vec<Point3<f64>>, Vec<bool>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let noise = Normal::new(0.0, 0.02).unwrap();
        let mut rows: Vec<(Point3<f64>, Point3<f64>, bool)> = Vec::new();
        let random_point = |rng: &mut ChaCha8Rng| {
            Point3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(0.0..2.5),
            )
        };
        for _ in 0..inliers {
            let s = random_point(&mut rng);
            let jitter = Vector3::from_fn(|_, _| noise.sample(&mut rng));
            rows.push((s, truth * s + jitter, true));
        }
        for _ in 0..outliers {
            let s = random_point(&mut rng);
            let t = truth * random_point(&mut rng);
            rows.push((s, t, false));
        }
        // Deterministic shuffle.
        for i in (1..rows.len()).rev() {
            rows.swap(i, rng.random_range(0..=i));
        }
        let source = rows.iter().map(|r| r.0).collect();
        let target = rows.iter().map(|r| r.1).collect();
        let truth_mask = rows.iter().map(|r| r.2).collect();
        (source, target, truth_mask)
    }

    fn truth() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(3.0, -1.0, 0.5),
            UnitQuaternion::from_euler_angles(0.2, -0.1, 2.0),
        )
    }

    #[test]
    fn finds_the_transform_at_three_percent_inliers_and_is_deterministic() {
        let truth = truth();
        let (source, target, is_inlier) = correspondences(&truth, 60, 1940, 1);
        let found = find_consensus(&source, &target, &params());
        let best = found.best.as_ref().expect("a hypothesis");
        let (angle, distance) =
            transform_difference(&best.target_from_source, &truth, &Point3::origin());
        assert!(
            angle < 1f64.to_radians() && distance < 0.03,
            "{angle} {distance}"
        );
        assert!(best.support() >= 55, "{}", best.support());
        let wrong = best
            .inliers
            .iter()
            .filter(|&&k| !is_inlier[k as usize])
            .count();
        assert!(wrong <= 3, "{wrong} outliers among the inliers");
        // A chance runner-up has a handful of supporters.
        let runner_up = found.runner_up.as_ref().map_or(0, Hypothesis::support);
        assert!(runner_up * 4 < best.support(), "{runner_up}");
        assert!(found.fitted * 20 < found.samples, "{found:?}");
        assert_eq!(find_consensus(&source, &target, &params()), found);
        // Another seed finds the same transform.
        let other = find_consensus(
            &source,
            &target,
            &RansacParams {
                seed: 8,
                ..params()
            },
        );
        let (angle, distance) = transform_difference(
            &other.best.unwrap().target_from_source,
            &best.target_from_source,
            &Point3::origin(),
        );
        assert!(angle < 0.2f64.to_radians() && distance < 0.01);
    }

    #[test]
    fn two_equally_supported_transforms_are_best_and_runner_up() {
        let truth = truth();
        let mirror = truth * Isometry3::rotation(Vector3::z() * std::f64::consts::PI);
        let (mut source, mut target, _) = correspondences(&truth, 50, 900, 2);
        let (s2, t2, _) = correspondences(&mirror, 45, 0, 3);
        source.extend(s2);
        target.extend(t2);
        let found = find_consensus(&source, &target, &params());
        let best = found.best.clone().unwrap();
        let runner_up = found.runner_up.clone().expect("the mirrored transform");
        assert!(
            best.support() >= 48 && runner_up.support() >= 43,
            "{found:?}"
        );
        let (angle, _) = transform_difference(
            &best.target_from_source,
            &runner_up.target_from_source,
            &Point3::origin(),
        );
        assert!((angle - std::f64::consts::PI).abs() < 0.05, "{angle}");
        // Too few correspondences: nothing.
        assert_eq!(
            find_consensus(&source[..2], &target[..2], &params()),
            Consensus::default()
        );
    }
}
