//! Replica in the NICE-SLAM layout, also one agent of Multi-agent Replica (CP-SLAM):
//! `results/frameXXXXXX.jpg` (or .png), `results/depthXXXXXX.png` (u16, metres = raw / 6553.5),
//! `traj.txt` (one row-major 4x4 camera-to-world matrix per line, line k = frame k).
//! An optional `camera-intrinsics.txt` (3x3 K) overrides the defaults. No clock: timestamp =
//! frame number / 30 s.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use geometry::camera::Intrinsics;
use geometry::files::DatasetError;
use geometry::trajectory::{NO_CLOCK_FRAMES_PER_SECOND, Trajectory};

use crate::{Dataset, DepthEncoding, Frame, FrameRange, read_rgbd};

/// Replica renders of NICE-SLAM: 1200x680, fx = fy = 600, principal point at the image centre.
pub const DEFAULT_INTRINSICS: Intrinsics = Intrinsics {
    fx: 600.0,
    fy: 600.0,
    cx: 599.5,
    cy: 339.5,
    width: 1200,
    height: 680,
};
/// Depth PNG units: raw / 6553.5 = metres (so 65535 = 10 m).
pub const DEPTH_UNITS_PER_METRE: f64 = 6553.5;
const DEPTH_ENCODING: DepthEncoding = DepthEncoding {
    units_per_metre: DEPTH_UNITS_PER_METRE,
    invalid_raw: None,
};

/// A folder in the Replica layout (see the module documentation), indexed by [`Replica::open`];
/// images are decoded as frames load.
pub struct Replica {
    dir: PathBuf,
    /// (frame number, colour file) in frame order.
    frames: Vec<(usize, PathBuf)>,
    /// Poses of traj.txt, indexed by frame number.
    poses: Vec<Isometry3<f64>>,
    intrinsics: Intrinsics,
}

impl Replica {
    /// Indexes `dir`, keeping the frames whose number is in `range`, and reads `traj.txt` and the
    /// optional `camera-intrinsics.txt` (its image size taken from the first colour image). No
    /// image is decoded. Fails when `results/` cannot be listed, a frame number is not an integer,
    /// no frame number is in `range`, `traj.txt` is unreadable or has no pose for the last frame,
    /// or the K file (or the first image's size it needs) cannot be read.
    pub fn open(dir: &Path, range: FrameRange) -> Result<Self, DatasetError> {
        let results = dir.join("results");
        let mut frames = BTreeMap::new();
        for entry in std::fs::read_dir(&results).map_err(|e| DatasetError::io(&results, e))? {
            let entry = entry.map_err(|e| DatasetError::io(&results, e))?;
            let name = entry.file_name();
            let name = name.to_string_lossy();
            let Some(rest) = name.strip_prefix("frame") else {
                continue;
            };
            let Some((number, ext)) = rest.rsplit_once('.') else {
                continue;
            };
            if !matches!(ext, "jpg" | "png") {
                continue;
            }
            let number: usize = number.parse().map_err(|_| {
                DatasetError::format(
                    &entry.path(),
                    None,
                    format!("frame number {number:?} is not an integer"),
                )
            })?;
            if range.contains(number) {
                frames.insert(number, entry.path());
            }
        }
        if frames.is_empty() {
            return Err(DatasetError::Invalid(format!(
                "{}: no frameXXXXXX.jpg files with frame numbers in {range}",
                results.display()
            )));
        }
        let traj_path = dir.join("traj.txt");
        let poses = Trajectory::read_kitti_c2w(&traj_path)?.poses;
        if let Some((&last, path)) = frames.iter().next_back()
            && last >= poses.len()
        {
            return Err(DatasetError::format(
                &traj_path,
                None,
                format!(
                    "has {} poses but {} is frame {last}",
                    poses.len(),
                    path.display()
                ),
            ));
        }
        let k_path = dir.join(crate::seven_scenes::INTRINSICS_FILE);
        let intrinsics = if k_path.is_file() {
            let first = frames.values().next().expect("frames is not empty");
            let (w, h) =
                image::image_dimensions(first).map_err(|e| DatasetError::decode(first, e))?;
            Intrinsics::read_k_file(&k_path, w, h)?
        } else {
            DEFAULT_INTRINSICS
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            frames: frames.into_iter().collect(),
            poses,
            intrinsics,
        })
    }
}

impl Dataset for Replica {
    fn describe(&self) -> String {
        format!("Replica layout at {}", self.dir.display())
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.frames[position].0
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.frames[position].0 as f64 / NO_CLOCK_FRAMES_PER_SECOND
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(self.poses.get(self.frames[position].0).copied())
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let (number, color) = &self.frames[position];
        let depth_file = self
            .dir
            .join("results")
            .join(format!("depth{number:06}.png"));
        let (rgb, depth) = read_rgbd(
            color,
            &depth_file,
            *number,
            &self.intrinsics,
            DEPTH_ENCODING,
        )?;
        Ok(Frame {
            index: *number,
            timestamp: self.timestamp(position),
            rgb,
            depth,
            world_from_camera_gt: self.ground_truth(position)?,
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: self.intrinsics,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_nice_slam_layout() {
        let dir = tempfile::tempdir().unwrap();
        let results = dir.path().join("results");
        std::fs::create_dir(&results).unwrap();
        std::fs::write(
            dir.path().join("camera-intrinsics.txt"),
            "600 0 3.5\n0 600 2.5\n0 0 1\n",
        )
        .unwrap();
        let mut traj = String::new();
        for i in 0..3 {
            image::RgbImage::from_pixel(8, 6, image::Rgb([i as u8, 0, 0]))
                .save(results.join(format!("frame{i:06}.png")))
                .unwrap();
            image::ImageBuffer::<image::Luma<u16>, _>::from_pixel(8, 6, image::Luma([6554u16]))
                .save(results.join(format!("depth{i:06}.png")))
                .unwrap();
            traj.push_str(&format!("1 0 0 {i} 0 1 0 0 0 0 1 0 0 0 0 1\n"));
        }
        std::fs::write(dir.path().join("traj.txt"), &traj).unwrap();
        let ds = crate::open(dir.path().to_str().unwrap(), "1..".parse().unwrap()).unwrap();
        assert_eq!(ds.len(), 2);
        let f = ds.load(1).unwrap();
        assert_eq!(f.index, 2);
        assert!((f.depth.data[0] - 6554.0 / 6553.5).abs() < 1e-6);
        assert_eq!(f.world_from_camera_gt.unwrap().translation.vector.x, 2.0);
        assert_eq!(f.intrinsics.width, 8);
        // traj.txt shorter than the frames -> an error naming traj.txt.
        std::fs::write(
            dir.path().join("traj.txt"),
            "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n",
        )
        .unwrap();
        let err = Replica::open(dir.path(), FrameRange::ALL)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("traj.txt"), "{err}");
    }
}
