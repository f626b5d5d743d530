//! `mac-ego3d bench tracking`: G-ICP odometry over a dataset from the identity pose, timed per
//! frame (points, covariances, alignment and map update; image decoding is excluded), with the
//! trajectory's ATE against ground truth. `--dump-points` also writes the frames' points so an
//! outside tracker can run on exactly the same input (scripts/bench_vs_small_gicp.sh).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use config::Config;
use datasets::{self, FrameRange};
use geometry::trajectory::Trajectory;
use metrics::ate::{Alignment, DEFAULT_MAX_DT, ate};
use metrics::stats::{median, quantile};
use nalgebra::Point3;
use registration::{FrameInput, Odometry, OdometryMode, TrackingOutcome};
use serde::Serialize;

use crate::cmd::{fmt_num, print_json};

#[derive(Args)]
pub struct TrackingArgs {
    /// Dataset folder or synthetic spec. Default: the shared redkitchen frames.
    #[arg(long)]
    dataset: Option<String>,
    /// Frames to track, FIRST..END (END excluded). The default is the benchmark range.
    #[arg(long, default_value = "0..300")]
    frames: FrameRange,
    /// Align each frame to the previous one, or to the map of keyframe points.
    #[arg(long, default_value_t = OdometryMode::FrameToModel)]
    mode: OdometryMode,
    /// Configuration file (its [tracking] and [keyframes] sections). Default: the built-in defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Write the estimated trajectory here (TUM format).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write each tracked frame's points, as the tracker back-projected them (pixel stride,
    /// truncation, intrinsics applied), to this folder: DIR/points-NNNNNN.f32 (x y z per point,
    /// little-endian f32, camera frame, metres; NNNNNN is the frame number) and DIR/frames.tsv
    /// (timestamp and file name per frame, in tracking order). Written after each frame's timing;
    /// the file writes still disturb the caches, so time with a run without it.
    #[arg(long)]
    dump_points: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

/// Writes frames' points for `--dump-points`: one raw f32 file per frame plus an index.
struct PointDump {
    dir: PathBuf,
    index: std::io::BufWriter<std::fs::File>,
}

impl PointDump {
    const INDEX: &str = "frames.tsv";

    fn create(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(Self::INDEX);
        let mut index = std::io::BufWriter::new(
            std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?,
        );
        writeln!(
            index,
            "# timestamp\tpoints file (x y z little-endian f32, camera frame, m)"
        )
        .with_context(|| format!("writing {}", path.display()))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            index,
        })
    }

    fn write(
        &mut self,
        frame_index: usize,
        timestamp: f64,
        points: &[Point3<f32>],
    ) -> anyhow::Result<()> {
        let name = format!("points-{frame_index:06}.f32");
        let path = self.dir.join(&name);
        let bytes: Vec<u8> = points
            .iter()
            .flat_map(|p| [p.x, p.y, p.z])
            .flat_map(f32::to_le_bytes)
            .collect();
        std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        // The timestamp as the TUM writer prints it, so trajectories match the ground truth.
        writeln!(self.index, "{timestamp:.6}\t{name}")
            .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }

    fn finish(mut self) -> anyhow::Result<()> {
        self.index
            .flush()
            .with_context(|| format!("writing {}", self.dir.join(Self::INDEX).display()))
    }
}

#[derive(Serialize)]
struct TrackingReport {
    dataset: String,
    mode: String,
    threads: usize,
    frames: usize,
    points_per_frame: f64,
    tracking_ms_median: f64,
    tracking_ms_p90: f64,
    tracking_ms_max: f64,
    /// Medians of the stages: points + covariances, registration, map update.
    points_ms_median: f64,
    registration_ms_median: f64,
    map_update_ms_median: f64,
    iterations_median: f64,
    /// SE(3)-aligned against ground truth; `null` without ground truth.
    ate_rmse_m: Option<f64>,
    ate_mean_m: Option<f64>,
    failures: usize,
    not_converged: usize,
    reinitialisations: usize,
    /// Frames whose G-ICP started from the previous pose (`OdometryStats::still_starts`).
    still_starts: usize,
    keyframes: usize,
    map_points: usize,
}

pub fn run(args: &TrackingArgs) -> anyhow::Result<()> {
    let spec = args.dataset.clone().unwrap_or_else(|| {
        datasets::shared_data::shared_dir()
            .join("datasets/7scenes-redkitchen")
            .to_string_lossy()
            .into_owned()
    });
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let ds = datasets::open_with(&spec, args.frames, config.camera.distortion())
        .with_context(|| format!("opening {spec}"))?;
    anyhow::ensure!(!ds.is_empty(), "{spec}: no frames in {}", args.frames);
    let mut odometry = Odometry::new(args.mode, &config.tracking, &config.keyframes);
    let mut estimate = Trajectory::default();
    let mut ground_truth = Trajectory::default();
    let mut times_ms = Vec::with_capacity(ds.len());
    let mut iterations = Vec::with_capacity(ds.len());
    let mut stage_ms: [Vec<f64>; 3] = Default::default();
    let mut points = 0usize;
    let mut dump = args
        .dump_points
        .as_deref()
        .map(PointDump::create)
        .transpose()?;
    for position in 0..ds.len() {
        let frame = match ds.load(position) {
            Ok(frame) => frame,
            Err(e) if e.is_missing_frame() => {
                tracing::warn!("{e}; skipped");
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        let start = Instant::now();
        let tracked = odometry.track(FrameInput {
            timestamp_s: frame.timestamp,
            depth: &frame.depth,
            rgb: Some(&frame.rgb),
            intrinsics: &frame.intrinsics,
        });
        let elapsed_ms = start.elapsed().as_secs_f64() * 1e3;
        // The first frame only seeds the target; timing it would mix set-up into tracking.
        if tracked.outcome != TrackingOutcome::Initialised {
            times_ms.push(elapsed_ms);
            stage_ms[0].push(tracked.timings.points_ms);
            stage_ms[1].push(tracked.timings.registration_ms);
            stage_ms[2].push(tracked.timings.map_update_ms);
        }
        if let Some(registration) = &tracked.registration {
            iterations.push(registration.iterations as f64);
        }
        points += tracked.points;
        if let Some(dump) = dump.as_mut() {
            dump.write(
                frame.index,
                frame.timestamp,
                &tracked.frame_points.positions,
            )?;
        }
        estimate.push(frame.timestamp, tracked.world_from_camera);
        if let Some(gt) = frame.world_from_camera_gt {
            ground_truth.push(frame.timestamp, gt);
        }
    }
    if let Some(dump) = dump {
        dump.finish()?;
    }
    if let Some(out) = &args.out {
        estimate
            .write_tum(out)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    let ate_stats = if ground_truth.len() >= 3 {
        Some(ate(&ground_truth, &estimate, Alignment::Se3, DEFAULT_MAX_DT)?.stats)
    } else {
        tracing::warn!("{spec}: no ground truth, ATE not computed");
        None
    };
    // An empty run has no timings: NaN prints as such in the table and as null in the JSON.
    let median_or_nan = |values: &[f64]| median(values).unwrap_or(f64::NAN);
    let stats = odometry.stats();
    let report = TrackingReport {
        dataset: ds.describe(),
        mode: args.mode.to_string(),
        threads: registration::worker_threads(),
        frames: estimate.len(),
        points_per_frame: points as f64 / estimate.len().max(1) as f64,
        tracking_ms_median: median_or_nan(&times_ms),
        tracking_ms_p90: quantile(&times_ms, 0.9).unwrap_or(f64::NAN),
        tracking_ms_max: quantile(&times_ms, 1.0).unwrap_or(f64::NAN),
        points_ms_median: median_or_nan(&stage_ms[0]),
        registration_ms_median: median_or_nan(&stage_ms[1]),
        map_update_ms_median: median_or_nan(&stage_ms[2]),
        iterations_median: median_or_nan(&iterations),
        ate_rmse_m: ate_stats.map(|s| s.rmse),
        ate_mean_m: ate_stats.map(|s| s.mean),
        failures: stats.failures,
        not_converged: stats.not_converged,
        reinitialisations: stats.segments_started,
        still_starts: stats.still_starts,
        keyframes: stats.keyframes,
        map_points: odometry.map().len(),
    };
    if args.json {
        return print_json(&report);
    }
    let cm = |m: Option<f64>| m.map_or("n/a".to_string(), |m| fmt_num(m * 100.0, 2));
    println!(
        "G-ICP tracking ({}, {} threads): {}",
        report.mode, report.threads, report.dataset
    );
    let rows: [(&str, String); 17] = [
        ("frames", report.frames.to_string()),
        ("points per frame", fmt_num(report.points_per_frame, 0)),
        ("tracking ms, median", fmt_num(report.tracking_ms_median, 2)),
        ("tracking ms, p90", fmt_num(report.tracking_ms_p90, 2)),
        ("tracking ms, max", fmt_num(report.tracking_ms_max, 2)),
        (
            "  points + covariances ms, median",
            fmt_num(report.points_ms_median, 2),
        ),
        (
            "  registration ms, median",
            fmt_num(report.registration_ms_median, 2),
        ),
        (
            "  map update ms, median",
            fmt_num(report.map_update_ms_median, 2),
        ),
        (
            "G-ICP iterations, median",
            fmt_num(report.iterations_median, 1),
        ),
        ("ATE RMSE cm (SE(3)-aligned)", cm(report.ate_rmse_m)),
        ("ATE mean cm", cm(report.ate_mean_m)),
        ("failures", report.failures.to_string()),
        ("not converged", report.not_converged.to_string()),
        ("re-initialisations", report.reinitialisations.to_string()),
        (
            "started from the previous pose",
            report.still_starts.to_string(),
        ),
        ("keyframes", report.keyframes.to_string()),
        ("map points", report.map_points.to_string()),
    ];
    for (name, value) in rows {
        println!("  {name:<32} {value:>10}");
    }
    Ok(())
}
