//! Helpers shared by the bridge's integration tests.
#![allow(dead_code, reason = "each test binary uses a different subset")]

use std::path::Path;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

pub const BRIDGE: &str = env!("CARGO_BIN_EXE_mac-bridge");

pub fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|out| String::from_utf8_lossy(&out.stdout).trim() == "0")
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `mac-bridge certs --out folder --host ...`.
pub fn make_certs(folder: &Path, hosts: &[&str]) {
    let mut command = Command::new(BRIDGE);
    command.arg("certs").arg("--out").arg(folder);
    for host in hosts {
        command.args(["--host", host]);
    }
    let status = command.status().unwrap();
    assert!(status.success(), "mac-bridge certs: {status}");
}

/// The arguments that give a bridge host `host`'s files in `folder`.
pub fn credentials(folder: &Path, host: &str) -> [String; 4] {
    [
        "--certificates".to_string(),
        folder.display().to_string(),
        "--host".to_string(),
        host.to_string(),
    ]
}

/// Stops a child at the end of the test, whatever happens.
pub struct Reaped(pub Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        if self.0.try_wait().ok().flatten().is_some() {
            return;
        }
        // SIGTERM first: a bridge stops in order.
        let _ = Command::new("kill")
            .args(["-TERM", &self.0.id().to_string()])
            .status();
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(5) {
            if self.0.try_wait().ok().flatten().is_some() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Two simulated hosts joined over mutual TLS on 127.0.0.1, with certificates made for the
/// test: host B is the test process (a consumer) with a consumer-role bridge that listens; host
/// A runs an agent (this test binary again, running one ignored test) inside
/// scripts/simulated_host.sh with an agent-role bridge that connects.
pub struct TwoHosts {
    pub namespace: String,
    pub endpoint: String,
    /// Scratch folder of the test (the certificates are in it).
    pub work: tempfile::TempDir,
}

impl TwoHosts {
    /// `prefix` names the test's swarm namespace (the process id is appended).
    pub fn new(prefix: &str) -> Self {
        let work = tempfile::tempdir().unwrap();
        make_certs(&work.path().join("certs"), &["b=127.0.0.1", "a"]);
        Self {
            namespace: format!("{prefix}{}", std::process::id()),
            endpoint: format!("tls/127.0.0.1:{}", free_port()),
            work,
        }
    }

    fn swarm(&self) -> [&str; 4] {
        ["--namespace", &self.namespace, "--agents", "1"]
    }

    fn credentials(&self, host: &str) -> [String; 4] {
        credentials(&self.work.path().join("certs"), host)
    }

    /// Host B's consumer-role bridge (call again to start it again).
    pub fn consumer_bridge(&self) -> Reaped {
        Reaped(
            Command::new(BRIDGE)
                .args(["--role", "consumers", "--listen", &self.endpoint])
                .args(self.swarm())
                .args(self.credentials("b"))
                .spawn()
                .unwrap(),
        )
    }

    /// Host A, ready to spawn: its bridge gets `bridge_args` besides the swarm's, the agent is
    /// this binary running `agent_test` (`--exact NAME --ignored`, then `agent_args`) with the
    /// environment variable `agent_role` set to the namespace.
    pub fn agent_host(
        &self,
        bridge_args: &[&std::ffi::OsStr],
        agent_test: &str,
        agent_args: &[&str],
        agent_role: &str,
    ) -> Command {
        let repository = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        let mut command = Command::new(repository.join("scripts/simulated_host.sh"));
        command
            .arg(BRIDGE)
            .args(["--role", "agents", "--local-agent", "0"])
            .args(["--connect", &self.endpoint])
            .args(self.swarm())
            .args(self.credentials("a"))
            .args(bridge_args)
            .arg("--")
            .arg(std::env::current_exe().unwrap())
            .args(["--exact", agent_test, "--ignored"])
            .args(agent_args)
            .env(agent_role, &self.namespace);
        command
    }
}
