//! Joint photometric refinement on the synthetic scene (exact images, depth and poses): a merged
//! map made from two "agents'" views, with colours that disagree between the agents (as two
//! agents' maps do where they overlap), is refined against the views. Runs on the CPU Vulkan
//! device (lavapipe) in CI.

use config::ConsensusConfig;
use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{Dataset, Frame, FrameRange};
use mac_consensus::place_recognition::KeyframeRef;
use mac_consensus::refinement::{PoseEdge, RefinementProblem, RefinementView, refine};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use splats::GaussianCloud;

const WIDTH: u32 = 160;
const HEIGHT: u32 = 120;
const FRAMES: usize = 60;
/// Views taken from the sequence, every this many frames.
const VIEW_STEP: usize = 15;
/// Pixels between back-projected map points.
const MAP_STRIDE: u32 = 2;
/// Colour error of the degraded map: one agent too bright, the other too dark.
const COLOUR_BIAS: f32 = 0.15;
const INITIAL_OPACITY_LOGIT: f32 = 2.0;

fn frames() -> Vec<Frame> {
    let spec = SyntheticSpec {
        agents: 1,
        frames: FRAMES,
        width: WIDTH,
        height: HEIGHT,
        ..SyntheticSpec::default()
    }
    .with_agent(0);
    let dataset = SyntheticDataset::new(spec, FrameRange::ALL).unwrap();
    (0..dataset.len())
        .step_by(VIEW_STEP)
        .map(|k| dataset.load(k).unwrap())
        .collect()
}

/// Every `MAP_STRIDE`-th pixel of each frame back-projected with its true pose; view `k`'s
/// colours biased by `+-colour_bias` (even views one way, odd views the other).
fn map_from_views(frames: &[Frame], colour_bias: f32) -> GaussianCloud {
    let mut cloud = GaussianCloud::default();
    for (k, frame) in frames.iter().enumerate() {
        let pose = frame.world_from_camera_gt.unwrap();
        let bias = if k % 2 == 0 {
            colour_bias
        } else {
            -colour_bias
        };
        let i = &frame.intrinsics;
        for y in (0..HEIGHT).step_by(MAP_STRIDE as usize) {
            for x in (0..WIDTH).step_by(MAP_STRIDE as usize) {
                let z = f64::from(frame.depth.get(x, y));
                if z <= 0.0 {
                    continue;
                }
                let camera_point = nalgebra::Point3::new(
                    (f64::from(x) - i.cx) * z / i.fx,
                    (f64::from(y) - i.cy) * z / i.fy,
                    z,
                );
                let world = pose * camera_point;
                // A footprint of about the sample spacing.
                let sigma = (f64::from(MAP_STRIDE) * z / i.fx) as f32;
                let pixel = frame.rgb.get_pixel(x, y).0;
                cloud.push(
                    [world.x, world.y, world.z].map(|v| v as f32),
                    [sigma.ln(); 3],
                    [1.0, 0.0, 0.0, 0.0],
                    INITIAL_OPACITY_LOGIT,
                    pixel.map(|c| (f32::from(c) / 255.0 + bias).clamp(0.0, 1.0)),
                );
            }
        }
    }
    cloud
}

fn view(k: usize, frame: &Frame, world_from_camera: Isometry3<f64>) -> RefinementView {
    RefinementView {
        id: KeyframeRef {
            agent_id: (k % 2) as u32,
            keyframe_id: k as u64,
        },
        world_from_camera,
        intrinsics: frame.intrinsics,
        rgb8: frame.rgb.as_raw().clone(),
        depth_m: frame.depth.data.clone(),
    }
}

fn config(iterations: usize, refine_poses: bool) -> ConsensusConfig {
    let mut config = ConsensusConfig::default();
    // Exactly `iterations` in all, however many views.
    config.refinement.max_iterations = iterations;
    config.refinement.iterations_per_view = iterations;
    config.refinement.image_downscale = 1;
    config.refinement.refine_poses = refine_poses;
    config
}

#[test]
fn refinement_makes_the_merged_map_agree_with_every_view() {
    let frames = frames();
    let views: Vec<RefinementView> = frames
        .iter()
        .enumerate()
        .map(|(k, f)| view(k, f, f.world_from_camera_gt.unwrap()))
        .collect();
    let outcome = refine(
        RefinementProblem {
            map: map_from_views(&frames, COLOUR_BIAS),
            views,
            edges: Vec::new(),
            anchor: Some(0),
        },
        &config(60, false),
    )
    .unwrap();
    let report = &outcome.report;
    let (before, after) = (
        report.psnr_views_before.unwrap(),
        report.psnr_views_after.unwrap(),
    );
    eprintln!(
        "view PSNR {before:.2} -> {after:.2} dB in {:.1} s",
        report.seconds
    );
    assert_eq!(report.iterations, 60);
    assert!(after > before + 3.0, "PSNR {before} -> {after}");
    assert_eq!(outcome.map.len(), report.gaussians);
    assert!(outcome.map.colours.iter().flatten().all(|c| c.is_finite()));
    // Poses were not asked to move.
    for (k, frame) in frames.iter().enumerate() {
        let id = KeyframeRef {
            agent_id: (k % 2) as u32,
            keyframe_id: k as u64,
        };
        assert_eq!(
            outcome.world_from_camera[&id],
            frame.world_from_camera_gt.unwrap()
        );
    }
}

#[test]
fn pose_refinement_keeps_the_anchor_and_reduces_the_pose_disagreement() {
    let frames = frames();
    // View 1's pose is off by 1 cm and 0.3 degrees; the odometry edges (the true relative poses)
    // and the images disagree with it; the anchor (view 0) must not move.
    let error = Isometry3::from_parts(
        Translation3::new(0.01, 0.0, 0.0),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.3f64.to_radians(), 0.0)),
    );
    let truth: Vec<Isometry3<f64>> = frames
        .iter()
        .map(|f| f.world_from_camera_gt.unwrap())
        .collect();
    let views: Vec<RefinementView> = frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let pose = if k == 1 { truth[k] * error } else { truth[k] };
            view(k, f, pose)
        })
        .collect();
    let edges: Vec<PoseEdge> = (1..frames.len())
        .map(|j| PoseEdge {
            i: j - 1,
            j,
            camera_i_from_camera_j: truth[j - 1].inverse() * truth[j],
        })
        .collect();
    let mut config = config(80, true);
    config.refinement.pose_warmup_fraction = 0.25;
    // An unbiased map: only the pose is wrong.
    let map = map_from_views(&frames, 0.0);
    let outcome = refine(
        RefinementProblem {
            map,
            views,
            edges,
            anchor: Some(0),
        },
        &config,
    )
    .unwrap();
    let report = &outcome.report;
    eprintln!("{report:?}");
    let anchor = KeyframeRef {
        agent_id: 0,
        keyframe_id: 0,
    };
    assert_eq!(outcome.world_from_camera[&anchor], truth[0]);
    assert!(report.pose_consistency_after < report.pose_consistency_before);
    let moved = KeyframeRef {
        agent_id: 1,
        keyframe_id: 1,
    };
    let error_before = (truth[1] * error).translation.vector - truth[1].translation.vector;
    let error_after =
        outcome.world_from_camera[&moved].translation.vector - truth[1].translation.vector;
    eprintln!(
        "view 1 position error {:.2} -> {:.2} mm",
        error_before.norm() * 1e3,
        error_after.norm() * 1e3
    );
    assert!(error_after.norm() < error_before.norm());
}

#[test]
fn gaussians_the_refinement_leaves_transparent_are_pruned() {
    let frames = frames();
    let views: Vec<RefinementView> = frames
        .iter()
        .enumerate()
        .map(|(k, f)| view(k, f, f.world_from_camera_gt.unwrap()))
        .collect();
    let mut map = map_from_views(&frames, 0.0);
    let visible = map.len();
    // Nearly transparent copies far behind every view (a faded duplicate): nothing brings
    // them back, and the pruning removes them.
    const FADED: usize = 40;
    for k in 0..FADED {
        map.push(
            [k as f32 * 0.05, 50.0, 50.0],
            [0.01f32.ln(); 3],
            [1.0, 0.0, 0.0, 0.0],
            -8.0,
            [0.5; 3],
        );
    }
    let mut config = config(8, false);
    config.refinement.prune_min_opacity = 0.005;
    config.refinement.lr_final_fraction = 0.1;
    let outcome = refine(
        RefinementProblem {
            map,
            views,
            edges: Vec::new(),
            anchor: Some(0),
        },
        &config,
    )
    .unwrap();
    assert_eq!(outcome.report.gaussians, visible + FADED);
    assert!(outcome.report.pruned >= FADED, "{:?}", outcome.report);
    assert_eq!(outcome.map.len(), visible + FADED - outcome.report.pruned);
    assert!(outcome.map.means.iter().all(|m| m[1] < 49.0));
}

/// `poses_first_fraction`: the first iterations step the poses alone. Here all of them do: the
/// map comes back as it went in, bit for bit, while the poses (all but the anchor's) moved.
#[test]
fn in_the_poses_first_phase_only_the_poses_move() {
    let frames = frames();
    let error = Isometry3::from_parts(
        Translation3::new(0.01, 0.0, 0.0),
        UnitQuaternion::identity(),
    );
    let truth: Vec<Isometry3<f64>> = frames
        .iter()
        .map(|f| f.world_from_camera_gt.unwrap())
        .collect();
    let start: Vec<Isometry3<f64>> = (0..frames.len())
        .map(|k| if k == 1 { truth[k] * error } else { truth[k] })
        .collect();
    let views: Vec<RefinementView> = frames
        .iter()
        .enumerate()
        .map(|(k, f)| view(k, f, start[k]))
        .collect();
    let mut config = config(40, true);
    config.refinement.poses_first_fraction = 1.0;
    let map = map_from_views(&frames, 0.0);
    let outcome = refine(
        RefinementProblem {
            map: map.clone(),
            views,
            edges: Vec::new(),
            anchor: Some(0),
        },
        &config,
    )
    .unwrap();
    assert_eq!(outcome.report.iterations, 40);
    assert_eq!(outcome.map, map, "the map holds while the poses go first");
    for (k, pose) in start.iter().enumerate() {
        let id = KeyframeRef {
            agent_id: (k % 2) as u32,
            keyframe_id: k as u64,
        };
        let refined = outcome.world_from_camera[&id];
        if k == 0 {
            assert_eq!(refined, *pose, "the anchor never moves");
        } else {
            assert_ne!(refined, *pose, "view {k} took pose steps");
        }
    }
}
