//! The `mac-consensus` process: receives every agent's keyframes over iceoryx2, runs the
//! [`Engine`] on a worker thread, sends corrections back, and writes the world map, the agents'
//! world trajectories and consensus.json at the end.
//!
//! Threads, and why:
//! - the main thread owns the transport (iceoryx2 ports stay on the thread that made them): it
//!   waits on the consumers' event (no spinning), joins each keyframe's descriptor and image
//!   (they arrive on different topics, in any order; [`crate::inbox`]), asks agents to publish
//!   again what arrived incomplete, and sends corrections as soon as the worker has them. It
//!   never aligns or solves, so agents are never blocked by the consensus;
//! - the worker thread owns the [`Engine`]: preparing keyframes and solving the pose graph
//!   (about a millisecond) as soon as a keyframe arrives or an alignment finishes;
//! - an aligner thread aligns candidate pairs one at a time (about a second each on a CPU,
//!   longer under load), so no keyframe waits for an alignment before it is placed.
//!
//! The run ends when every expected agent has said goodbye and the worker has aligned every
//! queued candidate, or on SIGINT/SIGTERM (the stop flag); either way every output is written.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;
use config::Config;
use crossbeam_channel::{Receiver, Sender, unbounded};
use geometry::se3::isometry_to_tum;
use geometry::trajectory::Trajectory;
use metrics::stats::median;
use nalgebra::Isometry3;
use protocol::convert;
use protocol::messages::{
    ControlMessage, FINAL_MAP_KEYFRAME_ID, KeyframePose, LifecycleKind, Pose,
};
use protocol::transport::{ConsumerLink, Incoming, TransportConfig};
use render_core::types::GaussianCloud;
use serde::Serialize;

use crate::alignment::Keyframe;
use crate::engine::{
    AttemptKind, ClosureEvent, Engine, Finished, Job, KeyframeArrival, KeyframeInfo,
};
use crate::inbox::KeyframeInbox;
use crate::place_recognition::KeyframeRef;
use crate::refinement::{self, RefinementReport};

/// What to run and where to write.
#[derive(Debug, Clone)]
pub struct ConsensusOptions {
    pub config: Config,
    pub transport: TransportConfig,
    /// Output directory; agent K's own outputs are expected in `out/agent_K/`.
    pub out: PathBuf,
    /// Agents the run waits for: it ends once all of them have said goodbye. `None`: run until
    /// stopped.
    pub expected_agents: Option<u32>,
    /// On a stop request (SIGINT / SIGTERM), ask every agent still running to stop too
    /// (`ControlMessage::Shutdown`: each finishes its frame, sends its final map and says
    /// goodbye) and wait up to this long for their goodbyes before writing the outputs, so
    /// the outputs include everything the agents had. `None`: stop at once and leave the
    /// agents running (they go on without a consensus).
    pub stop_agents_wait: Option<Duration>,
}

/// Messages to the worker.
enum WorkerInput {
    Keyframe(Box<KeyframeArrival>, Instant),
    Gaussians(KeyframeRef, GaussianCloud),
    /// Write the outputs as they stand now (on request: SIGUSR1), without refinement.
    Snapshot(Box<SnapshotRequest>),
}

/// What the main thread knows that a snapshot's consensus.json needs.
struct SnapshotRequest {
    agents: BTreeMap<u32, AgentRecord>,
    latencies: Vec<f64>,
    wall_s: f64,
}

/// A pose-graph solution, as the main thread forwards it.
struct SolutionUpdate {
    world_from_agent: BTreeMap<u32, Isometry3<f64>>,
    world_from_camera: BTreeMap<KeyframeRef, Isometry3<f64>>,
}

/// Per agent, what the process saw of it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct AgentRecord {
    pub hellos: usize,
    pub goodbyes: usize,
    pub config_hash: u64,
    pub keyframes: usize,
    pub gaussians_received: usize,
    pub gaps: usize,
    /// `ResendKeyframe` requests sent for keyframes that arrived incomplete.
    pub resend_requests: usize,
    /// Keyframes still missing a part at the end (descriptor, image or patch).
    pub keyframes_incomplete: usize,
    /// Keyframe parts that arrived more than once (ignored).
    pub duplicate_parts: usize,
    /// Keyframe images whose id this agent had already used for another frame (ignored): a
    /// restart that did not re-run the same frames numbers its keyframes from 0 again.
    pub keyframe_id_conflicts: usize,
    /// Restarts found to run on other frames (their hello's run anchor differs from the
    /// agent's first run's): each tracks in a frame of its own, which the consensus cannot
    /// place, so everything such a run publishes is ignored (see `KeyframeInbox`).
    pub restarts_on_other_frames: usize,
    /// Keyframe parts (descriptors, images, patches, final map) of those restarts, ignored.
    pub restart_parts_ignored: usize,
    /// Whether the agent's last run was such a restart: its corrections are withheld (they
    /// would name keyframes it does not have) and its trajectory file, written in its own
    /// frame, is not turned into a world trajectory.
    pub last_run_on_other_frames: bool,
    /// Corrections not sent because the agent's running process is such a restart.
    pub corrections_withheld: usize,
    pub corrections_sent: usize,
    pub corrections_undelivered: usize,
    /// `world_from_agent` as `[tx, ty, tz, qx, qy, qz, qw]` (TUM order); absent when the agent
    /// was never linked to the world.
    pub world_from_agent: Option<[f64; 7]>,
    pub bytes_received: u64,
    pub seconds_seen: f64,
}

/// consensus.json.
#[derive(Debug, Clone, Serialize)]
pub struct ConsensusReport {
    pub agents: BTreeMap<u32, AgentRecord>,
    pub keyframes: usize,
    pub closures_proposed: usize,
    pub closures_verified: usize,
    pub closures_rejected_by_alignment: usize,
    pub loop_closures_accepted: usize,
    pub loop_closures_rejected: usize,
    pub inter_agent_closures_accepted: usize,
    /// From a keyframe's arrival to the first correction that includes it.
    pub consensus_latency_ms_median: Option<f64>,
    pub consensus_latency_ms: Vec<f64>,
    pub pose_graph_solve_ms_median: Option<f64>,
    pub merged_gaussians: usize,
    pub unplaced_gaussians: usize,
    /// The joint photometric refinement of the merged map (`null`: not run).
    pub refinement: Option<RefinementReport>,
    pub wall_s: f64,
    pub interrupted: bool,
    /// Written on request while the run went on (no refinement; later outputs replace it).
    pub snapshot: bool,
    /// Per pair of agents (`"A-B"`, A < B), what linking them took: every attempt is in
    /// `events` (with its kind, inliers, overlap and reason); this is their tally.
    pub agent_pairs: BTreeMap<String, PairAttempts>,
    pub events: Vec<ClosureEvent>,
    pub keyframe_info: Vec<(KeyframeRef, KeyframeInfo)>,
}

/// The inter-agent attempts of one pair of agents (consensus.json `agent_pairs`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct PairAttempts {
    pub keyframe_attempts: usize,
    pub map_attempts: usize,
    /// Attempts that alignment or map registration verified.
    pub verified: usize,
    /// Verified attempts the robust pose graph kept.
    pub accepted: usize,
    /// Why the most recent refused attempt was refused.
    pub last_rejection: Option<String>,
}

/// Tallies the inter-agent attempts of `events` per pair of agents.
fn pair_attempts(events: &[ClosureEvent]) -> BTreeMap<String, PairAttempts> {
    let mut pairs: BTreeMap<(u32, u32), PairAttempts> = BTreeMap::new();
    for event in events.iter().filter(|e| e.inter_agent) {
        let (a, b) = (event.source.agent_id, event.target.agent_id);
        let pair = pairs.entry((a.min(b), a.max(b))).or_default();
        match event.kind {
            AttemptKind::Keyframe => pair.keyframe_attempts += 1,
            AttemptKind::Map => pair.map_attempts += 1,
        }
        pair.verified += usize::from(event.verified);
        pair.accepted += usize::from(event.accepted_by_pose_graph == Some(true));
        if let Some(reason) = &event.rejection {
            pair.last_rejection = Some(reason.clone());
        }
    }
    pairs
        .into_iter()
        .map(|((a, b), attempts)| (format!("{a}-{b}"), attempts))
        .collect()
}

/// Runs the consensus until the expected agents are done or `stop` is raised.
pub fn run(options: &ConsensusOptions, stop: &AtomicBool) -> anyhow::Result<ConsensusReport> {
    run_with_snapshots(options, stop, &AtomicBool::new(false))
}

/// [`run`], and each time `snapshot` is raised (the flag is lowered again), the outputs are
/// written as they stand (merged map without refinement, world trajectories, consensus.json with
/// `snapshot: true`) while the run goes on.
pub fn run_with_snapshots(
    options: &ConsensusOptions,
    stop: &AtomicBool,
    snapshot: &AtomicBool,
) -> anyhow::Result<ConsensusReport> {
    let _span = tracing::info_span!("consensus").entered();
    std::fs::create_dir_all(&options.out)
        .with_context(|| format!("creating output directory {}", options.out.display()))?;
    let started = Instant::now();
    let mut link = ConsumerLink::open(&options.transport).context("opening the transport")?;
    tracing::info!(namespace = %options.transport.namespace, "consensus listening");

    let (input_tx, input_rx) = unbounded::<WorkerInput>();
    let (solution_tx, solution_rx) = unbounded::<SolutionUpdate>();
    let (latency_tx, latency_rx) = unbounded::<f64>();
    let worker = spawn_worker(options.clone(), input_rx, solution_tx, latency_tx)?;

    let mut agents: BTreeMap<u32, AgentRecord> = BTreeMap::new();
    let mut first_seen: BTreeMap<u32, Instant> = BTreeMap::new();
    let mut finished: BTreeSet<u32> = BTreeSet::new();
    let mut inbox = KeyframeInbox::new(options.config.consensus.resend.clone());
    let mut world_from_agent: BTreeMap<u32, Isometry3<f64>> = BTreeMap::new();
    let mut interrupted = false;
    let mut latencies: Vec<f64> = Vec::new();
    let wait = options.transport.wait_slice;

    // When the agents were asked to stop (with `stop_agents_wait`).
    let mut agents_asked_to_stop: Option<Instant> = None;
    loop {
        if stop.load(Ordering::Relaxed) {
            interrupted = true;
            let running = running_agents(&agents, &finished);
            // With `stop_agents_wait`, the loop goes on receiving (the agents' last keyframes,
            // final maps and goodbyes) until they are done or the wait is over.
            let mut waiting = false;
            if let Some(wait_for_agents) = options.stop_agents_wait {
                let asked = *agents_asked_to_stop.get_or_insert_with(|| {
                    ask_agents_to_stop(&mut link, &running);
                    Instant::now()
                });
                waiting = !running.is_empty() && asked.elapsed() < wait_for_agents;
                if !waiting && !running.is_empty() {
                    tracing::warn!(
                        agents = ?running,
                        "agents did not say goodbye within {wait_for_agents:?}"
                    );
                }
            }
            if !waiting {
                tracing::warn!("stop requested: writing outputs");
                break;
            }
        }
        if let Some(expected) = options.expected_agents
            && (0..expected).all(|id| finished.contains(&id))
        {
            tracing::info!("every agent said goodbye");
            break;
        }
        match link.recv_timeout(wait) {
            Ok(Some(message)) => {
                let agent_id = message.agent_id();
                let record = agents.entry(agent_id).or_default();
                first_seen.entry(agent_id).or_insert_with(Instant::now);
                if matches!(
                    message.delivery(),
                    protocol::transport::Delivery::Gap { .. }
                ) {
                    record.gaps += 1;
                    tracing::warn!(agent_id, topic = %message.topic(), "messages lost");
                }
                handle(message, record, &mut inbox, &mut finished, &input_tx)?;
            }
            Ok(None) => {}
            Err(error) => tracing::warn!(%error, "receive failed"),
        }
        request_resends(&mut link, &mut inbox, &finished, &mut agents);
        for update in solution_rx.try_iter() {
            send_corrections(&mut link, &update, &inbox, &mut agents);
            world_from_agent = update.world_from_agent;
        }
        latencies.extend(latency_rx.try_iter());
        if snapshot.swap(false, Ordering::Relaxed) {
            tracing::info!("snapshot requested: writing the outputs as they stand");
            let mut records = agents.clone();
            fill_records(&mut records, &world_from_agent, &link, &first_seen);
            fill_inbox_counts(&mut records, &inbox);
            input_tx
                .send(WorkerInput::Snapshot(Box::new(SnapshotRequest {
                    agents: records,
                    latencies: latencies.clone(),
                    wall_s: started.elapsed().as_secs_f64(),
                })))
                .context("the consensus worker stopped")?;
        }
    }

    // Let the worker finish its queue (it ends when the input channel closes).
    drop(input_tx);
    let mut engine = worker
        .join()
        .map_err(|_| anyhow::anyhow!("the consensus worker thread panicked"))?;
    for update in solution_rx.try_iter() {
        send_corrections(&mut link, &update, &inbox, &mut agents);
        world_from_agent = update.world_from_agent;
    }
    latencies.extend(latency_rx.try_iter());
    fill_records(&mut agents, &world_from_agent, &link, &first_seen);
    fill_inbox_counts(&mut agents, &inbox);
    for (agent_id, record) in agents.iter_mut() {
        if record.keyframes_incomplete > 0 {
            tracing::warn!(
                agent_id,
                keyframes = record.keyframes_incomplete,
                "keyframes never arrived complete"
            );
        }
    }
    let (map, unplaced) = engine.merged_map();
    write_progress(&options.out, &engine, ProgressStage::Refining);
    let (map, refinement) = refine_world_map(options, &mut engine, map, interrupted)?;
    let report = write_outputs(
        options,
        &engine,
        WorldMap {
            map,
            unplaced,
            refinement,
        },
        agents,
        latencies,
        started.elapsed().as_secs_f64(),
        if interrupted {
            OutputKind::Interrupted
        } else {
            OutputKind::Final
        },
    )?;
    write_progress(&options.out, &engine, ProgressStage::Done);
    Ok(report)
}

/// Copies the inbox's per-agent counts into the records.
fn fill_inbox_counts(agents: &mut BTreeMap<u32, AgentRecord>, inbox: &KeyframeInbox) {
    for (agent_id, record) in agents.iter_mut() {
        record.keyframes_incomplete = inbox.incomplete(*agent_id);
        record.duplicate_parts = inbox.duplicates(*agent_id);
        record.keyframe_id_conflicts = inbox.conflicts(*agent_id);
        record.restarts_on_other_frames = inbox.foreign_incarnations(*agent_id);
        record.restart_parts_ignored = inbox.foreign_parts(*agent_id);
        record.last_run_on_other_frames = inbox.latest_is_foreign(*agent_id);
    }
}

/// Completes the per-agent records with what the transport and the solution know.
fn fill_records(
    agents: &mut BTreeMap<u32, AgentRecord>,
    world_from_agent: &BTreeMap<u32, Isometry3<f64>>,
    link: &ConsumerLink,
    first_seen: &BTreeMap<u32, Instant>,
) {
    let bandwidth = link.bandwidth();
    for (id, record) in agents.iter_mut() {
        record.world_from_agent = world_from_agent.get(id).map(isometry_to_tum);
        record.bytes_received = bandwidth
            .entries
            .iter()
            .filter(|e| e.agent_id == *id)
            .map(|e| e.traffic.bytes)
            .sum();
        record.seconds_seen = first_seen
            .get(id)
            .map_or(0.0, |at| at.elapsed().as_secs_f64());
    }
}

/// Agents that said hello and have not said goodbye since.
fn running_agents(agents: &BTreeMap<u32, AgentRecord>, finished: &BTreeSet<u32>) -> Vec<u32> {
    agents
        .iter()
        .filter(|(id, record)| record.hellos > 0 && !finished.contains(id))
        .map(|(id, _)| *id)
        .collect()
}

/// Sends `ControlMessage::Shutdown` to each of `agent_ids`.
fn ask_agents_to_stop(link: &mut ConsumerLink, agent_ids: &[u32]) {
    if agent_ids.is_empty() {
        return;
    }
    tracing::warn!(
        agents = ?agent_ids,
        "stop requested: asking the running agents to stop and send their final maps"
    );
    let message = ControlMessage::Shutdown {
        reason: "the consensus was asked to stop".into(),
    };
    for &agent_id in agent_ids {
        if let Err(error) = link.send_control(agent_id, &message) {
            tracing::warn!(agent_id, %error, "stop request not delivered");
        }
    }
}

/// Routes one received message.
fn handle(
    message: Incoming,
    record: &mut AgentRecord,
    inbox: &mut KeyframeInbox,
    finished: &mut BTreeSet<u32>,
    to_worker: &Sender<WorkerInput>,
) -> anyhow::Result<()> {
    let agent_id = message.agent_id();
    let epoch = message.stamp().epoch;
    match message {
        Incoming::Lifecycle(lifecycle) => match lifecycle.kind() {
            Ok(LifecycleKind::Hello) => {
                record.hellos += 1;
                if record.hellos > 1 && record.config_hash != lifecycle.config_hash {
                    tracing::warn!(agent_id, "agent restarted with a different configuration");
                }
                record.config_hash = lifecycle.config_hash;
                inbox.hello(agent_id, epoch, lifecycle.run_anchor);
                // A restarted agent is back in the run; its previous process's incomplete
                // keyframes are gone with it.
                finished.remove(&agent_id);
                if record.hellos > 1 {
                    inbox.forget_incomplete(agent_id);
                }
                tracing::info!(agent_id, "agent joined");
            }
            Ok(LifecycleKind::Alive) => {}
            Ok(LifecycleKind::Goodbye) => {
                record.goodbyes += 1;
                finished.insert(agent_id);
                tracing::info!(agent_id, "agent left");
            }
            Err(error) => tracing::warn!(agent_id, %error, "lifecycle message ignored"),
        },
        Incoming::Descriptor(descriptor) => {
            let id = KeyframeRef {
                agent_id,
                keyframe_id: descriptor.keyframe_id,
            };
            if let Some(arrival) =
                inbox.descriptor(id, epoch, descriptor.descriptor.to_vec(), Instant::now())
            {
                forward(arrival, record, to_worker)?;
            }
        }
        Incoming::KeyframeImage(image) => {
            let header = image.header();
            let id = KeyframeRef {
                agent_id,
                keyframe_id: header.keyframe_id,
            };
            let (rgb, depth) = convert::rgbd_images(header.width, header.height, image.pixels());
            let keyframe = Keyframe {
                id,
                rgb,
                depth,
                intrinsics: (&header.intrinsics).into(),
                agent_from_camera: header.camera_to_agent_world.to_isometry(),
            };
            if let Some(arrival) = inbox.image(
                id,
                epoch,
                keyframe,
                header.frame_index,
                header.timestamp_s,
                Instant::now(),
            ) {
                forward(arrival, record, to_worker)?;
            }
        }
        Incoming::Patch(patch) => {
            let id = KeyframeRef {
                agent_id,
                keyframe_id: patch.header().keyframe_id,
            };
            if id.keyframe_id == FINAL_MAP_KEYFRAME_ID {
                if inbox.ignores(agent_id, epoch) {
                    tracing::warn!(
                        agent_id,
                        "final map of a run restarted on other frames (a frame of its own): \
                         ignored"
                    );
                    return Ok(());
                }
            } else if !inbox.patch(id, epoch, Instant::now()) {
                // Already stored (a resend crossing a late original), or from a run restarted
                // on other frames.
                return Ok(());
            }
            let (cloud, dropped) = convert::gaussian_cloud(patch.records());
            if dropped > 0 {
                tracing::warn!(
                    agent_id,
                    dropped,
                    "patch records with non-finite values dropped"
                );
            }
            record.gaussians_received += cloud.len();
            to_worker
                .send(WorkerInput::Gaussians(id, cloud))
                .context("the consensus worker stopped")?;
        }
    }
    Ok(())
}

/// Hands a keyframe whose descriptor and image are both there to the worker.
fn forward(
    arrival: KeyframeArrival,
    record: &mut AgentRecord,
    to_worker: &Sender<WorkerInput>,
) -> anyhow::Result<()> {
    record.keyframes += 1;
    to_worker
        .send(WorkerInput::Keyframe(Box::new(arrival), Instant::now()))
        .context("the consensus worker stopped")
}

/// Asks agents to publish again the keyframes that waited too long for a missing part.
fn request_resends(
    link: &mut ConsumerLink,
    inbox: &mut KeyframeInbox,
    finished: &BTreeSet<u32>,
    agents: &mut BTreeMap<u32, AgentRecord>,
) {
    for request in inbox.due_requests(Instant::now(), finished) {
        let agent_id = request.keyframe.agent_id;
        tracing::warn!(
            agent_id,
            keyframe_id = request.keyframe.keyframe_id,
            reason = %request.reason,
            "keyframe incomplete: asking the agent to publish it again"
        );
        agents.entry(agent_id).or_default().resend_requests += 1;
        let message = ControlMessage::ResendKeyframe {
            keyframe_id: request.keyframe.keyframe_id,
            reason: request.reason,
        };
        if let Err(error) = link.send_control(agent_id, &message) {
            // Asked again after the next wait, up to the configured number of requests.
            tracing::debug!(agent_id, %error, "resend request not delivered");
        }
    }
}

fn spawn_worker(
    options: ConsensusOptions,
    inputs: Receiver<WorkerInput>,
    solutions: Sender<SolutionUpdate>,
    latencies: Sender<f64>,
) -> anyhow::Result<JoinHandle<Engine>> {
    std::thread::Builder::new()
        .name("consensus-worker".into())
        .spawn(move || {
            let _span = tracing::info_span!("consensus worker").entered();
            let mut worker = Worker {
                engine: Engine::new(options.config.consensus.clone()),
                options,
                waiting: BTreeMap::new(),
                early_gaussians: BTreeMap::new(),
            };
            // Alignments run on their own thread, one at a time, so that a slow one (seconds
            // on a loaded CPU, tens of seconds for a hopeless pair) never holds up new
            // keyframes: those are prepared, placed by their odometry edges and solved (about a
            // millisecond) while it runs, and their agents get corrections at once.
            let (job_tx, job_rx) = crossbeam_channel::bounded::<Job>(1);
            let (done_tx, done_rx) = crossbeam_channel::bounded::<Finished>(1);
            let aligner = std::thread::Builder::new()
                .name("consensus-aligner".into())
                .spawn(move || {
                    let _span = tracing::info_span!("consensus aligner").entered();
                    for job in job_rx {
                        if done_tx.send(job.run()).is_err() {
                            break;
                        }
                    }
                })
                .expect("starting the consensus aligner thread");
            let no_inputs = crossbeam_channel::never();
            let no_alignment = crossbeam_channel::never();
            let mut open = true;
            let mut in_flight = false;
            let mut last_progress: Option<Instant> = None;
            loop {
                if last_progress.is_none_or(|at| at.elapsed() >= PROGRESS_INTERVAL) {
                    write_progress(&worker.options.out, &worker.engine, ProgressStage::Aligning);
                    last_progress = Some(Instant::now());
                }
                if !in_flight && let Some(job) = worker.engine.next_job() {
                    in_flight = job_tx.send(job).is_ok();
                }
                if !in_flight && !open {
                    break;
                }
                // Wait for whichever comes first: an input or the running alignment (a closed
                // input or no alignment in flight waits on a channel that never delivers).
                let live_inputs = if open { &inputs } else { &no_inputs };
                let live_done = if in_flight { &done_rx } else { &no_alignment };
                crossbeam_channel::select! {
                    recv(live_inputs) -> input => match input {
                        Ok(input) => worker.take(input),
                        Err(_) => open = false,
                    },
                    recv(live_done) -> done => match done {
                        Ok(done) => {
                            in_flight = false;
                            worker.engine.record(done);
                        }
                        Err(_) => break,
                    },
                }
                while open {
                    match inputs.try_recv() {
                        Ok(input) => worker.take(input),
                        Err(crossbeam_channel::TryRecvError::Empty) => break,
                        Err(crossbeam_channel::TryRecvError::Disconnected) => open = false,
                    }
                }
                if let Some(update) = worker.solve(&latencies)
                    && solutions.send(update).is_err()
                {
                    break;
                }
            }
            drop(job_tx);
            if aligner.join().is_err() {
                tracing::error!("the consensus aligner thread panicked");
            }
            worker.engine
        })
        .context("starting the consensus worker thread")
}

/// How often the worker rewrites consensus_progress.json at most.
const PROGRESS_INTERVAL: std::time::Duration = std::time::Duration::from_millis(500);

/// What the consensus is doing, for the progress display.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(rename_all = "snake_case")]
enum ProgressStage {
    Aligning,
    Refining,
    Done,
}

/// OUT/consensus_progress.json, read by scripts/launch_swarm.sh's progress line: one flat JSON
/// object, written to a temporary file and renamed so a reader never sees half of it. A failed
/// write is logged at debug level only: progress is a display, never a reason to stop.
fn write_progress(out: &Path, engine: &Engine, stage: ProgressStage) {
    #[derive(Serialize)]
    struct Progress {
        stage: ProgressStage,
        keyframes: usize,
        closures_verified: usize,
        closures_rejected: usize,
        inter_agent_closures: usize,
        pending_alignments: usize,
    }
    let events = engine.events();
    let progress = Progress {
        stage,
        keyframes: engine.keyframes().len(),
        closures_verified: events.iter().filter(|e| e.verified).count(),
        closures_rejected: events.iter().filter(|e| !e.verified).count(),
        inter_agent_closures: events
            .iter()
            .filter(|e| e.verified && e.inter_agent)
            .count(),
        pending_alignments: engine.pending(),
    };
    let path = out.join("consensus_progress.json");
    let temporary = out.join(".consensus_progress.json.tmp");
    let written = serde_json::to_string(&progress)
        .map_err(std::io::Error::other)
        .and_then(|text| std::fs::write(&temporary, text))
        .and_then(|()| std::fs::rename(&temporary, &path));
    if let Err(error) = written {
        tracing::debug!(%error, path = %path.display(), "progress not written");
    }
}

/// The worker thread's state.
struct Worker {
    engine: Engine,
    options: ConsensusOptions,
    /// Keyframes whose first correction has not gone out yet, with their arrival time.
    waiting: BTreeMap<KeyframeRef, Instant>,
    /// Gaussians that arrived before their keyframe's images.
    early_gaussians: BTreeMap<KeyframeRef, GaussianCloud>,
}

impl Worker {
    fn take(&mut self, input: WorkerInput) {
        match input {
            WorkerInput::Keyframe(mut arrival, at) => {
                let id = arrival.keyframe.id;
                if let Some(cloud) = self.early_gaussians.remove(&id) {
                    arrival.gaussians = cloud;
                }
                if self.engine.add_keyframe(*arrival) {
                    self.waiting.insert(id, at);
                }
            }
            WorkerInput::Gaussians(id, cloud) => {
                if let Err(cloud) = self.engine.set_gaussians(id, cloud) {
                    self.early_gaussians.insert(id, cloud);
                }
            }
            WorkerInput::Snapshot(request) => {
                let (map, unplaced) = self.engine.merged_map();
                let written = write_outputs(
                    &self.options,
                    &self.engine,
                    WorldMap {
                        map,
                        unplaced,
                        refinement: None,
                    },
                    request.agents,
                    request.latencies,
                    request.wall_s,
                    OutputKind::Snapshot,
                );
                match written {
                    Ok(_) => tracing::info!(out = %self.options.out.display(), "snapshot written"),
                    Err(error) => tracing::error!(%error, "snapshot not written"),
                }
            }
        }
    }

    /// Solves if anything changed; the update to forward, and the latency of every keyframe
    /// it places for the first time.
    fn solve(&mut self, latencies: &Sender<f64>) -> Option<SolutionUpdate> {
        let solution = self.engine.solve_if_changed()?;
        let update = SolutionUpdate {
            world_from_agent: solution
                .world_from_agent
                .iter()
                .filter_map(|(id, t)| Some((*id, (*t)?)))
                .collect(),
            world_from_camera: solution.world_from_camera.clone(),
        };
        self.waiting.retain(|id, at| {
            if update.world_from_camera.contains_key(id) {
                // The main thread may be gone at shutdown; the figure is then not needed.
                let _ = latencies.send(at.elapsed().as_secs_f64() * 1e3);
                false
            } else {
                true
            }
        });
        Some(update)
    }
}

fn send_corrections(
    link: &mut ConsumerLink,
    update: &SolutionUpdate,
    inbox: &KeyframeInbox,
    agents: &mut BTreeMap<u32, AgentRecord>,
) {
    for (agent_id, world_from_agent) in &update.world_from_agent {
        if inbox.latest_is_foreign(*agent_id) {
            // Its keyframe ids name other frames in the running process.
            agents.entry(*agent_id).or_default().corrections_withheld += 1;
            continue;
        }
        let poses: Vec<KeyframePose> = update
            .world_from_camera
            .iter()
            .filter(|(id, _)| id.agent_id == *agent_id)
            .map(|(id, pose)| KeyframePose {
                keyframe_id: id.keyframe_id,
                camera_to_world: Pose::from(pose),
            })
            .collect();
        let record = agents.entry(*agent_id).or_default();
        match link.send_correction(*agent_id, Pose::from(world_from_agent), &poses) {
            Ok(_) => record.corrections_sent += 1,
            Err(error) => {
                // An agent that left or crashed simply misses this correction; the final
                // outputs carry it anyway.
                record.corrections_undelivered += 1;
                tracing::debug!(agent_id, %error, "correction not delivered");
            }
        }
    }
}

/// The agent's own per-frame trajectory (its frame), written by the agent next to ours.
pub fn agent_trajectory_path(out: &Path, agent_id: u32) -> PathBuf {
    out.join(format!("agent_{agent_id}")).join("trajectory.tum")
}

/// The merged world map as written.
struct WorldMap {
    map: GaussianCloud,
    /// Gaussians of agents not placed in the world (left out of `map`).
    unplaced: usize,
    refinement: Option<RefinementReport>,
}

/// The joint photometric refinement of the merged map (skipped when turned off, when the run was
/// interrupted, or before any solution); the refined keyframe poses go into the engine, so the
/// world trajectories follow them. The unrefined map is kept as map_realtime.ply. A refinement
/// that fails is logged and the unrefined map is used: nothing computed is lost.
fn refine_world_map(
    options: &ConsensusOptions,
    engine: &mut Engine,
    map: GaussianCloud,
    interrupted: bool,
) -> anyhow::Result<(GaussianCloud, Option<RefinementReport>)> {
    let consensus = &options.config.consensus;
    if consensus.refinement.iterations == 0 || interrupted || map.is_empty() {
        return Ok((map, None));
    }
    let Some(problem) = engine.refinement_problem(map.clone()) else {
        return Ok((map, None));
    };
    let realtime_path = options.out.join("map_realtime.ply");
    render_core::ply::save_ply(&realtime_path, &map)
        .with_context(|| format!("writing {}", realtime_path.display()))?;
    match refinement::refine(problem, consensus) {
        Ok(outcome) => {
            if consensus.refinement.refine_poses {
                engine.apply_refined_poses(&outcome.world_from_camera);
            }
            Ok((outcome.map, Some(outcome.report)))
        }
        Err(error) => {
            tracing::error!(%error, "joint refinement failed: writing the unrefined map");
            Ok((map, None))
        }
    }
}

/// Why outputs are written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum OutputKind {
    /// Every expected agent said goodbye.
    Final,
    /// SIGINT / SIGTERM.
    Interrupted,
    /// On request while the run goes on.
    Snapshot,
}

fn write_outputs(
    options: &ConsensusOptions,
    engine: &Engine,
    world: WorldMap,
    agents: BTreeMap<u32, AgentRecord>,
    latencies: Vec<f64>,
    wall_s: f64,
    kind: OutputKind,
) -> anyhow::Result<ConsensusReport> {
    let out = &options.out;
    let WorldMap {
        map,
        unplaced,
        refinement,
    } = world;
    let map_path = out.join("map.ply");
    render_core::ply::save_ply(&map_path, &map)
        .with_context(|| format!("writing {}", map_path.display()))?;
    for (agent_id, record) in &agents {
        if record.last_run_on_other_frames {
            tracing::warn!(
                agent_id,
                "the agent's last run restarted on other frames, in a frame of its own: no world \
                 trajectory written from its trajectory file"
            );
            continue;
        }
        let path = agent_trajectory_path(out, *agent_id);
        if !path.exists() {
            tracing::warn!(agent_id, path = %path.display(), "no agent trajectory to correct");
            continue;
        }
        let tracked = Trajectory::read_tum(&path)
            .with_context(|| format!("reading agent {agent_id}'s trajectory"))?;
        let pairs: Vec<(f64, Isometry3<f64>)> = tracked
            .stamps
            .iter()
            .copied()
            .zip(tracked.poses.iter().copied())
            .collect();
        match engine.world_trajectory(*agent_id, &pairs) {
            Some(world) => {
                let target = out.join(format!("agent_{agent_id}.tum"));
                Trajectory::from_pairs(world)
                    .write_tum(&target)
                    .with_context(|| format!("writing {}", target.display()))?;
            }
            None => tracing::warn!(
                agent_id,
                "agent not linked to the world frame: no world trajectory written"
            ),
        }
    }
    let events = engine.events().to_vec();
    let solution = engine.solution();
    let accepted = solution.map_or(0, |s| s.accepted_loops());
    let report = ConsensusReport {
        keyframes: engine.keyframes().len(),
        closures_proposed: events.len(),
        closures_verified: events.iter().filter(|e| e.verified).count(),
        closures_rejected_by_alignment: events.iter().filter(|e| !e.verified).count(),
        loop_closures_accepted: accepted,
        loop_closures_rejected: events.len() - accepted,
        inter_agent_closures_accepted: solution.map_or(0, |s| {
            s.loops
                .iter()
                .filter(|l| l.inter_agent && l.accepted)
                .count()
        }),
        consensus_latency_ms_median: median(&latencies),
        consensus_latency_ms: latencies,
        pose_graph_solve_ms_median: median(engine.solve_ms()),
        merged_gaussians: map.len(),
        unplaced_gaussians: unplaced,
        refinement,
        wall_s,
        interrupted: kind == OutputKind::Interrupted,
        snapshot: kind == OutputKind::Snapshot,
        agents,
        agent_pairs: pair_attempts(&events),
        events,
        keyframe_info: engine.keyframes().iter().map(|(k, v)| (*k, *v)).collect(),
    };
    let path = out.join("consensus.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(report)
}
