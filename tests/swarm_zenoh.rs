//! The synthetic swarm over zenoh (`mac-ego3d swarm --transport zenoh`: the consensus
//! and each agent on a simulated host of its own, joined only by their bridges over TCP on
//! 127.0.0.1) gives the same result as over one host's iceoryx2 shared memory, and metrics.json
//! says which transport ran and what each agent put on the network; and the IPC benchmark's
//! TLS link between two simulated hosts holds under sustained two-way load. Needs root (mount
//! namespaces); skipped with a message otherwise.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::is_root;

/// As the issue asked: the synthetic 3-agent swarm.
const AGENTS: usize = 3;
/// The bridge-kill run: agent 0's host is the one that matters; one more agent to merge with.
const KILL_RUN_AGENTS: usize = 2;
const FRAMES: usize = 150;
/// Joint ATE over zenoh within this fraction of the iceoryx2 run's, plus `ATE_FLOOR_M`: at
/// sub-millimetre to millimetre ATE the consensus's own run-to-run spread (its alignments and
/// time-bounded refinement depend on thread timing) is larger than 10 %: two runs over
/// iceoryx2 measured 0.09 and 1.8 mm, two over zenoh 1.0 and 2.5 mm.
const ATE_TOLERANCE: f64 = 0.10;
const ATE_FLOOR_M: f64 = 0.005;
/// The joint refinement at the end is bounded by time; a short bound keeps the test short and
/// is the same in both runs.
const REFINEMENT_SECONDS: f64 = 5.0;

fn binaries() -> &'static Path {
    Path::new(env!("CARGO_BIN_EXE_mac-ego3d")).parent().unwrap()
}

/// configs/synthetic.toml with a short joint refinement.
fn short_config(dir: &Path) -> PathBuf {
    let repository = Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(repository.join("configs/synthetic.toml")).unwrap();
    let mut config: toml::Table = toml::from_str(&text).unwrap();
    config["consensus"]["refinement"]
        .as_table_mut()
        .unwrap()
        .insert("max_seconds".into(), toml::Value::Float(REFINEMENT_SECONDS));
    let path = dir.join("synthetic-short.toml");
    std::fs::write(&path, toml::to_string(&config).unwrap()).unwrap();
    path
}

/// Starts `mac-ego3d swarm --transport TRANSPORT` on the synthetic scene with `extra`
/// arguments; the runtime folder must outlive the run.
fn spawn_swarm(
    agents: usize,
    transport: &str,
    config: &Path,
    out: &Path,
    extra: &[&str],
) -> (std::process::Child, tempfile::TempDir) {
    let runtime = tempfile::tempdir().unwrap();
    let child = Command::new(binaries().join("mac-ego3d"))
        .arg("swarm")
        .args([
            "--agents",
            &agents.to_string(),
            "--frames",
            &FRAMES.to_string(),
        ])
        .args(["--transport", transport])
        .arg("--config")
        .arg(config)
        .arg("--out")
        .arg(out)
        .args(extra)
        .env("XDG_RUNTIME_DIR", runtime.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    (child, runtime)
}

/// Waits for a swarm started by [`spawn_swarm`]; its metrics.json.
fn finish_swarm(child: std::process::Child, transport: &str, out: &Path) -> serde_json::Value {
    let output = child.wait_with_output().unwrap();
    assert!(
        output.status.success(),
        "mac-ego3d swarm --transport {transport} failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap()
}

fn run_swarm(transport: &str, config: &Path, out: &Path) -> serde_json::Value {
    let (child, _runtime) = spawn_swarm(AGENTS, transport, config, out, &[]);
    finish_swarm(child, transport, out)
}

/// Two whole swarms take 3-11 minutes on 2 cores, over the suite's budget: run it with
/// `cargo test --test swarm_zenoh -- --ignored`. CI's short form is bridge/tests/simulated_hosts.rs
/// (the bridges between two simulated hosts, a 1,000,000-record patch).
#[test]
#[ignore = "two swarm runs, 3-11 min on 2 cores: cargo test --test swarm_zenoh -- --ignored"]
fn synthetic_swarm_over_zenoh_matches_iceoryx2() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let config = short_config(dir.path());
    let local = run_swarm("iceoryx2", &config, &dir.path().join("iceoryx2"));
    let networked = run_swarm("zenoh", &config, &dir.path().join("zenoh"));
    assert_eq!(local["transport"], "iceoryx2");
    assert_eq!(networked["transport"], "zenoh");
    assert!(local.get("network_bytes_per_agent").is_none());

    let ate = |metrics: &serde_json::Value| metrics["ate_joint_rmse_m"].as_f64().unwrap();
    let (local_ate, networked_ate) = (ate(&local), ate(&networked));
    eprintln!("joint ATE over iceoryx2 {local_ate} m, over zenoh {networked_ate} m");
    assert!(
        (networked_ate - local_ate).abs() <= ATE_TOLERANCE * local_ate + ATE_FLOOR_M,
        "joint ATE over zenoh {networked_ate} m, over iceoryx2 {local_ate} m"
    );
    // Not compared: which agents the consensus linked, which like the ATE depends on its
    // thread timing at this short length (at 100 frames one iceoryx2 run linked agent 1, one
    // zenoh run did not, with the same keyframes received).

    // The consensus got every agent's keyframes, complete and without sequence gaps, exactly
    // as many as on one host; every goodbye crossed.
    let consensus = |out: &str| -> serde_json::Value {
        let path = dir.path().join(out).join("consensus.json");
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    };
    let (local_consensus, networked_consensus) = (consensus("iceoryx2"), consensus("zenoh"));
    for k in 0..AGENTS {
        let agent = &networked_consensus["agents"][k.to_string()];
        let local_agent = &local_consensus["agents"][k.to_string()];
        assert_eq!(agent["keyframes"], local_agent["keyframes"], "agent {k}");
        assert!(agent["keyframes"].as_u64().unwrap() > 0, "agent {k}");
        for field in ["gaps", "keyframes_incomplete", "resend_requests"] {
            assert_eq!(agent[field], 0, "agent {k}: {field}");
        }
        assert_eq!(agent["goodbyes"], 1, "agent {k}");
    }

    // Every agent's keyframes crossed the network: its bridge counted them.
    for k in 0..AGENTS {
        let sent = networked["network_bytes_per_agent"][k.to_string()]["bytes_to_network"]
            .as_u64()
            .unwrap_or(0);
        assert!(
            sent > 1_000_000,
            "agent {k} put {sent} bytes on the network"
        );
    }
}

/// Short form of `mac-ego3d bench ipc --transport zenoh --link tls`: 10k and 100k patches one
/// way, acknowledgements the other, between two simulated hosts whose bridges are linked by
/// mutual TLS. The link must never reset: each reset is logged by the agent host's bridge as
/// `link to the consumer host re-established` (`consumer host unreachable` alone is also logged
/// when the peer's host ends before the driver's bridge stops). Before the bridge
/// kept a link's receive and send tasks on one thread (bridge/src/network.rs,
/// `ZENOH_RUNTIME_SETTING`), this load reset zenoh's TLS link 7-13 times in this short form.
#[test]
fn bench_ipc_over_tls_keeps_its_link_under_two_way_load() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let runtime = tempfile::tempdir().unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args(["bench", "ipc", "--transport", "zenoh", "--link", "tls"])
        .args(["--samples", "300", "--throughput-messages", "300", "--json"])
        .env("XDG_RUNTIME_DIR", runtime.path())
        .env_remove("ZENOH_RUNTIME")
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "bench ipc failed:\n{log}");
    let resets = log
        .lines()
        .filter(|line| line.contains("link to the consumer host re-established"))
        .count();
    assert_eq!(resets, 0, "the TLS link reset under load:\n{log}");
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(report["transport"], "zenoh over TLS");
    assert!(report["patch_100k_msgs_per_s"].as_f64().unwrap() > 0.0);
}

/// Agent 0's host's bridge is SIGKILLed twice (scripts/simulated_host.sh restarts it): mid-run,
/// and while it drains a bandwidth budget's backlog after the agent's last frame, holding
/// images, patches, the final map and the goodbye. The consensus still gets every keyframe the
/// agent published, complete, and its goodbye: lost keyframes are published again after the
/// consensus's loss report (`MessagesLost`), the lost goodbye is said again with what the
/// consensus had not confirmed. One swarm run, 3-5 min on 2 cores: on demand.
#[test]
#[ignore = "one swarm run, 3-5 min on 2 cores: cargo test --test swarm_zenoh -- --ignored"]
fn agent_host_bridge_killed_mid_run_and_while_draining_loses_no_keyframe() {
    if !is_root() {
        eprintln!("skipped: simulated hosts need root (unshare --mount)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let config = short_config(dir.path());
    let out = dir.path().join("killed");
    let (child, _runtime) = spawn_swarm(
        KILL_RUN_AGENTS,
        "zenoh",
        &config,
        &out,
        &["--bandwidth", "100"],
    );
    let progress = out.join("agent_0/progress.json");
    let reached = |test: &dyn Fn(&serde_json::Value) -> bool| {
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(600) {
            let text = std::fs::read_to_string(&progress).unwrap_or_default();
            if serde_json::from_str(&text).is_ok_and(|p: serde_json::Value| test(&p)) {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!("agent 0 never reached the kill point");
    };
    let kill_agent_host_bridge = || {
        // The bridge itself, not the simulated_host.sh that restarts it (whose command line
        // names it too).
        let pattern = "^[^ ]*mac-bridge .*--local-agent 0 ";
        let killed = Command::new("pkill")
            .args(["-KILL", "-f", pattern])
            .status()
            .unwrap();
        assert!(killed.success(), "no bridge of agent 0's host to kill");
    };
    reached(&|p| p["frames_done"].as_u64().unwrap_or(0) >= FRAMES as u64 * 2 / 5);
    kill_agent_host_bridge();
    reached(&|p| p["stage"] == "finishing");
    kill_agent_host_bridge();
    finish_swarm(child, "zenoh", &out);

    let agent: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("agent_0/metrics.json")).unwrap())
            .unwrap();
    let published = agent["swarm"]["keyframes_published_ids"]
        .as_array()
        .unwrap()
        .len();
    let consensus: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("consensus.json")).unwrap())
            .unwrap();
    let received = &consensus["agents"]["0"];
    assert!(published > 0);
    assert_eq!(received["keyframes"], published, "{received}");
    assert_eq!(received["keyframes_incomplete"], 0, "{received}");
    assert_eq!(received["goodbyes"], 1, "{received}");
    assert!(
        agent["swarm"]["keyframes_unrecoverable"]
            .as_array()
            .unwrap()
            .is_empty()
    );
}
