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
//!
//! The link's work by concern: `presence.rs` (the hello, heartbeats, the schedule and whether
//! the consensus is attached), `upload.rs` (keyframes: describe, send or queue, keep for
//! re-sends, spool), `control.rs` (the consensus's requests: re-send, resumed, messages lost,
//! stop), `corrections.rs` (corrections between frames), `finish.rs` (the final map and the
//! goodbye), `wire.rs` (a keyframe's messages).

use std::collections::{BTreeSet, VecDeque};
use std::hash::{Hash, Hasher};
use std::path::Path;
use std::time::Instant;

use alexnet::descriptor::GlobalDescriptorExtractor;
use anyhow::Context;
use config::Config;
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;
use protocol::messages::Intrinsics as WireIntrinsics;
use protocol::transport::{AgentLink, TransportConfig};
use serde::Serialize;
use splats::GaussianCloud;

use crate::describer::Describer;
use crate::link_schedule::{BoundedQueue, CorrectionGate, LinkPlan, LinkSummary};
use crate::local_corrections::ReceivedCorrection;
use crate::spool::KeyframeSpool;

mod control;
mod corrections;
mod finish;
mod presence;
#[cfg(test)]
mod tests;
mod upload;
mod wire;

use wire::WireKeyframe;

/// A keyframe the agent may publish.
pub struct PublishableKeyframe {
    /// The keyframe's id (ids count up from 0 in the order the agent makes keyframes).
    pub keyframe_id: u64,
    /// The frame's number in its sequence.
    pub frame_index: u64,
    /// The frame's timestamp, seconds.
    pub timestamp_s: f64,
    /// The camera's pose in the agent's tracked frame, from which the consensus builds its
    /// odometry edges (never moved by corrections); metres.
    pub agent_from_camera: Isometry3<f64>,
    /// The intrinsics of `rgb` and `depth`.
    pub intrinsics: Intrinsics,
    /// The colour image: sent, and what the global descriptor is computed from.
    pub rgb: RgbImage,
    /// Depth in metres (0 = invalid), the same size as `rgb`; sent in whole millimetres.
    pub depth: DepthImage,
    /// The Gaussians this keyframe seeded, in the agent's frame.
    pub gaussians: GaussianCloud,
}

/// What the swarm link did, for metrics.json.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SwarmSummary {
    /// Keyframes delivered, each counted once (`keyframes_resent` counts those published
    /// again).
    pub keyframes_published: usize,
    /// Sends that failed or never happened: a hello or keyframe send that failed (each try),
    /// a keyframe whose descriptor or messages could not be made, a final map not delivered.
    pub send_failures: usize,
    /// Corrections taken from the link, those held while it was down included.
    pub corrections_received: usize,
    /// Latest `world_from_agent` from the consensus, `[tx, ty, tz, qx, qy, qz, qw]`.
    pub world_from_agent: Option<[f64; 7]>,
    /// Bytes this agent sent over the transport (set when the link finishes; 0 before).
    pub bytes_sent: u64,
    /// `bytes_sent` over the seconds since the link opened.
    pub bytes_sent_per_s: f64,
    /// The global descriptor the agent computes: `alexnet-gem`, or `thumbnail` without weights.
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
    /// Keyframes published again: on request, after the consensus resumed or lost messages,
    /// and at the end of the run those it had not confirmed.
    pub keyframes_resent: usize,
    /// Of those, published again at the end of the run because the consensus had not
    /// confirmed them (see `SwarmLink::finish`).
    pub keyframes_resent_at_end: usize,
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
    /// Delivered keyframes written to the spool (beyond `agent_keeps`, not confirmed yet).
    pub keyframes_spooled: usize,
    /// The spool's largest size, in bytes.
    pub spool_peak_bytes: u64,
    /// Ids of the keyframes the spool dropped to stay within `agent_spool_bytes`.
    pub keyframes_spool_dropped: Vec<u64>,
    /// Spool writes and reads that failed (a full disk, a file that does not read back).
    pub spool_failures: usize,
    /// The reason the consensus gave when it asked the swarm to stop
    /// (`ControlMessage::Shutdown`); absent when it never did.
    pub stopped_by_consensus: Option<String>,
}

/// Whether the link is up now and what waits for it, for the progress file.
#[derive(Debug, Clone, Copy)]
pub struct LinkStatus {
    /// The schedule has the link up and the consensus was attached at the last check.
    pub up: bool,
    /// Keyframes queued until the link is up.
    pub queued_keyframes: usize,
}

/// This agent's link to the consensus (see the module documentation): opened by
/// [`Self::connect`], served between frames by [`Self::after_frame`], closed by `finish`.
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
    /// After a failed send, queued keyframes wait until then (see [`SEND_RETRY_AFTER`]).
    retry_sends_at: Option<Instant>,
}

/// How long sends wait after one failed (a queue that stayed full, a consensus gone): every
/// failed send costs the transport's full-queue or delivery timeout, which tracking must not pay
/// at every frame.
const SEND_RETRY_AFTER: std::time::Duration = std::time::Duration::from_secs(1);

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
            retry_sends_at: None,
        })
    }

    /// Keeps delivered keyframes beyond the in-memory `agent_keeps` in a spool on disk in `dir`
    /// until the consensus confirms them ([`crate::spool`]); `dir` is emptied first.
    pub fn with_spool(mut self, dir: &Path) -> anyhow::Result<Self> {
        self.spool = Some(KeyframeSpool::open(dir, self.spool_limit_bytes)?);
        Ok(self)
    }

    /// What the link is doing, for the progress file.
    pub fn status(&self) -> LinkStatus {
        LinkStatus {
            up: self.link_up && self.consensus_present,
            queued_keyframes: self.queue.len(),
        }
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
        if up {
            self.heartbeat_if_due();
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
