//! Which files make a bag: rosbag2 writes a folder with `metadata.yaml` naming its storage files
//! (`relative_file_paths`, in recording order) and the storage kind; a folder without it, or a
//! single `.mcap` / `.db3` file, is read as it is.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::BagError;

/// The name of the file in a rosbag2 folder that lists its storage files and topics.
pub const METADATA_FILE: &str = "metadata.yaml";
const STORAGE_EXTENSIONS: [&str; 2] = ["mcap", "db3"];

#[derive(Deserialize)]
struct Metadata {
    rosbag2_bagfile_information: Information,
}

#[derive(Deserialize)]
struct Information {
    #[serde(default)]
    storage_identifier: String,
    #[serde(default)]
    relative_file_paths: Vec<String>,
}

fn is_storage_file(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| STORAGE_EXTENSIONS.contains(&e))
}

/// True when `path` looks like a bag: a storage file, or a folder with metadata.yaml or with
/// storage files.
pub fn is_bag(path: &Path) -> bool {
    storage_files(path).is_ok()
}

/// The bag's storage files in recording order.
pub fn storage_files(path: &Path) -> Result<Vec<PathBuf>, BagError> {
    if is_storage_file(path) {
        return Ok(vec![path.to_path_buf()]);
    }
    if !path.is_dir() {
        return Err(BagError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "no bag here: expected a bag folder or a .mcap / .db3 file",
            ),
        ));
    }
    let metadata = path.join(METADATA_FILE);
    if metadata.is_file() {
        let text = std::fs::read_to_string(&metadata).map_err(|e| BagError::io(&metadata, e))?;
        let parsed: Metadata = serde_yaml::from_str(&text)
            .map_err(|e| BagError::format(&metadata, format!("not rosbag2 metadata: {e}")))?;
        let information = parsed.rosbag2_bagfile_information;
        if !information.storage_identifier.is_empty()
            && !["mcap", "sqlite3"].contains(&information.storage_identifier.as_str())
        {
            return Err(BagError::format(
                &metadata,
                format!(
                    "storage {:?}: this reader reads mcap and sqlite3",
                    information.storage_identifier
                ),
            ));
        }
        if !information.relative_file_paths.is_empty() {
            return information
                .relative_file_paths
                .iter()
                .map(|relative| {
                    let file = path.join(relative);
                    if file.is_file() {
                        Ok(file)
                    } else {
                        Err(BagError::format(
                            &metadata,
                            format!("names {relative}, which is not in the bag folder"),
                        ))
                    }
                })
                .collect();
        }
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(path)
        .map_err(|e| BagError::io(path, e))?
        .flatten()
        .map(|entry| entry.path())
        .filter(|file| is_storage_file(file))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(BagError::format(
            path,
            "no rosbag2 storage files (.mcap or .db3) in this folder",
        ));
    }
    Ok(files)
}
