use super::*;
use crate::gicp::RegistrationFailure;
use datasets::FrameRange;
use geometry::trajectory::Trajectory;
use metrics::ate::{Alignment, DEFAULT_MAX_DT, ate};
use nalgebra::Isometry3;

/// The tracker's view of a dataset frame.
fn input(frame: &datasets::Frame) -> FrameInput<'_> {
    FrameInput {
        timestamp_s: frame.timestamp,
        depth: &frame.depth,
        rgb: Some(&frame.rgb),
        intrinsics: &frame.intrinsics,
        colour_offset_s: frame.colour_offset_s,
        real_time: false,
    }
}

/// Tracks `frames` of a dataset from identity; returns (ATE RMSE in metres, stats).
fn track_sequence(spec: &str, frames: FrameRange, mode: OdometryMode) -> (f64, OdometryStats) {
    let ds = datasets::open(spec, frames).unwrap();
    let mut odometry = Odometry::new(mode, &TrackingConfig::default(), &KeyframeConfig::default());
    let mut estimate = Trajectory::default();
    let mut ground_truth = Trajectory::default();
    for i in 0..ds.len() {
        let frame = ds.load(i).unwrap();
        let tracked = odometry.track(input(&frame));
        // Poses go on the wire, which refuses quaternions off unit norm by more than 1e-6.
        let norm = tracked.world_from_camera.rotation.quaternion().norm();
        assert!(
            (norm - 1.0).abs() < 1e-12,
            "frame {i}: quaternion norm {norm}"
        );
        estimate.push(frame.timestamp, tracked.world_from_camera);
        ground_truth.push(frame.timestamp, frame.world_from_camera_gt.unwrap());
    }
    let result = ate(&ground_truth, &estimate, Alignment::Se3, DEFAULT_MAX_DT).unwrap();
    (result.stats.rmse, odometry.stats().clone())
}

#[test]
fn tracks_the_synthetic_scene_in_both_modes() {
    for mode in [OdometryMode::FrameToFrame, OdometryMode::FrameToModel] {
        let (rmse, stats) = track_sequence(
            "synthetic:agents=1,frames=20,width=320,height=240",
            FrameRange::ALL,
            mode,
        );
        assert_eq!(stats.frames, 20);
        assert_eq!(stats.failures, 0, "{mode}: {stats:?}");
        assert!(rmse < 0.01, "{mode}: ATE RMSE {rmse} m");
    }
}

/// Tracks the frames of `spec` (in `frames`) at `positions`, in that order, with `tracking`;
/// returns ATE RMSE and the stats.
fn track_positions(
    spec: &str,
    frames: FrameRange,
    positions: impl IntoIterator<Item = usize>,
    tracking: &TrackingConfig,
) -> (f64, OdometryStats) {
    let ds = datasets::open(spec, frames).unwrap();
    let mut odometry = Odometry::new(
        OdometryMode::FrameToModel,
        tracking,
        &KeyframeConfig::default(),
    );
    let mut estimate = Trajectory::default();
    let mut ground_truth = Trajectory::default();
    for position in positions {
        let frame = ds.load(position).unwrap();
        let tracked = odometry.track(input(&frame));
        estimate.push(frame.timestamp, tracked.world_from_camera);
        ground_truth.push(frame.timestamp, frame.world_from_camera_gt.unwrap());
    }
    let result = ate(&ground_truth, &estimate, Alignment::Se3, DEFAULT_MAX_DT).unwrap();
    (result.stats.rmse, odometry.stats().clone())
}

/// Tracks every frame of `spec` (in `frames`) at the positions `gaps` steps through, in a
/// cycle, as a live agent that falls behind skips frames; returns ATE RMSE and the stats.
fn track_with_gaps(spec: &str, frames: FrameRange, gaps: &[usize]) -> (f64, OdometryStats) {
    let len = datasets::open(spec, frames).unwrap().len();
    let positions = gaps
        .iter()
        .cycle()
        .scan(0, |position, gap| {
            let this = *position;
            *position += gap;
            Some(this)
        })
        .take_while(|&position| position < len);
    track_positions(spec, frames, positions, &TrackingConfig::default())
}

/// The frames an agent tracking tum-fr1-rpy at sensor pace with the photometric term on took
/// (the others dropped while it was busy), as its tracking.csv listed them: after a stall of
/// 17 frames (positions 328 to 345, a 22 degree turn) the wide G-ICP guess from the previous
/// pose slid 0.7 m along the scene and still passed the depth check (0.92 agreement, but 22 %
/// overlap where the frame before had 81 %); the image features were never tried and the rest
/// of the run was 0.6 m off (ATE 27.8 cm). A passing guess whose overlap dropped does not stop
/// the search now.
const TUM_RPY_SENSOR_PACE_POSITIONS: &str = "0..=33,35,39,42,44,51,55,59..=60,62,64,66..=67,\
    69..=160,162,164..=165,167..=168,171,174,176..=177,179..=182,184..=240,242,244..=245,\
    247..=249,251..=252,254,258,267,270,273..=320,322,324,326,328,345,351,354,356..=375,\
    377..=378,380,382..=384,386..=387,389,391,393,395,398,400,402,404..=419";

fn positions_of(list: &str) -> Vec<usize> {
    list.split(',')
        .flat_map(|item| {
            let item = item.trim();
            match item.split_once("..=") {
                Some((a, b)) => (a.parse().unwrap()..=b.parse().unwrap()).collect::<Vec<usize>>(),
                None => vec![item.parse().unwrap()],
            }
        })
        .collect()
}

#[test]
fn real_data_a_wide_guess_that_slid_after_a_stall_is_not_taken() {
    let dir = datasets::shared_data::require("datasets/tum-fr1-rpy");
    let positions = positions_of(TUM_RPY_SENSOR_PACE_POSITIONS);
    assert_eq!(positions.len(), 326);
    let mut tracking = TrackingConfig::default();
    tracking.photometric.weight = 0.3;
    let (rmse, stats) =
        track_positions(dir.to_str().unwrap(), FrameRange::ALL, positions, &tracking);
    assert_eq!(stats.failures, 0, "{stats:?}");
    assert!(rmse < 0.06, "ATE RMSE {rmse} m, {stats:?}");
}

/// Redkitchen 0..300 taken with gaps of up to 8 frame times: a constant-velocity motion
/// measured over a 1-frame step and not scaled to a 5-frame gap puts the frame 4 steps short,
/// and tracking loses the map (the figures with and without scaling: docs/benchmarks.md,
/// 2026-12-04).
#[test]
fn real_data_tracks_redkitchen_with_irregular_frame_gaps() {
    let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
    let range: FrameRange = "0..300".parse().unwrap();
    for gaps in [&[1, 1, 1, 5, 1, 1, 6][..], &[2, 2, 6, 2, 2, 8]] {
        let (rmse, stats) = track_with_gaps(dir.to_str().unwrap(), range, gaps);
        assert_eq!(stats.failures, 0, "gaps {gaps:?}: {stats:?}");
        assert!(rmse < 0.04, "gaps {gaps:?}: ATE RMSE {rmse} m");
    }
}

#[test]
fn frames_without_depth_are_counted_failures_not_panics() {
    let ds = datasets::open(
        "synthetic:agents=1,frames=20,width=320,height=240",
        FrameRange::ALL,
    )
    .unwrap();
    let mut odometry = Odometry::new(
        OdometryMode::FrameToModel,
        &TrackingConfig::default(),
        &KeyframeConfig::default(),
    );
    let first = ds.load(0).unwrap();
    let start = odometry.track(input(&first));
    assert_eq!(start.outcome, TrackingOutcome::Initialised);
    assert!(start.keyframe && !odometry.map().is_empty());
    let map_size = odometry.map().len();
    let mut blank = first.depth.clone();
    blank.data.fill(f32::NAN);
    for _ in 0..TrackingConfig::default().max_consecutive_failures + 1 {
        let lost = odometry.track(FrameInput {
            depth: &blank,
            ..input(&first)
        });
        assert!(matches!(
            lost.outcome,
            TrackingOutcome::Lost(TrackingFailure::Registration(
                RegistrationFailure::TooFewSourcePoints { found: 0, .. }
            ))
        ));
        assert_eq!(lost.world_from_camera, start.world_from_camera);
    }
    // Without points there is nothing to re-initialise from: the map is kept as it was.
    assert_eq!(odometry.map().len(), map_size);
    assert_eq!(
        odometry.stats().failures,
        TrackingConfig::default().max_consecutive_failures + 1
    );
    let next = ds.load(1).unwrap();
    let back = odometry.track(input(&next));
    // Tracking resumes: after lost frames the prior is doubtful, so the frame is placed by a
    // wide-baseline guess.
    assert!(
        matches!(back.outcome, TrackingOutcome::Recovered(_)),
        "{:?} {:?}",
        back.outcome,
        back.registration
    );
}

#[test]
fn real_data_tracks_redkitchen_frames_0_to_100() {
    let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
    let range: FrameRange = "0..100".parse().unwrap();
    let (rmse, stats) = track_sequence(dir.to_str().unwrap(), range, OdometryMode::FrameToModel);
    assert_eq!(stats.frames, 100);
    assert_eq!(stats.failures, 0, "{stats:?}");
    assert!(rmse < 0.05, "ATE RMSE {rmse} m over frames 0..100");
}

/// Tracks `spec` frame by frame, with `depth_of` choosing each frame's depth (to blank some);
/// returns (root-frame ATE RMSE of the placed frames in metres, stats, frames placed).
fn track_placed(
    spec: &str,
    tracking: &TrackingConfig,
    blank: impl Fn(usize) -> bool,
) -> (f64, OdometryStats, usize) {
    track_covered(spec, tracking, blank, 0.0, false)
}

/// The frames of `spec` and a frame-to-model tracker with `tracking` and default keyframes.
fn frame_to_model(spec: &str, tracking: &TrackingConfig) -> (Box<dyn datasets::Dataset>, Odometry) {
    let ds = spec
        .parse::<datasets::DatasetSpec>()
        .unwrap()
        .open()
        .unwrap();
    let odometry = Odometry::new(
        OdometryMode::FrameToModel,
        tracking,
        &KeyframeConfig::default(),
    );
    (ds, odometry)
}

/// [`track_placed`] with the frames `covered` picks replaced by a flat surface at `cover_depth_m`
/// filling the view (a hand over the lens; 0: no depth at all) in a uniform colour; `real_time`
/// marks every frame real-time ([`FrameInput::real_time`]).
fn track_covered(
    spec: &str,
    tracking: &TrackingConfig,
    covered: impl Fn(usize) -> bool,
    cover_depth_m: f32,
    real_time: bool,
) -> (f64, OdometryStats, usize) {
    let (ds, mut odometry) = frame_to_model(spec, tracking);
    let mut poses: Vec<(f64, Isometry3<f64>, Placement, bool)> = Vec::new();
    let mut ground_truth = Trajectory::default();
    for position in 0..ds.len() {
        let frame = ds.load(position).unwrap();
        let mut cover = frame.depth.clone();
        cover.data.fill(cover_depth_m);
        let (width, height) = frame.rgb.dimensions();
        let skin = image::RgbImage::from_pixel(width, height, image::Rgb([190, 140, 120]));
        let tracked = if covered(position) {
            odometry.track(FrameInput {
                depth: &cover,
                rgb: Some(&skin),
                real_time,
                ..input(&frame)
            })
        } else {
            odometry.track(FrameInput {
                real_time,
                ..input(&frame)
            })
        };
        if let Some(join) = &tracked.join {
            move_joined(&mut poses, join);
        }
        let placed = !matches!(tracked.outcome, TrackingOutcome::Lost(_));
        poses.push((
            frame.timestamp,
            tracked.world_from_camera,
            tracked.placement,
            placed,
        ));
        ground_truth.push(frame.timestamp, frame.world_from_camera_gt.unwrap());
    }
    if let Some(join) = odometry.finish_search() {
        move_joined(&mut poses, &join);
    }
    let estimate = Trajectory::from_pairs(
        poses
            .iter()
            .filter(|p| p.2 == Placement::Root && p.3)
            .map(|p| (p.0, p.1)),
    );
    let result = ate(&ground_truth, &estimate, Alignment::Se3, DEFAULT_MAX_DT).unwrap();
    (result.stats.rmse, odometry.stats().clone(), estimate.len())
}

/// Moves the recorded poses of a joined segment into the root.
fn move_joined(poses: &mut [(f64, Isometry3<f64>, Placement, bool)], join: &SegmentJoin) {
    for (_, pose, placement, _) in poses {
        if let Some((moved_placement, moved)) = join.moved(*placement, pose) {
            *placement = moved_placement;
            *pose = moved;
        }
    }
}

/// Every 15th frame of the synthetic scene: steps of ~30 cm.
const FAST_MOTION: &str = "synthetic:agents=1,frames=300,width=320,height=240:0..300:15";

/// The tracking configuration of the synthetic tests: at 320x240 every 2nd pixel samples the
/// surfaces as densely as every 4th does at 640x480 (about 3.4 cm apart at the scene's median
/// depth), so the sparse-points retry (`spacing`) reaches at most 2.4 cm and steps of 30 cm stay
/// far beyond what the ordinary path can take.
fn tracking_320x240() -> TrackingConfig {
    TrackingConfig {
        pixel_stride: 2,
        ..TrackingConfig::default()
    }
}

/// Steps fifteen times the correspondence distance: the ordinary path alone slides off; the check
/// catches it and the wide-baseline guesses place every frame.
#[test]
fn fast_motion_is_recovered_not_lost() {
    let (rmse, stats, placed) = track_placed(FAST_MOTION, &tracking_320x240(), |_| false);
    assert_eq!(stats.failures, 0, "{stats:?}");
    assert!(stats.recoveries > 0, "{stats:?}");
    assert_eq!(placed, 20);
    assert!(rmse < 0.01, "ATE RMSE {rmse} m, {stats:?}");
}

/// The same frames with the wide-baseline guesses restricted to the fine distance: the check
/// must report the frames the ordinary path gets wrong instead of accepting them silently.
#[test]
fn divergence_is_reported_when_it_cannot_be_recovered() {
    let spec = "synthetic:agents=1,frames=150,width=320,height=240:0..150:5";
    let blind = TrackingConfig {
        recovery_distances_m: Vec::new(),
        recovery_geometry: false,
        // Segments would start and hide the count; this test is about detection.
        max_consecutive_failures: usize::MAX,
        ..TrackingConfig::default()
    };
    let (ds, mut odometry) = frame_to_model(spec, &blind);
    let mut silent_errors = 0;
    let mut reported = 0;
    let mut previous: Option<(Isometry3<f64>, Isometry3<f64>)> = None;
    for position in 0..ds.len() {
        let frame = ds.load(position).unwrap();
        // Depth only: the image-feature guess would rescue the frames this test wants lost.
        let tracked = odometry.track(FrameInput {
            rgb: None,
            ..input(&frame)
        });
        let truth = frame.world_from_camera_gt.unwrap();
        let lost = matches!(tracked.outcome, TrackingOutcome::Lost(_));
        reported += usize::from(lost || tracked.outcome != TrackingOutcome::Tracked);
        if let Some((estimate_before, truth_before)) = previous
            && !lost
        {
            let step_error = ((estimate_before.inverse() * tracked.world_from_camera).inverse()
                * (truth_before.inverse() * truth))
                .translation
                .vector
                .norm();
            silent_errors += usize::from(step_error > 0.05);
        }
        if !lost {
            previous = Some((tracked.world_from_camera, truth));
        }
    }
    assert!(reported > 0, "{:?}", odometry.stats());
    assert_eq!(
        silent_errors,
        0,
        "a step wrong by more than 5 cm was accepted: {:?}",
        odometry.stats()
    );
}

/// The sensor gives no depth for a while (frames 20-49 of 90, 1.2 m of travel) as the camera keeps
/// moving: the frames are lost, and the tracker finds its way back when depth returns.
#[test]
fn tracking_resumes_after_a_blackout() {
    let spec = "synthetic:agents=1,frames=180,width=320,height=240:0..180:2";
    let (rmse, stats, placed) = track_placed(spec, &tracking_320x240(), |p| (20..50).contains(&p));
    assert_eq!(stats.failures, 30, "{stats:?}");
    assert_eq!(placed, 60, "{stats:?}");
    assert!(rmse < 0.03, "ATE RMSE {rmse} m, {stats:?}");
}

/// A hand covers the lens for 7 frames (a flat surface 40 cm away): after 3 lost frames the
/// tracker starts a segment, which is the hand's; when the hand goes, the room cannot be tracked
/// against the hand and a second segment starts, which the tracker relocalises in the map by
/// place recognition and keyframe alignment and joins to it. The hand's segment is never joined
/// and stays out of the trajectory, and the joined one lands where the camera was.
#[test]
fn a_segment_after_the_lens_was_covered_is_joined_to_the_map() {
    let spec = "synthetic:agents=1,frames=240,width=320,height=240:0..240:3";
    let tracking = TrackingConfig {
        // Texture only: the FPFH guess is not what this test is about.
        recovery_geometry: false,
        // Every 3rd pixel, as this test was written for; at every 2nd the second segment was
        // not joined within the 80 frames (noted on the tracking issue).
        pixel_stride: 3,
        ..tracking_320x240()
    };
    let (rmse, stats, placed) =
        track_covered(spec, &tracking, |p| (30..37).contains(&p), 0.4, false);
    assert_eq!(stats.segments_started, 2, "{stats:?}");
    assert_eq!(stats.segments_joined, 1, "{stats:?}");
    assert_eq!(stats.searches_rationed, 0, "{stats:?}");
    assert!(placed >= 70, "{placed} of 80 frames placed, {stats:?}");
    assert!(
        rmse < 0.03,
        "ATE RMSE {rmse} m over the joined trajectory, {stats:?}"
    );
}

/// The covered lens of [`a_segment_after_the_lens_was_covered_is_joined_to_the_map`] with
/// real-time frames and no time at all for the expensive guesses: none starts (each is counted),
/// so the hand's frames are lost fast; the segment after it is still relocalised, by a search on
/// a thread of its own, and joined where the camera was. With time to spare (a share of 1)
/// nothing is rationed.
#[test]
fn at_sensor_pace_guesses_wait_for_their_share_and_relocalisation_runs_aside() {
    let spec = "synthetic:agents=1,frames=240,width=320,height=240:0..240:3";
    let covered = |p: usize| (30..37).contains(&p);
    let starved = TrackingConfig {
        recovery_geometry: false,
        pixel_stride: 3,
        recovery_burst_ms: 0.0,
        ..tracking_320x240()
    };
    for (tracking, rationed) in [
        (starved.clone(), true),
        (
            TrackingConfig {
                recovery_time_share: 1.0,
                ..starved
            },
            false,
        ),
    ] {
        let (rmse, stats, placed) = track_covered(spec, &tracking, covered, 0.4, true);
        assert_eq!(stats.segments_started, 2, "{stats:?}");
        assert_eq!(stats.segments_joined, 1, "{stats:?}");
        assert_eq!(stats.searches_rationed > 0, rationed, "{stats:?}");
        assert!(placed >= 70, "{placed} of 80 frames placed, {stats:?}");
        assert!(rmse < 0.03, "ATE RMSE {rmse} m, {stats:?}");
    }
}

/// Every 10th frame of redkitchen 0..300 (steps of 7 cm median, 14 cm at most): tracked
/// without loss within a few centimetres.
#[test]
fn real_data_tracks_every_tenth_redkitchen_frame() {
    let dir = datasets::shared_data::require("datasets/7scenes-redkitchen");
    let spec = format!("{}:0..300:10", dir.display());
    let (rmse, stats, placed) = track_placed(&spec, &TrackingConfig::default(), |_| false);
    assert_eq!(stats.failures, 0, "{stats:?}");
    assert_eq!(placed, 30);
    assert!(rmse < 0.05, "ATE RMSE {rmse} m, {stats:?}");
}

/// tum-fr1-rpy (fast rotation, Kinect v1; undistorted colour re-projected into the registered
/// depth's pinhole): every 3rd frame, no frame lost.
#[test]
fn real_data_tracks_tum_rpy_every_third_frame() {
    let dir = datasets::shared_data::require("datasets/tum-fr1-rpy");
    let spec = format!("{}:0..:3", dir.display());
    let (rmse, stats, _) = track_placed(&spec, &TrackingConfig::default(), |_| false);
    assert_eq!(stats.failures, 0, "{stats:?}");
    assert!(rmse < 0.045, "ATE RMSE {rmse} m, {stats:?}");
}
