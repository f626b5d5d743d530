//! Start-up shared by the workspace's binaries (`mac-agent`, `mac-consensus`, `mac-ego3d`):
//! logging and the stop flag raised by termination signals, set up the same way everywhere.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;

/// Logs with `tracing` to stderr (stdout is for results a user or script reads), at the level
/// `RUST_LOG` names, `info` without it.
pub fn init_logging() {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
}

/// A flag raised by SIGINT or SIGTERM: long runs check it between steps, finish the current
/// one and write every output instead of dying with nothing written.
pub fn stop_on_termination_signals() -> anyhow::Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(signal, stop.clone())
            .with_context(|| format!("installing the handler of signal {signal}"))?;
    }
    Ok(stop)
}
