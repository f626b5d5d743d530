//! Start-up shared by the workspace's binaries (`mac-agent`, `mac-consensus`, `mac-ego3d`):
//! logging, the stop flag raised by termination signals, and the scheduling priority of work
//! that must yield to real-time tracking, set up the same way everywhere.

use std::io::IsTerminal;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;

/// The log filter without `RUST_LOG`: `info`, except RustDDS (live ROS 2 topics), which logs
/// every discovery step at info and every unreachable peer at warn, and ros2-client, which warns
/// that ROS_DISTRO is unset (no ROS installation is needed): their errors only.
pub const DEFAULT_LOG_FILTER: &str = "info,rustdds=error,ros2_client::distributions=error";

/// The start-up every binary makes first in `main`, before any thread runs: a runtime folder for
/// the Vulkan loader when the environment lacks one ([`provide_runtime_dir`]), then logging with
/// `tracing` to stderr (stdout is for results a user or script reads), at the level `RUST_LOG`
/// names, [`DEFAULT_LOG_FILTER`] without it. Colours only on a terminal: a log redirected to a file (a swarm's
/// `*.log`) is plain text.
pub fn init_logging() {
    provide_runtime_dir();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(DEFAULT_LOG_FILTER)),
        )
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .init();
}

/// Mesa's Vulkan loader (libwayland, probing for a display) prints "error: XDG_RUNTIME_DIR is
/// invalid or not set in the environment." twice in every process that opens a device when the
/// variable is unset or not an absolute path to a folder, as on a headless machine, in a
/// container or over plain ssh. Nothing here opens a window: a private, empty runtime folder
/// (`$TMPDIR/mac-ego3d-runtime-UID`, mode 700, owned by this user) silences it and hides no other
/// message; child processes inherit it. A folder of that name owned by someone else is not used
/// (the message then stays).
///
/// Sets an environment variable: call it before any thread is started (as [`init_logging`]).
pub fn provide_runtime_dir() {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    let valid = std::env::var_os("XDG_RUNTIME_DIR")
        .map(std::path::PathBuf::from)
        .is_some_and(|dir| dir.is_absolute() && dir.is_dir());
    if valid {
        return;
    }
    // SAFETY: getuid(2) has no preconditions and cannot fail.
    let uid = unsafe { libc::getuid() };
    let dir = std::env::temp_dir().join(format!("mac-ego3d-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let private = std::fs::symlink_metadata(&dir).is_ok_and(|meta| {
        meta.is_dir() && meta.uid() == uid && meta.permissions().mode() & 0o777 == 0o700
    });
    if private {
        // SAFETY: called at the start of `main` before any thread exists (see above), so no
        // other thread reads or writes the environment meanwhile.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", &dir) };
    }
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

/// Lowers the calling thread's scheduling priority to `niceness` (0: unchanged). On Linux the
/// nice value belongs to the thread, and threads it starts afterwards inherit it.
pub fn lower_thread_priority(niceness: i32) {
    if niceness != 0 {
        // `who = 0`: the calling thread.
        set_thread_niceness(0, niceness);
    }
}

/// Lowers the priority of every thread of this process to `niceness` (0: unchanged); threads
/// started later inherit it from the thread that starts them.
pub fn lower_process_priority(niceness: i32) {
    if niceness == 0 {
        return;
    }
    let threads = match std::fs::read_dir("/proc/self/task") {
        Ok(threads) => threads,
        Err(error) => {
            tracing::warn!(niceness, %error, "could not list this process's threads to lower their priority");
            return;
        }
    };
    for thread in threads.flatten() {
        let Some(tid) = thread
            .file_name()
            .to_str()
            .and_then(|t| t.parse::<libc::id_t>().ok())
        else {
            continue;
        };
        set_thread_niceness(tid, niceness);
    }
}

/// Sets thread `tid`'s nice value (0: the calling thread). A failure only costs tracking its
/// head start, so it is logged, not returned.
fn set_thread_niceness(tid: libc::id_t, niceness: i32) {
    // SAFETY: setpriority reads only its integer arguments; a thread id names one thread.
    if unsafe { libc::setpriority(libc::PRIO_PROCESS, tid, niceness) } != 0 {
        tracing::warn!(
            niceness,
            tid,
            error = %std::io::Error::last_os_error(),
            "could not lower a thread's priority: it shares the cores with tracking as an equal"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The calling thread's nice value.
    fn own_niceness() -> i32 {
        // SAFETY: getpriority reads only its integer arguments; `who = 0` is the calling thread.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
    }

    /// Lowering the whole process would slow the other tests: the check runs in a child
    /// process of this test binary, which runs only this test.
    #[test]
    fn a_lowered_process_priority_holds_for_threads_started_before_and_after() {
        const CHILD: &str = "MAC_EGO3D_PRIORITY_CHECK_CHILD";
        if std::env::var_os(CHILD).is_none() {
            let child = std::process::Command::new(std::env::current_exe().unwrap())
                .args([
                    "--exact",
                    "process::tests::a_lowered_process_priority_holds_for_threads_started_before_and_after",
                ])
                .env(CHILD, "1")
                .output()
                .unwrap();
            assert!(
                child.status.success(),
                "the child check failed: {}\n{}",
                String::from_utf8_lossy(&child.stdout),
                String::from_utf8_lossy(&child.stderr)
            );
            return;
        }
        let (go, wait) = std::sync::mpsc::channel::<()>();
        let before = std::thread::spawn(move || {
            wait.recv().unwrap();
            own_niceness()
        });
        lower_process_priority(6);
        go.send(()).unwrap();
        assert_eq!(before.join().unwrap(), 6, "a thread started before");
        assert_eq!(own_niceness(), 6, "the calling thread");
        assert_eq!(
            std::thread::spawn(own_niceness).join().unwrap(),
            6,
            "a thread started after"
        );
    }

    #[test]
    fn a_lowered_priority_holds_for_the_thread_and_the_threads_it_starts_only() {
        // What the test process was started with (0, or more under `nice cargo test`).
        let started_with = own_niceness();
        let (own, child) = std::thread::spawn(|| {
            lower_thread_priority(7);
            let child = std::thread::spawn(own_niceness).join().unwrap();
            (own_niceness(), child)
        })
        .join()
        .unwrap();
        assert_eq!((own, child), (7, 7));
        // A sibling started afterwards (tracking's threads) keeps the process's niceness.
        assert_eq!(
            std::thread::spawn(own_niceness).join().unwrap(),
            started_with
        );
    }

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
