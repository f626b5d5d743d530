//! Scoring against ground truth, and the table and JSON of a run.

use std::collections::BTreeMap;

use metrics::stats::median;
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

use crate::cmd::bench::figures::Figure;
use crate::cmd::fmt_num;

/// Success thresholds against ground truth.
pub const SUCCESS_TRANSLATION_M: f64 = 0.05;
pub const SUCCESS_ROTATION_DEG: f64 = 2.0;

/// How far an estimate is from the truth: the rotation angle, and the distance between where
/// the two put the source map's centre (independent of where the source frame's origin lies).
pub fn errors(
    estimate: &Isometry3<f64>,
    truth: &Isometry3<f64>,
    source_centre: &Point3<f64>,
) -> (f64, f64) {
    (
        estimate.rotation.angle_to(&truth.rotation).to_degrees(),
        (estimate * source_centre - truth * source_centre).norm(),
    )
}

/// One method on one pair.
#[derive(Debug, Clone, Serialize)]
pub struct MethodRun {
    pub method: String,
    pub accepted: bool,
    /// Within the thresholds, whatever the verdict.
    pub correct: bool,
    /// Overlapping pairs: accepted and correct. Disjoint pairs: refused.
    pub success: bool,
    pub rotation_error_deg: f64,
    pub translation_error_m: f64,
    pub time_ms: f64,
    /// Why it refused (or could not run).
    pub reason: Option<String>,
    /// The method's own figures.
    pub details: serde_json::Value,
}

impl MethodRun {
    /// A run of `method` whose estimate is `estimate` (`None`: it could not run; `reason` says
    /// why), judged against `truth`.
    #[allow(clippy::too_many_arguments, reason = "a method run's figures")]
    pub fn judged(
        method: &str,
        estimate: Option<Isometry3<f64>>,
        accepted: bool,
        time_ms: f64,
        reason: Option<String>,
        details: serde_json::Value,
        truth: &Isometry3<f64>,
        source_centre: &Point3<f64>,
        disjoint: bool,
    ) -> Self {
        let (rotation_error_deg, translation_error_m) = match &estimate {
            Some(estimate) => errors(estimate, truth, source_centre),
            None => (f64::NAN, f64::NAN),
        };
        let accepted = accepted && estimate.is_some();
        let correct = !disjoint
            && rotation_error_deg <= SUCCESS_ROTATION_DEG
            && translation_error_m <= SUCCESS_TRANSLATION_M;
        Self {
            method: method.to_string(),
            accepted,
            correct,
            success: if disjoint {
                !accepted
            } else {
                accepted && correct
            },
            rotation_error_deg,
            translation_error_m,
            time_ms,
            reason,
            details,
        }
    }

    /// The verdict column of the per-pair lines.
    fn verdict(&self, disjoint: bool) -> &'static str {
        match (self.accepted, self.success, disjoint) {
            (false, true, _) => "refused",
            (false, false, _) if self.correct => "refused (right)",
            (false, false, _) => "refused",
            (true, true, _) => "ok",
            (true, false, true) => "MERGED",
            (true, false, false) => "WRONG",
        }
    }
}

/// One pair and every method's run on it.
#[derive(Debug, Serialize)]
pub struct PairRun {
    pub bin: String,
    pub pair: String,
    pub seed: u64,
    pub disjoint: bool,
    pub true_overlap: f64,
    pub source_points: usize,
    pub target_points: usize,
    pub methods: Vec<MethodRun>,
}

/// A method's figures over one bin.
#[derive(Debug, Serialize)]
pub struct BinSummary {
    pub bin: String,
    pub method: String,
    pub pairs: usize,
    pub successes: usize,
    pub success_rate: f64,
    pub accepted: usize,
    /// Accepted but wrong (on disjoint pairs: any acceptance).
    pub wrong: usize,
    /// Within the thresholds whatever the verdict.
    pub correct: usize,
    /// Medians over the accepted, correct runs.
    pub median_rotation_error_deg: f64,
    pub median_translation_error_m: f64,
    pub median_time_ms: f64,
    pub p90_time_ms: f64,
}

fn percentile(values: &[f64], q: f64) -> f64 {
    let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted.sort_by(f64::total_cmp);
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Per bin and method, in the order bins and methods first appear.
pub fn summarise(runs: &[PairRun]) -> Vec<BinSummary> {
    let mut order: Vec<(String, String)> = Vec::new();
    let mut groups: BTreeMap<(String, String), Vec<&MethodRun>> = BTreeMap::new();
    for run in runs {
        for m in &run.methods {
            let key = (run.bin.clone(), m.method.clone());
            if !groups.contains_key(&key) {
                order.push(key.clone());
            }
            groups.entry(key).or_default().push(m);
        }
    }
    order
        .into_iter()
        .map(|key| {
            let group = &groups[&key];
            let good: Vec<&&MethodRun> = group.iter().filter(|m| m.success && m.correct).collect();
            let successes = group.iter().filter(|m| m.success).count();
            let times: Vec<f64> = group.iter().map(|m| m.time_ms).collect();
            BinSummary {
                pairs: group.len(),
                successes,
                success_rate: successes as f64 / group.len().max(1) as f64,
                accepted: group.iter().filter(|m| m.accepted).count(),
                wrong: group.iter().filter(|m| m.accepted && !m.success).count(),
                correct: group.iter().filter(|m| m.correct).count(),
                median_rotation_error_deg: median(
                    &good
                        .iter()
                        .map(|m| m.rotation_error_deg)
                        .collect::<Vec<_>>(),
                )
                .unwrap_or(f64::NAN),
                median_translation_error_m: median(
                    &good
                        .iter()
                        .map(|m| m.translation_error_m)
                        .collect::<Vec<_>>(),
                )
                .unwrap_or(f64::NAN),
                median_time_ms: median(&times).unwrap_or(f64::NAN),
                p90_time_ms: percentile(&times, 0.9),
                bin: key.0,
                method: key.1,
            }
        })
        .collect()
}

/// The line of one pair: its overlap, then each method's verdict, errors and time.
pub fn pair_line(run: &PairRun) -> String {
    let mut line = format!(
        "  {:<10} {:>6} {:>5} {:>13}",
        run.bin,
        run.pair,
        fmt_num(run.true_overlap * 100.0, 0),
        format!("{}/{}", run.source_points, run.target_points)
    );
    for m in &run.methods {
        line += &format!(
            " | {} {} {}deg {}cm {}ms",
            m.method,
            m.verdict(run.disjoint),
            fmt_num(m.rotation_error_deg, 1),
            fmt_num(m.translation_error_m * 100.0, 1),
            fmt_num(m.time_ms, 0)
        );
    }
    if let Some(ours) = run.methods.first()
        && !ours.success
        && let Some(reason) = &ours.reason
    {
        line += &format!("\n      {}: {reason}", ours.method);
    }
    line
}

/// The summary table.
pub fn print_summary(summaries: &[BinSummary]) {
    println!(
        "  {:<12} {:<9} {:>5} {:>14} {:>8} {:>6} {:>8} {:>8} {:>9} {:>16}",
        "bin",
        "method",
        "pairs",
        "success",
        "accepted",
        "wrong",
        "correct",
        "rot deg",
        "trans cm",
        "time ms (p90)"
    );
    for s in summaries {
        println!(
            "  {:<12} {:<9} {:>5} {:>14} {:>8} {:>6} {:>8} {:>8} {:>9} {:>16}",
            s.bin,
            s.method,
            s.pairs,
            format!("{} ({}%)", s.successes, fmt_num(s.success_rate * 100.0, 0)),
            s.accepted,
            s.wrong,
            s.correct,
            fmt_num(s.median_rotation_error_deg, 2),
            fmt_num(s.median_translation_error_m * 100.0, 1),
            format!(
                "{} ({})",
                fmt_num(s.median_time_ms, 0),
                fmt_num(s.p90_time_ms, 0)
            )
        );
    }
}

/// What `--figures` records, per method: the successes in each bin (in the order run) and the
/// wrong transforms accepted over all pairs.
pub fn headline_figures(summaries: &[BinSummary], label: &str) -> Vec<Figure> {
    let mut methods: Vec<&str> = Vec::new();
    let mut bins: Vec<&str> = Vec::new();
    for summary in summaries {
        if !methods.contains(&summary.method.as_str()) {
            methods.push(&summary.method);
        }
        if !bins.contains(&summary.bin.as_str()) {
            bins.push(&summary.bin);
        }
    }
    let mut figures = Vec::new();
    for method in methods {
        let rows: Vec<&BinSummary> = summaries.iter().filter(|s| s.method == method).collect();
        let successes: Vec<String> = rows
            .iter()
            .map(|s| format!("{}/{}", s.successes, s.pairs))
            .collect();
        figures.push(Figure::text(
            format!("{label}: successes per bin ({}), {method}", bins.join(", ")),
            successes.join("; "),
            "",
        ));
        let pairs: usize = rows.iter().map(|s| s.pairs).sum();
        let wrong: usize = rows.iter().map(|s| s.wrong).sum();
        figures.push(Figure::text(
            format!("{label}: wrong transforms accepted of {pairs} pairs, {method}"),
            wrong.to_string(),
            "",
        ));
    }
    figures
}
