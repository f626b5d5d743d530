//! The peers (Open3D, splatreg) registering the same pairs: scripts/map_registration_peers.py,
//! started once and asked pair by pair over its stdin and stdout (one JSON object a line; the
//! protocol and the peers' fixed settings are in that script's documentation).

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use anyhow::{Context, bail};
use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// The driver, beside the sources.
pub const DEFAULT_DRIVER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/scripts/map_registration_peers.py"
);

/// A peer the driver runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Peer {
    Open3d,
    Splatreg,
}

impl Peer {
    pub fn name(self) -> &'static str {
        match self {
            Peer::Open3d => "open3d",
            Peer::Splatreg => "splatreg",
        }
    }
}

#[derive(Serialize)]
struct Request<'a> {
    pair: &'a str,
    source: &'a Path,
    target: &'a Path,
    splat_source: &'a Path,
    splat_target: &'a Path,
    methods: Vec<&'static str>,
}

/// One peer's answer for one pair, as the driver writes it.
#[derive(Debug, Clone, Deserialize)]
pub struct PeerAnswer {
    #[serde(default)]
    pub target_from_source: Option<Vec<f64>>,
    #[serde(default)]
    pub accepted: bool,
    #[serde(default)]
    pub time_ms: f64,
    #[serde(default)]
    pub reason: Option<String>,
    /// The driver could not run the peer on this pair.
    #[serde(default)]
    pub error: Option<String>,
    #[serde(default)]
    pub details: serde_json::Value,
}

impl PeerAnswer {
    /// The estimate as a rigid transform: the 4x4 matrix's rotation block projected onto the
    /// nearest rotation (a peer's float32 matrix is orthonormal to about 1e-7).
    pub fn transform(&self) -> anyhow::Result<Isometry3<f64>> {
        let values = self
            .target_from_source
            .as_ref()
            .context("no transform in the answer")?;
        if values.len() != 16 || values.iter().any(|v| !v.is_finite()) {
            bail!("the transform is not 16 finite numbers: {values:?}");
        }
        let m = Matrix4::from_row_slice(values);
        let block: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
        let rotation = Rotation3::from_matrix(&block);
        Ok(Isometry3::from_parts(
            Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]),
            UnitQuaternion::from_rotation_matrix(&rotation),
        ))
    }
}

#[derive(Deserialize)]
struct Reply {
    #[serde(default)]
    pair: Option<String>,
    #[serde(default)]
    results: BTreeMap<String, PeerAnswer>,
    #[serde(default)]
    error: Option<String>,
}

/// The running driver.
pub struct PeerDriver {
    child: Child,
    /// `None` once closed (which ends the driver's loop).
    stdin: Option<ChildStdin>,
    stdout: BufReader<ChildStdout>,
    peers: Vec<Peer>,
}

impl PeerDriver {
    /// Starts `driver` with `python`, the peers on `threads` threads each.
    pub fn start(
        python: &Path,
        driver: &Path,
        peers: &[Peer],
        threads: usize,
        splatreg_init: &str,
    ) -> anyhow::Result<Self> {
        let mut child = Command::new(python)
            .arg(driver)
            .args(["--threads", &threads.to_string()])
            .args(["--splatreg-init", splatreg_init])
            .env("OMP_NUM_THREADS", threads.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| {
                format!(
                    "starting {} {} (the peers' python: scripts/peers_venv.sh prints it)",
                    python.display(),
                    driver.display()
                )
            })?;
        let stdin = child.stdin.take().context("the driver's stdin")?;
        let stdout = BufReader::new(child.stdout.take().context("the driver's stdout")?);
        Ok(Self {
            child,
            stdin: Some(stdin),
            stdout,
            peers: peers.to_vec(),
        })
    }

    /// Every peer's answer for the maps in `files` (3DGS PLY files).
    pub fn register(
        &mut self,
        pair: &str,
        files: &PairFiles,
    ) -> anyhow::Result<BTreeMap<Peer, PeerAnswer>> {
        let request = Request {
            pair,
            source: &files.source,
            target: &files.target,
            splat_source: &files.splat_source,
            splat_target: &files.splat_target,
            methods: self.peers.iter().map(|p| p.name()).collect(),
        };
        let mut line = serde_json::to_string(&request)?;
        line.push('\n');
        let stdin = self.stdin.as_mut().context("the peers' driver is closed")?;
        stdin
            .write_all(line.as_bytes())
            .and_then(|()| stdin.flush())
            .context("writing to the peers' driver (did it exit?)")?;
        let mut answer = String::new();
        let read = self.stdout.read_line(&mut answer)?;
        if read == 0 {
            bail!("the peers' driver exited before answering pair {pair}");
        }
        let reply: Reply = serde_json::from_str(&answer)
            .with_context(|| format!("the peers' driver answered {answer:?}"))?;
        if let Some(error) = reply.error {
            bail!("the peers' driver refused pair {pair}: {error}");
        }
        if reply.pair.as_deref() != Some(pair) {
            bail!(
                "the peers' driver answered for {:?}, not {pair}",
                reply.pair
            );
        }
        let mut answers = BTreeMap::new();
        for peer in &self.peers {
            let answer = reply
                .results
                .get(peer.name())
                .cloned()
                .with_context(|| format!("no answer of {} for pair {pair}", peer.name()))?;
            answers.insert(*peer, answer);
        }
        Ok(answers)
    }
}

impl Drop for PeerDriver {
    fn drop(&mut self) {
        // Closing stdin ends the driver's loop.
        drop(self.stdin.take());
        let _ = self.child.wait();
    }
}

/// One pair's Gaussian maps: at the maps' spacing, and with one Gaussian per
/// [`SPLATREG_SPACING_M`] cell for splatreg (see the driver's documentation).
pub struct PairFiles {
    pub source: PathBuf,
    pub target: PathBuf,
    pub splat_source: PathBuf,
    pub splat_target: PathBuf,
}

/// Spacing of the Gaussian maps splatreg gets (metres).
pub const SPLATREG_SPACING_M: f64 = 0.05;

/// A folder for the pairs' files: `keep` when given (created), else a fresh one under the
/// system's temporary folder, removed by [`PairFolder`]'s drop.
pub struct PairFolder {
    pub path: PathBuf,
    remove: bool,
}

impl PairFolder {
    pub fn new(keep: Option<&Path>) -> anyhow::Result<Self> {
        let (path, remove) = match keep {
            Some(path) => (path.to_path_buf(), false),
            None => (
                std::env::temp_dir().join(format!("mac-ego3d-map-pairs-{}", std::process::id())),
                true,
            ),
        };
        std::fs::create_dir_all(&path).with_context(|| format!("creating {}", path.display()))?;
        Ok(Self { path, remove })
    }
}

impl Drop for PairFolder {
    fn drop(&mut self) {
        if self.remove {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}
