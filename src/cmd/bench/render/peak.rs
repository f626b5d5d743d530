//! The machine's peak (pixel, splat) evaluation rate: the forward rasterizer timed on a scene
//! where every evaluation it makes changes the image. Every splat covers the whole view with an
//! alpha above `min_splat_alpha` and no pixel reaches the transmittance floor, so no splat is
//! skipped, no pixel stops early and every (pixel, splat) pair of every tile is evaluated and
//! visible. The rasterize stage's time over that count is the fastest this rasterizer
//! evaluates pairs on this machine; a real view's rate against it shows how much of its time
//! goes into pairs it could not have avoided.

use render_core::constants::TILE_SIZE;
use render_core::context::{GpuContext, GpuError};
use render_core::gpu::{DeviceGaussians, GpuRenderer, StageTimes};
use render_core::{Camera, RasterConfig};
use splats::GaussianCloud;

use super::harness::{BenchConfig, bench_camera};

/// Splats of the peak scene, one per depth layer: every tile's list holds all of them.
pub const PEAK_LAYERS: u32 = 128;
/// sigmoid(-3.9) = 0.0198 per layer: 128 layers leave a transmittance of 0.077, far above
/// the floor, and every layer's alpha stays above 1/255 wherever its value exceeds 0.2.
const PEAK_OPACITY_LOGIT: f32 = -3.9;
/// Standard deviation of the layers' footprint, in image diagonals: the value at a corner
/// is exp(-0.5 * 0.5^2) = 0.88, well above the 0.2 the alpha cut-off needs.
const PEAK_SIGMA_DIAGONALS: f32 = 1.0;
/// Camera z of the nearest and farthest layer (metres).
const PEAK_NEAREST: f32 = 1.0;
const PEAK_FARTHEST: f32 = 2.0;
/// Thickness of the flat layers relative to their width.
const PEAK_FLAT_FACTOR: f32 = 0.01;
/// The rasterize stage's name in [`StageTimes`] (render_core::gpu::GpuRenderer::render_frame_profiled).
pub const RASTERIZE_STAGE: &str = "rasterize";

/// The peak rate on one image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeakRate {
    pub width: u32,
    pub height: u32,
    /// (pixel, splat) evaluations of one render: every pixel slot of every tile times
    /// [`PEAK_LAYERS`] (slots past the image's edge are evaluated too).
    pub evaluations: u64,
    /// Median time of the rasterize stage (submitted and waited for on its own).
    pub rasterize_ms: f64,
}

impl PeakRate {
    pub fn evaluations_per_second(&self) -> f64 {
        self.evaluations as f64 / (self.rasterize_ms * 1e-3)
    }
}

/// [`PEAK_LAYERS`] flat, low-opacity Gaussians facing `camera`, centred on its view, each
/// covering all of it (see the module doc).
pub fn peak_scene(camera: &Camera) -> GaussianCloud {
    let world_from_camera = camera.world_from_camera();
    let diagonal = (camera.width as f32).hypot(camera.height as f32);
    let sigma_pixels = PEAK_SIGMA_DIAGONALS * diagonal;
    let mut cloud = GaussianCloud::default();
    for layer in 0..PEAK_LAYERS {
        let z =
            PEAK_NEAREST + (PEAK_FARTHEST - PEAK_NEAREST) * layer as f32 / (PEAK_LAYERS - 1) as f32;
        let centre = [
            (camera.width as f32 / 2.0 - camera.cx) * z / camera.fx,
            (camera.height as f32 / 2.0 - camera.cy) * z / camera.fy,
            z,
        ];
        let sigma = sigma_pixels * z / camera.fx;
        let grey = layer as f32 / PEAK_LAYERS as f32;
        cloud.push(
            world_from_camera.transform_point(centre),
            [sigma.ln(), sigma.ln(), (PEAK_FLAT_FACTOR * sigma).ln()],
            [1.0, 0.0, 0.0, 0.0],
            PEAK_OPACITY_LOGIT,
            [grey, 1.0 - grey, 0.5],
        );
    }
    cloud
}

/// Times the forward rasterizer on [`peak_scene`] at `width` x `height` (`config.warmup` and
/// `config.repeats` as for the other measurements).
pub fn peak_rate(
    context: &GpuContext,
    renderer: &GpuRenderer,
    config: &BenchConfig,
    width: u32,
    height: u32,
) -> Result<PeakRate, GpuError> {
    let camera = bench_camera(width, height);
    let gaussians = DeviceGaussians::upload(context, &peak_scene(&camera))?;
    let raster = RasterConfig::default();
    // Size the pair buffers for this view first (every layer reaches every tile).
    let first = renderer.render_frame(context, &gaussians, &camera, &raster)?;
    if renderer.check_pairs(context, &first)?.overflowed() {
        renderer.render_frame(context, &gaussians, &camera, &raster)?;
    }
    for _ in 0..config.warmup {
        renderer.render_frame(context, &gaussians, &camera, &raster)?;
        context.wait_idle()?;
    }
    let mut runs = Vec::with_capacity(config.repeats.max(1));
    for _ in 0..config.repeats.max(1) {
        let mut times = StageTimes::default();
        renderer.render_frame_profiled(context, &gaussians, &camera, &raster, Some(&mut times))?;
        runs.push(times);
    }
    let rasterize_ms = rasterize_ms(&StageTimes::median_of(&runs)).ok_or_else(|| {
        GpuError::InvalidInput(format!("no {RASTERIZE_STAGE:?} stage in the profile"))
    })?;
    let (tiles_x, tiles_y) = camera.tile_counts();
    let slots = u64::from(tiles_x * tiles_y) * u64::from(TILE_SIZE * TILE_SIZE);
    Ok(PeakRate {
        width,
        height,
        evaluations: slots * u64::from(PEAK_LAYERS),
        rasterize_ms,
    })
}

/// The rasterize stage's time in a forward profile.
fn rasterize_ms(stages: &StageTimes) -> Option<f64> {
    stages
        .0
        .iter()
        .find(|(stage, _)| *stage == RASTERIZE_STAGE)
        .map(|&(_, ms)| ms)
}

#[cfg(test)]
mod tests {
    use super::super::harness::raster_workload;
    use super::*;

    #[test]
    fn every_evaluation_of_the_peak_scene_is_visible() {
        // 64x48: 4x3 whole tiles, so every evaluated slot is a pixel.
        let camera = bench_camera(64, 48);
        let cloud = peak_scene(&camera);
        let raster = RasterConfig::default();
        let pixels = u64::from(camera.width * camera.height);
        for (band_rows, band_columns) in [(16, 16), (8, 8), (4, 16)] {
            let workload =
                raster_workload(&cloud, &camera, &raster, 16, band_rows, band_columns).unwrap();
            assert_eq!(workload.pairs, 12 * u64::from(PEAK_LAYERS));
            assert_eq!(workload.evaluations, pixels * u64::from(PEAK_LAYERS));
            assert_eq!(workload.visible_evaluations, workload.evaluations);
        }
    }
}
