//! G-ICP against known transforms, rival guesses, thread-count independence and failures.

use super::correspondences::POINTS_PER_TASK;
use super::*;
use crate::kdtree::PointTree;
use nalgebra::{Translation3, UnitQuaternion};

const EPSILON: f64 = 1e-3;
const NEIGHBOURS: usize = 10;

/// Points on three orthogonal walls of a room corner (2 cm grid, shifted by `phase` of a grid
/// step): the smallest scene that pins down all six degrees of freedom.
fn corner(phase: f32) -> Vec<Point3<f32>> {
    let step = 0.02f32;
    let cells = 40;
    let mut points = Vec::new();
    for i in 0..cells {
        for j in 0..cells {
            let (a, b) = ((i as f32 + phase) * step, (j as f32 + phase) * step);
            points.push(Point3::new(a, b, 0.0));
            points.push(Point3::new(a, 0.0, b + step));
            points.push(Point3::new(0.0, a + step, b + step));
        }
    }
    // Seen from a camera 1.5 m away, so coordinates look like a camera-frame cloud.
    points
        .into_iter()
        .map(|p| p + nalgebra::Vector3::new(-0.4, -0.4, 1.5))
        .collect()
}

fn with_covariances(points: Vec<Point3<f32>>) -> PointTree {
    PointTree::with_covariances(PointCloud::from_positions(points), NEIGHBOURS, EPSILON).unwrap()
}

fn params(max_correspondence_m: f64) -> GicpParams {
    GicpParams {
        max_correspondence_m,
        ..GicpParams::tracking(&TrackingConfig::default(), &KeyframeConfig::default())
    }
}

/// Target = `truth` applied to a differently sampled corner, so G-ICP must find `truth`.
fn source_and_target(truth: &Isometry3<f64>) -> (PointTree, PointTree) {
    let source = with_covariances(corner(0.0));
    let target = with_covariances(
        corner(0.5)
            .iter()
            .map(|p| (truth * p.cast::<f64>()).cast::<f32>())
            .collect(),
    );
    (source, target)
}

fn assert_close(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) {
    let error = estimate.inverse() * truth;
    let translation_mm = error.translation.vector.norm() * 1e3;
    let rotation_deg = error.rotation.angle().to_degrees();
    assert!(
        translation_mm < 1.0 && rotation_deg < 0.05,
        "off by {translation_mm:.3} mm, {rotation_deg:.4} deg"
    );
}

/// The first search's sampled count is exactly `count_correspondences`'s at the initial
/// guess (so choosing between guesses does not change), for a kd-tree and a voxel-map
/// target and for sample steps that do and do not divide the points per task: a rival with
/// that many matches loses a tie it does not win and the result is `register`'s; a rival
/// with one more, or a tie it wins, wins.
#[test]
fn a_rival_guess_is_judged_by_the_first_search_as_by_count_correspondences() {
    let truth = Isometry3::from_parts(
        Translation3::new(0.012, -0.008, 0.01),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
    );
    let (source, tree) = source_and_target(&truth);
    let voxels = crate::voxel_map::VoxelMap::from_cloud(tree.cloud(), 0.06);
    let params = params(0.02);
    let initial = Isometry3::identity();
    let targets: [&dyn RegistrationTarget; 2] = [&tree, &voxels];
    for (t, target) in targets.into_iter().enumerate() {
        for sample_step in [1, 3, 4] {
            let matches =
                count_correspondences(source.cloud(), target, &initial, 0.02, sample_step);
            assert!(
                matches > 0 && matches < source.len().div_ceil(sample_step),
                "target {t}, step {sample_step}: {matches} matches, want some but not all"
            );
            let tied = RivalGuess {
                sample_step,
                matches,
                wins_ties: false,
            };
            let kept =
                register_unless_outscored(source.cloud(), target, &initial, &params, Some(tied))
                    .expect("a tie goes to the initial guess");
            let plain = register(source.cloud(), target, &initial, &params);
            assert_eq!(kept.target_from_source, plain.target_from_source);
            assert_eq!(kept.iterations, plain.iterations);
            let better = RivalGuess {
                matches: matches + 1,
                ..tied
            };
            let tie_to_rival = RivalGuess {
                wins_ties: true,
                ..tied
            };
            for (rival, why) in [(better, "more matches"), (tie_to_rival, "a tie it wins")] {
                assert!(
                    register_unless_outscored(
                        source.cloud(),
                        target,
                        &initial,
                        &params,
                        Some(rival)
                    )
                    .is_none(),
                    "target {t}, step {sample_step}: a rival with {why} wins"
                );
            }
        }
    }
}

#[test]
fn recovers_a_known_transform() {
    let truth = Isometry3::from_parts(
        Translation3::new(0.012, -0.008, 0.01),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
    );
    let (source, target) = source_and_target(&truth);
    let result = register(
        source.cloud(),
        &target,
        &Isometry3::identity(),
        &params(0.05),
    );
    assert!(result.is_success(), "{:?}", result.failure);
    assert!(result.converged && result.iterations <= 64);
    assert_close(&result.target_from_source, &truth);
    assert!(
        result.inlier_fraction() > 0.9,
        "{}",
        result.inlier_fraction()
    );
    assert!(result.overlap_fraction > 0.9 && result.error.is_finite());
}

#[test]
fn the_result_does_not_depend_on_the_thread_count() {
    // 4800 points: five chunks of POINTS_PER_TASK, which rayon may combine in any tree.
    let truth = Isometry3::from_parts(
        Translation3::new(0.012, -0.008, 0.01),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
    );
    let (source, target) = source_and_target(&truth);
    assert!(source.len() > 4 * POINTS_PER_TASK);
    let with_threads = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                register(
                    source.cloud(),
                    &target,
                    &Isometry3::identity(),
                    &params(0.05),
                )
            })
    };
    let bits = |result: &RegistrationResult| {
        result
            .target_from_source
            .to_homogeneous()
            .iter()
            .map(|v| v.to_bits())
            .chain([result.error.to_bits()])
            .collect::<Vec<_>>()
    };
    let one = bits(&with_threads(1));
    for threads in [2, 3, 4] {
        for _ in 0..3 {
            assert_eq!(bits(&with_threads(threads)), one, "{threads} threads");
        }
    }
}

#[test]
fn coarse_to_fine_converges_from_ten_centimetres_and_five_degrees() {
    let truth = Isometry3::from_parts(
        Translation3::new(0.06, -0.05, 0.065),
        UnitQuaternion::from_scaled_axis(
            nalgebra::Vector3::new(1.0, -2.0, 1.5).normalize() * 5f64.to_radians(),
        ),
    );
    assert!(truth.translation.vector.norm() > 0.099);
    let (source, target) = source_and_target(&truth);
    let at_identity = |distance_m: f64| {
        register(
            source.cloud(),
            &target,
            &Isometry3::identity(),
            &params(distance_m),
        )
    };
    let coarse_to_fine_giving_up_below = |fraction: f64| {
        register_coarse_to_fine(
            source.cloud(),
            &target,
            &Isometry3::identity(),
            &[0.1, 0.05, 0.02],
            &params(0.02),
            fraction,
        )
    };
    let fine_only = at_identity(0.02);
    let coarse_to_fine = coarse_to_fine_giving_up_below(0.0);
    assert!(coarse_to_fine.is_success(), "{:?}", coarse_to_fine.failure);
    // Giving up below a fraction no stage reaches stops after the first stage.
    let first_stage = at_identity(0.1);
    let given_up = coarse_to_fine_giving_up_below(1.01);
    assert_eq!(given_up.iterations, first_stage.iterations);
    assert!(given_up.iterations < coarse_to_fine.iterations);
    assert_close(&coarse_to_fine.target_from_source, &truth);
    // The fine distance alone cannot bridge 10 cm: the coarse stages are what make it work.
    let fine_error = (fine_only.target_from_source.inverse() * truth)
        .translation
        .vector
        .norm();
    assert!(!fine_only.is_success() || fine_error > 0.01, "{fine_error}");
}

#[test]
fn degenerate_input_is_a_classified_failure() {
    let target = with_covariances(corner(0.0));
    let initial = Isometry3::translation(0.1, 0.2, 0.3);
    let p = params(0.02);
    // Empty source, and an all-NaN depth image (which yields no points).
    let empty = register(&PointCloud::default(), &target, &initial, &p);
    assert!(matches!(
        empty.failure,
        Some(RegistrationFailure::TooFewSourcePoints { found: 0, .. })
    ));
    assert_eq!(empty.target_from_source, initial);
    let k = geometry::camera::Intrinsics::new(50.0, 50.0, 15.5, 11.5, 32, 24);
    let mut nan_depth = geometry::depth::DepthImage::new(32, 24);
    nan_depth.data.fill(f32::NAN);
    let from_nan = crate::points_from_depth(&nan_depth, &k, 1, 10.0);
    assert!(!register(&from_nan, &target, &initial, &p).is_success());
    // Fewer than six points.
    let five = with_covariances(corner(0.0)[..5].to_vec());
    assert!(matches!(
        register(five.cloud(), &target, &initial, &p).failure,
        Some(RegistrationFailure::TooFewSourcePoints { found: 5, .. })
    ));
    // Missing covariances, empty target.
    let bare = PointCloud::from_positions(corner(0.0));
    assert_eq!(
        register(&bare, &target, &initial, &p).failure,
        Some(RegistrationFailure::MissingSourceCovariances)
    );
    let source = with_covariances(corner(0.0));
    let nothing = PointTree::new(Vec::new()).unwrap();
    assert!(matches!(
        register(source.cloud(), &nothing, &initial, &p).failure,
        Some(RegistrationFailure::TooFewTargetPoints { found: 0, .. })
    ));
    // A target out of reach: no correspondences, and the initial guess comes back untouched.
    let far = register(
        source.cloud(),
        &target,
        &Isometry3::translation(5.0, 0.0, 0.0),
        &p,
    );
    assert!(matches!(
        far.failure,
        Some(RegistrationFailure::TooFewCorrespondences { .. })
    ));
    assert_eq!(
        far.target_from_source,
        Isometry3::translation(5.0, 0.0, 0.0)
    );
    // Non-finite covariances (corrupted input) never produce a pose.
    let mut corrupted = source.cloud().clone();
    corrupted.covariances.fill(Covariance([f32::NAN; 6]));
    let result = register(&corrupted, &target, &Isometry3::identity(), &p);
    assert!(!result.is_success() && result.target_from_source == Isometry3::identity());
}
