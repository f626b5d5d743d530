//! Everything checked and prepared before a process starts: the agents' datasets, the run's
//! configuration (written to DIR/config.toml), the binaries, the weights, the link schedule, the
//! live view and, with zenoh, the simulated hosts. A mistake here stops the launch with exit
//! status 2 and a message naming the option, before anything runs.

use std::ffi::OsString;
use std::io::IsTerminal;
use std::net::{TcpStream, ToSocketAddrs};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use datasets::{DatasetSpec, FrameRange};
use mac_agent::link_schedule::LinkSchedule;

use super::SwarmArgs;
use super::hosts::{SimulatedHosts, find_script};
use super::record::Transport;
use super::supervisor::Launch;
use crate::cmd::UsageError;

/// How long an interrupted consensus waits for the agents' final maps and goodbyes.
pub const STOP_WAIT_S: f64 = 60.0;

/// A prepared launch: the processes' command lines and what the launcher does around them.
pub struct Plan {
    pub launch: Launch,
    pub transport: Transport,
    /// LPIPS weights for the run's figures (the `--descriptor-weights` file carries LPIPS's
    /// layers too).
    pub lpips_weights: Option<PathBuf>,
}

fn usage(message: String) -> anyhow::Error {
    UsageError(message).into()
}

/// Checks the options and prepares the run folder.
pub fn prepare(args: &SwarmArgs) -> anyhow::Result<Plan> {
    let datasets = agent_datasets(args)?;
    let agents = datasets.len() as u32;
    if !args.config.is_file() {
        return Err(usage(format!(
            "--config {}: no such file",
            args.config.display()
        )));
    }
    check_transport(args)?;
    let binaries = binaries(args)?;
    config::process::prepare_output_dir(&args.out)?;
    let run_config = args.out.join("config.toml");
    write_run_config(args, &run_config)?;

    let mut agent_args: Vec<OsString> = Vec::new();
    let mut lpips_weights = None;
    if let Some(weights) = &args.descriptor_weights {
        if !weights.is_file() {
            return Err(usage(format!(
                "--descriptor-weights {}: no such file",
                weights.display()
            )));
        }
        agent_args.extend(["--descriptor-weights".into(), weights.into()]);
        lpips_weights = Some(weights.clone());
    }
    if let Some(schedule) = &args.link_schedule {
        let kept = copy_link_schedule(schedule, &args.out, agents)?;
        agent_args.extend(["--link-schedule".into(), kept.into()]);
    }

    // One namespace per run, so two runs on one host never share services; the run id names
    // the run in the consensus store.
    let namespace = format!("mac{}", std::process::id());
    let started_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let run_id = format!("{namespace}-{started_s}");
    let live_args = live_view_args(args, &run_id)?;
    agent_args.extend(live_args.iter().cloned());
    let mut consensus_args: Vec<OsString> =
        vec!["--stop-agents".into(), STOP_WAIT_S.to_string().into()];
    consensus_args.extend(live_args);

    let hosts = match args.transport {
        Transport::Iceoryx2 => None,
        Transport::Zenoh => {
            let hosts = SimulatedHosts::prepare(
                find_script()?,
                &binaries,
                &namespace,
                agents,
                args.insecure_plain_tcp,
                &args.out,
                &run_config,
            )?;
            if hosts.is_plain_tcp() {
                eprintln!(
                    "[swarm] WARNING: --insecure-plain-tcp: the simulated hosts talk plain TCP \
                     without authentication"
                );
            }
            eprintln!(
                "[swarm] transport zenoh: simulated hosts joined over {}; bridge logs in {}/*.log",
                hosts.endpoint(),
                args.out.display()
            );
            Some(hosts)
        }
    };
    Ok(Plan {
        launch: Launch {
            binaries,
            config: run_config,
            out: args.out.clone(),
            namespace,
            run_id,
            datasets,
            agent_threads: Some(agent_threads(agents)),
            agent_args,
            consensus_args,
            hosts,
        },
        transport: args.transport,
        lpips_weights,
    })
}

/// One dataset per agent: the `--agent` specs, else the synthetic scene's `--agents` views of
/// `--frames` frames.
fn agent_datasets(args: &SwarmArgs) -> anyhow::Result<Vec<DatasetSpec>> {
    if !args.agent.is_empty() {
        return Ok(args.agent.clone());
    }
    if args.agents == 0 {
        return Err(usage("--agents must be at least 1".into()));
    }
    Ok((0..args.agents)
        .map(|k| DatasetSpec {
            dataset: format!(
                "synthetic:agents={},agent={k},frames={}",
                args.agents, args.frames
            ),
            frames: FrameRange::ALL,
        })
        .collect())
}

fn check_transport(args: &SwarmArgs) -> anyhow::Result<()> {
    let zenoh = args.transport == Transport::Zenoh;
    // SAFETY: geteuid(2) has no preconditions and cannot fail.
    if zenoh && unsafe { libc::geteuid() } != 0 {
        return Err(usage(
            "--transport zenoh simulates hosts with mount namespaces: run as root".into(),
        ));
    }
    if args.insecure_plain_tcp && !zenoh {
        return Err(usage(
            "--insecure-plain-tcp is for --transport zenoh".into(),
        ));
    }
    if args.bandwidth.is_some() && !zenoh {
        return Err(usage(
            "--bandwidth caps traffic between hosts: give --transport zenoh too (on one host \
             the swarm shares memory)"
                .into(),
        ));
    }
    Ok(())
}

/// `--bin-dir`, else the folder of this program (cargo builds every binary into one folder).
fn binaries(args: &SwarmArgs) -> anyhow::Result<PathBuf> {
    let dir = match &args.bin_dir {
        Some(dir) => dir.clone(),
        None => std::env::current_exe()?
            .parent()
            .context("the folder of mac-ego3d")?
            .to_path_buf(),
    };
    let mut needed = vec!["mac-agent", "mac-consensus"];
    if args.transport == Transport::Zenoh {
        needed.push("mac-bridge");
    }
    for binary in needed {
        if !dir.join(binary).is_file() {
            return Err(usage(format!(
                "{} is missing (--bin-dir names the folder of mac-agent, mac-consensus and, \
                 for --transport zenoh, mac-bridge)",
                dir.join(binary).display()
            )));
        }
    }
    Ok(dir)
}

/// The given configuration with `--tcomm`, `--noise`, `--bandwidth` and every `--set` applied,
/// every key listed: the run folder says exactly what ran. Written beside and renamed: the
/// given file may be this very path (a rerun into one folder).
fn write_run_config(args: &SwarmArgs, run_config: &Path) -> anyhow::Result<()> {
    let mut overrides = Vec::new();
    if let Some(t_comm) = args.tcomm {
        overrides.push(format!("consensus.t_comm={t_comm}"));
    }
    if let Some(noise) = &args.noise {
        overrides.push(format!("noise.target={noise}"));
    }
    if let Some(kb_per_s) = args.bandwidth {
        overrides.push(format!("network.agent_kb_per_s={kb_per_s}"));
    }
    overrides.extend(args.set.iter().cloned());
    let (_, text) = crate::cmd::config::resolve(Some(&args.config), &overrides)
        .map_err(|error| usage(format!("the configuration is refused: {error:#}")))?;
    let temporary = run_config.with_extension("toml.new");
    std::fs::write(&temporary, text).with_context(|| format!("writing {}", temporary.display()))?;
    std::fs::rename(&temporary, run_config)
        .with_context(|| format!("writing {}", run_config.display()))
}

/// Keeps the schedule with the outputs (like config.toml) and checks it once here rather than
/// failing in every agent; prints every agent's windows.
fn copy_link_schedule(schedule: &Path, out: &Path, agents: u32) -> anyhow::Result<PathBuf> {
    if !schedule.is_file() {
        return Err(usage(format!(
            "--link-schedule {}: no such file",
            schedule.display()
        )));
    }
    let kept = out.join("link_schedule.toml");
    let same = std::fs::canonicalize(schedule).ok() == std::fs::canonicalize(&kept).ok();
    if !same {
        std::fs::copy(schedule, &kept)
            .with_context(|| format!("copying {} to {}", schedule.display(), kept.display()))?;
    }
    let loaded = LinkSchedule::load(&kept).map_err(|error| usage(format!("{error}")))?;
    for line in loaded.describe(agents).lines() {
        println!("[swarm] {line}");
    }
    Ok(kept)
}

/// `--viewer` / `--record` for every process, under one recording id (the run id). A local
/// viewer address with nothing listening starts `rerun` when it is on PATH.
fn live_view_args(args: &SwarmArgs, run_id: &str) -> anyhow::Result<Vec<OsString>> {
    let mut live: Vec<OsString> = Vec::new();
    if let Some(address) = &args.viewer {
        start_viewer_if_needed(address, &args.out);
        live.extend(["--viewer".into(), address.into()]);
    }
    if let Some(record) = &args.record {
        std::fs::create_dir_all(record)
            .with_context(|| format!("creating {}", record.display()))?;
        // Recordings of an earlier run into this folder would open beside this run's.
        for entry in std::fs::read_dir(record)?.flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if name.ends_with(".rrd")
                && (name.starts_with("consensus") || name.starts_with("agent_"))
            {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        live.extend(["--record".into(), record.into()]);
        println!(
            "[swarm] recording the live view to {}/*.rrd (open with: rerun {}/*.rrd)",
            record.display(),
            record.display()
        );
    }
    if !live.is_empty() {
        live.extend(["--recording-id".into(), run_id.into()]);
    }
    Ok(live)
}

fn listening(address: &str) -> bool {
    address
        .to_socket_addrs()
        .ok()
        .and_then(|mut addresses| addresses.next())
        .is_some_and(|socket| {
            TcpStream::connect_timeout(&socket, Duration::from_millis(200)).is_ok()
        })
}

fn start_viewer_if_needed(address: &str, out: &Path) {
    if address.contains("://") || listening(address) {
        println!("[swarm] live view: connecting to the rerun viewer at {address}");
        return;
    }
    let (host, port) = address.rsplit_once(':').unwrap_or((address, "9876"));
    let local = matches!(host, "127.0.0.1" | "localhost");
    let log = std::fs::File::create(out.join("rerun.log"));
    let started = match log {
        Ok(log) if local => Command::new("rerun")
            .args(["--port", port])
            .stdin(Stdio::null())
            .stdout(log.try_clone().map_or(Stdio::null(), Stdio::from))
            .stderr(log)
            // The viewer stays open after the run, in a process group of its own.
            .process_group(0)
            .spawn()
            .is_ok(),
        _ => false,
    };
    if !started {
        println!(
            "[swarm] no viewer listens at {address} (and no `rerun` on PATH to start one): the \
             processes connect to it and send once a viewer is there; what they cannot send in \
             time is dropped"
        );
        return;
    }
    println!(
        "[swarm] starting the rerun viewer (port {port}; log {}/rerun.log)",
        out.display()
    );
    for _ in 0..50 {
        if listening(address) {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// The agents share this host's cores: each tracks with its share of them (a worker pool
/// larger than its share waits at every parallel step for a worker another process holds). A
/// `RAYON_NUM_THREADS` set by the caller wins.
fn agent_threads(agents: u32) -> usize {
    if let Some(threads) = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        return threads;
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores / agents as usize).max(1)
}

/// Whether the progress line is shown (stdout is a terminal).
pub fn shows_progress() -> bool {
    std::io::stdout().is_terminal()
}
