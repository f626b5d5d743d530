//! The mapping thread (docs/method.md, Map optimisation and Pruning).
//!
//! The tracker hands every keyframe (its images, its pose and the Gaussians it seeds) to
//! [`Mapper::spawn`]'s thread over a channel and never waits: the send is non-blocking and the
//! mapper picks keyframes up between iterations. The mapper owns the device map and runs Adam over
//! keyframes, new ones first (newest first), then random earlier ones, with the loss
//! `0.8 L1 + 0.2 (1 - SSIM) + 2 L1(depth / truncation)` (weights from `[mapping]`); keyframe poses
//! are fixed (the agent's poses come from tracking; the consensus refines them). Every
//! `prune_every` iterations it prunes (opacity, scale, elongation).
//!
//! Under `mapping.pace = "paced"` the mapper spends exactly `iterations_per_keyframe` iterations
//! after each keyframe, then waits for the next one; [`Mapper::wait_for_budget`] is where the
//! tracker waits for that (docs/method.md, One agent: Pace). Otherwise it iterates whenever it
//! has a map and no command waits.
//!
//! Keyframe targets are uploaded once, when the keyframe arrives. Nothing is read back inside an
//! iteration except a wait for the device to finish it (so the
//! host does not queue unbounded work), the pair-count check every `check_pairs_every`
//! iterations, and the pruning mask.
//!
//! `state.rs` holds the mapping thread's state (keyframes on the device, commands, corrections,
//! the map's download), `iteration.rs` one Adam iteration and the keyframe pose step.

use std::sync::Arc;
use std::sync::atomic::AtomicUsize;
use std::thread::JoinHandle;

use config::{MappingConfig, Pace};
use crossbeam_channel::{Receiver, Sender};
use geometry::camera::Intrinsics;
use geometry::correction::CorrectionField;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;

use registration::config::TrackingConfig;
use render_core::context::{GpuContext, GpuError};
use splats::{GaussianCloud, RigidTransform};

mod iteration;
mod state;
#[cfg(test)]
mod tests;

use state::MapperState;
pub use state::downscale_target;

/// Why a keyframe was made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyframeKind {
    /// Too little overlap with the map: all points seed Gaussians, the new ones trackable.
    Tracking,
    /// Every n-th frame otherwise: uncovered points seed non-trackable Gaussians.
    Mapping,
}

/// A keyframe as the mapper receives it.
pub struct MappingKeyframe {
    /// Keyframe id: ids count up from 0 in the order keyframes are made, and index the moves of
    /// [`Mapper::correct`].
    pub keyframe_id: usize,
    /// The frame's number in its sequence ([`datasets::Frame::index`]).
    pub frame_index: usize,
    /// The frame's timestamp (seconds): where the keyframe anchors its pose refinement's
    /// correction ([`MappingStats::keyframe_pose_corrections`]).
    pub timestamp_s: f64,
    /// Which rule made the keyframe (the mapper optimises both kinds alike).
    pub kind: KeyframeKind,
    /// The camera's pose in the agent's local-map frame (consensus corrections applied), the
    /// frame the map is built in; metres.
    pub world_from_camera: Isometry3<f64>,
    /// Full-resolution intrinsics of `rgb` and `depth`.
    pub intrinsics: Intrinsics,
    /// The frame's colour image, the colour target of its iterations.
    pub rgb: RgbImage,
    /// The frame's depth (metres, 0 = invalid), the depth target of its iterations.
    pub depth: DepthImage,
    /// Gaussians this keyframe adds to the map (world frame).
    pub new_gaussians: GaussianCloud,
}

/// Counters of a mapping phase.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MappingStats {
    /// Adam iterations of the phase (one keyframe view each).
    pub iterations: usize,
    /// Wall time of the phase, seconds.
    pub seconds: f64,
    /// Gaussians removed by pruning during the phase.
    pub pruned: usize,
    /// Keyframes in the map at the end of the phase.
    pub keyframes: usize,
    /// Consensus corrections applied to the map.
    pub corrections: usize,
    /// Loss of the last iteration whose loss was read back (weighted L1, SSIM, depth terms).
    pub last_loss: Option<[f32; 3]>,
    /// `refine_keyframe_poses`: the farthest any keyframe camera moved from its tracked pose,
    /// metres.
    pub max_pose_change_m: f64,
    /// `refine_keyframe_poses`: the largest rotation of any keyframe pose from its tracked pose,
    /// in degrees.
    pub max_pose_change_deg: f64,
    /// `refine_keyframe_poses`: pose steps not taken because they would have moved a pose past
    /// `max_pose_change_m` or `max_pose_change_rad` from its tracked pose.
    pub pose_steps_refused: usize,
    /// `refine_keyframe_poses`: how the refinement moved the cameras, as a correction field
    /// anchored at the keyframes' timestamps (each keyframe's refined pose times its tracked
    /// pose's inverse, blended between keyframes). A frame's camera in this map is
    /// `field.at(t) * (its tracked pose, after consensus corrections)`. Empty otherwise.
    pub keyframe_pose_corrections: CorrectionField,
    /// Iterations whose frame was too large for the fixed gradient order (render-core's
    /// `GradientOrder`) and summed in arrival order: with any, the run does not repeat bit for
    /// bit.
    pub arrival_order_iterations: usize,
    /// Pair checks (every `check_pairs_every` iterations) that found a rasterizer's walk cut
    /// short by the adapter's loop limit: tiles whose splat lists outgrew it.
    pub loop_limited_checks: usize,
}

impl MappingStats {
    /// Iterations per wall-clock second of the phase; 0 when no time was measured.
    pub fn iterations_per_second(&self) -> f64 {
        if self.seconds > 0.0 {
            self.iterations as f64 / self.seconds
        } else {
            0.0
        }
    }
}

/// What the mapping thread returns.
pub struct MappingOutcome {
    /// The map when the stream ended (real-time mapping only).
    pub realtime_map: GaussianCloud,
    /// Counters of real-time mapping (while the frames came in).
    pub realtime: MappingStats,
    /// After the optional refinement pass.
    pub refined: Option<(GaussianCloud, MappingStats)>,
}

/// Why the mapping thread could not start or did not finish.
#[derive(Debug, thiserror::Error)]
pub enum MapperError {
    /// The device failed: no usable adapter at start, or an upload, render or read-back.
    #[error("mapping device: {0}")]
    Gpu(#[from] GpuError),
    /// The mapping thread panicked (or ended before it reported its start).
    #[error("the mapping thread panicked")]
    Panicked,
}

enum Command {
    Keyframe(Box<MappingKeyframe>),
    /// A consensus correction ([`crate::local_corrections`]): the move of each keyframe's part of the
    /// map, indexed by keyframe id (keyframes made later stay).
    Correct(Vec<RigidTransform>),
    Finish {
        refine_iterations: usize,
    },
}

/// Live counters the tracker may read (progress display, logs).
#[derive(Debug, Default)]
pub struct MapperProgress {
    /// Mapping iterations so far, real-time and refinement together.
    pub iterations: AtomicUsize,
    /// Gaussians in the device map after the latest iteration or keyframe.
    pub gaussians: AtomicUsize,
}

/// Handle of the mapping thread.
pub struct Mapper {
    commands: Sender<Command>,
    /// Paced: one message each time the mapper has spent a keyframe's budget.
    budget_spent: Option<Receiver<()>>,
    thread: JoinHandle<Result<MappingOutcome, MapperError>>,
    /// Live counters, updated by the mapping thread.
    pub progress: Arc<MapperProgress>,
}

impl Mapper {
    /// Starts the mapping thread on its own device context.
    pub fn spawn(tracking: &TrackingConfig, mapping: &MappingConfig) -> Result<Self, MapperError> {
        let (commands, receiver) = crossbeam_channel::unbounded();
        let (budget_sender, budget_spent) = match mapping.pace {
            Pace::Paced => {
                let (sender, receiver) = crossbeam_channel::unbounded();
                (Some(sender), Some(receiver))
            }
            Pace::Sensor | Pace::Unthrottled => (None, None),
        };
        let progress = Arc::new(MapperProgress::default());
        let niceness = mapping.background_niceness();
        // The device context is made on the mapping thread, after its priority is lowered: the
        // renderer's worker threads (lavapipe starts them with the device) inherit it. Tracking's
        // worker pool must not: it starts here first, if nothing started it yet.
        if niceness != 0 {
            let _ = rayon::current_num_threads();
        }
        let (started_sender, started) = crossbeam_channel::bounded(1);
        let (tracking, mapping, thread_progress) =
            (tracking.clone(), mapping.clone(), progress.clone());
        let thread = std::thread::Builder::new()
            .name("mapper".into())
            .spawn(move || {
                config::process::lower_thread_priority(niceness);
                let context = match GpuContext::new() {
                    Ok(context) => context,
                    Err(error) => {
                        let _ = started_sender.send(Err(error));
                        return Err(MapperError::Panicked);
                    }
                };
                tracing::info!(adapter = %context.describe(), niceness, "mapping device");
                let state = MapperState::new(context, &tracking, &mapping, thread_progress);
                let _ = started_sender.send(Ok(()));
                state.run(receiver, budget_sender)
            })
            .expect("spawning the mapping thread");
        match started.recv() {
            Ok(Ok(())) => {}
            Ok(Err(error)) => {
                let _ = thread.join();
                return Err(MapperError::Gpu(error));
            }
            Err(_) => {
                let _ = thread.join();
                return Err(MapperError::Panicked);
            }
        }
        Ok(Self {
            commands,
            budget_spent,
            thread,
            progress,
        })
    }

    /// Paced: waits until the mapper has spent its iterations on the keyframe sent last (at
    /// once when the mapping thread has died: `finish` reports that). Otherwise returns at once.
    pub fn wait_for_budget(&self) {
        if let Some(budget_spent) = &self.budget_spent {
            let _ = budget_spent.recv();
        }
    }

    /// Queues a keyframe; never blocks.
    pub fn add_keyframe(&self, keyframe: MappingKeyframe) {
        // The receiver lives until Finish; a send error means the thread died, which `finish`
        // reports.
        let _ = self.commands.send(Command::Keyframe(Box::new(keyframe)));
    }

    /// Moves each keyframe's Gaussians and pose by `keyframe_moves[keyframe id]` (a non-rigid
    /// correction; keyframes past the end stay). Queued behind the keyframes already sent, so
    /// every keyframe it names is in the map when it is applied; never blocks.
    pub fn correct(&self, keyframe_moves: Vec<RigidTransform>) {
        let _ = self.commands.send(Command::Correct(keyframe_moves));
    }

    /// Ends real-time mapping (after the queued keyframes are in the map), runs
    /// `refine_iterations` more iterations over random keyframes, and returns the maps.
    pub fn finish(self, refine_iterations: usize) -> Result<MappingOutcome, MapperError> {
        let _ = self.commands.send(Command::Finish { refine_iterations });
        self.thread.join().map_err(|_| MapperError::Panicked)?
    }
}
