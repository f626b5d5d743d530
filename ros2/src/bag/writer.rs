//! Writes rosbag2 bags in MCAP storage: a folder with the `.mcap` file and its metadata.yaml, the
//! schemas as ROS 2 message definitions (`ros2msg`, what `ros2 bag play`, Foxglove and rosbags
//! need to decode the messages), CDR payloads. The file is written to a temporary name and renamed
//! when finished, so a bag that is there is whole.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::BagError;
use crate::msg;

/// `.msg` definitions of the types this writer writes and of what they contain.
const DEFINITIONS: &[(&str, &str)] = &[
    ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"),
    (
        "std_msgs/Header",
        "builtin_interfaces/Time stamp\nstring frame_id\n",
    ),
    ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
    (
        "geometry_msgs/Quaternion",
        "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    ),
    (
        "geometry_msgs/Pose",
        "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    ),
    (
        "geometry_msgs/PoseStamped",
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    ),
    (
        "geometry_msgs/Transform",
        "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    ),
    (
        "geometry_msgs/TransformStamped",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
    ),
    (
        "tf2_msgs/TFMessage",
        "geometry_msgs/TransformStamped[] transforms\n",
    ),
    (
        "nav_msgs/Path",
        "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    ),
    (
        "sensor_msgs/PointField",
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n\
         uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n\
         string name\nuint32 offset\nuint8 datatype\nuint32 count\n",
    ),
    (
        "sensor_msgs/PointCloud2",
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n\
         bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
    ),
];

/// The `ros2msg` schema text of `type_name` (`pkg/msg/Type`): its definition, then each type it
/// uses (depth first, once) after a separator line and `MSG: pkg/Type`.
pub fn schema_text(type_name: &str) -> Option<String> {
    let short = type_name.replace("/msg/", "/");
    let definition = |name: &str| DEFINITIONS.iter().find(|(n, _)| *n == name).map(|d| d.1);
    let mut text = definition(&short)?.to_string();
    let mut done = vec![short.clone()];
    let mut pending: Vec<String> = Vec::new();
    let uses = |body: &str| -> Vec<String> {
        body.lines()
            .filter_map(|line| line.split_whitespace().next())
            .map(|field_type| field_type.trim_end_matches("[]").to_string())
            .filter(|field_type| field_type.contains('/'))
            .collect()
    };
    pending.extend(uses(&text).into_iter().rev());
    while let Some(name) = pending.pop() {
        if done.contains(&name) {
            continue;
        }
        let body = definition(&name)?;
        text.push_str(&format!("{}\nMSG: {name}\n{body}", "=".repeat(80)));
        done.push(name);
        pending.extend(uses(body).into_iter().rev());
    }
    Some(text)
}

/// A bag being written.
pub struct BagWriter {
    folder: PathBuf,
    file_name: String,
    writer: mcap::Writer<BufWriter<File>>,
    channels: BTreeMap<String, (u16, String, usize)>,
    first_ns: Option<u64>,
    last_ns: u64,
}

impl BagWriter {
    /// Starts a bag in `folder` (created; a bag already there is replaced when finished).
    pub fn create(folder: &Path) -> Result<Self, BagError> {
        std::fs::create_dir_all(folder).map_err(|e| BagError::io(folder, e))?;
        let name = folder
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "bag".into());
        let file_name = format!("{name}_0.mcap");
        let partial = folder.join(format!("{file_name}.partial"));
        let file = File::create(&partial).map_err(|e| BagError::io(&partial, e))?;
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library("mac-ego3d")
            .compression(Some(mcap::Compression::Zstd));
        let writer = options
            .create(BufWriter::new(file))
            .map_err(|e| BagError::format(&partial, e.to_string()))?;
        Ok(Self {
            folder: folder.to_path_buf(),
            file_name,
            writer,
            channels: BTreeMap::new(),
            first_ns: None,
            last_ns: 0,
        })
    }

    fn partial(&self) -> PathBuf {
        self.folder.join(format!("{}.partial", self.file_name))
    }

    /// Writes `message` of ROS 2 type `type_name` on `topic`, received at `stamp_s`.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        type_name: &str,
        stamp_s: f64,
        message: &T,
    ) -> Result<(), BagError> {
        let path = self.partial();
        let failed = |e: mcap::McapError| BagError::format(&path, e.to_string());
        let channel = match self.channels.get_mut(topic) {
            Some((channel, _, count)) => {
                *count += 1;
                *channel
            }
            None => {
                let schema = schema_text(type_name).ok_or_else(|| {
                    BagError::format(&path, format!("no message definition for {type_name}"))
                })?;
                let schema_id = self
                    .writer
                    .add_schema(type_name, "ros2msg", schema.as_bytes())
                    .map_err(failed)?;
                let channel = self
                    .writer
                    .add_channel(schema_id, topic, "cdr", &BTreeMap::new())
                    .map_err(failed)?;
                self.channels
                    .insert(topic.to_string(), (channel, type_name.to_string(), 1));
                channel
            }
        };
        let log_time = (stamp_s.max(0.0) * 1e9).round() as u64;
        self.first_ns = Some(self.first_ns.map_or(log_time, |f| f.min(log_time)));
        self.last_ns = self.last_ns.max(log_time);
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: 0,
            log_time,
            publish_time: log_time,
        };
        self.writer
            .write_to_known_channel(&header, &msg::encode(message))
            .map_err(failed)
    }

    /// Closes the file, writes metadata.yaml, and gives the bag its final name.
    pub fn finish(mut self) -> Result<PathBuf, BagError> {
        let partial = self.partial();
        self.writer
            .finish()
            .map_err(|e| BagError::format(&partial, e.to_string()))?;
        let file = self.folder.join(&self.file_name);
        std::fs::rename(&partial, &file).map_err(|e| BagError::io(&file, e))?;
        let metadata = self.folder.join(super::metadata::METADATA_FILE);
        std::fs::write(&metadata, self.metadata_yaml()).map_err(|e| BagError::io(&metadata, e))?;
        Ok(self.folder)
    }

    /// rosbag2's metadata.yaml (version 5, which Humble and later read).
    fn metadata_yaml(&self) -> String {
        let first = self.first_ns.unwrap_or(0);
        let total: usize = self.channels.values().map(|c| c.2).sum();
        let mut yaml = format!(
            "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n  \
             duration:\n    nanoseconds: {}\n  starting_time:\n    nanoseconds_since_epoch: \
             {first}\n  message_count: {total}\n  topics_with_message_count:\n",
            self.last_ns.saturating_sub(first)
        );
        for (topic, (_, type_name, count)) in &self.channels {
            yaml.push_str(&format!(
                "    - topic_metadata:\n        name: {topic}\n        type: {type_name}\n        \
                 serialization_format: cdr\n        offered_qos_profiles: \"\"\n      \
                 message_count: {count}\n"
            ));
        }
        yaml.push_str(&format!(
            "  compression_format: \"\"\n  compression_mode: \"\"\n  relative_file_paths:\n    \
             - {}\n  files:\n    - path: {}\n      starting_time:\n        \
             nanoseconds_since_epoch: {first}\n      duration:\n        nanoseconds: {}\n      \
             message_count: {total}\n",
            self.file_name,
            self.file_name,
            self.last_ns.saturating_sub(first)
        ));
        yaml
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bag::Bag;

    #[test]
    fn schema_texts_hold_every_type_they_use_once() {
        let tf = schema_text("tf2_msgs/msg/TFMessage").unwrap();
        assert!(tf.starts_with("geometry_msgs/TransformStamped[] transforms\n"));
        for used in [
            "MSG: geometry_msgs/TransformStamped\n",
            "MSG: std_msgs/Header\n",
            "MSG: builtin_interfaces/Time\n",
            "MSG: geometry_msgs/Transform\n",
            "MSG: geometry_msgs/Vector3\n",
            "MSG: geometry_msgs/Quaternion\n",
        ] {
            assert_eq!(tf.matches(used).count(), 1, "{used} in\n{tf}");
        }
        assert!(schema_text("sensor_msgs/msg/Imu").is_none());
    }

    #[test]
    fn a_written_bag_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("out");
        let mut writer = BagWriter::create(&folder).unwrap();
        for k in 0..5 {
            let pose = msg::PoseStamped {
                header: msg::Header {
                    stamp: msg::Time::from_seconds(10.0 + k as f64),
                    frame_id: "world".into(),
                },
                ..Default::default()
            };
            let path = msg::Path {
                header: pose.header.clone(),
                poses: vec![pose; k + 1],
            };
            writer
                .write(
                    "/agent0/path",
                    crate::msg::type_names::PATH,
                    10.0 + k as f64,
                    &path,
                )
                .unwrap();
        }
        writer.finish().unwrap();
        let bag = Bag::open(&folder).unwrap();
        assert!(bag.damage().is_none());
        assert_eq!(bag.topics().len(), 1);
        assert_eq!(bag.topics()[0].type_name, crate::msg::type_names::PATH);
        assert_eq!(bag.messages().len(), 5);
        let last: msg::Path = msg::decode(&bag.read(&bag.messages()[4]).unwrap()).unwrap();
        assert_eq!(last.poses.len(), 5);
    }
}
