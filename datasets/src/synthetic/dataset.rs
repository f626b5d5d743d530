//! The synthetic scene as a [`Dataset`]: frames rendered on demand, without touching disk.

use image::RgbImage;
use nalgebra::Isometry3;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use geometry::files::DatasetError;

use crate::{Dataset, Frame, FrameRange};

use super::render::render;
use super::scene::Scene;
use super::spec::{FRAMES_PER_SECOND, SyntheticSpec};
use super::walk::trajectory;

/// One agent's synthetic sequence, rendered on demand.
pub struct SyntheticDataset {
    pub(super) spec: SyntheticSpec,
    pub(super) intrinsics: Intrinsics,
    pub(super) scene: Scene,
    /// Ground truth of every frame 0..frames (not only the selected ones).
    pub(super) trajectory: Vec<Isometry3<f64>>,
    /// Frame numbers selected by the range.
    pub(super) numbers: Vec<usize>,
}

impl SyntheticDataset {
    /// The sequence `spec` describes, limited to the frame numbers in `range`. Builds the scene and
    /// the whole trajectory; frames are rendered as they load. Fails when `spec` is out of range
    /// ([`SyntheticSpec::validate`]) or `range` selects none of its frames.
    pub fn new(spec: SyntheticSpec, range: FrameRange) -> Result<Self, DatasetError> {
        spec.validate()
            .map_err(|reason| DatasetError::Invalid(format!("synthetic spec {spec}: {reason}")))?;
        let numbers: Vec<usize> = (0..spec.frames).filter(|&n| range.contains(n)).collect();
        if numbers.is_empty() {
            return Err(DatasetError::Invalid(format!(
                "{spec}: frame range {range} selects none of its frames 0..{}",
                spec.frames
            )));
        }
        Ok(Self {
            spec,
            intrinsics: spec.intrinsics(),
            scene: Scene::generate(spec.seed),
            trajectory: trajectory(&spec),
            numbers,
        })
    }

    /// The spec the sequence was made from.
    pub fn spec(&self) -> &SyntheticSpec {
        &self.spec
    }

    /// Renders an arbitrary view of the scene (e.g. for visual checks), returning RGB and depth.
    pub fn render_view(&self, world_from_camera: &Isometry3<f64>) -> (RgbImage, DepthImage) {
        render(&self.scene, &self.intrinsics, world_from_camera)
    }
}

impl Dataset for SyntheticDataset {
    fn describe(&self) -> String {
        format!("synthetic scene ({})", self.spec)
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn len(&self) -> usize {
        self.numbers.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.numbers[position]
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.numbers[position] as f64 / FRAMES_PER_SECOND
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(Some(self.trajectory[self.numbers[position]]))
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let number = self.numbers[position];
        let pose = self.trajectory[number];
        let (rgb, depth) = render(&self.scene, &self.intrinsics, &pose);
        Ok(Frame {
            index: number,
            timestamp: self.timestamp(position),
            rgb,
            depth,
            world_from_camera_gt: Some(pose),
            ground_truth_error: None,
            colour_offset_s: 0.0,
            intrinsics: self.intrinsics,
        })
    }
}
