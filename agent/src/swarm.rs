//! The agent's side of the swarm (SPEC sections 4.1 and 5): every T_comm frames it publishes its
//! latest keyframe (global descriptor, RGB-D image, the keyframe's Gaussians) to the consensus,
//! receives corrections between frames, sends heartbeats, and at the end publishes its final map
//! and says goodbye.
//!
//! Nothing here blocks tracking for long: publishing copies one image and one patch into shared
//! memory; the descriptor (AlexNet at 320 px) is the costliest step, once per T_comm frames.
//! A failed send is logged and counted, never fatal: the agent's own outputs do not depend on the
//! consensus.

use std::hash::{Hash, Hasher};
use std::time::{Duration, Instant};

use anyhow::Context;
use image::RgbImage;
use nalgebra::Isometry3;
use protocol::messages::{
    CoordinateFrame, FINAL_MAP_KEYFRAME_ID, GaussianRecord, Intrinsics as WireIntrinsics,
    KeyframeDescriptor, Pose, RgbdPixel,
};
use protocol::transport::{AgentLink, KeyframeImageMeta, TransportConfig};
use render_core::types::GaussianCloud;
use serde::Serialize;
use slam_core::camera::Intrinsics;
use slam_core::config::Config;
use slam_core::dataset::DepthImage;
use slam_core::descriptor::GlobalDescriptorExtractor;
use slam_core::se3::isometry_to_tum;

/// Heartbeat period: the consensus learns that a quiet agent is still alive.
const HEARTBEAT_EVERY: Duration = Duration::from_secs(1);

/// A keyframe the agent may publish.
pub struct PublishableKeyframe {
    pub keyframe_id: u64,
    pub frame_index: u64,
    pub timestamp_s: f64,
    pub agent_from_camera: Isometry3<f64>,
    pub intrinsics: Intrinsics,
    pub rgb: RgbImage,
    pub depth: DepthImage,
    /// The Gaussians this keyframe seeded, in the agent's frame.
    pub gaussians: GaussianCloud,
}

/// What the swarm link did, for metrics.json.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SwarmSummary {
    pub keyframes_published: usize,
    pub send_failures: usize,
    pub corrections_received: usize,
    /// Latest `world_from_agent` from the consensus, `[tx, ty, tz, qx, qy, qz, qw]`.
    pub world_from_agent: Option<[f64; 7]>,
    pub bytes_sent: u64,
    pub bytes_sent_per_s: f64,
    pub descriptor: String,
}

pub struct SwarmLink {
    link: AgentLink,
    extractor: GlobalDescriptorExtractor,
    t_comm: usize,
    config_hash: u64,
    announced: bool,
    latest: Option<PublishableKeyframe>,
    frames_since_publication: usize,
    last_heartbeat: Instant,
    opened: Instant,
    summary: SwarmSummary,
    world_from_agent: Option<Isometry3<f64>>,
}

impl SwarmLink {
    /// Opens this agent's services (a second live agent with the same id is refused here).
    pub fn connect(
        agent_id: u32,
        transport: &TransportConfig,
        config: &Config,
    ) -> anyhow::Result<Self> {
        let link = AgentLink::open(transport, agent_id)
            .with_context(|| format!("joining the swarm as agent {agent_id}"))?;
        let extractor =
            GlobalDescriptorExtractor::from_weights(config.consensus.descriptor_weights.as_deref());
        let summary = SwarmSummary {
            descriptor: extractor.kind().to_string(),
            ..SwarmSummary::default()
        };
        Ok(Self {
            link,
            extractor,
            t_comm: config.consensus.t_comm,
            config_hash: config_hash(config),
            announced: false,
            latest: None,
            frames_since_publication: 0,
            last_heartbeat: Instant::now(),
            opened: Instant::now(),
            summary,
            world_from_agent: None,
        })
    }

    /// Announces the agent with its camera (first frame).
    pub fn announce(&mut self, intrinsics: &Intrinsics) {
        if self.announced {
            return;
        }
        match self
            .link
            .announce(wire_intrinsics(intrinsics), self.config_hash)
        {
            Ok(_) => self.announced = true,
            Err(error) => {
                self.summary.send_failures += 1;
                tracing::warn!(%error, "hello not delivered");
            }
        }
    }

    /// Remembers the latest keyframe; it goes out at the next publication.
    pub fn on_keyframe(&mut self, keyframe: PublishableKeyframe) {
        self.latest = Some(keyframe);
    }

    /// Between frames: publishes every T_comm frames, applies corrections, heartbeats.
    pub fn after_frame(&mut self) {
        self.frames_since_publication += 1;
        if self.frames_since_publication >= self.t_comm && self.latest.is_some() {
            self.publish_latest();
        }
        self.receive_corrections();
        if self.last_heartbeat.elapsed() >= HEARTBEAT_EVERY {
            self.last_heartbeat = Instant::now();
            if let Err(error) = self.link.heartbeat() {
                tracing::debug!(%error, "heartbeat not delivered");
            }
        }
    }

    /// The consensus's latest estimate of this agent's frame in the world.
    pub fn world_from_agent(&self) -> Option<Isometry3<f64>> {
        self.world_from_agent
    }

    fn publish_latest(&mut self) {
        let Some(keyframe) = self.latest.take() else {
            return;
        };
        self.frames_since_publication = 0;
        let _span = tracing::info_span!("publish keyframe", id = keyframe.keyframe_id).entered();
        match self.publish(&keyframe) {
            Ok(()) => self.summary.keyframes_published += 1,
            Err(error) => {
                self.summary.send_failures += 1;
                tracing::warn!(error = %format!("{error:#}"), "keyframe not published");
            }
        }
    }

    fn publish(&mut self, keyframe: &PublishableKeyframe) -> anyhow::Result<()> {
        let descriptor = self
            .extractor
            .describe(&keyframe.rgb)
            .context("computing the global descriptor")?;
        let mut message = KeyframeDescriptor::new(
            keyframe.keyframe_id,
            keyframe.frame_index,
            keyframe.timestamp_s,
        );
        message.camera_to_agent_world = Pose::from(&keyframe.agent_from_camera);
        message.intrinsics = wire_intrinsics(&keyframe.intrinsics);
        anyhow::ensure!(
            descriptor.len() == message.descriptor.len(),
            "descriptor has {} values, the wire carries {}",
            descriptor.len(),
            message.descriptor.len()
        );
        message.descriptor.copy_from_slice(&descriptor);
        self.link.send_descriptor(&message)?;
        let meta = KeyframeImageMeta {
            keyframe_id: keyframe.keyframe_id,
            frame_index: keyframe.frame_index,
            timestamp_s: keyframe.timestamp_s,
            camera_to_agent_world: message.camera_to_agent_world,
            intrinsics: message.intrinsics,
            width: keyframe.rgb.width(),
            height: keyframe.rgb.height(),
        };
        self.link
            .send_keyframe_image(&meta, &rgbd_pixels(&keyframe.rgb, &keyframe.depth))?;
        self.link.send_patch(
            keyframe.keyframe_id,
            CoordinateFrame::AgentWorld,
            &gaussian_records(&keyframe.gaussians),
        )?;
        Ok(())
    }

    fn receive_corrections(&mut self) {
        loop {
            match self.link.try_recv_correction() {
                Ok(Some(correction)) => {
                    let header = correction.header();
                    let world_from_agent = header.agent_world_to_world.to_isometry();
                    self.summary.corrections_received += 1;
                    tracing::info!(
                        keyframes = correction.poses().len(),
                        translation_m = world_from_agent.translation.vector.norm(),
                        "correction received"
                    );
                    self.world_from_agent = Some(world_from_agent);
                }
                Ok(None) => break,
                Err(error) => {
                    tracing::warn!(%error, "correction refused");
                    break;
                }
            }
        }
    }

    /// Publishes the last keyframe if it has not gone out, then the final map, and says goodbye
    /// (waiting until the consensus has everything).
    pub fn finish(mut self, final_map: &GaussianCloud) -> SwarmSummary {
        self.publish_latest();
        if let Err(error) = self.link.send_patch(
            FINAL_MAP_KEYFRAME_ID,
            CoordinateFrame::AgentWorld,
            &gaussian_records(final_map),
        ) {
            self.summary.send_failures += 1;
            tracing::warn!(%error, "final map not delivered");
        }
        self.receive_corrections();
        let bandwidth = self.link.bandwidth();
        self.summary.bytes_sent = bandwidth
            .entries
            .iter()
            .filter(|e| e.direction == protocol::transport::Direction::Sent)
            .map(|e| e.traffic.bytes)
            .sum();
        self.summary.bytes_sent_per_s =
            self.summary.bytes_sent as f64 / self.opened.elapsed().as_secs_f64().max(1e-9);
        self.summary.world_from_agent = self.world_from_agent.as_ref().map(isometry_to_tum);
        if let Err(error) = self.link.close() {
            tracing::warn!(%error, "goodbye not acknowledged");
        }
        self.summary
    }
}

/// A hash of the whole configuration: the consensus warns when agents differ.
fn config_hash(config: &Config) -> u64 {
    let mut hasher = std::collections::hash_map::DefaultHasher::new();
    serde_json::to_string(config)
        .unwrap_or_default()
        .hash(&mut hasher);
    hasher.finish()
}

fn wire_intrinsics(intrinsics: &Intrinsics) -> WireIntrinsics {
    WireIntrinsics {
        fx: intrinsics.fx,
        fy: intrinsics.fy,
        cx: intrinsics.cx,
        cy: intrinsics.cy,
        width: intrinsics.width,
        height: intrinsics.height,
    }
}

/// Row-major RGB-D pixels; invalid or out-of-range depth becomes 0 (invalid).
fn rgbd_pixels(rgb: &RgbImage, depth: &DepthImage) -> Vec<RgbdPixel> {
    rgb.pixels()
        .zip(&depth.data)
        .map(|(colour, metres)| RgbdPixel::new(colour.0, *metres))
        .collect()
}

fn gaussian_records(cloud: &GaussianCloud) -> Vec<GaussianRecord> {
    (0..cloud.len())
        .map(|i| GaussianRecord {
            mean: cloud.means[i],
            log_scale: cloud.log_scales[i],
            rotation_wxyz: cloud.quaternions[i],
            opacity_logit: cloud.opacity_logits[i],
            colour: cloud.colours[i],
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_out_of_range_or_invalid_is_sent_as_zero() {
        let rgb = RgbImage::from_pixel(4, 1, image::Rgb([1, 2, 3]));
        let depth = DepthImage {
            width: 4,
            height: 1,
            data: vec![1.2345, f32::NAN, -1.0, 100.0],
        };
        let pixels = rgbd_pixels(&rgb, &depth);
        let mm: Vec<u16> = pixels.iter().map(|p| p.depth_mm).collect();
        assert_eq!(mm, vec![1235, 0, 0, 0]);
        assert_eq!(pixels[0].rgb, [1, 2, 3]);
    }
}
