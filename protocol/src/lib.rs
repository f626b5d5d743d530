//! protocol: every message type and service name exchanged between mac-ego3d processes, the
//! control-message codec, the conversions between wire and in-memory types, and the iceoryx2
//! transport. Of this workspace it depends only on geometry and splats, for the in-memory side of
//! the conversions (no GPU crate: a process that only moves messages, mac-bridge included,
//! builds without wgpu).
//!
//! - [`messages`]: `#[repr(C)]` zero-copy payloads (descriptor, Gaussian patch, keyframe RGB-D
//!   image, correction, lifecycle) and the serde control messages (carried consumer -> agent on
//!   the `control` topic as codec frames).
//! - [`services`]: service names, defined once.
//! - [`codec`]: serde + bincode 2 framing with magic and format version.
//! - [`convert`]: every conversion between wire types and the processes' own types (poses,
//!   intrinsics, keyframe RGB-D images, Gaussian clouds), both directions.
//! - [`transport`]: typed publishers/subscribers over iceoryx2 0.10 with delivery handshake,
//!   sequence/gap tracking, a full-queue policy per topic, an agent-id range sized by the swarm,
//!   crash clean-up and bandwidth accounting; its module documentation lists its modules.
//! - [`bench`](mod@bench): the two-process IPC benchmark behind `mac-ego3d bench ipc`.

pub mod bench;
pub mod codec;
pub mod convert;
pub mod messages;
pub mod services;
pub mod transport;
