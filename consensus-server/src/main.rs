//! `mac-consensus`: the consensus process (docs/method.md, The consensus).
//!
//! `mac-consensus --config configs/7scenes.toml --out DIR [--agents N] [--namespace mac]`
//! listens for every agent's keyframes, aligns and optimises them, sends corrections back, and
//! when the N agents have said goodbye (or on SIGINT / SIGTERM) writes DIR/map.ply (the merged
//! world map), DIR/agent_K.tum (each agent's trajectory in the world frame, from the agent's own
//! DIR/agent_K/trajectory.tum) and DIR/consensus.json. SIGUSR1 writes the same outputs as they
//! stand (without the final refinement, `"snapshot": true` in consensus.json) and the run goes on.
//! With `--stop-agents SECONDS`, SIGINT / SIGTERM first ask every running agent to stop
//! (`ControlMessage::Shutdown`) and wait up to SECONDS for their final maps and goodbyes.
//!
//! Everything the consensus accepts is committed to DIR/consensus.redb before it is acted on.
//! Started again on a folder whose store belongs to the same run (`--run-id`, the namespace when
//! not given; the same configuration and `--agents`), it resumes: it replays the store, tells
//! the running agents it is back and which of their keyframes it holds, and they publish again
//! what they still hold of the rest. A store of another run is refused; `--fresh` moves it aside
//! (DIR/consensus.redb.replaced) and starts over.
//!
//! `--rebuild-from RUN --out NEW` builds the end of the finished run in RUN again (merged map,
//! joint refinement, outputs) with this configuration, from a copy of its store and without its
//! agents, into NEW: e.g. another `[consensus.refinement]` on the same agents' maps and keyframes.
//!
//! `--viewer [ADDR]` streams closures, corrected trajectories, the merged map and the figures to
//! a rerun viewer, `--record DIR` writes them to DIR/consensus.rrd, under `--recording-id`
//! (default: the run id); see the `live_view` crate.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use config::Config;
use mac_consensus::process::{ConsensusOptions, run_with_snapshots};
use protocol::transport::TransportConfig;

#[derive(Parser)]
#[command(
    name = "mac-consensus",
    version,
    about = "The mac-ego3d consensus: place recognition, alignment and pose graph over all agents"
)]
struct Args {
    /// Configuration file (configs/*.toml); the built-in defaults when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Output directory (agents write theirs to DIR/agent_K).
    #[arg(long, default_value = "out/swarm")]
    out: PathBuf,
    /// Agents 0..N to wait for, and the swarm's agent-id range; the run ends when all of them
    /// said goodbye. Without it the consensus runs until SIGINT / SIGTERM, for the default id
    /// range (protocol::transport::DEFAULT_MAX_AGENTS).
    #[arg(long)]
    agents: Option<u32>,
    /// iceoryx2 service namespace shared by the swarm's processes.
    #[arg(long, default_value = protocol::services::DEFAULT_NAMESPACE)]
    namespace: String,
    /// On SIGINT / SIGTERM, ask every running agent to stop as well (each finishes its frame,
    /// sends its final map and says goodbye) and wait up to this many seconds for them before
    /// writing the outputs. Without it the agents keep running on their own.
    #[arg(long, value_name = "SECONDS")]
    stop_agents: Option<f64>,
    /// The run this consensus belongs to, recorded in DIR/consensus.redb: started again with
    /// the same run id (and configuration and --agents) it resumes from the store. Default: the
    /// namespace.
    #[arg(long)]
    run_id: Option<String>,
    /// Start a new run even if DIR holds a consensus store: the old store is moved aside to
    /// DIR/consensus.redb.replaced.
    #[arg(long)]
    fresh: bool,
    /// Fault injection for `mac-ego3d chaos`: kill this process (SIGKILL) while storing a
    /// keyframe whenever OUT/crash_while_storing exists (it names the point: before_commit or
    /// after_commit). Never for a real run.
    #[arg(long, hide = true)]
    fault_injection: bool,
    /// Build the end of the finished run in RUN again (merged map, joint refinement, outputs)
    /// with this configuration, into --out (an empty folder), from a copy of RUN's store and
    /// without its agents; RUN is only read (see mac_consensus::rebuild).
    #[arg(long, value_name = "RUN", conflicts_with_all = ["fresh", "run_id", "agents"])]
    rebuild_from: Option<PathBuf>,
    #[command(flatten)]
    live_view: live_view::LiveViewArgs,
}

fn main() -> anyhow::Result<()> {
    config::process::init_logging();
    let args = Args::parse();
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if config.mapping.pace == config::Pace::Sensor {
        // Real time on a shared host: the agents' tracking comes first.
        config::process::lower_process_priority(config.consensus.sensor_niceness);
    }
    let (run_id, agents, namespace) = match &args.rebuild_from {
        Some(run) => {
            let identity = mac_consensus::rebuild::prepare(run, &args.out, config.hash())?;
            // A namespace of its own: no running swarm hears the rebuild, nor it them.
            let namespace = format!("{}rebuild{}", args.namespace, std::process::id());
            (Some(identity.run_id), identity.agents, namespace)
        }
        None => (args.run_id.clone(), args.agents, args.namespace.clone()),
    };
    let options = ConsensusOptions {
        config,
        transport: TransportConfig::for_swarm(namespace.clone(), agents),
        out: args.out.clone(),
        expected_agents: agents,
        stop_agents_wait: args
            .stop_agents
            .map(|seconds| {
                Duration::try_from_secs_f64(seconds)
                    .with_context(|| format!("--stop-agents {seconds}: not a number of seconds"))
            })
            .transpose()?,
        live_view: args
            .live_view
            .open("consensus", run_id.as_deref().unwrap_or(&namespace))?,
        run_id,
        fresh: args.fresh,
        fault_injection: args.fault_injection,
    };
    let stop = config::process::stop_on_termination_signals()?;
    let snapshot = Arc::new(AtomicBool::new(false));
    signal_hook::flag::register(signal_hook::consts::SIGUSR1, snapshot.clone())
        .context("installing the handler of SIGUSR1 (snapshots)")?;
    let report = run_with_snapshots(&options, &stop, &snapshot)?;
    println!(
        "consensus: {} keyframes, {} closures proposed, {} verified, {} accepted ({} inter-agent), \
         latency median {} ms, {} Gaussians merged; outputs in {}",
        report.keyframes,
        report.closures_proposed,
        report.closures_verified,
        report.loop_closures_accepted,
        report.inter_agent_closures_accepted,
        report
            .consensus_latency_ms_median
            .map_or("-".to_string(), |v| format!("{v:.0}")),
        report.merged_gaussians,
        args.out.display()
    );
    for (agent_id, record) in &report.agents {
        if record.world_from_agent.is_some() {
            continue;
        }
        // The agent's pairs with the others: what was tried and why it did not link them.
        let tried: Vec<String> = report
            .agent_pairs
            .iter()
            .filter(|(pair, _)| pair.split('-').any(|a| a == agent_id.to_string()))
            .map(|(pair, a)| {
                format!(
                    "{pair}: {} keyframe and {} map attempts{}",
                    a.keyframe_attempts,
                    a.map_attempts,
                    a.last_rejection
                        .as_ref()
                        .map(|r| format!(", last refused: {r}"))
                        .unwrap_or_default()
                )
            })
            .collect();
        println!(
            "consensus: agent {agent_id} not linked to the world (its map overlaps no linked \
             agent's, or not clearly enough){}",
            if tried.is_empty() {
                " - nothing to compare it with".to_string()
            } else {
                format!(" - {}", tried.join("; "))
            }
        );
    }
    Ok(())
}
