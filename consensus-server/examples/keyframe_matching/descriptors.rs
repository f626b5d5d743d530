//! Descriptor matching against the truth: the Hamming table of a pair, the matches under
//! several rules, and the oracle (B described exactly where A's keypoints fall).

use config::AlignmentConfig;
use registration::alignment::features::{Features, describe_at, hamming};

use crate::measure::Truth;
use crate::report::{Counted, median};

/// A keypoint index and its Hamming distance: the best and second best of a row or column.
pub type TwoBest = ((usize, u32), (usize, u32));

/// Hamming distances of every A descriptor to every B descriptor, and each side's two nearest.
pub struct DescriptorTable {
    pub nb: usize,
    /// Row per A keypoint.
    pub distances: Vec<u32>,
    pub forward: Vec<TwoBest>,
    pub backward: Vec<TwoBest>,
}

impl DescriptorTable {
    pub fn new(fa: &Features, fb: &Features) -> Self {
        let nb = fb.len();
        let distances: Vec<u32> = fa
            .descriptors
            .iter()
            .flat_map(|da| fb.descriptors.iter().map(move |db| hamming(da, db)))
            .collect();
        let two_best = |values: &mut dyn Iterator<Item = (usize, u32)>| {
            let (mut best, mut second) = ((usize::MAX, u32::MAX), (usize::MAX, u32::MAX));
            for (k, d) in values {
                if d < best.1 {
                    second = best;
                    best = (k, d);
                } else if d < second.1 {
                    second = (k, d);
                }
            }
            (best, second)
        };
        let forward: Vec<TwoBest> = (0..fa.len())
            .map(|i| two_best(&mut distances[i * nb..(i + 1) * nb].iter().copied().enumerate()))
            .collect();
        let backward: Vec<TwoBest> = (0..nb)
            .map(|j| two_best(&mut (0..fa.len()).map(|i| (i, distances[i * nb + j]))))
            .collect();
        Self {
            nb,
            distances,
            forward,
            backward,
        }
    }

    pub fn row(&self, i: usize) -> &[u32] {
        &self.distances[i * self.nb..(i + 1) * self.nb]
    }

    /// A's keypoint `i`'s mutual nearest neighbour in B when both directions pass the distance
    /// `cap` and the `ratio` test.
    pub fn mutual(&self, i: usize, cap: u32, ratio: f64) -> Option<usize> {
        let ((j, best), (_, second)) = self.forward[i];
        let ((back, bbest), (_, bsecond)) = *self.backward.get(j)?;
        let ok = |b: u32, s: u32| b <= cap && (b as f64) < ratio * s as f64;
        (back == i && ok(best, second) && ok(bbest, bsecond)).then_some(j)
    }

    /// A's keypoint `i`'s nearest neighbour in B, if B has any.
    pub fn nearest(&self, i: usize) -> Option<usize> {
        let j = self.forward[i].0.0;
        (j != usize::MAX).then_some(j)
    }
}

/// Matches under several rules, counted against the truth.
pub struct Matching {
    /// The configured rule (mutual, capped, ratio test).
    pub matches: Counted,
    /// The configured matches by their distance under the truth: <2, 2-3, 3-5, 5-10, >= 10 cm.
    pub distances_cm: [usize; 5],
    pub mutual_no_cap: Counted,
    pub mutual_ratio_08: Counted,
    pub one_way_nn: Counted,
}

impl Matching {
    pub fn of(truth: &Truth<'_>, table: &DescriptorTable, config: &AlignmentConfig) -> Self {
        let count = |filter: &dyn Fn(usize) -> Option<usize>| {
            let mut c = Counted::default();
            for i in 0..truth.a.len() {
                if let Some(j) = filter(i) {
                    c.total += 1;
                    c.correct += truth.is_correct(i, j) as usize;
                }
            }
            c
        };
        let configured = |i| table.mutual(i, config.max_hamming_distance, config.match_ratio);
        let mut distances_cm = [0usize; 5];
        for i in 0..truth.a.len() {
            if let Some(j) = configured(i) {
                let d = (truth.moved[i] - truth.b.camera_points[j]).norm() * 100.0;
                let bin = [2.0, 3.0, 5.0, 10.0]
                    .iter()
                    .position(|&e| d < e)
                    .unwrap_or(4);
                distances_cm[bin] += 1;
            }
        }
        Self {
            matches: count(&configured),
            distances_cm,
            mutual_no_cap: count(&|i| table.mutual(i, u32::MAX, 1.0 + 1e-9)),
            mutual_ratio_08: count(&|i| table.mutual(i, config.max_hamming_distance, 0.8)),
            one_way_nn: count(&|i| table.nearest(i)),
        }
    }
}

/// B described exactly where A's covisible keypoints fall (scale level from the depth ratio):
/// how different are descriptors of the same place, and would they beat the best of B's real
/// keypoints?
pub struct Oracle {
    pub described: usize,
    pub median_hamming: u32,
    pub wins: usize,
    /// Median distance of A's nearest real neighbour in B, over the same keypoints.
    pub nn_median_hamming: u32,
}

impl Oracle {
    pub fn of(truth: &Truth<'_>, table: &DescriptorTable, config: &AlignmentConfig) -> Self {
        let (fa, b) = (truth.a, &truth.pair.b);
        let mut places = Vec::new();
        let mut oracle_of = Vec::new();
        for i in 0..fa.len() {
            if let Some(pixel) = truth.seen_in_b(i) {
                let ratio = fa.camera_points[i].z / truth.moved[i].z;
                let level =
                    fa.keypoints[i].level as f64 + ratio.ln() / config.pyramid_scale_factor.ln();
                places.push((pixel.x, pixel.y, level.round().max(0.0) as usize));
                oracle_of.push(i);
            }
        }
        let oracle = describe_at(&b.rgb, &b.depth, &b.intrinsics, config, &places);
        let mut hammings = Vec::new();
        let mut wins = 0;
        for (&i, d) in oracle_of.iter().zip(&oracle) {
            if let Some(d) = d {
                let h = hamming(&fa.descriptors[i], d);
                hammings.push(h);
                wins += (h < table.forward[i].0.1) as usize;
            }
        }
        let mut nn_hamming: Vec<u32> = oracle_of.iter().map(|&i| table.forward[i].0.1).collect();
        Self {
            described: hammings.len(),
            median_hamming: median(&mut hammings).unwrap_or(0),
            wins,
            nn_median_hamming: median(&mut nn_hamming).unwrap_or(0),
        }
    }
}
