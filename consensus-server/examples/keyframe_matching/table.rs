//! The report on stdout: a row per pair and variant (with `--verbose` the per-bucket detail
//! under it), then totals per variant.

use config::AlignmentConfig;

use crate::report::{Bucket, PairReport, median};

/// The column titles of [`print_row`].
pub fn print_header() {
    println!(
        "{:<30} {:<10} {:>5} {:>5} {:>5} {:>9} {:>9} {:>5} {:>4} {:>4} {:>5} {:>5} {:>4} {:>9} {:>9} {:>9} {:>9} {:>8} {:>4} {:>6} {:>6}",
        "pair",
        "variant",
        "base",
        "angle",
        "covis",
        "lifted",
        "covis/rep",
        "clust",
        "grid",
        "nn+",
        "top2",
        "ori",
        "",
        "matches",
        "no-cap",
        "ratio.8",
        "1-way",
        "ransac",
        "ok",
        "prep",
        "align"
    );
}

/// One pair and variant.
pub fn print_row(r: &PairReport) {
    println!(
        "{:<30} {:<10} {:>5.2} {:>5.0} {:>5.2} {:>4}/{:<4} {:>4}/{:<4} {:>5} {:>4.2} {:>4} {:>5} {:>5.0} {:>4} {:>4}/{:<4} {:>4}/{:<4} {:>4}/{:<4} {:>4}/{:<4} {:>3}/{:<4} {:>4} {:>6.0} {:>6.0}",
        r.pair,
        r.variant,
        r.baseline_m,
        r.view_angle_deg,
        r.covisibility,
        r.lifted[0],
        r.lifted[1],
        r.covisible_a,
        r.repeatable,
        r.clustered_a,
        r.grid_coverage_a,
        r.nn_correct,
        r.top2_correct,
        r.median_orientation_error_deg,
        "",
        r.matches.correct,
        r.matches.total,
        r.mutual_no_cap.correct,
        r.mutual_no_cap.total,
        r.mutual_ratio_08.correct,
        r.mutual_ratio_08.total,
        r.one_way_nn.correct,
        r.one_way_nn.total,
        r.ransac_inliers_correct,
        r.ransac_inliers,
        if r.accepted { "yes" } else { "no" },
        r.prepare_ms,
        r.align_ms
    );
}

/// Per-bucket detail of one pair and variant.
pub fn print_detail(r: &PairReport) {
    let show = |title: &str, buckets: &[Bucket]| {
        let cells: Vec<String> = buckets
            .iter()
            .map(|b| {
                format!(
                    "{}: {}/{} (h{})",
                    b.label, b.nn_correct, b.repeatable, b.median_true_hamming
                )
            })
            .collect();
        println!("    {title}: {}", cells.join("  "));
    };
    show("rotation nn+/rep", &r.by_rotation);
    show("scale    nn+/rep", &r.by_scale);
    let levels: Vec<String> = r
        .by_level
        .iter()
        .enumerate()
        .map(|(l, [rep, m, nn])| format!("L{l}: rep {rep} nn+ {nn} match+ {m}"))
        .collect();
    println!("    levels: {}", levels.join("  "));
    println!(
        "    oracle: {} described, median hamming {} (nearest real {}), {} would win",
        r.oracle_described, r.oracle_median_hamming, r.nn_median_hamming, r.oracle_wins
    );
    println!(
        "    match truth distances <2/2-3/3-5/5-10/>10 cm: {:?}",
        r.match_distances_cm
    );
    println!(
        "    verdict: {} (pose error {:.1} cm, {:.1} deg); truth polished by {:.1} cm: {}",
        r.verdict, r.error_cm, r.error_deg, r.truth_shift_cm, r.polished_truth
    );
}

/// Totals per variant: pairs accepted, repeatable keypoints, correct matches and the median
/// times.
pub fn print_totals(variants: &[(String, AlignmentConfig)], reports: &[PairReport]) {
    println!();
    println!(
        "{:<10} {:>6} {:>8} {:>9} {:>9} {:>12} {:>12} {:>9} {:>9} {:>9}",
        "variant",
        "pairs",
        "accepted",
        "repeat",
        "nn+",
        "match+/all",
        "ransac+",
        "prep ms",
        "align ms",
        "sum ms"
    );
    for (name, _) in variants {
        let rs: Vec<&PairReport> = reports.iter().filter(|r| &r.variant == name).collect();
        let sum = |f: &dyn Fn(&PairReport) -> usize| rs.iter().map(|r| f(r)).sum::<usize>();
        let mut prep: Vec<f64> = rs.iter().map(|r| r.prepare_ms).collect();
        let mut align: Vec<f64> = rs.iter().map(|r| r.align_ms).collect();
        let mut total: Vec<f64> = rs.iter().map(|r| 2.0 * r.prepare_ms + r.align_ms).collect();
        println!(
            "{:<10} {:>6} {:>8} {:>9} {:>9} {:>5}/{:<6} {:>12} {:>9.0} {:>9.0} {:>9.0}",
            name,
            rs.len(),
            sum(&|r| r.accepted as usize),
            sum(&|r| r.repeatable),
            sum(&|r| r.nn_correct),
            sum(&|r| r.matches.correct),
            sum(&|r| r.matches.total),
            sum(&|r| r.ransac_inliers_correct),
            median(&mut prep).unwrap_or(0.0),
            median(&mut align).unwrap_or(0.0),
            median(&mut total).unwrap_or(0.0),
        );
    }
}
