//! DIR/launch.json: how `mac-ego3d swarm` ran the swarm (transport, agents, the run's identity,
//! consensus restarts, how each process ended), written before the run's figures; and the
//! network figures `eval swarm` adds to metrics.json from it and the bridges' reports.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::supervisor::Exit;

pub const LAUNCH_FILE_NAME: &str = "launch.json";

/// What carried the swarm's messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Transport {
    /// This host's shared memory (every process on one host).
    Iceoryx2,
    /// Each process on a simulated host of its own, joined by zenoh (needs root).
    Zenoh,
}

impl std::fmt::Display for Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Transport::Iceoryx2 => "iceoryx2",
            Transport::Zenoh => "zenoh",
        })
    }
}

/// DIR/launch.json.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LaunchRecord {
    pub transport: Transport,
    pub run_id: String,
    pub namespace: String,
    /// Agent K's dataset spec is the K-th.
    pub datasets: Vec<String>,
    /// Tracking threads per agent.
    pub agent_threads: Option<usize>,
    /// Times the consensus was started again on its store after dying.
    pub consensus_restarts: usize,
    /// Whether the run was stopped by Ctrl-C / SIGTERM.
    pub interrupted: bool,
    /// How each process ended last (`consensus`, `agent_0`, ...).
    pub exits: BTreeMap<String, Exit>,
}

impl LaunchRecord {
    pub fn write(&self, dir: &Path) -> anyhow::Result<()> {
        let path = dir.join(LAUNCH_FILE_NAME);
        std::fs::write(&path, serde_json::to_string_pretty(self)?)
            .with_context(|| format!("writing {}", path.display()))
    }

    /// The record in `dir`; `None` for a run `mac-ego3d swarm` did not launch.
    pub fn read(dir: &Path) -> anyhow::Result<Option<Self>> {
        let path = dir.join(LAUNCH_FILE_NAME);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        serde_json::from_str(&text)
            .map(Some)
            .with_context(|| format!("parsing {}", path.display()))
    }
}

/// One agent's traffic on the network as its host's bridge counted it (relayed bytes, both
/// directions, and the mean rate), and what the bandwidth budget did.
#[derive(Debug, Clone, Serialize)]
pub struct AgentNetwork {
    pub bytes_to_network: u64,
    pub bytes_from_network: u64,
    pub elapsed_s: f64,
    pub kb_per_s_to_network: Option<f64>,
    /// Bytes as published and as sent, messages per encoding, Gaussians left out, deferral
    /// (the bridge's report, as it wrote it).
    pub budget: Option<serde_json::Value>,
}

/// The part of a bridge's report (bridge/src/report.rs) read here.
#[derive(Debug, Deserialize)]
struct BridgeReport {
    agents: BTreeMap<String, BridgeTraffic>,
    elapsed_s: f64,
    #[serde(default)]
    budget: BTreeMap<String, serde_json::Value>,
}

#[derive(Debug, Default, Clone, Copy, Deserialize)]
struct BridgeTraffic {
    #[serde(default)]
    bytes_to_network: u64,
    #[serde(default)]
    bytes_from_network: u64,
}

/// Per agent (`"0"`, `"1"`, ...): its traffic from `dir/bridge_agent_K.json`; `None` when that
/// report is missing.
pub fn network_per_agent(
    dir: &Path,
    agents: usize,
) -> anyhow::Result<BTreeMap<String, Option<AgentNetwork>>> {
    let mut network = BTreeMap::new();
    for k in 0..agents {
        let path = dir.join(format!("bridge_agent_{k}.json"));
        let figures = if path.exists() {
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("reading {}", path.display()))?;
            let report: BridgeReport = serde_json::from_str(&text)
                .with_context(|| format!("parsing {}", path.display()))?;
            let traffic = report
                .agents
                .get(&k.to_string())
                .copied()
                .unwrap_or_default();
            Some(AgentNetwork {
                bytes_to_network: traffic.bytes_to_network,
                bytes_from_network: traffic.bytes_from_network,
                elapsed_s: report.elapsed_s,
                kb_per_s_to_network: (report.elapsed_s > 0.0)
                    .then(|| traffic.bytes_to_network as f64 / 1000.0 / report.elapsed_s),
                budget: report.budget.get(&k.to_string()).cloned(),
            })
        } else {
            None
        };
        network.insert(k.to_string(), figures);
    }
    Ok(network)
}
