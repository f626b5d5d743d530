//! Microsoft 7-Scenes layout (also what `mac-ego3d synth` writes):
//! `frame-XXXXXX.color.{png,jpg}`, `frame-XXXXXX.depth.png` (u16 millimetres, 0 and 65535
//! invalid), `frame-XXXXXX.pose.txt` (4x4 camera-to-world, row-major). An optional
//! `camera-intrinsics.txt` (3x3 K) overrides the default intrinsics. Frame numbers need not start at
//! 0 nor be contiguous; a hole in a regularly numbered sequence is read as missing frames. The layout has no clock: timestamp = frame number / 30 s.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use geometry::camera::Intrinsics;
use geometry::files::{DatasetError, parse_floats};
use geometry::se3::pose_from_row_major;
use geometry::trajectory::NO_CLOCK_FRAMES_PER_SECOND;

use crate::{Dataset, DepthEncoding, Frame, FrameRange, read_rgbd};

/// Kinect v1 defaults of the 7-Scenes release.
pub const DEFAULT_INTRINSICS: Intrinsics = Intrinsics {
    fx: 585.0,
    fy: 585.0,
    cx: 320.0,
    cy: 240.0,
    width: 640,
    height: 480,
};
/// Depth PNG units: millimetres.
pub const DEPTH_UNITS_PER_METRE: f64 = 1000.0;
/// Raw depth value the 7-Scenes release uses for holes (besides 0).
pub const INVALID_DEPTH_RAW: u16 = 65535;
const DEPTH_ENCODING: DepthEncoding = DepthEncoding {
    units_per_metre: DEPTH_UNITS_PER_METRE,
    invalid_raw: Some(INVALID_DEPTH_RAW),
};
/// File holding the 3x3 K that overrides [`DEFAULT_INTRINSICS`].
pub const INTRINSICS_FILE: &str = "camera-intrinsics.txt";

/// One frame's files.
#[derive(Debug, Clone)]
struct FrameFiles {
    number: usize,
    color: PathBuf,
}

/// A folder in the 7-Scenes layout (see the module documentation), indexed by
/// [`SevenScenes::open`]; images are decoded as frames load.
pub struct SevenScenes {
    dir: PathBuf,
    frames: Vec<FrameFiles>,
    intrinsics: Intrinsics,
}

impl SevenScenes {
    /// Indexes the folder (no image is decoded). Frames are the frame numbers in `range` that
    /// have any of the three files (colour, depth, pose), and the numbers a regularly numbered
    /// sequence skips ([`fill_numbering_gaps`]): a frame whose colour image or every file is
    /// missing is indexed, so that loading it reports the missing file instead of the frame
    /// vanishing from the sequence unnoticed.
    pub fn open(dir: &Path, range: FrameRange) -> Result<Self, DatasetError> {
        let mut colors: BTreeMap<usize, Option<PathBuf>> = BTreeMap::new();
        for entry in std::fs::read_dir(dir).map_err(|e| DatasetError::io(dir, e))? {
            let entry = entry.map_err(|e| DatasetError::io(dir, e))?;
            let name = entry.file_name();
            let name = name.to_string_lossy();
            let Some(rest) = name.strip_prefix("frame-") else {
                continue;
            };
            let Some((number, kind)) = rest.split_once('.') else {
                continue;
            };
            let is_color = matches!(kind, "color.png" | "color.jpg");
            if !is_color && kind != "depth.png" && kind != "pose.txt" {
                continue;
            }
            let number: usize = number.parse().map_err(|_| {
                DatasetError::format(
                    &entry.path(),
                    None,
                    format!("frame number {number:?} is not an integer"),
                )
            })?;
            if !range.contains(number) {
                continue;
            }
            let color = colors.entry(number).or_default();
            if !is_color {
                continue;
            }
            if let Some(previous) = color.replace(entry.path()) {
                return Err(DatasetError::Invalid(format!(
                    "{} and {}: two colour images for frame {number}",
                    previous.display(),
                    entry.path().display()
                )));
            }
        }
        let Some(first_color) = colors.values().flatten().next().cloned() else {
            return Err(DatasetError::Invalid(format!(
                "{}: no frame-XXXXXX.color.png/jpg files with frame numbers in {range}",
                dir.display()
            )));
        };
        let intrinsics_path = dir.join(INTRINSICS_FILE);
        let intrinsics = if intrinsics_path.is_file() {
            // The K file has no image size; take it from the first colour image's header.
            let (w, h) = image_size(&first_color)?;
            Intrinsics::read_k_file(&intrinsics_path, w, h)?
        } else {
            DEFAULT_INTRINSICS
        };
        fill_numbering_gaps(&mut colors);
        // Named in the missing-frame warning of a frame without colour image: the extension of
        // the sequence's other colour images.
        let color_extension = first_color.extension().unwrap_or_default().to_os_string();
        let frames = colors
            .into_iter()
            .map(|(number, color)| FrameFiles {
                number,
                color: color.unwrap_or_else(|| {
                    dir.join(format!(
                        "frame-{number:06}.color.{}",
                        color_extension.to_string_lossy()
                    ))
                }),
            })
            .collect();
        Ok(Self {
            dir: dir.to_path_buf(),
            frames,
            intrinsics,
        })
    }

    /// The folder read.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

/// Indexes the frames a regularly numbered sequence lacks (every file of them deleted or never
/// copied) as frames without colour image, so that reading them reports each one missing instead
/// of the sequence closing over the hole. The step is the commonest one between frame numbers (1
/// for a full sequence, N for one kept every N-th frame); only gaps that are whole multiples of
/// it count, and nothing outside the first and last frame present is added.
fn fill_numbering_gaps(frames: &mut BTreeMap<usize, Option<PathBuf>>) {
    let numbers: Vec<usize> = frames.keys().copied().collect();
    let mut step_counts: BTreeMap<usize, usize> = BTreeMap::new();
    for pair in numbers.windows(2) {
        *step_counts.entry(pair[1] - pair[0]).or_default() += 1;
    }
    // The commonest step; the smaller one on a tie.
    let Some(step) = step_counts
        .iter()
        .max_by_key(|(step, count)| (**count, std::cmp::Reverse(**step)))
        .map(|(step, _)| *step)
    else {
        return;
    };
    for pair in numbers.windows(2) {
        let gap = pair[1] - pair[0];
        if gap > step && gap.is_multiple_of(step) {
            for absent in (pair[0] + step..pair[1]).step_by(step) {
                frames.insert(absent, None);
            }
        }
    }
}

fn depth_path(dir: &Path, number: usize) -> PathBuf {
    dir.join(format!("frame-{number:06}.depth.png"))
}

fn pose_path(dir: &Path, number: usize) -> PathBuf {
    dir.join(format!("frame-{number:06}.pose.txt"))
}

fn image_size(path: &Path) -> Result<(u32, u32), DatasetError> {
    image::image_dimensions(path).map_err(|e| match e {
        image::ImageError::IoError(io) => DatasetError::io(path, io),
        other => DatasetError::decode(path, other),
    })
}

/// Reads a 4x4 camera-to-world pose file (four rows of four numbers).
pub fn read_pose_file(path: &Path) -> Result<Isometry3<f64>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| DatasetError::io(path, e))?;
    let mut values = Vec::with_capacity(16);
    let mut rows = 0;
    for (line_no, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let row =
            parse_floats(line).map_err(|r| DatasetError::format(path, Some(line_no + 1), r))?;
        if row.len() != 4 {
            return Err(DatasetError::format(
                path,
                Some(line_no + 1),
                format!("expected 4 numbers, found {}", row.len()),
            ));
        }
        values.extend(row);
        rows += 1;
    }
    if rows != 4 {
        return Err(DatasetError::format(
            path,
            None,
            format!("expected a 4x4 matrix, found {rows} rows"),
        ));
    }
    pose_from_row_major(&values).map_err(|r| DatasetError::format(path, None, r))
}

impl Dataset for SevenScenes {
    fn describe(&self) -> String {
        format!("7-Scenes layout at {}", self.dir.display())
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.frames[position].number
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.frames[position].number as f64 / NO_CLOCK_FRAMES_PER_SECOND
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        let path = pose_path(&self.dir, self.frames[position].number);
        if !path.exists() {
            return Ok(None);
        }
        read_pose_file(&path).map(Some)
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let files = &self.frames[position];
        let depth_file = depth_path(&self.dir, files.number);
        let (rgb, depth) = read_rgbd(
            &files.color,
            &depth_file,
            files.number,
            &self.intrinsics,
            DEPTH_ENCODING,
        )?;
        // A broken pose file costs the frame its place in the evaluation, not its tracking.
        let (world_from_camera_gt, ground_truth_error) = match self.ground_truth(position) {
            Ok(pose) => (pose, None),
            Err(error) => (None, Some(error.to_string())),
        };
        Ok(Frame {
            index: files.number,
            timestamp: self.timestamp(position),
            rgb,
            depth,
            world_from_camera_gt,
            ground_truth_error,
            colour_offset_s: 0.0,
            intrinsics: self.intrinsics,
        })
    }
}

/// Writes frames in the 7-Scenes layout: lossless PNG colour, millimetre depth, pose files with
/// full f64 precision, `camera-intrinsics.txt`, and a `groundtruth_tum.txt` for evaluation tools.
pub struct SevenScenesWriter {
    dir: PathBuf,
    tum_lines: Vec<(f64, Isometry3<f64>)>,
}

impl SevenScenesWriter {
    /// Creates `dir` (with its parents) and writes [`INTRINSICS_FILE`] for `intrinsics` into it;
    /// the image size is not written (the reader takes it from the first colour image).
    pub fn create(dir: &Path, intrinsics: &Intrinsics) -> Result<Self, DatasetError> {
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
        let k_path = dir.join(INTRINSICS_FILE);
        let k = format!(
            "{:.17e} 0 {:.17e}\n0 {:.17e} {:.17e}\n0 0 1\n",
            intrinsics.fx, intrinsics.cx, intrinsics.fy, intrinsics.cy
        );
        std::fs::write(&k_path, k).map_err(|e| DatasetError::io(&k_path, e))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            tum_lines: Vec::new(),
        })
    }

    /// Writes one frame's files, named by its frame number: the colour PNG, the depth PNG in
    /// millimetres and, when the frame has a ground-truth pose, its pose file (the pose is also
    /// kept for [`SevenScenesWriter::finish`]). Files already there are replaced.
    pub fn write(&mut self, frame: &Frame) -> Result<(), DatasetError> {
        let color = self.dir.join(format!("frame-{:06}.color.png", frame.index));
        frame
            .rgb
            .save(&color)
            .map_err(|e| DatasetError::decode(&color, e))?;
        crate::write_depth_png(
            &depth_path(&self.dir, frame.index),
            &frame.depth,
            DEPTH_UNITS_PER_METRE,
        )?;
        if let Some(pose) = &frame.world_from_camera_gt {
            let path = pose_path(&self.dir, frame.index);
            let m = pose.to_homogeneous();
            let mut text = String::new();
            for r in 0..4 {
                let row: Vec<String> = (0..4).map(|c| format!("{:.17e}", m[(r, c)])).collect();
                text.push_str(&row.join(" "));
                text.push('\n');
            }
            std::fs::write(&path, text).map_err(|e| DatasetError::io(&path, e))?;
            self.tum_lines.push((frame.timestamp, *pose));
        }
        Ok(())
    }

    /// Writes `groundtruth_tum.txt` for the frames written so far.
    pub fn finish(self) -> Result<PathBuf, DatasetError> {
        let path = self.dir.join("groundtruth_tum.txt");
        let mut file = std::fs::File::create(&path).map_err(|e| DatasetError::io(&path, e))?;
        let traj = geometry::trajectory::Trajectory::from_pairs(self.tum_lines);
        traj.write_tum_to(&mut file)
            .map_err(|e| DatasetError::io(&path, e))?;
        file.flush().map_err(|e| DatasetError::io(&path, e))?;
        Ok(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use geometry::depth::DepthImage;
    use image::RgbImage;

    fn tiny_frame(index: usize) -> Frame {
        let mut depth = DepthImage::new(4, 3);
        depth.data[5] = 1.234;
        Frame {
            index,
            timestamp: index as f64 / NO_CLOCK_FRAMES_PER_SECOND,
            rgb: RgbImage::from_fn(4, 3, |x, y| {
                image::Rgb([x as u8 * 10, y as u8 * 20, index as u8])
            }),
            depth,
            world_from_camera_gt: Some(Isometry3::translation(0.1 * index as f64, 0.0, 1.0)),
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: Intrinsics::new(5.0, 5.0, 1.5, 1.0, 4, 3),
        }
    }

    #[test]
    fn write_then_read_round_trips_with_gaps() {
        let dir = tempfile::tempdir().unwrap();
        let k = Intrinsics::new(5.0, 5.0, 1.5, 1.0, 4, 3);
        let mut writer = SevenScenesWriter::create(dir.path(), &k).unwrap();
        for index in [3, 4, 9] {
            writer.write(&tiny_frame(index)).unwrap();
        }
        writer.finish().unwrap();
        let ds = SevenScenes::open(dir.path(), FrameRange::ALL).unwrap();
        // 5..=8 are a hole in a sequence numbered in steps of 1: missing frames.
        assert_eq!(ds.len(), 7);
        assert_eq!(ds.intrinsics(), k);
        assert_eq!(ds.frame_index(6), 9);
        let hole = ds.load(2).unwrap_err();
        assert!(
            hole.is_missing_frame() && hole.to_string().contains("frame-000005.color.png"),
            "{hole}"
        );
        let frame = ds.load(6).unwrap();
        let expected = tiny_frame(9);
        assert_eq!(frame.rgb, expected.rgb);
        assert_eq!(frame.depth.data[5], 1.234);
        assert_eq!(frame.world_from_camera_gt, expected.world_from_camera_gt);
        assert_eq!(frame.timestamp, 0.3);
        let ranged = SevenScenes::open(dir.path(), "4..9".parse().unwrap()).unwrap();
        assert_eq!(ranged.len(), 1);
    }

    #[test]
    fn bad_input_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let k = Intrinsics::new(5.0, 5.0, 1.5, 1.0, 4, 3);
        let mut writer = SevenScenesWriter::create(dir.path(), &k).unwrap();
        for index in 0..4 {
            writer.write(&tiny_frame(index)).unwrap();
        }
        // 0: depth missing, 1: depth is 8-bit, 2: corrupt colour, 3: malformed pose line.
        std::fs::remove_file(dir.path().join("frame-000000.depth.png")).unwrap();
        image::GrayImage::new(4, 3)
            .save(dir.path().join("frame-000001.depth.png"))
            .unwrap();
        std::fs::write(dir.path().join("frame-000002.color.png"), b"not a png").unwrap();
        std::fs::write(
            dir.path().join("frame-000003.pose.txt"),
            "1 0 0 0\n0 1 0 0\n0 0 1 zz\n0 0 0 1\n",
        )
        .unwrap();
        let ds = SevenScenes::open(dir.path(), FrameRange::ALL).unwrap();
        let e0 = ds.load(0).unwrap_err();
        assert!(
            e0.is_missing_frame() && e0.to_string().contains("frame-000000.depth.png"),
            "{e0}"
        );
        let e1 = ds.load(1).unwrap_err().to_string();
        assert!(
            e1.contains("frame-000001.depth.png") && e1.contains("16-bit"),
            "{e1}"
        );
        let e2 = ds.load(2).unwrap_err().to_string();
        assert!(e2.contains("frame-000002.color.png"), "{e2}");
        // A broken pose file leaves the frame usable, without ground truth.
        let f3 = ds.load(3).unwrap();
        assert!(f3.world_from_camera_gt.is_none());
        let e3 = f3.ground_truth_error.unwrap();
        assert!(e3.contains("frame-000003.pose.txt line 3"), "{e3}");
    }

    #[test]
    fn missing_colour_and_broken_poses_are_reported_not_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let k = Intrinsics::new(5.0, 5.0, 1.5, 1.0, 4, 3);
        let mut writer = SevenScenesWriter::create(dir.path(), &k).unwrap();
        for index in 0..5 {
            writer.write(&tiny_frame(index)).unwrap();
        }
        // 1: colour gone (depth and pose there), 2: pose cut short, 3: pose not rigid,
        // 4: pose with NaN.
        std::fs::remove_file(dir.path().join("frame-000001.color.png")).unwrap();
        let pose_2 = dir.path().join("frame-000002.pose.txt");
        let text = std::fs::read_to_string(&pose_2).unwrap();
        std::fs::write(&pose_2, &text[..text.len() / 2]).unwrap();
        std::fs::write(
            dir.path().join("frame-000003.pose.txt"),
            "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("frame-000004.pose.txt"),
            "1 0 0 NaN\n0 1 0 0\n0 0 1 0\n0 0 0 1\n",
        )
        .unwrap();
        let ds = SevenScenes::open(dir.path(), FrameRange::ALL).unwrap();
        assert_eq!(ds.len(), 5, "the frame without colour is still indexed");
        let e1 = ds.load(1).unwrap_err();
        assert!(
            e1.is_missing_frame() && e1.to_string().contains("frame-000001.color.png"),
            "{e1}"
        );
        for (position, expected) in [
            (2, "frame-000002.pose.txt"),
            (3, "not orthonormal"),
            (4, "not a finite number"),
        ] {
            let frame = ds.load(position).unwrap();
            assert!(frame.world_from_camera_gt.is_none());
            let error = frame.ground_truth_error.unwrap();
            assert!(
                error.contains(&format!("frame-{position:06}.pose.txt"))
                    && error.contains(expected),
                "{error}"
            );
        }
        let intact = ds.load(0).unwrap();
        assert!(intact.world_from_camera_gt.is_some() && intact.ground_truth_error.is_none());
    }

    #[test]
    fn mismatched_sizes_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let k = Intrinsics::new(5.0, 5.0, 1.5, 1.0, 4, 3);
        let mut writer = SevenScenesWriter::create(dir.path(), &k).unwrap();
        writer.write(&tiny_frame(0)).unwrap();
        writer.write(&tiny_frame(1)).unwrap();
        RgbImage::new(5, 3)
            .save(dir.path().join("frame-000001.color.png"))
            .unwrap();
        let ds = SevenScenes::open(dir.path(), FrameRange::ALL).unwrap();
        assert!(ds.load(0).is_ok());
        let err = ds.load(1).unwrap_err().to_string();
        assert!(
            err.contains("frame-000001.color.png") && err.contains("5x3"),
            "{err}"
        );
    }

    #[test]
    fn real_data_redkitchen_clock_and_poses_match_groundtruth_tum() {
        use metrics::ate::{Alignment, ate};
        let dir = crate::shared_data::require("datasets/7scenes-redkitchen");
        let ds = SevenScenes::open(&dir, FrameRange::ALL).unwrap();
        assert_eq!(ds.len(), 1000);
        assert_eq!(ds.intrinsics(), DEFAULT_INTRINSICS);
        let mut from_reader = geometry::trajectory::Trajectory::default();
        for i in 0..ds.len() {
            from_reader.push(ds.timestamp(i), ds.ground_truth(i).unwrap().unwrap());
        }
        let tum =
            geometry::trajectory::Trajectory::read_tum(&dir.join("groundtruth_tum.txt")).unwrap();
        let r = ate(&tum, &from_reader, Alignment::None, 1e-4).unwrap();
        assert_eq!(r.stats.pairs, 1000);
        assert!(
            r.stats.max < 1e-5,
            "reader poses differ from groundtruth_tum.txt by {} m",
            r.stats.max
        );
        let frame = ds.load(500).unwrap();
        assert_eq!((frame.rgb.width(), frame.depth.height), (640, 480));
        let valid = frame.depth.valid_count() as f64 / frame.depth.data.len() as f64;
        assert!(
            valid > 0.5 && frame.depth.data.iter().all(|d| *d < 65.0),
            "valid {valid}"
        );
    }
}
