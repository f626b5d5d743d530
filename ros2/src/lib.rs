//! ROS 2 without a ROS installation: the messages mac-ego3d reads and writes ([`msg`], CDR
//! through serde), camera images out of them ([`image`]), and rosbag2 bags ([`bag`]: MCAP and
//! sqlite3 storage, read by path like any dataset).
//!
//! How the pieces are used: docs/ros2.md.

pub mod bag;
pub mod image;
pub mod msg;
