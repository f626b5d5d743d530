//! mac-bridge: joins one host's iceoryx2 swarm namespace to the other hosts of the swarm over
//! zenoh. Run one per host: on the host of the consensus with `--role consumers` (it stands in
//! for every remote agent), on each host of agents with `--role agents --local-agent K...`
//! (it stands in for the remote consumers). On a host, agents and the consensus keep talking
//! iceoryx2 through shared memory, unchanged; messages cross hosts with their typed payloads
//! and stamps (agent, epoch, sequence) unchanged. The module documentation of `hosts` says how
//! loops are avoided, `network` which zenoh settings carry the messages and why, `keys` the
//! key expressions.

mod hosts;
mod keys;
mod network;
mod report;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use clap::{Parser, ValueEnum};
use protocol::services::DEFAULT_NAMESPACE;
use protocol::transport::TransportConfig;

use crate::hosts::{BridgeContext, run_agent_host, run_consumer_host};
use crate::keys::SwarmKeys;
use crate::network::Endpoints;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Role {
    /// This host runs agents (`--local-agent`); the consumers are elsewhere.
    Agents,
    /// This host runs the consensus (and any observer); the agents are elsewhere.
    Consumers,
}

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Joins this host's iceoryx2 swarm to other hosts over zenoh"
)]
struct Cli {
    #[arg(long, value_enum)]
    role: Role,
    /// Swarm namespace (the same on every host and process of the swarm).
    #[arg(long, default_value = DEFAULT_NAMESPACE)]
    namespace: String,
    /// Agent-id range of the swarm, 0..N (as `mac-consensus --agents N`).
    #[arg(long)]
    agents: Option<u32>,
    /// With `--role agents`: an agent id this host runs (repeat for several).
    #[arg(long = "local-agent")]
    local_agents: Vec<u32>,
    /// Zenoh endpoint to listen on, e.g. `tcp/0.0.0.0:7447` (repeatable).
    #[arg(long)]
    listen: Vec<String>,
    /// Zenoh endpoint of another host's bridge, e.g. `tcp/192.168.1.10:7447` (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// Transport settings (a JSON `TransportConfig`) when the swarm's processes do not use the
    /// defaults: queue depths and limits must match theirs. `--namespace` and `--agents`
    /// override its namespace and agent range.
    #[arg(long)]
    transport_config: Option<PathBuf>,
    /// Writes the per-agent network traffic here (JSON) when the bridge stops.
    #[arg(long)]
    report: Option<PathBuf>,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    if cli.listen.is_empty() && cli.connect.is_empty() {
        bail!("give --listen ENDPOINT (this host accepts connections) and/or --connect ENDPOINT");
    }
    match (cli.role, cli.local_agents.is_empty()) {
        (Role::Agents, true) => bail!("--role agents needs at least one --local-agent K"),
        (Role::Consumers, false) => bail!("--local-agent is for --role agents only"),
        _ => {}
    }
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, Arc::clone(&stop))?;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(run(cli, stop))
}

fn transport_config(cli: &Cli) -> Result<TransportConfig> {
    let Some(path) = &cli.transport_config else {
        return Ok(TransportConfig::for_swarm(
            cli.namespace.clone(),
            cli.agents,
        ));
    };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--transport-config {}", path.display()))?;
    let mut config: TransportConfig = serde_json::from_str(&text).with_context(|| {
        format!(
            "--transport-config {}: not a transport config",
            path.display()
        )
    })?;
    config.namespace = cli.namespace.clone();
    if let Some(agents) = cli.agents {
        config.max_agents = agents;
    }
    Ok(config)
}

async fn run(cli: Cli, stop: Arc<AtomicBool>) -> Result<()> {
    let endpoints = Endpoints {
        listen: cli.listen.clone(),
        connect: cli.connect.clone(),
    };
    let session = zenoh::open(network::config(&endpoints)?)
        .await
        .map_err(|e| anyhow!("opening the zenoh session ({endpoints:?}): {e}"))?;
    tracing::info!(zid = %session.zid(), ?endpoints, role = ?cli.role, namespace = %cli.namespace, "zenoh session open");
    let context = BridgeContext {
        session: session.clone(),
        keys: SwarmKeys::new(&cli.namespace),
        transport: transport_config(&cli)?,
        stop,
    };
    let start = Instant::now();
    let (role, traffic) = match cli.role {
        Role::Agents => ("agents", run_agent_host(context, cli.local_agents).await?),
        Role::Consumers => ("consumers", run_consumer_host(context).await?),
    };
    if let Some(path) = &cli.report {
        report::write(path, role, start.elapsed().as_secs_f64(), &traffic)?;
    }
    session
        .close()
        .await
        .map_err(|e| anyhow!("closing the zenoh session: {e}"))?;
    tracing::info!("stopped");
    Ok(())
}
