use super::*;
use crate::alignment::Keyframe;
use crate::engine::{Job, KeyframeArrival};
use config::ConsensusConfig;
use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{Dataset, FrameRange};

/// Frames of the synthetic agent 0 published as keyframes: close enough that each pair of
/// neighbours aligns and is verified.
const FRAMES: [usize; 3] = [0, 8, 16];

fn dataset() -> SyntheticDataset {
    let spec = SyntheticSpec {
        agents: 1,
        frames: 20,
        width: 320,
        height: 240,
        ..SyntheticSpec::default()
    }
    .with_agent(0);
    SyntheticDataset::new(spec, FrameRange::ALL).unwrap()
}

fn arrival(dataset: &SyntheticDataset, keyframe_id: usize) -> KeyframeArrival {
    let position = FRAMES[keyframe_id];
    let frame = dataset.load(position).unwrap();
    let world_from_first = dataset.ground_truth(0).unwrap().unwrap().inverse();
    KeyframeArrival {
        keyframe: Keyframe {
            id: KeyframeRef {
                agent_id: 0,
                keyframe_id: keyframe_id as u64,
            },
            rgb: frame.rgb,
            depth: frame.depth,
            intrinsics: frame.intrinsics,
            agent_from_camera: world_from_first * frame.world_from_camera_gt.unwrap(),
        },
        frame_index: position as u64,
        timestamp_s: position as f64 / 30.0,
        descriptor: vec![1.0, 0.0, 0.0],
        gaussians: Default::default(),
    }
}

fn config() -> ConsensusConfig {
    let mut config = ConsensusConfig::default();
    // Keyframe pairs only: the odometry candidates of consecutive keyframes.
    config.map_registration.enabled = false;
    config.max_candidates_per_keyframe = 0;
    config
}

/// Runs every due job on this thread, deciding and applying each; returns the decisions.
fn align_all(engine: &mut Engine) -> Vec<Decision> {
    let mut decisions = Vec::new();
    while let Some(job) = engine.next_job() {
        assert!(matches!(job, Job::Keyframes(_)));
        if let Some(decision) = engine.decide(job.run()) {
            decisions.push(decision.clone());
            engine.apply(decision);
        }
    }
    decisions
}

fn json(events: &[ClosureEvent]) -> String {
    serde_json::to_string(events).unwrap()
}

#[test]
fn a_resumed_engine_takes_the_stored_closures_bit_for_bit_and_aligns_only_new_pairs() {
    let dataset = dataset();
    let mut live = Engine::new(config());
    let mut decisions = Vec::new();
    for keyframe_id in 0..FRAMES.len() - 1 {
        live.add_keyframe(arrival(&dataset, keyframe_id));
        decisions.extend(align_all(&mut live));
    }
    assert_eq!(decisions.len(), 1, "one odometry pair before the kill");
    assert!(decisions[0].event.verified, "{:?}", decisions[0].event);
    // Through the store's encoding, as a restarted process reads them.
    let stored: Vec<Decision> = decisions
        .iter()
        .map(|d| {
            let bytes = bincode::serde::encode_to_vec(d, bincode::config::standard()).unwrap();
            bincode::serde::decode_from_slice(&bytes, bincode::config::standard())
                .unwrap()
                .0
        })
        .collect();

    let mut resumed = Engine::new(config());
    resumed.resume_decisions(stored);
    for keyframe_id in 0..FRAMES.len() - 1 {
        resumed.add_keyframe(arrival(&dataset, keyframe_id));
    }
    assert_eq!(resumed.stored_decisions_waiting(), 0);
    assert!(
        resumed.next_job().is_none(),
        "a pair with a stored decision was queued for alignment again"
    );
    assert_eq!(resumed.graph.loops(), live.graph.loops(), "closures differ");
    assert_eq!(json(resumed.events()), json(live.events()));

    // A keyframe published after the resume is aligned as live.
    let last = FRAMES.len() - 1;
    live.add_keyframe(arrival(&dataset, last));
    resumed.add_keyframe(arrival(&dataset, last));
    assert_eq!(align_all(&mut live).len(), 1);
    assert_eq!(
        align_all(&mut resumed).len(),
        1,
        "the new pair was not aligned"
    );
    assert_eq!(resumed.graph.loops().len(), live.graph.loops().len());
    let (live_solution, resumed_solution) = (
        live.solve_if_changed().unwrap().world_from_camera.clone(),
        resumed
            .solve_if_changed()
            .unwrap()
            .world_from_camera
            .clone(),
    );
    assert_eq!(live_solution, resumed_solution);
}

#[test]
fn a_stored_decision_waits_for_its_keyframes() {
    let dataset = dataset();
    let mut live = Engine::new(config());
    live.add_keyframe(arrival(&dataset, 0));
    live.add_keyframe(arrival(&dataset, 1));
    let decisions = align_all(&mut live);

    let mut resumed = Engine::new(config());
    resumed.resume_decisions(decisions);
    resumed.add_keyframe(arrival(&dataset, 0));
    assert_eq!(resumed.stored_decisions_waiting(), 1);
    assert!(resumed.graph.loops().is_empty());
    resumed.add_keyframe(arrival(&dataset, 1));
    assert_eq!(resumed.stored_decisions_waiting(), 0);
    assert_eq!(resumed.graph.loops(), live.graph.loops());
}
