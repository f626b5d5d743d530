//! Duplicate Gaussians of overlapping agents' maps fused into one (docs/method.md, The consensus:
//! the merged map).
//!
//! Where two agents mapped the same surface, each map holds its own copy, a few centimetres from
//! the other's. Keeping both doubles the Gaussians there and blurs the surface; keeping one side
//! throws away what the other agent saw. Fusing keeps one Gaussian per pair of duplicates that
//! carries both: a Gaussian of one agent and a Gaussian of another are duplicates when each is
//! the other's nearest Gaussian among that agent's and they are closer than `radius_m`. The fused
//! Gaussian is their moment-matched mixture (weights: opacities): the mean and covariance of the
//! two together, the weighted colour, and the opacity both had together where they overlapped
//! (`1 - (1 - a)(1 - b)`). Gaussians with no duplicate stay as they are, so a surface only one
//! agent saw is never lost. Agents are fused in turn: the third agent's Gaussians pair with the
//! map fused so far.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Quaternion, Rotation3, SymmetricEigen, UnitQuaternion, Vector3};
use splats::GaussianCloud;

use super::merge::WorldAgentMap;

/// Highest opacity a fused Gaussian gets: the mapper's opacities stay below it as well, and
/// the logit of a value nearer 1 would be a step Adam needs hundreds of iterations to undo.
const MAX_FUSED_OPACITY: f32 = 0.995;
/// Smallest standard deviation a fused Gaussian keeps along any axis (metres): a mixture of two
/// flat discs is flat too, and its eigenvalue along the normal can round to zero or below.
const MIN_FUSED_SCALE_M: f64 = 1e-5;

/// What [`fuse`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FuseStats {
    /// Pairs of duplicates fused into one Gaussian each.
    pub fused_pairs: usize,
}

/// Every agent's map in one cloud, duplicates across agents fused (module documentation).
pub fn fuse(maps: &[WorldAgentMap], radius_m: f64) -> (GaussianCloud, FuseStats) {
    let radius_sq = (radius_m * radius_m) as f32;
    let mut fused = GaussianCloud::default();
    let mut stats = FuseStats::default();
    for map in maps {
        if fused.is_empty() || map.cloud.is_empty() {
            fused.extend_from(&map.cloud);
            continue;
        }
        let pairs = mutual_nearest(&fused, &map.cloud, radius_sq);
        let mut taken = vec![false; map.cloud.len()];
        for &(into, from) in &pairs {
            fuse_into(&mut fused, into, &map.cloud, from);
            taken[from] = true;
        }
        stats.fused_pairs += pairs.len();
        let rest: Vec<bool> = taken.iter().map(|t| !t).collect();
        fused.extend_from(&map.cloud.select(&rest));
    }
    (fused, stats)
}

/// Pairs `(index in a, index in b)` whose Gaussians are each other's nearest and closer than
/// `sqrt(radius_sq)`.
fn mutual_nearest(a: &GaussianCloud, b: &GaussianCloud, radius_sq: f32) -> Vec<(usize, usize)> {
    let a_tree: ImmutableKdTree<f32, 3> =
        ImmutableKdTree::new_from_slice(&a.means).expect("Gaussian count fits in u32");
    let b_tree: ImmutableKdTree<f32, 3> =
        ImmutableKdTree::new_from_slice(&b.means).expect("Gaussian count fits in u32");
    b.means
        .iter()
        .enumerate()
        .filter_map(|(j, mean)| {
            let nearest = a_tree
                .query(mean)
                .nearest_one::<SquaredEuclidean<f32>>()
                .execute();
            if nearest.distance > radius_sq {
                return None;
            }
            let i = nearest.item as usize;
            let back = b_tree
                .query(&a.means[i])
                .nearest_one::<SquaredEuclidean<f32>>()
                .execute();
            (back.item as usize == j).then_some((i, j))
        })
        .collect()
}

fn sigmoid(logit: f32) -> f32 {
    1.0 / (1.0 + (-logit).exp())
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

fn covariance(log_scales: [f32; 3], quaternion: [f32; 4]) -> Matrix3<f64> {
    let [w, x, y, z] = quaternion.map(f64::from);
    let rotation = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
    let variances = Vector3::from(log_scales.map(|s| (2.0 * f64::from(s)).exp()));
    let r = rotation.to_rotation_matrix().into_inner();
    r * Matrix3::from_diagonal(&variances) * r.transpose()
}

/// Replaces Gaussian `into` of `target` by the moment-matched mixture of itself and Gaussian
/// `from` of `source` (module documentation).
fn fuse_into(target: &mut GaussianCloud, into: usize, source: &GaussianCloud, from: usize) {
    let alpha = [
        sigmoid(target.opacity_logits[into]),
        sigmoid(source.opacity_logits[from]),
    ];
    let total = alpha[0] + alpha[1];
    // Two transparent Gaussians: equal weights rather than a division by (almost) nothing.
    let weights: [f64; 2] = if total > f32::EPSILON {
        [f64::from(alpha[0] / total), f64::from(alpha[1] / total)]
    } else {
        [0.5, 0.5]
    };
    let means = [
        Vector3::from(target.means[into].map(f64::from)),
        Vector3::from(source.means[from].map(f64::from)),
    ];
    let covariances = [
        covariance(target.log_scales[into], target.quaternions[into]),
        covariance(source.log_scales[from], source.quaternions[from]),
    ];
    let mean = means[0] * weights[0] + means[1] * weights[1];
    let mut mixed = Matrix3::zeros();
    for k in 0..2 {
        let offset = means[k] - mean;
        mixed += (covariances[k] + offset * offset.transpose()) * weights[k];
    }
    let (log_scales, quaternion) = scales_and_rotation(&mixed);
    let colour = [0, 1, 2].map(|c| {
        (f64::from(target.colours[into][c]) * weights[0]
            + f64::from(source.colours[from][c]) * weights[1]) as f32
    });
    let opacity = (1.0 - (1.0 - alpha[0]) * (1.0 - alpha[1])).min(MAX_FUSED_OPACITY);
    target.means[into] = [mean.x as f32, mean.y as f32, mean.z as f32];
    target.log_scales[into] = log_scales;
    target.quaternions[into] = quaternion;
    target.opacity_logits[into] = logit(opacity);
    target.colours[into] = colour;
}

/// Log standard deviations and `[w, x, y, z]` rotation of a covariance matrix.
fn scales_and_rotation(covariance: &Matrix3<f64>) -> ([f32; 3], [f32; 4]) {
    let eigen = SymmetricEigen::new(*covariance);
    let mut axes = eigen.eigenvectors;
    // A rotation, not a reflection: the third axis follows from the first two.
    if axes.determinant() < 0.0 {
        axes.set_column(2, &(-axes.column(2)));
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(axes));
    let log_scales = [0, 1, 2].map(|k| {
        (eigen.eigenvalues[k]
            .max(MIN_FUSED_SCALE_M.powi(2))
            .sqrt()
            .ln()) as f32
    });
    let q = rotation.into_inner();
    (log_scales, [q.w as f32, q.i as f32, q.j as f32, q.k as f32])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::merge::tests::wall;

    fn agent(agent_id: u32, cloud: GaussianCloud) -> WorldAgentMap {
        WorldAgentMap {
            agent_id,
            cloud,
            observers: Vec::new(),
        }
    }

    #[test]
    fn overlapping_copies_become_one_and_the_rest_stays() {
        // Agent 0 maps x in [0, 1), agent 1 x in [0.5, 1.5), 4 mm deeper: 50 duplicates.
        let maps = [
            agent(0, wall(0.0, 100, 2.0)),
            agent(1, wall(0.5, 100, 2.004)),
        ];
        let (fused, stats) = fuse(&maps, 0.02);
        assert_eq!(stats.fused_pairs, 50);
        assert_eq!(fused.len(), 150);
        // A fused Gaussian sits between its two copies (equal opacities: half way), and is as
        // opaque as the two were together.
        let at = fused
            .means
            .iter()
            .position(|m| (m[0] - 0.7).abs() < 1e-4)
            .unwrap();
        assert!(
            (fused.means[at][2] - 2.002).abs() < 1e-5,
            "{:?}",
            fused.means[at]
        );
        assert!((sigmoid(fused.opacity_logits[at]) - 0.75).abs() < 1e-5);
        // Outside the overlap every Gaussian is kept as it was.
        assert!(fused.means.iter().any(|m| m[0] < 0.1));
        assert!(fused.means.iter().any(|m| m[0] > 1.4));
        // Farther apart than the radius: nothing is fused.
        let apart = [agent(0, wall(0.0, 10, 2.0)), agent(1, wall(0.0, 10, 2.1))];
        assert_eq!(fuse(&apart, 0.02).0.len(), 20);
    }

    #[test]
    fn the_fused_covariance_holds_both_gaussians() {
        let mut a = GaussianCloud::default();
        // A disc in the xy plane (sigma 1 cm, 0.1 mm thick), turned an eighth about z.
        let half_angle = std::f32::consts::FRAC_PI_8;
        a.push(
            [0.0, 0.0, 0.0],
            [0.01f32.ln(), 0.01f32.ln(), 1e-4f32.ln()],
            [half_angle.cos(), 0.0, 0.0, half_angle.sin()],
            logit(0.5),
            [1.0, 0.0, 0.0],
        );
        let mut b = a.clone();
        b.means[0] = [0.0, 0.0, 0.002];
        b.colours[0] = [0.0, 0.0, 1.0];
        b.opacity_logits[0] = logit(0.5);
        fuse_into(&mut a, 0, &b, 0);
        let sigma = covariance(a.log_scales[0], a.quaternions[0]);
        // In plane as before; along z the two centres 2 mm apart: sigma_z^2 = 1e-8 + 1e-6.
        assert!((sigma[(0, 0)] - 1e-4).abs() < 1e-9, "{sigma}");
        assert!((sigma[(2, 2)] - (1e-8 + 1e-6)).abs() < 1e-10, "{sigma}");
        assert!(sigma[(0, 2)].abs() < 1e-10);
        assert_eq!(a.colours[0], [0.5, 0.0, 0.5]);
        assert!((a.means[0][2] - 0.001).abs() < 1e-7);
    }
}
