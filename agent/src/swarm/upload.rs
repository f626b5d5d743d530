//! Keyframe upload: the latest keyframe goes to the describing thread every T_comm frames, and
//! once described it is sent (or queued behind what waits for the link); a delivered keyframe
//! is kept for re-sends, the newest in memory, older unconfirmed ones in the spool.

use std::time::Instant;

use anyhow::Context;
use protocol::convert::{gaussian_record, rgbd_pixel};
use protocol::messages::CoordinateFrame;
use protocol::transport::TransportError;

use crate::describer::Described;

use super::wire::{WireKeyframe, prepare};
use super::{PublishableKeyframe, SEND_RETRY_AFTER, SwarmLink};

impl SwarmLink {
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

    /// Hands the latest keyframe to the describing thread; [`Self::deliver_described`] sends it
    /// once described.
    pub(super) fn publish_latest(&mut self) {
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
    pub(super) fn deliver_described(&mut self, link_up: bool, wait: bool) {
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
    /// keyframes, a failed send's back-off) and the link is up; otherwise queues it behind them.
    /// A keyframe whose send fails is queued too: it goes out again once the consensus takes
    /// messages (never dropped for a failed send).
    pub(super) fn send_or_enqueue(&mut self, wire: WireKeyframe, link_up: bool) {
        if link_up && self.queue.is_empty() && self.pending_hello.is_none() && !self.backing_off() {
            if let Some(undelivered) = self.send_now(wire) {
                self.enqueue(undelivered);
            }
        } else {
            self.enqueue(wire);
        }
    }

    /// Whether sends wait after a failure (see [`SEND_RETRY_AFTER`]).
    pub(super) fn backing_off(&self) -> bool {
        self.retry_sends_at.is_some_and(|at| Instant::now() < at)
    }

    /// Sends a keyframe's messages; a delivered keyframe is kept for resend requests. A
    /// keyframe that did not get through (the consensus gone, a queue that stayed full) is
    /// returned for the caller to queue, and sends wait [`SEND_RETRY_AFTER`]: a consensus that is
    /// killed after taking part of it, or before storing it, gets it whole again. One the
    /// transport refuses as invalid could never be delivered: it is dropped, counted and logged.
    pub(super) fn send_now(&mut self, wire: WireKeyframe) -> Option<WireKeyframe> {
        let error = match self.send(&wire) {
            Ok(()) => {
                let first_delivery = self
                    .summary
                    .keyframes_published_ids
                    .insert(wire.descriptor.keyframe_id);
                if first_delivery {
                    self.summary.keyframes_published += 1;
                }
                self.keep_for_resend(wire);
                self.retry_sends_at = None;
                return None;
            }
            Err(error) => error,
        };
        self.summary.send_failures += 1;
        let invalid = matches!(
            error.downcast_ref::<TransportError>(),
            Some(TransportError::InvalidMessage { .. })
        );
        tracing::warn!(
            keyframe = wire.descriptor.keyframe_id,
            error = %format!("{error:#}"),
            "{}",
            if invalid {
                "keyframe not published: refused as invalid"
            } else {
                "keyframe not delivered: queued to go out again"
            }
        );
        self.recheck_presence();
        if invalid {
            return None;
        }
        self.retry_sends_at = Some(Instant::now() + SEND_RETRY_AFTER);
        Some(wire)
    }

    pub(super) fn enqueue(&mut self, wire: WireKeyframe) {
        let keyframe_id = wire.descriptor.keyframe_id;
        let bytes = wire.bytes();
        self.summary.link.keyframes_queued += 1;
        for (dropped, dropped_bytes) in self.queue.push(wire, bytes) {
            let id = dropped.descriptor.keyframe_id;
            if self.summary.keyframes_published_ids.contains(&id) {
                // Delivered once and queued to go out again: the spool keeps it for the
                // consensus's requests, as any delivered keyframe it has not confirmed.
                self.spool_unless_confirmed(&dropped);
                continue;
            }
            self.summary.link.keyframes_dropped_queue_full += 1;
            self.summary.link.bytes_dropped_queue_full += dropped_bytes;
            tracing::warn!(
                dropped_keyframe = id,
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

    /// Delivers the pending hello and every queued keyframe, oldest first, until a send fails
    /// (that keyframe stays at the head). `despite_schedule`: the end of the run, which delivers
    /// whatever the schedule and a failed send's back-off say.
    pub(super) fn flush_queue(&mut self, despite_schedule: bool) {
        if !despite_schedule && self.backing_off() {
            return;
        }
        if !self.deliver_pending_hello() {
            // Nothing may overtake the hello; it is tried again after the next frame.
            return;
        }
        let with_link_down = despite_schedule && !self.link_up;
        while self.consensus_present
            && let Some(wire) = self.queue.pop_front()
        {
            let waited_s = wire.due.elapsed().as_secs_f64();
            let failures = self.summary.send_failures;
            match self.send_now(wire) {
                None if self.summary.send_failures == failures => {
                    self.summary.link.delivered_late(waited_s, with_link_down)
                }
                // Refused as invalid: dropped and counted.
                None => {}
                Some(undelivered) => {
                    let bytes = undelivered.bytes();
                    self.queue.push_front(undelivered, bytes);
                    break;
                }
            }
        }
    }

    pub(super) fn send(&mut self, wire: &WireKeyframe) -> anyhow::Result<()> {
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
    pub(super) fn keep_for_resend(&mut self, wire: WireKeyframe) {
        self.published.push_back(wire);
        while self.published.len() > self.keep_published {
            let Some(oldest) = self.published.pop_front() else {
                break;
            };
            self.spool_unless_confirmed(&oldest);
        }
    }

    pub(super) fn spool_unless_confirmed(&mut self, wire: &WireKeyframe) {
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
    pub(super) fn confirm(&mut self, ids: impl IntoIterator<Item = u64>) {
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

    /// Spooled keyframe `id`, ready to send again (it stays spooled until confirmed); `None`
    /// when not spooled, or unreadable (logged).
    pub(super) fn spooled(&mut self, id: u64) -> Option<WireKeyframe> {
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
}
