//! Joint photometric refinement of the merged world map (SPEC section 4, step 4, second half).
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

use std::collections::BTreeMap;
use std::time::Instant;

use geometry::camera::Intrinsics;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use render_core::backward::DeviceImageGradients;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::GpuRenderer;
use render_core::map::DeviceMap;
use render_core::training::{AdamConfig, DeviceTarget, LossWeights, TargetImage, TrainingKernels};
use render_core::types::{Camera, GaussianCloud, RasterConfig, RenderMode, RigidTransform};
use serde::Serialize;

use crate::place_recognition::KeyframeRef;
use crate::pose_graph::residual::residual;
use config::{ConsensusConfig, RefinementConfig};

/// Depth errors enter the loss in metres: SPEC's joint loss weights plain depth L1 (the mapper
/// divides by the truncation distance instead).
const DEPTH_IN_METRES: f32 = 1.0;
/// Step of the central differences of the pose-consistency term (radians / metres): far below
/// any pose change that matters, far above f64 round-off of poses a few metres from the origin.
const CONSISTENCY_DIFFERENCE_STEP: f64 = 1e-6;
/// Adam moment decay rates and the division guard, as render-core's map optimiser uses.
const POSE_ADAM_BETA1: f64 = 0.9;
const POSE_ADAM_BETA2: f64 = 0.999;
const POSE_ADAM_EPSILON: f64 = 1e-12;
/// Smallest map radius the mean learning rate is scaled by (metres).
const MIN_SCENE_SCALE_M: f64 = 1e-3;
/// An iteration whose tile pairs overflowed the buffers is retried this many times (the renderer
/// grows them after the first overflow, so one retry suffices unless the adapter's binding limit
/// is reached).
const PAIR_OVERFLOW_RETRIES: usize = 1;
/// After every view has been rendered (and its tile pairs checked) once, the pair count is read
/// back only every this many iterations: the map's footprint changes slowly, and each check is
/// a blocking read in the middle of an iteration.
const CHECK_PAIRS_EVERY: usize = 50;

/// One keyframe as refinement sees it.
pub struct RefinementView {
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
    pub i: usize,
    pub j: usize,
    pub camera_i_from_camera_j: Isometry3<f64>,
}

/// What refinement optimises.
pub struct RefinementProblem {
    /// The merged map in the world frame.
    pub map: GaussianCloud,
    pub views: Vec<RefinementView>,
    /// Edges between `views` (indices).
    pub edges: Vec<PoseEdge>,
    /// The view that defines the world frame (never moved), if it is among `views`.
    pub anchor: Option<usize>,
}

/// consensus.json's account of a refinement.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RefinementReport {
    pub iterations: usize,
    pub seconds: f64,
    /// Stopped by `max_seconds` before `iterations` were done.
    pub stopped_by_time: bool,
    pub views: usize,
    pub pose_edges: usize,
    pub gaussians: usize,
    /// Mean PSNR (dB) of the views before (pose-graph poses) and after (refined poses).
    pub psnr_views_before: Option<f64>,
    pub psnr_views_after: Option<f64>,
    /// Pose-consistency cost `sum |r_ij|^2` before and after.
    pub pose_consistency_before: f64,
    pub pose_consistency_after: f64,
    pub poses_refined: bool,
    /// Largest pose change kept (metres, degrees) and the poses put back for moving too far.
    pub max_pose_change_m: f64,
    pub max_pose_change_deg: f64,
    pub poses_reverted: usize,
}

/// The refined map and poses.
pub struct RefinementOutcome {
    pub map: GaussianCloud,
    /// Camera-to-world of every view after refinement (the pose graph's where not moved).
    pub world_from_camera: BTreeMap<KeyframeRef, Isometry3<f64>>,
    pub report: RefinementReport,
}

#[derive(Debug, thiserror::Error)]
pub enum RefinementError {
    #[error("refinement device: {0}")]
    Gpu(#[from] GpuError),
    #[error("view {view:?}: {reason}")]
    InvalidView { view: KeyframeRef, reason: String },
}

/// Adam over one pose's 6-vector `[translation, rotation]` (left perturbation of
/// `camera_from_world`, render-core's pose-gradient convention).
#[derive(Default, Clone, Copy)]
struct PoseAdam {
    first_moment: Vector6<f64>,
    second_moment: Vector6<f64>,
    steps: i32,
}

impl PoseAdam {
    /// The perturbation to apply for `gradient`, with per-component step sizes `rates`.
    fn step(&mut self, gradient: &Vector6<f64>, rates: &Vector6<f64>) -> Vector6<f64> {
        self.steps += 1;
        self.first_moment =
            POSE_ADAM_BETA1 * self.first_moment + (1.0 - POSE_ADAM_BETA1) * gradient;
        self.second_moment = POSE_ADAM_BETA2 * self.second_moment
            + (1.0 - POSE_ADAM_BETA2) * gradient.component_mul(gradient);
        let m_hat = self.first_moment / (1.0 - POSE_ADAM_BETA1.powi(self.steps));
        let v_hat = self.second_moment / (1.0 - POSE_ADAM_BETA2.powi(self.steps));
        Vector6::from_fn(|k, _| -rates[k] * m_hat[k] / (v_hat[k].sqrt() + POSE_ADAM_EPSILON))
    }
}

/// `camera_from_world` perturbed on the left by `xi = [translation, rotation]`, returned as
/// `world_from_camera`. First-order equal to render-core's SE(3) exponential, which is all a
/// gradient step (and its finite difference) needs.
fn perturbed(world_from_camera: &Isometry3<f64>, xi: &Vector6<f64>) -> Isometry3<f64> {
    let delta = Isometry3::from_parts(
        Translation3::from(Vector3::new(xi[0], xi[1], xi[2])),
        UnitQuaternion::from_scaled_axis(Vector3::new(xi[3], xi[4], xi[5])),
    );
    (delta * world_from_camera.inverse()).inverse()
}

/// `sum |r_ij|^2` over `edges`.
pub fn consistency_cost(poses: &[Isometry3<f64>], edges: &[PoseEdge]) -> f64 {
    edges
        .iter()
        .map(|e| residual(&poses[e.i], &poses[e.j], &e.camera_i_from_camera_j).norm_squared())
        .sum()
}

/// Gradient of `weight * sum |r_ij|^2` over the edges touching `view`, w.r.t. the left
/// perturbation of that view's `camera_from_world` (central differences: 12 residual evaluations
/// per edge, nothing next to a render).
fn consistency_gradient(
    poses: &[Isometry3<f64>],
    edges: &[PoseEdge],
    view: usize,
    weight: f64,
) -> Vector6<f64> {
    let touching: Vec<&PoseEdge> = edges
        .iter()
        .filter(|e| e.i == view || e.j == view)
        .collect();
    if touching.is_empty() || weight == 0.0 {
        return Vector6::zeros();
    }
    let cost_with = |pose: &Isometry3<f64>| -> f64 {
        touching
            .iter()
            .map(|e| {
                let (x_i, x_j) = if e.i == view {
                    (pose, &poses[e.j])
                } else {
                    (&poses[e.i], pose)
                };
                residual(x_i, x_j, &e.camera_i_from_camera_j).norm_squared()
            })
            .sum()
    };
    Vector6::from_fn(|k, _| {
        let mut step = Vector6::zeros();
        step[k] = CONSISTENCY_DIFFERENCE_STEP;
        let plus = cost_with(&perturbed(&poses[view], &step));
        let minus = cost_with(&perturbed(&poses[view], &(-step)));
        weight * (plus - minus) / (2.0 * CONSISTENCY_DIFFERENCE_STEP)
    })
}

/// A view at refinement resolution: its camera intrinsics and size, and its target.
struct PreparedView {
    intrinsics: [f32; 4],
    width: u32,
    height: u32,
    target: TargetImage,
}

impl PreparedView {
    fn camera(&self, world_from_camera: &Isometry3<f64>) -> Camera {
        Camera::from_world_from_camera(
            RigidTransform::from(world_from_camera),
            self.intrinsics,
            self.width,
            self.height,
        )
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
    let scaled = view.intrinsics.scaled(1.0 / f64::from(downscale.max(1)));
    Ok(PreparedView {
        intrinsics: [scaled.fx, scaled.fy, scaled.cx, scaled.cy].map(|v| v as f32),
        width: target.width,
        height: target.height,
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
    let unchanged = |report: RefinementReport, map: GaussianCloud| RefinementOutcome {
        map,
        world_from_camera: problem
            .views
            .iter()
            .map(|v| (v.id, v.world_from_camera))
            .collect(),
        report,
    };
    if problem.map.is_empty() || prepared.is_empty() || config.iterations == 0 {
        report.pose_consistency_after = report.pose_consistency_before;
        return Ok(unchanged(report, problem.map));
    }

    let context = GpuContext::new()?;
    tracing::info!(adapter = %context.describe(), "refinement device");
    let renderer = GpuRenderer::new(&context);
    let kernels = TrainingKernels::new(&context);
    let scene_scale = problem.map.radius_around_centroid().max(MIN_SCENE_SCALE_M);
    let adam = AdamConfig {
        means: (config.lr_means * scene_scale) as f32,
        log_scales: config.lr_log_scales as f32,
        quaternions: config.lr_rotations as f32,
        opacity_logits: config.lr_opacity as f32,
        colours: config.lr_colours as f32,
        ..Default::default()
    };
    let mut map = DeviceMap::upload(&context, &problem.map, adam)?;
    let targets: Vec<DeviceTarget> = prepared
        .iter()
        .map(|view| DeviceTarget::upload(&context, &view.target))
        .collect::<Result<_, _>>()?;
    // The loss kernel rewrites every pixel of these, so one buffer per view serves every visit.
    let image_gradients: Vec<DeviceImageGradients> = prepared
        .iter()
        .map(|view| DeviceImageGradients::zeros(&context, &view.camera(&Isometry3::identity())))
        .collect::<Result<_, _>>()?;
    let mut pairs_checked = vec![false; prepared.len()];
    let weights = LossWeights {
        l1: consensus.weight_l1 as f32,
        ssim: consensus.weight_ssim as f32,
        depth: consensus.weight_depth as f32,
        depth_truncation: DEPTH_IN_METRES,
    };
    let raster = RasterConfig::default();
    report.psnr_views_before = mean_psnr(&context, &renderer, &map, &prepared, &initial)?;

    let mut poses = initial.clone();
    let mut pose_adam = vec![PoseAdam::default(); poses.len()];
    let rates = Vector6::new(
        config.lr_pose_translation_m,
        config.lr_pose_translation_m,
        config.lr_pose_translation_m,
        config.lr_pose_rotation_rad,
        config.lr_pose_rotation_rad,
        config.lr_pose_rotation_rad,
    );
    let mut rng = ChaCha8Rng::seed_from_u64(config.random_seed);
    let mut order: Vec<usize> = Vec::new();
    let pose_warmup = (config.pose_warmup_fraction * config.iterations as f64).ceil() as usize;
    while report.iterations < config.iterations {
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
            order = (0..prepared.len()).collect();
            order.shuffle(&mut rng);
        }
        let view = order.pop().expect("refilled above");
        let camera = prepared[view].camera(&poses[view]);
        let mut frame = renderer.render_frame(&context, map.gaussians(), &camera, &raster)?;
        if !pairs_checked[view] || report.iterations.is_multiple_of(CHECK_PAIRS_EVERY) {
            pairs_checked[view] = true;
            for _ in 0..PAIR_OVERFLOW_RETRIES {
                if !renderer.check_pairs(&context, &frame)?.overflowed() {
                    break;
                }
                frame = renderer.render_frame(&context, map.gaussians(), &camera, &raster)?;
            }
        }
        kernels.image_loss(
            &context,
            &renderer,
            &frame,
            &targets[view],
            &weights,
            &image_gradients[view],
        )?;
        let gradients =
            renderer.backward(&context, map.gaussians(), &frame, &image_gradients[view])?;
        map.adam_step(&context, &kernels, &gradients)?;
        let pose_time = report.iterations >= pose_warmup
            || started.elapsed().as_secs_f64() >= config.pose_warmup_fraction * config.max_seconds;
        if config.refine_poses && pose_time && Some(view) != problem.anchor {
            let photometric = gradients.read_pose(&context)?.as_array().map(f64::from);
            let gradient = Vector6::from_column_slice(&photometric)
                + consistency_gradient(
                    &poses,
                    &problem.edges,
                    view,
                    consensus.weight_pose_consistency,
                );
            if gradient.iter().all(|g| g.is_finite()) {
                let xi = pose_adam[view].step(&gradient, &rates);
                poses[view] = perturbed(&poses[view], &xi);
            }
        } else {
            context.wait_idle()?;
        }
        report.iterations += 1;
    }

    // Poses that moved too far are put back before the final figures.
    for (pose, start) in poses.iter_mut().zip(&initial) {
        let change = start.inverse() * *pose;
        let moved_m = change.translation.vector.norm();
        let turned_rad = change.rotation.angle();
        if moved_m > config.max_pose_change_m || turned_rad > config.max_pose_change_rad {
            *pose = *start;
            report.poses_reverted += 1;
        } else {
            report.max_pose_change_m = report.max_pose_change_m.max(moved_m);
            report.max_pose_change_deg = report.max_pose_change_deg.max(turned_rad.to_degrees());
        }
    }
    report.psnr_views_after = mean_psnr(&context, &renderer, &map, &prepared, &poses)?;
    report.pose_consistency_after = consistency_cost(&poses, &problem.edges);
    report.seconds = started.elapsed().as_secs_f64();
    tracing::info!(
        iterations = report.iterations,
        seconds = format!("{:.1}", report.seconds),
        psnr_before = ?report.psnr_views_before,
        psnr_after = ?report.psnr_views_after,
        poses_reverted = report.poses_reverted,
        "joint refinement done"
    );
    let refined_map = map.download(&context)?;
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

/// Mean PSNR of the views rendered at `poses` against their targets.
fn mean_psnr(
    context: &GpuContext,
    renderer: &GpuRenderer,
    map: &DeviceMap,
    views: &[PreparedView],
    poses: &[Isometry3<f64>],
) -> Result<Option<f64>, GpuError> {
    let mut total = 0.0;
    for (view, pose) in views.iter().zip(poses) {
        let output = renderer.render(
            context,
            map.gaussians(),
            &view.camera(pose),
            RenderMode::Rgb,
        )?;
        let rendered: Vec<f64> = output
            .rgb
            .unwrap_or_default()
            .iter()
            .flat_map(|c| c.map(f64::from))
            .collect();
        let reference: Vec<f64> = view
            .target
            .rgb
            .iter()
            .flat_map(|c| c.map(f64::from))
            .collect();
        total += metrics::image::psnr(&reference, &rendered);
    }
    Ok((!views.is_empty()).then(|| total / views.len() as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(t: [f64; 3], axis_angle: [f64; 3]) -> Isometry3<f64> {
        Isometry3::new(Vector3::from(t), Vector3::from(axis_angle))
    }

    #[test]
    fn consistency_gradient_matches_the_cost_and_vanishes_at_agreement() {
        let poses = vec![
            pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
            pose([1.0, 0.2, -0.1], [0.05, -0.1, 0.2]),
            pose([1.5, 0.9, 0.3], [0.1, 0.3, -0.2]),
        ];
        // Measurements that agree with the poses: zero cost, zero gradient.
        let agreeing: Vec<PoseEdge> = [(0, 1), (1, 2), (0, 2)]
            .iter()
            .map(|&(i, j)| PoseEdge {
                i,
                j,
                camera_i_from_camera_j: poses[i].inverse() * poses[j],
            })
            .collect();
        assert!(consistency_cost(&poses, &agreeing) < 1e-20);
        for view in 0..3 {
            assert!(consistency_gradient(&poses, &agreeing, view, 1.0).norm() < 1e-8);
        }
        // A disagreeing edge: a small step against the gradient lowers the cost.
        let mut edges = agreeing.clone();
        edges[1].camera_i_from_camera_j =
            pose([0.02, -0.01, 0.03], [0.01, 0.0, -0.02]) * edges[1].camera_i_from_camera_j;
        let before = consistency_cost(&poses, &edges);
        for view in 1..3 {
            let gradient = consistency_gradient(&poses, &edges, view, 1.0);
            assert!(gradient.norm() > 1e-4, "view {view}: {gradient}");
            let mut moved = poses.clone();
            moved[view] = perturbed(&poses[view], &(-1e-2 * gradient));
            assert!(consistency_cost(&moved, &edges) < before, "view {view}");
        }
    }

    #[test]
    fn perturbation_moves_the_camera_from_world_on_the_left() {
        let world_from_camera = pose([0.5, -0.2, 1.0], [0.1, 0.2, 0.3]);
        let xi = Vector6::new(0.01, 0.0, 0.0, 0.0, 0.0, 0.0);
        let moved = perturbed(&world_from_camera, &xi);
        // A left translation of camera_from_world shifts the camera-frame coordinates of every
        // world point by the same vector.
        let point = nalgebra::Point3::new(0.3, 0.4, 2.0);
        let before = world_from_camera.inverse() * point;
        let after = moved.inverse() * point;
        assert!(((after - before) - Vector3::new(0.01, 0.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn pose_adam_moves_against_the_gradient_by_the_step_size() {
        let mut adam = PoseAdam::default();
        let rates = Vector6::from_element(1e-3);
        let step = adam.step(&Vector6::new(2.0, -3.0, 0.0, 1.0, 0.0, 0.0), &rates);
        // The first Adam step has magnitude lr in every non-zero component.
        assert!((step[0] + 1e-3).abs() < 1e-9);
        assert!((step[1] - 1e-3).abs() < 1e-9);
        assert_eq!(step[2], 0.0);
        assert!((step[3] + 1e-3).abs() < 1e-9);
    }

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
