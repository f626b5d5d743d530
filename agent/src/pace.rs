//! The camera clock of `mapping.pace = "sensor"` (docs/method.md, One agent: Pace).
//!
//! A live RGB-D driver holds the newest frame; a frame nobody took before the next one arrived
//! is overwritten. [`SensorClock`] replays a dataset that way: frame `i` becomes available at its
//! own timestamp (relative to the first frame's, on the wall clock from the moment the agent took
//! the first frame); when the agent asks for a frame it gets the newest one available, waiting
//! for it when it is early; every older one it never took is dropped and counted.

use std::time::{Duration, Instant};

/// What to do with the next frame in order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Admission {
    /// Take it, after waiting this long for it to arrive (zero when it is already there).
    Take {
        /// The frame's arrival (its timestamp relative to the first frame's) minus the wall time
        /// since the first frame was taken; zero when it is already there.
        wait: Duration,
    },
    /// A newer frame has already arrived: a live driver would have overwritten this one.
    Drop,
}

/// Replays frame timestamps on the wall clock; counts what a slow agent missed.
#[derive(Debug, Default)]
pub struct SensorClock {
    /// The first frame's timestamp, once it was taken.
    first_timestamp_s: Option<f64>,
    /// When the first frame was taken ([`Self::take_now`]).
    started: Option<Instant>,
    dropped: usize,
}

impl SensorClock {
    /// A clock that has taken no frame yet: the first frame it admits starts it.
    pub fn new() -> Self {
        Self::default()
    }

    /// The next frame in order has `timestamp_s`, the one after it `next_timestamp_s` (`None` at
    /// the end); `elapsed` is the wall time since the first frame was taken. The first frame is
    /// always taken at once and starts the clock.
    pub fn admit(
        &mut self,
        timestamp_s: f64,
        next_timestamp_s: Option<f64>,
        elapsed: Duration,
    ) -> Admission {
        let Some(first) = self.first_timestamp_s else {
            self.first_timestamp_s = Some(timestamp_s);
            return Admission::Take {
                wait: Duration::ZERO,
            };
        };
        let now_s = elapsed.as_secs_f64();
        let arrives_s = timestamp_s - first;
        if arrives_s > now_s {
            return Admission::Take {
                wait: Duration::from_secs_f64(arrives_s - now_s),
            };
        }
        match next_timestamp_s {
            Some(next) if next - first <= now_s => {
                self.dropped += 1;
                Admission::Drop
            }
            _ => Admission::Take {
                wait: Duration::ZERO,
            },
        }
    }

    /// [`Self::admit`] on the wall clock: sleeps until the frame arrives when it is early;
    /// returns false for a frame to drop.
    pub fn take_now(&mut self, timestamp_s: f64, next_timestamp_s: Option<f64>) -> bool {
        let started = *self.started.get_or_insert_with(Instant::now);
        match self.admit(timestamp_s, next_timestamp_s, started.elapsed()) {
            Admission::Take { wait } => {
                std::thread::sleep(wait);
                true
            }
            Admission::Drop => false,
        }
    }

    /// Frames dropped so far.
    pub fn dropped(&self) -> usize {
        self.dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Replays `frames` timestamps through the clock for an agent that needs `work_s` per frame
    /// it takes, on a simulated wall clock; returns (the frames taken, at what time each).
    fn replay(timestamps: &[f64], work_s: f64) -> (Vec<usize>, Vec<f64>, usize) {
        let mut clock = SensorClock::new();
        let mut now_s = 0.0;
        let (mut taken, mut at) = (Vec::new(), Vec::new());
        for (i, &t) in timestamps.iter().enumerate() {
            let next = timestamps.get(i + 1).copied();
            match clock.admit(t, next, Duration::from_secs_f64(now_s)) {
                Admission::Take { wait } => {
                    now_s += wait.as_secs_f64();
                    taken.push(i);
                    at.push(now_s);
                    now_s += work_s;
                }
                Admission::Drop => {}
            }
        }
        (taken, at, clock.dropped())
    }

    fn camera(frames: usize, hz: f64) -> Vec<f64> {
        // An arbitrary start: only differences count.
        (0..frames).map(|i| 1000.0 + i as f64 / hz).collect()
    }

    #[test]
    fn a_fast_agent_takes_every_frame_at_its_timestamp() {
        let timestamps = camera(30, 30.0);
        let (taken, at, dropped) = replay(&timestamps, 0.010);
        assert_eq!(taken.len(), 30);
        assert_eq!(dropped, 0);
        for (i, t) in taken.iter().zip(&at) {
            assert!((t - (timestamps[*i] - timestamps[0])).abs() < 1e-9);
        }
    }

    #[test]
    fn a_slow_agent_gets_the_newest_frame_and_counts_the_overwritten_ones() {
        // 30 Hz camera, 80 ms per frame: the agent takes about one frame in 2.4.
        let timestamps = camera(90, 30.0);
        let (taken, at, dropped) = replay(&timestamps, 0.080);
        assert_eq!(taken.len() + dropped, 90);
        assert!((35..=40).contains(&taken.len()), "{} taken", taken.len());
        for (i, t) in taken.iter().zip(&at) {
            let arrived = timestamps[*i] - timestamps[0];
            // Never before it arrived, and it is the newest one there when taken.
            assert!(*t >= arrived - 1e-9);
            if let Some(next) = timestamps.get(i + 1) {
                assert!(
                    next - timestamps[0] > *t,
                    "frame {i} was already overwritten"
                );
            }
        }
    }

    #[test]
    fn gaps_in_the_sequence_are_waited_for_not_dropped() {
        // A 2 s gap (a recording paused): the frame after it is waited for.
        let timestamps = [0.0, 0.033, 2.033, 2.066];
        let (taken, at, dropped) = replay(&timestamps, 0.010);
        assert_eq!((taken.len(), dropped), (4, 0));
        assert!((at[2] - 2.033).abs() < 1e-9);
    }
}
