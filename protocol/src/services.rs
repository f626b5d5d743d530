//! Service names, defined once.
//!
//! Data topics (one service per agent and topic):
//! - `{ns}/agent/{id}/descriptor`      agent -> consumers, [`crate::messages::KeyframeDescriptor`]
//! - `{ns}/agent/{id}/patch`           agent -> consumers, `[GaussianRecord]` + `PatchHeader`
//! - `{ns}/agent/{id}/keyframe_image`  agent -> consumers, `[RgbdPixel]` + `KeyframeImageHeader`
//!   (a keyframe's colour and depth, for feature-based alignment of agents in the consensus)
//! - `{ns}/agent/{id}/correction`      consumer -> agent, `[KeyframePose]` + `CorrectionHeader`
//! - `{ns}/agent/{id}/control`         consumer -> agent, `[u8]` (one [`crate::codec`] frame of a
//!   [`crate::messages::ControlMessage`]) + `ControlHeader`
//! - `{ns}/lifecycle`                  everyone -> consumers, [`crate::messages::Lifecycle`]
//!
//! Wake-up event services (iceoryx2 event pattern; they carry no data, only "look now"):
//! - `{ns}/agent/{id}/wake`            consumers -> agent: correction arrived, consumer attached
//! - `{ns}/consumers/wake`             agents -> consumers: new data on topic `event id`
//!
//! `{ns}` is [`DEFAULT_NAMESPACE`] in production; tests and benchmarks use their own namespace
//! (e.g. with the process id) so that parallel runs never share services.

/// Namespace of a production swarm.
pub const DEFAULT_NAMESPACE: &str = "mac";

/// The data topics of one agent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Topic {
    /// Keyframe descriptors, agent -> consumers.
    Descriptor,
    /// Gaussian patches, agent -> consumers.
    Patch,
    /// Corrections, consumer -> agent.
    Correction,
    /// Hello, heartbeat and goodbye, agent -> consumers; one service shared by all agents.
    Lifecycle,
    /// Keyframe RGB-D images, agent -> consumers.
    KeyframeImage,
    /// Control messages as codec frames, consumer -> agent.
    Control,
}

impl Topic {
    /// Every topic, in [`Topic::index`] order.
    pub const ALL: [Topic; 6] = [
        Topic::Descriptor,
        Topic::Patch,
        Topic::Correction,
        Topic::Lifecycle,
        Topic::KeyframeImage,
        Topic::Control,
    ];

    /// Small dense index, used for per-topic tables and wake-up event ids.
    pub const fn index(self) -> usize {
        match self {
            Topic::Descriptor => 0,
            Topic::Patch => 1,
            Topic::Correction => 2,
            Topic::Lifecycle => 3,
            Topic::KeyframeImage => 4,
            Topic::Control => 5,
        }
    }

    /// Topics whose messages are large (slices of records or pixels): building one in shared
    /// memory takes long enough (tens of microseconds for a 10k-record patch) that a sender
    /// wakes its receivers before it starts rather than after it is done.
    pub const fn is_bulk(self) -> bool {
        matches!(self, Topic::Patch | Topic::KeyframeImage)
    }

    /// Last component of the topic's service names (e.g. `keyframe_image`); also its `Display`
    /// and serialised form.
    pub const fn name(self) -> &'static str {
        match self {
            Topic::Descriptor => "descriptor",
            Topic::Patch => "patch",
            Topic::Correction => "correction",
            Topic::Lifecycle => "lifecycle",
            Topic::KeyframeImage => "keyframe_image",
            Topic::Control => "control",
        }
    }
}

impl std::fmt::Display for Topic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Builds every service name of one namespace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServiceNames {
    namespace: String,
}

impl Default for ServiceNames {
    fn default() -> Self {
        Self::new(DEFAULT_NAMESPACE)
    }
}

impl ServiceNames {
    /// Names under `namespace` ([`DEFAULT_NAMESPACE`] in production).
    pub fn new(namespace: impl Into<String>) -> Self {
        Self {
            namespace: namespace.into(),
        }
    }

    /// The namespace: the first component of every name.
    pub fn namespace(&self) -> &str {
        &self.namespace
    }

    /// Name of an agent's data topic; [`Topic::Lifecycle`] is shared by all agents.
    pub fn topic(&self, agent_id: u32, topic: Topic) -> String {
        match topic {
            Topic::Lifecycle => self.lifecycle(),
            other => format!("{}/agent/{agent_id}/{}", self.namespace, other.name()),
        }
    }

    /// `{ns}/agent/{agent_id}/descriptor`.
    pub fn descriptor(&self, agent_id: u32) -> String {
        self.topic(agent_id, Topic::Descriptor)
    }

    /// `{ns}/agent/{agent_id}/patch`.
    pub fn patch(&self, agent_id: u32) -> String {
        self.topic(agent_id, Topic::Patch)
    }

    /// `{ns}/agent/{agent_id}/keyframe_image`.
    pub fn keyframe_image(&self, agent_id: u32) -> String {
        self.topic(agent_id, Topic::KeyframeImage)
    }

    /// `{ns}/agent/{agent_id}/correction`.
    pub fn correction(&self, agent_id: u32) -> String {
        self.topic(agent_id, Topic::Correction)
    }

    /// `{ns}/agent/{agent_id}/control`.
    pub fn control(&self, agent_id: u32) -> String {
        self.topic(agent_id, Topic::Control)
    }

    /// `{ns}/lifecycle`, shared by all agents.
    pub fn lifecycle(&self) -> String {
        format!("{}/lifecycle", self.namespace)
    }

    /// Event service that wakes agent `agent_id`.
    pub fn agent_wake(&self, agent_id: u32) -> String {
        format!("{}/agent/{agent_id}/wake", self.namespace)
    }

    /// Event service that wakes the consumers (consensus, observers).
    pub fn consumers_wake(&self) -> String {
        format!("{}/consumers/wake", self.namespace)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn production_names_match_the_spec() {
        let names = ServiceNames::default();
        assert_eq!(names.descriptor(3), "mac/agent/3/descriptor");
        assert_eq!(names.patch(0), "mac/agent/0/patch");
        assert_eq!(names.keyframe_image(2), "mac/agent/2/keyframe_image");
        assert_eq!(names.correction(12), "mac/agent/12/correction");
        assert_eq!(names.control(4), "mac/agent/4/control");
        assert_eq!(names.lifecycle(), "mac/lifecycle");
        assert_eq!(names.topic(5, Topic::Lifecycle), "mac/lifecycle");
        assert_eq!(names.agent_wake(1), "mac/agent/1/wake");
    }

    #[test]
    fn topic_indices_are_dense() {
        for (i, t) in Topic::ALL.iter().enumerate() {
            assert_eq!(t.index(), i);
        }
    }
}
