//! The messages a SLAM system gives ROS users, built from mac-ego3d's results: tf following REP 105
//! (`world -> agentK/odom -> agentK/camera`), a `nav_msgs/Path` per agent in the world frame, and
//! the map's Gaussian centres with their colour as a `sensor_msgs/PointCloud2` for rviz2.

use nalgebra::Isometry3;

use crate::msg::{self, Header, PointCloud2, PointField, Time, TransformStamped};

/// The frame names of one agent under a prefix (`agent0/odom`, `agent0/camera_optical_frame`).
#[derive(Debug, Clone, PartialEq)]
pub struct AgentFrames {
    /// The world frame all agents share (REP 105's `map`).
    pub world: String,
    /// The agent's own odometry frame: where its tracking puts its poses.
    pub odom: String,
    /// The agent's camera (optical convention: z forward, x right, y down; REP 103).
    pub camera: String,
}

impl AgentFrames {
    /// Agent `agent_id`'s frames under `world` (`[ros2] world_frame`) and `prefix`
    /// (`[ros2] frame_prefix`): `{prefix}{agent_id}/odom` and
    /// `{prefix}{agent_id}/camera_optical_frame`.
    pub fn new(world: &str, prefix: &str, agent_id: u32) -> Self {
        let agent = format!("{prefix}{agent_id}");
        Self {
            world: world.to_string(),
            odom: format!("{agent}/odom"),
            camera: format!("{agent}/camera_optical_frame"),
        }
    }
}

/// One transform `parent_from_child` at `stamp_s`.
pub fn transform(
    parent: &str,
    child: &str,
    stamp_s: f64,
    parent_from_child: &Isometry3<f64>,
) -> TransformStamped {
    let pose = msg::pose_of(parent_from_child);
    TransformStamped {
        header: Header {
            stamp: Time::from_seconds(stamp_s),
            frame_id: parent.to_string(),
        },
        child_frame_id: child.to_string(),
        transform: msg::Transform {
            translation: pose.position,
            rotation: pose.orientation,
        },
    }
}

/// A path of `(stamp, frame_from_camera)` poses in `frame`, stamped with its last pose.
pub fn path(frame: &str, poses: &[(f64, Isometry3<f64>)]) -> msg::Path {
    let stamped = |(t, pose): &(f64, Isometry3<f64>)| msg::PoseStamped {
        header: Header {
            stamp: Time::from_seconds(*t),
            frame_id: frame.to_string(),
        },
        pose: msg::pose_of(pose),
    };
    msg::Path {
        header: Header {
            stamp: Time::from_seconds(poses.last().map_or(0.0, |p| p.0)),
            frame_id: frame.to_string(),
        },
        poses: poses.iter().map(stamped).collect(),
    }
}

/// Points with colour as rviz2 reads them: x, y, z float32 and `rgb` packed into a float32 field
/// (bytes b, g, r, 0), from colours in [0, 1] (a Gaussian map's). At most `max_points` points:
/// every k-th point when there are more, so a large map does not flood the network.
pub fn point_cloud(
    frame: &str,
    stamp_s: f64,
    positions: &[[f32; 3]],
    colours: &[[f32; 3]],
    max_points: usize,
) -> PointCloud2 {
    let byte = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let step = positions.len().div_ceil(max_points.max(1)).max(1);
    let mut data = Vec::with_capacity(positions.len() / step * 16 + 16);
    let mut count = 0u32;
    for (position, colour) in positions.iter().zip(colours).step_by(step) {
        for c in position {
            data.extend_from_slice(&c.to_le_bytes());
        }
        data.extend_from_slice(&[byte(colour[2]), byte(colour[1]), byte(colour[0]), 0]);
        count += 1;
    }
    let field = |name: &str, offset: u32| PointField {
        name: name.to_string(),
        offset,
        datatype: PointField::FLOAT32,
        count: 1,
    };
    PointCloud2 {
        header: Header {
            stamp: Time::from_seconds(stamp_s),
            frame_id: frame.to_string(),
        },
        height: 1,
        width: count,
        fields: vec![
            field("x", 0),
            field("y", 4),
            field("z", 8),
            field("rgb", 12),
        ],
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * count,
        data,
        is_dense: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_clouds_decimate_and_pack_colour_as_rviz_reads_it() {
        let positions: Vec<[f32; 3]> = (0..10).map(|i| [i as f32, 0.5, -1.0]).collect();
        let colours: Vec<[f32; 3]> = (0..10).map(|i| [i as f32 / 255.0, 0.4, 1.5]).collect();
        let cloud = point_cloud("world", 3.5, &positions, &colours, 4);
        assert_eq!(cloud.width, 4, "every 3rd of 10 points");
        assert_eq!(cloud.data.len(), 4 * 16);
        let second = &cloud.data[16..32];
        assert_eq!(f32::from_le_bytes(second[0..4].try_into().unwrap()), 3.0);
        assert_eq!(
            &second[12..16],
            &[255, 102, 3, 0],
            "b clamped to 1, g 0.4, r 3/255"
        );
        let back: PointCloud2 = msg::decode(&msg::encode(&cloud)).unwrap();
        assert_eq!(back, cloud);
    }

    #[test]
    fn frames_follow_the_prefix() {
        let frames = AgentFrames::new("world", "agent", 2);
        assert_eq!(frames.odom, "agent2/odom");
        assert_eq!(frames.camera, "agent2/camera_optical_frame");
        let t = transform(
            &frames.odom,
            &frames.camera,
            1.0,
            &Isometry3::translation(1.0, 2.0, 3.0),
        );
        assert_eq!(t.transform.translation.y, 2.0);
        assert_eq!(t.child_frame_id, "agent2/camera_optical_frame");
    }
}
