//! A swarm run as a user starts one: one `mac-consensus` and N `mac-agent` processes (the
//! workspace's own binaries, each its own OS process) in a temporary folder, then `mac-ego3d eval
//! swarm` for the figures. Shared by the swarm tests of this package.
//!
//! The agent and consensus binaries belong to other packages of the workspace; `cargo test
//! --workspace` (the README's test command) builds them next to `mac-ego3d`.

#![allow(dead_code, reason = "each test file uses its own part")]

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use config::Config;

/// A run that takes longer than this has hung.
pub const RUN_TIMEOUT: Duration = Duration::from_secs(900);

/// A binary of the workspace, built next to this package's `mac-ego3d`.
pub fn workspace_binary(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .parent()
        .unwrap()
        .join(name);
    assert!(
        path.exists(),
        "{} is missing: run the tests with `cargo test --workspace` (it builds every binary)",
        path.display()
    );
    path
}

/// A file or folder of the shared real data (`$MAC_EGO3D_SHARED`, default ../shared); a clear
/// failure when it is missing (scripts/test.sh skips `real_data_` tests without the data).
pub fn shared_data(relative: &str) -> PathBuf {
    let dir = std::env::var_os("MAC_EGO3D_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared"));
    let path = dir.join(relative);
    assert!(
        path.exists(),
        "real data missing: {} (set MAC_EGO3D_SHARED)",
        path.display()
    );
    path
}

/// True when this process runs as root (network and mount namespaces for simulated hosts and
/// isolated DDS domains).
pub fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|out| String::from_utf8_lossy(&out.stdout).trim() == "0")
}

/// The peers' python (scripts/peers_venv.sh: rosbags, cyclonedds, ...), or None when PyPI cannot
/// be reached outside CI (the caller's test then says NOT RUN and passes; under CI it fails).
pub fn peers_python() -> Option<PathBuf> {
    let out = Command::new("bash")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/peers_venv.sh"))
        .output()
        .expect("running scripts/peers_venv.sh");
    if out.status.code() == Some(3) && std::env::var("CI").as_deref() != Ok("true") {
        eprintln!(
            "NOT RUN: the peers' environment cannot be made (no PyPI): {}",
            String::from_utf8_lossy(&out.stderr)
        );
        return None;
    }
    assert!(
        out.status.success(),
        "scripts/peers_venv.sh failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    Some(PathBuf::from(
        String::from_utf8(out.stdout).unwrap().trim().to_string(),
    ))
}

/// Runs `scripts/<script>` with `args` on redkitchen from the shared data, with the binaries
/// `cargo test --workspace` built (`--bin-dir`) and its outputs in `out` (`--out`); asserts it
/// succeeded and returns its standard output.
pub fn run_bench_script(script: &str, args: &[&str], out: &Path) -> String {
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_mac-ego3d")).parent().unwrap();
    let run = Command::new("bash")
        .arg(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("scripts")
                .join(script),
        )
        .args(args)
        .arg("--dataset")
        .arg(&dataset)
        .arg("--bin-dir")
        .arg(bin_dir)
        .arg("--out")
        .arg(out)
        .env("XDG_RUNTIME_DIR", out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout).into_owned();
    assert!(
        run.status.success(),
        "{script} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    stdout
}

/// A configuration file of the repository (`configs/...`).
pub fn repository_config(relative: &str) -> Config {
    Config::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join(relative)).unwrap()
}

/// The last `lines` lines of every `*.log` file in `dir` and its sub-folders (two levels), each
/// under its path: what a failed run's processes said, for the failure message (the run's
/// temporary folder is gone once the test ends).
pub fn log_tails(dir: &Path, lines: usize) -> String {
    let mut logs = Vec::new();
    let mut folders = vec![(dir.to_path_buf(), 0)];
    while let Some((folder, depth)) = folders.pop() {
        let Ok(entries) = std::fs::read_dir(&folder) else {
            continue;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() && depth < 2 {
                folders.push((path, depth + 1));
            } else if path.extension().is_some_and(|e| e == "log") {
                logs.push(path);
            }
        }
    }
    logs.sort();
    let mut text = String::new();
    for path in logs {
        let content = std::fs::read_to_string(&path).unwrap_or_default();
        let all: Vec<&str> = content.lines().collect();
        let tail = &all[all.len().saturating_sub(lines)..];
        text += &format!(
            "--- {} (last {} lines)\n{}\n",
            path.display(),
            tail.len(),
            tail.join("\n")
        );
    }
    text
}

/// One agent of a run: its dataset (path or `synthetic:...` spec) and frame range.
#[derive(Debug, Clone)]
pub struct AgentSpec {
    pub dataset: String,
    pub frames: String,
}

impl AgentSpec {
    pub fn new(dataset: impl Into<String>, frames: &str) -> Self {
        Self {
            dataset: dataset.into(),
            frames: frames.to_string(),
        }
    }
}

pub struct SwarmRun {
    pub dir: tempfile::TempDir,
    pub config: PathBuf,
    pub namespace: String,
    pub agents: Vec<AgentSpec>,
    /// Options every process gets (the live view's `--record DIR`, ...).
    pub extra_args: Vec<std::ffi::OsString>,
}

impl SwarmRun {
    /// A run folder with `config` written into it; `tag` keeps namespaces of concurrent tests
    /// apart.
    pub fn new(tag: &str, config: &Config, agents: Vec<AgentSpec>) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let written = dir.path().join("config.toml");
        std::fs::write(&written, toml::to_string(config).unwrap()).unwrap();
        Self {
            namespace: format!("e2e{}{tag}", std::process::id()),
            dir,
            config: written,
            agents,
            extra_args: Vec::new(),
        }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Every process records its live view to `rrd/` of the run folder, under the namespace as
    /// recording id; the folder.
    pub fn record_live_view(&mut self) -> PathBuf {
        let dir = self.path().join("rrd");
        self.extra_args.extend([
            "--record".into(),
            dir.clone().into_os_string(),
            "--recording-id".into(),
            self.namespace.clone().into(),
        ]);
        dir
    }

    pub fn log(&self, name: &str) -> std::fs::File {
        std::fs::File::create(self.path().join(format!("{name}.log"))).unwrap()
    }

    /// A command for one of the run's processes, independent of the user's environment: no
    /// default AlexNet weights (`MAC_EGO3D_WEIGHTS` empty; a test that wants them names them in
    /// its config, which wins), and, where unset, the run folder (mode 700) as runtime folder, so
    /// headless Vulkan prints no "XDG_RUNTIME_DIR is invalid" lines into the logs.
    pub fn command(&self, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut command = Command::new(program);
        command.env(alexnet::weights::WEIGHTS_ENV, "");
        if !std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|dir| Path::new(&dir).is_absolute()) {
            command.env("XDG_RUNTIME_DIR", self.path());
        }
        command
    }

    pub fn spawn_consensus(&self) -> Child {
        self.spawn_consensus_logged("consensus")
    }

    /// [`Self::spawn_consensus`], logging to `log`.log.
    pub fn spawn_consensus_logged(&self, log: &str) -> Child {
        self.command(workspace_binary("mac-consensus"))
            .arg("--config")
            .arg(&self.config)
            .arg("--out")
            .arg(self.path())
            .args(["--agents", &self.agents.len().to_string()])
            .args(["--namespace", &self.namespace])
            .args(&self.extra_args)
            .stderr(self.log(log))
            .spawn()
            .expect("starting mac-consensus")
    }

    pub fn spawn_agent(&self, agent_id: u32, log: &str) -> Child {
        let agent = &self.agents[agent_id as usize];
        self.command(workspace_binary("mac-agent"))
            .arg("--config")
            .arg(&self.config)
            .args(["--dataset", &agent.dataset, "--frames", &agent.frames])
            .args(["--agent-id", &agent_id.to_string()])
            .args(["--agents", &self.agents.len().to_string()])
            .args(["--namespace", &self.namespace])
            .args(["--eval-every", "50", "--renders", "0"])
            .arg("--out")
            .arg(self.path().join(format!("agent_{agent_id}")))
            .args(&self.extra_args)
            .stderr(self.log(log))
            .spawn()
            .expect("starting mac-agent")
    }

    /// Runs the consensus and every agent to the end.
    pub fn run_to_end(&self) {
        let consensus = self.spawn_consensus();
        let agents: Vec<Child> = (0..self.agents.len() as u32)
            .map(|k| self.spawn_agent(k, &format!("agent_{k}")))
            .collect();
        for (k, agent) in agents.into_iter().enumerate() {
            self.wait(agent, &format!("agent {k}"), &format!("agent_{k}"));
        }
        self.wait(consensus, "mac-consensus", "consensus");
    }

    /// Waits for `child`; on failure, panics with the tail of its log.
    pub fn wait(&self, mut child: Child, what: &str, log: &str) {
        let started = Instant::now();
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                if !status.success() {
                    panic!(
                        "{what} exited with {status}; its log ends:\n{}",
                        self.log_tail(log, 20)
                    );
                }
                return;
            }
            if started.elapsed() > RUN_TIMEOUT {
                let _ = child.kill();
                panic!("{what} did not finish within {RUN_TIMEOUT:?}");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// The last `lines` lines of a process's log.
    pub fn log_tail(&self, log: &str, lines: usize) -> String {
        let text =
            std::fs::read_to_string(self.path().join(format!("{log}.log"))).unwrap_or_default();
        let tail: Vec<&str> = text.lines().rev().take(lines).collect();
        tail.into_iter().rev().collect::<Vec<_>>().join("\n")
    }

    /// `mac-ego3d eval swarm --json` over the run's outputs, rendering every `render_every`-th
    /// frame (0: no renders, trajectories only).
    pub fn evaluate(&self, render_every: usize) -> serde_json::Value {
        let every = render_every.to_string();
        self.mac_ego3d_json(&[
            "eval",
            "swarm",
            "--json",
            "--renders",
            "0",
            "--render-every",
            &every,
        ])
    }

    /// `mac-ego3d bench merge --json` on the finished run: each agent's own map against the
    /// merged map on its frames.
    pub fn bench_merge(&self, every: usize) -> serde_json::Value {
        self.mac_ego3d_json(&["bench", "merge", "--json", "--every", &every.to_string()])
    }

    /// `mac-ego3d ARGS --dir RUN`, which must succeed and print JSON.
    fn mac_ego3d_json(&self, args: &[&str]) -> serde_json::Value {
        let what = args[..2].join(" ");
        let output = self
            .command(env!("CARGO_BIN_EXE_mac-ego3d"))
            .args(args)
            .arg("--dir")
            .arg(self.path())
            .output()
            .unwrap_or_else(|e| panic!("running mac-ego3d {what}: {e}"));
        assert!(
            output.status.success(),
            "{what} failed: {}",
            String::from_utf8_lossy(&output.stderr)
        );
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| {
            panic!(
                "{what} printed no JSON ({e}): {}",
                String::from_utf8_lossy(&output.stdout)
            )
        })
    }

    pub fn consensus_report(&self) -> serde_json::Value {
        let text = std::fs::read_to_string(self.path().join("consensus.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    }

    /// Whether the consensus placed agent `k` in the world (it wrote a world trajectory).
    pub fn is_linked(&self, k: u32) -> bool {
        self.path().join(format!("agent_{k}.tum")).exists()
    }

    /// One line per inter-agent attempt of consensus.json, for failure messages.
    pub fn attempts_summary(&self) -> String {
        let report = self.consensus_report();
        let Some(events) = report["events"].as_array() else {
            return "no events".into();
        };
        events
            .iter()
            .filter(|e| e["inter_agent"] == true)
            .map(|e| {
                format!(
                    "{} {}->{} verified {} pose graph {} inliers {} overlap {} {}",
                    e["kind"],
                    e["source"]["agent_id"],
                    e["target"]["agent_id"],
                    e["verified"],
                    e["accepted_by_pose_graph"],
                    e["inliers"],
                    e["overlap"],
                    e["rejection"]
                )
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}
