//! Live ROS 2 topics, end to end, over real DDS: a camera published by an independent DDS
//! implementation (Eclipse Cyclone DDS from PyPI, scripts/ros2/publish_dataset.py, in the peers'
//! virtual environment) and an agent subscribing through RustDDS (`--dataset ros2:/robot0`), in a
//! network namespace of its own (loopback only, multicast on, as a LAN: standard DDS discovery,
//! and no packet leaves the test).
//!
//! Without PyPI (scripts/peers_venv.sh exits 3) or without root (network namespaces) these tests
//! say NOT RUN and pass, except under CI (CI=true), where they fail.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::{is_root, peers_python, shared_data, workspace_binary};

const REPO: &str = env!("CARGO_MANIFEST_DIR");

/// The first lines of every test's script: the new namespace's loopback up, with multicast, as a
/// LAN (standard DDS discovery; no packet leaves the namespace).
const LOOPBACK_LAN: &str = "ip link set lo up\n\
    ip link set lo multicast on\n\
    ip route add 224.0.0.0/4 dev lo\n";

/// 7-Scenes frames are published stamped 1.7e9 s + N / 30 (a ROS stamp of zero means none):
/// scripts/ros2/dataset_to_bag.py's SEVEN_SCENES_EPOCH_S.
const SEVEN_SCENES_EPOCH_S: f64 = 1.7e9;

/// The camera tests run one at a time: each is a real-time publisher and agent, and two of them
/// on a 2-core machine would measure the machine, not the agent.
static REAL_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// What a live test needs: the peers' python, and root for the network namespace.
fn prerequisites() -> Option<PathBuf> {
    if !is_root() {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "live ROS 2 tests need root (network namespaces) under CI"
        );
        eprintln!("NOT RUN: live ROS 2 tests need root (a network namespace per test)");
        return None;
    }
    peers_python()
}

/// What one live run gave: the agent's output, what the publisher says it sent, the agent's
/// metrics.json, and what a listener heard of the agent's live outputs (Null unless asked).
struct LiveRun {
    agent: Output,
    sent: serde_json::Value,
    metrics: serde_json::Value,
    heard: serde_json::Value,
}

/// Runs the publisher (with `publisher_args`) and `mac-agent --standalone --dataset ros2:/robot0`
/// (with `config`) side by side in a new network namespace, and with `listen`
/// scripts/ros2/listen_outputs.py too.
fn publish_and_track(
    python: &Path,
    publisher_args: &[&str],
    config: &Path,
    out: &Path,
    listen: bool,
) -> LiveRun {
    let sent = out.with_extension("sent.json");
    let heard = out.with_extension("heard.json");
    let script = format!(
        "set -e\n\
         {LOOPBACK_LAN}\
         \"$PYTHON\" \"$PUBLISHER\" --namespace /robot0 {args} > \"$SENT\" &\n\
         publisher=$!\n\
         {listener}\
         status=0\n\
         \"$AGENT\" --standalone --config \"$CONFIG\" --dataset ros2:/robot0 --renders 0 \
           --eval-every 5 --out \"$OUT\" || status=$?\n\
         wait $publisher || echo \"the publisher failed: $?\" >&2\n\
         wait\n\
         exit $status\n",
        args = publisher_args.join(" "),
        listener = if listen {
            "\"$PYTHON\" \"$LISTENER\" --agent 0 --idle 10 > \"$HEARD\" &\n"
        } else {
            ""
        }
    );
    let run = Command::new("unshare")
        .args(["--net", "bash", "-c", &script])
        .env("PYTHON", python)
        .env(
            "PUBLISHER",
            Path::new(REPO).join("scripts/ros2/publish_dataset.py"),
        )
        .env("AGENT", workspace_binary("mac-agent"))
        .env("CONFIG", config)
        .env("OUT", out)
        .env("SENT", &sent)
        .env(
            "LISTENER",
            Path::new(REPO).join("scripts/ros2/listen_outputs.py"),
        )
        .env("HEARD", &heard)
        .env("NO_COLOR", "1")
        .output()
        .expect("running unshare");
    let read = |path: &Path| {
        std::fs::read_to_string(path)
            .ok()
            .and_then(|text| serde_json::from_str(text.trim()).ok())
            .unwrap_or(serde_json::Value::Null)
    };
    LiveRun {
        sent: read(&sent),
        metrics: read(&out.join("metrics.json")),
        heard: read(&heard),
        agent: run,
    }
}

/// The standalone agent on `frames` of the `dataset` folder, paced (every frame tracked), with
/// `config` (default: none), into `out`: what a live run of the same frames is compared with.
fn paced_folder_run(dataset: &Path, frames: &str, config: Option<&Path>, out: &Path) {
    let mut command = Command::new(workspace_binary("mac-agent"));
    command
        .args(["--standalone", "--renders", "0", "--eval-every", "1000"])
        .args(["--pace", "paced", "--frames", frames]);
    if let Some(config) = config {
        command.arg("--config").arg(config);
    }
    let run = command
        .arg("--dataset")
        .arg(dataset)
        .arg("--out")
        .arg(out)
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", log(&run));
}

fn log(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn config(dir: &Path, name: &str, extra: &str) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, format!("[ros2]\nidle_timeout_s = 4.0\n{extra}")).unwrap();
    path
}

/// redkitchen's ground truth with the stamps the publisher gives 7-Scenes frames.
fn shifted_ground_truth(dir: &Path) -> PathBuf {
    let original = shared_data("datasets/7scenes-redkitchen/groundtruth_tum.txt");
    let text = std::fs::read_to_string(original).unwrap();
    let shifted: String = text
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let (stamp, rest) = l.split_once(' ').unwrap();
            let stamp: f64 = stamp.parse().unwrap();
            format!("{:.6} {rest}\n", stamp + SEVEN_SCENES_EPOCH_S)
        })
        .collect();
    let path = dir.join("groundtruth_live.tum");
    std::fs::write(&path, shifted).unwrap();
    path
}

fn ate_m(ground_truth: &Path, estimate: &Path) -> f64 {
    let out = Command::new(workspace_binary("mac-ego3d"))
        .args(["eval", "ate", "--json", "--max-dt", "0.005"])
        .arg("--gt")
        .arg(ground_truth)
        .arg("--est")
        .arg(estimate)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", log(&out));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    json["rmse"]
        .as_f64()
        .unwrap_or_else(|| panic!("no ATE in {json}"))
}

fn count(metrics: &serde_json::Value, key: &str) -> u64 {
    metrics["live"][key]
        .as_u64()
        .unwrap_or_else(|| panic!("metrics.json live.{key} missing: {}", metrics["live"]))
}

/// Raw images at 10 Hz with faults on the way (depth images never sent, colour images sent
/// twice): every message is accounted for, the frames the agent took are tracked where the
/// ground truth says, and the run ends by itself once the camera stops.
#[test]
fn real_data_live_camera_over_dds_with_faults() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let work = tempfile::tempdir().unwrap();
    let config = config(work.path(), "live", "publish = true\n");
    let out = work.path().join("agent");
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let LiveRun {
        agent: run,
        sent,
        metrics,
        heard,
    } = publish_and_track(
        &python,
        &[
            "--dataset",
            dataset.to_str().unwrap(),
            "--frames",
            "0..90",
            "--rate",
            "10",
            "--skip-depth-every",
            "15",
            "--duplicate-every",
            "20",
        ],
        &config,
        &out,
        true,
    );
    assert!(run.status.success(), "{}", log(&run));
    assert_eq!(sent["frames"], 90, "publisher: {sent}");
    let (skipped, duplicates) = (
        sent["depth_skipped"].as_u64().unwrap(),
        sent["duplicates"].as_u64().unwrap(),
    );
    assert_eq!((skipped, duplicates), (6, 4), "publisher: {sent}");
    // Loopback loses nothing: every message the camera sent arrived.
    assert_eq!(count(&metrics, "colour_received"), 90 + duplicates);
    assert_eq!(count(&metrics, "depth_received"), 90 - skipped);
    assert!(count(&metrics, "camera_info_received") >= 1);
    // Each duplicate is stale; each colour image without depth goes unpaired (the last one
    // may still be waiting when the run ends).
    assert_eq!(count(&metrics, "stale"), duplicates);
    let unpaired = count(&metrics, "unpaired");
    assert!(
        (skipped - 1..=skipped).contains(&unpaired),
        "unpaired {unpaired}"
    );
    let paired = count(&metrics, "paired");
    assert_eq!(paired, 90 - skipped);
    // Pairs the agent did not take were dropped for newer ones, never lost.
    assert_eq!(
        count(&metrics, "frames") + count(&metrics, "dropped"),
        paired
    );
    assert_eq!(count(&metrics, "decode_errors"), 0);
    assert_eq!(metrics["frames"].as_u64(), Some(count(&metrics, "frames")));
    let end = metrics["live"]["end"].as_str().unwrap();
    assert!(end.starts_with("no frame for 4.0 s"), "{end}");
    assert!(metrics["psnr"].as_f64().unwrap() > 15.0, "{metrics}");

    let ate = ate_m(
        &shifted_ground_truth(work.path()),
        &out.join("trajectory.tum"),
    );
    eprintln!(
        "live: {} frames tracked of {paired} paired, ATE {:.2} cm, hand-over median {} ms",
        count(&metrics, "frames"),
        ate * 100.0,
        metrics["live"]["handover_ms_median"]
    );
    assert!(ate < 0.05, "ATE {ate} m");
    // The publisher stamps 7-Scenes frames on an epoch of its own, not this host's clock: no
    // latency is claimed, neither to arrival nor to pose (scripts/bench_live.sh measures them
    // with stamps of this host's clock).
    let live = &metrics["live"];
    assert!(live["stamp_to_arrival_ms_median"].is_null(), "{live}");
    assert!(live["stamp_to_pose_ms_median"].is_null(), "{live}");
    assert!(live["dropped_while_starting"].as_u64().unwrap() <= count(&metrics, "dropped"));
    // The same frames replayed from the folder, paced (every frame tracked): the live run, which
    // lost a few pairs on the way and took the newest of the rest, lands within 5 mm of it.
    let folder_out = work.path().join("folder");
    paced_folder_run(&dataset, "0..90", None, &folder_out);
    let folder_metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(folder_out.join("metrics.json")).unwrap())
            .unwrap();
    let folder_ate = folder_metrics["ate_rmse_m"].as_f64().unwrap();
    eprintln!(
        "live ATE {:.2} cm, paced folder {:.2} cm",
        ate * 100.0,
        folder_ate * 100.0
    );
    assert!(
        (ate - folder_ate).abs() < 0.005,
        "live {ate} m, folder {folder_ate} m"
    );

    // What the agent published live, as a ROS 2 node (rviz2) would hear it: a camera transform
    // per placed frame, the world -> odom transform, the whole path, the map with colour.
    let placed = std::fs::read_to_string(out.join("trajectory.tum"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .count() as u64;
    eprintln!("heard: {heard}");
    // /tf is volatile, as in ROS: transforms sent before the listener matched are not replayed.
    let tf = heard["messages"]["tf"].as_u64().unwrap();
    assert!(
        tf <= placed && tf + 5 >= placed,
        "{tf} of {placed}: {heard}"
    );
    assert_eq!(heard["messages"]["tf_static"].as_u64(), Some(1), "{heard}");
    assert_eq!(
        heard["tf_children"],
        serde_json::json!(["agent0/camera_optical_frame", "agent0/odom"])
    );
    assert_eq!(heard["path"]["poses"].as_u64(), Some(placed), "{heard}");
    assert_eq!(heard["path"]["frame"], "world");
    assert_eq!(
        heard["map"]["points"].as_u64(),
        metrics["gaussians"].as_u64(),
        "the final map, whole: {heard}"
    );
    assert_eq!(
        heard["map"]["fields"],
        serde_json::json!(["x", "y", "z", "rgb"])
    );
}

/// Compressed images (JPEG colour, compressedDepth PNG), and a
/// publisher that restarts part way (its stamps jump back): the agent pairs again and goes on.
/// tum-fr1-rpy (a real Kinect with a lens to undistort, fast rotation) at 10 Hz with the
/// recording's own stamps, depth as 32FC1 metres, the lens as CameraInfo's plumb_bob and the
/// depth's registration pinhole on the depth's own CameraInfo: the agent, which sets up its
/// mapper before it subscribes, takes nearly every frame, and its poses land within 5 mm (ATE)
/// of the paced folder run on the same frames, both against the dataset's ground truth.
#[test]
fn real_data_live_tum_at_its_own_stamps() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let work = tempfile::tempdir().unwrap();
    let tum = shared_data("datasets/tum-fr1-rpy");
    let config = work.path().join("live.toml");
    std::fs::write(
        &config,
        format!(
            "{}\n[ros2]\nidle_timeout_s = 4.0\n",
            std::fs::read_to_string(Path::new(REPO).join("configs/tum.toml")).unwrap()
        ),
    )
    .unwrap();
    let out = work.path().join("agent");
    let LiveRun {
        agent: run,
        sent,
        metrics,
        ..
    } = publish_and_track(
        &python,
        &[
            "--dataset",
            tum.to_str().unwrap(),
            "--frames",
            "0..100",
            "--rate",
            "10",
            "--stamps",
            "dataset",
        ],
        &config,
        &out,
        false,
    );
    assert!(run.status.success(), "{}", log(&run));
    assert_eq!(sent["frames"], 100, "publisher: {sent}");
    assert_eq!(count(&metrics, "paired"), 100, "{}", metrics["live"]);
    assert_eq!(count(&metrics, "frames") + count(&metrics, "dropped"), 100);
    assert!(count(&metrics, "frames") >= 90, "{}", metrics["live"]);
    // A recording's stamps are not this host's clock: no latency is claimed.
    assert!(metrics["live"]["stamp_to_arrival_ms_median"].is_null());
    assert!(metrics["live"]["stamp_to_pose_ms_median"].is_null());

    let folder_out = work.path().join("folder");
    let tum_config = Path::new(REPO).join("configs/tum.toml");
    paced_folder_run(&tum, "0..100", Some(&tum_config), &folder_out);
    let ground_truth = tum.join("groundtruth.txt");
    let live_ate = ate_m(&ground_truth, &out.join("trajectory.tum"));
    let folder_ate = ate_m(&ground_truth, &folder_out.join("trajectory.tum"));
    eprintln!(
        "tum-fr1-rpy live at 10 Hz: {} frames taken, ATE {:.2} cm; paced folder {:.2} cm",
        count(&metrics, "frames"),
        live_ate * 100.0,
        folder_ate * 100.0
    );
    assert!(
        (live_ate - folder_ate).abs() < 0.005,
        "live {live_ate} m, folder {folder_ate} m"
    );
}

#[test]
fn real_data_live_compressed_camera_restarting() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let work = tempfile::tempdir().unwrap();
    let config = config(
        work.path(),
        "compressed",
        "colour_topic = \"/camera/camera/color/image_raw/compressed\"\n\
         depth_topic = \"/camera/camera/aligned_depth_to_color/image_raw/compressedDepth\"\n",
    );
    let out = work.path().join("agent");
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let LiveRun {
        agent: run,
        sent,
        metrics,
        ..
    } = publish_and_track(
        &python,
        &[
            "--dataset",
            dataset.to_str().unwrap(),
            "--frames",
            "0..45",
            "--rate",
            "10",
            "--images",
            "compressed",
            "--restart-after",
            "45",
        ],
        &config,
        &out,
        false,
    );
    assert!(run.status.success(), "{}", log(&run));
    // The whole range twice: the stamps jump back by 1.5 s, past the restart threshold.
    assert_eq!(sent["frames"], 90, "publisher: {sent}");
    assert_eq!(count(&metrics, "restarts"), 1);
    assert_eq!(count(&metrics, "paired"), 90);
    assert_eq!(count(&metrics, "decode_errors"), 0);
    assert_eq!(count(&metrics, "frames") + count(&metrics, "dropped"), 90);
    // Frames of both passes were tracked: the trajectory's stamps go back once, at the restart.
    let stamps: Vec<f64> = std::fs::read_to_string(out.join("trajectory.tum"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    let jumps_back = stamps.windows(2).filter(|w| w[1] < w[0]).count();
    assert_eq!(
        jumps_back,
        1,
        "{} frames, {}\n{}",
        stamps.len(),
        metrics["live"],
        log(&run)
    );
}

/// No camera on the namespace: the agent gives up after `wait_for_camera_s` and names the
/// topic it waited on.
#[test]
fn a_live_camera_that_never_appears_is_named() {
    if !is_root() {
        eprintln!("NOT RUN: live ROS 2 tests need root (a network namespace per test)");
        return;
    }
    let work = tempfile::tempdir().unwrap();
    let config = config(work.path(), "absent", "wait_for_camera_s = 2.0\n");
    let run = Command::new("unshare")
        .args([
            "--net",
            "bash",
            "-c",
            "ip link set lo up && exec \"$@\"",
            "agent",
        ])
        .arg(workspace_binary("mac-agent"))
        .args(["--standalone", "--dataset", "ros2:/nobody"])
        .arg("--config")
        .arg(&config)
        .arg("--out")
        .arg(work.path().join("agent"))
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    assert!(!run.status.success());
    let log = log(&run);
    assert!(
        log.contains("no CameraInfo on /nobody/camera/camera/color/camera_info within 2 s"),
        "{log}"
    );
}

/// Two robots, each a camera under its own namespace, and `mac-ego3d swarm --agent
/// ros2:/robot0 --agent ros2:/robot1`: both are linked into one map, with no ground truth (the
/// figures leave the ATE out), and the consensus writes its bag.
#[test]
fn real_data_live_swarm_of_two_robots() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let work = tempfile::tempdir().unwrap();
    let config = config(
        work.path(),
        "swarm",
        "colour_topic = \"/camera/camera/color/image_raw/compressed\"\n\
         depth_topic = \"/camera/camera/aligned_depth_to_color/image_raw/compressedDepth\"\n\
         publish = true\n\
         [consensus.refinement]\nmax_seconds = 10.0\n",
    );
    let out = work.path().join("swarm");
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let script = format!(
        "set -e\n\
         {LOOPBACK_LAN}\
         for k in 0 1; do\n\
           \"$PYTHON\" \"$PUBLISHER\" --dataset \"$DATASET\" --frames $((k * 100))..$((k * 100 + 150)) \
             --namespace /robot$k --rate 10 --images compressed > \"$OUT.sent$k\" &\n\
         done\n\
         \"$PYTHON\" \"$LISTENER\" --agent 0 --map-topic /map --wait-for map --idle 30 > \"$OUT.heard\" &\n\
         \"$MAC_EGO3D\" swarm --config \"$CONFIG\" --agent ros2:/robot0 --agent ros2:/robot1 \
           --out \"$OUT\"\n\
         wait\n"
    );
    let run = Command::new("unshare")
        .args(["--net", "bash", "-c", &script])
        .env("PYTHON", &python)
        .env(
            "PUBLISHER",
            Path::new(REPO).join("scripts/ros2/publish_dataset.py"),
        )
        .env("MAC_EGO3D", workspace_binary("mac-ego3d"))
        .env(
            "LISTENER",
            Path::new(REPO).join("scripts/ros2/listen_outputs.py"),
        )
        .env("DATASET", &dataset)
        .env("CONFIG", &config)
        .env("OUT", &out)
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let tails = common::log_tails(&out, 30);
    assert!(run.status.success(), "{}\n{tails}", log(&run));
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(
        metrics["agents_not_linked"],
        serde_json::json!([]),
        "{metrics}\n{tails}"
    );
    assert!(metrics["ate_joint_rmse_m"].is_null(), "{metrics}");
    for k in 0..2 {
        let agent: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.join(format!("agent_{k}/metrics.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(agent["live"]["paired"], 150, "agent {k}: {}", agent["live"]);
        assert_eq!(agent["live"]["namespace"], format!("/robot{k}"));
    }
    assert!(out.join("ros2_bag/metadata.yaml").is_file());
    assert!(out.join("map.ply").is_file());
    // What the consensus published live, as rviz2 hears it: both agents placed in the world,
    // agent 0's world path, the merged map.
    let heard: serde_json::Value = serde_json::from_str(
        std::fs::read_to_string(out.with_extension("heard"))
            .unwrap()
            .trim(),
    )
    .unwrap_or_else(|e| panic!("the listener's JSON: {e}\n{}", log(&run)));
    let children = heard["tf_children"].as_array().unwrap();
    for expected in ["agent0/odom", "agent1/odom", "agent0/camera_optical_frame"] {
        assert!(
            children.iter().any(|c| c == expected),
            "{expected}: {heard}"
        );
    }
    assert_eq!(heard["path"]["frame"], "world", "{heard}");
    let world_path = std::fs::read_to_string(out.join("agent_0.tum")).unwrap();
    let world_poses = world_path.lines().filter(|l| !l.starts_with('#')).count();
    assert_eq!(
        heard["path"]["poses"].as_u64(),
        Some(world_poses as u64),
        "{heard}"
    );
    assert_eq!(heard["map"]["frame"], "world", "{heard}");
    assert!(heard["map"]["points"].as_u64().unwrap() > 1000, "{heard}");
}

/// Garbage over the wire: colour images with an encoding nobody knows, with one row more than
/// their data, unstamped pairs, and a burst at 200 Hz to start: each is counted where it belongs,
/// the agent goes on, and its map is kept.
#[test]
fn real_data_live_camera_sending_garbage() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let work = tempfile::tempdir().unwrap();
    let config = config(work.path(), "garbage", "");
    let out = work.path().join("agent");
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let LiveRun {
        agent: run,
        sent,
        metrics,
        ..
    } = publish_and_track(
        &python,
        &[
            "--dataset",
            dataset.to_str().unwrap(),
            "--frames",
            "0..60",
            "--rate",
            "10",
            "--burst",
            "20",
            "--corrupt",
            "encoding:10",
            "--corrupt",
            "size:14",
            "--corrupt",
            "zero-stamp:23",
        ],
        &config,
        &out,
        false,
    );
    assert!(run.status.success(), "{}", log(&run));
    assert_eq!(
        sent["corrupted"],
        serde_json::json!({"encoding": 6, "size": 4, "zero-stamp": 2}),
        "{sent}"
    );
    // Both images of an unstamped frame are refused before pairing.
    assert_eq!(count(&metrics, "unstamped"), 4);
    let paired = count(&metrics, "paired");
    assert_eq!(paired, 58);
    // A spoilt pair the agent took is a decode error; one it never took was dropped.
    let decode_errors = count(&metrics, "decode_errors");
    assert!((1..=10).contains(&decode_errors), "{}", metrics["live"]);
    assert_eq!(
        count(&metrics, "frames") + count(&metrics, "dropped") + decode_errors,
        paired
    );
    assert_eq!(metrics["frames_broken"].as_u64(), Some(decode_errors));
    let log = log(&run);
    assert!(
        log.contains("skipping a live frame that cannot be used"),
        "{log}"
    );
    assert!(out.join("map.ply").is_file());
    assert!(metrics["gaussians"].as_u64().unwrap() > 1000, "{metrics}");
}

/// `mac-ego3d dataset info ros2:/robot0` lists the topics a camera announces, says that the
/// agent's raw topics are not among them and which keys to set for the compressed ones, and
/// counts what came.
#[test]
fn real_data_dataset_info_of_a_live_camera() {
    let Some(python) = prerequisites() else {
        return;
    };
    let _one_at_a_time = REAL_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dataset = shared_data("datasets/7scenes-redkitchen");
    let script = format!(
        "set -e\n\
         {LOOPBACK_LAN}\
         \"$PYTHON\" \"$PUBLISHER\" --dataset \"$DATASET\" --frames 0..150 --namespace /robot0 \
           --rate 10 --images compressed --wait-subscribers 0 > /dev/null &\n\
         sleep 3\n\
         \"$MAC_EGO3D\" dataset info ros2:/robot0\n\
         kill %1\n"
    );
    let run = Command::new("unshare")
        .args(["--net", "bash", "-c", &script])
        .env("PYTHON", &python)
        .env(
            "PUBLISHER",
            Path::new(REPO).join("scripts/ros2/publish_dataset.py"),
        )
        .env("MAC_EGO3D", workspace_binary("mac-ego3d"))
        .env("DATASET", &dataset)
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let printed = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{printed}\n{}", log(&run));
    for expected in [
        "/robot0/camera/camera/color/image_raw/compressed",
        "sensor_msgs/msg/CompressedImage",
        "/robot0/camera/camera/color/image_raw                        NOT ANNOUNCED",
        "set [ros2] colour_topic = \"/camera/camera/color/image_raw/compressed\"",
        "set [ros2] depth_topic = \"/camera/camera/aligned_depth_to_color/image_raw/compressedDepth\"",
        "camera: 640x480 fx 585 fy 585",
    ] {
        assert!(printed.contains(expected), "{expected}:\n{printed}");
    }
}
