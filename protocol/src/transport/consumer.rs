//! [`ConsumerLink`]: the transport endpoint of the consensus (or any observer of the swarm). It
//! receives from every agent id `0..max_agents`, lifecycle messages first, and sends
//! corrections and control messages to one agent at a time.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::{EventId, Node};
use iceoryx2::service::port_factory::event::PortFactory as EventService;

use super::error::port_error;
use super::inbox::Inbox;
use super::open::{create_node, open_agent_wake, open_consumers_wake, open_lifecycle};
use super::outbox::{Outbox, Recipients, SendReport, Sent, WhenAbsent};
use super::sequence::{ReceiveBook, new_epoch};
use super::topic::{
    ControlTopic, CorrectionTopic, DescriptorTopic, KeyframeImageTopic, LifecycleTopic, PatchTopic,
    TopicService,
};
use super::traffic::{BandwidthReport, TrafficTable};
use super::wake::{
    Receiving, WAKE_CONSUMER_ATTACHED, WAKE_CONTROL, WAKE_CORRECTION, WAKE_GOODBYE_SEEN, Waiting,
    notify, receive_within,
};
use super::{
    DescriptorSample, Incoming, Ipc, KeyframeImageSample, LifecycleSample, PatchSample,
    TransportConfig, TransportError, checks,
};
use crate::codec;
use crate::messages::{
    CONSUMER_AGENT_ID, ControlHeader, ControlMessage, CorrectionHeader, KeyframePose,
    LifecycleKind, Pose, Stamp,
};

/// The consumer -> agent topics (correction, control) have exactly one subscriber: the agent.
const AGENT_RECIPIENTS: usize = 1;

/// Topics a consumer receives per agent (descriptor, keyframe image, patch), scanned round-robin.
const AGENT_SOURCES: usize = 3;

/// A consumer's ports to one agent.
struct AgentPorts {
    descriptor: Inbox<DescriptorTopic>,
    patch: Inbox<PatchTopic>,
    keyframe_image: Inbox<KeyframeImageTopic>,
    correction: Outbox<CorrectionTopic>,
    control: Outbox<ControlTopic>,
    wake: Notifier<Ipc>,
    _wake_service: EventService<Ipc>,
}

impl AgentPorts {
    fn open(
        node: &Node<Ipc>,
        config: &TransportConfig,
        agent_id: u32,
    ) -> Result<Self, TransportError> {
        let descriptor = Inbox::open(node, config, agent_id)?;
        let patch = Inbox::open(node, config, agent_id)?;
        let keyframe_image = Inbox::open(node, config, agent_id)?;
        let correction = Outbox::open(node, config, agent_id)?;
        let control = Outbox::open(node, config, agent_id)?;
        let wake_service = open_agent_wake(node, config, agent_id)?;
        let wake = wake_service
            .notifier_builder()
            .create()
            .map_err(|e| port_error(&config.names().agent_wake(agent_id), "notifier", e))?;
        Ok(Self {
            descriptor,
            patch,
            keyframe_image,
            correction,
            control,
            wake,
            _wake_service: wake_service,
        })
    }

    /// Whether the agent still has queued data (this also maps the memory of its publishers,
    /// after which their samples survive the publisher's exit).
    fn has_data(&self) -> Result<bool, TransportError> {
        Ok(self.descriptor.has_samples()?
            || self.keyframe_image.has_samples()?
            || self.patch.has_samples()?)
    }
}

/// The transport endpoint of the consensus (or any observer of the swarm).
pub struct ConsumerLink {
    config: TransportConfig,
    epoch: u64,
    agents: Vec<AgentPorts>,
    lifecycle: Inbox<LifecycleTopic>,
    waiting: Waiting,
    traffic: TrafficTable,
    book: ReceiveBook,
    /// Round-robin start of the next receive scan, so no agent starves the others.
    cursor: usize,
    /// Goodbyes held back until their agent's data topics are drained.
    deferred_goodbyes: Vec<LifecycleSample>,
    // Kept last: ports above must be dropped before the services and the node that own them.
    _wake_service: EventService<Ipc>,
    _node: Node<Ipc>,
}

impl ConsumerLink {
    /// Subscribes to every agent id `0..max_agents` and tells running agents that a consumer
    /// attached (so their pending sends proceed).
    pub fn open(config: &TransportConfig) -> Result<Self, TransportError> {
        config.validate()?;
        let names = config.names();
        let node = create_node(&format!("mac-consumer-{}", std::process::id()))?;
        // The swarm's own range may differ from ours; we listen to exactly 0..max_agents.
        let (lifecycle_service, _swarm_max_agents) = open_lifecycle(&node, config)?;
        let lifecycle = Inbox::on(names.lifecycle(), lifecycle_service, config)?;
        let wake_service = open_consumers_wake(&node, config)?;
        let wake_listener = wake_service
            .listener_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "listener", e))?;
        let agents = (0..config.max_agents)
            .map(|agent_id| AgentPorts::open(&node, config, agent_id))
            .collect::<Result<Vec<_>, _>>()?;
        // Only now are all subscribers registered: wake agents blocked in their handshake.
        for ports in &agents {
            notify(
                &ports.wake,
                EventId::new(WAKE_CONSUMER_ATTACHED),
                "an agent after attaching",
            );
        }
        Ok(Self {
            config: config.clone(),
            epoch: new_epoch(),
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

    /// See [`super::AgentLink::shutdown_handle`].
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.waiting.shutdown)
    }

    /// Next pending message of any agent, without blocking. Lifecycle messages come first, so
    /// an agent's hello is handled before the data it sent after it (the consensus needs a
    /// restarted agent's run anchor before its first keyframe); they are few and small. The
    /// data sources are scanned round-robin. An agent's `Goodbye` comes after all data it sent
    /// before it.
    pub fn try_recv(&mut self) -> Result<Option<Incoming>, TransportError> {
        if let Some(goodbye) = self.take_drained_goodbye()? {
            return Ok(Some(Incoming::Lifecycle(goodbye)));
        }
        if let Some(lifecycle) = self.receive_lifecycle()? {
            return Ok(Some(lifecycle));
        }
        // Data sources: (descriptor, keyframe image, patch) of each agent. The image comes
        // before the patch of the same keyframe, as an agent sends them.
        let sources = AGENT_SOURCES * self.agents.len();
        for step in 0..sources {
            let source = (self.cursor + step) % sources;
            let agent = (source / AGENT_SOURCES) as u32;
            let received = match source % AGENT_SOURCES {
                0 => self.receive_descriptor(agent)?,
                1 => self.receive_keyframe_image(agent)?,
                _ => self.receive_patch(agent)?,
            };
            if let Some(incoming) = received {
                self.cursor = (source + 1) % sources;
                return Ok(Some(incoming));
            }
        }
        Ok(None)
    }

    /// Waits (event-driven) up to `timeout` for the next message.
    pub fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Incoming>, TransportError> {
        receive_within(self, timeout, Self::try_recv)
    }

    /// Tells the agent its goodbye was seen after its data was drained (it may exit now).
    fn acknowledge_goodbye(&self, agent_id: u32) {
        let wake = &self.agents[agent_id as usize].wake;
        notify(
            wake,
            EventId::new(WAKE_GOODBYE_SEEN),
            "an agent to acknowledge a goodbye",
        );
    }

    fn take_drained_goodbye(&mut self) -> Result<Option<LifecycleSample>, TransportError> {
        for i in 0..self.deferred_goodbyes.len() {
            let agent_id = self.deferred_goodbyes[i].stamp.agent_id;
            if !self.agents[agent_id as usize].has_data()? {
                self.acknowledge_goodbye(agent_id);
                return Ok(Some(self.deferred_goodbyes.remove(i)));
            }
        }
        Ok(None)
    }

    fn receive_lifecycle(&mut self) -> Result<Option<Incoming>, TransportError> {
        let max_agents = self.config.max_agents;
        loop {
            let Some((sample, delivery)) = self.lifecycle.receive(
                &mut self.book,
                &mut self.traffic,
                |sample| checks::lifecycle_sender(&sample.payload().stamp, max_agents),
                |stamp| stamp.agent_id,
            )?
            else {
                return Ok(None);
            };
            // Copied out: it is small, and a held-back goodbye must not pin a shared-memory
            // sample.
            let received = LifecycleSample {
                message: *sample.payload(),
                delivery,
            };
            drop(sample);
            let agent_id = received.stamp.agent_id;
            if received.kind() == Ok(LifecycleKind::Goodbye) {
                if self.agents[agent_id as usize].has_data()? {
                    self.deferred_goodbyes.push(received);
                    continue;
                }
                self.acknowledge_goodbye(agent_id);
            }
            return Ok(Some(Incoming::Lifecycle(received)));
        }
    }

    fn receive_descriptor(&mut self, agent: u32) -> Result<Option<Incoming>, TransportError> {
        let received = self.agents[agent as usize].descriptor.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::sender(&sample.payload().stamp, agent),
            |_| agent,
        )?;
        Ok(received
            .map(|(sample, delivery)| Incoming::Descriptor(DescriptorSample { sample, delivery })))
    }

    fn receive_patch(&mut self, agent: u32) -> Result<Option<Incoming>, TransportError> {
        let received = self.agents[agent as usize].patch.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::patch_header(sample.user_header(), sample.payload().len(), agent),
            |_| agent,
        )?;
        Ok(received.map(|(sample, delivery)| Incoming::Patch(PatchSample { sample, delivery })))
    }

    fn receive_keyframe_image(&mut self, agent: u32) -> Result<Option<Incoming>, TransportError> {
        let received = self.agents[agent as usize].keyframe_image.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| {
                checks::keyframe_image_header(sample.user_header(), sample.payload().len(), agent)
            },
            |_| agent,
        )?;
        Ok(received.map(|(sample, delivery)| {
            Incoming::KeyframeImage(KeyframeImageSample { sample, delivery })
        }))
    }

    /// Agent `agent_id` as the one receiver of a consumer -> agent topic: it is not waited for
    /// when absent, and is woken with `wake_event`.
    fn to_agent(&self, agent_id: u32, wake_event: usize) -> Result<Recipients<'_>, TransportError> {
        let ports = self.ports(agent_id)?;
        Ok(Recipients {
            required: AGENT_RECIPIENTS,
            when_absent: WhenAbsent::Fail,
            wake: &ports.wake,
            wake_event: EventId::new(wake_event),
            config: &self.config,
            shutdown: &self.waiting.shutdown,
        })
    }

    fn ports(&self, agent_id: u32) -> Result<&AgentPorts, TransportError> {
        self.agents
            .get(agent_id as usize)
            .ok_or(TransportError::AgentIdOutOfRange {
                agent_id,
                max_agents: self.config.max_agents,
            })
    }

    fn stamp(&self, sequence: u64) -> Stamp {
        Stamp {
            agent_id: CONSUMER_AGENT_ID,
            reserved: 0,
            epoch: self.epoch,
            sequence,
        }
    }

    /// Counts a send of `T` to agent `agent_id` (or its failure with a full queue).
    fn account<T: TopicService>(
        &mut self,
        agent_id: u32,
        outcome: Result<Sent, TransportError>,
    ) -> Result<SendReport, TransportError> {
        let report = self.traffic.count_send(agent_id, T::TOPIC, outcome)?;
        self.waiting.mark_activity();
        Ok(report)
    }

    /// Sends a correction to agent `agent_id`. An agent that is not attached is never waited
    /// for ([`TransportError::Undelivered`]). A full queue of the agent's: with the default
    /// [`super::FullQueuePolicy::NewestWins`] the correction replaces the oldest queued one at
    /// once (the consensus never waits on a slow agent); with `Block` the send waits up to
    /// `full_queue_timeout`, then fails with [`TransportError::QueueFull`].
    pub fn send_correction(
        &mut self,
        agent_id: u32,
        agent_world_to_world: Pose,
        poses: &[KeyframePose],
    ) -> Result<SendReport, TransportError> {
        let outbox = &self.ports(agent_id)?.correction;
        checks::correction(&outbox.name, &agent_world_to_world, poses)?;
        let header = |sequence| CorrectionHeader {
            stamp: self.stamp(sequence),
            target_agent_id: agent_id,
            reserved: 0,
            agent_world_to_world,
            count: poses.len() as u64,
        };
        let outcome = outbox.send_slice(&self.to_agent(agent_id, WAKE_CORRECTION)?, header, poses);
        self.account::<CorrectionTopic>(agent_id, outcome)
    }

    /// Sends a control message to agent `agent_id` as one [`crate::codec`] frame (encoded here;
    /// an unencodable or oversized message is [`TransportError::InvalidMessage`]). Full queues
    /// follow `full_queue.control` (default `Block`, bounded by `full_queue_timeout`); an agent
    /// that is not attached is never waited for ([`TransportError::Undelivered`]).
    pub fn send_control(
        &mut self,
        agent_id: u32,
        message: &ControlMessage,
    ) -> Result<SendReport, TransportError> {
        let outbox = &self.ports(agent_id)?.control;
        let frame = codec::encode(message).map_err(|e| TransportError::InvalidMessage {
            service: outbox.name.clone(),
            reason: e.to_string(),
        })?;
        self.send_control_frame(agent_id, &frame)
    }

    /// Sends an already encoded codec frame on agent `agent_id`'s control topic.
    fn send_control_frame(
        &mut self,
        agent_id: u32,
        frame: &[u8],
    ) -> Result<SendReport, TransportError> {
        let header = |sequence| ControlHeader {
            stamp: self.stamp(sequence),
            target_agent_id: agent_id,
            reserved: 0,
            frame_len: frame.len() as u64,
        };
        let outcome = self.ports(agent_id)?.control.send_slice(
            &self.to_agent(agent_id, WAKE_CONTROL)?,
            header,
            frame,
        );
        self.account::<ControlTopic>(agent_id, outcome)
    }

    /// Received traffic per agent and topic (and corrections sent) since [`ConsumerLink::open`].
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

impl Receiving for ConsumerLink {
    fn waiting(&mut self) -> &mut Waiting {
        &mut self.waiting
    }
}

#[cfg(test)]
mod tests {
    use super::super::AgentLink;
    use super::super::sequence::Delivery;
    use super::*;
    use crate::codec::CodecError;

    /// A control frame of another codec format version (an agent built from other sources) is
    /// refused on receive with an error naming the topic and both versions, and the frames
    /// after it are still received in order.
    #[test]
    fn control_frame_of_another_format_version_is_refused_clearly() {
        let config = TransportConfig::with_namespace(format!("unit-ctlver-{}", std::process::id()));
        let mut consumer = ConsumerLink::open(&config).unwrap();
        let mut agent = AgentLink::open(&config, 0).unwrap();
        let message = ControlMessage::Shutdown {
            reason: "test".into(),
        };
        let mut frame = codec::encode(&message).unwrap();
        let foreign_version = codec::FORMAT_VERSION + 1;
        frame[4..6].copy_from_slice(&foreign_version.to_le_bytes());
        consumer.send_control_frame(0, &frame).unwrap();
        consumer.send_control(0, &message).unwrap();
        let timeout = Duration::from_secs(2);
        match agent.recv_control_timeout(timeout) {
            Err(
                err @ TransportError::ControlFrame {
                    sequence: 0,
                    source: CodecError::UnsupportedVersion { .. },
                    ..
                },
            ) => {
                let text = err.to_string();
                assert!(text.contains(&config.names().control(0)), "{text}");
                assert!(
                    text.contains(&format!("version {foreign_version}"))
                        && text.contains(&format!("version {}", codec::FORMAT_VERSION)),
                    "{text}"
                );
            }
            other => panic!("expected a ControlFrame error, got {other:?}"),
        }
        let next = agent.recv_control_timeout(timeout).unwrap().unwrap();
        assert_eq!(next.message, message);
        assert_eq!(next.header.stamp.sequence, 1);
        assert_eq!(next.delivery, Delivery::InOrder);
    }
}
