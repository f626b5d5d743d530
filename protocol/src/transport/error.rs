//! [`TransportError`]: every way a transport call fails, with the service it concerns.

use std::fmt::Debug;
use std::time::Duration;

use crate::codec::CodecError;
use crate::services::Topic;

/// Every way a transport call fails. Each error names the service (or agent id) it concerns,
/// and the reasons from iceoryx2 are kept as text.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransportError {
    /// The [`TransportConfig`](super::TransportConfig) failed validation when a link was opened.
    #[error("invalid transport configuration: {reason}")]
    InvalidConfig {
        /// Which setting is wrong, and why.
        reason: String,
    },
    /// An agent id outside this process's configured range `0..max_agents`: opening an agent
    /// link with it, or sending to it.
    #[error("agent id {agent_id} is out of range: the swarm is configured for ids 0..{max_agents}")]
    AgentIdOutOfRange {
        /// The id refused.
        agent_id: u32,
        /// This process's [`TransportConfig::max_agents`](super::TransportConfig::max_agents).
        max_agents: u32,
    },
    /// An agent id outside the range the swarm's shared services were created for, by the
    /// process that created them first (usually the consensus).
    #[error(
        "agent id {agent_id} is outside the swarm in namespace '{namespace}': it was set up for \
         agent ids 0..{swarm_max_agents} by the process that started it (usually \
         mac-consensus --agents {swarm_max_agents}); use an id in that range or start the swarm \
         for more agents"
    )]
    AgentIdOutsideSwarm {
        /// The id refused.
        agent_id: u32,
        /// The swarm's agent-id range `0..swarm_max_agents`, recorded on its lifecycle service.
        swarm_max_agents: u32,
        /// The swarm's namespace.
        namespace: String,
    },
    /// A live process already publishes as this agent id: an agent's own topics admit one
    /// publisher each.
    #[error(
        "agent id {agent_id} is already used by a live process in namespace '{namespace}'; \
         give every agent its own id"
    )]
    DuplicateAgent {
        /// The id already in use.
        agent_id: u32,
        /// The swarm's namespace.
        namespace: String,
    },
    /// The link's iceoryx2 node could not be created.
    #[error("iceoryx2 node '{node}' could not be created: {reason}")]
    Node {
        /// Name of the node (e.g. `mac-agent-0`).
        node: String,
        /// iceoryx2's error.
        reason: String,
    },
    /// A service could not be opened or created: an invalid name, limits or attributes that
    /// differ from those of the processes already on it, or an iceoryx2 failure.
    #[error("service '{service}' could not be opened or created: {reason}")]
    Service {
        /// Service name.
        service: String,
        /// What went wrong.
        reason: String,
    },
    /// A port could not be created on a service.
    #[error("{port} port on '{service}' could not be created: {reason}")]
    Port {
        /// Service name.
        service: String,
        /// Kind of port: `publisher`, `subscriber`, `listener` or `notifier`.
        port: &'static str,
        /// iceoryx2's error.
        reason: String,
    },
    /// Fewer than the required receivers attached to a service within `delivery_timeout`
    /// (the delivery handshake before a send).
    #[error(
        "no consumer on '{service}' after {waited:?}: {attached} attached, {required} required \
         (is the consensus running with the same namespace?)"
    )]
    NoConsumer {
        /// Service name.
        service: String,
        /// Receivers attached when the wait ended.
        attached: usize,
        /// Receivers required (`required_consumers`).
        required: usize,
        /// How long the send waited.
        waited: Duration,
    },
    /// A message reached fewer receivers than required, and the send does not wait for more:
    /// the agent a consumer sends to is not attached, or a `NewestWins` send could not reach
    /// the required receivers within `full_queue_timeout`.
    #[error(
        "message {sequence} on '{service}' reached {delivered} of {required} required receivers"
    )]
    Undelivered {
        /// Service name.
        service: String,
        /// Sequence number of the message.
        sequence: u64,
        /// Receivers it reached.
        delivered: usize,
        /// Receivers it had to reach.
        required: usize,
    },
    /// A `Block` send found a required receiver's queue full for `full_queue_timeout`: the
    /// receiver does not read fast enough. Counted in
    /// [`TopicTraffic::full_queue_failures`](super::TopicTraffic::full_queue_failures).
    #[error(
        "message {sequence} on '{service}' ({topic} topic): a consumer's queue stayed full for \
         {waited:?} (reached {delivered} of {required} required receivers); the consumer is not \
         reading fast enough"
    )]
    QueueFull {
        /// Service name.
        service: String,
        /// The service's topic.
        topic: Topic,
        /// Sequence number of the message.
        sequence: u64,
        /// Receivers it reached.
        delivered: usize,
        /// Receivers it had to reach.
        required: usize,
        /// How long the send re-tried.
        waited: Duration,
    },
    /// A received control frame did not decode (another codec format version, corruption).
    /// The frame is consumed; the next receive goes on with the following one.
    #[error("control message {sequence} on '{service}' refused: {source}")]
    ControlFrame {
        /// Service name.
        service: String,
        /// Sequence number of the refused message.
        sequence: u64,
        /// Why the codec refused the frame.
        source: CodecError,
    },
    /// Shared memory for an outgoing message could not be loaned from the publisher.
    #[error("could not loan {elements} elements on '{service}': {reason}")]
    Loan {
        /// Service name.
        service: String,
        /// Payload elements asked for (1 for a one-value message).
        elements: usize,
        /// iceoryx2's error.
        reason: String,
    },
    /// iceoryx2 failed to send a filled sample.
    #[error("send on '{service}' failed: {reason}")]
    Send {
        /// Service name.
        service: String,
        /// iceoryx2's error.
        reason: String,
    },
    /// iceoryx2 failed to take a sample from a subscriber.
    #[error("receive on '{service}' failed: {reason}")]
    Receive {
        /// Service name.
        service: String,
        /// iceoryx2's error.
        reason: String,
    },
    /// A message refused before sending, so nothing was sent: content that would mislead its
    /// receivers (an unnormalised descriptor, an invalid pose, an image whose size does not
    /// match, an unencodable control message), or, at a relay, an agent or topic it does not
    /// send to.
    #[error("refusing to send on '{service}': {reason}")]
    InvalidMessage {
        /// Service name.
        service: String,
        /// What is wrong with the message.
        reason: String,
    },
    /// A received message failed the receive checks (its header does not match its payload or
    /// names another agent, or relayed bytes do not form the message): corruption or a foreign
    /// sender.
    #[error("malformed message on '{service}': {reason}")]
    Malformed {
        /// Service name.
        service: String,
        /// What is wrong with the message.
        reason: String,
    },
    /// Not every consumer that received the agent's goodbye acknowledged it in time.
    #[error("goodbye acknowledged by {acknowledged} of {expected} consumers within {waited:?}")]
    GoodbyeUnacknowledged {
        /// Acknowledgements received.
        acknowledged: u64,
        /// Consumers the goodbye reached.
        expected: usize,
        /// How long the agent waited.
        waited: Duration,
    },
    /// A consumer that took the goodbye left before acknowledging it (its process, e.g. a
    /// bridge, died): what the agent sent before may be lost with it.
    #[error(
        "goodbye lost: a consumer that took it left (its process died) before acknowledging it, after {waited:?}"
    )]
    GoodbyeLost {
        /// How long the agent had waited for acknowledgements.
        waited: Duration,
    },
    /// Waiting on a wake-up event listener failed.
    #[error("waiting for wake-up events failed: {reason}")]
    Wait {
        /// iceoryx2's error.
        reason: String,
    },
    /// The link's shutdown flag was set (`shutdown_handle`): a blocking call gave up, within
    /// one `wait_slice`.
    #[error("shutdown requested")]
    ShutdownRequested,
}

pub(super) fn service_error(name: &str, error: impl Debug) -> TransportError {
    TransportError::Service {
        service: name.to_string(),
        reason: format!("{error:?}"),
    }
}

pub(super) fn port_error(name: &str, port: &'static str, error: impl Debug) -> TransportError {
    TransportError::Port {
        service: name.to_string(),
        port,
        reason: format!("{error:?}"),
    }
}

pub(super) fn loan_error(name: &str, elements: usize, error: impl Debug) -> TransportError {
    TransportError::Loan {
        service: name.to_string(),
        elements,
        reason: format!("{error:?}"),
    }
}

pub(super) fn send_error(name: &str, error: impl Debug) -> TransportError {
    TransportError::Send {
        service: name.to_string(),
        reason: format!("{error:?}"),
    }
}

pub(super) fn receive_error(name: &str, error: impl Debug) -> TransportError {
    TransportError::Receive {
        service: name.to_string(),
        reason: format!("{error:?}"),
    }
}

pub(super) fn wait_error(error: impl Debug) -> TransportError {
    TransportError::Wait {
        reason: format!("{error:?}"),
    }
}
