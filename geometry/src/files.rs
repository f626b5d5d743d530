//! Errors and number parsing shared by every reader of dataset files: image folders, trajectory
//! files, calibration files. Each error names the file and, where there is one, the line.
//!
//! Here rather than in the `datasets` crate because this crate reads such files too
//! ([`crate::trajectory::Trajectory::read`], [`crate::camera::Intrinsics::read_k_file`]), and the
//! metrics read trajectories without depending on the readers.

use std::fmt;
use std::path::{Path, PathBuf};

/// Errors of reading or writing dataset files. Each names the file and, where there is one, the
/// line.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode image: {reason}")]
    Decode { path: PathBuf, reason: String },
    #[error("{path}{}: {reason}", line.map(|l| format!(" line {l}")).unwrap_or_default())]
    Format {
        path: PathBuf,
        line: Option<usize>,
        reason: String,
    },
    #[error("{path}: missing frame {index} (file not found)")]
    MissingFrame { path: PathBuf, index: usize },
    #[error(
        "{path}: image is {found_w}x{found_h}, expected {expected_w}x{expected_h} like the other images of this dataset"
    )]
    SizeMismatch {
        path: PathBuf,
        expected_w: u32,
        expected_h: u32,
        found_w: u32,
        found_h: u32,
    },
    #[error("{0}")]
    Invalid(String),
}

impl DatasetError {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    pub fn format(path: &Path, line: Option<usize>, reason: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            line,
            reason: reason.into(),
        }
    }
    pub fn decode(path: &Path, reason: impl fmt::Display) -> Self {
        Self::Decode {
            path: path.to_path_buf(),
            reason: reason.to_string(),
        }
    }
    /// True when the error means "this frame is not there" rather than "this frame is broken";
    /// callers may skip such frames with a warning.
    pub fn is_missing_frame(&self) -> bool {
        matches!(self, Self::MissingFrame { .. })
    }
}

/// Parses whitespace-separated floats; the error names the token that is not a number.
pub fn parse_floats(line: &str) -> Result<Vec<f64>, String> {
    line.split_whitespace()
        .map(|tok| {
            let v: f64 = tok
                .parse()
                .map_err(|_| format!("{tok:?} is not a number"))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(format!("{tok:?} is not a finite number"))
            }
        })
        .collect()
}

/// Writes `path` whole or not at all: `write` fills a temporary file next to it (`NAME.partial`,
/// same folder, so the rename cannot cross file systems), which is renamed over `path` once
/// complete and flushed. A reader never sees a half-written output, and a write that fails (a
/// full disk) leaves what `path` held before; the temporary file is removed then. The error is
/// `write`'s own; callers name `path` in it.
pub fn write_whole<E: From<std::io::Error>>(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> Result<(), E>,
) -> Result<(), E> {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    let temporary = path.with_file_name(name);
    let written = std::fs::File::create(&temporary)
        .map_err(E::from)
        .and_then(|mut file| {
            write(&mut file)?;
            // Data the kernel could not place (delayed allocation) surfaces here, not at close.
            file.sync_data().map_err(E::from)
        })
        .and_then(|()| std::fs::rename(&temporary, path).map_err(E::from));
    if written.is_err() {
        // Best effort: the error that matters is the write's.
        let _ = std::fs::remove_file(&temporary);
    }
    written
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn a_failed_write_keeps_the_previous_file_and_leaves_no_partial_one() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.txt");
        write_whole(&path, |file| file.write_all(b"first")).unwrap();
        let failed = write_whole(&path, |file| {
            file.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(failed.is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"first");
        assert!(!dir.path().join("out.txt.partial").exists());
        write_whole(&path, |file| file.write_all(b"second")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
    }
}
