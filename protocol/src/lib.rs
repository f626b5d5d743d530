//! protocol: every message type and service name exchanged between mac-ego3d processes, the
//! control-message codec and the iceoryx2 transport. Depends on nothing else of this workspace.
//!
//! - [`messages`]: `#[repr(C)]` zero-copy payloads (descriptor, Gaussian patch, keyframe RGB-D
//!   image, correction, lifecycle) and the serde control messages (carried consumer -> agent on
//!   the `control` topic as codec frames).
//! - [`services`]: service names, defined once.
//! - [`codec`]: serde + bincode 2 framing with magic and format version.
//! - [`convert`]: wire poses to and from nalgebra isometries.
//! - [`transport`]: typed publishers/subscribers over iceoryx2 0.10 with delivery handshake,
//!   sequence/gap tracking, a full-queue policy per topic, an agent-id range sized by the swarm,
//!   crash clean-up and bandwidth accounting.
//! - [`bench`](mod@bench): the two-process IPC benchmark behind `mac-ego3d bench ipc`.

pub mod bench;
pub mod codec;
pub mod convert;
pub mod messages;
pub mod services;
pub mod transport;
