//! What a message must satisfy. A sender refuses a message that would mislead its receivers
//! ([`TransportError::InvalidMessage`], nothing is sent); a receiver refuses a sample whose
//! header does not match its payload or names another agent (the `*_header` checks: the
//! reason, which the receive path reports as [`TransportError::Malformed`]). The sender
//! checks everything the receiver does, so a receive-side failure means corruption or a
//! foreign sender.

use super::TransportError;
use super::agent::KeyframeImageMeta;
use crate::messages::{
    ControlHeader, CorrectionHeader, DESCRIPTOR_NORM_TOLERANCE, KeyframeDescriptor,
    KeyframeImageHeader, KeyframePose, PatchHeader, Pose, Stamp,
};

/// Quaternion norm tolerance for poses accepted on send.
const POSE_NORM_TOLERANCE: f64 = 1e-6;

fn refuse(service: &str, reason: String) -> Result<(), TransportError> {
    Err(TransportError::InvalidMessage {
        service: service.to_string(),
        reason,
    })
}

pub(super) fn pose(service: &str, what: &str, pose: &Pose) -> Result<(), TransportError> {
    if !pose.is_valid(POSE_NORM_TOLERANCE) {
        return refuse(
            service,
            format!("{what} is not finite or its quaternion is not unit: {pose:?}"),
        );
    }
    Ok(())
}

/// A descriptor must be L2-normalised and its pose valid.
pub(super) fn descriptor(
    service: &str,
    descriptor: &KeyframeDescriptor,
) -> Result<(), TransportError> {
    let norm = descriptor.descriptor_norm();
    if !norm.is_finite() || (norm - 1.0).abs() > DESCRIPTOR_NORM_TOLERANCE {
        return refuse(
            service,
            format!("descriptor norm is {norm}, expected 1 (L2-normalised)"),
        );
    }
    pose(
        service,
        "camera_to_agent_world",
        &descriptor.camera_to_agent_world,
    )
}

/// Refuses a keyframe image whose header would mislead the consensus: an empty image, a pixel
/// count that does not match `width * height`, intrinsics of another image size (the usual
/// mistake when downscaling), unusable intrinsics or an invalid pose.
pub(super) fn keyframe_image(
    service: &str,
    meta: &KeyframeImageMeta,
    pixels: usize,
) -> Result<(), TransportError> {
    let (width, height) = (meta.width, meta.height);
    if width == 0 || height == 0 {
        return refuse(
            service,
            format!(
                "keyframe {} image size {width}x{height} is empty",
                meta.keyframe_id
            ),
        );
    }
    // u64: width * height of two u32 cannot overflow it, unlike usize on 32-bit targets.
    let expected = u64::from(width) * u64::from(height);
    if expected != pixels as u64 {
        return refuse(
            service,
            format!(
                "keyframe {} image is {width}x{height} = {expected} pixels, but {pixels} pixels \
                 were given",
                meta.keyframe_id
            ),
        );
    }
    let k = &meta.intrinsics;
    if (k.width, k.height) != (width, height) {
        return refuse(
            service,
            format!(
                "keyframe {} intrinsics are for a {}x{} image but the image is \
                 {width}x{height} (scale the intrinsics with the image)",
                meta.keyframe_id, k.width, k.height
            ),
        );
    }
    let focal_ok = [k.fx, k.fy].iter().all(|f| f.is_finite() && *f > 0.0);
    if !focal_ok || !k.cx.is_finite() || !k.cy.is_finite() {
        return refuse(
            service,
            format!(
                "keyframe {} intrinsics need finite positive focal lengths and a finite \
                 principal point: {k:?}",
                meta.keyframe_id
            ),
        );
    }
    pose(
        service,
        "camera_to_agent_world",
        &meta.camera_to_agent_world,
    )
}

/// A correction's poses must all be valid.
pub(super) fn correction(
    service: &str,
    agent_world_to_world: &Pose,
    poses: &[KeyframePose],
) -> Result<(), TransportError> {
    pose(service, "agent_world_to_world", agent_world_to_world)?;
    if let Some(bad) = poses
        .iter()
        .find(|p| !p.camera_to_world.is_valid(POSE_NORM_TOLERANCE))
    {
        pose(
            service,
            &format!("keyframe {} pose", bad.keyframe_id),
            &bad.camera_to_world,
        )?;
    }
    Ok(())
}

/// A message on agent `agent`'s own topic must name that agent as its sender.
pub(super) fn sender(stamp: &Stamp, agent: u32) -> Result<Stamp, String> {
    if stamp.agent_id != agent {
        return Err(format!(
            "stamp names agent {} on agent {agent}'s topic",
            stamp.agent_id
        ));
    }
    Ok(*stamp)
}

/// A lifecycle message must come from an agent id the receiver listens to.
pub(super) fn lifecycle_sender(stamp: &Stamp, max_agents: u32) -> Result<Stamp, String> {
    if stamp.agent_id >= max_agents {
        return Err(format!(
            "sender agent id {} is outside 0..{max_agents}",
            stamp.agent_id
        ));
    }
    Ok(*stamp)
}

pub(super) fn patch_header(header: &PatchHeader, len: usize, agent: u32) -> Result<Stamp, String> {
    if header.stamp.agent_id != agent || header.count != len as u64 || header.frame().is_err() {
        return Err(format!(
            "header (agent {}, count {}, frame tag {}) does not match agent {agent}'s slice of \
             {len}",
            header.stamp.agent_id, header.count, header.frame
        ));
    }
    Ok(header.stamp)
}

/// Reading pixels with the wrong size would scramble every row.
pub(super) fn keyframe_image_header(
    header: &KeyframeImageHeader,
    len: usize,
    agent: u32,
) -> Result<Stamp, String> {
    if header.stamp.agent_id != agent
        || header.pixel_count() != len as u64
        || len == 0
        || (header.intrinsics.width, header.intrinsics.height) != (header.width, header.height)
    {
        return Err(format!(
            "header (agent {}, {}x{} image, intrinsics for {}x{}) does not match agent {agent}'s \
             slice of {len} pixels",
            header.stamp.agent_id,
            header.width,
            header.height,
            header.intrinsics.width,
            header.intrinsics.height
        ));
    }
    Ok(header.stamp)
}

pub(super) fn correction_header(
    header: &CorrectionHeader,
    len: usize,
    agent: u32,
) -> Result<Stamp, String> {
    if header.count != len as u64 || header.target_agent_id != agent {
        return Err(format!(
            "header says {} poses for agent {}, slice has {len} (this is agent {agent})",
            header.count, header.target_agent_id
        ));
    }
    Ok(header.stamp)
}

pub(super) fn control_header(
    header: &ControlHeader,
    len: usize,
    agent: u32,
) -> Result<Stamp, String> {
    if header.frame_len != len as u64 || header.target_agent_id != agent {
        return Err(format!(
            "header says a {}-byte frame for agent {}, slice has {len} bytes (this is agent \
             {agent})",
            header.frame_len, header.target_agent_id
        ));
    }
    Ok(header.stamp)
}
