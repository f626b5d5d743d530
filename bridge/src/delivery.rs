//! End-to-end delivery of the agents' messages between the bridges, across link drops and
//! restarts of the consumer host's bridge; and, the other way, of the consumers' corrections
//! and control messages across restarts of an agent host's bridge.
//!
//! Zenoh's reliability holds within one session: a message queued on a link that breaks, or
//! received by a bridge that dies before handing it on, is gone. So the consumer host's bridge
//! acknowledges each message once its consumers have it (an [`Acknowledgement`] on
//! `{ns}/agent/{id}/delivered`, see `keys`, naming the topic and stamp), and the agent host's bridge keeps
//! every message until then ([`Unacknowledged`]). When the consumer host becomes reachable again
//! it sends what is still unacknowledged, oldest first, before anything new. A message that did
//! arrive the first time arrives twice; receivers drop the repeat by its stamp (the transport's
//! sequence rules), so nothing is lost and nothing is delivered twice.
//!
//! While no consumer host is reachable the agent host's bridge detaches from its agents, and they
//! queue what they publish as during a scheduled link outage. The bound
//! [`UNACKNOWLEDGED_LIMIT_BYTES`] is the flow control between the hosts: it holds the bridge
//! back (and through the iceoryx2 queues the agents) while the consumer host has not taken what
//! it was sent, so the consumer host's receive queue stays bounded without ever stalling the
//! link.
//!
//! The other way round the roles swap: an agent host's bridge acknowledges each correction or
//! control message once its agent has it (a receipt on `{ns}/agent/{id}/received`), and the
//! consumer host's bridge keeps each until then ([`Unacknowledged::push_bounded`]: the oldest
//! corrections of an agent that never answers again are forgotten). It sends an agent's messages
//! only while that agent's host is there (its liveliness token); when the host appears again, its
//! backlog goes first, in order, so nothing newer overtakes it.

use std::collections::VecDeque;

use anyhow::{Result, bail};
use protocol::services::Topic;
use protocol::transport::relay::RelayedMessage;

use crate::encoding::WireMessage;

/// Bytes of unacknowledged messages above which an agent host's bridge takes no more from its
/// agents: room for a few keyframes (a 640x480 image is 1.8 MB, a patch tens of MB at most; a
/// larger message still goes, alone).
pub const UNACKNOWLEDGED_LIMIT_BYTES: usize = 128 << 20;

/// A consumer host's receipt for one relayed message of agent `agent_id` (the agent is in the
/// key, the rest in the payload).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Acknowledgement {
    pub topic: Topic,
    pub epoch: u64,
    pub sequence: u64,
}

const ACKNOWLEDGEMENT_BYTES: usize = 1 + 8 + 8;

impl Acknowledgement {
    pub fn of(message: &RelayedMessage) -> Self {
        Self {
            topic: message.topic,
            epoch: message.stamp.epoch,
            sequence: message.stamp.sequence,
        }
    }

    pub fn to_bytes(self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(ACKNOWLEDGEMENT_BYTES);
        bytes.push(self.topic.index() as u8);
        bytes.extend_from_slice(&self.epoch.to_le_bytes());
        bytes.extend_from_slice(&self.sequence.to_le_bytes());
        bytes
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        if bytes.len() != ACKNOWLEDGEMENT_BYTES {
            bail!(
                "acknowledgement of {} bytes, expected {ACKNOWLEDGEMENT_BYTES}",
                bytes.len()
            );
        }
        let Some(topic) = Topic::ALL
            .into_iter()
            .find(|t| t.index() == usize::from(bytes[0]))
        else {
            bail!("acknowledgement of unknown topic index {}", bytes[0]);
        };
        let word = |at: usize| u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
        Ok(Self {
            topic,
            epoch: word(1),
            sequence: word(9),
        })
    }
}

/// The agent host's messages not yet acknowledged, in the order they were taken from the agents.
#[derive(Debug, Default)]
pub struct Unacknowledged {
    messages: VecDeque<WireMessage>,
    bytes: usize,
}

impl Unacknowledged {
    pub fn push(&mut self, message: WireMessage) {
        self.bytes += message.bytes.len();
        self.messages.push_back(message);
    }

    /// As [`Unacknowledged::push`], forgetting the oldest messages beyond `limit` bytes (for
    /// corrections and control messages of agents that may never acknowledge again: each
    /// correction carries the whole solution, so the newest ones are what matters).
    pub fn push_bounded(&mut self, message: WireMessage, limit: usize) {
        self.push(message);
        while self.bytes > limit && self.messages.len() > 1 {
            let oldest = self.messages.pop_front().expect("more than one");
            self.bytes -= oldest.bytes.len();
        }
    }

    /// Forgets agent `agent_id`'s messages that `ack` covers: the same topic with an older
    /// epoch, or the same epoch up to its sequence (each topic of an agent is delivered in
    /// order, so an acknowledgement covers everything before it).
    pub fn acknowledge(&mut self, agent_id: u32, ack: Acknowledgement) {
        self.messages.retain(|m| {
            let covered = m.agent_id == agent_id
                && m.topic == ack.topic
                && (m.stamp.epoch, m.stamp.sequence) <= (ack.epoch, ack.sequence);
            if covered {
                self.bytes -= m.bytes.len();
            }
            !covered
        });
    }

    pub fn iter(&self) -> impl Iterator<Item = &WireMessage> {
        self.messages.iter()
    }

    pub fn len(&self) -> usize {
        self.messages.len()
    }

    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::messages::Stamp;

    fn message(agent_id: u32, topic: Topic, epoch: u64, sequence: u64) -> WireMessage {
        let stamp = Stamp {
            agent_id,
            reserved: 0,
            epoch,
            sequence,
        };
        let mut bytes = bytemuck::bytes_of(&stamp).to_vec();
        bytes.extend_from_slice(&[0; 8]);
        WireMessage {
            agent_id,
            topic,
            stamp,
            encoding: crate::encoding::Encoding::Raw,
            bytes,
        }
    }

    #[test]
    fn acknowledgements_round_trip_and_bad_bytes_are_refused() {
        let ack = Acknowledgement {
            topic: Topic::KeyframeImage,
            epoch: 1 << 60,
            sequence: 77,
        };
        assert_eq!(Acknowledgement::from_bytes(&ack.to_bytes()).unwrap(), ack);
        assert!(Acknowledgement::from_bytes(&[0; 5]).is_err());
        let mut unknown = ack.to_bytes();
        unknown[0] = 200;
        assert!(Acknowledgement::from_bytes(&unknown).is_err());
    }

    #[test]
    fn an_acknowledgement_covers_its_topic_up_to_its_stamp_only() {
        let mut book = Unacknowledged::default();
        for sequence in 0..4 {
            book.push(message(0, Topic::Descriptor, 5, sequence));
            book.push(message(0, Topic::Patch, 5, sequence));
            book.push(message(1, Topic::Descriptor, 5, sequence));
        }
        book.push(message(0, Topic::Descriptor, 6, 0));
        let per_message = book.bytes() / book.len();
        book.acknowledge(
            0,
            Acknowledgement {
                topic: Topic::Descriptor,
                epoch: 5,
                sequence: 2,
            },
        );
        let left: Vec<_> = book
            .iter()
            .map(|m| (m.agent_id, m.topic, m.stamp.epoch, m.stamp.sequence))
            .collect();
        assert_eq!(left.len(), 13 - 3);
        assert_eq!(book.bytes(), left.len() * per_message);
        assert!(left.contains(&(0, Topic::Descriptor, 5, 3)));
        assert!(left.contains(&(0, Topic::Descriptor, 6, 0)));
        assert!(left.contains(&(1, Topic::Descriptor, 5, 0)));
        assert_eq!(left.iter().filter(|m| m.1 == Topic::Patch).count(), 4);
    }
}
