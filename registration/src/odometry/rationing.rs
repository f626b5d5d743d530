//! At sensor pace, how much of the tracker's time the expensive recovery guesses may take
//! (docs/method.md, One agent: Tracking, "Recovery at sensor pace").
//!
//! A live camera does not wait for the tracker: while one frame is searched for, the next ones
//! are overwritten, and each one missed widens the step the next frame must bridge. The
//! image-feature and geometry guesses cost tenths of a second each on a CPU. When they fail
//! frame after frame, each failure leaves the tracker further behind the camera, the next frame
//! is harder still, and the tracker may never catch up: a stall that feeds itself. So their time
//! is rationed like a token bucket: the tracker earns `share` of every wall-clock millisecond as
//! credit, up to `burst_ms`; a guess may start while the credit is positive, and what it took is
//! paid from it (the credit may go negative, so one long search is paid back before the next).
//! Over any long stretch at most `share` of the time goes to them; a first stall still gets
//! every guess (the burst). In between, a lost frame tries only the coarse-to-fine G-ICP, fails
//! fast, and the tracker reaches the newest frame sooner: after `max_consecutive_failures` it
//! starts a new segment there, whose relocalisation runs on a thread of its own
//! (super::relocalisation).
//!
//! Paced and offline runs have time and are never rationed, so their results do not depend on
//! the machine's speed.

use std::cell::Cell;
use std::time::Instant;

/// The credit of the expensive recovery work; see the module documentation. Its state is in
/// cells so that the guesses, which borrow the odometry, can consult and pay it.
#[derive(Debug, Clone)]
pub struct RecoveryRation {
    share: f64,
    burst_ms: f64,
    credit_ms: Cell<f64>,
    /// When the credit was last brought up to date.
    updated: Cell<Option<Instant>>,
    /// Work not started for want of credit.
    refused: Cell<usize>,
}

impl RecoveryRation {
    /// A full credit (`burst_ms`), earning `share` of the wall time; `share >= 1` never limits.
    pub fn new(share: f64, burst_ms: f64) -> Self {
        Self {
            share,
            burst_ms,
            credit_ms: Cell::new(burst_ms),
            updated: Cell::new(None),
            refused: Cell::new(0),
        }
    }

    /// Whether expensive work may start at `now`; a refusal is counted.
    pub fn allows(&self, now: Instant) -> bool {
        self.earn(now);
        let allowed = self.share >= 1.0 || self.credit_ms.get() > 0.0;
        if !allowed {
            self.refused.set(self.refused.get() + 1);
        }
        allowed
    }

    /// Pays for work that took `ms`, ending at `now`.
    pub fn pay(&self, ms: f64, now: Instant) {
        self.earn(now);
        self.credit_ms.set(self.credit_ms.get() - ms);
    }

    /// The credit now (ms; negative while a search is being paid back).
    pub fn credit_ms(&self) -> f64 {
        self.credit_ms.get()
    }

    /// How many times work was refused.
    pub fn refused(&self) -> usize {
        self.refused.get()
    }

    fn earn(&self, now: Instant) {
        if let Some(updated) = self.updated.get() {
            let earned = now.saturating_duration_since(updated).as_secs_f64() * 1e3 * self.share;
            self.credit_ms
                .set((self.credit_ms.get() + earned).min(self.burst_ms));
        }
        self.updated.set(Some(now));
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    fn at(start: Instant, ms: u64) -> Instant {
        start + Duration::from_millis(ms)
    }

    #[test]
    fn a_first_search_may_take_the_burst_then_searches_wait_for_their_share() {
        let start = Instant::now();
        let ration = RecoveryRation::new(0.5, 1000.0);
        assert!(ration.allows(start));
        // A 900 ms search from a full credit (what it earned meanwhile is over the burst).
        ration.pay(900.0, at(start, 900));
        assert!((ration.credit_ms() - 100.0).abs() < 1e-9);
        assert!(ration.allows(at(start, 900)));
        // A second one overdraws it: 100 + 450 earned - 900.
        ration.pay(900.0, at(start, 1800));
        assert!((ration.credit_ms() + 350.0).abs() < 1e-9);
        // 350 ms of debt at a share of 0.5: 700 ms of wall time pay it back.
        assert!(!ration.allows(at(start, 1800)));
        assert!(!ration.allows(at(start, 2499)));
        assert!(ration.allows(at(start, 2501)));
        assert_eq!(ration.refused(), 2);
    }

    #[test]
    fn credit_never_exceeds_the_burst() {
        let start = Instant::now();
        let ration = RecoveryRation::new(0.5, 1000.0);
        assert!(ration.allows(start));
        assert!(ration.allows(at(start, 60_000)));
        assert!((ration.credit_ms() - 1000.0).abs() < 1e-9);
    }

    #[test]
    fn a_share_of_one_never_limits() {
        let start = Instant::now();
        let ration = RecoveryRation::new(1.0, 0.0);
        ration.pay(10_000.0, at(start, 1));
        assert!(ration.allows(at(start, 2)));
    }
}
