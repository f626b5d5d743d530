//! ROS 2 without a ROS installation: the messages mac-ego3d reads and writes ([`msg`], CDR
//! through serde), camera images out of them ([`image`]), rosbag2 bags ([`bag`]: MCAP and sqlite3
//! storage read by path like any dataset; MCAP written), and the outputs ROS users look at
//! ([`outputs`]: tf, paths, point clouds).
//!
//! How the pieces are used: docs/ros2.md.

pub mod bag;
pub mod image;
pub mod live;
pub mod msg;
pub mod outputs;
