//! The zenoh session of a bridge: peer mode, only the endpoints given on the command line (no
//! multicast scouting, so a bridge never reaches hosts it was not told about), links
//! authenticated both ways by TLS, and the QoS every relayed message travels with.
//!
//! Authentication ([`LinkSecurity::MutualTls`]): every link is TLS 1.3 with mutual
//! authentication against the swarm's own CA (`mac-bridge certs`). A listening bridge requires
//! the connecting bridge's certificate and accepts only one the swarm CA signed; a connecting
//! bridge checks the listening bridge's certificate and that it names the address of the
//! endpoint it dialled. A peer without such a certificate fails the handshake, so it never
//! joins the zenoh session: nothing it publishes reaches the swarm and it cannot subscribe to
//! anything. Plain TCP ([`LinkSecurity::InsecurePlainTcp`]) is only for an explicit request.
//!
//! Name verification stays on: zenoh's connecting side trusts the public web roots next to the
//! swarm CA, so without it any publicly certified server would pass.
//!
//! Zenoh's runtimes ([`ZENOH_RUNTIME_SETTING`]): a link's receive task runs on the thread of its
//! send task, so that one TLS connection is never read and written at the same instant.

use std::path::Path;

use anyhow::{Context, Result, bail};
use zenoh::Config;
use zenoh::qos::{CongestionControl, Priority};

use crate::certs::HostFiles;

/// Where a bridge listens and whom it connects to (zenoh endpoints such as
/// `tcp/192.168.1.10:7447`).
#[derive(Debug, Clone, Default)]
pub struct Endpoints {
    pub listen: Vec<String>,
    pub connect: Vec<String>,
}

/// Every relayed message crosses with:
/// - reliability `Reliable` (zenoh's default): a lost packet is re-sent by the link, never
///   skipped: receivers would see a sequence gap, and a lost keyframe is never acceptable
///   (across a broken link or a restarted bridge, `delivery` re-sends what was not
///   acknowledged);
/// - congestion control `Block`: when the network is slower than the agents, the bridge's put
///   waits instead of dropping; the wait reaches the agent through the iceoryx2 queues and
///   their full-queue policy, like a slow consumer on one host;
/// - one priority (`Data`) for every topic: zenoh keeps order only within a priority, and the
///   consumers rely on an agent's order (hello before data, final map before goodbye);
/// - zenoh's own fragmentation for large messages (a patch of a million Gaussians is 56 MB;
///   the link splits it into batches and the far side reassembles it before delivery), and no
///   link compression: Gaussian attributes and depth are floats and small integers that LZ4
///   barely shrinks, so compression would cost CPU on every byte for little gain.
pub const CONGESTION_CONTROL: CongestionControl = CongestionControl::Block;
pub const PRIORITY: Priority = Priority::Data;

/// Zenoh's runtime layout for a bridge (RON, read by zenoh from the `ZENOH_RUNTIME` environment
/// variable when its first runtime starts): the receive runtime is handed over to the
/// single-threaded send runtime.
///
/// Why: zenoh-link-tls (1.10.1) reads and writes one rustls connection from its receive and send
/// tasks through shared interior mutability, with no lock between the two. While a read decodes
/// records, rustls briefly marks the connection's state as failed ("handshake not complete"); a
/// write on another thread at that instant fails, and zenoh closes the link and opens a new
/// one, losing what was in flight. Under sustained two-way traffic (the IPC benchmark: 100k
/// patches one way, acknowledgements the other) this happened every few hundred milliseconds
/// after ~30 s. On one thread the two tasks interleave at their await points, where the
/// connection's state is whole. Plain TCP links are unaffected either way; the cost is one
/// thread for a host's network traffic (docs/benchmarks.md has the figures).
pub const ZENOH_RUNTIME_SETTING: &str = "(rx: (handover: tx), tx: (worker_threads: 1))";

/// Applies [`ZENOH_RUNTIME_SETTING`] unless the user set `ZENOH_RUNTIME`; returns the user's
/// value when it was kept (for a warning once logging is up). Must be called before any thread
/// starts (first thing in `main`): it changes the process environment.
pub fn configure_zenoh_runtime() -> Option<String> {
    if let Some(theirs) = std::env::var_os("ZENOH_RUNTIME") {
        return Some(theirs.to_string_lossy().into_owned());
    }
    // SAFETY: called at the start of `main`, before this process starts any thread, so no other
    // thread reads or writes the environment concurrently.
    unsafe { std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME_SETTING) };
    None
}

/// How a bridge's links are protected.
#[derive(Debug, Clone)]
pub enum LinkSecurity {
    /// TLS with mutual authentication: this host's files from `mac-bridge certs`. Endpoints
    /// are `tls/ADDRESS:PORT`.
    MutualTls(HostFiles),
    /// Plain TCP: anyone who reaches the port joins the swarm. Endpoints are
    /// `tcp/ADDRESS:PORT`.
    InsecurePlainTcp,
}

impl LinkSecurity {
    fn scheme(&self) -> &'static str {
        match self {
            Self::MutualTls(_) => "tls",
            Self::InsecurePlainTcp => "tcp",
        }
    }
}

impl Endpoints {
    /// Every endpoint uses the link `security` asks for, so a TLS bridge never also opens a
    /// plain port.
    pub fn check(&self, security: &LinkSecurity) -> Result<()> {
        let scheme = security.scheme();
        for endpoint in self.listen.iter().chain(&self.connect) {
            if endpoint.split_once('/').map(|(s, _)| s) != Some(scheme) {
                let hint = match security {
                    LinkSecurity::MutualTls(_) => {
                        "links are TLS with mutual authentication; plain TCP needs --insecure-plain-tcp"
                    }
                    LinkSecurity::InsecurePlainTcp => "--insecure-plain-tcp takes tcp/ endpoints",
                };
                bail!("endpoint '{endpoint}': expected {scheme}/ADDRESS:PORT ({hint})");
            }
        }
        Ok(())
    }
}

/// The zenoh configuration of a bridge.
pub fn config(endpoints: &Endpoints, security: &LinkSecurity) -> Result<Config> {
    endpoints.check(security)?;
    let mut config = Config::default();
    let set = |config: &mut Config, key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow::anyhow!("zenoh config {key} = {value}: {e}"))
    };
    set(&mut config, "mode", "\"peer\"".into())?;
    set(&mut config, "scouting/multicast/enabled", "false".into())?;
    set(
        &mut config,
        "listen/endpoints",
        serde_json::to_string(&endpoints.listen).context("listen endpoints")?,
    )?;
    set(
        &mut config,
        "connect/endpoints",
        serde_json::to_string(&endpoints.connect).context("connect endpoints")?,
    )?;
    // A bridge started before its peer keeps trying to connect instead of giving up.
    set(&mut config, "connect/exit_on_failure", "false".into())?;
    set(&mut config, "connect/timeout_ms", "-1".into())?;
    if let LinkSecurity::MutualTls(files) = security {
        let path = |path: &Path| -> Result<String> {
            std::fs::File::open(path).with_context(|| {
                format!(
                    "TLS file {} (make the swarm's files with `mac-bridge certs`)",
                    path.display()
                )
            })?;
            Ok(serde_json::to_string(&path.display().to_string())?)
        };
        let tls = "transport/link/tls";
        set(
            &mut config,
            &format!("{tls}/root_ca_certificate"),
            path(&files.ca_certificate)?,
        )?;
        for side in ["listen", "connect"] {
            set(
                &mut config,
                &format!("{tls}/{side}_certificate"),
                path(&files.certificate)?,
            )?;
            set(
                &mut config,
                &format!("{tls}/{side}_private_key"),
                path(&files.private_key)?,
            )?;
        }
        set(&mut config, &format!("{tls}/enable_mtls"), "true".into())?;
        set(
            &mut config,
            &format!("{tls}/verify_name_on_connect"),
            "true".into(),
        )?;
    }
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_must_match_the_link_security() {
        let tls = LinkSecurity::MutualTls(HostFiles::in_folder(Path::new("certs"), "agent0"));
        let endpoints = |listen: &str, connect: &str| Endpoints {
            listen: vec![listen.to_string()],
            connect: vec![connect.to_string()],
        };
        assert!(
            endpoints("tls/0.0.0.0:7447", "tls/10.0.0.1:7447")
                .check(&tls)
                .is_ok()
        );
        let plain = endpoints("tls/0.0.0.0:7447", "tcp/10.0.0.1:7447").check(&tls);
        assert!(format!("{:#}", plain.unwrap_err()).contains("--insecure-plain-tcp"));
        let insecure = LinkSecurity::InsecurePlainTcp;
        assert!(
            endpoints("tcp/0.0.0.0:7447", "tcp/10.0.0.1:7447")
                .check(&insecure)
                .is_ok()
        );
        assert!(
            endpoints("tls/0.0.0.0:7447", "tcp/10.0.0.1:7447")
                .check(&insecure)
                .is_err()
        );
    }

    #[test]
    fn missing_tls_files_are_named() {
        let tls = LinkSecurity::MutualTls(HostFiles::in_folder(Path::new("/nonexistent"), "a"));
        let endpoints = Endpoints {
            listen: vec!["tls/127.0.0.1:7447".into()],
            connect: Vec::new(),
        };
        let error = format!("{:#}", config(&endpoints, &tls).unwrap_err());
        assert!(error.contains("/nonexistent/ca.pem"), "{error}");
    }
}
