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
    /// The file could not be opened, read, written or renamed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        #[source]
        source: std::io::Error,
    },
    /// An image file could not be decoded (or saved, by a writer), or is not the kind of image
    /// expected (an 8-bit colour image, a 16-bit single-channel depth PNG).
    #[error("{path}: cannot decode image: {reason}")]
    Decode {
        /// The image file.
        path: PathBuf,
        /// The decoder's message, or which kind of image was expected and found.
        reason: String,
    },
    /// A file holds something its format does not allow: a text file (trajectory, calibration,
    /// association list) or a bag.
    #[error("{path}{}: {reason}", line.map(|l| format!(" line {l}")).unwrap_or_default())]
    Format {
        /// The file.
        path: PathBuf,
        /// The offending line, 1-based; `None` when the problem is the file as a whole (no poses,
        /// too few rows).
        line: Option<usize>,
        /// What is wrong.
        reason: String,
    },
    /// A file of a frame is not there. Callers may skip the frame
    /// ([`DatasetError::is_missing_frame`]).
    #[error("{path}: missing frame {index} (file not found)")]
    MissingFrame {
        /// The file that was not found.
        path: PathBuf,
        /// The frame's number in its sequence.
        index: usize,
    },
    /// An image's size differs from the dataset's (its intrinsics' width and height).
    #[error(
        "{path}: image is {found_w}x{found_h}, expected {expected_w}x{expected_h} like the other images of this dataset"
    )]
    SizeMismatch {
        /// The image file.
        path: PathBuf,
        /// The dataset's width in pixels.
        expected_w: u32,
        /// The dataset's height in pixels.
        expected_h: u32,
        /// The image's width in pixels.
        found_w: u32,
        /// The image's height in pixels.
        found_h: u32,
    },
    /// Anything else that makes a dataset or a frame unusable: an unknown layout, a bad synthetic
    /// spec, calibrations that do not fit together, no frames in the selected range, a decoder
    /// thread that died. The message says what, and names the file where there is one.
    #[error("{0}")]
    Invalid(String),
}

impl DatasetError {
    /// An [`DatasetError::Io`] error for `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    /// A [`DatasetError::Format`] error for `path`, at 1-based `line` when there is one.
    pub fn format(path: &Path, line: Option<usize>, reason: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            line,
            reason: reason.into(),
        }
    }
    /// A [`DatasetError::Decode`] error for `path`, `reason` being the decoder's error or message.
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
