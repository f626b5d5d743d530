//! What a bridge carried, per agent: messages and bytes put on the network and taken from it
//! (relayed message bytes: headers and payloads, without zenoh's own framing), written as JSON
//! when the bridge stops. A bridge started again in the same run (same namespace and role: after
//! a crash, by simulated_host.sh or a service manager) adds its counts to the report the earlier
//! one wrote, so the report covers the whole run; a report of another run is replaced.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};

use anyhow::{Context, Result};
use protocol::services::Topic;
use serde::{Deserialize, Serialize};

use crate::budget::BudgetStats;

/// Counters of one agent, seen from one bridge.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct AgentNetworkTraffic {
    pub messages_to_network: u64,
    pub bytes_to_network: u64,
    pub messages_from_network: u64,
    pub bytes_from_network: u64,
}

/// Per agent id.
#[derive(Debug, Clone, Default)]
pub struct NetworkTraffic {
    pub agents: BTreeMap<u32, AgentNetworkTraffic>,
    pub by_topic: BTreeMap<(u32, &'static str), u64>,
    /// The bandwidth budget's work per agent (agent hosts).
    pub budget: BTreeMap<u32, BudgetStats>,
}

impl NetworkTraffic {
    pub fn count_out(&mut self, agent_id: u32, topic: &'static str, bytes: usize) {
        let agent = self.agents.entry(agent_id).or_default();
        agent.messages_to_network += 1;
        agent.bytes_to_network += bytes as u64;
        *self.by_topic.entry((agent_id, topic)).or_default() += bytes as u64;
    }

    pub fn count_in(&mut self, agent_id: u32, topic: &'static str, bytes: usize) {
        let agent = self.agents.entry(agent_id).or_default();
        agent.messages_from_network += 1;
        agent.bytes_from_network += bytes as u64;
        *self.by_topic.entry((agent_id, topic)).or_default() += bytes as u64;
    }
}

impl AgentNetworkTraffic {
    fn add(&mut self, other: &AgentNetworkTraffic) {
        self.messages_to_network += other.messages_to_network;
        self.bytes_to_network += other.bytes_to_network;
        self.messages_from_network += other.messages_from_network;
        self.bytes_from_network += other.bytes_from_network;
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct Report {
    transport: String,
    /// The swarm namespace: one per run.
    #[serde(default)]
    namespace: String,
    role: String,
    /// How many bridge processes of this run and role the counts add up (1 + restarts).
    #[serde(default)]
    incarnations: u32,
    /// Summed over the incarnations.
    elapsed_s: f64,
    /// Agent id (as a string: JSON keys) -> counters.
    agents: BTreeMap<String, AgentNetworkTraffic>,
    /// Agent id -> topic -> bytes, both directions.
    bytes_by_topic: BTreeMap<String, BTreeMap<String, u64>>,
    /// Agent id -> what the bandwidth budget did (agent hosts).
    #[serde(default)]
    budget: BTreeMap<String, BudgetStats>,
}

impl Report {
    fn new(namespace: &str, role: &str, elapsed_s: f64, traffic: &NetworkTraffic) -> Self {
        let mut bytes_by_topic: BTreeMap<String, BTreeMap<String, u64>> = BTreeMap::new();
        for (&(agent_id, topic), &bytes) in &traffic.by_topic {
            bytes_by_topic
                .entry(agent_id.to_string())
                .or_default()
                .insert(topic.to_string(), bytes);
        }
        Self {
            transport: "zenoh".into(),
            namespace: namespace.into(),
            role: role.into(),
            incarnations: 1,
            elapsed_s,
            agents: traffic
                .agents
                .iter()
                .map(|(id, t)| (id.to_string(), *t))
                .collect(),
            bytes_by_topic,
            budget: traffic
                .budget
                .iter()
                .map(|(id, stats)| (id.to_string(), stats.clone()))
                .collect(),
        }
    }

    /// Adds what an earlier incarnation of the same bridge counted.
    fn add_earlier(&mut self, earlier: &Report) {
        self.incarnations += earlier.incarnations.max(1);
        self.elapsed_s += earlier.elapsed_s;
        for (agent, traffic) in &earlier.agents {
            self.agents.entry(agent.clone()).or_default().add(traffic);
        }
        for (agent, stats) in &earlier.budget {
            self.budget.entry(agent.clone()).or_default().add(stats);
        }
        for (agent, topics) in &earlier.bytes_by_topic {
            let mine = self.bytes_by_topic.entry(agent.clone()).or_default();
            for (topic, bytes) in topics {
                *mine.entry(topic.clone()).or_default() += bytes;
            }
        }
    }
}

/// The counters every thread of a bridge adds to and the report writer reads.
#[derive(Debug, Clone, Default)]
pub struct SharedTraffic(Arc<Mutex<NetworkTraffic>>);

impl SharedTraffic {
    fn counters(&self) -> std::sync::MutexGuard<'_, NetworkTraffic> {
        // Counters stay meaningful if a thread panicked while holding them.
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub fn count_out(&self, agent_id: u32, topic: &'static str, bytes: usize) {
        self.counters().count_out(agent_id, topic, bytes);
    }

    pub fn count_in(&self, agent_id: u32, topic: &'static str, bytes: usize) {
        self.counters().count_in(agent_id, topic, bytes);
    }

    /// The budget's statistics as they stand (replacing the previous ones).
    pub fn set_budget(&self, budget: BTreeMap<u32, BudgetStats>) {
        self.counters().budget = budget;
    }

    pub fn snapshot(&self) -> NetworkTraffic {
        self.counters().clone()
    }
}

/// Writes one bridge's report, as often as asked (so that a bridge killed mid-run leaves its
/// counts up to its last write), each time through `PATH.partial` renamed when complete. Created
/// once per bridge process: it takes the report an earlier incarnation of the same run
/// (`namespace`) and role left at the path, and adds it to every report it writes.
#[derive(Clone)]
pub struct ReportWriter {
    path: PathBuf,
    namespace: String,
    role: String,
    earlier: Option<Arc<Report>>,
    /// One write at a time (the periodic writer and the final one).
    writing: Arc<Mutex<()>>,
}

impl ReportWriter {
    pub fn new(path: &Path, namespace: &str, role: &str) -> Self {
        let earlier = std::fs::read_to_string(path)
            .ok()
            .and_then(|text| serde_json::from_str::<Report>(&text).ok())
            .filter(|report| report.namespace == namespace && report.role == role);
        if let Some(earlier) = &earlier {
            tracing::info!(
                report = %path.display(),
                incarnations = earlier.incarnations,
                "this bridge's earlier incarnations in this run left a report: adding to it"
            );
        }
        Self {
            path: path.to_path_buf(),
            namespace: namespace.into(),
            role: role.into(),
            earlier: earlier.map(Arc::new),
            writing: Arc::default(),
        }
    }

    /// Writes what this process counted in `elapsed_s`, plus the earlier incarnations'.
    pub fn write(&self, elapsed_s: f64, traffic: &NetworkTraffic) -> Result<()> {
        let mut report = Report::new(&self.namespace, &self.role, elapsed_s, traffic);
        if let Some(earlier) = &self.earlier {
            report.add_earlier(earlier);
        }
        let text = serde_json::to_string_pretty(&report).context("bridge report")?;
        let _one_at_a_time = self.writing.lock().unwrap_or_else(PoisonError::into_inner);
        let partial = self.path.with_extension("json.partial");
        std::fs::write(&partial, text + "\n")
            .with_context(|| format!("writing {}", partial.display()))?;
        std::fs::rename(&partial, &self.path)
            .with_context(|| format!("writing {}", self.path.display()))
    }
}

/// The name a topic's bytes are counted under.
pub fn topic_label(topic: Topic) -> &'static str {
    topic.name()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn traffic(bytes: usize) -> NetworkTraffic {
        let mut traffic = NetworkTraffic::default();
        traffic.count_out(0, "descriptors", bytes);
        traffic.count_in(1, "corrections", bytes / 2);
        let mut budget = BudgetStats {
            cap_kb_per_s: 50.0,
            raw_bytes: 4 * bytes as u64,
            wire_bytes: bytes as u64,
            deferral_max_s: bytes as f64 / 100.0,
            messages: 1,
            ..BudgetStats::default()
        };
        budget.messages_by_encoding.insert("compact".into(), 1);
        traffic.budget.insert(0, budget);
        traffic
    }

    fn read(path: &Path) -> Report {
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
    }

    #[test]
    fn a_restarted_bridge_adds_to_its_runs_report_and_a_new_run_replaces_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bridge.json");
        // The first incarnation writes twice (periodically, then at the end): no double count.
        let first = ReportWriter::new(&path, "run-a", "agents");
        first.write(1.0, &traffic(60)).unwrap();
        first.write(2.0, &traffic(100)).unwrap();
        assert_eq!(read(&path).agents["0"].bytes_to_network, 100);
        // Killed; started again in the same run.
        let second = ReportWriter::new(&path, "run-a", "agents");
        second.write(3.0, &traffic(40)).unwrap();
        let report = read(&path);
        assert_eq!(report.incarnations, 2);
        assert_eq!(report.elapsed_s, 5.0);
        assert_eq!(report.agents["0"].bytes_to_network, 140);
        assert_eq!(report.agents["0"].messages_to_network, 2);
        assert_eq!(report.agents["1"].bytes_from_network, 70);
        assert_eq!(report.bytes_by_topic["0"]["descriptors"], 140);
        // The budget's work adds up too; the longest deferral is the longest of either.
        let budget = &report.budget["0"];
        assert_eq!((budget.raw_bytes, budget.wire_bytes), (560, 140));
        assert_eq!(budget.messages_by_encoding["compact"], 2);
        assert_eq!(budget.deferral_max_s, 1.0);
        assert!(!path.with_extension("json.partial").exists());

        // Another role or another run starts over.
        ReportWriter::new(&path, "run-a", "consumers")
            .write(1.0, &traffic(10))
            .unwrap();
        assert_eq!(read(&path).incarnations, 1);
        ReportWriter::new(&path, "run-b", "consumers")
            .write(1.0, &traffic(10))
            .unwrap();
        let report = read(&path);
        assert_eq!(report.incarnations, 1);
        assert_eq!(report.agents["0"].bytes_to_network, 10);
    }
}
