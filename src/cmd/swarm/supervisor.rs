//! The swarm's processes under one supervisor: the consensus and N agents (each, with zenoh, on
//! a simulated host of its own with its bridge), started with their command lines, signalled,
//! killed, started again, and reaped. `mac-ego3d swarm` and the chaos soak both run their
//! swarms through it.
//!
//! Every child runs in a process group of its own, so the Ctrl-C a terminal sends to its
//! foreground group reaches the supervisor only, which stops the children in order. A child's
//! stdout and stderr go to its log in the run folder (`consensus.log`, `agent_K.log`): the first
//! start of a process truncates it, a restart appends to it. No child outlives the supervisor
//! (an error path included: they are killed when it is dropped).

use std::ffi::OsString;
use std::fs::OpenOptions;
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};

use anyhow::Context;
use datasets::DatasetSpec;
use serde::{Deserialize, Serialize};

/// Which process of the swarm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
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

impl Role {
    /// The process's log in the run folder.
    pub fn log_name(self) -> String {
        match self {
            Role::Consensus => "consensus.log".to_string(),
            Role::Agent(k) => format!("agent_{k}.log"),
        }
    }
}

/// How each process of the swarm is started.
pub struct Launch {
    /// The folder of `mac-consensus`, `mac-agent` (and `mac-bridge` with zenoh).
    pub binaries: PathBuf,
    /// The run's configuration, read by every process.
    pub config: PathBuf,
    pub out: PathBuf,
    /// The iceoryx2 namespace: one per run, so two runs on one host never share services.
    pub namespace: String,
    /// The run's identity in the consensus store: a restarted consensus resumes this run only.
    pub run_id: String,
    /// One dataset (with its frames) per agent; agent K is the K-th.
    pub datasets: Vec<DatasetSpec>,
    /// Tracking threads per agent (`RAYON_NUM_THREADS`), when set.
    pub agent_threads: Option<usize>,
    /// Arguments every agent gets after its own (weights, link schedule, live view, evaluation).
    pub agent_args: Vec<OsString>,
    /// Arguments the consensus gets after its own (live view, `--stop-agents`).
    pub consensus_args: Vec<OsString>,
    /// With zenoh: each process on a simulated host of its own.
    pub hosts: Option<super::hosts::SimulatedHosts>,
}

impl Launch {
    pub fn agents(&self) -> u32 {
        self.datasets.len() as u32
    }

    /// Every process, the consensus first.
    pub fn roles(&self) -> impl Iterator<Item = Role> + use<> {
        std::iter::once(Role::Consensus).chain((0..self.agents()).map(Role::Agent))
    }

    /// The command that starts `role`; `fresh` starts a new consensus run (`--fresh`), else it
    /// resumes from its store.
    fn command(&self, role: Role, fresh: bool) -> Command {
        let prefix = self
            .hosts
            .as_ref()
            .map(|hosts| hosts.prefix(role))
            .unwrap_or_default();
        let program = self.binaries.join(match role {
            Role::Consensus => "mac-consensus",
            Role::Agent(_) => "mac-agent",
        });
        let mut command = match prefix.split_first() {
            Some((first, rest)) => {
                let mut command = Command::new(first);
                command.args(rest).arg(&program);
                command
            }
            None => Command::new(&program),
        };
        command
            .arg("--config")
            .arg(&self.config)
            .args(["--namespace", &self.namespace]);
        match role {
            Role::Consensus => {
                command
                    .arg("--out")
                    .arg(&self.out)
                    .args(["--agents", &self.agents().to_string()])
                    .args(["--run-id", &self.run_id]);
                if fresh {
                    command.arg("--fresh");
                }
                command.args(&self.consensus_args);
            }
            Role::Agent(k) => {
                command
                    .args(["--dataset", &self.datasets[k as usize].to_string()])
                    .args(["--agent-id", &k.to_string()])
                    .args(["--agents", &self.agents().to_string()])
                    .arg("--out")
                    .arg(self.out.join(format!("agent_{k}")))
                    .args(&self.agent_args);
                if let Some(threads) = self.agent_threads {
                    command.env("RAYON_NUM_THREADS", threads.to_string());
                }
            }
        }
        command
    }
}

/// A signal the supervisor sends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Signal {
    /// The consensus's orderly stop: it asks the agents to stop and writes its outputs.
    Interrupt,
    /// An agent's orderly stop: it finishes its frame and writes its outputs.
    Terminate,
    Kill,
}

impl Signal {
    fn number(self) -> libc::c_int {
        match self {
            Signal::Interrupt => libc::SIGINT,
            Signal::Terminate => libc::SIGTERM,
            Signal::Kill => libc::SIGKILL,
        }
    }
}

/// How a process ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Exit {
    /// Its exit code; absent when a signal ended it.
    pub code: Option<i32>,
    pub signal: Option<i32>,
}

impl Exit {
    pub fn success(&self) -> bool {
        self.code == Some(0)
    }
}

impl From<ExitStatus> for Exit {
    fn from(status: ExitStatus) -> Self {
        Self {
            code: status.code(),
            signal: status.signal(),
        }
    }
}

impl std::fmt::Display for Exit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.code, self.signal) {
            (Some(code), _) => write!(f, "status {code}"),
            (None, Some(signal)) => write!(f, "signal {signal}"),
            (None, None) => write!(f, "an unknown status"),
        }
    }
}

/// The running processes (`None`: ended, or killed and not started again yet).
pub struct Supervisor {
    launch: Launch,
    consensus: Option<Child>,
    agents: Vec<Option<Child>>,
    consensus_starts: usize,
    agent_starts: Vec<usize>,
}

impl Supervisor {
    /// Starts the consensus (a new run: `--fresh`) and every agent.
    pub fn start(launch: Launch) -> anyhow::Result<Self> {
        let agents = launch.datasets.len();
        let mut supervisor = Self {
            launch,
            consensus: None,
            agents: (0..agents).map(|_| None).collect(),
            consensus_starts: 0,
            agent_starts: vec![0; agents],
        };
        for role in supervisor.launch.roles() {
            supervisor.spawn(role)?;
        }
        Ok(supervisor)
    }

    pub fn launch(&self) -> &Launch {
        &self.launch
    }

    /// Times the consensus was started again after its first start.
    pub fn consensus_restarts(&self) -> usize {
        self.consensus_starts.saturating_sub(1)
    }

    /// Starts `role`'s process (again) with its command line. A consensus started again
    /// resumes the run from its store.
    pub fn spawn(&mut self, role: Role) -> anyhow::Result<()> {
        let starts = match role {
            Role::Consensus => self.consensus_starts,
            Role::Agent(k) => self.agent_starts[k as usize],
        };
        let log_path = self.launch.out.join(role.log_name());
        let log = OpenOptions::new()
            .create(true)
            .write(true)
            .append(starts > 0)
            .truncate(starts == 0)
            .open(&log_path)
            .with_context(|| format!("opening {}", log_path.display()))?;
        let mut command = self.launch.command(role, starts == 0);
        command
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .process_group(0);
        let child = command
            .spawn()
            .with_context(|| format!("starting {role}: {command:?}"))?;
        match role {
            Role::Consensus => {
                self.consensus_starts += 1;
                self.consensus = Some(child);
            }
            Role::Agent(k) => {
                self.agent_starts[k as usize] += 1;
                self.agents[k as usize] = Some(child);
            }
        }
        Ok(())
    }

    fn slot(&mut self, role: Role) -> &mut Option<Child> {
        match role {
            Role::Consensus => &mut self.consensus,
            Role::Agent(k) => &mut self.agents[k as usize],
        }
    }

    pub fn is_running(&self, role: Role) -> bool {
        match role {
            Role::Consensus => self.consensus.is_some(),
            Role::Agent(k) => self.agents[k as usize].is_some(),
        }
    }

    /// The process id of `role`, while it runs.
    pub fn pid(&self, role: Role) -> Option<u32> {
        match role {
            Role::Consensus => self.consensus.as_ref().map(Child::id),
            Role::Agent(k) => self.agents[k as usize].as_ref().map(Child::id),
        }
    }

    /// Sends `signal` to `role` if it runs (it is reaped by [`Self::poll`]).
    pub fn signal(&mut self, role: Role, signal: Signal) {
        if let Some(pid) = self.pid(role) {
            // SAFETY: kill(2) with the pid of a child this supervisor has not reaped yet (a
            // reaped child's slot is empty), so the pid cannot have been reused.
            unsafe {
                libc::kill(pid as libc::pid_t, signal.number());
            }
        }
    }

    /// SIGKILLs `role` and waits for it; false when it was not running.
    pub fn kill(&mut self, role: Role) -> anyhow::Result<bool> {
        let Some(mut child) = self.slot(role).take() else {
            return Ok(false);
        };
        child.kill().with_context(|| format!("killing {role}"))?;
        child.wait()?;
        Ok(true)
    }

    /// Reaps every process that ended since the last call, with how it ended.
    pub fn poll(&mut self) -> anyhow::Result<Vec<(Role, Exit)>> {
        let mut ended = Vec::new();
        for role in self.launch.roles() {
            let slot = self.slot(role);
            let Some(child) = slot.as_mut() else {
                continue;
            };
            if let Some(status) = child
                .try_wait()
                .with_context(|| format!("waiting for {role}"))?
            {
                *slot = None;
                ended.push((role, Exit::from(status)));
            }
        }
        Ok(ended)
    }

    /// Whether every process has ended.
    pub fn all_ended(&self) -> bool {
        self.consensus.is_none() && self.agents.iter().all(Option::is_none)
    }

    /// The log of `role`.
    pub fn log_of(&self, role: Role) -> PathBuf {
        log_path(&self.launch.out, role)
    }
}

/// The log of `role` in the run folder `out`.
pub fn log_path(out: &Path, role: Role) -> PathBuf {
    out.join(role.log_name())
}

impl Drop for Supervisor {
    /// No process outlives the supervisor.
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
