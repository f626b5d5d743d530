//! ROS 2 bags, end to end. The bags are written by an independent tool, the `rosbags` package from
//! PyPI (scripts/ros2/dataset_to_bag.py, in the peers' virtual environment), from the shared
//! TUM fr1/rpy and redkitchen folders, in MCAP and sqlite3 storage, raw and compressed. The agent
//! (paced) must place the frames of a bag exactly where it places the frames of the folder they
//! came from; damaged bags must be named and what came before the damage kept.
//!
//! Without PyPI (scripts/peers_venv.sh exits 3) these tests say so and pass, except under CI
//! (CI=true), where they fail.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::{peers_python, shared_data, workspace_binary};

const REPO: &str = env!("CARGO_MANIFEST_DIR");

/// Writes `dataset`'s `frames` as a bag at `out` with the converter's `options`.
fn write_bag(python: &Path, dataset: &Path, frames: &str, out: &Path, options: &[&str]) {
    let run = Command::new(python)
        .arg(Path::new(REPO).join("scripts/ros2/dataset_to_bag.py"))
        .arg("--dataset")
        .arg(dataset)
        .args(["--frames", frames])
        .arg("--out")
        .arg(out)
        .args(options)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "dataset_to_bag.py {options:?}: {}",
        String::from_utf8_lossy(&run.stderr)
    );
}

/// A configuration that maps little (the ATE is tracking's) with the paced loop, plus `extra`,
/// written as `dir/<name>.toml`.
fn light_config(dir: &Path, name: &str, extra: &str) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(
        &path,
        format!("[mapping]\npace = \"paced\"\niterations_per_keyframe = 2\n{extra}"),
    )
    .unwrap();
    path
}

/// `mac-agent --standalone` (paced) on `dataset`; its output and its metrics.json.
fn run_agent(dataset: &str, config: &Path, out: &Path) -> (Output, serde_json::Value) {
    let run = Command::new(workspace_binary("mac-agent"))
        .args(["--standalone", "--renders", "0", "--eval-every", "1000"])
        .args(["--pace", "paced", "--decode-workers", "2"])
        .arg("--config")
        .arg(config)
        .args(["--dataset", dataset])
        .arg("--out")
        .arg(out)
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let metrics = std::fs::read_to_string(out.join("metrics.json"))
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or(serde_json::Value::Null);
    (run, metrics)
}

fn log(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Runs the agent on a folder range and on bags of it; every bag's ATE is within `tolerance_m`
/// of the folder's, with as many frames.
fn assert_bags_replay_like_the_folder(
    work: &Path,
    folder_spec: &str,
    bags: &[(&str, PathBuf, f64)],
    config: &Path,
) -> f64 {
    let (run, folder) = run_agent(
        folder_spec,
        config,
        &work.join(format!("out-folder-for-{}", bags[0].0)),
    );
    assert!(run.status.success(), "{}", log(&run));
    let folder_ate = folder["ate_rmse_m"].as_f64().unwrap();
    for (name, bag, tolerance_m) in bags {
        let (run, metrics) = run_agent(
            bag.to_str().unwrap(),
            config,
            &work.join(format!("out-{name}")),
        );
        assert!(run.status.success(), "{name}: {}", log(&run));
        assert_eq!(metrics["frames"], folder["frames"], "{name}");
        let ate = metrics["ate_rmse_m"].as_f64().unwrap();
        eprintln!("{folder_spec}: folder ATE {folder_ate:.5} m, {name} {ate:.5} m");
        assert!(
            (ate - folder_ate).abs() <= *tolerance_m,
            "{name}: ATE {ate} m against the folder's {folder_ate} m"
        );
    }
    folder_ate
}

/// Reads an agent's ros2_bag with rosbags and compares its path with trajectory.tum; prints
/// `tf N, path N, map rgb`.
const OUTPUT_BAG_CHECK: &str = r##"
import sys
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
store = get_typestore(Stores.ROS2_HUMBLE)
rows = [l.split() for l in open(sys.argv[2]) if l.strip() and not l.startswith("#")]
tf = path = 0
fields = []
with Reader(sys.argv[1]) as reader:
    for connection, _, raw in reader.messages():
        message = store.deserialize_cdr(raw, connection.msgtype)
        if connection.topic == "/tf":
            tf += len(message.transforms)
            assert message.transforms[0].child_frame_id == "agent0/camera_optical_frame"
        elif connection.topic == "/agent0/path":
            path = len(message.poses)
            assert path == len(rows), (path, len(rows))
            for pose, row in zip(message.poses, rows):
                p = pose.pose.position
                stamp = pose.header.stamp.sec + pose.header.stamp.nanosec * 1e-9
                assert abs(stamp - float(row[0])) < 1e-6, (stamp, row)
                assert max(abs(p.x - float(row[1])), abs(p.y - float(row[2])), abs(p.z - float(row[3]))) < 1e-6
        elif connection.topic == "/agent0/map":
            assert message.width > 1000 and message.point_step == 16, message.width
            fields = [f.name for f in message.fields]
print(f"tf {tf}, path {path}, map {fields[3]}")
"##;

#[test]
fn real_data_bags_replay_like_their_folders() {
    let Some(python) = peers_python() else {
        return;
    };
    let work = tempfile::tempdir().unwrap();
    // Both shared sequences store colour as JPEG. A raw bag holds the pixels the converter's
    // decoder (Pillow) made, which differ from the image crate's by a few levels on some
    // pixels, so tracking's photometric term sees slightly different images; the depth is the
    // same. Raw bags are therefore compared with depth-only tracking (the default), which must
    // agree exactly; the compressed bag carries the dataset's own JPEG bytes and is compared
    // with the photometric term turned on.
    let depth_only = light_config(
        work.path(),
        "depth-only",
        "[tracking.photometric]\nweight = 0.0\n",
    );
    let config = light_config(
        work.path(),
        "photometric",
        "[tracking.photometric]\nweight = 0.3\n",
    );

    // TUM fr1/rpy: raw colour + 32FC1 depth (as TUM's own bags) reproduce the folder's frames
    // exactly, in both storages. The depth has its own CameraInfo (the Kinect's registration
    // pinhole), the colour a plumb_bob lens.
    let tum = shared_data("datasets/tum-fr1-rpy");
    let tum_mcap = work.path().join("tum-raw-mcap");
    let tum_sqlite = work.path().join("tum-raw-sqlite");
    write_bag(&python, &tum, "0..60", &tum_mcap, &["--storage", "mcap"]);
    write_bag(
        &python,
        &tum,
        "0..60",
        &tum_sqlite,
        &["--storage", "sqlite3"],
    );
    assert_bags_replay_like_the_folder(
        work.path(),
        &format!("{}:0..60", tum.display()),
        &[
            ("tum-raw-mcap", tum_mcap.clone(), 0.001),
            ("tum-raw-sqlite", tum_sqlite, 0.001),
        ],
        &depth_only,
    );

    // redkitchen: raw (16UC1 millimetres) and compressed (its own JPEG bytes, compressedDepth
    // PNG) hold the folder's pixels exactly.
    let kitchen = shared_data("datasets/7scenes-redkitchen");
    let kitchen_sqlite = work.path().join("kitchen-raw-sqlite");
    let kitchen_compressed = work.path().join("kitchen-compressed-mcap");
    write_bag(
        &python,
        &kitchen,
        "200..260",
        &kitchen_sqlite,
        &["--storage", "sqlite3"],
    );
    write_bag(
        &python,
        &kitchen,
        "200..260",
        &kitchen_compressed,
        &["--storage", "mcap", "--images", "compressed"],
    );
    let kitchen_range = format!("{}:200..260", kitchen.display());
    assert_bags_replay_like_the_folder(
        work.path(),
        &kitchen_range,
        &[("kitchen-raw-sqlite", kitchen_sqlite, 0.001)],
        &depth_only,
    );
    assert_bags_replay_like_the_folder(
        work.path(),
        &kitchen_range,
        &[("kitchen-compressed-mcap", kitchen_compressed.clone(), 0.001)],
        &config,
    );

    // The agent's ROS 2 outputs, read by rosbags: the path is trajectory.tum, a tf per placed
    // frame, the map as a coloured PointCloud2.
    let out = work.path().join("out-kitchen-compressed-mcap");
    let check = Command::new(&python)
        .arg("-c")
        .arg(OUTPUT_BAG_CHECK)
        .arg(out.join("ros2_bag"))
        .arg(out.join("trajectory.tum"))
        .output()
        .unwrap();
    assert!(check.status.success(), "{}", log(&check));
    let summary = String::from_utf8_lossy(&check.stdout);
    assert!(summary.contains("tf 60, path 60, map rgb"), "{summary}");

    // dataset info: counts, rates and the topics it would use.
    let info = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args(["dataset", "info", "--json", "--samples", "2"])
        .arg(&kitchen_compressed)
        .output()
        .unwrap();
    assert!(info.status.success(), "{}", log(&info));
    let info: serde_json::Value = serde_json::from_slice(&info.stdout).unwrap();
    assert_eq!(info["frames"], 60);
    assert_eq!(info["ground_truth_poses"], 60);
    let bag = &info["bag"];
    assert_eq!(
        bag["uses"]["colour_topic"],
        "/camera/camera/color/image_raw/compressed"
    );
    assert_eq!(
        bag["uses"]["depth_topic"],
        "/camera/camera/aligned_depth_to_color/image_raw/compressedDepth"
    );
    assert_eq!(bag["uses"]["ground_truth"], "/gt_pose");
    for topic in bag["topics"].as_array().unwrap() {
        assert_eq!(topic["count"], 60, "{topic}");
        let rate = topic["rate_hz"].as_f64().unwrap();
        assert!((rate - 30.0).abs() < 0.1, "{topic}");
    }

    // Ground truth from tf (a named child frame) is the same ground truth, and a frame range
    // selects pair numbers as on folders.
    let tf_config = light_config(
        work.path(),
        "tf",
        "[ros2]\nground_truth = \"tf:gt_camera\"\n",
    );
    let (run, from_tf) = run_agent(
        &format!("{}:10..50", tum_mcap.display()),
        &tf_config,
        &work.path().join("out-tf"),
    );
    assert!(run.status.success(), "{}", log(&run));
    // The same tracking as the tf run's (depth only, the default): only the ground truth's
    // source differs.
    let (run, from_pose) = run_agent(
        &format!("{}:10..50", tum_mcap.display()),
        &depth_only,
        &work.path().join("out-pose"),
    );
    assert!(run.status.success(), "{}", log(&run));
    assert_eq!(from_tf["frames"], 40);
    let (a, b) = (
        from_tf["ate_rmse_m"].as_f64().unwrap(),
        from_pose["ate_rmse_m"].as_f64().unwrap(),
    );
    assert!((a - b).abs() < 1e-6, "tf {a} against PoseStamped {b}");
}

#[test]
fn real_data_damaged_bags_are_named_and_what_came_before_is_kept() {
    let Some(python) = peers_python() else {
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let config = light_config(work.path(), "light", "");
    let kitchen = shared_data("datasets/7scenes-redkitchen");

    // A message of the wrong type and an unknown encoding: those frames are skipped, each named
    // once by topic and message index, the rest tracked.
    let bad = work.path().join("bad-messages");
    write_bag(
        &python,
        &kitchen,
        "0..20",
        &bad,
        &["--corrupt", "wrong-type:5", "--corrupt", "encoding:8"],
    );
    let (run, metrics) = run_agent(bad.to_str().unwrap(), &config, &work.path().join("out-bad"));
    let text = log(&run);
    assert!(run.status.success(), "{text}");
    assert_eq!(metrics["frames"], 18, "{text}");
    assert_eq!(metrics["frames_broken"], 2, "{text}");
    for (index, why) in [(5, "of another type"), (8, "\"yuv422\"")] {
        let named = format!("/camera/camera/color/image_raw message {index}:");
        let lines: Vec<&str> = text.lines().filter(|l| l.contains(&named)).collect();
        assert_eq!(lines.len(), 1, "{named} once:\n{text}");
        assert!(lines[0].contains(why), "{}", lines[0]);
    }

    // A bag cut short: MCAP keeps the frames before the cut, and says where it broke.
    let cut = work.path().join("cut-mcap");
    write_bag(&python, &kitchen, "0..40", &cut, &["--storage", "mcap"]);
    let file = cut.join("cut-mcap.mcap");
    let length = std::fs::metadata(&file).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&file)
        .unwrap()
        .set_len(length * 6 / 10)
        .unwrap();
    let (run, metrics) = run_agent(cut.to_str().unwrap(), &config, &work.path().join("out-cut"));
    let text = log(&run);
    assert!(run.status.success(), "{text}");
    let frames = metrics["frames"].as_u64().unwrap();
    assert!((20..40).contains(&frames), "{frames} frames before the cut");
    let damage = metrics["dataset_damage"].as_str().unwrap();
    assert!(
        damage.contains("cut-mcap.mcap") && damage.contains("cut short"),
        "{damage}"
    );
    assert!(metrics["ate_rmse_m"].as_f64().unwrap() < 0.05, "{metrics}");

    // sqlite3 cut short where SQLite keeps its tables cannot be read at all: one clear error.
    let cut_sqlite = work.path().join("cut-sqlite");
    write_bag(
        &python,
        &kitchen,
        "0..20",
        &cut_sqlite,
        &["--storage", "sqlite3"],
    );
    let file = cut_sqlite.join("cut-sqlite.db3");
    let length = std::fs::metadata(&file).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&file)
        .unwrap()
        .set_len(length / 2)
        .unwrap();
    let (run, _) = run_agent(
        cut_sqlite.to_str().unwrap(),
        &config,
        &work.path().join("out-cut-sqlite"),
    );
    let text = log(&run);
    assert!(!run.status.success());
    assert!(
        text.contains("cut-sqlite.db3") && text.contains("damaged"),
        "{text}"
    );

    // No CameraInfo: refused, naming the topic it looked for.
    let no_info = work.path().join("no-info");
    write_bag(&python, &kitchen, "0..5", &no_info, &["--no-camera-info"]);
    let (run, _) = run_agent(
        no_info.to_str().unwrap(),
        &config,
        &work.path().join("out-no-info"),
    );
    let text = log(&run);
    assert!(!run.status.success());
    assert!(
        text.contains("/camera/camera/color/camera_info") && text.contains("CameraInfo"),
        "{text}"
    );
}

#[test]
fn real_data_a_swarm_runs_on_ranges_of_a_bag() {
    let Some(python) = peers_python() else {
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let runtime = tempfile::tempdir().unwrap();
    let kitchen = shared_data("datasets/7scenes-redkitchen");
    let bag = work.path().join("kitchen");
    write_bag(
        &python,
        &kitchen,
        "0..200",
        &bag,
        &["--images", "compressed"],
    );
    let out = work.path().join("swarm");
    let run = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .arg("swarm")
        .arg("--config")
        .arg(Path::new(REPO).join("configs/7scenes.toml"))
        .args(["--agent", &format!("{}:0..120", bag.display())])
        .args(["--agent", &format!("{}:80..200", bag.display())])
        .args(["--render-every", "1000"])
        .arg("--out")
        .arg(&out)
        .env("XDG_RUNTIME_DIR", runtime.path())
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}\n{}",
        log(&run),
        common::log_tails(&out, 20)
    );
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(
        metrics["agents_not_linked"],
        serde_json::json!([]),
        "{metrics}"
    );
    let joint = metrics["ate_joint_rmse_m"].as_f64().unwrap();
    assert!(joint <= 0.05, "joint ATE {joint} m");
    for k in 0..2 {
        assert!(
            out.join(format!("agent_{k}/ros2_bag/metadata.yaml"))
                .is_file()
        );
    }
    // The consensus's bag, read by rosbags: both agents' frames placed in the world, their
    // world paths as agent_K.tum, the merged map.
    let check = Command::new(&python)
        .arg("-c")
        .arg(CONSENSUS_BAG_CHECK)
        .arg(out.join("ros2_bag"))
        .arg(&out)
        .output()
        .unwrap();
    assert!(check.status.success(), "{}", log(&check));
    assert_eq!(
        String::from_utf8_lossy(&check.stdout).trim(),
        "agent0/odom agent1/odom, paths 2, map"
    );
}

/// Reads the consensus's ros2_bag with rosbags and compares the paths with OUT/agent_K.tum.
const CONSENSUS_BAG_CHECK: &str = r##"
import sys
from pathlib import Path
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
store = get_typestore(Stores.ROS2_HUMBLE)
out = Path(sys.argv[2])
children, paths, cloud = [], 0, ""
with Reader(sys.argv[1]) as reader:
    for connection, _, raw in reader.messages():
        message = store.deserialize_cdr(raw, connection.msgtype)
        if connection.topic == "/tf_static":
            children = sorted(t.child_frame_id for t in message.transforms)
            assert all(t.header.frame_id == "world" for t in message.transforms)
        elif connection.topic.endswith("/path"):
            agent = connection.topic.split("/")[1].removeprefix("agent")
            rows = [l.split() for l in open(out / f"agent_{agent}.tum") if l.strip() and not l.startswith("#")]
            assert len(rows) == len(message.poses), (len(rows), len(message.poses))
            for pose, row in zip(message.poses, rows):
                p = pose.pose.position
                assert max(abs(p.x - float(row[1])), abs(p.y - float(row[2])), abs(p.z - float(row[3]))) < 1e-6
            paths += 1
        elif connection.topic == "/map":
            assert message.width > 1000 and message.header.frame_id == "world"
            cloud = "map"
print(" ".join(children) + f", paths {paths}, {cloud}")
"##;
