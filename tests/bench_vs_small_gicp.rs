//! The parts of scripts/bench_vs_small_gicp.sh that need neither PyPI nor small_gicp: the point
//! dump of `bench tracking --dump-points` as scripts/small_gicp_odometry.py reads it, the driver's
//! TUM writer as our reader reads it, and the side-by-side report. They need python3 (standard
//! library only), which the script itself needs too.

use std::path::Path;
use std::process::{Command, Output};

use geometry::trajectory::Trajectory;
use nalgebra::Matrix3;

const DRIVER: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/scripts/small_gicp_odometry.py"
);

fn python(args: &[&str]) -> Output {
    Command::new("python3")
        .args(args)
        .output()
        .expect("running python3 (scripts/bench_vs_small_gicp.sh needs it)")
}

/// Runs `code` with the driver importable as `driver`; `args` are its `sys.argv[1:]`.
fn python_with_driver(code: &str, args: &[&str]) -> Output {
    let program = format!(
        "import importlib.util, sys\n\
         spec = importlib.util.spec_from_file_location('driver', {DRIVER:?})\n\
         driver = importlib.util.module_from_spec(spec)\n\
         spec.loader.exec_module(driver)\n\
         {code}"
    );
    Command::new("python3")
        .arg("-c")
        .arg(program)
        .args(args)
        .output()
        .expect("running python3 (scripts/bench_vs_small_gicp.sh needs it)")
}

fn succeeded(out: &Output) -> String {
    assert!(
        out.status.success(),
        "failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout.clone()).unwrap()
}

#[test]
fn dumped_points_are_the_trackers_and_the_driver_reads_them() {
    let dir = tempfile::tempdir().unwrap();
    let dump = dir.path().join("points");
    let out = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args([
            "bench",
            "tracking",
            "--dataset",
            "synthetic:agents=1,agent=0,frames=4,width=160,height=120",
            "--frames",
            "0..4",
            "--json",
            "--dump-points",
            dump.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_str(&succeeded(&out)).unwrap();
    let frames = report["frames"].as_u64().unwrap() as usize;
    assert_eq!(frames, 4);

    // The driver's reader: every frame, in order, each file whole x y z triples.
    let listed = succeeded(&python_with_driver(
        "import array\n\
         for stamp, path in driver.read_frames_index(sys.argv[1]):\n\
         \x20   floats = array.array('f', open(path, 'rb').read())\n\
         \x20   assert len(floats) % 3 == 0, path\n\
         \x20   print(stamp, len(floats) // 3, min(floats[2::3]))\n",
        &[dump.to_str().unwrap()],
    ));
    let rows: Vec<(f64, usize, f64)> = listed
        .lines()
        .map(|line| {
            let f: Vec<&str> = line.split(' ').collect();
            (
                f[0].parse().unwrap(),
                f[1].parse().unwrap(),
                f[2].parse().unwrap(),
            )
        })
        .collect();
    assert_eq!(rows.len(), frames);
    assert!(rows.windows(2).all(|w| w[0].0 < w[1].0), "{listed}");
    // The same points the tracker counted, in front of the camera.
    let total: usize = rows.iter().map(|r| r.1).sum();
    let per_frame = report["points_per_frame"].as_f64().unwrap();
    assert!((total as f64 / frames as f64 - per_frame).abs() < 1e-9);
    assert!(rows.iter().all(|r| r.1 > 100 && r.2 > 0.0), "{listed}");
}

#[test]
fn driver_tum_rotations_read_back_as_written() {
    // Rotations that take each branch of the matrix-to-quaternion conversion (trace > 0, and each
    // diagonal element largest near 180 degrees).
    let dir = tempfile::tempdir().unwrap();
    let tum = dir.path().join("t.tum");
    let printed = succeeded(&python_with_driver(
        "import math, json\n\
         def axis_angle(axis, angle):\n\
         \x20   x, y, z = axis; n = math.sqrt(x*x + y*y + z*z); x, y, z = x/n, y/n, z/n\n\
         \x20   c, s, t = math.cos(angle), math.sin(angle), 1 - math.cos(angle)\n\
         \x20   return [[t*x*x + c, t*x*y - s*z, t*x*z + s*y],\n\
         \x20           [t*x*y + s*z, t*y*y + c, t*y*z - s*x],\n\
         \x20           [t*x*z - s*y, t*y*z + s*x, t*z*z + c]]\n\
         cases = [((0.3, -0.5, 0.8), 0.4), ((1, 0.1, 0), 3.1), ((0.1, 1, 0.05), 3.0), ((0, 0.2, 1), 3.13)]\n\
         with open(sys.argv[1], 'w') as out:\n\
         \x20   for i, (axis, angle) in enumerate(cases):\n\
         \x20       r = axis_angle(axis, angle)\n\
         \x20       pose = [r[0] + [0.5 * i], r[1] + [-1.0], r[2] + [2.0], [0, 0, 0, 1]]\n\
         \x20       out.write(driver.tum_line(f'{i / 30:.6f}', pose) + '\\n')\n\
         \x20       print(json.dumps(r))\n",
        &[tum.to_str().unwrap()],
    ));
    let read = Trajectory::read_tum(&tum).unwrap();
    assert_eq!(read.len(), 4);
    for (i, (line, pose)) in printed.lines().zip(&read.poses).enumerate() {
        let rows: Vec<Vec<f64>> = serde_json::from_str(line).unwrap();
        let expected = Matrix3::from_fn(|r, c| rows[r][c]);
        let got = pose.rotation.to_rotation_matrix().into_inner();
        assert!(
            (got - expected).abs().max() < 1e-12,
            "case {i}: {got} vs {expected}"
        );
        assert!((pose.translation.vector.x - 0.5 * i as f64).abs() < 1e-12);
    }
}

fn write(path: &Path, text: &str) {
    std::fs::write(path, text).unwrap();
}

#[test]
fn report_tabulates_medians_over_repeats_and_the_ratio_to_each_configuration() {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs");
    std::fs::create_dir(&runs).unwrap();
    let run = |name: &str, ms: f64, p90: f64, ate_m: f64| {
        write(
            &runs.join(format!("{name}.json")),
            &format!(
                r#"{{"frames": 300, "points_per_frame": 11000.0, "tracking_ms_median": {ms},
                "tracking_ms_p90": {p90}, "points_ms_median": 3.0, "registration_ms_median": 6.0,
                "map_update_ms_median": 0.5, "iterations_median": 4.0}}"#
            ),
        );
        write(
            &runs.join(format!("{name}.ate.json")),
            &format!(
                r#"{{"rmse": {ate_m}, "mean": 0.0, "median": 0.0, "max": 0.0, "pairs": 300}}"#
            ),
        );
    };
    // Medians over three repeats: ours 10 ms (p90 14), small_gicp 8 ms (p90 20); the outlier
    // repeats do not move them.
    run("ours-r1", 10.0, 14.0, 0.021);
    run("ours-r2", 30.0, 40.0, 0.021);
    run("ours-r3", 9.0, 13.0, 0.021);
    run("small_gicp-voxel0.05-r1", 8.0, 20.0, 0.031);
    run("small_gicp-voxel0.05-r2", 7.0, 19.0, 0.031);
    run("small_gicp-voxel0.05-r3", 50.0, 60.0, 0.031);
    let json = dir.path().join("summary.json");
    let figures_input = dir.path().join("figures-input.json");
    let table = succeeded(&python(&[
        DRIVER,
        "report",
        "--runs",
        runs.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
        "--context",
        r#"{"frames": "0..300"}"#,
        "--figures",
        figures_input.to_str().unwrap(),
        "--label",
        "redkitchen 0..300",
    ]));
    assert!(
        table.lines().nth(1).unwrap().starts_with("ours "),
        "{table}"
    );
    assert!(table.contains("small_gicp-voxel0.05"), "{table}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(summary["context"]["frames"], "0..300");
    let ours = &summary["trackers"]["ours"];
    let theirs = &summary["trackers"]["small_gicp-voxel0.05"];
    assert_eq!(ours["repeats"], 3);
    assert_eq!(ours["tracking_ms_median"], 10.0);
    assert_eq!(ours["tracking_ms_p90"], 14.0);
    assert_eq!(theirs["tracking_ms_median"], 8.0);
    assert_eq!(theirs["ate_rmse_m"], 0.031);
    assert_eq!(theirs["tracking_ms_median_spread"][0], 7.0);
    assert_eq!(theirs["tracking_ms_median_spread"][1], 50.0);
    assert_eq!(theirs["ours_over_this_ms_median"], 10.0 / 8.0);
    assert_eq!(theirs["ours_over_this_ms_p90"], 14.0 / 20.0);

    // The headline figures, written into a docs/figures file by `bench record-figures`.
    let figures = dir.path().join("10_tracking.json");
    let out = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args([
            "bench",
            "record-figures",
            "--from",
            figures_input.to_str().unwrap(),
            "--command",
            "scripts/bench_vs_small_gicp.sh --frames 0..300 --repeats 3",
            "--figures",
            figures.to_str().unwrap(),
            "--figures-section",
            "2026-12-07: a test",
            "--machine",
            "a test machine",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    succeeded(&out);
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&figures).unwrap()).unwrap();
    let rows: Vec<(String, String, String)> = written
        .as_array()
        .unwrap()
        .iter()
        .map(|row| {
            assert_eq!(
                row["command"],
                "scripts/bench_vs_small_gicp.sh --frames 0..300 --repeats 3"
            );
            assert_eq!(row["machine"], "a test machine");
            assert_eq!(row["source_section"], "2026-12-07: a test");
            (
                row["name"].as_str().unwrap().to_string(),
                row["value"].to_string(),
                row["unit"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let expected = [
        ("tracking ATE, redkitchen 0..300 (median of 3)", "2.1", "cm"),
        (
            "tracking ATE of small_gicp (5 cm voxels), redkitchen 0..300 (median of 3)",
            "3.1",
            "cm",
        ),
        (
            "tracking time of ours / small_gicp (5 cm voxels), redkitchen 0..300 (medians of 3)",
            "1.25",
            "",
        ),
    ];
    assert_eq!(rows.len(), expected.len(), "{rows:?}");
    for ((name, value, unit), (want_name, want_value, want_unit)) in rows.iter().zip(expected) {
        assert_eq!((name.as_str(), unit.as_str()), (want_name, want_unit));
        // Written with two decimals ("2.10"), read back as the number.
        assert_eq!(
            value.parse::<f64>().unwrap(),
            want_value.parse::<f64>().unwrap()
        );
    }

    // A run without its ATE is an error naming the missing file.
    std::fs::remove_file(runs.join("ours-r2.ate.json")).unwrap();
    let out = python(&[DRIVER, "report", "--runs", runs.to_str().unwrap()]);
    assert!(!out.status.success());
    let message = String::from_utf8_lossy(&out.stderr);
    assert!(message.contains("ours-r2.ate.json"), "{message}");
}

#[test]
fn report_counts_real_failures_against_ground_truth_and_which_were_flagged() {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs");
    std::fs::create_dir(&runs).unwrap();
    // Ground truth: 12 frames 1 cm apart along x, 30 Hz.
    let tum = |offset: &dyn Fn(usize) -> f64| -> String {
        (0..12)
            .map(|i| {
                format!(
                    "{:.6} {} 0 0 0 0 0 1\n",
                    i as f64 / 30.0,
                    0.01 * i as f64 + offset(i)
                )
            })
            .collect()
    };
    let gt = dir.path().join("groundtruth.txt");
    write(&gt, &tum(&|_| 0.0));
    let run = |name: &str, trajectory: String, flagged: &str| {
        write(
            &runs.join(format!("{name}.json")),
            r#"{"frames": 12, "tracking_ms_median": 5.0, "tracking_ms_p90": 6.0}"#,
        );
        write(
            &runs.join(format!("{name}.ate.json")),
            r#"{"rmse": 0.01, "mean": 0.0, "median": 0.0, "max": 0.0, "pairs": 12}"#,
        );
        write(&runs.join(format!("{name}.tum")), &trajectory);
        write(&runs.join(format!("{name}.flagged.txt")), flagged);
    };
    run("ours-r1", tum(&|_| 0.0), "");
    // The peer jumps 20 cm at frame 5 without saying so, and 30 cm at frame 8, which it flags.
    let jumps = |i: usize| 0.2 * f64::from(u8::from(i >= 5)) + 0.3 * f64::from(u8::from(i >= 8));
    run("peer-r1", tum(&jumps), &format!("{:.6}\n", 8.0 / 30.0));
    let json = dir.path().join("summary.json");
    let table = succeeded(&python(&[
        DRIVER,
        "report",
        "--runs",
        runs.to_str().unwrap(),
        "--gt",
        gt.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]));
    assert!(
        table.contains("flagged") && table.contains("silent"),
        "{table}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let (ours, peer) = (&summary["trackers"]["ours"], &summary["trackers"]["peer"]);
    assert_eq!(ours["real_failures"], 0.0);
    assert_eq!(peer["real_failures"], 2.0);
    assert_eq!(peer["real_failures_unreported"], 1.0);
    assert_eq!(peer["failures_reported"], 1.0);
}
