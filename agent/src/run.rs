//! One agent run (SPEC section 3): frame source -> G-ICP tracking -> keyframes -> seeding ->
//! mapping thread; then the outputs a user opens: trajectory.tum, map.ply, metrics.json and
//! renders next to ground truth.
//!
//! The tracking loop never waits for the mapper (keyframes go over a channel). A stop request
//! (SIGINT / SIGTERM in the binary) ends the loop after the current frame; everything computed
//! so far is still written.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use alexnet::lpips::Lpips;
use anyhow::Context;
use config::Config;
use datasets::{self, Dataset, FrameRange};
use geometry::trajectory::Trajectory;
use indicatif::{ProgressBar, ProgressStyle};
use metrics::ate::{Alignment, AteStats, DEFAULT_MAX_DT, ate};
use metrics::stats::{median, quantile};
use nalgebra::Isometry3;
use registration::config::TrackingKeyframeSeeds;
use registration::odometry::{Odometry, OdometryMode, TrackingOutcome};
use render_core::types::RigidTransform;
use serde::Serialize;

use crate::corrections::{LocalCorrectionStats, LocalCorrections, LocalMaps};
use crate::evaluation::{
    FrameQuality, MapRenderer, QualitySummary, comparison_path, evaluate_frame,
};
use crate::mapper::{KeyframeKind, Mapper, MappingKeyframe, MappingStats};
use crate::progress::{Progress, ProgressFile, Stage};
use crate::seeding::{CoverageIndex, SeedFrame, seed_gaussians};
use crate::source::FrameSource;
use crate::swarm::{PublishableKeyframe, SwarmLink, SwarmSummary, run_anchor};

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
    pub tracking_failures: usize,
    pub reinitialisations: usize,
    pub frames_missing: usize,
    pub frames_broken: usize,
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
}

/// One frame's estimate.
#[derive(Clone, Copy)]
struct TrackedPose {
    position: usize,
    timestamp: f64,
    world_from_camera: Isometry3<f64>,
    ground_truth: Option<Isometry3<f64>>,
}

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
    mut swarm: Option<SwarmLink>,
) -> anyhow::Result<AgentMetrics> {
    let _span = tracing::info_span!("agent", id = options.agent_id).entered();
    std::fs::create_dir_all(&options.out)
        .with_context(|| format!("creating output directory {}", options.out.display()))?;
    let dataset: Arc<dyn Dataset> = Arc::from(
        datasets::open(&options.dataset, options.frames)
            .with_context(|| format!("opening dataset {}", options.dataset))?,
    );
    tracing::info!(dataset = %dataset.describe(), frames = dataset.len(), "agent starting");
    let config = &options.config;
    let lpips = match &options.lpips_weights {
        Some(path) => Some(
            Lpips::load(path)
                .with_context(|| format!("loading LPIPS weights {}", path.display()))?,
        ),
        None => None,
    };

    let in_swarm = swarm.is_some();
    let started = Instant::now();
    let mut source = FrameSource::new(dataset.clone(), options.decode_workers.max(1), config.noise);
    let mut odometry = Odometry::new(
        OdometryMode::FrameToModel,
        &config.tracking,
        &config.keyframes,
    );
    let mapper =
        Mapper::spawn(&config.tracking, &config.mapping).context("starting the mapping thread")?;
    let mut coverage = CoverageIndex::new(config.keyframes.mapping_seed_min_distance_sq_m2.sqrt());
    // Consensus corrections of the local maps (swarm only; the identity when standalone).
    let mut corrections = LocalCorrections::new(&config.consensus.local_corrections);
    let progress = progress_bar(dataset.len());
    let mut progress_file = ProgressFile::new(&options.out);
    let frames_total = Some(dataset.len());
    let snapshot =
        |stage: Stage, frames_done: usize, keyframes: usize, swarm: &Option<SwarmLink>| {
            let link = swarm.as_ref().map(SwarmLink::status);
            Progress {
                stage,
                frames_done,
                frames_total,
                keyframes,
                link_up: link.map(|l| l.up),
                queued_keyframes: link.map(|l| l.queued_keyframes),
            }
        };
    progress_file.write(&snapshot(Stage::Tracking, 0, 0, &swarm));

    let mut poses: Vec<TrackedPose> = Vec::with_capacity(dataset.len());
    let mut tracking_ms: Vec<f64> = Vec::with_capacity(dataset.len());
    let (mut tracking_keyframes, mut mapping_keyframes) = (0usize, 0usize);
    let mut frames_since_tracking_keyframe = 0usize;
    let mut interrupted = false;
    {
        let _span = tracing::info_span!("tracking").entered();
        for item in source.by_ref() {
            let clock = Instant::now();
            let frame = &item.frame;
            if let Some(swarm) = swarm.as_mut()
                && !swarm.is_announced()
            {
                // Announced with the first frame: the one the tracked frame starts at.
                let anchor = run_anchor(&options.dataset, frame.index, frame.timestamp);
                swarm.announce(&frame.intrinsics, anchor);
            }
            let tracker_first_point = odometry.next_point_id();
            let tracked = odometry.track(&frame.depth, &frame.intrinsics);
            if odometry.next_point_id() > tracker_first_point {
                corrections.record_tracker_points(tracker_first_point, frame.timestamp);
            }
            // Tracking runs in the local-map frame; outputs use the tracked frame
            // (crate::corrections).
            let tracked_pose = corrections.to_tracked(frame.timestamp, &tracked.world_from_camera);
            let usable = item.has_depth
                && matches!(
                    tracked.outcome,
                    TrackingOutcome::Initialised
                        | TrackingOutcome::Tracked
                        | TrackingOutcome::TrackedNotConverged
                );
            frames_since_tracking_keyframe += 1;
            let uncovered_points = || {
                let seed_frame = SeedFrame {
                    points: &tracked.frame_points,
                    world_from_camera: &tracked.world_from_camera,
                    rgb: &frame.rgb,
                    intrinsics: &frame.intrinsics,
                };
                coverage.uncovered(
                    &seed_frame,
                    config.keyframes.mapping_seed_min_distance_sq_m2,
                )
            };
            let keyframe = if let Some(trackable) = &tracked.trackable {
                frames_since_tracking_keyframe = 0;
                let selected = match config.keyframes.tracking_keyframe_seeds {
                    TrackingKeyframeSeeds::All => vec![true; trackable.len()],
                    TrackingKeyframeSeeds::Uncovered => uncovered_points(),
                };
                Some((KeyframeKind::Tracking, selected))
            } else if usable
                && frames_since_tracking_keyframe
                    .is_multiple_of(config.keyframes.mapping_keyframe_every)
            {
                Some((KeyframeKind::Mapping, uncovered_points()))
            } else {
                None
            };
            if let Some((kind, selected)) = keyframe {
                let seed_frame = SeedFrame {
                    points: &tracked.frame_points,
                    world_from_camera: &tracked.world_from_camera,
                    rgb: &frame.rgb,
                    intrinsics: &frame.intrinsics,
                };
                let new_gaussians =
                    seed_gaussians(&seed_frame, &selected, &config.tracking, &config.keyframes);
                corrections.record_coverage_points(coverage.next_id(), frame.timestamp);
                coverage.insert(&new_gaussians);
                let keyframe_id = tracking_keyframes + mapping_keyframes;
                corrections.record_keyframe(keyframe_id, frame.timestamp, tracked_pose);
                if let Some(swarm) = swarm.as_mut() {
                    // Published in the tracked frame, the consensus's frame for this agent.
                    let mut gaussians = new_gaussians.clone();
                    gaussians.transform_rigid(&RigidTransform::from(
                        &corrections.tracked_from_local(frame.timestamp),
                    ));
                    swarm.on_keyframe(PublishableKeyframe {
                        keyframe_id: keyframe_id as u64,
                        frame_index: frame.index as u64,
                        timestamp_s: frame.timestamp,
                        agent_from_camera: tracked_pose,
                        intrinsics: frame.intrinsics,
                        rgb: frame.rgb.clone(),
                        depth: frame.depth.clone(),
                        gaussians,
                    });
                }
                match kind {
                    KeyframeKind::Tracking => tracking_keyframes += 1,
                    KeyframeKind::Mapping => mapping_keyframes += 1,
                }
                tracing::debug!(
                    frame = frame.index,
                    ?kind,
                    new_gaussians = new_gaussians.len(),
                    "keyframe"
                );
                mapper.add_keyframe(MappingKeyframe {
                    keyframe_id,
                    frame_index: frame.index,
                    kind,
                    world_from_camera: tracked.world_from_camera,
                    intrinsics: frame.intrinsics,
                    rgb: frame.rgb.clone(),
                    depth: frame.depth.clone(),
                    new_gaussians,
                });
            }
            if let Some(swarm) = swarm.as_mut()
                && let Some(correction) = swarm.after_frame()
            {
                corrections.apply(
                    &correction,
                    frame.timestamp,
                    LocalMaps {
                        odometry: &mut odometry,
                        coverage: &mut coverage,
                        mapper: &mapper,
                    },
                );
            }
            tracking_ms.push(clock.elapsed().as_secs_f64() * 1e3);
            poses.push(TrackedPose {
                position: item.position,
                timestamp: frame.timestamp,
                world_from_camera: tracked_pose,
                ground_truth: frame.world_from_camera_gt,
            });
            progress.inc(1);
            progress_file.update(|| {
                snapshot(
                    Stage::Tracking,
                    poses.len(),
                    tracking_keyframes + mapping_keyframes,
                    &swarm,
                )
            });
            if poses.len().is_multiple_of(PROGRESS_MESSAGE_EVERY) {
                progress.set_message(format!(
                    "{} keyframes, {} Gaussians, {} mapping iterations",
                    tracking_keyframes + mapping_keyframes,
                    mapper.progress.gaussians.load(Ordering::Relaxed),
                    mapper.progress.iterations.load(Ordering::Relaxed)
                ));
            }
            let stopped_by_consensus = swarm.as_ref().and_then(|s| s.stop_requested());
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
    let keyframes = tracking_keyframes + mapping_keyframes;
    progress_file.write(&snapshot(Stage::Finishing, poses.len(), keyframes, &swarm));
    let refine_iterations = if interrupted {
        0
    } else {
        options.refine_iterations
    };
    let outcome = mapper.finish(refine_iterations)?;

    // Outputs that need no rendering first: an interrupted evaluation still leaves these.
    let trajectory =
        Trajectory::from_pairs(poses.iter().map(|p| (p.timestamp, p.world_from_camera)));
    let trajectory_path = options.out.join("trajectory.tum");
    trajectory.write_tum(&trajectory_path)?;
    // Ground truth next to the estimate (evaluation only: evo and the swarm report read it).
    let ground_truth: Vec<(f64, Isometry3<f64>)> = poses
        .iter()
        .filter_map(|p| Some((p.timestamp, p.ground_truth?)))
        .collect();
    if !ground_truth.is_empty() {
        Trajectory::from_pairs(ground_truth).write_tum(&options.out.join("groundtruth.tum"))?;
    }
    let map_path = options.out.join("map.ply");
    render_core::ply::save_ply(&map_path, &outcome.realtime_map)
        .with_context(|| format!("writing {}", map_path.display()))?;
    if let Some((refined_map, _)) = &outcome.refined {
        let path = options.out.join("map_refined.ply");
        render_core::ply::save_ply(&path, refined_map)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    // The consensus reads trajectory.tum once this agent has said goodbye, so that goes first;
    // the evaluation below takes a while and needs nothing from the swarm.
    let swarm_summary = swarm.map(|link| link.finish(&outcome.realtime_map));
    let ate_stats = trajectory_ate(&poses, &trajectory);

    // The map is in the local-map frame: each frame is rendered where the corrections applied
    // to the map put it (the tracked pose when none were).
    let evaluated: Vec<TrackedPose> = poses
        .iter()
        .enumerate()
        .filter(|(i, _)| i % options.eval_every.max(1) == 0)
        .map(|(_, p)| TrackedPose {
            world_from_camera: corrections.applied().at(p.timestamp) * p.world_from_camera,
            ..*p
        })
        .collect();
    let realtime_quality = evaluate_map(
        &outcome.realtime_map,
        &dataset,
        &evaluated,
        lpips.as_ref(),
        Some(&options.out.join("renders")),
        options.comparison_renders,
    )?;
    let refined = match &outcome.refined {
        Some((map, stats)) => {
            let quality = evaluate_map(
                map,
                &dataset,
                &evaluated,
                lpips.as_ref(),
                Some(&options.out.join("renders_refined")),
                options.comparison_renders,
            )?;
            Some(map_metrics(&quality, map.len(), stats))
        }
        None => None,
    };
    let realtime = map_metrics(
        &realtime_quality,
        outcome.realtime_map.len(),
        &outcome.realtime,
    );
    let stats = odometry.stats();
    let source_stats = source.stats();
    let metrics = AgentMetrics {
        agent_id: options.agent_id,
        dataset: dataset.describe(),
        dataset_spec: options.dataset.clone(),
        frame_range: options.frames.to_string(),
        ate_rmse_m: ate_stats.as_ref().map(|s| s.rmse),
        ate_mean_m: ate_stats.as_ref().map(|s| s.mean),
        psnr: realtime.psnr,
        ssim: realtime.ssim,
        lpips: realtime.lpips,
        depth_l1_cm: realtime.depth_l1_cm,
        frames: poses.len(),
        keyframes: tracking_keyframes + mapping_keyframes,
        tracking_keyframes,
        mapping_keyframes,
        gaussians: outcome.realtime_map.len(),
        tracking_ms_median: median(&tracking_ms).unwrap_or(0.0),
        tracking_ms_p90: quantile(&tracking_ms, 0.9).unwrap_or(0.0),
        mapping_iters_per_s: outcome.realtime.iterations_per_second(),
        mapping_iters: outcome.realtime.iterations,
        fps: if loop_seconds > 0.0 {
            poses.len() as f64 / loop_seconds
        } else {
            0.0
        },
        wall_s: started.elapsed().as_secs_f64(),
        tracking_failures: stats.failures,
        reinitialisations: stats.reinitialisations,
        frames_missing: source_stats.frames_missing,
        frames_broken: source_stats.frames_broken,
        frames_without_depth: source_stats.frames_without_depth,
        eval_frames: realtime_quality.frames,
        eval_every: options.eval_every.max(1),
        mapping_image_downscale: config.mapping.image_downscale,
        peak_rss_mib: peak_rss_mib(),
        interrupted,
        refined,
        swarm: swarm_summary,
        local_corrections: in_swarm.then(|| corrections.stats().clone()),
    };
    let metrics_path = options.out.join("metrics.json");
    std::fs::write(&metrics_path, serde_json::to_string_pretty(&metrics)?)
        .with_context(|| format!("writing {}", metrics_path.display()))?;
    progress_file.write(&snapshot(Stage::Done, poses.len(), keyframes, &None));
    Ok(metrics)
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

fn evaluate_map(
    map: &render_core::types::GaussianCloud,
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
    if let Some(dir) = comparison_dir.filter(|_| comparison_renders > 0) {
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
