//! `mac-ego3d bench tracking`: the odometry over a dataset from the identity pose, timed per
//! frame (points, covariances, alignment, recovery and map update; image decoding is excluded),
//! with the trajectory's ATE against ground truth and what the tracker reported: frames lost,
//! divergences detected, recoveries, segments started and joined. `--dump-points` and
//! `--dump-images` also write the frames as the tracker saw them so outside trackers can run on
//! exactly the same input (scripts/bench_vs_small_gicp.sh), `--frames-csv` every frame's outcome.

mod dump;

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use config::Config;
use datasets::{self, FrameRange};
use geometry::trajectory::Trajectory;
use metrics::ate::{Alignment, DEFAULT_MAX_DT, ate};
use metrics::stats::{median, quantile};
use nalgebra::Isometry3;
use registration::{FrameInput, Odometry, OdometryMode, Placement, TrackingOutcome};
use serde::Serialize;

use super::figures::{Figure, FigureArgs};
use crate::cmd::{fmt_num, print_json};
use dump::{ImageDump, PointDump};

#[derive(Args)]
pub struct TrackingArgs {
    /// Dataset folder or synthetic spec, optionally with its frames (`DIR:0..1000:10`).
    /// Default: the shared redkitchen frames.
    #[arg(long)]
    dataset: Option<String>,
    /// Frames to track, FIRST..END (END excluded), optionally :STEP for every STEP-th frame.
    /// The default is the benchmark range.
    #[arg(long, default_value = "0..300")]
    frames: FrameRange,
    /// Align each frame to the previous one, or to the map of keyframe points.
    #[arg(long, default_value_t = OdometryMode::FrameToModel)]
    mode: OdometryMode,
    /// Configuration file (its [tracking], [keyframes] and [camera] sections). Default: the
    /// built-in defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Write the estimated trajectory here (TUM format): the frames placed in the first
    /// segment's frame (segments joined to it included; lost frames left out).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write every frame's outcome here (CSV: timestamp, segment, placed, outcome, confidence).
    #[arg(long)]
    frames_csv: Option<PathBuf>,
    /// Also write each tracked frame's points, as the tracker back-projected them (pixel stride,
    /// truncation, intrinsics applied), to this folder: DIR/points-NNNNNN.f32 (x y z per point,
    /// little-endian f32, camera frame, metres; NNNNNN is the frame number) and DIR/frames.tsv
    /// (timestamp and file name per frame, in tracking order). Written after each frame's timing;
    /// the file writes still disturb the caches, so time with a run without it.
    #[arg(long)]
    dump_points: Option<PathBuf>,
    /// Also write each frame's images as the tracker saw them (undistorted where the dataset
    /// is): DIR/rgb-NNNNNN.png, DIR/depth-NNNNNN.png (u16 millimetres), DIR/intrinsics.json and
    /// DIR/frames.tsv. The same caveat on timings as --dump-points.
    #[arg(long)]
    dump_images: Option<PathBuf>,
    /// Track only these frame positions (of the opened frames), in the order given: a file with
    /// one per line, or a CSV whose header names a `frame_position` column (an agent's
    /// tracking.csv), so a sensor-pace run's frames, drops included, replay frame by frame.
    #[arg(long)]
    positions: Option<PathBuf>,
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    figures: FigureArgs,
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
    /// Medians of the stages: points + covariances, registration, recovery, map update.
    points_ms_median: f64,
    registration_ms_median: f64,
    recovery_ms_median: f64,
    map_update_ms_median: f64,
    iterations_median: f64,
    /// SE(3)-aligned against ground truth over the frames placed in the first segment's frame;
    /// `null` without ground truth.
    ate_rmse_m: Option<f64>,
    ate_mean_m: Option<f64>,
    /// The same with the lost frames at the pose they kept (the constant-velocity prediction).
    ate_rmse_with_lost_m: Option<f64>,
    /// Frames in the trajectory (placed in the first segment's frame).
    frames_placed: usize,
    /// Frames no guess placed (pose = prediction).
    failures: usize,
    /// Frames whose ordinary G-ICP result the check refused.
    divergences: usize,
    /// Frames placed by a wide-baseline guess.
    recoveries: usize,
    not_converged: usize,
    segments_started: usize,
    segments_joined: usize,
    /// Frames of segments never joined (not in the trajectory).
    frames_unjoined: usize,
    /// Median per-frame confidence (the check's depth agreement) over placed frames.
    confidence_median: Option<f64>,
    /// Frames whose ordinary G-ICP started from the previous pose (`OdometryStats::still_starts`).
    still_starts: usize,
    keyframes: usize,
    map_points: usize,
}

/// One frame's result as the report and --frames-csv need it.
struct FrameRecord {
    timestamp: f64,
    world_from_camera: Isometry3<f64>,
    placement: Placement,
    outcome: String,
    placed: bool,
    confidence: f64,
    ground_truth: Option<Isometry3<f64>>,
}

pub fn run(args: &TrackingArgs) -> anyhow::Result<()> {
    let spec: datasets::DatasetSpec = match &args.dataset {
        Some(text) => text
            .parse()
            .map_err(|e| anyhow::anyhow!("--dataset: {e}"))?,
        None => datasets::DatasetSpec {
            dataset: datasets::shared_data::shared_dir()
                .join("datasets/7scenes-redkitchen")
                .to_string_lossy()
                .into_owned(),
            frames: FrameRange::ALL,
        },
    };
    let frames = if spec.frames == FrameRange::ALL {
        args.frames
    } else {
        spec.frames
    };
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let name = &spec.dataset;
    let ds = datasets::open_with(name, frames, &config.dataset_options())
        .with_context(|| format!("opening {name}"))?;
    anyhow::ensure!(!ds.is_empty(), "{name}: no frames in {frames}");
    let mut odometry = Odometry::new(args.mode, &config.tracking, &config.keyframes);
    let mut records: Vec<FrameRecord> = Vec::with_capacity(ds.len());
    let mut times_ms = Vec::with_capacity(ds.len());
    let mut iterations = Vec::with_capacity(ds.len());
    let mut stage_ms: [Vec<f64>; 4] = Default::default();
    let mut points = 0usize;
    let mut point_dump = args
        .dump_points
        .as_deref()
        .map(PointDump::create)
        .transpose()?;
    let mut image_dump = args
        .dump_images
        .as_deref()
        .map(ImageDump::create)
        .transpose()?;
    let positions = match &args.positions {
        Some(path) => read_positions(path, ds.len())?,
        None => (0..ds.len()).collect(),
    };
    for (index, position) in positions.into_iter().enumerate() {
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
            colour_offset_s: frame.colour_offset_s,
            real_time: false,
        });
        let elapsed_ms = start.elapsed().as_secs_f64() * 1e3;
        // The first frame only seeds the target; timing it would mix set-up into tracking.
        if index > 0 {
            times_ms.push(elapsed_ms);
            let t = &tracked.timings;
            for (stage, ms) in stage_ms.iter_mut().zip([
                t.points_ms,
                t.registration_ms,
                t.recovery_ms,
                t.map_update_ms,
            ]) {
                stage.push(ms);
            }
        }
        if let Some(registration) = &tracked.registration {
            iterations.push(registration.iterations as f64);
        }
        points += tracked.points;
        if let Some(join) = &tracked.join {
            for record in &mut records {
                if let Some((placement, moved)) =
                    join.moved(record.placement, &record.world_from_camera)
                {
                    record.placement = placement;
                    record.world_from_camera = moved;
                }
            }
        }
        records.push(FrameRecord {
            timestamp: frame.timestamp,
            world_from_camera: tracked.world_from_camera,
            placement: tracked.placement,
            outcome: outcome_label(&tracked.outcome),
            placed: !matches!(tracked.outcome, TrackingOutcome::Lost(_)),
            confidence: tracked.confidence(),
            ground_truth: frame.world_from_camera_gt,
        });
        if let Some(dump) = point_dump.as_mut() {
            dump.write(
                frame.index,
                frame.timestamp,
                &tracked.frame_points.positions,
            )?;
        }
        if let Some(dump) = image_dump.as_mut() {
            dump.write(&frame)?;
        }
    }
    if let Some(dump) = point_dump {
        dump.finish()?;
    }
    if let Some(dump) = image_dump {
        dump.finish()?;
    }
    let in_root = |r: &&FrameRecord| r.placement == Placement::Root;
    let placed = |r: &&FrameRecord| in_root(r) && r.placed;
    let estimate = Trajectory::from_pairs(
        records
            .iter()
            .filter(placed)
            .map(|r| (r.timestamp, r.world_from_camera)),
    );
    let with_lost = Trajectory::from_pairs(
        records
            .iter()
            .filter(in_root)
            .map(|r| (r.timestamp, r.world_from_camera)),
    );
    let ground_truth = Trajectory::from_pairs(
        records
            .iter()
            .filter(in_root)
            .filter_map(|r| Some((r.timestamp, r.ground_truth?))),
    );
    if let Some(out) = &args.out {
        estimate
            .write_tum(out)
            .with_context(|| format!("writing {}", out.display()))?;
    }
    if let Some(path) = &args.frames_csv {
        write_frames_csv(path, &records)?;
    }
    let (ate_stats, ate_with_lost) = if ground_truth.len() >= 3 && estimate.len() >= 3 {
        (
            Some(ate(&ground_truth, &estimate, Alignment::Se3, DEFAULT_MAX_DT)?.stats),
            Some(ate(&ground_truth, &with_lost, Alignment::Se3, DEFAULT_MAX_DT)?.stats),
        )
    } else {
        tracing::warn!("{name}: no ground truth, ATE not computed");
        (None, None)
    };
    // An empty run has no timings: NaN prints as such in the table and as null in the JSON.
    let median_or_nan = |values: &[f64]| median(values).unwrap_or(f64::NAN);
    let stats = odometry.stats();
    let confidences: Vec<f64> = records
        .iter()
        .filter(|r| r.placed)
        .map(|r| r.confidence)
        .collect();
    let report = TrackingReport {
        dataset: ds.describe(),
        mode: args.mode.to_string(),
        threads: registration::worker_threads(),
        frames: records.len(),
        points_per_frame: points as f64 / records.len().max(1) as f64,
        tracking_ms_median: median_or_nan(&times_ms),
        tracking_ms_p90: quantile(&times_ms, 0.9).unwrap_or(f64::NAN),
        tracking_ms_max: quantile(&times_ms, 1.0).unwrap_or(f64::NAN),
        points_ms_median: median_or_nan(&stage_ms[0]),
        registration_ms_median: median_or_nan(&stage_ms[1]),
        recovery_ms_median: median_or_nan(&stage_ms[2]),
        map_update_ms_median: median_or_nan(&stage_ms[3]),
        iterations_median: median_or_nan(&iterations),
        ate_rmse_m: ate_stats.map(|s| s.rmse),
        ate_mean_m: ate_stats.map(|s| s.mean),
        ate_rmse_with_lost_m: ate_with_lost.map(|s| s.rmse),
        frames_placed: estimate.len(),
        failures: stats.failures,
        divergences: stats.divergences,
        recoveries: stats.recoveries,
        not_converged: stats.not_converged,
        segments_started: stats.segments_started,
        segments_joined: stats.segments_joined,
        frames_unjoined: records.iter().filter(|r| !in_root(r)).count(),
        confidence_median: median(&confidences),
        still_starts: stats.still_starts,
        keyframes: stats.keyframes,
        map_points: odometry.map().len(),
    };
    // The dataset's folder name (or synthetic spec), not its long description.
    let short_name = std::path::Path::new(name)
        .file_name()
        .map_or(name.to_string(), |n| n.to_string_lossy().into_owned());
    let label = args
        .figures
        .label(|| format!("bench tracking, {short_name} {frames}"));
    args.figures.record(&headline_figures(&report, &label))?;
    if args.json {
        return print_json(&report);
    }
    print_report(&report);
    Ok(())
}

/// What `--figures` records: the ATE, the time per frame, and what was lost.
fn headline_figures(report: &TrackingReport, label: &str) -> Vec<Figure> {
    let mut figures = Vec::new();
    if let Some(rmse) = report.ate_rmse_m {
        figures.push(Figure::number(
            format!("{label}: tracking ATE"),
            rmse * 100.0,
            2,
            "cm",
        ));
    }
    figures.push(Figure::number(
        format!("{label}: tracking time per frame, median"),
        report.tracking_ms_median,
        1,
        "ms",
    ));
    figures.push(Figure::text(
        format!("{label}: frames lost / segments started / joined"),
        format!(
            "{} / {} / {}",
            report.failures, report.segments_started, report.segments_joined
        ),
        "",
    ));
    figures
}

fn outcome_label(outcome: &TrackingOutcome) -> String {
    match outcome {
        TrackingOutcome::Initialised => "initialised".into(),
        TrackingOutcome::Tracked => "tracked".into(),
        TrackingOutcome::TrackedNotConverged => "tracked_not_converged".into(),
        TrackingOutcome::Recovered(guess) => format!("recovered_{guess:?}").to_lowercase(),
        TrackingOutcome::Lost(_) => "lost".into(),
    }
}

fn write_frames_csv(path: &std::path::Path, records: &[FrameRecord]) -> anyhow::Result<()> {
    let mut file = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    writeln!(file, "timestamp,segment,placed,outcome,confidence")?;
    for r in records {
        let segment = match r.placement {
            Placement::Root => "root".to_string(),
            Placement::Unjoined(segment) => segment.to_string(),
        };
        writeln!(
            file,
            "{:.6},{segment},{},{},{:.4}",
            r.timestamp, r.placed, r.outcome, r.confidence
        )?;
    }
    file.flush()
        .with_context(|| format!("writing {}", path.display()))
}

fn print_report(report: &TrackingReport) {
    let cm = |m: Option<f64>| m.map_or("n/a".to_string(), |m| fmt_num(m * 100.0, 2));
    println!(
        "G-ICP tracking ({}, {} threads): {}",
        report.mode, report.threads, report.dataset
    );
    let rows = [
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
            "  recovery ms, median",
            fmt_num(report.recovery_ms_median, 2),
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
        (
            "ATE RMSE cm, lost frames included",
            cm(report.ate_rmse_with_lost_m),
        ),
        ("frames placed", report.frames_placed.to_string()),
        ("frames lost", report.failures.to_string()),
        ("divergences detected", report.divergences.to_string()),
        ("recoveries", report.recoveries.to_string()),
        ("not converged", report.not_converged.to_string()),
        ("segments started", report.segments_started.to_string()),
        ("segments joined", report.segments_joined.to_string()),
        (
            "frames in unjoined segments",
            report.frames_unjoined.to_string(),
        ),
        (
            "confidence, median",
            report
                .confidence_median
                .map_or("n/a".to_string(), |c| fmt_num(c, 3)),
        ),
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
}

/// The frame positions of `--positions`: one per line, or the `frame_position` column of a CSV
/// with a header; each below `len` (the opened frames).
fn read_positions(path: &std::path::Path, len: usize) -> anyhow::Result<Vec<usize>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--positions: reading {}", path.display()))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let mut column = None;
    let mut positions = Vec::new();
    if let Some(first) = text.lines().find(|l| !l.trim().is_empty())
        && first.contains(',')
    {
        let header: Vec<&str> = first.split(',').map(str::trim).collect();
        column = Some(
            header
                .iter()
                .position(|name| *name == "frame_position")
                .with_context(|| {
                    format!("--positions {}: no frame_position column", path.display())
                })?,
        );
        lines.next();
    }
    for (number, line) in lines {
        let field = match column {
            Some(c) => line.split(',').nth(c).unwrap_or("").trim(),
            None => line.trim(),
        };
        let position: usize = field.parse().with_context(|| {
            format!(
                "--positions {} line {}: {field:?} is not a frame position",
                path.display(),
                number + 1
            )
        })?;
        anyhow::ensure!(
            position < len,
            "--positions {} line {}: position {position} is past the {len} frames opened",
            path.display(),
            number + 1
        );
        positions.push(position);
    }
    Ok(positions)
}
