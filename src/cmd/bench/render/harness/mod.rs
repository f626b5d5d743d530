//! Render benchmark: wall-clock timings of the device pipeline on a deterministic synthetic
//! scene that looks like an indoor SLAM map (a room of surfaces 1-4 m from the camera covered
//! by Gaussians of a few centimetres), seen from inside the room so that it fills the view.
//!
//! Every timing is "submit, then block until the device is idle", so it measures the device
//! work and the host-side encoding together (what a mapping loop waits for). Reported figures
//! are the median of `repeats` runs after `warmup` untimed runs.
//!
//! `scene.rs` builds the scene and the camera, `workload.rs` counts a tile rasterizer's work on
//! the host; this file times the device.

use std::time::Instant;

use render_core::backward::DeviceImageGradients;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::{DeviceGaussians, DeviceSortBench, GpuRenderer, StageTimes};
use render_core::training::{
    AdamConfig, DeviceAdam, DeviceTarget, LossWeights, TargetImage, TrainingKernels,
};
use render_core::{Camera, RasterConfig};
use splats::GaussianCloud;

mod scene;
#[cfg(test)]
mod tests;
mod workload;

use scene::SplitMix64;
pub use scene::{bench_camera, realistic_scene};
pub use workload::{RasterWorkload, raster_workload};

/// Depth of the synthetic target image used by the loss (metres).
const TARGET_DEPTH: f32 = 2.5;

/// The benchmark's default cases: these Gaussian counts at these image sizes, each
/// figure the median of [`DEFAULT_REPEATS`] runs after [`DEFAULT_WARMUP`] untimed ones.
pub const DEFAULT_GAUSSIAN_COUNTS: [usize; 3] = [10_000, 100_000, 300_000];
pub const DEFAULT_IMAGE_SIZES: [(u32, u32); 2] = [(320, 240), (640, 480)];
pub const DEFAULT_REPEATS: usize = 20;
pub const DEFAULT_WARMUP: usize = 2;

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    pub gaussian_counts: Vec<usize>,
    pub width: u32,
    pub height: u32,
    /// Untimed runs before measuring (pipeline warm-up, buffer growth).
    pub warmup: usize,
    /// Timed runs; the median is reported.
    pub repeats: usize,
    /// Also time forward + backward and the full optimisation iteration.
    pub iteration: bool,
    pub seed: u64,
}

impl Default for BenchConfig {
    fn default() -> Self {
        Self {
            gaussian_counts: DEFAULT_GAUSSIAN_COUNTS.to_vec(),
            width: DEFAULT_IMAGE_SIZES[1].0,
            height: DEFAULT_IMAGE_SIZES[1].1,
            warmup: DEFAULT_WARMUP,
            repeats: DEFAULT_REPEATS,
            iteration: true,
            seed: 7,
        }
    }
}

/// Timings of one scene size (milliseconds, medians).
#[derive(Clone, Debug, PartialEq)]
pub struct BenchCase {
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    /// Tile/Gaussian pairs of the benchmark view.
    pub intersections: u32,
    pub forward_ms: f64,
    /// Forward + backward (with the loss gradient as input), `None` when not measured.
    pub forward_backward_ms: Option<f64>,
    /// Forward + loss + backward + Adam, `None` when not measured.
    pub iteration_ms: Option<f64>,
    /// The device radix sort of `gaussians` random 32-bit keys with values.
    pub sort_ms: f64,
    /// Forward stages, each submitted and waited for separately (sums exceed `forward_ms`
    /// by the extra synchronisation).
    pub stages: StageTimes,
    /// Stages of the optimisation iteration (forward, loss, backward stages, Adam), each
    /// submitted and waited for separately; empty when the iteration is not measured.
    pub iteration_stages: StageTimes,
    /// The most device memory buffers held at once during the case (the map, its Adam state,
    /// every frame, loss and gradient buffer; not the sort measurement's own keys), in bytes
    /// ([`GpuContext::peak_buffer_bytes`]).
    pub peak_device_bytes: u64,
}

/// A smooth target image with constant valid depth for the loss of the iteration timing.
fn target_image(camera: &Camera) -> TargetImage {
    let (width, height) = (camera.width, camera.height);
    let rgb = (0..height)
        .flat_map(|row| {
            (0..width).map(move |col| {
                let (x, y) = (col as f32 / width as f32, row as f32 / height as f32);
                // A smooth gradient: red along x, green along y, blue their mean.
                [x, y, (x + y) / 2.0]
            })
        })
        .collect();
    TargetImage {
        width,
        height,
        rgb,
        depth: Some(vec![TARGET_DEPTH; camera.pixel_count()]),
    }
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Median milliseconds of `repeats` runs of `run` (each followed by a wait for the device)
/// after `warmup` untimed runs.
fn time_ms(
    context: &GpuContext,
    warmup: usize,
    repeats: usize,
    mut run: impl FnMut() -> Result<(), GpuError>,
) -> Result<f64, GpuError> {
    for _ in 0..warmup {
        run()?;
        context.wait_idle()?;
    }
    let mut times = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        run()?;
        context.wait_idle()?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(times))
}

/// Measures one size of the synthetic scene.
pub fn run_case(
    context: &GpuContext,
    renderer: &GpuRenderer,
    kernels: &TrainingKernels,
    config: &BenchConfig,
    gaussian_count: usize,
) -> Result<BenchCase, GpuError> {
    let camera = bench_camera(config.width, config.height);
    let cloud = realistic_scene(&camera, gaussian_count, config.seed);
    run_case_on(context, renderer, kernels, config, &cloud, &camera)
}

/// Measures a given map seen by a given camera (e.g. a map saved by a SLAM run, seen from one of
/// its keyframes); `config.width`/`height` are ignored in favour of the camera's.
pub fn run_case_on(
    context: &GpuContext,
    renderer: &GpuRenderer,
    kernels: &TrainingKernels,
    config: &BenchConfig,
    cloud: &GaussianCloud,
    camera: &Camera,
) -> Result<BenchCase, GpuError> {
    let gaussian_count = cloud.len();
    let camera = *camera;
    // The peak counts from here, without the buffers of an earlier case.
    context.release_dropped_buffers()?;
    context.reset_peak_buffer_bytes();
    let gaussians = DeviceGaussians::upload(context, cloud)?;
    let raster = RasterConfig::default();
    let (warmup, repeats) = (config.warmup, config.repeats);

    // One checked render first: it sizes the pair buffers for this view (outside the timing,
    // as a mapping loop would after its first frames).
    let first = renderer.render_frame(context, &gaussians, &camera, &raster)?;
    let mut usage = renderer.check_pairs(context, &first)?;
    if usage.overflowed() {
        let refit = renderer.render_frame(context, &gaussians, &camera, &raster)?;
        usage = renderer.check_pairs(context, &refit)?;
    }
    if usage.rasterizers_cut_short() {
        tracing::warn!(
            gaussians = gaussian_count,
            width = camera.width,
            height = camera.height,
            "a tile's splat list is too long for the adapter's loop limit: the rasterizer skips \
             the rest of it, so these timings are of less work (see render-core/README.md)"
        );
    }
    let intersections = usage.pairs;
    let forward_ms = time_ms(context, warmup, repeats, || {
        renderer.render_frame(context, &gaussians, &camera, &raster)?;
        Ok(())
    })?;

    let mut stage_runs = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let mut times = StageTimes::default();
        renderer.render_frame_profiled(context, &gaussians, &camera, &raster, Some(&mut times))?;
        stage_runs.push(times);
    }
    let stages = StageTimes::median_of(&stage_runs);

    let (forward_backward_ms, iteration_ms, iteration_stages) = if config.iteration {
        let timings = time_iteration(context, renderer, kernels, &gaussians, &camera, config)?;
        (Some(timings.0), Some(timings.1), timings.2)
    } else {
        (None, None, StageTimes::default())
    };

    let peak_device_bytes = context.peak_buffer_bytes();
    let sort_ms = time_sort(context, renderer, gaussian_count, config)?;
    Ok(BenchCase {
        gaussians: gaussian_count,
        width: camera.width,
        height: camera.height,
        intersections,
        forward_ms,
        forward_backward_ms,
        iteration_ms,
        sort_ms,
        stages,
        iteration_stages,
        peak_device_bytes,
    })
}

/// Medians of forward + backward and of a full optimisation iteration (forward, loss,
/// backward, Adam), and the iteration's stages, on `camera`'s view of `gaussians`.
fn time_iteration(
    context: &GpuContext,
    renderer: &GpuRenderer,
    kernels: &TrainingKernels,
    gaussians: &DeviceGaussians,
    camera: &Camera,
    config: &BenchConfig,
) -> Result<(f64, f64, StageTimes), GpuError> {
    let (warmup, repeats) = (config.warmup, config.repeats);
    let raster = RasterConfig::default();
    let target = DeviceTarget::upload(context, &target_image(camera))?;
    let image_gradients = DeviceImageGradients::zeros(context, camera)?;
    let weights = LossWeights::default();
    // Loss gradient computed once: the forward+backward timing reuses it as its input.
    let frame = renderer.render_frame(context, gaussians, camera, &raster)?;
    kernels.image_loss(
        context,
        renderer,
        &frame,
        &target,
        &weights,
        &image_gradients,
    )?;
    let forward_backward_ms = time_ms(context, warmup, repeats, || {
        let frame = renderer.render_frame(context, gaussians, camera, &raster)?;
        renderer.backward(context, gaussians, &frame, &image_gradients)?;
        Ok(())
    })?;
    let mut adam = DeviceAdam::new(context, gaussians, AdamConfig::default())?;
    let iteration_ms = time_ms(context, warmup, repeats, || {
        let frame = renderer.render_frame(context, gaussians, camera, &raster)?;
        kernels.image_loss(
            context,
            renderer,
            &frame,
            &target,
            &weights,
            &image_gradients,
        )?;
        let gradients = renderer.backward(context, gaussians, &frame, &image_gradients)?;
        kernels.adam_step(context, &mut adam, gaussians, &gradients)
    })?;
    let mut runs = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let mut times = StageTimes::default();
        context.wait_idle()?;
        let mut mark = Instant::now();
        let mut lap = |times: &mut StageTimes, name: &'static str| -> Result<(), GpuError> {
            context.wait_idle()?;
            let now = Instant::now();
            times.0.push((name, (now - mark).as_secs_f64() * 1e3));
            mark = now;
            Ok(())
        };
        let frame = renderer.render_frame(context, gaussians, camera, &raster)?;
        lap(&mut times, "forward")?;
        kernels.image_loss(
            context,
            renderer,
            &frame,
            &target,
            &weights,
            &image_gradients,
        )?;
        lap(&mut times, "loss")?;
        let mut backward_times = StageTimes::default();
        let gradients = renderer.backward_profiled(
            context,
            gaussians,
            &frame,
            &image_gradients,
            Some(&mut backward_times),
        )?;
        lap(&mut StageTimes::default(), "backward")?;
        times.0.extend(backward_times.0);
        kernels.adam_step(context, &mut adam, gaussians, &gradients)?;
        lap(&mut times, "adam")?;
        runs.push(times);
    }
    Ok((
        forward_backward_ms,
        iteration_ms,
        StageTimes::median_of(&runs),
    ))
}

/// Median time of the device radix sort of `count` random full-width keys (with values).
fn time_sort(
    context: &GpuContext,
    renderer: &GpuRenderer,
    count: usize,
    config: &BenchConfig,
) -> Result<f64, GpuError> {
    let mut rng = SplitMix64(config.seed ^ 0x5eed);
    let keys: Vec<u32> = (0..count).map(|_| rng.next_u64() as u32).collect();
    let values: Vec<u32> = (0..count as u32).collect();
    let sorter = DeviceSortBench::new(context, &keys, &values)?;
    time_ms(context, config.warmup, config.repeats, || {
        sorter.sort(context, renderer, u32::BITS)
    })
}
