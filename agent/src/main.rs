//! `mac-agent`: one agent process (docs/method.md, One agent).
//!
//! `mac-agent --config configs/7scenes.toml --dataset PATH [--frames 0..600] --agent-id 0
//! --standalone --out DIR` tracks and maps one sequence and writes DIR/trajectory.tum,
//! DIR/map.ply, DIR/metrics.json and DIR/renders/*.png. Without --dataset it runs on the
//! embedded synthetic scene. SIGINT / SIGTERM finish the current frame and write every output.
//!
//! Without --standalone the agent joins the swarm of `mac-consensus` in the same iceoryx2
//! namespace: it publishes a keyframe every T_comm frames, receives corrections, and says goodbye
//! with its final map before it evaluates itself. `--link-schedule FILE` simulates an
//! intermittent link (format in `mac_agent::link_schedule`); `--link-schedule FILE
//! --check-link-schedule N` only validates the file for a swarm of N agents and prints every
//! agent's windows.
//!
//! `--pace` overrides `mapping.pace` (sensor, paced, unthrottled).
//!
//! `--viewer [ADDR]` streams the agent's camera, trajectory, keyframes and map to a rerun viewer,
//! `--record DIR` writes them to DIR/agent_K.rrd, under `--recording-id` (default: the
//! namespace); see the `live_view` crate.
//!
//! DIR/progress.json tells how far the run is (for the swarm launcher's progress line).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::bail;
use clap::Parser;
use config::{Config, Pace};
use datasets::{DatasetSpec, FrameRange};
use mac_agent::link_schedule::{LinkPlan, LinkSchedule};
use mac_agent::run::{AgentOptions, metrics_table, run_agent, run_standalone};
use mac_agent::spool::KEYFRAME_SPOOL_DIR;
use mac_agent::swarm::SwarmLink;
use protocol::transport::TransportConfig;

#[derive(Parser)]
#[command(
    name = "mac-agent",
    version,
    about = "One mac-ego3d agent: RGB-D tracking and Gaussian mapping"
)]
struct Args {
    /// Configuration file (configs/*.toml); the built-in defaults (those of configs/7scenes.toml) when absent.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Dataset directory (7-Scenes, Replica, TUM) or a `synthetic:...` spec, optionally with its
    /// frames (`DIR:0..600:10`); the embedded synthetic scene when absent.
    #[arg(long)]
    dataset: Option<String>,
    /// Frame numbers `A..B` (end exclusive), optionally `:STEP` for every STEP-th frame
    /// (`0..1000:10`); instead of a range in --dataset.
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
    /// Agents in the swarm (ids 0..N), as `mac-consensus --agents N` says: whichever process
    /// sets the swarm's services up first sizes them for this many. Default: 8, or what the
    /// swarm already running in the namespace was set up for.
    #[arg(long, value_name = "N")]
    agents: Option<u32>,
    /// Global-descriptor weights (AlexNet .npz) for the swarm; overrides the config. Default:
    /// `consensus.descriptor_weights`, else $MAC_EGO3D_WEIGHTS, else the cache that
    /// scripts/setup.sh fills (~/.cache/mac-ego3d/weights/lpips/alexnet.npz); without any, the
    /// classical thumbnail descriptor.
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
    /// Default with --standalone: $MAC_EGO3D_WEIGHTS, else the cache that scripts/setup.sh
    /// fills. In the swarm, none: `mac-ego3d eval swarm` measures LPIPS on the merged map (an
    /// agent's own LPIPS costs it about a second per evaluated frame on a CPU).
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// Overrides `mapping.pace`: `sensor` (frames at their timestamps, late ones dropped and
    /// counted), `paced` (each keyframe waits for its mapping budget) or `unthrottled`.
    #[arg(long, value_parser = ["sensor", "paced", "unthrottled"])]
    pace: Option<String>,
    /// Frame-decoding threads.
    #[arg(long, default_value_t = 2)]
    decode_workers: usize,
    /// Swarm mode: simulate an intermittent link to the consensus with this schedule (TOML: per
    /// agent, the windows in seconds since start in which the link is up; see
    /// mac_agent::link_schedule). Without it the link is always up.
    #[arg(long, value_name = "FILE")]
    link_schedule: Option<PathBuf>,
    /// Only validate --link-schedule for a swarm of this many agents, print every agent's
    /// windows, and exit.
    #[arg(long, value_name = "AGENTS", requires = "link_schedule")]
    check_link_schedule: Option<u32>,
    #[command(flatten)]
    live_view: live_view::LiveViewArgs,
}

fn main() -> anyhow::Result<()> {
    // The link schedule's clock: seconds since the agent started.
    let started = Instant::now();
    config::process::init_logging();
    let args = Args::parse();
    let schedule = match &args.link_schedule {
        Some(path) => Some(LinkSchedule::load(path)?),
        None => None,
    };
    if let (Some(schedule), Some(agents)) = (&schedule, args.check_link_schedule) {
        print!("{}", schedule.describe(agents));
        return Ok(());
    }
    if schedule.is_some() && args.standalone {
        bail!(
            "--link-schedule simulates the link to the consensus: it needs swarm mode (no --standalone)"
        );
    }
    let mut config = match &args.config {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    match args.pace.as_deref() {
        Some("sensor") => config.mapping.pace = Pace::Sensor,
        Some("paced") => config.mapping.pace = Pace::Paced,
        Some("unthrottled") => config.mapping.pace = Pace::Unthrottled,
        // clap admits only the three names.
        _ => {}
    }
    if let Some(weights) = &args.descriptor_weights {
        if !weights.is_file() {
            bail!("--descriptor-weights {}: no such file", weights.display());
        }
        config.consensus.descriptor_weights = Some(weights.clone());
    } else if !args.standalone && config.consensus.descriptor_weights.is_none() {
        config.consensus.descriptor_weights = alexnet::weights::default_alexnet_weights();
    }
    let lpips_weights = match &args.lpips_weights {
        Some(path) => Some(path.clone()),
        None if args.standalone => alexnet::weights::default_alexnet_weights(),
        None => None,
    };
    let frames: FrameRange = args
        .frames
        .parse()
        .map_err(|e| anyhow::anyhow!("--frames {:?}: {e}", args.frames))?;
    let spec = match &args.dataset {
        Some(text) => text
            .parse::<DatasetSpec>()
            .map_err(|e| anyhow::anyhow!("--dataset: {e}"))?,
        None => DatasetSpec {
            dataset: AgentOptions::synthetic_dataset(args.agent_id),
            frames: FrameRange::ALL,
        },
    };
    if frames != FrameRange::ALL && spec.frames != FrameRange::ALL {
        bail!(
            "frames given twice: --dataset {} and --frames {frames}; give them once",
            spec
        );
    }
    let options = AgentOptions {
        config,
        frames: if frames == FrameRange::ALL {
            spec.frames
        } else {
            frames
        },
        dataset: spec.dataset,
        agent_id: args.agent_id,
        out: args.out.clone(),
        refine_iterations: args.refine_iters,
        eval_every: args.eval_every,
        comparison_renders: args.renders,
        lpips_weights,
        decode_workers: args.decode_workers,
        live_view: args
            .live_view
            .open(&format!("agent_{}", args.agent_id), &args.namespace)?,
    };
    // Before joining the swarm: an agent that could not write its outputs should not announce
    // itself to the consensus.
    config::process::prepare_output_dir(&options.out)?;
    let stop = config::process::stop_on_termination_signals()?;
    let metrics = if args.standalone {
        run_standalone(&options, &stop)?
    } else {
        let transport = TransportConfig::for_swarm(args.namespace.clone(), args.agents);
        let plan = match &schedule {
            Some(schedule) => {
                let ignored = schedule.agents_outside(transport.max_agents);
                if !ignored.is_empty() {
                    tracing::warn!(
                        file = %schedule.path().display(),
                        ?ignored,
                        max_agents = transport.max_agents,
                        "link schedule lists agent ids no agent can have: ignored"
                    );
                }
                let plan = schedule.plan(args.agent_id, started);
                tracing::info!(
                    file = %schedule.path().display(),
                    windows = %plan.windows,
                    queue_limit_bytes = plan.queue_limit_bytes,
                    "link schedule"
                );
                plan
            }
            None => LinkPlan {
                started,
                ..LinkPlan::always_up()
            },
        };
        let swarm = SwarmLink::connect(args.agent_id, &transport, &options.config, plan)?
            .with_spool(&options.out.join(KEYFRAME_SPOOL_DIR))?;
        run_agent(&options, &stop, Some(swarm))?
    };
    println!("agent {} on {}", metrics.agent_id, metrics.dataset);
    print!("{}", metrics_table(&metrics));
    println!("outputs in {}", options.out.display());
    Ok(())
}
