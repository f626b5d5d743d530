//! The relay on a host that runs agents, standing in for the remote consumers:
//! [`AgentHostEgress`] takes what the local agents publish (as a consumer would), and
//! [`AgentHostIngress`] hands the local agents what the remote consumers send them.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::{EventId, Node};
use iceoryx2::service::port_factory::event::PortFactory as EventService;

use super::super::error::port_error;
use super::super::inbox::Inbox;
use super::super::open::{create_node, open_agent_wake, open_consumers_wake, open_lifecycle};
use super::super::outbox::{Outbox, Recipients, SendReport, WhenAbsent};
use super::super::sequence::ReceiveBook;
use super::super::topic::{
    ControlTopic, CorrectionTopic, DescriptorTopic, KeyframeImageTopic, LifecycleTopic, PatchTopic,
};
use super::super::traffic::{BandwidthReport, TrafficTable};
use super::super::wake::{
    Receiving, WAKE_CONSUMER_ATTACHED, WAKE_CONTROL, WAKE_CORRECTION, WAKE_GOODBYE_SEEN, Waiting,
    notify, receive_within,
};
use super::super::{Ipc, TransportConfig, TransportError, checks};
use super::wire::{RelayedMessage, read_slice, slice_bytes, value_bytes};
use crate::messages::{ControlHeader, CorrectionHeader, KeyframePose, LifecycleKind};
use crate::services::Topic;

/// The data topics of one local agent, as a consumer receives them.
struct AgentSources {
    descriptor: Inbox<DescriptorTopic>,
    patch: Inbox<PatchTopic>,
    keyframe_image: Inbox<KeyframeImageTopic>,
}

impl AgentSources {
    fn has_data(&self) -> Result<bool, TransportError> {
        Ok(self.descriptor.has_samples()?
            || self.keyframe_image.has_samples()?
            || self.patch.has_samples()?)
    }
}

/// Data sources per agent (descriptor, keyframe image, patch), scanned round-robin.
const AGENT_SOURCES: usize = 3;

/// Everything the local agents publish, as [`RelayedMessage`]s, in the order a consumer
/// would take it: lifecycle first, an agent's goodbye only after its data.
pub struct AgentHostEgress {
    config: TransportConfig,
    agents: Vec<(u32, AgentSources)>,
    lifecycle: Inbox<LifecycleTopic>,
    waiting: Waiting,
    traffic: TrafficTable,
    book: ReceiveBook,
    cursor: usize,
    deferred_goodbyes: Vec<RelayedMessage>,
    // Kept last: ports above must be dropped before the services and the node that own them.
    _wake_service: EventService<Ipc>,
    _node: Node<Ipc>,
}

impl AgentHostEgress {
    /// Subscribes to the topics of `local_agents` (this attaches a consumer for them: open it
    /// only once the remote consumers are reachable, so the agents' delivery handshake still
    /// means something).
    pub fn open(config: &TransportConfig, local_agents: &[u32]) -> Result<Self, TransportError> {
        config.validate()?;
        let names = config.names();
        let node = create_node(&format!("mac-relay-egress-{}", std::process::id()))?;
        let (lifecycle_service, _) = open_lifecycle(&node, config)?;
        let lifecycle = Inbox::on(names.lifecycle(), lifecycle_service, config)?;
        let wake_service = open_consumers_wake(&node, config)?;
        let wake_listener = wake_service
            .listener_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "listener", e))?;
        let agents = local_agents
            .iter()
            .map(|&agent_id| {
                check_agent_id(config, agent_id)?;
                Ok((
                    agent_id,
                    AgentSources {
                        descriptor: Inbox::open(&node, config, agent_id)?,
                        patch: Inbox::open(&node, config, agent_id)?,
                        keyframe_image: Inbox::open(&node, config, agent_id)?,
                    },
                ))
            })
            .collect::<Result<Vec<_>, TransportError>>()?;
        Ok(Self {
            config: config.clone(),
            agents,
            lifecycle,
            waiting: Waiting::new(wake_listener, config),
            traffic: TrafficTable::new(),
            book: ReceiveBook::default(),
            cursor: 0,
            deferred_goodbyes: Vec::new(),
            _wake_service: wake_service,
            _node: node,
        })
    }

    /// See [`crate::transport::AgentLink::shutdown_handle`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.waiting.shutdown)
    }

    /// Next message of a local agent, without blocking.
    pub fn try_recv(&mut self) -> Result<Option<RelayedMessage>, TransportError> {
        if let Some(goodbye) = self.take_drained_goodbye()? {
            return Ok(Some(goodbye));
        }
        if let Some(lifecycle) = self.receive_lifecycle()? {
            return Ok(Some(lifecycle));
        }
        let sources = AGENT_SOURCES * self.agents.len();
        for step in 0..sources {
            let source = (self.cursor + step) % sources;
            let slot = source / AGENT_SOURCES;
            let received = match source % AGENT_SOURCES {
                0 => self.receive_descriptor(slot)?,
                1 => self.receive_keyframe_image(slot)?,
                _ => self.receive_patch(slot)?,
            };
            if received.is_some() {
                self.cursor = (source + 1) % sources;
                return Ok(received);
            }
        }
        Ok(None)
    }

    /// Waits (event-driven, woken by the agents' notifications) up to `timeout`.
    pub fn recv_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<RelayedMessage>, TransportError> {
        receive_within(self, timeout, Self::try_recv)
    }

    /// Received traffic per local agent and topic.
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }

    fn sources(&self, agent_id: u32) -> Option<&AgentSources> {
        self.agents
            .iter()
            .find(|(id, _)| *id == agent_id)
            .map(|(_, sources)| sources)
    }

    fn take_drained_goodbye(&mut self) -> Result<Option<RelayedMessage>, TransportError> {
        for i in 0..self.deferred_goodbyes.len() {
            let agent_id = self.deferred_goodbyes[i].agent_id;
            let drained = match self.sources(agent_id) {
                Some(sources) => !sources.has_data()?,
                None => true,
            };
            if drained {
                return Ok(Some(self.deferred_goodbyes.remove(i)));
            }
        }
        Ok(None)
    }

    fn receive_lifecycle(&mut self) -> Result<Option<RelayedMessage>, TransportError> {
        let max_agents = self.config.max_agents;
        loop {
            let Some((sample, _)) = self.lifecycle.receive(
                &mut self.book,
                &mut self.traffic,
                |sample| checks::lifecycle_sender(&sample.payload().stamp, max_agents),
                |stamp| stamp.agent_id,
            )?
            else {
                return Ok(None);
            };
            let message = *sample.payload();
            drop(sample);
            let agent_id = message.stamp.agent_id;
            let Some(sources) = self.sources(agent_id) else {
                tracing::warn!(
                    agent_id,
                    "lifecycle message of an agent this relay was not told is local: not relayed"
                );
                continue;
            };
            let goodbye = message.kind() == Ok(LifecycleKind::Goodbye);
            let has_data = goodbye && sources.has_data()?;
            let relayed = RelayedMessage {
                agent_id,
                topic: Topic::Lifecycle,
                stamp: message.stamp,
                bytes: value_bytes(&message),
            };
            if has_data {
                // After the data it sent before it, as a consumer would see it.
                self.deferred_goodbyes.push(relayed);
                continue;
            }
            return Ok(Some(relayed));
        }
    }

    fn receive_descriptor(
        &mut self,
        slot: usize,
    ) -> Result<Option<RelayedMessage>, TransportError> {
        let (agent, sources) = &self.agents[slot];
        let agent = *agent;
        let received = sources.descriptor.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::sender(&sample.payload().stamp, agent),
            |_| agent,
        )?;
        Ok(received.map(|(sample, _)| RelayedMessage {
            agent_id: agent,
            topic: Topic::Descriptor,
            stamp: sample.payload().stamp,
            bytes: value_bytes(sample.payload()),
        }))
    }

    fn receive_patch(&mut self, slot: usize) -> Result<Option<RelayedMessage>, TransportError> {
        let (agent, sources) = &self.agents[slot];
        let agent = *agent;
        let received = sources.patch.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::patch_header(sample.user_header(), sample.payload().len(), agent),
            |_| agent,
        )?;
        Ok(received.map(|(sample, _)| RelayedMessage {
            agent_id: agent,
            topic: Topic::Patch,
            stamp: sample.user_header().stamp,
            bytes: slice_bytes(sample.user_header(), sample.payload()),
        }))
    }

    fn receive_keyframe_image(
        &mut self,
        slot: usize,
    ) -> Result<Option<RelayedMessage>, TransportError> {
        let (agent, sources) = &self.agents[slot];
        let agent = *agent;
        let received = sources.keyframe_image.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| {
                checks::keyframe_image_header(sample.user_header(), sample.payload().len(), agent)
            },
            |_| agent,
        )?;
        Ok(received.map(|(sample, _)| RelayedMessage {
            agent_id: agent,
            topic: Topic::KeyframeImage,
            stamp: sample.user_header().stamp,
            bytes: slice_bytes(sample.user_header(), sample.payload()),
        }))
    }
}

impl Receiving for AgentHostEgress {
    fn waiting(&mut self) -> &mut Waiting {
        &mut self.waiting
    }
}

pub(super) fn check_agent_id(
    config: &TransportConfig,
    agent_id: u32,
) -> Result<(), TransportError> {
    if agent_id >= config.max_agents {
        return Err(TransportError::AgentIdOutOfRange {
            agent_id,
            max_agents: config.max_agents,
        });
    }
    Ok(())
}

/// A consumer's sending ports to one local agent.
struct AgentSinks {
    correction: Outbox<CorrectionTopic>,
    control: Outbox<ControlTopic>,
    wake: Notifier<Ipc>,
    _wake_service: EventService<Ipc>,
}

/// Hands the local agents the corrections and control messages the remote consumers sent,
/// with their original stamps, and relays the consumers' goodbye acknowledgements.
pub struct AgentHostIngress {
    config: TransportConfig,
    agents: BTreeMap<u32, AgentSinks>,
    shutdown: Arc<AtomicBool>,
    traffic: TrafficTable,
    // Kept last: ports above must be dropped before the node that owns them.
    _node: Node<Ipc>,
}

impl AgentHostIngress {
    /// Opens, for each of `local_agents`, the correction and control publishers and a notifier
    /// on its wake-up service, as a local consumer would. Refuses an id outside `0..max_agents`
    /// ([`TransportError::AgentIdOutOfRange`]).
    pub fn open(config: &TransportConfig, local_agents: &[u32]) -> Result<Self, TransportError> {
        config.validate()?;
        let node = create_node(&format!("mac-relay-ingress-{}", std::process::id()))?;
        let mut agents = BTreeMap::new();
        for &agent_id in local_agents {
            check_agent_id(config, agent_id)?;
            let wake_service = open_agent_wake(&node, config, agent_id)?;
            let wake = wake_service
                .notifier_builder()
                .create()
                .map_err(|e| port_error(&config.names().agent_wake(agent_id), "notifier", e))?;
            let sinks = AgentSinks {
                correction: Outbox::open(&node, config, agent_id)?,
                control: Outbox::open(&node, config, agent_id)?,
                wake,
                _wake_service: wake_service,
            };
            agents.insert(agent_id, sinks);
        }
        Ok(Self {
            config: config.clone(),
            agents,
            shutdown: Arc::new(AtomicBool::new(false)),
            traffic: TrafficTable::new(),
            _node: node,
        })
    }

    /// See [`crate::transport::AgentLink::shutdown_handle`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.shutdown)
    }

    fn sinks(&self, agent_id: u32) -> Result<&AgentSinks, TransportError> {
        self.agents
            .get(&agent_id)
            .ok_or_else(|| TransportError::InvalidMessage {
                service: self.config.names().agent_wake(agent_id),
                reason: format!("agent {agent_id} is not one of this relay's local agents"),
            })
    }

    /// Tells the local agents that a consumer is attached (their pending sends proceed now
    /// rather than at their next wait slice).
    pub fn announce_attached(&self) {
        for sinks in self.agents.values() {
            notify(
                &sinks.wake,
                EventId::new(WAKE_CONSUMER_ATTACHED),
                "an agent after attaching",
            );
        }
    }

    /// Relays a remote consumer's acknowledgement of agent `agent_id`'s goodbye.
    pub fn acknowledge_goodbye(&self, agent_id: u32) -> Result<(), TransportError> {
        notify(
            &self.sinks(agent_id)?.wake,
            EventId::new(WAKE_GOODBYE_SEEN),
            "an agent to acknowledge a goodbye",
        );
        Ok(())
    }

    /// Publishes a relayed correction or control message to its local agent, stamp unchanged.
    /// An agent that is not attached is not waited for ([`TransportError::Undelivered`]), as
    /// from a local consumer.
    pub fn forward(&mut self, message: &RelayedMessage) -> Result<SendReport, TransportError> {
        let agent_id = message.agent_id;
        let sinks = self.sinks(agent_id)?;
        let recipients = |wake_event| Recipients {
            required: 1,
            when_absent: WhenAbsent::Fail,
            wake: &sinks.wake,
            wake_event: EventId::new(wake_event),
            config: &self.config,
            shutdown: &self.shutdown,
        };
        let outcome = match message.topic {
            Topic::Correction => {
                let name = &sinks.correction.name;
                let (header, poses) =
                    read_slice::<CorrectionHeader, KeyframePose>(name, &message.bytes)?;
                check_target(name, header.target_agent_id, agent_id)?;
                sinks
                    .correction
                    .send_slice(&recipients(WAKE_CORRECTION), |_| header, poses)
            }
            Topic::Control => {
                let name = &sinks.control.name;
                let (header, frame) = read_slice::<ControlHeader, u8>(name, &message.bytes)?;
                check_target(name, header.target_agent_id, agent_id)?;
                sinks
                    .control
                    .send_slice(&recipients(WAKE_CONTROL), |_| header, frame)
            }
            other => {
                return Err(TransportError::InvalidMessage {
                    service: self.config.names().topic(agent_id, other),
                    reason: format!("topic {other} does not go to agents"),
                });
            }
        };
        let topic = message.topic;
        self.traffic.count_send(agent_id, topic, outcome)
    }

    /// Sent traffic per local agent and topic.
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

/// A consumer -> agent message must name, in its header, the agent it is relayed to.
fn check_target(service: &str, target: u32, agent_id: u32) -> Result<(), TransportError> {
    if target != agent_id {
        return Err(TransportError::Malformed {
            service: service.to_string(),
            reason: format!("relayed for agent {agent_id} but addressed to agent {target}"),
        });
    }
    Ok(())
}
