use super::*;
use crate::alignment::Keyframe;
use crate::engine::Decision;
use crate::engine::KeyframeArrival;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use protocol::messages::GaussianRecord;

fn identity(run_id: &str) -> RunIdentity {
    RunIdentity {
        run_id: run_id.to_string(),
        config_hash: 42,
        agents: Some(2),
    }
}

fn arrival(keyframe_id: u64) -> KeyframeArrival {
    let (width, height) = (4, 3);
    let rgb = RgbImage::from_fn(width, height, |x, y| image::Rgb([x as u8, y as u8, 7]));
    let mut depth = DepthImage::new(width, height);
    depth.data[5] = 1.25;
    KeyframeArrival {
        keyframe: Keyframe {
            id: crate::place_recognition::KeyframeRef {
                agent_id: 1,
                keyframe_id,
            },
            rgb,
            depth,
            intrinsics: Intrinsics {
                fx: 3.0,
                fy: 3.0,
                cx: 1.5,
                cy: 1.0,
                width,
                height,
            },
            agent_from_camera: Isometry3::from_parts(
                Translation3::new(0.5, -1.0, 2.0),
                UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
            ),
        },
        frame_index: 10 * keyframe_id,
        timestamp_s: keyframe_id as f64,
        descriptor: vec![0.5, 0.5, 0.0],
        gaussians: Default::default(),
    }
}

use image::RgbImage;

#[test]
fn inputs_come_back_in_order_after_reopening() {
    let dir = tempfile::tempdir().unwrap();
    let run = identity("run-a");
    {
        let (mut store, opened, inputs) = Store::open(dir.path(), &run, false).unwrap();
        assert_eq!(opened, Opened::New);
        assert!(inputs.is_empty());
        store
            .append(&StoredInput::Hello {
                agent_id: 1,
                epoch: 9,
                run_anchor: 77,
                config_hash: 5,
            })
            .unwrap();
        store
            .append(&StoredInput::Keyframe(Box::new(StoredKeyframe::new(
                &arrival(3),
                9,
            ))))
            .unwrap();
        store
            .append(&StoredInput::Patch {
                agent_id: 1,
                keyframe_id: 3,
                epoch: 9,
                records: vec![GaussianRecord::default(); 2],
            })
            .unwrap();
        assert_eq!(store.keyframe_write_ms().len(), 1);
    }
    let (mut store, opened, inputs) = Store::open(dir.path(), &run, false).unwrap();
    assert_eq!(opened, Opened::Resumed);
    assert_eq!(inputs.len(), 3);
    assert!(matches!(
        inputs[0],
        StoredInput::Hello { run_anchor: 77, .. }
    ));
    let StoredInput::Keyframe(stored) = &inputs[1] else {
        panic!("second input is not the keyframe");
    };
    let keyframe = stored.keyframe().unwrap();
    let original = arrival(3);
    assert_eq!(keyframe.rgb, original.keyframe.rgb);
    assert_eq!(keyframe.depth, original.keyframe.depth);
    assert!(
        (keyframe.agent_from_camera.to_homogeneous()
            - original.keyframe.agent_from_camera.to_homogeneous())
        .norm()
            < 1e-12
    );
    assert_eq!(stored.frame_index, 30);
    assert!(matches!(&inputs[2], StoredInput::Patch { records, .. } if records.len() == 2));
    // Appending after a resume continues the sequence rather than overwriting.
    store.append(&StoredInput::Goodbye { agent_id: 1 }).unwrap();
    drop(store);
    let (_, _, inputs) = Store::open(dir.path(), &run, false).unwrap();
    assert_eq!(inputs.len(), 4);
    assert!(matches!(inputs[3], StoredInput::Goodbye { agent_id: 1 }));
}

#[test]
fn a_store_of_another_run_is_refused_naming_the_file_and_the_difference() {
    let dir = tempfile::tempdir().unwrap();
    drop(Store::open(dir.path(), &identity("run-a"), false).unwrap());
    for (other, expected) in [
        (identity("run-b"), "run id 'run-a' there, 'run-b' here"),
        (
            RunIdentity {
                config_hash: 43,
                ..identity("run-a")
            },
            "configuration hash",
        ),
        (
            RunIdentity {
                agents: Some(3),
                ..identity("run-a")
            },
            "2 agents there, 3 here",
        ),
    ] {
        let error = Store::open(dir.path(), &other, false)
            .err()
            .expect("a store of another run must be refused");
        let message = format!("{error:#}");
        assert!(message.contains(STORE_FILE), "{message}");
        assert!(message.contains(expected), "{message}");
        assert!(message.contains("--fresh"), "{message}");
    }
}

#[test]
fn fresh_moves_the_old_store_aside_and_starts_empty() {
    let dir = tempfile::tempdir().unwrap();
    {
        let (mut store, _, _) = Store::open(dir.path(), &identity("run-a"), false).unwrap();
        store.append(&StoredInput::Goodbye { agent_id: 0 }).unwrap();
    }
    let (_, opened, inputs) = Store::open(dir.path(), &identity("run-b"), true).unwrap();
    assert_eq!(opened, Opened::New);
    assert!(inputs.is_empty());
    assert!(dir.path().join(format!("{STORE_FILE}.replaced")).exists());
}

fn decision(source: u64, target: u64, transform: &Isometry3<f64>) -> Decision {
    let id = |keyframe_id| crate::place_recognition::KeyframeRef {
        agent_id: 1,
        keyframe_id,
    };
    Decision {
        event: crate::engine::ClosureEvent {
            at_s: 1.5,
            source: id(source),
            target: id(target),
            origin: crate::engine::CandidateSource::Odometry,
            inter_agent: false,
            score: None,
            verified: true,
            kind: crate::engine::AttemptKind::Keyframe,
            inliers: Some(40),
            overlap: Some(0.8),
            map: None,
            rejection: None,
            accepted_by_pose_graph: None,
            alignment_ms: 900.0,
            measurement: Some(crate::engine::ClosureMeasurement {
                target_camera_from_source_camera: transform.into(),
                sigmas: None,
            }),
        },
        map_attempt: None,
    }
}

fn correction(agent_id: u32, transform: &Isometry3<f64>) -> StoredCorrection {
    StoredCorrection {
        agent_id,
        sequence: 0,
        world_from_agent: transform.into(),
        world_from_camera: vec![(3, (&transform.inverse()).into())],
    }
}

#[test]
fn decisions_and_corrections_come_back_bit_for_bit_after_reopening() {
    let dir = tempfile::tempdir().unwrap();
    let run = identity("run-a");
    // Not a round number in any component, so a lossy encoding would show.
    let transform = Isometry3::from_parts(
        Translation3::new(0.1, -1.0 / 3.0, 2.0_f64.sqrt()),
        UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
    );
    {
        let (store, _, _) = Store::open(dir.path(), &run, false).unwrap();
        let mut log = store.decision_log().unwrap();
        log.append(&decision(1, 0, &transform)).unwrap();
        log.append(&decision(2, 1, &transform.inverse())).unwrap();
        drop(log);
        let mut store = store;
        let sent = store
            .append_corrections(vec![correction(0, &transform), correction(1, &transform)])
            .unwrap();
        assert_eq!(sent.iter().map(|c| c.sequence).collect::<Vec<_>>(), [0, 0]);
        let sent = store
            .append_corrections(vec![correction(1, &transform.inverse())])
            .unwrap();
        assert_eq!(sent[0].sequence, 1);
    }
    let decisions = read_decisions(&dir.path().join(STORE_FILE)).unwrap();
    let (mut store, opened, _) = Store::open(dir.path(), &run, false).unwrap();
    assert_eq!(opened, Opened::Resumed);
    let reopened = store.decisions().unwrap();
    assert_eq!(reopened.len(), 2);
    assert_eq!(decisions.len(), 2);
    let measured = |d: &Decision| {
        d.event
            .measurement
            .unwrap()
            .target_camera_from_source_camera
            .isometry()
    };
    assert_eq!(measured(&reopened[0]), transform);
    assert_eq!(measured(&reopened[1]), transform.inverse());
    let last = store.last_corrections().unwrap();
    assert_eq!(last.len(), 2);
    assert_eq!(last[&0].sequence, 0);
    assert_eq!(last[&1].sequence, 1);
    assert_eq!(last[&1].world_from_agent.isometry(), transform.inverse());
    assert_eq!(
        last[&1].world_from_camera[0].1.isometry(),
        transform.inverse().inverse()
    );
    // Numbering goes on where the stored corrections end; decisions append after the stored.
    let sent = store
        .append_corrections(vec![correction(1, &transform)])
        .unwrap();
    assert_eq!(sent[0].sequence, 2);
    store
        .decision_log()
        .unwrap()
        .append(&decision(3, 2, &transform))
        .unwrap();
    assert_eq!(store.decisions().unwrap().len(), 3);
}
