//! [`TransportError`]: every way a transport call fails, with the service it concerns.

use std::fmt::Debug;
use std::time::Duration;

use crate::codec::CodecError;
use crate::services::Topic;

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
    #[error(
        "goodbye lost: a consumer that took it left (its process died) before acknowledging it, after {waited:?}"
    )]
    GoodbyeLost { waited: Duration },
    #[error("waiting for wake-up events failed: {reason}")]
    Wait { reason: String },
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
