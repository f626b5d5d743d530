//! The consensus's results as a ROS 2 bag (OUT/ros2_bag/, MCAP), beside map.ply and the agents'
//! world trajectories: `/tf_static` with `world -> agentK/odom` for every linked agent (where the
//! consensus put the agent's own frame), `/agentK/path` (its trajectory in the world, agent_K.tum)
//! and `/map` (the merged map's Gaussian centres with colour, decimated to
//! `ros2.cloud_max_points`). Together with the agents' own bags (the camera at frame rate in
//! `agentK/odom`) this is the REP 105 tree a ROS user expects.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use geometry::trajectory::Trajectory;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use ros2::bag::writer::BagWriter;
use ros2::msg::{TfMessage, type_names};
use ros2::outputs::{AgentFrames, path, point_cloud, transform};
use splats::GaussianCloud;

use super::outputs::AgentRecord;

/// The bag's folder in the consensus's output folder.
pub const BAG_FOLDER: &str = "ros2_bag";

/// `[tx, ty, tz, qx, qy, qz, qw]` as an isometry.
fn isometry_of(tum: &[f64; 7]) -> Isometry3<f64> {
    let [tx, ty, tz, qx, qy, qz, qw] = *tum;
    Isometry3::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(Quaternion::new(qw, qx, qy, qz)),
    )
}

/// Writes the bag from the agents' records, their world trajectories (OUT/agent_K.tum) and the
/// merged map; returns its folder.
pub fn write_consensus_bag(
    out: &Path,
    agents: &BTreeMap<u32, AgentRecord>,
    map: &GaussianCloud,
    config: &config::Ros2Config,
) -> anyhow::Result<PathBuf> {
    let folder = out.join(BAG_FOLDER);
    let mut paths = Vec::new();
    for agent_id in agents.keys() {
        let file = out.join(format!("agent_{agent_id}.tum"));
        if file.is_file() {
            let trajectory = Trajectory::read_tum(&file)
                .with_context(|| format!("reading {}", file.display()))?;
            let poses: Vec<(f64, Isometry3<f64>)> = trajectory
                .stamps
                .iter()
                .copied()
                .zip(trajectory.poses.iter().copied())
                .collect();
            paths.push((*agent_id, poses));
        }
    }
    let last_stamp = paths
        .iter()
        .filter_map(|(_, poses)| poses.last().map(|p| p.0))
        .fold(0.0, f64::max);
    let first_stamp = paths
        .iter()
        .filter_map(|(_, poses)| poses.first().map(|p| p.0))
        .fold(last_stamp, f64::min);
    let mut bag = BagWriter::create(&folder)?;
    let transforms = agents
        .iter()
        .filter_map(|(agent_id, record)| {
            let frames = AgentFrames::new(&config.world_frame, &config.frame_prefix, *agent_id);
            let world_from_agent = isometry_of(record.world_from_agent.as_ref()?);
            Some(transform(
                &frames.world,
                &frames.odom,
                first_stamp,
                &world_from_agent,
            ))
        })
        .collect();
    bag.write(
        "/tf_static",
        type_names::TF_MESSAGE,
        first_stamp,
        &TfMessage { transforms },
    )?;
    for (agent_id, poses) in &paths {
        let topic = format!("/{}{agent_id}/path", config.frame_prefix);
        let stamp = poses.last().map_or(last_stamp, |p| p.0);
        bag.write(
            &topic,
            type_names::PATH,
            stamp,
            &path(&config.world_frame, poses),
        )?;
    }
    bag.write(
        "/map",
        type_names::POINT_CLOUD2,
        last_stamp,
        &point_cloud(
            &config.world_frame,
            last_stamp,
            &map.means,
            &map.colours,
            config.cloud_max_points,
        ),
    )?;
    bag.finish()
        .with_context(|| format!("writing {}", folder.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_order_becomes_the_same_isometry() {
        let pose = Isometry3::new(
            nalgebra::Vector3::new(1.0, -2.0, 0.5),
            nalgebra::Vector3::new(0.1, 0.2, -0.3),
        );
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        let back = isometry_of(&[t.x, t.y, t.z, q.i, q.j, q.k, q.w]);
        assert!((back.to_homogeneous() - pose.to_homogeneous()).norm() < 1e-12);
    }
}
