//! Absolute trajectory error (ATE). Pairs are found by nearest timestamp exactly as evo does
//! (each pose of the shorter trajectory takes the nearest stamp of the longer one within
//! `max_dt`), the estimate is aligned to ground truth by Umeyama (SE(3) by default, Sim(3) for
//! monocular-scale methods, or none), and the translation errors are summarised.
//!
//! Joint multi-agent ATE: all agents' trajectories, already in one shared world frame, are aligned
//! with ONE transform; per-agent figures are reported both under that joint alignment and each
//! aligned on its own (the paper's protocol, which hides inter-agent misalignment).

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::MetricError;
use geometry::se3::{Similarity, umeyama};
use geometry::trajectory::Trajectory;

/// evo's default maximum timestamp difference for association, seconds.
pub const DEFAULT_MAX_DT: f64 = 0.01;

/// How the estimate is aligned to the ground truth before measuring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    /// Rotation + translation (metric RGB-D trajectories).
    #[default]
    Se3,
    /// Rotation + translation + scale.
    Sim3,
    /// Compare as-is (both already in the same frame).
    None,
}

impl std::str::FromStr for Alignment {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "se3" => Ok(Self::Se3),
            "sim3" => Ok(Self::Sim3),
            "none" => Ok(Self::None),
            other => Err(format!(
                "unknown alignment {other:?}: expected se3, sim3 or none"
            )),
        }
    }
}

/// Summary of translation errors, metres. `rmse` is the root mean square; `mean` is what the
/// published MAC-Ego3D code prints under the name "RMSE".
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AteStats {
    /// Root mean square error.
    pub rmse: f64,
    /// Mean error.
    pub mean: f64,
    /// Median error (the mean of the middle two for an even count).
    pub median: f64,
    /// Largest error.
    pub max: f64,
    /// Number of errors (associated pose pairs) summarised.
    pub pairs: usize,
}

impl AteStats {
    /// Summarises errors in metres. With no errors every statistic is NaN and `pairs` is 0.
    pub fn from_errors(errors: &[f64]) -> Self {
        if errors.is_empty() {
            return Self {
                rmse: f64::NAN,
                mean: f64::NAN,
                median: f64::NAN,
                max: f64::NAN,
                pairs: 0,
            };
        }
        let n = errors.len() as f64;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len().is_multiple_of(2) {
            0.5 * (sorted[mid - 1] + sorted[mid])
        } else {
            sorted[mid]
        };
        Self {
            rmse: (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt(),
            mean: errors.iter().sum::<f64>() / n,
            median,
            max: *sorted.last().expect("not empty"),
            pairs: errors.len(),
        }
    }
}

/// Index pairs `(ground_truth, estimate)` matched by nearest timestamp, evo's rule.
pub fn associate(
    ground_truth: &Trajectory,
    estimate: &Trajectory,
    max_dt: f64,
) -> Vec<(usize, usize)> {
    let gt_is_longer = ground_truth.len() > estimate.len();
    let (short, long) = if gt_is_longer {
        (estimate, ground_truth)
    } else {
        (ground_truth, estimate)
    };
    let mut order: Vec<usize> = (0..long.len()).collect();
    order.sort_by(|&a, &b| long.stamps[a].total_cmp(&long.stamps[b]));
    let sorted_stamps: Vec<f64> = order.iter().map(|&i| long.stamps[i]).collect();
    let mut pairs = Vec::new();
    for (i_short, &t) in short.stamps.iter().enumerate() {
        let k = sorted_stamps.partition_point(|&s| s < t);
        // Nearest of the two neighbours; on a tie the earlier stamp wins (numpy argmin's rule).
        let best = [k.checked_sub(1), (k < sorted_stamps.len()).then_some(k)]
            .into_iter()
            .flatten()
            .min_by(|&a, &b| {
                (sorted_stamps[a] - t)
                    .abs()
                    .total_cmp(&(sorted_stamps[b] - t).abs())
            });
        if let Some(j) = best
            && (sorted_stamps[j] - t).abs() <= max_dt
        {
            let i_long = order[j];
            pairs.push(if gt_is_longer {
                (i_long, i_short)
            } else {
                (i_short, i_long)
            });
        }
    }
    pairs
}

/// ATE of one trajectory: statistics, the alignment applied to the estimate, and per-pair errors.
#[derive(Debug, Clone)]
pub struct AteResult {
    /// Statistics of the errors after alignment.
    pub stats: AteStats,
    /// Maps estimate positions into the ground-truth frame.
    pub alignment: Similarity,
    /// (ground-truth timestamp, error in metres) per associated pair.
    pub errors: Vec<(f64, f64)>,
}

fn positions(traj: &Trajectory, indices: impl Iterator<Item = usize>) -> Vec<Point3<f64>> {
    indices
        .map(|i| Point3::from(traj.poses[i].translation.vector))
        .collect()
}

fn align(
    estimate: &[Point3<f64>],
    ground_truth: &[Point3<f64>],
    how: Alignment,
) -> Result<Similarity, MetricError> {
    match how {
        Alignment::None => Ok(Similarity::identity()),
        Alignment::Se3 | Alignment::Sim3 => umeyama(estimate, ground_truth, how == Alignment::Sim3)
            .ok_or_else(|| {
                MetricError::Trajectory(format!(
                    "cannot align: {} pairs, or all positions identical",
                    estimate.len()
                ))
            }),
    }
}

/// ATE of one estimated trajectory against its ground truth.
pub fn ate(
    ground_truth: &Trajectory,
    estimate: &Trajectory,
    how: Alignment,
    max_dt: f64,
) -> Result<AteResult, MetricError> {
    let pairs = associate(ground_truth, estimate, max_dt);
    if pairs.is_empty() {
        return Err(MetricError::Trajectory(format!(
            "no pose pairs within {max_dt} s: check that both files use the same clock"
        )));
    }
    let gt = positions(ground_truth, pairs.iter().map(|p| p.0));
    let est = positions(estimate, pairs.iter().map(|p| p.1));
    let alignment = align(&est, &gt, how)?;
    let errors: Vec<(f64, f64)> = pairs
        .iter()
        .zip(gt.iter().zip(&est))
        .map(|(p, (g, e))| {
            (
                ground_truth.stamps[p.0],
                (alignment.transform_point(e) - g).norm(),
            )
        })
        .collect();
    let values: Vec<f64> = errors.iter().map(|e| e.1).collect();
    Ok(AteResult {
        stats: AteStats::from_errors(&values),
        alignment,
        errors,
    })
}

/// Joint multi-agent ATE.
#[derive(Debug, Clone, Serialize)]
pub struct JointAte {
    /// All agents together under one alignment.
    pub joint: AteStats,
    /// Each agent's errors under the joint alignment.
    pub per_agent_joint_aligned: Vec<AteStats>,
    /// Each agent aligned on its own (the paper's per-agent protocol).
    pub per_agent_self_aligned: Vec<AteStats>,
    /// The one alignment applied to all agents' estimates; maps estimate positions into the
    /// ground-truth frame. Not serialised.
    #[serde(skip)]
    pub alignment: Similarity,
}

/// Joint ATE over several agents; `agents` holds (ground truth, estimate) per agent, the
/// estimates all expressed in the one shared world frame.
pub fn joint_ate(
    agents: &[(Trajectory, Trajectory)],
    how: Alignment,
    max_dt: f64,
) -> Result<JointAte, MetricError> {
    let mut all_gt = Vec::new();
    let mut all_est = Vec::new();
    let mut ranges = Vec::new();
    let mut per_agent_self_aligned = Vec::new();
    for (k, (gt, est)) in agents.iter().enumerate() {
        let pairs = associate(gt, est, max_dt);
        if pairs.is_empty() {
            return Err(MetricError::Trajectory(format!(
                "agent {k}: no pose pairs within {max_dt} s"
            )));
        }
        let start = all_gt.len();
        all_gt.extend(positions(gt, pairs.iter().map(|p| p.0)));
        all_est.extend(positions(est, pairs.iter().map(|p| p.1)));
        ranges.push(start..all_gt.len());
        per_agent_self_aligned.push(
            ate(gt, est, how, max_dt)
                .map_err(|e| MetricError::Trajectory(format!("agent {k}: {e}")))?
                .stats,
        );
    }
    let alignment = align(&all_est, &all_gt, how)?;
    let errors: Vec<f64> = all_est
        .iter()
        .zip(&all_gt)
        .map(|(e, g)| (alignment.transform_point(e) - g).norm())
        .collect();
    Ok(JointAte {
        joint: AteStats::from_errors(&errors),
        per_agent_joint_aligned: ranges
            .into_iter()
            .map(|r| AteStats::from_errors(&errors[r]))
            .collect(),
        per_agent_self_aligned,
        alignment,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    fn circle(n: usize, dt: f64, offset: f64) -> Trajectory {
        Trajectory::from_pairs((0..n).map(|i| {
            let a = i as f64 * 0.1;
            (
                offset + i as f64 * dt,
                Isometry3::translation(a.cos(), a.sin(), 0.3 * a),
            )
        }))
    }

    #[test]
    fn association_follows_evo() {
        let gt = circle(100, 0.01, 0.0);
        let est = Trajectory::from_pairs(
            (0..10).map(|i| (i as f64 * 0.1 + 0.004, Isometry3::identity())),
        );
        let pairs = associate(&gt, &est, 0.01);
        assert_eq!(pairs.len(), 10);
        assert!(
            pairs
                .iter()
                .enumerate()
                .all(|(i, p)| p.1 == i && p.0 == 10 * i)
        );
        assert!(associate(&gt, &est, 0.001).is_empty());
    }

    #[test]
    fn aligned_copy_has_zero_error_and_offsets_are_measured() {
        let gt = circle(50, 0.1, 0.0);
        let moved = Isometry3::from_parts(
            Translation3::new(3.0, -1.0, 2.0),
            UnitQuaternion::from_euler_angles(0.4, 0.1, -1.2),
        );
        let est = Trajectory::from_pairs(
            gt.stamps
                .iter()
                .zip(&gt.poses)
                .map(|(t, p)| (*t, moved * p)),
        );
        let r = ate(&gt, &est, Alignment::Se3, DEFAULT_MAX_DT).unwrap();
        assert!(r.stats.rmse < 1e-9 && r.stats.pairs == 50);
        let unaligned = ate(&gt, &est, Alignment::None, DEFAULT_MAX_DT).unwrap();
        assert!(unaligned.stats.rmse > 1.0);
        // A constant 5 cm offset on every other pose: errors exactly measurable without alignment.
        let bumped = Trajectory::from_pairs(gt.stamps.iter().zip(&gt.poses).enumerate().map(
            |(i, (t, p))| {
                (
                    *t,
                    if i % 2 == 0 {
                        Isometry3::from_parts(
                            Translation3::from(p.translation.vector + Vector3::new(0.05, 0.0, 0.0)),
                            p.rotation,
                        )
                    } else {
                        *p
                    },
                )
            },
        ));
        let s = ate(&gt, &bumped, Alignment::None, DEFAULT_MAX_DT)
            .unwrap()
            .stats;
        assert!(
            (s.rmse - 0.05 / 2f64.sqrt()).abs() < 1e-12
                && (s.mean - 0.025).abs() < 1e-12
                && (s.max - 0.05).abs() < 1e-12
        );
        assert!((s.median - 0.025).abs() < 1e-12);
    }

    #[test]
    fn joint_alignment_exposes_inter_agent_misalignment() {
        let gt_a = circle(40, 0.1, 0.0);
        let gt_b = circle(40, 0.1, 10.0);
        // Agent b's estimate is shifted by 20 cm relative to agent a: each alone aligns perfectly,
        // jointly they cannot.
        let shifted = Trajectory::from_pairs(
            gt_b.stamps
                .iter()
                .zip(&gt_b.poses)
                .map(|(t, p)| (*t, Isometry3::translation(0.2, 0.0, 0.0) * p)),
        );
        let j = joint_ate(
            &[(gt_a.clone(), gt_a.clone()), (gt_b.clone(), shifted)],
            Alignment::Se3,
            DEFAULT_MAX_DT,
        )
        .unwrap();
        assert!(j.per_agent_self_aligned.iter().all(|s| s.rmse < 1e-9));
        assert!(j.joint.rmse > 0.05, "joint {}", j.joint.rmse);
        assert_eq!(j.joint.pairs, 80);
        let clean = joint_ate(
            &[(gt_a.clone(), gt_a), (gt_b.clone(), gt_b)],
            Alignment::Se3,
            DEFAULT_MAX_DT,
        )
        .unwrap();
        assert!(clean.joint.rmse < 1e-9);
    }

    #[test]
    fn real_data_ate_matches_evo_golden_value() {
        let dir = datasets::shared_data::require("reference/tum-trajectories");
        let gt = Trajectory::read_tum(&dir.join("freiburg1_xyz-groundtruth.txt")).unwrap();
        let est = Trajectory::read_tum(&dir.join("freiburg1_xyz-rgbdslam.txt")).unwrap();
        let r = ate(&gt, &est, Alignment::Se3, DEFAULT_MAX_DT).unwrap();
        // evo 1.38.1: 785 pairs, RMSE 0.013470, mean 0.012024, median 0.011183, max 0.034760.
        assert_eq!(r.stats.pairs, 785);
        assert!(
            (r.stats.rmse - 0.013470).abs() < 5e-7,
            "ATE RMSE {} (evo: 0.013470)",
            r.stats.rmse
        );
        assert!(
            (r.stats.mean - 0.012024).abs() < 5e-7,
            "mean {}",
            r.stats.mean
        );
        assert!(
            (r.stats.median - 0.011183).abs() < 5e-7,
            "median {}",
            r.stats.median
        );
        assert!((r.stats.max - 0.034760).abs() < 5e-7, "max {}", r.stats.max);
        let wide = ate(&gt, &est, Alignment::Se3, 0.02).unwrap();
        assert!(
            (wide.stats.rmse - 0.013473).abs() < 5e-7,
            "ATE RMSE at 0.02 s {}",
            wide.stats.rmse
        );
    }
}
