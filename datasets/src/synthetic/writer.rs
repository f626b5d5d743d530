//! Writing the synthetic scene to disk in the 7-Scenes layout (what `mac-ego3d synth` does), one
//! folder per agent, and removing what was written.

use std::path::{Path, PathBuf};

use geometry::camera::Intrinsics;
use geometry::files::DatasetError;
use serde::{Deserialize, Serialize};

use crate::seven_scenes::{DEPTH_UNITS_PER_METRE, SevenScenesWriter};
use crate::{Dataset, Frame, FrameRange};

use super::dataset::SyntheticDataset;
use super::shapes::{ROOM_MAX, ROOM_MIN};
use super::spec::{FRAMES_PER_SECOND, SyntheticSpec};

/// Description of a written dataset, saved as `scene.json` next to the agent folders.
pub const SCENE_FILE: &str = "scene.json";

/// Folder of agent `agent` inside an output folder.
pub fn agent_folder(out_dir: &Path, agent: usize) -> PathBuf {
    out_dir.join(format!("agent_{agent}"))
}

#[derive(Debug, Serialize, Deserialize)]
struct SceneDescription {
    pub(super) generator: String,
    pub(super) spec: String,
    pub(super) agents: usize,
    frames_per_agent: usize,
    pub(super) seed: u64,
    pub(super) intrinsics: Intrinsics,
    frames_per_second: f64,
    depth_units_per_metre: f64,
    room_min: [f64; 3],
    room_max: [f64; 3],
    agent_folders: Vec<String>,
}

/// Frames rendered ahead of the writer: rendering and PNG encoding run concurrently.
const WRITE_QUEUE_DEPTH: usize = 4;

/// Writes every agent of `spec` (its `agent` field is ignored) into `out_dir/agent_K/` in the
/// 7-Scenes layout (PNG colour, millimetre depth PNG, pose files, `camera-intrinsics.txt`,
/// `groundtruth_tum.txt`) plus `out_dir/scene.json`. `progress(done, total)` is called after each
/// frame. Refuses to write into an agent folder that already holds files, so frames of an
/// earlier, longer run cannot mix in (see [`remove_written`]). Returns the agent folders.
pub fn write_seven_scenes(
    spec: &SyntheticSpec,
    out_dir: &Path,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<PathBuf>, DatasetError> {
    let spec = spec.with_agent(0);
    spec.validate()
        .map_err(|reason| DatasetError::Invalid(format!("synthetic spec {spec}: {reason}")))?;
    let folders: Vec<PathBuf> = (0..spec.agents)
        .map(|agent| agent_folder(out_dir, agent))
        .collect();
    for folder in &folders {
        if let Ok(mut entries) = std::fs::read_dir(folder)
            && entries.next().is_some()
        {
            return Err(DatasetError::Invalid(format!(
                "{}: folder is not empty; remove it (or use --overwrite) so frames of an earlier run do not mix in",
                folder.display()
            )));
        }
    }
    std::fs::create_dir_all(out_dir).map_err(|e| DatasetError::io(out_dir, e))?;
    let description = SceneDescription {
        generator: "mac-ego3d synthetic scene".into(),
        spec: spec.to_string(),
        agents: spec.agents,
        frames_per_agent: spec.frames,
        seed: spec.seed,
        intrinsics: spec.intrinsics(),
        frames_per_second: FRAMES_PER_SECOND,
        depth_units_per_metre: DEPTH_UNITS_PER_METRE,
        room_min: ROOM_MIN,
        room_max: ROOM_MAX,
        agent_folders: folders
            .iter()
            .map(|f| {
                f.file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect(),
    };
    let scene_path = out_dir.join(SCENE_FILE);
    let json = serde_json::to_string_pretty(&description)
        .map_err(|e| DatasetError::Invalid(format!("{}: {e}", scene_path.display())))?;
    std::fs::write(&scene_path, json + "\n").map_err(|e| DatasetError::io(&scene_path, e))?;

    let total = spec.agents * spec.frames;
    let (sender, receiver) =
        std::sync::mpsc::sync_channel::<Result<(usize, Frame), DatasetError>>(WRITE_QUEUE_DEPTH);
    std::thread::scope(|scope| {
        scope.spawn(move || {
            for agent in 0..spec.agents {
                let dataset = match SyntheticDataset::new(spec.with_agent(agent), FrameRange::ALL) {
                    Ok(dataset) => dataset,
                    Err(e) => {
                        let _ = sender.send(Err(e));
                        return;
                    }
                };
                for position in 0..dataset.len() {
                    // A send error means the writer stopped on an error of its own: stop too.
                    if sender
                        .send(dataset.load(position).map(|frame| (agent, frame)))
                        .is_err()
                    {
                        return;
                    }
                }
            }
        });
        let mut writer: Option<(usize, SevenScenesWriter)> = None;
        let mut done = 0;
        for message in receiver {
            let (agent, frame) = message?;
            if writer.as_ref().is_none_or(|(current, _)| *current != agent) {
                if let Some((_, finished)) = writer.take() {
                    finished.finish()?;
                }
                writer = Some((
                    agent,
                    SevenScenesWriter::create(&folders[agent], &frame.intrinsics)?,
                ));
            }
            if let Some((_, current)) = writer.as_mut() {
                current.write(&frame)?;
            }
            done += 1;
            progress(done, total);
        }
        if let Some((_, finished)) = writer.take() {
            finished.finish()?;
        }
        Ok::<(), DatasetError>(())
    })?;
    Ok(folders)
}

/// Removes what [`write_seven_scenes`] writes (the `agent_K` folders' frame, intrinsics and
/// ground-truth files, then the folders if empty, and `scene.json`), touching nothing else.
/// Returns the number of files removed.
pub fn remove_written(out_dir: &Path) -> Result<usize, DatasetError> {
    let mut removed = 0;
    let Ok(entries) = std::fs::read_dir(out_dir) else {
        return Ok(0);
    };
    for entry in entries.flatten() {
        let folder = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        let is_agent_folder = name
            .strip_prefix("agent_")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !is_agent_folder || !folder.is_dir() {
            continue;
        }
        for file in std::fs::read_dir(&folder)
            .map_err(|e| DatasetError::io(&folder, e))?
            .flatten()
        {
            let file_name = file.file_name().to_string_lossy().into_owned();
            let ours = (file_name.starts_with("frame-")
                && (file_name.ends_with(".color.png")
                    || file_name.ends_with(".depth.png")
                    || file_name.ends_with(".pose.txt")))
                || file_name == crate::seven_scenes::INTRINSICS_FILE
                || file_name == "groundtruth_tum.txt";
            if ours {
                std::fs::remove_file(file.path()).map_err(|e| DatasetError::io(&file.path(), e))?;
                removed += 1;
            }
        }
        // Leave a folder that still holds someone else's files.
        let _ = std::fs::remove_dir(&folder);
    }
    let scene = out_dir.join(SCENE_FILE);
    if scene.is_file() {
        std::fs::remove_file(&scene).map_err(|e| DatasetError::io(&scene, e))?;
        removed += 1;
    }
    Ok(removed)
}
