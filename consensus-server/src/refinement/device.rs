//! The map half of joint refinement on the device: the merged map, every view's target and
//! gradient buffers, and one render-loss-backward-Adam iteration of the map per view.

use nalgebra::Isometry3;
use render_core::backward::{DeviceGradients, DeviceImageGradients};
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::GpuRenderer;
use render_core::map::{DeviceMap, PruneCriteria};
use render_core::training::{AdamConfig, DeviceTarget, LossWeights, TrainingKernels};
use render_core::types::{RasterConfig, RenderMode};
use splats::GaussianCloud;

use super::PreparedView;
use config::ConsensusConfig;

/// Depth errors enter the loss in metres: the joint loss weights plain depth L1 (the mapper
/// divides by the truncation distance instead).
const DEPTH_IN_METRES: f32 = 1.0;
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

/// The device state of a refinement.
pub(super) struct MapTrainer<'v> {
    pub context: GpuContext,
    renderer: GpuRenderer,
    kernels: TrainingKernels,
    map: DeviceMap,
    /// The learning rates the refinement starts with ([`Self::scale_learning_rates`]).
    initial_rates: AdamConfig,
    views: &'v [PreparedView],
    targets: Vec<DeviceTarget>,
    image_gradients: Vec<DeviceImageGradients>,
    /// Whether each view's tile pairs were checked once.
    pairs_checked: Vec<bool>,
    weights: LossWeights,
    raster: RasterConfig,
    /// Whether a frame too large for the fixed gradient order was reported.
    arrival_order_reported: bool,
    /// Set once a rasterizer walk cut short by the adapter's loop limit was reported.
    loop_limit_reported: bool,
}

impl<'v> MapTrainer<'v> {
    /// Opens the device and uploads `map` (with Adam learning rates scaled to its size), the
    /// views' targets and their gradient buffers.
    pub fn new(
        map: &GaussianCloud,
        views: &'v [PreparedView],
        consensus: &ConsensusConfig,
    ) -> Result<Self, GpuError> {
        let config = &consensus.refinement;
        let context = GpuContext::new()?;
        tracing::info!(adapter = %context.describe(), "refinement device");
        let renderer = GpuRenderer::new(&context);
        let kernels = TrainingKernels::new(&context);
        let scene_scale = map.radius_around_centroid().max(MIN_SCENE_SCALE_M);
        let adam = AdamConfig {
            means: (config.lr_means * scene_scale) as f32,
            log_scales: config.lr_log_scales as f32,
            quaternions: config.lr_rotations as f32,
            opacity_logits: config.lr_opacity as f32,
            colours: config.lr_colours as f32,
            ..Default::default()
        };
        let map = DeviceMap::upload(&context, map, adam)?;
        let initial_rates = adam;
        let targets: Vec<DeviceTarget> = views
            .iter()
            .map(|view| DeviceTarget::upload(&context, &view.target))
            .collect::<Result<_, _>>()?;
        // The loss kernel rewrites every pixel of these, so one buffer per view serves every
        // visit.
        let image_gradients: Vec<DeviceImageGradients> = views
            .iter()
            .map(|view| DeviceImageGradients::zeros(&context, &view.camera(&Isometry3::identity())))
            .collect::<Result<_, _>>()?;
        Ok(Self {
            context,
            renderer,
            kernels,
            map,
            initial_rates,
            views,
            targets,
            image_gradients,
            pairs_checked: vec![false; views.len()],
            arrival_order_reported: false,
            loop_limit_reported: false,
            weights: LossWeights {
                l1: consensus.weight_l1 as f32,
                ssim: consensus.weight_ssim as f32,
                depth: consensus.weight_depth as f32,
                depth_truncation: DEPTH_IN_METRES,
            },
            raster: RasterConfig::default(),
        })
    }

    /// Iteration `iteration` of the map on `view` seen from `world_from_camera`: render (checking
    /// the tile pairs on the view's first visit and every [`CHECK_PAIRS_EVERY`] iterations),
    /// loss, backward and, with `step_map`, an Adam step of the map. Returns the gradients (the
    /// pose's among them).
    pub fn step(
        &mut self,
        view: usize,
        world_from_camera: &Isometry3<f64>,
        iteration: usize,
        step_map: bool,
    ) -> Result<DeviceGradients, GpuError> {
        let (context, renderer) = (&self.context, &self.renderer);
        let camera = self.views[view].camera(world_from_camera);
        let mut frame =
            renderer.render_frame(context, self.map.gaussians(), &camera, &self.raster)?;
        let check = !self.pairs_checked[view] || iteration.is_multiple_of(CHECK_PAIRS_EVERY);
        if check {
            self.pairs_checked[view] = true;
            for _ in 0..PAIR_OVERFLOW_RETRIES {
                if !renderer.check_pairs(context, &frame)?.overflowed() {
                    break;
                }
                frame =
                    renderer.render_frame(context, self.map.gaussians(), &camera, &self.raster)?;
            }
        }
        if frame.gradient_order_fell_back() && !self.arrival_order_reported {
            self.arrival_order_reported = true;
            tracing::warn!(
                view,
                gaussians = frame.gaussian_count,
                pair_capacity = frame.pair_capacity,
                fixed_order_mib = frame.fixed_order_bytes() as f64 / (1024.0 * 1024.0),
                "the view's per-pair gradient sums do not fit one storage binding: gradients are \
                 summed in arrival order, so this refinement will not repeat bit for bit"
            );
        }
        self.kernels.image_loss(
            context,
            renderer,
            &frame,
            &self.targets[view],
            &self.weights,
            &self.image_gradients[view],
        )?;
        let gradients = renderer.backward(
            context,
            self.map.gaussians(),
            &frame,
            &self.image_gradients[view],
        )?;
        // The rasterizers' loop-limit flags, the backward's included, once its pass is queued.
        if check && !self.loop_limit_reported {
            let usage = renderer.check_pairs(context, &frame)?;
            if usage.rasterizers_cut_short() {
                self.loop_limit_reported = true;
                tracing::warn!(
                    view,
                    gaussians = frame.gaussian_count,
                    forward = usage.rasterize_cut_short,
                    backward = usage.rasterize_backward_cut_short,
                    "a tile's splat list is too long for the adapter's loop limit: the \
                     rasterizer skipped the rest of it (see render-core/README.md)"
                );
            }
        }
        if step_map {
            self.map.adam_step(context, &self.kernels, &gradients)?;
        }
        Ok(gradients)
    }

    /// Sets every Gaussian learning rate to `factor` times its initial value.
    pub fn scale_learning_rates(&mut self, factor: f64) {
        let f = factor as f32;
        let initial = self.initial_rates;
        let rates = self.map.adam_config_mut();
        rates.means = initial.means * f;
        rates.log_scales = initial.log_scales * f;
        rates.quaternions = initial.quaternions * f;
        rates.opacity_logits = initial.opacity_logits * f;
        rates.colours = initial.colours * f;
    }

    /// Removes the Gaussians that fail `criteria` (their Adam state with them); returns how
    /// many.
    pub fn prune(&mut self, criteria: &PruneCriteria) -> Result<usize, GpuError> {
        Ok(self.map.prune(&self.context, criteria)?.removed)
    }

    pub fn view_count(&self) -> usize {
        self.views.len()
    }

    /// Mean PSNR of the views rendered at `poses` against their targets.
    pub fn mean_psnr(&self, poses: &[Isometry3<f64>]) -> Result<Option<f64>, GpuError> {
        mean_psnr(&self.context, &self.renderer, &self.map, self.views, poses)
    }

    pub fn download(&self) -> Result<GaussianCloud, GpuError> {
        self.map.download(&self.context)
    }
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
