//! A consensus killed (SIGKILL) at any point of a store write never leaves a store that fails to
//! open: a child process appends keyframes to the store as fast as it can and is killed at
//! seeded random times; after each kill the store opens, every input it holds reads back whole,
//! and every input whose commit had returned before the kill is there.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use geometry::camera::Intrinsics;
use mac_consensus::store::{Opened, RunIdentity, Store, StoredInput, StoredKeyframe};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The child's run folder (set only in the child).
const WRITER_DIR_ENV: &str = "MAC_CONSENSUS_STORE_WRITER_DIR";
const KILLS: usize = 12;
const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn identity() -> RunIdentity {
    RunIdentity {
        run_id: "kill-points".into(),
        config_hash: 7,
        agents: Some(1),
    }
}

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
            .map(|i| (i as u64 ^ keyframe_id) as u8)
            .collect(),
        depth_m: vec![1.5; pixels],
    }))
}

/// The child: opens (resuming) the store and appends keyframes until killed, printing the count
/// of committed inputs after each commit.
#[test]
#[ignore = "the child process of store_survives_sigkill_at_random_points; run by it"]
fn store_writer_child() {
    let dir = std::env::var(WRITER_DIR_ENV).expect("run by the kill-point test");
    let (mut store, _, inputs) = Store::open(Path::new(&dir), &identity(), false).unwrap();
    let mut next = inputs.len() as u64;
    loop {
        store.append(&keyframe(next)).unwrap();
        next += 1;
        println!("committed {next}");
    }
}

#[test]
fn store_survives_sigkill_at_random_points() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut stored = 0;
    for kill in 0..KILLS {
        let mut child = Command::new(std::env::current_exe().unwrap())
            .args(["--ignored", "--exact", "store_writer_child", "--nocapture"])
            .env(WRITER_DIR_ENV, dir.path())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        // Killed while writing: a random time after its first commit (opening a store that
        // was not closed includes its repair, which takes a while).
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let committed_count = |line: String| line.strip_prefix("committed ")?.parse::<usize>().ok();
        let first = lines
            .by_ref()
            .map_while(Result::ok)
            .find_map(committed_count)
            .expect("the writer ended before its first commit");
        std::thread::sleep(Duration::from_millis(rng.random_range(0..150)));
        child.kill().unwrap();
        child.wait().unwrap();
        // The last count the child printed: those inputs were committed before the kill.
        let committed = lines
            .map_while(Result::ok)
            .filter_map(committed_count)
            .last()
            .unwrap_or(first);
        let (store, opened, inputs) = Store::open(dir.path(), &identity(), false)
            .unwrap_or_else(|e| panic!("kill {kill}: the store does not open: {e:#}"));
        assert_eq!(opened, Opened::Resumed, "kill {kill}");
        assert!(
            inputs.len() >= committed,
            "kill {kill}: {} inputs in the store, {committed} were committed",
            inputs.len()
        );
        for (i, input) in inputs.iter().enumerate() {
            let StoredInput::Keyframe(stored) = input else {
                panic!("kill {kill}: input {i} is not a keyframe");
            };
            assert_eq!(
                stored.keyframe_id, i as u64,
                "kill {kill}: inputs out of order"
            );
            stored
                .keyframe()
                .unwrap_or_else(|e| panic!("kill {kill}: input {i}: {e:#}"));
        }
        eprintln!(
            "kill {kill}: {} inputs stored ({committed} reported committed)",
            inputs.len()
        );
        assert!(inputs.len() > stored, "kill {kill}: nothing written");
        stored = inputs.len();
        drop(store);
    }
}
