//! `--transport zenoh`: every process of the swarm on a simulated host of its own
//! (scripts/simulated_host.sh: own mount namespace, private /dev/shm and iceoryx2 root, its own
//! `mac-bridge`), all joined by zenoh on 127.0.0.1, over TLS with a swarm CA and a certificate
//! per host made for the run (`mac-bridge certs`), or over plain TCP when asked.

use std::ffi::OsString;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::Context;

use super::supervisor::Role;

/// How the simulated hosts authenticate each other.
#[derive(Debug, Clone)]
pub enum Security {
    /// Mutual TLS with the run's certificates in this folder.
    Tls { certificates: PathBuf },
    /// Plain TCP, no authentication.
    PlainTcp,
}

/// The command prefixes that run each process on a simulated host of its own.
#[derive(Debug, Clone)]
pub struct SimulatedHosts {
    script: PathBuf,
    bridge: PathBuf,
    namespace: String,
    agents: u32,
    /// The consensus host's zenoh endpoint, `tls/127.0.0.1:PORT` (or `tcp/...`).
    endpoint: String,
    security: Security,
    out: PathBuf,
    config: PathBuf,
}

impl SimulatedHosts {
    /// Hosts for a swarm of `agents` writing into `out`: a free port on 127.0.0.1 for the
    /// consensus host, and (TLS) a new CA and host certificates in `out/certs` (an earlier run's
    /// are replaced).
    pub fn prepare(
        script: PathBuf,
        binaries: &Path,
        namespace: &str,
        agents: u32,
        plain_tcp: bool,
        out: &Path,
        config: &Path,
    ) -> anyhow::Result<Self> {
        let bridge = binaries.join("mac-bridge");
        anyhow::ensure!(
            bridge.is_file(),
            "{} is missing (--transport zenoh needs it)",
            bridge.display()
        );
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .context("finding a free port on 127.0.0.1")?
            .port();
        let security = if plain_tcp {
            Security::PlainTcp
        } else {
            let certificates = out.join("certs");
            if certificates.exists() {
                std::fs::remove_dir_all(&certificates)
                    .with_context(|| format!("removing {}", certificates.display()))?;
            }
            let log_path = out.join("certs.log");
            let log = std::fs::File::create(&log_path)
                .with_context(|| format!("creating {}", log_path.display()))?;
            let mut command = Command::new(&bridge);
            command
                .arg("certs")
                .arg("--out")
                .arg(&certificates)
                .args(["--host", "consensus=127.0.0.1"]);
            for k in 0..agents {
                command.args(["--host", &format!("agent{k}")]);
            }
            let status = command
                .stdout(log.try_clone()?)
                .stderr(log)
                .status()
                .with_context(|| format!("running {}", bridge.display()))?;
            anyhow::ensure!(
                status.success(),
                "making the run's certificates failed; see {}",
                log_path.display()
            );
            Security::Tls { certificates }
        };
        let scheme = match security {
            Security::Tls { .. } => "tls",
            Security::PlainTcp => "tcp",
        };
        Ok(Self {
            script,
            bridge,
            namespace: namespace.to_string(),
            agents,
            endpoint: format!("{scheme}/127.0.0.1:{port}"),
            security,
            out: out.to_path_buf(),
            config: config.to_path_buf(),
        })
    }

    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    pub fn is_plain_tcp(&self) -> bool {
        matches!(self.security, Security::PlainTcp)
    }

    /// `simulated_host.sh BRIDGE BRIDGE_ARGS --`: what runs `role`'s program on its host.
    pub fn prefix(&self, role: Role) -> Vec<OsString> {
        let mut prefix: Vec<OsString> =
            vec![self.script.clone().into(), self.bridge.clone().into()];
        let mut push = |args: &[&str]| prefix.extend(args.iter().map(OsString::from));
        let agents = self.agents.to_string();
        let host = match role {
            Role::Consensus => {
                push(&["--role", "consumers", "--namespace", &self.namespace]);
                push(&["--agents", &agents, "--listen", &self.endpoint]);
                "consensus".to_string()
            }
            Role::Agent(k) => {
                push(&["--role", "agents", "--namespace", &self.namespace]);
                push(&["--agents", &agents, "--local-agent", &k.to_string()]);
                push(&["--connect", &self.endpoint]);
                format!("agent{k}")
            }
        };
        match &self.security {
            Security::PlainTcp => push(&["--insecure-plain-tcp"]),
            Security::Tls { certificates } => {
                prefix.push("--certificates".into());
                prefix.push(certificates.clone().into());
                prefix.extend(["--host".into(), host.into()]);
            }
        }
        let report = match role {
            Role::Consensus => "bridge_consensus.json".to_string(),
            Role::Agent(k) => format!("bridge_agent_{k}.json"),
        };
        prefix.push("--report".into());
        prefix.push(self.out.join(report).into());
        if let Role::Agent(_) = role {
            prefix.push("--config".into());
            prefix.push(self.config.clone().into());
        }
        prefix.push("--".into());
        prefix
    }
}

/// scripts/simulated_host.sh: beside the current folder's scripts/ (the repository root, where
/// the launcher is run from), else in the repository the running binary was built in.
pub fn find_script() -> anyhow::Result<PathBuf> {
    let relative = Path::new("scripts/simulated_host.sh");
    let mut candidates = vec![std::env::current_dir()?.join(relative)];
    if let Ok(exe) = std::env::current_exe() {
        candidates.extend(exe.ancestors().skip(1).map(|dir| dir.join(relative)));
    }
    candidates
        .into_iter()
        .find(|path| path.is_file())
        .context("scripts/simulated_host.sh not found (run from the repository root)")
}
