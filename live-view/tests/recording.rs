//! The live view end to end inside one process: what it logs reads back from the .rrd file with
//! rerun's decoder, and a sink that takes nothing never blocks the caller (items are dropped and
//! counted instead).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use geometry::camera::Intrinsics;
use image::RgbImage;
use live_view::{ClosureLine, ClosureOutcome, LiveView, LiveViewSettings, RrdSummary, paths};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

const FRAMES: usize = 23;

fn pose(i: usize) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(i as f64 * 0.01, 0.0, 0.0),
        UnitQuaternion::from_euler_angles(0.0, i as f64 * 0.01, 0.0),
    )
}

fn intrinsics() -> Intrinsics {
    Intrinsics::new(100.0, 100.0, 80.0, 60.0, 160, 120)
}

#[test]
fn a_recording_reads_back_with_every_documented_entity() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("agent_3.rrd");
    let settings = LiveViewSettings {
        // Room for everything: this test counts what was logged.
        queue_capacity: 1000,
        ..LiveViewSettings::default()
    };
    let view = LiveView::open("run-42", None, Some(&file), settings.clone()).unwrap();
    let rgb = RgbImage::from_fn(160, 120, |x, y| image::Rgb([x as u8, y as u8, 7]));
    for i in 0..FRAMES {
        view.frame(3, i, &pose(i), &intrinsics(), &rgb);
    }
    view.keyframe(3, &pose(0));
    view.keyframe(3, &pose(10));
    let means: Vec<[f32; 3]> = (0..50_000).map(|i| [i as f32 * 1e-4, 0.0, 1.0]).collect();
    let colours = vec![[0.2, 0.4, 0.6]; means.len()];
    view.map_points(3, &means, &colours, false);
    view.agent_placement(3, &pose(5));
    view.closures(vec![
        ClosureLine {
            from: [0.0; 3],
            to: [1.0, 0.0, 0.0],
            outcome: ClosureOutcome::Accepted,
        },
        ClosureLine {
            from: [0.0; 3],
            to: [0.0, 1.0, 0.0],
            outcome: ClosureOutcome::Rejected,
        },
    ]);
    view.consensus_trajectories(BTreeMap::from([(3, vec![[0.0; 3], [0.1, 0.0, 0.0]])]));
    view.merged_map(&means, &colours);
    view.scalar(paths::CONSENSUS_CLOSURES_ACCEPTED, 1.0);
    view.scalar(paths::CONSENSUS_CLOSURES_ACCEPTED, 4.0);
    let stats = view.finish().unwrap();
    assert!(stats.finished, "{stats:?}");
    assert_eq!(stats.items_dropped, 0);
    assert_eq!(stats.frames_queued, FRAMES as u64);

    let summary = RrdSummary::read(&file).unwrap();
    let shown = format!("{summary:#?}");
    assert_eq!(
        summary.recording_ids.iter().collect::<Vec<_>>(),
        ["run-42"],
        "{shown}"
    );
    let camera = paths::agent_camera(3);
    assert_eq!(
        summary.rows(&camera, "Transform3D:translation"),
        FRAMES,
        "one camera pose per frame: {shown}"
    );
    // One frame in `image_every` carries its image and pinhole.
    let with_image = FRAMES.div_ceil(settings.image_every);
    assert_eq!(
        summary.rows(&camera, "EncodedImage:blob"),
        with_image,
        "{shown}"
    );
    assert_eq!(
        summary.rows(&camera, "Pinhole:image_from_camera"),
        with_image,
        "{shown}"
    );
    assert!(
        summary.rows(&paths::agent_trajectory(3), "LineStrips3D:strips") >= 1,
        "{shown}"
    );
    assert_eq!(
        summary.rows(&paths::agent_keyframes(3), "Points3D:positions"),
        2,
        "{shown}"
    );
    assert!(
        summary.rows(&paths::agent_map(3), "Points3D:positions") >= 1,
        "{shown}"
    );
    assert_eq!(
        summary.rows(&paths::agent(3), "Transform3D:translation"),
        1,
        "{shown}"
    );
    assert_eq!(
        summary.rows(paths::CONSENSUS_CLOSURES, "LineStrips3D:strips"),
        1,
        "{shown}"
    );
    assert_eq!(
        summary.rows(&paths::consensus_trajectory(3), "LineStrips3D:strips"),
        1,
        "{shown}"
    );
    assert_eq!(
        summary.rows(paths::CONSENSUS_MAP, "Points3D:positions"),
        1,
        "{shown}"
    );
    assert_eq!(
        summary.scalar_max(paths::CONSENSUS_CLOSURES_ACCEPTED),
        Some(4.0),
        "{shown}"
    );
    // The world frame's axes (camera convention: y down), said once.
    assert_eq!(
        summary.rows(paths::WORLD, "ViewCoordinates:xyz"),
        1,
        "{shown}"
    );
    // The map shown is bounded.
    assert!(
        summary.max_instances(&paths::agent_map(3), "Points3D:positions")
            <= settings.map_points_max,
        "{shown}"
    );
}

/// A sink that takes nothing until the test ends (a viewer that never reads).
struct BlockedSink {
    release: crossbeam_channel::Receiver<()>,
}

impl rerun::sink::LogSink for BlockedSink {
    fn send(&self, message: rerun::log::LogMsg) {
        if matches!(message, rerun::log::LogMsg::ArrowMsg(..)) {
            let _ = self.release.recv();
        }
    }

    fn flush_blocking(&self, timeout: Duration) -> Result<(), rerun::sink::SinkFlushError> {
        let _ = self.release.recv_timeout(timeout);
        Ok(())
    }
}

#[test]
fn a_sink_that_takes_nothing_never_blocks_the_caller_and_drops_are_counted() {
    let (release_tx, release_rx) = crossbeam_channel::bounded::<()>(0);
    let stream = rerun::RecordingStreamBuilder::new(live_view::APPLICATION_ID)
        // rerun's own backpressure: a small budget in flight, so the blocked sink soon blocks the
        // live view's background thread as a stalled network connection would.
        .batcher_config(rerun::log::ChunkBatcherConfig {
            max_bytes_in_flight: 256 * 1024,
            ..rerun::log::ChunkBatcherConfig::LOW_LATENCY
        })
        .set_sinks(vec![Box::new(BlockedSink {
            release: release_rx,
        }) as Box<dyn rerun::sink::LogSink>])
        .unwrap();
    let settings = LiveViewSettings {
        queue_capacity: 4,
        image_every: 1,
        finish_timeout: Duration::from_millis(500),
        ..LiveViewSettings::default()
    };
    let view = LiveView::with_stream(stream, settings).unwrap();
    // Noise does not compress: every frame carries tens of kB of JPEG.
    let rgb = RgbImage::from_fn(160, 120, |x, y| {
        let v = (x.wrapping_mul(7919) ^ y.wrapping_mul(104_729)) as u8;
        image::Rgb([v, v.wrapping_mul(3), v.wrapping_mul(5)])
    });
    let offered = 2000;
    let started = Instant::now();
    for i in 0..offered {
        view.frame(0, i, &pose(i), &intrinsics(), &rgb);
    }
    let offering = started.elapsed();
    let stats = view.finish().unwrap();
    assert_eq!(
        stats.frames_queued + stats.frames_dropped,
        offered as u64,
        "{stats:?}"
    );
    assert!(stats.frames_dropped > 0, "nothing dropped: {stats:?}");
    assert!(!stats.finished, "{stats:?}");
    eprintln!("{offered} frames offered in {offering:?}: {stats:?}");
    drop(release_tx);
}
