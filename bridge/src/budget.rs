//! The per-agent bandwidth budget of an agent host's bridge (`[network]` in the run's config;
//! docs/method.md, Across hosts: bandwidth budget).
//!
//! Each agent has a token bucket of `agent_kb_per_s`, `burst_s` deep. Descriptors (a few
//! hundred bytes, what place recognition needs first) and lifecycle messages other than the
//! goodbye go at once and are charged to the bucket. Every other message waits in the agent's queue, in the order the agent published
//! it, and goes when the bucket is not in debt; a message larger than the bucket puts it in
//! debt, which the following messages wait out, so the rate averaged over a few seconds is the
//! cap. Nothing is dropped: a message waits as long as it must.
//!
//! The encoding of a bulk message (module `encoding`) is chosen when it is its turn to go: the
//! least lossy one under which everything the agent has waiting would go within
//! `target_delay_s`, estimated with each encoding's recent size ratio per topic. A backlog
//! therefore turns the compression up, and as it drains, down again. Without a cap messages go
//! at once and unchanged.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use config::NetworkConfig;
use protocol::messages::{KeyframeImageHeader, Lifecycle, LifecycleKind, PatchHeader};
use protocol::services::Topic;
use protocol::transport::relay::RelayedMessage;
use serde::{Deserialize, Serialize};

use crate::encoding::{Encoded, Encoding, WireMessage, encode};

/// How fast the size ratios follow what the encodings achieve (weight of the newest message).
const RATIO_WEIGHT: f64 = 0.3;

/// What the budget did for one agent (in the bridge's report).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BudgetStats {
    /// The cap, kB/s (0: none).
    pub cap_kb_per_s: f64,
    /// Bytes the agent published (shared-memory layout) and bytes that went on the network.
    pub raw_bytes: u64,
    pub wire_bytes: u64,
    /// Messages per encoding (`raw`, `lossless`, `compact`, `reduced`).
    pub messages_by_encoding: BTreeMap<String, u64>,
    /// Near-transparent Gaussians left out of patches.
    pub gaussians_dropped: u64,
    /// Time messages waited for the budget: the longest and the sum (mean = sum / messages).
    pub deferral_max_s: f64,
    pub deferral_sum_s: f64,
    pub messages: u64,
    /// Re-sends of keyframe parts that were still waiting (not sent twice).
    #[serde(default)]
    pub resends_dropped: u64,
}

impl BudgetStats {
    /// Adds what an earlier incarnation of the bridge counted.
    pub fn add(&mut self, other: &BudgetStats) {
        self.cap_kb_per_s = self.cap_kb_per_s.max(other.cap_kb_per_s);
        self.raw_bytes += other.raw_bytes;
        self.wire_bytes += other.wire_bytes;
        for (encoding, count) in &other.messages_by_encoding {
            *self
                .messages_by_encoding
                .entry(encoding.clone())
                .or_default() += count;
        }
        self.gaussians_dropped += other.gaussians_dropped;
        self.deferral_max_s = self.deferral_max_s.max(other.deferral_max_s);
        self.deferral_sum_s += other.deferral_sum_s;
        self.messages += other.messages;
        self.resends_dropped += other.resends_dropped;
    }
}

struct Waiting {
    message: RelayedMessage,
    since: Instant,
}

/// One agent's bucket, queues and statistics.
struct AgentBudget {
    /// Bytes the agent may send now; negative while a large message is paid off.
    tokens: f64,
    refilled_at: Instant,
    /// Descriptors: they go at once.
    urgent: VecDeque<Waiting>,
    /// Everything else, in publication order.
    ordered: VecDeque<Waiting>,
    waiting_bytes: usize,
    /// Encoded size / raw size per (topic, encoding), recent messages weighted most.
    ratios: BTreeMap<(Topic, Encoding), f64>,
    stats: BudgetStats,
}

/// The budget of every agent of the host.
pub struct Budget {
    /// Bytes per second per agent; `None`: no cap.
    cap: Option<f64>,
    config: NetworkConfig,
    agents: BTreeMap<u32, AgentBudget>,
}

/// Messages that go at once: descriptors (place recognition needs them first) and lifecycle
/// messages other than the goodbye (hello, alive: small, and they tell the consensus the agent
/// is there). A goodbye waits behind the agent's deferred messages, so it never overtakes its
/// final map.
fn is_urgent(message: &RelayedMessage) -> bool {
    match message.topic {
        Topic::Descriptor => true,
        Topic::Lifecycle => message
            .bytes
            .get(..size_of::<Lifecycle>())
            .map(bytemuck::pod_read_unaligned::<Lifecycle>)
            .is_some_and(|l| l.kind() != Ok(LifecycleKind::Goodbye)),
        _ => false,
    }
}

/// The keyframe part a message is (topic, incarnation, keyframe id), for patches and images.
fn keyframe_part(message: &RelayedMessage) -> Option<(Topic, u64, u64)> {
    let keyframe_id = match message.topic {
        Topic::Patch => message
            .bytes
            .get(..size_of::<PatchHeader>())
            .map(|b| bytemuck::pod_read_unaligned::<PatchHeader>(b).keyframe_id),
        Topic::KeyframeImage => message
            .bytes
            .get(..size_of::<KeyframeImageHeader>())
            .map(|b| bytemuck::pod_read_unaligned::<KeyframeImageHeader>(b).keyframe_id),
        _ => None,
    }?;
    Some((message.topic, message.stamp.epoch, keyframe_id))
}

/// A first guess of an encoding's size ratio, until messages have been encoded with it.
fn prior_ratio(topic: Topic, encoding: Encoding) -> f64 {
    match (topic, encoding) {
        (_, Encoding::Raw) => 1.0,
        (Topic::KeyframeImage, Encoding::Lossless) => 0.6,
        (Topic::KeyframeImage, Encoding::Compact) => 0.2,
        (Topic::KeyframeImage, Encoding::Reduced) => 0.06,
        (Topic::Patch, Encoding::Lossless) => 0.8,
        (Topic::Patch, _) => 0.4,
        _ => 1.0,
    }
}

impl AgentBudget {
    fn new(config: &NetworkConfig, cap: Option<f64>, now: Instant) -> Self {
        Self {
            tokens: cap.map_or(0.0, |cap| cap * config.burst_s),
            refilled_at: now,
            urgent: VecDeque::new(),
            ordered: VecDeque::new(),
            waiting_bytes: 0,
            ratios: BTreeMap::new(),
            stats: BudgetStats {
                cap_kb_per_s: config.agent_kb_per_s,
                ..BudgetStats::default()
            },
        }
    }

    fn refill(&mut self, cap: f64, burst_s: f64, now: Instant) {
        let elapsed = now
            .saturating_duration_since(self.refilled_at)
            .as_secs_f64();
        self.tokens = (self.tokens + cap * elapsed).min(cap * burst_s);
        self.refilled_at = now;
    }

    fn ratio(&self, topic: Topic, encoding: Encoding) -> f64 {
        self.ratios
            .get(&(topic, encoding))
            .copied()
            .unwrap_or_else(|| prior_ratio(topic, encoding))
    }

    /// The least lossy encoding under which what waits would go within `target_delay_s`.
    fn choose(&self, cap: f64, target_delay_s: f64) -> Encoding {
        let debt = (-self.tokens).max(0.0);
        for encoding in Encoding::UNDER_A_CAP {
            let waiting: f64 = self
                .ordered
                .iter()
                .map(|w| w.message.bytes.len() as f64 * self.ratio(w.message.topic, encoding))
                .sum();
            if (waiting + debt) / cap <= target_delay_s {
                return encoding;
            }
        }
        Encoding::Reduced
    }
}

impl Budget {
    pub fn new(config: &NetworkConfig) -> Self {
        Self {
            cap: config.agent_bytes_per_s(),
            config: config.clone(),
            agents: BTreeMap::new(),
        }
    }

    /// Takes a message an agent published; it goes when [`Budget::next`] says so. A re-send of
    /// a keyframe part that still waits here (the consensus asked again for a part the budget
    /// deferred) is dropped, and counted: the waiting one carries the same content.
    pub fn admit(&mut self, message: RelayedMessage, now: Instant) {
        let agent = self
            .agents
            .entry(message.agent_id)
            .or_insert_with(|| AgentBudget::new(&self.config, self.cap, now));
        if let Some(part) = keyframe_part(&message)
            && agent
                .ordered
                .iter()
                .any(|w| keyframe_part(&w.message) == Some(part))
        {
            agent.stats.resends_dropped += 1;
            return;
        }
        agent.waiting_bytes += message.bytes.len();
        let urgent = is_urgent(&message);
        let waiting = Waiting {
            message,
            since: now,
        };
        if urgent {
            agent.urgent.push_back(waiting);
        } else {
            agent.ordered.push_back(waiting);
        }
    }

    /// Whether nothing waits.
    pub fn is_empty(&self) -> bool {
        self.agents
            .values()
            .all(|a| a.urgent.is_empty() && a.ordered.is_empty())
    }

    /// Bytes (as published) waiting for the budget, all agents.
    pub fn waiting_bytes(&self) -> usize {
        self.agents.values().map(|a| a.waiting_bytes).sum()
    }

    /// The next message that may go now, encoded; `None` when every agent's queue is empty or
    /// waits for its bucket.
    pub fn next(&mut self, now: Instant) -> Option<WireMessage> {
        let (cap, burst_s, target_delay_s) =
            (self.cap, self.config.burst_s, self.config.target_delay_s);
        for agent in self.agents.values_mut() {
            if let Some(cap) = cap {
                agent.refill(cap, burst_s, now);
            }
            let (waiting, encoding) = if let Some(waiting) = agent.urgent.pop_front() {
                (waiting, Encoding::Raw)
            } else if agent.ordered.is_empty() || (cap.is_some() && agent.tokens <= 0.0) {
                continue;
            } else {
                let encoding = cap.map_or(Encoding::Raw, |cap| agent.choose(cap, target_delay_s));
                (
                    agent.ordered.pop_front().expect("checked non-empty"),
                    encoding,
                )
            };
            let message = waiting.message;
            agent.waiting_bytes -= message.bytes.len();
            // A message that cannot be encoded (malformed) goes as it is: the consumer host
            // refuses it with the reason, as it would without a budget.
            let encoded = encode(message.topic, &message.bytes, encoding, self.config.jpeg_quality)
                .unwrap_or_else(|error| {
                    tracing::warn!(agent_id = message.agent_id, topic = %message.topic,
                        error = %format!("{error:#}"), "could not encode a message: it goes unchanged");
                    Encoded { encoding: Encoding::Raw, bytes: message.bytes.clone(), gaussians_dropped: 0 }
                });
            if encoded.encoding != Encoding::Raw {
                let ratio = encoded.bytes.len() as f64 / message.bytes.len().max(1) as f64;
                let previous = agent.ratio(message.topic, encoded.encoding);
                agent.ratios.insert(
                    (message.topic, encoded.encoding),
                    (1.0 - RATIO_WEIGHT) * previous + RATIO_WEIGHT * ratio,
                );
            }
            if cap.is_some() {
                agent.tokens -= encoded.bytes.len() as f64;
            }
            let stats = &mut agent.stats;
            let deferral = now.saturating_duration_since(waiting.since).as_secs_f64();
            stats.raw_bytes += message.bytes.len() as u64;
            stats.wire_bytes += encoded.bytes.len() as u64;
            *stats
                .messages_by_encoding
                .entry(encoded.encoding.name().to_string())
                .or_default() += 1;
            stats.gaussians_dropped += encoded.gaussians_dropped;
            stats.deferral_max_s = stats.deferral_max_s.max(deferral);
            stats.deferral_sum_s += deferral;
            stats.messages += 1;
            return Some(WireMessage {
                agent_id: message.agent_id,
                topic: message.topic,
                stamp: message.stamp,
                encoding: encoded.encoding,
                bytes: encoded.bytes,
            });
        }
        None
    }

    /// How long until an agent's bucket lets its next message go (zero when one may go now),
    /// `None` when nothing waits.
    pub fn next_due_in(&self, now: Instant) -> Option<Duration> {
        let cap = self.cap;
        self.agents
            .values()
            .filter_map(|agent| {
                if !agent.urgent.is_empty() {
                    return Some(Duration::ZERO);
                }
                agent.ordered.front()?;
                let Some(cap) = cap else {
                    return Some(Duration::ZERO);
                };
                let elapsed = now
                    .saturating_duration_since(agent.refilled_at)
                    .as_secs_f64();
                let tokens = agent.tokens + cap * elapsed;
                // The bucket must be strictly positive; a microsecond past the break-even.
                Some(Duration::from_secs_f64(((-tokens).max(0.0) / cap) + 1e-6))
            })
            .min()
    }

    /// Per agent.
    pub fn stats(&self) -> BTreeMap<u32, BudgetStats> {
        self.agents
            .iter()
            .map(|(&id, agent)| (id, agent.stats.clone()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::messages::Stamp;

    fn message(agent_id: u32, topic: Topic, sequence: u64, bytes: usize) -> RelayedMessage {
        let stamp = Stamp {
            agent_id,
            sequence,
            ..Stamp::default()
        };
        // Lifecycle stand-ins for bulk messages without encodings are goodbyes (they wait in
        // order); other topics carry their stamp and zeros.
        let mut payload = if topic == Topic::Lifecycle {
            let goodbye = Lifecycle {
                stamp,
                kind: LifecycleKind::Goodbye as u32,
                ..bytemuck::Zeroable::zeroed()
            };
            bytemuck::bytes_of(&goodbye).to_vec()
        } else {
            bytemuck::bytes_of(&stamp).to_vec()
        };
        payload.resize(bytes.max(payload.len()), 0);
        RelayedMessage {
            agent_id,
            topic,
            stamp,
            bytes: payload,
        }
    }

    fn capped(kb_per_s: f64) -> NetworkConfig {
        NetworkConfig {
            agent_kb_per_s: kb_per_s,
            ..NetworkConfig::default()
        }
    }

    #[test]
    fn without_a_cap_messages_go_at_once_and_unchanged() {
        let mut budget = Budget::new(&NetworkConfig::default());
        let now = Instant::now();
        let raw = message(0, Topic::Lifecycle, 0, 5000);
        budget.admit(raw.clone(), now);
        assert_eq!(budget.next_due_in(now), Some(Duration::ZERO));
        let wire = budget.next(now).unwrap();
        assert_eq!((wire.encoding, &wire.bytes), (Encoding::Raw, &raw.bytes));
        assert_eq!(budget.next(now), None);
        assert_eq!(budget.next_due_in(now), None);
    }

    /// Sends `messages` through a budget of `kb_per_s`, stepping a simulated clock to each
    /// moment the budget names; returns (sequence, departure s, wire bytes) in order.
    fn drain(budget: &mut Budget, start: Instant) -> Vec<(u64, f64, usize)> {
        let mut now = start;
        let mut sent = Vec::new();
        while let Some(due) = budget.next_due_in(now) {
            now += due;
            while let Some(wire) = budget.next(now) {
                sent.push((
                    wire.stamp.sequence,
                    (now - start).as_secs_f64(),
                    wire.bytes.len(),
                ));
            }
        }
        sent
    }

    #[test]
    fn a_capped_agent_keeps_to_its_rate_in_order_and_loses_nothing() {
        // 10 kB/s, 1 s burst; forty 5 kB lifecycle-sized messages (no encoding applies).
        let mut budget = Budget::new(&capped(10.0));
        let start = Instant::now();
        for sequence in 0..40 {
            budget.admit(message(0, Topic::Lifecycle, sequence, 5000), start);
        }
        let sent = drain(&mut budget, start);
        assert_eq!(
            sent.iter().map(|s| s.0).collect::<Vec<_>>(),
            (0..40).collect::<Vec<_>>()
        );
        // 200 kB at 10 kB/s with 10 kB up front: the last one goes after about 19 s.
        let last = sent.last().unwrap().1;
        assert!((18.5..19.6).contains(&last), "{last}");
        // Over any window of 5 s, no more than the cap plus the burst.
        for &(_, t0, _) in &sent {
            let window: usize = sent
                .iter()
                .filter(|s| s.1 >= t0 && s.1 < t0 + 5.0)
                .map(|s| s.2)
                .sum();
            assert!(window <= 60_000, "{window} bytes in 5 s from {t0}");
        }
        let stats = &budget.stats()[&0];
        assert_eq!((stats.messages, stats.raw_bytes), (40, 200_000));
        assert!(stats.deferral_max_s > 18.0);
    }

    #[test]
    fn descriptors_overtake_waiting_bulk_messages_and_agents_do_not_wait_for_each_other() {
        let mut budget = Budget::new(&capped(1.0));
        let start = Instant::now();
        for sequence in 0..3 {
            budget.admit(message(0, Topic::Lifecycle, sequence, 4000), start);
        }
        budget.admit(message(0, Topic::Descriptor, 0, 300), start);
        budget.admit(message(1, Topic::Lifecycle, 0, 500), start);
        let mut order = Vec::new();
        while let Some(wire) = budget.next(start) {
            order.push((wire.agent_id, wire.topic, wire.stamp.sequence));
        }
        // Agent 0's descriptor first, then one lifecycle message of each agent puts both
        // buckets in debt; agent 0's other two wait.
        assert_eq!(
            order,
            [
                (0, Topic::Descriptor, 0),
                (0, Topic::Lifecycle, 0),
                (1, Topic::Lifecycle, 0)
            ]
        );
        assert!(budget.next_due_in(start).unwrap() > Duration::from_secs(3));
    }

    #[test]
    fn a_backlog_turns_the_compression_up_and_its_end_turns_it_down() {
        let config = capped(100.0);
        let mut budget = Budget::new(&config);
        let now = Instant::now();
        let agent = |budget: &Budget| -> Encoding {
            budget.agents[&0].choose(budget.cap.unwrap(), config.target_delay_s)
        };
        // One 100 kB patch-sized message: lossless goes within the 3 s target.
        budget.admit(message(0, Topic::Patch, 0, 100_000), now);
        assert_eq!(agent(&budget), Encoding::Lossless);
        // Ten 1.8 MB images waiting: only the reduced encoding drains them in time.
        for sequence in 0..10 {
            budget.admit(message(0, Topic::KeyframeImage, sequence, 1_800_000), now);
        }
        assert_eq!(agent(&budget), Encoding::Reduced);
        budget.agents.get_mut(&0).unwrap().ordered.truncate(1);
        assert_eq!(agent(&budget), Encoding::Lossless);
    }

    #[test]
    fn a_resent_keyframe_part_that_still_waits_is_not_queued_twice() {
        let mut budget = Budget::new(&capped(1.0));
        let now = Instant::now();
        let patch = |sequence: u64, keyframe_id: u64| {
            let header = PatchHeader {
                stamp: Stamp {
                    agent_id: 0,
                    sequence,
                    ..Stamp::default()
                },
                keyframe_id,
                ..PatchHeader::default()
            };
            RelayedMessage::from_network(0, Topic::Patch, bytemuck::bytes_of(&header).to_vec())
                .unwrap()
        };
        budget.admit(message(0, Topic::Lifecycle, 0, 5000), now);
        budget.admit(patch(0, 7), now);
        budget.admit(patch(1, 8), now);
        budget.admit(patch(2, 7), now);
        assert_eq!(budget.agents[&0].ordered.len(), 3);
        assert_eq!(budget.agents[&0].stats.resends_dropped, 1);
    }
}
