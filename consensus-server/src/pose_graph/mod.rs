//! The robust pose graph over all agents' keyframes (docs/method.md, The consensus: pose graph).
//!
//! Nodes: keyframes, each with its pose in its own agent's frame (from tracking; agents start at
//! identity). Edges: odometry between consecutive keyframes of an agent (the relative pose
//! tracking measured, trusted) and loop closures within and between agents (from
//! [`crate::alignment`], possibly wrong). The solve:
//!
//! 1. [`initial`]: each agent's frame in the world from the inter-agent closures (votes).
//! 2. [`gnc`] + [`solver`]: graduated non-convexity with truncated least squares on the loop
//!    edges, each step a weighted Levenberg-Marquardt solve, so wrong closures end with weight 0.
//! 3. A final solve with the accepted closures only.
//!
//! Solver: our own dense Levenberg-Marquardt over nalgebra, not a factor-graph crate. The graph
//! is small (one node per published keyframe: tens to a few hundred 6-DoF poses, solved in well
//! under a millisecond), GNC needs the per-edge weights changed between LM solves, and
//! the candidate crates bring a second linear-algebra stack (tiny-solver 0.18: faer plus
//! nalgebra 0.34, the workspace pins 0.35). The residual and its closed-form Jacobians are unit
//! tested against finite differences ([`residual`]).
//!
//! Output: per agent its `world_from_agent` (agent 0 = identity; `None` for an agent that no
//! accepted closure links to agent 0), every linked keyframe's corrected `world_from_camera`,
//! and the decision on every closure; [`correction`] carries the keyframes' corrections over to
//! the frames tracked between them.

pub mod gnc;
pub mod initial;
pub mod residual;
pub mod solver;

use std::collections::{BTreeMap, BTreeSet};

use geometry::correction;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::place_recognition::KeyframeRef;
use config::PoseGraphConfig;
use initial::ImpliedTransform;
use solver::Edge;

/// Agent whose frame is the world frame.
pub const WORLD_AGENT: u32 = 0;
/// A closure whose final GNC weight is at least this is accepted.
const ACCEPTED_WEIGHT: f64 = 0.5;

/// A verified relative pose between two keyframes (an [`crate::alignment::AlignmentResult`], or
/// a map registration carried to two keyframes, [`crate::map_links`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopClosure {
    /// The keyframe whose camera frame the measurement maps from.
    pub source: KeyframeRef,
    /// The keyframe whose camera frame the measurement maps into.
    pub target: KeyframeRef,
    /// The measured relative pose: source camera coordinates to target camera coordinates
    /// (metres).
    pub target_camera_from_source_camera: Isometry3<f64>,
    /// The measurement's own standard deviations; `None`: the configured loop-closure ones
    /// ([`PoseGraphConfig::loop_rotation_sigma_rad`], `loop_translation_sigma_m`).
    pub sigmas: Option<EdgeSigmas>,
}

/// Standard deviations of a relative-pose measurement (isotropic per block).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EdgeSigmas {
    /// Standard deviation of each rotation-vector component, radians.
    pub rotation_rad: f64,
    /// Standard deviation of each translation component, metres.
    pub translation_m: f64,
}

/// A graph that cannot be solved as given.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseGraphError {
    /// A loop closure names a keyframe that was never added ([`PoseGraph::add_loop`]).
    #[error("loop closure names keyframe {0:?}, which is not in the graph")]
    UnknownKeyframe(KeyframeRef),
    /// A loop closure's two ends are the same keyframe ([`PoseGraph::add_loop`]).
    #[error("loop closure from keyframe {0:?} to itself")]
    SelfLoop(KeyframeRef),
    /// No keyframe of agent [`WORLD_AGENT`] yet, so there is no world frame to solve in
    /// ([`PoseGraph::solve`]).
    #[error("agent {WORLD_AGENT} (the world frame) has no keyframes")]
    NoWorldAgent,
}

/// Keyframes and loop closures of all agents.
#[derive(Debug, Clone, Default)]
pub struct PoseGraph {
    /// Every keyframe, ordered by agent then keyframe id (odometry order).
    keyframes: BTreeMap<KeyframeRef, GraphKeyframe>,
    loops: Vec<LoopClosure>,
}

/// A node of the graph as tracking gave it.
#[derive(Debug, Clone, Copy)]
struct GraphKeyframe {
    agent_from_camera: Isometry3<f64>,
    /// Index of the keyframe's frame in its agent's input sequence: consecutive keyframes'
    /// difference is the span of their odometry edge.
    frame_index: u64,
}

/// The decision on one loop closure.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LoopDecision {
    /// Index in the order the closures were added.
    pub index: usize,
    /// The closure's source keyframe.
    pub source: KeyframeRef,
    /// The closure's target keyframe.
    pub target: KeyframeRef,
    /// Whether the two ends belong to different agents.
    pub inter_agent: bool,
    /// Whether the closure is kept: its final GNC weight is at least 0.5. A closure not in the
    /// solve is rejected.
    pub accepted: bool,
    /// Final GNC weight (0 = outlier, 1 = inlier).
    pub weight: f64,
    /// Squared Mahalanobis residual at the final estimate; `NaN` for a closure not in the solve
    /// (an end's agent not linked to the world).
    pub chi2: f64,
}

/// Corrections for every agent.
#[derive(Debug, Clone)]
pub struct PoseGraphSolution {
    /// `world_from_agent` per agent: the rigid transform that best maps the agent's tracked
    /// keyframes onto their corrected poses (agent 0: identity by definition). `None` for an agent
    /// that no accepted closure links to agent 0.
    pub world_from_agent: BTreeMap<u32, Option<Isometry3<f64>>>,
    /// Corrected `world_from_camera` of every keyframe of the linked agents.
    pub world_from_camera: BTreeMap<KeyframeRef, Isometry3<f64>>,
    /// Per keyframe of the linked agents, the correction it received (see
    /// [`correction::correction`]): apply it, or a [`correction::CorrectionField`] through them, to
    /// tracked poses.
    pub corrections: BTreeMap<KeyframeRef, Isometry3<f64>>,
    /// The decision on every loop closure of the graph, in the order they were added.
    pub loops: Vec<LoopDecision>,
    /// GNC steps taken (each a weighted Levenberg-Marquardt solve); 0 when no closure's residual
    /// exceeded the outlier threshold at the initial guess, so none was needed.
    pub gnc_steps: usize,
}

impl PoseGraphSolution {
    /// How many loop closures the solve accepted.
    pub fn accepted_loops(&self) -> usize {
        self.loops.iter().filter(|l| l.accepted).count()
    }
}

impl PoseGraph {
    /// A graph with no keyframes and no closures.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a keyframe taken at frame `frame_index` of its agent's input, or updates it if it
    /// is already there.
    pub fn add_keyframe(
        &mut self,
        id: KeyframeRef,
        agent_from_camera: Isometry3<f64>,
        frame_index: u64,
    ) {
        self.keyframes.insert(
            id,
            GraphKeyframe {
                agent_from_camera,
                frame_index,
            },
        );
    }

    /// Adds a loop closure between two keyframes already in the graph; returns its index.
    pub fn add_loop(&mut self, closure: LoopClosure) -> Result<usize, PoseGraphError> {
        for id in [closure.source, closure.target] {
            if !self.keyframes.contains_key(&id) {
                return Err(PoseGraphError::UnknownKeyframe(id));
            }
        }
        if closure.source == closure.target {
            return Err(PoseGraphError::SelfLoop(closure.source));
        }
        self.loops.push(closure);
        Ok(self.loops.len() - 1)
    }

    /// Every keyframe with its tracked `agent_from_camera`, by agent then keyframe id.
    pub fn keyframes(&self) -> impl Iterator<Item = (&KeyframeRef, &Isometry3<f64>)> {
        self.keyframes
            .iter()
            .map(|(id, keyframe)| (id, &keyframe.agent_from_camera))
    }

    /// The frame index a keyframe was added with.
    pub fn frame_index(&self, id: &KeyframeRef) -> Option<u64> {
        self.keyframes.get(id).map(|keyframe| keyframe.frame_index)
    }

    /// Every loop closure, in the order added.
    pub fn loops(&self) -> &[LoopClosure] {
        &self.loops
    }

    /// How many keyframes (nodes) the graph holds, of all agents.
    pub fn keyframe_count(&self) -> usize {
        self.keyframes.len()
    }

    /// How many loop closures were added, whatever a solve decides about them.
    pub fn loop_count(&self) -> usize {
        self.loops.len()
    }

    /// Solves the graph; see the module documentation.
    pub fn solve(&self, config: &PoseGraphConfig) -> Result<PoseGraphSolution, PoseGraphError> {
        let _span = tracing::info_span!(
            "pose graph",
            keyframes = self.keyframes.len(),
            loops = self.loops.len()
        )
        .entered();
        if !self.keyframes.keys().any(|k| k.agent_id == WORLD_AGENT) {
            return Err(PoseGraphError::NoWorldAgent);
        }
        let initial_frames = initial::agent_frames(WORLD_AGENT, &self.implied(), config);
        // Only agents placed in the world take part; the others have nothing to be solved against.
        let ids: Vec<KeyframeRef> = self
            .keyframes
            .keys()
            .filter(|k| initial_frames.contains_key(&k.agent_id))
            .copied()
            .collect();
        let node_of: BTreeMap<KeyframeRef, usize> =
            ids.iter().enumerate().map(|(n, k)| (*k, n)).collect();
        let mut poses: Vec<Isometry3<f64>> = ids
            .iter()
            .map(|k| initial_frames[&k.agent_id] * self.keyframes[k].agent_from_camera)
            .collect();
        let odometry = self.odometry_edges(&ids, config);
        let loop_edges = self.loop_edges(&node_of, config);
        let edges: Vec<Edge> = odometry
            .iter()
            .cloned()
            .chain(loop_edges.iter().map(|(_, e)| e.clone()))
            .collect();
        // The world agent's first keyframe holds the gauge (ids are sorted, agent 0 first).
        let fixed = 0;

        let (gnc_weights, gnc_steps) = graduate(&mut poses, fixed, &edges, odometry.len(), config);
        // Final solve with the decided closures at full weight and the rejected ones left out.
        let final_weights: Vec<f64> = std::iter::repeat_n(1.0, odometry.len())
            .chain(
                gnc_weights
                    .iter()
                    .map(|&w| if w >= ACCEPTED_WEIGHT { 1.0 } else { 0.0 }),
            )
            .collect();
        let report = solver::optimise(
            &mut poses,
            fixed,
            &edges,
            &final_weights,
            config.lm_max_iterations,
            config.lm_step_tolerance,
        );
        let decisions = self.decisions(&loop_edges, &gnc_weights, &poses);
        tracing::info!(
            gnc_steps,
            accepted = decisions.iter().filter(|d| d.accepted).count(),
            cost = report.final_cost,
            "pose graph solved"
        );
        let linked = linked_agents(&decisions, &ids);
        Ok(self.solution(&ids, &poses, &linked, decisions, gnc_steps))
    }

    /// `(closure index, edge)` for the closures whose both ends take part in the solve.
    fn loop_edges(
        &self,
        node_of: &BTreeMap<KeyframeRef, usize>,
        config: &PoseGraphConfig,
    ) -> Vec<(usize, Edge)> {
        self.loops
            .iter()
            .enumerate()
            .filter_map(|(index, closure)| {
                let sigmas = closure.sigmas.unwrap_or(EdgeSigmas {
                    rotation_rad: config.loop_rotation_sigma_rad,
                    translation_m: config.loop_translation_sigma_m,
                });
                Some((
                    index,
                    Edge {
                        from: *node_of.get(&closure.target)?,
                        to: *node_of.get(&closure.source)?,
                        measured: closure.target_camera_from_source_camera,
                        rotation_information: sigmas.rotation_rad.powi(-2),
                        translation_information: sigmas.translation_m.powi(-2),
                    },
                ))
            })
            .collect()
    }

    /// One decision per closure; closures outside the solve are rejected with weight 0.
    fn decisions(
        &self,
        loop_edges: &[(usize, Edge)],
        gnc_weights: &[f64],
        poses: &[Isometry3<f64>],
    ) -> Vec<LoopDecision> {
        let mut decisions: Vec<LoopDecision> = self
            .loops
            .iter()
            .enumerate()
            .map(|(index, closure)| LoopDecision {
                index,
                source: closure.source,
                target: closure.target,
                inter_agent: closure.source.agent_id != closure.target.agent_id,
                accepted: false,
                weight: 0.0,
                chi2: f64::NAN,
            })
            .collect();
        for ((index, edge), &weight) in loop_edges.iter().zip(gnc_weights) {
            let decision = &mut decisions[*index];
            decision.accepted = weight >= ACCEPTED_WEIGHT;
            decision.weight = weight;
            decision.chi2 = edge.chi2(poses);
        }
        decisions
    }

    fn implied(&self) -> Vec<ImpliedTransform> {
        self.loops
            .iter()
            .filter(|c| c.source.agent_id != c.target.agent_id)
            .map(|c| {
                let target_agent_from_source_agent = self.keyframes[&c.target].agent_from_camera
                    * c.target_camera_from_source_camera
                    * self.keyframes[&c.source].agent_from_camera.inverse();
                if c.target.agent_id < c.source.agent_id {
                    ImpliedTransform {
                        lower_agent: c.target.agent_id,
                        higher_agent: c.source.agent_id,
                        lower_from_higher: target_agent_from_source_agent,
                    }
                } else {
                    ImpliedTransform {
                        lower_agent: c.source.agent_id,
                        higher_agent: c.target.agent_id,
                        lower_from_higher: target_agent_from_source_agent.inverse(),
                    }
                }
            })
            .collect()
    }

    /// One edge between each pair of consecutive keyframes of an agent (ids sorted), its
    /// uncertainty growing with the frames between them ([`PoseGraphConfig::odometry_sigmas`]).
    fn odometry_edges(&self, ids: &[KeyframeRef], config: &PoseGraphConfig) -> Vec<Edge> {
        ids.windows(2)
            .enumerate()
            .filter(|(_, pair)| pair[0].agent_id == pair[1].agent_id)
            .map(|(n, pair)| {
                let (from, to) = (&self.keyframes[&pair[0]], &self.keyframes[&pair[1]]);
                let span_frames = from.frame_index.abs_diff(to.frame_index);
                let (rotation_sigma, translation_sigma) = config.odometry_sigmas(span_frames);
                Edge {
                    from: n,
                    to: n + 1,
                    measured: from.agent_from_camera.inverse() * to.agent_from_camera,
                    rotation_information: rotation_sigma.powi(-2),
                    translation_information: translation_sigma.powi(-2),
                }
            })
            .collect()
    }

    fn solution(
        &self,
        ids: &[KeyframeRef],
        poses: &[Isometry3<f64>],
        linked: &BTreeSet<u32>,
        loops: Vec<LoopDecision>,
        gnc_steps: usize,
    ) -> PoseGraphSolution {
        let mut per_agent: BTreeMap<u32, Vec<Isometry3<f64>>> = BTreeMap::new();
        let mut world_from_camera = BTreeMap::new();
        let mut corrections = BTreeMap::new();
        for (id, pose) in ids.iter().zip(poses) {
            if linked.contains(&id.agent_id) {
                let correction =
                    correction::correction(pose, &self.keyframes[id].agent_from_camera);
                world_from_camera.insert(*id, *pose);
                corrections.insert(*id, correction);
                per_agent.entry(id.agent_id).or_default().push(correction);
            }
        }
        let agents: BTreeSet<u32> = self.keyframes.keys().map(|k| k.agent_id).collect();
        let world_from_agent = agents
            .into_iter()
            .map(|agent| {
                let frame = if agent == WORLD_AGENT {
                    Some(Isometry3::identity())
                } else {
                    per_agent.get(&agent).map(|samples| mean_pose(samples))
                };
                (agent, frame)
            })
            .collect();
        PoseGraphSolution {
            world_from_agent,
            world_from_camera,
            corrections,
            loops,
            gnc_steps,
        }
    }
}

/// GNC over the loop edges (`edges[first_loop..]`; odometry edges keep weight 1). Returns the
/// final loop weights and the number of GNC steps.
fn graduate(
    poses: &mut [Isometry3<f64>],
    fixed: usize,
    edges: &[Edge],
    first_loop: usize,
    config: &PoseGraphConfig,
) -> (Vec<f64>, usize) {
    let _span = tracing::debug_span!("gnc").entered();
    let threshold = config.outlier_threshold_chi2;
    let loop_chi2 = |poses: &[Isometry3<f64>]| -> Vec<f64> {
        edges[first_loop..].iter().map(|e| e.chi2(poses)).collect()
    };
    let mut residuals = loop_chi2(poses);
    let largest = residuals.iter().copied().fold(0.0, f64::max);
    let Some(mut mu) = gnc::initial_mu(largest, threshold) else {
        return (vec![1.0; residuals.len()], 0);
    };
    let mut steps = 0;
    while steps < config.gnc_max_steps {
        steps += 1;
        let loop_weights: Vec<f64> = residuals
            .iter()
            .map(|&r| gnc::tls_weight(r, threshold, mu))
            .collect();
        let weights: Vec<f64> = std::iter::repeat_n(1.0, first_loop)
            .chain(loop_weights.iter().copied())
            .collect();
        solver::optimise(
            poses,
            fixed,
            edges,
            &weights,
            config.lm_max_iterations,
            config.lm_step_tolerance,
        );
        residuals = loop_chi2(poses);
        if gnc::weights_are_binary(&loop_weights) {
            break;
        }
        mu *= config.gnc_mu_factor;
    }
    // Decide with the residuals of the last solve.
    let decided = residuals
        .iter()
        .map(|&r| gnc::tls_weight(r, threshold, mu))
        .collect();
    tracing::debug!(steps, mu, "gnc finished");
    (decided, steps)
}

/// Agents linked to the world agent through accepted inter-agent closures.
fn linked_agents(decisions: &[LoopDecision], ids: &[KeyframeRef]) -> BTreeSet<u32> {
    let present: BTreeSet<u32> = ids.iter().map(|k| k.agent_id).collect();
    let mut linked = BTreeSet::from([WORLD_AGENT]);
    loop {
        let newly: Vec<u32> = decisions
            .iter()
            .filter(|d| d.accepted && d.inter_agent)
            .filter_map(|d| {
                let (a, b) = (d.source.agent_id, d.target.agent_id);
                match (linked.contains(&a), linked.contains(&b)) {
                    (true, false) => Some(b),
                    (false, true) => Some(a),
                    _ => None,
                }
            })
            .filter(|agent| present.contains(agent))
            .collect();
        if newly.is_empty() {
            return linked;
        }
        linked.extend(newly);
    }
}

/// Mean of rigid transforms: translations averaged, rotations by the chordal L2 mean (the
/// rotation nearest to the sum of the rotation matrices).
fn mean_pose(samples: &[Isometry3<f64>]) -> Isometry3<f64> {
    let n = samples.len().max(1) as f64;
    let translation: Vector3<f64> = samples
        .iter()
        .map(|p| p.translation.vector)
        .sum::<Vector3<f64>>()
        / n;
    let rotation_sum: Matrix3<f64> = samples
        .iter()
        .map(|p| p.rotation.to_rotation_matrix().into_inner())
        .sum();
    // Only non-finite samples leave no mean rotation; keep the first sample's then.
    let rotation = geometry::se3::nearest_rotation(&rotation_sum).unwrap_or_else(|| {
        samples
            .first()
            .map_or_else(Rotation3::identity, |p| p.rotation.to_rotation_matrix())
    });
    Isometry3::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kf(agent_id: u32, keyframe_id: u64) -> KeyframeRef {
        KeyframeRef {
            agent_id,
            keyframe_id,
        }
    }

    #[test]
    fn mean_pose_is_the_chordal_mean_of_the_samples() {
        let centre = Isometry3::from_parts(
            Translation3::new(0.5, -1.0, 2.0),
            UnitQuaternion::from_euler_angles(0.4, -2.9, 1.3),
        );
        let turn = |angle: f64| {
            Isometry3::from_parts(
                Translation3::new(angle, 0.0, 0.0),
                UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle),
            )
        };
        // Symmetric spreads around the centre, and many equal samples (a multiple of one
        // rotation matrix, where nalgebra's iterative from_matrix can fail to return).
        for samples in [
            vec![centre * turn(0.1), centre * turn(-0.1)],
            vec![centre * turn(0.3), centre, centre * turn(-0.3)],
            vec![centre; 37],
        ] {
            let mean = mean_pose(&samples);
            assert!(mean.rotation.angle_to(&centre.rotation) < 1e-9);
            assert!((mean.translation.vector - centre.translation.vector).norm() < 1e-9);
        }
    }

    #[test]
    fn malformed_graphs_are_refused() {
        let mut graph = PoseGraph::new();
        graph.add_keyframe(kf(1, 0), Isometry3::identity(), 0);
        assert_eq!(
            graph.solve(&PoseGraphConfig::default()).unwrap_err(),
            PoseGraphError::NoWorldAgent
        );
        let closure = |source, target| LoopClosure {
            source,
            target,
            target_camera_from_source_camera: Isometry3::identity(),
            sigmas: None,
        };
        assert_eq!(
            graph.add_loop(closure(kf(1, 0), kf(0, 0))),
            Err(PoseGraphError::UnknownKeyframe(kf(0, 0)))
        );
        assert_eq!(
            graph.add_loop(closure(kf(1, 0), kf(1, 0))),
            Err(PoseGraphError::SelfLoop(kf(1, 0)))
        );
    }

    #[test]
    fn odometry_edges_trust_short_spans_more() {
        // The sigmas are for 60-frame edges here.
        let config = PoseGraphConfig {
            odometry_sigma_span_frames: 60,
            ..PoseGraphConfig::default()
        };
        let mut graph = PoseGraph::new();
        // Agent 0's keyframes at frames 0, 15 and 75 (in arrival order), agent 1's at 0 and 60.
        for (agent, keyframe, frame) in [(0, 0, 0), (0, 1, 15), (0, 2, 75), (1, 0, 0), (1, 1, 60)] {
            graph.add_keyframe(kf(agent, keyframe), Isometry3::identity(), frame);
        }
        let ids: Vec<KeyframeRef> = graph.keyframes.keys().copied().collect();
        let edges = graph.odometry_edges(&ids, &config);
        let translation = |sigma: f64| sigma.powi(-2);
        let information: Vec<(usize, usize, f64)> = edges
            .iter()
            .map(|e| (e.from, e.to, e.translation_information))
            .collect();
        // No edge between agents; 15 frames: half the sigma of 60 frames, four times the
        // information.
        assert_eq!(information.len(), 3);
        assert_eq!((information[0].0, information[0].1), (0, 1));
        assert!(
            (information[0].2 - translation(config.odometry_translation_sigma_m / 2.0)).abs()
                < 1e-6
        );
        assert!((information[1].2 - translation(config.odometry_translation_sigma_m)).abs() < 1e-6);
        assert_eq!((information[2].0, information[2].1), (3, 4));
        assert!((information[2].2 - translation(config.odometry_translation_sigma_m)).abs() < 1e-6);
        assert!(
            (edges[0].rotation_information - (config.odometry_rotation_sigma_rad / 2.0).powi(-2))
                .abs()
                < 1e-6
        );
    }

    #[test]
    fn agents_without_closures_stay_unplaced() {
        let mut graph = PoseGraph::new();
        for k in 0..3 {
            graph.add_keyframe(
                kf(0, k),
                Isometry3::translation(0.1 * k as f64, 0.0, 0.0),
                60 * k,
            );
            graph.add_keyframe(
                kf(1, k),
                Isometry3::translation(0.1 * k as f64, 0.0, 0.0),
                60 * k,
            );
            graph.add_keyframe(
                kf(2, k),
                Isometry3::translation(0.1 * k as f64, 0.0, 0.0),
                60 * k,
            );
        }
        // Agent 1's keyframe 0 sees agent 0's keyframe 2 from 1 m further along x.
        let one_metre = Isometry3::translation(1.0, 0.0, 0.0);
        graph
            .add_loop(LoopClosure {
                source: kf(1, 0),
                target: kf(0, 2),
                target_camera_from_source_camera: one_metre,
                sigmas: None,
            })
            .unwrap();
        let solution = graph.solve(&PoseGraphConfig::default()).unwrap();
        assert_eq!(solution.world_from_agent[&0], Some(Isometry3::identity()));
        let world_from_agent1 = solution.world_from_agent[&1].unwrap();
        let expected = Isometry3::translation(0.2, 0.0, 0.0) * one_metre;
        assert!((world_from_agent1.translation.vector - expected.translation.vector).norm() < 1e-9);
        assert_eq!(solution.world_from_agent[&2], None);
        assert!(!solution.world_from_camera.contains_key(&kf(2, 0)));
        assert!(solution.loops[0].accepted && solution.loops[0].inter_agent);
    }
}
