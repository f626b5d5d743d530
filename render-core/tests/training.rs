//! Image losses and Adam: the CPU loss against finite differences, the device loss against the
//! CPU loss, and an end-to-end fit on the device.

mod common;

use common::{default_camera, gpu, parameter_groups, random_scene, read_buffer};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use render_core::backward::DeviceImageGradients;
use render_core::gpu::DeviceGaussians;
use render_core::training::{
    AdamConfig, DeviceAdam, DeviceTarget, LossWeights, TargetImage, TrainingKernels,
    reference_image_loss,
};
use render_core::{Camera, RasterConfig, RenderMode, RenderOutput, reference};
use splats::GaussianCloud;

fn random_image(width: u32, height: u32, seed: u64) -> (Vec<[f32; 3]>, Vec<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pixels = (width * height) as usize;
    let rgb = (0..pixels)
        .map(|_| {
            [
                rng.random_range(0.0f32..1.0),
                rng.random_range(0.0f32..1.0),
                rng.random_range(0.0f32..1.0),
            ]
        })
        .collect();
    let depth = (0..pixels).map(|_| rng.random_range(0.5f32..4.0)).collect();
    (rgb, depth)
}

#[test]
fn reference_loss_gradient_matches_finite_differences() {
    let (width, height) = (14, 11);
    let (rgb, depth) = random_image(width, height, 1);
    let (target_rgb, mut target_depth) = random_image(width, height, 2);
    // Every third target depth invalid: those pixels must not contribute.
    for (i, d) in target_depth.iter_mut().enumerate() {
        if i % 3 == 0 {
            *d = 0.0;
        }
    }
    let target = TargetImage {
        width,
        height,
        rgb: target_rgb,
        depth: Some(target_depth),
    };
    let weights = LossWeights {
        depth_truncation: 3.0,
        ..LossWeights::default()
    };
    let rendered = RenderOutput {
        width,
        height,
        rgb: Some(rgb),
        depth: Some(depth),
        alpha: vec![0.0; (width * height) as usize],
    };
    let (_, gradients) = reference_image_loss(&rendered, &target, &weights);
    // Steps small enough that no |x - y| kink is crossed (values differ by far more).
    const STEP: f32 = 1e-3;
    let mut worst = 0.0f64;
    let mut skipped = 0;
    for p in 0..(width * height) as usize {
        for c in 0..4 {
            // |x - y| is not differentiable at x = y: skip entries a central step would straddle.
            let (x, y) = if c < 3 {
                (rendered.rgb.as_ref().unwrap()[p][c], target.rgb[p][c])
            } else {
                (
                    rendered.depth.as_ref().unwrap()[p],
                    target.depth.as_ref().unwrap()[p],
                )
            };
            if (x - y).abs() < 2.0 * STEP {
                skipped += 1;
                continue;
            }
            let evaluate = |delta: f32| {
                let mut image = rendered.clone();
                if c < 3 {
                    image.rgb.as_mut().unwrap()[p][c] += delta;
                } else {
                    image.depth.as_mut().unwrap()[p] += delta;
                }
                reference_image_loss(&image, &target, &weights).0
            };
            let numeric = (evaluate(STEP) - evaluate(-STEP)) / (2.0 * f64::from(STEP));
            let analytic = if c < 3 {
                f64::from(gradients.v_rgb[p][c])
            } else {
                f64::from(gradients.v_depth[p])
            };
            let error = (numeric - analytic).abs();
            worst = worst.max(error);
            assert!(
                error <= 1e-6 + 1e-3 * numeric.abs(),
                "pixel {p} channel {c}: analytic {analytic} vs numeric {numeric}"
            );
            if c == 3 && p % 3 == 0 {
                assert_eq!(analytic, 0.0, "invalid depth pixel {p} has a gradient");
            }
        }
    }
    assert!(skipped < 10, "{skipped} entries skipped");
    eprintln!("worst loss-gradient error {worst:.2e} ({skipped} entries at an L1 kink skipped)");
}

fn target_from(output: &RenderOutput) -> TargetImage {
    TargetImage {
        width: output.width,
        height: output.height,
        rgb: output.rgb.clone().unwrap(),
        depth: output.depth.clone(),
    }
}

#[test]
fn device_loss_matches_reference() {
    check_device_loss(&default_camera());
}

/// Runs that end inside the image, after an odd number of pixels: 75 = 64 + 11 columns and
/// 71 = 64 + 7 rows (the loss kernels work in runs of LOSS_RUN = 64 pixels).
#[test]
fn device_loss_matches_reference_on_partial_odd_runs() {
    check_device_loss(&common::camera(75, 71, 37.0, 35.0));
}

fn check_device_loss(camera: &Camera) {
    let gpu = gpu();
    let camera = *camera;
    let cloud = random_scene(&camera, 60, 31, (-3.0, -1.5), (0.0, 3.0));
    let other = random_scene(&camera, 60, 32, (-3.0, -1.5), (0.0, 3.0));
    let mut target = target_from(&reference::render(
        &other,
        &camera,
        RenderMode::RgbD,
        &RasterConfig::default(),
    ));
    // Target depth where nothing was rendered is 0 = invalid, and some more holes.
    for (i, d) in target.depth.as_mut().unwrap().iter_mut().enumerate() {
        if i % 5 == 0 {
            *d = 0.0;
        }
    }
    let weights = weights_with_depth();
    let gaussians = DeviceGaussians::upload(&gpu.context, &cloud).unwrap();
    let frame = gpu
        .renderer
        .render_frame(&gpu.context, &gaussians, &camera, &RasterConfig::default())
        .unwrap();
    let rendered = gpu
        .renderer
        .read_output(&gpu.context, &frame, RenderMode::RgbD)
        .unwrap();
    let (expected_loss, expected) = reference_image_loss(&rendered, &target, &weights);

    let kernels = TrainingKernels::new(&gpu.context);
    let device_target = DeviceTarget::upload(&gpu.context, &target).unwrap();
    let image_gradients = DeviceImageGradients::zeros(&gpu.context, &camera).unwrap();
    let loss = kernels
        .image_loss(
            &gpu.context,
            &gpu.renderer,
            &frame,
            &device_target,
            &weights,
            &image_gradients,
        )
        .unwrap()
        .read(&gpu.context)
        .unwrap();
    let total: f32 = loss.iter().sum();
    eprintln!("device loss terms {loss:?}, total {total}, reference {expected_loss}");
    assert!(
        loss.iter().all(|&t| t > 0.0),
        "every term should be active: {loss:?}"
    );
    assert!((f64::from(total) - expected_loss).abs() <= 1e-5 * expected_loss.max(1.0));

    let pixels = camera.pixel_count();
    let v_rgbd: Vec<f32> = read_buffer(&gpu.context, &image_gradients.v_rgbd, 4 * pixels);
    let scale = expected
        .v_rgb
        .iter()
        .flatten()
        .fold(0.0f32, |m, v| m.max(v.abs()));
    for p in 0..pixels {
        for c in 0..3 {
            let (a, e) = (v_rgbd[4 * p + c], expected.v_rgb[p][c]);
            assert!(
                (a - e).abs() <= 1e-3 * scale,
                "v_rgb[{p}][{c}]: device {a} vs reference {e}"
            );
        }
        let (a, e) = (v_rgbd[4 * p + 3], expected.v_depth[p]);
        assert!(
            (a - e).abs() <= 1e-6 * e.abs().max(1e-3),
            "v_depth[{p}]: device {a} vs reference {e}"
        );
    }
}

fn psnr(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let mse: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| (0..3).map(move |c| f64::from(x[c] - y[c]).powi(2)))
        .sum::<f64>()
        / (3 * a.len()) as f64;
    -10.0 * mse.log10()
}

#[test]
fn fitting_a_perturbed_map_to_known_views_reduces_the_loss_and_reaches_30_db() {
    let gpu = gpu();
    let context = &gpu.context;
    let base = default_camera();
    let cameras: Vec<Camera> = [[0.0, 0.0, 0.0], [0.15, -0.05, 0.0], [-0.1, 0.08, 0.05]]
        .iter()
        .map(|&offset| {
            let mut pose = base.world_from_camera();
            for (coordinate, delta) in pose.translation.iter_mut().zip(offset) {
                *coordinate += delta;
            }
            Camera::from_world_from_camera(
                pose,
                [base.fx, base.fy, base.cx, base.cy],
                base.width,
                base.height,
            )
        })
        .collect();
    let truth = random_scene(&base, 80, 41, (-2.8, -2.0), (0.0, 3.0));
    let targets: Vec<TargetImage> = cameras
        .iter()
        .map(|camera| {
            target_from(&reference::render(
                &truth,
                camera,
                RenderMode::RgbD,
                &RasterConfig::default(),
            ))
        })
        .collect();

    // Start: same Gaussians with jittered positions and scales, random colours, mid opacity.
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut start = GaussianCloud::default();
    for i in 0..truth.len() {
        let mean = truth.means[i].map(|v| v + rng.random_range(-0.02f32..0.02));
        let log_scale = truth.log_scales[i].map(|v| v + rng.random_range(-0.3f32..0.3));
        let colour = [
            rng.random_range(0.0f32..1.0),
            rng.random_range(0.0f32..1.0),
            rng.random_range(0.0f32..1.0),
        ];
        start.push(mean, log_scale, truth.quaternions[i], 0.0, colour);
    }

    let weights = weights_with_depth();
    let config = AdamConfig {
        means: 1e-3,
        log_scales: 0.01,
        quaternions: 0.0,
        opacity_logits: 0.05,
        colours: 0.02,
        ..AdamConfig::default()
    };
    let kernels = TrainingKernels::new(context);
    let gaussians = DeviceGaussians::upload(context, &start).unwrap();
    let mut adam = DeviceAdam::new(context, &gaussians, config).unwrap();
    let device_targets: Vec<DeviceTarget> = targets
        .iter()
        .map(|t| DeviceTarget::upload(context, t).unwrap())
        .collect();
    let image_gradients = DeviceImageGradients::zeros(context, &base).unwrap();

    let total_loss = |gaussians: &DeviceGaussians| -> f32 {
        cameras
            .iter()
            .zip(&device_targets)
            .map(|(camera, target)| {
                let frame = gpu
                    .renderer
                    .render_frame(context, gaussians, camera, &RasterConfig::default())
                    .unwrap();
                let loss = kernels
                    .image_loss(
                        context,
                        &gpu.renderer,
                        &frame,
                        target,
                        &weights,
                        &image_gradients,
                    )
                    .unwrap();
                loss.read(context).unwrap().iter().sum::<f32>()
            })
            .sum()
    };
    let initial_loss = total_loss(&gaussians);
    const ITERATIONS: usize = 60;
    for iteration in 0..ITERATIONS {
        let view = iteration % cameras.len();
        let frame = gpu
            .renderer
            .render_frame(
                context,
                &gaussians,
                &cameras[view],
                &RasterConfig::default(),
            )
            .unwrap();
        kernels
            .image_loss(
                context,
                &gpu.renderer,
                &frame,
                &device_targets[view],
                &weights,
                &image_gradients,
            )
            .unwrap();
        let gradients = gpu
            .renderer
            .backward(context, &gaussians, &frame, &image_gradients)
            .unwrap();
        kernels
            .adam_step(context, &mut adam, &gaussians, &gradients)
            .unwrap();
    }
    let final_loss = total_loss(&gaussians);
    let fitted = gaussians.download(context).unwrap();
    let psnr_before: f64 = cameras
        .iter()
        .zip(&targets)
        .map(|(c, t)| {
            psnr(
                reference::render(&start, c, RenderMode::Rgb, &RasterConfig::default())
                    .rgb
                    .as_ref()
                    .unwrap(),
                &t.rgb,
            )
        })
        .sum::<f64>()
        / cameras.len() as f64;
    let psnr_after: f64 = cameras
        .iter()
        .zip(&targets)
        .map(|(c, t)| {
            psnr(
                reference::render(&fitted, c, RenderMode::Rgb, &RasterConfig::default())
                    .rgb
                    .as_ref()
                    .unwrap(),
                &t.rgb,
            )
        })
        .sum::<f64>()
        / cameras.len() as f64;
    eprintln!(
        "loss {initial_loss:.4} -> {final_loss:.4}, PSNR {psnr_before:.2} -> {psnr_after:.2} dB after {ITERATIONS} Adam steps"
    );
    assert!(
        final_loss < 0.5 * initial_loss,
        "loss only went from {initial_loss} to {final_loss}"
    );
    assert!(
        psnr_after > psnr_before + 3.0,
        "PSNR {psnr_before} -> {psnr_after}"
    );
    assert!(
        psnr_after >= 30.0,
        "training-view PSNR {psnr_after} dB below the 30 dB target"
    );
    assert_eq!(
        fitted.quaternions, start.quaternions,
        "a zero learning rate must freeze its group"
    );
    assert_ne!(fitted.colours, start.colours);
    assert!(fitted.means.iter().flatten().all(|v| v.is_finite()));
    assert_eq!(adam.step_count(), ITERATIONS as u32);
}

#[test]
fn device_adam_steps_match_the_host_formula_for_any_group_length() {
    let gpu = gpu();
    let context = &gpu.context;
    let camera = default_camera();
    // 7 Gaussians: groups of 21, 21, 28, 7 and 21 elements, so the kernel's vectors of 4 and
    // its tail of the last elements % 4 both run.
    let cloud = random_scene(&camera, 7, 41, (-2.0, -1.0), (0.0, 2.0));
    let other = random_scene(&camera, 7, 42, (-2.0, -1.0), (0.0, 2.0));
    let target = target_from(&reference::render(
        &other,
        &camera,
        RenderMode::RgbD,
        &RasterConfig::default(),
    ));
    let config = AdamConfig {
        means: 1e-2,
        log_scales: 0.01,
        quaternions: 0.003,
        opacity_logits: 0.05,
        colours: 0.02,
        ..AdamConfig::default()
    };
    let rates = [
        config.means,
        config.log_scales,
        config.quaternions,
        config.opacity_logits,
        config.colours,
    ];
    let kernels = TrainingKernels::new(context);
    let gaussians = DeviceGaussians::upload(context, &cloud).unwrap();
    let mut adam = DeviceAdam::new(context, &gaussians, config).unwrap();
    let device_target = DeviceTarget::upload(context, &target).unwrap();
    let image_gradients = DeviceImageGradients::zeros(context, &camera).unwrap();

    let mut parameters = parameter_groups(&cloud);
    let mut first = parameters.clone().map(|g| vec![0.0f32; g.len()]);
    let mut second = first.clone();
    let mut any_gradient = false;
    for step in 1..=3 {
        let frame = gpu
            .renderer
            .render_frame(context, &gaussians, &camera, &RasterConfig::default())
            .unwrap();
        kernels
            .image_loss(
                context,
                &gpu.renderer,
                &frame,
                &device_target,
                &weights_with_depth(),
                &image_gradients,
            )
            .unwrap();
        let gradients = gpu
            .renderer
            .backward(context, &gaussians, &frame, &image_gradients)
            .unwrap();
        if step == 2 {
            // A non-finite gradient element counts as zero: one in a vector, one in the tail.
            for element in [5u64, 20] {
                context.queue.write_buffer(
                    &gradients.v_means,
                    element * 4,
                    bytemuck::bytes_of(&f32::NAN),
                );
            }
        }
        let host = gradients.download(context).unwrap();
        let host_gradients = [
            host.v_means.iter().flatten().copied().collect::<Vec<f32>>(),
            host.v_log_scales.iter().flatten().copied().collect(),
            host.v_quaternions.iter().flatten().copied().collect(),
            host.v_opacity_logits.clone(),
            host.v_colours.iter().flatten().copied().collect(),
        ];
        if step == 2 {
            assert!(host_gradients[0][5].is_nan() && host_gradients[0][20].is_nan());
        }
        kernels
            .adam_step(context, &mut adam, &gaussians, &gradients)
            .unwrap();
        let bias_correction1 = 1.0 / (1.0 - config.beta1.powi(step));
        let bias_correction2 = 1.0 / (1.0 - config.beta2.powi(step));
        for group in 0..5 {
            for i in 0..parameters[group].len() {
                let raw = host_gradients[group][i];
                let gradient = if raw.is_finite() { raw } else { 0.0 };
                any_gradient |= gradient != 0.0;
                let m = config.beta1 * first[group][i] + (1.0 - config.beta1) * gradient;
                let v =
                    config.beta2 * second[group][i] + (1.0 - config.beta2) * gradient * gradient;
                first[group][i] = m;
                second[group][i] = v;
                parameters[group][i] -= rates[group] * (m * bias_correction1)
                    / ((v * bias_correction2).sqrt() + config.epsilon);
            }
        }
    }
    assert!(any_gradient, "the scene should give some non-zero gradient");
    let moments = adam.download_moments(context).unwrap();
    let device = [
        parameter_groups(&gaussians.download(context).unwrap()),
        parameter_groups(&moments.first),
        parameter_groups(&moments.second),
    ];
    for (name, host, device) in [
        ("parameter", &parameters, &device[0]),
        ("first moment", &first, &device[1]),
        ("second moment", &second, &device[2]),
    ] {
        for group in 0..5 {
            assert_eq!(host[group].len(), device[group].len());
            for (i, (h, d)) in host[group].iter().zip(&device[group]).enumerate() {
                assert!(
                    (h - d).abs() <= 1e-6 * h.abs().max(1e-6),
                    "{name} group {group} element {i}: host {h}, device {d}"
                );
            }
        }
    }
}

/// The default loss weights with the depth term on (truncation 4 m).
fn weights_with_depth() -> LossWeights {
    LossWeights {
        depth_truncation: 4.0,
        ..LossWeights::default()
    }
}
