//! The wgpu backward pass against the CPU reference backward (itself checked by finite
//! differences in src/reference/tests.rs).

mod common;

use common::{
    default_camera, gpu, has_lavapipe_loop_limit, loop_limit_scene, pair_overflow_scene,
    random_scene, render_checked, renderer_without_subgroups,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use render_core::backward::DeviceImageGradients;
use render_core::gpu::{
    DeviceGaussians, GpuRenderer, GradientAtomics, GradientOrder, RendererOptions, Subgroups,
};
use render_core::reference;
use render_core::{Camera, GaussianGradients, ImageGradients, RasterConfig};
use splats::GaussianCloud;

/// Relative error allowed per entry, plus this fraction of the group's largest magnitude
/// (f32 device arithmetic and atomic summation order against the f64 reference).
const RELATIVE_TOLERANCE: f32 = 2e-3;
const GROUP_TOLERANCE: f32 = 2e-4;

fn random_image_gradients(camera: &Camera, seed: u64) -> ImageGradients {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pixels = camera.pixel_count();
    ImageGradients {
        v_rgb: (0..pixels)
            .map(|_| {
                [
                    rng.random_range(-1.0f32..1.0),
                    rng.random_range(-1.0f32..1.0),
                    rng.random_range(-1.0f32..1.0),
                ]
            })
            .collect(),
        v_depth: (0..pixels)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect(),
        v_alpha: (0..pixels)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect(),
    }
}

fn compare(name: &str, actual: &[f32], expected: &[f32]) {
    assert_eq!(actual.len(), expected.len(), "{name}: length");
    let scale = expected.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(
        scale > 1e-3,
        "{name}: reference gradients vanish; the comparison would be vacuous"
    );
    let mut worst = 0.0f32;
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        let tolerance = RELATIVE_TOLERANCE * e.abs() + GROUP_TOLERANCE * scale;
        assert!(
            (a - e).abs() <= tolerance,
            "{name}[{i}]: gpu {a} vs reference {e} (scale {scale})"
        );
        worst = worst.max((a - e).abs() / scale);
    }
    eprintln!("{name}: worst error {worst:.1e} of scale {scale:.2e}");
}

fn flatten<const N: usize>(values: &[[f32; N]]) -> Vec<f32> {
    values.iter().flatten().copied().collect()
}

fn check_backward(renderer: &GpuRenderer, cloud: &GaussianCloud, camera: &Camera, seed: u64) {
    let context = &gpu().context;
    let image_gradients = random_image_gradients(camera, seed);
    let expected =
        reference::render_backward(cloud, camera, &RasterConfig::default(), &image_gradients);
    let gaussians = DeviceGaussians::upload(context, cloud).unwrap();
    let frame = renderer
        .render_frame(context, &gaussians, camera, &RasterConfig::default())
        .unwrap();
    let device_image_gradients =
        DeviceImageGradients::upload(context, camera, &image_gradients).unwrap();
    let actual: GaussianGradients = renderer
        .backward(context, &gaussians, &frame, &device_image_gradients)
        .unwrap()
        .download(context)
        .unwrap();
    compare(
        "v_means",
        &flatten(&actual.v_means),
        &flatten(&expected.v_means),
    );
    compare(
        "v_log_scales",
        &flatten(&actual.v_log_scales),
        &flatten(&expected.v_log_scales),
    );
    compare(
        "v_quaternions",
        &flatten(&actual.v_quaternions),
        &flatten(&expected.v_quaternions),
    );
    compare(
        "v_opacity_logits",
        &actual.v_opacity_logits,
        &expected.v_opacity_logits,
    );
    compare(
        "v_colours",
        &flatten(&actual.v_colours),
        &flatten(&expected.v_colours),
    );
    compare(
        "v_pose",
        &actual.v_pose.as_array(),
        &expected.v_pose.as_array(),
    );
}

#[test]
fn backward_matches_reference_with_default_atomics() {
    let camera = default_camera();
    let cloud = random_scene(&camera, 40, 21, (-3.0, -1.8), (-1.0, 2.0));
    check_backward(&gpu().renderer, &cloud, &camera, 1);
}

#[test]
fn backward_matches_reference_with_compare_exchange_atomics() {
    let gpu = gpu();
    let renderer = GpuRenderer::with_atomics(&gpu.context, GradientAtomics::CompareExchange);
    assert!(!renderer.uses_float_atomics);
    let camera = default_camera();
    let cloud = random_scene(&camera, 40, 22, (-3.0, -1.8), (-1.0, 2.0));
    check_backward(&renderer, &cloud, &camera, 2);
}

#[test]
fn backward_matches_reference_on_dense_opaque_scene() {
    // Clamped alphas, early termination and several batches per tile.
    let camera = default_camera();
    let cloud = random_scene(&camera, 400, 23, (-2.6, -1.8), (1.0, 6.0));
    check_backward(&gpu().renderer, &cloud, &camera, 3);
}

#[test]
fn backward_without_subgroups_matches_reference() {
    // The workgroup-memory kernels (adapters without subgroups), with both atomics.
    let gpu = gpu();
    let camera = default_camera();
    for atomics in [GradientAtomics::Auto, GradientAtomics::CompareExchange] {
        let renderer = GpuRenderer::with_options(
            &gpu.context,
            RendererOptions {
                atomics,
                subgroups: Subgroups::Never,
                ..RendererOptions::default()
            },
        );
        assert!(!renderer.uses_subgroups);
        let cloud = random_scene(&camera, 400, 25, (-2.6, -1.8), (1.0, 6.0));
        check_backward(&renderer, &cloud, &camera, 6);
        let cloud = random_scene(&camera, 40, 26, (-3.0, -1.8), (-1.0, 2.0));
        check_backward(&renderer, &cloud, &camera, 7);
    }
}

#[test]
fn backward_in_arrival_order_matches_reference() {
    // GradientOrder::Arrival: atomics straight into the per-Gaussian sums, both kernel sets.
    let gpu = gpu();
    let camera = default_camera();
    for subgroups in [Subgroups::Auto, Subgroups::Never] {
        let renderer = GpuRenderer::with_options(
            &gpu.context,
            RendererOptions {
                subgroups,
                gradient_order: GradientOrder::Arrival,
                ..RendererOptions::default()
            },
        );
        let cloud = random_scene(&camera, 400, 28, (-2.6, -1.8), (1.0, 6.0));
        check_backward(&renderer, &cloud, &camera, 9);
    }
}

#[test]
fn a_frame_too_large_for_the_fixed_order_falls_back_to_arrival_order_and_says_so() {
    let gpu = gpu();
    let camera = default_camera();
    let cloud = random_scene(&camera, 400, 28, (-2.6, -1.8), (1.0, 6.0));
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    let renderer = GpuRenderer::new(&gpu.context);
    let render = |renderer: &GpuRenderer| {
        renderer
            .render_frame(&gpu.context, &gaussians, &camera, &RasterConfig::default())
            .unwrap()
    };
    let fitting = render(&renderer);
    assert_eq!(fitting.gradient_order(), GradientOrder::Fixed);
    assert!(!fitting.gradient_order_fell_back());
    // Room for just more pairs than one binding holds the fixed order's sums of.
    let binding = gpu.context.max_storage_binding_bytes();
    let bytes_per_pair = fitting.fixed_order_bytes() / u64::from(fitting.pair_capacity);
    renderer.reserve_pairs(binding / bytes_per_pair + 1);
    let too_large = render(&renderer);
    assert!(too_large.fixed_order_bytes() > binding);
    assert_eq!(too_large.gradient_order(), GradientOrder::Arrival);
    assert!(too_large.gradient_order_fell_back());
    // Its backward pass still gives the reference's gradients.
    check_backward(&renderer, &cloud, &camera, 9);
    // A renderer set to the arrival order did not fall back from anything.
    let arrival = GpuRenderer::with_options(
        &gpu.context,
        RendererOptions {
            gradient_order: GradientOrder::Arrival,
            ..RendererOptions::default()
        },
    );
    let frame = render(&arrival);
    assert_eq!(frame.gradient_order(), GradientOrder::Arrival);
    assert!(!frame.gradient_order_fell_back());
}

/// Every gradient of a backward pass, as bits.
fn gradient_bits(gradients: &GaussianGradients) -> Vec<u32> {
    flatten(&gradients.v_means)
        .into_iter()
        .chain(flatten(&gradients.v_log_scales))
        .chain(flatten(&gradients.v_quaternions))
        .chain(gradients.v_opacity_logits.iter().copied())
        .chain(flatten(&gradients.v_colours))
        .chain(gradients.v_pose.as_array())
        .map(f32::to_bits)
        .collect()
}

#[test]
fn fixed_order_backward_repeats_bit_for_bit() {
    // Large translucent splats over many tiles: every Gaussian's gradient sums pairs from tiles
    // that different device threads process, in whatever order they finish. The fixed order
    // must give the same bits every time, with both kernel sets.
    let gpu = gpu();
    let context = &gpu.context;
    let camera = default_camera();
    let cloud = random_scene(&camera, 800, 29, (-1.6, -0.8), (-3.0, -1.0));
    let image_gradients = random_image_gradients(&camera, 10);
    let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let device_image_gradients =
        DeviceImageGradients::upload(context, &camera, &image_gradients).unwrap();
    for subgroups in [Subgroups::Auto, Subgroups::Never] {
        let renderer = GpuRenderer::with_options(
            context,
            RendererOptions {
                subgroups,
                ..RendererOptions::default()
            },
        );
        assert_eq!(renderer.gradient_order, GradientOrder::Fixed);
        let run = || {
            let frame = renderer
                .render_frame(context, &gaussians, &camera, &RasterConfig::default())
                .unwrap();
            let gradients = renderer
                .backward(context, &gaussians, &frame, &device_image_gradients)
                .unwrap()
                .download(context)
                .unwrap();
            gradient_bits(&gradients)
        };
        let first = run();
        assert!(first.iter().any(|&bits| f32::from_bits(bits) != 0.0));
        for repeat in 1..6 {
            assert!(
                run() == first,
                "{subgroups:?}: repeat {repeat} differs from the first backward pass"
            );
        }
    }
}

#[test]
fn fixed_order_sums_start_from_zero_after_a_frame_that_overflowed_its_pairs() {
    // The per-pair sums are kept between backward passes and must be all zeros between them.
    // A frame that overflowed its pair capacity keeps only its first pairs in depth order; its
    // backward pass must still leave nothing behind for the next one.
    let gpu = gpu();
    let context = &gpu.context;
    let (camera, cloud) = pair_overflow_scene();
    let image_gradients = random_image_gradients(&camera, 12);
    let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let device_image_gradients =
        DeviceImageGradients::upload(context, &camera, &image_gradients).unwrap();
    let config = RasterConfig::default();
    // Many small splats first: 8 pairs reserved for each of them make the kept sums large
    // enough for every frame below, so no frame gets a fresh (zero-filled) buffer.
    let small = random_scene(&camera, 4000, 13, (-4.0, -3.5), (-1.0, 1.0));
    let small_gaussians = DeviceGaussians::upload(context, &small).unwrap();
    let backward_bits = |renderer: &GpuRenderer, run_backward_on_the_overflow: bool| {
        let frame = renderer
            .render_frame(context, &small_gaussians, &camera, &config)
            .unwrap();
        assert!(frame.pair_capacity >= 4000 * 8);
        renderer
            .backward(context, &small_gaussians, &frame, &device_image_gradients)
            .unwrap();
        let overflowed = renderer
            .render_frame(context, &gaussians, &camera, &config)
            .unwrap();
        assert!(
            renderer
                .check_pairs(context, &overflowed)
                .unwrap()
                .overflowed()
        );
        if run_backward_on_the_overflow {
            let truncated = renderer
                .backward(context, &gaussians, &overflowed, &device_image_gradients)
                .unwrap()
                .download(context)
                .unwrap();
            assert!(
                gradient_bits(&truncated)
                    .iter()
                    .all(|&bits| f32::from_bits(bits).is_finite())
            );
        }
        let fitting = renderer
            .render_frame(context, &gaussians, &camera, &config)
            .unwrap();
        assert!(
            !renderer
                .check_pairs(context, &fitting)
                .unwrap()
                .overflowed()
        );
        assert!(
            fitting.pair_capacity <= 4000 * 8,
            "the kept sums would be regrown"
        );
        renderer
            .backward(context, &gaussians, &fitting, &device_image_gradients)
            .unwrap()
            .download(context)
            .unwrap()
    };
    let after_overflow = backward_bits(&GpuRenderer::new(context), true);
    let fresh = backward_bits(&GpuRenderer::new(context), false);
    assert!(
        gradient_bits(&after_overflow) == gradient_bits(&fresh),
        "the overflowed frame's backward pass left per-pair sums behind"
    );
    let expected = reference::render_backward(&cloud, &camera, &config, &image_gradients);
    compare(
        "v_means",
        &flatten(&after_overflow.v_means),
        &flatten(&expected.v_means),
    );
    compare(
        "v_colours",
        &flatten(&after_overflow.v_colours),
        &flatten(&expected.v_colours),
    );
}

#[test]
fn backward_matches_reference_on_long_translucent_lists() {
    // Hundreds of entries per tile that all contribute: many subgroup steps or batches.
    let camera = default_camera();
    let cloud = random_scene(&camera, 800, 27, (-2.8, -2.0), (-3.0, -1.0));
    check_backward(&gpu().renderer, &cloud, &camera, 8);
}

#[test]
fn backward_of_empty_scene_is_empty() {
    let gpu = gpu();
    let camera = default_camera();
    let gaussians = DeviceGaussians::upload(&gpu.context, &GaussianCloud::default()).unwrap();
    let frame = gpu
        .renderer
        .render_frame(&gpu.context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let image_gradients =
        DeviceImageGradients::upload(&gpu.context, &camera, &random_image_gradients(&camera, 4))
            .unwrap();
    let gradients = gpu
        .renderer
        .backward(&gpu.context, &gaussians, &frame, &image_gradients)
        .unwrap();
    let host = gradients.download(&gpu.context).unwrap();
    assert!(host.v_means.is_empty());
    assert_eq!(host.v_pose.as_array(), [0.0; 6]);
}

#[test]
fn culled_gaussians_get_zero_gradients_and_all_gradients_stay_finite() {
    let gpu = gpu();
    let camera = default_camera();
    let mut cloud = random_scene(&camera, 30, 24, (-3.0, -1.8), (-1.0, 2.0));
    let behind = camera.world_from_camera().transform_point([0.0, 0.0, -2.0]);
    let first_hostile = cloud.len();
    cloud.push(behind, [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 1.0, [0.5; 3]);
    cloud.push(
        cloud.means[0],
        [f32::NAN; 3],
        [1.0, 0.0, 0.0, 0.0],
        1.0,
        [0.5; 3],
    );
    cloud.push(cloud.means[1], [-2.0; 3], [0.0; 4], 1.0, [0.5; 3]);
    cloud.push(
        cloud.means[2],
        [-2.0; 3],
        [1.0, 0.0, 0.0, 0.0],
        f32::INFINITY,
        [0.5; 3],
    );
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    let frame = gpu
        .renderer
        .render_frame(&gpu.context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let image_gradients =
        DeviceImageGradients::upload(&gpu.context, &camera, &random_image_gradients(&camera, 5))
            .unwrap();
    let host = gpu
        .renderer
        .backward(&gpu.context, &gaussians, &frame, &image_gradients)
        .unwrap()
        .download(&gpu.context)
        .unwrap();
    for i in first_hostile..cloud.len() {
        assert_eq!(host.v_means[i], [0.0; 3], "culled Gaussian {i}");
        assert_eq!(host.v_opacity_logits[i], 0.0, "culled Gaussian {i}");
        assert_eq!(host.v_quaternions[i], [0.0; 4], "culled Gaussian {i}");
    }
    let all_finite = host.v_means.iter().flatten().all(|v| v.is_finite())
        && host.v_log_scales.iter().flatten().all(|v| v.is_finite())
        && host.v_quaternions.iter().flatten().all(|v| v.is_finite())
        && host.v_colours.iter().flatten().all(|v| v.is_finite())
        && host.v_opacity_logits.iter().all(|v| v.is_finite())
        && host.v_pose.as_array().iter().all(|v| v.is_finite());
    assert!(all_finite, "non-finite gradients: {host:?}");
    assert!(
        host.v_means[..first_hostile]
            .iter()
            .flatten()
            .any(|&v| v != 0.0)
    );
}

/// The backward rasterizer's walk cut short by lavapipe's loop limit is flagged
/// (PairUsage::rasterize_backward_cut_short) once the backward pass has run. The flag must
/// agree with the gradients: the walk (back to front) cut short never reaches the red splat
/// at the front, which then gets no gradient.
#[test]
fn a_backward_walk_cut_short_by_the_loop_limit_is_reported() {
    let gpu = gpu();
    let context = &gpu.context;
    for renderer in [
        &GpuRenderer::new(context),
        &renderer_without_subgroups(context),
    ] {
        // With subgroups the top band's backward walk takes about 4 of Mesa 22's lavapipe loop
        // trips per entry (measured with this scene: 15 000 faint splats stay within the limit,
        // 16 000 do not), the forward walk about 1.1 (55 000 within, 60 000 not). So 30 000
        // outgrow the limit in the backward walk only. Without subgroups both walks take about
        // one trip per entry, and the backward walk never outgrows it before the forward one.
        for (boundary_splats, outgrows_lavapipe) in
            [(8_000, false), (30_000, renderer.uses_subgroups)]
        {
            let (camera, cloud) = loop_limit_scene(boundary_splats);
            let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
            let (frame, usage) = render_checked(renderer, &gaussians, &camera);
            assert!(!usage.rasterizers_cut_short(), "{usage:?}");
            let pixels = camera.pixel_count();
            let image_gradients = ImageGradients {
                v_rgb: vec![[1.0; 3]; pixels],
                ..ImageGradients::default()
            };
            let device_image_gradients =
                DeviceImageGradients::upload(context, &camera, &image_gradients).unwrap();
            let gradients = renderer
                .backward(context, &gaussians, &frame, &device_image_gradients)
                .unwrap()
                .download(context)
                .unwrap();
            let usage = renderer.check_pairs(context, &frame).unwrap();
            // The red splat is the cloud's first, the green one its last.
            let red = gradients.v_colours[0];
            let green = gradients.v_colours[cloud.len() - 1];
            let case = format!(
                "{boundary_splats} faint splats, subgroups {}: {usage:?}, red {red:?}, green \
                 {green:?}",
                renderer.uses_subgroups
            );
            eprintln!("{case}");
            assert!(!usage.rasterize_cut_short, "{case}");
            assert!(green[1] > 0.0, "{case}");
            assert_eq!(usage.rasterize_backward_cut_short, red[0] == 0.0, "{case}");
            if has_lavapipe_loop_limit(context) {
                assert_eq!(
                    usage.rasterize_backward_cut_short, outgrows_lavapipe,
                    "{case}"
                );
            }
        }
    }
}
