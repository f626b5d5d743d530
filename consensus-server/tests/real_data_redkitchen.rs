//! Two agents on 7-Scenes redkitchen (frames 0..600 and 400..1000), each tracked on its own from
//! identity with slam_core's frame-to-model odometry. The consensus pipeline then runs as the
//! process will: place recognition over keyframe descriptors (AlexNet GeM), alignment of the
//! proposed pairs and of each agent's consecutive keyframes, the robust pose graph, and finally
//! the joint ATE of both agents' corrected trajectories under one alignment to ground truth.
//! Ground truth is only used to score (the joint ATE, and the printed closure errors).

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use alexnet::descriptor::GlobalDescriptorExtractor;
use config::ConsensusConfig;
use datasets::prefetch::Prefetcher;
use datasets::{self, Dataset, FrameRange};
use geometry::correction::blend;
use geometry::trajectory::Trajectory;
use mac_consensus::alignment::{Keyframe, PreparedKeyframe, Verdict, align_prepared};
use mac_consensus::place_recognition::{KeyframeRef, PlaceDatabase, SelectionThresholds};
use mac_consensus::pose_graph::{LoopClosure, PoseGraph};
use metrics::ate::{Alignment, DEFAULT_MAX_DT, JointAte, ate, joint_ate};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use registration::config::{KeyframeConfig, TrackingConfig};
use registration::{Odometry, OdometryMode};

/// The two agents' frame ranges: 200 frames of overlap in time, and the second half of agent 1
/// revisits what agent 0 saw first.
const AGENT_RANGES: [&str; 2] = ["0..600", "400..1000"];
/// A keyframe every this many frames; agent 1's keyframes are shifted by half of it so that no
/// two keyframes of the overlap are the same image.
const KEYFRAME_EVERY: usize = 20;
/// Loop candidates aligned per new keyframe at most (the best-scoring ones): bounds the test's
/// run time; the process aligns in the background and can afford more.
const CANDIDATES_PER_KEYFRAME: usize = 3;
/// Frames decoded ahead by the prefetcher.
const DECODE_WORKERS: usize = 1;
const QUEUE_PER_WORKER: usize = 8;
/// The figure the test must meet (metres).
const MAX_JOINT_ATE_M: f64 = 0.05;

/// One agent after tracking.
struct TrackedAgent {
    /// (timestamp, tracked `agent_from_camera`, ground truth) per frame.
    frames: Vec<(f64, Isometry3<f64>, Isometry3<f64>)>,
    /// Frame index (position in `frames`) of each keyframe, with the keyframe.
    keyframes: Vec<(usize, Keyframe)>,
}

fn track(agent_id: u32, dir: &str, range: &str) -> TrackedAgent {
    let range: FrameRange = range.parse().unwrap();
    let dataset: Arc<dyn Dataset> = Arc::from(datasets::open(dir, range).unwrap());
    let mut odometry = Odometry::new(
        OdometryMode::FrameToModel,
        &TrackingConfig::default(),
        &KeyframeConfig::default(),
    );
    let phase = agent_id as usize * KEYFRAME_EVERY / 2;
    let mut tracked = TrackedAgent {
        frames: Vec::new(),
        keyframes: Vec::new(),
    };
    for (position, frame) in Prefetcher::new(dataset, DECODE_WORKERS, QUEUE_PER_WORKER) {
        let frame = frame.unwrap();
        let result = odometry.track(registration::FrameInput {
            timestamp_s: frame.timestamp,
            depth: &frame.depth,
            rgb: Some(&frame.rgb),
            intrinsics: &frame.intrinsics,
            colour_offset_s: frame.colour_offset_s,
            real_time: false,
        });
        tracked.frames.push((
            frame.timestamp,
            result.world_from_camera,
            frame.world_from_camera_gt.unwrap(),
        ));
        if position % KEYFRAME_EVERY == phase {
            tracked.keyframes.push((
                position,
                Keyframe {
                    id: KeyframeRef {
                        agent_id,
                        keyframe_id: frame.index as u64,
                    },
                    rgb: frame.rgb,
                    depth: frame.depth,
                    intrinsics: frame.intrinsics,
                    agent_from_camera: result.world_from_camera,
                },
            ));
        }
    }
    eprintln!("agent {agent_id}: {:?}", odometry.stats());
    tracked
}

/// Every frame's corrected pose: its tracked pose under the correction blended between the
/// keyframes before and after it (the nearest one's alone at either end).
fn corrected_trajectory(
    agent: &TrackedAgent,
    corrections: &BTreeMap<KeyframeRef, Isometry3<f64>>,
) -> Trajectory {
    let mut trajectory = Trajectory::default();
    for (position, (stamp, agent_from_camera, _)) in agent.frames.iter().enumerate() {
        let after = agent.keyframes.iter().position(|(p, _)| *p > position);
        let (before, after) = match after {
            Some(0) => (&agent.keyframes[0], &agent.keyframes[0]),
            Some(k) => (&agent.keyframes[k - 1], &agent.keyframes[k]),
            None => {
                let last = agent.keyframes.last().unwrap();
                (last, last)
            }
        };
        let span = after.0.saturating_sub(before.0).max(1) as f64;
        let fraction = position.saturating_sub(before.0) as f64 / span;
        let correction = blend(
            &corrections[&before.1.id],
            &corrections[&after.1.id],
            fraction,
        );
        trajectory.push(*stamp, correction * agent_from_camera);
    }
    trajectory
}

fn ground_truth(agent: &TrackedAgent) -> Trajectory {
    Trajectory::from_pairs(agent.frames.iter().map(|(t, _, gt)| (*t, *gt)))
}

#[test]
fn real_data_two_agents_redkitchen_joint_ate_within_5_cm() {
    let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
    let weights = datasets::shared_data::require("weights/lpips/alexnet.npz");
    let config = ConsensusConfig::default();

    let clock = Instant::now();
    let agents: Vec<TrackedAgent> = AGENT_RANGES
        .iter()
        .enumerate()
        .map(|(id, range)| track(id as u32, dir.to_str().unwrap(), range))
        .collect();
    let tracking_time = clock.elapsed();
    report_tracking(&agents);

    let clock = Instant::now();
    let selection = select(&agents, &weights, &config);
    let selection_time = clock.elapsed();

    let clock = Instant::now();
    let aligned = align_candidates(&agents, &selection, &config);
    let alignment_time = clock.elapsed();

    let clock = Instant::now();
    let solution = aligned.graph.solve(&config.pose_graph).unwrap();
    let graph_time = clock.elapsed();
    let candidates = &selection.candidates;
    let proposed = selection.proposed;
    let inter_agent_candidates = candidates
        .iter()
        .filter(|(s, t)| s.agent_id != t.agent_id)
        .count();
    let inter_accepted = solution
        .loops
        .iter()
        .filter(|l| l.inter_agent && l.accepted)
        .count();
    eprintln!(
        "{proposed} pairs proposed by place recognition ({inter_agent_candidates} inter-agent), \
         {} consecutive; alignment accepted {}, rejected {:?}; pose graph accepted {} \
         ({inter_accepted} inter-agent), rejected {}",
        candidates.len() - proposed,
        aligned.graph.loop_count(),
        aligned.rejections,
        solution.accepted_loops(),
        solution.loops.len() - solution.accepted_loops()
    );
    let world_from_agent1 = solution.world_from_agent[&1].expect("agent 1 linked to the world");
    eprintln!("world_from_agent1: {world_from_agent1}");

    let joint = joint_ate_of(&agents, &solution.corrections);
    eprintln!(
        "joint ATE {:.2} cm (agent 0 {:.2} cm, agent 1 {:.2} cm under the joint alignment)",
        joint.joint.rmse * 100.0,
        joint.per_agent_joint_aligned[0].rmse * 100.0,
        joint.per_agent_joint_aligned[1].rmse * 100.0
    );
    eprintln!(
        "time: tracking {:.1} s, descriptors {:.1} s, alignment {:.1} s, pose graph {:.2} s",
        tracking_time.as_secs_f64(),
        selection_time.as_secs_f64(),
        alignment_time.as_secs_f64(),
        graph_time.as_secs_f64()
    );
    assert!(inter_accepted > 0, "no inter-agent closure survived");
    assert!(
        joint.joint.rmse <= MAX_JOINT_ATE_M,
        "joint ATE {} m",
        joint.joint.rmse
    );

    // The same graph with 30 % of the accepted closures replaced by random transforms.
    let (wrong, corrupted) = with_random_closures(&aligned.graph, &aligned.closures);
    let robust = corrupted.solve(&config.pose_graph).unwrap();
    let wrong_accepted = wrong.iter().filter(|&&k| robust.loops[k].accepted).count();
    let robust_joint = joint_ate_of(&agents, &robust.corrections);
    eprintln!(
        "with {} of {} closures replaced by random transforms: {wrong_accepted} of them \
         accepted, joint ATE {:.2} cm",
        wrong.len(),
        aligned.closures.len(),
        robust_joint.joint.rmse * 100.0
    );
    assert_eq!(wrong_accepted, 0, "random closures accepted");
    assert!(
        robust_joint.joint.rmse <= MAX_JOINT_ATE_M,
        "joint ATE {} m with random closures",
        robust_joint.joint.rmse
    );
}

/// Each agent's own ATE (self-aligned) and keyframe count.
fn report_tracking(agents: &[TrackedAgent]) {
    for (id, agent) in agents.iter().enumerate() {
        let estimate = Trajectory::from_pairs(agent.frames.iter().map(|(t, p, _)| (*t, *p)));
        let own = ate(
            &ground_truth(agent),
            &estimate,
            Alignment::Se3,
            DEFAULT_MAX_DT,
        )
        .unwrap();
        eprintln!(
            "agent {id}: tracking alone, ATE {:.2} cm (self-aligned), {} keyframes",
            own.stats.rmse * 100.0,
            agent.keyframes.len()
        );
    }
}

/// The pairs to align: place recognition's proposals, then each agent's consecutive keyframes.
struct Selection<'a> {
    /// Keyframes in arrival order.
    arrivals: Vec<(usize, &'a Keyframe)>,
    /// (source, target) keyframe pairs to align.
    candidates: Vec<(KeyframeRef, KeyframeRef)>,
    /// How many of `candidates` place recognition proposed (the first ones).
    proposed: usize,
}

/// Selection: keyframes arrive in time order (both agents run at once).
fn select<'a>(
    agents: &'a [TrackedAgent],
    weights: &std::path::Path,
    config: &ConsensusConfig,
) -> Selection<'a> {
    let extractor = GlobalDescriptorExtractor::from_weights(Some(weights));
    assert_eq!(extractor.kind(), "alexnet-gem");
    let mut arrivals: Vec<(usize, &Keyframe)> = agents
        .iter()
        .flat_map(|a| a.keyframes.iter().map(|(position, k)| (*position, k)))
        .collect();
    arrivals.sort_by_key(|(position, k)| (*position, k.id));
    let mut database = PlaceDatabase::new(SelectionThresholds::from_config(config));
    let mut candidates: Vec<(KeyframeRef, KeyframeRef)> = Vec::new();
    for (_, keyframe) in &arrivals {
        let descriptor = extractor.describe(&keyframe.rgb).unwrap();
        let proposals =
            database.insert_and_query(keyframe.id, keyframe.id.keyframe_id, &descriptor);
        candidates.extend(
            proposals
                .into_iter()
                .take(CANDIDATES_PER_KEYFRAME)
                .map(|c| (c.query, c.matched)),
        );
    }
    let proposed = candidates.len();
    // Consecutive keyframes of one agent are aligned too: the verified relative pose corrects
    // tracking where it slipped between them (redkitchen has 20 cm slips over 20 frames).
    for agent in agents {
        for pair in agent.keyframes.windows(2) {
            candidates.push((pair[1].1.id, pair[0].1.id));
        }
    }
    Selection {
        arrivals,
        candidates,
        proposed,
    }
}

/// The pose graph with every verified closure, and what alignment refused.
struct Aligned {
    graph: PoseGraph,
    closures: Vec<LoopClosure>,
    /// Rejections per reason.
    rejections: BTreeMap<String, usize>,
}

/// Association and alignment of every candidate pair; accepted closures are scored against the
/// ground truth (printed only).
fn align_candidates(
    agents: &[TrackedAgent],
    selection: &Selection<'_>,
    config: &ConsensusConfig,
) -> Aligned {
    let prepared: BTreeMap<KeyframeRef, PreparedKeyframe> = selection
        .arrivals
        .iter()
        .map(|(_, k)| (k.id, PreparedKeyframe::new((*k).clone(), &config.alignment)))
        .collect();
    let mut graph = PoseGraph::new();
    for (position, keyframe) in &selection.arrivals {
        graph.add_keyframe(keyframe.id, keyframe.agent_from_camera, *position as u64);
    }
    let mut rejections: BTreeMap<String, usize> = BTreeMap::new();
    // Ground truth of every keyframe, to score the accepted closures (evaluation only).
    let truth: BTreeMap<KeyframeRef, Isometry3<f64>> = agents
        .iter()
        .flat_map(|a| a.keyframes.iter().map(|(p, k)| (k.id, a.frames[*p].2)))
        .collect();
    let mut closure_errors_mm = Vec::new();
    let mut closures = Vec::new();
    for (source, target) in &selection.candidates {
        let result = align_prepared(&prepared[source], &prepared[target], &config.alignment);
        match &result.verdict {
            Verdict::Accepted => {
                closures.push(LoopClosure {
                    source: result.source,
                    target: result.target,
                    target_camera_from_source_camera: result.target_camera_from_source_camera,
                    sigmas: None,
                });
                let truth_relative = truth[&result.target].inverse() * truth[&result.source];
                let error = result.target_camera_from_source_camera.inverse() * truth_relative;
                closure_errors_mm.push(error.translation.vector.norm() * 1e3);
                if std::env::var_os("VERBOSE").is_some() {
                    eprintln!(
                        "{source:?} -> {target:?}: error {:.1} mm {:.2} deg, {:?} {:?}",
                        error.translation.vector.norm() * 1e3,
                        error.rotation.angle().to_degrees(),
                        result.coarse,
                        result.refinement
                    );
                }
                graph.add_loop(*closures.last().unwrap()).unwrap();
            }
            Verdict::Rejected(reason) => {
                if std::env::var_os("VERBOSE").is_some() {
                    eprintln!("{source:?} -> {target:?}: {reason} {:?}", result.coarse);
                }
                let kind = format!("{reason:?}");
                let kind = kind.split([' ', '(', '{']).next().unwrap_or("").to_string();
                *rejections.entry(kind).or_default() += 1;
            }
        }
    }
    closure_errors_mm.sort_by(f64::total_cmp);
    if let (Some(median), Some(worst)) = (
        closure_errors_mm.get(closure_errors_mm.len() / 2),
        closure_errors_mm.last(),
    ) {
        eprintln!(
            "accepted closures against ground truth: median {median:.1} mm, worst {worst:.1} mm"
        );
    }
    Aligned {
        graph,
        closures,
        rejections,
    }
}

/// The joint ATE of both agents' corrected trajectories under one alignment.
fn joint_ate_of(
    agents: &[TrackedAgent],
    corrections: &BTreeMap<KeyframeRef, Isometry3<f64>>,
) -> JointAte {
    let pairs: Vec<(Trajectory, Trajectory)> = agents
        .iter()
        .map(|a| (ground_truth(a), corrected_trajectory(a, corrections)))
        .collect();
    joint_ate(&pairs, Alignment::Se3, DEFAULT_MAX_DT).unwrap()
}

/// Share of closures replaced by random transforms in the robustness check.
const WRONG_FRACTION: f64 = 0.3;
/// Random closures translate by up to this much per axis (metres; the kitchen is ~3 m across).
const WRONG_TRANSLATION_M: f64 = 2.0;

/// A copy of `graph`'s keyframes with `closures`, a share of which replaced by random transforms
/// (indices returned).
fn with_random_closures(graph: &PoseGraph, closures: &[LoopClosure]) -> (Vec<usize>, PoseGraph) {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut corrupted = PoseGraph::new();
    for (id, pose) in graph.keyframes() {
        let frame_index = graph.frame_index(id).expect("every keyframe has its frame");
        corrupted.add_keyframe(*id, *pose, frame_index);
    }
    let mut wrong = Vec::new();
    for (index, closure) in closures.iter().enumerate() {
        let mut closure = *closure;
        if rng.random_bool(WRONG_FRACTION) {
            let mut uniform = |limit: f64| rng.random_range(-limit..limit);
            let axis = Vector3::new(uniform(1.0), uniform(1.0), uniform(1.0));
            let angle = uniform(std::f64::consts::PI);
            let translation = Vector3::new(
                uniform(WRONG_TRANSLATION_M),
                uniform(WRONG_TRANSLATION_M),
                uniform(WRONG_TRANSLATION_M),
            );
            closure.target_camera_from_source_camera = Isometry3::from_parts(
                Translation3::from(translation),
                UnitQuaternion::from_scaled_axis(axis.normalize() * angle),
            );
            wrong.push(index);
        }
        corrupted.add_loop(closure).unwrap();
    }
    (wrong, corrupted)
}
