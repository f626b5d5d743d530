//! `mac-ego3d chaos`: a soak of the swarm under crashes. Runs the synthetic swarm once as is
//! (the reference) and once while SIGKILLing its processes at seeded random times (each agent
//! and the consensus `--kills-each` times, or only the consensus with `--only-consensus`, within
//! `--window` seconds), starting each again as a user would (same command line; the consensus
//! resumes from its store, an agent re-runs its frames). `--store-crashes N` adds N deaths of the
//! consensus in the middle of storing a keyframe (before its commit, or after it and before the
//! consensus acted on it, in turn; the consensus runs with its fault injection armed by a file).
//! Then checks that every keyframe each agent's last run delivered is in the final
//! consensus.json, that the outputs are complete and readable, and compares joint ATE and PSNR
//! with the reference. Prints a table and writes OUT/chaos.json; exits non-zero when a check
//! fails.

mod checks;
mod swarm;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use datasets::DatasetSpec;
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use checks::{RunChecks, check_run};
use mac_consensus::store::{CRASH_TRIGGER_FILE, CrashPoint};
use swarm::SwarmSetup;

use crate::cmd::swarm::supervisor::{Role, Supervisor};

use crate::cmd::eval::swarm::{SwarmArgs, swarm_metrics};
use crate::cmd::{fmt_num, print_json};

#[derive(Args)]
pub struct ChaosArgs {
    /// Configuration file (its options as the swarm runs them).
    #[arg(long, default_value = "configs/synthetic.toml")]
    config: PathBuf,
    #[arg(long, default_value_t = 2)]
    agents: u32,
    /// Frames per agent of the synthetic scene.
    #[arg(long, default_value_t = 200)]
    frames: usize,
    /// Image size of the synthetic scene (its default when absent).
    #[arg(long)]
    width: Option<u32>,
    #[arg(long)]
    height: Option<u32>,
    /// Seed of the kill plan (which process, when).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// SIGKILLs per process (each agent and the consensus).
    #[arg(long, default_value_t = 2)]
    kills_each: usize,
    /// Kill only the consensus (the agents run through).
    #[arg(long)]
    only_consensus: bool,
    /// Deaths of the consensus while it stores a keyframe, on top of the SIGKILLs (before the
    /// commit and after it, in turn).
    #[arg(long, default_value_t = 0)]
    store_crashes: usize,
    /// The kills fall in this many seconds after the start (at most 80 % of the time the
    /// reference run's first agent took).
    #[arg(long, default_value_t = 60.0)]
    window: f64,
    /// Seconds between a kill and the process's new start.
    #[arg(long, default_value_t = 1.0)]
    restart_after: f64,
    /// Render the merged map at every n-th frame for the PSNR (0: no PSNR).
    #[arg(long, default_value_t = 20)]
    render_every: usize,
    /// Folder of mac-agent and mac-consensus (default: beside this program).
    #[arg(long)]
    binaries: Option<PathBuf>,
    /// Print the JSON instead of a table (OUT/chaos.json is written either way).
    #[arg(long)]
    json: bool,
    #[arg(long, default_value = "out/chaos")]
    out: PathBuf,
}

/// How a process is made to die.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Fault {
    /// SIGKILL from outside, at any instant.
    Sigkill,
    /// The consensus kills itself while storing its next keyframe, at this point.
    WhileStoring(#[serde(serialize_with = "crash_point_name")] CrashPoint),
}

fn crash_point_name<S: serde::Serializer>(point: &CrashPoint, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(point.name())
}

/// One planned kill and what happened.
#[derive(Debug, Clone, Serialize)]
pub struct Kill {
    pub at_s: f64,
    pub target: Role,
    pub fault: Fault,
    /// False when the process had already ended by then (nothing to kill), or, while storing,
    /// when no keyframe was stored within [`STORE_CRASH_WAIT`].
    pub killed: bool,
}

/// How long an armed store crash waits for the consensus to store a keyframe.
const STORE_CRASH_WAIT: Duration = Duration::from_secs(60);

/// OUT/chaos.json.
#[derive(Debug, Serialize)]
pub struct ChaosReport {
    pub seed: u64,
    pub agents: u32,
    pub frames: usize,
    pub kills: Vec<Kill>,
    /// Kills done per process (`consensus`, `agent 0`, ...).
    pub kills_per_process: Vec<(String, usize)>,
    /// Deaths of the consensus while storing a keyframe.
    pub store_crashes: usize,
    pub restarts: usize,
    pub reference: RunChecks,
    pub chaos: RunChecks,
    /// Every check held: each process killed `kills_each` times, every keyframe delivered in
    /// the final state, outputs complete and readable (both runs).
    pub passed: bool,
    pub failures: Vec<String>,
}

pub fn run(args: &ChaosArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.agents >= 1, "--agents must be at least 1");
    let binaries = match &args.binaries {
        Some(dir) => dir.clone(),
        None => std::env::current_exe()?
            .parent()
            .context("the folder of mac-ego3d")?
            .to_path_buf(),
    };
    config::process::prepare_output_dir(&args.out)?;
    // Checked here once rather than failing in every process; both runs read the copy.
    config::Config::load(&args.config)?;
    let run_config = args.out.join("config.toml");
    std::fs::copy(&args.config, &run_config).with_context(|| {
        format!(
            "copying {} to {}",
            args.config.display(),
            run_config.display()
        )
    })?;
    let setup = |name: &str| SwarmSetup {
        binaries: binaries.clone(),
        config: run_config.clone(),
        out: args.out.join(name),
        namespace: format!("chaos{}{name}", std::process::id()),
        fault_injection: name == "killed" && args.store_crashes > 0,
        datasets: (0..args.agents)
            .map(|k| DatasetSpec {
                dataset: dataset(args, k),
                frames: datasets::FrameRange::ALL,
            })
            .collect(),
    };
    let timeout = Duration::from_secs(1800);

    eprintln!(
        "[chaos] reference run (no kills) in {}",
        args.out.join("reference").display()
    );
    let mut reference = swarm::start(setup("reference"))?;
    let first_agent_ended = swarm::wait_all(&mut reference, timeout)?;
    drop(reference);
    // Kills after the agents are done would find nothing to kill: on a fast machine the window
    // shrinks to 80 % of the time the reference's first agent took.
    let window = args.window.min(0.8 * first_agent_ended.as_secs_f64());
    if window < args.window {
        eprintln!(
            "[chaos] the reference's first agent ended after {:.1} s: kills fall within {window:.1} s",
            first_agent_ended.as_secs_f64()
        );
    }

    eprintln!(
        "[chaos] run with kills in {}",
        args.out.join("killed").display()
    );
    let plan = kill_plan(args, window);
    let mut killed = swarm::start(setup("killed"))?;
    let kills = execute(
        &mut killed,
        plan,
        Duration::from_secs_f64(args.restart_after),
    )?;
    swarm::wait_all(&mut killed, timeout)?;
    drop(killed);

    let evaluate = |name: &str| -> anyhow::Result<RunChecks> {
        let dir = args.out.join(name);
        let metrics = swarm_metrics(&dir, &SwarmArgs::for_dir(&dir, args.render_every))?;
        check_run(&dir, args.agents, args.frames, &metrics)
    };
    let reference = evaluate("reference")?;
    let chaos = evaluate("killed")?;
    let report = report(args, kills, reference, chaos);
    let path = args.out.join("chaos.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", path.display()))?;
    if args.json {
        print_json(&report)?;
    } else {
        print_table(&report);
    }
    anyhow::ensure!(
        report.passed,
        "the chaos soak failed: {}",
        report.failures.join("; ")
    );
    Ok(())
}

fn dataset(args: &ChaosArgs, k: u32) -> String {
    let mut spec = format!(
        "synthetic:agents={},agent={k},frames={}",
        args.agents, args.frames
    );
    if let Some(width) = args.width {
        spec.push_str(&format!(",width={width}"));
    }
    if let Some(height) = args.height {
        spec.push_str(&format!(",height={height}"));
    }
    spec
}

/// `kills_each` SIGKILLs of every process (of the consensus only with `--only-consensus`) and
/// `store_crashes` deaths of the consensus while storing (before and after the commit, in turn),
/// in a seeded random order at seeded random times in (1 s, window), sorted by time.
fn kill_plan(args: &ChaosArgs, window: f64) -> Vec<(f64, Role, Fault)> {
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let agents = if args.only_consensus { 0 } else { args.agents };
    let mut faults: Vec<(Role, Fault)> = std::iter::once(Role::Consensus)
        .chain((0..agents).map(Role::Agent))
        .flat_map(|role| std::iter::repeat_n((role, Fault::Sigkill), args.kills_each))
        .chain((0..args.store_crashes).map(|i| {
            let point = if i % 2 == 0 {
                CrashPoint::BeforeCommit
            } else {
                CrashPoint::AfterCommit
            };
            (Role::Consensus, Fault::WhileStoring(point))
        }))
        .collect();
    faults.shuffle(&mut rng);
    let mut times: Vec<f64> = faults
        .iter()
        .map(|_| rng.random_range(1.0..window.max(1.5)))
        .collect();
    times.sort_by(f64::total_cmp);
    times
        .into_iter()
        .zip(faults)
        .map(|(at_s, (role, fault))| (at_s, role, fault))
        .collect()
}

/// Carries out `plan`: at each time, kill the target if it runs (SIGKILL, or the consensus
/// while storing its next keyframe) and start it again after `restart_after`.
fn execute(
    swarm: &mut Supervisor,
    plan: Vec<(f64, Role, Fault)>,
    restart_after: Duration,
) -> anyhow::Result<Vec<Kill>> {
    let started = Instant::now();
    let mut kills = Vec::new();
    for (at_s, target, fault) in plan {
        while started.elapsed().as_secs_f64() < at_s {
            swarm::reap(swarm)?;
            std::thread::sleep(Duration::from_millis(50));
        }
        swarm::reap(swarm)?;
        let killed = match fault {
            Fault::Sigkill => swarm.kill(target)?,
            Fault::WhileStoring(point) => crash_while_storing(swarm, point)?,
        };
        let how = match fault {
            Fault::Sigkill => "killed (SIGKILL)".to_string(),
            Fault::WhileStoring(point) => format!("died storing a keyframe ({})", point.name()),
        };
        eprintln!(
            "[chaos] {:>6.1} s: {target} {}",
            started.elapsed().as_secs_f64(),
            if killed {
                format!("{how}, starting it again")
            } else {
                "had already ended (or stored nothing): not killed".to_string()
            }
        );
        if killed {
            std::thread::sleep(restart_after);
            swarm.spawn(target)?;
        }
        kills.push(Kill {
            at_s,
            target,
            fault,
            killed,
        });
    }
    Ok(kills)
}

/// Arms the consensus's fault injection and waits until it has killed itself storing a
/// keyframe; false when it was not running, or stored none within [`STORE_CRASH_WAIT`].
fn crash_while_storing(swarm: &mut Supervisor, point: CrashPoint) -> anyhow::Result<bool> {
    if !swarm.is_running(Role::Consensus) {
        return Ok(false);
    }
    let trigger = swarm.launch().out.join(CRASH_TRIGGER_FILE);
    std::fs::write(&trigger, point.name())
        .with_context(|| format!("writing {}", trigger.display()))?;
    let armed = Instant::now();
    loop {
        for (role, exit) in swarm.poll()? {
            if role == Role::Consensus && exit.signal == Some(libc::SIGKILL) {
                return Ok(true);
            }
            anyhow::ensure!(
                exit.success(),
                "{role} exited with {exit}; see {}",
                swarm.log_of(role).display()
            );
            if role == Role::Consensus {
                let _ = std::fs::remove_file(&trigger);
                return Ok(false);
            }
        }
        if armed.elapsed() > STORE_CRASH_WAIT {
            let _ = std::fs::remove_file(&trigger);
            return Ok(false);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn report(
    args: &ChaosArgs,
    kills: Vec<Kill>,
    reference: RunChecks,
    chaos: RunChecks,
) -> ChaosReport {
    let mut failures = Vec::new();
    let killed_agents = if args.only_consensus { 0 } else { args.agents };
    let roles: Vec<Role> = std::iter::once(Role::Consensus)
        .chain((0..killed_agents).map(Role::Agent))
        .collect();
    let kills_per_process: Vec<(String, usize)> = roles
        .iter()
        .map(|role| {
            let done = kills
                .iter()
                .filter(|k| k.killed && k.target == *role && k.fault == Fault::Sigkill)
                .count();
            (role.to_string(), done)
        })
        .collect();
    let store_crashes = kills
        .iter()
        .filter(|k| k.killed && matches!(k.fault, Fault::WhileStoring(_)))
        .count();
    if store_crashes < args.store_crashes {
        failures.push(format!(
            "the consensus died storing a keyframe {store_crashes} times, {} planned (it stored \
             none in time: narrow --window)",
            args.store_crashes
        ));
    }
    for (role, done) in &kills_per_process {
        if *done < args.kills_each {
            failures.push(format!(
                "{role} killed {done} times, {} planned (it ended first: widen --frames or \
                 narrow --window)",
                args.kills_each
            ));
        }
    }
    for (name, run) in [("reference", &reference), ("killed", &chaos)] {
        failures.extend(run.failures.iter().map(|f| format!("{name} run: {f}")));
    }
    ChaosReport {
        seed: args.seed,
        agents: args.agents,
        frames: args.frames,
        restarts: kills.iter().filter(|k| k.killed).count(),
        store_crashes,
        kills,
        kills_per_process,
        reference,
        chaos,
        passed: failures.is_empty(),
        failures,
    }
}

fn print_table(report: &ChaosReport) {
    let opt =
        |v: Option<f64>, scale: f64, d: usize| v.map_or("-".into(), |v| fmt_num(v * scale, d));
    println!(
        "chaos soak: seed {}, {} agents x {} frames",
        report.seed, report.agents, report.frames
    );
    for (role, done) in &report.kills_per_process {
        println!("  {:<36} {:>12}", format!("{role}: SIGKILLs"), done);
    }
    println!(
        "  {:<36} {:>12}",
        "consensus deaths while storing", report.store_crashes
    );
    println!("  {:<36} {:>12}", "restarts", report.restarts);
    println!("  {:<36} {:>12} {:>12}", "", "no kills", "with kills");
    let (a, b) = (&report.reference, &report.chaos);
    let rows = [
        (
            "keyframes delivered (last runs)",
            a.keyframes_delivered.to_string(),
            b.keyframes_delivered.to_string(),
        ),
        (
            "of them in the final state",
            a.keyframes_in_final_state.to_string(),
            b.keyframes_in_final_state.to_string(),
        ),
        (
            "keyframes in consensus.json",
            a.consensus_keyframes.to_string(),
            b.consensus_keyframes.to_string(),
        ),
        (
            "joint ATE cm",
            opt(a.ate_joint_rmse_m, 100.0, 2),
            opt(b.ate_joint_rmse_m, 100.0, 2),
        ),
        ("PSNR dB", opt(a.psnr, 1.0, 2), opt(b.psnr, 1.0, 2)),
        (
            "agents linked",
            a.agents_linked.to_string(),
            b.agents_linked.to_string(),
        ),
    ];
    for (name, x, y) in rows {
        println!("  {name:<36} {x:>12} {y:>12}");
    }
    if report.passed {
        println!("  every check held");
    } else {
        for failure in &report.failures {
            println!("  FAILED: {failure}");
        }
    }
}

/// The run folder's consensus.json.
fn read_json(path: &Path) -> anyhow::Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}
