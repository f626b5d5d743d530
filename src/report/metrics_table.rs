//! The metrics table: every key of metrics.json, with a readable name and unit. Keys this table
//! does not know yet (a figure added to `SwarmMetrics` later) are still shown, raw, so the
//! report never hides a figure.

use serde_json::{Map, Value};

use super::html::{Cell, table};

/// How a metrics.json value is shown.
#[derive(Debug, Clone, Copy)]
enum Unit {
    /// Metres, shown in centimetres (trajectory errors are centimetre-scale).
    MetresAsCentimetres,
    /// Bytes per second, shown in kB/s.
    BytesPerSecondAsKilobytes,
    /// A number with a unit suffix (empty for dimensionless figures) and fixed decimals.
    Scaled {
        suffix: &'static str,
        decimals: usize,
    },
    /// A whole number.
    Count,
    /// A list of agent ids.
    AgentIds,
    /// Shown as written.
    Text,
}

const CENTIMETRES_PER_METRE: f64 = 100.0;
const BYTES_PER_KILOBYTE: f64 = 1000.0;
/// Decimals of a centimetre figure (0.01 cm = 0.1 mm, below any tracker's accuracy).
const CENTIMETRE_DECIMALS: usize = 2;
const KILOBYTE_DECIMALS: usize = 1;
/// Decimals of a number the table has no format for.
const RAW_DECIMALS: usize = 4;

/// Known keys in the order the table lists them: (key, readable name, unit).
const FORMATS: &[(&str, &str, Unit)] = &[
    (
        "ate_joint_rmse_m",
        "Joint ATE RMSE (one SE(3) alignment for all agents)",
        Unit::MetresAsCentimetres,
    ),
    (
        "ate_per_agent_rmse_m",
        "ATE RMSE per agent (under the joint alignment)",
        Unit::MetresAsCentimetres,
    ),
    (
        "agents_not_linked",
        "Agents never placed in the world frame",
        Unit::AgentIds,
    ),
    (
        "descriptor_per_agent",
        "Global descriptor (place recognition), per agent",
        Unit::Text,
    ),
    (
        "psnr",
        "PSNR",
        Unit::Scaled {
            suffix: " dB",
            decimals: 2,
        },
    ),
    (
        "ssim",
        "SSIM",
        Unit::Scaled {
            suffix: "",
            decimals: 3,
        },
    ),
    (
        "lpips",
        "LPIPS (AlexNet)",
        Unit::Scaled {
            suffix: "",
            decimals: 3,
        },
    ),
    (
        "depth_l1_cm",
        "Depth L1",
        Unit::Scaled {
            suffix: " cm",
            decimals: 2,
        },
    ),
    (
        "rendering_source",
        "Rendering figures measured on",
        Unit::Text,
    ),
    ("rendering_frames", "Frames rendered", Unit::Count),
    (
        "psnr_held_out",
        "PSNR, held-out frames (no map was optimised on them)",
        Unit::Scaled {
            suffix: " dB",
            decimals: 2,
        },
    ),
    (
        "ssim_held_out",
        "SSIM, held-out frames",
        Unit::Scaled {
            suffix: "",
            decimals: 3,
        },
    ),
    (
        "lpips_held_out",
        "LPIPS (AlexNet), held-out frames",
        Unit::Scaled {
            suffix: "",
            decimals: 3,
        },
    ),
    (
        "depth_l1_cm_held_out",
        "Depth L1, held-out frames",
        Unit::Scaled {
            suffix: " cm",
            decimals: 2,
        },
    ),
    ("held_out_frames", "Held-out frames rendered", Unit::Count),
    (
        "held_out_unavailable",
        "Why there are no held-out figures",
        Unit::Text,
    ),
    (
        "fps_per_agent",
        "Frames per second, per agent",
        Unit::Scaled {
            suffix: " frames/s",
            decimals: 2,
        },
    ),
    (
        "bytes_per_agent_per_s",
        "Data sent, per agent",
        Unit::BytesPerSecondAsKilobytes,
    ),
    (
        "consensus_latency_ms_median",
        "Consensus latency (median, keyframe in -> correction out)",
        Unit::Scaled {
            suffix: " ms",
            decimals: 0,
        },
    ),
    (
        "loop_closures_accepted",
        "Loop closures accepted",
        Unit::Count,
    ),
    (
        "loop_closures_rejected",
        "Loop closures rejected",
        Unit::Count,
    ),
    (
        "inter_agent_closures_accepted",
        "Inter-agent loop closures accepted",
        Unit::Count,
    ),
    (
        "wall_s",
        "Wall time of the consensus",
        Unit::Scaled {
            suffix: " s",
            decimals: 1,
        },
    ),
    ("transport", "Transport between the processes", Unit::Text),
    (
        "network_bytes_per_agent",
        "Network traffic per agent (bridge reports)",
        Unit::Text,
    ),
];

/// Shown for a figure that is `null` (not measured in this run).
const NOT_MEASURED: &str = "n/a";

fn number(value: f64, unit: Unit) -> String {
    match unit {
        Unit::MetresAsCentimetres => {
            format!("{:.CENTIMETRE_DECIMALS$} cm", value * CENTIMETRES_PER_METRE)
        }
        Unit::BytesPerSecondAsKilobytes => {
            format!("{:.KILOBYTE_DECIMALS$} kB/s", value / BYTES_PER_KILOBYTE)
        }
        Unit::Scaled { suffix, decimals } => format!("{value:.decimals$}{suffix}"),
        Unit::Count => format!("{value:.0}"),
        Unit::AgentIds | Unit::Text => format!("{value:.RAW_DECIMALS$}"),
    }
}

/// One value as text: numbers in their unit, lists as "agent k: ..." (lists of numbers in
/// metrics.json are per agent, in agent order).
fn format_value(value: &Value, unit: Unit) -> String {
    match (value, unit) {
        (Value::Null, _) => NOT_MEASURED.to_string(),
        (Value::Array(ids), Unit::AgentIds) if ids.is_empty() => "none".to_string(),
        (Value::Array(ids), Unit::AgentIds) => ids
            .iter()
            .map(|id| format!("agent {id}"))
            .collect::<Vec<_>>()
            .join(", "),
        (Value::Array(items), _) => items
            .iter()
            .enumerate()
            .map(|(k, item)| format!("agent {k}: {}", format_value(item, unit)))
            .collect::<Vec<_>>()
            .join("; "),
        (Value::Number(n), _) => n
            .as_f64()
            .map_or_else(|| n.to_string(), |v| number(v, unit)),
        (Value::String(text), _) => text.clone(),
        (other, _) => other.to_string(),
    }
}

/// Rows (readable name, value, key) for every key of `metrics`: known keys first, in
/// [`FORMATS`] order, then any other key as it is.
fn rows(metrics: &Map<String, Value>) -> Vec<(String, String, String)> {
    let known = FORMATS.iter().filter_map(|(key, name, unit)| {
        let value = metrics.get(*key)?;
        Some((
            name.to_string(),
            format_value(value, *unit),
            key.to_string(),
        ))
    });
    let unknown = metrics
        .iter()
        .filter(|(key, _)| !FORMATS.iter().any(|(known, ..)| known == key))
        .map(|(key, value)| (key.clone(), format_value(value, Unit::Text), key.clone()));
    known.chain(unknown).collect()
}

/// Whether a key's value is words rather than figures.
fn is_text(key: &str) -> bool {
    FORMATS
        .iter()
        .any(|(known, _, unit)| *known == key && matches!(unit, Unit::Text | Unit::AgentIds))
}

/// The metrics table's HTML.
pub fn metrics_table(metrics: &Map<String, Value>) -> String {
    let rows: Vec<Vec<Cell>> = rows(metrics)
        .into_iter()
        .map(|(name, value, key)| {
            // Figures line up on the right; words (a source, agent names) read from the left.
            let value = if is_text(&key) {
                Cell::text(value)
            } else {
                Cell::number(value)
            };
            vec![Cell::text(name), value, Cell::text(key)]
        })
        .collect();
    table(&["Figure", "Value", "metrics.json key"], &rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd::eval::swarm::SwarmMetrics;

    fn example() -> SwarmMetrics {
        SwarmMetrics {
            ate_joint_rmse_m: Some(0.0123),
            ate_per_agent_rmse_m: vec![Some(0.01), None],
            agents_not_linked: vec![1],
            descriptor_per_agent: vec![Some("alexnet-gem".into()), None],
            psnr: Some(25.5),
            ssim: Some(0.8),
            lpips: None,
            depth_l1_cm: Some(1.5),
            rendering_source: "merged map",
            rendering_frames: 10,
            psnr_held_out: Some(25.0),
            ssim_held_out: Some(0.79),
            lpips_held_out: None,
            depth_l1_cm_held_out: Some(1.6),
            held_out_frames: 9,
            held_out_unavailable: None,
            fps_per_agent: vec![Some(2.0), None],
            bytes_per_agent_per_s: vec![Some(150_000.0), None],
            consensus_latency_ms_median: Some(420.0),
            loop_closures_accepted: 3,
            loop_closures_rejected: 1,
            inter_agent_closures_accepted: 2,
            wall_s: Some(100.0),
            transport: Some(crate::cmd::swarm::record::Transport::Zenoh),
            network_bytes_per_agent: Some(Default::default()),
        }
    }

    #[test]
    fn every_swarm_metrics_key_has_a_readable_format() {
        let value = serde_json::to_value(example()).unwrap();
        for key in value.as_object().unwrap().keys() {
            assert!(
                FORMATS.iter().any(|(known, ..)| known == key),
                "metrics.json key {key} has no entry in FORMATS"
            );
        }
    }

    #[test]
    fn values_read_in_their_units() {
        let value = serde_json::to_value(example()).unwrap();
        let rows = rows(value.as_object().unwrap());
        let find = |key: &str| rows.iter().find(|r| r.2 == key).unwrap().1.clone();
        assert_eq!(find("ate_joint_rmse_m"), "1.23 cm");
        assert_eq!(
            find("ate_per_agent_rmse_m"),
            "agent 0: 1.00 cm; agent 1: n/a"
        );
        assert_eq!(find("agents_not_linked"), "agent 1");
        assert_eq!(
            find("descriptor_per_agent"),
            "agent 0: alexnet-gem; agent 1: n/a"
        );
        assert_eq!(
            find("bytes_per_agent_per_s"),
            "agent 0: 150.0 kB/s; agent 1: n/a"
        );
        assert_eq!(find("lpips"), "n/a");
        assert_eq!(find("loop_closures_accepted"), "3");
        assert_eq!(rows.len(), value.as_object().unwrap().len());
    }

    #[test]
    fn unknown_keys_are_still_listed() {
        let mut map = Map::new();
        map.insert("new_figure".into(), serde_json::json!(1.5));
        let rows = rows(&map);
        assert_eq!(
            rows,
            [("new_figure".into(), "1.5000".into(), "new_figure".into())]
        );
    }
}
