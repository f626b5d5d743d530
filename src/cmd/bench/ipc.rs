//! `mac-ego3d bench ipc`: one-way latency and throughput of the agent -> consensus transport
//! between two processes, for a keyframe descriptor and for Gaussian patches of 10k and 100k
//! records, plus the measured copy count. The peer process is this binary re-executed with the
//! hidden `bench ipc-peer` subcommand.
//!
//! `--transport iceoryx2` (default): both processes on this host's shared memory.
//! `--transport zenoh` (root): the peer runs on a simulated host of its own
//! (scripts/simulated_host.sh: private /dev/shm and iceoryx2 root) with a consumer-role
//! mac-bridge; the driver's host gets an agent-role mac-bridge that listens on 127.0.0.1. The two
//! bridges talk zenoh over TLS with mutual authentication, as a swarm does by default (`--link
//! tls`, certificates made for the run with `mac-bridge certs`), or over plain TCP (`--link
//! tcp`, the bridges' `--insecure-plain-tcp`). Latencies then include both bridges, TLS and the
//! network stack, and the acknowledgements come back the same way.

use anyhow::Context;
use clap::{Args, ValueEnum};
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::Duration;

use protocol::bench::{IpcBenchConfig, PeerCommand, bench_transport_config, run_ipc_bench};
use protocol::transport::TransportConfig;

use crate::cmd::{fmt_num, print_json};

#[derive(Args)]
pub struct IpcArgs {
    /// Timed one-way samples per latency case.
    #[arg(long, default_value_t = 1000)]
    samples: usize,
    /// Untimed messages before each case.
    #[arg(long, default_value_t = 50)]
    warmup: usize,
    /// Patches per throughput case.
    #[arg(long, default_value_t = 500)]
    throughput_messages: usize,
    /// How long each receiver polls before it blocks on the wake-up event (0: block at once).
    #[arg(long, default_value_t = TransportConfig::default().poll_before_wait.as_micros() as u64)]
    poll_before_wait_us: u64,
    /// CPUs for the driver and the peer process, e.g. `0,1`, so the two never share a core and
    /// the figures do not depend on where the scheduler happens to put them. `none` leaves
    /// placement to the scheduler. Default: the first two CPUs this process may use.
    #[arg(long)]
    cpus: Option<String>,
    /// What carries the messages between the two processes.
    #[arg(long, value_enum, default_value_t = Transport::Iceoryx2)]
    transport: Transport,
    /// With `--transport zenoh`: how the two hosts' bridges are linked.
    #[arg(long, value_enum, default_value_t = Link::Tls)]
    link: Link,
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Transport {
    /// Shared memory on this host.
    Iceoryx2,
    /// Two simulated hosts joined by mac-bridge over zenoh (TCP on 127.0.0.1); needs root.
    Zenoh,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Link {
    /// TLS with mutual authentication (a swarm's default).
    Tls,
    /// Plain TCP without authentication.
    Tcp,
}

#[derive(Args)]
pub struct IpcPeerArgs {
    /// Service namespace chosen by the benchmark driver.
    #[arg(long)]
    namespace: String,
    /// Receivers' poll before blocking, as the driver was given it.
    #[arg(long)]
    poll_before_wait_us: u64,
}

pub fn run(args: &IpcArgs) -> anyhow::Result<()> {
    let config = IpcBenchConfig {
        latency_samples: args.samples,
        warmup: args.warmup,
        throughput_messages: args.throughput_messages,
        poll_before_wait: Duration::from_micros(args.poll_before_wait_us),
        cpus: parse_cpus(args.cpus.as_deref())?,
        ..IpcBenchConfig::default()
    };
    let program = std::env::current_exe().context("locating this executable to start the peer")?;
    let peer = PeerCommand {
        program,
        args: vec!["bench".into(), "ipc-peer".into()],
    };
    let report = match args.transport {
        Transport::Iceoryx2 => run_ipc_bench(&config, &peer).context("IPC benchmark")?,
        Transport::Zenoh => across_simulated_hosts(&config, peer, args.link)?,
    };
    let transport = match (args.transport, args.link) {
        (Transport::Iceoryx2, _) => "iceoryx2",
        (Transport::Zenoh, Link::Tls) => "zenoh over TLS",
        (Transport::Zenoh, Link::Tcp) => "zenoh over plain TCP",
    };
    if args.json {
        let mut json = serde_json::to_value(&report)?;
        json["transport"] = transport.into();
        return print_json(&json);
    }
    println!("transport: {transport}");
    let placement = match report.cpus {
        Some([driver, peer]) => format!("driver on CPU {driver}, peer on CPU {peer}"),
        None => "placed by the scheduler".to_string(),
    };
    println!(
        "IPC benchmark (one-way, {} samples per case after {} warm-up; receivers poll {} us \
         before blocking; {placement})",
        args.samples, args.warmup, args.poll_before_wait_us
    );
    println!(
        "  {:<30} {:>10} {:>10} {:>10} {:>16}",
        "message", "median us", "p99 us", "max us", "send call us"
    );
    let cases = [
        (
            "descriptor (1 KiB)",
            &report.descriptor,
            &report.descriptor_send_call,
        ),
        (
            "patch 10k (copied in)",
            &report.patch_10k,
            &report.patch_10k_send_call,
        ),
        (
            "patch 10k, peer idle before",
            &report.patch_10k_after_idle,
            &report.patch_10k_after_idle_send_call,
        ),
        (
            "patch 10k (built in place)",
            &report.patch_10k_in_place,
            &report.patch_10k_in_place_send_call,
        ),
        (
            "patch 100k (copied in)",
            &report.patch_100k,
            &report.patch_100k_send_call,
        ),
    ];
    for (name, s, call) in cases {
        println!(
            "  {:<30} {:>10} {:>10} {:>10} {:>16}",
            name,
            fmt_num(s.median_us, 1),
            fmt_num(s.p99_us, 1),
            fmt_num(s.max_us, 1),
            format!(
                "{} / {}",
                fmt_num(call.median_us, 1),
                fmt_num(call.p99_us, 1)
            )
        );
    }
    println!("  (send call: the driver's loan + write + send + notify alone, median / p99)");
    println!(
        "  throughput: patch 10k {} msg/s, patch 100k {} msg/s",
        fmt_num(report.patch_10k_msgs_per_s, 0),
        fmt_num(report.patch_100k_msgs_per_s, 0)
    );
    println!(
        "  copies per patch: {} copied in, {} built in place, {} at the consumer",
        fmt_num(report.copies_per_patch, 2),
        fmt_num(report.copies_per_patch_in_place, 2),
        fmt_num(report.receiver_copies_per_patch, 2)
    );
    Ok(())
}

/// Runs the benchmark with the peer on a simulated host of its own, the two hosts joined by
/// mac-bridge over zenoh on 127.0.0.1 (see the module documentation).
fn across_simulated_hosts(
    config: &IpcBenchConfig,
    peer: PeerCommand,
    link: Link,
) -> anyhow::Result<protocol::bench::IpcBenchReport> {
    let bridge = peer.program.with_file_name("mac-bridge");
    anyhow::ensure!(
        bridge.exists(),
        "{} is missing: build it first (cargo build -p mac-bridge, same profile)",
        bridge.display()
    );
    let host_script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/simulated_host.sh");
    // Both bridges must open the services exactly as the two benchmark processes do.
    let transport = bench_transport_config(&config.namespace, config.poll_before_wait);
    // The run's transport settings and certificates (with private keys): removed however the
    // benchmark ends.
    let scratch = RemoveOnDrop(std::env::temp_dir().join(format!("{}-hosts", config.namespace)));
    // A leftover of a killed run with the same process id would refuse new certificates.
    let _ = std::fs::remove_dir_all(&scratch.0);
    std::fs::create_dir_all(&scratch.0)
        .with_context(|| format!("creating {}", scratch.0.display()))?;
    let transport_file: PathBuf = scratch.0.join("transport.json");
    std::fs::write(&transport_file, serde_json::to_string(&transport)?)
        .with_context(|| format!("writing {}", transport_file.display()))?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let certificates = scratch.0.join("certs");
    let (endpoint, driver_security, peer_security) = match link {
        Link::Tcp => {
            let plain = vec!["--insecure-plain-tcp".to_string()];
            (format!("tcp/127.0.0.1:{port}"), plain.clone(), plain)
        }
        Link::Tls => {
            let made = Command::new(&bridge)
                .args(["certs", "--out"])
                .arg(&certificates)
                .args(["--host", "driver=127.0.0.1", "--host", "peer"])
                .env("RUST_LOG", "warn")
                .status()
                .with_context(|| format!("starting {} certs", bridge.display()))?;
            anyhow::ensure!(made.success(), "mac-bridge certs failed ({made})");
            let security = |host: &str| {
                vec![
                    "--certificates".to_string(),
                    certificates.display().to_string(),
                    "--host".to_string(),
                    host.to_string(),
                ]
            };
            (
                format!("tls/127.0.0.1:{port}"),
                security("driver"),
                security("peer"),
            )
        }
    };
    let bridge_args = |role: &str, security: &[String]| -> Vec<String> {
        [
            "--role",
            role,
            "--namespace",
            &config.namespace,
            "--agents",
            "1",
            "--transport-config",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([transport_file.display().to_string()])
        .chain(security.iter().cloned())
        .collect()
    };
    // The driver's host: this process and an agent-role bridge that listens.
    let driver_bridge = Command::new(&bridge)
        .args(bridge_args("agents", &driver_security))
        .args(["--local-agent", "0", "--listen", &endpoint])
        .env("RUST_LOG", "warn")
        .spawn()
        .with_context(|| format!("starting {}", bridge.display()))?;
    let driver_bridge = StopOnDrop(driver_bridge);
    // The peer's host: the peer and a consumer-role bridge that connects.
    let mut host_args = vec![
        "RUST_LOG=warn".to_string(),
        host_script.display().to_string(),
    ];
    host_args.push(bridge.display().to_string());
    host_args.extend(bridge_args("consumers", &peer_security));
    host_args.extend(["--connect".to_string(), endpoint, "--".to_string()]);
    host_args.push(peer.program.display().to_string());
    host_args.extend(peer.args);
    let peer = PeerCommand {
        program: PathBuf::from("env"),
        args: host_args,
    };
    let report = run_ipc_bench(config, &peer).context("IPC benchmark across simulated hosts");
    drop(driver_bridge);
    report
}

/// A folder removed with everything in it when the benchmark ends either way.
struct RemoveOnDrop(PathBuf);

impl Drop for RemoveOnDrop {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A bridge process, stopped (SIGTERM, then waited for) when the benchmark ends either way.
struct StopOnDrop(Child);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.0.id().to_string()])
            .status();
        let _ = self.0.wait();
    }
}

/// The benchmark's peer process (consumer side).
pub fn run_peer(args: &IpcPeerArgs) -> anyhow::Result<()> {
    protocol::bench::run_peer(
        &args.namespace,
        Duration::from_micros(args.poll_before_wait_us),
    )
    .context("IPC benchmark peer")
}

/// `--cpus`: `none`, `A,B`, or absent (the first two CPUs this process may use, when there are
/// two).
fn parse_cpus(arg: Option<&str>) -> anyhow::Result<Option<[usize; 2]>> {
    match arg {
        Some("none") => Ok(None),
        Some(list) => {
            let cpus: Vec<usize> = list
                .split(',')
                .map(|c| c.trim().parse::<usize>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("--cpus '{list}': expected two CPU numbers like 0,1"))?;
            match cpus[..] {
                [driver, peer] if driver != peer => Ok(Some([driver, peer])),
                _ => anyhow::bail!("--cpus '{list}': expected two different CPU numbers like 0,1"),
            }
        }
        None => Ok(protocol::bench::first_two_cpus()),
    }
}
