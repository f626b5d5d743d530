//! A consensus correction applied to an agent's local maps (agent/src/corrections.rs): after the
//! tracking map is moved, tracking goes on in the moved map, and the poses the agent publishes
//! (its tracked frame) do not jump.
//!
//! Two odometries track the same synthetic frames. One is left alone (the reference). The other
//! gets, after frame `CORRECT_AFTER`, a correction saying that every keyframe it made sits
//! `fix` away from where it was tracked (a rigid fix of the whole map: easy to predict). From
//! then on its local-map poses must be `fix * reference` and its tracked-frame poses equal to
//! the reference.

use mac_agent::corrections::{LocalCorrections, LocalMaps, ReceivedCorrection};
use mac_agent::mapper::Mapper;
use mac_agent::seeding::CoverageIndex;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use slam_core::config::{Config, LocalCorrectionConfig};
use slam_core::dataset::{self, FrameRange};
use slam_core::registration::odometry::{Odometry, OdometryMode};

const FRAMES: usize = 24;
const CORRECT_AFTER: usize = 12;
/// Tracking repeats to well below a millimetre on exact synthetic depth.
const TOLERANCE_M: f64 = 2e-3;
const TOLERANCE_RAD: f64 = 2e-3;

fn distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle())
}

#[test]
fn tracking_continues_in_the_corrected_map_and_published_poses_do_not_jump() {
    let config = Config::default();
    let dataset = dataset::open(
        &format!("synthetic:agents=2,agent=0,frames={FRAMES},width=320,height=240"),
        FrameRange::ALL,
    )
    .unwrap();
    let new_odometry = || {
        Odometry::new(
            OdometryMode::FrameToModel,
            &config.tracking,
            &config.keyframes,
        )
    };
    let mut reference = new_odometry();
    let mut odometry = new_odometry();
    let mut coverage = CoverageIndex::new(0.02);
    let mapper = Mapper::spawn(&config.tracking, &config.mapping).unwrap();
    let mut corrections = LocalCorrections::new(&LocalCorrectionConfig::default());
    let fix = Isometry3::from_parts(
        Translation3::new(0.04, -0.02, 0.03),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
    );
    let mut keyframes = Vec::new();
    let mut checked = 0;
    for position in 0..dataset.len() {
        let frame = dataset.load(position).unwrap();
        let expected = reference
            .track(&frame.depth, &frame.intrinsics)
            .world_from_camera;
        let first_point = odometry.next_point_id();
        let tracked = odometry.track(&frame.depth, &frame.intrinsics);
        if odometry.next_point_id() > first_point {
            corrections.record_tracker_points(first_point, frame.timestamp);
        }
        let tracked_pose = corrections.to_tracked(frame.timestamp, &tracked.world_from_camera);
        if tracked.keyframe {
            corrections.record_keyframe(keyframes.len(), frame.timestamp, tracked_pose);
            keyframes.push(tracked_pose);
        }
        if position > CORRECT_AFTER {
            let (local_m, local_rad) = distance(&tracked.world_from_camera, &(fix * expected));
            assert!(
                local_m < TOLERANCE_M && local_rad < TOLERANCE_RAD,
                "frame {position}: local-map pose {local_m} m / {local_rad} rad from fix * reference"
            );
            checked += 1;
        }
        let (m, rad) = distance(&tracked_pose, &expected);
        assert!(
            m < TOLERANCE_M && rad < TOLERANCE_RAD,
            "frame {position}: tracked-frame pose {m} m / {rad} rad from the reference"
        );
        if position == CORRECT_AFTER {
            assert!(keyframes.len() >= 2, "the scene makes keyframes");
            // The consensus: agent 1's frame is 3 m and 90 degrees away (irrelevant to the local
            // maps), and every keyframe of this agent belongs `fix` away.
            let world_from_agent = Isometry3::from_parts(
                Translation3::new(3.0, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
            );
            let received = ReceivedCorrection {
                world_from_agent,
                keyframes: keyframes
                    .iter()
                    .enumerate()
                    .map(|(id, pose)| (id as u64, world_from_agent * fix * pose))
                    .collect(),
            };
            let applied = corrections.apply(
                &received,
                frame.timestamp,
                LocalMaps {
                    odometry: &mut odometry,
                    coverage: &mut coverage,
                    mapper: &mapper,
                },
            );
            assert!(applied);
            assert_eq!(corrections.stats().applied, 1);
            // The same correction again moves nothing: it is below the threshold now.
            assert!(!corrections.apply(
                &received,
                frame.timestamp,
                LocalMaps {
                    odometry: &mut odometry,
                    coverage: &mut coverage,
                    mapper: &mapper,
                },
            ));
            assert_eq!(corrections.stats().below_threshold, 1);
        }
    }
    assert_eq!(checked, FRAMES - CORRECT_AFTER - 1);
    let outcome = mapper.finish(0).unwrap();
    assert_eq!(outcome.realtime.corrections, 1);
}
