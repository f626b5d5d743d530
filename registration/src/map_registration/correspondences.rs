//! Stage 3: putative correspondences, nearest neighbours in descriptor space.
//!
//! Every source descriptor's nearest target descriptor and every target descriptor's nearest
//! source descriptor are found (Euclidean distance over the 33 FPFH values and, when the maps have
//! colour, the weighted colour signature of `colour`: 43 values); a pair that
//! chose each other (mutual nearest neighbours) is a correspondence. Mutuality removes most
//! matches of repeated structure (a thousand wall points all choose the same few "most wall-like"
//! descriptors of the other map; at most one of each such choice is mutual) at the price of some
//! good ones; when too few are mutual (small or very different maps), the best one-way matches
//! by descriptor distance top the list up, because RANSAC copes with outliers but not with too
//! few correspondences.
//!
//! Only the most distinctive descriptors of each map take part ([`most_distinctive`]): those
//! farthest from the map's mean descriptor. Most of an indoor map is wall and floor, whose
//! descriptors all look alike and only produce wrong matches; keeping the rest bounds the cost,
//! which is the product of the two counts.
//!
//! The search compares every pair, once, for both directions ([`nearest_brute_force_both_ways`]).
//! kiddo's kd-tree in 33 (now 43) dimensions ([`nearest_kd_tree`], kept as a second
//! implementation the tests compare) was slower at these sizes, by a factor of about three on the
//! unit test's room (docs/benchmarks.md): kd-trees prune little in that many dimensions.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::colour::SIGNATURE_LEN;
use super::fpfh::DESCRIPTOR_LEN;

/// Length of a descriptor as matched: the FPFH histogram, then the colour signature scaled by
/// its weight (zeros for maps without colour, which change no distance).
pub const MATCH_LEN: usize = DESCRIPTOR_LEN + SIGNATURE_LEN;
/// One point's descriptor as matched.
pub type MatchDescriptor = [f32; MATCH_LEN];

/// Queries per rayon task.
const QUERIES_PER_TASK: usize = 64;

/// A putative correspondence between the `source`-th source descriptor and the `target`-th
/// target descriptor (indices into the descriptor lists, not the clouds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureMatch {
    /// Index into the source map's descriptors.
    pub source: u32,
    /// Index into the target map's descriptors.
    pub target: u32,
    /// Squared descriptor distance.
    pub distance_sq: f32,
    /// Descriptor distance over the distance to the chooser's second nearest descriptor (Lowe's
    /// ratio; 1 when there is no second); the smaller of the two directions for a mutual pair.
    pub ratio: f32,
    /// Whether the pair chose each other.
    pub mutual: bool,
}

/// Index and squared distance of the nearest `reference` descriptor of every query, by kd-tree.
/// Empty when `reference` is.
pub fn nearest_kd_tree(
    queries: &[MatchDescriptor],
    reference: &[MatchDescriptor],
) -> Vec<(u32, f32)> {
    if reference.is_empty() {
        return Vec::new();
    }
    let tree: ImmutableKdTree<f32, MATCH_LEN> =
        ImmutableKdTree::new_from_slice(reference).expect("descriptor count fits in u32");
    queries
        .par_iter()
        .with_min_len(QUERIES_PER_TASK)
        .map(|q| {
            let found = tree
                .query(q)
                .nearest_one::<SquaredEuclidean<f32>>()
                .execute();
            (found.item, found.distance)
        })
        .collect()
}

/// Squared Euclidean distance of two descriptors.
#[inline]
pub fn descriptor_distance_sq(a: &MatchDescriptor, b: &MatchDescriptor) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Lanes of the distance accumulator.
const LANES: usize = 8;
/// Descriptor length padded to whole SIMD lanes (zeros add nothing to a distance).
const PADDED_LEN: usize = MATCH_LEN.div_ceil(LANES) * LANES;
/// Source descriptors compared with each target descriptor while it is in the L1 cache.
const ROWS_PER_BLOCK: usize = 16;

type Padded = [f32; PADDED_LEN];

fn padded(descriptors: &[MatchDescriptor]) -> Vec<Padded> {
    descriptors
        .iter()
        .map(|d| {
            let mut p = [0.0f32; PADDED_LEN];
            p[..MATCH_LEN].copy_from_slice(d);
            p
        })
        .collect()
}

/// Squared distance of two padded descriptors, summed lane-wise in a fixed order (the compiler
/// turns the lanes into SIMD registers).
#[inline]
fn padded_distance_sq(a: &Padded, b: &Padded) -> f32 {
    let mut lanes = [0.0f32; LANES];
    for (a, b) in a.chunks_exact(LANES).zip(b.chunks_exact(LANES)) {
        for k in 0..LANES {
            let d = a[k] - b[k];
            lanes[k] += d * d;
        }
    }
    lanes.iter().sum()
}

/// Each query's nearest neighbour: (index, squared distance).
pub type Nearest = Vec<(u32, f32)>;

/// A query's nearest neighbour and the squared distance to its second nearest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NearestTwo {
    /// Index of the nearest reference descriptor.
    pub index: u32,
    /// Squared distance to it.
    pub distance_sq: f32,
    /// Infinite when there is no second.
    pub second_sq: f32,
}

impl NearestTwo {
    const NONE: Self = Self {
        index: u32::MAX,
        distance_sq: f32::INFINITY,
        second_sq: f32::INFINITY,
    };

    /// Lowe's ratio `distance / second distance` (1 without a second, or at distance 0 to both).
    pub fn ratio(&self) -> f32 {
        if self.second_sq.is_finite() && self.second_sq > 0.0 {
            (self.distance_sq / self.second_sq).sqrt()
        } else {
            1.0
        }
    }

    /// Adds a candidate: the nearest is the smaller distance, then the lower index (so merging
    /// does not depend on how the work was split); the second the next smaller distance.
    #[inline]
    fn offer(&mut self, index: u32, distance_sq: f32) {
        if distance_sq < self.distance_sq || (distance_sq == self.distance_sq && index < self.index)
        {
            self.second_sq = self.distance_sq;
            self.distance_sq = distance_sq;
            self.index = index;
        } else if distance_sq < self.second_sq {
            self.second_sq = distance_sq;
        }
    }

    /// Both candidates' union: associative and commutative.
    fn merge(mut self, other: Self) -> Self {
        if other.index != u32::MAX {
            self.offer(other.index, other.distance_sq);
        }
        self.second_sq = self.second_sq.min(other.second_sq);
        self
    }
}

/// Nearest neighbours in both directions from one pass over all pairs: each source
/// descriptor's nearest target and each target descriptor's nearest source (ties to the lower
/// index), with the distance to the second nearest. Blocked so that a target descriptor is
/// compared with [`ROWS_PER_BLOCK`] source descriptors while it is in cache; rows in parallel,
/// each worker keeping its own column minima, merged at the end.
pub fn nearest_two_both_ways(
    source: &[MatchDescriptor],
    target: &[MatchDescriptor],
) -> (Vec<NearestTwo>, Vec<NearestTwo>) {
    if source.is_empty() || target.is_empty() {
        return (Vec::new(), Vec::new());
    }
    let (source, target) = (padded(source), padded(target));
    let none = NearestTwo::NONE;
    let (mut rows, columns) = source
        .par_chunks(ROWS_PER_BLOCK)
        .enumerate()
        .fold(
            || (Vec::new(), vec![none; target.len()]),
            |(mut rows, mut columns), (block, chunk)| {
                let first = block * ROWS_PER_BLOCK;
                let mut row_best = [none; ROWS_PER_BLOCK];
                for (t, (b, column)) in target.iter().zip(columns.iter_mut()).enumerate() {
                    for (r, a) in chunk.iter().enumerate() {
                        let d = padded_distance_sq(a, b);
                        row_best[r].offer(t as u32, d);
                        column.offer((first + r) as u32, d);
                    }
                }
                rows.extend(
                    row_best[..chunk.len()]
                        .iter()
                        .enumerate()
                        .map(|(r, &best)| (first + r, best)),
                );
                (rows, columns)
            },
        )
        .reduce(
            || (Vec::new(), vec![none; target.len()]),
            |(mut rows_a, columns_a), (rows_b, columns_b)| {
                rows_a.extend(rows_b);
                let columns = columns_a
                    .into_iter()
                    .zip(columns_b)
                    .map(|(a, b)| a.merge(b))
                    .collect();
                (rows_a, columns)
            },
        );
    rows.sort_unstable_by_key(|&(row, _)| row);
    (rows.into_iter().map(|(_, best)| best).collect(), columns)
}

/// [`nearest_two_both_ways`] without the second distances.
pub fn nearest_brute_force_both_ways(
    source: &[MatchDescriptor],
    target: &[MatchDescriptor],
) -> (Nearest, Nearest) {
    let (rows, columns) = nearest_two_both_ways(source, target);
    let strip = |list: Vec<NearestTwo>| list.iter().map(|n| (n.index, n.distance_sq)).collect();
    (strip(rows), strip(columns))
}

/// The same as [`nearest_kd_tree`] by comparing every pair (ties go to the lower index).
pub fn nearest_brute_force(
    queries: &[MatchDescriptor],
    reference: &[MatchDescriptor],
) -> Vec<(u32, f32)> {
    nearest_brute_force_both_ways(queries, reference).0
}

/// Indices (ascending) of the at most `max_count` most distinctive descriptors: those farthest
/// from the list's mean descriptor (ties to the lower index). All of them when there are no more.
pub fn most_distinctive(descriptors: &[MatchDescriptor], max_count: usize) -> Vec<u32> {
    if descriptors.len() <= max_count {
        return (0..descriptors.len() as u32).collect();
    }
    let mut mean = [0.0f64; MATCH_LEN];
    for d in descriptors {
        for (m, v) in mean.iter_mut().zip(d) {
            *m += *v as f64;
        }
    }
    let mean: MatchDescriptor = mean.map(|m| (m / descriptors.len() as f64) as f32);
    let mut ranked: Vec<(f32, u32)> = descriptors
        .par_iter()
        .map(|d| descriptor_distance_sq(d, &mean))
        .enumerate()
        .map(|(i, d)| (d, i as u32))
        .collect();
    ranked.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut kept: Vec<u32> = ranked[..max_count].iter().map(|&(_, i)| i).collect();
    kept.sort_unstable();
    kept
}

/// How correspondences are chosen (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct MatchParams {
    /// The most distinctive descriptors of each map that take part.
    pub max_per_map: usize,
    /// One-way matches whose Lowe ratio is below this join the mutual ones (0: none).
    pub max_ratio: f32,
    /// Correspondences at most: mutual ones first, then one-way ones by ratio.
    pub max_correspondences: usize,
    /// When fewer, the best remaining one-way matches (by distance) top the list up to this.
    pub min_correspondences: usize,
}

/// Correspondences from each direction's two nearest neighbours: the mutual nearest neighbours,
/// then the one-way matches that pass Lowe's ratio test, up to `max_correspondences`, then, if
/// fewer than `min_correspondences`, the best remaining one-way matches (see the module
/// documentation). Ordered: mutual ones by source index, the ratio-tested ones by ratio, the
/// rest by distance.
pub fn mutual_matches(
    source_to_target: &[NearestTwo],
    target_to_source: &[NearestTwo],
    params: &MatchParams,
) -> Vec<FeatureMatch> {
    let is_mutual = |s: u32, t: u32| {
        source_to_target[s as usize].index == t && target_to_source[t as usize].index == s
    };
    let mut matches: Vec<FeatureMatch> = source_to_target
        .iter()
        .enumerate()
        .filter(|(s, n)| is_mutual(*s as u32, n.index))
        .map(|(s, n)| FeatureMatch {
            source: s as u32,
            target: n.index,
            distance_sq: n.distance_sq,
            ratio: n.ratio().min(target_to_source[n.index as usize].ratio()),
            mutual: true,
        })
        .collect();
    matches.truncate(params.max_correspondences);
    let one_way = source_to_target
        .iter()
        .enumerate()
        .map(|(s, n)| (s as u32, n.index, n))
        .chain(
            target_to_source
                .iter()
                .enumerate()
                .map(|(t, n)| (n.index, t as u32, n)),
        );
    // Not mutual: mutual pairs are already in, and appear in both directions.
    let mut extra: Vec<FeatureMatch> = one_way
        .filter(|&(s, t, _)| !is_mutual(s, t))
        .map(|(source, target, n)| FeatureMatch {
            source,
            target,
            distance_sq: n.distance_sq,
            ratio: n.ratio(),
            mutual: false,
        })
        .collect();
    let by_pair =
        |a: &FeatureMatch, b: &FeatureMatch| a.source.cmp(&b.source).then(a.target.cmp(&b.target));
    extra.sort_by(|a, b| {
        let a_passes = a.ratio < params.max_ratio;
        let b_passes = b.ratio < params.max_ratio;
        b_passes
            .cmp(&a_passes)
            .then_with(|| {
                if a_passes {
                    a.ratio.total_cmp(&b.ratio)
                } else {
                    std::cmp::Ordering::Equal
                }
            })
            .then(a.distance_sq.total_cmp(&b.distance_sq))
            .then_with(|| by_pair(a, b))
    });
    extra.dedup_by(|a, b| a.source == b.source && a.target == b.target);
    let passing = extra.partition_point(|m| m.ratio < params.max_ratio);
    let room = params.max_correspondences.saturating_sub(matches.len());
    let taken = passing.min(room);
    let mut extra = extra.into_iter();
    matches.extend(extra.by_ref().take(taken));
    if matches.len() < params.min_correspondences {
        let mut rest: Vec<FeatureMatch> = extra.collect();
        rest.sort_by(|a, b| {
            a.distance_sq
                .total_cmp(&b.distance_sq)
                .then_with(|| by_pair(a, b))
        });
        let missing = params.min_correspondences - matches.len();
        matches.extend(rest.into_iter().take(missing));
    }
    matches
}

/// Correspondences between two descriptor lists: the [`most_distinctive`] `max_per_map` of each,
/// [`nearest_two_both_ways`] between them, then [`mutual_matches`]. Indices refer to the full
/// lists.
pub fn match_descriptors(
    source: &[MatchDescriptor],
    target: &[MatchDescriptor],
    params: &MatchParams,
) -> Vec<FeatureMatch> {
    if source.is_empty() || target.is_empty() {
        return Vec::new();
    }
    let (source_kept, target_kept) = rayon::join(
        || most_distinctive(source, params.max_per_map),
        || most_distinctive(target, params.max_per_map),
    );
    let pick = |all: &[MatchDescriptor], kept: &[u32]| -> Vec<MatchDescriptor> {
        kept.iter().map(|&i| all[i as usize]).collect()
    };
    let (forward, backward) =
        nearest_two_both_ways(&pick(source, &source_kept), &pick(target, &target_kept));
    let mut matches = mutual_matches(&forward, &backward, params);
    for m in &mut matches {
        m.source = source_kept[m.source as usize];
        m.target = target_kept[m.target as usize];
    }
    matches
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Mutual matches of at most `max_per_map` descriptors each, topped up to `min`.
    fn params(max_per_map: usize, min: usize) -> MatchParams {
        MatchParams {
            max_per_map,
            max_ratio: 0.0,
            max_correspondences: usize::MAX,
            min_correspondences: min,
        }
    }

    /// Histogram-like random descriptors clustered around a few prototypes, as real ones are.
    fn descriptors(seed: u64, n: usize) -> Vec<MatchDescriptor> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let prototypes: Vec<MatchDescriptor> = (0..8)
            .map(|_| std::array::from_fn(|_| rng.random_range(0.0..0.3)))
            .collect();
        (0..n)
            .map(|k| {
                let base = &prototypes[k % prototypes.len()];
                std::array::from_fn(|i| (base[i] + rng.random_range(-0.05..0.05f32)).max(0.0))
            })
            .collect()
    }

    /// Target descriptors: noisy copies of the first `copies` source descriptors, then others.
    fn related(
        source: &[MatchDescriptor],
        copies: usize,
        others: usize,
        seed: u64,
    ) -> Vec<MatchDescriptor> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut target: Vec<MatchDescriptor> = source[..copies]
            .iter()
            .map(|d| std::array::from_fn(|i| (d[i] + rng.random_range(-0.01..0.01f32)).max(0.0)))
            .collect();
        target.extend(descriptors(seed + 100, others));
        target
    }

    /// Nearest neighbours straight from the definition.
    fn reference_nearest(queries: &[MatchDescriptor], set: &[MatchDescriptor]) -> Vec<(u32, f32)> {
        queries
            .iter()
            .map(|q| {
                let j = (0..set.len())
                    .min_by(|&a, &b| {
                        descriptor_distance_sq(q, &set[a])
                            .total_cmp(&descriptor_distance_sq(q, &set[b]))
                    })
                    .unwrap();
                (j as u32, descriptor_distance_sq(q, &set[j]))
            })
            .collect()
    }

    fn assert_same_neighbours(found: &[(u32, f32)], reference: &[(u32, f32)]) {
        assert_eq!(found.len(), reference.len());
        for (f, r) in found.iter().zip(reference) {
            // Random descriptors have no ties: the same neighbour, the same distance to rounding.
            assert_eq!(f.0, r.0, "{f:?} vs {r:?}");
            assert!((f.1 - r.1).abs() <= 1e-5 * r.1.max(1e-3), "{f:?} vs {r:?}");
        }
    }

    #[test]
    fn nearest_neighbours_and_mutual_matches_agree_with_brute_force() {
        let source = descriptors(1, 1500);
        let target = related(&source, 600, 700, 2);
        let forward = reference_nearest(&source, &target);
        let backward = reference_nearest(&target, &source);
        assert_same_neighbours(&nearest_kd_tree(&source, &target), &forward);
        let (blocked_forward, blocked_backward) = nearest_brute_force_both_ways(&source, &target);
        assert_same_neighbours(&blocked_forward, &forward);
        assert_same_neighbours(&blocked_backward, &backward);
        let mutual = match_descriptors(&source, &target, &params(usize::MAX, 0));
        let pairs: Vec<(u32, u32)> = mutual.iter().map(|m| (m.source, m.target)).collect();
        let expected: Vec<(u32, u32)> = (0..source.len())
            .filter(|&s| backward[forward[s].0 as usize].0 as usize == s)
            .map(|s| (s as u32, forward[s].0))
            .collect();
        assert_eq!(pairs, expected);
        // Most noisy copies find their original; the unrelated descriptors rarely pair up.
        let copies_matched = pairs.iter().filter(|&&(s, t)| s == t).count();
        assert!(
            copies_matched > 500 && pairs.len() < copies_matched + 100,
            "{copies_matched} of {}",
            pairs.len()
        );
        assert!(mutual.iter().all(|m| m.mutual));
    }

    #[test]
    fn too_few_mutual_matches_are_topped_up_with_the_best_one_way_ones() {
        let source = descriptors(3, 400);
        let target = descriptors(4, 300);
        let mutual = match_descriptors(&source, &target, &params(usize::MAX, 0));
        let wanted = mutual.len() + 25;
        let topped = match_descriptors(&source, &target, &params(usize::MAX, wanted));
        assert_eq!(topped.len(), wanted);
        assert_eq!(&topped[..mutual.len()], &mutual[..]);
        let extra = &topped[mutual.len()..];
        assert!(extra.iter().all(|m| !m.mutual));
        assert!(
            extra
                .windows(2)
                .all(|w| w[0].distance_sq <= w[1].distance_sq)
        );
        // The extra ones are the smallest one-way distances there are.
        let forward = nearest_brute_force(&source, &target);
        let backward = nearest_brute_force(&target, &source);
        let mut one_way: Vec<f32> = forward
            .iter()
            .enumerate()
            .filter(|(s, (t, _))| backward[*t as usize].0 as usize != *s)
            .map(|(_, &(_, d))| d)
            .chain(
                backward
                    .iter()
                    .enumerate()
                    .filter(|(t, (s, _))| forward[*s as usize].0 as usize != *t)
                    .map(|(_, &(_, d))| d),
            )
            .collect();
        one_way.sort_by(f32::total_cmp);
        assert!((extra.last().unwrap().distance_sq - one_way[24]).abs() < 1e-6);
        assert!(match_descriptors(&source, &[], &params(usize::MAX, 10)).is_empty());
    }

    #[test]
    fn the_most_distinctive_descriptors_are_kept_for_matching() {
        // 900 alike ("walls") and 100 different ones ("corners").
        let mut list = vec![[0.1f32; MATCH_LEN]; 900];
        list.extend(descriptors(5, 100));
        let kept = most_distinctive(&list, 100);
        assert_eq!(kept, (900..1000).collect::<Vec<u32>>());
        assert_eq!(most_distinctive(&list, 5000).len(), 1000);
        // Matching a list with itself under a cap: every kept descriptor matches itself, and the
        // indices refer to the full list.
        let matches = match_descriptors(&list, &list, &params(100, 0));
        assert_eq!(matches.len(), 100);
        assert!(
            matches
                .iter()
                .all(|m| m.source == m.target && m.source >= 900)
        );
    }
}
