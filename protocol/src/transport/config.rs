//! [`TransportConfig`]: the settings every process of one swarm shares (they size the shared
//! services), and the [`FullQueuePolicy`] of each topic.

use std::time::Duration;

use iceoryx2::prelude::ServiceName;
use serde::{Deserialize, Serialize};

use super::TransportError;
use crate::services::{ServiceNames, Topic};

/// Agent-id range of a swarm whose size is not known (a consensus started without `--agents`,
/// tests): ids `0..DEFAULT_MAX_AGENTS`.
pub const DEFAULT_MAX_AGENTS: u32 = 8;

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
    /// Per-consumer queue length of each agent's patch topic.
    pub patch_queue_depth: usize,
    /// Keyframe images are large (1.8 MB at 640x480) and sent once per keyframe, so a short
    /// queue suffices; each queued image also occupies a slot of the publisher's data segment.
    pub keyframe_image_queue_depth: usize,
    /// Queue length of an agent's correction subscriber; with `NewestWins` (the default) a full
    /// queue drops its oldest correction.
    pub correction_queue_depth: usize,
    /// Control messages are rare (a shutdown, a re-send request), so a short queue suffices.
    pub control_queue_depth: usize,
    /// Per-consumer queue length of the lifecycle service, which all agents share.
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

    pub(super) fn validate(&self) -> Result<(), TransportError> {
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

    /// First data-segment size of `topic`'s publisher, in payload elements (slice topics;
    /// descriptors and lifecycle messages are one value each).
    pub(super) fn initial_capacity(&self, topic: Topic) -> usize {
        match topic {
            Topic::Patch => self.initial_patch_records,
            Topic::KeyframeImage => self.initial_keyframe_image_pixels,
            Topic::Correction => self.initial_correction_poses,
            Topic::Control => self.initial_control_bytes,
            Topic::Descriptor | Topic::Lifecycle => 1,
        }
    }

    pub(super) fn names(&self) -> ServiceNames {
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
