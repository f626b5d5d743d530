//! The worker thread: owns the [`Engine`], takes the keyframes and Gaussians the main thread
//! forwards, hands alignment jobs to the aligner thread one at a time, solves, and sends every
//! new solution (and the latency of each keyframe it places) back to the main thread.

use std::collections::BTreeMap;
use std::path::Path;
use std::thread::JoinHandle;
use std::time::Instant;

use anyhow::Context;
use crossbeam_channel::{Receiver, Sender, unbounded};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use splats::GaussianCloud;

use super::ConsensusOptions;
use super::outputs::{AgentRecord, OutputKind, WorldMap, write_outputs};
use crate::engine::{
    CandidateSource, ClosureEvent, Decision, Engine, Finished, Job, KeyframeArrival,
};
use crate::place_recognition::KeyframeRef;
use crate::store::DecisionLog;

/// Messages to the worker.
pub(super) enum WorkerInput {
    Keyframe(Box<KeyframeArrival>, Instant),
    Gaussians(KeyframeRef, GaussianCloud),
    /// Write the outputs as they stand now (on request: SIGUSR1), without refinement.
    Snapshot(Box<SnapshotRequest>),
}

/// What the main thread knows that a snapshot's consensus.json needs.
pub(super) struct SnapshotRequest {
    pub agents: BTreeMap<u32, AgentRecord>,
    pub latencies: Vec<f64>,
    pub wall_s: f64,
}

/// A pose-graph solution, as the main thread forwards it.
pub(super) struct SolutionUpdate {
    pub world_from_agent: BTreeMap<u32, Isometry3<f64>>,
    pub world_from_camera: BTreeMap<KeyframeRef, Isometry3<f64>>,
}

/// The main thread's end of the worker: its input channel, what comes back, and the thread.
pub(super) struct WorkerHandle {
    pub inputs: Sender<WorkerInput>,
    pub solutions: Receiver<SolutionUpdate>,
    pub latencies: Receiver<f64>,
    thread: JoinHandle<Engine>,
}

impl WorkerHandle {
    /// Starts the worker thread (and its aligner thread). Its engine takes the `decisions` an
    /// earlier process of the run stored, and commits each new one to `log` before applying it.
    pub fn spawn(
        options: ConsensusOptions,
        decisions: Vec<Decision>,
        log: DecisionLog,
    ) -> anyhow::Result<Self> {
        let (input_tx, input_rx) = unbounded::<WorkerInput>();
        let (solution_tx, solution_rx) = unbounded::<SolutionUpdate>();
        let (latency_tx, latency_rx) = unbounded::<f64>();
        let thread = std::thread::Builder::new()
            .name("consensus-worker".into())
            .spawn(move || {
                let _span = tracing::info_span!("consensus worker").entered();
                let mut engine = Engine::new(options.config.consensus.clone());
                if !decisions.is_empty() {
                    tracing::info!(
                        decisions = decisions.len(),
                        "stored decisions taken: their pairs are not aligned again"
                    );
                    engine.resume_decisions(decisions);
                }
                let worker = Worker {
                    engine,
                    log,
                    options,
                    waiting: BTreeMap::new(),
                    early_gaussians: BTreeMap::new(),
                };
                worker.run(input_rx, solution_tx, latency_tx)
            })
            .context("starting the consensus worker thread")?;
        Ok(Self {
            inputs: input_tx,
            solutions: solution_rx,
            latencies: latency_rx,
            thread,
        })
    }

    /// Lets the worker finish its queue (it ends when the input channel closes) and returns its
    /// engine, with the solutions and latencies it sent that were not taken yet.
    pub fn finish(self) -> anyhow::Result<(Engine, Vec<SolutionUpdate>, Vec<f64>)> {
        drop(self.inputs);
        let engine = self
            .thread
            .join()
            .map_err(|_| anyhow::anyhow!("the consensus worker thread panicked"))?;
        Ok((
            engine,
            self.solutions.try_iter().collect(),
            self.latencies.try_iter().collect(),
        ))
    }
}

/// Alignments run on their own thread, one at a time, so that a slow one (seconds on a loaded
/// CPU, tens of seconds for a hopeless pair) never holds up new keyframes: those are prepared,
/// placed by their odometry edges and solved (about a millisecond) while it runs, and their
/// agents get corrections at once.
fn spawn_aligner(jobs: Receiver<Job>, done: Sender<Finished>) -> JoinHandle<()> {
    std::thread::Builder::new()
        .name("consensus-aligner".into())
        .spawn(move || {
            let _span = tracing::info_span!("consensus aligner").entered();
            for job in jobs {
                if done.send(job.run()).is_err() {
                    break;
                }
            }
        })
        .expect("starting the consensus aligner thread")
}

/// The worker thread's state.
struct Worker {
    engine: Engine,
    /// Every decision is committed here before the engine applies it.
    log: DecisionLog,
    options: ConsensusOptions,
    /// Keyframes whose first correction has not gone out yet, with their arrival time.
    waiting: BTreeMap<KeyframeRef, Instant>,
    /// Gaussians that arrived before their keyframe's images.
    early_gaussians: BTreeMap<KeyframeRef, GaussianCloud>,
}

impl Worker {
    /// The worker's loop: until the inputs close and no alignment is in flight, take inputs and
    /// finished alignments as they come, start the next alignment, and solve after each.
    fn run(
        mut self,
        inputs: Receiver<WorkerInput>,
        solutions: Sender<SolutionUpdate>,
        latencies: Sender<f64>,
    ) -> Engine {
        let (job_tx, job_rx) = crossbeam_channel::bounded::<Job>(1);
        let (done_tx, done_rx) = crossbeam_channel::bounded::<Finished>(1);
        let aligner = spawn_aligner(job_rx, done_tx);
        let no_inputs = crossbeam_channel::never();
        let no_alignment = crossbeam_channel::never();
        let mut open = true;
        let mut in_flight = false;
        let mut last_progress: Option<Instant> = None;
        loop {
            if last_progress.is_none_or(|at| at.elapsed() >= PROGRESS_INTERVAL) {
                write_progress(&self.options.out, &self.engine, ProgressStage::Aligning);
                last_progress = Some(Instant::now());
            }
            if !in_flight && let Some(job) = self.engine.next_job() {
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
                    Ok(input) => self.take(input),
                    Err(_) => open = false,
                },
                recv(live_done) -> done => match done {
                    Ok(done) => {
                        in_flight = false;
                        self.decide(done);
                        super::live::show_closures(&self.options.live_view, &self.engine);
                    }
                    Err(_) => break,
                },
            }
            while open {
                match inputs.try_recv() {
                    Ok(input) => self.take(input),
                    Err(crossbeam_channel::TryRecvError::Empty) => break,
                    Err(crossbeam_channel::TryRecvError::Disconnected) => open = false,
                }
            }
            if let Some(update) = self.solve(&latencies)
                && solutions.send(update).is_err()
            {
                break;
            }
        }
        drop(job_tx);
        if aligner.join().is_err() {
            tracing::error!("the consensus aligner thread panicked");
        }
        let waiting = self.engine.stored_decisions_waiting();
        if waiting > 0 {
            tracing::warn!(
                decisions = waiting,
                "stored decisions never applied: a keyframe of theirs did not come back"
            );
        }
        self.engine
    }

    /// Commits what a finished job decided, then applies it. A decision the store cannot take
    /// is not applied either, so that a resume never lacks a closure the pose graph had.
    fn decide(&mut self, done: Finished) {
        let Some(decision) = self.engine.decide(done) else {
            return;
        };
        match self.log.append(&decision) {
            Ok(()) => self.engine.apply(decision),
            Err(error) => tracing::error!("{error:#}: decision dropped"),
        }
    }

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
                let (map, unplaced) = self.engine.merged_map(false);
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
        super::live::show_solution(&self.options.live_view, &update.world_from_camera);
        self.waiting.retain(|id, at| {
            if update.world_from_camera.contains_key(id) {
                let latency_ms = at.elapsed().as_secs_f64() * 1e3;
                self.options
                    .live_view
                    .scalar(live_view::paths::CONSENSUS_LATENCY_MS, latency_ms);
                // The main thread may be gone at shutdown; the figure is then not needed.
                let _ = latencies.send(latency_ms);
                false
            } else {
                true
            }
        });
        Some(update)
    }
}

/// How often the worker rewrites consensus_progress.json at most.
const PROGRESS_INTERVAL: std::time::Duration = std::time::Duration::from_millis(500);

/// What the consensus is doing, for the progress display.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProgressStage {
    /// The run goes on: keyframes arrive, candidates are aligned, the pose graph is solved.
    Aligning,
    /// The run's intake has ended: the merged map is refined (when refinement runs) and the
    /// outputs are written.
    Refining,
    /// Every output is written.
    Done,
}

/// OUT/consensus_progress.json: how far the consensus is, for `mac-ego3d swarm`'s progress line.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ConsensusProgress {
    /// What the consensus is doing.
    pub stage: ProgressStage,
    /// Keyframes the engine has received, of all agents.
    pub keyframes: usize,
    /// Attempts (keyframe pairs and map registrations) verified so far; injected wrong closures
    /// are not counted.
    pub closures_verified: usize,
    /// Attempts refused so far.
    pub closures_rejected: usize,
    /// Verified attempts between two different agents.
    pub inter_agent_closures: usize,
    /// Keyframe candidates queued for alignment.
    pub pending_alignments: usize,
}

/// The progress file's name in the output folder.
pub const PROGRESS_FILE_NAME: &str = "consensus_progress.json";

/// Writes [`ConsensusProgress`]: one flat JSON object, written to a temporary file and renamed
/// so a reader never sees half of it. A failed write is logged at debug level only: progress
/// is a display, never a reason to stop.
pub(super) fn write_progress(out: &Path, engine: &Engine, stage: ProgressStage) {
    let events: Vec<&ClosureEvent> = engine
        .events()
        .iter()
        .filter(|e| e.origin != CandidateSource::Injected)
        .collect();
    let progress = ConsensusProgress {
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
    let path = out.join(PROGRESS_FILE_NAME);
    let temporary = out.join(format!(".{PROGRESS_FILE_NAME}.tmp"));
    let written = serde_json::to_string(&progress)
        .map_err(std::io::Error::other)
        .and_then(|text| std::fs::write(&temporary, text))
        .and_then(|()| std::fs::rename(&temporary, &path));
    if let Err(error) = written {
        tracing::debug!(%error, path = %path.display(), "progress not written");
    }
}
