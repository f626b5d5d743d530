//! End to end: the consensus plus two agent processes on the synthetic scene, over iceoryx2.
//! The agents are real `mac-agent` processes; the consensus runs the process's own `run` on a
//! thread of the test (its binary belongs to another package, which Cargo does not build for
//! this crate's tests).
//!
//! Named real_data_* because the agents' global descriptor needs the AlexNet weights of the shared
//! data folder.
//!
//! No ground truth reaches any process: each agent starts at identity in its own frame, and the
//! consensus finds agent 1's frame from image matches. Ground truth only scores the result.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mac_consensus::process::{ConsensusOptions, ConsensusReport, run};
use protocol::transport::TransportConfig;
use slam_core::config::Config;
use slam_core::metrics::ate::{Alignment, DEFAULT_MAX_DT, joint_ate};
use slam_core::trajectory::Trajectory;

/// Frames per agent: the two synthetic loops overlap within this many frames.
const FRAMES: usize = 150;
/// Publish a keyframe every this many frames (more chances to meet than the default 60).
const T_COMM: usize = 30;
/// The bound on the joint ATE (metres).
const MAX_JOINT_ATE_M: f64 = 0.02;
/// A run that takes longer than this has hung.
const RUN_TIMEOUT: Duration = Duration::from_secs(600);

fn config() -> Config {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/synthetic.toml");
    let mut config = Config::load(&path).unwrap();
    config.consensus.t_comm = T_COMM;
    // The pretrained descriptor (shared data): the classical thumbnail rarely proposes the
    // overlapping pair of this scene.
    config.consensus.descriptor_weights =
        Some(slam_core::shared_data::require("weights/lpips/alexnet.npz"));
    config
}

fn write_config(dir: &Path, config: &Config) -> PathBuf {
    let path = dir.join("config.toml");
    std::fs::write(&path, toml::to_string(config).unwrap()).unwrap();
    path
}

fn spawn_consensus(
    dir: &Path,
    namespace: &str,
    stop: Arc<AtomicBool>,
) -> JoinHandle<anyhow::Result<ConsensusReport>> {
    let options = ConsensusOptions {
        config: config(),
        transport: TransportConfig::with_namespace(namespace),
        out: dir.to_path_buf(),
        expected_agents: Some(2),
    };
    std::thread::spawn(move || run(&options, &stop))
}

fn spawn_agent(dir: &Path, config_path: &Path, namespace: &str, agent_id: u32) -> Child {
    Command::new(env!("CARGO_BIN_EXE_mac-agent"))
        .args(["--config", config_path.to_str().unwrap()])
        .args([
            "--dataset",
            &format!("synthetic:agents=2,agent={agent_id},frames={FRAMES},width=320,height=240"),
        ])
        .args(["--agent-id", &agent_id.to_string()])
        .args(["--namespace", namespace])
        .args(["--eval-every", "50", "--renders", "0"])
        .arg("--out")
        .arg(dir.join(format!("agent_{agent_id}")))
        .spawn()
        .expect("starting mac-agent")
}

fn wait(mut child: Child, what: &str) {
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            assert!(status.success(), "{what} exited with {status}");
            return;
        }
        if started.elapsed() > RUN_TIMEOUT {
            let _ = child.kill();
            panic!("{what} did not finish within {RUN_TIMEOUT:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Joint ATE of both agents' world trajectories (written by the consensus).
fn joint_ate_m(dir: &Path) -> f64 {
    let pairs: Vec<(Trajectory, Trajectory)> = (0..2)
        .map(|k| {
            let world = dir.join(format!("agent_{k}.tum"));
            assert!(
                world.exists(),
                "agent {k} was not placed in the world frame"
            );
            (
                Trajectory::read_tum(&dir.join(format!("agent_{k}/groundtruth.tum"))).unwrap(),
                Trajectory::read_tum(&world).unwrap(),
            )
        })
        .collect();
    assert!(pairs.iter().all(|(_, est)| est.len() == FRAMES));
    joint_ate(&pairs, Alignment::Se3, DEFAULT_MAX_DT)
        .unwrap()
        .joint
        .rmse
}

fn check(dir: &Path, report: &ConsensusReport) {
    let ate = joint_ate_m(dir);
    eprintln!(
        "joint ATE {:.2} cm; {} closures verified, {} accepted ({} inter-agent); latency median \
         {:?} ms",
        ate * 100.0,
        report.closures_verified,
        report.loop_closures_accepted,
        report.inter_agent_closures_accepted,
        report.consensus_latency_ms_median
    );
    assert!(report.inter_agent_closures_accepted >= 1);
    assert!(ate <= MAX_JOINT_ATE_M, "joint ATE {ate} m");
    assert!(report.merged_gaussians > 0);
    assert!(dir.join("map.ply").exists() && dir.join("consensus.json").exists());
}

#[test]
fn real_data_swarm_two_agents_and_the_consensus_agree_on_one_world() {
    let dir = tempfile::tempdir().unwrap();
    let namespace = format!("swarmtest{}a", std::process::id());
    let config_path = write_config(dir.path(), &config());
    let consensus = spawn_consensus(dir.path(), &namespace, Arc::new(AtomicBool::new(false)));
    let agents: Vec<Child> = (0..2)
        .map(|k| spawn_agent(dir.path(), &config_path, &namespace, k))
        .collect();
    for (k, agent) in agents.into_iter().enumerate() {
        wait(agent, &format!("agent {k}"));
    }
    let report = consensus.join().unwrap().unwrap();
    check(dir.path(), &report);
}

#[test]
fn real_data_swarm_agent_killed_mid_run_and_restarted_still_gives_a_complete_result() {
    let dir = tempfile::tempdir().unwrap();
    let namespace = format!("swarmtest{}b", std::process::id());
    let config_path = write_config(dir.path(), &config());
    let consensus = spawn_consensus(dir.path(), &namespace, Arc::new(AtomicBool::new(false)));
    let survivor = spawn_agent(dir.path(), &config_path, &namespace, 0);
    let mut victim = spawn_agent(dir.path(), &config_path, &namespace, 1);
    // Let it publish something first, then SIGKILL: no goodbye, shared memory left behind.
    std::thread::sleep(Duration::from_secs(6));
    assert!(
        victim.try_wait().unwrap().is_none(),
        "agent 1 finished before it could be killed mid-run"
    );
    victim.kill().unwrap();
    victim.wait().unwrap();
    let restarted = spawn_agent(dir.path(), &config_path, &namespace, 1);
    wait(survivor, "agent 0");
    wait(restarted, "restarted agent 1");
    let report = consensus.join().unwrap().unwrap();
    assert_eq!(
        report.agents[&1].hellos, 2,
        "the restarted agent re-announced itself"
    );
    check(dir.path(), &report);
}
