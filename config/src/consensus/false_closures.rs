//! `[consensus.false_closures]`: deliberately wrong loop closures, injected into the pose graph to
//! measure how robust the consensus is to the place-recognition and alignment mistakes a real
//! swarm makes (docs/method.md, The consensus: pose graph). Off by default; never for a real run.

use geometry::checks::{FieldError, non_negative, positive};
use serde::{Deserialize, Serialize};

/// Every time a verified closure joins the pose graph, wrong ones are added beside it until they
/// make up `fraction` of the graph's closures. Each joins two random keyframes (of the same agent
/// or of two agents, half of each where the swarm has both) with a random transform: a rotation
/// about a random axis by up to `max_rotation_deg`, a translation in a random direction of up to
/// `max_translation_m`. They go through the same robust solve as the real ones and are listed in
/// consensus.json with `origin: "injected"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FalseClosureConfig {
    /// Share of the pose graph's closures that are injected wrong ones, in [0, 0.9] (0: none).
    pub fraction: f64,
    /// Seed of the choice of keyframes and transforms (the same seed injects the same closures
    /// for the same closure order).
    pub seed: u64,
    /// Largest translation of an injected transform.
    pub max_translation_m: f64,
    /// Largest rotation angle of an injected transform.
    pub max_rotation_deg: f64,
}

impl Default for FalseClosureConfig {
    fn default() -> Self {
        Self {
            fraction: 0.0,
            seed: 0,
            // The size of a room: a wrong place match points anywhere in it.
            max_translation_m: 2.0,
            max_rotation_deg: 180.0,
        }
    }
}

impl FalseClosureConfig {
    /// Checks ranges; returns the offending field (`consensus.false_closures.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        // At 0.9 nine in ten closures are wrong; beyond it the real ones are a rounding error.
        if !(0.0..=0.9).contains(&self.fraction) {
            return Err((
                "consensus.false_closures.fraction",
                format!("must be in [0, 0.9], got {}", self.fraction),
            ));
        }
        positive(
            "consensus.false_closures.max_translation_m",
            self.max_translation_m,
        )?;
        non_negative(
            "consensus.false_closures.max_rotation_deg",
            self.max_rotation_deg,
        )?;
        if self.max_rotation_deg > 180.0 {
            return Err((
                "consensus.false_closures.max_rotation_deg",
                format!("must be at most 180, got {}", self.max_rotation_deg),
            ));
        }
        Ok(())
    }

    /// Whether any closure is injected.
    pub fn enabled(&self) -> bool {
        self.fraction > 0.0
    }

    /// Injected closures due beside `verified` real ones: the smallest count that keeps the
    /// injected share at `fraction` or above, `ceil(fraction / (1 - fraction) * verified)`.
    pub fn due(&self, verified: usize) -> usize {
        if !self.enabled() || verified == 0 {
            return 0;
        }
        // The small epsilon keeps exact ratios (0.25 / 0.75 * 3 = 1) from rounding up.
        (self.fraction / (1.0 - self.fraction) * verified as f64 - 1e-9).ceil() as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn due_keeps_the_injected_share_at_the_fraction() {
        let config = |fraction| FalseClosureConfig {
            fraction,
            ..FalseClosureConfig::default()
        };
        assert_eq!(config(0.0).due(50), 0);
        assert_eq!(config(0.3).due(0), 0);
        for fraction in [0.1, 0.3, 0.5] {
            for verified in 1..40 {
                let injected = config(fraction).due(verified);
                let share = injected as f64 / (injected + verified) as f64;
                assert!(share >= fraction - 1e-12, "{fraction} {verified}: {share}");
                // One fewer would fall below the fraction.
                let fewer = (injected - 1) as f64 / (injected - 1 + verified) as f64;
                assert!(fewer < fraction, "{fraction} {verified}: {fewer}");
            }
        }
    }

    #[test]
    fn out_of_range_values_name_their_field() {
        let bad = FalseClosureConfig {
            fraction: 0.95,
            ..FalseClosureConfig::default()
        };
        assert_eq!(
            bad.validate().unwrap_err().0,
            "consensus.false_closures.fraction"
        );
        let bad = FalseClosureConfig {
            max_rotation_deg: 200.0,
            ..FalseClosureConfig::default()
        };
        assert_eq!(
            bad.validate().unwrap_err().0,
            "consensus.false_closures.max_rotation_deg"
        );
        assert!(FalseClosureConfig::default().validate().is_ok());
    }
}
