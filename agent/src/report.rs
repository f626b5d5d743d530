//! metrics.json of one agent: what a finished run measured (tracking, map quality, pace,
//! swarm link, live input), gathered from the run's parts, and the table the agent prints.

use datasets::Dataset;
use live_view::LiveViewStats;
use metrics::ate::AteStats;
use metrics::stats::{median, quantile};
use registration::odometry::Placement;
use serde::Serialize;

use crate::evaluation::QualitySummary;
use crate::local_corrections::LocalCorrectionStats;
use crate::mapper::{MappingOutcome, MappingStats};
use crate::pipeline::FinishedPipeline;
use crate::run::AgentOptions;
use crate::segments::TrackingReport;
use crate::source::{LiveInputReport, SourceStats};
use crate::swarm::SwarmSummary;
use config::Pace;

/// Rendering quality of one map.
#[derive(Debug, Clone, Serialize)]
pub struct MapMetrics {
    /// Mean PSNR in dB over the evaluated frames (those with a finite one).
    pub psnr: Option<f64>,
    /// Mean SSIM, zero-padded (the 3DGS convention).
    pub ssim: Option<f64>,
    /// Mean LPIPS (AlexNet); absent without weights.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    /// Mean depth L1 in cm over the evaluated frames with valid depth.
    pub depth_l1_cm: Option<f64>,
    /// Frames evaluated (loaded and rendered).
    pub eval_frames: usize,
    /// Gaussians in the map.
    pub gaussians: usize,
    /// Iterations of the phase that made the map (real-time mapping, or the refinement alone).
    pub mapping_iters: usize,
    /// Those iterations per wall-clock second of the phase.
    pub mapping_iters_per_s: f64,
}

/// metrics.json.
#[derive(Debug, Clone, Serialize)]
pub struct AgentMetrics {
    /// This agent's id.
    pub agent_id: u32,
    /// The dataset in words (layout and path).
    pub dataset: String,
    /// The `--dataset` argument and frame range, so that tools can reopen the same frames.
    pub dataset_spec: String,
    /// The frame range as given (`FIRST..END:STEP`).
    pub frame_range: String,
    /// SE(3)-aligned ATE RMSE against ground truth; absent without ground truth.
    pub ate_rmse_m: Option<f64>,
    /// Mean translation error under the same alignment, metres; absent as the RMSE.
    pub ate_mean_m: Option<f64>,
    /// The real-time map's mean PSNR in dB over the evaluated frames.
    pub psnr: Option<f64>,
    /// The real-time map's mean SSIM (zero-padded).
    pub ssim: Option<f64>,
    /// The real-time map's mean LPIPS; absent without weights.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    /// The real-time map's mean depth L1 in cm.
    pub depth_l1_cm: Option<f64>,
    /// Frames the loop took: placed, lost and those of unjoined segments.
    pub frames: usize,
    /// Keyframes made (tracking + mapping).
    pub keyframes: usize,
    /// Keyframes made for too little overlap with the tracking map.
    pub tracking_keyframes: usize,
    /// Keyframes made every `mapping_keyframe_every` frames otherwise.
    pub mapping_keyframes: usize,
    /// Gaussians in the real-time map.
    pub gaussians: usize,
    /// Median wall time of a frame's pass through the loop's stages, milliseconds.
    pub tracking_ms_median: f64,
    /// 90th percentile of that time, milliseconds.
    pub tracking_ms_p90: f64,
    /// Real-time mapping iterations per second.
    pub mapping_iters_per_s: f64,
    /// Real-time mapping iterations.
    pub mapping_iters: usize,
    /// Frames per second of the whole real-time loop (decode, tracking, seeding, hand-off).
    pub fps: f64,
    /// Wall time of the whole run (the loop, finishing, outputs and evaluation), seconds.
    pub wall_s: f64,
    /// Tracking failures, recoveries and segments.
    pub tracking: TrackingReport,
    /// How the loop was timed (`mapping.pace`).
    pub pace: Pace,
    /// Sensor pace: frames a live camera would have overwritten before the agent took them
    /// (not tracked, not in `frames`).
    pub frames_dropped: usize,
    /// Frames skipped because a file is missing (the log names it).
    pub frames_missing: usize,
    /// Frames skipped because a file could not be decoded or validated (the log names it).
    pub frames_broken: usize,
    /// Where the dataset is damaged (a bag cut short), when it is: the run used the frames
    /// before the damage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dataset_damage: Option<String>,
    /// A live ROS 2 camera's input: what was received, paired, dropped, and why it ended.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live: Option<LiveInputReport>,
    /// Tracked frames whose ground-truth pose file is broken (the log names it): left out of
    /// the ATE only.
    pub ground_truth_broken: usize,
    /// Frames without a single valid depth pixel (still yielded: tracking sees the gap in time).
    pub frames_without_depth: usize,
    /// Frames the real-time map was evaluated on.
    pub eval_frames: usize,
    /// Every n-th tracked frame was evaluated (`eval_every`, at least 1).
    pub eval_every: usize,
    /// `[mapping] image_downscale`: keyframes are optimised at their resolution over this.
    pub mapping_image_downscale: u32,
    /// Peak resident set size of the process, MiB; absent where /proc does not tell.
    pub peak_rss_mib: Option<f64>,
    /// True when a stop request ended the run early.
    pub interrupted: bool,
    /// The optional post-run refinement, kept apart from the real-time figures.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refined: Option<MapMetrics>,
    /// Swarm mode only: what went to and came from the consensus.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub swarm: Option<SwarmSummary>,
    /// Swarm mode only: the consensus corrections applied to the local maps.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub local_corrections: Option<LocalCorrectionStats>,
    /// With `--viewer` or `--record`: what the live view queued and dropped (a full queue drops
    /// visualisation, never slows the agent).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live_view: Option<LiveViewStats>,
}

/// What a finished run measured, gathered for metrics.json.
pub(crate) struct RunRecord<'r> {
    pub(crate) options: &'r AgentOptions,
    pub(crate) dataset: &'r dyn Dataset,
    pub(crate) run: &'r FinishedPipeline,
    pub(crate) outcome: &'r MappingOutcome,
    pub(crate) source: &'r SourceStats,
    /// Frames a live camera would have overwritten before the agent took them (sensor pace).
    pub(crate) frames_dropped: usize,
    /// The frame loop's duration (frames per second).
    pub(crate) loop_seconds: f64,
    pub(crate) wall_s: f64,
    pub(crate) interrupted: bool,
    pub(crate) ate: Option<AteStats>,
    pub(crate) realtime: MapMetrics,
    pub(crate) realtime_frames: usize,
    pub(crate) refined: Option<MapMetrics>,
    pub(crate) swarm: Option<SwarmSummary>,
    pub(crate) in_swarm: bool,
    pub(crate) live_view: Option<LiveViewStats>,
    pub(crate) live: Option<LiveInputReport>,
}

pub(crate) fn agent_metrics(record: RunRecord<'_>) -> AgentMetrics {
    let RunRecord {
        options,
        run,
        outcome,
        realtime,
        ..
    } = record;
    let frames = run.poses.len();
    let loop_ms: Vec<f64> = run.poses.iter().map(|p| p.loop_ms).collect();
    AgentMetrics {
        agent_id: options.agent_id,
        dataset: record.dataset.describe(),
        dataset_spec: options.dataset.clone(),
        frame_range: options.frames.to_string(),
        ate_rmse_m: record.ate.as_ref().map(|s| s.rmse),
        ate_mean_m: record.ate.as_ref().map(|s| s.mean),
        psnr: realtime.psnr,
        ssim: realtime.ssim,
        lpips: realtime.lpips,
        depth_l1_cm: realtime.depth_l1_cm,
        frames,
        keyframes: run.keyframes.total(),
        tracking_keyframes: run.keyframes.tracking,
        mapping_keyframes: run.keyframes.mapping,
        gaussians: outcome.realtime_map.len(),
        tracking_ms_median: median(&loop_ms).unwrap_or(0.0),
        tracking_ms_p90: quantile(&loop_ms, 0.9).unwrap_or(0.0),
        mapping_iters_per_s: outcome.realtime.iterations_per_second(),
        mapping_iters: outcome.realtime.iterations,
        fps: if record.loop_seconds > 0.0 {
            frames as f64 / record.loop_seconds
        } else {
            0.0
        },
        wall_s: record.wall_s,
        tracking: tracking_report(run),
        pace: options.config.mapping.pace,
        frames_dropped: record.frames_dropped,
        frames_missing: record.source.frames_missing,
        frames_broken: record.source.frames_broken,
        dataset_damage: record.source.dataset_damage.clone(),
        live: record.live,
        ground_truth_broken: record.source.ground_truth_broken,
        frames_without_depth: record.source.frames_without_depth,
        eval_frames: record.realtime_frames,
        eval_every: options.eval_every.max(1),
        mapping_image_downscale: options.config.mapping.image_downscale,
        peak_rss_mib: peak_rss_mib(),
        interrupted: record.interrupted,
        refined: record.refined,
        swarm: record.swarm,
        local_corrections: record.in_swarm.then(|| run.corrections.stats().clone()),
        live_view: record.live_view,
    }
}

/// metrics.json's tracking block.
pub(crate) fn tracking_report(run: &FinishedPipeline) -> TrackingReport {
    let stats = run.odometry.stats();
    let confidences: Vec<f64> = run
        .poses
        .iter()
        .filter(|p| p.tracked)
        .map(|p| p.confidence)
        .collect();
    TrackingReport {
        frames_lost: stats.failures,
        divergences_detected: stats.divergences,
        recoveries: stats.recoveries,
        segments_started: stats.segments_started,
        segments_joined: stats.segments_joined,
        frames_unjoined: run
            .poses
            .iter()
            .filter(|p| p.placement != Placement::Root)
            .count(),
        keyframes_dropped_unjoined: run.keyframes_dropped_unjoined,
        searches_rationed: stats.searches_rationed,
        confidence_median: median(&confidences),
        confidence_min: confidences.iter().copied().reduce(f64::min),
    }
}

pub(crate) fn map_metrics(
    quality: &QualitySummary,
    gaussians: usize,
    stats: &MappingStats,
) -> MapMetrics {
    MapMetrics {
        psnr: quality.psnr,
        ssim: quality.ssim,
        lpips: quality.lpips,
        depth_l1_cm: quality.depth_l1_cm,
        eval_frames: quality.frames,
        gaussians,
        mapping_iters: stats.iterations,
        mapping_iters_per_s: stats.iterations_per_second(),
    }
}

/// Peak resident set size of this process (Linux `VmHWM`), MiB.
pub fn peak_rss_mib() -> Option<f64> {
    const KIB_PER_MIB: f64 = 1024.0;
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / KIB_PER_MIB)
}

/// The metrics as a readable table.
pub fn metrics_table(metrics: &AgentMetrics) -> String {
    fn opt(value: Option<f64>, scale: f64, digits: usize) -> String {
        value.map_or("-".into(), |v| format!("{:.*}", digits, v * scale))
    }
    let mut rows = vec![
        ("frames".to_string(), metrics.frames.to_string()),
        ("ATE RMSE cm".into(), opt(metrics.ate_rmse_m, 100.0, 2)),
        ("ATE mean cm".into(), opt(metrics.ate_mean_m, 100.0, 2)),
        (
            format!("PSNR dB ({} frames)", metrics.eval_frames),
            opt(metrics.psnr, 1.0, 2),
        ),
        ("SSIM (zero-padded)".into(), opt(metrics.ssim, 1.0, 3)),
        ("LPIPS".into(), opt(metrics.lpips, 1.0, 3)),
        ("depth L1 cm".into(), opt(metrics.depth_l1_cm, 1.0, 2)),
        (
            "keyframes (tracking + mapping)".into(),
            format!(
                "{} ({} + {})",
                metrics.keyframes, metrics.tracking_keyframes, metrics.mapping_keyframes
            ),
        ),
        ("Gaussians".into(), metrics.gaussians.to_string()),
        (
            "tracking ms median / p90".into(),
            format!(
                "{:.1} / {:.1}",
                metrics.tracking_ms_median, metrics.tracking_ms_p90
            ),
        ),
        (
            "mapping iterations (per s)".into(),
            format!(
                "{} ({:.2})",
                metrics.mapping_iters, metrics.mapping_iters_per_s
            ),
        ),
        ("frames per second".into(), format!("{:.2}", metrics.fps)),
        ("peak RSS MiB".into(), opt(metrics.peak_rss_mib, 1.0, 0)),
    ];
    // Bad input shows here as well as in the log, where each file is named.
    if metrics.frames_missing + metrics.frames_broken + metrics.ground_truth_broken > 0 {
        rows.push((
            "frames skipped missing / broken".into(),
            format!("{} / {}", metrics.frames_missing, metrics.frames_broken),
        ));
        rows.push((
            "broken ground-truth poses".into(),
            metrics.ground_truth_broken.to_string(),
        ));
    }
    if let Some(refined) = &metrics.refined {
        rows.push((
            format!("refined ({} iterations) PSNR dB", refined.mapping_iters),
            opt(refined.psnr, 1.0, 2),
        ));
        rows.push(("refined SSIM".into(), opt(refined.ssim, 1.0, 3)));
        rows.push((
            "refined depth L1 cm".into(),
            opt(refined.depth_l1_cm, 1.0, 2),
        ));
    }
    let width = rows.iter().map(|r| r.0.len()).max().unwrap_or(0);
    rows.iter()
        .map(|(k, v)| format!("  {k:<width$}  {v:>12}\n"))
        .collect()
}
