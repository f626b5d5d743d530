//! The ROS 2 message types mac-ego3d reads (camera images, calibration, ground-truth poses) and
//! writes (tf, paths, point clouds), as serde structs whose field order is the `.msg` definition's:
//! CDR (XCDR1, what ROS 2's default middlewares and rosbag2 use) writes fields in order, aligned to
//! their size, with no names. [`decode`] and [`encode`] add the 4-byte encapsulation header every
//! serialized ROS 2 message starts with.
//!
//! Byte arrays (`uint8[]`) go through `serde_bytes`, so an image's pixels are borrowed from the
//! message buffer, not copied element by element.

use serde::{Deserialize, Serialize};

/// Full type names as ROS 2 spells them in bags and in DDS discovery (`pkg/msg/Type`).
pub mod type_names {
    pub const IMAGE: &str = "sensor_msgs/msg/Image";
    pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
    pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
    pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
    pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";
    pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
    pub const PATH: &str = "nav_msgs/msg/Path";
    pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
}

/// Why a payload is not the message it should be.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("payload of {0} bytes is shorter than the 4-byte CDR encapsulation header")]
    TooShort(usize),
    #[error("encapsulation {0:#06x} is not plain CDR (0x0000 big endian or 0x0001 little endian)")]
    Encapsulation(u16),
    #[error("CDR does not decode as {type_name}: {reason}")]
    Cdr {
        type_name: &'static str,
        reason: String,
    },
    #[error(
        "{extra} bytes left over after decoding it as {type_name}: the message is of another type"
    )]
    Trailing {
        type_name: &'static str,
        extra: usize,
    },
}

/// Bytes CDR may pad a message's end with (alignment of a following field that is not there).
const MAX_END_PADDING: usize = 7;

/// Decodes a serialized ROS 2 message (encapsulation header + CDR body) as `T`.
pub fn decode<'de, T: Deserialize<'de>>(payload: &'de [u8]) -> Result<T, DecodeError> {
    let type_name = std::any::type_name::<T>()
        .split('<')
        .next()
        .and_then(|path| path.rsplit("::").next())
        .unwrap_or("message");
    let (value, extra) = decode_leaving(payload, type_name)?;
    if extra > MAX_END_PADDING {
        return Err(DecodeError::Trailing { type_name, extra });
    }
    Ok(value)
}

/// Decodes the first fields of a message as `T` (a prefix of its definition, such as its
/// header), ignoring the rest.
pub fn decode_prefix<'de, T: Deserialize<'de>>(payload: &'de [u8]) -> Result<T, DecodeError> {
    decode_leaving(payload, "a message header").map(|(value, _)| value)
}

/// `T` from the payload's CDR body in the byte order its encapsulation header names, and the
/// number of body bytes left after it.
fn decode_leaving<'de, T: Deserialize<'de>>(
    payload: &'de [u8],
    type_name: &'static str,
) -> Result<(T, usize), DecodeError> {
    if payload.len() < 4 {
        return Err(DecodeError::TooShort(payload.len()));
    }
    let cdr_error = |e: re_cdr::Error| DecodeError::Cdr {
        type_name,
        reason: e.to_string(),
    };
    let body = &payload[4..];
    let (value, consumed) = match u16::from_be_bytes([payload[0], payload[1]]) {
        0x0000 => re_cdr::from_bytes::<T, re_cdr::BigEndian>(body).map_err(cdr_error)?,
        0x0001 => re_cdr::from_bytes::<T, re_cdr::LittleEndian>(body).map_err(cdr_error)?,
        other => return Err(DecodeError::Encapsulation(other)),
    };
    Ok((value, body.len().saturating_sub(consumed)))
}

/// Serializes `message` as ROS 2 does: little-endian CDR behind its encapsulation header.
pub fn encode<T: Serialize>(message: &T) -> Vec<u8> {
    let mut payload = vec![0x00, 0x01, 0x00, 0x00];
    let body = re_cdr::to_vec::<T, re_cdr::LittleEndian>(message)
        .expect("the message structs of this module always serialize");
    payload.extend_from_slice(&body);
    payload
}

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    pub fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    /// The stamp nearest `seconds` (non-negative, within i32 seconds).
    pub fn from_seconds(seconds: f64) -> Self {
        let nanos = (seconds.max(0.0) * 1e9).round() as i64;
        Self {
            sec: (nanos / 1_000_000_000) as i32,
            nanosec: (nanos % 1_000_000_000) as u32,
        }
    }

    pub fn is_zero(&self) -> bool {
        self.sec == 0 && self.nanosec == 0
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/Image`: raw pixels rows of `step` bytes. Messages own their bytes: a live
/// subscription keeps them past the network buffer, and a bag read copies them once.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/CompressedImage`: `format` names the codec (`jpeg`, `png`, or the
/// compressed_depth_image_transport's `16UC1; compressedDepth png`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/RegionOfInterest`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/CameraInfo`: `k` is the row-major 3x3 pinhole of the raw image, `d` the
/// distortion coefficients of `distortion_model` (`plumb_bob`: k1 k2 t1 t2 k3).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    pub d: Vec<f64>,
    pub k: [f64; 9],
    pub r: [f64; 9],
    pub p: [f64; 12],
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/Point` and `geometry_msgs/Vector3` (the same fields).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Vector3,
    pub orientation: Quaternion,
}

/// `geometry_msgs/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// `geometry_msgs/PoseWithCovariance` (row-major 6x6 covariance).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    pub covariance: [[f64; 6]; 6],
}

/// `geometry_msgs/Twist`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    pub covariance: [[f64; 6]; 6],
}

/// `nav_msgs/Odometry`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`: `child_frame_id`'s pose in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage` (the `/tf` and `/tf_static` topics).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `nav_msgs/Path`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    pub header: Header,
    pub poses: Vec<PoseStamped>,
}

/// `sensor_msgs/PointField`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    /// One of the `PointField` datatype constants (7 = FLOAT32).
    pub datatype: u8,
    pub count: u32,
}

impl PointField {
    pub const FLOAT32: u8 = 7;
}

/// `sensor_msgs/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    pub is_dense: bool,
}

/// The isometry a pose message describes (`world_from_child`).
pub fn isometry(position: Vector3, orientation: Quaternion) -> nalgebra::Isometry3<f64> {
    let rotation = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        orientation.w,
        orientation.x,
        orientation.y,
        orientation.z,
    ));
    nalgebra::Isometry3::from_parts(
        nalgebra::Translation3::new(position.x, position.y, position.z),
        rotation,
    )
}

/// A pose message's fields for an isometry.
pub fn pose_of(isometry: &nalgebra::Isometry3<f64>) -> Pose {
    let t = isometry.translation.vector;
    let q = isometry.rotation.quaternion();
    Pose {
        position: Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        orientation: Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bytes of a `std_msgs/Header` + `sensor_msgs/Image` laid out by hand from the CDR rules
    /// (4-byte alignment of u32 and string lengths, strings with their NUL), so the serde
    /// structs are checked against the wire format, not against themselves.
    #[test]
    fn an_image_decodes_from_hand_laid_cdr() {
        let mut bytes = vec![0x00, 0x01, 0x00, 0x00];
        bytes.extend_from_slice(&7i32.to_le_bytes()); // stamp.sec
        bytes.extend_from_slice(&500u32.to_le_bytes()); // stamp.nanosec
        bytes.extend_from_slice(&4u32.to_le_bytes()); // frame_id length with NUL
        bytes.extend_from_slice(b"cam\0");
        bytes.extend_from_slice(&2u32.to_le_bytes()); // height
        bytes.extend_from_slice(&3u32.to_le_bytes()); // width
        bytes.extend_from_slice(&6u32.to_le_bytes()); // encoding length with NUL
        bytes.extend_from_slice(b"mono8\0");
        bytes.push(0); // is_bigendian
        bytes.push(0); // pad to 4 for step
        bytes.extend_from_slice(&3u32.to_le_bytes()); // step
        bytes.extend_from_slice(&6u32.to_le_bytes()); // data length
        bytes.extend_from_slice(&[1, 2, 3, 4, 5, 6]);
        let image: Image = decode(&bytes).unwrap();
        assert_eq!(
            image.header.stamp,
            Time {
                sec: 7,
                nanosec: 500
            }
        );
        assert_eq!(image.header.frame_id, "cam");
        assert_eq!((image.width, image.height, image.step), (3, 2, 3));
        assert_eq!(image.encoding, "mono8");
        assert_eq!(image.data, &[1, 2, 3, 4, 5, 6]);
        assert_eq!(encode(&image), bytes, "encoding gives the same bytes back");
    }

    #[test]
    fn messages_round_trip_and_bad_payloads_are_refused() {
        let info = CameraInfo {
            header: Header {
                stamp: Time::from_seconds(1305031102.175304),
                frame_id: "camera_color_optical_frame".into(),
            },
            height: 480,
            width: 640,
            distortion_model: "plumb_bob".into(),
            d: vec![0.26, -0.95, -0.005, 0.002, 1.16],
            k: [517.3, 0.0, 318.6, 0.0, 516.5, 255.3, 0.0, 0.0, 1.0],
            ..Default::default()
        };
        let back: CameraInfo = decode(&encode(&info)).unwrap();
        assert_eq!(back, info);
        let odometry = Odometry {
            child_frame_id: "camera".into(),
            pose: PoseWithCovariance {
                pose: Pose {
                    position: Vector3 {
                        x: 1.0,
                        y: -2.0,
                        z: 0.5,
                    },
                    ..Default::default()
                },
                covariance: [[0.25; 6]; 6],
            },
            ..Default::default()
        };
        assert_eq!(decode::<Odometry>(&encode(&odometry)).unwrap(), odometry);
        let payload = encode(&info);
        assert!(matches!(
            decode::<CameraInfo>(&payload[..payload.len() / 2]),
            Err(DecodeError::Cdr { .. })
        ));
        assert!(matches!(
            decode::<CameraInfo>(&[0, 1]),
            Err(DecodeError::TooShort(2))
        ));
        let mut xcdr2 = payload.clone();
        xcdr2[1] = 0x07;
        assert!(matches!(
            decode::<CameraInfo>(&xcdr2),
            Err(DecodeError::Encapsulation(0x0007))
        ));
        assert!((Time::from_seconds(12.25).seconds() - 12.25).abs() < 1e-9);
        let error = decode::<PoseStamped>(&encode(&info)).unwrap_err();
        assert!(
            matches!(
                error,
                DecodeError::Trailing {
                    type_name: "PoseStamped",
                    ..
                }
            ),
            "{error}"
        );
    }
}
