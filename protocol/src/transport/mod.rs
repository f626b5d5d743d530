//! Typed transport over iceoryx2 0.10 (`ipc::Service`) between agents and consumers.
//!
//! Two endpoints: [`AgentLink`] (one per agent process: publishes descriptors, patches, keyframe
//! RGB-D images and lifecycle messages, receives corrections and control messages) and
//! [`ConsumerLink`] (the consensus or an observer: receives from every agent id
//! `0..max_agents`, publishes corrections and control messages).
//!
//! Control messages ([`ControlMessage`](crate::messages::ControlMessage), heap data) travel
//! consumer -> agent on the `control` topic as one [`crate::codec`] frame in a byte slice behind
//! a [`ControlHeader`](crate::messages::ControlHeader), with the same stamps, gap detection and
//! accounting as every topic; a frame of another format version is refused on receive
//! ([`TransportError::ControlFrame`]). The agent -> consensus direction has no control topic:
//! everything an agent says fits the typed topics.
//!
//! Modules, one concept each:
//! - `config`: [`TransportConfig`] and the [`FullQueuePolicy`] per topic.
//! - `error`: [`TransportError`].
//! - `topic`: each topic's payload and header types, so a port on the wrong types does not
//!   compile.
//! - `open`: the node and every service, with limits from the config; one generic opener for
//!   all publish-subscribe topics, the shared services sized by the agent count.
//! - `outbox`: the one send path (delivery handshake, full-queue policy, re-sends).
//! - `inbox`: the one receive path (header checks, sequence rules, accounting).
//! - `checks`: what a message must satisfy on send and on receive.
//! - `sequence`: stamps, gaps, restarts ([`Delivery`]).
//! - `wake`: wake-up events, and how a receive polls and then blocks.
//! - `traffic`: bandwidth accounting ([`BandwidthReport`]).
//! - `samples`: what receivers get ([`Incoming`] and one sample type per topic).
//! - `agent`, `consumer`: the two endpoints.
//! - [`relay`]: ports that stand in for processes on other hosts (the cross-host bridge).
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
//! - **Sequence numbers and restarts.** Every message carries a
//!   [`Stamp`](crate::messages::Stamp): an incarnation epoch (start time in ns) and a per-topic
//!   sequence from 0. Receivers report gaps and accept a larger epoch as a restart (sequence from
//!   0 again); messages of an older epoch are dropped. A consumer takes lifecycle messages before
//!   data, so a (re)started agent's hello, with its run anchor, is handled before the keyframes
//!   it sent after it.
//! - **Crash safety.** Each link creates its own node with dead-node clean-up on creation and
//!   also calls `try_cleanup_dead_nodes()` explicitly (and on every heartbeat), so shared memory
//!   left by a SIGKILLed process (/dev/shm/iox2_*, /tmp/iceoryx2) is reclaimed by the next start.
//! - **Large patches and images.** Patch, keyframe-image, correction and control publishers use
//!   dynamic data segments with power-of-two growth from `initial_patch_records`,
//!   `initial_keyframe_image_pixels`, `initial_correction_poses` and `initial_control_bytes`, so
//!   any size that fits in memory can be sent (tested with 1,000,000 records and 640x480
//!   images).
//! - **No busy waiting, but a short poll before sleeping** (`wake`). Receivers block on an
//!   iceoryx2 event listener, woken by the sender's notification after each send; for
//!   `poll_before_wait` after its last message a receive polls its queues first, which catches
//!   the next message of a burst without paying for a wake-up.
//! - **Early notice for large messages.** Before it builds a patch or a keyframe image in shared
//!   memory, an agent already notifies the consumers ([`Topic::is_bulk`](crate::services::Topic::is_bulk));
//!   a wake-up counts as activity, so a consumer that was asleep polls until the message is
//!   sent. Its wake-up overlaps the copy instead of following it. Before blocking, a receiver
//!   discards the notifications of messages it already took while polling, so that a stale
//!   notification does not wake it for nothing.
//! - **Full queues: a policy per topic** ([`FullQueuePolicy`], [`TransportConfig::full_queue`]).
//!   `Block` (descriptors, keyframe images, patches, control; lifecycle always): the queue never
//!   overwrites, so nothing is lost silently; the sender re-sends until the required receivers
//!   have the message, up to `full_queue_timeout` ([`TransportError::QueueFull`], counted in
//!   [`TopicTraffic::full_queue_failures`]). `NewestWins` (corrections): iceoryx2's safe
//!   overflow, the newest sample replaces the oldest queued one, the send never waits and the
//!   receiver sees the replaced messages as a gap. Right for corrections, each of which carries
//!   the whole current solution. The policy is a property of the service, so all processes of a
//!   swarm must agree on it. Why the re-send is ours and not iceoryx2's backpressure handler:
//!   see `outbox`.
//! - **Orderly goodbye.** iceoryx2 loses samples of a publisher that is gone before the
//!   subscriber mapped its memory. So [`AgentLink::close`] sends `Goodbye` and waits until every
//!   consumer that got it acknowledges, and a consumer holds back an agent's `Goodbye` until it
//!   has drained that agent's data topics: once acknowledged, nothing sent before is lost.

mod agent;
mod checks;
mod config;
mod consumer;
mod error;
mod inbox;
mod open;
mod outbox;
pub mod relay;
mod samples;
mod sequence;
mod topic;
mod traffic;
mod wake;

pub use agent::{AgentLink, KeyframeImageMeta};
pub use config::{DEFAULT_MAX_AGENTS, FullQueuePolicies, FullQueuePolicy, TransportConfig};
pub use consumer::ConsumerLink;
pub use error::TransportError;
pub use outbox::SendReport;
pub use samples::{
    ControlSample, CorrectionSample, DescriptorSample, Incoming, KeyframeImageSample,
    LifecycleSample, PatchSample,
};
pub use sequence::Delivery;
pub use traffic::{BandwidthReport, Direction, TopicTraffic, TrafficEntry};

/// The iceoryx2 service variant of every port: inter-process, shared memory.
type Ipc = iceoryx2::prelude::ipc::Service;
