//! Start-up shared by the workspace's binaries (`mac-agent`, `mac-consensus`, `mac-ego3d`):
//! logging and the stop flag raised by termination signals, set up the same way everywhere.

use std::path::Path;
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

/// Creates a process's output folder and checks that files can be created in it, so that a run
/// into a folder it cannot write (a file in its place, no permission, a read-only mount) stops
/// at start with an error naming the folder, not after minutes of work when the first output is
/// written.
pub fn prepare_output_dir(dir: &Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("creating output directory {}", dir.display()))?;
    let probe = dir.join(format!(".write-check-{}", std::process::id()));
    std::fs::File::create(&probe)
        .and_then(|_| std::fs::remove_file(&probe))
        .with_context(|| format!("output directory {} is not writable", dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_folder_that_is_a_file_is_refused_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        prepare_output_dir(&dir.path().join("a/b")).unwrap();
        assert_eq!(
            std::fs::read_dir(dir.path().join("a/b")).unwrap().count(),
            0
        );
        let file = dir.path().join("taken");
        std::fs::write(&file, "").unwrap();
        for out in [file.clone(), file.join("run")] {
            let error = format!("{:#}", prepare_output_dir(&out).unwrap_err());
            assert!(error.contains(&out.display().to_string()), "{error}");
        }
    }
}
