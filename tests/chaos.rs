//! The chaos soak in its short form: 2 agents on a small synthetic scene, each agent and the
//! consensus SIGKILLed twice at seeded random times and started again, and the consensus killed
//! twice more while storing a keyframe (before its commit, and after it before the consensus
//! acted on it); `mac-ego3d chaos` checks
//! that every keyframe the agents delivered is in the final consensus state and that the outputs
//! are complete, and compares with the same swarm without kills. The long form is documented in
//! docs/architecture.md ("The chaos soak").
//!
//! Named real_data_* because the agents' global descriptor needs the AlexNet weights of the
//! shared data folder (as in swarm.rs).

mod common;

use std::process::Command;

use config::Config;

const FRAMES: usize = 100;
/// Kills fall in the first seconds, while every agent still runs (a killed agent starts its
/// frames over).
const WINDOW_S: &str = "25";
const SEED: &str = "1";
/// The bound the uninterrupted swarm is held to (swarm.rs).
const MAX_JOINT_ATE_M: f64 = 0.02;

fn config() -> Config {
    let mut config = common::repository_config("configs/synthetic.toml");
    // A small scene publishing often, with a short final refinement (as swarm.rs).
    config.consensus.t_comm = 20;
    config.tracking.pixel_stride = 2;
    config.keyframes.footprint_sigma_per_spacing = 1.0;
    config.consensus.refinement.max_iterations = 30;
    config.consensus.refinement.max_seconds = 20.0;
    config.consensus.descriptor_weights =
        Some(datasets::shared_data::require("weights/lpips/alexnet.npz"));
    config
}

#[test]
fn real_data_chaos_soak_short_form_loses_no_keyframe() {
    let dir = tempfile::tempdir().unwrap();
    let config_path = dir.path().join("chaos.toml");
    std::fs::write(&config_path, toml::to_string(&config()).unwrap()).unwrap();
    let out = dir.path().join("out");
    let mut command = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"));
    command
        .arg("chaos")
        .arg("--config")
        .arg(&config_path)
        .args(["--agents", "2", "--frames", &FRAMES.to_string()])
        .args(["--width", "320", "--height", "240"])
        .args(["--seed", SEED, "--kills-each", "2", "--window", WINDOW_S])
        .args(["--store-crashes", "2"])
        .args(["--render-every", "0", "--json"])
        .arg("--binaries")
        .arg(common::workspace_binary("mac-agent").parent().unwrap())
        .arg("--out")
        .arg(&out)
        .env(alexnet::weights::WEIGHTS_ENV, "");
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        command.env("XDG_RUNTIME_DIR", dir.path());
    }
    let output = command.output().unwrap();
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap_or_else(|e| {
        panic!(
            "chaos printed no JSON ({e}); stderr:\n{}\n{}",
            String::from_utf8_lossy(&output.stderr),
            common::log_tails(&out, 40)
        )
    });
    eprintln!("{}", serde_json::to_string_pretty(&report).unwrap());
    assert!(
        output.status.success(),
        "the soak failed: {}\n{}",
        report["failures"],
        common::log_tails(&out, 40)
    );
    for (process, kills) in report["kills_per_process"]
        .as_array()
        .unwrap()
        .iter()
        .map(|pair| (pair[0].as_str().unwrap(), pair[1].as_u64().unwrap()))
    {
        assert!(kills >= 2, "{process} killed {kills} times");
    }
    assert_eq!(
        report["store_crashes"], 2,
        "deaths while storing a keyframe"
    );
    let chaos = &report["chaos"];
    assert!(chaos["keyframes_delivered"].as_u64().unwrap() > 0);
    assert_eq!(
        chaos["keyframes_delivered"], chaos["keyframes_in_final_state"],
        "keyframes lost"
    );
    let ate = chaos["ate_joint_rmse_m"].as_f64().expect("joint ATE");
    assert!(ate <= MAX_JOINT_ATE_M, "joint ATE {ate} m with kills");
    assert!(out.join("chaos.json").exists());
}
