//! Every shipped configuration (configs/**/*.toml, the per-dataset files and the scenarios under
//! configs/scenarios/) loads through the real loader, `config::Config::load`, which
//! refuses unknown keys and out-of-range values.

use std::path::{Path, PathBuf};

use config::Config;

fn configs_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("configs")
}

/// Every .toml file under `dir`, at any depth, sorted.
fn toml_files(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            found.extend(toml_files(&path));
        } else if path.extension().is_some_and(|e| e == "toml") {
            found.push(path);
        }
    }
    found.sort();
    found
}

fn load(relative: &str) -> Config {
    Config::load(&configs_dir().join(relative)).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn every_config_loads_and_is_documented() {
    let files = toml_files(&configs_dir());
    for path in &files {
        Config::load(path).unwrap_or_else(|e| panic!("{e}"));
        let text = std::fs::read_to_string(path).unwrap();
        assert!(
            text.starts_with('#'),
            "{}: a config opens with comments saying what it is for and how to use it",
            path.display()
        );
    }
    let names: Vec<String> = files
        .iter()
        .map(|p| {
            p.strip_prefix(configs_dir())
                .unwrap()
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    for expected in [
        "synthetic.toml",
        "7scenes.toml",
        "7scenes-paced.toml",
        "replica.toml",
        "multiagent-replica.toml",
        "tum.toml",
        "scenarios/swarm-2-agents.toml",
        "scenarios/swarm-3-agents.toml",
        "scenarios/swarm-4-agents.toml",
        "scenarios/fast-motion.toml",
    ] {
        assert!(
            names.iter().any(|n| n == expected),
            "configs/{expected} is missing (found {names:?})"
        );
    }
}

#[test]
fn multiagent_replica_uses_the_replica_sensor_and_tcomm() {
    let multi = load("multiagent-replica.toml");
    let single = load("replica.toml");
    assert_eq!(
        multi.consensus.t_comm, 150,
        "T_comm 150 on Replica (docs/method.md, The consensus: selection)"
    );
    assert_eq!(multi.tracking, single.tracking);
    assert_eq!(multi.mapping, single.mapping);
    assert_eq!(
        multi.consensus.alignment.pixel_stride,
        multi.tracking.pixel_stride
    );
}

#[test]
fn scenarios_share_the_sensor_and_scale_the_candidates() {
    let synthetic = load("synthetic.toml");
    let candidates: Vec<usize> = [2, 3, 4]
        .iter()
        .map(|agents| {
            let scenario = load(&format!("scenarios/swarm-{agents}-agents.toml"));
            assert_eq!(scenario.tracking, synthetic.tracking);
            assert_eq!(scenario.mapping, synthetic.mapping);
            assert_eq!(scenario.consensus.t_comm, synthetic.consensus.t_comm);
            scenario.consensus.max_candidates_per_keyframe
        })
        .collect();
    assert!(
        candidates.windows(2).all(|w| w[0] <= w[1]),
        "more agents never get fewer proposals per keyframe: {candidates:?}"
    );
}

/// configs/7scenes-paced.toml is configs/7scenes.toml with only its paced keys changed: every key
/// it leaves out must default to 7scenes.toml's value.
#[test]
fn the_paced_7scenes_config_differs_from_7scenes_only_in_its_paced_keys() {
    let real_time = load("7scenes.toml");
    let mut paced = load("7scenes-paced.toml");
    assert_eq!(paced.mapping.pace, config::Pace::Paced);
    assert!(paced.mapping.refine_keyframe_poses);
    assert!(paced.consensus.t_comm < real_time.consensus.t_comm);
    assert!(
        paced.consensus.refinement.iterations_per_view
            > real_time.consensus.refinement.iterations_per_view
    );
    paced.keyframes.tracking_keyframe_seeds = real_time.keyframes.tracking_keyframe_seeds;
    paced.mapping.pace = real_time.mapping.pace;
    paced.mapping.image_downscale = real_time.mapping.image_downscale;
    paced.mapping.refine_keyframe_poses = real_time.mapping.refine_keyframe_poses;
    paced.consensus.t_comm = real_time.consensus.t_comm;
    paced.consensus.refinement.iterations_per_view =
        real_time.consensus.refinement.iterations_per_view;
    assert!(
        paced.consensus.refinement.lr_pose_translation_m
            > real_time.consensus.refinement.lr_pose_translation_m
    );
    paced.consensus.refinement.lr_pose_translation_m =
        real_time.consensus.refinement.lr_pose_translation_m;
    paced.consensus.refinement.lr_pose_rotation_rad =
        real_time.consensus.refinement.lr_pose_rotation_rad;
    assert_eq!(paced, real_time);
}
