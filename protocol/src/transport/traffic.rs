//! Bandwidth accounting: messages and bytes per (agent, topic, direction), with the receive
//! side's gap and drop counters, reported as a [`BandwidthReport`].

use std::collections::BTreeMap;
use std::time::Instant;

use serde::Serialize;

use super::TransportError;
use super::outbox::{SendReport, Sent};
use crate::services::Topic;

/// Direction of counted traffic, seen from the reporting process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// Sent by the reporting process.
    Sent,
    /// Received by the reporting process.
    Received,
}

/// Counters of one (agent, topic, direction).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct TopicTraffic {
    /// Messages sent, or received and delivered (stale and repeated ones not counted).
    pub messages: u64,
    /// Payload plus user-header bytes.
    pub bytes: u64,
    /// Sent only: payload bytes the transport copied from caller memory into shared memory
    /// (headers, which the transport builds, are not counted). Zero for in-place builds
    /// ([`super::AgentLink::send_patch_with`]); receivers never copy.
    pub bytes_copied: u64,
    /// Sent only: messages that failed with [`TransportError::QueueFull`] (not in `messages`).
    pub full_queue_failures: u64,
    /// Received only: number of jumps in the sequence, and messages lost in them.
    pub gaps: u64,
    /// Received only: messages lost in those gaps.
    pub missed: u64,
    /// Received only: incarnations (epochs) seen, 1 + restarts.
    pub incarnations: u64,
    /// Received only: messages dropped for belonging to an older epoch.
    pub stale_dropped: u64,
    /// Received only: repeated messages (a re-send after a full queue) dropped.
    pub duplicates_dropped: u64,
}

/// One row of a [`BandwidthReport`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrafficEntry {
    /// The agent the messages came from or went to (an agent's link: its own id).
    pub agent_id: u32,
    /// The topic counted.
    pub topic: Topic,
    /// Whether this process sent or received them.
    pub direction: Direction,
    /// The counters.
    #[serde(flatten)]
    pub traffic: TopicTraffic,
}

/// Bandwidth per agent and topic, for the swarm report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BandwidthReport {
    /// Seconds since the link was opened.
    pub elapsed_s: f64,
    /// One row per (agent, topic, direction) with traffic, in that order.
    pub entries: Vec<TrafficEntry>,
}

impl BandwidthReport {
    /// The counters of one (agent, topic, direction); `None` when it had no traffic.
    pub fn get(&self, agent_id: u32, topic: Topic, direction: Direction) -> Option<&TopicTraffic> {
        self.entries
            .iter()
            .find(|e| e.agent_id == agent_id && e.topic == topic && e.direction == direction)
            .map(|e| &e.traffic)
    }

    /// Bytes per second of one agent over all topics in one direction.
    pub fn bytes_per_second(&self, agent_id: u32, direction: Direction) -> f64 {
        let bytes: u64 = self
            .entries
            .iter()
            .filter(|e| e.agent_id == agent_id && e.direction == direction)
            .map(|e| e.traffic.bytes)
            .sum();
        if self.elapsed_s > 0.0 {
            bytes as f64 / self.elapsed_s
        } else {
            0.0
        }
    }
}

#[derive(Debug)]
pub(super) struct TrafficTable {
    opened: Instant,
    rows: BTreeMap<(u32, Topic, Direction), TopicTraffic>,
}

impl TrafficTable {
    pub(super) fn new() -> Self {
        Self {
            opened: Instant::now(),
            rows: BTreeMap::new(),
        }
    }

    pub(super) fn row(
        &mut self,
        agent_id: u32,
        topic: Topic,
        direction: Direction,
    ) -> &mut TopicTraffic {
        self.rows.entry((agent_id, topic, direction)).or_default()
    }

    pub(super) fn report(&self) -> BandwidthReport {
        BandwidthReport {
            elapsed_s: self.opened.elapsed().as_secs_f64(),
            entries: self
                .rows
                .iter()
                .map(|(&(agent_id, topic, direction), &traffic)| TrafficEntry {
                    agent_id,
                    topic,
                    direction,
                    traffic,
                })
                .collect(),
        }
    }

    /// Counts the outcome of a send under `agent_id`: a message sent, or a failure with a
    /// full queue ([`TopicTraffic::full_queue_failures`]).
    pub(super) fn count_send(
        &mut self,
        agent_id: u32,
        topic: Topic,
        outcome: Result<Sent, TransportError>,
    ) -> Result<SendReport, TransportError> {
        match outcome {
            Ok(Sent { report, copied }) => {
                let row = self.row(agent_id, topic, Direction::Sent);
                row.messages += 1;
                row.bytes += report.bytes as u64;
                row.bytes_copied += copied as u64;
                Ok(report)
            }
            Err(error) => {
                if matches!(error, TransportError::QueueFull { .. }) {
                    self.row(agent_id, topic, Direction::Sent)
                        .full_queue_failures += 1;
                }
                Err(error)
            }
        }
    }
}
