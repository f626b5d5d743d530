//! The consensus's control messages: a keyframe asked for again, a consensus resumed from its
//! store, messages lost on the way (each answered by publishing again what the consensus lacks),
//! and the request to stop.

use std::collections::{BTreeSet, VecDeque};

use protocol::messages::ControlMessage;
use protocol::transport::TransportError;

use super::SwarmLink;
use super::wire::WireKeyframe;

impl SwarmLink {
    /// Answers the consensus's control messages: a keyframe that arrived incomplete there is
    /// published again (in order behind anything queued) if this agent still holds it.
    pub(super) fn answer_control_messages(&mut self) {
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
    pub(super) fn publish_again_what_the_consensus_lacks(&mut self, keyframes_held: &[u64]) {
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
    pub(super) fn publish_again_what_was_lost(
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
    /// in the spool) for which `arrived(id)` is false; reports those no longer held (the
    /// consensus said it lacks them). Returns how many went out again.
    pub(super) fn publish_again_unless(&mut self, arrived: impl Fn(u64) -> bool) -> usize {
        let resent = self.publish_again_held_unless(&arrived);
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
        resent.len()
    }

    /// Publishes again, oldest first, every delivered keyframe still held here (in memory or
    /// in the spool) for which `arrived(id)` is false. Returns their ids.
    pub(super) fn publish_again_held_unless(
        &mut self,
        arrived: &impl Fn(u64) -> bool,
    ) -> BTreeSet<u64> {
        let (mut lacking, kept): (VecDeque<WireKeyframe>, VecDeque<WireKeyframe>) =
            std::mem::take(&mut self.published)
                .into_iter()
                .partition(|wire| !arrived(wire.descriptor.keyframe_id));
        self.published = kept;
        // Older ones from the spool, oldest first, ahead of the in-memory ones.
        for wire in self.spooled_lacking(arrived).into_iter().rev() {
            lacking.push_front(wire);
        }
        let resent: BTreeSet<u64> = lacking
            .iter()
            .map(|wire| wire.descriptor.keyframe_id)
            .collect();
        for wire in lacking {
            self.summary.keyframes_resent += 1;
            // Control messages are only read with the link up.
            self.send_or_enqueue(wire, true);
        }
        resent
    }

    /// The spooled keyframes for which `arrived(id)` is false, oldest first (they stay
    /// spooled until confirmed).
    pub(super) fn spooled_lacking(&mut self, arrived: &impl Fn(u64) -> bool) -> Vec<WireKeyframe> {
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
}
