//! The `[network]` section: what an agent may send between hosts, read by the agent host's
//! `mac-bridge` (docs/method.md, Across hosts: bandwidth budget). On one host the swarm shares
//! memory and nothing here applies.

use geometry::checks::{FieldError, non_negative, positive};
use serde::{Deserialize, Serialize};

/// The per-agent bandwidth budget across hosts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NetworkConfig {
    /// Cap on what each agent sends to the other hosts, in kB/s (1 kB = 1000 bytes), averaged
    /// over `burst_s`. 0: no cap (messages cross as they are laid out in shared memory). With a
    /// cap, the agent host's bridge compresses keyframe images and Gaussian patches (lossless
    /// first, then lossy as the backlog grows) and defers them; it never drops a keyframe.
    pub agent_kb_per_s: f64,
    /// Seconds of unused budget an agent may spend at once (the token bucket's depth).
    pub burst_s: f64,
    /// The deferral the bridge aims for: it picks the least lossy encoding under which what an
    /// agent has waiting would go within this many seconds at the cap.
    pub target_delay_s: f64,
    /// JPEG quality (1-100) of keyframe colour under the lossy encodings.
    pub jpeg_quality: u8,
    /// Under a cap, the consensus waits this many seconds more before it asks an agent again
    /// for the missing part of a keyframe (`[consensus.resend] after_s`): parts deferred by the
    /// budget are late, not lost.
    pub resend_allowance_s: f64,
    /// A bridge asked to stop (its host shutting down, its agent done) first sends what still
    /// waits for the budget and for the consumer host's acknowledgement, for at most this long.
    pub drain_timeout_s: f64,
}

impl Default for NetworkConfig {
    fn default() -> Self {
        Self {
            agent_kb_per_s: 0.0,
            burst_s: 1.0,
            target_delay_s: 3.0,
            jpeg_quality: 90,
            resend_allowance_s: 60.0,
            drain_timeout_s: 600.0,
        }
    }
}

impl NetworkConfig {
    /// The cap in bytes per second, `None` when there is none.
    pub fn agent_bytes_per_s(&self) -> Option<f64> {
        (self.agent_kb_per_s > 0.0).then_some(self.agent_kb_per_s * 1000.0)
    }

    /// Seconds the consensus waits for a keyframe's missing part before asking again.
    pub fn resend_after_s(&self, after_s: f64) -> f64 {
        match self.agent_bytes_per_s() {
            Some(_) => after_s + self.resend_allowance_s,
            None => after_s,
        }
    }

    /// Checks ranges; returns the offending field (`network.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        non_negative("network.agent_kb_per_s", self.agent_kb_per_s)?;
        positive("network.burst_s", self.burst_s)?;
        positive("network.target_delay_s", self.target_delay_s)?;
        non_negative("network.resend_allowance_s", self.resend_allowance_s)?;
        non_negative("network.drain_timeout_s", self.drain_timeout_s)?;
        if !(1..=100).contains(&self.jpeg_quality) {
            return Err((
                "network.jpeg_quality",
                format!("{} is not in 1..=100", self.jpeg_quality),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_cap_by_default_and_bad_values_are_named() {
        let config = NetworkConfig::default();
        assert_eq!(config.agent_bytes_per_s(), None);
        assert!(config.validate().is_ok());
        let capped = NetworkConfig {
            agent_kb_per_s: 50.0,
            ..NetworkConfig::default()
        };
        assert_eq!(capped.agent_bytes_per_s(), Some(50_000.0));
        assert_eq!(config.resend_after_s(2.0), 2.0);
        assert_eq!(capped.resend_after_s(2.0), 62.0);
        let negative = NetworkConfig {
            agent_kb_per_s: -1.0,
            ..NetworkConfig::default()
        };
        assert_eq!(negative.validate().unwrap_err().0, "network.agent_kb_per_s");
        let quality = NetworkConfig {
            jpeg_quality: 0,
            ..NetworkConfig::default()
        };
        assert_eq!(quality.validate().unwrap_err().0, "network.jpeg_quality");
    }
}
