//! Unit tests of detection, description and matching.

use image::GrayImage;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::matching::two_nearest;
use super::patch::{draw_test_pairs, test_pairs};
use super::*;

#[test]
fn test_pairs_are_fixed_and_inside_the_patch_disc() {
    let a = test_pairs();
    assert_eq!(a, draw_test_pairs().as_slice());
    assert_eq!(a.len(), DESCRIPTOR_BITS);
    let radius = PATCH_RADIUS as f32;
    assert!(a.iter().all(|p| {
        p.p0 != p.p1
            && [p.p0, p.p1]
                .iter()
                .all(|[x, y]| x * x + y * y <= radius * radius)
    }));
}

#[test]
fn two_nearest_and_mutual_matching() {
    let d = |v: u128| [v, 0];
    assert_eq!(
        two_nearest(&d(0b1111), &[d(0), d(0b111), d(0b1)]),
        Some((1, 1, 3))
    );
    let config = AlignmentConfig {
        max_hamming_distance: 10,
        ..AlignmentConfig::default()
    };
    let features = |values: &[u128]| Features {
        camera_points: vec![Point3::origin(); values.len()],
        descriptors: values.iter().map(|&v| d(v)).collect(),
        keypoints: Vec::new(),
        detected: values.len(),
    };
    // 0 <-> 0 is exact and unambiguous; u128::MAX has no partner within 10 bits.
    let source = features(&[0, u128::MAX]);
    let target = features(&[0, 0xffff_ffff]);
    assert_eq!(match_features(&source, &target, &config), vec![(0, 0)]);
}

/// Random 3x3-pixel blocks: plenty of corners with distinct surroundings.
fn blocky_texture(width: u32, height: u32) -> RgbImage {
    use rand::RngExt;
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let blocks: Vec<u8> = (0..(width * height) as usize)
        .map(|_| rng.random_range(0..=255))
        .collect();
    RgbImage::from_fn(width, height, |x, y| {
        let v = blocks[((y / 3) * width + x / 3) as usize];
        image::Rgb([v, v, v])
    })
}

#[test]
fn keypoints_of_a_shifted_view_match_their_originals() {
    let (width, height, shift) = (240u32, 180u32, (7u32, 4u32));
    let texture = blocky_texture(width + shift.0, height + shift.1);
    let source_image = image::imageops::crop_imm(&texture, 0, 0, width, height).to_image();
    let target_image =
        image::imageops::crop_imm(&texture, shift.0, shift.1, width, height).to_image();
    let mut depth = DepthImage::new(width, height);
    depth.data.fill(2.0);
    let k = Intrinsics::new(200.0, 200.0, 119.5, 89.5, width, height);
    let config = AlignmentConfig::default();
    let source = extract(&source_image, &depth, &k, &config);
    let target = extract(&target_image, &depth, &k, &config);
    assert!(source.len() > 100 && target.len() > 100);
    let matches = match_features(&source, &target, &config);
    // The target camera sees the same plane moved by the shift in pixels.
    let offset = nalgebra::Vector3::new(
        shift.0 as f64 * 2.0 / k.fx,
        shift.1 as f64 * 2.0 / k.fy,
        0.0,
    );
    let correct = matches
        .iter()
        .filter(|(i, j)| {
            (source.camera_points[*i] - offset - target.camera_points[*j]).norm() < 0.02
        })
        .count();
    assert!(
        matches.len() >= 50 && correct * 10 >= matches.len() * 9,
        "{correct} of {} matches correct",
        matches.len()
    );
}

/// Correct matches between `source` and `target` when a source keypoint at level-0 pixel
/// `p` should be found at `map(p)` in the target (within 1.5 pixels), and all matches.
fn correct_matches(
    source: &Features,
    target: &Features,
    config: &AlignmentConfig,
    map: impl Fn(f64, f64) -> (f64, f64),
) -> (usize, usize) {
    let matches = match_features(source, target, config);
    let correct = matches
        .iter()
        .filter(|&&(i, j)| {
            let (u, v) = map(source.keypoints[i].u, source.keypoints[i].v);
            let (tu, tv) = (target.keypoints[j].u, target.keypoints[j].v);
            (u - tu).hypot(v - tv) <= 1.5
        })
        .count();
    (correct, matches.len())
}

#[test]
fn steered_descriptors_match_a_view_turned_by_90_degrees() {
    // The camera rolled by 90 degrees about its optical axis: the image turns clockwise,
    // pixel (x, y) moves to (height - 1 - y, x).
    let (width, height) = (240u32, 180u32);
    let source_image = blocky_texture(width, height);
    let target_image = image::imageops::rotate90(&source_image);
    let mut depth = DepthImage::new(width, height);
    depth.data.fill(2.0);
    let mut turned_depth = DepthImage::new(height, width);
    turned_depth.data.fill(2.0);
    let k = Intrinsics::new(200.0, 200.0, 119.5, 89.5, width, height);
    let turned_k = Intrinsics::new(200.0, 200.0, 89.5, 119.5, height, width);
    let turn = |u: f64, v: f64| (height as f64 - 1.0 - v, u);
    for radius in [0.0, 0.08] {
        let steered = AlignmentConfig {
            descriptor_radius_m: radius,
            ..AlignmentConfig::default()
        };
        let unsteered = AlignmentConfig {
            steer_descriptors: false,
            ..steered.clone()
        };
        let count = |config: &AlignmentConfig| {
            let source = extract(&source_image, &depth, &k, config);
            let target = extract(&target_image, &turned_depth, &turned_k, config);
            correct_matches(&source, &target, config, turn)
        };
        let (correct, all) = count(&steered);
        let (unsteered_correct, _) = count(&unsteered);
        eprintln!(
            "patch radius {radius} m: steered {correct} of {all} correct, unsteered {unsteered_correct}"
        );
        assert!(
            correct >= 100 && correct * 10 >= all * 8,
            "patch radius {radius} m: {correct} of {all} matches correct"
        );
        assert!(unsteered_correct * 4 < correct);
    }
}

#[test]
fn keypoints_spread_over_the_image() {
    // Strong texture in the left quarter, faint texture elsewhere.
    let (width, height) = (320u32, 240u32);
    let texture = blocky_texture(width, height);
    let image = RgbImage::from_fn(width, height, |x, y| {
        let v = texture.get_pixel(x, y).0[0];
        let v = if x < width / 4 { v } else { 100 + v / 8 };
        image::Rgb([v, v, v])
    });
    let mut depth = DepthImage::new(width, height);
    depth.data.fill(2.0);
    let k = Intrinsics::new(260.0, 260.0, 159.5, 119.5, width, height);
    let in_strong_part = |cell_px: u32| {
        let config = AlignmentConfig {
            keypoint_cell_px: cell_px,
            features_per_image: 300,
            ..AlignmentConfig::default()
        };
        let features = extract(&image, &depth, &k, &config);
        let strong = features
            .keypoints
            .iter()
            .filter(|p| p.u < (width / 4) as f64)
            .count();
        strong as f64 / features.len() as f64
    };
    let (spread, strongest_first) = (in_strong_part(32), in_strong_part(0));
    eprintln!("in the textured quarter: {spread:.2} spread, {strongest_first:.2} strongest first");
    assert!(strongest_first > 0.9 && spread < 0.5);
}

#[test]
fn one_corner_per_blob() {
    let mut image = GrayImage::new(80, 80);
    for y in 30..50 {
        for x in 30..50 {
            image.put_pixel(x, y, image::Luma([200]));
        }
    }
    image.put_pixel(60, 60, image::Luma([255]));
    let corners = local_maxima(&image, 20);
    assert!(!corners.is_empty());
    for (a, &(xa, ya, _)) in corners.iter().enumerate() {
        for &(xb, yb, _) in &corners[a + 1..] {
            assert!(xa.abs_diff(xb) > 1 || ya.abs_diff(yb) > 1, "{corners:?}");
        }
    }
    // The four corners of the square and the single bright pixel, nothing else.
    assert!(corners.len() <= 5 * 2, "{corners:?}");
}

#[test]
fn depth_must_be_valid_and_smooth() {
    let mut depth = DepthImage::new(5, 5);
    depth.data.fill(2.0);
    let config = AlignmentConfig::default();
    assert_eq!(reliable_depth(&depth, 2, 2, &config), Some(2.0));
    assert_eq!(
        reliable_depth(&depth, 0, 2, &config),
        None,
        "window leaves the image"
    );
    depth.data[3 * 5 + 3] = 2.5; // a depth edge next to the centre
    assert_eq!(reliable_depth(&depth, 2, 2, &config), None);
    depth.data[3 * 5 + 3] = 0.0; // a hole
    assert_eq!(reliable_depth(&depth, 2, 2, &config), None);
}
