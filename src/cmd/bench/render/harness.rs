//! Render benchmark: wall-clock timings of the device pipeline on a deterministic synthetic
//! scene that looks like an indoor SLAM map (a room of surfaces 1-4 m from the camera covered
//! by Gaussians of a few centimetres), seen from inside the room so that it fills the view.
//!
//! Every timing is "submit, then block until the device is idle", so it measures the device
//! work and the host-side encoding together (what a mapping loop waits for). Reported figures
//! are the median of `repeats` runs after `warmup` untimed runs.

use std::time::Instant;

use render_core::backward::DeviceImageGradients;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::{DeviceGaussians, DeviceSortBench, GpuRenderer, StageTimes};
use render_core::reference::{ProjectedGaussian, project_and_sort, splat_at_pixel};
use render_core::training::{
    AdamConfig, DeviceAdam, DeviceTarget, LossWeights, TargetImage, TrainingKernels,
};
use render_core::{Camera, GaussianCloud, RasterConfig, RigidTransform};

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

/// The (pixel, splat) work of a tile rasterizer on one view, counted on the host (no device):
/// what the rasterizer kernels spend their arithmetic on, against what contributes to the
/// image. Splats are the reference projection's, binned into every tile their visible ellipse
/// (where opacity x exp(power) can reach `min_splat_alpha`) reaches, as the renderer's tile
/// masks do, and walked front to back per band of `band_rows` tile rows, as the subgroup
/// rasterizers walk them per subgroup, each band tested in parts of `band_columns` columns
/// (8, the rasterizers' two halves of a tile; 16, the whole tile): a part the
/// splat's visible ellipse misses is skipped, any other costs one evaluation per pixel of the
/// part, until every pixel of the band has terminated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RasterWorkload {
    pub tile_size: u32,
    /// Tile rows one skip test and one early-termination test cover (the subgroup's rows in
    /// the subgroup rasterizer: one row per lane).
    pub band_rows: u32,
    /// Columns of one skip test (a divisor of `tile_size`).
    pub band_columns: u32,
    /// Tile/splat pairs. Within 1 % of the renderer's on the benchmark scene, which masks
    /// tiles by the ellipse only for rectangles of up to 32 tiles and adds safety margins.
    pub pairs: u64,
    /// (band part, splat) steps that were not skipped.
    pub band_steps: u64,
    /// Pixel evaluations: `band_steps` x pixels per band part.
    pub evaluations: u64,
    /// Evaluations where the pixel was still compositing and the splat's alpha reached
    /// `min_splat_alpha`: the part of the arithmetic that changes the image.
    pub visible_evaluations: u64,
}

/// Counts [`RasterWorkload`] for `cloud` seen by `camera` with `tile_size` x `tile_size` tiles
/// walked in bands of `band_rows` rows, skip-tested in parts of `band_columns` columns
/// (divisors of `tile_size`). The early-termination test
/// runs after every splat here; the kernels test after every batch of one splat per lane, so
/// they run a few more steps than counted.
pub fn raster_workload(
    cloud: &GaussianCloud,
    camera: &Camera,
    raster: &RasterConfig,
    tile_size: u32,
    band_rows: u32,
    band_columns: u32,
) -> Result<RasterWorkload, GpuError> {
    for (what, length) in [("rows", band_rows), ("columns", band_columns)] {
        if tile_size == 0 || length == 0 || !tile_size.is_multiple_of(length) {
            return Err(GpuError::InvalidInput(format!(
                "band of {length} {what} does not divide a tile of {tile_size} pixels"
            )));
        }
    }
    let (width, height) = (camera.width, camera.height);
    let min_transmittance = f64::from(raster.min_transmittance);
    let splats = project_and_sort(cloud, camera);
    let ellipses: Vec<VisibleEllipse> = splats
        .iter()
        .map(|splat| VisibleEllipse::of(splat, raster))
        .collect();
    let tiles_x = width.div_ceil(tile_size);
    let tiles_y = height.div_ceil(tile_size);
    // Inclusive pixel-centre range of tile k along one axis.
    let tile_span = |k: u32| (f64::from(k * tile_size), f64::from((k + 1) * tile_size - 1));
    let mut workload = RasterWorkload {
        tile_size,
        band_rows,
        band_columns,
        pairs: 0,
        band_steps: 0,
        evaluations: 0,
        visible_evaluations: 0,
    };

    // Binning: each splat into the tiles its visible ellipse reaches, in depth order.
    let mut lists: Vec<Vec<usize>> = vec![Vec::new(); (tiles_x * tiles_y) as usize];
    for (index, ellipse) in ellipses.iter().enumerate() {
        let Some((x_min, x_max)) = ellipse
            .x_extent((0.0, f64::from(height - 1)))
            .filter(|&(left, right)| right >= 0.0 && left <= f64::from(width - 1))
        else {
            continue;
        };
        let [_, half_y] = ellipse.half_extents();
        let y_min = (ellipse.mean[1] - half_y).max(0.0);
        let first_x = (x_min.max(0.0) / f64::from(tile_size)) as u32;
        let last_x = ((x_max / f64::from(tile_size)) as u32).min(tiles_x - 1);
        let first_y = (y_min / f64::from(tile_size)) as u32;
        let last_y = (((ellipse.mean[1] + half_y) / f64::from(tile_size)) as u32).min(tiles_y - 1);
        for tile_y in first_y..=last_y {
            let Some((reach_min, reach_max)) = ellipse.x_extent(tile_span(tile_y)) else {
                continue;
            };
            for tile_x in first_x..=last_x {
                let (columns_min, columns_max) = tile_span(tile_x);
                if reach_max >= columns_min && reach_min <= columns_max {
                    lists[(tile_y * tiles_x + tile_x) as usize].push(index);
                    workload.pairs += 1;
                }
            }
        }
    }

    // Compositing, band by band, with the per-pixel arithmetic of the CPU reference.
    let band_pixels = band_rows * tile_size;
    let mut transmittance = vec![1.0f64; band_pixels as usize];
    let mut done = vec![false; band_pixels as usize];
    for tile_y in 0..tiles_y {
        for tile_x in 0..tiles_x {
            let list = &lists[(tile_y * tiles_x + tile_x) as usize];
            for first_row in
                (tile_y * tile_size..(tile_y + 1) * tile_size).step_by(band_rows as usize)
            {
                let pixel_at = |p: u32| {
                    (
                        tile_x * tile_size + p % tile_size,
                        first_row + p / tile_size,
                    )
                };
                let mut compositing = 0;
                for p in 0..band_pixels {
                    let (column, row) = pixel_at(p);
                    transmittance[p as usize] = 1.0;
                    done[p as usize] = column >= width || row >= height;
                    compositing += usize::from(!done[p as usize]);
                }
                let band_rows_span = (f64::from(first_row), f64::from(first_row + band_rows - 1));
                for &index in list {
                    if compositing == 0 {
                        break;
                    }
                    let reached_parts = (0..tile_size / band_columns)
                        .filter(|part| {
                            let first = f64::from(tile_x * tile_size + part * band_columns);
                            let columns = (first, first + f64::from(band_columns - 1));
                            !ellipses[index].misses_box(band_rows_span, columns)
                        })
                        .count() as u64;
                    if reached_parts == 0 {
                        continue;
                    }
                    workload.band_steps += reached_parts;
                    workload.evaluations += reached_parts * u64::from(band_rows * band_columns);
                    for p in 0..band_pixels {
                        if done[p as usize] {
                            continue;
                        }
                        let (column, row) = pixel_at(p);
                        let pixel = [f64::from(column), f64::from(row)];
                        let Some(hit) = splat_at_pixel(&splats[index], pixel, raster) else {
                            continue;
                        };
                        workload.visible_evaluations += 1;
                        let next = transmittance[p as usize] * (1.0 - hit.alpha);
                        if next < min_transmittance {
                            done[p as usize] = true;
                            compositing -= 1;
                        } else {
                            transmittance[p as usize] = next;
                        }
                    }
                }
            }
        }
    }
    Ok(workload)
}

/// Where a projected splat can reach `min_splat_alpha`: the ellipse conic(offset) <=
/// radius_squared, radius_squared = 2 ln(opacity / min_alpha), around its mean (the host
/// counterpart of `visible_radius_squared` in common.wgsl, without its safety margins). The conic
/// `[a, b, c]` is the quadratic form a dx^2 + 2 b dx dy + c dy^2.
struct VisibleEllipse {
    mean: [f64; 2],
    conic: [f64; 3],
    radius_squared: f64,
}

impl VisibleEllipse {
    fn of(splat: &ProjectedGaussian, raster: &RasterConfig) -> Self {
        let min_alpha = f64::from(raster.min_splat_alpha);
        Self {
            mean: splat.mean2d,
            conic: splat.conic,
            radius_squared: (2.0 * (splat.opacity / min_alpha).ln()).max(0.0),
        }
    }

    /// Half extents (x, y) of its bounding box: sqrt(r^2 * covariance) per axis. NaN for a
    /// degenerate conic.
    fn half_extents(&self) -> [f64; 2] {
        let [a, b, c] = self.conic;
        let determinant = a * c - b * b;
        [
            (self.radius_squared * c / determinant).sqrt(),
            (self.radius_squared * a / determinant).sqrt(),
        ]
    }

    /// Whether it misses the box of pixel centres `columns` x `rows` (inclusive ranges), as
    /// the subgroup rasterizers' skip test (`ellipse_misses_box` in common.wgsl) decides.
    fn misses_box(&self, rows: (f64, f64), (x_min, x_max): (f64, f64)) -> bool {
        self.x_extent(rows)
            .is_none_or(|(left, right)| right < x_min || left > x_max)
    }

    /// Its x range over the rows `y_min ..= y_max`, or `None` when it misses them (or is
    /// degenerate).
    fn x_extent(&self, (y_min, y_max): (f64, f64)) -> Option<(f64, f64)> {
        let [a, b, c] = self.conic;
        let [half_x, half_y] = self.half_extents();
        let mean = self.mean;
        let low = y_min.max(mean[1] - half_y);
        let high = y_max.min(mean[1] + half_y);
        // A degenerate conic gives NaN bounds: that misses too.
        if low.is_nan() || high.is_nan() || low > high {
            return None;
        }
        // The chord at row y: centre mean.x - b dy / a, half-width sqrt(a r^2 - det dy^2) / a.
        let determinant = a * c - b * b;
        let chord = |y: f64| {
            let dy = y - mean[1];
            let centre = mean[0] - b * dy / a;
            let half = (a * self.radius_squared - determinant * dy * dy)
                .max(0.0)
                .sqrt()
                / a;
            (centre - half, centre + half)
        };
        let (low_left, low_right) = chord(low);
        let (high_left, high_right) = chord(high);
        let (mut left, mut right) = (low_left.min(high_left), low_right.max(high_right));
        // The extreme points (dx = +-half_x, where the gradient is horizontal: b dx + c dy = 0)
        // bound the range when their rows lie inside.
        let rightmost_dy = -b * half_x / c;
        if (low..=high).contains(&(mean[1] + rightmost_dy)) {
            right = mean[0] + half_x;
        }
        if (low..=high).contains(&(mean[1] - rightmost_dy)) {
            left = mean[0] - half_x;
        }
        Some((left, right))
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use render_core::reference;

    #[test]
    fn raster_workload_counts_band_steps_and_visible_pixels() {
        // One opaque-ish splat near the corner of a 32x32 image (2x2 tiles of 16), small
        // enough (visible box about 4 pixels each way) to stay inside tile (0, 0)'s first
        // band of 8 rows and its left 8 columns.
        let camera = bench_camera(32, 32);
        let mut cloud = GaussianCloud::default();
        let depth = 2.0;
        let (u, v) = (3.5, 3.5);
        let mean = [
            (u - camera.cx) / camera.fx * depth,
            (v - camera.cy) / camera.fy * depth,
            depth,
        ];
        // About one pixel of standard deviation; opacity 0.9 (logit ln 9).
        let sigma = depth / camera.fx;
        cloud.push(
            mean,
            [sigma.ln(); 3],
            [1.0, 0.0, 0.0, 0.0],
            9f32.ln(),
            [0.5; 3],
        );
        let raster = RasterConfig::default();
        let workload = raster_workload(&cloud, &camera, &raster, 16, 8, 16).unwrap();
        assert_eq!(workload.pairs, 1);
        assert_eq!(workload.band_steps, 1);
        assert_eq!(workload.evaluations, 16 * 8);
        // It stays in the tile's left half: halves evaluate that half only.
        let halves = raster_workload(&cloud, &camera, &raster, 16, 8, 8).unwrap();
        assert_eq!(halves.band_steps, 1);
        assert_eq!(halves.evaluations, 8 * 8);
        assert_eq!(halves.visible_evaluations, workload.visible_evaluations);
        assert!(workload.visible_evaluations > 0);
        assert!(workload.visible_evaluations < workload.evaluations);
        // Bands of a whole tile evaluate the tile once; the visible count does not change.
        let whole = raster_workload(&cloud, &camera, &raster, 16, 16, 16).unwrap();
        assert_eq!(whole.evaluations, 16 * 16);
        assert_eq!(whole.visible_evaluations, workload.visible_evaluations);
        assert!(raster_workload(&cloud, &camera, &raster, 16, 5, 16).is_err());
        assert!(raster_workload(&cloud, &camera, &raster, 16, 8, 5).is_err());
    }

    #[test]
    fn visible_ellipse_x_extent_matches_a_dense_scan() {
        let mean = [10.0, 20.0];
        // A tilted ellipse (b != 0).
        let conic = [0.2, 0.12, 0.1];
        let radius_squared = 4.0;
        for (y_min, y_max) in [(14.0, 16.0), (18.0, 30.0), (25.0, 27.0), (0.0, 5.0)] {
            let mut scanned: Option<(f64, f64)> = None;
            for step in 0..=2000 {
                let y = y_min + (y_max - y_min) * f64::from(step) / 2000.0;
                for x_step in 0..=4000 {
                    let x = -20.0 + 60.0 * f64::from(x_step) / 4000.0;
                    let (dx, dy) = (x - mean[0], y - mean[1]);
                    let q = conic[0] * dx * dx + 2.0 * conic[1] * dx * dy + conic[2] * dy * dy;
                    if q <= radius_squared {
                        scanned = Some(scanned.map_or((x, x), |(l, r)| (l.min(x), r.max(x))));
                    }
                }
            }
            let ellipse = VisibleEllipse {
                mean,
                conic,
                radius_squared,
            };
            let exact = ellipse.x_extent((y_min, y_max));
            match (exact, scanned) {
                (None, None) => {}
                (Some((l, r)), Some((sl, sr))) => {
                    // The scan's grid is 0.015 pixel wide.
                    assert!(
                        l <= sl + 1e-9 && l > sl - 0.02,
                        "left {l} vs {sl} for {y_min}..{y_max}"
                    );
                    assert!(
                        r >= sr - 1e-9 && r < sr + 0.02,
                        "right {r} vs {sr} for {y_min}..{y_max}"
                    );
                }
                other => panic!("rows {y_min}..{y_max}: {other:?}"),
            }
        }
    }

    #[test]
    fn raster_workload_is_bounded_and_narrower_bands_see_the_same_image() {
        let camera = bench_camera(160, 120);
        let cloud = realistic_scene(&camera, 5_000, 7);
        let raster = RasterConfig::default();
        let bands_of_8 = raster_workload(&cloud, &camera, &raster, 16, 8, 16).unwrap();
        let bands_of_4 = raster_workload(&cloud, &camera, &raster, 16, 4, 16).unwrap();
        let halves_of_8 = raster_workload(&cloud, &camera, &raster, 16, 8, 8).unwrap();
        assert!(bands_of_8.visible_evaluations > 0);
        assert!(bands_of_8.visible_evaluations <= bands_of_8.evaluations);
        assert!(bands_of_8.evaluations <= bands_of_8.pairs * 16 * 16);
        // Narrower bands skip more and never see a different image.
        assert!(bands_of_4.evaluations <= bands_of_8.evaluations);
        assert_eq!(
            bands_of_4.visible_evaluations,
            bands_of_8.visible_evaluations
        );
        // So do narrower parts.
        assert!(halves_of_8.evaluations < bands_of_8.evaluations);
        assert_eq!(
            halves_of_8.visible_evaluations,
            bands_of_8.visible_evaluations
        );
    }

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
