//! Relay ports for joining one host's swarm to other hosts (the `mac-bridge` process). A relay
//! stands in, on its host, for the processes that run elsewhere:
//! - on a host that runs agents, for the remote consumers: [`AgentHostEgress`] receives what
//!   the local agents publish, [`AgentHostIngress`] publishes corrections and control messages
//!   to them and relays goodbye acknowledgements;
//! - on a host that runs the consumers, for the remote agents: [`ConsumerHostIngress`]
//!   publishes what they sent, [`ConsumerHostEgress`] receives what the consumers send them.
//!
//! Messages cross as [`RelayedMessage`]s: the original [`Stamp`](crate::messages::Stamp)
//! (agent, epoch, sequence) and the shared-memory layout as bytes (`wire`), so receivers on the
//! far host apply the same sequence, gap and restart rules as on one host. The relay ports use
//! the same services, limits, delivery handshake and full-queue policies as
//! [`AgentLink`](super::AgentLink) and [`ConsumerLink`](super::ConsumerLink); agents and
//! consumers cannot tell a relay from a local peer.
//!
//! Ordering: each egress yields messages in the order a consumer takes them (lifecycle first,
//! an agent's goodbye held back until its data topics are drained), so a network that keeps
//! the order of one sender's messages delivers a hello before the data that follows it and a
//! goodbye after the final map. A goodbye is acknowledged to the agent only when a far
//! consumer acknowledged it ([`ConsumerHostOutgoing::GoodbyeSeen`] ->
//! [`AgentHostIngress::acknowledge_goodbye`]), so an agent that exits after its acknowledged
//! goodbye has lost nothing.

mod agent_host;
mod consumer_host;
mod wire;

pub use agent_host::{AgentHostEgress, AgentHostIngress};
pub use consumer_host::{ConsumerHostEgress, ConsumerHostIngress, ConsumerHostOutgoing};
pub use wire::RelayedMessage;
