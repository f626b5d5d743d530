//! The wgpu forward path against the CPU reference, plus determinism and robustness.

mod common;

use common::{
    HEIGHT, WIDTH, camera, default_camera, gpu, has_lavapipe_loop_limit, loop_limit_scene,
    pair_overflow_scene, random_scene, read_buffer, render_checked, renderer_without_subgroups,
};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use render_core::gpu::{DeviceGaussians, GpuRenderer};
use render_core::reference;
use render_core::{Camera, RasterConfig, RenderMode, RenderOutput, constants};
use splats::GaussianCloud;

/// f32 GPU arithmetic against the f64 reference: colours and alpha are in [0, 1].
const COLOUR_TOLERANCE: f32 = 1e-5;
/// Depth is alpha-weighted metres (scenes sit at 1-4 m).
const DEPTH_TOLERANCE: f32 = 1e-4;

fn render_gpu(cloud: &GaussianCloud, camera: &Camera) -> RenderOutput {
    render_with(&gpu().renderer, cloud, camera)
}

fn render_with(renderer: &GpuRenderer, cloud: &GaussianCloud, camera: &Camera) -> RenderOutput {
    let context = &gpu().context;
    let gaussians = DeviceGaussians::upload(context, cloud).unwrap();
    renderer
        .render(context, &gaussians, camera, RenderMode::RgbD)
        .unwrap()
}

fn output_bits(o: &RenderOutput) -> Vec<u32> {
    let mut bits: Vec<u32> = o
        .rgb
        .as_ref()
        .unwrap()
        .iter()
        .flatten()
        .map(|v| v.to_bits())
        .collect();
    bits.extend(o.depth.as_ref().unwrap().iter().map(|v| v.to_bits()));
    bits.extend(o.alpha.iter().map(|v| v.to_bits()));
    bits
}

fn max_abs_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn assert_matches_reference(name: &str, cloud: &GaussianCloud, camera: &Camera) {
    assert_renderer_matches_reference(&gpu().renderer, name, cloud, camera);
}

fn assert_renderer_matches_reference(
    renderer: &GpuRenderer,
    name: &str,
    cloud: &GaussianCloud,
    camera: &Camera,
) {
    let expected = reference::render(cloud, camera, RenderMode::RgbD, &RasterConfig::default());
    let actual = render_with(renderer, cloud, camera);
    let flat = |rgb: &Option<Vec<[f32; 3]>>| {
        rgb.as_ref()
            .unwrap()
            .iter()
            .flatten()
            .copied()
            .collect::<Vec<f32>>()
    };
    let rgb_error = max_abs_difference(&flat(&actual.rgb), &flat(&expected.rgb));
    let depth_error = max_abs_difference(
        actual.depth.as_ref().unwrap(),
        expected.depth.as_ref().unwrap(),
    );
    let alpha_error = max_abs_difference(&actual.alpha, &expected.alpha);
    let covered = expected.alpha.iter().filter(|&&a| a > 0.5).count();
    eprintln!(
        "{name}: max |rgb| {rgb_error:.2e}, |depth| {depth_error:.2e}, |alpha| {alpha_error:.2e}, {covered} covered pixels"
    );
    assert!(
        covered > 0,
        "{name}: scene renders nothing, the comparison would be vacuous"
    );
    assert!(
        rgb_error <= COLOUR_TOLERANCE,
        "{name}: rgb differs by {rgb_error}"
    );
    assert!(
        alpha_error <= COLOUR_TOLERANCE,
        "{name}: alpha differs by {alpha_error}"
    );
    assert!(
        depth_error <= DEPTH_TOLERANCE,
        "{name}: depth differs by {depth_error}"
    );
}

#[test]
fn matches_reference_on_a_sparse_scene() {
    let camera = default_camera();
    let cloud = random_scene(&camera, 40, 1, (-3.5, -2.0), (-1.0, 2.0));
    assert_matches_reference("sparse", &cloud, &camera);
}

#[test]
fn matches_reference_with_large_splats_across_tiles() {
    let camera = default_camera();
    let cloud = random_scene(&camera, 12, 2, (-1.8, -0.8), (-2.0, 1.0));
    assert_matches_reference("large splats", &cloud, &camera);
}

#[test]
fn matches_reference_with_dense_opaque_layers_and_early_termination() {
    // Hundreds of nearly opaque splats: exercises the 0.99 cap, early termination, and more
    // than one 256-splat batch per tile.
    let camera = default_camera();
    let cloud = random_scene(&camera, 700, 3, (-2.6, -1.8), (3.0, 6.0));
    assert_matches_reference("dense opaque", &cloud, &camera);
}

#[test]
fn tile_masks_bin_fewer_pairs_than_the_rectangles_and_change_no_pixel() {
    // Thin tilted splats spanning several tiles: their visible ellipses miss many tiles of
    // their bounding rectangles, which project.wgsl leaves out of the binning.
    let camera = camera(128, 96, 63.5, 47.5);
    let mut cloud = random_scene(&camera, 150, 12, (-2.4, -1.6), (-1.0, 3.0));
    for log_scale in &mut cloud.log_scales {
        log_scale[1] = log_scale[0] - 2.5;
    }
    assert_matches_reference("thin tilted", &cloud, &camera);
    let rectangle_pairs: u32 = reference::project_and_sort(&cloud, &camera)
        .iter()
        .map(|splat| {
            let [x0, y0, x1, y1] = splat.tile_rect;
            (x1 - x0 + 1) * (y1 - y0 + 1)
        })
        .sum();
    let gpu = gpu();
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    let frame = gpu
        .renderer
        .render_frame(&gpu.context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let usage = gpu.renderer.check_pairs(&gpu.context, &frame).unwrap();
    eprintln!(
        "{} pairs binned, {rectangle_pairs} in the 3-sigma rectangles",
        usage.pairs
    );
    assert!(
        usage.pairs * 10 < rectangle_pairs * 9,
        "{} pairs binned of {rectangle_pairs}",
        usage.pairs
    );
}

#[test]
fn matches_reference_with_off_centre_principal_point_and_odd_size() {
    let camera = camera(37, 29, 9.0, 21.5);
    let cloud = random_scene(&camera, 30, 4, (-3.2, -2.0), (-0.5, 2.0));
    assert_matches_reference("off-centre", &cloud, &camera);
}

#[test]
fn renders_are_bit_identical() {
    let camera = default_camera();
    let cloud = random_scene(&camera, 300, 5, (-3.0, -1.5), (-1.0, 3.0));
    let first = render_gpu(&cloud, &camera);
    let second = render_gpu(&cloud, &camera);
    assert_eq!(output_bits(&first), output_bits(&second));
}

#[test]
fn workgroup_memory_rasterizer_matches_reference_and_the_subgroup_one_bit_for_bit() {
    // The kernels without subgroup operations (adapters without them); on an adapter without
    // subgroups both renderers run them and the comparison is trivially equal.
    let gpu = gpu();
    let without = renderer_without_subgroups(&gpu.context);
    assert!(!without.uses_subgroups);
    let default = default_camera();
    let odd = camera(37, 29, 9.0, 21.5);
    let scenes = [
        (
            "dense opaque",
            random_scene(&default, 700, 3, (-2.6, -1.8), (3.0, 6.0)),
            default,
        ),
        (
            "large splats",
            random_scene(&default, 12, 2, (-1.8, -0.8), (-2.0, 1.0)),
            default,
        ),
        // Long lists: many batches per tile.
        (
            "many",
            random_scene(&odd, 1500, 6, (-3.0, -2.0), (-1.0, 1.0)),
            odd,
        ),
    ];
    for (name, cloud, camera) in &scenes {
        assert_renderer_matches_reference(&without, name, cloud, camera);
        assert_eq!(
            output_bits(&render_with(&without, cloud, camera)),
            output_bits(&render_gpu(cloud, camera)),
            "{name}: the two rasterizers differ"
        );
    }
}

#[test]
fn empty_scene_renders_black_and_transparent() {
    let camera = default_camera();
    let out = render_gpu(&GaussianCloud::default(), &camera);
    assert_eq!(out.alpha.len(), (WIDTH * HEIGHT) as usize);
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    assert!(out.depth.unwrap().iter().all(|&d| d == 0.0));
    assert!(out.rgb.unwrap().iter().flatten().all(|&c| c == 0.0));
}

#[test]
fn render_modes_select_outputs() {
    let gpu = gpu();
    let camera = default_camera();
    let cloud = random_scene(&camera, 10, 6, (-3.0, -2.0), (0.0, 2.0));
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    let rgb_only = gpu
        .renderer
        .render(&gpu.context, &gaussians, &camera, RenderMode::Rgb)
        .unwrap();
    assert!(rgb_only.rgb.is_some() && rgb_only.depth.is_none());
    let depth_only = gpu
        .renderer
        .render(&gpu.context, &gaussians, &camera, RenderMode::Depth)
        .unwrap();
    assert!(depth_only.rgb.is_none() && depth_only.depth.is_some());
    assert_eq!(rgb_only.alpha, depth_only.alpha);
}

/// Gaussians that must all be culled or rendered harmlessly.
fn hostile_gaussians(camera: &Camera) -> GaussianCloud {
    let world_from_camera = camera.world_from_camera();
    let in_front = world_from_camera.transform_point([0.0, 0.0, 2.0]);
    let camera_centre = world_from_camera.transform_point([0.0, 0.0, 0.0]);
    let behind = world_from_camera.transform_point([0.0, 0.0, -2.0]);
    let grazing = world_from_camera.transform_point([1e-3, 0.0, 1e-7]);
    let special = [
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::MIN_POSITIVE / 8.0,
        f32::MAX,
        -f32::MAX,
    ];
    let mut cloud = GaussianCloud::default();
    let unit = [1.0, 0.0, 0.0, 0.0];
    for &value in &special {
        cloud.push(
            [value, in_front[1], in_front[2]],
            [-2.0; 3],
            unit,
            1.0,
            [0.5; 3],
        );
        cloud.push(in_front, [value, -2.0, -2.0], unit, 1.0, [0.5; 3]);
        cloud.push(in_front, [-2.0; 3], [value, 0.0, 0.0, 0.0], 1.0, [0.5; 3]);
        cloud.push(in_front, [-2.0; 3], unit, value, [0.5; 3]);
        cloud.push(in_front, [-2.0; 3], unit, 1.0, [value, 0.2, 0.2]);
    }
    cloud.push(in_front, [-2.0; 3], [0.0; 4], 1.0, [0.5; 3]);
    cloud.push(in_front, [-2.0; 3], [1e-30, 0.0, 0.0, 0.0], 1.0, [0.5; 3]);
    cloud.push(camera_centre, [-2.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(behind, [-2.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(grazing, [-2.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(in_front, [9.9; 3], unit, 1.0, [0.5; 3]);
    cloud.push(in_front, [30.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(in_front, [-80.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(in_front, [-2.0, 8.0, -30.0], unit, 1.0, [0.5; 3]);
    cloud.push(in_front, [-2.0; 3], unit, 1e4, [0.5; 3]);
    cloud.push(in_front, [-2.0; 3], unit, -1e4, [0.5; 3]);
    cloud.push([1e30, 1e30, 1e30], [-2.0; 3], unit, 1.0, [0.5; 3]);
    cloud.push(beside_the_camera(camera), [-2.7; 3], unit, 1.0, [0.5; 3]);
    cloud
}

/// A point next to the camera, far outside the field of view (x/z = -12): a mapped wall
/// Gaussian an agent walks past. Linearised, its splat would cover the whole image.
fn beside_the_camera(camera: &Camera) -> [f32; 3] {
    camera
        .world_from_camera()
        .transform_point([-2.46, 0.7, 0.2])
}

#[test]
fn gaussians_beside_the_camera_are_culled_not_smeared_over_the_image() {
    let camera = default_camera();
    let mut cloud = GaussianCloud::default();
    cloud.push(
        beside_the_camera(&camera),
        [-2.7; 3],
        [1.0, 0.0, 0.0, 0.0],
        2.0,
        [0.9, 0.1, 0.1],
    );
    assert!(reference::project_gaussian(&cloud, 0, &camera).is_none());
    let output = render_gpu(&cloud, &camera);
    assert!(output.alpha.iter().all(|&a| a == 0.0));
}

fn assert_finite(output: &RenderOutput) {
    assert!(
        output
            .rgb
            .as_ref()
            .unwrap()
            .iter()
            .flatten()
            .all(|v| v.is_finite())
    );
    assert!(output.depth.as_ref().unwrap().iter().all(|v| v.is_finite()));
    assert!(
        output
            .alpha
            .iter()
            .all(|v| v.is_finite() && (0.0..=1.0).contains(v))
    );
}

#[test]
fn hostile_values_give_finite_output() {
    let camera = default_camera();
    let out = render_gpu(&hostile_gaussians(&camera), &camera);
    assert_finite(&out);
    // The reference agrees that these render (almost) nothing harmful: same finiteness.
    let expected = reference::render(
        &hostile_gaussians(&camera),
        &camera,
        RenderMode::RgbD,
        &RasterConfig::default(),
    );
    assert!(expected.alpha.iter().all(|v| v.is_finite()));
}

#[test]
fn random_fuzz_gives_finite_output() {
    let camera = default_camera();
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    let specials = [
        f32::NAN,
        f32::INFINITY,
        -f32::INFINITY,
        0.0,
        -0.0,
        1e-40,
        1e30,
        -1e30,
        1e-3,
    ];
    for round in 0..3 {
        let mut cloud = random_scene(&camera, 60, 100 + round, (-4.0, 1.0), (-5.0, 8.0));
        for _ in 0..40 {
            let i = rng.random_range(0..cloud.len());
            let value = specials[rng.random_range(0..specials.len())];
            match rng.random_range(0..5) {
                0 => cloud.means[i][rng.random_range(0..3)] = value,
                1 => cloud.log_scales[i][rng.random_range(0..3)] = value,
                2 => cloud.quaternions[i][rng.random_range(0..4)] = value,
                3 => cloud.opacity_logits[i] = value,
                _ => cloud.colours[i][rng.random_range(0..3)] = value,
            }
        }
        assert_finite(&render_gpu(&cloud, &camera));
    }
}

#[test]
fn culled_gaussians_change_nothing() {
    let camera = default_camera();
    let cloud = random_scene(&camera, 50, 7, (-3.0, -1.8), (-1.0, 2.0));
    let baseline = render_gpu(&cloud, &camera);
    let mut polluted = GaussianCloud::default();
    let hostile = hostile_gaussians(&camera);
    // Interleave culled Gaussians with the valid ones, keeping the valid ones' relative order.
    let culled_indices: Vec<usize> = (0..hostile.len())
        .filter(|&i| reference::project_gaussian(&hostile, i, &camera).is_none())
        .collect();
    assert!(
        culled_indices.len() > 20,
        "only {} hostile Gaussians are culled",
        culled_indices.len()
    );
    for i in 0..cloud.len() {
        let h = culled_indices[i % culled_indices.len()];
        polluted.push(
            hostile.means[h],
            hostile.log_scales[h],
            hostile.quaternions[h],
            hostile.opacity_logits[h],
            hostile.colours[h],
        );
        polluted.push(
            cloud.means[i],
            cloud.log_scales[i],
            cloud.quaternions[i],
            cloud.opacity_logits[i],
            cloud.colours[i],
        );
    }
    let with_culled = render_gpu(&polluted, &camera);
    assert_eq!(baseline, with_culled);
}

#[test]
fn device_radix_sort_is_stable_and_correct() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    // Many sort blocks (the last one partial) and many duplicate keys.
    let count = 70_000;
    let keys: Vec<u32> = (0..count)
        .map(|_| rng.random_range(0..5000u32) * 0x1_0001)
        .collect();
    let values: Vec<u32> = (0..count as u32).collect();
    let (sorted_keys, sorted_values) = gpu
        .renderer
        .sort_pairs(&gpu.context, &keys, &values, 32)
        .unwrap();
    let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    expected.sort_by_key(|&(k, _)| k); // std's sort_by_key is stable
    let (expected_keys, expected_values): (Vec<u32>, Vec<u32>) = expected.into_iter().unzip();
    assert_eq!(sorted_keys, expected_keys);
    assert_eq!(sorted_values, expected_values);
    let (low_keys, _) = gpu
        .renderer
        .sort_pairs(&gpu.context, &[7, 0x10, 3], &[0, 1, 2], 4)
        .unwrap();
    assert_eq!(low_keys, vec![0x10, 3, 7], "sorting on the low 4 bits only");
}

#[test]
fn device_radix_sort_matches_a_stable_sort_for_every_size_and_key_width() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    // Sizes around the 1024-key block boundary; 11 bits is a 640x480 tile id.
    for count in [1usize, 2, 1023, 1024, 1025, 4097] {
        for key_bits in [11u32, 32] {
            let keys: Vec<u32> = (0..count).map(|_| rng.random::<u32>()).collect();
            let values: Vec<u32> = (0..count as u32).collect();
            let (sorted_keys, sorted_values) = gpu
                .renderer
                .sort_pairs(&gpu.context, &keys, &values, key_bits)
                .unwrap();
            let mask = if key_bits == 32 {
                u32::MAX
            } else {
                (1 << key_bits) - 1
            };
            let mut expected: Vec<(u32, u32)> =
                keys.iter().copied().zip(values.iter().copied()).collect();
            expected.sort_by_key(|&(k, _)| k & mask);
            let (expected_keys, expected_values): (Vec<u32>, Vec<u32>) =
                expected.into_iter().unzip();
            assert_eq!(sorted_keys, expected_keys, "{count} keys, {key_bits} bits");
            assert_eq!(
                sorted_values, expected_values,
                "{count} keys, {key_bits} bits"
            );
        }
    }
}

#[test]
fn the_depth_sort_matches_a_stable_sort_of_keys_and_indices() {
    let gpu = gpu();
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let key_bits = constants::DEPTH_KEY_BITS;
    let culled_as_sorted = (1u32 << key_bits) - 1;
    // Sizes around the 1024-key block boundary; no culled key, some, most, all.
    for count in [1usize, 1023, 1025, 4097, 70_000] {
        for culled_share in [0.0, 0.3, 0.85, 1.0] {
            // Few distinct visible keys, k * 0x1_0101 with all three digits k (ties test stability),
            // and the largest visible key.
            let keys: Vec<u32> = (0..count)
                .map(|_| {
                    if rng.random::<f64>() < culled_share {
                        constants::CULLED_DEPTH_KEY
                    } else if rng.random::<f64>() < 0.1 {
                        constants::LARGEST_VISIBLE_DEPTH_KEY
                    } else {
                        rng.random_range(0..255u32) * 0x1_0101
                    }
                })
                .collect();
            let values: Vec<u32> = (0..count as u32).collect();
            let (sorted_keys, sorted_values) =
                gpu.renderer.sort_depth_keys(&gpu.context, &keys).unwrap();
            let mut expected: Vec<(u32, u32)> =
                keys.iter().copied().zip(values.iter().copied()).collect();
            expected.sort_by_key(|&(k, _)| k & culled_as_sorted);
            let (expected_keys, expected_values): (Vec<u32>, Vec<u32>) =
                expected.into_iter().unzip();
            assert_eq!(
                sorted_keys, expected_keys,
                "{count} keys, {culled_share} culled"
            );
            assert_eq!(
                sorted_values, expected_values,
                "{count} keys, {culled_share} culled"
            );
        }
    }
}

#[test]
fn gaussians_round_trip_through_the_device() {
    let gpu = gpu();
    let camera = default_camera();
    let cloud = random_scene(&camera, 17, 9, (-3.0, -2.0), (0.0, 1.0));
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    assert_eq!(gaussians.download(&gpu.context).unwrap(), cloud);
}

#[test]
fn pair_overflow_is_reported_and_the_next_frame_fits() {
    let gpu = gpu();
    let context = &gpu.context;
    let (camera, cloud) = pair_overflow_scene();
    let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    // A fresh renderer: the shared one may already have grown its pair capacity.
    let renderer = GpuRenderer::new(context);
    let config = RasterConfig::default();

    let first = renderer
        .render_frame(context, &gaussians, &camera, &config)
        .unwrap();
    let first_usage = renderer.check_pairs(context, &first).unwrap();
    assert!(
        first_usage.overflowed(),
        "{first_usage:?}: the scene must need more pairs than a fresh renderer reserves"
    );
    let truncated = renderer
        .read_output(context, &first, RenderMode::RgbD)
        .unwrap();
    assert!(truncated.alpha.iter().all(|a| a.is_finite()));

    let second = renderer
        .render_frame(context, &gaussians, &camera, &config)
        .unwrap();
    let second_usage = renderer.check_pairs(context, &second).unwrap();
    assert!(!second_usage.overflowed(), "{second_usage:?}");
    assert_eq!(second_usage.pairs, first_usage.pairs);
    let full = renderer
        .read_output(context, &second, RenderMode::RgbD)
        .unwrap();
    // Against the f64 reference: many translucent splats make a splat whose alpha sits right
    // at the 1/255 cut-off likely, where f32 and f64 may decide differently; one such splat
    // changes alpha by less than the cut-off itself.
    let expected = reference::render(&cloud, &camera, RenderMode::RgbD, &config);
    let alpha_error = max_abs_difference(&full.alpha, &expected.alpha);
    assert!(
        alpha_error <= render_core::constants::MIN_SPLAT_ALPHA,
        "alpha differs by {alpha_error}"
    );
    assert_ne!(
        truncated.alpha, full.alpha,
        "the overflowing frame dropped its farthest pairs"
    );

    // The one-off `render` checks and re-renders by itself.
    let fresh = GpuRenderer::new(context);
    let output = fresh
        .render(context, &gaussians, &camera, RenderMode::RgbD)
        .unwrap();
    assert_eq!(output.alpha, full.alpha);
}

/// Every pair lands in a tile list when blocks of Gaussians each bin many tiles, or the frame
/// says it lost some. lavapipe ends all loops of an invocation after 65535 trips in total, and
/// the binning walks a block of Gaussians per invocation: with 1200 tiles (640x480) and splats
/// of ~50-150 tiles each, a fresh renderer's blocks run out of trips (74 % of the pairs were
/// lost before the walks were checked); check_pairs then makes later frames' blocks small
/// enough (render_core::forward, loop_safe_bin_block).
#[test]
fn binning_keeps_every_pair_when_each_splat_covers_many_tiles() {
    let gpu = gpu();
    let context = &gpu.context;
    let camera = camera(640, 480, 319.5, 239.5);
    let cloud = random_scene(&camera, 1500, 21, (-0.9, -0.3), (1.0, 4.0));
    let renderer = GpuRenderer::new(context);
    renderer.reserve_pairs(400_000);
    let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let listed_pairs = |frame: &render_core::gpu::DeviceFrame| -> u32 {
        let ranges: Vec<u32> = read_buffer(
            context,
            &frame.tile_ranges,
            frame.tile_ranges.size() as usize / 4,
        );
        ranges.chunks(2).map(|range| range[1] - range[0]).sum()
    };
    let first = renderer
        .render_frame(context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let first_usage = renderer.check_pairs(context, &first).unwrap();
    let first_listed = listed_pairs(&first);
    eprintln!("first frame: {first_usage:?}, {first_listed} pairs in the tile lists");
    assert!(
        first_usage.pairs > 100_000,
        "the scene should bin many tiles per splat"
    );
    assert!(first_usage.pairs <= first_usage.capacity, "{first_usage:?}");
    // A frame that lost pairs says so.
    assert_eq!(
        first_listed == first_usage.pairs,
        !first_usage.binning_cut_short
    );
    let second = renderer
        .render_frame(context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let second_usage = renderer.check_pairs(context, &second).unwrap();
    eprintln!("second frame: {second_usage:?}");
    assert!(!second_usage.overflowed(), "{second_usage:?}");
    assert_eq!(listed_pairs(&second), second_usage.pairs);
}

/// lavapipe ends every loop of an invocation after 65535 trips in all (render-core/README.md).
/// A tile list long enough for a rasterizer's walk to outgrow it is flagged
/// (PairUsage::rasterize_cut_short), with both rasterizers; a shorter one is not. The flag
/// must agree with the image: the walk cut short never reaches the green splat at the back.
#[test]
fn a_forward_walk_cut_short_by_the_loop_limit_is_reported() {
    let gpu = gpu();
    let context = &gpu.context;
    for renderer in [
        &GpuRenderer::new(context),
        &renderer_without_subgroups(context),
    ] {
        // The top band's walk takes about 1.1 of lavapipe's loop trips per entry with
        // subgroups (measured with this scene: 55 000 faint splats stay within the limit,
        // 60 000 do not) and about one without (60 000 within, 65 000 not): 40 000 entries
        // stay within it, 70 000 do not.
        for (boundary_splats, outgrows_lavapipe) in [(40_000, false), (70_000, true)] {
            let (camera, cloud) = loop_limit_scene(boundary_splats);
            let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
            let checks_before = renderer.checks_cut_short();
            let (frame, usage) = render_checked(renderer, &gaussians, &camera);
            let output = renderer
                .read_output(context, &frame, RenderMode::RgbD)
                .unwrap();
            let pixel = 3 * camera.width as usize + 3;
            let green = output.rgb.as_ref().unwrap()[pixel][1];
            let case = format!(
                "{boundary_splats} faint splats, subgroups {}: {usage:?}, green {green}",
                renderer.uses_subgroups
            );
            eprintln!("{case}");
            assert!(!usage.rasterize_backward_cut_short, "{case}");
            assert_eq!(usage.rasterize_cut_short, green == 0.0, "{case}");
            assert_eq!(
                renderer.checks_cut_short() > checks_before,
                usage.rasterize_cut_short,
                "{case}"
            );
            if has_lavapipe_loop_limit(context) {
                assert_eq!(usage.rasterize_cut_short, outgrows_lavapipe, "{case}");
            }
        }
    }
}
