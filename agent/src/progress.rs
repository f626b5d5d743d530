//! `progress.json` in the agent's output directory: how far the run is, for
//! `mac-ego3d swarm`'s progress line.
//!
//! Written from the tracking loop at most every [`PROGRESS_FILE_EVERY`], so it costs one small
//! write twice a second; atomically (a temporary file renamed over the old one), so a reader
//! never sees half a file. A failed write is logged once and never stops the run.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

/// Least time between two writes of the progress file.
pub const PROGRESS_FILE_EVERY: Duration = Duration::from_millis(500);

/// The progress file's name, in the agent's output directory.
pub const PROGRESS_FILE_NAME: &str = "progress.json";

/// What the agent is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// The frame loop runs.
    Tracking,
    /// Tracking is over: final map, goodbye, evaluation.
    Finishing,
    /// The run is over and its outputs, metrics.json last, are written.
    Done,
}

/// One snapshot of progress.json.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Progress {
    /// What the agent is doing.
    pub stage: Stage,
    /// Frames the loop has taken so far (lost ones included, frames dropped at sensor pace not).
    pub frames_done: usize,
    /// Absent (null) when the source does not know its length.
    pub frames_total: Option<usize>,
    /// Keyframes made so far.
    pub keyframes: usize,
    /// Swarm mode only: whether the link to the consensus is up, and keyframes queued for it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub link_up: Option<bool>,
    /// Swarm mode only: keyframes queued until the link is up.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub queued_keyframes: Option<usize>,
}

/// The progress file of one run.
pub struct ProgressFile {
    path: PathBuf,
    temporary: PathBuf,
    last_write: Option<Instant>,
    failed: bool,
}

impl ProgressFile {
    /// The progress file in the output directory `out`; nothing is written before the first
    /// [`Self::update`] or [`Self::write`].
    pub fn new(out: &std::path::Path) -> Self {
        Self {
            path: out.join(PROGRESS_FILE_NAME),
            temporary: out.join(format!(".{PROGRESS_FILE_NAME}.tmp")),
            last_write: None,
            failed: false,
        }
    }

    /// Writes `progress` unless the last write was less than [`PROGRESS_FILE_EVERY`] ago.
    /// `progress` is only built when it is written.
    pub fn update(&mut self, progress: impl FnOnce() -> Progress) {
        if self
            .last_write
            .is_some_and(|at| at.elapsed() < PROGRESS_FILE_EVERY)
        {
            return;
        }
        self.write(&progress());
    }

    /// Writes `progress` now (stage changes).
    pub fn write(&mut self, progress: &Progress) {
        self.last_write = Some(Instant::now());
        if let Err(error) = self.replace(progress) {
            if !self.failed {
                tracing::warn!(path = %self.path.display(), %error, "progress file not written");
            }
            self.failed = true;
        }
    }

    fn replace(&self, progress: &Progress) -> std::io::Result<()> {
        let json = serde_json::to_vec(progress).map_err(std::io::Error::other)?;
        std::fs::write(&self.temporary, json)?;
        std::fs::rename(&self.temporary, &self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn snapshot(frames_done: usize) -> Progress {
        Progress {
            stage: Stage::Tracking,
            frames_done,
            frames_total: Some(200),
            keyframes: 3,
            link_up: None,
            queued_keyframes: None,
        }
    }

    fn read(dir: &std::path::Path) -> serde_json::Value {
        let text = std::fs::read_to_string(dir.join(PROGRESS_FILE_NAME)).unwrap();
        serde_json::from_str(&text).unwrap()
    }

    #[test]
    fn writes_whole_json_and_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = ProgressFile::new(dir.path());
        file.write(&Progress {
            link_up: Some(false),
            queued_keyframes: Some(2),
            ..snapshot(120)
        });
        let json = read(dir.path());
        assert_eq!(json["stage"], "tracking");
        assert_eq!(json["frames_done"], 120);
        assert_eq!(json["frames_total"], 200);
        assert_eq!(json["keyframes"], 3);
        assert_eq!(json["link_up"], false);
        assert_eq!(json["queued_keyframes"], 2);
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from(PROGRESS_FILE_NAME)]);
    }

    #[test]
    fn updates_are_throttled_but_stage_changes_are_not() {
        let dir = tempfile::tempdir().unwrap();
        let mut file = ProgressFile::new(dir.path());
        file.update(|| snapshot(1));
        file.update(|| panic!("built although it is not written"));
        assert_eq!(read(dir.path())["frames_done"], 1);
        file.write(&Progress {
            stage: Stage::Done,
            ..snapshot(200)
        });
        assert_eq!(read(dir.path())["stage"], "done");
        assert!(read(dir.path()).get("link_up").is_none());
    }

    #[test]
    fn an_unwritable_directory_is_not_fatal() {
        let mut file = ProgressFile::new(std::path::Path::new("/nonexistent/agent"));
        file.write(&snapshot(1));
        file.write(&snapshot(2));
        assert!(file.failed);
    }
}
