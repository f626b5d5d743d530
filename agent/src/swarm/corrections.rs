//! Corrections from the consensus, taken between frames (held while the link is down).

use crate::link_schedule::CorrectionArrival;
use crate::local_corrections::ReceivedCorrection;

use super::SwarmLink;

impl SwarmLink {
    /// Takes every pending correction. With the link up, the newest (a held one, or one that
    /// just arrived) is returned for applying; with it down, the newest is held and replaces
    /// older held ones. Each correction states every published keyframe's pose, so only the
    /// newest matters.
    pub(super) fn receive_corrections(&mut self, link_up: bool) -> Option<ReceivedCorrection> {
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
}
