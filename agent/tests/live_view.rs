//! The live view never holds an agent up: with `--viewer` at an address that accepts no
//! connection, the agent runs to the end and accounts for every frame it offered the view.

use std::net::TcpListener;
use std::path::Path;
use std::sync::atomic::AtomicBool;

use config::{Config, Pace};
use datasets::FrameRange;
use live_view::LiveViewArgs;
use mac_agent::run::{AgentOptions, run_standalone};

const FRAMES: usize = 30;

#[test]
fn an_agent_with_a_viewer_that_never_answers_finishes_and_counts_its_frames() {
    // A listening socket nobody accepts on: the connection never gets past the handshake.
    let silent = TcpListener::bind("127.0.0.1:0").unwrap();
    let address = silent.local_addr().unwrap().to_string();
    let out = tempfile::tempdir().unwrap();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic.toml");
    let mut config = Config::load(&path).unwrap();
    config.mapping.pace = Pace::Unthrottled;
    let live_view = LiveViewArgs {
        viewer: Some(address),
        record: None,
        recording_id: None,
    }
    .open("agent_0", "test")
    .unwrap();
    let options = AgentOptions {
        config,
        dataset: format!("synthetic:agents=1,agent=0,frames={FRAMES},width=160,height=120"),
        frames: FrameRange::ALL,
        agent_id: 0,
        out: out.path().to_path_buf(),
        refine_iterations: 0,
        eval_every: 10,
        comparison_renders: 0,
        lpips_weights: None,
        decode_workers: 1,
        live_view,
    };
    let metrics = run_standalone(&options, &AtomicBool::new(false)).unwrap();
    assert_eq!(metrics.frames, FRAMES);
    let stats = metrics
        .live_view
        .expect("metrics.json has the live view's figures");
    assert_eq!(
        (stats.frames_queued + stats.frames_dropped) as usize,
        FRAMES,
        "{stats:?}"
    );
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("metrics.json")).unwrap())
            .unwrap();
    assert_eq!(
        written["live_view"]["frames_queued"].as_u64(),
        Some(stats.frames_queued)
    );
    drop(silent);
}
