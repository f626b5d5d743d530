//! `mac-agent`: one agent process (SPEC section 3).
//!
//! `mac-agent --config configs/7scenes.toml --dataset PATH [--frames 0..600] --agent-id 0
//! --standalone --out DIR` tracks and maps one sequence and writes DIR/trajectory.tum,
//! DIR/map.ply, DIR/metrics.json and DIR/renders/*.png. Without --dataset it runs on the
//! embedded synthetic scene. SIGINT / SIGTERM finish the current frame and write every output.
//!
//! Without --standalone the agent joins the swarm of `mac-consensus` in the same iceoryx2
//! namespace: it publishes a keyframe every T_comm frames, receives corrections, and says goodbye
//! with its final map before it evaluates itself.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::{Context, bail};
use clap::Parser;
use mac_agent::run::{AgentOptions, metrics_table, run_agent, run_standalone};
use mac_agent::swarm::SwarmLink;
use protocol::transport::TransportConfig;
use slam_core::config::Config;
use slam_core::dataset::FrameRange;

#[derive(Parser)]
#[command(
    name = "mac-agent",
    version,
    about = "One mac-ego3d agent: RGB-D tracking and Gaussian mapping"
)]
struct Args {
    /// Configuration file (configs/*.toml); SPEC defaults when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Dataset directory (7-Scenes, Replica, TUM) or a `synthetic:...` spec; the embedded
    /// synthetic scene when absent.
    #[arg(long)]
    dataset: Option<String>,
    /// Frame range `A..B` (positions in the dataset, end exclusive).
    #[arg(long, default_value = "..")]
    frames: String,
    #[arg(long, default_value_t = 0)]
    agent_id: u32,
    /// Run without a consensus process.
    #[arg(long)]
    standalone: bool,
    /// iceoryx2 service namespace shared with the consensus (swarm mode).
    #[arg(long, default_value = protocol::services::DEFAULT_NAMESPACE)]
    namespace: String,
    /// Global-descriptor weights (AlexNet .npz) for the swarm; overrides the config.
    #[arg(long)]
    descriptor_weights: Option<PathBuf>,
    /// Output directory.
    #[arg(long, default_value = "out/agent")]
    out: PathBuf,
    /// Post-run map refinement iterations (reported separately from real-time figures).
    #[arg(long, default_value_t = 0)]
    refine_iters: usize,
    /// Evaluate rendering quality on every n-th frame.
    #[arg(long, default_value_t = 10)]
    eval_every: usize,
    /// Ground truth | render comparison images to write.
    #[arg(long, default_value_t = 4)]
    renders: usize,
    /// LPIPS weights (.npz, see scripts/get_lpips_weights.sh); LPIPS is left out without them.
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// Frame-decoding threads.
    #[arg(long, default_value_t = 2)]
    decode_workers: usize,
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    if let Some(weights) = &args.descriptor_weights {
        if !weights.is_file() {
            bail!("--descriptor-weights {}: no such file", weights.display());
        }
        config.consensus.descriptor_weights = Some(weights.clone());
    }
    let frames: FrameRange = args
        .frames
        .parse()
        .map_err(|e| anyhow::anyhow!("--frames {:?}: {e}", args.frames))?;
    let options = AgentOptions {
        config,
        dataset: args
            .dataset
            .clone()
            .unwrap_or_else(|| AgentOptions::synthetic_dataset(args.agent_id)),
        frames,
        agent_id: args.agent_id,
        out: args.out.clone(),
        refine_iterations: args.refine_iters,
        eval_every: args.eval_every,
        comparison_renders: args.renders,
        lpips_weights: args.lpips_weights.clone(),
        decode_workers: args.decode_workers,
    };
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone())
            .with_context(|| format!("installing the handler of signal {signal}"))?;
    }
    let metrics = if args.standalone {
        run_standalone(&options, &stop)?
    } else {
        let transport = TransportConfig::with_namespace(args.namespace.clone());
        let swarm = SwarmLink::connect(args.agent_id, &transport, &options.config)?;
        run_agent(&options, &stop, Some(swarm))?
    };
    println!("agent {} on {}", metrics.agent_id, metrics.dataset);
    print!("{}", metrics_table(&metrics));
    println!("outputs in {}", options.out.display());
    Ok(())
}
