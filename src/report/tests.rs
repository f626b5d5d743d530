//! The report built from small fabricated run directories.

use std::path::Path;

use geometry::trajectory::Trajectory;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::*;

/// Frame period of the fabricated trajectories (30 Hz, as the datasets without a clock).
const FRAME_PERIOD_S: f64 = 1.0 / 30.0;

/// A curved ground-truth path of `frames` poses in the x-y plane (z nearly constant), so the
/// top-down view is x-y.
fn ground_truth(frames: usize, phase: f64) -> Trajectory {
    Trajectory::from_pairs((0..frames).map(|i| {
        let a = phase + i as f64 * 0.3;
        (
            i as f64 * FRAME_PERIOD_S,
            Isometry3::translation(2.0 * a.cos(), 1.5 * a.sin(), 0.01 * i as f64),
        )
    }))
}

/// The ground truth seen in a world frame that differs from the ground-truth frame by a rigid
/// motion (what the consensus's world frame is: agent 0's first pose).
fn in_world_frame(truth: &Trajectory) -> Trajectory {
    let world_from_truth = Isometry3::from_parts(
        Translation3::new(0.5, -1.0, 0.2),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7),
    );
    Trajectory::from_pairs(
        truth
            .stamps
            .iter()
            .zip(&truth.poses)
            .map(|(t, pose)| (*t, world_from_truth * pose)),
    )
}

/// Writes agent `id`'s ground truth and, when `linked`, its world-frame estimate.
fn write_agent(dir: &Path, id: u32, frames: usize, linked: bool, with_truth: bool) {
    let truth = ground_truth(frames, id as f64);
    let own = dir.join(format!("agent_{id}"));
    std::fs::create_dir_all(&own).unwrap();
    if with_truth {
        truth.write_tum(&own.join("groundtruth.tum")).unwrap();
    }
    if linked {
        in_world_frame(&truth)
            .write_tum(&dir.join(format!("agent_{id}.tum")))
            .unwrap();
    }
}

fn write_json(path: &Path, value: &serde_json::Value) {
    std::fs::write(path, serde_json::to_string_pretty(value).unwrap()).unwrap();
}

fn consensus_json(agents: &[u32]) -> serde_json::Value {
    let agents: serde_json::Map<String, serde_json::Value> = agents
        .iter()
        .map(|id| (id.to_string(), serde_json::json!({"keyframes": 2})))
        .collect();
    serde_json::json!({
        "agents": agents,
        "wall_s": 40.0,
        "interrupted": false,
        "events": [
            {
                "at_s": 12.5,
                "source": {"agent_id": 1, "keyframe_id": 6},
                "target": {"agent_id": 0, "keyframe_id": 7},
                "origin": "place_recognition",
                "inter_agent": true,
                "score": 0.93,
                "verified": true,
                "rejection": null,
                "accepted_by_pose_graph": true,
                "alignment_ms": 400.0
            },
            {
                "at_s": 20.0,
                "source": {"agent_id": 0, "keyframe_id": 14},
                "target": {"agent_id": 0, "keyframe_id": 7},
                "origin": "odometry",
                "inter_agent": false,
                "score": null,
                "verified": false,
                "rejection": "<coarse> registration & too few inliers",
                "accepted_by_pose_graph": null,
                "alignment_ms": 50.0
            }
        ]
    })
}

/// A complete two-agent run: 7 and 5 frames, one render.
fn complete_run(dir: &Path) {
    write_agent(dir, 0, 7, true, true);
    write_agent(dir, 1, 5, true, true);
    write_json(
        &dir.join("metrics.json"),
        &serde_json::json!({
            "ate_joint_rmse_m": 0.0,
            "ate_per_agent_rmse_m": [0.0, 0.0],
            "agents_not_linked": [],
            "psnr": 27.5,
            "rendering_source": "<script>alert(1)</script>",
            "loop_closures_accepted": 1
        }),
    );
    write_json(&dir.join("consensus.json"), &consensus_json(&[0, 1]));
    std::fs::write(dir.join("config.toml"), "[consensus]\nt_comm = 60\n").unwrap();
    let renders = dir.join("renders");
    std::fs::create_dir_all(&renders).unwrap();
    image::RgbImage::from_pixel(4, 2, image::Rgb([10, 200, 30]))
        .save(renders.join("agent_0_frame_000000.png"))
        .unwrap();
}

/// The HTML of the section with this id.
fn section_of<'a>(html: &'a str, id: &str) -> &'a str {
    let start = html
        .find(&format!("<section id=\"{id}\">"))
        .unwrap_or_else(|| panic!("no section {id}"));
    let end = html[start..].find("</section>").unwrap() + start;
    &html[start..end]
}

/// Number of points of each polyline, in document order.
fn polyline_point_counts(html: &str) -> Vec<usize> {
    polyline_points(html)
        .iter()
        .map(|points| points.split_whitespace().count())
        .collect()
}

fn polyline_points(html: &str) -> Vec<&str> {
    html.split("<polyline")
        .skip(1)
        .map(|rest| {
            let start = rest.find("points=\"").unwrap() + "points=\"".len();
            let end = rest[start..].find('"').unwrap() + start;
            &rest[start..end]
        })
        .collect()
}

#[test]
fn complete_run_gives_every_section() {
    let dir = tempfile::tempdir().unwrap();
    complete_run(dir.path());
    let path = write_report(dir.path()).unwrap();
    assert_eq!(path, dir.path().join(REPORT_FILE));
    let html = std::fs::read_to_string(&path).unwrap();

    for id in [
        "run",
        "metrics",
        "trajectories",
        "ate",
        "renders",
        "consensus",
    ] {
        section_of(&html, id);
    }
    // Offline: no address of any kind, only inline data.
    assert!(
        !html.contains("http"),
        "the report references something online"
    );
    assert!(
        !html.contains("class=\"note\""),
        "nothing is missing:\n{html}"
    );

    let metrics = section_of(&html, "metrics");
    assert!(metrics.contains("0.00 cm") && metrics.contains("27.50 dB"));

    // Top-down: ground truth then estimate per agent, every pose drawn.
    let top_down = section_of(&html, "trajectories");
    assert_eq!(polyline_point_counts(top_down), [7, 7, 5, 5]);
    // The world frame differs from the ground-truth frame by a rigid motion; after the joint
    // alignment each estimate lies on its ground truth.
    let lines = polyline_points(top_down);
    assert_eq!(lines[0], lines[1]);
    assert_eq!(lines[2], lines[3]);
    assert!(top_down.contains("x (m)") && top_down.contains("y (m)"));

    // ATE over time: one line per agent, one point per matched pose.
    assert_eq!(polyline_point_counts(section_of(&html, "ate")), [7, 5]);

    let renders = section_of(&html, "renders");
    assert_eq!(renders.matches("src=\"data:image/png;base64,").count(), 1);
    assert!(renders.contains("agent 0, frame 0"));

    let consensus = section_of(&html, "consensus");
    // One marker per event, each with its hover text: a circle for the inter-agent closure, a
    // square for the agent's own.
    assert_eq!(consensus.matches("</title></circle>").count(), 1);
    assert_eq!(consensus.matches("</title></rect>").count(), 1);
    assert!(consensus.contains("2 closures proposed, 1 accepted"));
    assert!(section_of(&html, "run").contains("t_comm = 60"));
}

#[test]
fn text_from_the_run_is_escaped() {
    let dir = tempfile::tempdir().unwrap();
    complete_run(dir.path());
    let html = build_report(dir.path());
    assert!(!html.contains("<script>"));
    assert!(html.contains("&lt;script&gt;alert(1)&lt;/script&gt;"));
    assert!(html.contains("&lt;coarse&gt; registration &amp; too few inliers"));
}

#[test]
fn missing_agents_and_ground_truth_are_named_not_fatal() {
    let dir = tempfile::tempdir().unwrap();
    write_agent(dir.path(), 0, 6, true, true);
    write_agent(dir.path(), 1, 6, true, false);
    write_agent(dir.path(), 2, 6, false, true);
    write_json(
        &dir.path().join("consensus.json"),
        &consensus_json(&[0, 1, 2]),
    );
    let html = std::fs::read_to_string(write_report(dir.path()).unwrap()).unwrap();

    let top_down = section_of(&html, "trajectories");
    assert!(
        top_down.contains("agent 2: not linked to the world frame"),
        "{top_down}"
    );
    assert!(top_down.contains("agent 1: no ground truth"), "{top_down}");
    assert_eq!(polyline_point_counts(top_down), [6, 6]);
    let ate = section_of(&html, "ate");
    assert!(ate.contains("Some agents are left out"), "{ate}");
    assert_eq!(polyline_point_counts(ate), [6]);
    assert!(section_of(&html, "metrics").contains("No metrics"));
    assert!(section_of(&html, "renders").contains("No renders"));
}

#[test]
fn snapshots_and_interrupted_runs_say_so() {
    let dir = tempfile::tempdir().unwrap();
    complete_run(dir.path());
    let mut consensus = consensus_json(&[0, 1]);
    consensus["snapshot"] = serde_json::json!(true);
    consensus["interrupted"] = serde_json::json!(true);
    write_json(&dir.path().join("consensus.json"), &consensus);
    let html = build_report(dir.path());
    let run = section_of(&html, "run");
    assert!(
        run.contains("snapshot taken while the run was still going"),
        "{run}"
    );
    assert!(run.contains("The run was interrupted"), "{run}");
}

#[test]
fn an_empty_directory_still_gets_a_report() {
    let dir = tempfile::tempdir().unwrap();
    let html = std::fs::read_to_string(write_report(dir.path()).unwrap()).unwrap();
    assert!(section_of(&html, "consensus").contains("No consensus record"));
    assert!(section_of(&html, "trajectories").contains("nothing to draw"));
    assert!(section_of(&html, "ate").contains("nothing to draw"));
}
