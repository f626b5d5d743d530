//! The end of the run on the link: what still waits is delivered, then the final map and the
//! goodbye (said again while it is lost).

use geometry::se3::isometry_to_tum;
use protocol::convert::gaussian_record;
use protocol::messages::{CoordinateFrame, FINAL_MAP_KEYFRAME_ID};
use protocol::transport::{Direction, TransportError};
use splats::GaussianCloud;

use super::{SwarmLink, SwarmSummary};

/// Goodbyes an agent says at the end of its run while they are lost (see
/// `SwarmLink::say_goodbye`).
const GOODBYE_ATTEMPTS: usize = 3;

impl SwarmLink {
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
        // A consensus that was killed and resumed meanwhile (or lost messages) says what it
        // lacks: it gets that before the final map and the goodbye, or it would end the run
        // without keyframes this agent delivered to its previous process.
        self.answer_control_messages();
        self.flush_queue(true);
        self.publish_again_unconfirmed_at_end();
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

    /// Every delivered keyframe the consensus has not confirmed goes out again before the
    /// goodbye (repeats are dropped there). A consensus restarted near the end of this run says
    /// what it lacks (`ConsensusResumed`) before it reads anything of this agent, but that can
    /// reach this agent after its last look at the control topic, or die with a consensus
    /// killed again; the goodbye would then end this agent's part of the run without keyframes
    /// it delivered to the previous process. What is no longer held here is not reported as
    /// lost: unconfirmed is not missing.
    fn publish_again_unconfirmed_at_end(&mut self) {
        let confirmed = self.confirmed.clone();
        let resent = self.publish_again_held_unless(&|id| confirmed.contains(&id));
        self.summary.keyframes_resent_at_end = resent.len();
        if !resent.is_empty() {
            tracing::info!(
                keyframes = ?resent,
                "end of run: keyframes the consensus has not confirmed published again"
            );
            self.flush_queue(true);
        }
    }

    pub(super) fn send_final_map(&mut self, final_map: &GaussianCloud) {
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
    pub(super) fn say_goodbye(&mut self, final_map: &GaussianCloud) {
        // With no consensus attached (killed, not yet started again), the goodbye would wait in
        // the publisher's history and the next consensus would end this agent's run on it
        // without asking for what it lacks (a keyframe published again to the process that
        // died storing it). Wait for it, then publish again what it has not confirmed and the
        // final map before saying goodbye.
        if !self.link.consumers_present() {
            match self.link.await_all_consumers() {
                Ok(()) => self.publish_again_before_goodbye(final_map),
                Err(error) => tracing::warn!(%error, "no consensus to say goodbye to"),
            }
        }
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
            self.publish_again_before_goodbye(final_map);
        }
    }

    /// Every keyframe the consensus has not confirmed, published again (repeats are dropped
    /// there), then the final map: what a consensus reached again needs before a goodbye. As
    /// at the end of the run, what is no longer held here is not reported as lost: the
    /// consensus has not said it lacks it, only not yet confirmed it (a consensus that lacks
    /// it says so with `ConsensusResumed` or `MessagesLost`, and that report counts it).
    fn publish_again_before_goodbye(&mut self, final_map: &GaussianCloud) {
        let confirmed = self.confirmed.clone();
        let resent = self
            .publish_again_held_unless(&|id| confirmed.contains(&id))
            .len();
        tracing::warn!(
            publishing_again = resent,
            "the consensus is reachable again: publishing again what it has not confirmed, the \
             final map and the goodbye"
        );
        self.send_final_map(final_map);
    }

    /// The summary with the link's traffic figures.
    pub(super) fn finish_summary(&mut self) -> SwarmSummary {
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
