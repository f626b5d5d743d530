//! Dataset readers. Every layout yields the same [`Frame`]: RGB u8, depth in metres (invalid = 0),
//! a timestamp in seconds, the ground-truth `world_from_camera` pose when the dataset has one, and
//! the intrinsics.
//!
//! Layouts (docs/method.md, Datasets): 7-Scenes ([`seven_scenes`]), Replica / Multi-agent Replica
//! ([`replica`]), TUM RGB-D ([`tum`]), ROS 2 bags ([`rosbag`]) and the embedded procedural scene
//! ([`synthetic`]), which needs no files at all. [`open`] picks the reader from a path or a `synthetic:` spec string;
//! [`prefetch::Prefetcher`] decodes frames on worker threads so disk I/O overlaps compute;
//! [`noise`] degrades frames for robustness runs (the `[noise]` configuration section);
//! [`shared_data`] finds the real data tests and benchmarks read.
//!
//! The image and pose types the frames carry (depth images, intrinsics, trajectories, the file
//! errors) are the `geometry` crate's, so code that only handles frames need not depend on the
//! readers.

pub mod live;
pub mod noise;
pub mod prefetch;
pub mod replica;
pub mod rosbag;
pub mod seven_scenes;
pub mod shared_data;
pub mod synthetic;
pub mod tum;
pub mod undistort;

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::distortion::{DISTORTION_FILE, Distortion};
use geometry::files::DatasetError;
use image::RgbImage;
use nalgebra::Isometry3;

/// One RGB-D frame as every part of the system sees it.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Frame number in its sequence (the number in the file name for 7-Scenes and Replica, the
    /// row of the association for TUM, the render index for the synthetic scene).
    pub index: usize,
    /// Seconds. 7-Scenes and Replica have no clock: `index / fps` (30 Hz), as the shared
    /// groundtruth_tum.txt files use.
    pub timestamp: f64,
    /// Colour image, 8-bit RGB, of the size the intrinsics give.
    pub rgb: RgbImage,
    /// Depth in metres, `0.0` where invalid, the size of `rgb`. Frames from [`open`] have it on
    /// `rgb`'s pixel grid (see [`undistort`]); a reader's own frames may have it on a pinhole of
    /// its own ([`Dataset::depth_registration`]).
    pub depth: DepthImage,
    /// Ground-truth camera-to-world pose, when the dataset has one.
    pub world_from_camera_gt: Option<Isometry3<f64>>,
    /// Why the frame's ground-truth pose could not be read (the message names the file), when
    /// its pose file is there but broken. The frame itself is fine: it is tracked and mapped, and
    /// only left out of the evaluation.
    pub ground_truth_error: Option<String>,
    /// The camera of `rgb` (and of `depth` in frames from [`open`]). For frames [`open`]
    /// undistorts, it is the pinhole they were resampled into, not the recorded lens.
    pub intrinsics: Intrinsics,
    /// When the colour image was taken, relative to the depth image (seconds, colour stamp
    /// minus depth stamp): sensors that stream colour and depth separately (a Kinect through
    /// OpenNI, TUM's recordings, ROS 2 topics) pair images up to a frame period apart, and in a
    /// fast turn the two then see the scene from poses a degree apart. 0 where the two are taken
    /// together or the source does not say (7-Scenes, Replica, the synthetic scene).
    pub colour_offset_s: f64,
}

/// A source of frames with random access. Implementations are cheap to share between threads:
/// the prefetcher calls [`Dataset::load`] from several workers at once.
pub trait Dataset: Send + Sync {
    /// Human-readable description (layout and path).
    fn describe(&self) -> String;
    /// Intrinsics shared by all frames (of the colour camera as recorded, before any
    /// undistortion [`open`] adds).
    fn intrinsics(&self) -> Intrinsics;
    /// Where the depth pixels are relative to the colour image: aligned pixel for pixel unless a
    /// layout knows its sensor's driver registered them to a pinhole of its own.
    fn depth_registration(&self) -> undistort::DepthRegistration {
        undistort::DepthRegistration::ColourGrid
    }
    /// The colour lens's distortion when the dataset itself says it (a bag's CameraInfo); folders
    /// say it with [`geometry::distortion::DISTORTION_FILE`] instead.
    fn lens_distortion(&self) -> Option<Distortion> {
        None
    }
    /// Where the dataset is damaged, when its reader could only read part of it (a bag cut
    /// short): the frames are those before the damage.
    fn damage(&self) -> Option<String> {
        None
    }
    /// Number of frames in the (range-selected) sequence.
    fn len(&self) -> usize;
    /// True when the (range-selected) sequence has no frames.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Frame number of the `position`-th frame of the sequence.
    fn frame_index(&self, position: usize) -> usize;
    /// Timestamp of the `position`-th frame, without decoding images.
    fn timestamp(&self, position: usize) -> f64;
    /// Ground-truth pose of the `position`-th frame, without decoding images. `Ok(None)` when the
    /// dataset has no ground truth for it.
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError>;
    /// Whether [`Dataset::load`] can give the `position`-th frame again: always, except for a
    /// live camera, which keeps only some frames for the evaluation.
    fn can_load(&self, _position: usize) -> bool {
        true
    }
    /// Decodes the `position`-th frame.
    fn load(&self, position: usize) -> Result<Frame, DatasetError>;
}

/// A half-open range of frame numbers with an optional stride, written `A..B` (B excluded),
/// `A..` (to the end) or `..B`, each optionally followed by `:S` to take every `S`-th frame from
/// `A` on (`0..1000:10` = frames 0, 10, ..., 990). `0..600` and `400..1000` split a 1000-frame
/// sequence into two overlapping agents. A strided selection keeps each frame's own number and
/// timestamp, so a sensor-paced replay runs at the strided rate (every 10th frame of a 30 Hz
/// sequence arrives at 3 Hz) and ground truth stays associated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRange {
    /// First frame number selected.
    pub first: usize,
    /// Frame number the range stops before (excluded); `None`: to the end of the sequence.
    pub end: Option<usize>,
    /// Take every `step`-th frame number from `first` on (1: every frame).
    pub step: usize,
}

impl Default for FrameRange {
    fn default() -> Self {
        Self::ALL
    }
}

impl FrameRange {
    /// Every frame: `0..`, step 1.
    pub const ALL: FrameRange = FrameRange {
        first: 0,
        end: None,
        step: 1,
    };

    /// Frames `first..end` (end excluded), every one.
    pub fn new(first: usize, end: Option<usize>) -> Self {
        Self {
            first,
            end,
            step: 1,
        }
    }

    /// The same frames taken every `step`-th (at least 1).
    pub fn with_step(self, step: usize) -> Self {
        Self {
            step: step.max(1),
            ..self
        }
    }

    /// True when frame number `frame` is selected: inside `first..end` and a whole number of steps
    /// from `first`.
    pub fn contains(&self, frame: usize) -> bool {
        frame >= self.first
            && self.end.is_none_or(|end| frame < end)
            && (frame - self.first).is_multiple_of(self.step.max(1))
    }
}

impl FromStr for FrameRange {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || {
            format!(
                "invalid frame range {s:?}: expected FIRST..END (END excluded), FIRST.. or ..END, \
                 optionally followed by :STEP (every STEP-th frame)"
            )
        };
        let (range, step) = match s.trim().split_once(':') {
            Some((range, step)) => {
                let step: usize = step.trim().parse().map_err(|_| bad())?;
                if step == 0 {
                    return Err(format!(
                        "invalid frame range {s:?}: STEP must be at least 1"
                    ));
                }
                (range, step)
            }
            None => (s.trim(), 1),
        };
        let (a, b) = range.trim().split_once("..").ok_or_else(bad)?;
        let first = if a.is_empty() {
            0
        } else {
            a.trim().parse().map_err(|_| bad())?
        };
        let end = if b.is_empty() {
            None
        } else {
            Some(b.trim().parse().map_err(|_| bad())?)
        };
        if let Some(end) = end
            && end <= first
        {
            return Err(format!(
                "invalid frame range {s:?}: END must be greater than FIRST"
            ));
        }
        Ok(Self { first, end, step })
    }
}

impl fmt::Display for FrameRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.end {
            Some(end) => write!(f, "{}..{}", self.first, end)?,
            None => write!(f, "{}..", self.first)?,
        }
        if self.step > 1 {
            write!(f, ":{}", self.step)?;
        }
        Ok(())
    }
}

/// What one agent replays: a dataset (a folder or a `synthetic:` spec) and its frames, written
/// `DATASET`, `DATASET:RANGE` or `DATASET:RANGE:STEP` (`RANGE` and `STEP` as in [`FrameRange`]):
/// `../shared/datasets/7scenes-redkitchen:0..600:10`. A synthetic spec has colons of its own, so
/// only a trailing range (with its step) is split off. The one parser of these specs: the agent,
/// the benchmarks and the swarm launcher all read them through it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetSpec {
    /// The folder or synthetic spec [`open`] takes.
    pub dataset: String,
    /// Which of its frame numbers to replay ([`FrameRange::ALL`] when the spec names no range).
    pub frames: FrameRange,
}

impl DatasetSpec {
    /// Opens the dataset with its frame selection.
    pub fn open(&self) -> Result<Box<dyn Dataset>, DatasetError> {
        open(&self.dataset, self.frames)
    }
}

impl FromStr for DatasetSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s.is_empty() {
            return Err("empty dataset spec: expected DATASET[:FIRST..END[:STEP]]".into());
        }
        // The range is the last part holding "..", possibly followed by one more part (its
        // step); everything before it is the dataset.
        let parts: Vec<&str> = s.split(':').collect();
        let range_at = (1..parts.len())
            .rev()
            .take(2)
            .find(|&i| parts[i].contains(".."));
        let Some(range_at) = range_at else {
            return Ok(Self {
                dataset: s.to_string(),
                frames: FrameRange::ALL,
            });
        };
        let dataset = parts[..range_at].join(":");
        let range = parts[range_at..].join(":");
        let frames = range
            .parse()
            .map_err(|e| format!("dataset spec {s:?}: {e}"))?;
        if dataset.is_empty() {
            return Err(format!(
                "dataset spec {s:?}: no dataset before the frame range"
            ));
        }
        Ok(Self { dataset, frames })
    }
}

impl fmt::Display for DatasetSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.frames == FrameRange::ALL {
            f.write_str(&self.dataset)
        } else {
            write!(f, "{}:{}", self.dataset, self.frames)
        }
    }
}

/// Reads an 8-bit RGB image (PNG or JPEG; grey and RGBA are converted), naming the file on error.
pub fn read_rgb(path: &Path, index: usize) -> Result<RgbImage, DatasetError> {
    let bytes = read_frame_file(path, index)?;
    if ros2::image::is_truncated_jpeg(&bytes) {
        return Err(DatasetError::decode(
            path,
            "JPEG without its end-of-image marker: the file is truncated",
        ));
    }
    let img = image::load_from_memory(&bytes).map_err(|e| DatasetError::decode(path, e))?;
    match img {
        image::DynamicImage::ImageRgb8(rgb) => Ok(rgb),
        image::DynamicImage::ImageRgba8(_)
        | image::DynamicImage::ImageLuma8(_)
        | image::DynamicImage::ImageLumaA8(_) => Ok(img.to_rgb8()),
        other => Err(DatasetError::decode(
            path,
            format!("expected an 8-bit colour image, found {:?}", other.color()),
        )),
    }
}

/// The bytes of one of frame `index`'s files; a file that is not there is a missing frame.
fn read_frame_file(path: &Path, index: usize) -> Result<Vec<u8>, DatasetError> {
    std::fs::read(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            DatasetError::MissingFrame {
                path: path.to_path_buf(),
                index,
            }
        } else {
            DatasetError::io(path, e)
        }
    })
}

/// Reads a 16-bit single-channel depth PNG as raw units, refusing 8-bit or colour PNGs (a common
/// mistake that would silently scale depth by 256).
pub fn read_depth_u16(path: &Path, index: usize) -> Result<(u32, u32, Vec<u16>), DatasetError> {
    let bytes = read_frame_file(path, index)?;
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .map_err(|e| DatasetError::decode(path, e))?;
    match img {
        image::DynamicImage::ImageLuma16(buf) => {
            let (w, h) = buf.dimensions();
            Ok((w, h, buf.into_raw()))
        }
        other => Err(DatasetError::decode(
            path,
            format!(
                "depth must be a 16-bit single-channel PNG, found {:?}",
                other.color()
            ),
        )),
    }
}

/// Depth encoding of a layout's 16-bit depth PNGs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthEncoding {
    /// `metres = raw / units_per_metre`.
    pub units_per_metre: f64,
    /// A raw value besides 0 that marks a hole (7-Scenes: 65535).
    pub invalid_raw: Option<u16>,
}

/// Reads one frame's colour and depth images and checks both against the dataset's image size.
pub fn read_rgbd(
    color: &Path,
    depth: &Path,
    index: usize,
    intrinsics: &Intrinsics,
    encoding: DepthEncoding,
) -> Result<(RgbImage, DepthImage), DatasetError> {
    let rgb = read_rgb(color, index)?;
    check_size(color, intrinsics, rgb.width(), rgb.height())?;
    let (w, h, raw) = read_depth_u16(depth, index)?;
    check_size(depth, intrinsics, w, h)?;
    let depth =
        DepthImage::from_raw_u16(w, h, &raw, encoding.units_per_metre, encoding.invalid_raw);
    Ok((rgb, depth))
}

/// Writes a depth image as a 16-bit PNG in `units_per_metre` (1000 = millimetres).
pub fn write_depth_png(
    path: &Path,
    depth: &DepthImage,
    units_per_metre: f64,
) -> Result<(), DatasetError> {
    let raw = depth.to_raw_u16(units_per_metre);
    let buf: image::ImageBuffer<image::Luma<u16>, Vec<u16>> =
        image::ImageBuffer::from_raw(depth.width, depth.height, raw).ok_or_else(|| {
            DatasetError::Invalid("depth buffer size does not match its dimensions".into())
        })?;
    buf.save(path).map_err(|e| DatasetError::decode(path, e))
}

/// Checks an image against the dataset's expected size.
pub fn check_size(
    path: &Path,
    intrinsics: &Intrinsics,
    w: u32,
    h: u32,
) -> Result<(), DatasetError> {
    if (w, h) != (intrinsics.width, intrinsics.height) {
        return Err(DatasetError::SizeMismatch {
            path: path.to_path_buf(),
            expected_w: intrinsics.width,
            expected_h: intrinsics.height,
            found_w: w,
            found_h: h,
        });
    }
    Ok(())
}

/// Opens a dataset from a path or a synthetic spec, detecting the layout:
/// - `synthetic` or `synthetic:agents=3,agent=1,frames=300,seed=7`: the embedded scene, streamed
///   without touching disk (see [`synthetic::SyntheticSpec`]);
/// - a folder with `results/` and `traj.txt`: Replica (NICE-SLAM layout) or one agent of
///   Multi-agent Replica;
/// - a folder with `rgb.txt` and `depth.txt`: TUM RGB-D;
/// - a folder with `frame-XXXXXX.color.{png,jpg}` files: 7-Scenes (also what `mac-ego3d synth`
///   writes);
/// - a rosbag2 bag: a `.mcap` or `.db3` file, or a folder of them (with its metadata.yaml).
///
/// `range` selects frame numbers (see [`FrameRange`]). A folder holding
/// [`geometry::distortion::DISTORTION_FILE`] (`k1 k2 p1 p2 k3`) has its frames undistorted as
/// they load, and one holding [`undistort::DEPTH_INTRINSICS_FILE`] (a 3x3 K) has its colour
/// re-projected into the depth's pinhole ([`undistort`]).
pub fn open(spec: &str, range: FrameRange) -> Result<Box<dyn Dataset>, DatasetError> {
    open_with(spec, range, &OpenOptions::default())
}

/// What the configuration adds to a dataset's own description of itself.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct OpenOptions {
    /// Lens distortion coefficients that replace the folder's
    /// [`geometry::distortion::DISTORTION_FILE`] or the bag's CameraInfo (the `[camera]
    /// distortion` configuration key; all zeros turns undistortion off).
    pub distortion: Option<Distortion>,
    /// Which topics of a ROS 2 bag to read (the `[ros2]` section).
    pub ros2: rosbag::Ros2Config,
}

/// [`open`] with the configuration's [`OpenOptions`].
pub fn open_with(
    spec: &str,
    range: FrameRange,
    options: &OpenOptions,
) -> Result<Box<dyn Dataset>, DatasetError> {
    if live::is_live(spec) {
        return Err(DatasetError::Invalid(format!(
            "{spec}: a live ROS 2 camera is a frame source for an agent (mac-agent --dataset \
             {spec}), not a recording that can be read again"
        )));
    }
    let dataset: Box<dyn Dataset> = if spec == "synthetic" || spec.starts_with("synthetic:") {
        let parsed: synthetic::SyntheticSpec = spec.parse().map_err(DatasetError::Invalid)?;
        Box::new(synthetic::SyntheticDataset::new(parsed, range)?)
    } else {
        let dir = Path::new(spec);
        match detect_layout(dir)? {
            Layout::RosBag => Box::new(rosbag::RosBag::open(dir, range, &options.ros2)?),
            Layout::Replica => Box::new(replica::Replica::open(dir, range)?),
            Layout::Tum => Box::new(tum::Tum::open(dir, range)?),
            Layout::SevenScenes => Box::new(seven_scenes::SevenScenes::open(dir, range)?),
        }
    };
    let folder_file = |name: &str| Some(Path::new(spec).join(name)).filter(|f| f.is_file());
    let distortion = match options.distortion {
        Some(given) => given,
        None => match folder_file(DISTORTION_FILE) {
            Some(file) => Distortion::read_file(&file)?,
            None => dataset.lens_distortion().unwrap_or_default(),
        },
    };
    let colour = dataset.intrinsics();
    let depth = match folder_file(undistort::DEPTH_INTRINSICS_FILE) {
        Some(file) => undistort::DepthRegistration::Pinhole(Intrinsics::read_k_file(
            &file,
            colour.width,
            colour.height,
        )?),
        None => dataset.depth_registration(),
    };
    undistort::Undistorted::wrap(dataset, distortion, depth)
}

/// On-disk layouts [`open`] recognises.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// 7-Scenes, also what `mac-ego3d synth` writes: `frame-XXXXXX.color.{png,jpg}` files
    /// ([`seven_scenes`]).
    SevenScenes,
    /// Replica in the NICE-SLAM layout, or one agent of Multi-agent Replica: `results/` and
    /// `traj.txt` ([`replica`]).
    Replica,
    /// TUM RGB-D: `rgb.txt` and `depth.txt` ([`tum`]).
    Tum,
    /// A rosbag2 bag: a `.mcap` / `.db3` file or a folder of them.
    RosBag,
}

/// Recognises the layout of a dataset folder from the files it holds (or a bag file by its
/// extension).
pub fn detect_layout(dir: &Path) -> Result<Layout, DatasetError> {
    if rosbag::is_bag(&dir.to_string_lossy()) {
        return Ok(Layout::RosBag);
    }
    if !dir.is_dir() {
        return Err(DatasetError::io(
            dir,
            std::io::Error::new(std::io::ErrorKind::NotFound, "dataset folder not found"),
        ));
    }
    if dir.join("results").is_dir() && dir.join("traj.txt").is_file() {
        return Ok(Layout::Replica);
    }
    if dir.join("rgb.txt").is_file() && dir.join("depth.txt").is_file() {
        return Ok(Layout::Tum);
    }
    let entries = std::fs::read_dir(dir).map_err(|e| DatasetError::io(dir, e))?;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if name.starts_with("frame-")
            && (name.ends_with(".color.png") || name.ends_with(".color.jpg"))
        {
            return Ok(Layout::SevenScenes);
        }
    }
    Err(DatasetError::Invalid(format!(
        "{}: unknown dataset layout: expected 7-Scenes (frame-XXXXXX.color.png/jpg), Replica \
         (results/ + traj.txt), TUM RGB-D (rgb.txt + depth.txt) or a ROS 2 bag (.mcap / .db3)",
        dir.display()
    )))
}

/// Sub-folders of `dir` that are datasets themselves, sorted by name: the agents of a
/// multi-agent collection such as Multi-agent Replica (`Apart-0/part_1`, `part_2`, ...) or the
/// output of `mac-ego3d synth` (`agent_0`, `agent_1`, ...).
pub fn agent_folders(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir)
        .map_err(|e| DatasetError::io(dir, e))?
        .flatten()
    {
        let path = entry.path();
        if path.is_dir() && detect_layout(&path).is_ok() {
            found.push(path);
        }
    }
    // Natural order: agent_2 before agent_10.
    found.sort_by_key(|p| natural_key(&p.file_name().unwrap_or_default().to_string_lossy()));
    Ok(found)
}

/// Sort key that orders a trailing number numerically: ("agent_", 10) after ("agent_", 2).
fn natural_key(name: &str) -> (String, u64, String) {
    let digits_start = name.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    let number = name[digits_start..].parse().unwrap_or(0);
    (name[..digits_start].to_string(), number, name.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_truncated_jpeg_is_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frame-000000.color.jpg");
        let image = RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 4, y as u8 * 5, 90]));
        image.save(&path).unwrap();
        let complete = read_rgb(&path, 0).unwrap();
        assert_eq!(complete.dimensions(), (64, 48));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        let error = read_rgb(&path, 0).unwrap_err().to_string();
        assert!(
            error.contains("frame-000000.color.jpg") && error.contains("truncated"),
            "{error}"
        );
    }

    #[test]
    fn frame_range_parses_and_refuses() {
        assert_eq!(
            "0..600".parse::<FrameRange>().unwrap(),
            FrameRange::new(0, Some(600))
        );
        assert_eq!(
            "400..".parse::<FrameRange>().unwrap(),
            FrameRange::new(400, None)
        );
        assert_eq!(
            "..10".parse::<FrameRange>().unwrap(),
            FrameRange::new(0, Some(10))
        );
        assert!("5..5".parse::<FrameRange>().is_err());
        assert!("a..5".parse::<FrameRange>().is_err());
        assert!("12".parse::<FrameRange>().is_err());
        let r: FrameRange = "400..1000".parse().unwrap();
        assert!(r.contains(400) && r.contains(999) && !r.contains(1000) && !r.contains(399));
        assert_eq!(r.to_string(), "400..1000");
    }

    #[test]
    fn frame_range_strides_keep_frame_numbers() {
        let r: FrameRange = "5..40:10".parse().unwrap();
        assert_eq!(r, FrameRange::new(5, Some(40)).with_step(10));
        let taken: Vec<usize> = (0..50).filter(|&n| r.contains(n)).collect();
        assert_eq!(taken, [5, 15, 25, 35]);
        assert_eq!(r.to_string(), "5..40:10");
        assert_eq!("..:3".parse::<FrameRange>().unwrap().to_string(), "0..:3");
        assert_eq!(
            "0..100:1".parse::<FrameRange>().unwrap().to_string(),
            "0..100"
        );
        for bad in ["0..100:0", "0..100:x", "0..100:", ":3"] {
            let error = bad.parse::<FrameRange>().unwrap_err();
            assert!(error.contains(bad), "{bad}: {error}");
        }
    }

    #[test]
    fn dataset_specs_split_off_a_trailing_range_and_step() {
        let spec = |s: &str| s.parse::<DatasetSpec>().unwrap();
        assert_eq!(
            spec("../shared/datasets/7scenes-redkitchen:0..600:10"),
            DatasetSpec {
                dataset: "../shared/datasets/7scenes-redkitchen".into(),
                frames: FrameRange::new(0, Some(600)).with_step(10),
            }
        );
        assert_eq!(
            spec("synthetic:agents=2,agent=1:100.."),
            DatasetSpec {
                dataset: "synthetic:agents=2,agent=1".into(),
                frames: FrameRange::new(100, None),
            }
        );
        assert_eq!(spec("synthetic:agents=2").frames, FrameRange::ALL);
        assert_eq!(spec("data/run..1").dataset, "data/run..1");
        for text in ["a/b:0..600:10", "synthetic:frames=20:3..9", "dir"] {
            assert_eq!(spec(text).to_string(), text);
        }
        let error = "dir:9..3".parse::<DatasetSpec>().unwrap_err();
        assert!(
            error.contains("dir:9..3") && error.contains("END"),
            "{error}"
        );
        assert!(":0..5".parse::<DatasetSpec>().is_err());
        assert!("".parse::<DatasetSpec>().is_err());
    }

    #[test]
    fn agent_folders_sort_naturally() {
        let dir = tempfile::tempdir().unwrap();
        for k in [10, 2, 1] {
            let agent = dir.path().join(format!("agent_{k}"));
            std::fs::create_dir(&agent).unwrap();
            std::fs::write(agent.join("frame-000000.color.png"), b"").unwrap();
        }
        std::fs::create_dir(dir.path().join("not_a_dataset")).unwrap();
        let names: Vec<_> = agent_folders(dir.path())
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["agent_1", "agent_2", "agent_10"]);
    }
}
