//! Wire payloads shared by every mac-ego3d process.
//!
//! Every type here is `#[repr(C)]` and derives iceoryx2's `ZeroCopySend`, so it is written once
//! into shared memory by the sender and read in place by the receiver. Rules kept at this
//! boundary:
//! - Quaternions are stored **w first**: `[w, x, y, z]` (field names end in `_wxyz`).
//! - Poses are rigid transforms `p_target = R(q) * p_source + t` stored as [`Pose`].
//! - Enumerations travel as `u32` tags with checked accessors, never as Rust enums, so a corrupt
//!   or newer tag is reported as an error instead of being undefined behaviour.
//! - Every message carries a [`Stamp`] (agent id, incarnation epoch, sequence number); the
//!   transport fills it in, receivers use it for gap and restart detection.
//! - Every type is also `bytemuck::Pod` (checked at compile time: no padding, any bit pattern
//!   valid), so the cross-host relay ([`crate::transport::relay`]) can carry it as plain bytes.
//! - Type names carry [`WIRE_VERSION`] (`mac.v2.*`): iceoryx2 refuses to connect a process built
//!   with another layout version to the same service (`IncompatibleTypes`).

use bytemuck::{Pod, Zeroable};
use iceoryx2::prelude::ZeroCopySend;
use serde::{Deserialize, Serialize};

/// Version of the shared-memory layouts below. Baked into every `type_name` as `v2`; bump both
/// together when a layout changes.
pub const WIRE_VERSION: u32 = 2;

/// Length of the global keyframe descriptor: AlexNet's last convolution has 256 channels, and
/// GeM pooling keeps one value per channel. The classical thumbnail fallback is resampled to the
/// same length so both kinds share one wire type.
pub const DESCRIPTOR_LEN: usize = 256;

/// Tolerance on `| ||d|| - 1 |` accepted for an "L2-normalised" descriptor: f32 summation over
/// 256 entries loses about 1e-6 relative; 1e-3 still catches a forgotten normalisation.
pub const DESCRIPTOR_NORM_TOLERANCE: f32 = 1e-3;

/// Agent id used in the [`Stamp`] of messages sent by the consensus (or another consumer).
pub const CONSUMER_AGENT_ID: u32 = u32::MAX;

/// Keyframe id of the Gaussian patch in which an agent sends its final optimised map (in its own
/// frame) before it says goodbye; no real keyframe has this id.
pub const FINAL_MAP_KEYFRAME_ID: u64 = u64::MAX;

/// Sender identity and ordering, carried by every message.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize,
)]
#[repr(C)]
#[type_name("mac.v2.Stamp")]
pub struct Stamp {
    /// Sending agent, or [`CONSUMER_AGENT_ID`] for the consensus.
    pub agent_id: u32,
    /// Explicit padding so the layout has no implicit holes.
    pub reserved: u32,
    /// Incarnation of the sending process (nanoseconds since the Unix epoch at start-up): a
    /// restarted process has a larger epoch and its sequence numbers start again at 0.
    pub epoch: u64,
    /// Per (sender, topic) counter starting at 0 in every epoch; a jump is a lost message.
    pub sequence: u64,
}

/// Rigid transform. `translation` in metres; `rotation_wxyz` a unit quaternion, w first.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize)]
#[repr(C)]
#[type_name("mac.v2.Pose")]
pub struct Pose {
    /// Translation in metres: the source frame's origin in target coordinates.
    pub translation: [f64; 3],
    /// Unit quaternion `[w, x, y, z]`.
    pub rotation_wxyz: [f64; 4],
}

impl Pose {
    /// The identity transform (no translation, quaternion `[1, 0, 0, 0]`); also the `Default`.
    pub const IDENTITY: Pose = Pose {
        translation: [0.0; 3],
        rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
    };

    /// Finite values and a quaternion of unit norm (within `tolerance`).
    pub fn is_valid(&self, tolerance: f64) -> bool {
        let finite = self
            .translation
            .iter()
            .chain(&self.rotation_wxyz)
            .all(|v| v.is_finite());
        let norm = self.rotation_wxyz.iter().map(|v| v * v).sum::<f64>().sqrt();
        finite && (norm - 1.0).abs() <= tolerance
    }
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// Pinhole intrinsics of the camera that produced a keyframe, in pixels.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize,
)]
#[repr(C)]
#[type_name("mac.v2.Intrinsics")]
pub struct Intrinsics {
    /// Focal length along the image columns (x), pixels.
    pub fx: f64,
    /// Focal length along the image rows (y), pixels.
    pub fy: f64,
    /// Principal point column, pixels (pixel centres sit at integer coordinates).
    pub cx: f64,
    /// Principal point row, pixels.
    pub cy: f64,
    /// Image width in pixels (columns).
    pub width: u32,
    /// Image height in pixels (rows).
    pub height: u32,
}

/// Inter-agent selection input (docs/method.md, The consensus: selection): the latest
/// keyframe's global descriptor and pose. Topic `mac/agent/{id}/descriptor`, agent -> consensus.
#[derive(Debug, Clone, Copy, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.KeyframeDescriptor")]
pub struct KeyframeDescriptor {
    /// Sender and ordering; filled in by the transport on send.
    pub stamp: Stamp,
    /// The agent's id of the keyframe (counted up from 0); its keyframe image and patch carry
    /// the same id.
    pub keyframe_id: u64,
    /// Index of the frame in the agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// Camera-to-agent-world transform of the keyframe (agent's own world frame).
    pub camera_to_agent_world: Pose,
    /// Pinhole intrinsics of the keyframe's camera.
    pub intrinsics: Intrinsics,
    /// L2-normalised global image descriptor (scores are dot products).
    pub descriptor: [f32; DESCRIPTOR_LEN],
}

impl KeyframeDescriptor {
    /// A descriptor with zeroed fields and an identity pose; callers fill what they know.
    pub fn new(keyframe_id: u64, frame_index: u64, timestamp_s: f64) -> Self {
        Self {
            stamp: Stamp::default(),
            keyframe_id,
            frame_index,
            timestamp_s,
            camera_to_agent_world: Pose::IDENTITY,
            intrinsics: Intrinsics::default(),
            descriptor: [0.0; DESCRIPTOR_LEN],
        }
    }

    /// Euclidean norm of the descriptor (1 for a well-formed message).
    pub fn descriptor_norm(&self) -> f32 {
        self.descriptor.iter().map(|v| v * v).sum::<f32>().sqrt()
    }

    /// Divides the descriptor by its norm. Returns false (and leaves it unchanged) when the norm
    /// is zero or not finite, since such a vector has no direction to keep.
    pub fn normalise_descriptor(&mut self) -> bool {
        let norm = self.descriptor_norm();
        if !norm.is_finite() || norm == 0.0 {
            return false;
        }
        self.descriptor.iter_mut().for_each(|v| *v /= norm);
        true
    }

    /// Dot-product similarity of two descriptors: the selection score (docs/method.md, The
    /// consensus: selection).
    pub fn score(&self, other: &KeyframeDescriptor) -> f32 {
        descriptor_score(&self.descriptor, &other.descriptor)
    }
}

/// Similarity of two global descriptors: their dot product, the cosine as both are unit length
/// (docs/method.md, The consensus: selection).
pub fn descriptor_score(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// One Gaussian of the map (docs/method.md, The map). 14 f32 = 56 bytes, no padding.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize,
)]
#[repr(C)]
#[type_name("mac.v2.GaussianRecord")]
pub struct GaussianRecord {
    /// Mean position, metres, in the frame named by the patch header.
    pub mean: [f32; 3],
    /// Natural log of the three axis standard deviations (metres).
    pub log_scale: [f32; 3],
    /// Unit quaternion `[w, x, y, z]` of the principal axes.
    pub rotation_wxyz: [f32; 4],
    /// Opacity before the sigmoid.
    pub opacity_logit: f32,
    /// RGB colour in [0, 1] (SH degree 0).
    pub colour: [f32; 3],
}

/// Frame in which the records of a patch are expressed (a `u32` tag on the wire).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u32)]
pub enum CoordinateFrame {
    /// The agent's own world frame (its first camera pose). Keyframe patches are in the agent's
    /// tracked frame; the final map is in the agent's local-map frame, which the corrections
    /// the agent applied have moved so that `world_from_agent` places it in the world.
    AgentWorld = 0,
    /// The shared world frame (agent 0's first pose), after a correction.
    World = 1,
}

impl TryFrom<u32> for CoordinateFrame {
    type Error = UnknownTag;
    fn try_from(tag: u32) -> Result<Self, UnknownTag> {
        match tag {
            0 => Ok(Self::AgentWorld),
            1 => Ok(Self::World),
            _ => Err(UnknownTag {
                field: "coordinate frame",
                tag,
            }),
        }
    }
}

/// A `u32` tag on the wire that names no known variant (corrupt, or from a newer sender).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("unknown {field} tag {tag}")]
pub struct UnknownTag {
    /// The field that held the tag (`"coordinate frame"` or `"lifecycle kind"`).
    pub field: &'static str,
    /// The value found.
    pub tag: u32,
}

/// User header of a Gaussian patch (topic `mac/agent/{id}/patch`, agent -> consensus); the
/// payload is a slice of `count` [`GaussianRecord`]s.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.PatchHeader")]
pub struct PatchHeader {
    /// Sender and ordering; filled in by the transport on send.
    pub stamp: Stamp,
    /// Keyframe whose Gaussians these are.
    pub keyframe_id: u64,
    /// Number of records in the slice (checked against the slice length on receive).
    pub count: u64,
    /// [`CoordinateFrame`] tag.
    pub frame: u32,
    /// Explicit padding.
    pub reserved: u32,
}

impl PatchHeader {
    /// The [`CoordinateFrame`] of the records; [`UnknownTag`] when the tag names none.
    pub fn frame(&self) -> Result<CoordinateFrame, UnknownTag> {
        CoordinateFrame::try_from(self.frame)
    }
}

/// One pixel of a keyframe's RGB-D image: 8-bit sRGB colour and depth in millimetres. 6 bytes,
/// alignment 2, no padding (the explicit `reserved` byte fills the hole before `depth_mm`).
/// Millimetres in a `u16` cover 0.001 m to 65.535 m, beyond the range of any RGB-D sensor, at a
/// third of the size of an RGB + f32 depth layout.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize,
)]
#[repr(C)]
#[type_name("mac.v2.RgbdPixel")]
pub struct RgbdPixel {
    /// Colour `[r, g, b]`, 0..=255.
    pub rgb: [u8; 3],
    /// Explicit padding; senders write 0.
    pub reserved: u8,
    /// Depth along the optical axis in millimetres; [`RgbdPixel::INVALID_DEPTH_MM`] (0) means no
    /// measurement (hole, out of range, or saturated), as in the TUM/Replica depth PNGs.
    pub depth_mm: u16,
}

impl RgbdPixel {
    /// `depth_mm` value of a pixel without a depth measurement.
    pub const INVALID_DEPTH_MM: u16 = 0;

    /// Millimetres per metre: the wire carries depth in whole millimetres.
    const MM_PER_M: f32 = 1000.0;

    /// A pixel from a colour and a depth in metres; non-finite, non-positive or out-of-range
    /// (over 65.535 m) depth becomes [`RgbdPixel::INVALID_DEPTH_MM`].
    pub fn new(rgb: [u8; 3], depth_m: f32) -> Self {
        let mm = depth_m * Self::MM_PER_M;
        let depth_mm = if mm.is_finite() && mm > 0.0 && mm <= f32::from(u16::MAX) {
            mm.round() as u16
        } else {
            Self::INVALID_DEPTH_MM
        };
        Self {
            rgb,
            reserved: 0,
            depth_mm,
        }
    }

    /// Depth in metres, `None` where the pixel has no measurement.
    pub fn depth_m(&self) -> Option<f32> {
        (self.depth_mm != Self::INVALID_DEPTH_MM).then(|| f32::from(self.depth_mm) / Self::MM_PER_M)
    }
}

/// User header of a keyframe's RGB-D image (topic `mac/agent/{id}/keyframe_image`, agent ->
/// consensus); the payload is a slice of `width * height` [`RgbdPixel`]s in row-major order
/// (row 0 first, left to right). The consensus lifts image features of different agents'
/// keyframes to 3-D with the depth and these intrinsics to align the agents.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.KeyframeImageHeader")]
pub struct KeyframeImageHeader {
    /// Sender and ordering; filled in by the transport on send.
    pub stamp: Stamp,
    /// Keyframe this image belongs to (same id as its descriptor and patch).
    pub keyframe_id: u64,
    /// Index of the frame in the agent's input sequence.
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// Camera-to-agent-world transform of the keyframe (agent's own world frame).
    pub camera_to_agent_world: Pose,
    /// Intrinsics of the image as sent: when the agent downscales the image, these are the
    /// scaled intrinsics, and their `width`/`height` equal the fields below.
    pub intrinsics: Intrinsics,
    /// Image size in pixels; the slice holds `width * height` pixels.
    pub width: u32,
    /// Image height in pixels (rows).
    pub height: u32,
}

impl KeyframeImageHeader {
    /// Number of pixels the header announces (`width * height`, without overflow).
    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }
}

/// An updated keyframe pose inside a correction.
#[derive(
    Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable, Serialize, Deserialize,
)]
#[repr(C)]
#[type_name("mac.v2.KeyframePose")]
pub struct KeyframePose {
    /// Keyframe of the receiving agent whose pose this is.
    pub keyframe_id: u64,
    /// Corrected camera-to-world pose (shared world frame).
    pub camera_to_world: Pose,
}

/// User header of a correction (topic `mac/agent/{id}/correction`, consensus -> agent `id`); the
/// payload is a slice of `count` [`KeyframePose`]s.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.CorrectionHeader")]
pub struct CorrectionHeader {
    /// Sender and ordering (agent id [`CONSUMER_AGENT_ID`]); filled in by the transport on send.
    pub stamp: Stamp,
    /// Agent the correction is for (the service is per agent; repeated for logging and checks).
    pub target_agent_id: u32,
    /// Explicit padding.
    pub reserved: u32,
    /// Agent-world-to-world transform estimated by the consensus.
    pub agent_world_to_world: Pose,
    /// Number of keyframe poses in the slice.
    pub count: u64,
}

/// Kind of a lifecycle message (a `u32` tag on the wire).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[repr(u32)]
pub enum LifecycleKind {
    /// First message of an incarnation: intrinsics and configuration hash are valid.
    Hello = 1,
    /// Periodic heartbeat.
    Alive = 2,
    /// Orderly shutdown; no more messages from this epoch.
    Goodbye = 3,
}

impl TryFrom<u32> for LifecycleKind {
    type Error = UnknownTag;
    fn try_from(tag: u32) -> Result<Self, UnknownTag> {
        match tag {
            1 => Ok(Self::Hello),
            2 => Ok(Self::Alive),
            3 => Ok(Self::Goodbye),
            _ => Err(UnknownTag {
                field: "lifecycle kind",
                tag,
            }),
        }
    }
}

/// Heartbeat / lifecycle message (topic `mac/lifecycle`, every process -> every consumer).
/// A tagged struct rather than an enum so that unknown tags are detectable (see module doc).
#[derive(Debug, Clone, Copy, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.Lifecycle")]
pub struct Lifecycle {
    /// Sender and ordering; filled in by the transport on send.
    pub stamp: Stamp,
    /// [`LifecycleKind`] tag.
    pub kind: u32,
    /// [`WIRE_VERSION`] of the sender (informative; the type names already enforce it).
    pub wire_version: u32,
    /// Hello only: the agent's camera.
    pub intrinsics: Intrinsics,
    /// Hello only: hash of the agent's configuration, so the consensus can refuse a swarm whose
    /// agents run with different settings.
    pub config_hash: u64,
    /// Hello only: identifies the frame the agent tracks in, which is anchored at its first
    /// frame: a hash of its dataset and first frame. A restart that replays the same frames
    /// sends the same value; one on other frames another (the consensus then ignores it).
    pub run_anchor: u64,
}

impl Lifecycle {
    /// The first message of an incarnation: the agent's camera, configuration hash and run
    /// anchor (see the fields). The transport fills in the stamp.
    pub fn hello(intrinsics: Intrinsics, config_hash: u64, run_anchor: u64) -> Self {
        Self {
            run_anchor,
            ..Self::with_kind(LifecycleKind::Hello, intrinsics, config_hash)
        }
    }

    /// A heartbeat; intrinsics, configuration hash and run anchor are zero.
    pub fn alive() -> Self {
        Self::with_kind(LifecycleKind::Alive, Intrinsics::default(), 0)
    }

    /// An orderly goodbye; intrinsics, configuration hash and run anchor are zero.
    pub fn goodbye() -> Self {
        Self::with_kind(LifecycleKind::Goodbye, Intrinsics::default(), 0)
    }

    fn with_kind(kind: LifecycleKind, intrinsics: Intrinsics, config_hash: u64) -> Self {
        Self {
            stamp: Stamp::default(),
            kind: kind as u32,
            wire_version: WIRE_VERSION,
            intrinsics,
            config_hash,
            run_anchor: 0,
        }
    }

    /// The [`LifecycleKind`]; [`UnknownTag`] when the tag names none.
    pub fn kind(&self) -> Result<LifecycleKind, UnknownTag> {
        LifecycleKind::try_from(self.kind)
    }
}

/// User header of a control frame (topic `mac/agent/{id}/control`, consensus -> agent `id`);
/// the payload is `frame_len` bytes of one [`crate::codec`] frame holding a [`ControlMessage`].
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, Pod, Zeroable)]
#[repr(C)]
#[type_name("mac.v2.ControlHeader")]
pub struct ControlHeader {
    /// Sender and ordering (agent id [`CONSUMER_AGENT_ID`]); filled in by the transport on send.
    pub stamp: Stamp,
    /// Agent the message is for (the service is per agent; repeated for checks).
    pub target_agent_id: u32,
    /// Explicit padding.
    pub reserved: u32,
    /// Bytes in the slice: the whole codec frame, header included.
    pub frame_len: u64,
}

/// Control messages with heap data. They travel through [`crate::codec`] (serde + bincode 2),
/// never as shared-memory layouts; on the `control` topic (consensus -> agent) as a codec frame
/// in a byte slice. New variants go at the end and bump [`crate::codec::FORMAT_VERSION`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ControlMessage {
    /// An agent's full configuration (TOML text) for the swarm record; `Lifecycle::Hello` only
    /// carries its hash.
    AgentConfig {
        /// The agent whose configuration this is.
        agent_id: u32,
        /// The configuration as TOML text.
        config_toml: String,
    },
    /// Orderly stop of the whole swarm, with the reason shown to the user: an agent finishes its
    /// current frame, sends its final map and says goodbye.
    Shutdown {
        /// Why the swarm stops, as shown to the user.
        reason: String,
    },
    /// The consensus holds a keyframe it cannot use (e.g. a descriptor whose keyframe image or
    /// patch never arrived, a gap on that topic) and asks its agent to publish it again, with
    /// the reason for the log. An agent that no longer holds the keyframe ignores the request.
    ResendKeyframe {
        /// The keyframe whose descriptor, image and patch the agent publishes again.
        keyframe_id: u64,
        /// Why the consensus asks, for the agent's log.
        reason: String,
    },
    /// A consensus restarted on its run's store is back: it holds these keyframes of the agent
    /// complete. The agent publishes again every keyframe it still holds that is not among
    /// them (they were lost with the previous consensus process, or never reached it).
    ConsensusResumed {
        /// Ids of the agent's keyframes the restarted consensus holds complete.
        keyframes_held: Vec<u64>,
    },
    /// Messages of the agent were lost on the way (its sequence numbers jumped: e.g. the bridge
    /// of its host died holding them). The consensus holds `keyframes_held` complete and
    /// `keyframes_in_part` in part (it asks for their missing parts itself with
    /// [`ControlMessage::ResendKeyframe`]); the agent publishes again every keyframe up to
    /// `newest_seen` (the newest id the consensus has seen of it; later ones may still be on
    /// the way) that is in neither and that it still holds.
    MessagesLost {
        /// Ids of the agent's keyframes the consensus holds complete.
        keyframes_held: Vec<u64>,
        /// Ids of the agent's keyframes it holds only some messages of.
        keyframes_in_part: Vec<u64>,
        /// The newest keyframe id of the agent the consensus has seen.
        newest_seen: u64,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_record_is_fourteen_packed_floats() {
        assert_eq!(std::mem::size_of::<GaussianRecord>(), 14 * 4);
        assert_eq!(std::mem::align_of::<GaussianRecord>(), 4);
    }

    #[test]
    fn headers_have_no_implicit_padding() {
        // Sum of field sizes == struct size means no hidden holes.
        assert_eq!(std::mem::size_of::<Stamp>(), 4 + 4 + 8 + 8);
        assert_eq!(std::mem::size_of::<PatchHeader>(), 24 + 8 + 8 + 4 + 4);
        assert_eq!(std::mem::size_of::<Pose>(), 7 * 8);
        assert_eq!(std::mem::size_of::<Intrinsics>(), 4 * 8 + 2 * 4);
        assert_eq!(std::mem::size_of::<CorrectionHeader>(), 24 + 8 + 56 + 8);
        assert_eq!(std::mem::size_of::<KeyframePose>(), 8 + 56);
        assert_eq!(std::mem::size_of::<ControlHeader>(), 24 + 4 + 4 + 8);
        assert_eq!(std::mem::size_of::<Lifecycle>(), 24 + 8 + 40 + 8 + 8);
        assert_eq!(std::mem::size_of::<RgbdPixel>(), 3 + 1 + 2);
        assert_eq!(std::mem::align_of::<RgbdPixel>(), 2);
        assert_eq!(
            std::mem::size_of::<KeyframeImageHeader>(),
            24 + 8 + 8 + 8 + 56 + 40 + 4 + 4
        );
        assert_eq!(
            std::mem::size_of::<KeyframeDescriptor>(),
            24 + 8 + 8 + 8 + 56 + 40 + 4 * DESCRIPTOR_LEN
        );
    }

    #[test]
    fn tags_round_trip_and_unknown_tags_are_errors() {
        for kind in [
            LifecycleKind::Hello,
            LifecycleKind::Alive,
            LifecycleKind::Goodbye,
        ] {
            assert_eq!(LifecycleKind::try_from(kind as u32), Ok(kind));
        }
        assert_eq!(LifecycleKind::try_from(0).unwrap_err().tag, 0);
        assert_eq!(CoordinateFrame::try_from(1), Ok(CoordinateFrame::World));
        assert!(CoordinateFrame::try_from(7).is_err());
        assert_eq!(
            Lifecycle::hello(Intrinsics::default(), 9, 7).kind(),
            Ok(LifecycleKind::Hello)
        );
    }

    #[test]
    fn descriptor_normalisation() {
        let mut d = KeyframeDescriptor::new(1, 2, 0.5);
        assert!(!d.normalise_descriptor(), "a zero vector has no direction");
        d.descriptor[0] = 3.0;
        d.descriptor[1] = 4.0;
        assert!(d.normalise_descriptor());
        assert!((d.descriptor_norm() - 1.0).abs() < 1e-6);
        assert!((d.score(&d) - 1.0).abs() < 1e-6);
        assert!((d.descriptor[0] - 0.6).abs() < 1e-6);
    }

    #[test]
    fn pixel_depth_zero_is_invalid() {
        let mut pixel = RgbdPixel::default();
        assert_eq!(pixel.depth_m(), None);
        pixel.depth_mm = 1500;
        assert_eq!(pixel.depth_m(), Some(1.5));
    }

    #[test]
    fn pose_validity() {
        assert!(Pose::IDENTITY.is_valid(1e-9));
        let mut p = Pose::IDENTITY;
        p.rotation_wxyz = [2.0, 0.0, 0.0, 0.0];
        assert!(!p.is_valid(1e-6));
        p = Pose::IDENTITY;
        p.translation[1] = f64::NAN;
        assert!(!p.is_valid(1e-6));
    }
}
