//! `protocol-peer`: a small second process for the protocol crate's multi-process tests and the
//! IPC benchmark.
//!
//! ```text
//! protocol-peer agent --namespace NS --agent-id K [--descriptors N] [--patches P]
//!               [--patch-records R] [--interval-ms M] [--forever] [--await-correction]
//!               [--await-control N]
//! protocol-peer bench-peer --namespace NS --poll-before-wait-us US   (started by the benchmark)
//! protocol-peer bench            # runs the IPC benchmark against itself, prints JSON
//! ```
//! The agent role prints progress lines on stdout (`opened epoch=E`, `announced`,
//! `correction poses=N`, `control seq=S ...` per control message, `done`) that tests wait for. Exit codes: 0 success,
//! [`EXIT_DUPLICATE_AGENT`] when the id is taken, [`EXIT_FAILURE`] on any other error,
//! [`EXIT_USAGE`] on bad arguments.

use std::io::Write;
use std::process::ExitCode;
use std::time::Duration;

use protocol::bench::{
    IpcBenchConfig, PeerCommand, run_ipc_bench, run_peer, synthetic_descriptor, synthetic_record,
};
use protocol::messages::{ControlMessage, CoordinateFrame};
use protocol::transport::{AgentLink, TransportConfig, TransportError};

const EXIT_FAILURE: u8 = 1;
const EXIT_USAGE: u8 = 2;
const EXIT_DUPLICATE_AGENT: u8 = 3;
/// Longest wait for a correction with `--await-correction`, and for each control message with
/// `--await-control`.
const CORRECTION_TIMEOUT: Duration = Duration::from_secs(20);
/// Configuration hash announced by the test agent (any fixed value).
const PEER_CONFIG_HASH: u64 = 0x7e57;

#[derive(Debug, Default)]
struct AgentArgs {
    namespace: Option<String>,
    agent_id: u32,
    descriptors: u64,
    patches: u64,
    patch_records: usize,
    interval: Duration,
    forever: bool,
    await_correction: bool,
    /// Control messages to wait for (and print) before closing.
    await_control: u64,
}

fn parse_agent_args(args: &[String]) -> Result<AgentArgs, String> {
    let mut parsed = AgentArgs::default();
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let mut value = |name: &str| it.next().cloned().ok_or(format!("{name} needs a value"));
        let number =
            |text: String, name: &str| text.parse::<u64>().map_err(|e| format!("{name}: {e}"));
        match flag.as_str() {
            "--namespace" => parsed.namespace = Some(value(flag)?),
            "--agent-id" => parsed.agent_id = number(value(flag)?, flag)? as u32,
            "--descriptors" => parsed.descriptors = number(value(flag)?, flag)?,
            "--patches" => parsed.patches = number(value(flag)?, flag)?,
            "--patch-records" => parsed.patch_records = number(value(flag)?, flag)? as usize,
            "--interval-ms" => parsed.interval = Duration::from_millis(number(value(flag)?, flag)?),
            "--forever" => parsed.forever = true,
            "--await-correction" => parsed.await_correction = true,
            "--await-control" => parsed.await_control = number(value(flag)?, flag)?,
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(parsed)
}

fn say(line: &str) {
    let mut out = std::io::stdout().lock();
    // A closed stdout only means nobody listens; the exit code still reports the outcome.
    let _ = writeln!(out, "{line}");
    let _ = out.flush();
}

fn run_agent(args: &AgentArgs) -> Result<(), TransportError> {
    let namespace = args
        .namespace
        .clone()
        .unwrap_or_else(|| protocol::services::DEFAULT_NAMESPACE.into());
    let config = TransportConfig::with_namespace(namespace);
    let mut link = AgentLink::open(&config, args.agent_id)?;
    say(&format!("opened epoch={}", link.epoch()));
    link.announce(protocol::bench::SAMPLE_INTRINSICS, PEER_CONFIG_HASH, 0)?;
    say("announced");
    let mut keyframe = 0u64;
    loop {
        for _ in 0..args.descriptors.max(u64::from(args.forever)) {
            link.send_descriptor(&synthetic_descriptor(keyframe))?;
            keyframe += 1;
            std::thread::sleep(args.interval);
        }
        if !args.forever {
            break;
        }
    }
    for patch in 0..args.patches {
        link.send_patch_with(
            patch,
            CoordinateFrame::AgentWorld,
            args.patch_records,
            |i| synthetic_record(patch, i),
        )?;
    }
    if args.await_correction {
        match link.recv_correction_timeout(CORRECTION_TIMEOUT)? {
            Some(c) => say(&format!(
                "correction poses={} first_keyframe={} tx={}",
                c.poses().len(),
                c.poses().first().map_or(0, |p| p.keyframe_id),
                c.header().agent_world_to_world.translation[0]
            )),
            None => say("correction none"),
        }
    }
    for _ in 0..args.await_control {
        match link.recv_control_timeout(CORRECTION_TIMEOUT)? {
            Some(control) => say(&format!(
                "control seq={} {}",
                control.header.stamp.sequence,
                describe_control(&control.message)
            )),
            None => say("control none"),
        }
    }
    link.close()?;
    say("done");
    Ok(())
}

/// One line per control message, for the tests to compare.
fn describe_control(message: &ControlMessage) -> String {
    match message {
        ControlMessage::AgentConfig { agent_id, .. } => format!("agent_config agent={agent_id}"),
        ControlMessage::Shutdown { reason } => format!("shutdown reason={reason}"),
        ControlMessage::ResendKeyframe {
            keyframe_id,
            reason,
        } => format!("resend_keyframe keyframe={keyframe_id} reason={reason}"),
        ControlMessage::ConsensusResumed { keyframes_held } => {
            format!("consensus_resumed held={}", keyframes_held.len())
        }
        ControlMessage::MessagesLost {
            keyframes_held,
            keyframes_in_part,
            newest_seen,
        } => format!(
            "messages_lost held={} in_part={} newest_seen={newest_seen}",
            keyframes_held.len(),
            keyframes_in_part.len()
        ),
    }
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage =
        "usage: protocol-peer (agent|bench-peer) --namespace NS [options] | protocol-peer bench";
    match args.first().map(String::as_str) {
        Some("agent") => {
            let parsed = match parse_agent_args(&args[1..]) {
                Ok(p) => p,
                Err(e) => {
                    eprintln!("{e}\n{usage}");
                    return ExitCode::from(EXIT_USAGE);
                }
            };
            match run_agent(&parsed) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e @ TransportError::DuplicateAgent { .. }) => {
                    eprintln!("protocol-peer: {e}");
                    ExitCode::from(EXIT_DUPLICATE_AGENT)
                }
                Err(e) => {
                    eprintln!("protocol-peer: {e}");
                    ExitCode::from(EXIT_FAILURE)
                }
            }
        }
        Some("bench-peer") => {
            let (namespace, poll_before_wait) = match args.get(1..) {
                Some([ns_flag, ns, poll_flag, poll_us])
                    if ns_flag == "--namespace" && poll_flag == "--poll-before-wait-us" =>
                {
                    match poll_us.parse::<u64>() {
                        Ok(us) => (ns.clone(), Duration::from_micros(us)),
                        Err(e) => {
                            eprintln!("--poll-before-wait-us '{poll_us}': {e}\n{usage}");
                            return ExitCode::from(EXIT_USAGE);
                        }
                    }
                }
                _ => {
                    eprintln!("{usage}");
                    return ExitCode::from(EXIT_USAGE);
                }
            };
            match run_peer(&namespace, poll_before_wait) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    eprintln!("protocol-peer bench-peer: {e}");
                    ExitCode::from(EXIT_FAILURE)
                }
            }
        }
        Some("bench") => match run_bench() {
            Ok(json) => {
                say(&json);
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("protocol-peer bench: {e}");
                ExitCode::from(EXIT_FAILURE)
            }
        },
        _ => {
            eprintln!("{usage}");
            ExitCode::from(EXIT_USAGE)
        }
    }
}

/// The IPC benchmark with this executable as its peer; returns the report as JSON.
fn run_bench() -> Result<String, Box<dyn std::error::Error>> {
    let peer = PeerCommand {
        program: std::env::current_exe()?,
        args: vec!["bench-peer".into()],
    };
    let report = run_ipc_bench(&IpcBenchConfig::default(), &peer)?;
    Ok(serde_json::to_string_pretty(&report)?)
}
