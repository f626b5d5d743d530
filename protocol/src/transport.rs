//! Typed transport over iceoryx2 0.10 (`ipc::Service`) between agents and consumers.
//!
//! Two endpoints: [`AgentLink`] (one per agent process: publishes descriptors, patches, keyframe
//! RGB-D images and lifecycle messages, receives corrections and control messages) and
//! [`ConsumerLink`] (the consensus or an observer: receives from every agent id
//! `0..max_agents`, publishes corrections and control messages).
//!
//! Control messages ([`ControlMessage`], heap data) travel consumer -> agent on the `control`
//! topic as one [`crate::codec`] frame in a byte slice behind a [`ControlHeader`], with the same
//! stamps, gap detection and accounting as every topic; a frame of another format version is
//! refused on receive ([`TransportError::ControlFrame`]). The agent -> consensus direction has
//! no control topic: everything an agent says fits the typed topics.
//!
//! Design choices, and why:
//! - **Service limits from the config.** iceoryx2's defaults (2 publishers, 20 nodes per service)
//!   break a swarm; every service is opened with limits derived from [`TransportConfig`], so all
//!   processes of a swarm must use the same queue depths and consumer count (a mismatch is a
//!   clear `Service` error).
//! - **Agent count.** The agent-id range `0..max_agents` may differ between processes: the
//!   services shared by all agents (lifecycle, consumers' wake-up) are opened as their creator
//!   sized them and carry its range as a service attribute, so the consensus can size the swarm
//!   (`mac-consensus --agents N`) while agents keep the default, and an agent whose id is outside
//!   the swarm's range is refused by name ([`TransportError::AgentIdOutsideSwarm`]).
//! - **Duplicate agent ids.** Each agent-owned topic admits exactly one publisher, so a second
//!   live process with the same id cannot create its publisher: [`TransportError::DuplicateAgent`].
//! - **Delivery handshake.** iceoryx2 silently drops a sample sent before a subscriber is
//!   connected. History buffers were rejected (they pin large patches in shared memory and only
//!   replay the last few). Instead a publisher waits, before each send, until the service counts
//!   at least `required_consumers` subscribers. The wait is event-driven: a consumer notifies
//!   the agent's wake service right after its subscribers exist, so a waiting agent wakes at
//!   once; the wait is sliced by `wait_slice` to notice shutdown, and bounded by
//!   `delivery_timeout` ([`TransportError::NoConsumer`]). After `send()` the recipient count is
//!   checked ([`TransportError::Undelivered`]).
//! - **Sequence numbers and restarts.** Every message carries a [`Stamp`]: an incarnation epoch
//!   (start time in ns) and a per-topic sequence from 0. Receivers report gaps and accept a
//!   larger epoch as a restart (sequence from 0 again); messages of an older epoch are dropped.
//!   A consumer takes lifecycle messages before data, so a (re)started agent's hello, with its
//!   run anchor, is handled before the keyframes it sent after it.
//! - **Crash safety.** Each link creates its own node with dead-node clean-up on creation and
//!   also calls `try_cleanup_dead_nodes()` explicitly (and on every heartbeat), so shared memory
//!   left by a SIGKILLed process (/dev/shm/iox2_*, /tmp/iceoryx2) is reclaimed by the next start.
//! - **Large patches and images.** Patch, keyframe-image and correction publishers use dynamic
//!   data segments with power-of-two growth from `initial_patch_records`,
//!   `initial_keyframe_image_pixels` and `initial_correction_poses`, so any size that fits in
//!   memory can be sent (tested with 1,000,000 records and 640x480 images). Note that iceoryx2
//!   zeroes a new segment, and a segment holds `max_consumers * (queue depth + held samples) + 1`
//!   samples of the largest slice.
//! - **No busy waiting, but a short poll before sleeping.** Receivers block on an iceoryx2 event
//!   listener (`timed_wait`), woken by the sender's notification after each send; every wait is
//!   bounded by `wait_slice` so the shutdown flag is seen promptly. A sleeping process is slow to
//!   wake, though: on the 2-core development VM the wake-up added 50-150 us at the median to
//!   a message's one-way latency (`mac-ego3d bench ipc`, figures in protocol/README.md).
//!   So for `poll_before_wait` after its last message (sent or received) a link's receive
//!   polls its queues (yielding the core between polls), which catches the next message of a
//!   burst or stream, or the answer to a message just sent, without sleeping. A receiver idle
//!   for longer blocks at once, so the poll costs at most `poll_before_wait` of CPU per
//!   message and nothing while idle.
//! - **Early notice for large messages.** Before it builds a patch or a keyframe image in shared
//!   memory, an agent already notifies the consumers ([`Topic::is_bulk`]); a wake-up counts as
//!   activity, so a consumer that was asleep polls until the message is sent. Its wake-up
//!   overlaps the copy instead of following it: a lone 10k patch arrives in about half the
//!   time. Before blocking, a receiver discards the notifications of messages it already took
//!   while polling, so that a stale notification does not wake it for nothing.
//! - **Full queues: a policy per topic** ([`FullQueuePolicy`], [`TransportConfig::full_queue`]).
//!   `Block` (descriptors, keyframe images, patches; lifecycle always): the queue never
//!   overwrites, so nothing is lost silently. A sample that finds a consumer's queue full is not
//!   delivered there (`DiscardData`), `send()` reports fewer recipients, and the sender re-sends
//!   the same message (same sequence number; receivers drop duplicates) in 1 ms sleeps until
//!   `required_consumers` have it, or fails after `full_queue_timeout` with
//!   [`TransportError::QueueFull`] (counted in [`TopicTraffic::full_queue_failures`]); a
//!   shutdown request ends the wait. iceoryx2's own `RetryUntilDelivered` was not used: it has no
//!   time bound. `NewestWins` (corrections): iceoryx2's safe overflow, the newest sample
//!   replaces the oldest queued one, the send never waits and the receiver sees the replaced
//!   messages as a gap. Right for corrections, each of which carries the whole current solution.
//!   The policy is a property of the service, so all processes of a swarm must agree on it (a
//!   mismatch is a clear `Service` error).
//! - **Orderly goodbye.** iceoryx2 loses samples of a publisher that is gone before the
//!   subscriber mapped its memory. So [`AgentLink::close`] sends `Goodbye` and waits until every
//!   consumer that got it acknowledges, and a consumer holds back an agent's `Goodbye` until it
//!   has drained that agent's data topics: once acknowledged, nothing sent before is lost.

use std::collections::BTreeMap;
use std::fmt::Debug;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use iceoryx2::config::Config;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::{Publisher, PublisherCreateError};
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{
    AllocationStrategy, AttributeVerifier, BackpressureStrategy, EventId, IceoryxSend, Node,
    NodeBuilder, NodeName, ServiceName, SignalHandlingMode, ZeroCopySend, ipc,
};
use iceoryx2::sample::Sample;
use iceoryx2::service::attribute::{AttributeKey, AttributeValue};
use iceoryx2::service::builder::event::{EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{
    Builder as PubSubBuilder, PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::port_factory::PortFactory as _;
use iceoryx2::service::port_factory::event::PortFactory as EventService;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubService;
use serde::{Deserialize, Serialize};

use crate::codec::{self, CodecError};
use crate::messages::{
    CONSUMER_AGENT_ID, ControlHeader, ControlMessage, CoordinateFrame, CorrectionHeader,
    DESCRIPTOR_NORM_TOLERANCE, GaussianRecord, Intrinsics, KeyframeDescriptor, KeyframeImageHeader,
    KeyframePose, Lifecycle, LifecycleKind, PatchHeader, Pose, RgbdPixel, Stamp,
};
use crate::services::{ServiceNames, Topic};

type Ipc = ipc::Service;

/// Nodes of crashed processes may hold a service slot until they are cleaned up; this many
/// extra slots let a restarted process in even before the clean-up ran.
const NODE_SLACK: usize = 2;

/// Samples a publisher loans at once: every send path here loans, fills and sends one sample.
const PUBLISHER_MAX_LOANS: usize = 1;

/// Quaternion norm tolerance for poses accepted on send.
const POSE_NORM_TOLERANCE: f64 = 1e-6;

/// Event ids on an agent's wake service.
const WAKE_CORRECTION: usize = 0;
const WAKE_CONSUMER_ATTACHED: usize = 1;
const WAKE_GOODBYE_SEEN: usize = 2;
const WAKE_CONTROL: usize = 3;
const AGENT_WAKE_EVENT_IDS: usize = 4;

/// Re-send interval while a consumer's queue is full. Consumers do not signal freed space (that
/// would cost a syscall per received message), so an overloaded sender polls at this rate; it is
/// a sleep, not a spin.
const FULL_QUEUE_RETRY: Duration = Duration::from_millis(1);

/// Agent-id range of a swarm whose size is not known (a consensus started without `--agents`,
/// tests): ids `0..DEFAULT_MAX_AGENTS`.
pub const DEFAULT_MAX_AGENTS: u32 = 8;

/// Service attribute on the shared lifecycle service that records the agent-id range the swarm
/// was set up for (by whichever process created the service first), so that a process with
/// another range joins without a service-limit mismatch and an agent outside the range is
/// refused by name.
const SWARM_MAX_AGENTS_ATTRIBUTE: &str = "mac.swarm.max_agents";

/// Opening a shared service races with other processes creating or removing it; this many
/// rounds of "open as it is, else open-or-create with our limits" settle any such race.
const SHARED_SERVICE_OPEN_ATTEMPTS: usize = 4;

/// The consumer -> agent topics (correction, control) have exactly one subscriber: the agent.
const AGENT_RECIPIENTS: usize = 1;

/// Number of topics, for dense per-agent event ids on the consumers' wake service.
const TOPIC_COUNT: usize = Topic::ALL.len();

/// Topics a consumer receives per agent (descriptor, keyframe image, patch), scanned round-robin.
const AGENT_SOURCES: usize = 3;

/// Settings shared by every process of one swarm (they size the shared services).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TransportConfig {
    /// Service-name prefix; `mac` in production, unique per test run.
    pub namespace: String,
    /// Agent ids are `0..max_agents`. A consumer listens to exactly these ids. The shared
    /// services (lifecycle, consumers' wake-up) are sized for it by the process that creates
    /// them first, and remember it: a process configured otherwise still joins, and an agent
    /// whose id is outside the range the swarm was set up for is refused
    /// ([`TransportError::AgentIdOutsideSwarm`]). Size it from the swarm's agent count where
    /// it is known ([`TransportConfig::for_swarm`]); [`DEFAULT_MAX_AGENTS`] otherwise.
    pub max_agents: u32,
    /// Consumer processes (consensus + observers) that may attach to each topic.
    pub max_consumers: usize,
    /// Subscribers a publisher waits for before sending, and that `send()` must reach.
    /// 0 makes sends fire-and-forget (an agent running without consensus).
    pub required_consumers: usize,
    /// Longest wait for `required_consumers` to attach before a send fails.
    pub delivery_timeout: Duration,
    /// Longest single blocking wait, so a shutdown request is noticed within this time.
    pub wait_slice: Duration,
    /// For how long after the link's last message (sent or received) a receive polls its
    /// queues, yielding the core between polls, before it blocks on the wake-up event. Waking
    /// a blocked process costs tens of microseconds on a loaded or virtualised machine, as much
    /// as copying a 10k-Gaussian patch; the poll avoids it for messages that follow others
    /// closely (a keyframe's descriptor, image and patch; a stream of patches; the answer to a
    /// message just sent), while a receiver that has been idle for longer blocks at once and
    /// burns nothing. Zero always blocks.
    pub poll_before_wait: Duration,
    /// What a send does when a consumer's queue of a topic is full (see [`FullQueuePolicy`]).
    pub full_queue: FullQueuePolicies,
    /// Longest wait of a [`FullQueuePolicy::Block`] send for room in a full queue before
    /// [`TransportError::QueueFull`]: long enough to ride out a consumer stalled by a loaded
    /// machine, short enough that one that stopped reading surfaces as an error.
    pub full_queue_timeout: Duration,
    /// Per-consumer queue length of each topic (what happens when it is full: `full_queue`).
    pub descriptor_queue_depth: usize,
    pub patch_queue_depth: usize,
    /// Keyframe images are large (1.8 MB at 640x480) and sent once per keyframe, so a short
    /// queue suffices; each queued image also occupies a slot of the publisher's data segment.
    pub keyframe_image_queue_depth: usize,
    pub correction_queue_depth: usize,
    /// Control messages are rare (a shutdown, a re-send request), so a short queue suffices.
    pub control_queue_depth: usize,
    pub lifecycle_queue_depth: usize,
    /// Samples a receiver may hold (borrow) at once per topic.
    pub max_held_samples: usize,
    /// First data-segment sizing of the patch publisher, in records (grows by powers of two).
    pub initial_patch_records: usize,
    /// First data-segment sizing of the keyframe-image publisher, in pixels (grows by powers of
    /// two, so larger images are accepted at the cost of one segment re-allocation).
    pub initial_keyframe_image_pixels: usize,
    /// First data-segment sizing of the correction publisher, in keyframe poses.
    pub initial_correction_poses: usize,
    /// First data-segment sizing of the control publisher, in bytes of a codec frame (grows by
    /// powers of two up to the codec's limit).
    pub initial_control_bytes: usize,
}

impl Default for TransportConfig {
    fn default() -> Self {
        Self {
            namespace: crate::services::DEFAULT_NAMESPACE.to_string(),
            max_agents: DEFAULT_MAX_AGENTS,
            max_consumers: 2,
            required_consumers: 1,
            delivery_timeout: Duration::from_secs(10),
            wait_slice: Duration::from_millis(50),
            poll_before_wait: Duration::from_millis(1),
            full_queue: FullQueuePolicies::default(),
            full_queue_timeout: Duration::from_secs(10),
            descriptor_queue_depth: 64,
            patch_queue_depth: 2,
            keyframe_image_queue_depth: 4,
            correction_queue_depth: 4,
            control_queue_depth: 8,
            lifecycle_queue_depth: 64,
            max_held_samples: 2,
            initial_patch_records: 16 * 1024,
            // A QVGA image, the usual downscaled size for feature matching.
            initial_keyframe_image_pixels: 320 * 240,
            initial_correction_poses: 1024,
            // Room for a config text or a reason string without re-allocation.
            initial_control_bytes: 4096,
        }
    }
}

impl TransportConfig {
    /// A config for a private namespace (tests, benchmarks).
    pub fn with_namespace(namespace: impl Into<String>) -> Self {
        Self {
            namespace: namespace.into(),
            ..Self::default()
        }
    }

    /// A config for a swarm of `agents` agents (ids `0..agents`) when the count is known, e.g.
    /// `mac-consensus --agents N`; `None` keeps [`DEFAULT_MAX_AGENTS`].
    pub fn for_swarm(namespace: impl Into<String>, agents: Option<u32>) -> Self {
        Self {
            max_agents: agents.unwrap_or(DEFAULT_MAX_AGENTS),
            ..Self::with_namespace(namespace)
        }
    }

    fn validate(&self) -> Result<(), TransportError> {
        let fail = |reason: &str| {
            Err(TransportError::InvalidConfig {
                reason: reason.to_string(),
            })
        };
        if self.max_agents == 0 {
            return fail("max_agents must be at least 1");
        }
        if self.max_consumers == 0 {
            return fail("max_consumers must be at least 1");
        }
        if self.required_consumers > self.max_consumers {
            return fail("required_consumers exceeds max_consumers");
        }
        if self.wait_slice.is_zero() {
            return fail("wait_slice must be positive");
        }
        if self.poll_before_wait >= self.wait_slice {
            return fail("poll_before_wait must be shorter than wait_slice");
        }
        let depths = [
            self.descriptor_queue_depth,
            self.patch_queue_depth,
            self.keyframe_image_queue_depth,
            self.correction_queue_depth,
            self.control_queue_depth,
            self.lifecycle_queue_depth,
            self.max_held_samples,
            self.initial_patch_records,
            self.initial_keyframe_image_pixels,
            self.initial_correction_poses,
            self.initial_control_bytes,
        ];
        if depths.contains(&0) {
            return fail("queue depths, held samples and initial capacities must be at least 1");
        }
        if ServiceName::new(&ServiceNames::new(&self.namespace).patch(self.max_agents - 1)).is_err()
        {
            return fail("namespace does not form valid iceoryx2 service names");
        }
        Ok(())
    }

    /// Per-consumer queue length of `topic`.
    pub fn queue_depth(&self, topic: Topic) -> usize {
        match topic {
            Topic::Descriptor => self.descriptor_queue_depth,
            Topic::Patch => self.patch_queue_depth,
            Topic::KeyframeImage => self.keyframe_image_queue_depth,
            Topic::Correction => self.correction_queue_depth,
            Topic::Control => self.control_queue_depth,
            Topic::Lifecycle => self.lifecycle_queue_depth,
        }
    }

    fn names(&self) -> ServiceNames {
        ServiceNames::new(&self.namespace)
    }
}

/// What a send does when a consumer's queue of the topic is full.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FullQueuePolicy {
    /// Nothing is lost: the send waits (re-sending in 1 ms sleeps) until the consumer made
    /// room, at most `full_queue_timeout`, then fails with [`TransportError::QueueFull`].
    Block,
    /// The send never waits: the newest message replaces the oldest queued one, and the
    /// receiver sees the replaced ones as a gap in the sequence.
    NewestWins,
}

/// [`FullQueuePolicy`] of each topic. Lifecycle messages always block: a hello or goodbye must
/// never be overwritten.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct FullQueuePolicies {
    /// Every descriptor is a keyframe the consensus must know: block.
    pub descriptor: FullQueuePolicy,
    /// Patches are map content (and the final map): block.
    pub patch: FullQueuePolicy,
    /// A keyframe image is needed to align its keyframe: block.
    pub keyframe_image: FullQueuePolicy,
    /// A correction carries the whole current solution for the agent, so a newer one
    /// supersedes the older ones, and the consensus must not wait on a slow agent: newest wins.
    pub correction: FullQueuePolicy,
    /// A control message is a request that is not repeated (shutdown, re-send): block.
    pub control: FullQueuePolicy,
}

impl Default for FullQueuePolicies {
    fn default() -> Self {
        Self {
            descriptor: FullQueuePolicy::Block,
            patch: FullQueuePolicy::Block,
            keyframe_image: FullQueuePolicy::Block,
            correction: FullQueuePolicy::NewestWins,
            control: FullQueuePolicy::Block,
        }
    }
}

impl FullQueuePolicies {
    /// The policy of `topic`; [`Topic::Lifecycle`] always blocks.
    pub fn of(&self, topic: Topic) -> FullQueuePolicy {
        match topic {
            Topic::Descriptor => self.descriptor,
            Topic::Patch => self.patch,
            Topic::KeyframeImage => self.keyframe_image,
            Topic::Correction => self.correction,
            Topic::Control => self.control,
            Topic::Lifecycle => FullQueuePolicy::Block,
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransportError {
    #[error("invalid transport configuration: {reason}")]
    InvalidConfig { reason: String },
    #[error("agent id {agent_id} is out of range: the swarm is configured for ids 0..{max_agents}")]
    AgentIdOutOfRange { agent_id: u32, max_agents: u32 },
    #[error(
        "agent id {agent_id} is outside the swarm in namespace '{namespace}': it was set up for \
         agent ids 0..{swarm_max_agents} by the process that started it (usually \
         mac-consensus --agents {swarm_max_agents}); use an id in that range or start the swarm \
         for more agents"
    )]
    AgentIdOutsideSwarm {
        agent_id: u32,
        swarm_max_agents: u32,
        namespace: String,
    },
    #[error(
        "agent id {agent_id} is already used by a live process in namespace '{namespace}'; \
         give every agent its own id"
    )]
    DuplicateAgent { agent_id: u32, namespace: String },
    #[error("iceoryx2 node '{node}' could not be created: {reason}")]
    Node { node: String, reason: String },
    #[error("service '{service}' could not be opened or created: {reason}")]
    Service { service: String, reason: String },
    #[error("{port} port on '{service}' could not be created: {reason}")]
    Port {
        service: String,
        port: &'static str,
        reason: String,
    },
    #[error(
        "no consumer on '{service}' after {waited:?}: {attached} attached, {required} required \
         (is the consensus running with the same namespace?)"
    )]
    NoConsumer {
        service: String,
        attached: usize,
        required: usize,
        waited: Duration,
    },
    #[error(
        "message {sequence} on '{service}' reached {delivered} of {required} required receivers"
    )]
    Undelivered {
        service: String,
        sequence: u64,
        delivered: usize,
        required: usize,
    },
    #[error(
        "message {sequence} on '{service}' ({topic} topic): a consumer's queue stayed full for \
         {waited:?} (reached {delivered} of {required} required receivers); the consumer is not \
         reading fast enough"
    )]
    QueueFull {
        service: String,
        topic: Topic,
        sequence: u64,
        delivered: usize,
        required: usize,
        waited: Duration,
    },
    #[error("control message {sequence} on '{service}' refused: {source}")]
    ControlFrame {
        service: String,
        sequence: u64,
        source: CodecError,
    },
    #[error("could not loan {elements} elements on '{service}': {reason}")]
    Loan {
        service: String,
        elements: usize,
        reason: String,
    },
    #[error("send on '{service}' failed: {reason}")]
    Send { service: String, reason: String },
    #[error("receive on '{service}' failed: {reason}")]
    Receive { service: String, reason: String },
    #[error("refusing to send on '{service}': {reason}")]
    InvalidMessage { service: String, reason: String },
    #[error("malformed message on '{service}': {reason}")]
    Malformed { service: String, reason: String },
    #[error("goodbye acknowledged by {acknowledged} of {expected} consumers within {waited:?}")]
    GoodbyeUnacknowledged {
        acknowledged: u64,
        expected: usize,
        waited: Duration,
    },
    #[error("waiting for wake-up events failed: {reason}")]
    Wait { reason: String },
    #[error("shutdown requested")]
    ShutdownRequested,
}

/// Direction of counted traffic, seen from the reporting process.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    Sent,
    Received,
}

/// Counters of one (agent, topic, direction).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct TopicTraffic {
    pub messages: u64,
    /// Payload plus user-header bytes.
    pub bytes: u64,
    /// Sent only: bytes the transport copied from caller memory into shared memory. Zero for
    /// in-place builds ([`AgentLink::send_patch_with`]); receivers never copy.
    pub bytes_copied: u64,
    /// Sent only: messages that failed with [`TransportError::QueueFull`] (not in `messages`).
    pub full_queue_failures: u64,
    /// Received only: number of jumps in the sequence, and messages lost in them.
    pub gaps: u64,
    pub missed: u64,
    /// Received only: incarnations (epochs) seen, 1 + restarts.
    pub incarnations: u64,
    /// Received only: messages dropped for belonging to an older epoch, or repeated.
    pub stale_dropped: u64,
    pub duplicates_dropped: u64,
}

/// One row of a [`BandwidthReport`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrafficEntry {
    pub agent_id: u32,
    pub topic: Topic,
    pub direction: Direction,
    #[serde(flatten)]
    pub traffic: TopicTraffic,
}

/// Bandwidth per agent and topic, for the swarm report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BandwidthReport {
    /// Seconds since the link was opened.
    pub elapsed_s: f64,
    pub entries: Vec<TrafficEntry>,
}

impl BandwidthReport {
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
struct TrafficTable {
    opened: Instant,
    rows: BTreeMap<(u32, Topic, Direction), TopicTraffic>,
}

impl TrafficTable {
    fn new() -> Self {
        Self {
            opened: Instant::now(),
            rows: BTreeMap::new(),
        }
    }

    fn row(&mut self, agent_id: u32, topic: Topic, direction: Direction) -> &mut TopicTraffic {
        self.rows.entry((agent_id, topic, direction)).or_default()
    }

    fn report(&self) -> BandwidthReport {
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
}

/// How a received message relates to the ones before it from the same sender and topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// The next sequence number of the current epoch.
    InOrder,
    /// `missed` messages of the current epoch were lost before this one.
    Gap { missed: u64 },
    /// First message seen of a (new) incarnation; `missed` earlier messages of it were not seen
    /// (non-zero when a consumer attaches late).
    NewIncarnation {
        previous_epoch: Option<u64>,
        missed: u64,
    },
}

enum Verdict {
    Deliver(Delivery),
    Stale,
    Duplicate,
}

/// Per (sender, topic) ordering state.
#[derive(Debug, Default)]
struct SequenceTracker {
    last: Option<(u64, u64)>,
}

impl SequenceTracker {
    fn observe(&mut self, epoch: u64, sequence: u64) -> Verdict {
        let verdict = match self.last {
            None => Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: None,
                missed: sequence,
            }),
            Some((last_epoch, _)) if epoch > last_epoch => {
                Verdict::Deliver(Delivery::NewIncarnation {
                    previous_epoch: Some(last_epoch),
                    missed: sequence,
                })
            }
            Some((last_epoch, _)) if epoch < last_epoch => return Verdict::Stale,
            Some((_, last_sequence)) if sequence <= last_sequence => return Verdict::Duplicate,
            Some((_, last_sequence)) if sequence == last_sequence + 1 => {
                Verdict::Deliver(Delivery::InOrder)
            }
            Some((_, last_sequence)) => Verdict::Deliver(Delivery::Gap {
                missed: sequence - last_sequence - 1,
            }),
        };
        self.last = Some((epoch, sequence));
        verdict
    }
}

/// Result of a successful send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SendReport {
    pub sequence: u64,
    /// Subscribers the sample was delivered to.
    pub recipients: usize,
    /// Payload plus user-header bytes written to shared memory.
    pub bytes: usize,
}

/// What an agent says about a keyframe image besides its pixels; the transport adds the
/// [`Stamp`] and builds the [`KeyframeImageHeader`] from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeImageMeta {
    pub keyframe_id: u64,
    /// Index of the frame in the agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// Camera-to-agent-world transform of the keyframe (agent's own world frame).
    pub camera_to_agent_world: Pose,
    /// Intrinsics of the image as sent (scaled with it when the agent downscales); their
    /// `width`/`height` must equal the image size.
    pub intrinsics: Intrinsics,
    /// Image size; the pixel slice must hold exactly `width * height` pixels, row-major.
    pub width: u32,
    pub height: u32,
}

/// Incarnation number of this process: nanoseconds since the Unix epoch, so a restarted process
/// always has a larger one.
fn new_epoch() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(1)
}

/// Builds the iceoryx2 config explicitly so behaviour does not depend on a config file found on
/// the machine; dead-node clean-up is what makes a SIGKILLed process harmless.
fn iceoryx_config() -> Config {
    let mut config = Config::default();
    config.global.node.cleanup_dead_nodes_on_creation = true;
    config.global.node.cleanup_dead_nodes_on_destruction = true;
    config.global.service.cleanup_dead_nodes_on_open = true;
    config
}

fn create_node(name: &str) -> Result<Node<Ipc>, TransportError> {
    let node_error = |reason: String| TransportError::Node {
        node: name.to_string(),
        reason,
    };
    let node_name = NodeName::new(name).map_err(|e| node_error(format!("{e:?}")))?;
    let node = NodeBuilder::new()
        .name(&node_name)
        .config(&iceoryx_config())
        // The processes own their signal handling; the transport offers a shutdown flag.
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| node_error(format!("{e:?}")))?;
    let cleaned = node.try_cleanup_dead_nodes();
    if cleaned.cleanups > 0 || cleaned.failed_cleanups > 0 {
        tracing::info!(
            cleaned = cleaned.cleanups,
            failed = cleaned.failed_cleanups,
            "removed shared-memory leftovers of dead iceoryx2 nodes"
        );
    }
    Ok(node)
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|e| TransportError::Service {
        service: name.to_string(),
        reason: format!("invalid name: {e:?}"),
    })
}

/// Limits of one publish-subscribe service.
#[derive(Debug, Clone, Copy)]
struct PubSubLimits {
    publishers: usize,
    subscribers: usize,
    nodes: usize,
    queue_depth: usize,
    held_samples: usize,
    /// iceoryx2 safe overflow: a full queue drops its oldest sample ([`FullQueuePolicy::NewestWins`]).
    safe_overflow: bool,
}

fn with_limits<P: Debug + IceoryxSend + ?Sized, H: Debug + ZeroCopySend>(
    builder: PubSubBuilder<P, H, Ipc>,
    limits: PubSubLimits,
) -> PubSubBuilder<P, H, Ipc> {
    builder
        .max_publishers(limits.publishers)
        .max_subscribers(limits.subscribers)
        .max_nodes(limits.nodes)
        .subscriber_max_buffer_size(limits.queue_depth)
        .subscriber_max_borrowed_samples(limits.held_samples)
        .history_size(0)
        .enable_safe_overflow(limits.safe_overflow)
}

fn open_event_service(
    node: &Node<Ipc>,
    name: &str,
    notifiers: usize,
    listeners: usize,
    event_ids: usize,
) -> Result<EventService<Ipc>, TransportError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(notifiers)
        .max_listeners(listeners)
        .max_nodes(notifiers + listeners + NODE_SLACK)
        .event_id_max_value(event_ids)
        .open_or_create()
        .map_err(|e| TransportError::Service {
            service: name.to_string(),
            reason: format!("{e:?}"),
        })
}

fn service_error(name: &str, error: impl Debug) -> TransportError {
    TransportError::Service {
        service: name.to_string(),
        reason: format!("{error:?}"),
    }
}

fn port_error(name: &str, port: &'static str, error: impl Debug) -> TransportError {
    TransportError::Port {
        service: name.to_string(),
        port,
        reason: format!("{error:?}"),
    }
}

/// Limits of the services an agent publishes on (one publisher: the agent itself).
fn agent_topic_limits(config: &TransportConfig, topic: Topic) -> PubSubLimits {
    PubSubLimits {
        publishers: 1,
        subscribers: config.max_consumers,
        nodes: 1 + config.max_consumers + NODE_SLACK,
        queue_depth: config.queue_depth(topic),
        held_samples: config.max_held_samples,
        safe_overflow: config.full_queue.of(topic) == FullQueuePolicy::NewestWins,
    }
}

/// Limits of the services consumers publish on to one agent (corrections, control).
fn consumer_to_agent_limits(config: &TransportConfig, topic: Topic) -> PubSubLimits {
    PubSubLimits {
        publishers: config.max_consumers,
        subscribers: 1,
        nodes: 1 + config.max_consumers + NODE_SLACK,
        queue_depth: config.queue_depth(topic),
        held_samples: config.max_held_samples,
        safe_overflow: config.full_queue.of(topic) == FullQueuePolicy::NewestWins,
    }
}

fn lifecycle_limits(config: &TransportConfig) -> PubSubLimits {
    let processes = config.max_agents as usize + config.max_consumers;
    PubSubLimits {
        // Slack as for nodes: a restarted agent may come before its dead twin is cleaned up.
        publishers: processes + NODE_SLACK,
        subscribers: config.max_consumers,
        nodes: processes + NODE_SLACK,
        queue_depth: config.lifecycle_queue_depth,
        held_samples: config.max_held_samples,
        safe_overflow: false,
    }
}

struct DescriptorService;
struct PatchService;
struct KeyframeImageService;
struct CorrectionService;
struct ControlService;
struct LifecycleService;

impl DescriptorService {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<PubSubService<Ipc, KeyframeDescriptor, ()>, TransportError> {
        let name = config.names().descriptor(agent_id);
        let builder = node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<KeyframeDescriptor>();
        with_limits(builder, agent_topic_limits(config, Topic::Descriptor))
            .open_or_create()
            .map_err(|e| service_error(&name, e))
    }
}

impl PatchService {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<PubSubService<Ipc, [GaussianRecord], PatchHeader>, TransportError> {
        let name = config.names().patch(agent_id);
        let builder = node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<[GaussianRecord]>()
            .user_header::<PatchHeader>();
        with_limits(builder, agent_topic_limits(config, Topic::Patch))
            .open_or_create()
            .map_err(|e| service_error(&name, e))
    }
}

impl KeyframeImageService {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<PubSubService<Ipc, [RgbdPixel], KeyframeImageHeader>, TransportError> {
        let name = config.names().keyframe_image(agent_id);
        let builder = node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<[RgbdPixel]>()
            .user_header::<KeyframeImageHeader>();
        with_limits(builder, agent_topic_limits(config, Topic::KeyframeImage))
            .open_or_create()
            .map_err(|e| service_error(&name, e))
    }
}

impl CorrectionService {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<PubSubService<Ipc, [KeyframePose], CorrectionHeader>, TransportError> {
        let name = config.names().correction(agent_id);
        let builder = node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<[KeyframePose]>()
            .user_header::<CorrectionHeader>();
        with_limits(builder, consumer_to_agent_limits(config, Topic::Correction))
            .open_or_create()
            .map_err(|e| service_error(&name, e))
    }
}

impl ControlService {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<PubSubService<Ipc, [u8], ControlHeader>, TransportError> {
        let name = config.names().control(agent_id);
        let builder = node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<[u8]>()
            .user_header::<ControlHeader>();
        with_limits(builder, consumer_to_agent_limits(config, Topic::Control))
            .open_or_create()
            .map_err(|e| service_error(&name, e))
    }
}

impl LifecycleService {
    /// Opens the shared lifecycle service as its creator set it up, or creates it sized for
    /// `config.max_agents` with that range recorded as an attribute. Returns the service and
    /// the agent-id range of the swarm (the creator's `max_agents`).
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
    ) -> Result<(PubSubService<Ipc, Lifecycle, ()>, u32), TransportError> {
        let name = config.names().lifecycle();
        let service = service_name(&name)?;
        let attribute_error = |e: &dyn Debug| TransportError::Service {
            service: name.clone(),
            reason: format!("attribute {SWARM_MAX_AGENTS_ATTRIBUTE}: {e:?}"),
        };
        let key =
            AttributeKey::try_from(SWARM_MAX_AGENTS_ATTRIBUTE).map_err(|e| attribute_error(&e))?;
        let ours = AttributeValue::try_from(config.max_agents.to_string().as_str())
            .map_err(|e| attribute_error(&e))?;
        let any_range = AttributeVerifier::new()
            .require_key(&key)
            .map_err(|e| attribute_error(&e))?;
        let our_range = AttributeVerifier::new()
            .require(&key, &ours)
            .map_err(|e| attribute_error(&e))?;
        let builder = || {
            node.service_builder(&service)
                .publish_subscribe::<Lifecycle>()
        };
        let opened = open_shared(
            &name,
            // No limits requested: a swarm set up for another agent count opens as it is.
            || builder().open_with_attributes(&any_range),
            |e| {
                matches!(
                    e,
                    PublishSubscribeOpenError::DoesNotExist
                        | PublishSubscribeOpenError::HangsInCreation
                        | PublishSubscribeOpenError::IsMarkedForDestruction
                )
            },
            || {
                with_limits(builder(), lifecycle_limits(config))
                    .open_or_create_with_attributes(&our_range)
            },
            |e| {
                matches!(
                    e,
                    PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(_)
                )
            },
        )?;
        let swarm_max_agents = opened
            .attributes()
            .key_value(&key, 0)
            .and_then(|value| value.to_string().parse::<u32>().ok())
            .filter(|&agents| agents > 0)
            .ok_or_else(|| TransportError::Service {
                service: name.clone(),
                reason: format!(
                    "attribute {SWARM_MAX_AGENTS_ATTRIBUTE} is not a positive agent count: {:?}",
                    opened.attributes()
                ),
            })?;
        Ok((opened, swarm_max_agents))
    }
}

/// Opens a service shared by the whole swarm whose limits depend on the agent count: first as
/// it exists (`open_as_it_is`, requesting no limits, so processes configured for different agent
/// counts can meet), and only when it is absent (`is_absent`) with our own limits
/// (`open_or_create_ours`, which handles concurrent creation). When that finds a service
/// created meanwhile with other limits (`is_mismatch`), the next round opens it as it is.
fn open_shared<S, OpenError: Debug, OpenOrCreateError: Debug>(
    name: &str,
    mut open_as_it_is: impl FnMut() -> Result<S, OpenError>,
    is_absent: impl Fn(&OpenError) -> bool,
    mut open_or_create_ours: impl FnMut() -> Result<S, OpenOrCreateError>,
    is_mismatch: impl Fn(&OpenOrCreateError) -> bool,
) -> Result<S, TransportError> {
    let mut last_error = String::new();
    for _ in 0..SHARED_SERVICE_OPEN_ATTEMPTS {
        match open_as_it_is() {
            Ok(service) => return Ok(service),
            Err(e) if is_absent(&e) => {}
            Err(e) => return Err(service_error(name, e)),
        }
        match open_or_create_ours() {
            Ok(service) => return Ok(service),
            Err(e) if is_mismatch(&e) => last_error = format!("{e:?}"),
            Err(e) => return Err(service_error(name, e)),
        }
    }
    Err(service_error(
        name,
        format!(
            "still changing after {SHARED_SERVICE_OPEN_ATTEMPTS} attempts (processes creating \
             and removing it at the same time); last error: {last_error}"
        ),
    ))
}

fn open_agent_wake(
    node: &Node<Ipc>,
    config: &TransportConfig,
    agent_id: u32,
) -> Result<EventService<Ipc>, TransportError> {
    open_event_service(
        node,
        &config.names().agent_wake(agent_id),
        config.max_consumers,
        1,
        AGENT_WAKE_EVENT_IDS,
    )
}

/// The consumers' wake-up service is shared by all agents and sized by the agent count, so it
/// is opened like the lifecycle service ([`open_shared`]).
fn open_consumers_wake(
    node: &Node<Ipc>,
    config: &TransportConfig,
) -> Result<EventService<Ipc>, TransportError> {
    let name = config.names().consumers_wake();
    let service = service_name(&name)?;
    let agents = config.max_agents as usize;
    open_shared(
        &name,
        || node.service_builder(&service).event().open(),
        |e| {
            matches!(
                e,
                EventOpenError::DoesNotExist
                    | EventOpenError::HangsInCreation
                    | EventOpenError::IsMarkedForDestruction
            )
        },
        || {
            node.service_builder(&service)
                .event()
                .max_notifiers(agents + NODE_SLACK)
                .max_listeners(config.max_consumers)
                .max_nodes(agents + config.max_consumers + NODE_SLACK)
                .event_id_max_value(agents * TOPIC_COUNT)
                .open_or_create()
        },
        |e| matches!(e, EventOpenOrCreateError::EventOpenError(_)),
    )
}

/// Waits on `listener` for at most `timeout`, returning early on any event, with the number of
/// notifications that arrived (0 after a timeout). The event ids themselves are not needed:
/// callers re-check the state they wait for.
fn wait_for_event(
    listener: &Listener<Ipc>,
    timeout: Duration,
    shutdown: &AtomicBool,
) -> Result<u64, TransportError> {
    if shutdown.load(Ordering::Relaxed) {
        return Err(TransportError::ShutdownRequested);
    }
    listener
        .timed_wait(|_| {}, timeout)
        .map_err(|e| TransportError::Wait {
            reason: format!("{e:?}"),
        })
}

/// Discards the notifications pending on `listener` without blocking. A receiver that polled
/// its queues has already taken the messages those notifications announced; left pending, they
/// would wake its next wait at once for nothing.
fn discard_pending_events(listener: &Listener<Ipc>) -> Result<(), TransportError> {
    listener
        .try_wait(|_| {})
        .map(|_| ())
        .map_err(|e| TransportError::Wait {
            reason: format!("{e:?}"),
        })
}

/// A link that receives: what [`receive_within`] needs besides the receive itself.
trait Receiving {
    fn config(&self) -> &TransportConfig;
    fn wake_listener(&self) -> &Listener<Ipc>;
    fn shutdown_flag(&self) -> &AtomicBool;
    /// When the link last sent or received a message.
    fn last_activity(&self) -> Instant;
    fn mark_activity(&mut self);
}

/// [`Receiving`] for a link type with fields `config`, `wake_listener`, `shutdown` and
/// `last_activity`.
macro_rules! impl_receiving {
    ($link:ty) => {
        impl Receiving for $link {
            fn config(&self) -> &TransportConfig {
                &self.config
            }
            fn wake_listener(&self) -> &Listener<Ipc> {
                &self.wake_listener
            }
            fn shutdown_flag(&self) -> &AtomicBool {
                &self.shutdown
            }
            fn last_activity(&self) -> Instant {
                self.last_activity
            }
            fn mark_activity(&mut self) {
                self.last_activity = Instant::now();
            }
        }
    };
}

/// Calls `try_receive` until it yields a message or `timeout` has passed. While the link's
/// last activity (a message sent or received, or a wake-up) is less than `poll_before_wait`
/// old, it polls, yielding the core between polls; after that it blocks on the link's wake-up
/// event in slices of at most `wait_slice`. A wake-up counts as activity, so a receiver woken
/// by a sender's early notice ([`AgentLink`] sends one before it builds a large message) polls
/// until the message is complete instead of sleeping again. Returns `None` after `timeout`.
fn receive_within<L: Receiving, T>(
    link: &mut L,
    timeout: Duration,
    mut try_receive: impl FnMut(&mut L) -> Result<Option<T>, TransportError>,
) -> Result<Option<T>, TransportError> {
    let start = Instant::now();
    loop {
        if let Some(message) = try_receive(link)? {
            link.mark_activity();
            return Ok(Some(message));
        }
        let waited = start.elapsed();
        if waited >= timeout {
            return Ok(None);
        }
        let (poll_before_wait, wait_slice) =
            (link.config().poll_before_wait, link.config().wait_slice);
        if link.last_activity().elapsed() < poll_before_wait {
            if link.shutdown_flag().load(Ordering::Relaxed) {
                return Err(TransportError::ShutdownRequested);
            }
            std::thread::yield_now();
            continue;
        }
        // Before sleeping: drop the notifications of messages already taken while polling,
        // then look once more, so that only a notification sent from now on wakes the wait
        // (one sent between the two steps finds its message in the queues).
        discard_pending_events(link.wake_listener())?;
        if let Some(message) = try_receive(link)? {
            link.mark_activity();
            return Ok(Some(message));
        }
        let notifications = wait_for_event(
            link.wake_listener(),
            wait_slice.min(timeout - waited),
            link.shutdown_flag(),
        )?;
        if notifications > 0 {
            link.mark_activity();
        }
    }
}

/// Sender side of one topic.
struct Outbox<P: Debug + IceoryxSend + ?Sized + 'static, H: Debug + ZeroCopySend> {
    name: String,
    service: PubSubService<Ipc, P, H>,
    publisher: Publisher<Ipc, P, H>,
    next_sequence: u64,
}

impl<P: Debug + IceoryxSend + ?Sized + 'static, H: Debug + ZeroCopySend> Outbox<P, H> {
    fn attached(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    fn take_sequence(&mut self) -> u64 {
        let sequence = self.next_sequence;
        self.next_sequence += 1;
        sequence
    }
}

fn loan_error(name: &str, elements: usize, error: impl Debug) -> TransportError {
    TransportError::Loan {
        service: name.to_string(),
        elements,
        reason: format!("{error:?}"),
    }
}

fn send_error(name: &str, error: impl Debug) -> TransportError {
    TransportError::Send {
        service: name.to_string(),
        reason: format!("{error:?}"),
    }
}

fn check_recipients(
    name: &str,
    sequence: u64,
    delivered: usize,
    required: usize,
) -> Result<(), TransportError> {
    if delivered < required {
        return Err(TransportError::Undelivered {
            service: name.to_string(),
            sequence,
            delivered,
            required,
        });
    }
    Ok(())
}

fn validate_pose(name: &str, what: &str, pose: &Pose) -> Result<(), TransportError> {
    if !pose.is_valid(POSE_NORM_TOLERANCE) {
        return Err(TransportError::InvalidMessage {
            service: name.to_string(),
            reason: format!("{what} is not finite or its quaternion is not unit: {pose:?}"),
        });
    }
    Ok(())
}

/// Refuses a keyframe image whose header would mislead the consensus: an empty image, a pixel
/// slice that does not match `width * height`, intrinsics of another image size (the usual
/// mistake when downscaling), unusable intrinsics or an invalid pose.
fn validate_keyframe_image(
    name: &str,
    meta: &KeyframeImageMeta,
    pixels: usize,
) -> Result<(), TransportError> {
    let refuse = |reason: String| {
        Err(TransportError::InvalidMessage {
            service: name.to_string(),
            reason,
        })
    };
    let (width, height) = (meta.width, meta.height);
    if width == 0 || height == 0 {
        return refuse(format!(
            "keyframe {} image size {width}x{height} is empty",
            meta.keyframe_id
        ));
    }
    // u64: width * height of two u32 cannot overflow it, unlike usize on 32-bit targets.
    let expected = u64::from(width) * u64::from(height);
    if expected != pixels as u64 {
        return refuse(format!(
            "keyframe {} image is {width}x{height} = {expected} pixels, but {pixels} pixels were \
             given",
            meta.keyframe_id
        ));
    }
    let k = &meta.intrinsics;
    if (k.width, k.height) != (width, height) {
        return refuse(format!(
            "keyframe {} intrinsics are for a {}x{} image but the image is {width}x{height} \
             (scale the intrinsics with the image)",
            meta.keyframe_id, k.width, k.height
        ));
    }
    let focal_ok = [k.fx, k.fy].iter().all(|f| f.is_finite() && *f > 0.0);
    if !focal_ok || !k.cx.is_finite() || !k.cy.is_finite() {
        return refuse(format!(
            "keyframe {} intrinsics need finite positive focal lengths and a finite principal \
             point: {k:?}",
            meta.keyframe_id
        ));
    }
    validate_pose(name, "camera_to_agent_world", &meta.camera_to_agent_world)
}

/// A received keyframe descriptor, read in place from shared memory.
pub struct DescriptorSample {
    sample: Sample<Ipc, KeyframeDescriptor, ()>,
    pub delivery: Delivery,
}

impl std::ops::Deref for DescriptorSample {
    type Target = KeyframeDescriptor;
    fn deref(&self) -> &KeyframeDescriptor {
        self.sample.payload()
    }
}

/// A received Gaussian patch, read in place from shared memory (no copy).
pub struct PatchSample {
    sample: Sample<Ipc, [GaussianRecord], PatchHeader>,
    pub delivery: Delivery,
}

impl PatchSample {
    pub fn header(&self) -> &PatchHeader {
        self.sample.user_header()
    }

    pub fn records(&self) -> &[GaussianRecord] {
        self.sample.payload()
    }
}

/// A received keyframe RGB-D image, read in place from shared memory (no copy).
pub struct KeyframeImageSample {
    sample: Sample<Ipc, [RgbdPixel], KeyframeImageHeader>,
    pub delivery: Delivery,
}

impl KeyframeImageSample {
    pub fn header(&self) -> &KeyframeImageHeader {
        self.sample.user_header()
    }

    /// `width * height` pixels, row-major (checked on receive).
    pub fn pixels(&self) -> &[RgbdPixel] {
        self.sample.payload()
    }
}

/// A received lifecycle message (copied out of shared memory: it is small, and a held-back
/// goodbye must not pin a shared-memory sample).
pub struct LifecycleSample {
    message: Lifecycle,
    pub delivery: Delivery,
}

impl std::ops::Deref for LifecycleSample {
    type Target = Lifecycle;
    fn deref(&self) -> &Lifecycle {
        &self.message
    }
}

/// A received correction, read in place from shared memory.
pub struct CorrectionSample {
    sample: Sample<Ipc, [KeyframePose], CorrectionHeader>,
    pub delivery: Delivery,
}

impl CorrectionSample {
    pub fn header(&self) -> &CorrectionHeader {
        self.sample.user_header()
    }

    pub fn poses(&self) -> &[KeyframePose] {
        self.sample.payload()
    }
}

/// A received control message, decoded out of shared memory (it holds heap data).
#[derive(Debug, Clone, PartialEq)]
pub struct ControlSample {
    pub header: ControlHeader,
    pub message: ControlMessage,
    pub delivery: Delivery,
}

/// Anything a consumer receives.
pub enum Incoming {
    Descriptor(DescriptorSample),
    Patch(PatchSample),
    KeyframeImage(KeyframeImageSample),
    Lifecycle(LifecycleSample),
}

impl Incoming {
    pub fn agent_id(&self) -> u32 {
        self.stamp().agent_id
    }

    pub fn stamp(&self) -> Stamp {
        match self {
            Incoming::Descriptor(d) => d.stamp,
            Incoming::Patch(p) => p.header().stamp,
            Incoming::KeyframeImage(k) => k.header().stamp,
            Incoming::Lifecycle(l) => l.stamp,
        }
    }

    pub fn delivery(&self) -> Delivery {
        match self {
            Incoming::Descriptor(d) => d.delivery,
            Incoming::Patch(p) => p.delivery,
            Incoming::KeyframeImage(k) => k.delivery,
            Incoming::Lifecycle(l) => l.delivery,
        }
    }

    pub fn topic(&self) -> Topic {
        match self {
            Incoming::Descriptor(_) => Topic::Descriptor,
            Incoming::Patch(_) => Topic::Patch,
            Incoming::KeyframeImage(_) => Topic::KeyframeImage,
            Incoming::Lifecycle(_) => Topic::Lifecycle,
        }
    }
}

/// Ordering bookkeeping shared by both endpoints' receive paths.
#[derive(Debug, Default)]
struct ReceiveBook {
    trackers: BTreeMap<(u32, Topic), SequenceTracker>,
}

impl ReceiveBook {
    /// Records a received message under agent `account_as`; `None` means drop it (stale or
    /// duplicate). Ordering is tracked per sender (`stamp.agent_id`) and topic.
    fn admit(
        &mut self,
        traffic: &mut TrafficTable,
        stamp: Stamp,
        topic: Topic,
        bytes: usize,
        account_as: u32,
    ) -> Option<Delivery> {
        let verdict = self
            .trackers
            .entry((stamp.agent_id, topic))
            .or_default()
            .observe(stamp.epoch, stamp.sequence);
        let row = traffic.row(account_as, topic, Direction::Received);
        match verdict {
            Verdict::Stale => {
                row.stale_dropped += 1;
                None
            }
            Verdict::Duplicate => {
                row.duplicates_dropped += 1;
                None
            }
            Verdict::Deliver(delivery) => {
                row.messages += 1;
                row.bytes += bytes as u64;
                match delivery {
                    Delivery::InOrder => {}
                    Delivery::Gap { missed } => {
                        row.gaps += 1;
                        row.missed += missed;
                    }
                    Delivery::NewIncarnation { missed, .. } => {
                        row.incarnations += 1;
                        if missed > 0 {
                            row.gaps += 1;
                            row.missed += missed;
                        }
                    }
                }
                Some(delivery)
            }
        }
    }
}

/// The transport endpoint of one agent process.
pub struct AgentLink {
    agent_id: u32,
    epoch: u64,
    config: TransportConfig,
    descriptor: Outbox<KeyframeDescriptor, ()>,
    patch: Outbox<[GaussianRecord], PatchHeader>,
    keyframe_image: Outbox<[RgbdPixel], KeyframeImageHeader>,
    lifecycle: Outbox<Lifecycle, ()>,
    correction_name: String,
    correction_subscriber: Subscriber<Ipc, [KeyframePose], CorrectionHeader>,
    control_name: String,
    control_subscriber: Subscriber<Ipc, [u8], ControlHeader>,
    wake_listener: Listener<Ipc>,
    consumers_notifier: Notifier<Ipc>,
    traffic: TrafficTable,
    book: ReceiveBook,
    shutdown: Arc<AtomicBool>,
    /// When this link last sent or received a message: receives poll while it is recent.
    last_activity: Instant,
    said_goodbye: bool,
    // Kept last: ports above must be dropped before the node that owns them.
    _correction_service: PubSubService<Ipc, [KeyframePose], CorrectionHeader>,
    _control_service: PubSubService<Ipc, [u8], ControlHeader>,
    _wake_service: EventService<Ipc>,
    _consumers_wake_service: EventService<Ipc>,
    node: Node<Ipc>,
}

impl AgentLink {
    /// Opens the agent's services and ports. Cleans up dead processes' leftovers first, and
    /// refuses an id that a live agent already uses. Send [`AgentLink::announce`] next.
    pub fn open(config: &TransportConfig, agent_id: u32) -> Result<Self, TransportError> {
        config.validate()?;
        if agent_id >= config.max_agents {
            return Err(TransportError::AgentIdOutOfRange {
                agent_id,
                max_agents: config.max_agents,
            });
        }
        let names = config.names();
        let node = create_node(&format!("mac-agent-{agent_id}"))?;
        // Opened before the agent's own topics: an id outside the swarm must not leave them.
        let (lifecycle_service, swarm_max_agents) = LifecycleService::open(&node, config)?;
        if agent_id >= swarm_max_agents {
            return Err(TransportError::AgentIdOutsideSwarm {
                agent_id,
                swarm_max_agents,
                namespace: config.namespace.clone(),
            });
        }

        let descriptor_service = DescriptorService::open(&node, config, agent_id)?;
        let descriptor_name = names.descriptor(agent_id);
        // The first exclusive port: failing here with "too many publishers" means a live twin.
        let descriptor_publisher = descriptor_service
            .publisher_builder()
            .max_loaned_samples(PUBLISHER_MAX_LOANS)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| match e {
                PublisherCreateError::ExceedsMaxSupportedPublishers => {
                    TransportError::DuplicateAgent {
                        agent_id,
                        namespace: config.namespace.clone(),
                    }
                }
                other => port_error(&descriptor_name, "publisher", other),
            })?;

        let patch_service = PatchService::open(&node, config, agent_id)?;
        let patch_name = names.patch(agent_id);
        let patch_publisher = patch_service
            .publisher_builder()
            .max_loaned_samples(PUBLISHER_MAX_LOANS)
            .initial_max_slice_len(config.initial_patch_records)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| match e {
                PublisherCreateError::ExceedsMaxSupportedPublishers => {
                    TransportError::DuplicateAgent {
                        agent_id,
                        namespace: config.namespace.clone(),
                    }
                }
                other => port_error(&patch_name, "publisher", other),
            })?;

        let keyframe_image_service = KeyframeImageService::open(&node, config, agent_id)?;
        let keyframe_image_name = names.keyframe_image(agent_id);
        let keyframe_image_publisher = keyframe_image_service
            .publisher_builder()
            .max_loaned_samples(PUBLISHER_MAX_LOANS)
            .initial_max_slice_len(config.initial_keyframe_image_pixels)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| match e {
                PublisherCreateError::ExceedsMaxSupportedPublishers => {
                    TransportError::DuplicateAgent {
                        agent_id,
                        namespace: config.namespace.clone(),
                    }
                }
                other => port_error(&keyframe_image_name, "publisher", other),
            })?;

        let lifecycle_name = names.lifecycle();
        let lifecycle_publisher = lifecycle_service
            .publisher_builder()
            .max_loaned_samples(PUBLISHER_MAX_LOANS)
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .create()
            .map_err(|e| port_error(&lifecycle_name, "publisher", e))?;

        let correction_service = CorrectionService::open(&node, config, agent_id)?;
        let correction_name = names.correction(agent_id);
        let correction_subscriber = correction_service
            .subscriber_builder()
            .buffer_size(config.correction_queue_depth)
            .create()
            .map_err(|e| port_error(&correction_name, "subscriber", e))?;

        let control_service = ControlService::open(&node, config, agent_id)?;
        let control_name = names.control(agent_id);
        let control_subscriber = control_service
            .subscriber_builder()
            .buffer_size(config.control_queue_depth)
            .create()
            .map_err(|e| port_error(&control_name, "subscriber", e))?;

        let wake_service = open_agent_wake(&node, config, agent_id)?;
        let wake_listener = wake_service
            .listener_builder()
            .create()
            .map_err(|e| port_error(&names.agent_wake(agent_id), "listener", e))?;
        let consumers_wake_service = open_consumers_wake(&node, config)?;
        let consumers_notifier = consumers_wake_service
            .notifier_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "notifier", e))?;

        Ok(Self {
            agent_id,
            epoch: new_epoch(),
            config: config.clone(),
            descriptor: Outbox {
                name: descriptor_name,
                service: descriptor_service,
                publisher: descriptor_publisher,
                next_sequence: 0,
            },
            patch: Outbox {
                name: patch_name,
                service: patch_service,
                publisher: patch_publisher,
                next_sequence: 0,
            },
            keyframe_image: Outbox {
                name: keyframe_image_name,
                service: keyframe_image_service,
                publisher: keyframe_image_publisher,
                next_sequence: 0,
            },
            lifecycle: Outbox {
                name: lifecycle_name,
                service: lifecycle_service,
                publisher: lifecycle_publisher,
                next_sequence: 0,
            },
            correction_name,
            correction_subscriber,
            control_name,
            control_subscriber,
            wake_listener,
            consumers_notifier,
            traffic: TrafficTable::new(),
            book: ReceiveBook::default(),
            shutdown: Arc::new(AtomicBool::new(false)),
            last_activity: Instant::now(),
            said_goodbye: false,
            _correction_service: correction_service,
            _control_service: control_service,
            _wake_service: wake_service,
            _consumers_wake_service: consumers_wake_service,
            node,
        })
    }

    pub fn agent_id(&self) -> u32 {
        self.agent_id
    }

    /// This incarnation's epoch (see [`Stamp::epoch`]).
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Setting this flag makes every blocking call return [`TransportError::ShutdownRequested`]
    /// within `wait_slice`.
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.shutdown)
    }

    /// Consumers currently attached to this agent's patch topic.
    pub fn attached_consumers(&self) -> usize {
        self.patch.attached()
    }

    /// True when `required_consumers` consumers are attached to every outgoing topic now (a
    /// send would not wait for one). Does not block; first reclaims what processes that died
    /// left behind, so a killed consensus does not look attached.
    pub fn consumers_present(&self) -> bool {
        self.node.try_cleanup_dead_nodes();
        let required = self.config.required_consumers;
        Topic::ALL
            .into_iter()
            .filter_map(|topic| self.attached(topic))
            .all(|(attached, _)| attached >= required)
    }

    /// Waits (event-driven) up to the configured `delivery_timeout` for consumers to attach to
    /// every outgoing topic; [`TransportError::NoConsumer`] when they do not.
    pub fn await_all_consumers(&self) -> Result<(), TransportError> {
        // Incoming topics have no consumers to wait for: await_consumers passes them at once.
        Topic::ALL
            .into_iter()
            .try_for_each(|topic| self.await_consumers(topic))
    }

    /// Subscribers attached to one of this agent's outgoing topics, and the service name.
    fn attached(&self, topic: Topic) -> Option<(usize, &str)> {
        match topic {
            Topic::Descriptor => Some((self.descriptor.attached(), &self.descriptor.name)),
            Topic::Patch => Some((self.patch.attached(), &self.patch.name)),
            Topic::KeyframeImage => {
                Some((self.keyframe_image.attached(), &self.keyframe_image.name))
            }
            Topic::Lifecycle => Some((self.lifecycle.attached(), &self.lifecycle.name)),
            Topic::Correction | Topic::Control => None,
        }
    }

    /// Blocks (event-driven) until `required_consumers` subscribers are attached to `topic`.
    fn await_consumers(&self, topic: Topic) -> Result<(), TransportError> {
        let required = self.config.required_consumers;
        let start = Instant::now();
        while let Some((attached, name)) = self.attached(topic) {
            if attached >= required {
                return Ok(());
            }
            let waited = start.elapsed();
            if waited >= self.config.delivery_timeout {
                return Err(TransportError::NoConsumer {
                    service: name.to_string(),
                    attached,
                    required,
                    waited,
                });
            }
            let slice = self
                .config
                .wait_slice
                .min(self.config.delivery_timeout - waited);
            wait_for_event(&self.wake_listener, slice, &self.shutdown)?;
        }
        Ok(())
    }

    fn stamp(&self, sequence: u64) -> Stamp {
        Stamp {
            agent_id: self.agent_id,
            reserved: 0,
            epoch: self.epoch,
            sequence,
        }
    }

    fn notify_consumers(&self, topic: Topic) {
        let event = EventId::new(self.agent_id as usize * TOPIC_COUNT + topic.index());
        // A failed wake-up only delays the consumer to its next wait slice; the sample is queued.
        if let Err(e) = self.consumers_notifier.notify_with_custom_event_id(event) {
            tracing::warn!(error = ?e, "could not wake consumers");
        }
    }

    fn account_sent(&mut self, topic: Topic, bytes: usize, copied: usize) {
        self.last_activity = Instant::now();
        let row = self.traffic.row(self.agent_id, topic, Direction::Sent);
        row.messages += 1;
        row.bytes += bytes as u64;
        row.bytes_copied += copied as u64;
    }

    /// Announces this incarnation (first message after [`AgentLink::open`]); `run_anchor` as in
    /// [`Lifecycle::run_anchor`].
    pub fn announce(
        &mut self,
        intrinsics: Intrinsics,
        config_hash: u64,
        run_anchor: u64,
    ) -> Result<SendReport, TransportError> {
        self.send_lifecycle(Lifecycle::hello(intrinsics, config_hash, run_anchor))
    }

    /// Heartbeat; also reclaims leftovers of processes that died since the last one.
    pub fn heartbeat(&mut self) -> Result<SendReport, TransportError> {
        self.node.try_cleanup_dead_nodes();
        self.send_lifecycle(Lifecycle::alive())
    }

    /// Orderly goodbye: waits until every consumer that received it has drained this agent's
    /// topics and acknowledged, so nothing sent before is lost when the process exits.
    pub fn close(mut self) -> Result<SendReport, TransportError> {
        self.said_goodbye = true;
        self.goodbye(self.config.delivery_timeout)
    }

    /// Sends `Goodbye` and waits up to `ack_timeout` for every recipient's acknowledgement.
    fn goodbye(&mut self, ack_timeout: Duration) -> Result<SendReport, TransportError> {
        let report = self.send_lifecycle(Lifecycle::goodbye())?;
        let start = Instant::now();
        let mut acknowledged = 0u64;
        while acknowledged < report.recipients as u64 {
            let waited = start.elapsed();
            if waited >= ack_timeout {
                return Err(TransportError::GoodbyeUnacknowledged {
                    acknowledged,
                    expected: report.recipients,
                    waited,
                });
            }
            let slice = self.config.wait_slice.min(ack_timeout - waited);
            self.wake_listener
                .timed_wait(
                    |event| {
                        if event.id.as_value() == WAKE_GOODBYE_SEEN {
                            acknowledged += event.count;
                        }
                    },
                    slice,
                )
                .map_err(|e| TransportError::Wait {
                    reason: format!("{e:?}"),
                })?;
        }
        Ok(report)
    }

    /// Sends with `send_once` until `required_consumers` received the message: waits for
    /// consumers to attach first, then applies the topic's [`FullQueuePolicy`]: with `Block`,
    /// re-sends (same sequence) while a consumer's queue is full, up to `full_queue_timeout`.
    fn deliver(
        &self,
        topic: Topic,
        sequence: u64,
        mut send_once: impl FnMut() -> Result<usize, TransportError>,
    ) -> Result<usize, TransportError> {
        self.await_consumers(topic)?;
        if topic.is_bulk() && !self.config.poll_before_wait.is_zero() {
            // Early notice: a blocked consumer wakes while the message is being built (its
            // wake-up costs about as much as building a 10k-record patch) and polls until it
            // is sent. Receivers that never poll would only wake twice, hence the condition.
            self.notify_consumers(topic);
        }
        let required = self.config.required_consumers;
        let policy = self.config.full_queue.of(topic);
        let start = Instant::now();
        loop {
            let delivered = send_once()?;
            if delivered >= required {
                self.notify_consumers(topic);
                return Ok(delivered);
            }
            let (attached, name) = self.attached(topic).unwrap_or((0, ""));
            if attached < required {
                // A consumer left after the handshake: wait for one as before the first send.
                self.await_consumers(topic)?;
                continue;
            }
            // Attached but not reached: its queue is full (a `NewestWins` queue never is, so
            // there this is a consumer leaving right now; the next round tells).
            let waited = start.elapsed();
            if waited >= self.config.full_queue_timeout {
                let service = name.to_string();
                return Err(match policy {
                    FullQueuePolicy::Block => TransportError::QueueFull {
                        service,
                        topic,
                        sequence,
                        delivered,
                        required,
                        waited,
                    },
                    FullQueuePolicy::NewestWins => TransportError::Undelivered {
                        service,
                        sequence,
                        delivered,
                        required,
                    },
                });
            }
            // Wake the consumers again: they may be asleep with a full queue of older data.
            self.notify_consumers(topic);
            wait_for_event(&self.wake_listener, FULL_QUEUE_RETRY, &self.shutdown)?;
        }
    }

    /// Counts a [`TransportError::QueueFull`] of `topic` in the bandwidth report.
    fn count_full_queue(
        &mut self,
        topic: Topic,
        result: Result<usize, TransportError>,
    ) -> Result<usize, TransportError> {
        if let Err(TransportError::QueueFull { .. }) = &result {
            self.traffic
                .row(self.agent_id, topic, Direction::Sent)
                .full_queue_failures += 1;
        }
        result
    }

    fn send_lifecycle(&mut self, mut message: Lifecycle) -> Result<SendReport, TransportError> {
        let sequence = self.lifecycle.take_sequence();
        message.stamp = self.stamp(sequence);
        let outbox = &self.lifecycle;
        let result = self.deliver(Topic::Lifecycle, sequence, || {
            let sample = outbox
                .publisher
                .loan_uninit()
                .map_err(|e| loan_error(&outbox.name, 1, e))?;
            sample
                .write_payload(message)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::Lifecycle, result)?;
        let bytes = size_of::<Lifecycle>();
        self.account_sent(Topic::Lifecycle, bytes, bytes);
        Ok(SendReport {
            sequence,
            recipients: delivered,
            bytes,
        })
    }

    /// Publishes a keyframe descriptor. The stamp is filled in here; the descriptor must be
    /// L2-normalised and the pose valid.
    pub fn send_descriptor(
        &mut self,
        descriptor: &KeyframeDescriptor,
    ) -> Result<SendReport, TransportError> {
        let name = &self.descriptor.name;
        let norm = descriptor.descriptor_norm();
        if !norm.is_finite() || (norm - 1.0).abs() > DESCRIPTOR_NORM_TOLERANCE {
            return Err(TransportError::InvalidMessage {
                service: name.clone(),
                reason: format!("descriptor norm is {norm}, expected 1 (L2-normalised)"),
            });
        }
        validate_pose(
            name,
            "camera_to_agent_world",
            &descriptor.camera_to_agent_world,
        )?;
        let sequence = self.descriptor.take_sequence();
        let mut message = *descriptor;
        message.stamp = self.stamp(sequence);
        let outbox = &self.descriptor;
        let result = self.deliver(Topic::Descriptor, sequence, || {
            let sample = outbox
                .publisher
                .loan_uninit()
                .map_err(|e| loan_error(&outbox.name, 1, e))?;
            sample
                .write_payload(message)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::Descriptor, result)?;
        let bytes = size_of::<KeyframeDescriptor>();
        self.account_sent(Topic::Descriptor, bytes, bytes);
        Ok(SendReport {
            sequence,
            recipients: delivered,
            bytes,
        })
    }

    /// Publishes a patch by copying `records` into shared memory (one copy).
    pub fn send_patch(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        records: &[GaussianRecord],
    ) -> Result<SendReport, TransportError> {
        let (sequence, header) = self.next_patch_header(keyframe_id, frame, records.len());
        let outbox = &self.patch;
        let result = self.deliver(Topic::Patch, sequence, || {
            let mut sample = outbox
                .publisher
                .loan_slice_uninit(records.len())
                .map_err(|e| loan_error(&outbox.name, records.len(), e))?;
            *sample.user_header_mut() = header;
            sample
                .write_from_slice(records)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::Patch, result)?;
        Ok(self.account_patch(sequence, delivered, records.len(), size_of_val(records)))
    }

    /// Publishes a patch of `count` records built in place in shared memory by `build(i)`: no
    /// copy of a finished buffer (zero-copy when the producer computes records on the fly).
    /// `build` runs again for a re-send after a full queue, so it must be repeatable.
    pub fn send_patch_with(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        count: usize,
        mut build: impl FnMut(usize) -> GaussianRecord,
    ) -> Result<SendReport, TransportError> {
        let (sequence, header) = self.next_patch_header(keyframe_id, frame, count);
        let outbox = &self.patch;
        let result = self.deliver(Topic::Patch, sequence, || {
            let mut sample = outbox
                .publisher
                .loan_slice_uninit(count)
                .map_err(|e| loan_error(&outbox.name, count, e))?;
            *sample.user_header_mut() = header;
            sample
                .write_from_fn(&mut build)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::Patch, result)?;
        Ok(self.account_patch(sequence, delivered, count, 0))
    }

    fn next_patch_header(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        count: usize,
    ) -> (u64, PatchHeader) {
        let sequence = self.patch.take_sequence();
        let header = PatchHeader {
            stamp: self.stamp(sequence),
            keyframe_id,
            count: count as u64,
            frame: frame as u32,
            reserved: 0,
        };
        (sequence, header)
    }

    fn account_patch(
        &mut self,
        sequence: u64,
        delivered: usize,
        count: usize,
        copied: usize,
    ) -> SendReport {
        let bytes = count * size_of::<GaussianRecord>() + size_of::<PatchHeader>();
        self.account_sent(Topic::Patch, bytes, copied);
        SendReport {
            sequence,
            recipients: delivered,
            bytes,
        }
    }

    /// Publishes a keyframe's RGB-D image by copying `pixels` (row-major, `width * height` of
    /// them) into shared memory (one copy). Refuses an empty image, a pixel count that does not
    /// match the size, intrinsics of another size and an invalid pose
    /// ([`TransportError::InvalidMessage`]).
    pub fn send_keyframe_image(
        &mut self,
        meta: &KeyframeImageMeta,
        pixels: &[RgbdPixel],
    ) -> Result<SendReport, TransportError> {
        validate_keyframe_image(&self.keyframe_image.name, meta, pixels.len())?;
        let (sequence, header) = self.next_keyframe_image_header(meta);
        let outbox = &self.keyframe_image;
        let result = self.deliver(Topic::KeyframeImage, sequence, || {
            let mut sample = outbox
                .publisher
                .loan_slice_uninit(pixels.len())
                .map_err(|e| loan_error(&outbox.name, pixels.len(), e))?;
            *sample.user_header_mut() = header;
            sample
                .write_from_slice(pixels)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::KeyframeImage, result)?;
        Ok(self.account_keyframe_image(sequence, delivered, pixels.len(), size_of_val(pixels)))
    }

    /// Publishes a keyframe image whose `width * height` pixels are built in place in shared
    /// memory by `build(i)` (`i` row-major): no intermediate interleaved buffer when the agent
    /// holds colour and depth in separate images. `build` runs again for a re-send after a full
    /// queue, so it must be repeatable. Validated like [`AgentLink::send_keyframe_image`].
    pub fn send_keyframe_image_with(
        &mut self,
        meta: &KeyframeImageMeta,
        mut build: impl FnMut(usize) -> RgbdPixel,
    ) -> Result<SendReport, TransportError> {
        let count = meta.width as usize * meta.height as usize;
        validate_keyframe_image(&self.keyframe_image.name, meta, count)?;
        let (sequence, header) = self.next_keyframe_image_header(meta);
        let outbox = &self.keyframe_image;
        let result = self.deliver(Topic::KeyframeImage, sequence, || {
            let mut sample = outbox
                .publisher
                .loan_slice_uninit(count)
                .map_err(|e| loan_error(&outbox.name, count, e))?;
            *sample.user_header_mut() = header;
            sample
                .write_from_fn(&mut build)
                .send()
                .map_err(|e| send_error(&outbox.name, e))
        });
        let delivered = self.count_full_queue(Topic::KeyframeImage, result)?;
        Ok(self.account_keyframe_image(sequence, delivered, count, 0))
    }

    fn next_keyframe_image_header(
        &mut self,
        meta: &KeyframeImageMeta,
    ) -> (u64, KeyframeImageHeader) {
        let sequence = self.keyframe_image.take_sequence();
        let header = KeyframeImageHeader {
            stamp: self.stamp(sequence),
            keyframe_id: meta.keyframe_id,
            frame_index: meta.frame_index,
            timestamp_s: meta.timestamp_s,
            camera_to_agent_world: meta.camera_to_agent_world,
            intrinsics: meta.intrinsics,
            width: meta.width,
            height: meta.height,
        };
        (sequence, header)
    }

    fn account_keyframe_image(
        &mut self,
        sequence: u64,
        delivered: usize,
        count: usize,
        copied: usize,
    ) -> SendReport {
        let bytes = count * size_of::<RgbdPixel>() + size_of::<KeyframeImageHeader>();
        self.account_sent(Topic::KeyframeImage, bytes, copied);
        SendReport {
            sequence,
            recipients: delivered,
            bytes,
        }
    }

    /// Next pending correction, without blocking.
    pub fn try_recv_correction(&mut self) -> Result<Option<CorrectionSample>, TransportError> {
        loop {
            let Some(sample) =
                self.correction_subscriber
                    .receive()
                    .map_err(|e| TransportError::Receive {
                        service: self.correction_name.clone(),
                        reason: format!("{e:?}"),
                    })?
            else {
                return Ok(None);
            };
            let header = *sample.user_header();
            if header.count != sample.payload().len() as u64
                || header.target_agent_id != self.agent_id
            {
                return Err(TransportError::Malformed {
                    service: self.correction_name.clone(),
                    reason: format!(
                        "header says {} poses for agent {}, slice has {} (this is agent {})",
                        header.count,
                        header.target_agent_id,
                        sample.payload().len(),
                        self.agent_id
                    ),
                });
            }
            let bytes = size_of_val(sample.payload()) + size_of::<CorrectionHeader>();
            if let Some(delivery) = self.book.admit(
                &mut self.traffic,
                header.stamp,
                Topic::Correction,
                bytes,
                self.agent_id,
            ) {
                return Ok(Some(CorrectionSample { sample, delivery }));
            }
        }
    }

    /// Waits (event-driven) up to `timeout` for a correction.
    pub fn recv_correction_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<CorrectionSample>, TransportError> {
        receive_within(self, timeout, Self::try_recv_correction)
    }

    /// Next pending control message, without blocking. A frame that does not decode (another
    /// codec format version, corruption) is consumed and reported as
    /// [`TransportError::ControlFrame`]; the next call goes on with the following one.
    pub fn try_recv_control(&mut self) -> Result<Option<ControlSample>, TransportError> {
        loop {
            let Some(sample) =
                self.control_subscriber
                    .receive()
                    .map_err(|e| TransportError::Receive {
                        service: self.control_name.clone(),
                        reason: format!("{e:?}"),
                    })?
            else {
                return Ok(None);
            };
            let header = *sample.user_header();
            let frame = sample.payload();
            if header.frame_len != frame.len() as u64 || header.target_agent_id != self.agent_id {
                return Err(TransportError::Malformed {
                    service: self.control_name.clone(),
                    reason: format!(
                        "header says a {}-byte frame for agent {}, slice has {} bytes (this is \
                         agent {})",
                        header.frame_len,
                        header.target_agent_id,
                        frame.len(),
                        self.agent_id
                    ),
                });
            }
            let bytes = frame.len() + size_of::<ControlHeader>();
            let Some(delivery) = self.book.admit(
                &mut self.traffic,
                header.stamp,
                Topic::Control,
                bytes,
                self.agent_id,
            ) else {
                continue;
            };
            let message = codec::decode::<ControlMessage>(frame).map_err(|source| {
                TransportError::ControlFrame {
                    service: self.control_name.clone(),
                    sequence: header.stamp.sequence,
                    source,
                }
            })?;
            return Ok(Some(ControlSample {
                header,
                message,
                delivery,
            }));
        }
    }

    /// Waits (event-driven) up to `timeout` for a control message.
    pub fn recv_control_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<ControlSample>, TransportError> {
        receive_within(self, timeout, Self::try_recv_control)
    }

    /// Bytes and messages per topic sent (and corrections received) since [`AgentLink::open`].
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

impl_receiving!(AgentLink);

impl Drop for AgentLink {
    fn drop(&mut self) {
        // Best effort and short (one wait slice), since drop must not hang: consumers learn of
        // the stop. `close()` is the orderly path that also waits for them to drain.
        if !self.said_goodbye
            && self.lifecycle.attached() > 0
            && let Err(e) = self.goodbye(self.config.wait_slice)
        {
            tracing::warn!(agent_id = self.agent_id, error = %e, "goodbye on drop failed");
        }
    }
}

/// Receive side of one agent's topics, held by a consumer.
struct AgentInbox {
    descriptor_name: String,
    descriptor: Subscriber<Ipc, KeyframeDescriptor, ()>,
    patch_name: String,
    patch: Subscriber<Ipc, [GaussianRecord], PatchHeader>,
    keyframe_image_name: String,
    keyframe_image: Subscriber<Ipc, [RgbdPixel], KeyframeImageHeader>,
    correction: Outbox<[KeyframePose], CorrectionHeader>,
    control: Outbox<[u8], ControlHeader>,
    wake: Notifier<Ipc>,
    _descriptor_service: PubSubService<Ipc, KeyframeDescriptor, ()>,
    _patch_service: PubSubService<Ipc, [GaussianRecord], PatchHeader>,
    _keyframe_image_service: PubSubService<Ipc, [RgbdPixel], KeyframeImageHeader>,
    _wake_service: EventService<Ipc>,
}

/// The transport endpoint of the consensus (or any observer of the swarm).
pub struct ConsumerLink {
    config: TransportConfig,
    epoch: u64,
    agents: Vec<AgentInbox>,
    lifecycle_name: String,
    lifecycle: Subscriber<Ipc, Lifecycle, ()>,
    wake_listener: Listener<Ipc>,
    traffic: TrafficTable,
    book: ReceiveBook,
    /// Round-robin start of the next receive scan, so no agent starves the others.
    cursor: usize,
    /// Goodbyes held back until their agent's data topics are drained.
    deferred_goodbyes: Vec<LifecycleSample>,
    shutdown: Arc<AtomicBool>,
    /// When this link last sent or received a message: receives poll while it is recent.
    last_activity: Instant,
    _lifecycle_service: PubSubService<Ipc, Lifecycle, ()>,
    _wake_service: EventService<Ipc>,
    _node: Node<Ipc>,
}

impl_receiving!(ConsumerLink);

impl ConsumerLink {
    /// Subscribes to every agent id `0..max_agents` and tells running agents that a consumer
    /// attached (so their pending sends proceed).
    pub fn open(config: &TransportConfig) -> Result<Self, TransportError> {
        config.validate()?;
        let names = config.names();
        let node = create_node(&format!("mac-consumer-{}", std::process::id()))?;
        // The swarm's own range may differ from ours; we listen to exactly 0..max_agents.
        let (lifecycle_service, _swarm_max_agents) = LifecycleService::open(&node, config)?;
        let lifecycle_name = names.lifecycle();
        let lifecycle = lifecycle_service
            .subscriber_builder()
            .buffer_size(config.lifecycle_queue_depth)
            .create()
            .map_err(|e| port_error(&lifecycle_name, "subscriber", e))?;
        let wake_service = open_consumers_wake(&node, config)?;
        let wake_listener = wake_service
            .listener_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "listener", e))?;

        let mut agents = Vec::with_capacity(config.max_agents as usize);
        for agent_id in 0..config.max_agents {
            let descriptor_service = DescriptorService::open(&node, config, agent_id)?;
            let descriptor_name = names.descriptor(agent_id);
            let descriptor = descriptor_service
                .subscriber_builder()
                .buffer_size(config.descriptor_queue_depth)
                .create()
                .map_err(|e| port_error(&descriptor_name, "subscriber", e))?;
            let patch_service = PatchService::open(&node, config, agent_id)?;
            let patch_name = names.patch(agent_id);
            let patch = patch_service
                .subscriber_builder()
                .buffer_size(config.patch_queue_depth)
                .create()
                .map_err(|e| port_error(&patch_name, "subscriber", e))?;
            let keyframe_image_service = KeyframeImageService::open(&node, config, agent_id)?;
            let keyframe_image_name = names.keyframe_image(agent_id);
            let keyframe_image = keyframe_image_service
                .subscriber_builder()
                .buffer_size(config.keyframe_image_queue_depth)
                .create()
                .map_err(|e| port_error(&keyframe_image_name, "subscriber", e))?;
            let correction_service = CorrectionService::open(&node, config, agent_id)?;
            let correction_name = names.correction(agent_id);
            let correction_publisher = correction_service
                .publisher_builder()
                .max_loaned_samples(PUBLISHER_MAX_LOANS)
                .initial_max_slice_len(config.initial_correction_poses)
                .allocation_strategy(AllocationStrategy::PowerOfTwo)
                .backpressure_strategy(BackpressureStrategy::DiscardData)
                .create()
                .map_err(|e| port_error(&correction_name, "publisher", e))?;
            let control_service = ControlService::open(&node, config, agent_id)?;
            let control_name = names.control(agent_id);
            let control_publisher = control_service
                .publisher_builder()
                .max_loaned_samples(PUBLISHER_MAX_LOANS)
                .initial_max_slice_len(config.initial_control_bytes)
                .allocation_strategy(AllocationStrategy::PowerOfTwo)
                .backpressure_strategy(BackpressureStrategy::DiscardData)
                .create()
                .map_err(|e| port_error(&control_name, "publisher", e))?;
            let agent_wake_service = open_agent_wake(&node, config, agent_id)?;
            let wake = agent_wake_service
                .notifier_builder()
                .create()
                .map_err(|e| port_error(&names.agent_wake(agent_id), "notifier", e))?;
            agents.push(AgentInbox {
                descriptor_name,
                descriptor,
                patch_name,
                patch,
                keyframe_image_name,
                keyframe_image,
                correction: Outbox {
                    name: correction_name,
                    service: correction_service,
                    publisher: correction_publisher,
                    next_sequence: 0,
                },
                control: Outbox {
                    name: control_name,
                    service: control_service,
                    publisher: control_publisher,
                    next_sequence: 0,
                },
                wake,
                _descriptor_service: descriptor_service,
                _patch_service: patch_service,
                _keyframe_image_service: keyframe_image_service,
                _wake_service: agent_wake_service,
            });
        }
        // Only now are all subscribers registered: wake agents blocked in their handshake.
        for inbox in &agents {
            if let Err(e) = inbox
                .wake
                .notify_with_custom_event_id(EventId::new(WAKE_CONSUMER_ATTACHED))
            {
                tracing::warn!(error = ?e, "could not wake an agent after attaching");
            }
        }
        Ok(Self {
            config: config.clone(),
            epoch: new_epoch(),
            agents,
            lifecycle_name,
            lifecycle,
            wake_listener,
            traffic: TrafficTable::new(),
            book: ReceiveBook::default(),
            cursor: 0,
            deferred_goodbyes: Vec::new(),
            shutdown: Arc::new(AtomicBool::new(false)),
            last_activity: Instant::now(),
            _lifecycle_service: lifecycle_service,
            _wake_service: wake_service,
            _node: node,
        })
    }

    /// See [`AgentLink::shutdown_handle`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.shutdown)
    }

    /// Next pending message of any agent, without blocking. Lifecycle messages come first, so
    /// an agent's hello is handled before the data it sent after it (the consensus needs a
    /// restarted agent's run anchor before its first keyframe); they are few and small. The
    /// data sources are scanned round-robin. An agent's `Goodbye` comes after all data it sent
    /// before it.
    pub fn try_recv(&mut self) -> Result<Option<Incoming>, TransportError> {
        if let Some(goodbye) = self.take_drained_goodbye()? {
            return Ok(Some(Incoming::Lifecycle(goodbye)));
        }
        if let Some(lifecycle) = self.receive_lifecycle()? {
            return Ok(Some(lifecycle));
        }
        // Data sources: (descriptor, keyframe image, patch) of each agent. The image comes
        // before the patch of the same keyframe, as an agent sends them.
        let sources = AGENT_SOURCES * self.agents.len();
        for step in 0..sources {
            let source = (self.cursor + step) % sources;
            let agent = source / AGENT_SOURCES;
            let received = match source % AGENT_SOURCES {
                0 => self.receive_descriptor(agent)?,
                1 => self.receive_keyframe_image(agent)?,
                _ => self.receive_patch(agent)?,
            };
            if let Some(incoming) = received {
                self.cursor = (source + 1) % sources;
                return Ok(Some(incoming));
            }
        }
        Ok(None)
    }

    /// Waits (event-driven) up to `timeout` for the next message.
    pub fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Incoming>, TransportError> {
        receive_within(self, timeout, Self::try_recv)
    }

    /// Whether agent `agent_id` still has queued data (this also maps the memory of its
    /// publishers, after which their samples survive the publisher's exit).
    fn agent_has_data(&self, agent_id: u32) -> Result<bool, TransportError> {
        let inbox = &self.agents[agent_id as usize];
        let pending = |name: &str, result: Result<bool, _>| {
            result.map_err(|e| TransportError::Receive {
                service: name.to_string(),
                reason: format!("{e:?}"),
            })
        };
        Ok(
            pending(&inbox.descriptor_name, inbox.descriptor.has_samples())?
                || pending(
                    &inbox.keyframe_image_name,
                    inbox.keyframe_image.has_samples(),
                )?
                || pending(&inbox.patch_name, inbox.patch.has_samples())?,
        )
    }

    /// Tells the agent its goodbye was seen after its data was drained (it may exit now).
    fn acknowledge_goodbye(&self, agent_id: u32) {
        let wake = &self.agents[agent_id as usize].wake;
        if let Err(e) = wake.notify_with_custom_event_id(EventId::new(WAKE_GOODBYE_SEEN)) {
            tracing::warn!(error = ?e, agent_id, "could not acknowledge a goodbye");
        }
    }

    fn take_drained_goodbye(&mut self) -> Result<Option<LifecycleSample>, TransportError> {
        for i in 0..self.deferred_goodbyes.len() {
            let agent_id = self.deferred_goodbyes[i].stamp.agent_id;
            if !self.agent_has_data(agent_id)? {
                self.acknowledge_goodbye(agent_id);
                return Ok(Some(self.deferred_goodbyes.remove(i)));
            }
        }
        Ok(None)
    }

    fn receive_lifecycle(&mut self) -> Result<Option<Incoming>, TransportError> {
        loop {
            let Some(sample) = self
                .lifecycle
                .receive()
                .map_err(|e| TransportError::Receive {
                    service: self.lifecycle_name.clone(),
                    reason: format!("{e:?}"),
                })?
            else {
                return Ok(None);
            };
            let stamp = sample.payload().stamp;
            if stamp.agent_id >= self.config.max_agents {
                return Err(TransportError::Malformed {
                    service: self.lifecycle_name.clone(),
                    reason: format!(
                        "sender agent id {} is outside 0..{}",
                        stamp.agent_id, self.config.max_agents
                    ),
                });
            }
            let Some(delivery) = self.book.admit(
                &mut self.traffic,
                stamp,
                Topic::Lifecycle,
                size_of::<Lifecycle>(),
                stamp.agent_id,
            ) else {
                continue;
            };
            let received = LifecycleSample {
                message: *sample.payload(),
                delivery,
            };
            drop(sample);
            if received.kind() == Ok(LifecycleKind::Goodbye) {
                if self.agent_has_data(stamp.agent_id)? {
                    self.deferred_goodbyes.push(received);
                    continue;
                }
                self.acknowledge_goodbye(stamp.agent_id);
            }
            return Ok(Some(Incoming::Lifecycle(received)));
        }
    }

    fn receive_descriptor(&mut self, agent: usize) -> Result<Option<Incoming>, TransportError> {
        let inbox = &self.agents[agent];
        loop {
            let Some(sample) = inbox
                .descriptor
                .receive()
                .map_err(|e| TransportError::Receive {
                    service: inbox.descriptor_name.clone(),
                    reason: format!("{e:?}"),
                })?
            else {
                return Ok(None);
            };
            let stamp = sample.payload().stamp;
            if stamp.agent_id as usize != agent {
                return Err(TransportError::Malformed {
                    service: inbox.descriptor_name.clone(),
                    reason: format!(
                        "stamp names agent {} on agent {agent}'s topic",
                        stamp.agent_id
                    ),
                });
            }
            let bytes = size_of::<KeyframeDescriptor>();
            if let Some(delivery) = self.book.admit(
                &mut self.traffic,
                stamp,
                Topic::Descriptor,
                bytes,
                stamp.agent_id,
            ) {
                return Ok(Some(Incoming::Descriptor(DescriptorSample {
                    sample,
                    delivery,
                })));
            }
        }
    }

    fn receive_patch(&mut self, agent: usize) -> Result<Option<Incoming>, TransportError> {
        let inbox = &self.agents[agent];
        loop {
            let Some(sample) = inbox.patch.receive().map_err(|e| TransportError::Receive {
                service: inbox.patch_name.clone(),
                reason: format!("{e:?}"),
            })?
            else {
                return Ok(None);
            };
            let header = *sample.user_header();
            let len = sample.payload().len();
            if header.stamp.agent_id as usize != agent
                || header.count != len as u64
                || header.frame().is_err()
            {
                return Err(TransportError::Malformed {
                    service: inbox.patch_name.clone(),
                    reason: format!(
                        "header (agent {}, count {}, frame tag {}) does not match agent {agent}'s slice of {len}",
                        header.stamp.agent_id, header.count, header.frame
                    ),
                });
            }
            let bytes = size_of_val(sample.payload()) + size_of::<PatchHeader>();
            if let Some(delivery) = self.book.admit(
                &mut self.traffic,
                header.stamp,
                Topic::Patch,
                bytes,
                header.stamp.agent_id,
            ) {
                return Ok(Some(Incoming::Patch(PatchSample { sample, delivery })));
            }
        }
    }

    fn receive_keyframe_image(&mut self, agent: usize) -> Result<Option<Incoming>, TransportError> {
        let inbox = &self.agents[agent];
        loop {
            let Some(sample) =
                inbox
                    .keyframe_image
                    .receive()
                    .map_err(|e| TransportError::Receive {
                        service: inbox.keyframe_image_name.clone(),
                        reason: format!("{e:?}"),
                    })?
            else {
                return Ok(None);
            };
            let header = *sample.user_header();
            let len = sample.payload().len();
            // The sender validates all of this; a mismatch here is corruption or a foreign
            // sender, and reading pixels with the wrong size would scramble every row.
            if header.stamp.agent_id as usize != agent
                || header.pixel_count() != len as u64
                || len == 0
                || (header.intrinsics.width, header.intrinsics.height)
                    != (header.width, header.height)
            {
                return Err(TransportError::Malformed {
                    service: inbox.keyframe_image_name.clone(),
                    reason: format!(
                        "header (agent {}, {}x{} image, intrinsics for {}x{}) does not match \
                         agent {agent}'s slice of {len} pixels",
                        header.stamp.agent_id,
                        header.width,
                        header.height,
                        header.intrinsics.width,
                        header.intrinsics.height
                    ),
                });
            }
            let bytes = size_of_val(sample.payload()) + size_of::<KeyframeImageHeader>();
            if let Some(delivery) = self.book.admit(
                &mut self.traffic,
                header.stamp,
                Topic::KeyframeImage,
                bytes,
                header.stamp.agent_id,
            ) {
                return Ok(Some(Incoming::KeyframeImage(KeyframeImageSample {
                    sample,
                    delivery,
                })));
            }
        }
    }

    /// Sends a correction to agent `agent_id`. An agent that is not attached is never waited
    /// for ([`TransportError::Undelivered`]). A full queue of the agent's: with the default
    /// [`FullQueuePolicy::NewestWins`] the correction replaces the oldest queued one at once
    /// (the consensus never waits on a slow agent); with `Block` the send waits up to
    /// `full_queue_timeout`, then fails with [`TransportError::QueueFull`].
    pub fn send_correction(
        &mut self,
        agent_id: u32,
        agent_world_to_world: Pose,
        poses: &[KeyframePose],
    ) -> Result<SendReport, TransportError> {
        let epoch = self.epoch;
        let outbox = &mut self.inbox_mut(agent_id)?.correction;
        validate_pose(&outbox.name, "agent_world_to_world", &agent_world_to_world)?;
        if let Some(bad) = poses
            .iter()
            .find(|p| !p.camera_to_world.is_valid(POSE_NORM_TOLERANCE))
        {
            validate_pose(
                &outbox.name,
                &format!("keyframe {} pose", bad.keyframe_id),
                &bad.camera_to_world,
            )?;
        }
        let sequence = outbox.take_sequence();
        let header = CorrectionHeader {
            stamp: Stamp {
                agent_id: CONSUMER_AGENT_ID,
                reserved: 0,
                epoch,
                sequence,
            },
            target_agent_id: agent_id,
            reserved: 0,
            agent_world_to_world,
            count: poses.len() as u64,
        };
        let outbox = &self.agents[agent_id as usize].correction;
        let result = self.deliver_to_agent(
            agent_id,
            Topic::Correction,
            sequence,
            outbox,
            WAKE_CORRECTION,
            || {
                let mut sample = outbox
                    .publisher
                    .loan_slice_uninit(poses.len())
                    .map_err(|e| loan_error(&outbox.name, poses.len(), e))?;
                *sample.user_header_mut() = header;
                sample
                    .write_from_slice(poses)
                    .send()
                    .map_err(|e| send_error(&outbox.name, e))
            },
        );
        let bytes = size_of_val(poses) + size_of::<CorrectionHeader>();
        self.account_to_agent(agent_id, Topic::Correction, sequence, result, bytes)
    }

    /// Sends a control message to agent `agent_id` as one [`crate::codec`] frame (encoded here;
    /// an unencodable or oversized message is [`TransportError::InvalidMessage`]). Full queues
    /// follow `full_queue.control` (default `Block`, bounded by `full_queue_timeout`); an agent
    /// that is not attached is never waited for ([`TransportError::Undelivered`]).
    pub fn send_control(
        &mut self,
        agent_id: u32,
        message: &ControlMessage,
    ) -> Result<SendReport, TransportError> {
        let outbox = &self.inbox_mut(agent_id)?.control;
        let frame = codec::encode(message).map_err(|e| TransportError::InvalidMessage {
            service: outbox.name.clone(),
            reason: e.to_string(),
        })?;
        self.send_control_frame(agent_id, &frame)
    }

    /// Sends an already encoded codec frame on agent `agent_id`'s control topic.
    fn send_control_frame(
        &mut self,
        agent_id: u32,
        frame: &[u8],
    ) -> Result<SendReport, TransportError> {
        let epoch = self.epoch;
        let outbox = &mut self.inbox_mut(agent_id)?.control;
        let sequence = outbox.take_sequence();
        let header = ControlHeader {
            stamp: Stamp {
                agent_id: CONSUMER_AGENT_ID,
                reserved: 0,
                epoch,
                sequence,
            },
            target_agent_id: agent_id,
            reserved: 0,
            frame_len: frame.len() as u64,
        };
        let outbox = &self.agents[agent_id as usize].control;
        let result = self.deliver_to_agent(
            agent_id,
            Topic::Control,
            sequence,
            outbox,
            WAKE_CONTROL,
            || {
                let mut sample = outbox
                    .publisher
                    .loan_slice_uninit(frame.len())
                    .map_err(|e| loan_error(&outbox.name, frame.len(), e))?;
                *sample.user_header_mut() = header;
                sample
                    .write_from_slice(frame)
                    .send()
                    .map_err(|e| send_error(&outbox.name, e))
            },
        );
        let bytes = frame.len() + size_of::<ControlHeader>();
        self.account_to_agent(agent_id, Topic::Control, sequence, result, bytes)
    }

    fn inbox_mut(&mut self, agent_id: u32) -> Result<&mut AgentInbox, TransportError> {
        let max_agents = self.config.max_agents;
        self.agents
            .get_mut(agent_id as usize)
            .ok_or(TransportError::AgentIdOutOfRange {
                agent_id,
                max_agents,
            })
    }

    /// Sends one consumer -> agent message with `send_once` (loan, fill, send; the same
    /// sequence every time) under the topic's [`FullQueuePolicy`], then wakes the agent with
    /// `wake_event`. An agent that is not attached is not waited for.
    fn deliver_to_agent<P: Debug + IceoryxSend + ?Sized + 'static, H: Debug + ZeroCopySend>(
        &self,
        agent_id: u32,
        topic: Topic,
        sequence: u64,
        outbox: &Outbox<P, H>,
        wake_event: usize,
        mut send_once: impl FnMut() -> Result<usize, TransportError>,
    ) -> Result<usize, TransportError> {
        let policy = self.config.full_queue.of(topic);
        let wake = &self.agents[agent_id as usize].wake;
        let wake_agent = || {
            if let Err(e) = wake.notify_with_custom_event_id(EventId::new(wake_event)) {
                tracing::warn!(error = ?e, agent_id, %topic, "could not wake agent");
            }
        };
        let start = Instant::now();
        loop {
            let delivered = send_once()?;
            if delivered >= AGENT_RECIPIENTS {
                wake_agent();
                return Ok(delivered);
            }
            // Not attached (or NewestWins, whose queue is never full): nothing to wait for.
            if policy == FullQueuePolicy::NewestWins || outbox.attached() == 0 {
                check_recipients(&outbox.name, sequence, delivered, AGENT_RECIPIENTS)?;
            }
            let waited = start.elapsed();
            if waited >= self.config.full_queue_timeout {
                return Err(TransportError::QueueFull {
                    service: outbox.name.clone(),
                    topic,
                    sequence,
                    delivered,
                    required: AGENT_RECIPIENTS,
                    waited,
                });
            }
            if self.shutdown.load(Ordering::Relaxed) {
                return Err(TransportError::ShutdownRequested);
            }
            // The agent may be asleep with a full queue: wake it, then give it time to read.
            wake_agent();
            std::thread::sleep(FULL_QUEUE_RETRY);
        }
    }

    /// Counts a consumer -> agent send (or its `QueueFull` failure) and builds the report.
    fn account_to_agent(
        &mut self,
        agent_id: u32,
        topic: Topic,
        sequence: u64,
        result: Result<usize, TransportError>,
        bytes: usize,
    ) -> Result<SendReport, TransportError> {
        let row = self.traffic.row(agent_id, topic, Direction::Sent);
        match result {
            Ok(recipients) => {
                self.last_activity = Instant::now();
                row.messages += 1;
                row.bytes += bytes as u64;
                row.bytes_copied += bytes as u64;
                Ok(SendReport {
                    sequence,
                    recipients,
                    bytes,
                })
            }
            Err(error) => {
                if matches!(error, TransportError::QueueFull { .. }) {
                    row.full_queue_failures += 1;
                }
                Err(error)
            }
        }
    }

    /// Received traffic per agent and topic (and corrections sent) since [`ConsumerLink::open`].
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequence_tracker_classifies_order_gaps_restarts_and_stale() {
        let mut tracker = SequenceTracker::default();
        assert!(matches!(
            tracker.observe(10, 0),
            Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: None,
                missed: 0
            })
        ));
        assert!(matches!(
            tracker.observe(10, 1),
            Verdict::Deliver(Delivery::InOrder)
        ));
        assert!(matches!(
            tracker.observe(10, 4),
            Verdict::Deliver(Delivery::Gap { missed: 2 })
        ));
        assert!(matches!(tracker.observe(10, 4), Verdict::Duplicate));
        assert!(matches!(tracker.observe(10, 3), Verdict::Duplicate));
        assert!(matches!(
            tracker.observe(20, 0),
            Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: Some(10),
                missed: 0
            })
        ));
        assert!(matches!(tracker.observe(10, 5), Verdict::Stale));
        assert!(matches!(
            tracker.observe(20, 1),
            Verdict::Deliver(Delivery::InOrder)
        ));
    }

    #[test]
    fn config_validation_names_the_problem() {
        let mut config = TransportConfig::with_namespace("unit");
        config.required_consumers = config.max_consumers + 1;
        let err = config.validate().unwrap_err();
        assert!(err.to_string().contains("required_consumers"), "{err}");
        let zero_agents = TransportConfig {
            max_agents: 0,
            ..TransportConfig::default()
        };
        assert!(zero_agents.validate().is_err());
        let no_image_queue = TransportConfig {
            keyframe_image_queue_depth: 0,
            ..TransportConfig::default()
        };
        assert!(no_image_queue.validate().is_err());
        let poll_longer_than_a_wait = TransportConfig {
            poll_before_wait: Duration::from_millis(50),
            wait_slice: Duration::from_millis(50),
            ..TransportConfig::default()
        };
        let err = poll_longer_than_a_wait.validate().unwrap_err();
        assert!(err.to_string().contains("poll_before_wait"), "{err}");
        assert!(TransportConfig::default().validate().is_ok());
    }

    /// A control frame of another codec format version (an agent built from other sources) is
    /// refused on receive with an error naming the topic and both versions, and the frames
    /// after it are still received in order.
    #[test]
    fn control_frame_of_another_format_version_is_refused_clearly() {
        let config = TransportConfig::with_namespace(format!("unit-ctlver-{}", std::process::id()));
        let mut consumer = ConsumerLink::open(&config).unwrap();
        let mut agent = AgentLink::open(&config, 0).unwrap();
        let message = ControlMessage::Shutdown {
            reason: "test".into(),
        };
        let mut frame = codec::encode(&message).unwrap();
        let foreign_version = codec::FORMAT_VERSION + 1;
        frame[4..6].copy_from_slice(&foreign_version.to_le_bytes());
        consumer.send_control_frame(0, &frame).unwrap();
        consumer.send_control(0, &message).unwrap();
        let timeout = Duration::from_secs(2);
        match agent.recv_control_timeout(timeout) {
            Err(
                err @ TransportError::ControlFrame {
                    sequence: 0,
                    source: CodecError::UnsupportedVersion { .. },
                    ..
                },
            ) => {
                let text = err.to_string();
                assert!(text.contains(&config.names().control(0)), "{text}");
                assert!(
                    text.contains(&format!("version {foreign_version}"))
                        && text.contains(&format!("version {}", codec::FORMAT_VERSION)),
                    "{text}"
                );
            }
            other => panic!("expected a ControlFrame error, got {other:?}"),
        }
        let next = agent.recv_control_timeout(timeout).unwrap().unwrap();
        assert_eq!(next.message, message);
        assert_eq!(next.header.stamp.sequence, 1);
        assert_eq!(next.delivery, Delivery::InOrder);
    }

    #[test]
    fn agent_id_out_of_range_is_refused_before_touching_shared_memory() {
        let config = TransportConfig {
            max_agents: 2,
            ..TransportConfig::with_namespace("unit-range")
        };
        match AgentLink::open(&config, 2) {
            Err(TransportError::AgentIdOutOfRange {
                agent_id: 2,
                max_agents: 2,
            }) => {}
            Err(other) => panic!("unexpected error {other}"),
            Ok(_) => panic!("agent id 2 must be refused with max_agents 2"),
        }
    }
}
