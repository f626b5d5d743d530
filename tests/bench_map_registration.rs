//! `mac-ego3d bench map-registration` end to end on the embedded synthetic scene: one seed, small
//! images, the JSON report (tests/cli.rs covers the other commands).

use std::process::Command;

#[test]
fn bench_map_registration_registers_the_synthetic_agents() {
    let out = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args([
            "bench",
            "map-registration",
            "--seeds",
            "1",
            "--synthetic-frames",
            "200",
            "--synthetic-width",
            "160",
            "--synthetic-height",
            "120",
            "--pixel-stride",
            "1",
            "--json",
        ])
        .output()
        .expect("mac-ego3d runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let pair = &report["pairs"][0];
    assert!(pair["source_points"].as_u64().unwrap() > 10_000, "{pair}");
    assert_eq!(pair["disjoint"], false, "{pair}");
    let ours = &pair["methods"][0];
    assert_eq!(ours["method"], "ours", "{pair}");
    assert!(ours["time_ms"].as_f64().unwrap() > 0.0);
    assert_eq!(ours["accepted"], true, "{ours}");
    assert_eq!(ours["success"], true, "{ours}");
    assert!(ours["rotation_error_deg"].as_f64().unwrap() < 2.0, "{ours}");
    assert!(
        ours["translation_error_m"].as_f64().unwrap() < 0.05,
        "{ours}"
    );
    let summary = &report["summary"][0];
    assert_eq!(summary["method"], "ours");
    assert_eq!(summary["successes"], 1, "{summary}");
}
