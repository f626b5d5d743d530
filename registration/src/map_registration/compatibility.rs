//! Stage 4a: hypotheses from the compatibility graph of the correspondences, the estimator that
//! survives far more than 95 % wrong correspondences.
//!
//! A rigid motion preserves distances, so two right correspondences `(s_i, t_i)`, `(s_j, t_j)`
//! always satisfy `| |s_i - s_j| - |t_i - t_j| | <= tolerance`: they are *compatible*. The right
//! correspondences are therefore a clique of the graph whose edges join compatible pairs, and
//! finding the transform is finding a large clique (TEASER++, MAC). Wrong correspondences are
//! compatible with each other only by chance (a few percent of pairs at room scale), so their
//! cliques stay small, while the right ones, however few among thousands, are all joined to each
//! other. RANSAC's chance of drawing three of them falls with the cube of their fraction (at 2 %
//! of 5000, one sample in 125 000); the graph finds them from any one of them.
//!
//! The graph is held as one bit set per correspondence (5000 correspondences: 3 MB), built in
//! parallel. Each correspondence is scored by its second-order compatibility (SC^2, Chen et al.
//! 2022): the number of edges among its neighbours, `sum_j in N(i) |N(i) & N(j)|`, one AND and
//! popcount per word. A right correspondence's neighbours include all the other right ones, which
//! are all joined to each other, so its score grows with the square of their number; a wrong
//! one's neighbours are a chance set, sparsely joined. The best-scored correspondences are the
//! seeds; from each seed a clique is grown greedily, its neighbours taken in order of how many
//! neighbours they share with it (again SC^2) and kept when compatible with every member so far.
//! A seed already inside an earlier clique adds nothing and is skipped, so the seeds explore
//! different structures (the right transform, and the transforms of a symmetric room's turns,
//! which the ambiguity test needs to see). Each clique of at least three becomes a hypothesis
//! for [`super::consistency`], which fits, counts and locally optimises it like a RANSAC sample.
//!
//! Deterministic: ties are broken by index, and nothing depends on the thread count.

use nalgebra::Point3;
use rayon::prelude::*;

/// Rows per rayon task while building the graph.
const ROWS_PER_TASK: usize = 16;

/// Parameters of the clique search (lengths in metres).
#[derive(Debug, Clone, PartialEq)]
pub struct CliqueParams {
    /// Two correspondences are compatible when their lengths differ by at most this.
    pub tolerance_m: f64,
    /// Seeds tried at most.
    pub max_seeds: usize,
    /// A clique stops growing at this size (enough to fit and score a transform; the local
    /// optimisation then gathers every supporter).
    pub max_clique: usize,
}

/// The compatibility graph: one bit set per correspondence.
pub struct CompatibilityGraph {
    n: usize,
    words: usize,
    bits: Vec<u64>,
}

/// Number of set bits of `a & b`, with the processor's popcount where it has one.
fn common_bits(a: &[u64], b: &[u64]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the feature was detected just above.
            return unsafe { common_bits_popcnt(a, b) };
        }
    }
    a.iter().zip(b).map(|(x, y)| (x & y).count_ones()).sum()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn common_bits_popcnt(a: &[u64], b: &[u64]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x & y).count_ones()).sum()
}

impl CompatibilityGraph {
    /// The graph of `source[k] <-> target[k]`: `i` and `j` are joined when their lengths differ
    /// by at most `tolerance_m` (no self loops).
    pub fn new(source: &[Point3<f64>], target: &[Point3<f64>], tolerance_m: f64) -> Self {
        let n = source.len().min(target.len());
        let words = n.div_ceil(64);
        let mut bits = vec![0u64; n * words];
        if words > 0 {
            bits.par_chunks_mut(words * ROWS_PER_TASK)
                .enumerate()
                .for_each(|(chunk, rows)| {
                    for (r, row) in rows.chunks_mut(words).enumerate() {
                        let i = chunk * ROWS_PER_TASK + r;
                        let (si, ti) = (source[i], target[i]);
                        for j in 0..n {
                            let ds = (source[j] - si).norm();
                            let dt = (target[j] - ti).norm();
                            if j != i && (ds - dt).abs() <= tolerance_m {
                                row[j / 64] |= 1 << (j % 64);
                            }
                        }
                    }
                });
        }
        Self { n, words, bits }
    }

    /// Number of correspondences (vertices).
    pub fn len(&self) -> usize {
        self.n
    }

    /// True when the graph has no correspondences.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    fn row(&self, i: usize) -> &[u64] {
        &self.bits[i * self.words..(i + 1) * self.words]
    }

    /// Whether correspondences `i` and `j` are joined (false for `i == j`). Both must be below
    /// [`Self::len`].
    pub fn compatible(&self, i: usize, j: usize) -> bool {
        self.row(i)[j / 64] >> (j % 64) & 1 == 1
    }

    /// The neighbours of `i`, ascending.
    pub fn neighbours(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        self.row(i).iter().enumerate().flat_map(|(w, &word)| {
            let mut word = word;
            std::iter::from_fn(move || {
                if word == 0 {
                    return None;
                }
                let bit = word.trailing_zeros() as usize;
                word &= word - 1;
                Some(w * 64 + bit)
            })
        })
    }

    /// Neighbours `i` and `j` share.
    pub fn common(&self, i: usize, j: usize) -> u32 {
        common_bits(self.row(i), self.row(j))
    }

    /// Every node's second-order compatibility: the edges among its neighbours (counted twice).
    pub fn second_order_scores(&self) -> Vec<u64> {
        (0..self.n)
            .into_par_iter()
            .map(|i| {
                self.neighbours(i)
                    .map(|j| u64::from(self.common(i, j)))
                    .sum()
            })
            .collect()
    }

    /// A clique containing `seed`: its neighbours in order of shared neighbours (most first,
    /// then index), each kept when joined to every member so far, up to `max_size` members.
    pub fn grow_clique(&self, seed: usize, max_size: usize) -> Vec<u32> {
        let mut candidates: Vec<(u32, usize)> = self
            .neighbours(seed)
            .map(|j| (self.common(seed, j), j))
            .collect();
        candidates.sort_unstable_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut clique = vec![seed];
        for (_, j) in candidates {
            if clique.len() >= max_size {
                break;
            }
            if clique.iter().all(|&m| self.compatible(m, j)) {
                clique.push(j);
            }
        }
        clique.into_iter().map(|k| k as u32).collect()
    }
}

/// Cliques of the correspondences `source[k] <-> target[k]` (see the module documentation),
/// from the best-seeded first; each has at least three members.
pub fn clique_hypotheses(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    params: &CliqueParams,
) -> Vec<Vec<u32>> {
    let graph = CompatibilityGraph::new(source, target, params.tolerance_m);
    let scores = graph.second_order_scores();
    let mut order: Vec<usize> = (0..graph.len()).filter(|&i| scores[i] > 0).collect();
    order.sort_unstable_by(|&a, &b| scores[b].cmp(&scores[a]).then(a.cmp(&b)));
    let mut covered = vec![false; graph.len()];
    let mut cliques = Vec::new();
    for seed in order {
        if cliques.len() >= params.max_seeds {
            break;
        }
        if covered[seed] {
            continue;
        }
        let clique = graph.grow_clique(seed, params.max_clique);
        for &k in &clique {
            covered[k as usize] = true;
        }
        if clique.len() >= 3 {
            cliques.push(clique);
        }
    }
    cliques
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_graph_joins_pairs_that_keep_their_length() {
        let source = [
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 2.0, 0.0),
        ];
        // 0 and 1 keep their distance; 2 moved by 0.5 m.
        let target = [
            Point3::new(5.0, 0.0, 0.0),
            Point3::new(5.0, 1.0, 0.0),
            Point3::new(5.0, 0.0, 2.5),
        ];
        let graph = CompatibilityGraph::new(&source, &target, 0.1);
        assert!(graph.compatible(0, 1) && graph.compatible(1, 0));
        assert!(!graph.compatible(0, 2) && !graph.compatible(0, 0));
        assert_eq!(graph.neighbours(0).collect::<Vec<_>>(), vec![1]);
        assert_eq!(graph.common(0, 1), 0);
    }

    #[test]
    fn a_clique_of_two_percent_is_found_among_five_thousand() {
        let truth = Isometry3::from_parts(
            Translation3::new(2.0, -1.0, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 2.5),
        );
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let point = |rng: &mut ChaCha8Rng| {
            Point3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(0.0..2.5),
            )
        };
        let (mut source, mut target, mut right) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..5000 {
            let s = point(&mut rng);
            let is_right = k % 50 == 7;
            let t = if is_right {
                truth * s + Vector3::from_fn(|_, _| rng.random_range(-0.02..0.02))
            } else {
                truth * point(&mut rng)
            };
            source.push(s);
            target.push(t);
            right.push(is_right);
        }
        let params = CliqueParams {
            tolerance_m: 0.1,
            max_seeds: 8,
            max_clique: 200,
        };
        let cliques = clique_hypotheses(&source, &target, &params);
        let first = &cliques[0];
        let members_right = first.iter().filter(|&&k| right[k as usize]).count();
        assert!(
            members_right >= 90 && members_right + 5 >= first.len(),
            "{members_right} right of {}",
            first.len()
        );
        assert_eq!(clique_hypotheses(&source, &target, &params), cliques);
    }
}
