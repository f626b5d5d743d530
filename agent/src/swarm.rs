//! The agent's side of the swarm (docs/method.md, The consensus: selection, and Protocol): every T_comm frames it publishes its
//! latest keyframe (global descriptor, RGB-D image, the keyframe's Gaussians) to the consensus,
//! receives corrections between frames, sends heartbeats, and at the end publishes its final map
//! and says goodbye.
//!
//! Nothing here blocks tracking for long: publishing copies one image and one patch into shared
//! memory; the descriptor (AlexNet at 320 px), the costliest step, is computed beside the frame
//! loop ([`crate::describer`]) and the keyframe goes out after the first frame that finds it done.
//! A failed send is logged and counted, never fatal: the agent's own outputs do not depend on the
//! consensus.
//!
//! With a link schedule ([`crate::link_schedule`]) the link is only up in the scheduled windows:
//! while it is down, the hello and every keyframe due for publication are queued (bounded, oldest
//! dropped) and delivered in order at reconnect, corrections wait, and heartbeats stop; the end
//! of the run flushes the queue before the goodbye whatever the schedule says.

use std::collections::{BTreeSet, VecDeque};
use std::hash::{Hash, Hasher};
use std::path::Path;
use std::time::{Duration, Instant};

use alexnet::descriptor::GlobalDescriptorExtractor;
use anyhow::Context;
use config::Config;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::se3::{isometry_from_tum, isometry_to_tum};
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

use crate::describer::{Described, Describer};
use crate::link_schedule::{
    BoundedQueue, CorrectionArrival, CorrectionGate, LinkPlan, LinkSummary,
};
use crate::local_corrections::ReceivedCorrection;
use crate::spool::{KeyframeSpool, SpooledKeyframe};

/// Goodbyes an agent says at the end of its run while they are lost (see
/// `SwarmLink::say_goodbye`).
const GOODBYE_ATTEMPTS: usize = 3;
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
    /// Goodbyes said again after one was not acknowledged (with the keyframes the consensus had
    /// not confirmed and the final map before each).
    pub goodbye_retries: usize,
    /// Times the consensus said messages of this agent were lost on the way
    /// (`ControlMessage::MessagesLost`).
    pub messages_lost_reports: usize,
    /// Keyframes a resumed consensus lacked that this agent no longer held to publish again
    /// (`[consensus.resend] agent_keeps` in memory, `agent_spool_bytes` on disk): lost to the
    /// consensus.
    pub keyframes_unrecoverable: Vec<u64>,
    /// Delivered keyframes written to the spool (beyond `agent_keeps`, not confirmed yet), the
    /// spool's peak size, keyframes it dropped to stay within `agent_spool_bytes`, and writes
    /// that failed (a full disk).
    pub keyframes_spooled: usize,
    pub spool_peak_bytes: u64,
    pub keyframes_spool_dropped: Vec<u64>,
    pub spool_failures: usize,
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
    /// The keyframe as the spool keeps it.
    fn spooled(&self) -> SpooledKeyframe {
        let gaussians = &self.gaussians;
        SpooledKeyframe {
            keyframe_id: self.descriptor.keyframe_id,
            frame_index: self.descriptor.frame_index,
            timestamp_s: self.descriptor.timestamp_s,
            agent_from_camera: isometry_to_tum(
                &self.descriptor.camera_to_agent_world.to_isometry(),
            ),
            intrinsics: (&self.image_meta.intrinsics).into(),
            descriptor: self.descriptor.descriptor.to_vec(),
            width: self.image_meta.width,
            height: self.image_meta.height,
            rgb: self.rgb.as_raw().clone(),
            depth_m: self.depth.data.clone(),
            means: gaussians.means.clone(),
            log_scales: gaussians.log_scales.clone(),
            quaternions: gaussians.quaternions.clone(),
            opacity_logits: gaussians.opacity_logits.clone(),
            colours: gaussians.colours.clone(),
        }
    }

    /// A spooled keyframe ready to send again; an error names the keyframe when it does not
    /// read back whole.
    fn from_spooled(spooled: SpooledKeyframe) -> anyhow::Result<Self> {
        let id = spooled.keyframe_id;
        let rgb = RgbImage::from_raw(spooled.width, spooled.height, spooled.rgb)
            .with_context(|| format!("spooled keyframe {id}: RGB size does not match"))?;
        let agent_from_camera = isometry_from_tum(&spooled.agent_from_camera)
            .map_err(|error| anyhow::anyhow!("spooled keyframe {id}: pose: {error}"))?;
        let mut descriptor = KeyframeDescriptor::new(id, spooled.frame_index, spooled.timestamp_s);
        descriptor.camera_to_agent_world = Pose::from(&agent_from_camera);
        descriptor.intrinsics = WireIntrinsics::from(&spooled.intrinsics);
        anyhow::ensure!(
            spooled.descriptor.len() == descriptor.descriptor.len(),
            "spooled keyframe {id}: {} descriptor values, the wire carries {}",
            spooled.descriptor.len(),
            descriptor.descriptor.len()
        );
        descriptor.descriptor.copy_from_slice(&spooled.descriptor);
        Ok(Self {
            image_meta: KeyframeImageMeta {
                keyframe_id: id,
                frame_index: spooled.frame_index,
                timestamp_s: spooled.timestamp_s,
                camera_to_agent_world: descriptor.camera_to_agent_world,
                intrinsics: descriptor.intrinsics,
                width: spooled.width,
                height: spooled.height,
            },
            descriptor,
            rgb,
            depth: DepthImage {
                width: spooled.width,
                height: spooled.height,
                data: spooled.depth_m,
            },
            gaussians: GaussianCloud {
                means: spooled.means,
                log_scales: spooled.log_scales,
                quaternions: spooled.quaternions,
                opacity_logits: spooled.opacity_logits,
                colours: spooled.colours,
            },
            due: Instant::now(),
        })
    }

    fn bytes(&self) -> u64 {
        let pixels = self.image_meta.width as usize * self.image_meta.height as usize;
        (size_of::<KeyframeDescriptor>()
            + pixels * size_of::<RgbdPixel>()
            + self.gaussians.len() * size_of::<GaussianRecord>()) as u64
    }
}

pub struct SwarmLink {
    link: AgentLink,
    describer: Describer,
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
    /// Older delivered keyframes the consensus has not confirmed yet, on disk
    /// ([`Self::with_spool`]; `None`: only the in-memory ones are kept).
    spool: Option<KeyframeSpool>,
    spool_limit_bytes: u64,
    /// Keyframes the consensus confirmed it stored (named in a correction or a resume).
    confirmed: BTreeSet<u64>,
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
            describer: Describer::spawn(extractor, config.mapping.background_niceness()),
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
            spool: None,
            spool_limit_bytes: config.consensus.resend.agent_spool_bytes,
            confirmed: BTreeSet::new(),
        })
    }

    /// Keeps delivered keyframes beyond the in-memory `agent_keeps` in a spool on disk in `dir`
    /// until the consensus confirms them ([`crate::spool`]); `dir` is emptied first.
    pub fn with_spool(mut self, dir: &Path) -> anyhow::Result<Self> {
        self.spool = Some(KeyframeSpool::open(dir, self.spool_limit_bytes)?);
        Ok(self)
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
            self.publish_latest();
        }
        self.deliver_described(up, false);
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

    /// Hands the latest keyframe to the describing thread; [`Self::deliver_described`] sends it
    /// once described.
    fn publish_latest(&mut self) {
        let Some(keyframe) = self.latest.take() else {
            return;
        };
        self.frames_since_publication = 0;
        if let Err(keyframe) = self.describer.submit(keyframe) {
            self.summary.send_failures += 1;
            tracing::warn!(
                keyframe,
                "keyframe not published: the describing thread has died"
            );
        }
    }

    /// Prepares the messages of the keyframes described so far (all of them, waiting for the
    /// describing thread, when `wait`) and sends them, or queues them when the link is down (or
    /// older keyframes still wait, so that order is kept).
    fn deliver_described(&mut self, link_up: bool, wait: bool) {
        let described = if wait {
            let pending = self.describer.pending();
            let described = self.describer.wait_all();
            if described.len() < pending {
                let lost = pending - described.len();
                self.summary.send_failures += lost;
                tracing::warn!(
                    lost,
                    "keyframes not published: the describing thread died with them"
                );
            }
            described
        } else {
            self.describer.ready()
        };
        for Described {
            keyframe,
            descriptor,
        } in described
        {
            let _span =
                tracing::info_span!("publish keyframe", id = keyframe.keyframe_id).entered();
            let wire = match descriptor
                .context("computing the global descriptor")
                .and_then(|descriptor| prepare(keyframe, &descriptor))
            {
                Ok(wire) => wire,
                Err(error) => {
                    self.summary.send_failures += 1;
                    tracing::warn!(error = %format!("{error:#}"), "keyframe not published");
                    continue;
                }
            };
            self.send_or_enqueue(wire, link_up);
        }
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

    /// Keeps a delivered keyframe for a resend: the newest `agent_keeps` in memory, older ones
    /// not confirmed yet in the spool.
    fn keep_for_resend(&mut self, wire: WireKeyframe) {
        self.published.push_back(wire);
        while self.published.len() > self.keep_published {
            let Some(oldest) = self.published.pop_front() else {
                break;
            };
            self.spool_unless_confirmed(&oldest);
        }
    }

    fn spool_unless_confirmed(&mut self, wire: &WireKeyframe) {
        let id = wire.descriptor.keyframe_id;
        let Some(spool) = self.spool.as_mut() else {
            return;
        };
        if self.confirmed.contains(&id) {
            return;
        }
        match spool.put(&wire.spooled()) {
            Ok(dropped) => {
                self.summary.keyframes_spooled += 1;
                self.summary.spool_peak_bytes = self.summary.spool_peak_bytes.max(spool.bytes());
                if !dropped.is_empty() {
                    tracing::warn!(
                        keyframes = ?dropped,
                        limit_bytes = self.spool_limit_bytes,
                        "keyframe spool full: the oldest unconfirmed keyframes dropped \
                         ([consensus.resend] agent_spool_bytes)"
                    );
                    self.summary.keyframes_spool_dropped.extend(dropped);
                }
            }
            Err(error) => {
                self.summary.spool_failures += 1;
                tracing::error!("{error:#}");
            }
        }
    }

    /// The consensus stored `ids`: they need not be kept on disk any longer.
    fn confirm(&mut self, ids: impl IntoIterator<Item = u64>) {
        let before = self.confirmed.len();
        self.confirmed.extend(ids);
        if self.confirmed.len() == before {
            return;
        }
        if let Some(spool) = self.spool.as_mut()
            && let Err(error) = spool.confirm(self.confirmed.iter().copied())
        {
            tracing::warn!("{error:#}");
        }
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
                    let wire = match held.and_then(|at| self.published.remove(at)) {
                        Some(wire) => Some(wire),
                        None => self.spooled(keyframe_id),
                    };
                    let Some(wire) = wire else {
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
                ControlMessage::MessagesLost {
                    keyframes_held,
                    keyframes_in_part,
                    newest_seen,
                } => {
                    self.publish_again_what_was_lost(
                        &keyframes_held,
                        &keyframes_in_part,
                        newest_seen,
                    );
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
        self.confirm(held.iter().copied());
        let resent = self.publish_again_unless(|id| held.contains(&id));
        tracing::info!(
            held_there = held.len(),
            publishing_again = resent,
            "the consensus is back"
        );
    }

    /// Messages of this agent were lost on the way to the consensus, which holds
    /// `keyframes_held` complete and `keyframes_in_part` in part (it asks for their parts
    /// itself): every keyframe up to `newest_seen` in neither is published again. Newer ones
    /// may still be on the way (e.g. waiting in a bridge's bandwidth budget).
    fn publish_again_what_was_lost(
        &mut self,
        keyframes_held: &[u64],
        keyframes_in_part: &[u64],
        newest_seen: u64,
    ) {
        self.summary.messages_lost_reports += 1;
        let held: BTreeSet<u64> = keyframes_held.iter().copied().collect();
        let in_part: BTreeSet<u64> = keyframes_in_part.iter().copied().collect();
        self.confirm(held.iter().copied());
        let resent = self.publish_again_unless(|id| {
            held.contains(&id) || in_part.contains(&id) || id > newest_seen
        });
        tracing::warn!(
            held_there = held.len(),
            in_part_there = in_part.len(),
            newest_seen,
            publishing_again = resent,
            "messages to the consensus were lost on the way"
        );
    }

    /// Publishes again, oldest first, every delivered keyframe still held here (in memory or
    /// in the spool) for which `arrived(id)` is false; reports those no longer held. Returns
    /// how many went out again.
    fn publish_again_unless(&mut self, arrived: impl Fn(u64) -> bool) -> usize {
        let (mut lacking, kept): (VecDeque<WireKeyframe>, VecDeque<WireKeyframe>) =
            std::mem::take(&mut self.published)
                .into_iter()
                .partition(|wire| !arrived(wire.descriptor.keyframe_id));
        self.published = kept;
        // Older ones from the spool, oldest first, ahead of the in-memory ones.
        for wire in self.spooled_lacking(&arrived).into_iter().rev() {
            lacking.push_front(wire);
        }
        let resent: BTreeSet<u64> = lacking
            .iter()
            .map(|wire| wire.descriptor.keyframe_id)
            .collect();
        let unrecoverable: Vec<u64> = self
            .summary
            .keyframes_published_ids
            .iter()
            .filter(|&&id| !arrived(id) && !resent.contains(&id))
            .copied()
            .collect();
        if !unrecoverable.is_empty() {
            tracing::warn!(
                keyframes = ?unrecoverable,
                "keyframes the consensus lacks that this agent no longer holds \
                 ([consensus.resend] agent_keeps, agent_spool_bytes)"
            );
            self.summary.keyframes_unrecoverable.extend(unrecoverable);
        }
        for wire in lacking {
            self.summary.keyframes_resent += 1;
            // Control messages are only read with the link up.
            self.send_or_enqueue(wire, true);
        }
        resent.len()
    }

    /// The spooled keyframes for which `arrived(id)` is false, oldest first (they stay
    /// spooled until confirmed).
    fn spooled_lacking(&mut self, arrived: &impl Fn(u64) -> bool) -> Vec<WireKeyframe> {
        let lacking: Vec<u64> = self
            .spool
            .as_ref()
            .map(|spool| spool.ids().filter(|&id| !arrived(id)).collect())
            .unwrap_or_default();
        lacking
            .into_iter()
            .filter_map(|id| self.spooled(id))
            .collect()
    }

    /// Spooled keyframe `id`, ready to send again (it stays spooled until confirmed); `None`
    /// when not spooled, or unreadable (logged).
    fn spooled(&mut self, id: u64) -> Option<WireKeyframe> {
        let spool = self.spool.as_ref()?;
        match spool.get(id).map(|k| k.map(WireKeyframe::from_spooled)) {
            Ok(Some(Ok(wire))) => Some(wire),
            Ok(None) => None,
            Ok(Some(Err(error))) | Err(error) => {
                self.summary.spool_failures += 1;
                tracing::error!("{error:#}");
                None
            }
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
                    // The consensus places only keyframes it has stored.
                    self.confirm(received.keyframes.iter().map(|(id, _)| *id));
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
                    self.summary.undelivered_at_end = self.queue.len()
                        + self.describer.pending()
                        + usize::from(self.latest.is_some())
                        + 1;
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
        self.publish_latest();
        self.deliver_described(true, true);
        self.flush_queue(true);
        if !self.queue.is_empty() {
            tracing::warn!(
                keyframes = self.queue.len(),
                "queued keyframes not delivered: the hello never got through"
            );
        }
        self.send_final_map(final_map);
        let _ = self.receive_corrections(true);
        self.say_goodbye(final_map);
        let summary = self.finish_summary();
        // The goodbye waited until the consensus had everything.
        if let Some(spool) = self.spool.take()
            && let Err(error) = spool.close()
        {
            tracing::warn!("{error:#}");
        }
        summary
    }

    fn send_final_map(&mut self, final_map: &GaussianCloud) {
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
    }

    /// Says goodbye, at most [`GOODBYE_ATTEMPTS`] times while it is lost: the consumer that
    /// took it died before acknowledging it (a bridge between this host and the consensus,
    /// perhaps holding what came before, under a bandwidth budget many keyframes' images and
    /// patches). Once the consensus is reachable again, every keyframe it has not confirmed is
    /// published again (repeats are dropped there), then the final map, then another goodbye.
    /// A goodbye merely not acknowledged in time (a slow drain) is not said again.
    fn say_goodbye(&mut self, final_map: &GaussianCloud) {
        for attempt in 1..=GOODBYE_ATTEMPTS {
            let error = match self.link.say_goodbye() {
                Ok(_) => return,
                Err(error @ TransportError::GoodbyeLost { .. }) => error,
                Err(error) => {
                    tracing::warn!(%error, "goodbye not acknowledged");
                    return;
                }
            };
            tracing::warn!(attempt, %error, "goodbye lost");
            if attempt == GOODBYE_ATTEMPTS {
                return;
            }
            if let Err(error) = self.link.await_all_consumers() {
                tracing::warn!(%error, "the consensus is unreachable: no goodbye again");
                return;
            }
            self.summary.goodbye_retries += 1;
            let confirmed = self.confirmed.clone();
            let resent = self.publish_again_unless(|id| confirmed.contains(&id));
            tracing::warn!(
                publishing_again = resent,
                "the consensus is reachable again: publishing again what it has not confirmed, \
                 the final map and the goodbye"
            );
            self.send_final_map(final_map);
        }
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

/// The messages of one keyframe: its descriptor, RGB-D image and patch.
fn prepare(keyframe: PublishableKeyframe, descriptor: &[f32]) -> anyhow::Result<WireKeyframe> {
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
    message.descriptor.copy_from_slice(descriptor);
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

    /// One frame's link work, with the keyframe it published described and sent.
    fn after_frame(swarm: &mut SwarmLink) -> Option<ReceivedCorrection> {
        let correction = swarm.after_frame();
        let link_up = swarm.link_up;
        swarm.deliver_described(link_up, true);
        correction
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
        announced_agent_with(namespace, &Config::default(), None)
    }

    /// [`announced_agent`] with `config` (publishing every keyframe) and a keyframe spool in
    /// `spool`.
    fn announced_agent_with(
        namespace: &str,
        config: &Config,
        spool: Option<&Path>,
    ) -> (protocol::transport::ConsumerLink, SwarmLink, Intrinsics) {
        let transport =
            TransportConfig::with_namespace(format!("{namespace}-{}", std::process::id()));
        let consumer = protocol::transport::ConsumerLink::open(&transport).unwrap();
        let mut config = config.clone();
        config.consensus.t_comm = 1;
        let mut swarm = SwarmLink::connect(0, &transport, &config, LinkPlan::always_up()).unwrap();
        if let Some(dir) = spool {
            swarm = swarm.with_spool(dir).unwrap();
        }
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
        after_frame(&mut swarm);
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
        assert!(after_frame(&mut swarm).is_none());
        let received = received_keyframes(&mut consumer);
        assert_eq!(received.ids(), (vec![7], vec![7], vec![7]));
        content_is_the_keyframes(&received);

        let ask = |keyframe_id| ControlMessage::ResendKeyframe {
            keyframe_id,
            reason: "test".into(),
        };
        consumer.send_control(0, &ask(7)).unwrap();
        consumer.send_control(0, &ask(99)).unwrap();
        after_frame(&mut swarm);
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

    #[test]
    fn after_lost_messages_what_arrived_nowhere_up_to_the_newest_seen_is_published_again() {
        let dir = tempfile::tempdir().unwrap();
        let spool = dir.path().join(crate::spool::KEYFRAME_SPOOL_DIR);
        let mut config = Config::default();
        // Two in memory, the older ones on the spool: both places are looked in.
        config.consensus.resend.agent_keeps = 2;
        let (mut consumer, mut swarm, intrinsics) =
            announced_agent_with("lost-messages", &config, Some(&spool));
        for keyframe_id in 1..=6 {
            swarm.on_keyframe(small_keyframe(keyframe_id, intrinsics));
            after_frame(&mut swarm);
            received_keyframes(&mut consumer);
        }
        // The consensus holds 1 and 4 whole and 3 in part, and has seen nothing newer than 5:
        // 2 (spooled) and 5 (in memory) arrived nowhere; 6 may still be on the way.
        consumer
            .send_control(
                0,
                &ControlMessage::MessagesLost {
                    keyframes_held: vec![1, 4],
                    keyframes_in_part: vec![3],
                    newest_seen: 5,
                },
            )
            .unwrap();
        after_frame(&mut swarm);
        let again = received_keyframes(&mut consumer);
        assert_eq!(again.ids(), (vec![2, 5], vec![2, 5], vec![2, 5]));
        let summary = swarm.summary();
        assert_eq!(summary.messages_lost_reports, 1);
        assert_eq!(summary.keyframes_resent, 2);
        assert!(summary.keyframes_unrecoverable.is_empty());
    }

    /// Keyframe `keyframe_id` of a 32x24 camera with two Gaussians.
    fn small_keyframe(keyframe_id: u64, intrinsics: Intrinsics) -> PublishableKeyframe {
        let mut gaussians = GaussianCloud::default();
        for i in 0..2 {
            let v = (keyframe_id + i) as f32;
            gaussians.push([v, 1.0, 2.0], [-4.0; 3], [1.0, 0.0, 0.0, v], 0.5, [0.5; 3]);
        }
        PublishableKeyframe {
            keyframe_id,
            frame_index: keyframe_id * 10,
            timestamp_s: keyframe_id as f64,
            agent_from_camera: Isometry3::translation(keyframe_id as f64, 0.0, 0.0),
            intrinsics,
            rgb: RgbImage::from_fn(32, 24, |x, y| {
                image::Rgb([(x * 8) as u8, (y * 10) as u8, keyframe_id as u8])
            }),
            depth: DepthImage {
                width: 32,
                height: 24,
                data: vec![1.5; 32 * 24],
            },
            gaussians,
        }
    }

    #[test]
    fn keyframes_beyond_those_in_memory_are_spooled_until_confirmed_and_none_is_unrecoverable() {
        let dir = tempfile::tempdir().unwrap();
        let spool = dir.path().join(crate::spool::KEYFRAME_SPOOL_DIR);
        let mut config = Config::default();
        // Nothing in memory: every keyframe the consensus lacks comes from the spool.
        config.consensus.resend.agent_keeps = 0;
        let (mut consumer, mut swarm, intrinsics) =
            announced_agent_with("spool-agent", &config, Some(&spool));
        let mut first = Received::default();
        for keyframe_id in 1..=3 {
            swarm.on_keyframe(small_keyframe(keyframe_id, intrinsics));
            after_frame(&mut swarm);
            // Taken as they come: the patch queue holds few samples.
            let received = received_keyframes(&mut consumer);
            first.descriptors.extend(received.descriptors);
            first.images.extend(received.images);
            first.patches.extend(received.patches);
        }
        assert_eq!(first.ids(), (vec![1, 2, 3], vec![1, 2, 3], vec![1, 2, 3]));
        let spooled = |spool: &Path| {
            let mut names: Vec<String> = std::fs::read_dir(spool)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            names.sort();
            names
        };
        assert_eq!(
            spooled(&spool),
            ["keyframe_1.bin", "keyframe_2.bin", "keyframe_3.bin"]
        );

        // A consensus restarted on a store that holds keyframe 1 only.
        consumer
            .send_control(
                0,
                &ControlMessage::ConsensusResumed {
                    keyframes_held: vec![1],
                },
            )
            .unwrap();
        after_frame(&mut swarm);
        let again = received_keyframes(&mut consumer);
        assert_eq!(again.ids(), (vec![2, 3], vec![2, 3], vec![2, 3]));
        assert_eq!(again.images[0].1, first.images[1].1, "keyframe 2's pixels");
        assert_eq!(
            again.patches[1].1, first.patches[2].1,
            "keyframe 3's Gaussians"
        );
        assert_eq!(spooled(&spool), ["keyframe_2.bin", "keyframe_3.bin"]);
        assert!(swarm.summary().keyframes_unrecoverable.is_empty());

        // A correction naming them confirms them.
        let pose = |keyframe_id| protocol::messages::KeyframePose {
            keyframe_id,
            camera_to_world: Pose::IDENTITY,
        };
        consumer
            .send_correction(0, Pose::IDENTITY, &[pose(1), pose(2), pose(3)])
            .unwrap();
        after_frame(&mut swarm);
        assert!(spooled(&spool).is_empty());
        let summary = swarm.summary();
        assert_eq!(summary.keyframes_resent, 2);
        assert_eq!(summary.spool_failures, 0);
        assert!(summary.keyframes_spooled >= 3);
    }
}
