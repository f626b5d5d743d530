//! Tracking that survives fast motion, end to end in the agent (docs/method.md, One agent:
//! Tracking): every 15th frame of the synthetic scene (steps of ~30 cm) is tracked without a
//! frame lost, the recoveries are reported in metrics.json, and every frame's outcome is in
//! tracking.csv.

use std::path::Path;
use std::sync::atomic::AtomicBool;

use config::{Config, Pace};
use mac_agent::run::{AgentOptions, run_standalone};

#[test]
fn every_fifteenth_synthetic_frame_is_tracked_and_the_recoveries_reported() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic.toml");
    let mut config = Config::load(&path).unwrap();
    config.mapping.pace = Pace::Unthrottled;
    // 320x240: every 2nd pixel samples the surfaces as densely as every 4th at 640x480, so the
    // correspondence distance is hardly widened (registration::odometry::spacing) and 30 cm
    // steps are many times that distance: the ordinary path alone would slide off.
    config.tracking.pixel_stride = 2;
    let dir = tempfile::tempdir().unwrap();
    let options = AgentOptions {
        config,
        dataset: "synthetic:agents=1,agent=0,frames=300,width=320,height=240".into(),
        frames: "0..300:15".parse().unwrap(),
        agent_id: 0,
        out: dir.path().to_path_buf(),
        refine_iterations: 0,
        eval_every: 5,
        comparison_renders: 0,
        lpips_weights: None,
        decode_workers: 1,
        live_view: live_view::LiveView::disabled(),
    };
    let metrics = run_standalone(&options, &AtomicBool::new(false)).unwrap();
    let tracking = &metrics.tracking;
    assert_eq!(metrics.frames, 20);
    assert_eq!(tracking.frames_lost, 0, "{tracking:?}");
    assert!(tracking.recoveries > 0, "{tracking:?}");
    assert_eq!(tracking.segments_started, 0, "{tracking:?}");
    assert!(tracking.confidence_min.unwrap() > 0.8, "{tracking:?}");
    let ate = metrics.ate_rmse_m.unwrap();
    assert!(ate < 0.01, "ATE {ate} m");
    let csv = std::fs::read_to_string(dir.path().join("tracking.csv")).unwrap();
    assert_eq!(csv.lines().count(), 21, "{csv}");
    assert!(
        csv.lines().skip(1).all(|l| l.contains(",root,true,")),
        "{csv}"
    );
    let json = std::fs::read_to_string(dir.path().join("metrics.json")).unwrap();
    let value: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(value["tracking"]["frames_lost"], 0);
}
