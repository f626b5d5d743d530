//! The progress line on a terminal: per agent frames (of the total), keyframes and link state
//! from its `progress.json`; the consensus's keyframes, closures and pending alignments from
//! `consensus_progress.json`. A line wider than the terminal abbreviates the agents' part
//! (`0:120/200,8kf`).

use std::io::Write;
use std::path::Path;

use mac_agent::progress::{PROGRESS_FILE_NAME, Progress, Stage};
use mac_consensus::process::{ConsensusProgress, PROGRESS_FILE_NAME as CONSENSUS_PROGRESS};
use serde::de::DeserializeOwned;

/// Reads a progress file; `None` while it is missing or half-written.
fn read<T: DeserializeOwned>(path: &Path) -> Option<T> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Removes the progress files an earlier run in `out` left (they would show stale figures).
pub fn clear(out: &Path, agents: u32) {
    let _ = std::fs::remove_file(out.join(CONSENSUS_PROGRESS));
    for k in 0..agents {
        let _ = std::fs::remove_file(out.join(format!("agent_{k}")).join(PROGRESS_FILE_NAME));
    }
}

/// The line for the run in `out` of `agents` agents, at most `width` characters.
pub fn line(out: &Path, agents: u32, width: usize) -> String {
    let mut full = Vec::new();
    let mut short = Vec::new();
    for k in 0..agents {
        let path = out.join(format!("agent_{k}")).join(PROGRESS_FILE_NAME);
        let Some(progress) = read::<Progress>(&path) else {
            full.push(format!("agent {k}: starting"));
            short.push(format!("{k}:starting"));
            continue;
        };
        let (text, brief) = describe_agent(k, &progress);
        full.push(text);
        short.push(brief);
    }
    let consensus = read::<ConsensusProgress>(&out.join(CONSENSUS_PROGRESS))
        .map(|c| describe_consensus(&c))
        .unwrap_or_default();
    let line = format!("{}{consensus}", full.join(" | "));
    let line = if line.chars().count() > width {
        format!("agents {}{consensus}", short.join(" "))
    } else {
        line
    };
    line.chars().take(width).collect()
}

fn describe_agent(k: u32, progress: &Progress) -> (String, String) {
    let total = progress
        .frames_total
        .map(|t| format!("/{t}"))
        .unwrap_or_default();
    let mut text = format!(
        "agent {k}: {}{total} f, {} kf",
        progress.frames_done, progress.keyframes
    );
    let mut brief = format!(
        "{k}:{}{total},{}kf",
        progress.frames_done, progress.keyframes
    );
    if progress.link_up == Some(false) {
        text += &format!(
            ", link down ({} queued)",
            progress.queued_keyframes.unwrap_or(0)
        );
        brief += ",down";
    }
    match progress.stage {
        Stage::Tracking => {}
        Stage::Finishing => {
            text += ", finishing";
            brief += ",fin";
        }
        Stage::Done => {
            text += ", done";
            brief += ",done";
        }
    }
    (text, brief)
}

fn describe_consensus(progress: &ConsensusProgress) -> String {
    let mut text = format!(
        " | consensus: {} kf, {} closures ({} inter-agent)",
        progress.keyframes, progress.closures_verified, progress.inter_agent_closures
    );
    if progress.pending_alignments > 0 {
        text += &format!(", {} aligning", progress.pending_alignments);
    }
    text
}

/// The terminal's width in columns (80 when it cannot be asked).
pub fn terminal_width() -> usize {
    let mut size = libc::winsize {
        ws_row: 0,
        ws_col: 0,
        ws_xpixel: 0,
        ws_ypixel: 0,
    };
    // SAFETY: TIOCGWINSZ writes one `winsize` into the struct it is given, which lives here.
    let asked = unsafe { libc::ioctl(libc::STDOUT_FILENO, libc::TIOCGWINSZ, &mut size) };
    if asked == 0 && size.ws_col > 0 {
        size.ws_col as usize
    } else {
        80
    }
}

/// Rewrites the terminal's current line with `text`.
pub fn show(text: &str) {
    let mut stdout = std::io::stdout().lock();
    let _ = write!(stdout, "\r{text}\x1b[K");
    let _ = stdout.flush();
}

/// Erases the progress line (before a message, or at the end).
pub fn erase() {
    let mut stdout = std::io::stdout().lock();
    let _ = write!(stdout, "\r\x1b[K");
    let _ = stdout.flush();
}
