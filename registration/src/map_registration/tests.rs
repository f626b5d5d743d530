//! End-to-end tests of [`super::register_maps`] on procedural scenes: an indoor-like room with
//! furniture, an unrelated outdoor-like scene, and a room with four-fold symmetry; each surface
//! painted its own colour, for the tests with colour.

use crate::map_registration::MapRegistrationConfig;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::colour::Rgb;
use super::{MapPoints, MapRegistration, MapRejection, register_maps};

/// Surface sampling step of the scenes (metres).
const STEP: f64 = 0.025;

/// Points of a scene under construction, each with the colour its surface was painted.
struct Scene {
    points: Vec<Point3<f64>>,
    colours: Vec<Rgb>,
    /// Colour of the surfaces added next.
    paint: Rgb,
    rng: ChaCha8Rng,
    /// Shading of the colours (a stream of its own: the geometry does not depend on colours).
    shade_rng: ChaCha8Rng,
}

impl Scene {
    fn new(seed: u64) -> Self {
        Self {
            points: Vec::new(),
            colours: Vec::new(),
            paint: [0.5; 3],
            rng: ChaCha8Rng::seed_from_u64(seed),
            shade_rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_c010),
        }
    }

    /// Paints what is added next: `rgb`, brighter or darker by up to 15 % per point (texture).
    fn paint(&mut self, rgb: Rgb) -> &mut Self {
        self.paint = rgb;
        self
    }

    fn push(&mut self, p: Point3<f64>) {
        let shade: f32 = self.shade_rng.random_range(0.85..1.15);
        self.points.push(p);
        self.colours.push(self.paint.map(|c| (c * shade).min(1.0)));
    }

    /// A rectangle from `origin` along `u` and `v` (their lengths are the sides), sampled on a
    /// jittered grid of [`STEP`].
    fn rectangle(&mut self, origin: Vector3<f64>, u: Vector3<f64>, v: Vector3<f64>) {
        let (nu, nv) = (
            (u.norm() / STEP).ceil() as usize,
            (v.norm() / STEP).ceil() as usize,
        );
        for i in 0..nu {
            for j in 0..nv {
                let a = ((i as f64 + self.rng.random_range(0.0..1.0)) / nu as f64).min(1.0);
                let b = ((j as f64 + self.rng.random_range(0.0..1.0)) / nv as f64).min(1.0);
                self.push(Point3::from(origin + u * a + v * b));
            }
        }
    }

    /// The five visible faces (no bottom) of a box with its base centre at `base`, the given
    /// size, turned by `yaw` about the vertical.
    fn cuboid(&mut self, base: Vector3<f64>, size: Vector3<f64>, yaw: f64) {
        let r = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        let (ex, ey, ez) = (
            r * Vector3::x() * size.x,
            r * Vector3::y() * size.y,
            Vector3::z() * size.z,
        );
        let corner = base - ex / 2.0 - ey / 2.0;
        self.rectangle(corner + ez, ex, ey);
        self.rectangle(corner, ex, ez);
        self.rectangle(corner + ey, ex, ez);
        self.rectangle(corner, ey, ez);
        self.rectangle(corner + ex, ey, ez);
    }

    /// A sphere, sampled at about [`STEP`] spacing (Fibonacci lattice).
    fn sphere(&mut self, centre: Vector3<f64>, radius: f64) {
        let n = (4.0 * std::f64::consts::PI * radius * radius / (STEP * STEP)) as usize;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for k in 0..n {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * k as f64;
            self.push(Point3::from(
                centre + radius * Vector3::new(r * phi.cos(), r * phi.sin(), z),
            ));
        }
    }

    /// A vertical cylinder's side.
    fn cylinder(&mut self, base: Vector3<f64>, radius: f64, height: f64) {
        let around = (2.0 * std::f64::consts::PI * radius / STEP).ceil() as usize;
        let up = (height / STEP).ceil() as usize;
        for i in 0..around {
            for j in 0..up {
                let angle = 2.0 * std::f64::consts::PI * i as f64 / around as f64;
                let z = height * (j as f64 + 0.5) / up as f64;
                self.push(Point3::from(
                    base + Vector3::new(radius * angle.cos(), radius * angle.sin(), z),
                ));
            }
        }
    }

    /// A table: top at 0.75 m and four legs.
    fn table(&mut self, centre: Vector3<f64>, length: f64, width: f64, yaw: f64) {
        let r = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        self.cuboid(
            centre + Vector3::z() * 0.72,
            Vector3::new(length, width, 0.03),
            yaw,
        );
        for (sx, sy) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
            let offset =
                r * Vector3::new(sx * (length / 2.0 - 0.05), sy * (width / 2.0 - 0.05), 0.0);
            self.cuboid(centre + offset, Vector3::new(0.05, 0.05, 0.72), yaw);
        }
    }
}

/// An indoor-like room, 6 x 5 m with 2.5 m walls on three sides and half of the fourth, and
/// furniture placed without symmetry.
fn room(seed: u64) -> Vec<Point3<f64>> {
    coloured_room(seed).points
}

/// [`room`] with colours: each wall, the floor and each piece of furniture its own.
fn coloured_room(seed: u64) -> Scene {
    let mut s = Scene::new(seed);
    let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
    s.paint([0.55, 0.45, 0.35])
        .rectangle(Vector3::zeros(), x * 6.0, y * 5.0);
    s.paint([0.7, 0.3, 0.3])
        .rectangle(Vector3::zeros(), y * 5.0, z * 2.5);
    s.paint([0.3, 0.6, 0.35])
        .rectangle(Vector3::zeros(), x * 6.0, z * 2.5);
    s.paint([0.3, 0.4, 0.75])
        .rectangle(y * 5.0, x * 3.5, z * 2.5);
    s.paint([0.75, 0.7, 0.25])
        .rectangle(x * 6.0, y * 5.0, z * 2.5);
    s.paint([0.5, 0.25, 0.6])
        .table(Vector3::new(3.1, 2.2, 0.0), 1.4, 0.8, 0.3);
    s.paint([0.2, 0.6, 0.65]).cuboid(
        Vector3::new(3.4, 0.5, 0.0),
        Vector3::new(0.9, 0.45, 1.6),
        0.0,
    );
    s.cuboid(
        Vector3::new(2.8, 4.3, 0.0),
        Vector3::new(0.5, 0.5, 0.45),
        0.5,
    );
    s.cuboid(
        Vector3::new(2.8, 4.3, 0.45),
        Vector3::new(0.35, 0.35, 0.3),
        0.9,
    );
    s.sphere(Vector3::new(3.6, 3.4, 0.3), 0.3);
    s.cylinder(Vector3::new(2.9, 1.3, 0.0), 0.15, 1.1);
    s.cuboid(
        Vector3::new(0.6, 2.5, 0.0),
        Vector3::new(0.5, 1.8, 0.9),
        0.0,
    );
    s.cuboid(
        Vector3::new(1.5, 0.8, 0.0),
        Vector3::new(0.6, 0.6, 0.5),
        -0.4,
    );
    s.paint([0.8, 0.8, 0.8])
        .sphere(Vector3::new(1.2, 4.0, 0.9), 0.25);
    s.cylinder(Vector3::new(1.2, 4.0, 0.0), 0.05, 0.65);
    s.paint([0.25, 0.25, 0.6]).cuboid(
        Vector3::new(5.2, 1.0, 0.0),
        Vector3::new(1.2, 0.6, 0.75),
        0.0,
    );
    s.cuboid(
        Vector3::new(5.0, 3.8, 0.0),
        Vector3::new(0.4, 0.4, 1.9),
        0.2,
    );
    s.paint([0.8, 0.5, 0.2])
        .cylinder(Vector3::new(4.4, 2.6, 0.0), 0.25, 0.5);
    s.table(Vector3::new(5.0, 2.4, 0.0), 0.8, 0.8, 0.0);
    s
}

/// Something else entirely: rolling terrain with trees (trunks and crowns) and rocks.
fn outdoor(seed: u64) -> Vec<Point3<f64>> {
    let mut s = Scene::new(seed);
    let (nx, ny) = ((8.0 / STEP) as usize, (6.0 / STEP) as usize);
    for i in 0..nx {
        for j in 0..ny {
            let (x, y) = (i as f64 * STEP, j as f64 * STEP);
            let z = 0.3 * (0.8 * x).sin() * (0.6 * y).cos() + 0.1 * (2.3 * x + 1.1 * y).sin();
            s.push(Point3::new(x, y, z));
        }
    }
    for k in 0..7 {
        let (x, y) = (0.7 + 1.1 * k as f64, 1.0 + (k as f64 * 1.7) % 4.0);
        s.cylinder(Vector3::new(x, y, 0.0), 0.12 + 0.02 * k as f64, 1.4);
        s.sphere(Vector3::new(x, y, 1.8), 0.5);
    }
    s.sphere(Vector3::new(3.0, 5.0, 0.0), 0.4);
    s.sphere(Vector3::new(6.0, 0.8, 0.0), 0.3);
    s.points
}

/// A square 5 x 5 m room with four identical cabinets and pillars in four-fold rotational
/// symmetry about its centre: four transforms explain it equally well.
fn symmetric_room(seed: u64) -> Vec<Point3<f64>> {
    coloured_symmetric_room(seed).points
}

/// [`symmetric_room`] with colours that break the symmetry: a grey floor, and each quarter's
/// wall, cabinet, pillar and box in a colour of its own, as four identical rooms painted
/// differently.
fn coloured_symmetric_room(seed: u64) -> Scene {
    const QUARTERS: [[Rgb; 3]; 4] = [
        [[0.7, 0.3, 0.3], [0.3, 0.3, 0.7], [0.8, 0.8, 0.3]],
        [[0.3, 0.65, 0.3], [0.7, 0.4, 0.2], [0.6, 0.3, 0.7]],
        [[0.3, 0.4, 0.75], [0.25, 0.6, 0.6], [0.75, 0.3, 0.5]],
        [[0.75, 0.7, 0.25], [0.5, 0.7, 0.3], [0.3, 0.3, 0.35]],
    ];
    let mut s = Scene::new(seed);
    let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
    s.paint([0.5, 0.5, 0.5])
        .rectangle(Vector3::zeros(), x * 5.0, y * 5.0);
    let centre = Vector3::new(2.5, 2.5, 0.0);
    for quarter in 0..4 {
        let r = UnitQuaternion::from_euler_angles(
            0.0,
            0.0,
            quarter as f64 * std::f64::consts::FRAC_PI_2,
        );
        let at = |p: Vector3<f64>| centre + r * (p - centre);
        let mut part = Scene::new(seed + 1 + quarter);
        let [wall, cabinet, other] = QUARTERS[quarter as usize];
        part.paint(wall)
            .rectangle(Vector3::zeros(), x * 5.0, z * 2.5);
        part.paint(cabinet).cuboid(
            Vector3::new(1.0, 0.4, 0.0),
            Vector3::new(1.0, 0.5, 1.2),
            0.0,
        );
        part.paint(other)
            .cylinder(Vector3::new(3.6, 1.3, 0.0), 0.2, 2.5);
        part.cuboid(
            Vector3::new(1.8, 1.6, 0.0),
            Vector3::new(0.5, 0.5, 0.6),
            0.4,
        );
        s.points
            .extend(part.points.iter().map(|p| Point3::from(at(p.coords))));
        s.colours.extend(part.colours);
    }
    s
}

/// `points` moved by `pose`, with Gaussian noise of `sigma` (metres) per coordinate and
/// `outlier_fraction` (of the result) random points in the bounding box, shuffled.
fn observe(
    points: &[Point3<f64>],
    pose: &Isometry3<f64>,
    sigma: f64,
    outlier_fraction: f64,
    seed: u64,
) -> Vec<Point3<f32>> {
    let colours = vec![[0.5; 3]; points.len()];
    observe_coloured(points, &colours, pose, sigma, outlier_fraction, seed).0
}

/// [`observe`] with colours: each point keeps its colour, outliers get random ones.
fn observe_coloured(
    points: &[Point3<f64>],
    colours: &[Rgb],
    pose: &Isometry3<f64>,
    sigma: f64,
    outlier_fraction: f64,
    seed: u64,
) -> (Vec<Point3<f32>>, Vec<Rgb>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut colour_rng = ChaCha8Rng::seed_from_u64(seed ^ 0xc010);
    let noise = Normal::new(0.0, sigma.max(1e-12)).unwrap();
    let (mut min, mut max) = (
        Vector3::repeat(f64::INFINITY),
        Vector3::repeat(f64::NEG_INFINITY),
    );
    for p in points {
        min = min.inf(&p.coords);
        max = max.sup(&p.coords);
    }
    let mut observed: Vec<(Point3<f64>, Rgb)> = points
        .iter()
        .zip(colours)
        .map(|(p, &c)| (p + Vector3::from_fn(|_, _| noise.sample(&mut rng)), c))
        .collect();
    let outliers = (points.len() as f64 * outlier_fraction / (1.0 - outlier_fraction)) as usize;
    for _ in 0..outliers {
        let p = Point3::from(Vector3::from_fn(|i, _| rng.random_range(min[i]..max[i])));
        observed.push((
            p,
            std::array::from_fn(|_| colour_rng.random_range(0.0..1.0)),
        ));
    }
    for i in (1..observed.len()).rev() {
        observed.swap(i, rng.random_range(0..=i));
    }
    observed
        .iter()
        .map(|(p, c)| ((pose * p).cast::<f32>(), *c))
        .unzip()
}

fn crop(points: &[Point3<f64>], keep: impl Fn(&Point3<f64>) -> bool) -> Vec<Point3<f64>> {
    points.iter().copied().filter(|p| keep(p)).collect()
}

/// [`crop`] of a scene, with the colours of the points kept.
fn crop_coloured(
    scene: &Scene,
    keep: impl Fn(&Point3<f64>) -> bool,
) -> (Vec<Point3<f64>>, Vec<Rgb>) {
    scene
        .points
        .iter()
        .zip(&scene.colours)
        .filter(|(p, _)| keep(p))
        .map(|(p, c)| (*p, *c))
        .unzip()
}

/// 120 degrees about the vertical, tilted by 15 and 10 degrees, 4.2 m away.
fn far_pose() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(3.5, -2.0, 1.0),
        UnitQuaternion::from_euler_angles(
            15f64.to_radians(),
            -10f64.to_radians(),
            120f64.to_radians(),
        ),
    )
}

fn errors(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> (f64, f64) {
    let error = estimate.inverse() * truth;
    (
        error.rotation.angle().to_degrees(),
        error.translation.vector.norm(),
    )
}

fn report(result: &MapRegistration) -> String {
    format!("{:?}\n{:#?}", result.verdict, result.scores)
}

/// The room's left part (source, in the room frame) and its right part seen from `truth`
/// (target), ~30 % of the smaller part in common, 1 cm noise, 20 % outliers.
fn overlapping_parts(truth: &Isometry3<f64>) -> (Vec<Point3<f32>>, Vec<Point3<f32>>) {
    let scene = room(1);
    let left = crop(&scene, |p| p.x < 3.9);
    let right = crop(&scene, |p| p.x > 2.7);
    let source = observe(&left, &Isometry3::identity(), 0.01, 0.2, 2);
    // target = truth * source-frame points.
    let target = observe(&right, truth, 0.01, 0.2, 3);
    (source, target)
}

#[test]
fn recovers_a_far_transform_from_thirty_percent_overlap() {
    let truth = far_pose();
    let (source, target) = overlapping_parts(&truth);
    let config = MapRegistrationConfig::default();
    let result = register_maps(&source, &target, &config);
    let (rotation_deg, translation_m) = errors(&result.target_from_source, &truth);
    assert!(result.is_accepted(), "{}", report(&result));
    assert!(
        rotation_deg < 1.0 && translation_m < 0.02,
        "off by {rotation_deg:.3} degrees, {translation_m:.4} m\n{}",
        report(&result)
    );
    let s = &result.scores;
    assert!(
        s.overlap_fraction > 0.2 && s.overlap_fraction < 0.6,
        "{}",
        report(&result)
    );
    assert!(s.ambiguity_ratio < 0.5, "{}", report(&result));
    // The covariance is finite and the estimate is within a few of its standard deviations
    // (optimistic: the test only asks for ten).
    let covariance = result.covariance().expect("an information matrix");
    assert!(covariance.iter().all(|v| v.is_finite()));
    assert!(
        s.translation_sigma_m < 0.01 && s.rotation_sigma_deg < 0.5,
        "{}",
        report(&result)
    );
}

#[test]
fn unrelated_maps_are_refused_with_a_reason() {
    let scene = room(1);
    let source = observe(
        &crop(&scene, |p| p.x < 3.9),
        &Isometry3::identity(),
        0.01,
        0.2,
        2,
    );
    let target = observe(&outdoor(5), &far_pose(), 0.01, 0.2, 3);
    let result = register_maps(&source, &target, &MapRegistrationConfig::default());
    let reason = result.verdict.clone().expect_err(&report(&result));
    assert!(!reason.to_string().is_empty());
    eprintln!("refused: {reason}");
}

#[test]
fn a_symmetric_room_is_refused_as_ambiguous() {
    let scene = symmetric_room(9);
    let source = observe(&scene, &Isometry3::identity(), 0.01, 0.0, 2);
    let target = observe(&scene, &far_pose(), 0.01, 0.0, 3);
    let result = register_maps(&source, &target, &MapRegistrationConfig::default());
    // Refused either by the correspondences (the runner-up nearly as well supported) or, when
    // both symmetric transforms are verified, because residual and overlap tie (no free-space
    // test here). Either way the other transform is one of the symmetries: a multiple of 90
    // degrees away.
    let rotation_deg = match &result.verdict {
        Err(MapRejection::Ambiguous { .. }) => result.scores.runner_up_rotation_deg,
        Err(MapRejection::Tied { rotation_deg, .. }) => *rotation_deg,
        _ => panic!("not refused as ambiguous: {}", report(&result)),
    };
    let quarters = rotation_deg / 90.0;
    assert!(
        (quarters - quarters.round()).abs() < 0.05 && quarters.round() >= 1.0,
        "{}",
        report(&result)
    );
}

#[test]
fn registration_is_deterministic() {
    let truth = far_pose();
    let (source, target) = overlapping_parts(&truth);
    let config = MapRegistrationConfig {
        max_points: 4000,
        ..MapRegistrationConfig::default()
    };
    let strip = |mut r: MapRegistration| {
        r.elapsed_ms = 0.0;
        r.scores.timings = Default::default();
        r
    };
    let first = strip(register_maps(&source, &target, &config));
    let second = strip(register_maps(&source, &target, &config));
    assert_eq!(first.target_from_source, second.target_from_source);
    // Compared as text: a tie's figures are NaN where a test was not run.
    assert_eq!(
        format!("{:?}", first.verdict),
        format!("{:?}", second.verdict)
    );
    assert_eq!(first.information, second.information);
    assert_eq!(
        serde_json::to_string(&first.scores).unwrap(),
        serde_json::to_string(&second.scores).unwrap()
    );
    // A too-small input is refused, not a panic.
    let tiny = &source[..10];
    let result = register_maps(tiny, &target, &config);
    assert!(matches!(
        result.verdict,
        Err(MapRejection::TooFewPoints { .. })
    ));
}

#[test]
fn the_configuration_is_validated() {
    let mut config = MapRegistrationConfig::default();
    assert_eq!(config.validate(), Ok(()));
    config.refine_distances_voxels = vec![1.0, 2.0];
    assert_eq!(
        config.validate().unwrap_err().0,
        "consensus.map_registration.refine_distances_voxels"
    );
    let config = MapRegistrationConfig {
        max_ambiguity_ratio: 1.5,
        ..Default::default()
    };
    assert_eq!(
        config.validate().unwrap_err().0,
        "consensus.map_registration.max_ambiguity_ratio"
    );
    let config = MapRegistrationConfig {
        voxel_m: 0.0,
        ..Default::default()
    };
    assert_eq!(
        config.validate().unwrap_err().0,
        "consensus.map_registration.voxel_m"
    );
    for (field, set) in [
        (
            "colour_weight",
            (|g| g.colour_weight = -1.0) as fn(&mut MapRegistrationConfig),
        ),
        ("colour_tolerance", |g| g.colour_tolerance = 0.0),
        ("min_colour_kappa", |g| g.min_colour_kappa = 1.5),
        ("min_colour_comparisons", |g| g.min_colour_comparisons = 0),
        ("colour_confirmed_overlap_fraction", |g| {
            g.colour_confirmed_overlap_fraction = -0.1
        }),
        ("colour_confirmed_kappa", |g| {
            g.colour_confirmed_kappa = f64::NAN
        }),
    ] {
        let mut config = MapRegistrationConfig::default();
        set(&mut config);
        assert_eq!(
            config.validate().unwrap_err().0,
            format!("consensus.map_registration.{field}")
        );
    }
}

#[test]
fn a_room_ambiguous_in_geometry_is_registered_by_its_colours() {
    // The four-fold symmetric room of the test above, each quarter painted its own colours; the
    // target seen with a darker exposure.
    let scene = coloured_symmetric_room(9);
    let truth = far_pose();
    let (source, source_colours) = observe_coloured(
        &scene.points,
        &scene.colours,
        &Isometry3::identity(),
        0.01,
        0.0,
        2,
    );
    let (target, target_colours) =
        observe_coloured(&scene.points, &scene.colours, &truth, 0.01, 0.0, 3);
    let target_colours: Vec<Rgb> = target_colours.iter().map(|c| c.map(|v| v * 0.6)).collect();
    let config = MapRegistrationConfig::default();
    let geometry_only = register_maps(&source, &target, &config);
    assert!(
        matches!(
            geometry_only.verdict,
            Err(MapRejection::Ambiguous { .. } | MapRejection::Tied { .. })
        ),
        "{}",
        report(&geometry_only)
    );
    let result = register_maps(
        MapPoints::coloured(&source, Some(&source_colours)),
        MapPoints::coloured(&target, Some(&target_colours)),
        &config,
    );
    assert!(result.is_accepted(), "{}", report(&result));
    let (rotation_deg, translation_m) = errors(&result.target_from_source, &truth);
    assert!(
        rotation_deg < 1.0 && translation_m < 0.02,
        "off by {rotation_deg:.3} degrees, {translation_m:.4} m\n{}",
        report(&result)
    );
    let s = &result.scores;
    assert!(s.colour && s.ambiguity_ratio < 0.5, "{}", report(&result));
    assert!(
        s.colour_agreement > 0.9 && s.colour_kappa > 0.8,
        "{}",
        report(&result)
    );
}

#[test]
fn an_overlap_whose_colours_disagree_is_refused() {
    // The overlapping room parts, registered by geometry alone (no colour in the descriptors):
    // with the same colours (the target brighter) the overlap agrees; with the target's colour
    // channels rotated (every surface another hue) it is refused.
    let truth = far_pose();
    let scene = coloured_room(1);
    let (left, left_colours) = crop_coloured(&scene, |p| p.x < 3.9);
    let (right, right_colours) = crop_coloured(&scene, |p| p.x > 2.7);
    let (source, source_colours) =
        observe_coloured(&left, &left_colours, &Isometry3::identity(), 0.01, 0.2, 2);
    let (target, target_colours) = observe_coloured(&right, &right_colours, &truth, 0.01, 0.2, 3);
    let config = MapRegistrationConfig {
        colour_weight: 0.0,
        ..MapRegistrationConfig::default()
    };
    let brighter: Vec<Rgb> = target_colours
        .iter()
        .map(|c| c.map(|v| (v * 1.3).min(1.0)))
        .collect();
    let agreeing = register_maps(
        MapPoints::coloured(&source, Some(&source_colours)),
        MapPoints::coloured(&target, Some(&brighter)),
        &config,
    );
    assert!(agreeing.is_accepted(), "{}", report(&agreeing));
    assert!(agreeing.scores.colour_kappa > 0.6, "{}", report(&agreeing));
    let rotated: Vec<Rgb> = target_colours.iter().map(|c| [c[2], c[0], c[1]]).collect();
    let result = register_maps(
        MapPoints::coloured(&source, Some(&source_colours)),
        MapPoints::coloured(&target, Some(&rotated)),
        &config,
    );
    let (rotation_deg, translation_m) = errors(&result.target_from_source, &truth);
    assert!(
        rotation_deg < 1.0 && translation_m < 0.02,
        "{}",
        report(&result)
    );
    let Err(MapRejection::ColourDisagreement {
        compared, kappa, ..
    }) = result.verdict
    else {
        panic!("{}", report(&result));
    };
    assert!(compared > 1000 && kappa < 0.15, "{}", report(&result));
}

#[test]
fn colours_of_one_map_only_are_not_used() {
    let truth = far_pose();
    let (source, target) = overlapping_parts(&truth);
    let config = MapRegistrationConfig {
        max_points: 4000,
        ..MapRegistrationConfig::default()
    };
    let strip = |mut r: MapRegistration| {
        r.elapsed_ms = 0.0;
        r.scores.timings = Default::default();
        r
    };
    let plain = strip(register_maps(&source, &target, &config));
    let colours = vec![[0.3f32, 0.6, 0.2]; source.len()];
    let one_side = strip(register_maps(
        MapPoints::coloured(&source, Some(&colours)),
        &target,
        &config,
    ));
    assert!(!one_side.scores.colour);
    // The same registration twice: G-ICP's sums are reduced in parallel, in an order that can
    // change their last bits, so numbers are compared to 9 significant digits.
    let rounded = |scores: &super::MapRegistrationScores| {
        let mut value = serde_json::to_value(scores).unwrap();
        round_numbers(&mut value);
        value
    };
    assert_eq!(rounded(&plain.scores), rounded(&one_side.scores));
    let moved = plain.target_from_source.inverse() * one_side.target_from_source;
    assert!(
        moved.translation.vector.norm() < 1e-9 && moved.rotation.angle() < 1e-9,
        "{moved:?}"
    );
    // Colours that are not one per point are ignored too.
    let wrong_length = strip(register_maps(
        MapPoints::coloured(&source, Some(&colours[1..])),
        MapPoints::coloured(&target, Some(&colours)),
        &config,
    ));
    assert!(!wrong_length.scores.colour);
}

/// Rounds every non-integer number in `value` to 9 significant digits.
fn round_numbers(value: &mut serde_json::Value) {
    match value {
        serde_json::Value::Number(number) if !number.is_i64() && !number.is_u64() => {
            let x = number.as_f64().unwrap_or(0.0);
            if x == 0.0 || !x.is_finite() {
                return;
            }
            let digits = 8 - x.abs().log10().floor() as i32;
            let scale = 10f64.powi(digits.clamp(-300, 300));
            *value = serde_json::json!((x * scale).round() / scale);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(round_numbers),
        serde_json::Value::Object(fields) => fields.values_mut().for_each(round_numbers),
        _ => {}
    }
}
