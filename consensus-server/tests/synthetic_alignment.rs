//! Keyframe alignment and the agent-to-world transform on the synthetic scene, where ground truth
//! is exact. Ground truth only sets up the test (which frames to pair, the true transform to
//! compare with); the method sees images, depth and each agent's own poses.

use std::time::Instant;

use config::{AlignmentConfig, PoseGraphConfig};
use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{Dataset, FrameRange};
use mac_consensus::alignment::{Keyframe, Verdict, align};
use mac_consensus::place_recognition::KeyframeRef;
use mac_consensus::pose_graph::{LoopClosure, PoseGraph};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

const AGENTS: usize = 2;
const FRAMES: usize = 300;
/// Frames considered for the pair, every this many.
const CANDIDATE_STEP: usize = 5;
/// The pair is chosen with a camera baseline near this (metres) and optical axes within
/// `MAX_VIEW_ANGLE_DEG`: a real inter-agent closure, not two copies of one view.
const WANTED_BASELINE_M: f64 = 0.8;
const MAX_VIEW_ANGLE_DEG: f64 = 30.0;

fn dataset(agent: usize) -> SyntheticDataset {
    let spec = SyntheticSpec {
        agents: AGENTS,
        frames: FRAMES,
        ..SyntheticSpec::default()
    }
    .with_agent(agent);
    SyntheticDataset::new(spec, FrameRange::ALL).unwrap()
}

fn optical_axis(pose: &Isometry3<f64>) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}

/// Frames (agent 0, agent 1) whose cameras are about `WANTED_BASELINE_M` apart and look the same
/// way (test fixture selection from ground truth).
fn overlapping_pair(a: &SyntheticDataset, b: &SyntheticDataset) -> (usize, usize) {
    let mut best = None;
    for i in (0..a.len()).step_by(CANDIDATE_STEP) {
        for j in (0..b.len()).step_by(CANDIDATE_STEP) {
            let (pa, pb) = (
                a.ground_truth(i).unwrap().unwrap(),
                b.ground_truth(j).unwrap().unwrap(),
            );
            let angle = optical_axis(&pa).angle(&optical_axis(&pb)).to_degrees();
            let baseline = (pa.translation.vector - pb.translation.vector).norm();
            let badness = (baseline - WANTED_BASELINE_M).abs();
            if angle < MAX_VIEW_ANGLE_DEG && best.is_none_or(|(_, _, b)| badness < b) {
                best = Some((i, j, badness));
            }
        }
    }
    let (i, j, _) = best.expect("the synthetic agents' loops overlap");
    (i, j)
}

fn keyframe(
    dataset: &SyntheticDataset,
    position: usize,
    agent_id: u32,
    agent_from_room: &Isometry3<f64>,
) -> Keyframe {
    let frame = dataset.load(position).unwrap();
    Keyframe {
        id: KeyframeRef {
            agent_id,
            keyframe_id: position as u64,
        },
        rgb: frame.rgb,
        depth: frame.depth,
        intrinsics: frame.intrinsics,
        agent_from_camera: agent_from_room * frame.world_from_camera_gt.unwrap(),
    }
}

fn errors(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> (f64, f64) {
    let error = estimate.inverse() * truth;
    (
        error.translation.vector.norm(),
        error.rotation.angle().to_degrees(),
    )
}

#[test]
fn agent_to_world_transform_is_found_across_a_large_displacement() {
    let clock = Instant::now();
    let (a, b) = (dataset(0), dataset(1));
    let (i, j) = overlapping_pair(&a, &b);
    let (pa, pb) = (
        a.ground_truth(i).unwrap().unwrap(),
        b.ground_truth(j).unwrap().unwrap(),
    );
    eprintln!(
        "pair: agent 0 frame {i}, agent 1 frame {j}: baseline {:.2} m, view angle {:.1} deg",
        (pa.translation.vector - pb.translation.vector).norm(),
        optical_axis(&pa).angle(&optical_axis(&pb)).to_degrees()
    );
    // Agent 0 starts at identity: its frame (the world) is its first camera.
    let world_from_room = a.ground_truth(0).unwrap().unwrap().inverse();
    // Agent 1's frame is displaced from the world by 2 m and 90 degrees.
    let world_from_agent1 = Isometry3::from_parts(
        Translation3::new(1.2, -1.6, 0.0),
        UnitQuaternion::from_axis_angle(
            &nalgebra::Unit::new_normalize(Vector3::new(0.3, 1.0, -0.2)),
            90f64.to_radians(),
        ),
    );
    assert!((world_from_agent1.translation.vector.norm() - 2.0).abs() < 1e-12);
    let agent1_from_room = world_from_agent1.inverse() * world_from_room;

    let target = keyframe(&a, i, 0, &world_from_room);
    let source = keyframe(&b, j, 1, &agent1_from_room);
    let (target_id, source_id) = (target.id, source.id);
    let (target_pose, source_pose) = (target.agent_from_camera, source.agent_from_camera);
    let rendered = clock.elapsed();

    let clock = Instant::now();
    let result = align(source, target, &AlignmentConfig::default());
    let aligned = clock.elapsed();
    eprintln!("coarse: {:?}", result.coarse);
    eprintln!("refinement: {:?}", result.refinement);
    assert_eq!(result.verdict, Verdict::Accepted, "{result:?}");
    let truth_relative = pa.inverse() * pb;
    let (dt, dr) = errors(&result.target_camera_from_source_camera, &truth_relative);
    eprintln!("relative pose error: {:.2} mm, {:.3} deg", dt * 1e3, dr);

    let mut graph = PoseGraph::new();
    graph.add_keyframe(target_id, target_pose, i as u64);
    graph.add_keyframe(source_id, source_pose, j as u64);
    graph
        .add_loop(LoopClosure {
            source: source_id,
            target: target_id,
            target_camera_from_source_camera: result.target_camera_from_source_camera,
            sigmas: None,
        })
        .unwrap();
    let solution = graph.solve(&PoseGraphConfig::default()).unwrap();
    assert!(solution.loops[0].accepted);
    let estimate = solution.world_from_agent[&1].expect("agent 1 linked to the world");
    let (dt, dr) = errors(&estimate, &world_from_agent1);
    eprintln!(
        "agent-to-world error: {:.2} mm, {:.3} deg (render {:.2} s, align {:.2} s)",
        dt * 1e3,
        dr,
        rendered.as_secs_f64(),
        aligned.as_secs_f64()
    );
    assert!(
        dt < 0.01 && dr < 0.5,
        "agent-to-world off by {dt} m, {dr} deg"
    );
    assert_eq!(solution.world_from_agent[&0], Some(Isometry3::identity()));
}

#[test]
fn views_of_different_places_are_rejected_with_a_reason() {
    let (a, b) = (dataset(0), dataset(1));
    // Frame 0 of each agent: opposite sides of the loop, looking at opposite walls.
    let (pa, pb) = (
        a.ground_truth(0).unwrap().unwrap(),
        b.ground_truth(0).unwrap().unwrap(),
    );
    assert!(optical_axis(&pa).angle(&optical_axis(&pb)).to_degrees() > 120.0);
    let identity = Isometry3::identity();
    let result = align(
        keyframe(&b, 0, 1, &identity),
        keyframe(&a, 0, 0, &identity),
        &AlignmentConfig::default(),
    );
    eprintln!("{:?}\n{:?}", result.coarse, result.refinement);
    match &result.verdict {
        Verdict::Rejected(reason) => eprintln!("rejected: {reason}"),
        Verdict::Accepted => panic!("views of different walls accepted: {result:?}"),
    }
}
