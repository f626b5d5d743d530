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
    pub delivery: Delivery,
}

impl PatchSample {
    pub fn header(&self) -> &PatchHeader {
        self.sample.user_header()
    }

    pub fn records(&self) -> &[GaussianRecord] {
        self.sample.payload()
    }
}

/// A received keyframe RGB-D image, read in place from shared memory (no copy).
pub struct KeyframeImageSample {
    pub(super) sample: Sample<Ipc, [RgbdPixel], KeyframeImageHeader>,
    pub delivery: Delivery,
}

impl KeyframeImageSample {
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
    pub delivery: Delivery,
}

impl CorrectionSample {
    pub fn header(&self) -> &CorrectionHeader {
        self.sample.user_header()
    }

    pub fn poses(&self) -> &[KeyframePose] {
        self.sample.payload()
    }
}

/// A received control message, decoded out of shared memory (it holds heap data).
#[derive(Debug, Clone, PartialEq)]
pub struct ControlSample {
    pub header: ControlHeader,
    pub message: ControlMessage,
    pub delivery: Delivery,
}

/// Anything a consumer receives.
pub enum Incoming {
    Descriptor(DescriptorSample),
    Patch(PatchSample),
    KeyframeImage(KeyframeImageSample),
    Lifecycle(LifecycleSample),
}

impl Incoming {
    pub fn agent_id(&self) -> u32 {
        self.stamp().agent_id
    }

    pub fn stamp(&self) -> Stamp {
        match self {
            Incoming::Descriptor(d) => d.stamp,
            Incoming::Patch(p) => p.header().stamp,
            Incoming::KeyframeImage(k) => k.header().stamp,
            Incoming::Lifecycle(l) => l.stamp,
        }
    }

    pub fn delivery(&self) -> Delivery {
        match self {
            Incoming::Descriptor(d) => d.delivery,
            Incoming::Patch(p) => p.delivery,
            Incoming::KeyframeImage(k) => k.delivery,
            Incoming::Lifecycle(l) => l.delivery,
        }
    }

    pub fn topic(&self) -> Topic {
        match self {
            Incoming::Descriptor(_) => Topic::Descriptor,
            Incoming::Patch(_) => Topic::Patch,
            Incoming::KeyframeImage(_) => Topic::KeyframeImage,
            Incoming::Lifecycle(_) => Topic::Lifecycle,
        }
    }
}
