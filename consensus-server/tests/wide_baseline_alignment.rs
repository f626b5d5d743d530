//! Keyframe alignment where the two views differ a lot: a camera rolled by 90 degrees about its
//! optical axis, and two agents 1.5 m apart looking 36 degrees apart at the same corner of the
//! synthetic room. Both failed with unsteered BRIEF on strongest-first FAST corners (6 and 7
//! coarse inliers, 15 needed; `examples/keyframe_matching/`). Ground truth only picks the
//! views and scores the estimate.

use config::AlignmentConfig;
use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{Dataset, FrameRange};
use mac_consensus::alignment::{AlignmentResult, Keyframe, Verdict, align};
use mac_consensus::place_recognition::KeyframeRef;
use nalgebra::{Isometry3, UnitQuaternion, Vector3};

/// The scene of the pairs below: two agents, 300 frames each, the default seed and 640x480.
fn dataset(agent: usize) -> SyntheticDataset {
    let spec = SyntheticSpec {
        agents: 2,
        frames: 300,
        ..SyntheticSpec::default()
    }
    .with_agent(agent);
    SyntheticDataset::new(spec, FrameRange::ALL).unwrap()
}

fn keyframe(
    dataset: &SyntheticDataset,
    agent_id: u32,
    world_from_camera: &Isometry3<f64>,
) -> Keyframe {
    let (rgb, depth) = dataset.render_view(world_from_camera);
    Keyframe {
        id: KeyframeRef {
            agent_id,
            keyframe_id: 0,
        },
        rgb,
        depth,
        intrinsics: dataset.intrinsics(),
        // Alignment does not use the agents' poses.
        agent_from_camera: Isometry3::identity(),
    }
}

fn optical_axis(pose: &Isometry3<f64>) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}

/// Aligns the view of agent 1 at `source_pose` to agent 0's at `target_pose`; checks acceptance
/// and the pose against the truth.
fn align_and_check(source_pose: &Isometry3<f64>, target_pose: &Isometry3<f64>) -> AlignmentResult {
    let (a, b) = (dataset(0), dataset(1));
    let result = align(
        keyframe(&b, 1, source_pose),
        keyframe(&a, 0, target_pose),
        &AlignmentConfig::default(),
    );
    eprintln!("coarse: {:?}", result.coarse);
    eprintln!("refinement: {:?}", result.refinement);
    assert_eq!(result.verdict, Verdict::Accepted, "{result:?}");
    let truth = target_pose.inverse() * source_pose;
    let error = result.target_camera_from_source_camera.inverse() * truth;
    let (dt, dr) = (
        error.translation.vector.norm(),
        error.rotation.angle().to_degrees(),
    );
    eprintln!("pose error {:.2} mm, {:.3} deg", dt * 1e3, dr);
    assert!(dt < 0.01 && dr < 0.5, "off by {dt} m, {dr} deg");
    result
}

#[test]
fn a_view_rolled_by_90_degrees_aligns() {
    let (a, b) = (dataset(0), dataset(1));
    // 0.96 m apart, optical axes 17 degrees apart, 70 % co-visible before the roll.
    let target_pose = a.ground_truth(100).unwrap().unwrap();
    let source_pose = b.ground_truth(200).unwrap().unwrap()
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 90f64.to_radians());
    let result = align_and_check(&source_pose, &target_pose);
    assert!(result.coarse.unwrap().inliers >= 30);
}

#[test]
fn agents_one_and_a_half_metres_apart_align() {
    let (a, b) = (dataset(0), dataset(1));
    let target_pose = a.ground_truth(220).unwrap().unwrap();
    let source_pose = b.ground_truth(130).unwrap().unwrap();
    let baseline = (target_pose.translation.vector - source_pose.translation.vector).norm();
    let angle = optical_axis(&target_pose)
        .angle(&optical_axis(&source_pose))
        .to_degrees();
    eprintln!("baseline {baseline:.2} m, optical axes {angle:.0} degrees apart");
    assert!(baseline > 1.4 && angle > 30.0);
    align_and_check(&source_pose, &target_pose);
}
