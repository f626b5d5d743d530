//! Opening things: the iceoryx2 node, and every service with the limits the swarm's config
//! gives it. One generic opener serves all publish-subscribe topics ([`open_topic`], typed by
//! [`super::topic`]); the services shared by the whole swarm (lifecycle, the consumers'
//! wake-up) are sized by the agent count and opened as their creator sized them
//! ([`open_shared`]).

use std::fmt::Debug;

use iceoryx2::config::Config;
use iceoryx2::port::publisher::{Publisher, PublisherCreateError};
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::{
    AttributeVerifier, BackpressureStrategy, IceoryxSend, Node, NodeBuilder, NodeName, ServiceName,
    SignalHandlingMode, ZeroCopySend,
};
use iceoryx2::service::attribute::{AttributeKey, AttributeValue};
use iceoryx2::service::builder::event::{EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{
    Builder as PubSubBuilder, PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::port_factory::PortFactory as _;
use iceoryx2::service::port_factory::event::PortFactory as EventService;

use super::error::{port_error, service_error};
use super::topic::{LifecycleTopic, PayloadShape, Service, TopicService};
use super::wake::{AGENT_WAKE_EVENT_IDS, TOPIC_COUNT};
use super::{FullQueuePolicy, Ipc, TransportConfig, TransportError};
use crate::services::Topic;

/// Nodes of crashed processes may hold a service slot until they are cleaned up; this many
/// extra slots let a restarted process in even before the clean-up ran.
const NODE_SLACK: usize = 2;

/// Samples a publisher loans at once: every send loans, fills and sends one sample.
const PUBLISHER_MAX_LOANS: usize = 1;

/// Service attribute on the shared lifecycle service that records the agent-id range the swarm
/// was set up for (by whichever process created the service first), so that a process with
/// another range joins without a service-limit mismatch and an agent outside the range is
/// refused by name.
const SWARM_MAX_AGENTS_ATTRIBUTE: &str = "mac.swarm.max_agents";

/// Opening a shared service races with other processes creating or removing it; this many
/// rounds of "open as it is, else open-or-create with our limits" settle any such race.
const SHARED_SERVICE_OPEN_ATTEMPTS: usize = 4;

/// Who publishes on a topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Senders {
    /// The agent whose topic it is, alone (a second publisher is a live twin with its id).
    OneAgent,
    /// The consumers, to one agent (corrections, control).
    Consumers,
    /// Every process of the swarm (lifecycle).
    Everyone,
}

impl Senders {
    fn of(topic: Topic) -> Self {
        match topic {
            Topic::Descriptor | Topic::Patch | Topic::KeyframeImage => Senders::OneAgent,
            Topic::Correction | Topic::Control => Senders::Consumers,
            Topic::Lifecycle => Senders::Everyone,
        }
    }
}

/// Limits of one publish-subscribe service. iceoryx2's defaults (2 publishers, 20 nodes per
/// service) break a swarm, so every service is opened with limits from the config.
#[derive(Debug, Clone, Copy)]
struct PubSubLimits {
    publishers: usize,
    subscribers: usize,
    nodes: usize,
    queue_depth: usize,
    held_samples: usize,
    /// iceoryx2 safe overflow: a full queue drops its oldest sample ([`FullQueuePolicy::NewestWins`]).
    safe_overflow: bool,
}

impl PubSubLimits {
    fn of(config: &TransportConfig, topic: Topic) -> Self {
        let consumers = config.max_consumers;
        let (publishers, subscribers, nodes) = match Senders::of(topic) {
            Senders::OneAgent => (1, consumers, 1 + consumers + NODE_SLACK),
            Senders::Consumers => (consumers, 1, 1 + consumers + NODE_SLACK),
            Senders::Everyone => {
                let processes = config.max_agents as usize + consumers;
                // Slack as for nodes: a restarted agent may come before its dead twin is
                // cleaned up.
                (processes + NODE_SLACK, consumers, processes + NODE_SLACK)
            }
        };
        Self {
            publishers,
            subscribers,
            nodes,
            queue_depth: config.queue_depth(topic),
            held_samples: config.max_held_samples,
            safe_overflow: config.full_queue.of(topic) == FullQueuePolicy::NewestWins,
        }
    }

    fn apply<P: Debug + IceoryxSend + ?Sized, H: Debug + ZeroCopySend>(
        self,
        builder: PubSubBuilder<P, H, Ipc>,
    ) -> PubSubBuilder<P, H, Ipc> {
        builder
            .max_publishers(self.publishers)
            .max_subscribers(self.subscribers)
            .max_nodes(self.nodes)
            .subscriber_max_buffer_size(self.queue_depth)
            .subscriber_max_borrowed_samples(self.held_samples)
            // No history: it would pin large patches in shared memory and replay only the last
            // few; the delivery handshake makes sure a subscriber exists before each send.
            .history_size(0)
            .enable_safe_overflow(self.safe_overflow)
    }
}

/// Builds the iceoryx2 config explicitly so behaviour does not depend on a config file found on
/// the machine; dead-node clean-up is what makes a SIGKILLed process harmless.
fn iceoryx_config() -> Config {
    let mut config = Config::default();
    config.global.node.cleanup_dead_nodes_on_creation = true;
    config.global.node.cleanup_dead_nodes_on_destruction = true;
    config.global.service.cleanup_dead_nodes_on_open = true;
    config
}

/// A link's own node; first reclaims what dead processes left in shared memory.
pub(super) fn create_node(name: &str) -> Result<Node<Ipc>, TransportError> {
    let node_error = |reason: String| TransportError::Node {
        node: name.to_string(),
        reason,
    };
    let node_name = NodeName::new(name).map_err(|e| node_error(format!("{e:?}")))?;
    let node = NodeBuilder::new()
        .name(&node_name)
        .config(&iceoryx_config())
        // The processes own their signal handling; the transport offers a shutdown flag.
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()
        .map_err(|e| node_error(format!("{e:?}")))?;
    let cleaned = node.try_cleanup_dead_nodes();
    if cleaned.cleanups > 0 || cleaned.failed_cleanups > 0 {
        tracing::info!(
            cleaned = cleaned.cleanups,
            failed = cleaned.failed_cleanups,
            "removed shared-memory leftovers of dead iceoryx2 nodes"
        );
    }
    Ok(node)
}

fn service_name(name: &str) -> Result<ServiceName, TransportError> {
    ServiceName::new(name).map_err(|e| TransportError::Service {
        service: name.to_string(),
        reason: format!("invalid name: {e:?}"),
    })
}

fn pub_sub_builder<T: TopicService>(
    node: &Node<Ipc>,
    service: &ServiceName,
) -> PubSubBuilder<T::Payload, T::Header, Ipc> {
    node.service_builder(service)
        .publish_subscribe::<T::Payload>()
        .user_header::<T::Header>()
}

/// Opens (or creates) agent `agent_id`'s service of topic `T` with the limits the config gives
/// it; returns it with its name.
pub(super) fn open_topic<T: TopicService>(
    node: &Node<Ipc>,
    config: &TransportConfig,
    agent_id: u32,
) -> Result<(String, Service<T>), TransportError> {
    let name = config.names().topic(agent_id, T::TOPIC);
    let builder =
        PubSubLimits::of(config, T::TOPIC).apply(pub_sub_builder::<T>(node, &service_name(&name)?));
    let service = T::Payload::open_or_create(builder).map_err(|e| service_error(&name, e))?;
    Ok((name, service))
}

/// Creates the publisher of topic `T` on `service`. A full queue is not waited for inside
/// iceoryx2 (`DiscardData`): the send path decides, per topic, what happens then
/// ([`super::outbox`]). `agent_id` names the agent in a [`TransportError::DuplicateAgent`].
pub(super) fn create_publisher<T: TopicService>(
    service: &Service<T>,
    name: &str,
    config: &TransportConfig,
    agent_id: u32,
) -> Result<Publisher<Ipc, T::Payload, T::Header>, TransportError> {
    let builder = service
        .publisher_builder()
        .max_loaned_samples(PUBLISHER_MAX_LOANS)
        .backpressure_strategy(BackpressureStrategy::DiscardData);
    T::Payload::data_segment(builder, config.initial_capacity(T::TOPIC))
        .create()
        .map_err(|e| match e {
            // An agent's own topic admits one publisher: this is a live twin with the same id.
            PublisherCreateError::ExceedsMaxSupportedPublishers
                if Senders::of(T::TOPIC) == Senders::OneAgent =>
            {
                TransportError::DuplicateAgent {
                    agent_id,
                    namespace: config.namespace.clone(),
                }
            }
            other => port_error(name, "publisher", other),
        })
}

/// Creates the subscriber of topic `T` on `service`, with the topic's queue depth.
pub(super) fn create_subscriber<T: TopicService>(
    service: &Service<T>,
    name: &str,
    config: &TransportConfig,
) -> Result<Subscriber<Ipc, T::Payload, T::Header>, TransportError> {
    service
        .subscriber_builder()
        .buffer_size(config.queue_depth(T::TOPIC))
        .create()
        .map_err(|e| port_error(name, "subscriber", e))
}

/// Opens the shared lifecycle service as its creator set it up, or creates it sized for
/// `config.max_agents` with that range recorded as an attribute. Returns the service and the
/// agent-id range of the swarm (the creator's `max_agents`).
pub(super) fn open_lifecycle(
    node: &Node<Ipc>,
    config: &TransportConfig,
) -> Result<(Service<LifecycleTopic>, u32), TransportError> {
    let name = config.names().lifecycle();
    let service = service_name(&name)?;
    let attribute_error = |e: &dyn Debug| TransportError::Service {
        service: name.clone(),
        reason: format!("attribute {SWARM_MAX_AGENTS_ATTRIBUTE}: {e:?}"),
    };
    let key =
        AttributeKey::try_from(SWARM_MAX_AGENTS_ATTRIBUTE).map_err(|e| attribute_error(&e))?;
    let ours = AttributeValue::try_from(config.max_agents.to_string().as_str())
        .map_err(|e| attribute_error(&e))?;
    let any_range = AttributeVerifier::new()
        .require_key(&key)
        .map_err(|e| attribute_error(&e))?;
    let our_range = AttributeVerifier::new()
        .require(&key, &ours)
        .map_err(|e| attribute_error(&e))?;
    let opened = open_shared(
        &name,
        // No limits requested: a swarm set up for another agent count opens as it is.
        || pub_sub_builder::<LifecycleTopic>(node, &service).open_with_attributes(&any_range),
        |e| {
            matches!(
                e,
                PublishSubscribeOpenError::DoesNotExist
                    | PublishSubscribeOpenError::HangsInCreation
                    | PublishSubscribeOpenError::IsMarkedForDestruction
            )
        },
        || {
            PubSubLimits::of(config, Topic::Lifecycle)
                .apply(pub_sub_builder::<LifecycleTopic>(node, &service))
                .open_or_create_with_attributes(&our_range)
        },
        |e| {
            matches!(
                e,
                PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(_)
            )
        },
    )?;
    let swarm_max_agents = opened
        .attributes()
        .key_value(&key, 0)
        .and_then(|value| value.to_string().parse::<u32>().ok())
        .filter(|&agents| agents > 0)
        .ok_or_else(|| TransportError::Service {
            service: name.clone(),
            reason: format!(
                "attribute {SWARM_MAX_AGENTS_ATTRIBUTE} is not a positive agent count: {:?}",
                opened.attributes()
            ),
        })?;
    Ok((opened, swarm_max_agents))
}

/// Opens a service shared by the whole swarm whose limits depend on the agent count: first as
/// it exists (`open_as_it_is`, requesting no limits, so processes configured for different agent
/// counts can meet), and only when it is absent (`is_absent`) with our own limits
/// (`open_or_create_ours`, which handles concurrent creation). When that finds a service
/// created meanwhile with other limits (`is_mismatch`), the next round opens it as it is.
fn open_shared<S, OpenError: Debug, OpenOrCreateError: Debug>(
    name: &str,
    mut open_as_it_is: impl FnMut() -> Result<S, OpenError>,
    is_absent: impl Fn(&OpenError) -> bool,
    mut open_or_create_ours: impl FnMut() -> Result<S, OpenOrCreateError>,
    is_mismatch: impl Fn(&OpenOrCreateError) -> bool,
) -> Result<S, TransportError> {
    let mut last_error = String::new();
    for _ in 0..SHARED_SERVICE_OPEN_ATTEMPTS {
        match open_as_it_is() {
            Ok(service) => return Ok(service),
            Err(e) if is_absent(&e) => {}
            Err(e) => return Err(service_error(name, e)),
        }
        match open_or_create_ours() {
            Ok(service) => return Ok(service),
            Err(e) if is_mismatch(&e) => last_error = format!("{e:?}"),
            Err(e) => return Err(service_error(name, e)),
        }
    }
    Err(service_error(
        name,
        format!(
            "still changing after {SHARED_SERVICE_OPEN_ATTEMPTS} attempts (processes creating \
             and removing it at the same time); last error: {last_error}"
        ),
    ))
}

/// Limits of one wake-up event service.
#[derive(Debug, Clone, Copy)]
struct EventLimits {
    notifiers: usize,
    listeners: usize,
    nodes: usize,
    event_ids: usize,
}

impl EventLimits {
    fn open_or_create(
        self,
        node: &Node<Ipc>,
        service: &ServiceName,
    ) -> Result<EventService<Ipc>, EventOpenOrCreateError> {
        node.service_builder(service)
            .event()
            .max_notifiers(self.notifiers)
            .max_listeners(self.listeners)
            .max_nodes(self.nodes)
            .event_id_max_value(self.event_ids)
            .open_or_create()
    }
}

/// Agent `agent_id`'s wake-up service: the consumers notify, the agent listens.
pub(super) fn open_agent_wake(
    node: &Node<Ipc>,
    config: &TransportConfig,
    agent_id: u32,
) -> Result<EventService<Ipc>, TransportError> {
    let name = config.names().agent_wake(agent_id);
    let limits = EventLimits {
        notifiers: config.max_consumers,
        listeners: 1,
        nodes: config.max_consumers + 1 + NODE_SLACK,
        event_ids: AGENT_WAKE_EVENT_IDS,
    };
    limits
        .open_or_create(node, &service_name(&name)?)
        .map_err(|e| service_error(&name, e))
}

/// The consumers' wake-up service is shared by all agents and sized by the agent count, so it
/// is opened like the lifecycle service ([`open_shared`]).
pub(super) fn open_consumers_wake(
    node: &Node<Ipc>,
    config: &TransportConfig,
) -> Result<EventService<Ipc>, TransportError> {
    let name = config.names().consumers_wake();
    let service = service_name(&name)?;
    let agents = config.max_agents as usize;
    let limits = EventLimits {
        notifiers: agents + NODE_SLACK,
        listeners: config.max_consumers,
        nodes: agents + config.max_consumers + NODE_SLACK,
        event_ids: agents * TOPIC_COUNT,
    };
    open_shared(
        &name,
        || node.service_builder(&service).event().open(),
        |e| {
            matches!(
                e,
                EventOpenError::DoesNotExist
                    | EventOpenError::HangsInCreation
                    | EventOpenError::IsMarkedForDestruction
            )
        },
        || limits.open_or_create(node, &service),
        |e| matches!(e, EventOpenOrCreateError::EventOpenError(_)),
    )
}
