//! A keyframe that arrives incomplete (here: its image and patch lost) is asked for again with
//! `ControlMessage::ResendKeyframe`; the agent's answer completes it, and the part that arrives
//! twice is ignored. A fake agent on the real transport plays the agent.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use config::Config;
use mac_consensus::process::{ConsensusOptions, run};
use protocol::messages::{ControlMessage, CoordinateFrame, KeyframeDescriptor};
use protocol::transport::{AgentLink, KeyframeImageMeta, TransportConfig};

mod common;

use common::{HEIGHT, WIDTH, gaussian, intrinsics, pixels};

/// Much longer than the configured wait before a request.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
const KEYFRAME_ID: u64 = 5;

#[test]
fn an_incomplete_keyframe_is_asked_for_again_and_completed() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = Config::default();
    config.consensus.resend.after_s = 0.3;
    config.consensus.refinement.max_iterations = 0;
    let transport = TransportConfig::with_namespace(format!("resend{}", std::process::id()));
    let options = ConsensusOptions {
        config,
        transport: transport.clone(),
        out: dir.path().to_path_buf(),
        expected_agents: Some(1),
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

    let intrinsics = intrinsics();
    let mut agent = AgentLink::open(&transport, 0).unwrap();
    agent.announce(intrinsics, 0, 0).unwrap();
    let mut descriptor = KeyframeDescriptor::new(KEYFRAME_ID, 50, 1.5);
    descriptor.intrinsics = intrinsics;
    descriptor.descriptor[0] = 1.0;
    // Only the descriptor gets through.
    agent.send_descriptor(&descriptor).unwrap();

    let request = agent
        .recv_control_timeout(REQUEST_TIMEOUT)
        .unwrap()
        .expect("the consensus asks for the keyframe again");
    match &request.message {
        ControlMessage::ResendKeyframe {
            keyframe_id,
            reason,
        } => {
            assert_eq!(*keyframe_id, KEYFRAME_ID);
            assert!(
                reason.contains("RGB-D image") && reason.contains("patch"),
                "{reason}"
            );
        }
        other => panic!("expected a resend request, got {other:?}"),
    }

    // The answer: every part again.
    agent.send_descriptor(&descriptor).unwrap();
    let meta = KeyframeImageMeta {
        keyframe_id: KEYFRAME_ID,
        frame_index: 50,
        timestamp_s: 1.5,
        camera_to_agent_world: descriptor.camera_to_agent_world,
        intrinsics,
        width: WIDTH,
        height: HEIGHT,
    };
    agent.send_keyframe_image(&meta, &pixels()).unwrap();
    agent
        .send_patch(KEYFRAME_ID, CoordinateFrame::AgentWorld, &[gaussian()])
        .unwrap();
    agent.close().unwrap();

    let report = consensus.join().unwrap().unwrap();
    let record = &report.agents[&0];
    assert_eq!(report.keyframes, 1);
    assert_eq!(record.keyframes, 1, "the keyframe went to the engine once");
    assert!(record.resend_requests >= 1);
    assert_eq!(record.keyframes_incomplete, 0);
    assert_eq!(record.duplicate_parts, 1, "the descriptor arrived twice");
    assert_eq!(record.keyframe_id_conflicts, 0);
    assert_eq!(record.gaussians_received, 1);
}
