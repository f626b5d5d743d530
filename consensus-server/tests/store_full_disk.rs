//! A disk that fills under the consensus store: the append that fails names the store and the
//! input, and once there is room again the store opens with every input committed before the
//! failure, each reading back whole (a commit is all or nothing).
//!
//! The disk is a small tmpfs, which needs root (as CI runs); where mounting is not permitted the
//! test says so and does nothing.

use std::path::Path;
use std::process::Command;

use geometry::camera::Intrinsics;
use mac_consensus::store::{Opened, RunIdentity, STORE_FILE, Store, StoredInput, StoredKeyframe};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn identity() -> RunIdentity {
    RunIdentity {
        run_id: "full-disk".into(),
        config_hash: 7,
        agents: Some(1),
    }
}

/// About 0.5 MB in the store (RGB + depth at 320x240); its pixels depend on its id.
fn keyframe(keyframe_id: u64) -> StoredInput {
    let pixels = (WIDTH * HEIGHT) as usize;
    StoredInput::Keyframe(Box::new(StoredKeyframe {
        agent_id: 0,
        keyframe_id,
        epoch: 1,
        frame_index: keyframe_id,
        timestamp_s: keyframe_id as f64,
        descriptor: vec![0.1; 16],
        intrinsics: Intrinsics {
            fx: 300.0,
            fy: 300.0,
            cx: 159.5,
            cy: 119.5,
            width: WIDTH,
            height: HEIGHT,
        },
        agent_from_camera: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        width: WIDTH,
        height: HEIGHT,
        rgb: (0..pixels * 3)
            .map(|i| (i as u64 * 7 + keyframe_id) as u8)
            .collect(),
        depth_m: vec![1.0 + keyframe_id as f32; pixels],
    }))
}

struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    /// `None`, with the reason printed, where mounting is not permitted.
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

    /// More room, as a user who frees space: a tmpfs keeps its files when remounted.
    fn grow(&self, size: &str) {
        let status = Command::new("mount")
            .args(["-o", &format!("remount,size={size}")])
            .arg(self.path())
            .status()
            .unwrap();
        assert!(status.success(), "remounting the tmpfs larger failed");
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

#[test]
fn a_full_disk_fails_the_store_write_naming_it_and_keeps_every_committed_input() {
    let Some(disk) = Tmpfs::mount("size=4m") else {
        return;
    };
    let mut committed = 0u64;
    let error = {
        let (mut store, opened, inputs) = Store::open(disk.path(), &identity(), false).unwrap();
        assert_eq!(opened, Opened::New);
        assert!(inputs.is_empty());
        loop {
            match store.append(&keyframe(committed)) {
                Ok(()) => committed += 1,
                Err(error) => break error,
            }
            assert!(committed < 64, "a 4 MB disk took 64 keyframes of 0.5 MB");
        }
    };
    let message = format!("{error:#}");
    let store_path = disk.path().join(STORE_FILE);
    assert!(
        message.contains(&store_path.display().to_string())
            && message.contains(&format!("input {committed}")),
        "the error names neither the store nor the input: {message}"
    );
    assert!(
        committed >= 2,
        "only {committed} keyframes fitted: {message}"
    );
    println!("{committed} keyframes committed, then: {message}");

    disk.grow("64m");
    let (_store, opened, inputs) = Store::open(disk.path(), &identity(), false)
        .unwrap_or_else(|e| panic!("the store does not open after the full disk: {e:#}"));
    assert_eq!(opened, Opened::Resumed);
    // The failed commit is all or nothing: absent (or, had it reached the disk before the error
    // surfaced, whole).
    assert!(
        inputs.len() as u64 == committed || inputs.len() as u64 == committed + 1,
        "{} inputs in the store, {committed} committed",
        inputs.len()
    );
    for (i, input) in inputs.iter().enumerate() {
        let (StoredInput::Keyframe(stored), StoredInput::Keyframe(written)) =
            (input, keyframe(i as u64))
        else {
            panic!("input {i} is not a keyframe");
        };
        assert_eq!(stored.keyframe_id, i as u64, "inputs out of order");
        assert!(
            stored.rgb == written.rgb && stored.depth_m == written.depth_m,
            "input {i} does not read back as written"
        );
    }
}
