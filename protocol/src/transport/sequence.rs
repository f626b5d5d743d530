//! Sequence and gap rules: every message carries a [`Stamp`] (the sender's incarnation epoch
//! and a per-topic sequence from 0); a receiver classifies each message against the last one
//! it saw from the same sender and topic ([`Delivery`]), drops stale and repeated ones, and
//! counts gaps and restarts in the bandwidth report.

use std::collections::BTreeMap;
use std::time::{SystemTime, UNIX_EPOCH};

use super::traffic::{Direction, TrafficTable};
use crate::messages::Stamp;
use crate::services::Topic;

/// How a received message relates to the ones before it from the same sender and topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delivery {
    /// The next sequence number of the current epoch.
    InOrder,
    /// `missed` messages of the current epoch were lost before this one.
    Gap {
        /// Sequence numbers skipped since the previous message.
        missed: u64,
    },
    /// First message seen of a (new) incarnation; `missed` earlier messages of it were not seen
    /// (non-zero when a consumer attaches late).
    NewIncarnation {
        /// Epoch of the previous message seen from this sender on this topic; `None` when this is
        /// the first message seen from it.
        previous_epoch: Option<u64>,
        /// Messages of the new incarnation not seen: its sequence numbers before this one.
        missed: u64,
    },
}

pub(super) enum Verdict {
    Deliver(Delivery),
    Stale,
    Duplicate,
}

/// Per (sender, topic) ordering state.
#[derive(Debug, Default)]
pub(super) struct SequenceTracker {
    last: Option<(u64, u64)>,
}

impl SequenceTracker {
    pub(super) fn observe(&mut self, epoch: u64, sequence: u64) -> Verdict {
        let verdict = match self.last {
            None => Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: None,
                missed: sequence,
            }),
            Some((last_epoch, _)) if epoch > last_epoch => {
                Verdict::Deliver(Delivery::NewIncarnation {
                    previous_epoch: Some(last_epoch),
                    missed: sequence,
                })
            }
            Some((last_epoch, _)) if epoch < last_epoch => return Verdict::Stale,
            Some((_, last_sequence)) if sequence <= last_sequence => return Verdict::Duplicate,
            Some((_, last_sequence)) if sequence == last_sequence + 1 => {
                Verdict::Deliver(Delivery::InOrder)
            }
            Some((_, last_sequence)) => Verdict::Deliver(Delivery::Gap {
                missed: sequence - last_sequence - 1,
            }),
        };
        self.last = Some((epoch, sequence));
        verdict
    }
}

/// Incarnation number of this process: nanoseconds since the Unix epoch, so a restarted process
/// always has a larger one.
pub(super) fn new_epoch() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(1)
}

/// Ordering bookkeeping shared by both endpoints' receive paths.
#[derive(Debug, Default)]
pub(super) struct ReceiveBook {
    trackers: BTreeMap<(u32, Topic), SequenceTracker>,
}

impl ReceiveBook {
    /// Records a received message under agent `account_as`; `None` means drop it (stale or
    /// duplicate). Ordering is tracked per sender (`stamp.agent_id`) and topic.
    pub(super) fn admit(
        &mut self,
        traffic: &mut TrafficTable,
        stamp: Stamp,
        topic: Topic,
        bytes: usize,
        account_as: u32,
    ) -> Option<Delivery> {
        let verdict = self
            .trackers
            .entry((stamp.agent_id, topic))
            .or_default()
            .observe(stamp.epoch, stamp.sequence);
        let row = traffic.row(account_as, topic, Direction::Received);
        match verdict {
            Verdict::Stale => {
                row.stale_dropped += 1;
                None
            }
            Verdict::Duplicate => {
                row.duplicates_dropped += 1;
                None
            }
            Verdict::Deliver(delivery) => {
                row.messages += 1;
                row.bytes += bytes as u64;
                match delivery {
                    Delivery::InOrder => {}
                    Delivery::Gap { missed } => {
                        row.gaps += 1;
                        row.missed += missed;
                    }
                    Delivery::NewIncarnation { missed, .. } => {
                        row.incarnations += 1;
                        if missed > 0 {
                            row.gaps += 1;
                            row.missed += missed;
                        }
                    }
                }
                Some(delivery)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequence_tracker_classifies_order_gaps_restarts_and_stale() {
        let mut tracker = SequenceTracker::default();
        assert!(matches!(
            tracker.observe(10, 0),
            Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: None,
                missed: 0
            })
        ));
        assert!(matches!(
            tracker.observe(10, 1),
            Verdict::Deliver(Delivery::InOrder)
        ));
        assert!(matches!(
            tracker.observe(10, 4),
            Verdict::Deliver(Delivery::Gap { missed: 2 })
        ));
        assert!(matches!(tracker.observe(10, 4), Verdict::Duplicate));
        assert!(matches!(tracker.observe(10, 3), Verdict::Duplicate));
        assert!(matches!(
            tracker.observe(20, 0),
            Verdict::Deliver(Delivery::NewIncarnation {
                previous_epoch: Some(10),
                missed: 0
            })
        ));
        assert!(matches!(tracker.observe(10, 5), Verdict::Stale));
        assert!(matches!(
            tracker.observe(20, 1),
            Verdict::Deliver(Delivery::InOrder)
        ));
    }
}
