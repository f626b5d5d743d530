//! End-to-end tests of the `mac-ego3d` command line: the binary is run as a user would run it.

use std::path::Path;
use std::process::{Command, Output};

mod common;

fn mac_ego3d(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args(args)
        .output()
        .expect("running mac-ego3d")
}

fn stdout_json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "command failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

#[test]
fn synth_then_dataset_info_and_ate_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("synthetic");
    let out_s = out.to_str().unwrap();
    let synth = mac_ego3d(&[
        "synth", "--agents", "2", "--frames", "6", "--width", "160", "--height", "120", "--out",
        out_s,
    ]);
    assert!(
        synth.status.success(),
        "{}",
        String::from_utf8_lossy(&synth.stderr)
    );

    let info = stdout_json(&mac_ego3d(&["dataset", "info", out_s, "--json"]));
    let agents = info.as_array().expect("one entry per agent");
    assert_eq!(agents.len(), 2);
    for agent in agents {
        assert_eq!(agent["frames"], 6);
        assert_eq!(agent["width"], 160);
        assert!(agent["depth_valid_fraction"].as_f64().unwrap() > 0.9);
        assert!(agent["trajectory_length_m"].as_f64().unwrap() > 0.0);
    }
    let ranged = stdout_json(&mac_ego3d(&[
        "dataset",
        "info",
        &format!("{out_s}/agent_1"),
        "--frames",
        "2..5",
        "--json",
    ]));
    assert_eq!(ranged["frames"], 3);
    assert_eq!(ranged["first_frame"], 2);

    // The written ground truth against itself: zero error, every pose paired.
    let gt = format!("{out_s}/agent_0/groundtruth_tum.txt");
    let ate = stdout_json(&mac_ego3d(&[
        "eval", "ate", "--gt", &gt, "--est", &gt, "--json",
    ]));
    assert_eq!(ate["pairs"], 6);
    assert!(ate["rmse"].as_f64().unwrap() < 1e-9);

    // Joint ATE over both agents: agents live in one world frame, so also zero.
    let gt1 = format!("{out_s}/agent_1/groundtruth_tum.txt");
    let joint = stdout_json(&mac_ego3d(&[
        "eval", "ate", "--gt", &gt, "--est", &gt, "--gt", &gt1, "--est", &gt1, "--json",
    ]));
    assert_eq!(joint["pairs"], 12);
    assert_eq!(joint["agents"].as_array().unwrap().len(), 2);

    // A decoded frame exported and compared with itself.
    let png = dir.path().join("f.png");
    let exported = mac_ego3d(&[
        "dataset",
        "frame",
        &format!("{out_s}/agent_0"),
        "--frame",
        "3",
        "--rgb",
        png.to_str().unwrap(),
    ]);
    assert!(
        exported.status.success(),
        "{}",
        String::from_utf8_lossy(&exported.stderr)
    );
    let q = stdout_json(&mac_ego3d(&[
        "eval",
        "image",
        "--reference",
        png.to_str().unwrap(),
        "--rendered",
        png.to_str().unwrap(),
        "--json",
    ]));
    assert_eq!(q["ssim"], 1.0);
    assert_eq!(q["ssim_valid"], 1.0);
}

#[test]
fn synthetic_spec_streams_without_files() {
    let info = stdout_json(&mac_ego3d(&[
        "dataset",
        "info",
        "synthetic:agents=2,agent=1,frames=4,width=160,height=120",
        "--json",
    ]));
    assert_eq!(info["frames"], 4);
    assert_eq!(info["height"], 120);
}

#[test]
fn bad_input_gives_a_clear_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.txt");
    let out = mac_ego3d(&[
        "eval",
        "ate",
        "--gt",
        missing.to_str().unwrap(),
        "--est",
        missing.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("missing.txt") && !err.contains("panicked"),
        "{err}"
    );

    let bad = dir.path().join("bad.txt");
    std::fs::write(&bad, "0 0 0 0 0 0 0 1\n1 0 0 zero 0 0 0 1\n").unwrap();
    let out = mac_ego3d(&[
        "eval",
        "ate",
        "--gt",
        bad.to_str().unwrap(),
        "--est",
        bad.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad.txt line 2"),
        "{err}"
    );

    let out = mac_ego3d(&["dataset", "info", dir.path().to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("unknown dataset layout"),
        "{err}"
    );

    let out = mac_ego3d(&["dataset", "info", "synthetic:agents=2,agnt=1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("agnt"), "{err}");
}

fn shared(relative: &str) -> String {
    common::shared_data(relative).to_string_lossy().into_owned()
}

#[test]
fn real_data_eval_ate_reproduces_evo() {
    let gt = shared("reference/tum-trajectories/freiburg1_xyz-groundtruth.txt");
    let est = shared("reference/tum-trajectories/freiburg1_xyz-rgbdslam.txt");
    let ate = stdout_json(&mac_ego3d(&[
        "eval", "ate", "--gt", &gt, "--est", &est, "--json",
    ]));
    assert_eq!(ate["pairs"], 785);
    assert!(
        (ate["rmse"].as_f64().unwrap() - 0.013470).abs() < 5e-7,
        "{ate}"
    );
    // Sim(3) can only lower the error; no alignment at all must raise it.
    let sim3 = stdout_json(&mac_ego3d(&[
        "eval", "ate", "--gt", &gt, "--est", &est, "--align", "sim3", "--json",
    ]));
    assert!(sim3["rmse"].as_f64().unwrap() <= ate["rmse"].as_f64().unwrap() + 1e-12);
    let none = stdout_json(&mac_ego3d(&[
        "eval", "ate", "--gt", &gt, "--est", &est, "--align", "none", "--json",
    ]));
    assert!(none["rmse"].as_f64().unwrap() > ate["rmse"].as_f64().unwrap());
}

#[test]
fn real_data_eval_lpips_reproduces_golden_values() {
    let weights = shared("weights/lpips/alexnet.npz");
    let reference = shared("weights/lpips/imgs/ex_ref.png");
    for (other, golden) in [("ex_p0.png", 0.722), ("ex_p1.png", 0.138)] {
        let img = shared(&format!("weights/lpips/imgs/{other}"));
        let v = stdout_json(&mac_ego3d(&[
            "eval",
            "lpips",
            &reference,
            &img,
            "--weights",
            &weights,
            "--json",
        ]));
        assert!(
            (v["lpips"].as_f64().unwrap() - golden).abs() < 5e-4,
            "{other}: {v}"
        );
    }
}

#[test]
fn real_data_redkitchen_reads_through_the_cli() {
    let dir = shared("datasets/7scenes-redkitchen");
    let info = stdout_json(&mac_ego3d(&[
        "dataset",
        "info",
        &dir,
        "--frames",
        "400..1000",
        "--samples",
        "5",
        "--json",
    ]));
    assert_eq!(info["frames"], 600);
    assert_eq!(info["first_frame"], 400);
    assert_eq!(info["width"], 640);
    assert_eq!(info["intrinsics"]["fx"], 585.0);
    let valid = info["depth_valid_fraction"].as_f64().unwrap();
    assert!(valid > 0.7 && valid < 1.0, "valid depth fraction {valid}");
    // The shared groundtruth_tum.txt uses timestamp = frame / 30: the reader's clock must match it.
    let whole = stdout_json(&mac_ego3d(&[
        "dataset",
        "info",
        &dir,
        "--samples",
        "1",
        "--json",
    ]));
    assert!(
        (whole["trajectory_length_m"].as_f64().unwrap() - 7.4).abs() < 0.1,
        "{whole}"
    );
}

#[test]
fn render_command_renders_a_saved_map() {
    use splats::GaussianCloud;
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map.ply");
    let mut cloud = GaussianCloud::default();
    // One wide, nearly opaque red Gaussian 2 m in front of a camera at the origin.
    cloud.push(
        [0.0, 0.0, 2.0],
        [0.5f32.ln(); 3],
        [1.0, 0.0, 0.0, 0.0],
        6.0,
        [0.9, 0.1, 0.1],
    );
    splats::ply::save_ply(&map, &cloud).unwrap();
    let rgb = dir.path().join("rgb.png");
    let depth = dir.path().join("depth.png");
    let out = mac_ego3d(&[
        "render",
        "--map",
        map.to_str().unwrap(),
        "--pose",
        "0 0 0 0 0 0 1",
        "--intrinsics",
        "50,50,31.5,23.5",
        "--size",
        "64x48",
        "--out-rgb",
        rgb.to_str().unwrap(),
        "--out-depth",
        depth.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rgb = image::open(&rgb).unwrap().to_rgb8();
    assert_eq!(rgb.dimensions(), (64, 48));
    let centre = rgb.get_pixel(32, 24).0;
    assert!(
        centre[0] > 150 && centre[1] < 60 && centre[2] < 60,
        "centre pixel {centre:?}"
    );
    let depth = image::open(&depth).unwrap().to_luma16();
    let centre_mm = depth.get_pixel(32, 24).0[0];
    assert!(
        (1950..=2050).contains(&centre_mm),
        "centre depth {centre_mm} mm"
    );

    let bad = mac_ego3d(&[
        "render",
        "--map",
        map.to_str().unwrap(),
        "--pose",
        "0 0 0 0 0 0 0",
        "--intrinsics",
        "50,50,31.5,23.5",
        "--out-rgb",
        "/tmp/x.png",
    ]);
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("quaternion"), "{err}");
    let missing = mac_ego3d(&[
        "render",
        "--map",
        "/nonexistent/map.ply",
        "--pose",
        "0 0 0 0 0 0 1",
        "--intrinsics",
        "50,50,31.5,23.5",
        "--out-rgb",
        "/tmp/x.png",
    ]);
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        !missing.status.success() && err.contains("map.ply") && !err.contains("panicked"),
        "{err}"
    );
}

#[test]
fn config_resolves_overrides_and_refuses_unknown_keys() {
    let dir = tempfile::tempdir().unwrap();
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/synthetic.toml");
    let out = dir.path().join("run.toml");
    let resolved = mac_ego3d(&[
        "config",
        "--config",
        base.to_str().unwrap(),
        "--set",
        "consensus.t_comm=25",
        "--set",
        "noise.target=depth",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        resolved.status.success(),
        "{}",
        String::from_utf8_lossy(&resolved.stderr)
    );
    // What was written loads as a configuration with the overrides and the file's own values.
    let config = config::Config::load(&out).unwrap();
    assert_eq!(config.consensus.t_comm, 25);
    assert!(config.noise.is_some());
    assert_eq!(
        config.tracking.pixel_stride, 5,
        "from configs/synthetic.toml"
    );
    let refused = mac_ego3d(&[
        "config",
        "--config",
        base.to_str().unwrap(),
        "--set",
        "consensus.tcomm=25",
    ]);
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("tcomm") && stderr.contains("synthetic.toml"),
        "{stderr}"
    );
    let malformed = mac_ego3d(&["config", "--set", "consensus.t_comm"]);
    assert!(!malformed.status.success());
    assert!(String::from_utf8_lossy(&malformed.stderr).contains("KEY=VALUE"));
}

#[test]
fn bench_render_json_has_every_case_with_its_peak_memory_and_workload() {
    let report = stdout_json(&mac_ego3d(&[
        "bench",
        "render",
        "--gaussians",
        "300,600",
        "--sizes",
        "64x48,32x24",
        "--repeats",
        "1",
        "--warmup",
        "0",
        "--workload",
        "--json",
    ]));
    let cases = report["cases"].as_array().expect("cases");
    let sizes: Vec<(u64, u64, u64)> = cases
        .iter()
        .map(|c| {
            (
                c["width"].as_u64().unwrap(),
                c["height"].as_u64().unwrap(),
                c["gaussians"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        sizes,
        [(64, 48, 300), (64, 48, 600), (32, 24, 300), (32, 24, 600)]
    );
    for case in cases {
        for key in ["forward_ms", "forward_backward_ms", "iteration_ms"] {
            assert!(case[key].as_f64().unwrap() > 0.0, "{key}: {case}");
        }
        // The map, its frame buffers and the optimiser state: more than nothing, far less
        // than the 128 MiB binding limit at these sizes.
        let peak = case["peak_device_mib"].as_f64().unwrap();
        assert!(peak > 0.0 && peak < 128.0, "peak_device_mib {peak}");
        let workload = case["workload"].as_array().expect("workload");
        assert!(!workload.is_empty());
        for layout in workload {
            let evaluations = layout["evaluations"].as_u64().unwrap();
            let visible = layout["visible_evaluations"].as_u64().unwrap();
            assert!(visible <= evaluations, "{layout}");
        }
        // With subgroups of one size (lavapipe: 8) the rate against the peak is known.
        let adapter = report["adapter"].as_str().unwrap();
        if adapter.contains("subgroups: true") {
            let rate = &case["rate"];
            assert!(
                rate["evaluations_per_second"].as_f64().unwrap() > 0.0,
                "{rate}"
            );
            assert!(rate["fraction_of_peak"].as_f64().unwrap() > 0.0, "{rate}");
        }
    }
    // One peak measurement per image size, every evaluation of it counted.
    let peaks = report["peak"].as_array().expect("peak");
    let peak_sizes: Vec<(u64, u64)> = peaks
        .iter()
        .map(|p| (p["width"].as_u64().unwrap(), p["height"].as_u64().unwrap()))
        .collect();
    assert_eq!(peak_sizes, [(64, 48), (32, 24)]);
    for peak in peaks {
        let tiles_64x48 = 4 * 3;
        let expected = if peak["width"] == 64 {
            tiles_64x48
        } else {
            2 * 2
        } * 256
            * 128;
        assert_eq!(peak["evaluations"].as_u64().unwrap(), expected, "{peak}");
        assert!(
            peak["evaluations_per_second"].as_f64().unwrap() > 0.0,
            "{peak}"
        );
    }
}
