//! One world map from the agents' maps (docs/method.md, The consensus: the merged map).
//!
//! Each agent optimised its map for its own views. Where two agents mapped the same surface, the
//! two copies sit a few centimetres apart (the residual misalignment of the pose graph); rendered
//! together they blur, and each copy occludes the other from every view. Where the maps overlap,
//! each place keeps the Gaussians of the agent whose keyframes saw it from nearest: its samples
//! there are the finest, and its map was fitted from there. Outside the overlap every agent's
//! Gaussians stay, so nothing only one agent saw is lost.

use config::MergeConfig;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::Point3;
use splats::GaussianCloud;

/// One agent's map in the world frame and where its keyframes saw it from.
pub struct WorldAgentMap {
    pub agent_id: u32,
    pub cloud: GaussianCloud,
    /// World positions of the agent's placed keyframe cameras.
    pub observers: Vec<Point3<f64>>,
}

/// What [`merge`] kept and left out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MergeStats {
    /// Gaussians in the overlap of two agents' maps.
    pub overlapping: usize,
    /// Of those, left to an agent that saw their place from nearer.
    pub left_to_nearer_observer: usize,
}

/// The merged map: every agent's map, where maps overlap only the Gaussians of the nearest
/// observer (`config.nearest_observer`; off: all of them).
pub fn merge(maps: &[WorldAgentMap], config: &MergeConfig) -> (GaussianCloud, MergeStats) {
    let mut merged = GaussianCloud::default();
    let mut stats = MergeStats::default();
    let judged = maps
        .iter()
        .filter(|m| !m.observers.is_empty() && !m.cloud.is_empty())
        .count();
    if !config.nearest_observer || judged < 2 {
        for map in maps {
            merged.extend_from(&map.cloud);
        }
        return (merged, stats);
    }
    let radius_sq = (config.overlap_radius_m * config.overlap_radius_m) as f32;
    for (index, map) in maps.iter().enumerate() {
        let others: Vec<&WorldAgentMap> = maps
            .iter()
            .enumerate()
            .filter(|(other, m)| *other != index && m.agent_id != map.agent_id)
            .map(|(_, m)| m)
            .collect();
        let other_means: Vec<[f32; 3]> = others
            .iter()
            .flat_map(|m| m.cloud.means.iter().copied())
            .collect();
        let other_observers: Vec<[f64; 3]> = others
            .iter()
            .flat_map(|m| m.observers.iter().map(|p| [p.x, p.y, p.z]))
            .collect();
        let own_observers: Vec<[f64; 3]> = map.observers.iter().map(|p| [p.x, p.y, p.z]).collect();
        // An agent with no placed keyframe (or nobody else to compare with) keeps everything.
        if other_means.is_empty() || other_observers.is_empty() || own_observers.is_empty() {
            merged.extend_from(&map.cloud);
            continue;
        }
        let means_tree: ImmutableKdTree<f32, 3> =
            ImmutableKdTree::new_from_slice(&other_means).expect("Gaussian count fits in u32");
        let own_tree: ImmutableKdTree<f64, 3> =
            ImmutableKdTree::new_from_slice(&own_observers).expect("keyframe count fits in u32");
        let other_tree: ImmutableKdTree<f64, 3> =
            ImmutableKdTree::new_from_slice(&other_observers).expect("keyframe count fits in u32");
        let keep: Vec<bool> = map
            .cloud
            .means
            .iter()
            .map(|mean| {
                let nearest_other = means_tree
                    .query(mean)
                    .nearest_one::<SquaredEuclidean<f32>>()
                    .execute();
                if nearest_other.distance > radius_sq {
                    return true;
                }
                stats.overlapping += 1;
                let at = mean.map(f64::from);
                let own = own_tree
                    .query(&at)
                    .nearest_one::<SquaredEuclidean<f64>>()
                    .execute()
                    .distance;
                let other = other_tree
                    .query(&at)
                    .nearest_one::<SquaredEuclidean<f64>>()
                    .execute()
                    .distance;
                let kept = own <= other;
                if !kept {
                    stats.left_to_nearer_observer += 1;
                }
                kept
            })
            .collect();
        merged.extend_from(&map.cloud.select(&keep));
    }
    (merged, stats)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// `count` Gaussians on the plane z = `depth`, spaced 1 cm along x from `x0`.
    pub(in crate::engine) fn wall(x0: f32, count: usize, depth: f32) -> GaussianCloud {
        let mut cloud = GaussianCloud::default();
        for i in 0..count {
            cloud.means.push([x0 + 0.01 * i as f32, 0.0, depth]);
            cloud.log_scales.push([-5.0; 3]);
            cloud.quaternions.push([1.0, 0.0, 0.0, 0.0]);
            cloud.opacity_logits.push(0.0);
            cloud.colours.push([0.5; 3]);
        }
        cloud
    }

    #[test]
    fn overlap_keeps_the_nearest_observers_copy_and_everything_outside_it() {
        // Agent 0 maps x in [0, 1) from a camera at x = 0.205; agent 1 maps x in [0.5, 1.5)
        // from x = 1.2, 2 cm deeper (misaligned). On [0.5, 1) both mapped the wall; with a
        // 2.1 cm radius only the copies straight behind each other overlap.
        let maps = [
            WorldAgentMap {
                agent_id: 0,
                cloud: wall(0.0, 100, 2.0),
                observers: vec![Point3::new(0.205, 0.0, 0.0)],
            },
            WorldAgentMap {
                agent_id: 1,
                cloud: wall(0.5, 100, 2.02),
                observers: vec![Point3::new(1.2, 0.0, 0.0)],
            },
        ];
        let config = MergeConfig {
            nearest_observer: true,
            overlap_radius_m: 0.021,
            ..MergeConfig::default()
        };
        let (merged, stats) = merge(&maps, &config);
        // Every Gaussian of [0.5, 1) is in the overlap, 50 from each agent.
        assert_eq!(stats.overlapping, 100);
        // The cameras' midpoint is x = 0.7025: agent 0 keeps [0.5, 0.7], agent 1 [0.71, 1).
        assert_eq!(stats.left_to_nearer_observer, 50);
        assert_eq!(merged.len(), 150);
        for mean in &merged.means {
            let from_agent_1 = mean[2] > 2.01;
            if (0.5..1.0).contains(&mean[0]) {
                assert_eq!(from_agent_1, mean[0] > 0.7025, "{mean:?}");
            }
        }
        // Outside the overlap nothing is lost.
        assert!(merged.means.iter().any(|m| m[0] < 0.1));
        assert!(merged.means.iter().any(|m| m[0] > 1.4));

        let off = MergeConfig {
            nearest_observer: false,
            ..config
        };
        let (all, stats) = merge(&maps, &off);
        assert_eq!(all.len(), 200);
        assert_eq!(stats, MergeStats::default());
    }

    #[test]
    fn a_single_agent_or_one_without_placed_keyframes_keeps_its_whole_map() {
        let alone = [WorldAgentMap {
            agent_id: 0,
            cloud: wall(0.0, 10, 2.0),
            observers: vec![Point3::origin()],
        }];
        assert_eq!(merge(&alone, &MergeConfig::default()).0.len(), 10);
        let unjudged = [
            WorldAgentMap {
                agent_id: 0,
                cloud: wall(0.0, 10, 2.0),
                observers: vec![Point3::origin()],
            },
            WorldAgentMap {
                agent_id: 1,
                cloud: wall(0.0, 10, 2.0),
                observers: Vec::new(),
            },
        ];
        assert_eq!(merge(&unjudged, &MergeConfig::default()).0.len(), 20);
    }
}
