//! In-place edits of the device map: append (with growth), prune / retain (stable compaction,
//! Adam moments following), rigid transform; against host computations.

mod common;

use common::{default_camera, gpu, parameter_groups, random_scene};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use render_core::backward::DeviceImageGradients;
use render_core::context::GpuError;
use render_core::gpu::DeviceGaussians;
use render_core::map::{DeviceMap, MIN_GROWN_CAPACITY, PruneCriteria};
use render_core::training::{
    AdamConfig, AdamMoments, DeviceAdam, DeviceTarget, LossWeights, TargetImage, TrainingKernels,
};
use render_core::{Camera, RasterConfig, RenderMode, RenderOutput};
use splats::{GaussianCloud, RigidTransform};

/// Footprints of a few pixels at 1-4 m and mostly visible opacities.
const LOG_SCALE_RANGE: (f32, f32) = (-4.0, -2.5);
const LOGIT_RANGE: (f32, f32) = (-1.0, 3.0);

fn scene(count: usize, seed: u64) -> GaussianCloud {
    random_scene(&default_camera(), count, seed, LOG_SCALE_RANGE, LOGIT_RANGE)
}

fn concatenated(parts: &[&GaussianCloud]) -> GaussianCloud {
    let mut all = GaussianCloud::default();
    for part in parts {
        all.extend_from(part);
    }
    all
}

fn render(gaussians: &DeviceGaussians, camera: &Camera) -> RenderOutput {
    let gpu = gpu();
    gpu.renderer
        .render(&gpu.context, gaussians, camera, RenderMode::RgbD)
        .unwrap()
}

#[test]
fn append_then_render_equals_render_of_concatenated_upload() {
    let context = &gpu().context;
    let camera = default_camera();
    let parts = [scene(40, 1), scene(30, 2), scene(25, 3)];
    let mut gaussians = DeviceGaussians::upload(context, &parts[0]).unwrap();
    assert_eq!(gaussians.append(context, &parts[1]).unwrap(), 40..70);
    assert_eq!(gaussians.append(context, &parts[2]).unwrap(), 70..95);
    assert_eq!(gaussians.len(), 95);
    let all = concatenated(&[&parts[0], &parts[1], &parts[2]]);
    assert_eq!(gaussians.download(context).unwrap(), all);
    let uploaded = DeviceGaussians::upload(context, &all).unwrap();
    // Bit for bit: the same values through the same kernels, whatever the capacity.
    assert_eq!(render(&gaussians, &camera), render(&uploaded, &camera));
}

#[test]
fn growth_crosses_several_capacity_boundaries() {
    let context = &gpu().context;
    let camera = default_camera();
    let mut gaussians = DeviceGaussians::upload(context, &GaussianCloud::default()).unwrap();
    let mut all = GaussianCloud::default();
    let mut capacities = vec![gaussians.capacity()];
    const BATCH: usize = 97;
    const BATCHES: u64 = 16;
    for seed in 0..BATCHES {
        let batch = scene(BATCH, 100 + seed);
        let range = gaussians.append(context, &batch).unwrap();
        assert_eq!(range, all.len()..all.len() + BATCH);
        all.extend_from(&batch);
        assert!(gaussians.capacity() >= gaussians.len());
        if gaussians.capacity() != *capacities.last().unwrap() {
            capacities.push(gaussians.capacity());
        }
    }
    // 0 -> 256 -> 384 -> 576 -> 864 -> 1296 -> 1944 for 1552 Gaussians.
    assert!(capacities.len() >= 5, "capacities {capacities:?}");
    assert_eq!(capacities[1], MIN_GROWN_CAPACITY);
    for pair in capacities[1..].windows(2) {
        assert!(
            2 * pair[1] >= 3 * pair[0],
            "growth {pair:?} is not geometric"
        );
    }
    assert_eq!(gaussians.download(context).unwrap(), all);
    let uploaded = DeviceGaussians::upload(context, &all).unwrap();
    assert_eq!(render(&gaussians, &camera), render(&uploaded, &camera));
}

/// A cloud where every prune criterion fires for some Gaussians and most survive.
fn cloud_to_prune(count: usize, seed: u64) -> GaussianCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut cloud = scene(count, seed);
    for i in 0..count {
        match rng.random_range(0..10) {
            // Nearly transparent (opacity < 0.005 is a logit below -5.29).
            0 => cloud.opacity_logits[i] = rng.random_range(-8.0f32..-4.5),
            // Larger than tau_s = 0.25 m (log-scale -1.39) on one axis.
            1 => cloud.log_scales[i][rng.random_range(0..3)] = rng.random_range(-1.6f32..0.5),
            // Needle: one axis 5-40 times the others, small enough to pass the size test
            // (largest log-scale at most -1.8).
            2 => {
                let base = rng.random_range(-6.5f32..-5.5);
                cloud.log_scales[i] = [base, base, base];
                cloud.log_scales[i][rng.random_range(0..3)] = base + rng.random_range(1.6f32..3.7);
            }
            _ => {}
        }
    }
    // Non-finite values in every parameter group.
    cloud.means[3][1] = f32::NAN;
    cloud.log_scales[8][2] = f32::INFINITY;
    cloud.quaternions[13][0] = f32::NAN;
    cloud.opacity_logits[21] = f32::NAN;
    cloud.colours[34][2] = f32::NEG_INFINITY;
    cloud
}

#[test]
fn prune_matches_host_criteria_and_compacts_stably() {
    let context = &gpu().context;
    let cloud = cloud_to_prune(600, 7);
    let criteria = PruneCriteria {
        max_scale_m: PruneCriteria::REPLICA_MAX_SCALE_M,
        ..PruneCriteria::default()
    };
    let expected = criteria.keep_mask(&cloud);
    // Each criterion alone must remove some Gaussians, so that none goes untested.
    let disabled = [
        PruneCriteria {
            min_opacity: 0.0,
            ..criteria
        },
        PruneCriteria {
            max_scale_m: f32::INFINITY,
            ..criteria
        },
        PruneCriteria {
            max_elongation: f32::INFINITY,
            ..criteria
        },
    ];
    for without in disabled {
        let kept_without = without.keep_mask(&cloud);
        assert!(
            kept_without
                .iter()
                .zip(&expected)
                .filter(|(a, b)| a != b)
                .count()
                >= 10,
            "{without:?} removes almost the same Gaussians"
        );
    }
    let removed = expected.iter().filter(|&&kept| !kept).count();
    assert!(
        removed > 100 && removed < 400,
        "{removed} removed: the scene should exercise every criterion"
    );
    for non_finite in [3, 8, 13, 21, 34] {
        assert!(!expected[non_finite]);
    }
    let mut gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let report = gaussians.prune(context, &criteria).unwrap();
    let mismatches: Vec<usize> = (0..cloud.len())
        .filter(|&i| report.kept.get(i) != expected.get(i))
        .collect();
    assert!(
        mismatches.is_empty() && report.kept.len() == cloud.len(),
        "device and host disagree on Gaussians {mismatches:?}"
    );
    assert_eq!(report.removed, removed);
    assert_eq!(gaussians.len(), cloud.len() - removed);
    assert_eq!(
        gaussians.download(context).unwrap(),
        cloud.select(&expected)
    );
    // A second pass finds nothing more to remove.
    let again = gaussians.prune(context, &criteria).unwrap();
    assert_eq!(again.removed, 0);
    assert!(again.kept.iter().all(|&kept| kept));
}

#[test]
fn retain_keeps_the_callers_mask_in_order() {
    let context = &gpu().context;
    let cloud = scene(700, 11);
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let keep: Vec<bool> = (0..cloud.len()).map(|_| rng.random_bool(0.6)).collect();
    let mut gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let removed = gaussians.retain(context, &keep).unwrap();
    assert_eq!(removed, keep.iter().filter(|&&kept| !kept).count());
    let expected = cloud.select(&keep);
    assert_eq!(gaussians.download(context).unwrap(), expected);
    // Appending after a compaction reuses the freed capacity and renders like an upload.
    let extra = scene(50, 13);
    gaussians.append(context, &extra).unwrap();
    let all = concatenated(&[&expected, &extra]);
    assert_eq!(gaussians.download(context).unwrap(), all);
    let uploaded = DeviceGaussians::upload(context, &all).unwrap();
    let camera = default_camera();
    assert_eq!(render(&gaussians, &camera), render(&uploaded, &camera));
    assert!(matches!(
        gaussians.retain(context, &keep[..10]),
        Err(GpuError::InvalidInput(_))
    ));
}

/// Learning rates on every group, so that every moment buffer is exercised.
fn all_groups_config() -> AdamConfig {
    AdamConfig {
        means: 1e-3,
        log_scales: 1e-2,
        quaternions: 1e-2,
        opacity_logits: 5e-2,
        colours: 1e-2,
        ..AdamConfig::default()
    }
}

struct Trainer {
    kernels: TrainingKernels,
    camera: Camera,
    target: DeviceTarget,
    image_gradients: DeviceImageGradients,
}

impl Trainer {
    fn new() -> Self {
        let context = &gpu().context;
        let camera = default_camera();
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let pixels = camera.pixel_count();
        let target = TargetImage {
            width: camera.width,
            height: camera.height,
            rgb: (0..pixels)
                .map(|_| [rng.random(), rng.random(), rng.random()])
                .collect(),
            depth: Some((0..pixels).map(|_| rng.random_range(1.0..4.0)).collect()),
        };
        Self {
            kernels: TrainingKernels::new(context),
            camera,
            target: DeviceTarget::upload(context, &target).unwrap(),
            image_gradients: DeviceImageGradients::zeros(context, &camera).unwrap(),
        }
    }

    /// Render, loss, backward; returns the gradients (on the device).
    fn gradients(&self, map: &DeviceMap) -> render_core::backward::DeviceGradients {
        let gpu = gpu();
        let context = &gpu.context;
        let frame = gpu
            .renderer
            .render_frame(
                context,
                map.gaussians(),
                &self.camera,
                &RasterConfig::default(),
            )
            .unwrap();
        self.kernels
            .image_loss(
                context,
                &gpu.renderer,
                &frame,
                &self.target,
                &LossWeights::default(),
                &self.image_gradients,
            )
            .unwrap();
        gpu.renderer
            .backward(context, map.gaussians(), &frame, &self.image_gradients)
            .unwrap()
    }

    fn step(&self, map: &mut DeviceMap) {
        let gradients = self.gradients(map);
        map.adam_step(&gpu().context, &self.kernels, &gradients)
            .unwrap();
    }
}

fn moments_select(moments: &AdamMoments, keep: &[bool]) -> AdamMoments {
    AdamMoments {
        first: moments.first.select(keep),
        second: moments.second.select(keep),
    }
}

#[test]
fn adam_moments_follow_prune_and_append() {
    let context = &gpu().context;
    let trainer = Trainer::new();
    let cloud = cloud_to_prune(300, 21);
    // Non-finite parameters would make the loss meaningless; this test is about the moments.
    let finite: Vec<bool> = (0..cloud.len())
        .map(|i| ![3, 8, 13, 21, 34].contains(&i))
        .collect();
    let cloud = cloud.select(&finite);
    let config = all_groups_config();
    let mut map = DeviceMap::upload(context, &cloud, config).unwrap();
    const WARM_UP_STEPS: u32 = 3;
    for _ in 0..WARM_UP_STEPS {
        trainer.step(&mut map);
    }
    let parameters = map.download(context).unwrap();
    let moments = map.adam().download_moments(context).unwrap();
    assert!(moments.first.colours.iter().flatten().any(|&m| m != 0.0));

    let criteria = PruneCriteria::default();
    let report = map.prune(context, &criteria).unwrap();
    assert_eq!(report.kept, criteria.keep_mask(&parameters));
    assert!(report.removed > 0);
    assert_eq!(map.len(), map.adam().len());
    assert_eq!(
        map.download(context).unwrap(),
        parameters.select(&report.kept)
    );
    let pruned_moments = map.adam().download_moments(context).unwrap();
    assert_eq!(pruned_moments, moments_select(&moments, &report.kept));

    // Appended Gaussians start with zero moments; the others keep theirs.
    let extra = scene(40, 22);
    let appended = map.append(context, &extra).unwrap();
    let appended_moments = map.adam().download_moments(context).unwrap();
    let old: Vec<bool> = (0..map.len()).map(|i| !appended.contains(&i)).collect();
    let new: Vec<bool> = old.iter().map(|&is_old| !is_old).collect();
    assert_eq!(moments_select(&appended_moments, &old), pruned_moments);
    let zero_moments = moments_select(&appended_moments, &new);
    for group in parameter_groups(&zero_moments.first)
        .iter()
        .chain(&parameter_groups(&zero_moments.second))
    {
        assert!(group.iter().all(|&m| m == 0.0));
    }

    // One more step on the edited map equals Adam on the host from the edited state.
    let before = map.download(context).unwrap();
    let gradients = trainer.gradients(&map);
    let host_gradients = gradients.download(context).unwrap();
    map.adam_step(context, &trainer.kernels, &gradients)
        .unwrap();
    let after = map.download(context).unwrap();
    let after_moments = map.adam().download_moments(context).unwrap();
    let t = (WARM_UP_STEPS + 1) as i32;
    let first_correction = 1.0 / (1.0 - config.beta1.powi(t));
    let second_correction = 1.0 / (1.0 - config.beta2.powi(t));
    let gradient_groups = [
        host_gradients.v_means.iter().flatten().copied().collect(),
        host_gradients
            .v_log_scales
            .iter()
            .flatten()
            .copied()
            .collect(),
        host_gradients
            .v_quaternions
            .iter()
            .flatten()
            .copied()
            .collect(),
        host_gradients.v_opacity_logits.clone(),
        host_gradients
            .v_colours
            .iter()
            .flatten()
            .copied()
            .collect::<Vec<f32>>(),
    ];
    let rates = [
        config.means,
        config.log_scales,
        config.quaternions,
        config.opacity_logits,
        config.colours,
    ];
    let (old_first, old_second) = (
        parameter_groups(&appended_moments.first),
        parameter_groups(&appended_moments.second),
    );
    let (new_first, new_second) = (
        parameter_groups(&after_moments.first),
        parameter_groups(&after_moments.second),
    );
    let (old_parameters, new_parameters) = (parameter_groups(&before), parameter_groups(&after));
    let mut compared = 0;
    for group in 0..5 {
        for (i, &g) in gradient_groups[group].iter().enumerate() {
            let g = if g.is_finite() { g } else { 0.0 };
            let m = config.beta1 * old_first[group][i] + (1.0 - config.beta1) * g;
            let v = config.beta2 * old_second[group][i] + (1.0 - config.beta2) * g * g;
            let p = old_parameters[group][i]
                - rates[group] * (m * first_correction)
                    / ((v * second_correction).sqrt() + config.epsilon);
            let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 + 1e-5 * b.abs();
            assert!(close(new_first[group][i], m), "group {group} element {i}");
            assert!(close(new_second[group][i], v), "group {group} element {i}");
            assert!(
                close(new_parameters[group][i], p),
                "group {group} element {i}: {} vs {p}",
                new_parameters[group][i]
            );
            compared += 1;
        }
    }
    assert_eq!(compared, map.len() * 14);
}

#[test]
fn stale_state_is_rejected_after_editing_the_gaussians_alone() {
    let gpu = gpu();
    let context = &gpu.context;
    let trainer = Trainer::new();
    let cloud = scene(50, 31);
    let mut gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let mut adam = DeviceAdam::new(context, &gaussians, AdamConfig::default()).unwrap();
    let frame = gpu
        .renderer
        .render_frame(
            context,
            &gaussians,
            &trainer.camera,
            &RasterConfig::default(),
        )
        .unwrap();
    // Same count, different Gaussians: remove one, append one.
    let mut keep = vec![true; cloud.len()];
    keep[0] = false;
    gaussians.retain(context, &keep).unwrap();
    gaussians.append(context, &scene(1, 32)).unwrap();
    assert_eq!(gaussians.len(), adam.len());
    assert!(matches!(
        gpu.renderer
            .backward(context, &gaussians, &frame, &trainer.image_gradients),
        Err(GpuError::InvalidInput(_))
    ));
    let frame = gpu
        .renderer
        .render_frame(
            context,
            &gaussians,
            &trainer.camera,
            &RasterConfig::default(),
        )
        .unwrap();
    let gradients = gpu
        .renderer
        .backward(context, &gaussians, &frame, &trainer.image_gradients)
        .unwrap();
    assert!(matches!(
        trainer
            .kernels
            .adam_step(context, &mut adam, &gaussians, &gradients),
        Err(GpuError::InvalidInput(_))
    ));
    assert!(DeviceMap::from_parts(gaussians, adam).is_err());
}

/// Largest absolute difference between two equally long slices.
fn max_abs_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max)
}

/// `actual`'s means and quaternions equal `expected`'s up to the f32 rounding of a transform
/// (device and host compute it in a different order); the other parameters do not move.
fn assert_placed_like(actual: &GaussianCloud, expected: &GaussianCloud) {
    const TOLERANCE: f32 = 1e-5;
    let [means, _, quaternions, _, _] = parameter_groups(actual);
    let [expected_means, _, expected_quaternions, _, _] = parameter_groups(expected);
    assert!(max_abs_difference(&means, &expected_means) <= TOLERANCE);
    assert!(max_abs_difference(&quaternions, &expected_quaternions) <= TOLERANCE);
    assert_eq!(actual.log_scales, expected.log_scales);
    assert_eq!(actual.opacity_logits, expected.opacity_logits);
    assert_eq!(actual.colours, expected.colours);
}

#[test]
fn transform_rigid_matches_host_and_preserves_the_view() {
    let context = &gpu().context;
    let camera = default_camera();
    let cloud = scene(120, 41);
    let transform =
        RigidTransform::from_quaternion_translation([0.6, -0.3, 0.5, 0.55], [1.5, -0.7, 2.2]);
    let mut gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let original = render(&gaussians, &camera);
    gaussians.transform_rigid(context, &transform).unwrap();
    let transformed = gaussians.download(context).unwrap();
    let mut expected = cloud.clone();
    expected.transform_rigid(&transform);
    assert_placed_like(&transformed, &expected);
    let worst = max_abs_difference;
    // Moving the camera with the map shows the same picture.
    let moved_camera = Camera {
        camera_from_world: camera.camera_from_world.compose(&transform.inverse()),
        ..camera
    };
    let moved = render(&gaussians, &moved_camera);
    let rgb = |output: &RenderOutput| -> Vec<f32> {
        output
            .rgb
            .as_ref()
            .unwrap()
            .iter()
            .flatten()
            .copied()
            .collect()
    };
    let depth = |output: &RenderOutput| output.depth.clone().unwrap();
    let rgb_error = worst(&rgb(&moved), &rgb(&original));
    let depth_error = worst(&depth(&moved), &depth(&original));
    let alpha_error = worst(&moved.alpha, &original.alpha);
    eprintln!(
        "transformed view: max |rgb| {rgb_error}, |depth| {depth_error}, |alpha| {alpha_error}"
    );
    // f32 rounding of the composed transforms only; splats skipped at the 1/255 alpha cut-off
    // could flip at a pixel, bounded by that alpha.
    const VIEW_TOLERANCE: f32 = 1e-4;
    assert!(rgb_error <= VIEW_TOLERANCE, "rgb differs by {rgb_error}");
    assert!(
        alpha_error <= VIEW_TOLERANCE,
        "alpha differs by {alpha_error}"
    );
    assert!(
        depth_error <= 4.0 * VIEW_TOLERANCE,
        "depth differs by {depth_error}"
    );
}

#[test]
fn transform_groups_moves_each_group_by_its_own_transform() {
    let context = &gpu().context;
    let cloud = scene(700, 43);
    let transforms = [
        RigidTransform::from_quaternion_translation([0.6, -0.3, 0.5, 0.55], [1.5, -0.7, 2.2]),
        RigidTransform::IDENTITY,
        RigidTransform::from_quaternion_translation([0.9, 0.1, 0.0, -0.2], [0.0, 0.02, -0.01]),
    ];
    // Groups 0-2 in a pattern that crosses workgroup boundaries, plus groups past the end
    // (left unchanged).
    let group_of: Vec<u32> = (0..cloud.len() as u32)
        .map(|i| (i * 7 + i / 256) % 5)
        .collect();
    let mut gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    gaussians
        .transform_groups(context, &group_of, &transforms)
        .unwrap();
    let transformed = gaussians.download(context).unwrap();
    let mut expected = cloud.clone();
    expected.transform_groups(&group_of, &transforms);
    assert_placed_like(&transformed, &expected);
    // The host oracle itself: group 0 equals the rigid transform, groups 3 and 4 do not move.
    let mut rigid = cloud.clone();
    rigid.transform_rigid(&transforms[0]);
    for (i, &group) in group_of.iter().enumerate() {
        match group {
            0 => assert_eq!(expected.means[i], rigid.means[i]),
            1 | 3 | 4 => {
                assert_eq!(transformed.means[i], cloud.means[i]);
                assert_eq!(transformed.quaternions[i], cloud.quaternions[i]);
            }
            _ => assert_ne!(expected.means[i], cloud.means[i]),
        }
    }
    // A wrong number of group indices is refused and changes nothing.
    assert!(matches!(
        gaussians.transform_groups(context, &group_of[1..], &transforms),
        Err(GpuError::InvalidInput(_))
    ));
    assert_eq!(
        gaussians.download(context).unwrap().means,
        transformed.means
    );
}

#[test]
fn edits_on_empty_and_fully_pruned_maps_do_not_panic() {
    let gpu = gpu();
    let context = &gpu.context;
    let camera = default_camera();
    let trainer = Trainer::new();
    let mut empty =
        DeviceMap::upload(context, &GaussianCloud::default(), AdamConfig::default()).unwrap();
    let report = empty.prune(context, &PruneCriteria::default()).unwrap();
    assert!(report.kept.is_empty() && report.removed == 0);
    assert_eq!(empty.retain(context, &[]).unwrap(), 0);
    empty
        .transform_rigid(context, &RigidTransform::IDENTITY)
        .unwrap();
    assert_eq!(
        empty.append(context, &GaussianCloud::default()).unwrap(),
        0..0
    );
    trainer.step(&mut empty);

    let cloud = scene(60, 51);
    let mut map = DeviceMap::upload(context, &cloud, AdamConfig::default()).unwrap();
    trainer.step(&mut map);
    // min_opacity 1 removes every (finite) Gaussian.
    let everything = PruneCriteria {
        min_opacity: 1.0,
        ..PruneCriteria::default()
    };
    let report = map.prune(context, &everything).unwrap();
    assert_eq!(report.removed, cloud.len());
    assert!(map.is_empty() && map.adam().is_empty());
    assert_eq!(map.download(context).unwrap(), GaussianCloud::default());
    let blank = render(map.gaussians(), &camera);
    assert!(blank.alpha.iter().all(|&a| a == 0.0));
    trainer.step(&mut map);
    // The emptied map takes new Gaussians and trains again.
    map.append(context, &cloud).unwrap();
    assert_eq!(
        map.retain(context, &vec![false; cloud.len()]).unwrap(),
        cloud.len()
    );
    map.append(context, &cloud).unwrap();
    trainer.step(&mut map);
    assert_eq!(map.len(), cloud.len());
    assert!(
        map.prune(
            context,
            &PruneCriteria {
                max_scale_m: -1.0,
                ..PruneCriteria::default()
            }
        )
        .is_err()
    );
}
