//! What receivers get: each topic's sample type (most read in place from shared memory, no
//! copy) with its [`Delivery`], and [`Incoming`], anything a consumer receives.

use iceoryx2::sample::Sample;

use super::Ipc;
use super::sequence::Delivery;
use crate::messages::{
    ControlHeader, ControlMessage, CorrectionHeader, GaussianRecord, KeyframeDescriptor,
    KeyframeImageHeader, KeyframePose, Lifecycle, PatchHeader, RgbdPixel, Stamp,
};
use crate::services::Topic;

/// A received keyframe descriptor, read in place from shared memory.
pub struct DescriptorSample {
    pub(super) sample: Sample<Ipc, KeyframeDescriptor, ()>,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

impl std::ops::Deref for DescriptorSample {
    type Target = KeyframeDescriptor;
    fn deref(&self) -> &KeyframeDescriptor {
        self.sample.payload()
    }
}

/// A received Gaussian patch, read in place from shared memory (no copy).
pub struct PatchSample {
    pub(super) sample: Sample<Ipc, [GaussianRecord], PatchHeader>,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

impl PatchSample {
    /// Sender, keyframe id, record count and [`CoordinateFrame`](crate::messages::CoordinateFrame)
    /// tag.
    pub fn header(&self) -> &PatchHeader {
        self.sample.user_header()
    }

    /// The header's `count` records (checked on receive).
    pub fn records(&self) -> &[GaussianRecord] {
        self.sample.payload()
    }
}

/// A received keyframe RGB-D image, read in place from shared memory (no copy).
pub struct KeyframeImageSample {
    pub(super) sample: Sample<Ipc, [RgbdPixel], KeyframeImageHeader>,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

impl KeyframeImageSample {
    /// Sender, keyframe, pose, intrinsics and image size.
    pub fn header(&self) -> &KeyframeImageHeader {
        self.sample.user_header()
    }

    /// `width * height` pixels, row-major (checked on receive).
    pub fn pixels(&self) -> &[RgbdPixel] {
        self.sample.payload()
    }
}

/// A received lifecycle message (copied out of shared memory: it is small, and a held-back
/// goodbye must not pin a shared-memory sample).
pub struct LifecycleSample {
    pub(super) message: Lifecycle,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

impl std::ops::Deref for LifecycleSample {
    type Target = Lifecycle;
    fn deref(&self) -> &Lifecycle {
        &self.message
    }
}

/// A received correction, read in place from shared memory.
pub struct CorrectionSample {
    pub(super) sample: Sample<Ipc, [KeyframePose], CorrectionHeader>,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

impl CorrectionSample {
    /// Sender, target agent and the agent-world-to-world transform.
    pub fn header(&self) -> &CorrectionHeader {
        self.sample.user_header()
    }

    /// The header's `count` corrected keyframe poses (checked on receive).
    pub fn poses(&self) -> &[KeyframePose] {
        self.sample.payload()
    }
}

/// A received control message, decoded out of shared memory (it holds heap data).
#[derive(Debug, Clone, PartialEq)]
pub struct ControlSample {
    /// The frame's header, copied out of shared memory.
    pub header: ControlHeader,
    /// The decoded message.
    pub message: ControlMessage,
    /// Whether it follows the previous one on its topic in order, after a gap, or opens a new
    /// incarnation ([`Delivery`]).
    pub delivery: Delivery,
}

/// Anything a consumer receives.
pub enum Incoming {
    /// A keyframe descriptor.
    Descriptor(DescriptorSample),
    /// A Gaussian patch.
    Patch(PatchSample),
    /// A keyframe RGB-D image.
    KeyframeImage(KeyframeImageSample),
    /// A hello, heartbeat or goodbye.
    Lifecycle(LifecycleSample),
}

impl Incoming {
    /// The sending agent, from the stamp.
    pub fn agent_id(&self) -> u32 {
        self.stamp().agent_id
    }

    /// The sender's stamp (agent id, epoch, sequence).
    pub fn stamp(&self) -> Stamp {
        match self {
            Incoming::Descriptor(d) => d.stamp,
            Incoming::Patch(p) => p.header().stamp,
            Incoming::KeyframeImage(k) => k.header().stamp,
            Incoming::Lifecycle(l) => l.stamp,
        }
    }

    /// How the message follows the sender's previous one on its topic.
    pub fn delivery(&self) -> Delivery {
        match self {
            Incoming::Descriptor(d) => d.delivery,
            Incoming::Patch(p) => p.delivery,
            Incoming::KeyframeImage(k) => k.delivery,
            Incoming::Lifecycle(l) => l.delivery,
        }
    }

    /// The topic the message came on.
    pub fn topic(&self) -> Topic {
        match self {
            Incoming::Descriptor(_) => Topic::Descriptor,
            Incoming::Patch(_) => Topic::Patch,
            Incoming::KeyframeImage(_) => Topic::KeyframeImage,
            Incoming::Lifecycle(_) => Topic::Lifecycle,
        }
    }
}
