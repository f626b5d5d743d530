//! The reference renderer checked by hand-computed cases and its backward pass by finite
//! differences.

use super::*;
use crate::types::{ImageGradients, RigidTransform};

/// A small deterministic pseudo-random generator (keeps the oracle free of dependencies).
struct Lcg(u64);
impl Lcg {
    fn uniform(&mut self, low: f32, high: f32) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let unit = (self.0 >> 40) as f32 / (1u64 << 24) as f32;
        low + (high - low) * unit
    }
}

fn test_camera(width: u32, height: u32) -> Camera {
    let world_from_camera =
        RigidTransform::from_quaternion_translation([0.98, 0.05, -0.12, 0.1], [0.1, -0.05, -0.2]);
    Camera::from_world_from_camera(
        world_from_camera,
        [40.0, 42.0, width as f32 * 0.45, height as f32 * 0.55],
        width,
        height,
    )
}

/// Gaussians scattered in front of `camera`, footprints of a few pixels.
fn test_scene(camera: &Camera, count: usize, seed: u64) -> GaussianCloud {
    let mut rng = Lcg(seed);
    let world_from_camera = camera.world_from_camera();
    let mut cloud = GaussianCloud::default();
    for _ in 0..count {
        let z = rng.uniform(1.5, 3.0);
        let u = rng.uniform(0.0, camera.width as f32);
        let v = rng.uniform(0.0, camera.height as f32);
        let camera_point = [
            (u - camera.cx) * z / camera.fx,
            (v - camera.cy) * z / camera.fy,
            z,
        ];
        cloud.push(
            world_from_camera.transform_point(camera_point),
            [
                rng.uniform(-2.8, -1.6),
                rng.uniform(-2.8, -1.6),
                rng.uniform(-2.8, -1.6),
            ],
            [
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            ],
            rng.uniform(-1.0, 1.5),
            [
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ],
        );
    }
    cloud
}

struct LinearLoss {
    w_rgb: Vec<[f64; 3]>,
    w_depth: Vec<f64>,
    w_alpha: Vec<f64>,
}

impl LinearLoss {
    fn random(pixels: usize, seed: u64) -> Self {
        let mut rng = Lcg(seed);
        let mut sample = || f64::from(rng.uniform(-1.0, 1.0));
        Self {
            w_rgb: (0..pixels)
                .map(|_| [sample(), sample(), sample()])
                .collect(),
            w_depth: (0..pixels).map(|_| sample()).collect(),
            w_alpha: (0..pixels).map(|_| sample()).collect(),
        }
    }
    fn evaluate(&self, cloud: &GaussianCloud, camera: &Camera, config: &RasterConfig) -> f64 {
        let (rgb, depth, alpha) = render_f64(cloud, camera, config);
        let mut loss = 0.0;
        for i in 0..rgb.len() {
            loss += (0..3).map(|c| self.w_rgb[i][c] * rgb[i][c]).sum::<f64>()
                + self.w_depth[i] * depth[i]
                + self.w_alpha[i] * alpha[i];
        }
        loss
    }
    fn image_gradients(&self) -> ImageGradients {
        ImageGradients {
            v_rgb: self.w_rgb.iter().map(|w| w.map(|v| v as f32)).collect(),
            v_depth: self.w_depth.iter().map(|&v| v as f32).collect(),
            v_alpha: self.w_alpha.iter().map(|&v| v as f32).collect(),
        }
    }
}

const STEP: f32 = 1e-3;
const RELATIVE_TOLERANCE: f64 = 1e-2;
/// Absolute slack as a fraction of the largest gradient of the same parameter group.
const GROUP_TOLERANCE: f64 = 2e-3;

/// Central difference of `loss` in one f32 parameter, using the exactly representable
/// step actually taken.
fn central_difference(
    cloud: &GaussianCloud,
    set: impl Fn(&mut GaussianCloud, f32),
    get: impl Fn(&GaussianCloud) -> f32,
    loss: impl Fn(&GaussianCloud) -> f64,
) -> f64 {
    let original = get(cloud);
    let mut plus = cloud.clone();
    set(&mut plus, original + STEP);
    let mut minus = cloud.clone();
    set(&mut minus, original - STEP);
    let span = f64::from(get(&plus)) - f64::from(get(&minus));
    (loss(&plus) - loss(&minus)) / span
}

fn assert_close(name: &str, analytic: &[f64], numeric: &[f64]) {
    let scale = numeric.iter().fold(1e-6f64, |m, v| m.max(v.abs()));
    assert!(
        scale > 1e-4,
        "{name}: gradients vanish, the test would not test anything"
    );
    for (i, (a, f)) in analytic.iter().zip(numeric).enumerate() {
        let tolerance = RELATIVE_TOLERANCE * f.abs() + GROUP_TOLERANCE * scale;
        assert!(
            (a - f).abs() <= tolerance,
            "{name}[{i}]: analytic {a} vs numeric {f} (tolerance {tolerance})"
        );
    }
}

#[test]
fn gradients_match_finite_differences() {
    let camera = test_camera(32, 24);
    let cloud = test_scene(&camera, 8, 7);
    let config = RasterConfig::smooth_for_gradient_checks();
    let loss = LinearLoss::random(camera.pixel_count(), 11);
    let gradients = render_backward(&cloud, &camera, &config, &loss.image_gradients());
    let evaluate = |c: &GaussianCloud| loss.evaluate(c, &camera, &config);

    let (mut analytic, mut numeric) = (Vec::new(), Vec::new());
    macro_rules! check_group {
        ($name:expr, $field:ident, $grad:ident, $dims:expr) => {{
            analytic.clear();
            numeric.clear();
            for i in 0..cloud.len() {
                for d in 0..$dims {
                    numeric.push(central_difference(
                        &cloud,
                        |c, v| c.$field[i][d] = v,
                        |c| c.$field[i][d],
                        evaluate,
                    ));
                    analytic.push(f64::from(gradients.$grad[i][d]));
                }
            }
            assert_close($name, &analytic, &numeric);
        }};
    }
    check_group!("v_means", means, v_means, 3);
    check_group!("v_log_scales", log_scales, v_log_scales, 3);
    check_group!("v_quaternions", quaternions, v_quaternions, 4);
    check_group!("v_colours", colours, v_colours, 3);
    analytic.clear();
    numeric.clear();
    for i in 0..cloud.len() {
        numeric.push(central_difference(
            &cloud,
            |c, v| c.opacity_logits[i] = v,
            |c| c.opacity_logits[i],
            evaluate,
        ));
        analytic.push(f64::from(gradients.v_opacity_logits[i]));
    }
    assert_close("v_opacity_logits", &analytic, &numeric);

    let pose_step = f64::from(STEP);
    let pose_numeric: Vec<f64> = (0..6)
        .map(|k| {
            let mut xi = [0.0; 6];
            xi[k] = pose_step;
            let mut plus = camera;
            plus.camera_from_world = camera.camera_from_world.left_perturbed(xi);
            xi[k] = -pose_step;
            let mut minus = camera;
            minus.camera_from_world = camera.camera_from_world.left_perturbed(xi);
            (loss.evaluate(&cloud, &plus, &config) - loss.evaluate(&cloud, &minus, &config))
                / (2.0 * pose_step)
        })
        .collect();
    let pose_analytic: Vec<f64> = gradients
        .v_pose
        .as_array()
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    assert_close("v_pose", &pose_analytic, &pose_numeric);
}

#[test]
fn clamped_and_skipped_splats_get_consistent_gradients() {
    // Default thresholds: a nearly opaque splat (alpha clamped at 0.99) in front of others.
    // Away from the discontinuities the gradients must still match finite differences of
    // the colour and depth (which are smooth in the colour and the mean's z).
    let camera = test_camera(32, 24);
    let mut cloud = test_scene(&camera, 6, 3);
    cloud.opacity_logits[0] = 8.0;
    let config = RasterConfig::default();
    let loss = LinearLoss::random(camera.pixel_count(), 5);
    let gradients = render_backward(&cloud, &camera, &config, &loss.image_gradients());
    let evaluate = |c: &GaussianCloud| loss.evaluate(c, &camera, &config);
    let mut analytic = Vec::new();
    let mut numeric = Vec::new();
    for i in 0..cloud.len() {
        for d in 0..3 {
            numeric.push(central_difference(
                &cloud,
                |c, v| c.colours[i][d] = v,
                |c| c.colours[i][d],
                evaluate,
            ));
            analytic.push(f64::from(gradients.v_colours[i][d]));
        }
    }
    assert_close("v_colours (default thresholds)", &analytic, &numeric);
}

#[test]
fn depth_is_alpha_weighted_camera_z() {
    // A single large flat splat facing the camera: expected depth = depth / alpha = its z.
    let camera = test_camera(32, 24);
    let point = camera.world_from_camera().transform_point([0.0, 0.0, 2.0]);
    let mut cloud = GaussianCloud::default();
    cloud.push(
        point,
        [0.0, 0.0, -6.0],
        [1.0, 0.0, 0.0, 0.0],
        2.0,
        [0.2, 0.4, 0.6],
    );
    let out = render(&cloud, &camera, RenderMode::RgbD, &RasterConfig::default());
    let centre = (camera.cy.round() as u32 * camera.width + camera.cx.round() as u32) as usize;
    let alpha = out.alpha[centre];
    assert!(alpha > 0.5, "centre alpha {alpha}");
    let depth = out.depth.as_ref().unwrap()[centre];
    let camera_z = project_gaussian(&cloud, 0, &camera).unwrap().camera_point[2] as f32;
    assert!(
        (depth / alpha - camera_z).abs() < 1e-4,
        "expected depth {} vs z {camera_z}",
        depth / alpha
    );
    let rgb = out.rgb.as_ref().unwrap()[centre];
    assert!((rgb[2] / alpha - 0.6).abs() < 1e-5);
}

#[test]
fn principal_point_shifts_the_image() {
    let mut camera = test_camera(32, 24);
    let point = camera.world_from_camera().transform_point([0.0, 0.0, 2.0]);
    let mut cloud = GaussianCloud::default();
    cloud.push(point, [-3.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, [1.0; 3]);
    let brightest = |camera: &Camera| {
        let out = render(&cloud, camera, RenderMode::Rgb, &RasterConfig::default());
        let index = (0..out.alpha.len())
            .max_by(|&a, &b| out.alpha[a].total_cmp(&out.alpha[b]))
            .unwrap();
        (index as u32 % camera.width, index as u32 / camera.width)
    };
    camera.cx = 10.0;
    camera.cy = 7.0;
    assert_eq!(brightest(&camera), (10, 7));
    camera.cx = 20.0;
    camera.cy = 15.0;
    assert_eq!(brightest(&camera), (20, 15));
}
