//! Bad input, end to end: the binaries run on damaged 7-Scenes-layout sequences, a config with a
//! value of the wrong type, output folders they cannot write and a full disk. Each problem gives
//! one message naming the file (or folder, or field), the run either finishes with the problem
//! counted in metrics.json or stops with a non-zero exit, and nothing written before is damaged.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::workspace_binary;

/// A synthetic sequence of `frames` small frames in the 7-Scenes layout (`mac-ego3d synth`), in
/// `dir/agent_0`.
fn synthetic_sequence(dir: &Path, frames: usize) -> PathBuf {
    let out = Command::new(env!("CARGO_BIN_EXE_mac-ego3d"))
        .args([
            "synth", "--agents", "1", "--width", "160", "--height", "120",
        ])
        .args(["--frames", &frames.to_string()])
        .arg("--out")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    dir.join("agent_0")
}

/// `mac-agent --standalone` on `dataset`, writing to `out`, with the evaluation cut to one frame.
fn standalone_agent(dataset: &Path, out: &Path) -> Output {
    Command::new(workspace_binary("mac-agent"))
        // Every frame: the counts below are of what the source did, not of the clock.
        .args(["--standalone", "--renders", "0", "--eval-every", "1000"])
        .args(["--pace", "unthrottled"])
        .arg("--dataset")
        .arg(dataset)
        .arg("--out")
        .arg(out)
        .env("NO_COLOR", "1")
        .output()
        .unwrap()
}

/// The process's log, without terminal colours.
fn log_text(out: &Output) -> String {
    let text = String::from_utf8_lossy(&out.stderr);
    let mut plain = String::with_capacity(text.len());
    let mut chars = text.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            // An ANSI sequence: ESC [ ... letter.
            for c in chars.by_ref() {
                if c.is_ascii_alphabetic() {
                    break;
                }
            }
        } else {
            plain.push(c);
        }
    }
    plain
}

fn metrics(out_dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out_dir.join("metrics.json")).unwrap()).unwrap()
}

/// Poses in a TUM file (comment lines skipped).
fn tum_poses(path: &Path) -> usize {
    geometry::trajectory::Trajectory::read_tum(path)
        .unwrap()
        .len()
}

/// Each file is named on exactly one line of the log, and that line says `expected`.
fn assert_named_once(log: &str, files: &[(&str, &str)]) {
    for (file, expected) in files {
        let lines: Vec<&str> = log.lines().filter(|l| l.contains(file)).collect();
        assert_eq!(lines.len(), 1, "{file} should be named once:\n{log}");
        assert!(lines[0].contains(expected), "{file}: {}", lines[0]);
    }
}

/// Runs the agent on a sequence damaged as listed, expecting the run to finish with
/// `(frames tracked, missing, broken, broken ground truth)` and each damaged file named once.
fn assert_damage_is_counted_and_named(
    sequence: &Path,
    expected: (u64, u64, u64, u64),
    named: &[(&str, &str)],
) {
    let out_dir = sequence.with_file_name("out");
    let out = standalone_agent(sequence, &out_dir);
    let log = log_text(&out);
    assert!(out.status.success(), "{log}");
    assert!(!log.contains("panicked"), "{log}");
    assert_named_once(&log, named);
    let m = metrics(&out_dir);
    let counted = (
        m["frames"].as_u64().unwrap(),
        m["frames_missing"].as_u64().unwrap(),
        m["frames_broken"].as_u64().unwrap(),
        m["ground_truth_broken"].as_u64().unwrap(),
    );
    assert_eq!(counted, expected, "{m:#}");
    let (tracked, _, _, broken_ground_truth) = expected;
    assert_eq!(tum_poses(&out_dir.join("trajectory.tum")), tracked as usize);
    assert_eq!(
        tum_poses(&out_dir.join("groundtruth.tum")),
        (tracked - broken_ground_truth) as usize,
        "frames with a broken ground-truth pose are tracked but left out of the evaluation"
    );
}

fn cut_short(path: &Path) {
    let bytes = std::fs::read(path).unwrap();
    std::fs::write(path, &bytes[..bytes.len() / 2]).unwrap();
}

fn remove_frame(sequence: &Path, number: usize, kinds: &[&str]) {
    for kind in kinds {
        std::fs::remove_file(sequence.join(format!("frame-{number:06}.{kind}"))).unwrap();
    }
}

#[test]
fn damaged_frames_are_skipped_or_kept_counted_and_named() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = synthetic_sequence(dir.path(), 12);
    let file = |number: usize, kind: &str| sequence.join(format!("frame-{number:06}.{kind}"));
    cut_short(&file(3, "color.png"));
    remove_frame(&sequence, 5, &["color.png", "depth.png", "pose.txt"]);
    remove_frame(&sequence, 7, &["color.png"]);
    cut_short(&file(8, "pose.txt"));
    std::fs::write(file(9, "pose.txt"), "2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n").unwrap();
    std::fs::write(
        file(10, "pose.txt"),
        "1 0 0 NaN\n0 1 0 0\n0 0 1 0\n0 0 0 1\n",
    )
    .unwrap();
    assert_damage_is_counted_and_named(
        &sequence,
        (12 - 3, 2, 1, 3),
        &[
            ("frame-000003.color.png", "skipping broken frame"),
            ("frame-000005.color.png", "skipping missing frame"),
            ("frame-000007.color.png", "skipping missing frame"),
            ("frame-000008.pose.txt", "ground-truth pose unusable"),
            ("frame-000009.pose.txt", "not orthonormal"),
            ("frame-000010.pose.txt", "not a finite number"),
        ],
    );
}

#[test]
fn real_data_damaged_redkitchen_copy_is_skipped_counted_and_named() {
    let source = datasets::shared_data::require("datasets/7scenes-redkitchen");
    let dir = tempfile::tempdir().unwrap();
    let sequence = dir.path().join("redkitchen");
    std::fs::create_dir(&sequence).unwrap();
    for number in 0..30 {
        for kind in ["color.jpg", "depth.png", "pose.txt"] {
            let name = format!("frame-{number:06}.{kind}");
            std::fs::copy(source.join(&name), sequence.join(&name)).unwrap();
        }
    }
    // A cut-short JPEG decodes without an error (the decoder fills the rest with grey): the
    // reader refuses it by its missing end-of-image marker.
    cut_short(&sequence.join("frame-000010.color.jpg"));
    remove_frame(&sequence, 15, &["color.jpg", "depth.png", "pose.txt"]);
    remove_frame(&sequence, 20, &["color.jpg"]);
    cut_short(&sequence.join("frame-000025.pose.txt"));
    assert_damage_is_counted_and_named(
        &sequence,
        (30 - 3, 2, 1, 1),
        &[
            ("frame-000010.color.jpg", "truncated"),
            ("frame-000015.color.jpg", "skipping missing frame"),
            ("frame-000020.color.jpg", "skipping missing frame"),
            ("frame-000025.pose.txt", "ground-truth pose unusable"),
        ],
    );
}

#[test]
fn a_config_value_of_the_wrong_type_names_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("typo.toml");
    std::fs::write(&config, "[tracking]\npixel_stride = \"five\"\n").unwrap();
    let out_dir = dir.path().join("out");
    for binary in ["mac-agent", "mac-consensus"] {
        let out = Command::new(workspace_binary(binary))
            .arg("--config")
            .arg(&config)
            .arg("--out")
            .arg(&out_dir)
            .args(if binary == "mac-agent" {
                &["--standalone"][..]
            } else {
                &[][..]
            })
            .output()
            .unwrap();
        let log = log_text(&out);
        assert!(!out.status.success(), "{binary}: {log}");
        assert!(
            log.contains("typo.toml") && log.contains("pixel_stride") && log.contains("usize"),
            "{binary}: {log}"
        );
        assert!(!out_dir.exists(), "{binary} started work on a bad config");
    }
}

/// A tmpfs mounted on a fresh folder for the test's lifetime; unmounted on drop.
struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// `None`, with the reason printed, where mounting is not permitted (not root, a container
    /// without CAP_SYS_ADMIN).
    fn mount(options: &str) -> Option<Self> {
        let dir = tempfile::tempdir().unwrap();
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", options, "tmpfs"])
            .arg(dir.path())
            .output();
        match out {
            Ok(out) if out.status.success() => Some(Self { dir }),
            Ok(out) => {
                println!(
                    "skipped: cannot mount a tmpfs ({})",
                    String::from_utf8_lossy(&out.stderr).trim()
                );
                None
            }
            Err(error) => {
                println!("skipped: cannot run mount ({error})");
                None
            }
        }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

/// Output folders neither process can write fail at start, naming the folder. Tests run as root,
/// who may write anywhere the permission bits forbid, so the folder is a path through a regular
/// file (no process can create it) and, where mounting is permitted, a read-only tmpfs (not even
/// root can create a file there).
#[test]
fn an_unwritable_output_folder_fails_at_start_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = synthetic_sequence(dir.path(), 3);
    let file = dir.path().join("a-file");
    std::fs::write(&file, "").unwrap();
    let read_only = Tmpfs::mount("ro,size=1m");
    let mut folders = vec![file.clone(), file.join("run")];
    folders.extend(read_only.as_ref().map(|mount| mount.path().to_path_buf()));
    for folder in &folders {
        let agent = standalone_agent(&sequence, folder);
        let log = log_text(&agent);
        assert!(!agent.status.success(), "{log}");
        assert!(log.contains(&folder.display().to_string()), "{log}");
        assert!(
            !log.contains("agent starting"),
            "the agent must stop before any work: {log}"
        );
        let consensus = Command::new(workspace_binary("mac-consensus"))
            .args(["--agents", "1", "--namespace"])
            .arg(format!("badout{}", std::process::id()))
            .arg("--out")
            .arg(folder)
            .env("XDG_RUNTIME_DIR", dir.path())
            .output()
            .unwrap();
        let log = log_text(&consensus);
        assert!(!consensus.status.success(), "{log}");
        assert!(log.contains(&folder.display().to_string()), "{log}");
        assert!(!log.contains("consensus listening"), "{log}");
    }
}

/// A disk that fills while the outputs are written: the write that fails names its file, the
/// process exits non-zero with that message (no panic), the outputs written before it are
/// intact and no half-written file is left.
#[test]
fn a_full_disk_fails_the_output_naming_it_and_keeps_earlier_outputs() {
    // Room for the trajectories and the progress file, not for the map (about 360 kB).
    let Some(disk) = Tmpfs::mount("size=128k") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let sequence = synthetic_sequence(dir.path(), 12);
    let out = standalone_agent(&sequence, disk.path());
    let log = log_text(&out);
    assert!(!out.status.success(), "{log}");
    assert!(!log.contains("panicked"), "{log}");
    let map = disk.path().join("map.ply");
    assert!(
        log.contains(&format!("writing {}", map.display())) && log.contains("No space left"),
        "{log}"
    );
    assert_eq!(tum_poses(&disk.path().join("trajectory.tum")), 12);
    assert_eq!(tum_poses(&disk.path().join("groundtruth.tum")), 12);
    assert!(!map.exists() && !disk.path().join("map.ply.partial").exists());
}
