//! The agent's side of the swarm (docs/method.md, The consensus: selection, and Protocol): every T_comm frames it publishes its
//! latest keyframe (global descriptor, RGB-D image, the keyframe's Gaussians) to the consensus,
//! receives corrections between frames, sends heartbeats, and at the end publishes its final map
//! and says goodbye.
//!
//! Nothing here blocks tracking for long: publishing copies one image and one patch into shared
//! memory; the descriptor (AlexNet at 320 px) is the costliest step, once per T_comm frames.
//! A failed send is logged and counted, never fatal: the agent's own outputs do not depend on the
//! consensus.
//!
//! With a link schedule ([`crate::link_schedule`]) the link is only up in the scheduled windows:
//! while it is down, the hello and every keyframe due for publication are queued (bounded, oldest
//! dropped) and delivered in order at reconnect, corrections wait, and heartbeats stop; the end
//! of the run flushes the queue before the goodbye whatever the schedule says.

use std::collections::{BTreeSet, VecDeque};
use std::hash::{Hash, Hasher};
use std::time::{Duration, Instant};

use alexnet::descriptor::GlobalDescriptorExtractor;
use anyhow::Context;
use config::Config;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::se3::isometry_to_tum;
use image::RgbImage;
use nalgebra::Isometry3;
use protocol::convert::{gaussian_record, rgbd_pixel};
use protocol::messages::{
    ControlMessage, CoordinateFrame, FINAL_MAP_KEYFRAME_ID, GaussianRecord,
    Intrinsics as WireIntrinsics, KeyframeDescriptor, Pose, RgbdPixel,
};
use protocol::transport::{
    AgentLink, Direction, KeyframeImageMeta, TransportConfig, TransportError,
};
use render_core::types::GaussianCloud;
use serde::Serialize;

use crate::link_schedule::{
    BoundedQueue, CorrectionArrival, CorrectionGate, LinkPlan, LinkSummary,
};
use crate::local_corrections::ReceivedCorrection;

/// Heartbeat period: the consensus learns that a quiet agent is still alive.
const HEARTBEAT_EVERY: Duration = Duration::from_secs(1);
/// How often an agent without a consensus looks for one. Every send waits up to the transport's
/// `delivery_timeout` for a consumer, so an agent whose consensus is not there (not started yet,
/// crashed, restarting) does not send at all: it queues as with the link down and checks,
/// without blocking, this often whether the consensus is back.
const PRESENCE_CHECK_EVERY: Duration = Duration::from_secs(1);

/// A keyframe the agent may publish.
pub struct PublishableKeyframe {
    pub keyframe_id: u64,
    pub frame_index: u64,
    pub timestamp_s: f64,
    pub agent_from_camera: Isometry3<f64>,
    pub intrinsics: Intrinsics,
    pub rgb: RgbImage,
    pub depth: DepthImage,
    /// The Gaussians this keyframe seeded, in the agent's frame.
    pub gaussians: GaussianCloud,
}

/// What the swarm link did, for metrics.json.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SwarmSummary {
    /// Keyframes delivered (those published again on request included).
    pub keyframes_published: usize,
    pub send_failures: usize,
    pub corrections_received: usize,
    /// Latest `world_from_agent` from the consensus, `[tx, ty, tz, qx, qy, qz, qw]`.
    pub world_from_agent: Option<[f64; 7]>,
    pub bytes_sent: u64,
    pub bytes_sent_per_s: f64,
    pub descriptor: String,
    /// The link's schedule and what it queued, delivered late and dropped.
    pub link: LinkSummary,
    /// Seconds after the link opened at which the consensus was found attached (the first entry
    /// is its first attachment; more mean it came back after being gone).
    pub consensus_attached_at_s: Vec<f64>,
    /// Seconds after the link opened at which a failed send found the consensus gone.
    pub consensus_lost_at_s: Vec<f64>,
    /// Messages (keyframes, the final map and the goodbye) never delivered because no
    /// consensus was there at the end of the run.
    pub undelivered_at_end: usize,
    /// The consensus's requests to publish a keyframe again (it arrived incomplete there).
    pub resend_requests: usize,
    /// Keyframes published again on request.
    pub keyframes_resent: usize,
    /// Requests for keyframes this agent no longer held (`[consensus.resend] agent_keeps`).
    pub resend_unavailable: usize,
    /// Ids of the keyframes delivered to the consensus, ascending.
    pub keyframes_published_ids: BTreeSet<u64>,
    /// Times a consensus restarted on its store said it was back
    /// (`ControlMessage::ConsensusResumed`).
    pub consensus_resumed: usize,
    /// Keyframes a resumed consensus lacked that this agent no longer held to publish again
    /// (`[consensus.resend] agent_keeps`): lost to the consensus.
    pub keyframes_unrecoverable: Vec<u64>,
    /// The reason the consensus gave when it asked the swarm to stop
    /// (`ControlMessage::Shutdown`); absent when it never did.
    pub stopped_by_consensus: Option<String>,
}

/// Whether the link is up now and what waits for it, for the progress file.
#[derive(Debug, Clone, Copy)]
pub struct LinkStatus {
    pub up: bool,
    pub queued_keyframes: usize,
}

/// One keyframe's messages, ready to send (the descriptor is computed when the keyframe is due,
/// so a queued keyframe costs nothing more at reconnect). The image and the Gaussians stay in
/// the keyframe's own buffers, and each send builds the wire pixels and records straight into
/// shared memory: no intermediate wire buffer, no copy of one (a re-send builds them again).
struct WireKeyframe {
    descriptor: KeyframeDescriptor,
    image_meta: KeyframeImageMeta,
    rgb: RgbImage,
    depth: DepthImage,
    gaussians: GaussianCloud,
    /// When it was due: its wait in the queue is measured from here.
    due: Instant,
}

impl WireKeyframe {
    fn bytes(&self) -> u64 {
        let pixels = self.image_meta.width as usize * self.image_meta.height as usize;
        (size_of::<KeyframeDescriptor>()
            + pixels * size_of::<RgbdPixel>()
            + self.gaussians.len() * size_of::<GaussianRecord>()) as u64
    }
}

pub struct SwarmLink {
    link: AgentLink,
    extractor: GlobalDescriptorExtractor,
    t_comm: usize,
    config_hash: u64,
    announced: bool,
    latest: Option<PublishableKeyframe>,
    frames_since_publication: usize,
    last_heartbeat: Instant,
    opened: Instant,
    summary: SwarmSummary,
    world_from_agent: Option<Isometry3<f64>>,
    plan: LinkPlan,
    /// The link's state at the last check (checked between frames).
    link_up: bool,
    /// The hello, when it was due while the link was down.
    /// The hello's camera and run anchor, until delivered.
    pending_hello: Option<(WireIntrinsics, u64)>,
    /// Keyframes due while the link was down, oldest first.
    queue: BoundedQueue<WireKeyframe>,
    /// Corrections that arrive while the link is down wait here (the newest only).
    corrections: CorrectionGate<ReceivedCorrection>,
    /// Whether the consensus was attached at the last check (false until the first one).
    consensus_present: bool,
    last_presence_check: Option<Instant>,
    /// The last published keyframes, newest last, kept for the consensus's resend requests.
    published: VecDeque<WireKeyframe>,
    keep_published: usize,
}

impl SwarmLink {
    /// Opens this agent's services (a second live agent with the same id is refused here). The
    /// link follows `plan` ([`LinkPlan::always_up`] without a schedule).
    pub fn connect(
        agent_id: u32,
        transport: &TransportConfig,
        config: &Config,
        plan: LinkPlan,
    ) -> anyhow::Result<Self> {
        let link = AgentLink::open(transport, agent_id)
            .with_context(|| format!("joining the swarm as agent {agent_id}"))?;
        let extractor =
            GlobalDescriptorExtractor::from_weights(config.consensus.descriptor_weights.as_deref());
        let summary = SwarmSummary {
            descriptor: extractor.kind().to_string(),
            link: LinkSummary::new(&plan),
            ..SwarmSummary::default()
        };
        let link_up = plan.is_up_now();
        if !link_up {
            tracing::info!(schedule = %plan.windows, "link down at start (schedule)");
        }
        Ok(Self {
            link,
            extractor,
            t_comm: config.consensus.t_comm,
            config_hash: config.hash(),
            announced: false,
            latest: None,
            // The first keyframe goes out at once: with the last one (sent at the end) even an
            // agent whose run is shorter than T_comm gives the consensus two views to place.
            frames_since_publication: config.consensus.t_comm,
            last_heartbeat: Instant::now(),
            opened: Instant::now(),
            summary,
            world_from_agent: None,
            queue: BoundedQueue::new(plan.queue_limit_bytes),
            plan,
            link_up,
            pending_hello: None,
            corrections: CorrectionGate::default(),
            consensus_present: false,
            last_presence_check: None,
            published: VecDeque::new(),
            keep_published: config.consensus.resend.agent_keeps,
        })
    }

    /// Whether [`Self::announce`] was called (the hello may still wait for the link).
    pub fn is_announced(&self) -> bool {
        self.announced
    }

    /// Announces the agent with its camera and its run anchor ([`run_anchor`] of its first
    /// frame); while the link is down the hello waits for it (ahead of everything queued).
    pub fn announce(&mut self, intrinsics: &Intrinsics, run_anchor: u64) {
        if self.announced {
            return;
        }
        self.announced = true;
        self.pending_hello = Some((WireIntrinsics::from(intrinsics), run_anchor));
        if self.refresh_link_state() {
            self.deliver_pending_hello();
        } else {
            self.summary.link.hello_delivered_late = true;
        }
    }

    /// Sends the hello if one is pending; false when it could not be delivered (it stays pending
    /// and is tried again after the next frame).
    fn deliver_pending_hello(&mut self) -> bool {
        let Some((intrinsics, run_anchor)) = self.pending_hello else {
            return true;
        };
        match self.link.announce(intrinsics, self.config_hash, run_anchor) {
            Ok(_) => {
                self.pending_hello = None;
                true
            }
            Err(error) => {
                self.summary.send_failures += 1;
                tracing::warn!(%error, "hello not delivered");
                self.recheck_presence();
                false
            }
        }
    }

    /// Whether the consensus is attached: known true until a send fails; while absent, looked
    /// up (without blocking) at most every [`PRESENCE_CHECK_EVERY`].
    fn consensus_attached(&mut self) -> bool {
        if self.consensus_present {
            return true;
        }
        if self
            .last_presence_check
            .is_some_and(|at| at.elapsed() < PRESENCE_CHECK_EVERY)
        {
            return false;
        }
        self.last_presence_check = Some(Instant::now());
        if self.link.consumers_present() {
            self.mark_attached();
        }
        self.consensus_present
    }

    fn mark_attached(&mut self) {
        self.consensus_present = true;
        self.summary
            .consensus_attached_at_s
            .push(self.opened.elapsed().as_secs_f64());
        tracing::info!(
            queued_keyframes = self.queue.len(),
            "consensus attached: delivering what waited for it"
        );
    }

    /// After a failed send: is the consensus still there? When it is not, later sends wait for
    /// it to come back instead of each waiting out the delivery timeout.
    fn recheck_presence(&mut self) {
        if self.consensus_present && !self.link.consumers_present() {
            self.consensus_present = false;
            self.last_presence_check = Some(Instant::now());
            self.summary
                .consensus_lost_at_s
                .push(self.opened.elapsed().as_secs_f64());
            tracing::warn!("consensus gone: keyframes are queued until it is back");
        }
    }

    /// Whether messages can go out now: the link is up by its schedule and the consensus is
    /// attached.
    fn refresh_link_state(&mut self) -> bool {
        self.refresh_schedule_state() && self.consensus_attached()
    }

    /// Whether the link is up now by its schedule, logging and recording transitions.
    fn refresh_schedule_state(&mut self) -> bool {
        let now_s = self.plan.elapsed_s();
        let up = self.plan.windows.is_up(now_s);
        if up != self.link_up {
            self.link_up = up;
            if up {
                self.summary.link.came_up_at_s.push(now_s);
                tracing::info!(
                    at_s = now_s,
                    queued_keyframes = self.queue.len(),
                    queued_mib = self.queue.bytes() as f64 / (1024.0 * 1024.0),
                    "link up (schedule): delivering what was queued"
                );
            } else {
                self.summary.link.went_down_at_s.push(now_s);
                tracing::info!(
                    at_s = now_s,
                    "link down (schedule): keyframes are queued, corrections wait"
                );
            }
        }
        up
    }

    /// What the link is doing, for the progress file.
    pub fn status(&self) -> LinkStatus {
        LinkStatus {
            up: self.link_up && self.consensus_present,
            queued_keyframes: self.queue.len(),
        }
    }

    /// Remembers the latest keyframe; it goes out at the next publication. The Gaussians seeded
    /// at keyframes that are not published travel with the next published one, so the consensus
    /// sees the whole map grow (its map registration needs the map, not only the published
    /// views), not just the share seeded at published keyframes.
    pub fn on_keyframe(&mut self, mut keyframe: PublishableKeyframe) {
        if let Some(unpublished) = self.latest.take() {
            let mut gaussians = unpublished.gaussians;
            gaussians.extend_from(&keyframe.gaussians);
            keyframe.gaussians = gaussians;
        }
        self.latest = Some(keyframe);
    }

    /// Between frames: publishes every T_comm frames, takes corrections, heartbeats. While the
    /// link is down, the due keyframe is queued and corrections wait; the first check with the
    /// link up again delivers the queue in order and hands out the newest held correction.
    /// Returns the newest correction to apply to the local maps, if one arrived.
    pub fn after_frame(&mut self) -> Option<ReceivedCorrection> {
        self.frames_since_publication += 1;
        let up = self.refresh_link_state();
        if up {
            self.flush_queue(false);
        }
        if self.frames_since_publication >= self.t_comm && self.latest.is_some() {
            self.publish_latest(up);
        }
        if up {
            self.answer_control_messages();
        }
        let correction = self.receive_corrections(up);
        if up && self.last_heartbeat.elapsed() >= HEARTBEAT_EVERY {
            self.last_heartbeat = Instant::now();
            if let Err(error) = self.link.heartbeat() {
                tracing::debug!(%error, "heartbeat not delivered");
                self.recheck_presence();
            }
        }
        correction
    }

    /// The consensus's reason, once it has asked the swarm to stop: the run should end after
    /// the current frame as on SIGTERM (final map, goodbye, outputs).
    pub fn stop_requested(&self) -> Option<&str> {
        self.summary.stopped_by_consensus.as_deref()
    }

    /// What the link did so far (the final figures come from [`Self::finish`]).
    pub fn summary(&self) -> &SwarmSummary {
        &self.summary
    }

    /// The consensus's latest estimate of this agent's frame in the world.
    pub fn world_from_agent(&self) -> Option<Isometry3<f64>> {
        self.world_from_agent
    }

    /// Prepares the latest keyframe's messages and sends them, or queues them when the link is
    /// down (or older keyframes still wait, so that order is kept).
    fn publish_latest(&mut self, link_up: bool) {
        let Some(keyframe) = self.latest.take() else {
            return;
        };
        self.frames_since_publication = 0;
        let _span = tracing::info_span!("publish keyframe", id = keyframe.keyframe_id).entered();
        let wire = match self.prepare(keyframe) {
            Ok(wire) => wire,
            Err(error) => {
                self.summary.send_failures += 1;
                tracing::warn!(error = %format!("{error:#}"), "keyframe not published");
                return;
            }
        };
        self.send_or_enqueue(wire, link_up);
    }

    /// Sends a keyframe now when nothing it must not overtake waits (the hello, queued
    /// keyframes) and the link is up; otherwise queues it behind them.
    fn send_or_enqueue(&mut self, wire: WireKeyframe, link_up: bool) {
        if link_up && self.queue.is_empty() && self.pending_hello.is_none() {
            self.send_now(wire);
        } else {
            self.enqueue(wire);
        }
    }

    /// Sends a keyframe's messages; a delivered keyframe is kept for resend requests.
    fn send_now(&mut self, wire: WireKeyframe) -> bool {
        match self.send(&wire) {
            Ok(()) => {
                self.summary.keyframes_published += 1;
                self.summary
                    .keyframes_published_ids
                    .insert(wire.descriptor.keyframe_id);
                self.keep_for_resend(wire);
                true
            }
            Err(error) => {
                self.summary.send_failures += 1;
                tracing::warn!(
                    keyframe = wire.descriptor.keyframe_id,
                    error = %format!("{error:#}"),
                    "keyframe not published"
                );
                self.recheck_presence();
                false
            }
        }
    }

    fn enqueue(&mut self, wire: WireKeyframe) {
        let keyframe_id = wire.descriptor.keyframe_id;
        let bytes = wire.bytes();
        self.summary.link.keyframes_queued += 1;
        for (dropped, dropped_bytes) in self.queue.push(wire, bytes) {
            self.summary.link.keyframes_dropped_queue_full += 1;
            self.summary.link.bytes_dropped_queue_full += dropped_bytes;
            tracing::warn!(
                dropped_keyframe = dropped.descriptor.keyframe_id,
                limit_bytes = self.plan.queue_limit_bytes,
                dropped_total = self.summary.link.keyframes_dropped_queue_full,
                "link queue full: oldest queued keyframe dropped"
            );
        }
        self.summary.link.queue_peak_bytes =
            self.summary.link.queue_peak_bytes.max(self.queue.bytes());
        tracing::debug!(
            keyframe_id,
            queued = self.queue.len(),
            "keyframe queued until the link is up"
        );
    }

    /// Delivers the pending hello and every queued keyframe, oldest first. `despite_schedule`:
    /// the end of the run, which delivers whatever the schedule says.
    fn flush_queue(&mut self, despite_schedule: bool) {
        if !self.deliver_pending_hello() {
            // Nothing may overtake the hello; it is tried again after the next frame.
            return;
        }
        let with_link_down = despite_schedule && !self.link_up;
        while self.consensus_present
            && let Some(wire) = self.queue.pop_front()
        {
            let waited_s = wire.due.elapsed().as_secs_f64();
            if self.send_now(wire) {
                self.summary.link.delivered_late(waited_s, with_link_down);
            }
        }
    }

    /// The messages of one keyframe: descriptor (the costly step), RGB-D image and patch.
    fn prepare(&mut self, keyframe: PublishableKeyframe) -> anyhow::Result<WireKeyframe> {
        let descriptor = self
            .extractor
            .describe(&keyframe.rgb)
            .context("computing the global descriptor")?;
        let mut message = KeyframeDescriptor::new(
            keyframe.keyframe_id,
            keyframe.frame_index,
            keyframe.timestamp_s,
        );
        message.camera_to_agent_world = Pose::from(&keyframe.agent_from_camera);
        message.intrinsics = WireIntrinsics::from(&keyframe.intrinsics);
        anyhow::ensure!(
            descriptor.len() == message.descriptor.len(),
            "descriptor has {} values, the wire carries {}",
            descriptor.len(),
            message.descriptor.len()
        );
        message.descriptor.copy_from_slice(&descriptor);
        let (width, height) = keyframe.rgb.dimensions();
        anyhow::ensure!(
            (keyframe.depth.width, keyframe.depth.height) == (width, height)
                && keyframe.depth.data.len() == width as usize * height as usize,
            "keyframe {}: depth image is {}x{} ({} values), colour image {width}x{height}",
            keyframe.keyframe_id,
            keyframe.depth.width,
            keyframe.depth.height,
            keyframe.depth.data.len()
        );
        let image_meta = KeyframeImageMeta {
            keyframe_id: keyframe.keyframe_id,
            frame_index: keyframe.frame_index,
            timestamp_s: keyframe.timestamp_s,
            camera_to_agent_world: message.camera_to_agent_world,
            intrinsics: message.intrinsics,
            width,
            height,
        };
        Ok(WireKeyframe {
            descriptor: message,
            image_meta,
            rgb: keyframe.rgb,
            depth: keyframe.depth,
            gaussians: keyframe.gaussians,
            due: Instant::now(),
        })
    }

    fn send(&mut self, wire: &WireKeyframe) -> anyhow::Result<()> {
        self.link.send_descriptor(&wire.descriptor)?;
        self.link.send_keyframe_image_with(&wire.image_meta, |i| {
            rgbd_pixel(&wire.rgb, &wire.depth, i)
        })?;
        self.link.send_patch_with(
            wire.descriptor.keyframe_id,
            CoordinateFrame::AgentWorld,
            wire.gaussians.len(),
            |i| gaussian_record(&wire.gaussians, i),
        )?;
        Ok(())
    }

    fn keep_for_resend(&mut self, wire: WireKeyframe) {
        if self.keep_published == 0 {
            return;
        }
        while self.published.len() >= self.keep_published {
            self.published.pop_front();
        }
        self.published.push_back(wire);
    }

    /// Answers the consensus's control messages: a keyframe that arrived incomplete there is
    /// published again (in order behind anything queued) if this agent still holds it.
    fn answer_control_messages(&mut self) {
        loop {
            let control = match self.link.try_recv_control() {
                Ok(Some(control)) => control,
                Ok(None) => break,
                Err(error @ TransportError::ControlFrame { .. }) => {
                    // That frame is consumed; the next one may be fine.
                    tracing::warn!(%error, "control message refused");
                    continue;
                }
                Err(error) => {
                    tracing::warn!(%error, "control messages not readable");
                    break;
                }
            };
            match control.message {
                ControlMessage::ResendKeyframe {
                    keyframe_id,
                    reason,
                } => {
                    self.summary.resend_requests += 1;
                    let held = self
                        .published
                        .iter()
                        .position(|w| w.descriptor.keyframe_id == keyframe_id);
                    let Some(wire) = held.and_then(|at| self.published.remove(at)) else {
                        self.summary.resend_unavailable += 1;
                        tracing::warn!(
                            keyframe_id,
                            %reason,
                            "consensus asks for a keyframe this agent no longer holds"
                        );
                        continue;
                    };
                    tracing::info!(keyframe_id, %reason, "publishing a keyframe again on request");
                    self.summary.keyframes_resent += 1;
                    // Control messages are only read with the link up.
                    self.send_or_enqueue(wire, true);
                }
                ControlMessage::ConsensusResumed { keyframes_held } => {
                    self.publish_again_what_the_consensus_lacks(&keyframes_held);
                }
                ControlMessage::Shutdown { reason } => {
                    tracing::warn!(
                        %reason,
                        "the consensus stops the swarm: finishing after this frame"
                    );
                    self.summary.stopped_by_consensus = Some(reason);
                }
                other => tracing::debug!(message = ?other, "control message ignored"),
            }
        }
    }

    /// A consensus restarted on its store holds `keyframes_held` of this agent: every keyframe
    /// delivered before that it does not hold was lost with its previous process (or never
    /// reached it). Those still held here are published again; the others are reported.
    fn publish_again_what_the_consensus_lacks(&mut self, keyframes_held: &[u64]) {
        self.summary.consensus_resumed += 1;
        let held: BTreeSet<u64> = keyframes_held.iter().copied().collect();
        let (lacking, kept): (VecDeque<WireKeyframe>, VecDeque<WireKeyframe>) =
            std::mem::take(&mut self.published)
                .into_iter()
                .partition(|wire| !held.contains(&wire.descriptor.keyframe_id));
        self.published = kept;
        let resent: BTreeSet<u64> = lacking
            .iter()
            .map(|wire| wire.descriptor.keyframe_id)
            .collect();
        let unrecoverable: Vec<u64> = self
            .summary
            .keyframes_published_ids
            .iter()
            .filter(|id| !held.contains(id) && !resent.contains(id))
            .copied()
            .collect();
        tracing::info!(
            held_there = held.len(),
            publishing_again = resent.len(),
            unrecoverable = unrecoverable.len(),
            "the consensus is back"
        );
        if !unrecoverable.is_empty() {
            tracing::warn!(
                keyframes = ?unrecoverable,
                "keyframes the consensus lost that this agent no longer holds \
                 ([consensus.resend] agent_keeps)"
            );
            self.summary.keyframes_unrecoverable.extend(unrecoverable);
        }
        for wire in lacking {
            self.summary.keyframes_resent += 1;
            // Control messages are only read with the link up.
            self.send_or_enqueue(wire, true);
        }
    }

    /// Takes every pending correction. With the link up, the newest (a held one, or one that
    /// just arrived) is returned for applying; with it down, the newest is held and replaces
    /// older held ones. Each correction states every published keyframe's pose, so only the
    /// newest matters.
    fn receive_corrections(&mut self, link_up: bool) -> Option<ReceivedCorrection> {
        let mut newest = None;
        if link_up && let Some(held) = self.corrections.release() {
            tracing::info!(
                translation_m = held.world_from_agent.translation.vector.norm(),
                "correction held while the link was down released"
            );
            newest = Some(held);
        }
        loop {
            match self.link.try_recv_correction() {
                Ok(Some(correction)) => {
                    let received = ReceivedCorrection {
                        world_from_agent: correction.header().agent_world_to_world.to_isometry(),
                        keyframes: correction
                            .poses()
                            .iter()
                            .map(|p| (p.keyframe_id, p.camera_to_world.to_isometry()))
                            .collect(),
                    };
                    self.summary.corrections_received += 1;
                    match self.corrections.arrive(received, link_up) {
                        CorrectionArrival::Apply(received) => {
                            tracing::debug!(
                                keyframes = received.keyframes.len(),
                                translation_m = received.world_from_agent.translation.vector.norm(),
                                "correction received"
                            );
                            newest = Some(received);
                        }
                        CorrectionArrival::Held { superseded } => {
                            self.summary.link.corrections_held += 1;
                            if superseded {
                                self.summary.link.corrections_superseded += 1;
                            }
                            tracing::debug!("correction held until the link is up");
                        }
                    }
                }
                Ok(None) => break,
                Err(error) => {
                    tracing::warn!(%error, "correction refused");
                    break;
                }
            }
        }
        if let Some(received) = &newest {
            self.world_from_agent = Some(received.world_from_agent);
        }
        newest
    }

    /// Ends the run on the link, whatever the schedule says (the consensus waits for every
    /// agent's goodbye): delivers the hello and the queue if they still wait, the last keyframe
    /// if it has not gone out, then the final map, and says goodbye (waiting until the consensus
    /// has everything).
    pub fn finish(mut self, final_map: &GaussianCloud) -> SwarmSummary {
        if !self.link_up && (!self.queue.is_empty() || self.pending_hello.is_some()) {
            tracing::info!(
                queued_keyframes = self.queue.len(),
                "end of run with the link down: delivering the queue before the goodbye"
            );
        }
        if !self.consensus_attached() {
            // One last wait for a consensus that is starting or restarting.
            match self.link.await_all_consumers() {
                Ok(()) => self.mark_attached(),
                Err(error) => {
                    self.summary.undelivered_at_end =
                        self.queue.len() + usize::from(self.latest.is_some()) + 1;
                    tracing::warn!(
                        %error,
                        queued_keyframes = self.queue.len(),
                        "no consensus at the end of the run: queued keyframes, the final map \
                         and the goodbye are not delivered (this agent's own outputs are \
                         complete)"
                    );
                    return self.finish_summary();
                }
            }
        }
        // The last keyframe goes behind anything still queued.
        self.publish_latest(true);
        self.flush_queue(true);
        if !self.queue.is_empty() {
            tracing::warn!(
                keyframes = self.queue.len(),
                "queued keyframes not delivered: the hello never got through"
            );
        }
        // Built in place in shared memory: the final map is the largest patch (up to hundreds
        // of thousands of Gaussians), and no intermediate record buffer is needed.
        if let Err(error) = self.link.send_patch_with(
            FINAL_MAP_KEYFRAME_ID,
            CoordinateFrame::AgentWorld,
            final_map.len(),
            |i| gaussian_record(final_map, i),
        ) {
            self.summary.send_failures += 1;
            tracing::warn!(%error, "final map not delivered");
        }
        let _ = self.receive_corrections(true);
        let summary = self.finish_summary();
        if let Err(error) = self.link.close() {
            tracing::warn!(%error, "goodbye not acknowledged");
        }
        summary
    }

    /// The summary with the link's traffic figures.
    fn finish_summary(&mut self) -> SwarmSummary {
        let bandwidth = self.link.bandwidth();
        self.summary.bytes_sent = bandwidth
            .entries
            .iter()
            .filter(|e| e.direction == Direction::Sent)
            .map(|e| e.traffic.bytes)
            .sum();
        self.summary.bytes_sent_per_s =
            self.summary.bytes_sent as f64 / self.opened.elapsed().as_secs_f64().max(1e-9);
        self.summary.world_from_agent = self.world_from_agent.as_ref().map(isometry_to_tum);
        std::mem::take(&mut self.summary)
    }
}

/// The run anchor of an agent's hello (`Lifecycle::run_anchor`): a hash of its dataset (the
/// canonical path when it is one, else the spec as given) and of its first frame's index and
/// timestamp. The agent's tracked frame is anchored at that frame, so equal anchors mean the
/// same frame: a restart with the same frames sends the same anchor, one on other frames
/// (another start or another sequence) a different one.
pub fn run_anchor(dataset: &str, first_frame_index: usize, first_timestamp_s: f64) -> u64 {
    let identity = std::fs::canonicalize(dataset)
        .map(|path| path.display().to_string())
        .unwrap_or_else(|_| dataset.to_owned());
    let mut hasher = std::collections::hash_map::DefaultHasher::new();
    (identity, first_frame_index, first_timestamp_s.to_bits()).hash(&mut hasher);
    hasher.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The keyframe messages waiting at `consumer`.
    #[derive(Default)]
    struct Received {
        descriptors: Vec<u64>,
        images: Vec<(u64, Vec<RgbdPixel>)>,
        patches: Vec<(u64, Vec<GaussianRecord>)>,
    }

    impl Received {
        /// Keyframe ids: (descriptors, images, patches).
        fn ids(&self) -> (Vec<u64>, Vec<u64>, Vec<u64>) {
            (
                self.descriptors.clone(),
                self.images.iter().map(|(id, _)| *id).collect(),
                self.patches.iter().map(|(id, _)| *id).collect(),
            )
        }
    }

    fn received_keyframes(consumer: &mut protocol::transport::ConsumerLink) -> Received {
        use protocol::transport::Incoming;
        const QUIET: Duration = Duration::from_millis(500);
        let mut received = Received::default();
        while let Some(message) = consumer.recv_timeout(QUIET).unwrap() {
            match message {
                Incoming::Descriptor(d) => received.descriptors.push(d.keyframe_id),
                Incoming::KeyframeImage(k) => received
                    .images
                    .push((k.header().keyframe_id, k.pixels().to_vec())),
                Incoming::Patch(p) => received
                    .patches
                    .push((p.header().keyframe_id, p.records().to_vec())),
                Incoming::Lifecycle(_) => {}
            }
        }
        received
    }

    /// A consumer and agent 0 announced to it (publishing every keyframe), in a namespace of
    /// its own, with the agent's 32x24 camera.
    fn announced_agent(
        namespace: &str,
    ) -> (protocol::transport::ConsumerLink, SwarmLink, Intrinsics) {
        let transport =
            TransportConfig::with_namespace(format!("{namespace}-{}", std::process::id()));
        let consumer = protocol::transport::ConsumerLink::open(&transport).unwrap();
        let mut config = Config::default();
        config.consensus.t_comm = 1;
        let mut swarm = SwarmLink::connect(0, &transport, &config, LinkPlan::always_up()).unwrap();
        let intrinsics = Intrinsics::new(40.0, 40.0, 16.0, 12.0, 32, 24);
        swarm.announce(&intrinsics, run_anchor("synthetic", 0, 0.0));
        (consumer, swarm, intrinsics)
    }

    #[test]
    fn a_keyframe_whose_depth_and_colour_sizes_differ_is_refused_not_sent() {
        let (mut consumer, mut swarm, intrinsics) = announced_agent("size-mismatch");
        swarm.on_keyframe(PublishableKeyframe {
            keyframe_id: 3,
            frame_index: 30,
            timestamp_s: 3.0,
            agent_from_camera: Isometry3::identity(),
            intrinsics,
            rgb: RgbImage::from_pixel(32, 24, image::Rgb([1, 2, 3])),
            depth: DepthImage {
                width: 16,
                height: 12,
                data: vec![1.5; 16 * 12],
            },
            gaussians: GaussianCloud::default(),
        });
        swarm.after_frame();
        assert_eq!(
            received_keyframes(&mut consumer).ids(),
            (vec![], vec![], vec![])
        );
        assert_eq!(swarm.summary().send_failures, 1);
    }

    #[test]
    fn a_keyframe_the_consensus_asks_for_again_is_published_again() {
        let (mut consumer, mut swarm, intrinsics) = announced_agent("resend-agent");
        let keyframe = |keyframe_id| PublishableKeyframe {
            keyframe_id,
            frame_index: keyframe_id * 10,
            timestamp_s: keyframe_id as f64,
            agent_from_camera: Isometry3::identity(),
            intrinsics,
            rgb: RgbImage::from_fn(32, 24, |x, y| {
                image::Rgb([(x * 8) as u8, (y * 10) as u8, 7])
            }),
            depth: DepthImage {
                width: 32,
                height: 24,
                data: vec![1.5; 32 * 24],
            },
            gaussians: {
                let mut cloud = GaussianCloud::default();
                for i in 0..5 {
                    let v = i as f32;
                    cloud.push(
                        [v, 1.0, 2.0],
                        [-4.0; 3],
                        [1.0, 0.0, 0.0, v],
                        v - 2.0,
                        [0.5; 3],
                    );
                }
                cloud
            },
        };
        // What the consumer must see: the keyframe's pixels and Gaussians, built in place.
        let expected_pixels: Vec<RgbdPixel> = {
            let k = keyframe(7);
            (0..32 * 24)
                .map(|i| rgbd_pixel(&k.rgb, &k.depth, i))
                .collect()
        };
        let expected_records: Vec<GaussianRecord> = {
            let k = keyframe(7);
            (0..5).map(|i| gaussian_record(&k.gaussians, i)).collect()
        };
        assert_eq!(expected_pixels[33].rgb, [8, 10, 7]);
        assert_eq!(expected_records[3].mean, [3.0, 1.0, 2.0]);
        let content_is_the_keyframes = |received: &Received| {
            assert_eq!(received.images[0].1, expected_pixels);
            assert_eq!(received.patches[0].1, expected_records);
        };
        swarm.on_keyframe(keyframe(7));
        assert!(swarm.after_frame().is_none());
        let received = received_keyframes(&mut consumer);
        assert_eq!(received.ids(), (vec![7], vec![7], vec![7]));
        content_is_the_keyframes(&received);

        let ask = |keyframe_id| ControlMessage::ResendKeyframe {
            keyframe_id,
            reason: "test".into(),
        };
        consumer.send_control(0, &ask(7)).unwrap();
        consumer.send_control(0, &ask(99)).unwrap();
        swarm.after_frame();
        let received = received_keyframes(&mut consumer);
        assert_eq!(
            received.ids(),
            (vec![7], vec![7], vec![7]),
            "keyframe 7 again, nothing for the unknown 99"
        );
        content_is_the_keyframes(&received);
        let summary = swarm.summary();
        assert_eq!(summary.resend_requests, 2);
        assert_eq!(summary.keyframes_resent, 1);
        assert_eq!(summary.resend_unavailable, 1);
        assert_eq!(summary.send_failures, 0);
    }
}
