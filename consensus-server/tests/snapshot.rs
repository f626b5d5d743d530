//! Outputs on request: raising the snapshot flag (SIGUSR1 in `mac-consensus`) writes the
//! outputs as they stand while the run goes on; stopping still writes the final ones.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use config::Config;
use mac_consensus::process::{ConsensusOptions, run_with_snapshots};
use protocol::transport::TransportConfig;

/// Longer than this without the snapshot means it was never written.
const SNAPSHOT_TIMEOUT: Duration = Duration::from_secs(60);
const POLL: Duration = Duration::from_millis(50);

#[test]
fn a_snapshot_is_written_on_request_and_the_run_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let options = ConsensusOptions {
        config: Config::default(),
        transport: TransportConfig::with_namespace(format!("snapshot{}", std::process::id())),
        out: dir.path().to_path_buf(),
        // No agent: the run goes on until stopped.
        expected_agents: None,
        stop_agents_wait: None,
        run_id: None,
        fresh: false,
        live_view: live_view::LiveView::disabled(),
        fault_injection: false,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let snapshot = Arc::new(AtomicBool::new(false));
    let consensus = {
        let (stop, snapshot) = (stop.clone(), snapshot.clone());
        std::thread::spawn(move || run_with_snapshots(&options, &stop, &snapshot))
    };
    snapshot.store(true, Ordering::Relaxed);
    let report_path = dir.path().join("consensus.json");
    let started = Instant::now();
    while !report_path.exists() {
        assert!(
            started.elapsed() < SNAPSHOT_TIMEOUT,
            "no snapshot within {SNAPSHOT_TIMEOUT:?}"
        );
        assert!(
            !consensus.is_finished(),
            "the run ended on a snapshot request"
        );
        std::thread::sleep(POLL);
    }
    // The file is written in one go after the map; wait for it to parse.
    let written: serde_json::Value = loop {
        if let Ok(value) = serde_json::from_str(&std::fs::read_to_string(&report_path).unwrap()) {
            break value;
        }
        std::thread::sleep(POLL);
    };
    assert_eq!(written["snapshot"], true);
    assert_eq!(written["keyframes"], 0);
    assert!(dir.path().join("map.ply").exists());
    assert!(!snapshot.load(Ordering::Relaxed), "the request was taken");
    assert!(!consensus.is_finished(), "the run goes on after a snapshot");

    stop.store(true, Ordering::Relaxed);
    let report = consensus.join().unwrap().unwrap();
    assert!(!report.snapshot);
    assert!(report.interrupted);
    let last: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report_path).unwrap()).unwrap();
    assert_eq!(last["snapshot"], false);
}
