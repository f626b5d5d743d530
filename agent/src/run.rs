//! One agent run (docs/method.md, One agent): frame source -> G-ICP tracking -> keyframes ->
//! seeding -> publishing -> mapping thread, one [`AgentPipeline`] stage each; then the outputs a
//! user opens: trajectory.tum, map.ply, metrics.json and renders next to ground truth.
//!
//! `mapping.pace` times the loop: at the camera's timestamps, dropping what a slow agent misses
//! (`sensor`, [`crate::pace`]); waiting for the mapper's budget at each keyframe (`paced`); or
//! every frame as fast as possible (`unthrottled`). A stop request
//! (SIGINT / SIGTERM in the binary) ends the loop after the current frame; everything computed
//! so far is still written.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use alexnet::lpips::Lpips;
use anyhow::Context;
use config::{Config, Pace};
use datasets::{self, Dataset, FrameRange};
use geometry::correction::CorrectionField;
use geometry::se3::isometry_from_tum;
use geometry::trajectory::Trajectory;
use indicatif::{ProgressBar, ProgressStyle};
use live_view::{LiveView, LiveViewStats};
use metrics::ate::{Alignment, AteStats, DEFAULT_MAX_DT, ate};
use metrics::stats::{median, quantile};
use nalgebra::Isometry3;
use registration::odometry::{Placement, SegmentId};
use serde::Serialize;
use splats::GaussianCloud;

use crate::evaluation::{
    FrameQuality, MapRenderer, QualitySummary, comparison_path, evaluate_frame,
};
use crate::local_corrections::LocalCorrectionStats;
use crate::mapper::{MappingOutcome, MappingStats};
use crate::pace::SensorClock;
use crate::pipeline::{AgentPipeline, FinishedPipeline, TrackedPose, progress_snapshot};
use crate::progress::{ProgressFile, Stage};
use crate::segments::TrackingReport;
use crate::source::{FrameSource, LiveInputReport, SourceStats, open_frames};
use crate::swarm::{SwarmLink, SwarmSummary};
use crate::views::{poses_in_map, write_view_files};

/// Synthetic scene used when no dataset is given: three agents' loops, this agent's share.
pub const DEFAULT_SYNTHETIC_AGENTS: usize = 3;
pub const DEFAULT_SYNTHETIC_FRAMES: usize = 300;

/// What to run and where to write.
#[derive(Debug, Clone)]
pub struct AgentOptions {
    pub config: Config,
    /// Dataset path or `synthetic:...` spec.
    pub dataset: String,
    pub frames: FrameRange,
    pub agent_id: u32,
    pub out: PathBuf,
    /// Post-run refinement iterations (0 = none), reported separately.
    pub refine_iterations: usize,
    /// Evaluate rendering quality on every n-th frame.
    pub eval_every: usize,
    /// Comparison images written (spread over the evaluated frames).
    pub comparison_renders: usize,
    pub lpips_weights: Option<PathBuf>,
    pub decode_workers: usize,
    /// The rerun live view ([`LiveView::disabled`] unless `--viewer` or `--record`).
    pub live_view: LiveView,
}

impl AgentOptions {
    /// The embedded synthetic scene's spec for `agent_id`.
    pub fn synthetic_dataset(agent_id: u32) -> String {
        let agents = DEFAULT_SYNTHETIC_AGENTS.max(agent_id as usize + 1);
        format!("synthetic:agents={agents},agent={agent_id},frames={DEFAULT_SYNTHETIC_FRAMES}")
    }
}

/// Rendering quality of one map.
#[derive(Debug, Clone, Serialize)]
pub struct MapMetrics {
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    pub depth_l1_cm: Option<f64>,
    pub eval_frames: usize,
    pub gaussians: usize,
    pub mapping_iters: usize,
    pub mapping_iters_per_s: f64,
}

/// metrics.json.
#[derive(Debug, Clone, Serialize)]
pub struct AgentMetrics {
    pub agent_id: u32,
    pub dataset: String,
    /// The `--dataset` argument and frame range, so that tools can reopen the same frames.
    pub dataset_spec: String,
    pub frame_range: String,
    /// SE(3)-aligned ATE RMSE against ground truth; absent without ground truth.
    pub ate_rmse_m: Option<f64>,
    pub ate_mean_m: Option<f64>,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    pub depth_l1_cm: Option<f64>,
    pub frames: usize,
    pub keyframes: usize,
    pub tracking_keyframes: usize,
    pub mapping_keyframes: usize,
    pub gaussians: usize,
    pub tracking_ms_median: f64,
    pub tracking_ms_p90: f64,
    pub mapping_iters_per_s: f64,
    pub mapping_iters: usize,
    /// Frames per second of the whole real-time loop (decode, tracking, seeding, hand-off).
    pub fps: f64,
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
    pub frames_without_depth: usize,
    pub eval_frames: usize,
    pub eval_every: usize,
    pub mapping_image_downscale: u32,
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

/// A frame whose loop takes longer than this is logged (debug) with the time of each stage.
const SLOW_FRAME: Duration = Duration::from_millis(100);

/// Runs one agent without a consensus process and writes its outputs to `options.out`.
pub fn run_standalone(options: &AgentOptions, stop: &AtomicBool) -> anyhow::Result<AgentMetrics> {
    run_agent(options, stop, None)
}

/// Runs one agent, in the swarm when `swarm` is given (keyframes published every T_comm frames,
/// corrections received between frames, final map and goodbye before the evaluation), and
/// writes its outputs to `options.out`.
pub fn run_agent(
    options: &AgentOptions,
    stop: &AtomicBool,
    swarm: Option<SwarmLink>,
) -> anyhow::Result<AgentMetrics> {
    let _span = tracing::info_span!("agent", id = options.agent_id).entered();
    config::process::prepare_output_dir(&options.out)?;
    let config = &options.config;
    let (dataset, live_camera) = open_frames(options)?;
    tracing::info!(dataset = %dataset.describe(), frames = dataset.len(), "agent starting");
    let lpips = options
        .lpips_weights
        .as_deref()
        .map(|path| {
            Lpips::load(path).with_context(|| format!("loading LPIPS weights {}", path.display()))
        })
        .transpose()?;

    let in_swarm = swarm.is_some();
    let started = Instant::now();
    let mut source = match &live_camera {
        Some(camera) => FrameSource::live(
            camera.clone(),
            config.noise,
            stop,
            config.ros2.idle_timeout_s,
        ),
        None => FrameSource::new(dataset.clone(), options.decode_workers.max(1), config.noise),
    };
    let mut agent = AgentPipeline::new(
        config,
        &options.dataset,
        swarm,
        dataset.len(),
        options.agent_id,
        options.live_view.clone(),
    )?;
    let progress = progress_bar(dataset.len());
    let mut progress_file = ProgressFile::new(&options.out);
    let frames_total = live_camera.is_none().then(|| dataset.len());
    progress_file.write(&agent.progress(Stage::Tracking, frames_total));

    let mut interrupted = false;
    // A live camera sets its own pace (and drops what the agent cannot take).
    let mut sensor =
        (config.mapping.pace == Pace::Sensor && live_camera.is_none()).then(SensorClock::new);
    {
        let _span = tracing::info_span!("tracking").entered();
        for item in source.by_ref() {
            if let Some(sensor) = sensor.as_mut() {
                let next = item.position + 1;
                let next_timestamp = (next < dataset.len()).then(|| dataset.timestamp(next));
                if !sensor.take_now(item.frame.timestamp, next_timestamp) {
                    continue;
                }
            }
            let clock = Instant::now();
            let frame = &item.frame;
            agent.announce(frame);
            let tracked = agent.track(&item);
            let tracked_at = clock.elapsed();
            if let Some(decision) = agent.decide_keyframe(frame, &tracked) {
                agent.keyframe(frame, &tracked, decision);
            }
            let keyframe_done_at = clock.elapsed();
            agent.apply_corrections(frame);
            let link_done_at = clock.elapsed();
            agent.record(&item, &tracked, clock);
            if link_done_at > SLOW_FRAME {
                // Which stage held the frame loop up (a live camera drops frames meanwhile).
                tracing::debug!(
                    frame = frame.index,
                    tracking = ?tracked_at,
                    keyframe = ?(keyframe_done_at - tracked_at),
                    link_and_corrections = ?(link_done_at - keyframe_done_at),
                    "slow frame"
                );
            }

            progress.inc(1);
            progress_file.update(|| agent.progress(Stage::Tracking, frames_total));
            if agent.frames_done().is_multiple_of(PROGRESS_MESSAGE_EVERY) {
                progress.set_message(agent.progress_message());
            }
            let stopped_by_consensus = agent.stop_requested_by_consensus();
            if stop.load(Ordering::Relaxed) || stopped_by_consensus.is_some() {
                tracing::warn!(
                    frame = frame.index,
                    by_consensus = stopped_by_consensus,
                    "stop requested: finishing after this frame and writing outputs"
                );
                interrupted = true;
                break;
            }
        }
    }
    let loop_seconds = started.elapsed().as_secs_f64();
    progress.finish_and_clear();
    progress_file.write(&agent.progress(Stage::Finishing, frames_total));
    let (mapper, swarm, mut run) = agent.finish();
    let refine_iterations = if interrupted {
        0
    } else {
        options.refine_iterations
    };
    let outcome = mapper.finish(refine_iterations)?;
    if let Some(live) = run.ros2_live.as_mut() {
        live.finish(&outcome.realtime_map);
    }

    // Outputs that need no rendering first: an interrupted evaluation still leaves these.
    let trajectory = write_trajectories(&run.poses, &options.out)?;
    write_maps(&outcome, &options.out)?;
    crate::ros2_outputs::write_agent_bag(
        &options.out,
        options.agent_id,
        &run.poses,
        &outcome.realtime_map,
        &config.ros2,
        !in_swarm,
    )?;
    write_view_files(
        &run,
        &outcome.realtime.keyframe_pose_corrections,
        &options.out,
    )?;
    // The consensus reads trajectory.tum once this agent has said goodbye, so that goes first;
    // the evaluation below takes a while and needs nothing from the swarm.
    let swarm_summary = swarm.map(|link| link.finish(&outcome.realtime_map_at_tracked_poses()));
    // The latest placement the consensus sent, one that arrived while the link finished
    // included: the recording ends with this agent's map in the world frame.
    if let Some(world_from_agent) = swarm_summary
        .as_ref()
        .and_then(|summary| summary.world_from_agent.as_ref())
        .and_then(|tum| isometry_from_tum(tum).ok())
    {
        options
            .live_view
            .agent_placement(options.agent_id, &world_from_agent);
    }
    let live_view = finish_live_view(options, &outcome.realtime_map);
    let ate_stats = trajectory_ate(&run.poses, &trajectory);

    let (realtime, realtime_frames, refined) =
        evaluate_maps(options, &dataset, &run, &outcome, lpips.as_ref())?;
    let metrics = agent_metrics(RunRecord {
        options,
        dataset: dataset.as_ref(),
        run: &run,
        outcome: &outcome,
        source: source.stats(),
        frames_dropped: sensor.as_ref().map_or(0, SensorClock::dropped),
        loop_seconds,
        wall_s: started.elapsed().as_secs_f64(),
        interrupted,
        ate: ate_stats,
        realtime,
        realtime_frames,
        refined,
        swarm: swarm_summary,
        in_swarm,
        live_view,
        live: live_camera.as_ref().map(|camera| {
            LiveInputReport::new(
                camera,
                source.stats().live_end.clone(),
                &run.stamp_to_pose_ms,
            )
        }),
    });
    let metrics_path = options.out.join("metrics.json");
    let json = serde_json::to_string_pretty(&metrics)?;
    geometry::files::write_whole(&metrics_path, |file| file.write_all(json.as_bytes()))
        .with_context(|| format!("writing {}", metrics_path.display()))?;
    progress_file.write(&progress_snapshot(
        Stage::Done,
        run.poses.len(),
        frames_total,
        run.keyframes.total(),
        None,
    ));
    Ok(metrics)
}

/// Renders the real-time map (and the refined one, when there is one) at every
/// `eval_every`-th tracked pose and scores it against the frames: (real-time figures, frames
/// evaluated, refined figures).
fn evaluate_maps(
    options: &AgentOptions,
    dataset: &Arc<dyn Dataset>,
    run: &FinishedPipeline,
    outcome: &MappingOutcome,
    lpips: Option<&Lpips>,
) -> anyhow::Result<(MapMetrics, usize, Option<MapMetrics>)> {
    // The map is in the local-map frame: each frame is rendered where the corrections applied
    // to the map put it (the tracked pose when none were), then where the mapper's keyframe pose
    // refinement moved it (`refine_keyframe_poses`; nothing otherwise).
    // A live camera kept evenly spaced frames already (every eval_every-th or sparser).
    let evaluation_stride = if datasets::live::is_live(&options.dataset) {
        1
    } else {
        options.eval_every.max(1)
    };
    let evaluated = |pose_refinement: &CorrectionField| -> Vec<TrackedPose> {
        poses_in_map(run, pose_refinement)
            .into_iter()
            .filter(|pose| dataset.can_load(pose.position))
            .step_by(evaluation_stride)
            .collect()
    };
    let evaluate = |map: &GaussianCloud, stats: &MappingStats, renders: &str| {
        evaluate_map(
            map,
            dataset,
            &evaluated(&stats.keyframe_pose_corrections),
            lpips,
            Some(&options.out.join(renders)),
            options.comparison_renders,
        )
    };
    let realtime_quality = evaluate(&outcome.realtime_map, &outcome.realtime, "renders")?;
    let refined = match &outcome.refined {
        Some((map, stats)) => Some(map_metrics(
            &evaluate(map, stats, "renders_refined")?,
            map.len(),
            stats,
        )),
        None => None,
    };
    let realtime = map_metrics(
        &realtime_quality,
        outcome.realtime_map.len(),
        &outcome.realtime,
    );
    Ok((realtime, realtime_quality.frames, refined))
}

/// What a finished run measured, gathered for metrics.json.
struct RunRecord<'r> {
    options: &'r AgentOptions,
    dataset: &'r dyn Dataset,
    run: &'r FinishedPipeline,
    outcome: &'r MappingOutcome,
    source: &'r SourceStats,
    /// Frames a live camera would have overwritten before the agent took them (sensor pace).
    frames_dropped: usize,
    /// The frame loop's duration (frames per second).
    loop_seconds: f64,
    wall_s: f64,
    interrupted: bool,
    ate: Option<AteStats>,
    realtime: MapMetrics,
    realtime_frames: usize,
    refined: Option<MapMetrics>,
    swarm: Option<SwarmSummary>,
    in_swarm: bool,
    live_view: Option<LiveViewStats>,
    live: Option<LiveInputReport>,
}

fn agent_metrics(record: RunRecord<'_>) -> AgentMetrics {
    let RunRecord {
        options,
        run,
        outcome,
        realtime,
        ..
    } = record;
    let frames = run.poses.len();
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
        tracking_ms_median: median(&run.tracking_ms).unwrap_or(0.0),
        tracking_ms_p90: quantile(&run.tracking_ms, 0.9).unwrap_or(0.0),
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

/// Shows the final map in the live view, then lets the view log what it holds (at most its
/// finish timeout); what it took and dropped.
fn finish_live_view(options: &AgentOptions, map: &GaussianCloud) -> Option<LiveViewStats> {
    let view = &options.live_view;
    view.map_points(options.agent_id, &map.means, &map.colours, true);
    let stats = view.finish()?;
    tracing::info!(
        items_queued = stats.items_queued,
        items_dropped = stats.items_dropped,
        frames_dropped = stats.frames_dropped,
        "live view finished"
    );
    Some(stats)
}

/// trajectory.tum (the estimate, in the tracked frame; lost frames, whose pose is only the
/// prediction, left out; frames of tracking segments never joined to the map go to
/// trajectory_segment_K.tum, each in its own frame), tracking.csv (every frame's outcome and
/// confidence) and, when the dataset has ground truth, groundtruth.tum next to it (evo and the
/// swarm report read these).
fn write_trajectories(poses: &[TrackedPose], out: &Path) -> anyhow::Result<Trajectory> {
    let trajectory = Trajectory::from_pairs(
        poses
            .iter()
            .filter(|p| p.placement == Placement::Root && p.tracked)
            .map(|p| (p.timestamp, p.world_from_camera)),
    );
    trajectory.write_tum(&out.join("trajectory.tum"))?;
    let mut segments: Vec<SegmentId> = poses
        .iter()
        .filter_map(|p| match p.placement {
            Placement::Unjoined(segment) => Some(segment),
            Placement::Root => None,
        })
        .collect();
    segments.dedup();
    for segment in segments {
        let path = out.join(format!("trajectory_segment_{segment}.tum"));
        tracing::warn!(
            segment,
            path = %path.display(),
            "a tracking segment was never joined to the map: its poses are in a frame of their own"
        );
        Trajectory::from_pairs(
            poses
                .iter()
                .filter(|p| p.placement == Placement::Unjoined(segment))
                .map(|p| (p.timestamp, p.world_from_camera)),
        )
        .write_tum(&path)?;
    }
    let csv_path = out.join("tracking.csv");
    geometry::files::write_whole(&csv_path, |file| -> std::io::Result<()> {
        let mut file = std::io::BufWriter::new(file);
        writeln!(file, "timestamp,frame_position,segment,tracked,confidence")?;
        for p in poses {
            let segment = match p.placement {
                Placement::Root => "root".to_string(),
                Placement::Unjoined(segment) => segment.to_string(),
            };
            writeln!(
                file,
                "{:.6},{},{segment},{},{:.4}",
                p.timestamp, p.position, p.tracked, p.confidence
            )?;
        }
        file.flush()
    })
    .with_context(|| format!("writing {}", csv_path.display()))?;
    let ground_truth: Vec<(f64, Isometry3<f64>)> = poses
        .iter()
        .filter_map(|p| Some((p.timestamp, p.ground_truth?)))
        .collect();
    if !ground_truth.is_empty() {
        Trajectory::from_pairs(ground_truth).write_tum(&out.join("groundtruth.tum"))?;
    }
    Ok(trajectory)
}

/// metrics.json's tracking block.
fn tracking_report(run: &FinishedPipeline) -> TrackingReport {
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
        confidence_median: median(&confidences),
        confidence_min: confidences.iter().copied().reduce(f64::min),
    }
}

/// map.ply (the real-time map) and map_refined.ply (after the optional refinement).
fn write_maps(outcome: &MappingOutcome, out: &Path) -> anyhow::Result<()> {
    let map_path = out.join("map.ply");
    splats::ply::save_ply(&map_path, &outcome.realtime_map)
        .with_context(|| format!("writing {}", map_path.display()))?;
    if let Some((refined_map, _)) = &outcome.refined {
        let path = out.join("map_refined.ply");
        splats::ply::save_ply(&path, refined_map)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Frames between progress-message updates.
const PROGRESS_MESSAGE_EVERY: usize = 10;

fn progress_bar(frames: usize) -> ProgressBar {
    // indicatif draws to stderr only when it is a terminal.
    let bar = ProgressBar::new(frames as u64);
    if let Ok(style) = ProgressStyle::with_template(
        "{elapsed_precise} [{bar:30}] {pos}/{len} frames ({per_sec}) {msg}",
    ) {
        bar.set_style(style);
    }
    bar
}

fn trajectory_ate(poses: &[TrackedPose], estimate: &Trajectory) -> Option<AteStats> {
    let ground_truth = Trajectory::from_pairs(
        poses
            .iter()
            .filter(|p| p.placement == Placement::Root)
            .filter_map(|p| p.ground_truth.map(|gt| (p.timestamp, gt))),
    );
    if ground_truth.len() < 3 {
        return None;
    }
    match ate(&ground_truth, estimate, Alignment::Se3, DEFAULT_MAX_DT) {
        Ok(result) => Some(result.stats),
        Err(error) => {
            tracing::warn!(%error, "ATE not computed");
            None
        }
    }
}

/// `map` rendered at each of `evaluated` and scored against its frame; with `comparison_dir`,
/// `comparison_renders` side-by-side images and every frame's figures (quality.json) go there.
fn evaluate_map(
    map: &GaussianCloud,
    dataset: &Arc<dyn Dataset>,
    evaluated: &[TrackedPose],
    lpips: Option<&Lpips>,
    comparison_dir: Option<&Path>,
    comparison_renders: usize,
) -> anyhow::Result<QualitySummary> {
    let _span = tracing::info_span!("evaluation", frames = evaluated.len()).entered();
    let renderer = MapRenderer::new(map).context("uploading the map for evaluation")?;
    let comparison_step = if comparison_renders == 0 {
        usize::MAX
    } else {
        evaluated.len().div_ceil(comparison_renders).max(1)
    };
    if let Some(dir) = comparison_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let progress = progress_bar(evaluated.len());
    let mut qualities: Vec<FrameQuality> = Vec::with_capacity(evaluated.len());
    for (i, pose) in evaluated.iter().enumerate() {
        progress.inc(1);
        let frame = match dataset.load(pose.position) {
            Ok(frame) => frame,
            Err(error) => {
                tracing::warn!(%error, "evaluation frame skipped");
                continue;
            }
        };
        let comparison = comparison_dir
            .filter(|_| comparison_renders > 0 && i % comparison_step == 0)
            .map(|dir| comparison_path(dir, frame.index));
        qualities.push(evaluate_frame(
            &renderer,
            &frame,
            &pose.world_from_camera,
            lpips,
            comparison.as_deref(),
        )?);
    }
    progress.finish_and_clear();
    // Every evaluated frame's figures, next to the comparison images: which frames a mean hides.
    if let Some(dir) = comparison_dir {
        let path = dir.join("quality.json");
        let json = serde_json::to_string_pretty(&qualities)?;
        geometry::files::write_whole(&path, |file| file.write_all(json.as_bytes()))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(QualitySummary::of(&qualities))
}

fn map_metrics(quality: &QualitySummary, gaussians: usize, stats: &MappingStats) -> MapMetrics {
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
