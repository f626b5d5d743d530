//! The swarm end to end, as a user runs it: one `mac-consensus` and two `mac-agent` processes
//! (the workspace's own binaries, each its own OS process) on a small synthetic scene, then
//! `mac-ego3d eval swarm` for the figures (the swarm's end-to-end tests).
//!
//! Named real_data_* because the agents' global descriptor needs the AlexNet weights of the shared
//! data folder. No ground truth reaches any process: each agent starts at identity in its own
//! frame and the consensus finds agent 1's frame from image matches; ground truth only scores.
//!
//! The agent and consensus binaries belong to other packages of the workspace; `cargo test
//! --workspace` (the README's test command) builds them next to `mac-ego3d`.

mod common;

use std::time::Duration;

use common::{AgentSpec, SwarmRun};
use config::Config;

/// Frames per agent: the two synthetic loops overlap within this many frames.
const FRAMES: usize = 150;
/// A small scene, so that CI's two cores run the swarm in about two minutes.
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;
/// Publish a keyframe every this many frames (more chances to meet than the default 60).
const T_COMM: usize = 30;
/// Back-project every 2nd pixel: at 320x240, mapped at 160x120, that seeds about one Gaussian per
/// mapping pixel. The configured stride 5 (sized for tracking at 640x480) leaves this small
/// scene's textures blurred (about 5 dB lower merged-map PSNR).
const PIXEL_STRIDE: usize = 2;
/// New Gaussians as wide as the sample spacing (the default 2 spacings fills the gaps of sparse
/// 640x480 sampling; at one sample per mapping pixel it only blurs).
const FOOTPRINT_SIGMA_PER_SPACING: f64 = 1.0;
/// Joint refinement kept short for CI (the default runs 300 iterations or 2 minutes).
const REFINEMENT_ITERATIONS: usize = 60;
const REFINEMENT_MAX_SECONDS: f64 = 90.0;
/// What a merged synthetic swarm must reach: the scene is exact, so errors are the method's.
const MAX_JOINT_ATE_M: f64 = 0.02;
const MIN_MERGED_PSNR_DB: f64 = 25.0;
/// Render the merged map at every n-th frame of each agent for the PSNR.
const RENDER_EVERY: usize = 10;
/// Agent 1 is killed this long after it started (it has published keyframes by then).
const KILL_AFTER: Duration = Duration::from_secs(8);
/// The consensus is killed this long after the swarm started, and started again this long after.
const CONSENSUS_KILL_AFTER: Duration = Duration::from_secs(10);
const CONSENSUS_DOWN_FOR: Duration = Duration::from_secs(2);

fn config() -> Config {
    let mut config = common::repository_config("configs/synthetic.toml");
    config.consensus.t_comm = T_COMM;
    config.tracking.pixel_stride = PIXEL_STRIDE;
    config.keyframes.footprint_sigma_per_spacing = FOOTPRINT_SIGMA_PER_SPACING;
    config.consensus.refinement.iterations = REFINEMENT_ITERATIONS;
    config.consensus.refinement.max_seconds = REFINEMENT_MAX_SECONDS;
    // The pretrained descriptor (shared data): the classical thumbnail rarely proposes the
    // overlapping pair of this scene.
    config.consensus.descriptor_weights =
        Some(datasets::shared_data::require("weights/lpips/alexnet.npz"));
    config
}

fn swarm(tag: &str) -> SwarmRun {
    swarm_with(tag, &config())
}

fn swarm_with(tag: &str, config: &Config) -> SwarmRun {
    let agents = (0..2)
        .map(|k| {
            AgentSpec::new(
                format!(
                    "synthetic:agents=2,agent={k},frames={FRAMES},width={WIDTH},height={HEIGHT}"
                ),
                "..",
            )
        })
        .collect();
    SwarmRun::new(tag, config, agents)
}

/// Both agents placed in the world with a pose per frame, and the figures within bounds.
fn check(swarm: &SwarmRun, metrics: &serde_json::Value) {
    for k in 0..2 {
        let world = swarm.path().join(format!("agent_{k}.tum"));
        assert!(
            world.exists(),
            "agent {k} was not placed in the world frame"
        );
        let poses = geometry::trajectory::Trajectory::read_tum(&world).unwrap();
        assert_eq!(poses.len(), FRAMES, "agent {k}: one world pose per frame");
    }
    let ate = metrics["ate_joint_rmse_m"].as_f64().expect("joint ATE");
    assert!(ate <= MAX_JOINT_ATE_M, "joint ATE {ate} m");
    let inter_agent = metrics["inter_agent_closures_accepted"].as_u64().unwrap();
    assert!(inter_agent >= 1, "no inter-agent loop closure accepted");
    assert!(swarm.path().join("map.ply").exists());
}

/// The live view each process recorded (`--record`): one recording id for the swarm, every
/// documented entity, one camera pose per frame the agent logged, and the closures the consensus
/// accepted.
fn check_recordings(swarm: &SwarmRun, dir: &std::path::Path) {
    use live_view::{RrdSummary, paths};
    let consensus = RrdSummary::read(&dir.join("consensus.rrd")).unwrap();
    let shown = format!("{consensus:#?}");
    assert_eq!(
        consensus.recording_ids.iter().collect::<Vec<_>>(),
        [&swarm.namespace],
        "{shown}"
    );
    let accepted = swarm.consensus_report()["loop_closures_accepted"]
        .as_u64()
        .unwrap();
    assert!(accepted >= 1, "the consensus accepted no closure");
    assert!(
        consensus.rows(paths::CONSENSUS_CLOSURES, "LineStrips3D:strips") >= 1,
        "{shown}"
    );
    assert!(
        consensus.scalar_max(paths::CONSENSUS_CLOSURES_ACCEPTED) >= Some(1.0),
        "closures accepted but not shown: {shown}"
    );
    assert!(
        consensus.scalar_max(paths::CONSENSUS_LATENCY_MS).is_some(),
        "{shown}"
    );
    assert!(
        consensus.rows(paths::CONSENSUS_MAP, "Points3D:positions") >= 1,
        "{shown}"
    );
    for k in 0..2u32 {
        assert!(
            consensus.rows(&paths::consensus_trajectory(k), "LineStrips3D:strips") >= 1,
            "agent {k}: {shown}"
        );
        let agent = RrdSummary::read(&dir.join(format!("agent_{k}.rrd"))).unwrap();
        let shown = format!("{agent:#?}");
        assert_eq!(agent.recording_ids, consensus.recording_ids, "{shown}");
        let metrics: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(swarm.path().join(format!("agent_{k}/metrics.json"))).unwrap(),
        )
        .unwrap();
        let stats = &metrics["live_view"];
        assert_eq!(stats["finished"], true, "agent {k}: {stats}");
        let logged = stats["frames_queued"].as_u64().unwrap() as usize;
        let dropped = stats["frames_dropped"].as_u64().unwrap() as usize;
        assert_eq!(logged + dropped, FRAMES, "agent {k}: {stats}");
        assert_eq!(
            agent.rows(&paths::agent_camera(k), "Transform3D:translation"),
            logged,
            "agent {k}: one camera pose per frame logged: {shown}"
        );
        for (entity, component) in [
            (paths::agent_camera(k), "Pinhole:image_from_camera"),
            (paths::agent_camera(k), "EncodedImage:blob"),
            (paths::agent_trajectory(k), "LineStrips3D:strips"),
            (paths::agent_keyframes(k), "Points3D:positions"),
            (paths::agent_map(k), "Points3D:positions"),
        ] {
            assert!(
                agent.rows(&entity, component) >= 1,
                "agent {k}: {entity} {component}: {shown}"
            );
        }
    }
    // Agent 1 was placed in the world (`check`): its frame's transform was logged.
    let agent_1 = RrdSummary::read(&dir.join("agent_1.rrd")).unwrap();
    assert!(agent_1.rows(&paths::agent(1), "Transform3D:translation") >= 1);
}

#[test]
fn real_data_swarm_of_two_agent_processes_agrees_on_one_sharp_world() {
    let mut swarm = swarm("a");
    // The live view's recordings ride along on this run (a run of their own would double its
    // minutes in CI).
    let recordings = swarm.record_live_view();
    swarm.run_to_end();
    check_recordings(&swarm, &recordings);
    let metrics = swarm.evaluate(RENDER_EVERY);
    eprintln!(
        "joint ATE {:?} m, PSNR {:?} dB, SSIM {:?}, depth L1 {:?} cm, inter-agent closures {:?}, \
         refinement {}",
        metrics["ate_joint_rmse_m"],
        metrics["psnr"],
        metrics["ssim"],
        metrics["depth_l1_cm"],
        metrics["inter_agent_closures_accepted"],
        swarm.consensus_report()["refinement"]
    );
    check(&swarm, &metrics);
    let psnr = metrics["psnr"].as_f64().expect("merged-map PSNR");
    assert!(
        psnr >= MIN_MERGED_PSNR_DB,
        "merged-map PSNR {psnr} dB < {MIN_MERGED_PSNR_DB}"
    );
}

#[test]
fn real_data_swarm_agent_process_killed_and_restarted_still_gives_a_complete_result() {
    let swarm = swarm("b");
    let consensus = swarm.spawn_consensus();
    let survivor = swarm.spawn_agent(0, "agent_0");
    let mut victim = swarm.spawn_agent(1, "agent_1_killed");
    // Let it publish something first, then SIGKILL: no goodbye, shared memory left behind.
    std::thread::sleep(KILL_AFTER);
    assert!(
        victim.try_wait().unwrap().is_none(),
        "agent 1 finished before it could be killed mid-run"
    );
    victim.kill().unwrap();
    victim.wait().unwrap();
    let restarted = swarm.spawn_agent(1, "agent_1");
    swarm.wait(survivor, "agent 0", "agent_0");
    swarm.wait(restarted, "restarted agent 1", "agent_1");
    swarm.wait(consensus, "mac-consensus", "consensus");
    let report = swarm.consensus_report();
    assert_eq!(
        report["agents"]["1"]["hellos"], 2,
        "the restarted agent re-announced itself"
    );
    // Keyframe decisions after a correction depend on when it arrived, so a re-run's keyframe
    // N may show another frame than the killed run's: such images are counted, not asserted.
    eprintln!(
        "restarted agent 1: {} keyframe id conflicts",
        report["agents"]["1"]["keyframe_id_conflicts"]
    );
    let metrics = swarm.evaluate(RENDER_EVERY);
    check(&swarm, &metrics);
}

/// The consensus SIGKILLed mid-run and started again on its folder resumes from its store (the
/// agents keep running meanwhile): the final consensus.json holds every keyframe each agent
/// delivered, and the joint ATE meets the bound the uninterrupted run is held to
/// (`real_data_swarm_of_two_agent_processes_agrees_on_one_sharp_world`). Not a ratio to an
/// uninterrupted run made here: two uninterrupted runs of this scene already differ by more than
/// 10 % (8.2 and 2.8 mm measured), so a ratio would test timing noise and double the test's time.
#[test]
fn real_data_swarm_consensus_killed_and_restarted_resumes_and_loses_no_keyframe() {
    let swarm = swarm("d");
    let mut killed = swarm.spawn_consensus_logged("consensus_killed");
    let agents: Vec<_> = (0..2)
        .map(|k| swarm.spawn_agent(k, &format!("agent_{k}")))
        .collect();
    std::thread::sleep(CONSENSUS_KILL_AFTER);
    assert!(
        killed.try_wait().unwrap().is_none(),
        "the consensus finished before it could be killed mid-run"
    );
    killed.kill().unwrap();
    killed.wait().unwrap();
    let stored_at_kill = std::fs::metadata(swarm.path().join("consensus.redb"))
        .expect("the killed consensus left its store")
        .len();
    std::thread::sleep(CONSENSUS_DOWN_FOR);
    let consensus = swarm.spawn_consensus();
    for (k, agent) in agents.into_iter().enumerate() {
        swarm.wait(agent, &format!("agent {k}"), &format!("agent_{k}"));
    }
    swarm.wait(consensus, "mac-consensus", "consensus");
    let log = std::fs::read_to_string(swarm.path().join("consensus.log")).unwrap();
    assert!(
        log.contains("resuming the run from its consensus store"),
        "the restarted consensus did not resume ({stored_at_kill} bytes stored at the kill)"
    );

    let report = swarm.consensus_report();
    let held: std::collections::BTreeSet<(u64, u64)> = report["keyframe_info"]
        .as_array()
        .unwrap()
        .iter()
        .map(|entry| {
            (
                entry[0]["agent_id"].as_u64().unwrap(),
                entry[0]["keyframe_id"].as_u64().unwrap(),
            )
        })
        .collect();
    for k in 0..2u64 {
        let text =
            std::fs::read_to_string(swarm.path().join(format!("agent_{k}/metrics.json"))).unwrap();
        let metrics: serde_json::Value = serde_json::from_str(&text).unwrap();
        let published = metrics["swarm"]["keyframes_published_ids"]
            .as_array()
            .unwrap();
        assert!(!published.is_empty(), "agent {k} published nothing");
        let missing: Vec<u64> = published
            .iter()
            .map(|id| id.as_u64().unwrap())
            .filter(|id| !held.contains(&(k, *id)))
            .collect();
        assert!(
            missing.is_empty(),
            "agent {k}: keyframes {missing:?} published but not in the final consensus state"
        );
        eprintln!(
            "agent {k}: {} keyframes published, all in consensus.json; told the consensus was \
             back {} time(s), {} published again",
            published.len(),
            metrics["swarm"]["consensus_resumed"],
            metrics["swarm"]["keyframes_resent"]
        );
    }
    let metrics = swarm.evaluate(0);
    let ate = metrics["ate_joint_rmse_m"].as_f64().expect("joint ATE");
    eprintln!("joint ATE with the consensus killed and resumed: {ate} m");
    assert!(ate <= MAX_JOINT_ATE_M, "joint ATE {ate} m after the resume");
    assert!(
        metrics["inter_agent_closures_accepted"].as_u64().unwrap() >= 1,
        "no inter-agent loop closure after the resume"
    );
}

/// Wrong closures injected at 30 % of the pose graph's (`[consensus.false_closures]`): the robust
/// solve rejects them and the swarm's figures hold.
#[test]
fn real_data_swarm_with_injected_wrong_closures_keeps_its_world() {
    let mut config = config();
    config.consensus.false_closures.fraction = 0.3;
    config.consensus.false_closures.seed = 3;
    let swarm = swarm_with("c", &config);
    swarm.run_to_end();
    let report = swarm.consensus_report();
    let injected = report["false_closures_injected"].as_u64().unwrap();
    let accepted = report["false_closures_accepted"].as_u64().unwrap();
    let verified = report["closures_verified"].as_u64().unwrap();
    eprintln!("{injected} wrong closures injected beside {verified} verified; {accepted} kept");
    // At least 30 % of the graph's closures (the real ones include map links, not in
    // `closures_verified` when they came from map registration, hence >=).
    assert!(
        injected as f64 >= 0.3 / 0.7 * verified as f64 - 1.0 && injected >= 1,
        "{injected} injected beside {verified} verified"
    );
    assert_eq!(accepted, 0, "the pose graph kept wrong closures");
    let metrics = swarm.evaluate(RENDER_EVERY);
    check(&swarm, &metrics);
}
