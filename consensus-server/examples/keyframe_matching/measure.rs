//! The stage-by-stage measurement of one pair with one configuration: the truth the pair is
//! scored against, descriptor matching, repeatability per local rotation, scale and pyramid
//! level, the descriptor oracle, the keypoint spread and RANSAC's outcome.

use std::path::Path;
use std::time::Instant;

use config::AlignmentConfig;
use geometry::camera::Intrinsics;
use mac_consensus::alignment::{
    AlignmentResult, Keyframe, PreparedKeyframe, Verdict, align_prepared,
};
use mac_consensus::place_recognition::KeyframeRef;
use nalgebra::{Isometry3, Point2, Point3};
use registration::alignment::features::Features;
use registration::{GicpParams, register_coarse_to_fine};

use crate::descriptors::{DescriptorTable, Matching, Oracle};
use crate::dump;
use crate::pairs::{Pair, View, baseline, covisibility, depth_agrees, view_angle_deg};
use crate::repeatability::{Repeatability, buckets};
use crate::report::{PairReport, median};

/// Measures `pair` with `config` (see the example's documentation). `radius`: distance within
/// which two keypoints are the same 3-D point; `polish`: score against the ground truth polished
/// by G-ICP; `dump`: folder for the pair image.
pub fn measure(
    pair: &Pair,
    variant: &str,
    config: &AlignmentConfig,
    radius: f64,
    polish: bool,
    dump: Option<&Path>,
) -> PairReport {
    let clock = Instant::now();
    let target = PreparedKeyframe::new(keyframe(&pair.b, 1), config);
    let source = PreparedKeyframe::new(keyframe(&pair.a, 0), config);
    let prepare_ms = clock.elapsed().as_secs_f64() * 1e3 / 2.0;
    let clock = Instant::now();
    let result = align_prepared(&source, &target, config);
    let align_ms = clock.elapsed().as_secs_f64() * 1e3;

    let truth = Truth::of(pair, &source, &target, polish, radius);
    let table = DescriptorTable::new(truth.a, truth.b);
    let matching = Matching::of(&truth, &table, config);
    let repeat = Repeatability::of(&truth, &table, config);
    let oracle = Oracle::of(&truth, &table, config);
    let (clustered_a, grid_coverage_a) = spread(truth.a, &pair.a.intrinsics);
    if let Some(dir) = dump {
        dump::write_pair_image(dir, pair, variant, truth.a, truth.b, &repeat.status);
    }
    let (ransac_inliers, ransac_inliers_correct) = ransac_outcome(&result, &truth, config);
    let error = result.target_camera_from_source_camera.inverse() * truth.b_from_a;
    let mut orientation_errors = repeat.orientation_errors;
    PairReport {
        pair: pair.name.clone(),
        variant: variant.to_string(),
        baseline_m: baseline(&pair.a.world_from_camera, &pair.b.world_from_camera),
        view_angle_deg: view_angle_deg(&pair.a.world_from_camera, &pair.b.world_from_camera),
        covisibility: covisibility(&pair.a, &pair.b),
        truth_shift_cm: truth.shift_cm,
        polished_truth: truth.polished,
        detected: [truth.a.detected, truth.b.detected],
        lifted: [truth.a.len(), truth.b.len()],
        clustered_a,
        grid_coverage_a,
        covisible_a: repeat.covisible_a,
        oracle_described: oracle.described,
        oracle_median_hamming: oracle.median_hamming,
        oracle_wins: oracle.wins,
        nn_median_hamming: oracle.nn_median_hamming,
        repeatable: repeat.repeatable,
        nn_correct: repeat.nn_correct,
        top2_correct: repeat.top2_correct,
        median_orientation_error_deg: median(&mut orientation_errors).unwrap_or(f64::NAN),
        matches: matching.matches,
        match_distances_cm: matching.distances_cm,
        mutual_no_cap: matching.mutual_no_cap,
        mutual_ratio_08: matching.mutual_ratio_08,
        one_way_nn: matching.one_way_nn,
        by_rotation: buckets(
            repeat.by_rotation,
            &["<15", "15-30", "30-60", "60-90", ">90"],
        ),
        by_scale: buckets(repeat.by_scale, &["<1.25", "1.25-1.6", "1.6-2", ">2"]),
        by_level: repeat.by_level,
        ransac_inliers,
        ransac_inliers_correct,
        accepted: result.is_accepted(),
        verdict: match &result.verdict {
            Verdict::Accepted => "accepted".into(),
            Verdict::Rejected(reason) => reason.to_string(),
        },
        error_cm: error.translation.vector.norm() * 100.0,
        error_deg: error.rotation.angle().to_degrees(),
        prepare_ms,
        align_ms,
    }
}

fn keyframe(view: &View, agent: u32) -> Keyframe {
    Keyframe {
        id: KeyframeRef {
            agent_id: agent,
            keyframe_id: 0,
        },
        rgb: view.rgb.clone(),
        depth: view.depth.clone(),
        intrinsics: view.intrinsics,
        agent_from_camera: view.world_from_camera,
    }
}

/// The pair's keypoints under the truth: A's lifted keypoints moved into B's camera.
pub struct Truth<'p> {
    pub pair: &'p Pair,
    pub a: &'p Features,
    pub b: &'p Features,
    pub b_from_a: Isometry3<f64>,
    /// How far G-ICP moved the recorded truth (cm), and whether the moved pose scores.
    pub shift_cm: f64,
    pub polished: bool,
    pub moved: Vec<Point3<f64>>,
    pub radius: f64,
}

impl<'p> Truth<'p> {
    fn of(
        pair: &'p Pair,
        source: &'p PreparedKeyframe,
        target: &'p PreparedKeyframe,
        polish: bool,
        radius: f64,
    ) -> Self {
        let (fa, fb): (&Features, &Features) = (&source.view.features, &target.view.features);
        let recorded = pair.b.world_from_camera.inverse() * pair.a.world_from_camera;
        // Ground truth of real data is itself an estimate (KinectFusion tracking, cm-level drift
        // between distant frames): polish it with G-ICP from the truth and keep the polished pose
        // when G-ICP agrees with most of the overlap.
        let polished = register_coarse_to_fine(
            source.view.cloud.cloud(),
            &target.view.cloud,
            &recorded,
            &[0.05, 0.03, 0.02],
            &GicpParams {
                max_correspondence_m: 0.02,
                max_iterations: 64,
                rotation_epsilon_rad: 1e-5,
                translation_epsilon_m: 1e-5,
                overlap_distance_m: 0.02,
                min_inlier_fraction: 0.0,
            },
            0.0,
        );
        let shift = recorded.inverse() * polished.target_from_source;
        let truth_shift_cm = shift.translation.vector.norm() * 100.0;
        let use_polished = polish
            && polished.failure.is_none()
            && truth_shift_cm < 15.0
            && shift.rotation.angle().to_degrees() < 5.0;
        let b_from_a = if use_polished {
            polished.target_from_source
        } else {
            recorded
        };
        let moved: Vec<Point3<f64>> = fa.camera_points.iter().map(|p| b_from_a * p).collect();
        Self {
            pair,
            a: fa,
            b: fb,
            b_from_a,
            shift_cm: truth_shift_cm,
            polished: use_polished,
            moved,
            radius,
        }
    }

    /// Whether A's keypoint `i` and B's keypoint `j` are the same 3-D point.
    pub fn is_correct(&self, i: usize, j: usize) -> bool {
        (self.moved[i] - self.b.camera_points[j]).norm() < self.radius
    }

    /// Where B sees A's keypoint `i`, when B's depth agrees there.
    pub fn seen_in_b(&self, i: usize) -> Option<Point2<f64>> {
        let b = &self.pair.b;
        let pixel = b.intrinsics.project(&self.moved[i])?;
        (b.intrinsics.contains(&pixel)
            && depth_agrees(
                self.moved[i].z,
                b.depth.get(pixel.x.round() as u32, pixel.y.round() as u32) as f64,
            ))
        .then_some(pixel)
    }
}

/// Keypoint spread of A: keypoints with another on the same level within 2 pixels (scaled to
/// the level), and the fraction of an 8x6 image grid's cells holding one.
fn spread(fa: &Features, intrinsics: &Intrinsics) -> (usize, f64) {
    let mut clustered_a = 0;
    for (i, p) in fa.keypoints.iter().enumerate() {
        if fa.keypoints.iter().enumerate().any(|(k, q)| {
            k != i
                && q.level == p.level
                && (q.u - p.u).abs() <= 2.0 * (1.25f64).powi(p.level as i32)
                && (q.v - p.v).abs() <= 2.0 * (1.25f64).powi(p.level as i32)
        }) {
            clustered_a += 1;
        }
    }
    let (w, h) = (intrinsics.width as f64, intrinsics.height as f64);
    let mut cells = [false; 48];
    for p in &fa.keypoints {
        let cx = ((p.u / w * 8.0) as usize).min(7);
        let cy = ((p.v / h * 6.0) as usize).min(5);
        cells[cy * 8 + cx] = true;
    }
    (
        clustered_a,
        cells.iter().filter(|&&c| c).count() as f64 / 48.0,
    )
}

/// RANSAC's inliers, and how many of them the truth confirms.
fn ransac_outcome(
    result: &AlignmentResult,
    truth: &Truth<'_>,
    config: &AlignmentConfig,
) -> (usize, usize) {
    let Some(coarse) = &result.coarse else {
        return (0, 0);
    };
    // Recount correctness of the inliers of the final estimate against the truth: the coarse
    // estimate's inliers are the matches it places within the inlier distance.
    let (fa, fb) = (truth.a, truth.b);
    let estimate = result.target_camera_from_source_camera;
    let matched: Vec<(usize, usize)> =
        registration::alignment::features::match_features(fa, fb, config);
    let correct = matched
        .iter()
        .filter(|&&(i, j)| {
            (estimate * fa.camera_points[i] - fb.camera_points[j]).norm()
                <= config.ransac_inlier_distance_m
                && truth.is_correct(i, j)
        })
        .count();
    (coarse.inliers, correct)
}
