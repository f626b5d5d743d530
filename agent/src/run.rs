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
use nalgebra::Isometry3;
use registration::odometry::{Placement, SegmentId};
use splats::GaussianCloud;

use crate::evaluation::{
    FrameQuality, MapRenderer, QualitySummary, comparison_path, evaluate_frame,
};
use crate::mapper::{MappingOutcome, MappingStats};
use crate::pace::SensorClock;
use crate::pipeline::{AgentPipeline, FinishedPipeline, TrackedPose, progress_snapshot};
use crate::progress::{ProgressFile, Stage};
use crate::source::{FrameSource, LiveInputReport, open_frames};
use crate::swarm::SwarmLink;
use crate::views::{poses_in_map, write_view_files};

pub use crate::report::{AgentMetrics, MapMetrics, metrics_table, peak_rss_mib};
use crate::report::{RunRecord, agent_metrics, map_metrics};

/// Synthetic scene used when no dataset is given: three agents' loops, this agent's share.
pub const DEFAULT_SYNTHETIC_AGENTS: usize = 3;
/// Frames per agent of that scene (10 s at 30 frames per second).
pub const DEFAULT_SYNTHETIC_FRAMES: usize = 300;

/// What to run and where to write.
#[derive(Debug, Clone)]
pub struct AgentOptions {
    /// The agent's configuration (all of configs/*.toml's sections).
    pub config: Config,
    /// Dataset path or `synthetic:...` spec.
    pub dataset: String,
    /// Which frames of the dataset to replay; a live camera takes only [`FrameRange::ALL`].
    pub frames: FrameRange,
    /// This agent's id in the swarm (agent 0's frame is the world frame).
    pub agent_id: u32,
    /// Output folder, created at the start if needed (checked to be writable).
    pub out: PathBuf,
    /// Post-run refinement iterations (0 = none), reported separately.
    pub refine_iterations: usize,
    /// Evaluate rendering quality on every n-th frame.
    pub eval_every: usize,
    /// Comparison images written (spread over the evaluated frames).
    pub comparison_renders: usize,
    /// LPIPS weights (.npz); without them LPIPS is left out.
    pub lpips_weights: Option<PathBuf>,
    /// Threads decoding frames ahead of tracking (at least 1 is used).
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
    let in_swarm = swarm.is_some();
    let mut swarm = swarm;
    let new_pipeline = |swarm, frames_expected| {
        AgentPipeline::new(
            config,
            &options.dataset,
            swarm,
            frames_expected,
            options.agent_id,
            options.live_view.clone(),
        )
    };
    // A live camera sends whether the agent is ready or not: the mapper (its device and
    // shaders, seconds on a loaded CPU) is set up before subscribing, so no frame is dropped
    // to it. A dataset is opened first: a wrong path fails at once.
    let early_pipeline = match datasets::live::is_live(&options.dataset) {
        true => Some(new_pipeline(swarm.take(), 0)?),
        false => None,
    };
    let (dataset, live_camera) = open_frames(options)?;
    tracing::info!(dataset = %dataset.describe(), frames = dataset.len(), "agent starting");
    let lpips = options
        .lpips_weights
        .as_deref()
        .map(|path| {
            Lpips::load(path).with_context(|| format!("loading LPIPS weights {}", path.display()))
        })
        .transpose()?;

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
    let mut agent = match early_pipeline {
        Some(agent) => agent,
        None => new_pipeline(swarm.take(), dataset.len())?,
    };
    let progress = progress_bar(dataset.len());
    let mut progress_file = ProgressFile::new(&options.out);
    let frames_total = live_camera.is_none().then(|| dataset.len());
    progress_file.write(&agent.progress(Stage::Tracking, frames_total));

    let mut interrupted = false;
    // A live camera sets its own pace (and drops what the agent cannot take).
    let mut sensor =
        (config.mapping.pace == Pace::Sensor && live_camera.is_none()).then(SensorClock::new);
    // Frames that do not wait for the tracker: its expensive recovery work is rationed.
    let real_time = sensor.is_some() || live_camera.is_some();
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
            let tracked = agent.track(&item, real_time);
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
    // The map goes in the frame it was fitted in (its keyframes at their refined poses with
    // `refine_keyframe_poses`): moving each Gaussian back to its keyframe's tracked pose tears
    // surfaces seen from several keyframes (docs/method.md, The consensus: joint refinement).
    let swarm_summary = swarm.map(|link| link.finish(&outcome.realtime_map));
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
/// trajectory_segment_K.tum, each in its own frame), tracking.csv (every frame's outcome,
/// confidence and wall times: the loop, the recovery guesses, the map update) and, when the
/// dataset has ground truth, groundtruth.tum next to it (evo and the swarm report read these).
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
        writeln!(
            file,
            "timestamp,frame_position,segment,tracked,confidence,loop_ms,recovery_ms,map_update_ms"
        )?;
        for p in poses {
            let segment = match p.placement {
                Placement::Root => "root".to_string(),
                Placement::Unjoined(segment) => segment.to_string(),
            };
            writeln!(
                file,
                "{:.6},{},{segment},{},{:.4},{:.1},{:.1},{:.1}",
                p.timestamp,
                p.position,
                p.tracked,
                p.confidence,
                p.loop_ms,
                p.recovery_ms,
                p.map_update_ms
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
