//! The swarm's live view in the [rerun](https://rerun.io) viewer.
//!
//! Every process of a swarm (each `mac-agent`, the `mac-consensus`) can log what it does to
//! rerun under one recording id, so that one viewer shows the whole swarm as it runs, or so that
//! the `.rrd` files they write open together afterwards. A process holds one [`LiveView`]: its
//! methods take the project's own types (poses, intrinsics, images, point sets), and put them on
//! a bounded queue without ever waiting. A background thread owns the `rerun::RecordingStream`,
//! converts and logs. When the queue is full (the viewer or the disk is slower than the swarm),
//! the item is dropped and counted ([`LiveViewStats`]): visualisation never slows tracking.
//! [`LiveView::disabled`] is a handle that does nothing.
//!
//! The processes take the same options ([`LiveViewArgs`]): `--viewer [ADDR]` streams to a
//! viewer over gRPC, `--record DIR` writes `DIR/<process>.rrd`, `--recording-id ID` names the
//! recording (one per swarm run).
//!
//! # Entity paths
//!
//! Agent `K` logs in its own frame, under `world/agent_K`, whose transform is the consensus's
//! latest `world_from_agent` (the identity until the consensus has placed the agent), so the
//! viewer shows every agent in the world frame as far as the consensus knows it.
//!
//! | entity | logged by | holds |
//! |---|---|---|
//! | `world` | every process | ViewCoordinates (static): x right, y down, z forward (agent 0's first camera frame is the world frame) |
//! | `world/agent_K` | agent K | Transform3D: `world_from_agent`, after each correction |
//! | `world/agent_K/camera` | agent K | Transform3D (camera pose), Pinhole and the colour Image, per frame (timeline `frame`) |
//! | `world/agent_K/trajectory` | agent K | LineStrips3D: the tracked path so far |
//! | `world/agent_K/keyframes` | agent K | Points3D: the keyframes' camera positions |
//! | `world/agent_K/map` | agent K | Points3D: the map's Gaussians as coloured points, at most `map_points_max`; the final map at the end |
//! | `world/consensus/closures` | consensus | LineStrips3D: one line per closure attempt between the two keyframes' positions, green accepted, orange verified but dropped by the pose graph, red rejected |
//! | `world/consensus/trajectories/agent_K` | consensus | LineStrips3D: agent K's keyframe positions after each pose-graph solve |
//! | `world/consensus/map` | consensus | Points3D: the merged world map when it is written |
//! | `consensus/latency_ms` | consensus | Scalars: each keyframe's consensus latency |
//! | `consensus/closures/accepted`, `consensus/closures/rejected` | consensus | Scalars: counts so far |
//! | `consensus/agent_K/kbps` | consensus | Scalars: kB/s received from agent K |
//! | `consensus/refinement/psnr_db` | consensus | Scalars: the joint refinement's PSNR over its views, before and after (its loss stays on the device) |

mod args;
mod handle;
mod items;
pub mod paths;
mod points;
mod rrd;

pub use args::{DEFAULT_VIEWER_ADDRESS, LiveViewArgs, viewer_url};
pub use handle::{LiveView, LiveViewSettings, LiveViewStats};
pub use items::{ClosureLine, ClosureOutcome};
pub use points::ColouredPoints;
pub use rrd::RrdSummary;

/// The rerun application id every process logs under.
pub const APPLICATION_ID: &str = "mac-ego3d";
