//! `mac-ego3d bench ...`: throughput and timing benchmarks. Each prints a table, or one JSON
//! object with `--json`. Figures are wall-clock on the machine it runs on. `bench tracking` and
//! `bench merge` also write their headline figures for docs/benchmarks.md with `--figures`
//! ([`figures`]); `bench record-figures` writes those of the peer-comparison scripts.

use std::sync::Arc;
use std::time::Instant;

use alexnet::lpips::Lpips;
use anyhow::Context;
use clap::{Args, Subcommand};
use datasets::{self, Dataset, FrameRange, prefetch::Prefetcher};
use geometry::trajectory::Trajectory;
use metrics::ate::{Alignment, DEFAULT_MAX_DT, ate};
use metrics::depth::depth_l1_cm;
use metrics::image::image_quality;
use nalgebra::{Isometry3, Translation3};
use serde::Serialize;

use super::{fmt_num, print_json};

mod figures;
mod ipc;
mod map_registration;
mod merge;
mod render;
mod tracking;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Frame reader throughput: sequential decoding and the prefetching source.
    Readers(ReadersArgs),
    /// Timings of the evaluation metrics on frames of a dataset.
    Metrics(MetricsArgs),
    /// Timings of the Gaussian-splat renderer (forward, backward, optimisation iteration).
    Render(render::BenchRenderArgs),
    /// G-ICP odometry: per-frame tracking time and ATE.
    Tracking(tracking::TrackingArgs),
    /// Global registration of two agents' maps without an initial guess, against ground truth.
    MapRegistration(map_registration::MapRegistrationArgs),
    /// A swarm run's merged map against each agent's own map, on held-out and on all frames.
    Merge(merge::MergeArgs),
    /// Latency and throughput of the agent <-> consensus IPC transport between two processes.
    Ipc(ipc::IpcArgs),
    /// Peer process of `bench ipc` (started by it).
    #[command(hide = true)]
    IpcPeer(ipc::IpcPeerArgs),
    /// Write the headline figures a script measured into a docs/figures file (as the benches'
    /// own --figures do): the peer comparisons in shell and Python call it.
    RecordFigures(figures::RecordFiguresArgs),
}

#[derive(Args)]
pub struct ReadersArgs {
    /// Dataset folder or synthetic spec. Default: the shared redkitchen frames.
    #[arg(long)]
    dataset: Option<String>,
    #[arg(long, default_value = "0..200")]
    frames: FrameRange,
    /// Decoding threads of the prefetching source.
    #[arg(long, default_value_t = 2)]
    workers: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct MetricsArgs {
    /// Dataset folder or synthetic spec. Default: the shared redkitchen frames.
    #[arg(long)]
    dataset: Option<String>,
    /// Repetitions per timed metric (the median is reported).
    #[arg(long, default_value_t = 5)]
    repeats: usize,
    /// LPIPS weights (default: $MAC_EGO3D_WEIGHTS, else the cache scripts/setup.sh fills;
    /// skipped if missing).
    #[arg(long)]
    weights: Option<std::path::PathBuf>,
    #[arg(long)]
    json: bool,
}

fn default_dataset(given: &Option<String>) -> String {
    given.clone().unwrap_or_else(|| {
        datasets::shared_data::shared_dir()
            .join("datasets/7scenes-redkitchen")
            .to_string_lossy()
            .into_owned()
    })
}

#[derive(Serialize)]
struct ReadersReport {
    dataset: String,
    frames: usize,
    width: u32,
    height: u32,
    sequential_fps: f64,
    prefetch_fps: f64,
    prefetch_workers: usize,
}

fn run_readers(args: &ReadersArgs) -> anyhow::Result<()> {
    let spec = default_dataset(&args.dataset);
    let ds: Arc<dyn Dataset> =
        Arc::from(datasets::open(&spec, args.frames).with_context(|| format!("opening {spec}"))?);
    let n = ds.len();
    // Warm the page cache once so both runs measure decoding, not the first disk read.
    for i in 0..n {
        ds.load(i)?;
    }
    let start = Instant::now();
    for i in 0..n {
        ds.load(i)?;
    }
    let sequential_fps = n as f64 / start.elapsed().as_secs_f64();
    let start = Instant::now();
    for (_, frame) in Prefetcher::new(Arc::clone(&ds), args.workers, 4) {
        frame?;
    }
    let prefetch_fps = n as f64 / start.elapsed().as_secs_f64();
    let k = ds.intrinsics();
    let report = ReadersReport {
        dataset: ds.describe(),
        frames: n,
        width: k.width,
        height: k.height,
        sequential_fps,
        prefetch_fps,
        prefetch_workers: args.workers,
    };
    if args.json {
        return print_json(&report);
    }
    println!(
        "reader throughput: {} ({} frames, {}x{})",
        report.dataset, n, k.width, k.height
    );
    println!("  {:<34} {:>10}", "source", "frames/s");
    println!(
        "  {:<34} {:>10}",
        "sequential decode (1 thread)",
        fmt_num(sequential_fps, 1)
    );
    println!(
        "  {:<34} {:>10}",
        format!("prefetching source ({} workers)", args.workers),
        fmt_num(prefetch_fps, 1)
    );
    Ok(())
}

/// Median wall time of `repeats` runs of `f`, milliseconds.
fn time_ms(repeats: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<f64> {
    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        f()?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

#[derive(Serialize)]
struct MetricsReport {
    dataset: String,
    width: u32,
    height: u32,
    trajectory_poses: usize,
    ate_ms: f64,
    psnr_ssim_ms: f64,
    depth_l1_ms: f64,
    lpips_ms: Option<f64>,
}

fn run_metrics(args: &MetricsArgs) -> anyhow::Result<()> {
    let spec = default_dataset(&args.dataset);
    let ds = datasets::open(&spec, FrameRange::ALL).with_context(|| format!("opening {spec}"))?;
    let a = ds.load(0)?;
    let b = ds.load(ds.len().min(11) - 1)?;
    // ATE of the ground truth against a perturbed copy of itself: a realistic pair count.
    let mut gt = Trajectory::default();
    for i in 0..ds.len() {
        if let Some(p) = ds.ground_truth(i)? {
            gt.push(ds.timestamp(i), p);
        }
    }
    anyhow::ensure!(
        gt.len() >= 3,
        "{spec}: needs ground-truth poses to time ATE"
    );
    let est = Trajectory::from_pairs(gt.stamps.iter().zip(&gt.poses).enumerate().map(
        |(i, (t, p))| {
            let wobble = 0.01 * (i as f64 * 0.37).sin();
            (
                *t,
                Isometry3::from_parts(Translation3::new(wobble, -wobble, 0.0), Default::default())
                    * p,
            )
        },
    ));
    let ate_ms = time_ms(args.repeats, || {
        Ok(ate(&gt, &est, Alignment::Se3, DEFAULT_MAX_DT).map(|_| ())?)
    })?;
    let psnr_ssim_ms = time_ms(args.repeats, || {
        Ok(image_quality(&a.rgb, &b.rgb).map(|_| ())?)
    })?;
    let depth_l1_ms = time_ms(args.repeats, || {
        Ok(depth_l1_cm(&a.depth, &b.depth).map(|_| ())?)
    })?;
    let weights = match &args.weights {
        Some(path) if path.is_file() => Ok(path.clone()),
        Some(path) => Err(format!(
            "no weights at {} (scripts/get_lpips_weights.sh)",
            path.display()
        )),
        None => alexnet::weights::resolve_default().map_err(|missing| missing.to_string()),
    };
    let lpips_ms = match weights {
        Ok(weights) => {
            let lpips = Lpips::load(&weights)?;
            Some(time_ms(args.repeats, || {
                Ok(lpips.distance(&a.rgb, &b.rgb).map(|_| ())?)
            })?)
        }
        Err(why) => {
            eprintln!("LPIPS skipped: {why}");
            None
        }
    };
    let k = ds.intrinsics();
    let report = MetricsReport {
        dataset: ds.describe(),
        width: k.width,
        height: k.height,
        trajectory_poses: gt.len(),
        ate_ms,
        psnr_ssim_ms,
        depth_l1_ms,
        lpips_ms,
    };
    if args.json {
        return print_json(&report);
    }
    println!(
        "metric timings (median of {} runs): {}",
        args.repeats, report.dataset
    );
    println!("  {:<40} {:>10}", "metric", "ms");
    println!(
        "  {:<40} {:>10}",
        format!("ATE, {} poses, SE(3) alignment", gt.len()),
        fmt_num(ate_ms, 3)
    );
    println!(
        "  {:<40} {:>10}",
        format!("PSNR + SSIM (both), {}x{}", k.width, k.height),
        fmt_num(psnr_ssim_ms, 3)
    );
    println!(
        "  {:<40} {:>10}",
        format!("depth L1, {}x{}", k.width, k.height),
        fmt_num(depth_l1_ms, 3)
    );
    match lpips_ms {
        Some(ms) => println!(
            "  {:<40} {:>10}",
            format!("LPIPS AlexNet, {}x{}", k.width, k.height),
            fmt_num(ms, 3)
        ),
        None => println!("  {:<40} {:>10}", "LPIPS AlexNet", "skipped"),
    }
    Ok(())
}

pub fn run(command: &BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Readers(a) => run_readers(a),
        BenchCommand::Metrics(a) => run_metrics(a),
        BenchCommand::Render(a) => render::run_bench(a),
        BenchCommand::Tracking(a) => tracking::run(a),
        BenchCommand::MapRegistration(a) => map_registration::run(a),
        BenchCommand::Merge(a) => merge::run(a),
        BenchCommand::Ipc(a) => ipc::run(a),
        BenchCommand::IpcPeer(a) => ipc::run_peer(a),
        BenchCommand::RecordFigures(a) => figures::run_record(a),
    }
}
