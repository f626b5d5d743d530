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

use std::borrow::Cow;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::thread::JoinHandle;
use std::time::Instant;

use config::{MappingConfig, Pace};
use crossbeam_channel::{Receiver, Sender, TryRecvError};
use geometry::camera::Intrinsics;
use geometry::correction::{CorrectionField, correction};
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::{Isometry3, Vector6};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use registration::config::TrackingConfig;
use render_core::backward::DeviceImageGradients;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::GpuRenderer;
use render_core::map::{DeviceMap, PruneCriteria};
use render_core::pose::{PoseAdam, pose_rates};
use render_core::training::{DeviceTarget, LossWeights, TargetImage, TrainingKernels};
use render_core::types::{Camera, GaussianCloud, PoseGradient, RasterConfig, RigidTransform};

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
    pub keyframe_id: usize,
    pub frame_index: usize,
    /// The frame's timestamp (seconds): where the keyframe anchors its pose refinement's
    /// correction ([`MappingStats::keyframe_pose_corrections`]).
    pub timestamp_s: f64,
    pub kind: KeyframeKind,
    pub world_from_camera: Isometry3<f64>,
    /// Full-resolution intrinsics of `rgb` and `depth`.
    pub intrinsics: Intrinsics,
    pub rgb: RgbImage,
    pub depth: DepthImage,
    /// Gaussians this keyframe adds to the map (world frame).
    pub new_gaussians: GaussianCloud,
}

/// Counters of a mapping phase.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MappingStats {
    pub iterations: usize,
    /// Wall time of the phase, seconds.
    pub seconds: f64,
    pub pruned: usize,
    pub keyframes: usize,
    /// Consensus corrections applied to the map.
    pub corrections: usize,
    /// Loss of the last iteration whose loss was read back (weighted L1, SSIM, depth terms).
    pub last_loss: Option<[f32; 3]>,
    /// `refine_keyframe_poses`: the farthest any keyframe pose moved from its tracked pose
    /// (metres, degrees), and the pose steps not taken for going past the bound.
    pub max_pose_change_m: f64,
    pub max_pose_change_deg: f64,
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
    /// `refine_keyframe_poses` only: how `realtime_map` moves from where the pose refinement
    /// put the keyframe cameras back to their tracked poses (see
    /// [`MappingOutcome::realtime_map_at_tracked_poses`]).
    pub tracked_pose_moves: Option<TrackedPoseMoves>,
    pub realtime: MappingStats,
    /// After the optional refinement pass.
    pub refined: Option<(GaussianCloud, MappingStats)>,
}

impl MappingOutcome {
    /// `realtime_map` as the consensus is sent it: moved back to the tracked keyframe poses
    /// when the mapper refined them, since the consensus places the map with the tracked
    /// keyframes it knows; otherwise `realtime_map` itself. Built on demand: only a swarm agent
    /// needs the moved copy.
    pub fn realtime_map_at_tracked_poses(&self) -> Cow<'_, GaussianCloud> {
        match &self.tracked_pose_moves {
            Some(moves) => Cow::Owned(moves.apply(&self.realtime_map)),
            None => Cow::Borrowed(&self.realtime_map),
        }
    }
}

/// Moves a map from refined keyframe cameras back to tracked ones: each Gaussian by its
/// seeding keyframe's tracked `world_from_camera` times its refined `camera_from_world`.
pub struct TrackedPoseMoves {
    /// Per Gaussian of the map it was made for: its seeding keyframe's id.
    keyframe_of: Vec<u32>,
    /// Per keyframe id.
    moves: Vec<RigidTransform>,
}

impl TrackedPoseMoves {
    pub fn apply(&self, map: &GaussianCloud) -> GaussianCloud {
        let mut moved = map.clone();
        moved.transform_groups(&self.keyframe_of, &self.moves);
        moved
    }
}

#[derive(Debug, thiserror::Error)]
pub enum MapperError {
    #[error("mapping device: {0}")]
    Gpu(#[from] GpuError),
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
    pub iterations: AtomicUsize,
    pub gaussians: AtomicUsize,
}

/// Handle of the mapping thread.
pub struct Mapper {
    commands: Sender<Command>,
    /// Paced: one message each time the mapper has spent a keyframe's budget.
    budget_spent: Option<Receiver<()>>,
    thread: JoinHandle<Result<MappingOutcome, MapperError>>,
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

/// A keyframe kept for optimisation, at mapping resolution; its target lives on the device
/// (uploaded once, not every iteration).
struct StoredKeyframe {
    keyframe_id: usize,
    camera: Camera,
    target: DeviceTarget,
    /// dL/d(image) of its iterations (the loss kernel rewrites every pixel, so one buffer per
    /// keyframe serves every visit).
    image_gradients: DeviceImageGradients,
    timestamp_s: f64,
    /// The pose tracking gave it (moved by consensus corrections as `camera` is): what
    /// `camera` may move away from by at most `max_pose_change_*` when poses are refined.
    tracked_camera_from_world: RigidTransform,
    pose_adam: PoseAdam,
}

struct MapperState {
    context: GpuContext,
    renderer: GpuRenderer,
    kernels: TrainingKernels,
    map: Option<DeviceMap>,
    /// Per Gaussian of `map`, in its order: the id of the keyframe that seeded it (what a
    /// correction moves it with). Follows appends and pruning.
    keyframe_of: Vec<u32>,
    keyframes: Vec<StoredKeyframe>,
    /// Keyframes not optimised yet, oldest first (popped from the back: newest first).
    unvisited: Vec<usize>,
    rng: ChaCha8Rng,
    weights: LossWeights,
    raster: RasterConfig,
    prune_criteria: PruneCriteria,
    config: MappingConfig,
    /// Multiplies the mean learning rate (the method scales it by the scene's size), fixed at the first keyframe.
    scene_scale: Option<f64>,
    progress: Arc<MapperProgress>,
    stats: MappingStats,
    /// Iterations since the last pair-count check.
    since_pair_check: usize,
}

impl MapperState {
    fn new(
        context: GpuContext,
        tracking: &TrackingConfig,
        mapping: &MappingConfig,
        progress: Arc<MapperProgress>,
    ) -> Self {
        let renderer = GpuRenderer::new(&context);
        let kernels = TrainingKernels::new(&context);
        Self {
            context,
            renderer,
            kernels,
            map: None,
            keyframe_of: Vec::new(),
            keyframes: Vec::new(),
            unvisited: Vec::new(),
            rng: ChaCha8Rng::seed_from_u64(mapping.random_seed),
            weights: LossWeights {
                l1: mapping.weight_l1 as f32,
                ssim: mapping.weight_ssim as f32,
                depth: mapping.weight_depth as f32,
                depth_truncation: tracking.truncation_m as f32,
            },
            raster: RasterConfig::default(),
            prune_criteria: PruneCriteria {
                min_opacity: mapping.prune_min_opacity as f32,
                max_scale_m: mapping.prune_max_scale_m as f32,
                max_elongation: mapping.prune_max_elongation as f32,
            },
            config: mapping.clone(),
            scene_scale: None,
            progress,
            stats: MappingStats::default(),
            since_pair_check: 0,
        }
    }

    /// The real-time loop, then the optional refinement. `budget_spent` (paced only) hears each
    /// time a keyframe's iterations are spent.
    fn run(
        mut self,
        commands: Receiver<Command>,
        budget_spent: Option<Sender<()>>,
    ) -> Result<MappingOutcome, MapperError> {
        let _span = tracing::info_span!("mapping").entered();
        let started = Instant::now();
        // Paced: iterations still owed to the newest keyframe.
        let mut budget_left = 0usize;
        let refine_iterations = loop {
            // Take every queued keyframe before the next iteration; block when there is nothing
            // to optimise yet, or (paced) when the budget is spent.
            let idle = self.map_is_empty() || (budget_spent.is_some() && budget_left == 0);
            if idle && budget_left > 0 {
                // Nothing to optimise (a keyframe without Gaussians on an empty map): the
                // budget lapses rather than hold the tracker.
                budget_left = 0;
                notify(&budget_spent);
            }
            let command = if idle {
                match commands.recv() {
                    Ok(command) => Some(command),
                    Err(_) => break 0,
                }
            } else {
                match commands.try_recv() {
                    Ok(command) => Some(command),
                    Err(TryRecvError::Empty) => None,
                    Err(TryRecvError::Disconnected) => break 0,
                }
            };
            match command {
                Some(Command::Keyframe(keyframe)) => {
                    self.insert_keyframe(*keyframe)?;
                    if budget_spent.is_some() {
                        budget_left += self.config.iterations_per_keyframe;
                    }
                }
                Some(Command::Correct(keyframe_moves)) => self.correct(&keyframe_moves)?,
                Some(Command::Finish { refine_iterations }) => break refine_iterations,
                None => {
                    let stepped = self.iterate()?;
                    self.simulate_slower_machine();
                    if stepped && budget_left > 0 {
                        budget_left -= 1;
                        if budget_left == 0 {
                            notify(&budget_spent);
                        }
                    }
                }
            }
        };
        self.stats.seconds = started.elapsed().as_secs_f64();
        self.stats.keyframe_pose_corrections = self.keyframe_pose_corrections();
        let realtime = std::mem::take(&mut self.stats);
        let realtime_map = self.download()?;
        let tracked_pose_moves = self.tracked_pose_moves();
        tracing::info!(
            iterations = realtime.iterations,
            per_second = format!("{:.2}", realtime.iterations_per_second()),
            gaussians = realtime_map.len(),
            max_pose_change_cm = format!("{:.2}", 100.0 * realtime.max_pose_change_m),
            max_pose_change_deg = format!("{:.3}", realtime.max_pose_change_deg),
            pose_steps_refused = realtime.pose_steps_refused,
            arrival_order_iterations = realtime.arrival_order_iterations,
            loop_limited_checks = realtime.loop_limited_checks,
            "real-time mapping done"
        );
        let refined = if refine_iterations > 0 && !self.map_is_empty() {
            let _span = tracing::info_span!("refinement", iterations = refine_iterations).entered();
            let started = Instant::now();
            self.unvisited.clear();
            for _ in 0..refine_iterations {
                self.iterate()?;
                self.simulate_slower_machine();
            }
            self.stats.seconds = started.elapsed().as_secs_f64();
            self.stats.keyframes = self.keyframes.len();
            self.stats.keyframe_pose_corrections = self.keyframe_pose_corrections();
            Some((self.download()?, std::mem::take(&mut self.stats)))
        } else {
            None
        };
        Ok(MappingOutcome {
            realtime_map,
            tracked_pose_moves,
            realtime,
            refined,
        })
    }

    /// [`MappingStats::keyframe_pose_corrections`] of the keyframes as they stand.
    fn keyframe_pose_corrections(&self) -> CorrectionField {
        if !self.config.refine_keyframe_poses {
            return CorrectionField::default();
        }
        CorrectionField::from_anchors(self.keyframes.iter().map(|keyframe| {
            let refined = Isometry3::from(&keyframe.camera.camera_from_world).inverse();
            let tracked = Isometry3::from(&keyframe.tracked_camera_from_world).inverse();
            (keyframe.timestamp_s, correction(&refined, &tracked))
        }))
    }

    /// `refine_keyframe_poses` only: `map` (downloaded from this state's map, so in its order)
    /// with each Gaussian moved by its seeding keyframe's tracked pose times its refined pose's
    /// inverse, so that the map seen from the tracked pose looks as it did from the refined
    /// one. Each Gaussian moves with the keyframe that seeded it, as a consensus correction
    /// moves it; where keyframes refined differently see the same Gaussian, that is an
    /// approximation, which the consensus's joint refinement (poses and map) fits further.
    fn tracked_pose_moves(&self) -> Option<TrackedPoseMoves> {
        if !self.config.refine_keyframe_poses {
            return None;
        }
        let ids = self.keyframes.iter().map(|keyframe| keyframe.keyframe_id);
        let mut moves = vec![RigidTransform::IDENTITY; ids.max().map_or(0, |id| id + 1)];
        for keyframe in &self.keyframes {
            // tracked world_from_camera * refined camera_from_world.
            moves[keyframe.keyframe_id] = keyframe
                .tracked_camera_from_world
                .inverse()
                .compose(&keyframe.camera.camera_from_world);
        }
        Some(TrackedPoseMoves {
            keyframe_of: self.keyframe_of.clone(),
            moves,
        })
    }

    /// `simulated_iteration_delay_ms` of extra wall time per iteration.
    fn simulate_slower_machine(&self) {
        if self.config.simulated_iteration_delay_ms > 0.0 {
            std::thread::sleep(std::time::Duration::from_secs_f64(
                self.config.simulated_iteration_delay_ms / 1e3,
            ));
        }
    }

    fn map_is_empty(&self) -> bool {
        self.map.as_ref().is_none_or(|m| m.is_empty()) || self.keyframes.is_empty()
    }

    fn download(&self) -> Result<GaussianCloud, GpuError> {
        match &self.map {
            Some(map) => map.download(&self.context),
            None => Ok(GaussianCloud::default()),
        }
    }

    fn insert_keyframe(&mut self, keyframe: MappingKeyframe) -> Result<(), MapperError> {
        let _span = tracing::debug_span!("insert_keyframe", id = keyframe.keyframe_id).entered();
        let scale = *self
            .scene_scale
            .get_or_insert_with(|| scene_scale(&keyframe.new_gaussians));
        let (camera, target) = keyframe_target(&keyframe, self.config.image_downscale);
        if !keyframe.new_gaussians.is_empty() {
            match &mut self.map {
                Some(map) => {
                    map.append(&self.context, &keyframe.new_gaussians)?;
                }
                None => {
                    let adam = render_core::training::AdamConfig {
                        means: (self.config.lr_means * scale) as f32,
                        log_scales: self.config.lr_log_scales as f32,
                        quaternions: self.config.lr_rotations as f32,
                        opacity_logits: self.config.lr_opacity as f32,
                        colours: self.config.lr_colours as f32,
                        ..Default::default()
                    };
                    self.map = Some(DeviceMap::upload(
                        &self.context,
                        &keyframe.new_gaussians,
                        adam,
                    )?);
                }
            }
            self.keyframe_of.extend(std::iter::repeat_n(
                keyframe.keyframe_id as u32,
                keyframe.new_gaussians.len(),
            ));
            // New Gaussians may need more tile pairs than the buffers hold: check on the next
            // iteration.
            self.since_pair_check = self.config.check_pairs_every;
        }
        let stored = StoredKeyframe {
            keyframe_id: keyframe.keyframe_id,
            target: DeviceTarget::upload(&self.context, &target)?,
            image_gradients: DeviceImageGradients::zeros(&self.context, &camera)?,
            timestamp_s: keyframe.timestamp_s,
            tracked_camera_from_world: camera.camera_from_world,
            camera,
            pose_adam: PoseAdam::default(),
        };
        self.unvisited.push(self.keyframes.len());
        self.keyframes.push(stored);
        self.stats.keyframes += 1;
        self.progress
            .gaussians
            .store(self.map.as_ref().map_or(0, |m| m.len()), Ordering::Relaxed);
        Ok(())
    }

    /// Applies a correction: every Gaussian and keyframe camera moves with its keyframe.
    fn correct(&mut self, keyframe_moves: &[RigidTransform]) -> Result<(), MapperError> {
        let _span = tracing::debug_span!("correct", keyframes = keyframe_moves.len()).entered();
        if let Some(map) = self.map.as_mut() {
            debug_assert_eq!(map.len(), self.keyframe_of.len());
            map.transform_groups(&self.context, &self.keyframe_of, keyframe_moves)?;
        }
        for keyframe in &mut self.keyframes {
            if let Some(moved) = keyframe_moves.get(keyframe.keyframe_id) {
                // camera_from_world' = (moved * world_from_camera)^-1.
                keyframe.camera.camera_from_world =
                    keyframe.camera.camera_from_world.compose(&moved.inverse());
                keyframe.tracked_camera_from_world =
                    keyframe.tracked_camera_from_world.compose(&moved.inverse());
            }
        }
        self.stats.corrections += 1;
        Ok(())
    }

    /// One Adam iteration on one keyframe. Returns whether it took the step (not when there is
    /// nothing to optimise, or when the binning buffers had to grow first).
    fn iterate(&mut self) -> Result<bool, MapperError> {
        let Some(map) = self.map.as_mut() else {
            return Ok(false);
        };
        if map.is_empty() || self.keyframes.is_empty() {
            return Ok(false);
        }
        let index = match self.unvisited.pop() {
            Some(index) => index,
            None => self.rng.random_range(0..self.keyframes.len()),
        };
        let keyframe = &self.keyframes[index];
        let context = &self.context;
        let frame =
            self.renderer
                .render_frame(context, map.gaussians(), &keyframe.camera, &self.raster)?;
        if frame.gradient_order_fell_back() {
            if self.stats.arrival_order_iterations == 0 {
                tracing::warn!(
                    gaussians = frame.gaussian_count,
                    pair_capacity = frame.pair_capacity,
                    fixed_order_mib = frame.fixed_order_bytes() as f64 / (1024.0 * 1024.0),
                    "the frame's per-pair gradient sums do not fit one storage binding: gradients \
                     are summed in arrival order, so this run will not repeat bit for bit"
                );
            }
            self.stats.arrival_order_iterations += 1;
        }
        let loss = self.kernels.image_loss(
            context,
            &self.renderer,
            &frame,
            &keyframe.target,
            &self.weights,
            &keyframe.image_gradients,
        )?;
        let gradients =
            self.renderer
                .backward(context, map.gaussians(), &frame, &keyframe.image_gradients)?;
        // Checked after the backward pass, so the check sees its walks too (one read-back).
        if self.since_pair_check >= self.config.check_pairs_every {
            self.since_pair_check = 0;
            let usage = self.renderer.check_pairs(context, &frame)?;
            if usage.rasterizers_cut_short() {
                if self.stats.loop_limited_checks == 0 {
                    tracing::warn!(
                        keyframe = keyframe.keyframe_id,
                        gaussians = frame.gaussian_count,
                        forward = usage.rasterize_cut_short,
                        backward = usage.rasterize_backward_cut_short,
                        "a tile's splat list is too long for the adapter's loop limit: the \
                         rasterizer skipped the rest of it (see render-core/README.md)"
                    );
                }
                self.stats.loop_limited_checks += 1;
            }
            if usage.overflowed() {
                tracing::debug!(
                    pairs = usage.pairs,
                    capacity = usage.capacity,
                    binning_cut_short = usage.binning_cut_short,
                    "pair buffers grown or binning blocks made loop-safe; skipping this step"
                );
                return Ok(false);
            }
        }
        self.since_pair_check += 1;
        map.adam_step(context, &self.kernels, &gradients)?;
        // The first keyframe's pose fixes the map's frame.
        let pose_read_back = self.config.refine_keyframe_poses && index > 0;
        if pose_read_back {
            let gradient = gradients.read_pose(context)?;
            step_pose(
                &mut self.keyframes[index],
                &gradient,
                &self.config,
                &mut self.stats,
            );
        }
        self.stats.iterations += 1;
        if self
            .stats
            .iterations
            .is_multiple_of(self.config.check_pairs_every)
        {
            self.stats.last_loss = Some(loss.read(context)?);
            tracing::debug!(
                iterations = self.stats.iterations,
                loss = ?self.stats.last_loss,
                gaussians = map.len(),
                "mapping"
            );
        } else if !pose_read_back {
            // The pose read-back above already waited for the device.
            context.wait_idle()?;
        }
        if self
            .stats
            .iterations
            .is_multiple_of(self.config.prune_every)
        {
            let report = map.prune(context, &self.prune_criteria)?;
            let removed = report.removed;
            if removed > 0 {
                let mut kept = report.kept.iter();
                self.keyframe_of
                    .retain(|_| kept.next().copied().unwrap_or(false));
            }
            self.stats.pruned += removed;
            if removed > 0 {
                tracing::debug!(removed, remaining = map.len(), "pruned");
            }
        }
        self.progress
            .iterations
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.progress.gaussians.store(map.len(), Ordering::Relaxed);
        Ok(true)
    }
}

/// One Adam step of `keyframe`'s pose along the photometric gradient of its last iteration; a
/// step that is not finite, or that would take the pose farther than `max_pose_change_*` from
/// its tracked pose, is not taken.
fn step_pose(
    keyframe: &mut StoredKeyframe,
    gradient: &PoseGradient,
    config: &MappingConfig,
    stats: &mut MappingStats,
) {
    let photometric = Vector6::from_iterator(gradient.as_array().map(f64::from));
    if !photometric.iter().all(|g| g.is_finite()) {
        return;
    }
    let rates = pose_rates(config.lr_pose_translation_m, config.lr_pose_rotation_rad);
    let xi = keyframe.pose_adam.step(&photometric, &rates);
    let moved = keyframe
        .camera
        .camera_from_world
        .left_perturbed([xi[0], xi[1], xi[2], xi[3], xi[4], xi[5]]);
    let (moved_m, turned_rad) = pose_change(&keyframe.tracked_camera_from_world, &moved);
    if moved_m > config.max_pose_change_m || turned_rad > config.max_pose_change_rad {
        stats.pose_steps_refused += 1;
        return;
    }
    keyframe.camera.camera_from_world = moved;
    stats.max_pose_change_m = stats.max_pose_change_m.max(moved_m);
    stats.max_pose_change_deg = stats.max_pose_change_deg.max(turned_rad.to_degrees());
}

/// How far the camera of `camera_from_world` is from that of `reference` (metres, radians).
fn pose_change(reference: &RigidTransform, camera_from_world: &RigidTransform) -> (f64, f64) {
    geometry::se3::pose_change(
        &Isometry3::from(reference).inverse(),
        &Isometry3::from(camera_from_world).inverse(),
    )
}

/// Tells the tracker (paced) that a keyframe's budget is spent.
fn notify(budget_spent: &Option<Sender<()>>) {
    if let Some(sender) = budget_spent {
        // The receiver lives as long as the tracker's handle; gone means the run is over.
        let _ = sender.send(());
    }
}

/// The scene scale the mean learning rate is multiplied by: the first keyframe's radius around
/// its centroid (a single RGB-D view's extent is the natural stand-in before any camera has
/// moved), at least 1 mm; 1 m for an empty keyframe.
fn scene_scale(first: &GaussianCloud) -> f64 {
    const MIN_SCENE_SCALE_M: f64 = 1e-3;
    if first.is_empty() {
        return 1.0;
    }
    first.radius_around_centroid().max(MIN_SCENE_SCALE_M)
}

/// The keyframe's camera and target at mapping resolution (`downscale` x smaller).
fn keyframe_target(keyframe: &MappingKeyframe, downscale: u32) -> (Camera, TargetImage) {
    let target = downscale_target(&keyframe.rgb, &keyframe.depth, downscale);
    let intrinsics = keyframe.intrinsics.binned(downscale);
    debug_assert_eq!(
        (intrinsics.width, intrinsics.height),
        (target.width, target.height)
    );
    let camera = Camera::new(
        RigidTransform::from(&keyframe.world_from_camera),
        &intrinsics,
    );
    (camera, target)
}

/// Box-filters RGB (u8 -> [0, 1]) and depth by `factor` ([`TargetImage::downscaled`]).
pub fn downscale_target(rgb: &RgbImage, depth: &DepthImage, factor: u32) -> TargetImage {
    assert_eq!(
        (rgb.width(), rgb.height()),
        (depth.width, depth.height),
        "colour and depth of one frame have one size"
    );
    TargetImage::downscaled(rgb.width(), rgb.height(), rgb.as_raw(), &depth.data, factor)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn downscaling_averages_colour_and_valid_depth_only() {
        let rgb = RgbImage::from_fn(4, 2, |x, _| image::Rgb([(x * 50) as u8, 0, 255]));
        let mut depth = DepthImage::new(4, 2);
        depth.data = vec![1.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0];
        let target = downscale_target(&rgb, &depth, 2);
        assert_eq!((target.width, target.height), (2, 1));
        assert!((target.rgb[0][0] - 25.0 / 255.0).abs() < 1e-6);
        assert!((target.rgb[1][2] - 1.0).abs() < 1e-6);
        // Block 0 has valid depths 1 and 3; block 1 has none.
        assert_eq!(target.depth.unwrap(), vec![2.0, 0.0]);
    }

    /// A textured wall of Gaussians 2 m in front of the origin, facing the camera.
    fn textured_wall() -> GaussianCloud {
        let mut cloud = GaussianCloud::default();
        for row in 0..40 {
            for column in 0..50 {
                let (x, y) = (-0.6 + 0.025 * column as f32, -0.5 + 0.025 * row as f32);
                let colour = [
                    0.5 + 0.4 * (9.0 * x).sin(),
                    0.5 + 0.4 * (7.0 * y).cos(),
                    0.5 + 0.4 * (5.0 * (x + y)).sin(),
                ];
                cloud.push(
                    [x, y, 2.0],
                    [0.015f32.ln(); 3],
                    [1.0, 0.0, 0.0, 0.0],
                    3.0,
                    colour,
                );
            }
        }
        cloud
    }

    /// The keyframe `world_from_camera` would record, its images rendered at `true_pose`.
    fn keyframe_seen_from(
        keyframe_id: usize,
        cloud: &GaussianCloud,
        true_pose: &Isometry3<f64>,
        world_from_camera: Isometry3<f64>,
        new_gaussians: GaussianCloud,
    ) -> MappingKeyframe {
        let intrinsics = Intrinsics::new(120.0, 120.0, 80.0, 60.0, 160, 120);
        let camera = Camera::new(RigidTransform::from(true_pose), &intrinsics);
        let view = render_core::reference::render(
            cloud,
            &camera,
            render_core::RenderMode::RgbD,
            &RasterConfig::default(),
        );
        let colours = view.rgb.expect("rgb rendered");
        let rgb = RgbImage::from_fn(160, 120, |x, y| {
            let c = colours[(y * 160 + x) as usize];
            image::Rgb(c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
        });
        let mut depth = DepthImage::new(160, 120);
        let depths = view.depth.expect("depth rendered");
        depth.data = depths
            .iter()
            .zip(&view.alpha)
            .map(|(&d, &a)| if a > 0.5 { d / a } else { 0.0 })
            .collect();
        MappingKeyframe {
            keyframe_id,
            frame_index: keyframe_id,
            timestamp_s: keyframe_id as f64,
            kind: KeyframeKind::Mapping,
            world_from_camera,
            intrinsics,
            rgb,
            depth,
            new_gaussians,
        }
    }

    /// A mapping state on the test device (lavapipe on CI), with nothing in it yet.
    fn mapper_state(mapping: &MappingConfig) -> MapperState {
        let context = GpuContext::new().expect("a wgpu adapter (lavapipe on CI)");
        MapperState::new(
            context,
            &TrackingConfig::default(),
            mapping,
            Arc::new(MapperProgress::default()),
        )
    }

    /// The second keyframe's pose error (metres) after `iterations` mapper iterations on two
    /// keyframes of the wall, the second recorded 10 mm off where its images were taken; the map
    /// itself is held fixed (zero learning rates) so only the pose can move.
    fn pose_error_after(refine_keyframe_poses: bool, iterations: usize) -> f64 {
        let cloud = textured_wall();
        let true_pose = Isometry3::translation(0.05, 0.02, 0.0);
        let recorded = Isometry3::translation(0.058, 0.014, 0.0);
        let mapping = MappingConfig {
            image_downscale: 1,
            lr_means: 0.0,
            lr_colours: 0.0,
            lr_opacity: 0.0,
            lr_log_scales: 0.0,
            refine_keyframe_poses,
            lr_pose_translation_m: 5e-4,
            ..MappingConfig::default()
        };
        let mut state = mapper_state(&mapping);
        let identity = Isometry3::identity();
        state
            .insert_keyframe(keyframe_seen_from(
                0,
                &cloud,
                &identity,
                identity,
                cloud.clone(),
            ))
            .unwrap();
        state
            .insert_keyframe(keyframe_seen_from(
                1,
                &cloud,
                &true_pose,
                recorded,
                GaussianCloud::default(),
            ))
            .unwrap();
        for _ in 0..iterations {
            state.iterate().unwrap();
        }
        // The correction field takes each keyframe's recorded pose onto its refined one (the
        // identity at the first keyframe, and everywhere without refinement).
        let field = state.keyframe_pose_corrections();
        assert_eq!(field.is_empty(), !refine_keyframe_poses);
        let refined = Isometry3::from(&state.keyframes[1].camera.camera_from_world).inverse();
        let moved = field.at(1.0) * recorded;
        assert!((moved.translation.vector - refined.translation.vector).norm() < 1e-6);
        assert!(moved.rotation.angle_to(&refined.rotation) < 1e-5);
        assert!(field.at(0.0).translation.vector.norm() < 1e-9);
        let true_camera_from_world = RigidTransform::from(&true_pose.inverse());
        pose_change(
            &true_camera_from_world,
            &state.keyframes[1].camera.camera_from_world,
        )
        .0
    }

    #[test]
    fn refined_keyframe_poses_move_towards_where_the_images_were_taken() {
        let before = pose_error_after(false, 60);
        let after = pose_error_after(true, 60);
        // Off by 10 mm; without refinement the pose stays where tracking put it.
        assert!((before - 0.01).abs() < 1e-4, "{before}");
        assert!(after < 0.5 * before, "refined pose error {after} m");
    }

    /// With keyframe 1's camera refined away from its tracked pose, the map sent to the
    /// consensus has keyframe 1's Gaussians where the tracked camera sees them as the refined
    /// camera saw the map; keyframe 0's (the fixed first keyframe) stay put.
    #[test]
    fn tracked_pose_moves_move_each_keyframe_s_gaussians_by_its_refinement() {
        let wall = textured_wall();
        let second_wall = {
            let mut moved = wall.clone();
            moved.transform_rigid(&RigidTransform::from(&Isometry3::translation(
                0.0, 0.0, 0.5,
            )));
            moved
        };
        let state_with_refined_second_keyframe = |refine_keyframe_poses: bool| {
            let mapping = MappingConfig {
                image_downscale: 1,
                refine_keyframe_poses,
                ..MappingConfig::default()
            };
            let mut state = mapper_state(&mapping);
            let identity = Isometry3::identity();
            let tracked = Isometry3::translation(0.05, 0.0, 0.0);
            for (id, (pose, seeds)) in [(identity, &wall), (tracked, &second_wall)]
                .into_iter()
                .enumerate()
            {
                let keyframe = keyframe_seen_from(id, &wall, &pose, pose, seeds.clone());
                state.insert_keyframe(keyframe).unwrap();
            }
            let refined = Isometry3::new(
                nalgebra::Vector3::new(0.06, 0.01, -0.02),
                nalgebra::Vector3::new(0.0, 0.02, 0.01),
            );
            state.keyframes[1].camera.camera_from_world = RigidTransform::from(&refined.inverse());
            state
        };
        let state = state_with_refined_second_keyframe(true);
        let map = state.download().unwrap();
        let moved = state
            .tracked_pose_moves()
            .expect("refinement on")
            .apply(&map);
        assert_eq!(moved.len(), wall.len() + second_wall.len());
        for i in 0..map.len() {
            let keyframe = &state.keyframes[state.keyframe_of[i] as usize];
            let seen_refined = keyframe
                .camera
                .camera_from_world
                .transform_point(map.means[i]);
            let seen_tracked = keyframe
                .tracked_camera_from_world
                .transform_point(moved.means[i]);
            for axis in 0..3 {
                assert!(
                    (seen_refined[axis] - seen_tracked[axis]).abs() < 1e-5,
                    "Gaussian {i}"
                );
            }
            if i < wall.len() {
                assert_eq!(
                    moved.means[i], map.means[i],
                    "first keyframe's Gaussian {i}"
                );
            } else {
                assert_ne!(
                    moved.means[i], map.means[i],
                    "refined keyframe's Gaussian {i}"
                );
            }
        }
        let unrefined = state_with_refined_second_keyframe(false);
        assert!(unrefined.tracked_pose_moves().is_none());
    }

    #[test]
    fn pose_change_measures_translation_and_rotation_between_cameras() {
        let reference = RigidTransform::from(&Isometry3::translation(0.1, 0.0, 0.0));
        let moved = RigidTransform::from(&Isometry3::new(
            nalgebra::Vector3::new(0.1, 0.03, 0.04),
            nalgebra::Vector3::new(0.0, 0.0, 0.02),
        ));
        let (metres, radians) = pose_change(&reference, &moved);
        assert!((radians - 0.02).abs() < 1e-5, "{radians}");
        assert!(metres > 0.04 && metres < 0.06, "{metres}");
    }

    #[test]
    fn scene_scale_is_the_radius_around_the_centroid() {
        let mut cloud = GaussianCloud::default();
        for x in [-1.0, 1.0] {
            cloud.push([x, 0.0, 2.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, [0.0; 3]);
        }
        assert!((scene_scale(&cloud) - 1.0).abs() < 1e-12);
        assert_eq!(scene_scale(&GaussianCloud::default()), 1.0);
    }
}
