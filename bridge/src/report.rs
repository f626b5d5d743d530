//! What a bridge carried, per agent: messages and bytes put on the network and taken from it
//! (relayed message bytes: headers and payloads, without zenoh's own framing), written as JSON
//! when the bridge stops.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use protocol::services::Topic;
use serde::Serialize;

/// Counters of one agent, seen from one bridge.
#[derive(Debug, Clone, Copy, Default, Serialize)]
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

    pub fn merge(&mut self, other: NetworkTraffic) {
        for (agent_id, traffic) in other.agents {
            let agent = self.agents.entry(agent_id).or_default();
            agent.messages_to_network += traffic.messages_to_network;
            agent.bytes_to_network += traffic.bytes_to_network;
            agent.messages_from_network += traffic.messages_from_network;
            agent.bytes_from_network += traffic.bytes_from_network;
        }
        for (key, bytes) in other.by_topic {
            *self.by_topic.entry(key).or_default() += bytes;
        }
    }
}

#[derive(Serialize)]
struct Report<'a> {
    transport: &'static str,
    role: &'a str,
    elapsed_s: f64,
    /// Agent id (as a string: JSON keys) -> counters.
    agents: BTreeMap<String, AgentNetworkTraffic>,
    /// Agent id -> topic -> bytes, both directions.
    bytes_by_topic: BTreeMap<String, BTreeMap<&'static str, u64>>,
}

pub fn write(path: &Path, role: &str, elapsed_s: f64, traffic: &NetworkTraffic) -> Result<()> {
    let mut bytes_by_topic: BTreeMap<String, BTreeMap<&'static str, u64>> = BTreeMap::new();
    for (&(agent_id, topic), &bytes) in &traffic.by_topic {
        bytes_by_topic
            .entry(agent_id.to_string())
            .or_default()
            .insert(topic, bytes);
    }
    let report = Report {
        transport: "zenoh",
        role,
        elapsed_s,
        agents: traffic
            .agents
            .iter()
            .map(|(id, t)| (id.to_string(), *t))
            .collect(),
        bytes_by_topic,
    };
    let text = serde_json::to_string_pretty(&report).context("bridge report")?;
    std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))
}

/// The name a topic's bytes are counted under.
pub fn topic_label(topic: Topic) -> &'static str {
    topic.name()
}
