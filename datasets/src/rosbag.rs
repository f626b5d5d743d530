//! ROS 2 bags as a dataset: a rosbag2 folder or a `.mcap` / `.db3` file read by path, frames made
//! of a colour topic and a depth topic paired by header stamp, intrinsics and lens from the colour
//! topic's CameraInfo, ground truth (when the bag has it) from a pose topic or from tf.
//!
//! Which topics ([`Ros2Config`], the `[ros2]` configuration section): by default those of the
//! realsense2_camera driver with aligned depth; each name is tried raw and with its
//! image_transport suffix (`/compressed`, `/compressedDepth`). A bag without them is searched for
//! one colour and one depth image topic (a name with "depth" in it is depth). A depth topic must be
//! registered to colour: its images' frame must be the colour images' frame. When the depth topic
//! has a CameraInfo of its own (its sibling `camera_info`) with another K, the depth images are
//! that pinhole in the colour camera's frame, as a Kinect's registered depth is
//! ([`crate::undistort::DepthRegistration::Pinhole`]).
//!
//! Frames: each colour image with the depth image nearest in stamp, within
//! `pairing_tolerance_s`, numbered 0, 1, 2, ... in stamp order (frame ranges select these
//! numbers); the timestamp is the colour image's header stamp (its receive time when the stamp is
//! zero). Ground truth is the pose of the colour camera's optical frame in the world, nearest in
//! stamp within the same tolerance. The section also names the frames and topics of the outputs
//! written for ROS users (the agent's and the consensus's `ros2_bag/`). A bag damaged part way ([`ros2::bag::Damage`]) gives the frames
//! before the damage, and says where it broke ([`Dataset::damage`]).

use std::path::Path;

use geometry::camera::Intrinsics;
use geometry::distortion::Distortion;
use geometry::files::DatasetError;
use nalgebra::Isometry3;
use ros2::bag::{Bag, BagError, MessageRef};
use ros2::msg::{self, type_names};
use serde::{Deserialize, Serialize};

use crate::undistort::DepthRegistration;
use crate::{Dataset, Frame, FrameRange};

/// The `[ros2]` configuration section: which topics carry the camera and the ground truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ros2Config {
    /// Prefix of the topic names below (`/robot0`); empty for none.
    pub namespace: String,
    /// Colour images (`sensor_msgs/Image`, or `CompressedImage` at `<topic>/compressed`).
    pub colour_topic: String,
    /// Depth images registered to colour (`Image` 16UC1 / 32FC1, or `CompressedImage` at
    /// `<topic>/compressedDepth`).
    pub depth_topic: String,
    /// The colour camera's `sensor_msgs/CameraInfo`.
    pub camera_info_topic: String,
    /// Ground truth: a `geometry_msgs/PoseStamped` or `nav_msgs/Odometry` topic, or
    /// `tf:CHILD_FRAME` (the transform to CHILD_FRAME on `/tf`). Empty: the bag's only pose or
    /// odometry topic if it has exactly one, else none.
    pub ground_truth: String,
    /// Largest stamp difference between a colour image and its depth image (and its ground
    /// truth), seconds.
    pub pairing_tolerance_s: f64,
    /// Outputs: the frame all agents share (REP 105's map frame).
    pub world_frame: String,
    /// Outputs: agent K's frames are `<prefix>K/odom` and `<prefix>K/camera_optical_frame`, its
    /// topics `/<prefix>K/path` and `/<prefix>K/map`.
    pub frame_prefix: String,
    /// Outputs: most points of a map's PointCloud2 (every k-th Gaussian beyond it).
    pub cloud_max_points: usize,
    /// Live topics: the DDS domain; unset: `ROS_DOMAIN_ID`, else 0 (as ROS 2 itself).
    pub domain_id: Option<u16>,
    /// Live topics: subscribe reliably (matches reliable publishers only); false: best effort,
    /// which matches both kinds (a sensor-data publisher too).
    pub reliable: bool,
    /// Live topics: paired frames waiting for the agent at most; beyond it the oldest is
    /// dropped and counted (1: the agent always gets the newest pair).
    pub queue_pairs: usize,
    /// Live topics: how long to wait for the camera's first CameraInfo before giving up.
    pub wait_for_camera_s: f64,
    /// Live topics: the run ends after this long without a frame (0: only on Ctrl-C / SIGTERM).
    pub idle_timeout_s: f64,
    /// Live topics: frames kept in memory for the map evaluation at most (evenly spaced; about
    /// 2 MB each at 640x480).
    pub evaluation_frames: usize,
    /// Live outputs: publish tf, the path and the map over DDS while the agent runs (topics as
    /// in its bag), for rviz2.
    pub publish: bool,
    /// Live outputs: the map's PointCloud2 at most this often, seconds.
    pub publish_map_every_s: f64,
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            namespace: String::new(),
            colour_topic: "/camera/camera/color/image_raw".into(),
            depth_topic: "/camera/camera/aligned_depth_to_color/image_raw".into(),
            camera_info_topic: "/camera/camera/color/camera_info".into(),
            ground_truth: String::new(),
            pairing_tolerance_s: 0.02,
            world_frame: "world".into(),
            frame_prefix: "agent".into(),
            cloud_max_points: 200_000,
            domain_id: None,
            reliable: false,
            queue_pairs: 1,
            wait_for_camera_s: 30.0,
            idle_timeout_s: 10.0,
            evaluation_frames: 100,
            publish: false,
            publish_map_every_s: 2.0,
        }
    }
}

impl Ros2Config {
    /// Checks the section; returns the offending field and why.
    pub fn validate(&self) -> Result<(), geometry::checks::FieldError> {
        if !(self.pairing_tolerance_s.is_finite() && self.pairing_tolerance_s > 0.0) {
            return Err((
                "ros2.pairing_tolerance_s",
                format!(
                    "must be a positive number of seconds, got {}",
                    self.pairing_tolerance_s
                ),
            ));
        }
        for (field, seconds) in [
            ("ros2.wait_for_camera_s", self.wait_for_camera_s),
            ("ros2.idle_timeout_s", self.idle_timeout_s),
            ("ros2.publish_map_every_s", self.publish_map_every_s),
        ] {
            if !(seconds.is_finite() && seconds >= 0.0) {
                return Err((field, format!("must be seconds, 0 or more, got {seconds}")));
            }
        }
        if self.queue_pairs == 0 {
            return Err(("ros2.queue_pairs", "must be at least 1".into()));
        }
        if self.evaluation_frames == 0 {
            return Err(("ros2.evaluation_frames", "must be at least 1".into()));
        }
        if self.cloud_max_points == 0 {
            return Err(("ros2.cloud_max_points", "must be at least 1".into()));
        }
        for (field, topic) in [
            ("ros2.colour_topic", &self.colour_topic),
            ("ros2.depth_topic", &self.depth_topic),
            ("ros2.camera_info_topic", &self.camera_info_topic),
        ] {
            if !topic.starts_with('/') {
                return Err((
                    field,
                    format!("{topic:?} is not a topic name starting with /"),
                ));
            }
        }
        Ok(())
    }

    /// The DDS domain of live topics: `domain_id`, else `ROS_DOMAIN_ID`, else 0.
    pub fn domain_id(&self) -> u16 {
        self.domain_id
            .or_else(|| std::env::var("ROS_DOMAIN_ID").ok()?.trim().parse().ok())
            .unwrap_or(0)
    }

    /// `topic` under the namespace.
    pub fn qualified(&self, topic: &str) -> String {
        format!("{}{}", self.namespace.trim_end_matches('/'), topic)
    }
}

/// What the reader chose to read in a bag.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BagChoice {
    /// The colour image topic, namespace and any `/compressed` suffix included.
    pub colour_topic: String,
    /// The depth image topic, namespace and any `/compressedDepth` or `/compressed` suffix
    /// included.
    pub depth_topic: String,
    /// The colour camera's CameraInfo topic the intrinsics and lens come from.
    pub camera_info_topic: String,
    /// The depth topic's own CameraInfo, when the bag has one.
    pub depth_camera_info_topic: Option<String>,
    /// The ground-truth source (a topic, or `tf:CHILD`), when there is one.
    pub ground_truth: Option<String>,
}

struct Pair {
    number: usize,
    stamp: f64,
    /// The paired depth image's stamp.
    depth_stamp: f64,
    colour: usize,
    depth: usize,
    world_from_camera_gt: Option<Isometry3<f64>>,
}

/// A ROS 2 bag read as a sequence of RGB-D frames.
pub struct RosBag {
    bag: Bag,
    choice: BagChoice,
    pairs: Vec<Pair>,
    /// Pairs in the whole bag, before the frame range.
    pairs_in_bag: usize,
    intrinsics: Intrinsics,
    distortion: Option<Distortion>,
    depth_registration: DepthRegistration,
    ground_truth_poses: usize,
}

fn bag_error(error: BagError) -> DatasetError {
    match error {
        BagError::Io { path, source } => DatasetError::Io { path, source },
        BagError::Format { path, reason } => DatasetError::format(&path, None, reason),
    }
}

/// The header of any stamped message, read from its first bytes.
#[derive(Deserialize)]
struct Stamped {
    header: msg::Header,
}

impl RosBag {
    /// Opens the bag at `path` (a `.mcap` or `.db3` file, or a rosbag2 folder), chooses its topics
    /// ([`choose_topics`]), reads the intrinsics and lens from the first CameraInfo, pairs colour
    /// with depth (and ground truth) by stamp within `pairing_tolerance_s`, and keeps the pairs
    /// whose number is in `range`. No image is decoded. Fails when the bag cannot be read, the
    /// camera's topics cannot be told, the CameraInfo is unusable, the depth images' frame_id is
    /// not the colour images', or no pair is in `range`.
    pub fn open(path: &Path, range: FrameRange, config: &Ros2Config) -> Result<Self, DatasetError> {
        let bag = Bag::open(path).map_err(bag_error)?;
        let choice = choose_topics(&bag, config)?;
        let invalid = |reason: String| DatasetError::format(path, None, reason);
        let info: msg::CameraInfo = first_message(&bag, &choice.camera_info_topic)?;
        let intrinsics = intrinsics_of(&info)
            .map_err(|r| invalid(format!("{} message 0: {r}", choice.camera_info_topic)))?;
        let distortion = distortion_of(&info)
            .map_err(|r| invalid(format!("{} message 0: {r}", choice.camera_info_topic)))?;
        let depth_registration = match &choice.depth_camera_info_topic {
            Some(topic) => {
                let depth_info: msg::CameraInfo = first_message(&bag, topic)?;
                let depth_k = intrinsics_of(&depth_info)
                    .map_err(|r| invalid(format!("{topic} message 0: {r}")))?;
                if depth_info.k == info.k {
                    DepthRegistration::ColourGrid
                } else {
                    DepthRegistration::Pinhole(depth_k)
                }
            }
            None => DepthRegistration::ColourGrid,
        };
        let colour = stamped_messages(&bag, &choice.colour_topic)?;
        let depth = stamped_messages(&bag, &choice.depth_topic)?;
        if let (Some((_, c, _)), Some((_, d, _))) = (colour.first(), depth.first())
            && !c.is_empty()
            && !d.is_empty()
            && c != d
        {
            return Err(invalid(format!(
                "depth topic {} is in frame {d:?} but colour topic {} in {c:?}: depth must be \
                 registered to colour; record the driver's aligned depth ({}) instead",
                choice.depth_topic,
                choice.colour_topic,
                config.qualified(&Ros2Config::default().depth_topic)
            )));
        }
        let ground_truth = match &choice.ground_truth {
            Some(source) => ground_truth_poses(&bag, source)?,
            None => Vec::new(),
        };
        let gt_stamps: Vec<f64> = ground_truth.iter().map(|(t, _)| *t).collect();
        let depth_stamps: Vec<f64> = depth.iter().map(|(t, _, _)| *t).collect();
        let tolerance = config.pairing_tolerance_s;
        let mut pairs = Vec::new();
        for (stamp, _, colour_message) in &colour {
            let Some(d) = crate::tum::nearest(&depth_stamps, *stamp, tolerance) else {
                continue;
            };
            let gt = crate::tum::nearest(&gt_stamps, *stamp, tolerance).map(|j| ground_truth[j].1);
            pairs.push(Pair {
                number: pairs.len(),
                stamp: *stamp,
                depth_stamp: depth_stamps[d],
                colour: *colour_message,
                depth: depth[d].2,
                world_from_camera_gt: gt,
            });
        }
        let pairs_in_bag = pairs.len();
        pairs.retain(|p| range.contains(p.number));
        if pairs.is_empty() {
            return Err(invalid(format!(
                "no {} image has a {} image within {tolerance} s in frame range {range} \
                 ({} colour and {} depth messages)",
                choice.colour_topic,
                choice.depth_topic,
                colour.len(),
                depth.len()
            )));
        }
        Ok(Self {
            bag,
            choice,
            pairs,
            pairs_in_bag,
            intrinsics,
            distortion,
            depth_registration,
            ground_truth_poses: ground_truth.len(),
        })
    }

    /// The topics read.
    pub fn choice(&self) -> &BagChoice {
        &self.choice
    }

    /// The bag itself (its topics and messages).
    pub fn bag(&self) -> &Bag {
        &self.bag
    }

    /// Colour/depth pairs in the whole bag, before the frame range.
    pub fn pairs_in_bag(&self) -> usize {
        self.pairs_in_bag
    }

    /// Ground-truth poses the bag holds.
    pub fn ground_truth_poses(&self) -> usize {
        self.ground_truth_poses
    }

    fn message_error(&self, message: &MessageRef, reason: impl std::fmt::Display) -> DatasetError {
        DatasetError::format(
            self.bag.path(),
            None,
            format!(
                "{} message {}: {reason}",
                self.bag.topics()[message.topic].name,
                message.index_in_topic
            ),
        )
    }

    fn payload(&self, message: &MessageRef) -> Result<Vec<u8>, DatasetError> {
        self.bag
            .read(message)
            .map_err(|e| self.message_error(message, bag_error(e)))
    }

    fn check_size(
        &self,
        message: &MessageRef,
        (width, height): (u32, u32),
        expected: &Intrinsics,
    ) -> Result<(), DatasetError> {
        if (width, height) != (expected.width, expected.height) {
            return Err(self.message_error(
                message,
                format!(
                    "image is {width}x{height}, but its CameraInfo says {}x{}",
                    expected.width, expected.height
                ),
            ));
        }
        Ok(())
    }

    fn colour(&self, message: &MessageRef) -> Result<image::RgbImage, DatasetError> {
        let payload = self.payload(message)?;
        let fail = |e: &dyn std::fmt::Display| self.message_error(message, e);
        let rgb = match self.bag.topics()[message.topic].type_name.as_str() {
            type_names::IMAGE => {
                let image: msg::Image = msg::decode(&payload).map_err(|e| fail(&e))?;
                ros2::image::colour_from_image(&image).map_err(|e| fail(&e))?
            }
            _ => {
                let image: msg::CompressedImage = msg::decode(&payload).map_err(|e| fail(&e))?;
                ros2::image::colour_from_compressed(&image).map_err(|e| fail(&e))?
            }
        };
        self.check_size(message, rgb.dimensions(), &self.intrinsics)?;
        Ok(rgb)
    }

    fn depth(&self, message: &MessageRef) -> Result<geometry::depth::DepthImage, DatasetError> {
        let payload = self.payload(message)?;
        let fail = |e: &dyn std::fmt::Display| self.message_error(message, e);
        let depth = match self.bag.topics()[message.topic].type_name.as_str() {
            type_names::IMAGE => {
                let image: msg::Image = msg::decode(&payload).map_err(|e| fail(&e))?;
                ros2::image::depth_from_image(&image).map_err(|e| fail(&e))?
            }
            _ => {
                let image: msg::CompressedImage = msg::decode(&payload).map_err(|e| fail(&e))?;
                ros2::image::depth_from_compressed(&image).map_err(|e| fail(&e))?
            }
        };
        let expected = match self.depth_registration {
            DepthRegistration::Pinhole(k) => k,
            DepthRegistration::ColourGrid => self.intrinsics,
        };
        self.check_size(message, (depth.width, depth.height), &expected)?;
        Ok(depth)
    }
}

impl Dataset for RosBag {
    fn describe(&self) -> String {
        format!(
            "ROS 2 bag at {} ({} + {})",
            self.bag.path().display(),
            self.choice.colour_topic,
            self.choice.depth_topic
        )
    }
    fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }
    fn depth_registration(&self) -> DepthRegistration {
        self.depth_registration
    }
    fn lens_distortion(&self) -> Option<Distortion> {
        self.distortion
    }
    fn damage(&self) -> Option<String> {
        self.bag.damage().map(|d| d.to_string())
    }
    fn len(&self) -> usize {
        self.pairs.len()
    }
    fn frame_index(&self, position: usize) -> usize {
        self.pairs[position].number
    }
    fn timestamp(&self, position: usize) -> f64 {
        self.pairs[position].stamp
    }
    fn ground_truth(&self, position: usize) -> Result<Option<Isometry3<f64>>, DatasetError> {
        Ok(self.pairs[position].world_from_camera_gt)
    }
    fn load(&self, position: usize) -> Result<Frame, DatasetError> {
        let pair = &self.pairs[position];
        let messages = self.bag.messages();
        let rgb = self.colour(&messages[pair.colour])?;
        let depth = self.depth(&messages[pair.depth])?;
        Ok(Frame {
            index: pair.number,
            timestamp: pair.stamp,
            rgb,
            depth,
            world_from_camera_gt: pair.world_from_camera_gt,
            ground_truth_error: None,
            colour_offset_s: pair.stamp - pair.depth_stamp,
            intrinsics: self.intrinsics,
        })
    }
}

/// True when `spec` names a bag (a `.mcap` / `.db3` file, or a folder of them).
pub fn is_bag(spec: &str) -> bool {
    ros2::bag::metadata::is_bag(Path::new(spec))
}

/// Picks the topics to read (see the module documentation).
pub fn choose_topics(bag: &Bag, config: &Ros2Config) -> Result<BagChoice, DatasetError> {
    let path = bag.path();
    let has = |name: &str, types: &[&str]| {
        bag.topics()
            .iter()
            .any(|t| t.name == name && types.contains(&t.type_name.as_str()))
    };
    let image_types = [type_names::IMAGE, type_names::COMPRESSED_IMAGE];
    let first_present = |base: &str, suffixes: &[&str]| {
        suffixes
            .iter()
            .map(|suffix| format!("{base}{suffix}"))
            .find(|name| has(name, &image_types))
    };
    let colour = first_present(
        &config.qualified(&config.colour_topic),
        &["", "/compressed"],
    );
    let depth = first_present(
        &config.qualified(&config.depth_topic),
        &["", "/compressedDepth", "/compressed"],
    );
    let (colour, depth) = match (colour, depth) {
        (Some(colour), Some(depth)) => (colour, depth),
        (colour, depth) => {
            // No configured topics: one colour and one depth image topic, if that is all there is.
            let images: Vec<&str> = bag
                .topics()
                .iter()
                .filter(|t| image_types.contains(&t.type_name.as_str()))
                .map(|t| t.name.as_str())
                .collect();
            let (depths, colours): (Vec<&str>, Vec<&str>) =
                images.iter().partition(|name| name.contains("depth"));
            match (colour, depth, colours.as_slice(), depths.as_slice()) {
                (Some(colour), None, _, [depth]) => (colour, depth.to_string()),
                (None, Some(depth), [colour], _) => (colour.to_string(), depth),
                (None, None, [colour], [depth]) => (colour.to_string(), depth.to_string()),
                _ => {
                    return Err(DatasetError::format(
                        path,
                        None,
                        format!(
                            "cannot tell which topics are the camera: no {} and {} (nor their \
                             /compressed, /compressedDepth variants); its image topics are [{}]. \
                             Set ros2.colour_topic and ros2.depth_topic (and ros2.namespace)",
                            config.qualified(&config.colour_topic),
                            config.qualified(&config.depth_topic),
                            images.join(", ")
                        ),
                    ));
                }
            }
        }
    };
    let info_types = [type_names::CAMERA_INFO];
    let sibling_info = camera_info_beside;
    let mut info_candidates = vec![config.qualified(&config.camera_info_topic)];
    if !info_candidates.contains(&sibling_info(&colour)) {
        info_candidates.push(sibling_info(&colour));
    }
    let camera_info_topic = info_candidates
        .iter()
        .find(|name| has(name, &info_types))
        .cloned()
        .ok_or_else(|| {
            DatasetError::format(
                path,
                None,
                format!(
                    "no sensor_msgs/CameraInfo on {}: the intrinsics come from the colour \
                     camera's CameraInfo (set ros2.camera_info_topic)",
                    info_candidates.join(" or ")
                ),
            )
        })?;
    let depth_info = sibling_info(&depth);
    let depth_camera_info_topic =
        (depth_info != camera_info_topic && has(&depth_info, &info_types)).then_some(depth_info);
    let ground_truth = if config.ground_truth.is_empty() {
        let poses: Vec<&str> = bag
            .topics()
            .iter()
            .filter(|t| {
                [type_names::POSE_STAMPED, type_names::ODOMETRY].contains(&t.type_name.as_str())
            })
            .map(|t| t.name.as_str())
            .collect();
        match poses.as_slice() {
            [only] => Some(only.to_string()),
            _ => None,
        }
    } else if let Some(child) = config.ground_truth.strip_prefix("tf:") {
        Some(format!("tf:{child}"))
    } else {
        let topic = config.qualified(&config.ground_truth);
        let pose_types = [type_names::POSE_STAMPED, type_names::ODOMETRY];
        if !has(&topic, &pose_types) {
            return Err(DatasetError::format(
                path,
                None,
                format!(
                    "ros2.ground_truth names {topic}, which is not a PoseStamped or Odometry \
                     topic of this bag"
                ),
            ));
        }
        Some(topic)
    };
    Ok(BagChoice {
        colour_topic: colour,
        depth_topic: depth,
        camera_info_topic,
        depth_camera_info_topic,
        ground_truth,
    })
}

fn topic_messages<'a>(bag: &'a Bag, topic: &str) -> impl Iterator<Item = (usize, &'a MessageRef)> {
    let wanted = bag.topic(topic);
    bag.messages()
        .iter()
        .enumerate()
        .filter(move |(_, m)| Some(m.topic) == wanted)
}

/// The first message on `topic`, decoded.
fn first_message<T: for<'de> Deserialize<'de>>(bag: &Bag, topic: &str) -> Result<T, DatasetError> {
    let (_, message) = topic_messages(bag, topic)
        .next()
        .ok_or_else(|| DatasetError::format(bag.path(), None, format!("{topic} has no message")))?;
    let payload = bag.read(message).map_err(bag_error)?;
    msg::decode(&payload)
        .map_err(|e| DatasetError::format(bag.path(), None, format!("{topic} message 0: {e}")))
}

/// (stamp s, frame id, message position) of every message on an image topic, in stamp order.
fn stamped_messages(bag: &Bag, topic: &str) -> Result<Vec<(f64, String, usize)>, DatasetError> {
    let mut stamped = Vec::new();
    for (position, message) in topic_messages(bag, topic) {
        let header: Stamped = msg::decode_prefix(&message.head).map_err(|e| {
            DatasetError::format(
                bag.path(),
                None,
                format!("{topic} message {}: {e}", message.index_in_topic),
            )
        })?;
        let stamp = if header.header.stamp.is_zero() {
            message.log_time_ns as f64 * 1e-9
        } else {
            header.header.stamp.seconds()
        };
        stamped.push((stamp, header.header.frame_id, position));
    }
    stamped.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(stamped)
}

/// (stamp, world_from_child) of the ground-truth source, in stamp order.
fn ground_truth_poses(bag: &Bag, source: &str) -> Result<Vec<(f64, Isometry3<f64>)>, DatasetError> {
    let error = |topic: &str, index: usize, e: &dyn std::fmt::Display| {
        DatasetError::format(bag.path(), None, format!("{topic} message {index}: {e}"))
    };
    let mut poses = Vec::new();
    if let Some(child) = source.strip_prefix("tf:") {
        for (_, message) in topic_messages(bag, "/tf") {
            let payload = bag.read(message).map_err(bag_error)?;
            let tf: msg::TfMessage =
                msg::decode(&payload).map_err(|e| error("/tf", message.index_in_topic, &e))?;
            for transform in tf.transforms.iter().filter(|t| t.child_frame_id == child) {
                poses.push((
                    transform.header.stamp.seconds(),
                    msg::isometry(
                        transform.transform.translation,
                        transform.transform.rotation,
                    ),
                ));
            }
        }
        if poses.is_empty() {
            return Err(DatasetError::format(
                bag.path(),
                None,
                format!("ros2.ground_truth is tf:{child}, but /tf has no transform to {child}"),
            ));
        }
    } else {
        let odometry = bag
            .topic(source)
            .is_some_and(|t| bag.topics()[t].type_name == type_names::ODOMETRY);
        for (_, message) in topic_messages(bag, source) {
            let payload = bag.read(message).map_err(bag_error)?;
            let (header, pose) = if odometry {
                let o: msg::Odometry =
                    msg::decode(&payload).map_err(|e| error(source, message.index_in_topic, &e))?;
                (o.header, o.pose.pose)
            } else {
                let p: msg::PoseStamped =
                    msg::decode(&payload).map_err(|e| error(source, message.index_in_topic, &e))?;
                (p.header, p.pose)
            };
            poses.push((
                header.stamp.seconds(),
                msg::isometry(pose.position, pose.orientation),
            ));
        }
    }
    poses.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(poses)
}

/// The pinhole of a CameraInfo (its K, at its image size).
pub(crate) fn intrinsics_of(info: &msg::CameraInfo) -> Result<Intrinsics, String> {
    let k = &info.k;
    let intrinsics = Intrinsics::new(k[0], k[4], k[2], k[5], info.width, info.height);
    intrinsics.validate().map_err(|reason| {
        format!(
            "CameraInfo K {k:?} at {}x{}: {reason}",
            info.width, info.height
        )
    })?;
    Ok(intrinsics)
}

/// The lens of a CameraInfo: plumb_bob coefficients, none when all are zero; other models with
/// non-zero coefficients are refused.
pub(crate) fn distortion_of(info: &msg::CameraInfo) -> Result<Option<Distortion>, String> {
    if info.d.iter().all(|c| *c == 0.0) {
        return Ok(None);
    }
    if info.distortion_model != "plumb_bob" || info.d.len() > 5 {
        return Err(format!(
            "distortion model {:?} with coefficients {:?}: this reader undistorts plumb_bob \
             (k1 k2 t1 t2 k3) only",
            info.distortion_model, info.d
        ));
    }
    let mut coefficients = [0.0; 5];
    coefficients[..info.d.len()].copy_from_slice(&info.d);
    let distortion = Distortion::from_coefficients(coefficients);
    distortion.validate()?;
    Ok(Some(distortion))
}

/// The CameraInfo topic beside an image topic, as image_transport lays them out:
/// `/a/b/image_raw` and `/a/b/image_raw/compressedDepth` give `/a/b/camera_info`.
pub(crate) fn camera_info_beside(image_topic: &str) -> String {
    let base = image_topic
        .trim_end_matches("/compressedDepth")
        .trim_end_matches("/compressed");
    let parent = &base[..base.rfind('/').unwrap_or(0)];
    format!("{parent}/camera_info")
}
