//! `mac-ego3d bench ipc`: one-way latency and throughput of the agent -> consensus transport
//! (iceoryx2 shared memory) between two processes, for a keyframe descriptor and for Gaussian
//! patches of 10k and 100k records, plus the measured copy count. The peer process is this
//! binary re-executed with the hidden `bench ipc-peer` subcommand.

use anyhow::Context;
use clap::Args;
use std::time::Duration;

use protocol::bench::{IpcBenchConfig, PeerCommand, run_ipc_bench};
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
    #[arg(long)]
    json: bool,
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
    let report = run_ipc_bench(&config, &peer).context("IPC benchmark")?;
    if args.json {
        return print_json(&report);
    }
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
