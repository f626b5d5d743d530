//! `mac-ego3d swarm` (the launcher scripts/launch_swarm.sh and scripts/run.sh run) as a user
//! runs it from a terminal. A terminal's Ctrl-C sends SIGINT to the whole foreground process
//! group at once; the run must still end in order (the agents finish their frame and write their
//! outputs, then the consensus writes the world outputs from them) and leave a complete result.
//! A consensus killed mid-run is started again on its store, and a wrong option is refused
//! before anything starts.

mod common;

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, ExitStatus};
use std::time::{Duration, Instant};

const AGENTS: usize = 2;
const FRAMES: usize = 150;
/// Frames every agent has tracked before the interrupt: mid-run, after its first publications.
const INTERRUPT_AFTER_FRAMES: u64 = 40;
const TIMEOUT: Duration = Duration::from_secs(600);

/// `mac-ego3d swarm`, the binaries beside it (as cargo test built them).
fn swarm() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"));
    command.arg("swarm");
    command
}

fn frames_done(progress: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(progress).ok()?;
    let json: serde_json::Value = serde_json::from_str(&text).ok()?;
    json["frames_done"].as_u64()
}

fn wait_with_timeout(child: &mut std::process::Child, timeout: Duration) -> Option<ExitStatus> {
    let started = Instant::now();
    while started.elapsed() < timeout {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    None
}

fn lines(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .count()
}

#[test]
fn ctrl_c_to_the_whole_process_group_leaves_every_agents_outputs_and_the_world_outputs() {
    let out = tempfile::tempdir().unwrap();
    let runtime = tempfile::tempdir().unwrap();
    let mut child = swarm()
        .args([
            "--agents",
            &AGENTS.to_string(),
            "--frames",
            &FRAMES.to_string(),
            "--set",
            "consensus.t_comm=45",
        ])
        .arg("--out")
        .arg(out.path())
        .env("XDG_RUNTIME_DIR", runtime.path())
        // As a terminal's foreground job: its own process group, SIGINT at its default action.
        .process_group(0)
        .stdout(std::fs::File::create(out.path().join("launch.log")).unwrap())
        .stderr(std::fs::File::create(out.path().join("launch.err")).unwrap())
        .spawn()
        .unwrap();
    let log = || {
        std::fs::read_to_string(out.path().join("launch.err")).unwrap_or_default()
            + &std::fs::read_to_string(out.path().join("launch.log")).unwrap_or_default()
    };

    let started = Instant::now();
    loop {
        let done: Vec<Option<u64>> = (0..AGENTS)
            .map(|k| frames_done(&out.path().join(format!("agent_{k}/progress.json"))))
            .collect();
        if done
            .iter()
            .all(|d| d.is_some_and(|f| f >= INTERRUPT_AFTER_FRAMES))
        {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the swarm ended before the interrupt:\n{}",
            log()
        );
        assert!(
            started.elapsed() < TIMEOUT,
            "agents never reached frame {INTERRUPT_AFTER_FRAMES}:\n{}",
            log()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    // What a terminal's Ctrl-C does: SIGINT to every process of the foreground group.
    let status = Command::new("kill")
        .args(["-INT", "--", &format!("-{}", child.id())])
        .status()
        .unwrap();
    assert!(status.success());

    let status = wait_with_timeout(&mut child, TIMEOUT).unwrap_or_else(|| {
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", child.id())])
            .status();
        panic!("the interrupted swarm did not end:\n{}", log())
    });
    assert!(
        status.success(),
        "mac-ego3d swarm failed:\n{}\n{}",
        log(),
        common::log_tails(out.path(), 40)
    );
    assert!(log().contains("interrupted"), "{}", log());

    let consensus: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("consensus.json")).unwrap())
            .unwrap();
    assert_eq!(consensus["interrupted"], true);
    // `--set` reached the run's configuration, which every process read.
    let run_config = config::Config::load(&out.path().join("config.toml")).unwrap();
    assert_eq!(run_config.consensus.t_comm, 45);
    for k in 0..AGENTS {
        // Every agent handed over its trajectory, and it stopped early.
        let own = out.path().join(format!("agent_{k}/trajectory.tum"));
        let tracked = lines(&own);
        assert!(
            tracked >= INTERRUPT_AFTER_FRAMES as usize && tracked < FRAMES,
            "agent {k}: {tracked} poses in {}",
            own.display()
        );
        assert_eq!(
            consensus["agents"][k.to_string()]["goodbyes"],
            1,
            "agent {k}"
        );
        // Agent 0 defines the world frame; every agent the consensus placed has its world
        // trajectory, with every pose the agent tracked.
        let placed = !consensus["agents"][k.to_string()]["world_from_agent"].is_null();
        assert!(placed || k != 0, "agent 0 must be placed");
        if placed {
            let world = out.path().join(format!("agent_{k}.tum"));
            assert_eq!(lines(&world), tracked, "agent {k}: {}", world.display());
        }
    }
    assert!(out.path().join("map.ply").exists());
    assert!(out.path().join("metrics.json").exists());
}

/// The pid of the `mac-consensus` process writing into `out` (found in /proc by its command
/// line: `--out` names this test's own temporary folder).
fn consensus_pid(out: &Path) -> Option<u32> {
    let out = out.to_str()?;
    std::fs::read_dir("/proc").ok()?.find_map(|entry| {
        let pid: u32 = entry.ok()?.file_name().to_str()?.parse().ok()?;
        let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).ok()?;
        let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
        let is_consensus = args
            .first()
            .is_some_and(|program| program.ends_with(b"mac-consensus"));
        let writes_here = args
            .windows(2)
            .any(|pair| pair[0] == b"--out" && pair[1] == out.as_bytes());
        (is_consensus && writes_here).then_some(pid)
    })
}

/// A consensus killed mid-run (SIGKILL) is started again by the launcher on the run folder;
/// it resumes from its store and the run ends as one without the crash: every keyframe the
/// agents delivered is in consensus.json, both agents placed with every pose.
#[test]
fn a_killed_consensus_is_restarted_and_the_run_ends_complete() {
    let out = tempfile::tempdir().unwrap();
    let runtime = tempfile::tempdir().unwrap();
    let mut child = swarm()
        .args(["--agents", &AGENTS.to_string()])
        .args(["--frames", &FRAMES.to_string()])
        .arg("--out")
        .arg(out.path())
        .env("XDG_RUNTIME_DIR", runtime.path())
        .process_group(0)
        .stdout(std::fs::File::create(out.path().join("launch.log")).unwrap())
        .stderr(std::fs::File::create(out.path().join("launch.err")).unwrap())
        .spawn()
        .unwrap();
    let log = || {
        std::fs::read_to_string(out.path().join("launch.err")).unwrap_or_default()
            + &std::fs::read_to_string(out.path().join("launch.log")).unwrap_or_default()
    };
    let started = Instant::now();
    let victim = loop {
        let done: Vec<Option<u64>> = (0..AGENTS)
            .map(|k| frames_done(&out.path().join(format!("agent_{k}/progress.json"))))
            .collect();
        if done
            .iter()
            .all(|d| d.is_some_and(|f| f >= INTERRUPT_AFTER_FRAMES))
            && let Some(pid) = consensus_pid(out.path())
        {
            break pid;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the swarm ended before the kill:\n{}",
            log()
        );
        assert!(
            started.elapsed() < TIMEOUT,
            "agents never got going:\n{}",
            log()
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    let status = Command::new("kill")
        .args(["-KILL", &victim.to_string()])
        .status()
        .unwrap();
    assert!(status.success());

    let status = wait_with_timeout(&mut child, TIMEOUT).unwrap_or_else(|| {
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", child.id())])
            .status();
        panic!("the swarm did not end:\n{}", log())
    });
    assert!(
        status.success(),
        "mac-ego3d swarm failed:\n{}\n{}",
        log(),
        common::log_tails(out.path(), 40)
    );
    assert!(
        log().contains("starting it again on its store"),
        "{}",
        log()
    );
    let consensus_log = std::fs::read_to_string(out.path().join("consensus.log")).unwrap();
    assert!(
        consensus_log.contains("resuming the run from its consensus store"),
        "the restarted consensus did not resume"
    );

    let consensus: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("consensus.json")).unwrap())
            .unwrap();
    assert_eq!(consensus["interrupted"], false);
    let held: Vec<(u64, u64)> = consensus["keyframe_info"]
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
    for k in 0..AGENTS {
        let metrics: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.path().join(format!("agent_{k}/metrics.json"))).unwrap(),
        )
        .unwrap();
        for id in metrics["swarm"]["keyframes_published_ids"]
            .as_array()
            .unwrap()
        {
            let id = id.as_u64().unwrap();
            assert!(
                held.contains(&(k as u64, id)),
                "agent {k}: keyframe {id} delivered but not in consensus.json"
            );
        }
        let tracked = lines(&out.path().join(format!("agent_{k}/trajectory.tum")));
        assert_eq!(tracked, FRAMES, "agent {k} ran to the end");
        let world = out.path().join(format!("agent_{k}.tum"));
        if k == 0 || world.exists() {
            assert_eq!(lines(&world), tracked, "agent {k}: {}", world.display());
        }
    }
    assert!(out.path().join("map.ply").exists());
    assert!(out.path().join("metrics.json").exists());
}

/// A wrong `--set` stops the run before any process starts, naming the key.
#[test]
fn a_wrong_set_override_is_refused_before_anything_starts() {
    let out = tempfile::tempdir().unwrap();
    let output = swarm()
        .args(["--agents", "1", "--set", "consensus.t_comm=often"])
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&output.stderr).to_string()
        + &String::from_utf8_lossy(&output.stdout);
    assert_eq!(output.status.code(), Some(2), "{log}");
    assert!(log.contains("consensus.t_comm"), "{log}");
    assert!(!out.path().join("consensus.log").exists(), "{log}");
}
