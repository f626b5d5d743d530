//! What the engine produces at the end of a run: the merged world map, the joint refinement's
//! problem (and its refined poses taken back), and each agent's world trajectory.

use std::collections::BTreeMap;

use config::MergeConfig;
use geometry::correction::{CorrectionField, correction};
use geometry::se3::isometry_from_tum;
use nalgebra::{Isometry3, Point3};
use splats::{GaussianCloud, RigidTransform};

use super::fuse::fuse;
use super::merge::{WorldAgentMap, merge};
use super::{Engine, KeyframeInfo};
use crate::place_recognition::KeyframeRef;
use crate::refinement::{PoseEdge, RefinementProblem, RefinementView};

impl Engine {
    /// The merged map in the world frame: each linked agent's final map moved by its
    /// `world_from_agent`, or, for an agent that sent none, its keyframes' Gaussians moved by each
    /// keyframe's correction. When no joint refinement follows (`refinement_follows` false:
    /// snapshots, the live view, refinement off or interrupted), where agents' maps overlap only
    /// the nearest observer's Gaussians stay ([`merge`], `[consensus.merge]`); the refinement
    /// starts from every agent's whole map. Agents not linked to the world are left out (their
    /// frame is unknown); the count of those Gaussians is returned too.
    pub fn merged_map(&self, refinement_follows: bool) -> (GaussianCloud, usize) {
        let mut per_agent: BTreeMap<u32, GaussianCloud> = BTreeMap::new();
        let mut unplaced = 0;
        for (agent_id, cloud) in &self.final_maps {
            match self
                .solution
                .as_ref()
                .and_then(|s| s.world_from_agent.get(agent_id).copied().flatten())
            {
                Some(world_from_agent) => per_agent
                    .entry(*agent_id)
                    .or_default()
                    .extend_from(&transformed(cloud, &world_from_agent)),
                None => unplaced += cloud.len(),
            }
        }
        for (id, cloud) in &self.gaussians {
            if self.final_maps.contains_key(&id.agent_id) {
                continue;
            }
            match self.solution.as_ref().and_then(|s| s.corrections.get(id)) {
                Some(correction) => per_agent
                    .entry(id.agent_id)
                    .or_default()
                    .extend_from(&transformed(cloud, correction)),
                None => unplaced += cloud.len(),
            }
        }
        let maps: Vec<WorldAgentMap> = per_agent
            .into_iter()
            .map(|(agent_id, cloud)| WorldAgentMap {
                agent_id,
                cloud,
                observers: self.placed_cameras(agent_id),
            })
            .collect();
        if refinement_follows && self.config.merge.fuse_duplicates {
            let (fused, stats) = fuse(&maps, self.config.merge.fuse_radius_m);
            tracing::info!(
                fused_pairs = stats.fused_pairs,
                merged = fused.len(),
                "merged map: duplicates of overlapping agents' maps fused"
            );
            return (fused, unplaced);
        }
        let config = MergeConfig {
            nearest_observer: self.config.merge.nearest_observer && !refinement_follows,
            ..self.config.merge.clone()
        };
        let (merged, stats) = merge(&maps, &config);
        if stats.overlapping > 0 {
            tracing::info!(
                overlapping = stats.overlapping,
                left_to_nearer_observer = stats.left_to_nearer_observer,
                merged = merged.len(),
                "merged map: overlapping Gaussians kept from the agent that saw them nearest"
            );
        }
        (merged, unplaced)
    }

    /// World positions of `agent_id`'s keyframe cameras the pose graph placed.
    fn placed_cameras(&self, agent_id: u32) -> Vec<Point3<f64>> {
        let Some(solution) = self.solution.as_ref() else {
            return Vec::new();
        };
        solution
            .world_from_camera
            .iter()
            .filter(|(id, _)| id.agent_id == agent_id)
            .map(|(_, world_from_camera)| Point3::from(world_from_camera.translation.vector))
            .collect()
    }

    /// The joint refinement of `map` (the merged world map, [`Engine::merged_map`]) over every
    /// keyframe the pose graph placed in the world, with the pose graph's odometry edges
    /// (consecutive keyframes of one agent, as tracked) and accepted loop closures. `None` before
    /// a solution exists.
    pub fn refinement_problem(&self, map: GaussianCloud) -> Option<RefinementProblem> {
        let solution = self.solution.as_ref()?;
        let mut index = BTreeMap::new();
        let mut views = Vec::new();
        for (id, world_from_camera) in &solution.world_from_camera {
            let Some(prepared) = self.prepared.get(id) else {
                continue;
            };
            let keyframe = &prepared.keyframe;
            index.insert(*id, views.len());
            views.push(RefinementView {
                id: *id,
                world_from_camera: *world_from_camera,
                intrinsics: keyframe.intrinsics,
                rgb8: keyframe.rgb.as_raw().clone(),
                depth_m: keyframe.depth.data.clone(),
            });
        }
        let mut edges = Vec::new();
        // Keyframes are ordered by agent, then id: neighbours of one agent are odometry edges.
        let placed: Vec<&KeyframeRef> = index.keys().collect();
        for pair in placed.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            if a.agent_id != b.agent_id {
                continue;
            }
            let tracked_a = isometry_from_info(&self.info[a]);
            let tracked_b = isometry_from_info(&self.info[b]);
            edges.push(PoseEdge {
                i: index[a],
                j: index[b],
                camera_i_from_camera_j: tracked_a.inverse() * tracked_b,
            });
        }
        let loops = self.graph.loops();
        for decision in solution.loops.iter().filter(|d| d.accepted) {
            let closure = &loops[decision.index];
            if let (Some(&i), Some(&j)) = (index.get(&closure.target), index.get(&closure.source)) {
                edges.push(PoseEdge {
                    i,
                    j,
                    camera_i_from_camera_j: closure.target_camera_from_source_camera,
                });
            }
        }
        // Agent 0's first keyframe defines the world frame.
        let anchor = index
            .iter()
            .find(|(id, _)| id.agent_id == 0)
            .map(|(_, &view)| view);
        Some(RefinementProblem {
            map,
            views,
            edges,
            anchor,
        })
    }

    /// Replaces the pose graph's poses of the keyframes in `refined` (the joint refinement's
    /// views) and moves every other placed keyframe of their agents along: by the views' moves
    /// (`refined * before^-1`, in the world frame) blended to its time, as a correction is
    /// blended to a frame's time. A keyframe whose image never reached the consensus is no view;
    /// left where the pose graph put it, it would pull the world trajectory of the frames around
    /// it back towards the poses the map was not refined at. An agent with no view moves
    /// nothing.
    pub fn apply_refined_poses(&mut self, refined: &BTreeMap<KeyframeRef, Isometry3<f64>>) {
        let Some(solution) = self.solution.as_mut() else {
            return;
        };
        let mut moves: BTreeMap<u32, Vec<(f64, Isometry3<f64>)>> = BTreeMap::new();
        for (id, world_from_camera) in refined {
            let (Some(info), Some(before)) =
                (self.info.get(id), solution.world_from_camera.get(id))
            else {
                continue;
            };
            moves
                .entry(id.agent_id)
                .or_default()
                .push((info.timestamp_s, world_from_camera * before.inverse()));
        }
        for (agent_id, anchors) in moves {
            let field = CorrectionField::from_anchors(anchors);
            for (id, world_from_camera) in
                solution.world_from_camera.range_mut(agent_range(agent_id))
            {
                let Some(info) = self.info.get(id) else {
                    continue;
                };
                *world_from_camera = match refined.get(id) {
                    Some(refined) => *refined,
                    None => field.at(info.timestamp_s) * *world_from_camera,
                };
                solution.corrections.insert(
                    *id,
                    correction(world_from_camera, &isometry_from_info(info)),
                );
            }
        }
    }

    /// A per-frame trajectory of `agent_id` (tracked in its own frame, `(timestamp,
    /// agent_from_camera)`) in the world frame: each frame gets the correction blended between
    /// the published keyframes before and after it in time. `None` when the agent is not linked
    /// to the world.
    pub fn world_trajectory(
        &self,
        agent_id: u32,
        tracked: &[(f64, Isometry3<f64>)],
    ) -> Option<Vec<(f64, Isometry3<f64>)>> {
        let solution = self.solution.as_ref()?;
        let field = CorrectionField::from_anchors(
            self.info
                .iter()
                .filter(|(id, _)| id.agent_id == agent_id)
                .filter_map(|(id, info)| Some((info.timestamp_s, *solution.corrections.get(id)?))),
        );
        if field.is_empty() {
            return None;
        }
        Some(
            tracked
                .iter()
                .map(|(t, agent_from_camera)| (*t, field.at(*t) * agent_from_camera))
                .collect(),
        )
    }
}

/// The tracked `agent_from_camera` of a keyframe (stored in TUM order, always a valid pose).
fn isometry_from_info(info: &KeyframeInfo) -> Isometry3<f64> {
    isometry_from_tum(&info.agent_from_camera).expect("stored from an isometry")
}

/// `cloud` moved by the rigid `transform` (render-core's host transform, in f32).
fn transformed(cloud: &GaussianCloud, transform: &Isometry3<f64>) -> GaussianCloud {
    let rigid = RigidTransform::from(transform);
    let mut out = cloud.clone();
    out.transform_rigid(&rigid);
    out
}

/// Every keyframe of one agent in a map keyed by [`KeyframeRef`] (ordered by agent, then id).
pub(super) fn agent_range(agent_id: u32) -> std::ops::RangeInclusive<KeyframeRef> {
    KeyframeRef {
        agent_id,
        keyframe_id: 0,
    }..=KeyframeRef {
        agent_id,
        keyframe_id: u64::MAX,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::merge::tests::wall;
    use crate::pose_graph::PoseGraphSolution;
    use config::ConsensusConfig;
    use nalgebra::Translation3;

    /// Two agents placed at identity whose final maps overlap on x in [0.5, 1), each with one
    /// keyframe camera over its own half.
    fn engine(nearest_observer: bool) -> Engine {
        let mut config = ConsensusConfig::default();
        config.merge.nearest_observer = nearest_observer;
        let mut engine = Engine::new(config);
        engine.final_maps.insert(0, wall(0.0, 100, 2.0));
        engine.final_maps.insert(1, wall(0.5, 100, 2.01));
        let camera = |agent_id, x| {
            (
                KeyframeRef {
                    agent_id,
                    keyframe_id: 0,
                },
                Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), Default::default()),
            )
        };
        engine.solution = Some(PoseGraphSolution {
            world_from_agent: [
                (0, Some(Isometry3::identity())),
                (1, Some(Isometry3::identity())),
            ]
            .into(),
            world_from_camera: [camera(0, 0.2), camera(1, 1.3)].into(),
            corrections: BTreeMap::new(),
            loops: Vec::new(),
            gnc_steps: 0,
        });
        engine
    }

    /// Agent 0 with keyframes 0, 1, 2 at times 0, 1, 2 s, tracked and placed at x = 0, 1, 2 m.
    fn three_keyframes() -> Engine {
        let mut engine = Engine::new(ConsensusConfig::default());
        let mut world_from_camera = BTreeMap::new();
        let mut corrections = BTreeMap::new();
        for k in 0..3u64 {
            let id = KeyframeRef {
                agent_id: 0,
                keyframe_id: k,
            };
            let pose = Isometry3::translation(k as f64, 0.0, 0.0);
            engine.info.insert(
                id,
                KeyframeInfo {
                    frame_index: k * 10,
                    timestamp_s: k as f64,
                    agent_from_camera: geometry::se3::isometry_to_tum(&pose),
                },
            );
            world_from_camera.insert(id, pose);
            corrections.insert(id, Isometry3::identity());
        }
        engine.solution = Some(PoseGraphSolution {
            world_from_agent: [(0, Some(Isometry3::identity()))].into(),
            world_from_camera,
            corrections,
            loops: Vec::new(),
            gnc_steps: 0,
        });
        engine
    }

    #[test]
    fn keyframes_that_are_no_view_move_with_the_views_around_them() {
        let mut engine = three_keyframes();
        let id = |keyframe_id| KeyframeRef {
            agent_id: 0,
            keyframe_id,
        };
        // Views 0 and 2 refined 2 cm and 4 cm along y; keyframe 1 had no image.
        let refined: BTreeMap<KeyframeRef, Isometry3<f64>> = [
            (id(0), Isometry3::translation(0.0, 0.02, 0.0)),
            (id(2), Isometry3::translation(2.0, 0.04, 0.0)),
        ]
        .into();
        engine.apply_refined_poses(&refined);
        let solution = engine.solution.as_ref().unwrap();
        let middle = solution.world_from_camera[&id(1)];
        assert!(
            (middle.translation.vector - nalgebra::Vector3::new(1.0, 0.03, 0.0)).norm() < 1e-12,
            "half way between the views' moves: {middle:?}"
        );
        assert_eq!(solution.world_from_camera[&id(2)], refined[&id(2)]);
        let tracked = Isometry3::translation(1.0, 0.0, 0.0);
        assert!(
            (solution.corrections[&id(1)] * tracked)
                .translation
                .vector
                .relative_eq(&middle.translation.vector, 1e-12, 1e-12),
            "the correction follows the pose"
        );
    }

    #[test]
    fn overlaps_are_pruned_only_when_no_refinement_follows() {
        let union = 200;
        let (unrefined, unplaced) = engine(true).merged_map(false);
        assert_eq!(unplaced, 0);
        assert!(
            unrefined.len() < union,
            "the nearest observer's copy alone in the overlap: {} of {union}",
            unrefined.len()
        );
        assert_eq!(
            engine(true).merged_map(true).0.len(),
            union,
            "refinement starts from the union"
        );
        assert_eq!(
            engine(false).merged_map(false).0.len(),
            union,
            "pruning off"
        );
    }
}
