//! The relay on a host that runs the consumers (the consensus), standing in for the remote
//! agents: [`ConsumerHostIngress`] publishes what remote agents sent (as those agents would),
//! and [`ConsumerHostEgress`] takes what the consumers send the remote agents, and the
//! consumers' goodbye acknowledgements.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::{CallbackProgression, Node, SignalHandlingMode, WaitSetBuilder};
use iceoryx2::service::port_factory::event::PortFactory as EventService;

use super::super::error::{port_error, wait_error};
use super::super::inbox::Inbox;
use super::super::open::{create_node, open_agent_wake, open_consumers_wake, open_lifecycle};
use super::super::outbox::{Outbox, Recipients, SendReport, WhenAbsent};
use super::super::sequence::ReceiveBook;
use super::super::topic::{
    ControlTopic, CorrectionTopic, DescriptorTopic, KeyframeImageTopic, LifecycleTopic, PatchTopic,
};
use super::super::traffic::{BandwidthReport, TrafficTable};
use super::super::wake::{WAKE_GOODBYE_SEEN, consumers_wake_event};
use super::super::{Ipc, TransportConfig, TransportError, checks};
use super::agent_host::check_agent_id;
use super::wire::{RelayedMessage, read_slice, read_value, slice_bytes};
use crate::messages::{
    GaussianRecord, KeyframeDescriptor, KeyframeImageHeader, Lifecycle, PatchHeader, RgbdPixel,
    Stamp,
};
use crate::services::Topic;

/// The publishers of one remote agent's data topics.
struct AgentPublishers {
    descriptor: Outbox<DescriptorTopic>,
    patch: Outbox<PatchTopic>,
    keyframe_image: Outbox<KeyframeImageTopic>,
}

/// Publishes what remote agents sent to the local consumers, stamps unchanged, with the same
/// delivery handshake and full-queue policies as the agents themselves.
pub struct ConsumerHostIngress {
    config: TransportConfig,
    /// Opened at a remote agent's first message: each holds shared-memory segments sized for
    /// patches and images, which agents that never come should not cost.
    agents: BTreeMap<u32, AgentPublishers>,
    lifecycle: Outbox<LifecycleTopic>,
    consumers_notifier: Notifier<Ipc>,
    shutdown: Arc<AtomicBool>,
    traffic: TrafficTable,
    node: Node<Ipc>,
    // Kept last: ports above must be dropped before the services and the node that own them.
    _consumers_wake_service: EventService<Ipc>,
}

impl ConsumerHostIngress {
    /// Opens the lifecycle publisher and the consumers' wake-up notifier. A remote agent's data
    /// publishers are opened at its first relayed message.
    pub fn open(config: &TransportConfig) -> Result<Self, TransportError> {
        config.validate()?;
        let names = config.names();
        let node = create_node(&format!("mac-relay-ingress-{}", std::process::id()))?;
        let (lifecycle_service, _) = open_lifecycle(&node, config)?;
        let lifecycle = Outbox::on(names.lifecycle(), lifecycle_service, config, 0)?;
        let consumers_wake_service = open_consumers_wake(&node, config)?;
        let consumers_notifier = consumers_wake_service
            .notifier_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "notifier", e))?;
        Ok(Self {
            config: config.clone(),
            agents: BTreeMap::new(),
            lifecycle,
            consumers_notifier,
            shutdown: Arc::new(AtomicBool::new(false)),
            traffic: TrafficTable::new(),
            node,
            _consumers_wake_service: consumers_wake_service,
        })
    }

    /// See [`crate::transport::AgentLink::shutdown_handle`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.shutdown)
    }

    /// Whether `required_consumers` consumers are attached here (to the lifecycle service,
    /// which every consumer opens first): until then, what remote agents send would wait.
    pub fn consumers_attached(&self) -> bool {
        self.lifecycle.attached() >= self.config.required_consumers
    }

    fn publishers(&mut self, agent_id: u32) -> Result<&AgentPublishers, TransportError> {
        check_agent_id(&self.config, agent_id)?;
        if !self.agents.contains_key(&agent_id) {
            let (node, config) = (&self.node, &self.config);
            let publishers = AgentPublishers {
                // A local agent with this id (or a second relay) is refused here by name.
                descriptor: Outbox::open(node, config, agent_id)?,
                patch: Outbox::open(node, config, agent_id)?,
                keyframe_image: Outbox::open(node, config, agent_id)?,
            };
            self.agents.insert(agent_id, publishers);
        }
        Ok(&self.agents[&agent_id])
    }

    /// Publishes a relayed agent message to the local consumers. Waits, like the agent would,
    /// for `required_consumers` to attach (up to `delivery_timeout`) and for room in full
    /// queues (up to `full_queue_timeout`).
    pub fn forward(&mut self, message: &RelayedMessage) -> Result<SendReport, TransportError> {
        let agent_id = message.agent_id;
        let topic = message.topic;
        self.publishers(agent_id)?;
        let publishers = &self.agents[&agent_id];
        let to = Recipients {
            required: self.config.required_consumers,
            when_absent: WhenAbsent::Poll,
            wake: &self.consumers_notifier,
            wake_event: consumers_wake_event(agent_id, topic),
            config: &self.config,
            shutdown: &self.shutdown,
        };
        let bytes = &message.bytes;
        let outcome = match topic {
            Topic::Descriptor => {
                let name = &publishers.descriptor.name;
                let descriptor = read_value::<KeyframeDescriptor>(name, bytes)?;
                check_owner(name, &descriptor.stamp, agent_id)?;
                publishers.descriptor.send_value(&to, |_| descriptor)
            }
            Topic::Patch => {
                let name = &publishers.patch.name;
                let (header, records) = read_slice::<PatchHeader, GaussianRecord>(name, bytes)?;
                check_owner(name, &header.stamp, agent_id)?;
                publishers.patch.send_slice(&to, |_| header, records)
            }
            Topic::KeyframeImage => {
                let name = &publishers.keyframe_image.name;
                let (header, pixels) = read_slice::<KeyframeImageHeader, RgbdPixel>(name, bytes)?;
                check_owner(name, &header.stamp, agent_id)?;
                publishers
                    .keyframe_image
                    .send_slice(&to, |_| header, pixels)
            }
            Topic::Lifecycle => {
                let name = &self.lifecycle.name;
                let lifecycle = read_value::<Lifecycle>(name, bytes)?;
                check_owner(name, &lifecycle.stamp, agent_id)?;
                self.lifecycle.send_value(&to, |_| lifecycle)
            }
            Topic::Correction | Topic::Control => {
                return Err(TransportError::InvalidMessage {
                    service: self.config.names().topic(agent_id, topic),
                    reason: format!("topic {topic} does not go to consumers"),
                });
            }
        };
        self.traffic.count_send(agent_id, topic, outcome)
    }

    /// Sent traffic per remote agent and topic.
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

/// An agent -> consumers message must carry, in its stamp, the agent it is relayed for: a
/// network peer cannot speak for another agent.
fn check_owner(service: &str, stamp: &Stamp, agent_id: u32) -> Result<(), TransportError> {
    checks::sender(stamp, agent_id)
        .map(|_| ())
        .map_err(|reason| TransportError::Malformed {
            service: service.to_string(),
            reason,
        })
}

/// What the consumers send towards one remote agent.
struct AgentInboxes {
    correction: Inbox<CorrectionTopic>,
    control: Inbox<ControlTopic>,
    /// The agent's wake-up listener: corrections, control messages and goodbye
    /// acknowledgements are announced here.
    listener: Listener<Ipc>,
    _wake_service: EventService<Ipc>,
}

/// What leaves a consumer host.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConsumerHostOutgoing {
    /// A correction or control message for a remote agent.
    Message(RelayedMessage),
    /// A consumer acknowledged agent `agent_id`'s goodbye (it drained the agent's data).
    GoodbyeSeen {
        /// The remote agent whose goodbye was acknowledged.
        agent_id: u32,
    },
}

/// Takes what the local consumers send every remote agent `0..max_agents` (as that agent
/// would), and their goodbye acknowledgements.
pub struct ConsumerHostEgress {
    agents: Vec<AgentInboxes>,
    pending: VecDeque<ConsumerHostOutgoing>,
    shutdown: Arc<AtomicBool>,
    traffic: TrafficTable,
    book: ReceiveBook,
    // Kept last: ports above must be dropped before the node that owns them.
    _node: Node<Ipc>,
}

impl ConsumerHostEgress {
    /// Subscribes to the correction and control topics of every agent id `0..max_agents`, and
    /// listens on each one's wake-up service, as those agents would.
    pub fn open(config: &TransportConfig) -> Result<Self, TransportError> {
        config.validate()?;
        let node = create_node(&format!("mac-relay-egress-{}", std::process::id()))?;
        let agents = (0..config.max_agents)
            .map(|agent_id| {
                let wake_service = open_agent_wake(&node, config, agent_id)?;
                let listener = wake_service
                    .listener_builder()
                    .create()
                    .map_err(|e| port_error(&config.names().agent_wake(agent_id), "listener", e))?;
                Ok(AgentInboxes {
                    correction: Inbox::open(&node, config, agent_id)?,
                    control: Inbox::open(&node, config, agent_id)?,
                    listener,
                    _wake_service: wake_service,
                })
            })
            .collect::<Result<Vec<_>, TransportError>>()?;
        Ok(Self {
            agents,
            pending: VecDeque::new(),
            shutdown: Arc::new(AtomicBool::new(false)),
            traffic: TrafficTable::new(),
            book: ReceiveBook::default(),
            _node: node,
        })
    }

    /// Setting this flag ends [`ConsumerHostEgress::recv_timeout`] with
    /// [`TransportError::ShutdownRequested`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.shutdown)
    }

    /// Next outgoing item, without blocking.
    pub fn try_recv(&mut self) -> Result<Option<ConsumerHostOutgoing>, TransportError> {
        self.take_events()?;
        if let Some(item) = self.pending.pop_front() {
            return Ok(Some(item));
        }
        for agent in 0..self.agents.len() as u32 {
            if let Some(message) = self.receive(agent)? {
                return Ok(Some(ConsumerHostOutgoing::Message(message)));
            }
        }
        Ok(None)
    }

    /// Waits (event-driven, on every remote agent's wake-up listener at once) up to
    /// `timeout` for the next outgoing item.
    pub fn recv_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<ConsumerHostOutgoing>, TransportError> {
        if self.shutdown.load(std::sync::atomic::Ordering::Relaxed) {
            return Err(TransportError::ShutdownRequested);
        }
        if let Some(item) = self.try_recv()? {
            return Ok(Some(item));
        }
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(wait_error)?;
        let guards = self
            .agents
            .iter()
            .map(|agent| waitset.attach_notification(&agent.listener))
            .collect::<Result<Vec<_>, _>>()
            .map_err(wait_error)?;
        waitset
            .wait_and_process_once_with_timeout(|_| CallbackProgression::Stop, timeout)
            .map_err(wait_error)?;
        drop(guards);
        self.try_recv()
    }

    /// Collects the listeners' pending events: goodbye acknowledgements become outgoing items;
    /// the others only say "look at the inboxes", which every receive does anyway.
    fn take_events(&mut self) -> Result<(), TransportError> {
        for (agent_id, agent) in self.agents.iter().enumerate() {
            let mut goodbyes_seen = 0;
            agent
                .listener
                .try_wait(|event| {
                    if event.id.as_value() == WAKE_GOODBYE_SEEN {
                        goodbyes_seen += event.count;
                    }
                })
                .map_err(wait_error)?;
            for _ in 0..goodbyes_seen {
                self.pending.push_back(ConsumerHostOutgoing::GoodbyeSeen {
                    agent_id: agent_id as u32,
                });
            }
        }
        Ok(())
    }

    fn receive(&mut self, agent: u32) -> Result<Option<RelayedMessage>, TransportError> {
        let inboxes = &self.agents[agent as usize];
        if let Some((sample, _)) = inboxes.correction.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::correction_header(sample.user_header(), sample.payload().len(), agent),
            |_| agent,
        )? {
            return Ok(Some(RelayedMessage {
                agent_id: agent,
                topic: Topic::Correction,
                stamp: sample.user_header().stamp,
                bytes: slice_bytes(sample.user_header(), sample.payload()),
            }));
        }
        let control = inboxes.control.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::control_header(sample.user_header(), sample.payload().len(), agent),
            |_| agent,
        )?;
        Ok(control.map(|(sample, _)| RelayedMessage {
            agent_id: agent,
            topic: Topic::Control,
            stamp: sample.user_header().stamp,
            bytes: slice_bytes(sample.user_header(), sample.payload()),
        }))
    }

    /// Received traffic per remote agent and topic.
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}
