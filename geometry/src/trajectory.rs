//! Timestamped pose sequences and their file formats.
//! - TUM: `timestamp tx ty tz qx qy qz qw` per line, `#` comments (evo and the TUM tools read it).
//! - `kitti-c2w`: 16 (or 12) numbers per line, a row-major camera-to-world matrix, no timestamps
//!   (Replica's traj.txt); pose line k gets timestamp k / 30 s, the clock the dataset readers give
//!   such frames, so a TUM output can be compared with a traj.txt.

use std::io::Write;
use std::path::Path;

use nalgebra::Isometry3;

use crate::files::{DatasetError, parse_floats};
use crate::se3::{isometry_from_tum, isometry_to_tum, pose_from_row_major};

/// Frame rate assumed for layouts that have no clock (7-Scenes, Replica, `kitti-c2w` trajectory
/// files): frame number `n` has timestamp `n / 30` s, as the shared groundtruth_tum.txt files use.
pub const NO_CLOCK_FRAMES_PER_SECOND: f64 = 30.0;

/// File formats of [`Trajectory`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrajectoryFormat {
    /// `tum`: TUM text, `timestamp tx ty tz qx qy qz qw` per line.
    Tum,
    /// `kitti-c2w`: a row-major camera-to-world matrix per line (12 or 16 numbers), no timestamps;
    /// Replica's traj.txt.
    KittiC2w,
}

impl std::str::FromStr for TrajectoryFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "tum" => Ok(Self::Tum),
            "kitti-c2w" => Ok(Self::KittiC2w),
            other => Err(format!(
                "unknown trajectory format {other:?}: expected tum or kitti-c2w"
            )),
        }
    }
}

/// Camera-to-world poses with timestamps (seconds), in file order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// Timestamps in seconds, one per pose.
    pub stamps: Vec<f64>,
    /// `world_from_camera` poses; `poses[i]` is at `stamps[i]`.
    pub poses: Vec<Isometry3<f64>>,
}

impl Trajectory {
    /// A trajectory from `(timestamp in seconds, world_from_camera)` pairs, kept in their order.
    pub fn from_pairs(pairs: impl IntoIterator<Item = (f64, Isometry3<f64>)>) -> Self {
        let (stamps, poses) = pairs.into_iter().unzip();
        Self { stamps, poses }
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.stamps.len()
    }

    /// True when there are no poses.
    pub fn is_empty(&self) -> bool {
        self.stamps.is_empty()
    }

    /// Appends a pose at `stamp` (seconds). Time order is not checked.
    pub fn push(&mut self, stamp: f64, pose: Isometry3<f64>) {
        self.stamps.push(stamp);
        self.poses.push(pose);
    }

    /// Sum of distances between consecutive camera positions, metres.
    pub fn path_length(&self) -> f64 {
        self.poses
            .windows(2)
            .map(|w| (w[1].translation.vector - w[0].translation.vector).norm())
            .sum()
    }

    /// Reads a trajectory file in `format` ([`Trajectory::read_tum`] or
    /// [`Trajectory::read_kitti_c2w`]). Fails when the file cannot be read, a line is not a pose,
    /// or it holds no poses.
    pub fn read(path: &Path, format: TrajectoryFormat) -> Result<Self, DatasetError> {
        match format {
            TrajectoryFormat::Tum => Self::read_tum(path),
            TrajectoryFormat::KittiC2w => Self::read_kitti_c2w(path),
        }
    }

    /// Reads a TUM trajectory. Errors name the file and line.
    pub fn read_tum(path: &Path) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
        let mut traj = Self::default();
        for (line_no, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let err = |reason: String| DatasetError::format(path, Some(line_no + 1), reason);
            let values = parse_floats(&line.replace(',', " ")).map_err(err)?;
            if values.len() != 8 {
                return Err(err(format!(
                    "expected 8 numbers (t tx ty tz qx qy qz qw), found {}",
                    values.len()
                )));
            }
            let pose = isometry_from_tum(&[
                values[1], values[2], values[3], values[4], values[5], values[6], values[7],
            ])
            .map_err(err)?;
            traj.push(values[0], pose);
        }
        if traj.is_empty() {
            return Err(DatasetError::format(path, None, "no poses in file"));
        }
        Ok(traj)
    }

    /// Reads 16 (or 12) numbers per line, row-major camera-to-world; timestamp = pose index / 30 s.
    pub fn read_kitti_c2w(path: &Path) -> Result<Self, DatasetError> {
        let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
        let mut traj = Self::default();
        for (line_no, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let err = |reason: String| DatasetError::format(path, Some(line_no + 1), reason);
            let values = parse_floats(line).map_err(err)?;
            let pose = pose_from_row_major(&values).map_err(err)?;
            traj.push(traj.len() as f64 / NO_CLOCK_FRAMES_PER_SECOND, pose);
        }
        if traj.is_empty() {
            return Err(DatasetError::format(path, None, "no poses in file"));
        }
        Ok(traj)
    }

    /// Writes TUM lines with enough digits to round-trip f64 exactly.
    pub fn write_tum_to(&self, out: &mut impl Write) -> std::io::Result<()> {
        writeln!(out, "# timestamp tx ty tz qx qy qz qw (camera-to-world)")?;
        for (stamp, pose) in self.stamps.iter().zip(&self.poses) {
            let v = isometry_to_tum(pose);
            writeln!(
                out,
                "{stamp:.6} {} {} {} {} {} {} {}",
                v[0], v[1], v[2], v[3], v[4], v[5], v[6]
            )?;
        }
        Ok(())
    }

    /// Writes the TUM file, whole or not at all ([`crate::files::write_whole`]).
    pub fn write_tum(&self, path: &Path) -> Result<(), DatasetError> {
        crate::files::write_whole(path, |file| {
            let mut buffered = std::io::BufWriter::new(file);
            self.write_tum_to(&mut buffered)?;
            buffered.flush()
        })
        .map_err(|e| DatasetError::io(path, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn tum_round_trip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.txt");
        let traj = Trajectory::from_pairs((0..5).map(|i| {
            let f = i as f64;
            (
                f / 30.0,
                Isometry3::from_parts(
                    Translation3::new(f, -f, 0.5),
                    UnitQuaternion::from_euler_angles(0.1 * f, 0.2, -0.3),
                ),
            )
        }));
        traj.write_tum(&path).unwrap();
        let back = Trajectory::read_tum(&path).unwrap();
        assert_eq!(back.len(), 5);
        for (a, b) in back.poses.iter().zip(&traj.poses) {
            assert!((a.to_homogeneous() - b.to_homogeneous()).abs().max() < 1e-12);
        }
        std::fs::write(&path, "# c\n0 1 2 3 0 0 0 1\n0.1 1 2 3 0 0 nan 1\n").unwrap();
        let err = Trajectory::read_tum(&path).unwrap_err().to_string();
        assert!(err.contains("t.txt line 3"), "{err}");
        std::fs::write(&path, "0 1 2 3 0 0 0\n").unwrap();
        assert!(
            Trajectory::read_tum(&path)
                .unwrap_err()
                .to_string()
                .contains("line 1")
        );
        std::fs::write(&path, "").unwrap();
        assert!(Trajectory::read_tum(&path).is_err());
    }

    #[test]
    fn kitti_c2w_reads_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("traj.txt");
        std::fs::write(
            &path,
            "1 0 0 1 0 1 0 2 0 0 1 3 0 0 0 1\n1 0 0 4 0 1 0 5 0 0 1 6 0 0 0 1\n",
        )
        .unwrap();
        let t = Trajectory::read_kitti_c2w(&path).unwrap();
        assert_eq!(t.stamps, vec![0.0, 1.0 / 30.0]);
        assert_eq!(t.poses[1].translation.vector.z, 6.0);
        assert!((t.path_length() - 27f64.sqrt()).abs() < 1e-12);
    }
}
