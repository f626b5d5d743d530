//! DIR/report.html of a swarm run: one self-contained file that opens offline: the
//! metrics table, top-down trajectories under the joint alignment, per-agent ATE over time, the
//! merged map's renders next to ground-truth frames, and the consensus's closure events on a
//! timeline. Charts are inline SVG, images `data:` URIs; nothing is fetched.
//!
//! The report shows what the run left and says plainly what it did not (an agent never linked, no
//! renders, no consensus.json): a partial run still gets a report.

mod html;
mod metrics_table;
mod run_dir;
mod svg;

use std::path::{Path, PathBuf};

use anyhow::Context;
use base64::Engine as _;
use serde_json::Value;

use html::{Cell, details, document, note, paragraph, preformatted, section, table};
use run_dir::{ClosureEvent, Outcome, Trajectories};
use svg::{Chart, Range, Shape, Stroke, agent_colour};

/// The report's file name inside the run directory.
pub const REPORT_FILE: &str = "report.html";
/// Side-by-side PNGs embedded at most: each is a few hundred kB of base64, and a report of tens
/// of MB opens slowly.
const MAX_EMBEDDED_RENDERS: usize = 12;
const CENTIMETRES_PER_METRE: f64 = 100.0;
const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// Writes DIR/report.html and returns its path.
pub fn write_report(dir: &Path) -> anyhow::Result<PathBuf> {
    let path = dir.join(REPORT_FILE);
    std::fs::write(&path, build_report(dir))
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// The report's HTML for the run in `dir`.
pub fn build_report(dir: &Path) -> String {
    let metrics = run_dir::read_json(&dir.join("metrics.json"));
    let consensus = run_dir::read_json(&dir.join("consensus.json"));
    let ids = run_dir::agent_ids(metrics.as_ref().ok(), consensus.as_ref().ok());
    let trajectories = run_dir::load_trajectories(dir, &ids);
    let sections = vec![
        run_section(dir, &ids, consensus.as_ref().ok()),
        metrics_section(&metrics),
        top_down_section(&trajectories),
        ate_over_time_section(&trajectories),
        renders_section(dir),
        consensus_section(&consensus, &ids),
    ];
    document(&format!("Swarm run {}", dir.display()), &sections)
}

fn run_section(dir: &Path, ids: &[u32], consensus: Option<&Value>) -> String {
    let agents = if ids.is_empty() {
        "none found".to_string()
    } else {
        ids.iter()
            .map(u32::to_string)
            .collect::<Vec<_>>()
            .join(", ")
    };
    let mut body = paragraph(&format!(
        "Directory {}; agents: {agents}. Written by mac-ego3d {} (eval swarm).",
        dir.display(),
        env!("CARGO_PKG_VERSION")
    ));
    if consensus.is_some_and(|c| c["interrupted"].as_bool() == Some(true)) {
        body.push_str(&note(
            "The run was interrupted: the figures cover what was done before the stop.",
        ));
    }
    // mac-consensus writes snapshots on request while the run goes on (SIGUSR1).
    if consensus.is_some_and(|c| c["snapshot"].as_bool() == Some(true)) {
        body.push_str(&note(
            "consensus.json is a snapshot taken while the run was still going: the run may \
             have done more since.",
        ));
    }
    let config = dir.join("config.toml");
    match std::fs::read_to_string(&config) {
        Ok(text) => body.push_str(&details(
            "Configuration of the run (config.toml)",
            &preformatted(&text),
        )),
        Err(e) => body.push_str(&note(&format!(
            "No configuration: {}: {e}",
            config.display()
        ))),
    }
    section("run", "Run", &body)
}

fn metrics_section(metrics: &Result<Value, String>) -> String {
    let body = match metrics {
        Ok(Value::Object(map)) => metrics_table::metrics_table(map),
        Ok(_) => note("metrics.json is not a JSON object: no metrics to show."),
        Err(e) => note(&format!("No metrics: {e}")),
    };
    section("metrics", "Metrics", &body)
}

/// `notes` (why agents are not drawn), then `chart` (or a line saying there is nothing).
fn trajectory_body(notes: &[String], chart: Option<String>) -> String {
    let mut body: String = notes.iter().map(|n| note(n)).collect();
    match chart {
        Some(svg) => body.push_str(&svg),
        None => body.push_str(&note(
            "No agent has both a world-frame trajectory and ground truth: nothing to draw.",
        )),
    }
    body
}

/// The two axes along which the ground truth spreads most: the view from above for a walking
/// camera whatever the dataset's up axis is.
fn top_down_axes(trajectories: &Trajectories) -> (usize, usize) {
    let extent = |axis: usize| {
        Range::of(
            trajectories
                .tracks
                .iter()
                .flat_map(|t| t.ground_truth.iter().map(move |p| p[axis])),
        )
        .map_or(0.0, |r| r.span())
    };
    let mut axes = [0, 1, 2];
    axes.sort_by(|&a, &b| extent(b).total_cmp(&extent(a)));
    let (first, second) = (axes[0].min(axes[1]), axes[0].max(axes[1]));
    (first, second)
}

fn top_down_section(trajectories: &Trajectories) -> String {
    let (a, b) = top_down_axes(trajectories);
    let all_points = || {
        trajectories
            .tracks
            .iter()
            .flat_map(|t| t.ground_truth.iter().chain(&t.estimate))
    };
    let chart = Range::of(all_points().map(|p| p[a]))
        .zip(Range::of(all_points().map(|p| p[b])))
        .map(|(x_range, y_range)| {
            let mut chart = Chart::equal_aspect(
                x_range,
                y_range,
                &format!("{} (m)", AXIS_NAMES[a]),
                &format!("{} (m)", AXIS_NAMES[b]),
            );
            for track in &trajectories.tracks {
                let colour = agent_colour(track.id as usize);
                let project = |points: &[nalgebra::Point3<f64>]| -> Vec<(f64, f64)> {
                    points.iter().map(|p| (p[a], p[b])).collect()
                };
                chart.line(
                    &project(&track.ground_truth),
                    Stroke {
                        colour,
                        reference: true,
                    },
                    &format!("agent {} ground truth", track.id),
                );
                chart.line(
                    &project(&track.estimate),
                    Stroke {
                        colour,
                        reference: false,
                    },
                    &format!("agent {} estimate", track.id),
                );
            }
            chart.render()
        });
    let mut body = paragraph(&format!(
        "Seen along {}: every agent's world-frame estimate (agent_K.tum, solid) after the one \
         SE(3) alignment of the joint ATE, and its ground truth (wide, pale, dashed), in the \
         ground-truth frame.",
        AXIS_NAMES[3 - a - b]
    ));
    body.push_str(&trajectory_body(&trajectories.notes, chart));
    section("trajectories", "Trajectories, top-down", &body)
}

fn ate_over_time_section(trajectories: &Trajectories) -> String {
    let errors = || trajectories.tracks.iter().flat_map(|t| t.errors.iter());
    let chart = Range::of(errors().map(|e| e.0))
        .zip(Range::of(
            errors().map(|e| e.1 * CENTIMETRES_PER_METRE).chain([0.0]),
        ))
        .map(|(x_range, y_range)| {
            let mut chart = Chart::new(
                x_range,
                y_range,
                "time since the agent's first frame (s)",
                "translation error (cm)",
            );
            for track in &trajectories.tracks {
                let points: Vec<(f64, f64)> = track
                    .errors
                    .iter()
                    .map(|(t, e)| (*t, e * CENTIMETRES_PER_METRE))
                    .collect();
                chart.line(
                    &points,
                    Stroke {
                        colour: agent_colour(track.id as usize),
                        reference: false,
                    },
                    &format!("agent {}", track.id),
                );
            }
            chart.render()
        });
    let mut body = paragraph(
        "Each agent's translation error per frame under the joint alignment: the errors whose \
         RMS is the per-agent ATE of the metrics table.",
    );
    // The reasons were given once, under the trajectories.
    let left_out = if trajectories.notes.is_empty() {
        Vec::new()
    } else {
        vec!["Some agents are left out: see Trajectories, top-down, for why.".to_string()]
    };
    body.push_str(&trajectory_body(&left_out, chart));
    section("ate", "Per-agent ATE over time", &body)
}

/// An `<img>` with the PNG at `path` inline.
fn embedded_png(path: &Path) -> Result<String, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let caption = run_dir::render_caption(path);
    Ok(format!(
        "<figure><img alt=\"{0}\" src=\"data:image/png;base64,{1}\"><figcaption>{0}: \
         ground truth (left), merged map (right)</figcaption></figure>\n",
        html::escape(&caption),
        base64::engine::general_purpose::STANDARD.encode(bytes)
    ))
}

fn renders_section(dir: &Path) -> String {
    let files = match run_dir::render_files(dir) {
        Ok(files) if !files.is_empty() => files,
        Ok(_) | Err(_) => {
            let body = note(&format!(
                "No renders in {}: eval swarm ran with --render-every 0 or --renders 0, or \
                 could not reopen the agents' frames (see rendering_source in the metrics).",
                dir.join("renders").display()
            ));
            return section("renders", "Merged map against ground truth", &body);
        }
    };
    let mut body = paragraph(
        "The merged world map (map.ply) rendered at an agent's world pose, beside that dataset \
         frame.",
    );
    for path in files.iter().take(MAX_EMBEDDED_RENDERS) {
        match embedded_png(path) {
            Ok(figure) => body.push_str(&figure),
            Err(e) => body.push_str(&note(&format!("Render not readable: {e}"))),
        }
    }
    if files.len() > MAX_EMBEDDED_RENDERS {
        body.push_str(&note(&format!(
            "{} more renders in {} are not embedded.",
            files.len() - MAX_EMBEDDED_RENDERS,
            dir.join("renders").display()
        )));
    }
    section("renders", "Merged map against ground truth", &body)
}

fn outcome_colour(outcome: Outcome) -> &'static str {
    match outcome {
        Outcome::Accepted => "#59a14f",
        Outcome::RejectedByPoseGraph => "#e15759",
        Outcome::VerifiedUnsolved => "#4e79a7",
        Outcome::RejectedByAlignment => "#bab0ac",
    }
}

/// Inter-agent closures are what merges maps: a different shape keeps them apart from an agent
/// closing a loop on itself.
fn event_shape(event: &ClosureEvent) -> Shape {
    if event.inter_agent {
        Shape::Circle
    } else {
        Shape::Square
    }
}

fn describe_event(event: &ClosureEvent) -> String {
    let score = event
        .score
        .map(|s| format!(", score {s:.3}"))
        .unwrap_or_default();
    let reason = event
        .rejection
        .as_ref()
        .map(|r| format!(" ({r})"))
        .unwrap_or_default();
    format!(
        "{:.1} s: agent {} keyframe {} -> agent {} keyframe {} [{}{score}]: {}{reason}",
        event.at_s,
        event.source.agent_id,
        event.source.keyframe_id,
        event.target.agent_id,
        event.target.keyframe_id,
        event.origin.as_deref().unwrap_or("unknown origin"),
        event.outcome().label()
    )
}

/// Height of a timeline lane the markers spread over: one sub-row per partner agent, so
/// closures with different partners at about the same time do not cover each other.
const LANE_FILL: f64 = 0.4;

/// Offset within a lane of the sub-row for the partner in lane `target_lane` of `lanes`.
fn sub_row_offset(target_lane: usize, lanes: usize) -> f64 {
    if lanes < 2 {
        return 0.0;
    }
    (target_lane as f64 / (lanes - 1) as f64 - 0.5) * LANE_FILL
}

/// One lane per agent (events sit on their source agent's lane, raised by their partner's id),
/// x = seconds since the consensus started.
fn timeline_chart(events: &[ClosureEvent], ids: &[u32], wall_s: Option<f64>) -> Option<String> {
    let mut lanes: Vec<u32> = ids.to_vec();
    lanes.extend(
        events
            .iter()
            .flat_map(|e| [e.source.agent_id, e.target.agent_id]),
    );
    lanes.sort_unstable();
    lanes.dedup();
    let lane_of = |agent: u32| lanes.iter().position(|id| *id == agent).unwrap_or_default();
    let x_range = Range::of(events.iter().map(|e| e.at_s).chain(wall_s).chain([0.0]))?;
    let mut chart = Chart::with_lanes(
        x_range,
        lanes.iter().map(|id| format!("agent {id}")).collect(),
        "time since the consensus started (s)",
        "proposing agent",
    );
    for event in events {
        let y = lane_of(event.source.agent_id) as f64
            + sub_row_offset(lane_of(event.target.agent_id), lanes.len());
        let outcome = event.outcome();
        chart.marker(
            (event.at_s, y),
            event_shape(event),
            outcome_colour(outcome),
            &describe_event(event),
        );
    }
    for outcome in Outcome::ALL {
        chart.marker_legend(outcome.label(), Shape::Circle, outcome_colour(outcome));
    }
    chart.marker_legend("circle: inter-agent", Shape::Circle, "#ffffff");
    chart.marker_legend("square: same agent", Shape::Square, "#ffffff");
    Some(chart.render())
}

fn events_table(events: &[ClosureEvent]) -> String {
    let rows: Vec<Vec<Cell>> = events
        .iter()
        .map(|e| {
            vec![
                Cell::number(format!("{:.1}", e.at_s)),
                Cell::text(format!(
                    "agent {} kf {}",
                    e.source.agent_id, e.source.keyframe_id
                )),
                Cell::text(format!(
                    "agent {} kf {}",
                    e.target.agent_id, e.target.keyframe_id
                )),
                Cell::text(e.origin.clone().unwrap_or_default()),
                Cell::number(e.score.map(|s| format!("{s:.3}")).unwrap_or_default()),
                Cell::text(e.outcome().label()),
                Cell::text(e.rejection.clone().unwrap_or_default()),
            ]
        })
        .collect();
    table(
        &[
            "time (s)", "source", "target", "origin", "score", "outcome", "reason",
        ],
        &rows,
    )
}

fn consensus_section(consensus: &Result<Value, String>, ids: &[u32]) -> String {
    const HEADING: &str = "Consensus events";
    let consensus = match consensus {
        Ok(value) => value,
        Err(e) => {
            return section(
                "consensus",
                HEADING,
                &note(&format!("No consensus record: {e}")),
            );
        }
    };
    let events = match run_dir::closure_events(consensus) {
        Ok(events) => events,
        Err(e) => return section("consensus", HEADING, &note(&e)),
    };
    if events.is_empty() {
        return section(
            "consensus",
            HEADING,
            &note("The consensus proposed no loop closure in this run."),
        );
    }
    let accepted = events
        .iter()
        .filter(|e| e.outcome() == Outcome::Accepted)
        .count();
    let mut body = paragraph(&format!(
        "{} closures proposed, {accepted} accepted by the pose graph. A row is the agent whose \
         new keyframe proposed the closure; within it, the higher the marker, the higher the \
         partner agent's id. Hover a marker for the keyframes and the reason.",
        events.len()
    ));
    if let Some(chart) = timeline_chart(&events, ids, consensus["wall_s"].as_f64()) {
        body.push_str(&chart);
    }
    body.push_str(&details("Every event", &events_table(&events)));
    section("consensus", HEADING, &body)
}

#[cfg(test)]
mod tests;
