//! An agent restarted on other frames numbers its keyframes from 0 again, in a tracked frame of
//! its own: the consensus ignores that run whole (its hello's run anchor differs from the first
//! run's), including keyframe ids the first run never used and its final map, which would
//! otherwise land in the first run's frame. A fake agent on the real transport plays both runs;
//! each ends with an orderly goodbye, which waits until the consensus has drained it.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use config::Config;
use mac_consensus::process::{ConsensusOptions, run};
use protocol::messages::{CoordinateFrame, FINAL_MAP_KEYFRAME_ID, KeyframeDescriptor};
use protocol::transport::{AgentLink, KeyframeImageMeta, TransportConfig};

mod common;

use common::{HEIGHT, WIDTH, gaussian, intrinsics, pixels};

const AGENT_ID: u32 = 0;
/// Run anchors (`Lifecycle::run_anchor`) of the first run's frames and of other frames.
const FIRST_FRAMES: u64 = 77;
const OTHER_FRAMES: u64 = 88;

/// Publishes keyframe `keyframe_id` showing dataset frame `frame_index`: descriptor, RGB-D
/// image and a one-Gaussian patch.
fn publish(agent: &mut AgentLink, keyframe_id: u64, frame_index: u64) {
    let timestamp_s = frame_index as f64 / 30.0;
    let mut descriptor = KeyframeDescriptor::new(keyframe_id, frame_index, timestamp_s);
    descriptor.intrinsics = intrinsics();
    descriptor.descriptor[0] = 1.0;
    agent.send_descriptor(&descriptor).unwrap();
    let meta = KeyframeImageMeta {
        keyframe_id,
        frame_index,
        timestamp_s,
        camera_to_agent_world: descriptor.camera_to_agent_world,
        intrinsics: intrinsics(),
        width: WIDTH,
        height: HEIGHT,
    };
    agent.send_keyframe_image(&meta, &pixels()).unwrap();
    agent
        .send_patch(keyframe_id, CoordinateFrame::AgentWorld, &[gaussian()])
        .unwrap();
}

#[test]
fn a_restart_on_other_frames_is_ignored_whole() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::default();
    config.consensus.refinement.max_iterations = 0;
    let transport = TransportConfig::with_namespace(format!("restart{}", std::process::id()));
    let options = ConsensusOptions {
        config,
        transport: transport.clone(),
        out: dir.path().to_path_buf(),
        // Runs until stopped: a goodbye must not end it before the restart.
        expected_agents: None,
        stop_agents_wait: None,
        run_id: None,
        fresh: false,
        live_view: live_view::LiveView::disabled(),
        fault_injection: false,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let consensus = {
        let stop = stop.clone();
        std::thread::spawn(move || run(&options, &stop))
    };

    // First run: frames 0 and 10 become keyframes 0 and 1.
    let mut first = AgentLink::open(&transport, AGENT_ID).unwrap();
    first.announce(intrinsics(), 0, FIRST_FRAMES).unwrap();
    publish(&mut first, 0, 0);
    publish(&mut first, 1, 10);
    first.close().unwrap();

    // Restart on frames 300..: keyframe 0 is frame 300, then a keyframe id the first run never
    // used (2), then its final map.
    let mut restart = AgentLink::open(&transport, AGENT_ID).unwrap();
    restart.announce(intrinsics(), 0, OTHER_FRAMES).unwrap();
    publish(&mut restart, 0, 300);
    publish(&mut restart, 2, 320);
    restart
        .send_patch(
            FINAL_MAP_KEYFRAME_ID,
            CoordinateFrame::AgentWorld,
            &[gaussian(), gaussian()],
        )
        .unwrap();
    restart.close().unwrap();
    stop.store(true, Ordering::Relaxed);

    let report = consensus.join().unwrap().unwrap();
    let record = &report.agents[&AGENT_ID];
    assert_eq!(record.hellos, 2);
    assert_eq!(report.keyframes, 2, "only the first run's keyframes");
    assert_eq!(record.keyframes, 2);
    assert_eq!(record.gaussians_received, 2, "only the first run's patches");
    assert_eq!(record.restarts_on_other_frames, 1);
    assert!(record.last_run_on_other_frames);
    assert_eq!(record.keyframe_id_conflicts, 0);
    // Keyframes 0 and 2 (descriptor, image, patch each) and the final map.
    assert_eq!(record.restart_parts_ignored, 7);
    assert_eq!(record.keyframes_incomplete, 0);
}
