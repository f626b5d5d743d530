//! scripts/bench_gpu.sh in short form, on whatever adapter the machine has (lavapipe in CI): the
//! kernel benchmark at one small scene and the real-time swarm over redkitchen 0..24 + 16..40 at
//! full mapping resolution, run from the binaries `cargo test --workspace` built (`--bin-dir`, the
//! way the script runs on a GPU machine without cargo). Checks that the runs use full resolution
//! and that the table and the JSON report them; the GPU figures are a documented command
//! (docs/benchmarks.md).

mod common;

#[test]
fn real_data_bench_gpu_runs_the_kernels_and_a_full_resolution_swarm_from_given_binaries() {
    let out = tempfile::tempdir().unwrap();
    let stdout = common::run_bench_script(
        "bench_gpu.sh",
        &[
            "--runs",
            "render,swarm_sensor",
            "--end",
            "40",
            "--gaussians",
            "2000",
        ],
        out.path(),
    );
    assert!(stdout.contains("swarm_sensor"), "{stdout}");

    let config = config::Config::load(&out.path().join("swarm_sensor/config.toml")).unwrap();
    assert_eq!(config.mapping.image_downscale, 1);

    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap())
            .unwrap();
    let rows = summary.as_array().unwrap();
    assert_eq!(rows.len(), 2, "{summary}");
    let render = &rows[0];
    assert_eq!(render["run"], "render");
    assert_eq!(render["exit"], 0, "{render}");
    let cases = render["bench_render"]["cases"].as_array().unwrap();
    // One scene size at the two default image sizes.
    assert_eq!(cases.len(), 2, "{render}");
    assert!(
        cases
            .iter()
            .all(|c| c["gaussians"] == 2000 && c["forward_ms"].as_f64().unwrap() > 0.0)
    );

    let swarm = &rows[1];
    assert_eq!(swarm["run"], "swarm_sensor");
    assert_eq!(swarm["exit"], 0, "{swarm}");
    // The merged map of two dozen frames per agent renders them far above noise.
    let psnr = swarm["psnr"].as_f64().unwrap();
    assert!(psnr > 15.0 && psnr < 45.0, "{swarm}");
    let dropped = swarm["frames_dropped"].as_array().unwrap();
    assert_eq!(dropped.len(), 2, "{swarm}");
    assert!(dropped.iter().all(|d| d.as_u64().is_some()), "{swarm}");
}
