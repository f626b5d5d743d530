//! One Adam iteration on one keyframe (render, loss, backward, map and pose steps, pruning).

use std::sync::atomic::Ordering;

use config::MappingConfig;
use nalgebra::{Isometry3, Vector6};
use rand::RngExt;
use render_core::pose::pose_rates;
use render_core::types::PoseGradient;
use splats::RigidTransform;

use super::state::{MapperState, StoredKeyframe};
use super::{MapperError, MappingStats};

impl MapperState {
    /// One Adam iteration on one keyframe. Returns whether it took the step (not when there is
    /// nothing to optimise, or when the binning buffers had to grow first).
    pub(super) fn iterate(&mut self) -> Result<bool, MapperError> {
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
pub(super) fn step_pose(
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
pub(super) fn pose_change(
    reference: &RigidTransform,
    camera_from_world: &RigidTransform,
) -> (f64, f64) {
    geometry::se3::pose_change(
        &Isometry3::from(reference).inverse(),
        &Isometry3::from(camera_from_world).inverse(),
    )
}
