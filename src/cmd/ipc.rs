//! `mac-ego3d bench ipc`: one-way latency and throughput of the agent -> consensus transport
//! (iceoryx2 shared memory) between two processes, for a keyframe descriptor and for Gaussian
//! patches of 10k and 100k records, plus the measured copy count. The peer process is this
//! binary re-executed with the hidden `bench ipc-peer` subcommand.

use anyhow::Context;
use clap::Args;
use protocol::bench::{IpcBenchConfig, PeerCommand, run_ipc_bench};

use super::{fmt_num, print_json};

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
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct IpcPeerArgs {
    /// Service namespace chosen by the benchmark driver.
    #[arg(long)]
    namespace: String,
}

pub fn run(args: &IpcArgs) -> anyhow::Result<()> {
    let config = IpcBenchConfig {
        latency_samples: args.samples,
        warmup: args.warmup,
        throughput_messages: args.throughput_messages,
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
    println!(
        "IPC benchmark (one-way, {} samples per case after {} warm-up)",
        args.samples, args.warmup
    );
    println!(
        "  {:<34} {:>12} {:>12} {:>12}",
        "message", "median us", "p99 us", "max us"
    );
    let cases = [
        ("descriptor (1 KiB)", &report.descriptor),
        ("patch 10k (copied in)", &report.patch_10k),
        ("patch 10k (built in place)", &report.patch_10k_in_place),
        ("patch 100k (copied in)", &report.patch_100k),
    ];
    for (name, s) in cases {
        println!(
            "  {:<34} {:>12} {:>12} {:>12}",
            name,
            fmt_num(s.median_us, 1),
            fmt_num(s.p99_us, 1),
            fmt_num(s.max_us, 1)
        );
    }
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
    protocol::bench::run_peer(&args.namespace).context("IPC benchmark peer")
}
