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
    /// Raw colour or depth images ([`super::Image`]).
    pub const IMAGE: &str = "sensor_msgs/msg/Image";
    /// JPEG / PNG images, or compressed_depth_image_transport's depth
    /// ([`super::CompressedImage`]).
    pub const COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
    /// A camera's calibration: image size, K, lens ([`super::CameraInfo`]).
    pub const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
    /// Point clouds: the maps written and published for rviz2 ([`super::PointCloud2`]).
    pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
    /// A ground-truth pose topic a bag may hold ([`super::PoseStamped`]).
    pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";
    /// The other ground-truth pose topic a bag may hold ([`super::Odometry`]).
    pub const ODOMETRY: &str = "nav_msgs/msg/Odometry";
    /// A trajectory: the agents' paths written and published ([`super::Path`]).
    pub const PATH: &str = "nav_msgs/msg/Path";
    /// The messages of `/tf` and `/tf_static` ([`super::TfMessage`]).
    pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
}

/// Why a payload is not the message it should be.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// The payload (of this many bytes) cannot even hold the encapsulation header.
    #[error("payload of {0} bytes is shorter than the 4-byte CDR encapsulation header")]
    TooShort(usize),
    /// The encapsulation header names another representation (this one, read big endian), such
    /// as XCDR2 or a parameter list.
    #[error("encapsulation {0:#06x} is not plain CDR (0x0000 big endian or 0x0001 little endian)")]
    Encapsulation(u16),
    /// The body does not decode as the type: it ends too early, or holds a value the type
    /// cannot take.
    #[error("CDR does not decode as {type_name}: {reason}")]
    Cdr {
        /// The Rust type it was decoded as (`CameraInfo`), or `a message header`.
        type_name: &'static str,
        /// The CDR decoder's message.
        reason: String,
    },
    /// The body decoded, but more than the 7 bytes of end padding CDR allows were left over:
    /// the topic carries another type whose first fields happen to read as this one's.
    #[error(
        "{extra} bytes left over after decoding it as {type_name}: the message is of another type"
    )]
    Trailing {
        /// The Rust type it was decoded as (`PoseStamped`).
        type_name: &'static str,
        /// Body bytes left after the decoded value.
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
    /// Whole seconds (since the Unix epoch for wall-clock stamps).
    pub sec: i32,
    /// Nanoseconds past `sec`, 0 to 999 999 999.
    pub nanosec: u32,
}

impl Time {
    /// The stamp in seconds, as one number (an f64 resolves present-day epoch stamps to about
    /// 0.24 us).
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

    /// Whether the stamp is 0 s: what a publisher that does not stamp its messages sends.
    pub fn is_zero(&self) -> bool {
        self.sec == 0 && self.nanosec == 0
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was captured, by the publisher's clock.
    pub stamp: Time,
    /// The tf frame the data is expressed in (`camera_color_optical_frame`).
    pub frame_id: String,
}

/// `sensor_msgs/Image`: raw pixels rows of `step` bytes. Messages own their bytes: a live
/// subscription keeps them past the network buffer, and a bag read copies them once.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Image {
    /// Capture time and the camera's optical frame.
    pub header: Header,
    /// Rows, in pixels.
    pub height: u32,
    /// Columns, in pixels.
    pub width: u32,
    /// Pixel layout (`rgb8`, `bgr8`, `16UC1`, `32FC1`, ...; the names of sensor_msgs'
    /// image_encodings).
    pub encoding: String,
    /// Non-zero when multi-byte pixel values (16UC1, 32FC1) are big endian.
    pub is_bigendian: u8,
    /// Row length in bytes: at least `width` times the pixel size, more when rows are padded.
    pub step: u32,
    /// The pixels, `height` rows of `step` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/CompressedImage`: `format` names the codec (`jpeg`, `png`, or the
/// compressed_depth_image_transport's `16UC1; compressedDepth png`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Capture time and the camera's optical frame.
    pub header: Header,
    /// The codec, and for image_transport's plugins the raw encoding before it
    /// (`rgb8; jpeg compressed bgr8`).
    pub format: String,
    /// The compressed file: a JPEG or PNG, or compressedDepth's 12-byte header and PNG.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/RegionOfInterest`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Leftmost column of the region, in pixels of the full-resolution image.
    pub x_offset: u32,
    /// Top row of the region, in pixels of the full-resolution image.
    pub y_offset: u32,
    /// Rows of the region (0 with `width` 0: the whole image).
    pub height: u32,
    /// Columns of the region (0 with `height` 0: the whole image).
    pub width: u32,
    /// Whether the region is to be cut from the rectified image rather than the raw one.
    pub do_rectify: bool,
}

/// `sensor_msgs/CameraInfo`: `k` is the row-major 3x3 pinhole of the raw image, `d` the
/// distortion coefficients of `distortion_model` (`plumb_bob`: k1 k2 t1 t2 k3).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and the optical frame of the camera it describes.
    pub header: Header,
    /// Rows of the image the calibration is for, in pixels.
    pub height: u32,
    /// Columns of the image the calibration is for, in pixels.
    pub width: u32,
    /// The lens model `d` belongs to (`plumb_bob`, `rational_polynomial`, `equidistant`, ...).
    /// mac-ego3d reads `plumb_bob`, and any model whose coefficients are all zero.
    pub distortion_model: String,
    /// The lens model's coefficients, in its order (`plumb_bob`: k1 k2 t1 t2 k3).
    pub d: Vec<f64>,
    /// Intrinsics of the raw image, row-major `[fx 0 cx; 0 fy cy; 0 0 1]`, in pixels.
    pub k: [f64; 9],
    /// Rectification rotation, row-major 3x3 (stereo; the identity for a single camera).
    /// mac-ego3d ignores it.
    pub r: [f64; 9],
    /// Projection of the rectified image, row-major 3x4 `[fx' 0 cx' Tx; 0 fy' cy' Ty; 0 0 1 0]`.
    /// mac-ego3d uses `k` and `d`, not this.
    pub p: [f64; 12],
    /// Horizontal binning the camera applied (0 or 1: none). mac-ego3d ignores it.
    pub binning_x: u32,
    /// Vertical binning the camera applied (0 or 1: none). mac-ego3d ignores it.
    pub binning_y: u32,
    /// The part of the full image sent (all zeros: the whole image). mac-ego3d ignores it.
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/Point` and `geometry_msgs/Vector3` (the same fields).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// X component (metres in a position or translation, m/s or rad/s in a twist).
    pub x: f64,
    /// Y component, in the same unit as `x`.
    pub y: f64,
    /// Z component, in the same unit as `x`.
    pub z: f64,
}

/// `geometry_msgs/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// First imaginary component (`i`).
    pub x: f64,
    /// Second imaginary component (`j`).
    pub y: f64,
    /// Third imaginary component (`k`).
    pub z: f64,
    /// Real component: 1 with the others 0 is no rotation (the default).
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
    /// Where the posed frame's origin lies in the frame the pose is expressed in, metres.
    pub position: Vector3,
    /// How the posed frame's axes are rotated in that frame (unit quaternion).
    pub orientation: Quaternion,
}

/// `geometry_msgs/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// When the pose held, and the frame it is expressed in.
    pub header: Header,
    /// The pose in `header.frame_id`.
    pub pose: Pose,
}

/// `geometry_msgs/PoseWithCovariance` (row-major 6x6 covariance).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The estimated pose.
    pub pose: Pose,
    /// Its uncertainty over (x, y, z, rotation about X, about Y, about Z); the message's
    /// `float64[36]`, which CDR lays out the same.
    pub covariance: [[f64; 6]; 6],
}

/// `geometry_msgs/Twist`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity, m/s.
    pub linear: Vector3,
    /// Angular velocity about each axis, rad/s.
    pub angular: Vector3,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The estimated velocity.
    pub twist: Twist,
    /// Its uncertainty over (vx, vy, vz, wx, wy, wz), row-major 6x6 as in
    /// [`PoseWithCovariance`].
    pub covariance: [[f64; 6]; 6],
}

/// `nav_msgs/Odometry`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// When the pose held, and the frame the pose is in.
    pub header: Header,
    /// The frame whose pose this is (the robot's or camera's).
    pub child_frame_id: String,
    /// The pose of `child_frame_id` in `header.frame_id`.
    pub pose: PoseWithCovariance,
    /// The velocity, in `child_frame_id` (mac-ego3d ignores it).
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// The child frame's origin in the parent frame, metres.
    pub translation: Vector3,
    /// The rotation from the child's axes to the parent's.
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`: `child_frame_id`'s pose in `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// When the transform held, and the parent frame.
    pub header: Header,
    /// The frame the transform places in the parent.
    pub child_frame_id: String,
    /// `parent_from_child`.
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage` (the `/tf` and `/tf_static` topics).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms, each with its own stamp and frames.
    pub transforms: Vec<TransformStamped>,
}

/// `nav_msgs/Path`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// The path's frame, and a stamp (the paths written here carry their last pose's).
    pub header: Header,
    /// The poses in time order, each stamped and in the path's frame.
    pub poses: Vec<PoseStamped>,
}

/// `sensor_msgs/PointField`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    /// The field's name: `x`, `y`, `z`, `rgb`, ...
    pub name: String,
    /// Where the field starts in a point, bytes from the point's start.
    pub offset: u32,
    /// One of the `PointField` datatype constants (7 = FLOAT32).
    pub datatype: u8,
    /// Values of `datatype` in the field (1 for a scalar).
    pub count: u32,
}

impl PointField {
    /// `datatype` of a 32-bit IEEE float, the only one written here.
    pub const FLOAT32: u8 = 7;
}

/// `sensor_msgs/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp, and the frame the points are in.
    pub header: Header,
    /// Rows of an organised cloud; 1 for an unordered one (the clouds written here).
    pub height: u32,
    /// Points per row (of an unordered cloud, all of them).
    pub width: u32,
    /// The layout of one point.
    pub fields: Vec<PointField>,
    /// Whether multi-byte values in `data` are big endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row: `point_step * width` when rows are not padded.
    pub row_step: u32,
    /// The points, `height` rows of `row_step` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// True when every point is valid (no NaN or infinite coordinates).
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
