//! What the example reports per pair and variant (a table row, and JSON with `--json`).

use serde::Serialize;

/// Matches of one kind, and how many of them the truth confirms.
#[derive(Serialize, Default, Clone, Copy)]
pub struct Counted {
    pub total: usize,
    pub correct: usize,
}

/// Repeatable keypoints of one range of local rotation or scale change.
#[derive(Serialize, Default, Clone)]
pub struct Bucket {
    pub label: String,
    pub repeatable: usize,
    pub nn_correct: usize,
    pub median_true_hamming: u32,
}

/// Everything measured on one pair with one configuration variant.
#[derive(Serialize)]
pub struct PairReport {
    pub pair: String,
    pub variant: String,
    pub baseline_m: f64,
    pub view_angle_deg: f64,
    pub covisibility: f64,
    /// How far G-ICP moved the recorded ground truth (cm), and whether the moved pose scored.
    pub truth_shift_cm: f64,
    pub polished_truth: bool,
    pub detected: [usize; 2],
    pub lifted: [usize; 2],
    /// Lifted keypoints of A with another lifted keypoint of A within 2 px on the same level.
    pub clustered_a: usize,
    /// Fraction of 8x6 image cells holding a lifted keypoint of A.
    pub grid_coverage_a: f64,
    pub covisible_a: usize,
    /// Covisible keypoints of A described in B at their true place: how many could be,
    /// median Hamming distance to A's descriptor, how many would beat A's nearest real
    /// neighbour in B, and the median distance of that nearest neighbour.
    pub oracle_described: usize,
    pub oracle_median_hamming: u32,
    pub oracle_wins: usize,
    pub nn_median_hamming: u32,
    pub repeatable: usize,
    pub nn_correct: usize,
    pub top2_correct: usize,
    /// Orientation error (degrees) of repeatable pairs: median of |angle_B - angle_A - roll|.
    pub median_orientation_error_deg: f64,
    pub matches: Counted,
    /// The matches by their distance under the truth: <2, 2-3, 3-5, 5-10, >= 10 cm.
    pub match_distances_cm: [usize; 5],
    pub mutual_no_cap: Counted,
    pub mutual_ratio_08: Counted,
    pub one_way_nn: Counted,
    pub by_rotation: Vec<Bucket>,
    pub by_scale: Vec<Bucket>,
    /// Per level of A: repeatable keypoints and correct matches.
    pub by_level: Vec<[usize; 3]>,
    pub ransac_inliers: usize,
    pub ransac_inliers_correct: usize,
    pub accepted: bool,
    pub verdict: String,
    pub error_cm: f64,
    pub error_deg: f64,
    pub prepare_ms: f64,
    pub align_ms: f64,
}

/// An angle in degrees wrapped to (-180, 180].
pub fn wrap_deg(angle: f64) -> f64 {
    let a = angle.rem_euclid(360.0);
    if a > 180.0 { a - 360.0 } else { a }
}

/// The upper median (sorts `values`).
pub fn median<T: Copy + PartialOrd>(values: &mut [T]) -> Option<T> {
    values.sort_by(|a, b| a.partial_cmp(b).unwrap());
    values.get(values.len() / 2).copied()
}
