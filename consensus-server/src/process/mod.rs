//! The `mac-consensus` process: receives every agent's keyframes over iceoryx2, runs the
//! [`Engine`](crate::engine::Engine) on a worker thread, sends corrections back, and writes the
//! world map, the agents' world trajectories and consensus.json at the end.
//!
//! Threads, and why:
//! - the main thread owns the transport (iceoryx2 ports stay on the thread that made them): it
//!   waits on the consumers' event (no spinning), joins each keyframe's descriptor and image
//!   (they arrive on different topics, in any order; [`crate::inbox`]), asks agents to publish
//!   again what arrived incomplete, and sends corrections as soon as the worker has them. It
//!   never aligns or solves, so agents are never blocked by the consensus;
//! - the worker thread owns the [`Engine`](crate::engine::Engine): preparing keyframes and
//!   solving the pose graph (about a millisecond) as soon as a keyframe arrives or an alignment
//!   finishes;
//! - an aligner thread aligns candidate pairs one at a time (about a second each on a CPU,
//!   longer under load), so no keyframe waits for an alignment before it is placed.
//!
//! The run ends when every expected agent has said goodbye and the worker has aligned every
//! queued candidate, or on SIGINT/SIGTERM (the stop flag); either way every output is written.
//!
//! Files: `main_thread.rs` (transport, routing, corrections), `worker.rs` (engine, aligner,
//! progress), `outputs.rs` (consensus.json, map, trajectories, the final refinement), `live.rs`
//! (what the rerun live view shows).

mod live;
mod main_thread;
mod outputs;
mod ros2_outputs;
mod worker;

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use anyhow::Context;
use config::Config;
use live_view::LiveView;
use protocol::transport::{ConsumerLink, TransportConfig};

use crate::store::{Opened, RunIdentity, Store};
use main_thread::Listener;
pub use outputs::{AgentRecord, ConsensusReport, PairAttempts, agent_trajectory_path};
use outputs::{OutputKind, WorldMap, refine_world_map, write_outputs};
pub use worker::{ConsensusProgress, PROGRESS_FILE_NAME, ProgressStage};
use worker::{WorkerHandle, write_progress};

/// What to run and where to write.
#[derive(Debug, Clone)]
pub struct ConsensusOptions {
    /// The run's configuration: `[consensus]` runs the engine, `[ros2]` the ROS 2 outputs; its
    /// hash is part of the run identity the store checks on resume.
    pub config: Config,
    /// The iceoryx2 swarm to listen to (namespace, agent-id range); the namespace is also the
    /// run id when `run_id` is `None`.
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
    /// The run this consensus belongs to (its store, `out/consensus.redb`, records it): a
    /// consensus started again with the same run id, configuration and agents resumes from the
    /// store; any other is refused. `None`: the transport's namespace.
    pub run_id: Option<String>,
    /// Start over: an existing store is moved aside instead of resumed or refused.
    pub fresh: bool,
    /// The rerun live view ([`LiveView::disabled`] unless `--viewer` or `--record`).
    pub live_view: LiveView,
    /// Fault injection for the chaos soak: the process kills itself while storing a keyframe
    /// when `out/crash_while_storing` asks it to ([`Store::crash_when_armed`]). Off in normal
    /// runs.
    pub fault_injection: bool,
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
    config::process::prepare_output_dir(&options.out)?;
    let started = Instant::now();
    let identity = RunIdentity {
        run_id: options
            .run_id
            .clone()
            .unwrap_or_else(|| options.transport.namespace.clone()),
        config_hash: options.config.hash(),
        agents: options.expected_agents,
    };
    // Opened before the transport: a store of another run stops the consensus before any
    // agent hears of it.
    let (mut store, opened, inputs) = Store::open(&options.out, &identity, options.fresh)?;
    if options.fault_injection {
        store.crash_when_armed(&options.out);
    }
    let link = ConsumerLink::open(&options.transport).context("opening the transport")?;
    tracing::info!(namespace = %options.transport.namespace, "consensus listening");
    let worker = WorkerHandle::spawn(options.clone(), store.decisions()?, store.decision_log()?)?;
    let mut listener = Listener::new(link, options, started, store);
    if opened == Opened::Resumed {
        tracing::warn!(
            store = %listener.store_path().display(),
            inputs = inputs.len(),
            "resuming the run from its consensus store (start with --fresh to begin anew)"
        );
        listener.resume(inputs, options, &worker.inputs)?;
    }
    let interrupted = listener.listen(&worker, options, stop, snapshot)?;

    let (mut engine, updates, latencies) = worker.finish()?;
    let (agents, latencies) = listener.finish(updates, latencies);
    // Decided once: the joint refinement runs unless it is off or the run was interrupted, and
    // the merged map it starts from depends on whether it does.
    let refinement_follows = options.config.consensus.refinement.enabled() && !interrupted;
    let (map, unplaced) = engine.merged_map(refinement_follows);
    write_progress(&options.out, &engine, ProgressStage::Refining);
    let (map, refinement) = refine_world_map(options, &mut engine, map, refinement_follows)?;
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
    if let Some(stats) = options.live_view.finish() {
        tracing::info!(
            items_queued = stats.items_queued,
            items_dropped = stats.items_dropped,
            "live view finished"
        );
    }
    Ok(report)
}
