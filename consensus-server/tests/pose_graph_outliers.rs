//! The pose graph rejects wrong loop closures: three agents walking the synthetic scene's loops
//! (ground-truth trajectories, no rendering), odometry with drift, loop closures between nearby
//! keyframes within and between agents, and then 30 % of the closures replaced by random
//! transforms. Every agent starts at identity in its own frame. Ground truth builds the inputs and
//! scores the output; the solver never sees it.

use std::collections::BTreeMap;
use std::time::Instant;

use config::PoseGraphConfig;
use datasets::synthetic::{FRAMES_PER_SECOND, SyntheticDataset, SyntheticSpec};
use datasets::{Dataset, FrameRange};
use geometry::trajectory::Trajectory;
use mac_consensus::place_recognition::KeyframeRef;
use mac_consensus::pose_graph::{LoopClosure, PoseGraph, PoseGraphSolution};
use metrics::ate::{Alignment, DEFAULT_MAX_DT, joint_ate};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

const AGENTS: usize = 3;
const FRAMES: usize = 600;
const KEYFRAME_EVERY: usize = 20;
/// Odometry noise per keyframe step (makes the trajectories drift).
const ODOMETRY_SIGMA_M: f64 = 0.004;
const ODOMETRY_SIGMA_RAD: f64 = 0.003;
/// Noise of a correct loop closure (what a verified G-ICP alignment leaves).
const LOOP_SIGMA_M: f64 = 0.005;
const LOOP_SIGMA_RAD: f64 = 0.003;
/// Keyframes closer than this and looking within this angle close a loop (as place recognition
/// would propose); same-agent pairs must be this many keyframes apart (not neighbours).
const LOOP_MAX_DISTANCE_M: f64 = 0.8;
const LOOP_MAX_ANGLE_DEG: f64 = 30.0;
const SAME_AGENT_MIN_GAP: u64 = 8;
/// Fraction of closures replaced by random transforms, and their range.
const OUTLIER_FRACTION: f64 = 0.3;
const OUTLIER_TRANSLATION_M: f64 = 2.0;

struct Scenario {
    /// Ground-truth `room_from_camera` per keyframe.
    truth: BTreeMap<KeyframeRef, Isometry3<f64>>,
    /// Drifting `agent_from_camera` per keyframe (each agent starts at identity).
    tracked: BTreeMap<KeyframeRef, Isometry3<f64>>,
    closures: Vec<LoopClosure>,
}

fn gaussian_vector(rng: &mut ChaCha8Rng, sigma: f64) -> Vector3<f64> {
    // Sum of uniforms: close enough to Gaussian for noise, and needs no extra distribution crate.
    let mut sample = || (0..12).map(|_| rng.random_range(-0.5..0.5)).sum::<f64>() * sigma;
    Vector3::new(sample(), sample(), sample())
}

fn noisy(
    rng: &mut ChaCha8Rng,
    pose: &Isometry3<f64>,
    sigma_m: f64,
    sigma_rad: f64,
) -> Isometry3<f64> {
    let translation = gaussian_vector(rng, sigma_m);
    let rotation = gaussian_vector(rng, sigma_rad);
    pose * Isometry3::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_scaled_axis(rotation),
    )
}

fn scenario() -> Scenario {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let spec = SyntheticSpec {
        agents: AGENTS,
        frames: FRAMES,
        ..SyntheticSpec::default()
    };
    let mut truth = BTreeMap::new();
    let mut tracked = BTreeMap::new();
    for agent in 0..AGENTS {
        let dataset = SyntheticDataset::new(spec.with_agent(agent), FrameRange::ALL).unwrap();
        let mut agent_from_camera = Isometry3::identity();
        let mut previous: Option<Isometry3<f64>> = None;
        for position in (0..dataset.len()).step_by(KEYFRAME_EVERY) {
            let room_from_camera = dataset.ground_truth(position).unwrap().unwrap();
            if let Some(previous) = previous {
                let step = previous.inverse() * room_from_camera;
                agent_from_camera *= noisy(&mut rng, &step, ODOMETRY_SIGMA_M, ODOMETRY_SIGMA_RAD);
            }
            previous = Some(room_from_camera);
            let id = KeyframeRef {
                agent_id: agent as u32,
                keyframe_id: position as u64,
            };
            truth.insert(id, room_from_camera);
            tracked.insert(id, agent_from_camera);
        }
    }
    let ids: Vec<KeyframeRef> = truth.keys().copied().collect();
    let mut closures = Vec::new();
    for (n, source) in ids.iter().enumerate() {
        for target in &ids[..n] {
            if source.agent_id == target.agent_id
                && source.keyframe_id.abs_diff(target.keyframe_id)
                    < SAME_AGENT_MIN_GAP * KEYFRAME_EVERY as u64
            {
                continue;
            }
            let (s, t) = (truth[source], truth[target]);
            let axis_angle = (s.rotation * Vector3::z())
                .angle(&(t.rotation * Vector3::z()))
                .to_degrees();
            if (s.translation.vector - t.translation.vector).norm() > LOOP_MAX_DISTANCE_M
                || axis_angle > LOOP_MAX_ANGLE_DEG
            {
                continue;
            }
            closures.push(LoopClosure {
                source: *source,
                target: *target,
                target_camera_from_source_camera: noisy(
                    &mut rng,
                    &(t.inverse() * s),
                    LOOP_SIGMA_M,
                    LOOP_SIGMA_RAD,
                ),
                sigmas: None,
            });
        }
    }
    Scenario {
        truth,
        tracked,
        closures,
    }
}

/// Indices of the closures replaced by random transforms, and the corrupted list.
fn corrupt(closures: &[LoopClosure]) -> (Vec<usize>, Vec<LoopClosure>) {
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    let count = (OUTLIER_FRACTION * closures.len() as f64).round() as usize;
    let mut chosen: Vec<usize> = Vec::new();
    while chosen.len() < count {
        let k = rng.random_range(0..closures.len());
        if !chosen.contains(&k) {
            chosen.push(k);
        }
    }
    let mut corrupted = closures.to_vec();
    for &k in &chosen {
        let axis = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        let angle = rng.random_range(0.0..std::f64::consts::PI);
        let translation = Vector3::new(
            rng.random_range(-OUTLIER_TRANSLATION_M..OUTLIER_TRANSLATION_M),
            rng.random_range(-OUTLIER_TRANSLATION_M..OUTLIER_TRANSLATION_M),
            rng.random_range(-OUTLIER_TRANSLATION_M..OUTLIER_TRANSLATION_M),
        );
        corrupted[k].target_camera_from_source_camera = Isometry3::from_parts(
            Translation3::from(translation),
            UnitQuaternion::from_scaled_axis(axis * angle),
        );
    }
    chosen.sort_unstable();
    (chosen, corrupted)
}

fn solve(scenario: &Scenario, closures: &[LoopClosure]) -> PoseGraphSolution {
    let mut graph = PoseGraph::new();
    for (id, pose) in &scenario.tracked {
        // Keyframe ids are the frames' positions in the agent's sequence.
        graph.add_keyframe(*id, *pose, id.keyframe_id);
    }
    for closure in closures {
        graph.add_loop(*closure).unwrap();
    }
    graph.solve(&PoseGraphConfig::default()).unwrap()
}

/// Joint ATE (one SE(3) alignment for all agents) of keyframe poses against ground truth.
fn joint_keyframe_ate(
    scenario: &Scenario,
    world_from_camera: &BTreeMap<KeyframeRef, Isometry3<f64>>,
) -> f64 {
    let agents: Vec<(Trajectory, Trajectory)> = (0..AGENTS as u32)
        .map(|agent| {
            let ids = scenario.truth.keys().filter(|k| k.agent_id == agent);
            let stamp = |k: &KeyframeRef| k.keyframe_id as f64 / FRAMES_PER_SECOND;
            (
                Trajectory::from_pairs(ids.clone().map(|k| (stamp(k), scenario.truth[k]))),
                Trajectory::from_pairs(ids.map(|k| (stamp(k), world_from_camera[k]))),
            )
        })
        .collect();
    joint_ate(&agents, Alignment::Se3, DEFAULT_MAX_DT)
        .unwrap()
        .joint
        .rmse
}

#[test]
fn thirty_percent_random_loop_closures_are_rejected() {
    let scenario = scenario();
    let inter_agent = scenario
        .closures
        .iter()
        .filter(|c| c.source.agent_id != c.target.agent_id)
        .count();
    eprintln!(
        "{} keyframes, {} loop closures ({inter_agent} inter-agent, the others within one agent)",
        scenario.tracked.len(),
        scenario.closures.len()
    );
    assert!(inter_agent >= 10, "the agents' loops must overlap");

    let clock = Instant::now();
    let clean = solve(&scenario, &scenario.closures);
    let clean_time = clock.elapsed();
    assert_eq!(clean.world_from_agent.len(), AGENTS);
    assert!(clean.world_from_agent.values().all(Option::is_some));
    let clean_ate = joint_keyframe_ate(&scenario, &clean.world_from_camera);
    let clean_rejected = clean.loops.iter().filter(|l| !l.accepted).count();

    let (outliers, corrupted) = corrupt(&scenario.closures);
    // The same correct closures without the replaced ones: what a perfect outlier rejection can
    // at best achieve, since a replaced closure's correct measurement is lost.
    let kept: Vec<LoopClosure> = scenario
        .closures
        .iter()
        .enumerate()
        .filter(|(k, _)| !outliers.contains(k))
        .map(|(_, c)| *c)
        .collect();
    let kept_ate = joint_keyframe_ate(&scenario, &solve(&scenario, &kept).world_from_camera);
    let clock = Instant::now();
    let robust = solve(&scenario, &corrupted);
    let robust_time = clock.elapsed();
    let robust_ate = joint_keyframe_ate(&scenario, &robust.world_from_camera);
    let outliers_accepted: Vec<usize> = outliers
        .iter()
        .copied()
        .filter(|&k| robust.loops[k].accepted)
        .collect();
    let inliers_rejected = robust
        .loops
        .iter()
        .filter(|l| !l.accepted && !outliers.contains(&l.index))
        .count();
    eprintln!(
        "clean: ATE {:.2} cm, {clean_rejected} rejected, {} GNC steps, {:.2} s",
        clean_ate * 100.0,
        clean.gnc_steps,
        clean_time.as_secs_f64()
    );
    eprintln!(
        "30 % outliers ({}): ATE {:.2} cm, outliers accepted {:?}, inliers rejected {}, {} GNC \
         steps, {:.2} s",
        outliers.len(),
        robust_ate * 100.0,
        outliers_accepted,
        inliers_rejected,
        robust.gnc_steps,
        robust_time.as_secs_f64()
    );
    eprintln!(
        "the correct 70 % alone: ATE {:.2} cm; robust / that = {:.3}, robust / all clean = {:.3}",
        kept_ate * 100.0,
        robust_ate / kept_ate,
        robust_ate / clean_ate
    );
    assert!(outliers_accepted.is_empty(), "wrong closures accepted");
    assert!(
        inliers_rejected * 10 <= scenario.closures.len() - outliers.len(),
        "more than 10 % of the correct closures rejected"
    );
    assert!(robust.world_from_agent.values().all(Option::is_some));
    // Wrong closures must not bend the map: within 10 % of the run with only the correct 70 %.
    assert!(
        robust_ate <= 1.1 * kept_ate,
        "ATE {robust_ate} m vs {kept_ate} m with the outliers left out"
    );
    // Against all closures correct, the replaced closures' information is missing as well.
    assert!(
        robust_ate <= 1.25 * clean_ate,
        "ATE {robust_ate} m vs clean {clean_ate} m"
    );
}
