//! scripts/bench_render_against.sh in short form: the rounds, the driver sets and the report,
//! with the binary `cargo test` built standing in for both sides (`--rev-bin`, `--bin`), so
//! nothing is built. The comparison with a real earlier revision is a documented command
//! (docs/benchmarks.md).

use std::path::Path;
use std::process::{Command, Output};

fn script(args: &[&str], out: &Path) -> Output {
    Command::new("bash")
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/bench_render_against.sh"))
        .args(args)
        .env("XDG_RUNTIME_DIR", out)
        .output()
        .unwrap()
}

#[test]
fn both_sides_take_turns_on_each_driver_set_and_the_report_gives_medians_and_ratios() {
    let out = tempfile::tempdir().unwrap();
    let binary = env!("CARGO_BIN_EXE_mac-ego3d");
    let run = script(
        &[
            "--rev",
            "HEAD",
            "--rev-bin",
            binary,
            "--bin",
            binary,
            "--rounds",
            "2",
            "--repeats",
            "2",
            "--gaussians",
            "2000",
            "--sizes",
            "64x48",
            "--out",
            out.path().to_str().unwrap(),
        ],
        out.path(),
    );
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(stdout.contains("| system | 2000 | 64x48 |"), "{stdout}");

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["rev"], "HEAD");
    let provisioned = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("target/vulkan/icd.json")
        .exists();
    let expected: &[&str] = if provisioned {
        &["system", "provisioned", "rev system -> tree provisioned"]
    } else {
        &["system"]
    };
    let rows = summary["rows"].as_array().unwrap();
    let comparisons: Vec<&str> = rows
        .iter()
        .map(|row| row["comparison"].as_str().unwrap())
        .collect();
    assert_eq!(comparisons, expected, "{summary}");
    for row in rows {
        assert_eq!(
            (row["width"].as_u64(), row["height"].as_u64()),
            (Some(64), Some(48))
        );
        for metric in ["forward_ms", "iteration_ms"] {
            let figures = &row[metric];
            // Each side ran once per round; the median is one of the middle runs' span.
            for side in ["rev", "tree"] {
                let runs = figures[side]["runs"].as_array().unwrap();
                assert_eq!(runs.len(), 2, "{row}");
                let median = figures[side]["median"].as_f64().unwrap();
                let (low, high) = (runs[0].as_f64().unwrap(), runs[1].as_f64().unwrap());
                assert!(median >= low.min(high) && median <= low.max(high), "{row}");
            }
            let ratio = figures["ratio"].as_f64().unwrap();
            let expected_ratio = figures["tree"]["median"].as_f64().unwrap()
                / figures["rev"]["median"].as_f64().unwrap();
            assert!((ratio - expected_ratio).abs() < 1e-9, "{row}");
        }
    }
    // Every run's own report is kept beside the summary.
    let kept = std::fs::read_dir(out.path().join("runs"))
        .unwrap()
        .filter(|entry| {
            entry
                .as_ref()
                .unwrap()
                .path()
                .extension()
                .and_then(|e| e.to_str())
                == Some("json")
        })
        .count();
    assert_eq!(kept, 2 * 2 * if provisioned { 2 } else { 1 });
}

#[test]
fn a_revision_that_is_not_a_commit_is_named_in_the_error() {
    let out = tempfile::tempdir().unwrap();
    let run = script(
        &[
            "--rev",
            "no-such-revision-here",
            "--out",
            out.path().to_str().unwrap(),
        ],
        out.path(),
    );
    assert_eq!(run.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("no-such-revision-here is not a commit"),
        "{stderr}"
    );
}
