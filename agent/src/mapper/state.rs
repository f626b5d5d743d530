//! The mapping thread's state: its device map and keyframes, the loop that takes commands
//! between iterations, keyframe insertion, corrections and the map's download.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use config::MappingConfig;
use crossbeam_channel::{Receiver, Sender, TryRecvError};
use geometry::correction::{CorrectionField, correction};
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use registration::config::TrackingConfig;
use render_core::backward::DeviceImageGradients;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::GpuRenderer;
use render_core::map::{DeviceMap, PruneCriteria};
use render_core::pose::PoseAdam;
use render_core::training::{DeviceTarget, LossWeights, TargetImage, TrainingKernels};
use render_core::types::{Camera, RasterConfig};
use splats::{GaussianCloud, RigidTransform};

use super::{Command, MapperError, MapperProgress, MappingKeyframe, MappingOutcome, MappingStats};

/// A keyframe kept for optimisation, at mapping resolution; its target lives on the device
/// (uploaded once, not every iteration).
pub(super) struct StoredKeyframe {
    pub(super) keyframe_id: usize,
    pub(super) camera: Camera,
    pub(super) target: DeviceTarget,
    /// dL/d(image) of its iterations (the loss kernel rewrites every pixel, so one buffer per
    /// keyframe serves every visit).
    pub(super) image_gradients: DeviceImageGradients,
    pub(super) timestamp_s: f64,
    /// The pose tracking gave it (moved by consensus corrections as `camera` is): what
    /// `camera` may move away from by at most `max_pose_change_*` when poses are refined.
    pub(super) tracked_camera_from_world: RigidTransform,
    pub(super) pose_adam: PoseAdam,
}

pub(super) struct MapperState {
    pub(super) context: GpuContext,
    pub(super) renderer: GpuRenderer,
    pub(super) kernels: TrainingKernels,
    pub(super) map: Option<DeviceMap>,
    /// Per Gaussian of `map`, in its order: the id of the keyframe that seeded it (what a
    /// correction moves it with). Follows appends and pruning.
    pub(super) keyframe_of: Vec<u32>,
    pub(super) keyframes: Vec<StoredKeyframe>,
    /// Keyframes not optimised yet, oldest first (popped from the back: newest first).
    pub(super) unvisited: Vec<usize>,
    pub(super) rng: ChaCha8Rng,
    pub(super) weights: LossWeights,
    pub(super) raster: RasterConfig,
    pub(super) prune_criteria: PruneCriteria,
    pub(super) config: MappingConfig,
    /// Multiplies the mean learning rate (the method scales it by the scene's size), fixed at the first keyframe.
    pub(super) scene_scale: Option<f64>,
    pub(super) progress: Arc<MapperProgress>,
    pub(super) stats: MappingStats,
    /// Iterations since the last pair-count check.
    pub(super) since_pair_check: usize,
}

impl MapperState {
    pub(super) fn new(
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
    pub(super) fn run(
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
            realtime,
            refined,
        })
    }

    /// [`MappingStats::keyframe_pose_corrections`] of the keyframes as they stand.
    pub(super) fn keyframe_pose_corrections(&self) -> CorrectionField {
        if !self.config.refine_keyframe_poses {
            return CorrectionField::default();
        }
        CorrectionField::from_anchors(self.keyframes.iter().map(|keyframe| {
            let refined = Isometry3::from(&keyframe.camera.camera_from_world).inverse();
            let tracked = Isometry3::from(&keyframe.tracked_camera_from_world).inverse();
            (keyframe.timestamp_s, correction(&refined, &tracked))
        }))
    }

    /// `simulated_iteration_delay_ms` of extra wall time per iteration.
    pub(super) fn simulate_slower_machine(&self) {
        if self.config.simulated_iteration_delay_ms > 0.0 {
            std::thread::sleep(std::time::Duration::from_secs_f64(
                self.config.simulated_iteration_delay_ms / 1e3,
            ));
        }
    }

    pub(super) fn map_is_empty(&self) -> bool {
        self.map.as_ref().is_none_or(|m| m.is_empty()) || self.keyframes.is_empty()
    }

    pub(super) fn download(&self) -> Result<GaussianCloud, GpuError> {
        match &self.map {
            Some(map) => map.download(&self.context),
            None => Ok(GaussianCloud::default()),
        }
    }

    pub(super) fn insert_keyframe(&mut self, keyframe: MappingKeyframe) -> Result<(), MapperError> {
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
    pub(super) fn correct(&mut self, keyframe_moves: &[RigidTransform]) -> Result<(), MapperError> {
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
}

/// Tells the tracker (paced) that a keyframe's budget is spent.
pub(super) fn notify(budget_spent: &Option<Sender<()>>) {
    if let Some(sender) = budget_spent {
        // The receiver lives as long as the tracker's handle; gone means the run is over.
        let _ = sender.send(());
    }
}

/// The scene scale the mean learning rate is multiplied by: the first keyframe's radius around
/// its centroid (a single RGB-D view's extent is the natural stand-in before any camera has
/// moved), at least 1 mm; 1 m for an empty keyframe.
pub(super) fn scene_scale(first: &GaussianCloud) -> f64 {
    const MIN_SCENE_SCALE_M: f64 = 1e-3;
    if first.is_empty() {
        return 1.0;
    }
    first.radius_around_centroid().max(MIN_SCENE_SCALE_M)
}

/// The keyframe's camera and target at mapping resolution (`downscale` x smaller).
pub(super) fn keyframe_target(keyframe: &MappingKeyframe, downscale: u32) -> (Camera, TargetImage) {
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
