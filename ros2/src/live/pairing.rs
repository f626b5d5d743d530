//! Colour and depth messages paired by header stamp as they arrive (docs/ros2.md, Live topics).
//!
//! A camera publishes colour and depth on two topics; over a network either can arrive first,
//! late, twice or never. Each message waits in a short queue of its own kind until one of the
//! other kind lies within the pairing tolerance of its stamp; the pair is then handed on, and
//! every message older than it on either side is dropped as unpaired (the camera has moved on).
//! What is counted here is what the agent reports: nothing is dropped silently.

use std::collections::VecDeque;

use serde::Serialize;

/// Messages of one kind that wait for their partner at most: a third of a second at 30 Hz.
pub const WAITING_PER_KIND: usize = 10;

/// A stamp this far before the last pair's means the publisher restarted (a replayed bag
/// looping, a driver restarted with a clock of its own), not a late message.
pub const RESTART_JUMP_S: f64 = 1.0;

/// Counts of what the pairing did with the messages it saw.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct PairingCounts {
    /// Pairs formed.
    pub paired: u64,
    /// Messages that found no partner within the tolerance before a newer pair formed or their
    /// queue overflowed.
    pub unpaired: u64,
    /// Messages stamped at or before the last pair formed (late), or stamped like one of their
    /// kind still waiting (sent twice): dropped.
    pub stale: u64,
    /// Messages with no stamp (zero): dropped, since nothing can pair them.
    pub unstamped: u64,
    /// Times the stamps jumped back by more than [`RESTART_JUMP_S`]: the queues were cleared and
    /// pairing started again.
    pub restarts: u64,
}

/// Colour messages `C` and depth messages `D`, paired by stamp (seconds).
#[derive(Debug)]
pub struct Pairing<C, D> {
    tolerance_s: f64,
    colour: VecDeque<(f64, C)>,
    depth: VecDeque<(f64, D)>,
    last_pair_s: Option<f64>,
    counts: PairingCounts,
}

/// What a message's stamp says before it joins a queue.
enum Admission {
    Admit,
    Reject,
}

impl<C, D> Pairing<C, D> {
    /// Empty queues; a colour and a depth message pair when their stamps differ by at most
    /// `tolerance_s` seconds.
    pub fn new(tolerance_s: f64) -> Self {
        Self {
            tolerance_s,
            colour: VecDeque::new(),
            depth: VecDeque::new(),
            last_pair_s: None,
            counts: PairingCounts::default(),
        }
    }

    /// What the pairing did with the messages so far.
    pub fn counts(&self) -> PairingCounts {
        self.counts
    }

    /// A colour message; the pair it completes, if any: (stamp of the colour, colour, depth).
    pub fn push_colour(&mut self, stamp_s: f64, colour: C) -> Option<(f64, C, D)> {
        if let Admission::Reject = self.admit(stamp_s) {
            return None;
        }
        if is_waiting(&self.colour, stamp_s) {
            self.counts.stale += 1;
            return None;
        }
        match take_nearest(&mut self.depth, stamp_s, self.tolerance_s) {
            Some((_, depth)) => Some(self.paired(stamp_s, colour, depth)),
            None => {
                push_bounded(&mut self.colour, stamp_s, colour, &mut self.counts);
                None
            }
        }
    }

    /// A depth message; the pair it completes, if any: (stamp of the colour, colour, depth).
    pub fn push_depth(&mut self, stamp_s: f64, depth: D) -> Option<(f64, C, D)> {
        if let Admission::Reject = self.admit(stamp_s) {
            return None;
        }
        if is_waiting(&self.depth, stamp_s) {
            self.counts.stale += 1;
            return None;
        }
        match take_nearest(&mut self.colour, stamp_s, self.tolerance_s) {
            Some((colour_stamp, colour)) => Some(self.paired(colour_stamp, colour, depth)),
            None => {
                push_bounded(&mut self.depth, stamp_s, depth, &mut self.counts);
                None
            }
        }
    }

    fn admit(&mut self, stamp_s: f64) -> Admission {
        if stamp_s <= 0.0 || !stamp_s.is_finite() {
            self.counts.unstamped += 1;
            return Admission::Reject;
        }
        if let Some(last) = self.last_pair_s {
            if stamp_s < last - RESTART_JUMP_S {
                tracing::warn!(
                    stamp_s,
                    last_pair_s = last,
                    "stamps jumped back: the publisher restarted; pairing starts again"
                );
                self.counts.restarts += 1;
                self.counts.unpaired += (self.colour.len() + self.depth.len()) as u64;
                self.colour.clear();
                self.depth.clear();
                self.last_pair_s = None;
            } else if stamp_s <= last {
                self.counts.stale += 1;
                return Admission::Reject;
            }
        }
        Admission::Admit
    }

    /// Records a pair at `stamp_s`: everything older waits in vain and is dropped.
    fn paired(&mut self, stamp_s: f64, colour: C, depth: D) -> (f64, C, D) {
        let newest = self.last_pair_s.map_or(stamp_s, |last| last.max(stamp_s));
        self.last_pair_s = Some(newest);
        for queue_len in [
            drop_older(&mut self.colour, newest),
            drop_older(&mut self.depth, newest),
        ] {
            self.counts.unpaired += queue_len as u64;
        }
        self.counts.paired += 1;
        (stamp_s, colour, depth)
    }
}

/// A message stamped `stamp_s` already waits: this one was sent twice.
fn is_waiting<T>(queue: &VecDeque<(f64, T)>, stamp_s: f64) -> bool {
    queue.iter().any(|(t, _)| *t == stamp_s)
}

/// Removes and returns the message nearest `stamp_s` within `tolerance_s`, if any.
fn take_nearest<T>(
    queue: &mut VecDeque<(f64, T)>,
    stamp_s: f64,
    tolerance_s: f64,
) -> Option<(f64, T)> {
    let (at, gap) = queue
        .iter()
        .enumerate()
        .map(|(i, (t, _))| (i, (t - stamp_s).abs()))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    if gap > tolerance_s {
        return None;
    }
    queue.remove(at)
}

fn push_bounded<T>(
    queue: &mut VecDeque<(f64, T)>,
    stamp_s: f64,
    item: T,
    counts: &mut PairingCounts,
) {
    if queue.len() == WAITING_PER_KIND {
        queue.pop_front();
        counts.unpaired += 1;
    }
    // Arrival order is nearly stamp order; keep the queue sorted so the oldest leave first.
    let at = queue.partition_point(|(t, _)| *t <= stamp_s);
    queue.insert(at, (stamp_s, item));
}

/// Drops the messages stamped at or before `stamp_s`; how many.
fn drop_older<T>(queue: &mut VecDeque<(f64, T)>, stamp_s: f64) -> usize {
    let older = queue.partition_point(|(t, _)| *t <= stamp_s);
    queue.drain(..older);
    older
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pairing() -> Pairing<&'static str, &'static str> {
        Pairing::new(0.02)
    }

    #[test]
    fn pairs_in_either_order_within_the_tolerance() {
        let mut p = pairing();
        assert_eq!(p.push_colour(10.0, "c0"), None);
        assert_eq!(p.push_depth(10.015, "d0"), Some((10.0, "c0", "d0")));
        assert_eq!(p.push_depth(10.033, "d1"), None);
        assert_eq!(p.push_colour(10.034, "c1"), Some((10.034, "c1", "d1")));
        assert_eq!(p.counts().paired, 2);
        assert_eq!(p.counts().unpaired, 0);
    }

    #[test]
    fn a_message_without_partner_is_counted_once_a_newer_pair_forms() {
        let mut p = pairing();
        assert_eq!(p.push_colour(1.0, "lonely"), None);
        assert_eq!(p.push_colour(1.1, "c"), None);
        assert_eq!(p.push_depth(1.105, "d"), Some((1.1, "c", "d")));
        assert_eq!(p.counts().unpaired, 1);
        // Its depth, arriving after all, is now stale.
        assert_eq!(p.push_depth(1.0, "late"), None);
        assert_eq!(p.counts().stale, 1);
    }

    #[test]
    fn outside_the_tolerance_nothing_pairs() {
        let mut p = pairing();
        assert_eq!(p.push_colour(5.0, "c"), None);
        assert_eq!(p.push_depth(5.03, "d"), None);
        assert_eq!(p.counts().paired, 0);
    }

    #[test]
    fn the_nearest_partner_is_chosen() {
        let mut p = pairing();
        p.push_depth(2.0, "far");
        p.push_depth(2.012, "near");
        assert_eq!(p.push_colour(2.01, "c"), Some((2.01, "c", "near")));
        // "far" is older than the pair: dropped as unpaired.
        assert_eq!(p.counts().unpaired, 1);
    }

    #[test]
    fn duplicates_and_unstamped_messages_are_dropped_and_counted() {
        let mut p = pairing();
        p.push_colour(3.0, "c");
        assert!(p.push_depth(3.0, "d").is_some());
        assert_eq!(p.push_colour(3.0, "c again"), None);
        // Twice while the first still waits for its depth.
        p.push_colour(4.0, "c4");
        assert_eq!(p.push_colour(4.0, "c4 again"), None);
        assert_eq!(p.push_depth(4.0, "d4"), Some((4.0, "c4", "d4")));
        assert_eq!(p.push_depth(0.0, "no stamp"), None);
        assert_eq!(p.counts().stale, 2);
        assert_eq!(p.counts().unstamped, 1);
        assert_eq!(p.counts().unpaired, 0);
    }

    #[test]
    fn a_publisher_restart_starts_pairing_again() {
        let mut p = pairing();
        p.push_colour(100.0, "c");
        assert!(p.push_depth(100.0, "d").is_some());
        p.push_colour(100.5, "waiting");
        assert_eq!(p.push_colour(3.0, "c after restart"), None);
        assert_eq!(p.counts().restarts, 1);
        assert_eq!(p.counts().unpaired, 1);
        assert_eq!(
            p.push_depth(3.01, "d after restart"),
            Some((3.0, "c after restart", "d after restart"))
        );
    }

    #[test]
    fn a_queue_holds_a_bounded_number_of_waiting_messages() {
        let mut p = pairing();
        for i in 0..(WAITING_PER_KIND + 5) {
            assert_eq!(p.push_colour(1.0 + i as f64 * 0.1, "c"), None);
        }
        assert_eq!(p.counts().unpaired, 5);
    }
}
