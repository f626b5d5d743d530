//! Matching: mutual nearest neighbours in Hamming distance with Lowe's ratio test.

use super::{Descriptor, Features};
use crate::alignment::AlignmentConfig;

/// Bits in which two descriptors differ.
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

/// Best and second-best distance and the best index of `query` among `candidates`.
pub(super) fn two_nearest(
    query: &Descriptor,
    candidates: &[Descriptor],
) -> Option<(usize, u32, u32)> {
    let (mut best_index, mut best, mut second) = (None, u32::MAX, u32::MAX);
    for (index, candidate) in candidates.iter().enumerate() {
        let distance = hamming(query, candidate);
        if distance < best {
            second = best;
            best = distance;
            best_index = Some(index);
        } else if distance < second {
            second = distance;
        }
    }
    best_index.map(|index| (index, best, second))
}

/// Matches `(source index, target index)`: mutual nearest neighbours in Hamming distance that
/// pass the distance limit and Lowe's ratio test in both directions. Brute force: 1000 x 1000
/// descriptors are two million 256-bit comparisons, a few milliseconds.
///
/// Mutual only: every keypoint's nearest neighbour in either direction keeps about twice the
/// correct matches but four times the wrong ones, which uniform 3-point RANSAC cannot sort out
/// within its budget (on the synthetic pairs of `examples/keyframe_matching`, fewer pairs aligned:
/// docs/benchmarks.md).
pub fn match_features(
    source: &Features,
    target: &Features,
    config: &AlignmentConfig,
) -> Vec<(usize, usize)> {
    let passes = |best: u32, second: u32| {
        best <= config.max_hamming_distance && (best as f64) < config.match_ratio * second as f64
    };
    let backward: Vec<Option<usize>> = target
        .descriptors
        .iter()
        .map(|d| {
            two_nearest(d, &source.descriptors)
                .filter(|&(_, best, second)| passes(best, second))
                .map(|(index, _, _)| index)
        })
        .collect();
    source
        .descriptors
        .iter()
        .enumerate()
        .filter_map(|(i, d)| {
            let (j, best, second) = two_nearest(d, &target.descriptors)?;
            (passes(best, second) && backward[j] == Some(i)).then_some((i, j))
        })
        .collect()
}
