//! Joint photometric refinement of the merged world map (docs/method.md, The consensus: joint
//! refinement).
//!
//! After the pose graph has placed every agent's keyframes in the world, the merged map (every
//! agent's map moved into the world frame) still carries each agent's own blur and the seams
//! between agents. Refinement optimises it against every placed keyframe's RGB-D image, whichever
//! agent took it, through render-core:
//!
//! ```text
//!     L = w_l1 |I - I*|_1 + w_ssim (1 - SSIM(I, I*)) + w_depth |D - D*|_1
//!         + alpha * sum over pose-graph edges (i, j) of |r_ij|^2
//! ```
//!
//! with `r_ij = Log(Z_ij^-1 T_i^-1 T_j)` the pose graph's own edge residual
//! ([`crate::pose_graph::residual::residual`]; rotation in radians, translation in metres) over
//! the odometry edges (consecutive keyframes of one agent, as tracked) and the loop closures the
//! pose graph accepted. The photometric term pulls each keyframe's pose to where its image agrees
//! with the shared map; the consistency term keeps the relative poses near what tracking and the
//! verified alignments measured.
//!
//! One iteration = one keyframe view (every view in turn, a shuffled order per pass): render,
//! loss and backward on the device, one Adam step of the map on the device, and, for poses, a
//! 48-byte read-back of the pose gradient followed by an Adam step of that keyframe's pose on the
//! host, once the map has had `pose_warmup_fraction` of the iterations or of the time bound
//! (whichever ends first) to sharpen. Agent 0's first keyframe is never moved (it defines the
//! world frame). A pose that ends
//! farther from the pose graph's than `max_pose_change_*` is put back (the photometric term
//! pulled it into a wrong basin) and counted.
//!
//! Targets and image-gradient buffers are allocated once per view; nothing but the pose gradient
//! (and, on a view's first visit and every `CHECK_PAIRS_EVERY` iterations, the tile-pair count
//! that grows the binning buffers) is read back inside the loop.
//!
//! The map's side runs on the device (`device.rs`), the poses' on the host (`poses.rs`).

mod device;
mod poses;

use std::collections::BTreeMap;
use std::time::Instant;

use geometry::camera::Intrinsics;
use nalgebra::Isometry3;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use render_core::context::GpuError;
use render_core::map::PruneCriteria;
use render_core::training::TargetImage;
use render_core::types::Camera;
use serde::Serialize;
use splats::{GaussianCloud, RigidTransform};

use crate::place_recognition::KeyframeRef;
use config::{ConsensusConfig, RefinementConfig};
use device::MapTrainer;
use poses::PoseRefinement;
pub use poses::consistency_cost;

/// One keyframe as refinement sees it.
pub struct RefinementView {
    /// The keyframe the view is.
    pub id: KeyframeRef,
    /// The pose graph's pose (camera-to-world).
    pub world_from_camera: Isometry3<f64>,
    /// Full-resolution intrinsics of `rgb8` / `depth_m`.
    pub intrinsics: Intrinsics,
    /// Interleaved 8-bit RGB, `width * height * 3` bytes.
    pub rgb8: Vec<u8>,
    /// Depth in metres (`<= 0`: invalid).
    pub depth_m: Vec<f32>,
}

/// A pose-graph edge: `camera_i_from_camera_j` as measured (by tracking or a verified closure).
#[derive(Debug, Clone, Copy)]
pub struct PoseEdge {
    /// Index in [`RefinementProblem::views`] of camera i.
    pub i: usize,
    /// Index in [`RefinementProblem::views`] of camera j.
    pub j: usize,
    /// Maps camera j's coordinates into camera i's (metres).
    pub camera_i_from_camera_j: Isometry3<f64>,
}

/// What refinement optimises.
pub struct RefinementProblem {
    /// The merged map in the world frame.
    pub map: GaussianCloud,
    /// The keyframe views the map is optimised against (the engine gives every keyframe the
    /// pose graph placed), at their pose-graph poses.
    pub views: Vec<RefinementView>,
    /// Edges between `views` (indices).
    pub edges: Vec<PoseEdge>,
    /// The view that defines the world frame (never moved), if it is among `views`.
    pub anchor: Option<usize>,
}

/// consensus.json's account of a refinement.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RefinementReport {
    /// Iterations run, one view each.
    pub iterations: usize,
    /// Wall-clock seconds of the refinement, from the views' preparation to the final figures
    /// (0 when no iteration was due).
    pub seconds: f64,
    /// Stopped by `max_seconds` before `iterations` were done.
    pub stopped_by_time: bool,
    /// Keyframe views refined against.
    pub views: usize,
    /// Pose-graph edges of the consistency term (odometry and accepted closures).
    pub pose_edges: usize,
    /// Gaussians of the map refinement started from (before pruning).
    pub gaussians: usize,
    /// Mean PSNR (dB) of the views before (pose-graph poses) and after (refined poses).
    /// `None` for both when no iteration was due (empty map, no views or no iterations).
    pub psnr_views_before: Option<f64>,
    /// After: the final map at the refined poses, those that moved too far put back.
    pub psnr_views_after: Option<f64>,
    /// Pose-consistency cost `sum |r_ij|^2` before and after.
    pub pose_consistency_before: f64,
    /// After: at the refined poses (equal to the cost before when no iteration was due).
    pub pose_consistency_after: f64,
    /// Whether the keyframe poses were refined (`refine_poses`); false: the map only.
    pub poses_refined: bool,
    /// Largest pose change kept (metres, degrees) and the poses put back for moving too far.
    pub max_pose_change_m: f64,
    /// Largest rotation of a pose kept, degrees.
    pub max_pose_change_deg: f64,
    /// Poses put back to the pose graph's for moving farther than `max_pose_change_m` or
    /// turning more than `max_pose_change_rad`.
    pub poses_reverted: usize,
    /// Gaussians removed after the refinement (`prune_min_opacity`).
    pub pruned: usize,
}

/// The refined map and poses.
pub struct RefinementOutcome {
    /// The refined map in the world frame, pruned when `prune_min_opacity` is above 0 (the input
    /// map when no iteration was due).
    pub map: GaussianCloud,
    /// Camera-to-world of every view after refinement (the pose graph's where not moved).
    pub world_from_camera: BTreeMap<KeyframeRef, Isometry3<f64>>,
    /// What the refinement did, for consensus.json.
    pub report: RefinementReport,
}

/// Why a refinement could not run to the end.
#[derive(Debug, thiserror::Error)]
pub enum RefinementError {
    /// The render-core device failed: setting it up, a step, or a read-back.
    #[error("refinement device: {0}")]
    Gpu(#[from] GpuError),
    /// A view's images do not hold as many pixels as its intrinsics say.
    #[error("view {view:?}: {reason}")]
    InvalidView {
        /// The view's keyframe.
        view: KeyframeRef,
        /// The sizes found and expected.
        reason: String,
    },
}

/// A view at refinement resolution: its camera intrinsics (sized as its target) and its target.
struct PreparedView {
    intrinsics: Intrinsics,
    target: TargetImage,
}

impl PreparedView {
    fn camera(&self, world_from_camera: &Isometry3<f64>) -> Camera {
        Camera::new(RigidTransform::from(world_from_camera), &self.intrinsics)
    }
}

fn prepare(view: &RefinementView, downscale: u32) -> Result<PreparedView, RefinementError> {
    let (width, height) = (view.intrinsics.width, view.intrinsics.height);
    let pixels = width as usize * height as usize;
    if view.rgb8.len() != pixels * 3 || view.depth_m.len() != pixels {
        return Err(RefinementError::InvalidView {
            view: view.id,
            reason: format!(
                "images hold {} colour bytes and {} depths, intrinsics say {width}x{height}",
                view.rgb8.len(),
                view.depth_m.len()
            ),
        });
    }
    let target = TargetImage::downscaled(width, height, &view.rgb8, &view.depth_m, downscale);
    Ok(PreparedView {
        intrinsics: view.intrinsics.binned(downscale),
        target,
    })
}

/// Runs the refinement of `problem` (see the module documentation).
pub fn refine(
    problem: RefinementProblem,
    consensus: &ConsensusConfig,
) -> Result<RefinementOutcome, RefinementError> {
    let config: &RefinementConfig = &consensus.refinement;
    let _span = tracing::info_span!(
        "joint refinement",
        views = problem.views.len(),
        gaussians = problem.map.len()
    )
    .entered();
    let started = Instant::now();
    let prepared: Vec<PreparedView> = problem
        .views
        .iter()
        .map(|view| prepare(view, config.image_downscale))
        .collect::<Result<_, _>>()?;
    let initial: Vec<Isometry3<f64>> = problem.views.iter().map(|v| v.world_from_camera).collect();
    let mut report = RefinementReport {
        views: problem.views.len(),
        pose_edges: problem.edges.len(),
        gaussians: problem.map.len(),
        poses_refined: config.refine_poses,
        pose_consistency_before: consistency_cost(&initial, &problem.edges),
        ..Default::default()
    };
    let iterations = config.iterations_for(prepared.len());
    if problem.map.is_empty() || iterations == 0 {
        report.pose_consistency_after = report.pose_consistency_before;
        return Ok(RefinementOutcome {
            map: problem.map,
            world_from_camera: problem
                .views
                .iter()
                .map(|v| (v.id, v.world_from_camera))
                .collect(),
            report,
        });
    }

    let mut trainer = MapTrainer::new(&problem.map, &prepared, consensus)?;
    report.psnr_views_before = trainer.mean_psnr(&initial)?;
    let mut poses = PoseRefinement::new(initial.clone(), &problem.edges, consensus);
    optimise(
        &mut trainer,
        &mut poses,
        iterations,
        problem.anchor,
        started,
        config,
        &mut report,
    )?;
    if config.prune_min_opacity > 0.0 {
        // Only the opacity decides: the agents' mappers pruned by shape already.
        report.pruned = trainer.prune(&PruneCriteria {
            min_opacity: config.prune_min_opacity as f32,
            max_scale_m: f32::MAX,
            max_elongation: f32::MAX,
        })?;
    }
    // Poses that moved too far are put back before the final figures.
    let poses = poses.into_bounded(&initial, config, &mut report);
    report.psnr_views_after = trainer.mean_psnr(&poses)?;
    report.pose_consistency_after = consistency_cost(&poses, &problem.edges);
    report.seconds = started.elapsed().as_secs_f64();
    tracing::info!(
        iterations = report.iterations,
        seconds = format!("{:.1}", report.seconds),
        psnr_before = ?report.psnr_views_before,
        psnr_after = ?report.psnr_views_after,
        poses_reverted = report.poses_reverted,
        pruned = report.pruned,
        "joint refinement done"
    );
    let refined_map = trainer.download()?;
    Ok(RefinementOutcome {
        map: refined_map,
        world_from_camera: problem
            .views
            .iter()
            .zip(poses)
            .map(|(view, pose)| (view.id, pose))
            .collect(),
        report,
    })
}

/// The optimisation loop: one view per iteration, every view once per pass in a shuffled order,
/// until `iterations` (`iterations_per_view` per view, at most `max_iterations`) are done or
/// `max_seconds` have passed. The first `poses_first_fraction` of them step the poses alone;
/// then every iteration steps the map, and once the warm-up is over every view's pose but the
/// `anchor`'s steps too.
fn optimise(
    trainer: &mut MapTrainer<'_>,
    poses: &mut PoseRefinement<'_>,
    iterations: usize,
    anchor: Option<usize>,
    started: Instant,
    config: &RefinementConfig,
    report: &mut RefinementReport,
) -> Result<(), GpuError> {
    let mut rng = ChaCha8Rng::seed_from_u64(config.random_seed);
    let mut order: Vec<usize> = Vec::new();
    let pose_warmup = (config.pose_warmup_fraction * iterations as f64).ceil() as usize;
    let poses_first = (config.poses_first_fraction * iterations as f64).ceil() as usize;
    // A paced refinement runs for tens of minutes on a CPU: say how far it is, ten times.
    let progress_every = iterations.div_ceil(10).max(1);
    while report.iterations < iterations {
        if report.iterations > 0 && report.iterations.is_multiple_of(progress_every) {
            tracing::info!(
                done = report.iterations,
                of = iterations,
                seconds = format!("{:.0}", started.elapsed().as_secs_f64()),
                "joint refinement under way"
            );
        }
        if started.elapsed().as_secs_f64() > config.max_seconds {
            report.stopped_by_time = true;
            tracing::warn!(
                iterations = report.iterations,
                max_seconds = config.max_seconds,
                "refinement stopped by its time bound"
            );
            break;
        }
        if order.is_empty() {
            order = (0..trainer.view_count()).collect();
            order.shuffle(&mut rng);
        }
        let view = order.pop().expect("refilled above");
        if config.lr_final_fraction != 1.0 {
            let progress = report.iterations as f64 / iterations as f64;
            trainer.scale_learning_rates(config.lr_final_fraction.powf(progress));
        }
        let elapsed = started.elapsed().as_secs_f64();
        let poses_alone = config.refine_poses
            && report.iterations < poses_first
            && elapsed < config.poses_first_fraction * config.max_seconds;
        let gradients = trainer.step(view, &poses.poses[view], report.iterations, !poses_alone)?;
        let pose_time = poses_alone
            || report.iterations >= pose_warmup
            || elapsed >= config.pose_warmup_fraction * config.max_seconds;
        if config.refine_poses && pose_time && Some(view) != anchor {
            let photometric = gradients
                .read_pose(&trainer.context)?
                .as_array()
                .map(f64::from);
            poses.step(view, &photometric);
        } else {
            trainer.context.wait_idle()?;
        }
        report.iterations += 1;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_whose_images_do_not_match_its_intrinsics_is_refused() {
        let view = RefinementView {
            id: KeyframeRef {
                agent_id: 1,
                keyframe_id: 4,
            },
            world_from_camera: Isometry3::identity(),
            intrinsics: Intrinsics::new(100.0, 100.0, 16.0, 12.0, 32, 24),
            rgb8: vec![0; 10],
            depth_m: vec![1.0; 32 * 24],
        };
        let error = prepare(&view, 1).err().expect("refused");
        assert!(error.to_string().contains("keyframe_id: 4"), "{error}");
    }
}
