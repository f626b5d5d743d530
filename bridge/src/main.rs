//! mac-bridge: joins one host's iceoryx2 swarm namespace to the other hosts of the swarm over
//! zenoh. Run one per host: on the host of the consensus with `--role consumers` (it stands in
//! for every remote agent), on each host of agents with `--role agents --local-agent K...`
//! (it stands in for the remote consumers). On a host, agents and the consensus keep talking
//! iceoryx2 through shared memory, unchanged; messages cross hosts with their typed payloads
//! and stamps (agent, epoch, sequence) unchanged. The module documentation of `hosts` says how
//! loops are avoided, `network` which zenoh settings carry the messages and why, `keys` the
//! key expressions and `certs` the swarm's certificates (`mac-bridge certs`).

mod budget;
mod certs;
mod delivery;
mod encoding;
mod hosts;
mod keys;
mod network;
mod report;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use protocol::services::DEFAULT_NAMESPACE;
use protocol::transport::TransportConfig;

use crate::certs::{HostFiles, HostSpec};
use crate::hosts::{BridgeContext, run_agent_host, run_consumer_host};
use crate::keys::SwarmKeys;
use crate::network::{Endpoints, LinkSecurity};
use crate::report::{ReportWriter, SharedTraffic};

/// How often a running bridge rewrites its traffic report.
const REPORT_EVERY: Duration = Duration::from_secs(2);

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
    about = "Joins this host's iceoryx2 swarm to other hosts over zenoh",
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    bridge: BridgeArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Makes a new swarm certificate authority and a certificate and key per host.
    Certs(CertsArgs),
}

#[derive(Debug, Args)]
struct CertsArgs {
    /// Folder to write into (`ca.pem`, `ca.key`, `HOST.pem`, `HOST.key`); existing files are
    /// never overwritten.
    #[arg(long)]
    out: PathBuf,
    /// A host: `NAME`, or `NAME=ADDRESS,...` with the IP addresses or DNS names other hosts
    /// connect to it by (needed on the hosts that listen). Repeat for every host.
    #[arg(long = "host", required = true)]
    hosts: Vec<HostSpec>,
    /// Validity of the certificates in days.
    #[arg(long, default_value_t = 365)]
    days: u32,
}

#[derive(Debug, Args)]
struct BridgeArgs {
    #[arg(long, value_enum, required = true)]
    role: Option<Role>,
    /// Swarm namespace (the same on every host and process of the swarm).
    #[arg(long, default_value = DEFAULT_NAMESPACE)]
    namespace: String,
    /// Agent-id range of the swarm, 0..N (as `mac-consensus --agents N`).
    #[arg(long)]
    agents: Option<u32>,
    /// With `--role agents`: an agent id this host runs (repeat for several).
    #[arg(long = "local-agent")]
    local_agents: Vec<u32>,
    /// Zenoh endpoint to listen on, e.g. `tls/0.0.0.0:7447` (repeatable).
    #[arg(long)]
    listen: Vec<String>,
    /// Zenoh endpoint of another host's bridge, e.g. `tls/192.168.1.10:7447` (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// Folder with the swarm CA's certificate and this host's certificate and key (made by
    /// `mac-bridge certs`); links are TLS with mutual authentication.
    #[arg(long, requires = "host", conflicts_with = "insecure_plain_tcp")]
    certificates: Option<PathBuf>,
    /// This host's name in `--certificates` (its files are `NAME.pem` and `NAME.key`).
    #[arg(long, requires = "certificates")]
    host: Option<String>,
    /// Plain TCP links without authentication: anyone who reaches a port joins the swarm.
    #[arg(long)]
    insecure_plain_tcp: bool,
    /// Transport settings (a JSON `TransportConfig`) when the swarm's processes do not use the
    /// defaults: queue depths and limits must match theirs. `--namespace` and `--agents`
    /// override its namespace and agent range.
    #[arg(long)]
    transport_config: Option<PathBuf>,
    /// Writes the per-agent network traffic here (JSON) when the bridge stops.
    #[arg(long)]
    report: Option<PathBuf>,
    /// The swarm's configuration file (the run's config.toml): an agent host's bridge keeps its
    /// agents within `[network] agent_kb_per_s`. Without it, no cap.
    #[arg(long)]
    config: Option<PathBuf>,
}

fn main() -> Result<()> {
    // Before anything else: it sets an environment variable and no thread may be running yet.
    let users_zenoh_runtime = network::configure_zenoh_runtime();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        // Colours only on a terminal: a log redirected to a file is plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        .init();
    if let Some(theirs) = users_zenoh_runtime {
        tracing::warn!(
            ZENOH_RUNTIME = %theirs,
            ours = network::ZENOH_RUNTIME_SETTING,
            "ZENOH_RUNTIME set by the user is kept: unless it hands `rx` over to a \
             single-threaded `tx`, TLS links may reset under heavy two-way traffic"
        );
    }
    let cli = Cli::parse();
    if let Some(Command::Certs(args)) = &cli.command {
        return certs::make(&args.out, &args.hosts, args.days);
    }
    let cli = cli.bridge;
    let Some(role) = cli.role else {
        bail!("give --role agents|consumers (or the certs subcommand)");
    };
    if cli.listen.is_empty() && cli.connect.is_empty() {
        bail!("give --listen ENDPOINT (this host accepts connections) and/or --connect ENDPOINT");
    }
    match (role, cli.local_agents.is_empty()) {
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
    runtime.block_on(run(cli, role, stop))
}

fn link_security(cli: &BridgeArgs) -> Result<LinkSecurity> {
    match (&cli.certificates, &cli.host, cli.insecure_plain_tcp) {
        (Some(folder), Some(host), false) => {
            Ok(LinkSecurity::MutualTls(HostFiles::in_folder(folder, host)))
        }
        (None, None, true) => {
            tracing::warn!(
                "--insecure-plain-tcp: links are plain TCP without authentication; anyone who reaches a port can publish into and read from the swarm"
            );
            Ok(LinkSecurity::InsecurePlainTcp)
        }
        _ => bail!(
            "give --certificates DIR --host NAME (TLS with mutual authentication; make the files with `mac-bridge certs`), or --insecure-plain-tcp"
        ),
    }
}

fn transport_config(cli: &BridgeArgs) -> Result<TransportConfig> {
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

fn network_config(cli: &BridgeArgs) -> Result<config::NetworkConfig> {
    let Some(path) = &cli.config else {
        return Ok(config::NetworkConfig::default());
    };
    let network = config::Config::load(path)?.network;
    if let Some(kb_per_s) = network.agent_bytes_per_s().map(|b| b / 1000.0) {
        tracing::info!(kb_per_s, "bandwidth budget per agent");
    }
    Ok(network)
}

async fn run(cli: BridgeArgs, role: Role, stop: Arc<AtomicBool>) -> Result<()> {
    let endpoints = Endpoints {
        listen: cli.listen.clone(),
        connect: cli.connect.clone(),
    };
    let security = link_security(&cli)?;
    let session = zenoh::open(network::config(&endpoints, &security)?)
        .await
        .map_err(|e| anyhow!("opening the zenoh session ({endpoints:?}): {e}"))?;
    tracing::info!(zid = %session.zid(), ?endpoints, ?role, namespace = %cli.namespace, "zenoh session open");
    let context = BridgeContext {
        session: session.clone(),
        keys: SwarmKeys::new(&cli.namespace),
        transport: transport_config(&cli)?,
        stop: Arc::clone(&stop),
        traffic: SharedTraffic::default(),
        network: network_config(&cli)?,
    };
    let role_name = match role {
        Role::Agents => "agents",
        Role::Consumers => "consumers",
    };
    let start = Instant::now();
    let report = cli
        .report
        .as_deref()
        .map(|path| ReportWriter::new(path, &cli.namespace, role_name));
    // Written every few seconds as well as at the end: a bridge killed mid-run leaves its counts.
    let periodic = report.clone().map(|writer| {
        let traffic = context.traffic.clone();
        let stop = Arc::clone(&stop);
        tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                tokio::time::sleep(REPORT_EVERY).await;
                if let Err(error) = writer.write(start.elapsed().as_secs_f64(), &traffic.snapshot())
                {
                    tracing::warn!(error = %format!("{error:#}"), "bridge report not written");
                }
            }
        })
    });
    let traffic = context.traffic.clone();
    match role {
        Role::Agents => run_agent_host(context, cli.local_agents).await?,
        Role::Consumers => run_consumer_host(context).await?,
    }
    if let Some(periodic) = periodic {
        periodic.abort();
    }
    if let Some(writer) = &report {
        writer.write(start.elapsed().as_secs_f64(), &traffic.snapshot())?;
    }
    session
        .close()
        .await
        .map_err(|e| anyhow!("closing the zenoh session: {e}"))?;
    tracing::info!("stopped");
    Ok(())
}
