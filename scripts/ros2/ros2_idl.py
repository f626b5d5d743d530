"""The ROS 2 messages the scripts publish and subscribe with Cyclone DDS, as IDL structs under
ROS 2's DDS type names (`sensor_msgs::msg::dds_::Image_`): the same layouts as the ros2 crate's
msg.rs. Imported by publish_dataset.py and listen_outputs.py."""

from dataclasses import dataclass, field

import cyclonedds.idl as idl
import cyclonedds.idl.types as t


@dataclass
class Time(idl.IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header(idl.IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Image(idl.IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: t.uint32
    width: t.uint32
    encoding: str
    is_bigendian: t.uint8
    step: t.uint32
    data: t.sequence[t.uint8]


@dataclass
class CompressedImage(idl.IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    header: Header
    format: str
    data: t.sequence[t.uint8]


@dataclass
class RegionOfInterest(idl.IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: t.uint32 = 0
    y_offset: t.uint32 = 0
    height: t.uint32 = 0
    width: t.uint32 = 0
    do_rectify: bool = False


@dataclass
class CameraInfo(idl.IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header
    height: t.uint32
    width: t.uint32
    distortion_model: str
    d: t.sequence[t.float64]
    k: t.array[t.float64, 9]
    r: t.array[t.float64, 9]
    p: t.array[t.float64, 12]
    binning_x: t.uint32 = 0
    binning_y: t.uint32 = 0
    roi: RegionOfInterest = field(default_factory=RegionOfInterest)



@dataclass
class Vector3(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Point(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Transform(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(idl.IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(idl.IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped]


@dataclass
class Pose(idl.IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(idl.IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
class Path(idl.IdlStruct, typename="nav_msgs::msg::dds_::Path_"):
    header: Header
    poses: t.sequence[PoseStamped]


@dataclass
class PointField(idl.IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str
    offset: t.uint32
    datatype: t.uint8
    count: t.uint32


@dataclass
class PointCloud2(idl.IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header
    height: t.uint32
    width: t.uint32
    fields: t.sequence[PointField]
    is_bigendian: bool
    point_step: t.uint32
    row_step: t.uint32
    data: t.sequence[t.uint8]
    is_dense: bool
