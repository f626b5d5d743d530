//! What the agent writes about its map's views, so that the map can be evaluated again later on
//! frames it never trained on (docs/method.md, Metrics: held-out frames):
//! - keyframes.csv: every keyframe the mapper optimised the map on (frame number, timestamp,
//!   kind);
//! - trajectory_map.tum: every tracked frame's camera in map.ply's frame, where the agent's own
//!   evaluation renders it from: its tracked pose moved by the consensus corrections the map
//!   took and by the keyframe pose refinement (`[mapping] refine_keyframe_poses`), blended
//!   between keyframes.

use std::io::Write;
use std::path::Path;

use anyhow::Context;
use geometry::correction::CorrectionField;
use geometry::trajectory::Trajectory;
use registration::odometry::Placement;

use crate::mapper::KeyframeKind;
use crate::pipeline::{FinishedPipeline, KeyframeMade, TrackedPose};

/// The file names, in the agent's output folder.
pub const KEYFRAMES_FILE: &str = "keyframes.csv";
/// Every tracked frame's camera in map.ply's frame, as the agent's evaluation renders it.
pub const MAP_TRAJECTORY_FILE: &str = "trajectory_map.tum";

/// Every tracked frame of the root map with its camera where the map renders it: `pose_refinement
/// * applied correction * tracked pose`, each at the frame's time.
pub fn poses_in_map(run: &FinishedPipeline, pose_refinement: &CorrectionField) -> Vec<TrackedPose> {
    run.poses
        .iter()
        .filter(|p| p.placement == Placement::Root && p.tracked)
        .map(|p| TrackedPose {
            world_from_camera: pose_refinement.at(p.timestamp)
                * run.corrections.applied().at(p.timestamp)
                * p.world_from_camera,
            ..*p
        })
        .collect()
}

/// Writes keyframes.csv and trajectory_map.tum into `out`.
pub fn write_view_files(
    run: &FinishedPipeline,
    pose_refinement: &CorrectionField,
    out: &Path,
) -> anyhow::Result<()> {
    let path = out.join(KEYFRAMES_FILE);
    geometry::files::write_whole(&path, |file| write_keyframes(&run.keyframes_made, file))
        .with_context(|| format!("writing {}", path.display()))?;
    Trajectory::from_pairs(
        poses_in_map(run, pose_refinement)
            .iter()
            .map(|p| (p.timestamp, p.world_from_camera)),
    )
    .write_tum(&out.join(MAP_TRAJECTORY_FILE))?;
    Ok(())
}

fn write_keyframes(keyframes: &[KeyframeMade], file: &mut std::fs::File) -> std::io::Result<()> {
    let mut file = std::io::BufWriter::new(file);
    writeln!(file, "keyframe_id,frame_index,timestamp,kind")?;
    for keyframe in keyframes {
        let kind = match keyframe.kind {
            KeyframeKind::Tracking => "tracking",
            KeyframeKind::Mapping => "mapping",
        };
        writeln!(
            file,
            "{},{},{:.6},{kind}",
            keyframe.keyframe_id, keyframe.frame_index, keyframe.timestamp_s
        )?;
    }
    file.flush()
}
