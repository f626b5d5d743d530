//! Helpers shared by the bridge's integration tests.
#![allow(dead_code)]

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
