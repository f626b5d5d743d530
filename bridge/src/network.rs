//! The zenoh session of a bridge: peer mode, only the endpoints given on the command line (no
//! multicast scouting, so a bridge never reaches hosts it was not told about), and the QoS every
//! relayed message travels with.

use anyhow::{Context, Result};
use zenoh::Config;
use zenoh::qos::{CongestionControl, Priority};

/// Where a bridge listens and whom it connects to (zenoh endpoints such as
/// `tcp/192.168.1.10:7447`).
#[derive(Debug, Clone, Default)]
pub struct Endpoints {
    pub listen: Vec<String>,
    pub connect: Vec<String>,
}

/// Every relayed message crosses with:
/// - reliability `Reliable` (zenoh's default): a lost packet is re-sent by the link, never
///   skipped: receivers would see a sequence gap, and a lost keyframe is never acceptable;
/// - congestion control `Block`: when the network is slower than the agents, the bridge's put
///   waits instead of dropping; the wait reaches the agent through the iceoryx2 queues and
///   their full-queue policy, like a slow consumer on one host;
/// - one priority (`Data`) for every topic: zenoh keeps order only within a priority, and the
///   consumers rely on an agent's order (hello before data, final map before goodbye);
/// - zenoh's own fragmentation for large messages (a patch of a million Gaussians is 56 MB;
///   the link splits it into batches and the far side reassembles it before delivery), and no
///   link compression: Gaussian attributes and depth are floats and small integers that LZ4
///   barely shrinks, so compression would cost CPU on every byte for little gain.
pub const CONGESTION_CONTROL: CongestionControl = CongestionControl::Block;
pub const PRIORITY: Priority = Priority::Data;

/// The zenoh configuration of a bridge.
pub fn config(endpoints: &Endpoints) -> Result<Config> {
    let mut config = Config::default();
    let set = |config: &mut Config, key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow::anyhow!("zenoh config {key} = {value}: {e}"))
    };
    set(&mut config, "mode", "\"peer\"".into())?;
    set(&mut config, "scouting/multicast/enabled", "false".into())?;
    set(
        &mut config,
        "listen/endpoints",
        serde_json::to_string(&endpoints.listen).context("listen endpoints")?,
    )?;
    set(
        &mut config,
        "connect/endpoints",
        serde_json::to_string(&endpoints.connect).context("connect endpoints")?,
    )?;
    // A bridge started before its peer keeps trying to connect instead of giving up.
    set(&mut config, "connect/exit_on_failure", "false".into())?;
    set(&mut config, "connect/timeout_ms", "-1".into())?;
    Ok(config)
}
