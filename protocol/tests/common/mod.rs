//! Helpers shared by the protocol crate's integration tests: unique namespaces and a handle on a
//! spawned `protocol-peer` process whose stdout lines can be awaited.

#![allow(dead_code, reason = "each test binary uses a different subset")]

use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::time::{Duration, Instant};

/// Generous bound for anything a peer process should do promptly on a loaded 2-core machine.
pub const PEER_TIMEOUT: Duration = Duration::from_secs(30);
const EXIT_POLL: Duration = Duration::from_millis(10);

/// A namespace no other test (or concurrent test run) uses.
pub fn unique_namespace(test: &str) -> String {
    format!("mac-test-{}-{test}", std::process::id())
}

pub fn peer_binary() -> &'static str {
    env!("CARGO_BIN_EXE_protocol-peer")
}

/// A running `protocol-peer` process; killed on drop so a failing test leaves no orphan.
pub struct Peer {
    child: Child,
    lines: Receiver<String>,
    stderr: Option<std::process::ChildStderr>,
}

impl Peer {
    pub fn spawn(args: &[&str]) -> Peer {
        let mut child = Command::new(peer_binary())
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn protocol-peer");
        let stdout = child.stdout.take().expect("piped stdout");
        let stderr = child.stderr.take();
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Peer {
            child,
            lines,
            stderr,
        }
    }

    /// Spawns the agent role in `namespace` with `agent_id` and extra flags.
    pub fn agent(namespace: &str, agent_id: u32, extra: &[&str]) -> Peer {
        let id = agent_id.to_string();
        let mut args = vec!["agent", "--namespace", namespace, "--agent-id", &id];
        args.extend_from_slice(extra);
        Peer::spawn(&args)
    }

    /// Waits for a stdout line starting with `prefix`; returns it.
    pub fn expect_line(&self, prefix: &str) -> String {
        let deadline = Instant::now() + PEER_TIMEOUT;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) if line.starts_with(prefix) => return line,
                Ok(_) => continue,
                Err(RecvTimeoutError::Timeout) => {
                    panic!("peer printed no '{prefix}' line within {PEER_TIMEOUT:?}")
                }
                Err(RecvTimeoutError::Disconnected) => {
                    panic!("peer closed stdout before printing '{prefix}'")
                }
            }
        }
    }

    /// Waits for the process to exit; returns its status and stderr text.
    pub fn wait(&mut self) -> (ExitStatus, String) {
        let deadline = Instant::now() + PEER_TIMEOUT;
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                break status;
            }
            assert!(
                Instant::now() < deadline,
                "peer did not exit within {PEER_TIMEOUT:?}"
            );
            std::thread::sleep(EXIT_POLL);
        };
        let mut text = String::new();
        if let Some(mut stderr) = self.stderr.take() {
            let _ = stderr.read_to_string(&mut text);
        }
        (status, text)
    }

    /// SIGKILL (std's `Child::kill` sends SIGKILL on Unix) and reap.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            self.kill();
        }
    }
}
