//! `mac-ego3d swarm`: one `mac-consensus` and N `mac-agent` processes (each its own OS
//! process, in parallel; with `--transport zenoh` each on a simulated host of its own with its
//! bridge), supervised until they end, then the run's figures (metrics.json, report.html).
//!
//! Supervision: a child that dies is reported at once and every child is reaped (a dead,
//! unreaped child would keep its shared-memory slots). A consensus that dies (killed, crashed)
//! is started again on the run folder, up to [`CONSENSUS_RESTARTS_MAX`] times: it resumes from
//! its store (DIR/consensus.redb), the agents publish again what it lost, and the outputs are
//! those of a run without the crash (`--no-restart-consensus` reports its death instead). When
//! agents failed, the consensus is stopped once the others are done (it waits for every
//! agent's goodbye otherwise). Each launch is a new run: the consensus starts with a new run id
//! and `--fresh`, so an older run's store in DIR is moved aside, never resumed.
//!
//! Ctrl-C (or SIGTERM) stops the run in order: the agents get SIGTERM (they finish their frame
//! and hand over their outputs), the consensus SIGINT (it asks the agents it still hears from to
//! stop, waits up to [`plan::STOP_WAIT_S`] for their goodbyes, then writes the world trajectories
//! and map). The children run in process groups of their own, so a terminal's Ctrl-C reaches
//! the launcher only and the order holds; a second Ctrl-C kills everything at once (outputs may
//! then be incomplete).
//!
//! Exit status: 0 when every process ended well and the figures were written; 1 when a process
//! failed (its log is named) or the figures could not be computed; 2 when the options or the
//! configuration are refused (before anything starts).
//!
//! Output (DIR, default out/swarm): agent_K/ (each agent's own outputs, its frame), agent_K.tum
//! (world frame), map.ply (merged world map), consensus.json, config.toml (the configuration as
//! run), launch.json (how the swarm ran), metrics.json, report.html, *.log (one per process).

mod hosts;
mod plan;
mod progress;
pub mod record;
pub mod supervisor;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use datasets::DatasetSpec;

use record::{LaunchRecord, Transport};
use supervisor::{Exit, Role, Signal, Supervisor};

/// Restarts of a dead consensus at most (a consensus that cannot start fails fast each time).
pub const CONSENSUS_RESTARTS_MAX: usize = 10;

/// How often the supervisor looks at its children.
const POLL_EVERY: Duration = Duration::from_millis(200);
/// How often the progress line is redrawn.
const PROGRESS_EVERY: Duration = Duration::from_secs(1);

#[derive(Args)]
pub struct SwarmArgs {
    /// Configuration file every process reads (written with the overrides below to
    /// DIR/config.toml).
    #[arg(long, default_value = "configs/synthetic.toml")]
    config: PathBuf,
    /// Agents on the embedded synthetic scene (synthetic:agents=N,agent=K), when no --agent
    /// is given.
    #[arg(long, default_value_t = 3)]
    agents: u32,
    /// One agent's dataset and frames, DATASET[:FIRST..END[:STEP]]; repeat it, one per agent
    /// (agent K is the K-th).
    #[arg(long, value_name = "DATASET[:FIRST..END[:STEP]]")]
    agent: Vec<DatasetSpec>,
    /// Frames per agent of the synthetic scene.
    #[arg(long, default_value_t = 200)]
    frames: usize,
    /// T_comm: publish a keyframe every this many frames (`--set consensus.t_comm=K`).
    #[arg(long, value_name = "K")]
    tcomm: Option<usize>,
    /// Sensor noise on the agents' frames (`--set noise.target=...`).
    #[arg(long, value_parser = ["rgb", "depth", "rgbd"])]
    noise: Option<String>,
    /// Override one configuration key for every process of the run (dotted path, as `mac-ego3d
    /// config --set`); repeatable, applied after --tcomm, --noise and --bandwidth, checked before
    /// anything starts.
    #[arg(long, value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// AlexNet weights (global descriptor and LPIPS). Default: $MAC_EGO3D_WEIGHTS, else the
    /// cache scripts/setup.sh fills; without any, the classical descriptor.
    #[arg(long, value_name = "FILE")]
    descriptor_weights: Option<PathBuf>,
    /// Simulate intermittent links: per agent, the windows in which it can talk to the
    /// consensus (format: agent/src/link_schedule.rs); checked before anything starts.
    #[arg(long, value_name = "FILE")]
    link_schedule: Option<PathBuf>,
    /// Report a consensus that dies instead of starting it again on its store.
    #[arg(long)]
    no_restart_consensus: bool,
    /// What carries the messages: this host's shared memory, or zenoh between simulated hosts
    /// (each process on its own, scripts/simulated_host.sh; needs root).
    #[arg(long, value_enum, default_value_t = Transport::Iceoryx2)]
    transport: Transport,
    /// With zenoh: plain TCP between the simulated hosts instead of mutual TLS.
    #[arg(long)]
    insecure_plain_tcp: bool,
    /// With zenoh: cap what each agent sends to other hosts (`--set
    /// network.agent_kb_per_s=KB_PER_S`); its bridge compresses and defers, never drops.
    #[arg(long, value_name = "KB_PER_S")]
    bandwidth: Option<f64>,
    /// Stream every process to a rerun viewer (HOST:PORT); one is started when `rerun` is on
    /// PATH and nothing listens there yet.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:9876")]
    viewer: Option<String>,
    /// Write DIR/consensus.rrd and DIR/agent_K.rrd (`rerun DIR/*.rrd` opens them together).
    #[arg(long, value_name = "DIR")]
    record: Option<PathBuf>,
    /// Folder of mac-agent, mac-consensus (and mac-bridge); default: beside this program.
    #[arg(long, value_name = "DIR")]
    bin_dir: Option<PathBuf>,
    /// Render the merged map at every n-th frame for the run's figures (0: no renders).
    #[arg(long, default_value_t = 20)]
    render_every: usize,
    #[arg(long, default_value = "out/swarm")]
    out: PathBuf,
}

/// Counts SIGINT and SIGTERM (a thread of signal-hook's).
struct Interrupts(Arc<AtomicUsize>);

impl Interrupts {
    fn install() -> anyhow::Result<Self> {
        let count = Arc::new(AtomicUsize::new(0));
        let mut signals = signal_hook::iterator::Signals::new([
            signal_hook::consts::SIGINT,
            signal_hook::consts::SIGTERM,
        ])
        .context("installing the Ctrl-C handler")?;
        let counter = count.clone();
        std::thread::spawn(move || {
            for _ in signals.forever() {
                counter.fetch_add(1, Ordering::SeqCst);
            }
        });
        Ok(Self(count))
    }

    fn count(&self) -> usize {
        self.0.load(Ordering::SeqCst)
    }
}

/// What the supervision saw.
struct Outcome {
    /// How each process ended last.
    exits: BTreeMap<Role, Exit>,
    interrupted: bool,
}

pub fn run(args: &SwarmArgs) -> anyhow::Result<()> {
    let plan = plan::prepare(args)?;
    let interrupts = Interrupts::install()?;
    progress::clear(&args.out, plan.launch.agents());
    announce(&plan.launch);
    let mut supervisor = Supervisor::start(plan.launch)?;
    let outcome = supervise(&mut supervisor, &interrupts, !args.no_restart_consensus)?;
    let launch = supervisor.launch();
    let record = LaunchRecord {
        transport: plan.transport,
        run_id: launch.run_id.clone(),
        namespace: launch.namespace.clone(),
        datasets: launch.datasets.iter().map(ToString::to_string).collect(),
        agent_threads: launch.agent_threads,
        consensus_restarts: supervisor.consensus_restarts(),
        interrupted: outcome.interrupted,
        exits: outcome
            .exits
            .iter()
            .map(|(role, exit)| (role.log_name().trim_end_matches(".log").to_string(), *exit))
            .collect(),
    };
    record.write(&args.out)?;
    let failed: Vec<String> = outcome
        .exits
        .iter()
        .filter(|(_, exit)| !exit.success())
        .map(|(role, exit)| format!("{role} ({exit})"))
        .collect();
    drop(supervisor);

    let figures = crate::cmd::eval::swarm::SwarmArgs::for_run(
        &args.out,
        args.render_every,
        plan.lpips_weights.clone(),
    );
    let evaluated = crate::cmd::eval::swarm::run(&figures);
    if evaluated.is_ok() {
        print_next_steps(&args.out);
    }
    anyhow::ensure!(
        failed.is_empty(),
        "processes failed: {}; see their logs in {}",
        failed.join(", "),
        args.out.display()
    );
    evaluated.context("the run's figures")
}

fn announce(launch: &supervisor::Launch) {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if let Some(threads) = launch.agent_threads {
        println!(
            "[swarm] {} agents on {cores} cores: {threads} tracking threads each",
            launch.agents()
        );
    }
    for (k, dataset) in launch.datasets.iter().enumerate() {
        println!(
            "[swarm] agent {k}: {dataset}, log {}",
            launch.out.join(format!("agent_{k}.log")).display()
        );
    }
}

/// Waits for every child, reaping each as it ends: restarts a dead consensus, stops the
/// consensus when failed agents will never say goodbye, forwards Ctrl-C in order, and shows
/// the progress line on a terminal.
fn supervise(
    supervisor: &mut Supervisor,
    interrupts: &Interrupts,
    restart_consensus: bool,
) -> anyhow::Result<Outcome> {
    let show_progress = plan::shows_progress();
    let agents = supervisor.launch().agents();
    let out = supervisor.launch().out.clone();
    let mut exits = BTreeMap::new();
    let mut handled_interrupts = 0;
    let mut agents_failed = false;
    let mut stopping_consensus = false;
    let mut last_progress: Option<Instant> = None;
    let say = |message: &str| {
        if show_progress {
            progress::erase();
        }
        eprintln!("[swarm] {message}");
    };
    loop {
        let interrupted = interrupts.count();
        if interrupted > handled_interrupts {
            if handled_interrupts == 0 {
                say(
                    "interrupted: the agents finish their frame and hand over their outputs, \
                     then the consensus writes the world outputs (Ctrl-C again to stop \
                     everything now)",
                );
                for k in 0..agents {
                    supervisor.signal(Role::Agent(k), Signal::Terminate);
                }
                supervisor.signal(Role::Consensus, Signal::Interrupt);
            }
            if interrupted >= 2 {
                say("interrupted again: killing every process (outputs may be incomplete)");
                for role in supervisor.launch().roles() {
                    supervisor.signal(role, Signal::Kill);
                }
            }
            handled_interrupts = interrupted;
        }
        for (role, exit) in supervisor.poll()? {
            let restarts = supervisor.consensus_restarts();
            if role == Role::Consensus
                && !exit.success()
                && restart_consensus
                && handled_interrupts == 0
                && restarts < CONSENSUS_RESTARTS_MAX
            {
                say(&format!(
                    "the consensus exited with {exit}: starting it again on its store (restart \
                     {} of at most {CONSENSUS_RESTARTS_MAX}; log {})",
                    restarts + 1,
                    supervisor.log_of(role).display()
                ));
                supervisor.spawn(Role::Consensus)?;
                continue;
            }
            if !exit.success() {
                say(&format!(
                    "{role} exited with {exit}; see its log {}",
                    supervisor.log_of(role).display()
                ));
                agents_failed |= role != Role::Consensus;
            }
            exits.insert(role, exit);
        }
        let agents_ended = (0..agents).all(|k| !supervisor.is_running(Role::Agent(k)));
        // The consensus waits for every agent's goodbye; a failed agent may never send one.
        if agents_failed
            && agents_ended
            && !stopping_consensus
            && supervisor.is_running(Role::Consensus)
        {
            say(
                "every agent has ended, some failed: stopping the consensus (it writes its outputs)",
            );
            supervisor.signal(Role::Consensus, Signal::Terminate);
            stopping_consensus = true;
        }
        if supervisor.all_ended() {
            break;
        }
        if show_progress && last_progress.is_none_or(|at| at.elapsed() >= PROGRESS_EVERY) {
            progress::show(&progress::line(
                &out,
                agents,
                progress::terminal_width() - 1,
            ));
            last_progress = Some(Instant::now());
        }
        std::thread::sleep(POLL_EVERY);
    }
    if show_progress {
        progress::show(&progress::line(
            &out,
            agents,
            progress::terminal_width() - 1,
        ));
        println!();
    }
    Ok(Outcome {
        exits,
        interrupted: handled_interrupts > 0,
    })
}

/// Where to look next, with absolute paths (the user may be in another folder).
fn print_next_steps(out: &std::path::Path) {
    let dir = std::fs::canonicalize(out).unwrap_or_else(|_| out.to_path_buf());
    let dir = dir.display();
    println!();
    println!("[swarm] next:");
    println!(
        "[swarm]   the report: {dir}/report.html (open it in a browser, e.g. xdg-open \
         {dir}/report.html)"
    );
    println!(
        "[swarm]   the merged map: {dir}/map.ply (3DGS PLY: any Gaussian-splat viewer, e.g. \
         SuperSplat)"
    );
    println!(
        "[swarm]   trajectories: {dir}/agent_K.tum (world frame; e.g. evo_traj tum \
         {dir}/agent_*.tum --plot)"
    );
    println!("[swarm]   what each process logged: {dir}/*.log");
}
