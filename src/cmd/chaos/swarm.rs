//! The soak's swarm: one `mac-consensus` and N `mac-agent` processes on the synthetic scene,
//! run by the swarm supervisor (`mac-ego3d swarm`'s), killed (SIGKILL) and started again as a
//! user would, with the same command line.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::bail;
use datasets::DatasetSpec;

use crate::cmd::swarm::supervisor::{Launch, Role, Supervisor};

/// What the swarm's processes run with.
pub struct SwarmSetup {
    pub binaries: PathBuf,
    pub config: PathBuf,
    pub out: PathBuf,
    pub namespace: String,
    /// One dataset spec per agent.
    pub datasets: Vec<DatasetSpec>,
    /// The consensus runs with its fault injection (`--fault-injection`).
    pub fault_injection: bool,
}

/// Starts the consensus (a new run: `--fresh`) and every agent.
pub fn start(setup: SwarmSetup) -> anyhow::Result<Supervisor> {
    config::process::prepare_output_dir(&setup.out)?;
    Supervisor::start(Launch {
        binaries: setup.binaries,
        config: setup.config,
        out: setup.out,
        run_id: setup.namespace.clone(),
        namespace: setup.namespace,
        datasets: setup.datasets,
        agent_threads: None,
        // The agents' own quality figures on every 10th frame (eval swarm's PSNR without
        // merged-map renders), no comparison images.
        agent_args: ["--eval-every", "10", "--renders", "0"]
            .map(Into::into)
            .to_vec(),
        consensus_args: if setup.fault_injection {
            vec!["--fault-injection".into()]
        } else {
            Vec::new()
        },
        hosts: None,
    })
}

/// Takes the exit of every process that ended; one that failed is an error naming its log.
pub fn reap(swarm: &mut Supervisor) -> anyhow::Result<()> {
    for (role, exit) in swarm.poll()? {
        if !exit.success() {
            bail!(
                "{role} exited with {exit}; see {}",
                swarm.log_of(role).display()
            );
        }
    }
    Ok(())
}

/// Waits until every process has ended, up to `timeout` (then kills them all); returns how
/// long the first agent to end ran (from this call, made right after the start).
pub fn wait_all(swarm: &mut Supervisor, timeout: Duration) -> anyhow::Result<Duration> {
    let started = Instant::now();
    let agents = swarm.launch().agents();
    let mut first_agent_ended = None;
    loop {
        reap(swarm)?;
        let running = |role| swarm.is_running(role);
        if first_agent_ended.is_none() && (0..agents).any(|k| !running(Role::Agent(k))) {
            first_agent_ended = Some(started.elapsed());
        }
        if swarm.all_ended() {
            return Ok(first_agent_ended.unwrap_or_else(|| started.elapsed()));
        }
        if started.elapsed() > timeout {
            for role in swarm.launch().roles() {
                swarm.kill(role)?;
            }
            bail!(
                "the swarm in {} did not end within {timeout:?}",
                out(swarm).display()
            );
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn out(swarm: &Supervisor) -> &Path {
    &swarm.launch().out
}
