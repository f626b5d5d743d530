//! The consensus's results as a ROS 2 bag (OUT/ros2_bag/, MCAP), beside map.ply and the agents'
//! world trajectories: `/tf_static` with `world -> agentK/odom` for every linked agent (where the
//! consensus put the agent's own frame), `/agentK/path` (its trajectory in the world, agent_K.tum)
//! and `/map` (the merged map's Gaussian centres with colour, decimated to
//! `ros2.cloud_max_points`). Together with the agents' own bags (the camera at frame rate in
//! `agentK/odom`) this is the REP 105 tree a ROS user expects. With `[ros2] publish = true` the
//! same messages are published over DDS whenever the outputs are written (at the end, and on
//! SIGUSR1 snapshots).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use anyhow::Context;
use geometry::trajectory::Trajectory;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use ros2::bag::writer::BagWriter;
use ros2::live::publisher::LivePublisher;
use ros2::msg::{self, TfMessage, type_names};
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

/// What the consensus tells ROS users, as messages: the placements, the paths, the merged map.
pub struct ConsensusMessages {
    first_stamp: f64,
    last_stamp: f64,
    tf_static: TfMessage,
    /// (topic, stamp, path) per linked agent.
    paths: Vec<(String, f64, msg::Path)>,
    map: msg::PointCloud2,
}

/// The messages from the agents' records, their world trajectories (OUT/agent_K.tum) and the
/// merged map.
pub fn consensus_messages(
    out: &Path,
    agents: &BTreeMap<u32, AgentRecord>,
    map: &GaussianCloud,
    config: &config::Ros2Config,
) -> anyhow::Result<ConsensusMessages> {
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
    Ok(ConsensusMessages {
        first_stamp,
        last_stamp,
        tf_static: TfMessage { transforms },
        paths: paths
            .iter()
            .map(|(agent_id, poses)| {
                (
                    format!("/{}{agent_id}/path", config.frame_prefix),
                    poses.last().map_or(last_stamp, |p| p.0),
                    path(&config.world_frame, poses),
                )
            })
            .collect(),
        map: point_cloud(
            &config.world_frame,
            last_stamp,
            &map.means,
            &map.colours,
            config.cloud_max_points,
        ),
    })
}

/// Writes the bag; returns its folder.
pub fn write_consensus_bag(out: &Path, messages: &ConsensusMessages) -> anyhow::Result<PathBuf> {
    let folder = out.join(BAG_FOLDER);
    let mut bag = BagWriter::create(&folder)?;
    bag.write(
        "/tf_static",
        type_names::TF_MESSAGE,
        messages.first_stamp,
        &messages.tf_static,
    )?;
    for (topic, stamp, path) in &messages.paths {
        bag.write(topic, type_names::PATH, *stamp, path)?;
    }
    bag.write(
        "/map",
        type_names::POINT_CLOUD2,
        messages.last_stamp,
        &messages.map,
    )?;
    bag.finish()
        .with_context(|| format!("writing {}", folder.display()))
}

/// The consensus's one DDS publisher, made on its first use: it lives as long as the process, so
/// an rviz2 started later still gets the latest placements, paths and map (transient local).
static PUBLISHER: OnceLock<Mutex<Option<LivePublisher>>> = OnceLock::new();

/// Publishes the messages over DDS when `[ros2] publish` is on (docs/ros2.md, Live outputs);
/// `last`: the process ends next, so the samples are given time to land. A failure is logged and
/// publishing stops; the outputs on disk are unaffected.
pub fn publish(messages: &ConsensusMessages, config: &config::Ros2Config, last: bool) {
    if !config.publish {
        return;
    }
    let slot = PUBLISHER.get_or_init(|| {
        Mutex::new(
            LivePublisher::connect(config.domain_id(), "mac_ego3d_consensus")
                .inspect_err(|error| tracing::error!(%error, "cannot publish over DDS"))
                .ok(),
        )
    });
    let mut slot = slot.lock().unwrap_or_else(|e| e.into_inner());
    let Some(publisher) = slot.as_mut() else {
        return;
    };
    let sent = (|| {
        publisher.tf_static(messages.tf_static.clone())?;
        for (topic, _, path) in &messages.paths {
            publisher.path(topic, path.clone())?;
        }
        publisher.cloud("/map", messages.map.clone())
    })();
    match sent {
        Ok(()) => {
            tracing::info!(
                agents = messages.paths.len(),
                "published the placements, paths and merged map over DDS"
            );
            if last {
                publisher.linger();
            }
        }
        Err(error) => {
            tracing::error!(%error, "publishing over DDS failed: live outputs stop here");
            *slot = None;
        }
    }
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
