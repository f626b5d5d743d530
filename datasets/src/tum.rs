//! TUM RGB-D layout: `rgb.txt` and `depth.txt` (`timestamp path` lines, `#` comments),
//! `groundtruth.txt` (`t tx ty tz qx qy qz qw`), depth PNG u16 with metres = raw / 5000.
//! Colour and depth are associated by nearest timestamp, ground truth likewise; frames without a
//! depth image within [`MAX_ASSOCIATION_DT`] are left out. The frame number is the row of the
//! association (0, 1, 2, ...), the timestamp the colour image's; how far the depth image's lies
//! from it is the frame's `colour_offset_s`.
//!
//! Intrinsics: the calibrated pinhole of the Freiburg sensor named in the folder name
//! (`freiburg1/2/3`), else the ROS default; `camera-intrinsics.txt` (3x3 K) overrides both.
//! A `camera-distortion.txt` beside the lists (`k1 k2 p1 p2 k3`; TUM publishes them per Freiburg
//! sensor) has [`crate::open`] undistort the colour frames.
//!
//! Depth: TUM's depth images were registered to the colour images by the Kinect's OpenNI driver,
//! which projects them with the factory pinhole (fx = fy = 525, cx 319.5, cy 239.5: the "ROS
//! default" TUM recommends for them), not with the calibrated colour lens. A recording from the
//! Freiburg sensors (named `freiburgN` or `frN` in the folder name, or in the
//! `# file: 'rgbd_dataset_freiburgN_...'` header TUM's lists carry) therefore reports its depth
//! as that pinhole ([`crate::undistort::DepthRegistration::Pinhole`]), and the colour image is
//! re-projected into it; other folders in this layout have depth aligned to the colour grid, unless
//! a `depth-intrinsics.txt` says otherwise.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use geometry::camera::Intrinsics;
use geometry::files::DatasetError;
use geometry::trajectory::Trajectory;

use crate::undistort::DepthRegistration;
use crate::{Dataset, DepthEncoding, Frame, FrameRange, read_rgbd};

/// Largest timestamp difference accepted when pairing colour with depth and ground truth (s).
pub const MAX_ASSOCIATION_DT: f64 = 0.02;
/// Depth PNG units: raw / 5000 = metres.
pub const DEPTH_UNITS_PER_METRE: f64 = 5000.0;
const DEPTH_ENCODING: DepthEncoding = DepthEncoding {
    units_per_metre: DEPTH_UNITS_PER_METRE,
    invalid_raw: None,
};
/// TUM's published pinhole calibrations (640x480) per Freiburg sensor, and the ROS default.
pub const FREIBURG1: Intrinsics = Intrinsics {
    fx: 517.3,
    fy: 516.5,
    cx: 318.6,
    cy: 255.3,
    width: 640,
    height: 480,
};
/// TUM's calibration of the Freiburg 2 sensor.
pub const FREIBURG2: Intrinsics = Intrinsics {
    fx: 520.9,
    fy: 521.0,
    cx: 325.1,
    cy: 249.7,
    width: 640,
    height: 480,
};
/// TUM's calibration of the Freiburg 3 sensor.
pub const FREIBURG3: Intrinsics = Intrinsics {
    fx: 535.4,
    fy: 539.2,
    cx: 320.1,
    cy: 247.6,
    width: 640,
    height: 480,
};
/// The ROS default pinhole: the intrinsics of folders that name no Freiburg sensor, and the pinhole
/// a Freiburg sensor's depth images are registered to (see the module documentation).
pub const ROS_DEFAULT: Intrinsics = Intrinsics {
    fx: 525.0,
    fy: 525.0,
    cx: 319.5,
    cy: 239.5,
    width: 640,
    height: 480,
};

struct TumFrame {
    timestamp: f64,
    /// The paired depth image's timestamp.
    depth_timestamp: f64,
    rgb: PathBuf,
    depth: PathBuf,
    world_from_camera_gt: Option<Isometry3<f64>>,
}

/// A folder in the TUM RGB-D layout (see the module documentation), with colour, depth and ground
/// truth associated by [`Tum::open`]; images are decoded as frames load.
pub struct Tum {
    dir: PathBuf,
    frames: Vec<(usize, TumFrame)>,
    intrinsics: Intrinsics,
    depth_registration: DepthRegistration,
}

/// The Freiburg sensor (1, 2 or 3) a TUM recording comes from, from the folder name
/// (`freiburg2`, `fr2`) or the `# file: 'rgbd_dataset_freiburgN_...'` header of its depth list.
fn freiburg_sensor(dir: &Path) -> Option<u8> {
    let sensor_in = |text: &str| {
        let text = text.to_ascii_lowercase();
        (1..=3u8).find(|n| {
            text.contains(&format!("freiburg{n}"))
                || text
                    .split(|c: char| !c.is_ascii_alphanumeric())
                    .any(|word| word == format!("fr{n}"))
        })
    };
    let name = dir
        .canonicalize()
        .unwrap_or_else(|_| dir.to_path_buf())
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    sensor_in(&name).or_else(|| {
        let header = std::fs::read_to_string(dir.join("depth.txt")).ok()?;
        let comments: String = header
            .lines()
            .take_while(|l| l.starts_with('#'))
            .collect::<Vec<_>>()
            .join(" ");
        sensor_in(&comments)
    })
}

/// Reads a `timestamp path` list file.
fn read_list(path: &Path) -> Result<Vec<(f64, PathBuf)>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut out = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (Some(stamp), Some(file), None) = (parts.next(), parts.next(), parts.next()) else {
            return Err(DatasetError::format(
                path,
                Some(line_no + 1),
                "expected `timestamp filename`",
            ));
        };
        let stamp: f64 = stamp
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| {
                DatasetError::format(
                    path,
                    Some(line_no + 1),
                    format!("{stamp:?} is not a timestamp"),
                )
            })?;
        out.push((stamp, dir.join(file)));
    }
    if out.windows(2).any(|w| w[1].0 < w[0].0) {
        out.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    Ok(out)
}

/// Index of the entry of sorted `stamps` nearest to `t`, if within `max_dt`.
pub(crate) fn nearest(stamps: &[f64], t: f64, max_dt: f64) -> Option<usize> {
    let i = stamps.partition_point(|&s| s < t);
    let candidates = [i.checked_sub(1), (i < stamps.len()).then_some(i)];
    candidates
        .into_iter()
        .flatten()
        .min_by(|&a, &b| (stamps[a] - t).abs().total_cmp(&(stamps[b] - t).abs()))
        .filter(|&j| (stamps[j] - t).abs() <= max_dt)
}

impl Tum {
    /// Reads the lists of `dir` (and `groundtruth.txt` when there is one), associates them, and
    /// keeps the association rows whose number is in `range`. No image is decoded. Fails when a
    /// list or the ground truth cannot be read or parsed, no pair is in `range`, or
    /// `camera-intrinsics.txt` is malformed.
    pub fn open(dir: &Path, range: FrameRange) -> Result<Self, DatasetError> {
        let rgb = read_list(&dir.join("rgb.txt"))?;
        let depth = read_list(&dir.join("depth.txt"))?;
        let depth_stamps: Vec<f64> = depth.iter().map(|d| d.0).collect();
        let gt_path = dir.join("groundtruth.txt");
        let gt = if gt_path.is_file() {
            Some(Trajectory::read_tum(&gt_path)?)
        } else {
            None
        };
        let mut frames = Vec::new();
        for (t, rgb_path) in rgb {
            let Some(d) = nearest(&depth_stamps, t, MAX_ASSOCIATION_DT) else {
                continue;
            };
            let pose = gt
                .as_ref()
                .and_then(|g| nearest(&g.stamps, t, MAX_ASSOCIATION_DT).map(|j| g.poses[j]));
            let number = frames.len();
            frames.push((
                number,
                TumFrame {
                    timestamp: t,
                    depth_timestamp: depth_stamps[d],
                    rgb: rgb_path,
                    depth: depth[d].1.clone(),
                    world_from_camera_gt: pose,
                },
            ));
        }
        frames.retain(|(number, _)| range.contains(*number));
        if frames.is_empty() {
            return Err(DatasetError::Invalid(format!(
                "{}: no colour/depth pairs within {MAX_ASSOCIATION_DT} s in frame range {range}",
                dir.display()
            )));
        }
        let sensor = freiburg_sensor(dir);
        let mut intrinsics = match sensor {
            Some(1) => FREIBURG1,
            Some(2) => FREIBURG2,
            Some(3) => FREIBURG3,
            _ => ROS_DEFAULT,
        };
        let k_path = dir.join(crate::seven_scenes::INTRINSICS_FILE);
        if k_path.is_file() {
            intrinsics = Intrinsics::read_k_file(&k_path, intrinsics.width, intrinsics.height)?;
        }
        let depth_registration = match sensor {
            Some(_) => DepthRegistration::Pinhole(ROS_DEFAULT),
            None => DepthRegistration::ColourGrid,
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            frames,
            intrinsics,
            depth_registration,
        })
    }
}

impl Dataset for Tum {
    fn describe(&self) -> String {
        format!("TUM RGB-D layout at {}", self.dir.display())
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn depth_registration(&self) -> DepthRegistration {
        self.depth_registration
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.frames[position].0
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.frames[position].1.timestamp
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(self.frames[position].1.world_from_camera_gt)
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let (number, f) = &self.frames[position];
        let (rgb, depth) = read_rgbd(&f.rgb, &f.depth, *number, &self.intrinsics, DEPTH_ENCODING)?;
        Ok(Frame {
            index: *number,
            timestamp: f.timestamp,
            rgb,
            depth,
            world_from_camera_gt: f.world_from_camera_gt,
            ground_truth_error: None,
            colour_offset_s: f.timestamp - f.depth_timestamp,
            intrinsics: self.intrinsics,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn associates_by_nearest_timestamp() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("rgbd_dataset_freiburg1_xyz");
        std::fs::create_dir_all(root.join("rgb")).unwrap();
        std::fs::create_dir_all(root.join("depth")).unwrap();
        let mut rgb_list = String::from("# colour images\n");
        let mut depth_list = String::new();
        for i in 0..4 {
            let t = 100.0 + i as f64 * 0.033;
            rgb_list.push_str(&format!("{t:.6} rgb/{i}.png\n"));
            // Frame 2 has no depth close enough: it must be left out.
            let td = if i == 2 { t + 0.05 } else { t + 0.004 };
            depth_list.push_str(&format!("{td:.6} depth/{i}.png\n"));
            image::RgbImage::new(640, 480)
                .save(root.join(format!("rgb/{i}.png")))
                .unwrap();
            image::ImageBuffer::<image::Luma<u16>, _>::from_pixel(640, 480, image::Luma([5000u16]))
                .save(root.join(format!("depth/{i}.png")))
                .unwrap();
        }
        std::fs::write(root.join("rgb.txt"), rgb_list).unwrap();
        std::fs::write(root.join("depth.txt"), depth_list).unwrap();
        std::fs::write(
            root.join("groundtruth.txt"),
            "100.0 1 2 3 0 0 0 1\n100.099 4 5 6 0 0 0 1\n",
        )
        .unwrap();
        let ds = Tum::open(&root, FrameRange::ALL).unwrap();
        assert_eq!(ds.len(), 3);
        assert_eq!(ds.intrinsics(), FREIBURG1);
        assert_eq!(ds.timestamp(2), 100.099);
        let f = ds.load(0).unwrap();
        assert_eq!(f.depth.data[0], 1.0);
        // The colour image was stamped 4 ms before its depth image.
        assert!(
            (f.colour_offset_s + 0.004).abs() < 1e-9,
            "{}",
            f.colour_offset_s
        );
        assert_eq!(f.world_from_camera_gt.unwrap().translation.vector.x, 1.0);
        assert_eq!(
            ds.ground_truth(2).unwrap().unwrap().translation.vector.x,
            4.0
        );
        assert!(ds.ground_truth(1).unwrap().is_none());
        std::fs::write(root.join("rgb.txt"), "100.0\n").unwrap();
        let err = Tum::open(&root, FrameRange::ALL).err().unwrap().to_string();
        assert!(err.contains("rgb.txt line 1"), "{err}");
    }
}
