//! What goes on the live view's queue, and how the background thread logs it to rerun (entity
//! paths in [`crate::paths`]).

use std::collections::BTreeMap;
use std::io::Cursor;

use geometry::camera::Intrinsics;
use image::RgbImage;
use nalgebra::Isometry3;
use rerun::RecordingStream;

use crate::handle::LiveViewSettings;
use crate::paths;
use crate::points::{BoundedPoints, ColouredPoints};

/// How the consensus decided a closure attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClosureOutcome {
    /// Verified and kept by the pose graph.
    Accepted,
    /// Verified by alignment, then dropped by the pose graph.
    DroppedByPoseGraph,
    /// Refused by alignment.
    Rejected,
}

impl ClosureOutcome {
    fn colour(self) -> rerun::Color {
        match self {
            Self::Accepted => rerun::Color::from_rgb(40, 200, 60),
            Self::DroppedByPoseGraph => rerun::Color::from_rgb(240, 150, 20),
            Self::Rejected => rerun::Color::from_rgb(220, 40, 40),
        }
    }
}

/// One closure attempt, as a line between the two keyframes' positions (world frame where the
/// consensus has placed their agents).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClosureLine {
    /// The source keyframe's camera position, metres: in the world when the consensus has
    /// placed it, else in its agent's frame.
    pub from: [f64; 3],
    /// The target keyframe's camera position, in the same way.
    pub to: [f64; 3],
    /// What became of the attempt; it gives the line's colour.
    pub outcome: ClosureOutcome,
}

/// One item of the queue.
pub(crate) enum Item {
    Frame(Box<FrameItem>),
    Keyframe {
        agent_id: u32,
        world_from_camera: Isometry3<f64>,
    },
    MapPoints {
        agent_id: u32,
        points: ColouredPoints,
        /// The agent's final map: replaces what was accumulated.
        is_final: bool,
    },
    AgentPlacement {
        agent_id: u32,
        world_from_agent: Isometry3<f64>,
    },
    Closures(Vec<ClosureLine>),
    ConsensusTrajectories(BTreeMap<u32, Vec<[f64; 3]>>),
    MergedMap(ColouredPoints),
    Scalar {
        path: String,
        value: f64,
    },
}

pub(crate) struct FrameItem {
    pub agent_id: u32,
    pub frame_index: usize,
    pub world_from_camera: Isometry3<f64>,
    pub intrinsics: Intrinsics,
    /// Only on the frames that show their image (`image_every`).
    pub rgb: Option<RgbImage>,
}

/// What the background thread keeps between items (the accumulated trajectories, keyframes and
/// maps), and the stream it logs to.
pub(crate) struct Recorder {
    stream: RecordingStream,
    settings: LiveViewSettings,
    trajectories: BTreeMap<u32, Vec<[f32; 3]>>,
    keyframes: BTreeMap<u32, Vec<[f32; 3]>>,
    maps: BTreeMap<u32, BoundedPoints>,
    /// When each agent's map was last logged.
    map_logged: BTreeMap<u32, std::time::Instant>,
}

impl Recorder {
    pub fn new(stream: RecordingStream, settings: LiveViewSettings) -> Self {
        Self {
            stream,
            settings,
            trajectories: BTreeMap::new(),
            keyframes: BTreeMap::new(),
            maps: BTreeMap::new(),
            map_logged: BTreeMap::new(),
        }
    }

    pub fn stream(&self) -> &RecordingStream {
        &self.stream
    }

    /// The world frame is the first camera frame of agent 0 (x right, y down, z forward, as every
    /// camera here): said once, so that the viewer shows the floor below and not above.
    pub fn log_world_axes(&self) -> rerun::RecordingStreamResult<()> {
        self.stream
            .log_static(paths::WORLD, &rerun::ViewCoordinates::RDF())
    }

    pub fn log(&mut self, item: Item) -> rerun::RecordingStreamResult<()> {
        match item {
            Item::Frame(frame) => self.frame(*frame),
            Item::Keyframe {
                agent_id,
                world_from_camera,
            } => {
                let positions = self.keyframes.entry(agent_id).or_default();
                positions.push(position(&world_from_camera));
                self.stream.log(
                    paths::agent_keyframes(agent_id),
                    &rerun::Points3D::new(positions.iter().copied())
                        .with_radii([0.03])
                        .with_colors([rerun::Color::from_rgb(60, 140, 255)]),
                )
            }
            Item::MapPoints {
                agent_id,
                points,
                is_final,
            } => self.map(agent_id, points, is_final),
            Item::AgentPlacement {
                agent_id,
                world_from_agent,
            } => self
                .stream
                .log(paths::agent(agent_id), &transform(&world_from_agent)),
            Item::Closures(lines) => self.stream.log(
                paths::CONSENSUS_CLOSURES,
                &rerun::LineStrips3D::new(lines.iter().map(|l| [to_f32(l.from), to_f32(l.to)]))
                    .with_colors(lines.iter().map(|l| l.outcome.colour())),
            ),
            Item::ConsensusTrajectories(trajectories) => {
                for (agent_id, positions) in trajectories {
                    self.stream.log(
                        paths::consensus_trajectory(agent_id),
                        &rerun::LineStrips3D::new([positions.into_iter().map(to_f32)]),
                    )?;
                }
                Ok(())
            }
            Item::MergedMap(points) => self.stream.log(paths::CONSENSUS_MAP, &points3d(&points)),
            Item::Scalar { path, value } => self.stream.log(path, &rerun::Scalars::single(value)),
        }
    }

    /// Logs every accumulated map that changed since it was last logged (at the end of a run).
    pub fn log_pending_maps(&mut self) -> rerun::RecordingStreamResult<()> {
        let agents: Vec<u32> = self.maps.keys().copied().collect();
        for agent_id in agents {
            self.log_map(agent_id)?;
        }
        Ok(())
    }

    fn frame(&mut self, frame: FrameItem) -> rerun::RecordingStreamResult<()> {
        let agent_id = frame.agent_id;
        self.stream
            .set_time_sequence(paths::FRAME_TIMELINE, frame.frame_index as i64);
        let camera = paths::agent_camera(agent_id);
        self.stream
            .log(camera.as_str(), &transform(&frame.world_from_camera))?;
        if let Some(rgb) = &frame.rgb {
            let (image, factor) = binned(rgb, self.settings.image_max_width);
            let k = &frame.intrinsics;
            let scale = 1.0 / factor as f32;
            self.stream.log(
                camera.as_str(),
                &rerun::Pinhole::from_focal_length_and_resolution(
                    [k.fx as f32 * scale, k.fy as f32 * scale],
                    [image.width() as f32, image.height() as f32],
                )
                .with_principal_point([k.cx as f32 * scale, k.cy as f32 * scale])
                .with_image_plane_distance(0.2),
            )?;
            if let Some(image) = encoded(&image) {
                self.stream.log(camera.as_str(), &image)?;
            }
        }
        let trajectory = self.trajectories.entry(agent_id).or_default();
        trajectory.push(position(&frame.world_from_camera));
        if trajectory
            .len()
            .is_multiple_of(self.settings.trajectory_every_frames)
        {
            self.log_trajectory(agent_id)?;
        }
        Ok(())
    }

    fn log_trajectory(&self, agent_id: u32) -> rerun::RecordingStreamResult<()> {
        let Some(trajectory) = self.trajectories.get(&agent_id) else {
            return Ok(());
        };
        self.stream.log(
            paths::agent_trajectory(agent_id),
            &rerun::LineStrips3D::new([trajectory.iter().copied()])
                .with_colors([rerun::Color::from_rgb(255, 220, 0)]),
        )
    }

    /// Every trajectory as it stands (at the end of a run).
    pub fn log_trajectories(&self) -> rerun::RecordingStreamResult<()> {
        for agent_id in self.trajectories.keys() {
            self.log_trajectory(*agent_id)?;
        }
        Ok(())
    }

    fn map(
        &mut self,
        agent_id: u32,
        points: ColouredPoints,
        is_final: bool,
    ) -> rerun::RecordingStreamResult<()> {
        let max_points = self.settings.map_points_max;
        let map = self
            .maps
            .entry(agent_id)
            .or_insert_with(|| BoundedPoints::new(max_points));
        if is_final {
            *map = BoundedPoints::new(max_points);
        }
        map.extend(&points);
        let due = self
            .map_logged
            .get(&agent_id)
            .is_none_or(|at| at.elapsed() >= self.settings.map_interval);
        if is_final || due {
            self.log_map(agent_id)?;
        }
        Ok(())
    }

    fn log_map(&mut self, agent_id: u32) -> rerun::RecordingStreamResult<()> {
        let Some(map) = self.maps.get(&agent_id) else {
            return Ok(());
        };
        self.map_logged.insert(agent_id, std::time::Instant::now());
        self.stream
            .log(paths::agent_map(agent_id), &points3d(map.points()))
    }
}

fn points3d(points: &ColouredPoints) -> rerun::Points3D {
    rerun::Points3D::new(points.positions.iter().copied())
        .with_colors(
            points
                .colours
                .iter()
                .map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])),
        )
        .with_radii([0.01])
}

fn transform(pose: &Isometry3<f64>) -> rerun::Transform3D {
    let q = pose.rotation.coords;
    rerun::Transform3D::from_translation_rotation(
        position(pose),
        rerun::Quaternion::from_xyzw([q.x as f32, q.y as f32, q.z as f32, q.w as f32]),
    )
}

fn position(pose: &Isometry3<f64>) -> [f32; 3] {
    let t = pose.translation.vector;
    [t.x as f32, t.y as f32, t.z as f32]
}

fn to_f32(p: [f64; 3]) -> [f32; 3] {
    p.map(|v| v as f32)
}

/// The image binned by the smallest integer factor that makes it at most `max_width` wide
/// (mean of each factor x factor block), and the factor.
fn binned(rgb: &RgbImage, max_width: u32) -> (RgbImage, u32) {
    let factor = rgb.width().div_ceil(max_width.max(1)).max(1);
    if factor == 1 {
        return (rgb.clone(), 1);
    }
    let (width, height) = (rgb.width() / factor, rgb.height() / factor);
    let binned = RgbImage::from_fn(width, height, |x, y| {
        let mut sum = [0u32; 3];
        for dy in 0..factor {
            for dx in 0..factor {
                let pixel = rgb.get_pixel(x * factor + dx, y * factor + dy);
                for (total, value) in sum.iter_mut().zip(pixel.0) {
                    *total += value as u32;
                }
            }
        }
        image::Rgb(sum.map(|s| (s / (factor * factor)) as u8))
    });
    (binned, factor)
}

/// JPEG, so that a recording of images stays small (a raw 160x120 frame is 57 kB).
/// An in-memory JPEG of a valid image does not fail; should it, the frame shows no image.
fn encoded(image: &RgbImage) -> Option<rerun::EncodedImage> {
    let mut bytes = Vec::new();
    let written =
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut Cursor::new(&mut bytes), 80)
            .encode_image(image);
    match written {
        Ok(()) => Some(rerun::EncodedImage::from_file_contents(bytes)),
        Err(error) => {
            tracing::debug!(%error, "live view: frame image not encoded");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binning_averages_blocks_to_the_width_bound() {
        let rgb = RgbImage::from_fn(640, 480, |x, _| image::Rgb([(x % 2 * 200) as u8, 10, 20]));
        let (binned, factor) = binned(&rgb, 160);
        assert_eq!(factor, 4);
        assert_eq!((binned.width(), binned.height()), (160, 120));
        assert_eq!(binned.get_pixel(5, 5).0, [100, 10, 20]);
        assert_eq!(self::binned(&rgb, 640).1, 1);
    }
}
