//! Shared scenes and the shared wgpu context for the integration tests.
#![allow(dead_code, reason = "each test binary uses a different subset")]

use std::sync::OnceLock;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use render_core::context::GpuContext;
use render_core::gpu::{
    DeviceFrame, DeviceGaussians, GpuRenderer, PairUsage, RendererOptions, Subgroups,
};
use render_core::{Camera, RasterConfig};
use splats::{GaussianCloud, RigidTransform};

pub struct Gpu {
    pub context: GpuContext,
    pub renderer: GpuRenderer,
}

/// A renderer with the kernels that use no subgroup operations (for adapters without them).
pub fn renderer_without_subgroups(context: &GpuContext) -> GpuRenderer {
    GpuRenderer::with_options(
        context,
        RendererOptions {
            subgroups: Subgroups::Never,
            ..RendererOptions::default()
        },
    )
}

/// One device for all tests of a binary (lavapipe device creation is slow).
pub fn gpu() -> &'static Gpu {
    static GPU: OnceLock<Gpu> = OnceLock::new();
    GPU.get_or_init(|| {
        let context = GpuContext::new().expect("a wgpu adapter (lavapipe in CI) is required");
        eprintln!("adapter: {}", context.describe());
        let renderer = GpuRenderer::new(&context);
        Gpu { context, renderer }
    })
}

pub const WIDTH: u32 = 64;
pub const HEIGHT: u32 = 48;

pub fn camera(width: u32, height: u32, cx: f32, cy: f32) -> Camera {
    let world_from_camera =
        RigidTransform::from_quaternion_translation([0.97, 0.08, -0.15, 0.12], [0.3, -0.2, -0.5]);
    Camera::from_world_from_camera(world_from_camera, [55.0, 52.0, cx, cy], width, height)
}

pub fn default_camera() -> Camera {
    camera(
        WIDTH,
        HEIGHT,
        (WIDTH as f32 - 1.0) / 2.0,
        (HEIGHT as f32 - 1.0) / 2.0,
    )
}

/// A 128x96 camera (8 x 6 tiles) and large, fairly transparent splats in front of it: each
/// covers many of the 48 tiles (more than the 8 pairs per Gaussian a fresh renderer reserves)
/// and the far ones stay visible, so a fresh renderer's first frame overflows its pairs.
pub fn pair_overflow_scene() -> (Camera, GaussianCloud) {
    let (width, height) = (8 * 16, 6 * 16);
    let camera = camera(
        width,
        height,
        (width as f32 - 1.0) / 2.0,
        (height as f32 - 1.0) / 2.0,
    );
    let cloud = random_scene(&camera, 300, 11, (-1.2, -0.8), (-2.0, 0.0));
    (camera, cloud)
}

/// Random Gaussians in front of `camera`; `log_scale_range` controls footprint sizes and
/// `logit_range` the opacities.
pub fn random_scene(
    camera: &Camera,
    count: usize,
    seed: u64,
    log_scale_range: (f32, f32),
    logit_range: (f32, f32),
) -> GaussianCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let world_from_camera = camera.world_from_camera();
    let mut cloud = GaussianCloud::default();
    // Spill a little outside the image so border tiles see partial splats.
    const MARGIN_PIXELS: f32 = 10.0;
    for _ in 0..count {
        let z = rng.random_range(1.0f32..4.0);
        let u = rng.random_range(-MARGIN_PIXELS..camera.width as f32 + MARGIN_PIXELS);
        let v = rng.random_range(-MARGIN_PIXELS..camera.height as f32 + MARGIN_PIXELS);
        let point = [
            (u - camera.cx) * z / camera.fx,
            (v - camera.cy) * z / camera.fy,
            z,
        ];
        let mut log_scale = [0.0; 3];
        for s in &mut log_scale {
            *s = rng.random_range(log_scale_range.0..log_scale_range.1);
        }
        let quaternion = [
            rng.random_range(-1.0f32..1.0),
            rng.random_range(-1.0f32..1.0),
            rng.random_range(-1.0f32..1.0),
            rng.random_range(-1.0f32..1.0),
        ];
        cloud.push(
            world_from_camera.transform_point(point),
            log_scale,
            quaternion,
            rng.random_range(logit_range.0..logit_range.1),
            [
                rng.random_range(0.0f32..1.0),
                rng.random_range(0.0f32..1.0),
                rng.random_range(0.0f32..1.0),
            ],
        );
    }
    cloud
}

/// Each parameter group of a cloud (or of Adam moments, or gradients laid out like one) as one
/// flat f32 vector in buffer order: means, log-scales, quaternions, opacity logits, colours.
pub fn parameter_groups(cloud: &GaussianCloud) -> [Vec<f32>; 5] {
    [
        cloud.means.iter().flatten().copied().collect(),
        cloud.log_scales.iter().flatten().copied().collect(),
        cloud.quaternions.iter().flatten().copied().collect(),
        cloud.opacity_logits.clone(),
        cloud.colours.iter().flatten().copied().collect(),
    ]
}

/// The first `count` values of a device buffer, copied back to the host (blocking).
pub fn read_buffer<T: bytemuck::Pod>(
    context: &GpuContext,
    buffer: &wgpu::Buffer,
    count: usize,
) -> Vec<T> {
    let size = (count * std::mem::size_of::<T>()) as u64;
    let staging = context.device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = context.device.create_command_encoder(&Default::default());
    encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, size);
    context.queue.submit([encoder.finish()]);
    staging
        .slice(..)
        .map_async(wgpu::MapMode::Read, |result| result.unwrap());
    context
        .device
        .poll(wgpu::PollType::wait_indefinitely())
        .unwrap();
    let data = staging.slice(..).get_mapped_range().unwrap().to_vec();
    bytemuck::pod_collect_to_vec(&data)
}

/// A 16x16 camera (one tile) looking at `boundary_splats` faint splats between pixel centres,
/// with a red splat in front of them and a green one behind, both on pixel (3, 3).
///
/// Each faint splat sits at (7.5, 3.5), on the border of the tile's two 8-column halves and
/// between four pixel centres: its visible ellipse (where alpha could reach the 1/255 cut-off)
/// reaches both halves of the top band of rows, so the rasterizers walk it there, but at every
/// pixel centre its alpha stays below the cut-off, so it changes no pixel and no gradient. The
/// tile's list is `boundary_splats + 2` entries long, and the rasterizers' walks over the top
/// band take a few loop trips per entry: enough of them outgrow lavapipe's loop limit (65535
/// trips per invocation, render-core/README.md). What a walk cut short loses shows: the
/// forward walk (front to back) the green splat, the backward walk (back to front) the red
/// splat's gradient.
pub fn loop_limit_scene(boundary_splats: usize) -> (Camera, GaussianCloud) {
    const SIDE: u32 = 16;
    const FOCAL: f32 = 50.0;
    let centre = (SIDE as f32 - 1.0) / 2.0;
    let identity = RigidTransform::from_quaternion_translation([1.0, 0.0, 0.0, 0.0], [0.0; 3]);
    let camera =
        Camera::from_world_from_camera(identity, [FOCAL, FOCAL, centre, centre], SIDE, SIDE);
    // At pixel (u, v) and camera depth z (the camera is the world frame).
    let point = |u: f32, v: f32, z: f32| [(u - centre) * z / FOCAL, (v - centre) * z / FOCAL, z];
    // Tiny 3D extent: the splats are the 2D low-pass filter's (variance 0.3 px^2).
    let tiny = [-9.0; 3];
    let logit = |opacity: f32| (opacity / (1.0 - opacity)).ln();
    let mut cloud = GaussianCloud::default();
    let mut push = |point, logit, colour| {
        cloud.push(point, tiny, [1.0, 0.0, 0.0, 0.0], logit, colour);
    };
    push(point(3.0, 3.0, 1.0), logit(0.5), [1.0, 0.0, 0.0]);
    // alpha = opacity * exp(-d^2 / (2 * 0.3)): 1.9 / 255 gives 0.0032 at the nearest pixel
    // centres (d^2 = 0.5), under the 1/255 cut-off, while the visible ellipse's radius
    // (sqrt(2 ln 1.9 * 0.3) = 0.62 px) passes the halves' nearest points (0.5 px away).
    for _ in 0..boundary_splats {
        push(point(7.5, 3.5, 2.0), logit(1.9 / 255.0), [1.0; 3]);
    }
    push(point(3.0, 3.0, 3.0), logit(0.5), [0.0, 1.0, 0.0]);
    (camera, cloud)
}

/// Whether the adapter is a lavapipe of Mesa 22 or older (measured: 22.3), whose loop limit
/// `loop_limit_scene` is sized for (there a loop's body runs masked once more than its trips
/// and every subgroup operation is a loop over the lanes). Other adapters need not have one:
/// Mesa 25's lavapipe walks 70 000 entries of that scene, forward and backward, without
/// cutting them short.
pub fn has_lavapipe_loop_limit(context: &GpuContext) -> bool {
    context.describe().contains("llvmpipe")
        && render_core::context::mesa_version(&context.adapter_info.driver_info)
            .is_some_and(|version| version[0] <= 22)
}

/// A frame of `gaussians` and its check, rendered again once when the first overflowed its
/// pairs (check_pairs sizes the second, as `GpuRenderer::render` does).
pub fn render_checked(
    renderer: &GpuRenderer,
    gaussians: &DeviceGaussians,
    camera: &Camera,
) -> (DeviceFrame, PairUsage) {
    let context = &gpu().context;
    let render = || {
        let frame = renderer
            .render_frame(context, gaussians, camera, &RasterConfig::default())
            .unwrap();
        let usage = renderer.check_pairs(context, &frame).unwrap();
        (frame, usage)
    };
    let (frame, usage) = render();
    if usage.overflowed() {
        let (frame, usage) = render();
        assert!(!usage.overflowed(), "{usage:?}");
        return (frame, usage);
    }
    (frame, usage)
}
