//! The agent's results as a ROS 2 bag (`ros2_bag/`, MCAP) next to its TUM files, for ROS users:
//! `/tf` with `agentK/odom -> agentK/camera_optical_frame` at every placed frame; for a standalone
//! agent also `world -> agentK/odom` on `/tf_static` (the identity: its odometry frame is its
//! world), while in a swarm that transform is the consensus's (its own bag); `/agentK/path`
//! (`nav_msgs/Path` of the placed frames, in the world frame when standalone, else in
//! `agentK/odom`) and `/agentK/map`
//! (`sensor_msgs/PointCloud2` of the map's Gaussian centres with their colour, decimated to
//! `ros2.cloud_max_points`). `ros2 bag play` feeds rviz2 with it; Foxglove and rerun open it.

use std::path::Path;

use anyhow::Context;
use datasets::rosbag::Ros2Config;
use nalgebra::Isometry3;
use ros2::bag::writer::BagWriter;
use ros2::msg::{TfMessage, type_names};
use ros2::outputs::{AgentFrames, path, point_cloud, transform};
use splats::GaussianCloud;

use crate::pipeline::TrackedPose;
use registration::odometry::Placement;

/// The bag's folder inside the agent's output folder.
pub const BAG_FOLDER: &str = "ros2_bag";

/// Writes the bag; returns its folder.
pub fn write_agent_bag(
    out: &Path,
    agent_id: u32,
    poses: &[TrackedPose],
    map: &GaussianCloud,
    config: &Ros2Config,
    standalone: bool,
) -> anyhow::Result<std::path::PathBuf> {
    let folder = out.join(BAG_FOLDER);
    let frames = AgentFrames::new(&config.world_frame, &config.frame_prefix, agent_id);
    let placed: Vec<(f64, Isometry3<f64>)> = poses
        .iter()
        .filter(|p| p.placement == Placement::Root && p.tracked)
        .map(|p| (p.timestamp, p.world_from_camera))
        .collect();
    let mut bag = BagWriter::create(&folder)?;
    let first_stamp = placed.first().map_or(0.0, |p| p.0);
    let last_stamp = placed.last().map_or(0.0, |p| p.0);
    if standalone {
        let world_from_odom = transform(
            &frames.world,
            &frames.odom,
            first_stamp,
            &Isometry3::identity(),
        );
        bag.write(
            "/tf_static",
            type_names::TF_MESSAGE,
            first_stamp,
            &TfMessage {
                transforms: vec![world_from_odom],
            },
        )?;
    }
    // The frame the agent's own poses are in: the world only when it is alone.
    let pose_frame = if standalone {
        &frames.world
    } else {
        &frames.odom
    };
    for (stamp, odom_from_camera) in &placed {
        let tf = TfMessage {
            transforms: vec![transform(
                &frames.odom,
                &frames.camera,
                *stamp,
                odom_from_camera,
            )],
        };
        bag.write("/tf", type_names::TF_MESSAGE, *stamp, &tf)?;
    }
    let topic = |name: &str| format!("/{}{agent_id}/{name}", config.frame_prefix);
    bag.write(
        &topic("path"),
        type_names::PATH,
        last_stamp,
        &path(pose_frame, &placed),
    )?;
    bag.write(
        &topic("map"),
        type_names::POINT_CLOUD2,
        last_stamp,
        &point_cloud(
            pose_frame,
            last_stamp,
            &map.means,
            &map.colours,
            config.cloud_max_points,
        ),
    )?;
    bag.finish()
        .with_context(|| format!("writing {}", folder.display()))
}
