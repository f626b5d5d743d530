//! The two kinds of host a bridge serves, each with two threads that own the iceoryx2 side
//! (iceoryx2 ports stay on the thread that made them) while the zenoh session runs on tokio:
//! - an agent host ([`run_agent_host`]): its agents' messages go out, corrections, control
//!   messages and goodbye acknowledgements for them come in;
//! - the consumer host ([`run_consumer_host`]): the remote agents' messages come in, the
//!   consumers' corrections, control messages and goodbye acknowledgements go out.
//!
//! No loops: a bridge subscribes on zenoh only to the direction that enters its host and
//! publishes only the other (agent hosts: `correction`, `control`, `goodbye_seen` in; the
//! consumer host: `descriptor`, `patch`, `keyframe_image`, `lifecycle` in), its zenoh ports
//! exclude its own session (`Locality::Remote`), and on iceoryx2 it receives only from the
//! processes it stands in front of, never what it published itself.
//!
//! Faults (module `delivery`): the agent host's bridge attaches to its agents only while a
//! consumer host is reachable (its liveliness token), keeps what it sent until the consumer
//! host acknowledges it, and sends the rest again when the consumer host is back.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow};
use config::NetworkConfig;
use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use protocol::services::Topic;
use protocol::transport::relay::{
    AgentHostEgress, AgentHostIngress, ConsumerHostEgress, ConsumerHostIngress,
    ConsumerHostOutgoing, RelayedMessage,
};
use protocol::transport::{TransportConfig, TransportError};
use zenoh::pubsub::Publisher;
use zenoh::sample::{Locality, Sample, SampleKind};
use zenoh::{Session, Wait};

use crate::budget::Budget;
use crate::delivery::{Acknowledgement, UNACKNOWLEDGED_LIMIT_BYTES, Unacknowledged};
use crate::encoding::{Encoding, WireMessage, decode};
use crate::keys::{DELIVERED, GOODBYE_SEEN, SwarmKeys, topic_named};
use crate::network::{CONGESTION_CONTROL, PRIORITY};
use crate::report::{SharedTraffic, topic_label};

/// How often the loops look at the stop flag while nothing arrives.
const STOP_CHECK: Duration = Duration::from_millis(100);

/// Corrections, control messages and goodbye acknowledgements received from zenoh on an agent
/// host and not yet handed to iceoryx2. Bounded: they are small and few.
const INBOUND_QUEUE: usize = 64;

/// Bytes of corrections and control messages the consumer host's bridge keeps for agent hosts
/// that have not acknowledged them (the oldest are forgotten beyond it).
const CONSUMER_UNACKNOWLEDGED_LIMIT_BYTES: usize = 16 << 20;

/// Bytes (as published) waiting for an agent host's bandwidth budget above which the bridge
/// takes no more from its agents: they then queue what they publish as during an outage.
const WAITING_LIMIT_BYTES: usize = 256 << 20;

/// Everything a host's bridge shares between its tasks and threads.
#[derive(Clone)]
pub struct BridgeContext {
    pub session: Session,
    pub keys: SwarmKeys,
    pub transport: TransportConfig,
    pub stop: Arc<AtomicBool>,
    /// What crossed the network, per agent (the report).
    pub traffic: SharedTraffic,
    /// The agents' bandwidth budget (agent hosts).
    pub network: NetworkConfig,
}

impl BridgeContext {
    fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Sleeps in short steps until `stop` is set.
    async fn until_stopped(&self) {
        while !self.stopping() {
            tokio::time::sleep(STOP_CHECK).await;
        }
    }
}

/// What enters an agent host from the network.
enum AgentHostInbound {
    Message(RelayedMessage),
    GoodbyeSeen(u32),
    /// The egress attached to the local agents: wake them.
    ConsumersAttached,
}

/// Runs the bridge of a host whose agents are `local_agents` until `stop`.
pub async fn run_agent_host(context: BridgeContext, local_agents: Vec<u32>) -> Result<()> {
    let (inbound_tx, inbound_rx) = crossbeam_channel::bounded(INBOUND_QUEUE);
    let (acks_tx, acks_rx) = crossbeam_channel::unbounded();
    let ingress = spawn("ingress", &context.stop, {
        let (context, local_agents) = (context.clone(), local_agents.clone());
        move || agent_host_ingress(&context, &local_agents, &inbound_rx)
    })?;
    let mut subscribers = Vec::new();
    for &agent_id in &local_agents {
        for last in [
            Topic::Correction.name(),
            Topic::Control.name(),
            GOODBYE_SEEN,
            DELIVERED,
        ] {
            let key = format!("{}/agent/{agent_id}/{last}", context.transport.namespace);
            let (tx, acks) = (inbound_tx.clone(), acks_tx.clone());
            let subscriber = context
                .session
                .declare_subscriber(&key)
                .allowed_origin(Locality::Remote)
                .callback(move |sample: Sample| {
                    let bytes = sample.payload().to_bytes().into_owned();
                    let inbound = match topic_named(last) {
                        Some(topic) => match RelayedMessage::from_network(agent_id, topic, bytes) {
                            Ok(message) => AgentHostInbound::Message(message),
                            Err(e) => {
                                tracing::warn!(error = %e, "dropped a malformed relayed message");
                                return;
                            }
                        },
                        None if last == DELIVERED => {
                            match Acknowledgement::from_bytes(&bytes) {
                                Ok(ack) => {
                                    let _ = acks.send((agent_id, ack));
                                }
                                Err(e) => tracing::warn!(error = %e, "dropped a malformed acknowledgement"),
                            }
                            return;
                        }
                        None => AgentHostInbound::GoodbyeSeen(agent_id),
                    };
                    // Fails only when the ingress has stopped: nothing to deliver to.
                    let _ = tx.send(inbound);
                })
                .await
                .map_err(|e| anyhow!("zenoh subscriber {key}: {e}"))?;
            subscribers.push(subscriber);
        }
    }
    drop(acks_tx);
    let _agent_tokens = declare_tokens(
        &context,
        local_agents.iter().map(|&id| context.keys.agent_bridge(id)),
    )
    .await?;
    let reachable = Arc::new(AtomicBool::new(false));
    let appearances = Arc::new(AtomicU64::new(0));
    let _consumer_host_watch = context
        .session
        .liveliness()
        .declare_subscriber(context.keys.consumers_bridge())
        .history(true)
        .callback({
            let (reachable, appearances) = (Arc::clone(&reachable), Arc::clone(&appearances));
            move |sample: Sample| {
                let put = sample.kind() == SampleKind::Put;
                if put {
                    appearances.fetch_add(1, Ordering::Relaxed);
                }
                reachable.store(put, Ordering::Relaxed);
            }
        })
        .await
        .map_err(|e| anyhow!("zenoh liveliness subscriber: {e}"))?;
    tracing::info!(agents = ?local_agents, "waiting for a consumer host's bridge");
    let egress = spawn("egress", &context.stop, {
        let context = context.clone();
        let links = EgressLinks {
            inbound: inbound_tx.clone(),
            acknowledgements: acks_rx,
            reachable,
            appearances,
        };
        move || agent_host_egress(&context, &local_agents, &links)
    })?;
    drop(inbound_tx);
    context.until_stopped().await;
    // The egress drains before it ends, and needs the acknowledgements meanwhile.
    join(egress)?;
    drop(subscribers);
    join(ingress)
}

fn agent_host_ingress(
    context: &BridgeContext,
    local_agents: &[u32],
    inbound: &Receiver<AgentHostInbound>,
) -> Result<()> {
    let mut ingress = AgentHostIngress::open(&context.transport, local_agents)?;
    let mut receipts = Publishers::new(context);
    let traffic = &context.traffic;
    while !context.stopping() {
        let item = match inbound.recv_timeout(STOP_CHECK) {
            Ok(item) => item,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        match item {
            AgentHostInbound::Message(message) => {
                traffic.count_in(
                    message.agent_id,
                    topic_label(message.topic),
                    message.bytes.len(),
                );
                match ingress.forward(&message) {
                    Ok(_) => {
                        let key = context.keys.received(message.agent_id);
                        receipts.put(&key, Acknowledgement::of(&message).to_bytes())?;
                    }
                    Err(e) => {
                        tracing::warn!(agent_id = message.agent_id, topic = %message.topic, error = %e,
                            "could not hand a relayed message to its agent");
                    }
                }
            }
            AgentHostInbound::GoodbyeSeen(agent_id) => {
                traffic.count_in(agent_id, GOODBYE_SEEN, 0);
                ingress.acknowledge_goodbye(agent_id)?;
            }
            AgentHostInbound::ConsumersAttached => ingress.announce_attached(),
        }
    }
    Ok(())
}

/// What the egress thread of an agent host hears from the zenoh side.
struct EgressLinks {
    inbound: Sender<AgentHostInbound>,
    acknowledgements: Receiver<(u32, Acknowledgement)>,
    /// Whether a consumer host's bridge is reachable now (its liveliness token).
    reachable: Arc<AtomicBool>,
    /// How often its token has appeared: a link that zenoh closed and opened again within
    /// milliseconds (faster than the egress looks at `reachable`) still counts one more, and
    /// what was in flight on the closed link is sent again.
    appearances: Arc<AtomicU64>,
}

/// Relays the local agents' messages while a consumer host is reachable (see `delivery`),
/// within their bandwidth budget (see `budget`).
fn agent_host_egress(
    context: &BridgeContext,
    local_agents: &[u32],
    links: &EgressLinks,
) -> Result<()> {
    let mut publishers = Publishers::new(context);
    let mut unacknowledged = Unacknowledged::default();
    let mut budget = Budget::new(&context.network);
    let mut attached: Option<AgentHostEgress> = None;
    let mut appearances_seen = 0;
    while !context.stopping() {
        for (agent_id, ack) in links.acknowledgements.try_iter() {
            unacknowledged.acknowledge(agent_id, ack);
        }
        let reachable = links.reachable.load(Ordering::Relaxed);
        let appearances = links.appearances.load(Ordering::Relaxed);
        if reachable && attached.is_some() && appearances != appearances_seen {
            // The link was closed and opened again between two looks: what was in flight on
            // it may be gone.
            tracing::warn!(
                messages = unacknowledged.len(),
                bytes = unacknowledged.bytes(),
                "link to the consumer host re-established: sending again what it had not acknowledged"
            );
            send_again(&mut publishers, unacknowledged.iter())?;
        }
        appearances_seen = appearances;
        let Some(egress) = attached.as_mut() else {
            if !reachable {
                std::thread::sleep(STOP_CHECK);
                continue;
            }
            if unacknowledged.len() > 0 {
                tracing::info!(
                    messages = unacknowledged.len(),
                    bytes = unacknowledged.bytes(),
                    "consumer host back: sending again what it had not acknowledged"
                );
            }
            send_again(&mut publishers, unacknowledged.iter())?;
            attached = Some(AgentHostEgress::open(&context.transport, local_agents)?);
            let _ = links.inbound.send(AgentHostInbound::ConsumersAttached);
            tracing::info!("consumer host reachable: attached to the local agents");
            continue;
        };
        if !reachable {
            // What the agents already handed over waits in the budget's queues for the consumer
            // host's return; the agents queue the rest as during a scheduled outage.
            while let Some(message) = egress.try_recv()? {
                budget.admit(message, Instant::now());
            }
            attached = None;
            tracing::warn!(
                unacknowledged = unacknowledged.len(),
                waiting = budget.waiting_bytes(),
                "consumer host unreachable: detached from the local agents until it is back"
            );
            continue;
        }
        send_due(context, &mut publishers, &mut unacknowledged, &mut budget)?;
        if unacknowledged.bytes() >= UNACKNOWLEDGED_LIMIT_BYTES
            || budget.waiting_bytes() >= WAITING_LIMIT_BYTES
        {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        }
        let wait = budget
            .next_due_in(Instant::now())
            .map_or(STOP_CHECK, |due| due.min(STOP_CHECK));
        let received = if wait.is_zero() {
            egress.try_recv()?
        } else {
            egress.recv_timeout(wait)?
        };
        if let Some(message) = received {
            budget.admit(message, Instant::now());
        }
    }
    if let Some(egress) = attached.as_mut() {
        while let Some(message) = egress.try_recv()? {
            budget.admit(message, Instant::now());
        }
    }
    drain(
        context,
        links,
        &mut publishers,
        &mut unacknowledged,
        &mut budget,
    )
}

/// Sends what the budget lets go now, while the unacknowledged window has room, and keeps it
/// until acknowledged; the report's budget statistics follow.
fn send_due(
    context: &BridgeContext,
    publishers: &mut Publishers,
    unacknowledged: &mut Unacknowledged,
    budget: &mut Budget,
) -> Result<()> {
    let mut sent = false;
    while unacknowledged.bytes() < UNACKNOWLEDGED_LIMIT_BYTES {
        let Some(message) = budget.next(Instant::now()) else {
            break;
        };
        publishers.relay(&message)?;
        unacknowledged.push(message);
        sent = true;
    }
    if sent {
        context.traffic.set_budget(budget.stats());
    }
    Ok(())
}

/// On stop: sends what still waits for the budget and waits for the consumer host to
/// acknowledge everything, for at most `[network] drain_timeout_s` and only while the consumer
/// host is reachable (an agent that is done hands its last keyframes and final map to the
/// bridge, which may need minutes to send them within a tight budget).
fn drain(
    context: &BridgeContext,
    links: &EgressLinks,
    publishers: &mut Publishers,
    unacknowledged: &mut Unacknowledged,
    budget: &mut Budget,
) -> Result<()> {
    if budget.is_empty() && unacknowledged.len() == 0 {
        return Ok(());
    }
    let deadline = Instant::now() + Duration::from_secs_f64(context.network.drain_timeout_s);
    tracing::info!(
        waiting_bytes = budget.waiting_bytes(),
        unacknowledged = unacknowledged.len(),
        "stopping: sending what waits first"
    );
    while Instant::now() < deadline && links.reachable.load(Ordering::Relaxed) {
        for (agent_id, ack) in links.acknowledgements.try_iter() {
            unacknowledged.acknowledge(agent_id, ack);
        }
        if budget.is_empty() && unacknowledged.len() == 0 {
            context.traffic.set_budget(budget.stats());
            tracing::info!("everything sent and acknowledged");
            return Ok(());
        }
        send_due(context, publishers, unacknowledged, budget)?;
        let wait = budget
            .next_due_in(Instant::now())
            .map_or(Duration::from_millis(20), |due| {
                due.min(Duration::from_millis(20))
            });
        std::thread::sleep(wait);
    }
    tracing::warn!(
        waiting_bytes = budget.waiting_bytes(),
        unacknowledged = unacknowledged.len(),
        "stopped before everything was sent and acknowledged (consumer host unreachable or \
         [network] drain_timeout_s passed): the consensus asks the agents for what it misses"
    );
    Ok(())
}

/// Runs the bridge of the host that runs the consumers until `stop`.
pub async fn run_consumer_host(context: BridgeContext) -> Result<()> {
    // Unbounded, so that zenoh's receive path never waits on a slow local consumer: a receive
    // path that waits stalls the link, and zenoh closes a link whose blocked sends wait longer
    // than `wait_before_close`. The agent hosts' unacknowledged window
    // (`delivery::UNACKNOWLEDGED_LIMIT_BYTES` each) bounds what can pile up here.
    let (inbound_tx, inbound_rx) = crossbeam_channel::unbounded::<Received>();
    let (attached_tx, attached_rx) = crossbeam_channel::bounded::<()>(1);
    let ingress = spawn("ingress", &context.stop, {
        let context = context.clone();
        move || consumer_host_ingress(&context, &inbound_rx, &attached_tx)
    })?;
    let (receipts_tx, receipts_rx) = crossbeam_channel::unbounded();
    let agent_hosts = AgentHosts::default();
    let _receipts = context
        .session
        .declare_subscriber(context.keys.received_of_every_agent())
        .allowed_origin(Locality::Remote)
        .callback({
            let keys = context.keys.clone();
            move |sample: Sample| {
                let Some((agent_id, _)) = keys.parse(sample.key_expr().as_str()) else {
                    return;
                };
                match Acknowledgement::from_bytes(&sample.payload().to_bytes()) {
                    Ok(ack) => {
                        let _ = receipts_tx.send((agent_id, ack));
                    }
                    Err(e) => tracing::warn!(error = %e, "dropped a malformed receipt"),
                }
            }
        })
        .await
        .map_err(|e| anyhow!("zenoh receipt subscriber: {e}"))?;
    let _agent_hosts_watch = context
        .session
        .liveliness()
        .declare_subscriber(context.keys.every_agent_bridge())
        .history(true)
        .callback({
            let (hosts, keys) = (agent_hosts.clone(), context.keys.clone());
            move |sample: Sample| {
                let Some(agent_id) = keys.parse_agent_bridge(sample.key_expr().as_str()) else {
                    return;
                };
                hosts.update(agent_id, sample.kind() == SampleKind::Put);
            }
        })
        .await
        .map_err(|e| anyhow!("zenoh liveliness subscriber: {e}"))?;
    let egress = spawn("egress", &context.stop, {
        let context = context.clone();
        let links = ConsumerEgressLinks {
            receipts: receipts_rx,
            agent_hosts,
        };
        move || consumer_host_egress(&context, &links)
    })?;
    let mut subscribers = Vec::new();
    for topic in [
        Topic::Lifecycle,
        Topic::Descriptor,
        Topic::KeyframeImage,
        Topic::Patch,
    ] {
        let key = context.keys.topic_of_every_agent(topic);
        let (tx, keys) = (inbound_tx.clone(), context.keys.clone());
        let subscriber = context
            .session
            .declare_subscriber(&key)
            .allowed_origin(Locality::Remote)
            .callback(move |sample: Sample| {
                let Some((agent_id, _)) = keys.parse(sample.key_expr().as_str()) else {
                    tracing::warn!(key = %sample.key_expr(), "dropped a message on a key without an agent id");
                    return;
                };
                let encoding = match sample.attachment().map(|a| a.to_bytes()) {
                    None => Encoding::Raw,
                    Some(tag) => match tag.first().copied().map(Encoding::from_tag) {
                        Some(Ok(encoding)) => encoding,
                        _ => {
                            tracing::warn!(agent_id, topic = %topic, "dropped a message with an unknown encoding");
                            return;
                        }
                    },
                };
                let bytes = sample.payload().to_bytes().into_owned();
                let _ = tx.send(Received { agent_id, topic, encoding, bytes });
            })
            .await
            .map_err(|e| anyhow!("zenoh subscriber {key}: {e}"))?;
        subscribers.push(subscriber);
    }
    drop(inbound_tx);
    // Announced once the local consumers are there, so agent hosts attach to their agents only
    // when what they relay can be delivered.
    tracing::info!("waiting for the local consumers");
    while attached_rx.try_recv().is_err() {
        if context.stopping() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let _token = declare_tokens(&context, [context.keys.consumers_bridge()]).await?;
    tracing::info!("consumers attached: announced to agent hosts");
    context.until_stopped().await;
    drop(subscribers);
    join(ingress)?;
    join(egress)
}

/// An agent's message as it came off the network, decoded on the ingress thread (decoding an
/// image takes milliseconds, which zenoh's receive path should not wait for).
struct Received {
    agent_id: u32,
    topic: Topic,
    encoding: Encoding,
    bytes: Vec<u8>,
}

impl Received {
    fn decode(self) -> Result<RelayedMessage> {
        let raw = decode(self.topic, self.encoding, &self.bytes)?;
        Ok(RelayedMessage::from_network(
            self.agent_id,
            self.topic,
            raw,
        )?)
    }
}

fn consumer_host_ingress(
    context: &BridgeContext,
    inbound: &Receiver<Received>,
    attached: &Sender<()>,
) -> Result<()> {
    let mut ingress = ConsumerHostIngress::open(&context.transport)?;
    let mut acknowledgements = Publishers::new(context);
    let traffic = &context.traffic;
    let mut announced = false;
    while !context.stopping() {
        if !announced && ingress.consumers_attached() {
            announced = attached.send(()).is_ok();
        }
        let received = match inbound.recv_timeout(Duration::from_millis(20)) {
            Ok(received) => received,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        traffic.count_in(
            received.agent_id,
            topic_label(received.topic),
            received.bytes.len(),
        );
        let (agent_id, topic, encoding) = (received.agent_id, received.topic, received.encoding);
        let message = match received.decode() {
            Ok(message) => message,
            Err(e) => {
                tracing::warn!(agent_id, topic = %topic, encoding = encoding.name(),
                    error = %format!("{e:#}"), "dropped a message that does not decode");
                continue;
            }
        };
        match ingress.forward(&message) {
            Ok(_) => {
                let key = context.keys.delivered(message.agent_id);
                acknowledgements.put(&key, Acknowledgement::of(&message).to_bytes())?;
            }
            Err(TransportError::ShutdownRequested) => break,
            Err(e) => tracing::warn!(agent_id = message.agent_id, topic = %message.topic,
                sequence = message.stamp.sequence, error = %e,
                "could not hand a relayed message to the consumers"),
        }
    }
    Ok(())
}

/// Which agent hosts' bridges are reachable (their liveliness tokens), per agent id, and how
/// often each token has appeared.
#[derive(Clone, Default)]
struct AgentHosts(Arc<std::sync::Mutex<HashMap<u32, (bool, u64)>>>);

impl AgentHosts {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u32, (bool, u64)>> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn update(&self, agent_id: u32, present: bool) {
        let mut hosts = self.lock();
        let entry = hosts.entry(agent_id).or_insert((false, 0));
        entry.0 = present;
        if present {
            entry.1 += 1;
        }
    }

    /// (reachable now, appearances so far) of agent `agent_id`'s host.
    fn of(&self, agent_id: u32) -> (bool, u64) {
        self.lock().get(&agent_id).copied().unwrap_or((false, 0))
    }

    /// Every agent whose host was seen, with [`Self::of`] for each, in one look.
    fn all(&self) -> Vec<(u32, (bool, u64))> {
        self.lock()
            .iter()
            .map(|(&id, &state)| (id, state))
            .collect()
    }
}

/// Relays `messages` again (what a host had not acknowledged when its link came back).
fn send_again<'a>(
    publishers: &mut Publishers,
    messages: impl IntoIterator<Item = &'a WireMessage>,
) -> Result<()> {
    for message in messages {
        publishers.relay(message)?;
    }
    Ok(())
}

/// What the consumer host's egress hears from the zenoh side.
struct ConsumerEgressLinks {
    /// Agent hosts' receipts for corrections and control messages.
    receipts: Receiver<(u32, Acknowledgement)>,
    agent_hosts: AgentHosts,
}

/// Relays the consumers' corrections and control messages to the agent hosts, keeping each
/// until the agent host acknowledges it. While an agent's host is unreachable its messages are
/// only kept; when its host (re)appears, what it has not acknowledged goes again first, in
/// order, then the new ones (agents drop repeats by stamp); see `delivery`.
fn consumer_host_egress(context: &BridgeContext, links: &ConsumerEgressLinks) -> Result<()> {
    let mut egress = ConsumerHostEgress::open(&context.transport)?;
    let mut publishers = Publishers::new(context);
    let mut unacknowledged = Unacknowledged::default();
    // Per agent: the appearances of its host already served.
    let mut served: HashMap<u32, u64> = HashMap::new();
    let traffic = &context.traffic;
    while !context.stopping() {
        for (agent_id, ack) in links.receipts.try_iter() {
            unacknowledged.acknowledge(agent_id, ack);
        }
        for (agent_id, (present, appearances)) in links.agent_hosts.all() {
            let seen = served.entry(agent_id).or_insert(0);
            if !present || *seen == appearances {
                continue;
            }
            *seen = appearances;
            let again: Vec<&WireMessage> = unacknowledged
                .iter()
                .filter(|m| m.agent_id == agent_id)
                .collect();
            if !again.is_empty() {
                tracing::info!(
                    agent_id,
                    messages = again.len(),
                    "agent host (re)appeared: sending again what it had not acknowledged"
                );
            }
            send_again(&mut publishers, again)?;
        }
        match egress.recv_timeout(Duration::from_millis(20))? {
            None => {}
            Some(ConsumerHostOutgoing::Message(message)) => {
                let message = WireMessage::raw(message);
                let (present, appearances) = links.agent_hosts.of(message.agent_id);
                // Sent now only to a host that is there and has been served its backlog; the
                // loop above sends it with the backlog otherwise.
                if present && served.get(&message.agent_id) == Some(&appearances) {
                    publishers.relay(&message)?;
                }
                unacknowledged.push_bounded(message, CONSUMER_UNACKNOWLEDGED_LIMIT_BYTES);
            }
            Some(ConsumerHostOutgoing::GoodbyeSeen { agent_id }) => {
                traffic.count_out(agent_id, GOODBYE_SEEN, 0);
                publishers.put(&context.keys.goodbye_seen(agent_id), Vec::new())?;
            }
        }
    }
    Ok(())
}

/// One declared zenoh publisher per key, made at its first message.
struct Publishers<'c> {
    context: &'c BridgeContext,
    by_key: HashMap<String, Publisher<'static>>,
}

impl<'c> Publishers<'c> {
    fn new(context: &'c BridgeContext) -> Self {
        Self {
            context,
            by_key: HashMap::new(),
        }
    }

    /// Puts one relayed message on the network under its agent's topic key, counted in the
    /// traffic report; an encoding other than raw is named in the attachment.
    fn relay(&mut self, message: &WireMessage) -> Result<()> {
        let key = self.context.keys.topic(message.agent_id, message.topic);
        self.context.traffic.count_out(
            message.agent_id,
            topic_label(message.topic),
            message.bytes.len(),
        );
        let attachment = (message.encoding != Encoding::Raw).then(|| vec![message.encoding.tag()]);
        self.send(&key, message.bytes.clone(), attachment)
    }

    fn put(&mut self, key: &str, bytes: Vec<u8>) -> Result<()> {
        self.send(key, bytes, None)
    }

    fn send(&mut self, key: &str, bytes: Vec<u8>, attachment: Option<Vec<u8>>) -> Result<()> {
        if !self.by_key.contains_key(key) {
            let publisher = self
                .context
                .session
                .declare_publisher(key.to_string())
                .congestion_control(CONGESTION_CONTROL)
                .priority(PRIORITY)
                .allowed_destination(Locality::Remote)
                .wait()
                .map_err(|e| anyhow!("zenoh publisher {key}: {e}"))?;
            self.by_key.insert(key.to_string(), publisher);
        }
        self.by_key[key]
            .put(bytes)
            .attachment(attachment)
            .wait()
            .map_err(|e| anyhow!("zenoh put on {key}: {e}"))
    }
}

async fn declare_tokens(
    context: &BridgeContext,
    keys: impl IntoIterator<Item = String>,
) -> Result<Vec<zenoh::liveliness::LivelinessToken>> {
    let mut tokens = Vec::new();
    for key in keys {
        let token = context
            .session
            .liveliness()
            .declare_token(&key)
            .await
            .map_err(|e| anyhow!("zenoh liveliness token {key}: {e}"))?;
        tokens.push(token);
    }
    Ok(tokens)
}

/// Starts a thread of the bridge; when it fails, the whole bridge stops (the error is
/// returned at the join).
fn spawn(
    name: &str,
    stop: &Arc<AtomicBool>,
    work: impl FnOnce() -> Result<()> + Send + 'static,
) -> Result<JoinHandle<Result<()>>> {
    let stop = Arc::clone(stop);
    let thread = format!("bridge-{name}");
    std::thread::Builder::new()
        .name(thread.clone())
        .spawn(move || {
            let outcome = work();
            if let Err(e) = &outcome {
                tracing::error!(thread, error = %format!("{e:#}"), "stopping the bridge");
                stop.store(true, Ordering::Relaxed);
            }
            outcome
        })
        .with_context(|| format!("starting the {name} thread"))
}

fn join(handle: JoinHandle<Result<()>>) -> Result<()> {
    handle
        .join()
        .map_err(|_| anyhow!("a bridge thread panicked"))?
}
