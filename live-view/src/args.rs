//! The live-view options every process of the swarm takes (`mac-agent`, `mac-consensus`).

use std::path::PathBuf;

use anyhow::Context;

use crate::handle::{LiveView, LiveViewSettings};

/// Where a rerun viewer listens for SDKs by default (`rerun` with no arguments).
pub const DEFAULT_VIEWER_ADDRESS: &str = "127.0.0.1:9876";

/// `--viewer [ADDR]`, `--record DIR`, `--recording-id ID`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct LiveViewArgs {
    /// Stream to a rerun viewer over gRPC: ADDR is `HOST:PORT` or a `rerun+http://HOST:PORT/proxy`
    /// URL (default 127.0.0.1:9876, where `rerun` listens). The run never waits for the viewer:
    /// what it cannot take in time is dropped and counted.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = DEFAULT_VIEWER_ADDRESS)]
    pub viewer: Option<String>,
    /// Write the live view to DIR/<process>.rrd (DIR/<process>-2.rrd, ... when that exists: a
    /// restarted process); open the swarm's files together with `rerun DIR/*.rrd`.
    #[arg(long, value_name = "DIR")]
    pub record: Option<PathBuf>,
    /// The rerun recording id: the same for every process of one swarm run, so that one viewer
    /// shows them together. Default: the run's namespace.
    #[arg(long, value_name = "ID")]
    pub recording_id: Option<String>,
}

impl LiveViewArgs {
    /// Whether any live-view output was asked for.
    pub fn is_requested(&self) -> bool {
        self.viewer.is_some() || self.record.is_some()
    }

    /// The live view these options ask for, for the process named `process` (its .rrd file is
    /// `process.rrd`), with `default_recording_id` unless `--recording-id` was given;
    /// [`LiveView::disabled`] without `--viewer` and `--record`.
    pub fn open(&self, process: &str, default_recording_id: &str) -> anyhow::Result<LiveView> {
        if !self.is_requested() {
            return Ok(LiveView::disabled());
        }
        let recording_id = self
            .recording_id
            .clone()
            .unwrap_or_else(|| default_recording_id.to_string());
        let file = match &self.record {
            Some(dir) => {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("--record {}: cannot create it", dir.display()))?;
                Some(free_recording_path(dir, process))
            }
            None => None,
        };
        let viewer = self.viewer.as_deref().map(viewer_url);
        LiveView::open(
            &recording_id,
            viewer.as_deref(),
            file.as_deref(),
            LiveViewSettings::default(),
        )
    }
}

/// `dir/process.rrd`, or when that exists (the process was restarted on the same run),
/// `dir/process-2.rrd`, `dir/process-3.rrd`, ...: a recording is never overwritten.
fn free_recording_path(dir: &std::path::Path, process: &str) -> PathBuf {
    let first = dir.join(format!("{process}.rrd"));
    if !first.exists() {
        return first;
    }
    (2..)
        .map(|n| dir.join(format!("{process}-{n}.rrd")))
        .find(|path| !path.exists())
        .expect("some numbered name is free")
}

/// The gRPC URL of a viewer address: `HOST:PORT` becomes `rerun+http://HOST:PORT/proxy`; a URL
/// is kept as it is.
pub fn viewer_url(address: &str) -> String {
    if address.contains("://") {
        address.to_string()
    } else {
        format!("rerun+http://{address}/proxy")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        live_view: LiveViewArgs,
    }

    #[test]
    fn viewer_takes_an_optional_address() {
        let bare = Cli::parse_from(["x", "--viewer", "--record", "/tmp/r"]).live_view;
        assert_eq!(bare.viewer.as_deref(), Some(DEFAULT_VIEWER_ADDRESS));
        assert_eq!(bare.record, Some(PathBuf::from("/tmp/r")));
        let given = Cli::parse_from(["x", "--viewer", "127.0.0.1:1234"]).live_view;
        assert_eq!(given.viewer.as_deref(), Some("127.0.0.1:1234"));
        let none = Cli::parse_from(["x"]).live_view;
        assert!(!none.is_requested());
        assert_eq!(
            viewer_url("127.0.0.1:1234"),
            "rerun+http://127.0.0.1:1234/proxy"
        );
        assert_eq!(
            viewer_url("rerun+http://host:1/proxy"),
            "rerun+http://host:1/proxy"
        );
    }
}
