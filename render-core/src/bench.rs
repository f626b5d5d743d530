//! Render benchmark: wall-clock timings of the device pipeline on a deterministic synthetic
//! scene that looks like an indoor SLAM map (a room of surfaces 1-4 m from the camera covered
//! by Gaussians of a few centimetres), seen from inside the room so that it fills the view.
//!
//! Every timing is "submit, then block until the device is idle", so it measures the device
//! work and the host-side encoding together (what a mapping loop waits for). Reported figures
//! are the median of `repeats` runs after `warmup` untimed runs.

use std::time::Instant;

use crate::backward::DeviceImageGradients;
use crate::context::{GpuContext, GpuError};
use crate::gpu::{DeviceGaussians, DeviceSortBench, GpuRenderer, StageTimes};
use crate::training::{
    AdamConfig, DeviceAdam, DeviceTarget, LossWeights, TargetImage, TrainingKernels,
};
use crate::types::{Camera, GaussianCloud, RasterConfig, RigidTransform};

/// Focal length of the benchmark camera at 640 pixels of width (a Kinect-like sensor);
/// other widths scale it so that the field of view stays the same.
const FOCAL_AT_640: f32 = 525.0;
const REFERENCE_WIDTH: f32 = 640.0;
/// Camera z range of the synthetic surfaces (metres).
const NEAREST_SURFACE: f32 = 1.0;
const FARTHEST_SURFACE: f32 = 4.0;
/// Typical depth of the back wall the camera looks at (metres).
const WALL_DEPTH: f32 = 3.0;
/// The wall bulges by up to this much (metres) along sin/cos waves over the image, with these
/// spatial frequencies (radians per pixel), and each Gaussian sits up to WALL_JITTER off it.
const WALL_WAVE_AMPLITUDE: f32 = 0.3;
const WALL_WAVE_FREQUENCY_U: f32 = 0.02;
const WALL_WAVE_FREQUENCY_V: f32 = 0.015;
const WALL_JITTER: f32 = 0.01;
/// Colours: red and green vary smoothly over the image around mid-grey (frequencies in
/// radians per pixel), blue is random within [MIN_BLUE, MAX_BLUE).
const MID_GREY: f32 = 0.5;
const COLOUR_WAVE_AMPLITUDE: f32 = 0.4;
const RED_WAVE_FREQUENCY: f32 = 0.01;
const GREEN_WAVE_FREQUENCY: f32 = 0.013;
const MIN_BLUE: f32 = 0.1;
const MAX_BLUE: f32 = 0.9;
/// Fraction of Gaussians on objects in front of the wall (the rest cover the wall).
const OBJECT_FRACTION: f32 = 0.4;
/// Standard deviations of the Gaussians' two large axes: 1 to 4 cm; the third axis is
/// flattened (surfels on surfaces).
const MIN_SCALE: f32 = 0.01;
const MAX_SCALE: f32 = 0.04;
const FLAT_AXIS_FACTOR: f32 = 0.2;
/// Opacity logits: sigmoid(-1) = 0.27 to sigmoid(4) = 0.98, like a trained map.
const MIN_OPACITY_LOGIT: f32 = -1.0;
const MAX_OPACITY_LOGIT: f32 = 4.0;
/// Gaussians may sit this many pixels outside the image (partial splats on border tiles).
const MARGIN_PIXELS: f32 = 24.0;
/// Depth of the synthetic target image used by the loss (metres).
const TARGET_DEPTH: f32 = 2.5;

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
            gaussian_counts: vec![10_000, 100_000, 1_000_000],
            width: 640,
            height: 480,
            warmup: 1,
            repeats: 5,
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

/// The benchmark camera: `width x height`, principal point at the image centre, at the
/// world origin looking along +z (world = camera frame).
pub fn bench_camera(width: u32, height: u32) -> Camera {
    let focal = FOCAL_AT_640 * width as f32 / REFERENCE_WIDTH;
    Camera::from_world_from_camera(
        RigidTransform::IDENTITY,
        [
            focal,
            focal,
            (width as f32 - 1.0) / 2.0,
            (height as f32 - 1.0) / 2.0,
        ],
        width,
        height,
    )
}

/// A small deterministic generator (SplitMix64) so that the scene needs no RNG dependency
/// and is identical on every machine.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        // The published SplitMix64 increment and finaliser multipliers (Steele et al. 2014).
        const GOLDEN_GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;
        self.0 = self.0.wrapping_add(GOLDEN_GAMMA);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[low, high)`.
    fn uniform(&mut self, low: f32, high: f32) -> f32 {
        const MANTISSA_BITS: u32 = 24;
        let unit = (self.next_u64() >> (u64::BITS - MANTISSA_BITS)) as f32
            / (1u64 << MANTISSA_BITS) as f32;
        low + (high - low) * unit
    }
}

/// `count` Gaussians of an indoor-map-like scene in front of [`bench_camera`]: a wavy back
/// wall plus objects scattered in front of it, colours varying smoothly over the image.
pub fn realistic_scene(camera: &Camera, count: usize, seed: u64) -> GaussianCloud {
    let mut rng = SplitMix64(seed);
    let world_from_camera = camera.world_from_camera();
    let mut cloud = GaussianCloud::default();
    for _ in 0..count {
        let u = rng.uniform(-MARGIN_PIXELS, camera.width as f32 + MARGIN_PIXELS);
        let v = rng.uniform(-MARGIN_PIXELS, camera.height as f32 + MARGIN_PIXELS);
        let wall = WALL_DEPTH
            + WALL_WAVE_AMPLITUDE
                * (u * WALL_WAVE_FREQUENCY_U).sin()
                * (v * WALL_WAVE_FREQUENCY_V).cos()
            + rng.uniform(-WALL_JITTER, WALL_JITTER);
        let z = if rng.uniform(0.0, 1.0) < OBJECT_FRACTION {
            rng.uniform(NEAREST_SURFACE, wall)
        } else {
            wall
        }
        .clamp(NEAREST_SURFACE, FARTHEST_SURFACE);
        let point = [
            (u - camera.cx) * z / camera.fx,
            (v - camera.cy) * z / camera.fy,
            z,
        ];
        let large = [
            rng.uniform(MIN_SCALE, MAX_SCALE),
            rng.uniform(MIN_SCALE, MAX_SCALE),
        ];
        let log_scale = [
            large[0].ln(),
            large[1].ln(),
            (FLAT_AXIS_FACTOR * large[0].min(large[1])).ln(),
        ];
        let quaternion = [
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ];
        let colour = [
            MID_GREY + COLOUR_WAVE_AMPLITUDE * (u * RED_WAVE_FREQUENCY).sin(),
            MID_GREY + COLOUR_WAVE_AMPLITUDE * (v * GREEN_WAVE_FREQUENCY).cos(),
            rng.uniform(MIN_BLUE, MAX_BLUE),
        ];
        cloud.push(
            world_from_camera.transform_point(point),
            log_scale,
            quaternion,
            rng.uniform(MIN_OPACITY_LOGIT, MAX_OPACITY_LOGIT),
            colour,
        );
    }
    cloud
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
        let target = DeviceTarget::upload(context, &target_image(&camera))?;
        let image_gradients = DeviceImageGradients::zeros(context, &camera)?;
        let weights = LossWeights::default();
        // Loss gradient computed once: the forward+backward timing reuses it as its input.
        let frame = renderer.render_frame(context, &gaussians, &camera, &raster)?;
        kernels.image_loss(
            context,
            renderer,
            &frame,
            &target,
            &weights,
            &image_gradients,
        )?;
        let forward_backward_ms = time_ms(context, warmup, repeats, || {
            let frame = renderer.render_frame(context, &gaussians, &camera, &raster)?;
            renderer.backward(context, &gaussians, &frame, &image_gradients)?;
            Ok(())
        })?;
        let mut adam = DeviceAdam::new(context, &gaussians, AdamConfig::default())?;
        let iteration_ms = time_ms(context, warmup, repeats, || {
            let frame = renderer.render_frame(context, &gaussians, &camera, &raster)?;
            kernels.image_loss(
                context,
                renderer,
                &frame,
                &target,
                &weights,
                &image_gradients,
            )?;
            let gradients = renderer.backward(context, &gaussians, &frame, &image_gradients)?;
            kernels.adam_step(context, &mut adam, &gaussians, &gradients)
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
            let frame = renderer.render_frame(context, &gaussians, &camera, &raster)?;
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
                &gaussians,
                &frame,
                &image_gradients,
                Some(&mut backward_times),
            )?;
            lap(&mut StageTimes::default(), "backward")?;
            times.0.extend(backward_times.0);
            kernels.adam_step(context, &mut adam, &gaussians, &gradients)?;
            lap(&mut times, "adam")?;
            runs.push(times);
        }
        (
            Some(forward_backward_ms),
            Some(iteration_ms),
            StageTimes::median_of(&runs),
        )
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference;

    #[test]
    fn realistic_scene_is_deterministic_and_fills_the_view() {
        const COUNT: usize = 20_000;
        let camera = bench_camera(640, 480);
        let cloud = realistic_scene(&camera, COUNT, 3);
        assert_eq!(cloud, realistic_scene(&camera, COUNT, 3));
        assert_ne!(cloud, realistic_scene(&camera, COUNT, 4));
        cloud.validate_lengths().unwrap();
        let visible = reference::project_and_sort(&cloud, &camera);
        assert!(
            // The margin around the image holds about 15% of the centres.
            visible.len() > cloud.len() * 3 / 4,
            "only {} of {} Gaussians are in view",
            visible.len(),
            cloud.len()
        );
        for splat in &visible {
            let depth = splat.camera_point[2] as f32;
            assert!((NEAREST_SURFACE..=FARTHEST_SURFACE).contains(&depth));
        }
        // Every 16x16 tile is covered by some splat (the scene fills the view).
        let (tiles_x, tiles_y) = camera.tile_counts();
        let mut covered = vec![false; (tiles_x * tiles_y) as usize];
        for splat in &visible {
            let [x0, y0, x1, y1] = splat.tile_rect;
            for ty in y0..=y1 {
                for tx in x0..=x1 {
                    covered[(ty * tiles_x + tx) as usize] = true;
                }
            }
        }
        assert!(covered.iter().all(|&c| c));
    }
}
