//! Whether messages can go out: the hello, heartbeats, the link's schedule and whether the
//! consensus is attached (looked up without blocking while it is not).

use std::time::{Duration, Instant};

use geometry::camera::Intrinsics;
use protocol::messages::Intrinsics as WireIntrinsics;

use super::SwarmLink;

/// Heartbeat period: the consensus learns that a quiet agent is still alive.
const HEARTBEAT_EVERY: Duration = Duration::from_secs(1);
/// How often an agent without a consensus looks for one. Every send waits up to the transport's
/// `delivery_timeout` for a consumer, so an agent whose consensus is not there (not started yet,
/// crashed, restarting) does not send at all: it queues as with the link down and checks,
/// without blocking, this often whether the consensus is back.
const PRESENCE_CHECK_EVERY: Duration = Duration::from_secs(1);

impl SwarmLink {
    /// Whether [`Self::announce`] was called (the hello may still wait for the link).
    pub fn is_announced(&self) -> bool {
        self.announced
    }

    /// Announces the agent with its camera and its run anchor ([`super::run_anchor`] of its first
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
    pub(super) fn deliver_pending_hello(&mut self) -> bool {
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
    pub(super) fn consensus_attached(&mut self) -> bool {
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

    pub(super) fn mark_attached(&mut self) {
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
    pub(super) fn recheck_presence(&mut self) {
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
    pub(super) fn refresh_link_state(&mut self) -> bool {
        self.refresh_schedule_state() && self.consensus_attached()
    }

    /// Whether the link is up now by its schedule, logging and recording transitions.
    pub(super) fn refresh_schedule_state(&mut self) -> bool {
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

    /// Tells the consensus this agent is alive, at most every [`HEARTBEAT_EVERY`].
    pub(super) fn heartbeat_if_due(&mut self) {
        if self.last_heartbeat.elapsed() < HEARTBEAT_EVERY {
            return;
        }
        self.last_heartbeat = Instant::now();
        if let Err(error) = self.link.heartbeat() {
            tracing::debug!(%error, "heartbeat not delivered");
            self.recheck_presence();
        }
    }
}
