//! scripts/bench_map_levers.sh in short form: two of its rows on the first 20 frames of
//! redkitchen, with the binaries `cargo test --workspace` built (`--bin-dir`). Checks that each
//! row's run gets its overrides and that the table and the JSON report every row; the full table
//! is a documented command (docs/benchmarks.md).

mod common;

#[test]
fn real_data_map_levers_runs_each_row_with_its_overrides_and_reports_them() {
    let out = tempfile::tempdir().unwrap();
    let stdout = common::run_bench_script(
        "bench_map_levers.sh",
        &["--frames", "0..20", "--rows", "baseline,footprint_1.0"],
        out.path(),
    );
    for row in ["| baseline |", "| footprint_1.0 |"] {
        assert!(
            stdout.contains(row),
            "{row} missing from the table:\n{stdout}"
        );
    }

    // Each row's run used its own configuration: the override in one, the default in the other.
    let footprint = |row: &str| {
        config::Config::load(&out.path().join(row).join("1/config.toml"))
            .unwrap()
            .keyframes
            .footprint_sigma_per_spacing
    };
    assert_eq!(footprint("baseline"), 2.0);
    assert_eq!(footprint("footprint_1.0"), 1.0);

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap())
            .unwrap();
    let rows = summary["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{summary}");
    for (row, name) in rows.iter().zip(["baseline", "footprint_1.0"]) {
        assert_eq!(row["row"], name);
        let psnr = row["psnr"].as_f64().unwrap();
        // A map of two keyframes renders the first 20 frames far above noise (measured: ~24 dB).
        assert!(psnr > 15.0 && psnr < 40.0, "{name}: {row}");
        assert!(row["mapping_iters"].as_f64().unwrap() >= 100.0, "{row}");
    }
}
