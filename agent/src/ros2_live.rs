//! The agent's results published over DDS while it runs (`[ros2] publish = true`; docs/ros2.md,
//! Live outputs), with the names and frames of its bag (crate::ros2_outputs): `/tf` with
//! `agentK/odom -> agentK/camera_optical_frame` at every placed frame, `/tf_static` with `world ->
//! agentK/odom` when standalone, `/agentK/path` at every keyframe when standalone (in a swarm the
//! consensus publishes the paths, in the world), and `/agentK/map` at most every
//! `publish_map_every_s`: the Gaussians as seeded so far while the agent runs (the mapper holds
//! the optimised map on its own thread), the optimised map at the end. A publishing failure is
//! logged once and publishing stops; the run goes on.

use std::time::{Duration, Instant};

use datasets::rosbag::Ros2Config;
use nalgebra::Isometry3;
use ros2::live::publisher::LivePublisher;
use ros2::msg::TfMessage;
use ros2::outputs::{AgentFrames, path, point_cloud, transform};
use splats::GaussianCloud;

/// One agent's live DDS outputs: its tf, path and map topics (see the module documentation).
pub struct LiveOutputs {
    publisher: Option<LivePublisher>,
    frames: AgentFrames,
    /// The frame of the agent's poses: the world when standalone, its odometry frame in a swarm.
    pose_frame: String,
    /// None in a swarm: the world paths are the consensus's.
    path_topic: Option<String>,
    map_topic: String,
    placed: Vec<(f64, Isometry3<f64>)>,
    seeded_means: Vec<[f32; 3]>,
    seeded_colours: Vec<[f32; 3]>,
    map_every: Duration,
    map_sent: Option<Instant>,
    cloud_max_points: usize,
}

impl LiveOutputs {
    /// Joins the DDS domain when `[ros2] publish` is on; None otherwise.
    pub fn start(
        config: &Ros2Config,
        agent_id: u32,
        standalone: bool,
    ) -> anyhow::Result<Option<Self>> {
        if !config.publish {
            return Ok(None);
        }
        let publisher = LivePublisher::connect(
            config.domain_id(),
            &format!("mac_ego3d_agent{agent_id}_outputs"),
        )?;
        let frames = AgentFrames::new(&config.world_frame, &config.frame_prefix, agent_id);
        if standalone {
            publisher.tf_static(TfMessage {
                transforms: vec![transform(
                    &frames.world,
                    &frames.odom,
                    0.0,
                    &Isometry3::identity(),
                )],
            })?;
        }
        let topic = |name: &str| format!("/{}{agent_id}/{name}", config.frame_prefix);
        tracing::info!(
            domain_id = config.domain_id(),
            standalone,
            map = %topic("map"),
            "publishing tf, path and map over DDS"
        );
        Ok(Some(Self {
            publisher: Some(publisher),
            pose_frame: if standalone {
                frames.world.clone()
            } else {
                frames.odom.clone()
            },
            frames,
            path_topic: standalone.then(|| topic("path")),
            map_topic: topic("map"),
            placed: Vec::new(),
            seeded_means: Vec::new(),
            seeded_colours: Vec::new(),
            map_every: Duration::from_secs_f64(config.publish_map_every_s),
            map_sent: None,
            cloud_max_points: config.cloud_max_points,
        }))
    }

    /// Runs `send` on the publisher; the first failure stops publishing.
    fn send(&mut self, send: impl FnOnce(&mut LivePublisher) -> Result<(), ros2::live::LiveError>) {
        if let Some(publisher) = self.publisher.as_mut()
            && let Err(error) = send(publisher)
        {
            tracing::error!(%error, "publishing over DDS failed: live outputs stop here");
            self.publisher = None;
        }
    }

    fn send_path(&mut self) {
        if let Some(topic) = self.path_topic.clone() {
            let message = path(&self.pose_frame, &self.placed);
            self.send(|p| p.path(&topic, message));
        }
    }

    /// Points with colour in the pose frame, stamped with the latest placed frame.
    fn cloud(&self, means: &[[f32; 3]], colours: &[[f32; 3]]) -> ros2::msg::PointCloud2 {
        let stamp = self.placed.last().map_or(0.0, |p| p.0);
        point_cloud(
            &self.pose_frame,
            stamp,
            means,
            colours,
            self.cloud_max_points,
        )
    }

    fn send_cloud(&mut self, cloud: ros2::msg::PointCloud2) {
        let topic = self.map_topic.clone();
        self.send(|p| p.cloud(&topic, cloud));
    }

    /// A placed frame: its camera on `/tf`.
    pub fn frame(&mut self, stamp_s: f64, odom_from_camera: &Isometry3<f64>) {
        self.placed.push((stamp_s, *odom_from_camera));
        let tf = TfMessage {
            transforms: vec![transform(
                &self.frames.odom,
                &self.frames.camera,
                stamp_s,
                odom_from_camera,
            )],
        };
        self.send(|p| p.tf(tf));
    }

    /// A keyframe and the Gaussians it seeded: the path, and the map when it is due.
    pub fn keyframe(&mut self, seeds: &GaussianCloud) {
        self.seeded_means.extend_from_slice(&seeds.means);
        self.seeded_colours.extend_from_slice(&seeds.colours);
        self.send_path();
        if self
            .map_sent
            .is_none_or(|at| at.elapsed() >= self.map_every)
        {
            self.map_sent = Some(Instant::now());
            let cloud = self.cloud(&self.seeded_means, &self.seeded_colours);
            self.send_cloud(cloud);
        }
    }

    /// The run's end: the final path and the optimised map.
    pub fn finish(&mut self, map: &GaussianCloud) {
        tracing::info!(
            poses = self.placed.len(),
            gaussians = map.len(),
            "publishing the final path and map over DDS"
        );
        self.send_path();
        let cloud = self.cloud(&map.means, &map.colours);
        self.send_cloud(cloud);
        if let Some(publisher) = &self.publisher {
            publisher.linger();
        }
    }
}
