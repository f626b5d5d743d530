//! One keyframe's messages ready to send, as the spool keeps them, and how they are prepared.

use std::time::Instant;

use anyhow::Context;
use geometry::depth::DepthImage;
use geometry::se3::{isometry_from_tum, isometry_to_tum};
use image::RgbImage;
use protocol::messages::{
    GaussianRecord, Intrinsics as WireIntrinsics, KeyframeDescriptor, Pose, RgbdPixel,
};
use protocol::transport::KeyframeImageMeta;
use splats::GaussianCloud;

use crate::spool::SpooledKeyframe;

use super::PublishableKeyframe;

/// One keyframe's messages, ready to send (the descriptor is computed when the keyframe is due,
/// so a queued keyframe costs nothing more at reconnect). The image and the Gaussians stay in
/// the keyframe's own buffers, and each send builds the wire pixels and records straight into
/// shared memory: no intermediate wire buffer, no copy of one (a re-send builds them again).
pub(super) struct WireKeyframe {
    pub(super) descriptor: KeyframeDescriptor,
    pub(super) image_meta: KeyframeImageMeta,
    pub(super) rgb: RgbImage,
    pub(super) depth: DepthImage,
    pub(super) gaussians: GaussianCloud,
    /// When it was due: its wait in the queue is measured from here.
    pub(super) due: Instant,
}

impl WireKeyframe {
    /// The keyframe as the spool keeps it.
    pub(super) fn spooled(&self) -> SpooledKeyframe {
        let gaussians = &self.gaussians;
        SpooledKeyframe {
            keyframe_id: self.descriptor.keyframe_id,
            frame_index: self.descriptor.frame_index,
            timestamp_s: self.descriptor.timestamp_s,
            agent_from_camera: isometry_to_tum(
                &self.descriptor.camera_to_agent_world.to_isometry(),
            ),
            intrinsics: (&self.image_meta.intrinsics).into(),
            descriptor: self.descriptor.descriptor.to_vec(),
            width: self.image_meta.width,
            height: self.image_meta.height,
            rgb: self.rgb.as_raw().clone(),
            depth_m: self.depth.data.clone(),
            means: gaussians.means.clone(),
            log_scales: gaussians.log_scales.clone(),
            quaternions: gaussians.quaternions.clone(),
            opacity_logits: gaussians.opacity_logits.clone(),
            colours: gaussians.colours.clone(),
        }
    }

    /// A spooled keyframe ready to send again; an error names the keyframe when it does not
    /// read back whole.
    pub(super) fn from_spooled(spooled: SpooledKeyframe) -> anyhow::Result<Self> {
        let id = spooled.keyframe_id;
        let rgb = RgbImage::from_raw(spooled.width, spooled.height, spooled.rgb)
            .with_context(|| format!("spooled keyframe {id}: RGB size does not match"))?;
        let agent_from_camera = isometry_from_tum(&spooled.agent_from_camera)
            .map_err(|error| anyhow::anyhow!("spooled keyframe {id}: pose: {error}"))?;
        let mut descriptor = KeyframeDescriptor::new(id, spooled.frame_index, spooled.timestamp_s);
        descriptor.camera_to_agent_world = Pose::from(&agent_from_camera);
        descriptor.intrinsics = WireIntrinsics::from(&spooled.intrinsics);
        anyhow::ensure!(
            spooled.descriptor.len() == descriptor.descriptor.len(),
            "spooled keyframe {id}: {} descriptor values, the wire carries {}",
            spooled.descriptor.len(),
            descriptor.descriptor.len()
        );
        descriptor.descriptor.copy_from_slice(&spooled.descriptor);
        Ok(Self {
            image_meta: KeyframeImageMeta {
                keyframe_id: id,
                frame_index: spooled.frame_index,
                timestamp_s: spooled.timestamp_s,
                camera_to_agent_world: descriptor.camera_to_agent_world,
                intrinsics: descriptor.intrinsics,
                width: spooled.width,
                height: spooled.height,
            },
            descriptor,
            rgb,
            depth: DepthImage {
                width: spooled.width,
                height: spooled.height,
                data: spooled.depth_m,
            },
            gaussians: GaussianCloud {
                means: spooled.means,
                log_scales: spooled.log_scales,
                quaternions: spooled.quaternions,
                opacity_logits: spooled.opacity_logits,
                colours: spooled.colours,
            },
            due: Instant::now(),
        })
    }

    pub(super) fn bytes(&self) -> u64 {
        let pixels = self.image_meta.width as usize * self.image_meta.height as usize;
        (size_of::<KeyframeDescriptor>()
            + pixels * size_of::<RgbdPixel>()
            + self.gaussians.len() * size_of::<GaussianRecord>()) as u64
    }
}

/// The messages of one keyframe: its descriptor, RGB-D image and patch.
pub(super) fn prepare(
    keyframe: PublishableKeyframe,
    descriptor: &[f32],
) -> anyhow::Result<WireKeyframe> {
    let mut message = KeyframeDescriptor::new(
        keyframe.keyframe_id,
        keyframe.frame_index,
        keyframe.timestamp_s,
    );
    message.camera_to_agent_world = Pose::from(&keyframe.agent_from_camera);
    message.intrinsics = WireIntrinsics::from(&keyframe.intrinsics);
    anyhow::ensure!(
        descriptor.len() == message.descriptor.len(),
        "descriptor has {} values, the wire carries {}",
        descriptor.len(),
        message.descriptor.len()
    );
    message.descriptor.copy_from_slice(descriptor);
    let (width, height) = keyframe.rgb.dimensions();
    anyhow::ensure!(
        (keyframe.depth.width, keyframe.depth.height) == (width, height)
            && keyframe.depth.data.len() == width as usize * height as usize,
        "keyframe {}: depth image is {}x{} ({} values), colour image {width}x{height}",
        keyframe.keyframe_id,
        keyframe.depth.width,
        keyframe.depth.height,
        keyframe.depth.data.len()
    );
    let image_meta = KeyframeImageMeta {
        keyframe_id: keyframe.keyframe_id,
        frame_index: keyframe.frame_index,
        timestamp_s: keyframe.timestamp_s,
        camera_to_agent_world: message.camera_to_agent_world,
        intrinsics: message.intrinsics,
        width,
        height,
    };
    Ok(WireKeyframe {
        descriptor: message,
        image_meta,
        rgb: keyframe.rgb,
        depth: keyframe.depth,
        gaussians: keyframe.gaussians,
        due: Instant::now(),
    })
}
