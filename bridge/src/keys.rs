//! Zenoh key expressions of a swarm, defined once.
//!
//! Data keys equal the iceoryx2 service names on a host ([`protocol::services`]), one key per
//! swarm namespace, agent and topic:
//! - `{ns}/agent/{id}/descriptor`, `.../patch`, `.../keyframe_image`, `.../lifecycle`: agent
//!   host -> consumer host. Lifecycle messages get a key per agent (on a host they share one
//!   service), so a subscriber can take one agent's and the traffic is counted per agent.
//! - `{ns}/agent/{id}/correction`, `.../control`: consumer host -> the agent's host.
//! - `{ns}/agent/{id}/goodbye_seen`: consumer host -> the agent's host, no payload: a consumer
//!   acknowledged the agent's goodbye after draining its data.
//! - `{ns}/agent/{id}/delivered`: consumer host -> the agent's host: the consumers have one of
//!   the agent's messages (topic and stamp in the payload; see `delivery`).
//!
//! Liveliness tokens (zenoh liveliness, gone when the session is):
//! - `{ns}/bridge/consumers`: a consumer host's bridge whose consumers are attached; agent
//!   hosts attach to their agents only while one exists.
//! - `{ns}/bridge/agent/{id}`: the bridge of the host that runs agent `id`.

use protocol::services::{ServiceNames, Topic};

/// The keys of one swarm namespace.
#[derive(Debug, Clone)]
pub struct SwarmKeys {
    names: ServiceNames,
}

impl SwarmKeys {
    pub fn new(namespace: &str) -> Self {
        Self {
            names: ServiceNames::new(namespace),
        }
    }

    fn agent_prefix(&self, agent: &str) -> String {
        format!("{}/agent/{agent}", self.names.namespace())
    }

    /// Key of agent `agent_id`'s `topic` (lifecycle included: one key per agent).
    pub fn topic(&self, agent_id: u32, topic: Topic) -> String {
        format!(
            "{}/{}",
            self.agent_prefix(&agent_id.to_string()),
            topic.name()
        )
    }

    /// Every agent's `topic` (a subscription on the consumer host).
    pub fn topic_of_every_agent(&self, topic: Topic) -> String {
        format!("{}/{}", self.agent_prefix("*"), topic.name())
    }

    pub fn goodbye_seen(&self, agent_id: u32) -> String {
        format!(
            "{}/{GOODBYE_SEEN}",
            self.agent_prefix(&agent_id.to_string())
        )
    }

    pub fn delivered(&self, agent_id: u32) -> String {
        format!("{}/{DELIVERED}", self.agent_prefix(&agent_id.to_string()))
    }

    /// Where an agent host's bridge acknowledges a correction or control message its agent got.
    pub fn received(&self, agent_id: u32) -> String {
        format!("{}/{RECEIVED}", self.agent_prefix(&agent_id.to_string()))
    }

    pub fn received_of_every_agent(&self) -> String {
        format!("{}/{RECEIVED}", self.agent_prefix("*"))
    }

    /// The liveliness tokens of every agent host's bridge.
    pub fn every_agent_bridge(&self) -> String {
        format!("{}/bridge/agent/*", self.names.namespace())
    }

    /// The agent id of an agent host bridge's token key.
    pub fn parse_agent_bridge(&self, key: &str) -> Option<u32> {
        key.strip_prefix(self.names.namespace())?
            .strip_prefix("/bridge/agent/")?
            .parse()
            .ok()
    }

    pub fn consumers_bridge(&self) -> String {
        format!("{}/bridge/consumers", self.names.namespace())
    }

    pub fn agent_bridge(&self, agent_id: u32) -> String {
        format!("{}/bridge/agent/{agent_id}", self.names.namespace())
    }

    /// The agent id and last segment of a key `{ns}/agent/{id}/{last}` of this namespace.
    pub fn parse<'k>(&self, key: &'k str) -> Option<(u32, &'k str)> {
        let rest = key
            .strip_prefix(self.names.namespace())?
            .strip_prefix("/agent/")?;
        let (agent, last) = rest.split_once('/')?;
        Some((agent.parse().ok()?, last))
    }
}

/// Last key segment of a goodbye acknowledgement.
pub const GOODBYE_SEEN: &str = "goodbye_seen";
/// Last key segment of a delivery acknowledgement.
pub const DELIVERED: &str = "delivered";
/// The reverse of [`DELIVERED`]: agent host -> consumer host, for corrections and control.
pub const RECEIVED: &str = "received";

/// The topic whose name is `name`.
pub fn topic_named(name: &str) -> Option<Topic> {
    Topic::ALL.into_iter().find(|topic| topic.name() == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_match_service_names_and_parse_back() {
        let keys = SwarmKeys::new("mac7");
        let names = ServiceNames::new("mac7");
        assert_eq!(keys.topic(3, Topic::Patch), names.patch(3));
        assert_eq!(keys.topic(2, Topic::Lifecycle), "mac7/agent/2/lifecycle");
        assert_eq!(keys.parse_agent_bridge(&keys.agent_bridge(12)), Some(12));
        assert_eq!(keys.parse_agent_bridge("mac7/bridge/consumers"), None);
        assert_eq!(
            keys.parse("mac7/agent/12/correction"),
            Some((12, "correction"))
        );
        assert_eq!(keys.parse(&keys.goodbye_seen(4)), Some((4, GOODBYE_SEEN)));
        assert_eq!(keys.parse(&keys.delivered(5)), Some((5, DELIVERED)));
        assert_eq!(keys.parse("mac8/agent/1/patch"), None);
        assert_eq!(keys.parse("mac7/agent/x/patch"), None);
        assert_eq!(topic_named("keyframe_image"), Some(Topic::KeyframeImage));
        assert_eq!(topic_named(GOODBYE_SEEN), None);
    }
}
