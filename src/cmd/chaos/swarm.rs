//! The soak's swarm: one `mac-consensus` and N `mac-agent` processes on the synthetic scene,
//! started, killed (SIGKILL) and started again as a user would, with the same command line.

use std::fs::OpenOptions;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};

/// Which process of the swarm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Consensus,
    Agent(u32),
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Role::Consensus => write!(f, "consensus"),
            Role::Agent(k) => write!(f, "agent {k}"),
        }
    }
}

/// What the swarm's processes run with.
pub struct SwarmSetup {
    pub binaries: PathBuf,
    pub config: PathBuf,
    pub out: PathBuf,
    pub namespace: String,
    /// One dataset spec per agent.
    pub datasets: Vec<String>,
}

/// The running processes (`None`: ended or killed and not restarted yet) and their exits.
pub struct Swarm {
    setup: SwarmSetup,
    consensus: Option<Child>,
    agents: Vec<Option<Child>>,
    consensus_starts: usize,
}

impl Swarm {
    /// Starts the consensus (a new run: `--fresh`) and every agent.
    pub fn start(setup: SwarmSetup) -> anyhow::Result<Self> {
        config::process::prepare_output_dir(&setup.out)?;
        let agents = setup.datasets.len();
        let mut swarm = Self {
            setup,
            consensus: None,
            agents: (0..agents).map(|_| None).collect(),
            consensus_starts: 0,
        };
        swarm.spawn(Role::Consensus)?;
        for k in 0..agents as u32 {
            swarm.spawn(Role::Agent(k))?;
        }
        Ok(swarm)
    }

    /// Starts `role`'s process (again) with its command line; its log is appended to.
    pub fn spawn(&mut self, role: Role) -> anyhow::Result<()> {
        let setup = &self.setup;
        let (program, log) = match role {
            Role::Consensus => ("mac-consensus", "consensus.log".to_string()),
            Role::Agent(k) => ("mac-agent", format!("agent_{k}.log")),
        };
        let log_path = setup.out.join(log);
        let log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .with_context(|| format!("opening {}", log_path.display()))?;
        let mut command = Command::new(setup.binaries.join(program));
        command
            .arg("--config")
            .arg(&setup.config)
            .args(["--namespace", &setup.namespace])
            .stdout(Stdio::null())
            .stderr(log);
        match role {
            Role::Consensus => {
                command
                    .arg("--out")
                    .arg(&setup.out)
                    .args(["--agents", &setup.datasets.len().to_string()])
                    .args(["--run-id", &setup.namespace]);
                if self.consensus_starts == 0 {
                    command.arg("--fresh");
                }
            }
            Role::Agent(k) => {
                command
                    .args(["--dataset", &setup.datasets[k as usize], "--frames", ".."])
                    .args(["--agent-id", &k.to_string()])
                    // The agents' own quality figures on every 10th frame (eval swarm's PSNR
                    // without merged-map renders), no comparison images.
                    .args(["--eval-every", "10", "--renders", "0"])
                    .arg("--out")
                    .arg(setup.out.join(format!("agent_{k}")));
            }
        }
        let child = command
            .spawn()
            .with_context(|| format!("starting {}", setup.binaries.join(program).display()))?;
        match role {
            Role::Consensus => {
                self.consensus_starts += 1;
                self.consensus = Some(child);
            }
            Role::Agent(k) => self.agents[k as usize] = Some(child),
        }
        Ok(())
    }

    fn slot(&mut self, role: Role) -> &mut Option<Child> {
        match role {
            Role::Consensus => &mut self.consensus,
            Role::Agent(k) => &mut self.agents[k as usize],
        }
    }

    /// SIGKILLs `role` if it is running; false when it had already ended (cleanly: anything
    /// else is an error).
    pub fn kill(&mut self, role: Role) -> anyhow::Result<bool> {
        self.reap()?;
        let Some(mut child) = self.slot(role).take() else {
            return Ok(false);
        };
        child.kill().with_context(|| format!("killing {role}"))?;
        child.wait()?;
        Ok(true)
    }

    /// Takes the exit of every process that ended; one that failed is an error naming its log.
    pub fn reap(&mut self) -> anyhow::Result<()> {
        let roles: Vec<Role> = std::iter::once(Role::Consensus)
            .chain((0..self.agents.len() as u32).map(Role::Agent))
            .collect();
        for role in roles {
            let out = self.setup.out.clone();
            let slot = self.slot(role);
            let Some(child) = slot.as_mut() else {
                continue;
            };
            if let Some(status) = child.try_wait()? {
                *slot = None;
                check_exit(role, status, &out)?;
            }
        }
        Ok(())
    }

    /// Waits until every process has ended, up to `timeout` (then kills them all).
    /// Waits until every process has ended; returns how long the first agent to end ran
    /// (from this call, made right after the start).
    pub fn wait_all(&mut self, timeout: Duration) -> anyhow::Result<Duration> {
        let started = Instant::now();
        let mut first_agent_ended = None;
        loop {
            self.reap()?;
            if first_agent_ended.is_none() && self.agents.iter().any(Option::is_none) {
                first_agent_ended = Some(started.elapsed());
            }
            if self.consensus.is_none() && self.agents.iter().all(Option::is_none) {
                return Ok(first_agent_ended.unwrap_or_else(|| started.elapsed()));
            }
            if started.elapsed() > timeout {
                for role in std::iter::once(Role::Consensus)
                    .chain((0..self.agents.len() as u32).map(Role::Agent))
                {
                    self.kill(role)?;
                }
                bail!(
                    "the swarm in {} did not end within {timeout:?}",
                    self.setup.out.display()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Swarm {
    /// No process outlives the soak (an error path included).
    fn drop(&mut self) {
        for child in std::iter::once(&mut self.consensus)
            .chain(self.agents.iter_mut())
            .flatten()
        {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn check_exit(role: Role, status: ExitStatus, out: &Path) -> anyhow::Result<()> {
    if status.success() {
        return Ok(());
    }
    let log = match role {
        Role::Consensus => out.join("consensus.log"),
        Role::Agent(k) => out.join(format!("agent_{k}.log")),
    };
    bail!("{role} exited with {status}; see {}", log.display())
}
