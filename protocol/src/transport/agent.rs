//! [`AgentLink`]: the transport endpoint of one agent process. It publishes descriptors,
//! keyframe images, patches and lifecycle messages to the consumers, and receives corrections
//! and control messages from them.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::Node;
use iceoryx2::service::port_factory::event::PortFactory as EventService;

use super::error::{port_error, wait_error};
use super::inbox::Inbox;
use super::open::{create_node, open_agent_wake, open_consumers_wake, open_lifecycle};
use super::outbox::{BuiltInPlace, Elements, Outbox, Recipients, SendReport, Sent, WhenAbsent};
use super::sequence::{ReceiveBook, new_epoch};
use super::topic::{
    ControlTopic, CorrectionTopic, DescriptorTopic, KeyframeImageTopic, LifecycleTopic, PatchTopic,
    TopicService,
};
use super::traffic::{BandwidthReport, TrafficTable};
use super::wake::{Receiving, WAKE_GOODBYE_SEEN, Waiting, consumers_wake_event, receive_within};
use super::{ControlSample, CorrectionSample, Ipc, TransportConfig, TransportError, checks};
use crate::codec;
use crate::messages::{
    ControlMessage, CoordinateFrame, GaussianRecord, Intrinsics, KeyframeDescriptor,
    KeyframeImageHeader, Lifecycle, PatchHeader, Pose, RgbdPixel, Stamp,
};
use crate::services::Topic;

/// What an agent says about a keyframe image besides its pixels; the transport adds the
/// [`Stamp`] and builds the [`KeyframeImageHeader`] from it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeyframeImageMeta {
    /// The agent's id of the keyframe; its descriptor and patch carry the same id.
    pub keyframe_id: u64,
    /// Index of the frame in the agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// Camera-to-agent-world transform of the keyframe (agent's own world frame).
    pub camera_to_agent_world: Pose,
    /// Intrinsics of the image as sent (scaled with it when the agent downscales); their
    /// `width`/`height` must equal the image size.
    pub intrinsics: Intrinsics,
    /// Image size; the pixel slice must hold exactly `width * height` pixels, row-major.
    pub width: u32,
    /// Image height in pixels (rows).
    pub height: u32,
}

/// The transport endpoint of one agent process.
pub struct AgentLink {
    agent_id: u32,
    epoch: u64,
    config: TransportConfig,
    descriptor: Outbox<DescriptorTopic>,
    patch: Outbox<PatchTopic>,
    keyframe_image: Outbox<KeyframeImageTopic>,
    lifecycle: Outbox<LifecycleTopic>,
    correction: Inbox<CorrectionTopic>,
    control: Inbox<ControlTopic>,
    waiting: Waiting,
    consumers_notifier: Notifier<Ipc>,
    traffic: TrafficTable,
    book: ReceiveBook,
    said_goodbye: bool,
    // Kept last: ports above must be dropped before the services and the node that own them.
    _wake_service: EventService<Ipc>,
    _consumers_wake_service: EventService<Ipc>,
    node: Node<Ipc>,
}

/// How often a goodbye's wait checks that its consumers are still attached: a restarted bridge
/// reattaches after about a second (scripts/simulated_host.sh), so its predecessor's death is
/// seen in between.
const GOODBYE_PRESENCE_CHECK_EVERY: Duration = Duration::from_millis(200);

impl AgentLink {
    /// Opens the agent's services and ports. Cleans up dead processes' leftovers first, and
    /// refuses an id that a live agent already uses. Send [`AgentLink::announce`] next.
    pub fn open(config: &TransportConfig, agent_id: u32) -> Result<Self, TransportError> {
        config.validate()?;
        if agent_id >= config.max_agents {
            return Err(TransportError::AgentIdOutOfRange {
                agent_id,
                max_agents: config.max_agents,
            });
        }
        let names = config.names();
        let node = create_node(&format!("mac-agent-{agent_id}"))?;
        // Opened before the agent's own topics: an id outside the swarm must not leave them.
        let (lifecycle_service, swarm_max_agents) = open_lifecycle(&node, config)?;
        if agent_id >= swarm_max_agents {
            return Err(TransportError::AgentIdOutsideSwarm {
                agent_id,
                swarm_max_agents,
                namespace: config.namespace.clone(),
            });
        }
        // The first exclusive port: failing here with "too many publishers" means a live twin.
        let descriptor = Outbox::open(&node, config, agent_id)?;
        let patch = Outbox::open(&node, config, agent_id)?;
        let keyframe_image = Outbox::open(&node, config, agent_id)?;
        let lifecycle = Outbox::on(names.lifecycle(), lifecycle_service, config, agent_id)?;
        let correction = Inbox::open(&node, config, agent_id)?;
        let control = Inbox::open(&node, config, agent_id)?;

        let wake_service = open_agent_wake(&node, config, agent_id)?;
        let wake_listener = wake_service
            .listener_builder()
            .create()
            .map_err(|e| port_error(&names.agent_wake(agent_id), "listener", e))?;
        let consumers_wake_service = open_consumers_wake(&node, config)?;
        let consumers_notifier = consumers_wake_service
            .notifier_builder()
            .create()
            .map_err(|e| port_error(&names.consumers_wake(), "notifier", e))?;

        Ok(Self {
            agent_id,
            epoch: new_epoch(),
            config: config.clone(),
            descriptor,
            patch,
            keyframe_image,
            lifecycle,
            correction,
            control,
            waiting: Waiting::new(wake_listener, config),
            consumers_notifier,
            traffic: TrafficTable::new(),
            book: ReceiveBook::default(),
            said_goodbye: false,
            _wake_service: wake_service,
            _consumers_wake_service: consumers_wake_service,
            node,
        })
    }

    /// The agent id this link publishes as.
    pub fn agent_id(&self) -> u32 {
        self.agent_id
    }

    /// This incarnation's epoch (see [`Stamp::epoch`]).
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Setting this flag makes every blocking call return [`TransportError::ShutdownRequested`]
    /// within `wait_slice`.
    pub fn shutdown_handle(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.waiting.shutdown)
    }

    /// Consumers currently attached to this agent's patch topic.
    pub fn attached_consumers(&self) -> usize {
        self.patch.attached()
    }

    /// Subscribers attached to each outgoing topic, with its service name.
    fn outgoing(&self) -> [(usize, &str); 4] {
        [
            (self.descriptor.attached(), &self.descriptor.name),
            (self.patch.attached(), &self.patch.name),
            (self.lifecycle.attached(), &self.lifecycle.name),
            (self.keyframe_image.attached(), &self.keyframe_image.name),
        ]
    }

    /// True when `required_consumers` consumers are attached to every outgoing topic now (a
    /// send would not wait for one). Does not block; first reclaims what processes that died
    /// left behind, so a killed consensus does not look attached.
    pub fn consumers_present(&self) -> bool {
        self.node.try_cleanup_dead_nodes();
        let required = self.config.required_consumers;
        self.outgoing()
            .iter()
            .all(|&(attached, _)| attached >= required)
    }

    /// Waits (event-driven) up to the configured `delivery_timeout` for consumers to attach to
    /// every outgoing topic; [`TransportError::NoConsumer`] when they do not.
    pub fn await_all_consumers(&self) -> Result<(), TransportError> {
        let (required, config) = (self.config.required_consumers, &self.config);
        let (listener, shutdown) = (&self.waiting.listener, &*self.waiting.shutdown);
        self.descriptor
            .await_attached(required, config, listener, shutdown)?;
        self.patch
            .await_attached(required, config, listener, shutdown)?;
        self.lifecycle
            .await_attached(required, config, listener, shutdown)?;
        self.keyframe_image
            .await_attached(required, config, listener, shutdown)
    }

    /// The consumers, as the receivers of this agent's `topic`: the send waits for
    /// `required_consumers` of them to attach, and wakes them with the topic's event.
    fn to_consumers(&self, topic: Topic) -> Recipients<'_> {
        Recipients {
            required: self.config.required_consumers,
            when_absent: WhenAbsent::Wait(&self.waiting.listener),
            wake: &self.consumers_notifier,
            wake_event: consumers_wake_event(self.agent_id, topic),
            config: &self.config,
            shutdown: &self.waiting.shutdown,
        }
    }

    fn stamp(&self, sequence: u64) -> Stamp {
        Stamp {
            agent_id: self.agent_id,
            reserved: 0,
            epoch: self.epoch,
            sequence,
        }
    }

    /// Counts a send of `T` (or its failure with a full queue) in the bandwidth report.
    fn account<T: TopicService>(
        &mut self,
        outcome: Result<Sent, TransportError>,
    ) -> Result<SendReport, TransportError> {
        let report = self.traffic.count_send(self.agent_id, T::TOPIC, outcome)?;
        self.waiting.mark_activity();
        Ok(report)
    }

    /// Announces this incarnation (first message after [`AgentLink::open`]); `run_anchor` as in
    /// [`Lifecycle::run_anchor`].
    pub fn announce(
        &mut self,
        intrinsics: Intrinsics,
        config_hash: u64,
        run_anchor: u64,
    ) -> Result<SendReport, TransportError> {
        self.send_lifecycle(Lifecycle::hello(intrinsics, config_hash, run_anchor))
    }

    /// Heartbeat; also reclaims leftovers of processes that died since the last one.
    pub fn heartbeat(&mut self) -> Result<SendReport, TransportError> {
        self.node.try_cleanup_dead_nodes();
        self.send_lifecycle(Lifecycle::alive())
    }

    /// Orderly goodbye: waits until every consumer that received it has drained this agent's
    /// topics and acknowledged, so nothing sent before is lost when the process exits.
    pub fn close(mut self) -> Result<SendReport, TransportError> {
        self.said_goodbye = true;
        self.goodbye(self.config.delivery_timeout)
    }

    /// [`Self::close`] that keeps the link: when the goodbye was lost
    /// ([`TransportError::GoodbyeLost`]: a bridge on the way died holding it and what came
    /// before), the agent can deliver again what may have been lost and say goodbye once more.
    pub fn say_goodbye(&mut self) -> Result<SendReport, TransportError> {
        self.said_goodbye = true;
        self.goodbye(self.config.delivery_timeout)
    }

    /// Sends `Goodbye` and waits up to `ack_timeout` for every recipient's acknowledgement;
    /// [`TransportError::GoodbyeLost`] as soon as the consumers are no longer all attached (one
    /// that took the goodbye died before acknowledging it).
    fn goodbye(&mut self, ack_timeout: Duration) -> Result<SendReport, TransportError> {
        let report = self.send_lifecycle(Lifecycle::goodbye())?;
        let start = Instant::now();
        let mut acknowledged = 0u64;
        let mut presence_checked = start;
        while acknowledged < report.recipients as u64 {
            let waited = start.elapsed();
            if presence_checked.elapsed() >= GOODBYE_PRESENCE_CHECK_EVERY {
                presence_checked = Instant::now();
                if !self.consumers_present() {
                    return Err(TransportError::GoodbyeLost { waited });
                }
            }
            if waited >= ack_timeout {
                return Err(TransportError::GoodbyeUnacknowledged {
                    acknowledged,
                    expected: report.recipients,
                    waited,
                });
            }
            let slice = self.config.wait_slice.min(ack_timeout - waited);
            self.waiting
                .listener
                .timed_wait(
                    |event| {
                        if event.id.as_value() == WAKE_GOODBYE_SEEN {
                            acknowledged += event.count;
                        }
                    },
                    slice,
                )
                .map_err(wait_error)?;
        }
        Ok(report)
    }

    fn send_lifecycle(&mut self, message: Lifecycle) -> Result<SendReport, TransportError> {
        let outcome = self
            .lifecycle
            .send_value(&self.to_consumers(Topic::Lifecycle), |sequence| Lifecycle {
                stamp: self.stamp(sequence),
                ..message
            });
        self.account::<LifecycleTopic>(outcome)
    }

    /// Publishes a keyframe descriptor. The stamp is filled in here; the descriptor must be
    /// L2-normalised and the pose valid.
    pub fn send_descriptor(
        &mut self,
        descriptor: &KeyframeDescriptor,
    ) -> Result<SendReport, TransportError> {
        checks::descriptor(&self.descriptor.name, descriptor)?;
        let outcome =
            self.descriptor
                .send_value(&self.to_consumers(Topic::Descriptor), |sequence| {
                    KeyframeDescriptor {
                        stamp: self.stamp(sequence),
                        ..*descriptor
                    }
                });
        self.account::<DescriptorTopic>(outcome)
    }

    /// Publishes a patch by copying `records` into shared memory (one copy).
    pub fn send_patch(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        records: &[GaussianRecord],
    ) -> Result<SendReport, TransportError> {
        self.publish_patch(keyframe_id, frame, records)
    }

    /// Publishes a patch of `count` records built in place in shared memory by `build(i)`: no
    /// copy of a finished buffer (zero-copy when the producer computes records on the fly).
    /// `build` runs again for a re-send after a full queue, so it must be repeatable.
    pub fn send_patch_with(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        count: usize,
        build: impl FnMut(usize) -> GaussianRecord,
    ) -> Result<SendReport, TransportError> {
        self.publish_patch(keyframe_id, frame, BuiltInPlace { len: count, build })
    }

    fn publish_patch(
        &mut self,
        keyframe_id: u64,
        frame: CoordinateFrame,
        records: impl Elements<GaussianRecord>,
    ) -> Result<SendReport, TransportError> {
        let count = records.len() as u64;
        let header = |sequence| PatchHeader {
            stamp: self.stamp(sequence),
            keyframe_id,
            count,
            frame: frame as u32,
            reserved: 0,
        };
        let outcome = self
            .patch
            .send_slice(&self.to_consumers(Topic::Patch), header, records);
        self.account::<PatchTopic>(outcome)
    }

    /// Publishes a keyframe's RGB-D image by copying `pixels` (row-major, `width * height` of
    /// them) into shared memory (one copy). Refuses an empty image, a pixel count that does not
    /// match the size, intrinsics of another size and an invalid pose
    /// ([`TransportError::InvalidMessage`]).
    pub fn send_keyframe_image(
        &mut self,
        meta: &KeyframeImageMeta,
        pixels: &[RgbdPixel],
    ) -> Result<SendReport, TransportError> {
        self.publish_keyframe_image(meta, pixels)
    }

    /// Publishes a keyframe image whose `width * height` pixels are built in place in shared
    /// memory by `build(i)` (`i` row-major): no intermediate interleaved buffer when the agent
    /// holds colour and depth in separate images. `build` runs again for a re-send after a full
    /// queue, so it must be repeatable. Validated like [`AgentLink::send_keyframe_image`].
    pub fn send_keyframe_image_with(
        &mut self,
        meta: &KeyframeImageMeta,
        build: impl FnMut(usize) -> RgbdPixel,
    ) -> Result<SendReport, TransportError> {
        let len = meta.width as usize * meta.height as usize;
        self.publish_keyframe_image(meta, BuiltInPlace { len, build })
    }

    fn publish_keyframe_image(
        &mut self,
        meta: &KeyframeImageMeta,
        pixels: impl Elements<RgbdPixel>,
    ) -> Result<SendReport, TransportError> {
        checks::keyframe_image(&self.keyframe_image.name, meta, pixels.len())?;
        let header = |sequence| KeyframeImageHeader {
            stamp: self.stamp(sequence),
            keyframe_id: meta.keyframe_id,
            frame_index: meta.frame_index,
            timestamp_s: meta.timestamp_s,
            camera_to_agent_world: meta.camera_to_agent_world,
            intrinsics: meta.intrinsics,
            width: meta.width,
            height: meta.height,
        };
        let outcome = self.keyframe_image.send_slice(
            &self.to_consumers(Topic::KeyframeImage),
            header,
            pixels,
        );
        self.account::<KeyframeImageTopic>(outcome)
    }

    /// Next pending correction, without blocking.
    pub fn try_recv_correction(&mut self) -> Result<Option<CorrectionSample>, TransportError> {
        let agent_id = self.agent_id;
        let received = self.correction.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| {
                checks::correction_header(sample.user_header(), sample.payload().len(), agent_id)
            },
            |_| agent_id,
        )?;
        Ok(received.map(|(sample, delivery)| CorrectionSample { sample, delivery }))
    }

    /// Waits (event-driven) up to `timeout` for a correction.
    pub fn recv_correction_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<CorrectionSample>, TransportError> {
        receive_within(self, timeout, Self::try_recv_correction)
    }

    /// Next pending control message, without blocking. A frame that does not decode (another
    /// codec format version, corruption) is consumed and reported as
    /// [`TransportError::ControlFrame`]; the next call goes on with the following one.
    pub fn try_recv_control(&mut self) -> Result<Option<ControlSample>, TransportError> {
        let agent_id = self.agent_id;
        let Some((sample, delivery)) = self.control.receive(
            &mut self.book,
            &mut self.traffic,
            |sample| checks::control_header(sample.user_header(), sample.payload().len(), agent_id),
            |_| agent_id,
        )?
        else {
            return Ok(None);
        };
        let header = *sample.user_header();
        let message = codec::decode::<ControlMessage>(sample.payload()).map_err(|source| {
            TransportError::ControlFrame {
                service: self.control.name.clone(),
                sequence: header.stamp.sequence,
                source,
            }
        })?;
        Ok(Some(ControlSample {
            header,
            message,
            delivery,
        }))
    }

    /// Waits (event-driven) up to `timeout` for a control message.
    pub fn recv_control_timeout(
        &mut self,
        timeout: Duration,
    ) -> Result<Option<ControlSample>, TransportError> {
        receive_within(self, timeout, Self::try_recv_control)
    }

    /// Bytes and messages per topic sent (and corrections received) since [`AgentLink::open`].
    pub fn bandwidth(&self) -> BandwidthReport {
        self.traffic.report()
    }
}

impl Receiving for AgentLink {
    fn waiting(&mut self) -> &mut Waiting {
        &mut self.waiting
    }
}

impl Drop for AgentLink {
    fn drop(&mut self) {
        // Best effort and short (one wait slice), since drop must not hang: consumers learn of
        // the stop. `close()` is the orderly path that also waits for them to drain.
        if !self.said_goodbye
            && self.lifecycle.attached() > 0
            && let Err(e) = self.goodbye(self.config.wait_slice)
        {
            tracing::warn!(agent_id = self.agent_id, error = %e, "goodbye on drop failed");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agent_id_out_of_range_is_refused_before_touching_shared_memory() {
        let config = TransportConfig {
            max_agents: 2,
            ..TransportConfig::with_namespace("unit-range")
        };
        match AgentLink::open(&config, 2) {
            Err(TransportError::AgentIdOutOfRange {
                agent_id: 2,
                max_agents: 2,
            }) => {}
            Err(other) => panic!("unexpected error {other}"),
            Ok(_) => panic!("agent id 2 must be refused with max_agents 2"),
        }
    }
}
