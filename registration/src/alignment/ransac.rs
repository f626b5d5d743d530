//! Coarse registration: RANSAC over 3-point rigid fits of matched 3-D keypoints.
//!
//! Descriptor matches between two views taken metres and tens of degrees apart are mostly wrong
//! (repeated texture, similar corners); three correct ones determine the rigid transform. Each
//! hypothesis is fitted with Umeyama (the geometry crate's, scale fixed to 1) to three matches and scored by
//! the matches it places within [`AlignmentConfig::ransac_inlier_distance_m`]; the best is refitted
//! to all its inliers. A rigid motion preserves distances, so a sample whose pairwise distances
//! disagree between the two views is discarded before fitting.

use geometry::se3::umeyama;
use nalgebra::{Isometry3, Point3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::alignment::AlignmentConfig;

/// Points per minimal sample of a rigid transform.
const SAMPLE_SIZE: usize = 3;
/// Refits on the inlier set: the first refit may gain inliers the 3-point fit just missed.
const INLIER_REFITS: usize = 2;

/// Result of the coarse registration.
#[derive(Debug, Clone)]
pub struct CoarseEstimate {
    /// Maps source points onto their target partners: the best hypothesis, refitted to its
    /// inliers while a refit keeps at least as many.
    pub target_from_source: Isometry3<f64>,
    /// Indices into the match list of the inliers of the final estimate.
    pub inliers: Vec<usize>,
    /// Hypotheses drawn.
    pub iterations: usize,
}

/// Finds the rigid transform that places the most `source` points on their `target` partners
/// (`source[k]` matches `target[k]`). `None` when no hypothesis could be formed (fewer than three
/// matches or only degenerate samples).
pub fn register(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    config: &AlignmentConfig,
) -> Option<CoarseEstimate> {
    let _span = tracing::debug_span!("ransac", matches = source.len()).entered();
    let n = source.len().min(target.len());
    if n < SAMPLE_SIZE {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(config.ransac_seed);
    let mut best: Option<(Isometry3<f64>, usize)> = None;
    let mut required_iterations = config.ransac_max_iterations;
    let mut iterations = 0;
    while iterations < required_iterations.min(config.ransac_max_iterations) {
        iterations += 1;
        let sample = draw_sample(&mut rng, n);
        if !is_good_sample(&sample, source, target, config) {
            continue;
        }
        let Some(hypothesis) = fit(&sample, source, target) else {
            continue;
        };
        let count = count_inliers(&hypothesis, source, target, config);
        if best
            .as_ref()
            .is_none_or(|(_, best_count)| count > *best_count)
        {
            best = Some((hypothesis, count));
            required_iterations =
                iterations_for_confidence(count as f64 / n as f64, config.ransac_confidence);
        }
    }
    let (mut estimate, _) = best?;
    let mut inliers = inlier_indices(&estimate, source, target, config);
    for _ in 0..INLIER_REFITS {
        if inliers.len() < SAMPLE_SIZE {
            break;
        }
        let Some(refit) = fit(&inliers, source, target) else {
            break;
        };
        let refit_inliers = inlier_indices(&refit, source, target, config);
        if refit_inliers.len() < inliers.len() {
            break;
        }
        estimate = refit;
        inliers = refit_inliers;
    }
    tracing::debug!(iterations, inliers = inliers.len(), "coarse estimate");
    Some(CoarseEstimate {
        target_from_source: estimate,
        inliers,
        iterations,
    })
}

/// Hypotheses needed to draw one all-inlier sample with probability `confidence` when a fraction
/// `inlier_ratio` of the matches are inliers.
fn iterations_for_confidence(inlier_ratio: f64, confidence: f64) -> usize {
    let all_inlier = inlier_ratio.powi(SAMPLE_SIZE as i32);
    if all_inlier >= 1.0 {
        return 1;
    }
    if all_inlier <= 0.0 {
        return usize::MAX;
    }
    ((1.0 - confidence).ln() / (1.0 - all_inlier).ln()).ceil() as usize
}

/// Three distinct indices below `n`.
fn draw_sample(rng: &mut ChaCha8Rng, n: usize) -> [usize; SAMPLE_SIZE] {
    let mut sample = [0; SAMPLE_SIZE];
    let mut filled = 0;
    while filled < SAMPLE_SIZE {
        let candidate = rng.random_range(0..n);
        if !sample[..filled].contains(&candidate) {
            sample[filled] = candidate;
            filled += 1;
        }
    }
    sample
}

/// Rejects samples that cannot give a well-conditioned or correct transform: points too close
/// together (or the same point twice), and pairs whose distance differs between the views by more
/// than two inlier tolerances (at least one of the two matches is then wrong).
fn is_good_sample(
    sample: &[usize; SAMPLE_SIZE],
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    config: &AlignmentConfig,
) -> bool {
    for a in 0..SAMPLE_SIZE {
        for b in a + 1..SAMPLE_SIZE {
            let (i, j) = (sample[a], sample[b]);
            let source_distance = (source[i] - source[j]).norm();
            let target_distance = (target[i] - target[j]).norm();
            if source_distance < config.ransac_min_sample_spread_m
                || (source_distance - target_distance).abs() > 2.0 * config.ransac_inlier_distance_m
            {
                return false;
            }
        }
    }
    true
}

fn fit(
    indices: &[usize],
    source: &[Point3<f64>],
    target: &[Point3<f64>],
) -> Option<Isometry3<f64>> {
    let from: Vec<Point3<f64>> = indices.iter().map(|&i| source[i]).collect();
    let to: Vec<Point3<f64>> = indices.iter().map(|&i| target[i]).collect();
    umeyama(&from, &to, false).map(|similarity| similarity.rigid())
}

fn is_inlier(
    estimate: &Isometry3<f64>,
    source: &Point3<f64>,
    target: &Point3<f64>,
    config: &AlignmentConfig,
) -> bool {
    (estimate * source - target).norm() <= config.ransac_inlier_distance_m
}

fn count_inliers(
    estimate: &Isometry3<f64>,
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    config: &AlignmentConfig,
) -> usize {
    source
        .iter()
        .zip(target)
        .filter(|(s, t)| is_inlier(estimate, s, t, config))
        .count()
}

fn inlier_indices(
    estimate: &Isometry3<f64>,
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    config: &AlignmentConfig,
) -> Vec<usize> {
    (0..source.len().min(target.len()))
        .filter(|&k| is_inlier(estimate, &source[k], &target[k], config))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn finds_a_large_motion_among_sixty_percent_outliers() {
        let truth = Isometry3::from_parts(
            Translation3::new(1.5, -0.4, 2.0),
            UnitQuaternion::from_euler_angles(0.3, 1.2, -0.5),
        );
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut random_point = || {
            Point3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(0.5..4.0),
            )
        };
        let source: Vec<Point3<f64>> = (0..100).map(|_| random_point()).collect();
        let target: Vec<Point3<f64>> = source
            .iter()
            .enumerate()
            .map(|(k, p)| if k % 5 < 2 { truth * p } else { random_point() })
            .collect();
        let estimate = register(&source, &target, &AlignmentConfig::default()).unwrap();
        assert_eq!(estimate.inliers.len(), 40);
        let error = estimate.target_from_source.inverse() * truth;
        assert!(error.translation.vector.norm() < 1e-9 && error.rotation.angle() < 1e-9);
        assert!(register(&source[..2], &target[..2], &AlignmentConfig::default()).is_none());
    }

    #[test]
    fn iteration_count_follows_the_inlier_ratio() {
        assert_eq!(iterations_for_confidence(1.0, 0.999), 1);
        assert_eq!(iterations_for_confidence(0.0, 0.999), usize::MAX);
        // 50 % inliers: 1 - 0.125 per draw; 52 draws for 99.9 %.
        assert_eq!(iterations_for_confidence(0.5, 0.999), 52);
    }
}
