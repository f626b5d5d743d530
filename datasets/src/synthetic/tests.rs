//! Tests of the synthetic scene: spec parsing, determinism, exact depth, smooth trajectories,
//! overlap between agents, and the written dataset reading back identical.

use nalgebra::{Isometry3, Point3, Translation3, Vector3};

use geometry::depth::DepthImage;

use super::dataset::*;
use super::render::*;
use super::scene::*;
use super::shapes::*;
use super::spec::*;
use super::walk::*;
use super::writer::*;
use crate::seven_scenes::{DEPTH_UNITS_PER_METRE, INVALID_DEPTH_RAW};
use crate::{Dataset, FrameRange};
use std::f64::consts::PI;

/// Small images keep the rendering tests fast in the lightly optimised test build.
const TEST_WIDTH: u32 = 160;
const TEST_HEIGHT: u32 = 120;

/// How far a rotation may move through the pose file's re-orthonormalisation.
const POSE_FILE_ROTATION_TOLERANCE_RAD: f64 = 1e-10;

fn small_spec(agents: usize, agent: usize, frames: usize, seed: u64) -> SyntheticSpec {
    SyntheticSpec {
        agents,
        agent,
        frames,
        seed,
        width: TEST_WIDTH,
        height: TEST_HEIGHT,
    }
}

fn camera_looking(eye: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(eye), look_at(&eye, &target, 0.0))
}

#[test]
fn spec_parses_defaults_keys_and_round_trips() {
    let default: SyntheticSpec = "synthetic".parse().unwrap();
    assert_eq!(default, SyntheticSpec::default());
    assert_eq!(
        (default.agents, default.agent, default.frames, default.seed),
        (3, 0, 300, 0)
    );
    assert_eq!((default.width, default.height), (640, 480));
    let spec: SyntheticSpec = "synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240"
        .parse()
        .unwrap();
    assert_eq!(
        spec,
        SyntheticSpec {
            agents: 3,
            agent: 1,
            frames: 300,
            seed: 7,
            width: 320,
            height: 240
        }
    );
    assert_eq!(
        spec.to_string(),
        "synthetic:agents=3,agent=1,frames=300,seed=7,width=320,height=240"
    );
    assert_eq!(spec.to_string().parse::<SyntheticSpec>().unwrap(), spec);
    let partial: SyntheticSpec = "synthetic: seed=9 , agent=2".parse().unwrap();
    assert_eq!(
        (partial.seed, partial.agent, partial.frames),
        (9, 2, DEFAULT_FRAMES)
    );
}

#[test]
fn spec_errors_name_the_bad_key() {
    let cases = [
        ("synthetic:agnets=3", "agnets"),
        ("synthetic:frames=many", "frames"),
        ("synthetic:seed=-1", "seed"),
        ("synthetic:width=12", "width"),
        ("synthetic:height=0", "height"),
        ("synthetic:agents=2,agent=2", "agent=2"),
        ("synthetic:agents=0", "agents=0"),
        ("synthetic:frames=0", "frames=0"),
        ("synthetic:seed=1,seed=2", "seed"),
        ("synthetic:seed", "seed"),
    ];
    for (text, key) in cases {
        let err = text.parse::<SyntheticSpec>().unwrap_err();
        assert!(
            err.contains(key),
            "{text}: error {err:?} does not name {key:?}"
        );
    }
    assert!("synthetics".parse::<SyntheticSpec>().is_err());
    assert!("replica".parse::<SyntheticSpec>().is_err());
}

#[test]
fn intrinsics_follow_the_resolution() {
    let k = SyntheticSpec::default().intrinsics();
    assert_eq!(
        (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        (525.0, 525.0, 319.5, 239.5, 640, 480)
    );
    let half = small_spec(1, 0, 1, 0).intrinsics();
    let expected = k.scaled(0.25);
    assert!(
        (half.fx - expected.fx).abs() < 1e-12
            && (half.cx - expected.cx).abs() < 1e-12
            && (half.cy - expected.cy).abs() < 1e-12
    );
}

#[test]
fn frames_are_deterministic_for_a_seed_and_thread_count() {
    let spec = small_spec(2, 1, 40, 5);
    let a = SyntheticDataset::new(spec, FrameRange::ALL)
        .unwrap()
        .load(17)
        .unwrap();
    let single_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = single_thread.install(|| {
        SyntheticDataset::new(spec, FrameRange::ALL)
            .unwrap()
            .load(17)
            .unwrap()
    });
    assert_eq!(a.rgb, b.rgb);
    assert_eq!(a.depth, b.depth);
    assert_eq!(a.world_from_camera_gt, b.world_from_camera_gt);
    let other_seed = SyntheticDataset::new(SyntheticSpec { seed: 6, ..spec }, FrameRange::ALL)
        .unwrap()
        .load(17)
        .unwrap();
    assert_ne!(a.rgb, other_seed.rgb);
    assert_ne!(a.world_from_camera_gt, other_seed.world_from_camera_gt);
}

#[test]
fn range_selects_frame_numbers_and_timestamps() {
    let ds = SyntheticDataset::new(small_spec(3, 2, 50, 0), "10..20".parse().unwrap()).unwrap();
    assert_eq!(ds.len(), 10);
    assert_eq!(ds.frame_index(0), 10);
    assert_eq!(ds.timestamp(3), 13.0 / 30.0);
    let all = SyntheticDataset::new(small_spec(3, 2, 50, 0), FrameRange::ALL).unwrap();
    assert_eq!(ds.ground_truth(3).unwrap(), all.ground_truth(13).unwrap());
    let err = SyntheticDataset::new(small_spec(3, 2, 50, 0), "60..".parse().unwrap())
        .err()
        .unwrap();
    assert!(err.to_string().contains("60.."), "{err}");
    assert!(SyntheticDataset::new(small_spec(3, 3, 50, 0), FrameRange::ALL).is_err());
}

#[test]
fn depth_is_exact_camera_z_on_known_planes() {
    let scene = Scene::generate(0);
    let k = small_spec(1, 0, 1, 0).intrinsics();
    let eye = Vector3::new(0.1, -0.2, 1.5);
    let ceiling = ROOM_MAX[2];
    // Straight up at the ceiling: every pixel's camera z is the height difference.
    // The identity rotation looks along world +z: camera x = east, y = north, z = up.
    let up = Isometry3::translation(eye.x, eye.y, eye.z);
    let (_, depth) = render(&scene, &k, &up);
    let expected = ((ceiling - eye.z) * 1000.0).round() as f32 / 1000.0;
    assert!(
        depth.data.iter().all(|&d| (d - expected).abs() < 1e-6),
        "ceiling depth should be {expected} everywhere"
    );

    // Obliquely at the ceiling: z = (ceiling - eye_z) / (world-z component of the ray with
    // unit camera z), exact up to millimetre quantisation.
    let oblique = camera_looking(eye, eye + Vector3::new(1.0, 0.6, 1.2));
    let (_, depth) = render(&scene, &k, &oblique);
    let rotation = oblique.rotation.to_rotation_matrix();
    let mut checked = 0;
    for v in 0..k.height {
        for u in 0..k.width {
            let ray =
                rotation * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
            if ray.z <= 0.0 {
                continue;
            }
            let z = (ceiling - eye.z) / ray.z;
            let hit = eye + ray * z;
            // Only rays that reach the ceiling well inside the walls.
            let margin = 0.05;
            if hit.x.abs() > ROOM_MAX[0] - margin || hit.y.abs() > ROOM_MAX[1] - margin {
                continue;
            }
            let got = depth.get(u, v) as f64;
            assert!(
                (got - z).abs() <= 0.0005 + 1e-6,
                "pixel ({u}, {v}): depth {got}, expected {z}"
            );
            checked += 1;
        }
    }
    assert!(
        checked > (k.width * k.height / 2) as usize,
        "only {checked} pixels reached the ceiling"
    );

    // The optical axis through the centre of a sphere hits it at distance - radius.
    let (center, radius) = scene
        .primitives
        .iter()
        .find_map(|p| match p.shape {
            Shape::Sphere { center, radius } if radius > 0.3 => Some((center, radius)),
            _ => None,
        })
        .unwrap();
    let square = SyntheticSpec {
        width: 81,
        height: 61,
        ..small_spec(1, 0, 1, 0)
    }
    .intrinsics();
    let viewer = Vector3::new(0.5, 0.3, 1.2);
    let (_, depth) = render(&scene, &square, &camera_looking(viewer, center));
    let expected = (center - viewer).norm() - radius;
    let got = depth.get(40, 30) as f64;
    assert!(
        (got - expected).abs() <= 0.0005 + 1e-6,
        "sphere depth {got}, expected {expected}"
    );
}

#[test]
fn depth_quantisation_matches_the_png_reader() {
    for z in [
        0.0004,
        0.0006,
        1.2344,
        1.2346,
        3.0,
        65.534,
        65.5346,
        f64::INFINITY,
        f64::NAN,
        -1.0,
    ] {
        let raw = depth_to_raw(z);
        let streamed =
            DepthImage::from_raw_u16(1, 1, &[raw], DEPTH_UNITS_PER_METRE, Some(INVALID_DEPTH_RAW));
        let written = streamed.to_raw_u16(DEPTH_UNITS_PER_METRE);
        assert_eq!(written, vec![raw], "z = {z}");
        let valid = z.is_finite() && (0.0005..65.5345).contains(&z);
        assert_eq!(raw > 0, valid, "z = {z} gave raw {raw}");
    }
}

#[test]
fn frames_have_valid_depth_and_texture() {
    let ds = SyntheticDataset::new(small_spec(3, 0, 300, 0), FrameRange::ALL).unwrap();
    for position in [0, 150, 299] {
        let frame = ds.load(position).unwrap();
        let pixels = frame.depth.data.len();
        assert!(frame.depth.valid_count() as f64 >= 0.95 * pixels as f64);
        let min_depth = frame
            .depth
            .data
            .iter()
            .copied()
            .filter(|&d| d > 0.0)
            .fold(f32::INFINITY, f32::min);
        assert!(
            min_depth > 0.3,
            "frame {position}: something {min_depth} m from the camera"
        );
        // Texture: grey-level gradients are present over most of the image.
        let grey: Vec<f64> = frame
            .rgb
            .pixels()
            .map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0)
            .collect();
        let w = frame.rgb.width() as usize;
        let textured = (0..grey.len() - w - 1)
            .filter(|&i| (grey[i + 1] - grey[i]).abs() + (grey[i + w] - grey[i]).abs() > 2.0)
            .count();
        assert!(
            textured as f64 > 0.3 * pixels as f64,
            "frame {position}: only {textured} textured pixels"
        );
        let mean = grey.iter().sum::<f64>() / grey.len() as f64;
        assert!(
            (50.0..210.0).contains(&mean),
            "frame {position}: mean grey {mean}"
        );
    }
}

/// Per-frame translation (m) and rotation (rad) of a trajectory, maxima.
fn max_steps(poses: &[Isometry3<f64>]) -> (f64, f64) {
    poses.windows(2).fold((0.0, 0.0), |(t, r), w| {
        let delta = w[0].inverse() * w[1];
        (
            t.max(delta.translation.vector.norm()),
            r.max(delta.rotation.angle()),
        )
    })
}

#[test]
fn trajectories_are_smooth_and_stay_clear_of_walls_and_objects() {
    const MAX_STEP_M: f64 = 0.03;
    const MAX_TURN_RAD: f64 = 2.0 * PI / 180.0;
    const CLEARANCE_M: f64 = 0.3;
    for seed in 0..4 {
        let scene = Scene::generate(seed);
        for agents in [1, 3, 5] {
            for agent in 0..agents {
                let spec = SyntheticSpec {
                    agents,
                    agent,
                    frames: 1200,
                    seed,
                    ..SyntheticSpec::default()
                };
                let poses = trajectory(&spec);
                let (step, turn) = max_steps(&poses);
                assert!(
                    step <= MAX_STEP_M,
                    "seed {seed} agent {agent}/{agents}: step {step} m"
                );
                assert!(
                    turn <= MAX_TURN_RAD,
                    "seed {seed} agent {agent}/{agents}: turn {} deg",
                    turn.to_degrees()
                );
                for (frame, pose) in poses.iter().enumerate() {
                    let p = pose.translation.vector;
                    for axis in 0..3 {
                        assert!(
                            p[axis] > ROOM_MIN[axis] + CLEARANCE_M
                                && p[axis] < ROOM_MAX[axis] - CLEARANCE_M,
                            "seed {seed} agent {agent} frame {frame}: {p:?} too close to the room's walls"
                        );
                    }
                    for primitive in &scene.primitives {
                        let distance = primitive.distance(&p);
                        assert!(
                            distance > CLEARANCE_M,
                            "seed {seed} agent {agent} frame {frame}: {distance} m from {primitive:?}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn agents_start_apart_and_revisit_each_others_places() {
    const NEAR_M: f64 = 0.5;
    const SIMILAR_VIEW_RAD: f64 = 30.0 * PI / 180.0;
    let agents = 3;
    let trajectories: Vec<Vec<Isometry3<f64>>> = (0..agents)
        .map(|agent| {
            trajectory(&SyntheticSpec {
                agent,
                ..SyntheticSpec::default()
            })
        })
        .collect();
    for a in 0..agents {
        for b in a + 1..agents {
            let start_gap = (trajectories[a][0].translation.vector
                - trajectories[b][0].translation.vector)
                .norm();
            assert!(
                start_gap > 1.0,
                "agents {a} and {b} start only {start_gap} m apart"
            );
        }
    }
    // Every agent shares at least one place (near, looking the same way) with another agent.
    let mut best_pair = None;
    for a in 0..agents {
        let mut overlaps = 0;
        for b in (0..agents).filter(|&b| b != a) {
            for (i, pa) in trajectories[a].iter().enumerate() {
                for (j, pb) in trajectories[b].iter().enumerate() {
                    let gap = (pa.translation.vector - pb.translation.vector).norm();
                    let view_angle =
                        (pa.rotation * Vector3::z()).angle(&(pb.rotation * Vector3::z()));
                    if gap < NEAR_M && view_angle < SIMILAR_VIEW_RAD {
                        overlaps += 1;
                        if best_pair.is_none() {
                            best_pair = Some((a, i, b, j));
                        }
                    }
                }
            }
        }
        assert!(overlaps > 0, "agent {a} never sees what another agent sees");
    }

    // Geometric and photometric consistency of one such pair: agent a's depth, moved into
    // agent b's camera with the ground-truth poses, agrees with b's depth, and the colours of
    // corresponding pixels agree (Lambertian shading is view independent).
    let (a, i, b, j) = best_pair.unwrap();
    let frame_a = SyntheticDataset::new(small_spec(agents, a, 300, 0), FrameRange::ALL)
        .unwrap()
        .load(i)
        .unwrap();
    let frame_b = SyntheticDataset::new(small_spec(agents, b, 300, 0), FrameRange::ALL)
        .unwrap()
        .load(j)
        .unwrap();
    let k = frame_a.intrinsics;
    let b_from_a =
        frame_b.world_from_camera_gt.unwrap().inverse() * frame_a.world_from_camera_gt.unwrap();
    let (mut visible, mut consistent, mut colour_error) = (0usize, 0usize, 0.0);
    for v in 0..k.height {
        for u in 0..k.width {
            let z = frame_a.depth.get(u, v) as f64;
            if z <= 0.0 {
                continue;
            }
            let p_b = b_from_a * Point3::from(k.back_project(u as f64, v as f64, z).coords);
            let Some(pixel) = k.project(&p_b) else {
                continue;
            };
            if !k.contains(&pixel) {
                continue;
            }
            visible += 1;
            let (ub, vb) = (pixel.x.round() as u32, pixel.y.round() as u32);
            // One pixel of rounding at a slanted surface moves depth by up to a few cm.
            if (frame_b.depth.get(ub, vb) as f64 - p_b.z).abs() < 0.03 * p_b.z {
                consistent += 1;
                let (ca, cb) = (frame_a.rgb.get_pixel(u, v), frame_b.rgb.get_pixel(ub, vb));
                colour_error += (0..3)
                    .map(|c| (ca[c] as f64 - cb[c] as f64).abs())
                    .sum::<f64>()
                    / 3.0;
            }
        }
    }
    let pixels = (k.width * k.height) as usize;
    assert!(
        visible as f64 > 0.5 * pixels as f64,
        "agents {a}/{b}: only {visible} of {pixels} pixels co-visible"
    );
    assert!(
        consistent as f64 > 0.85 * visible as f64,
        "agents {a}/{b}: {consistent} of {visible} depths agree"
    );
    let mean_colour_error = colour_error / consistent as f64;
    assert!(
        mean_colour_error < 12.0,
        "agents {a}/{b}: mean colour difference {mean_colour_error}"
    );
}

#[test]
fn written_dataset_reads_back_identical() {
    let dir = tempfile::tempdir().unwrap();
    let spec = SyntheticSpec {
        width: 64,
        height: 48,
        ..small_spec(2, 0, 4, 3)
    };
    let mut calls = Vec::new();
    let folders =
        write_seven_scenes(&spec, dir.path(), |done, total| calls.push((done, total))).unwrap();
    assert_eq!(
        folders,
        vec![dir.path().join("agent_0"), dir.path().join("agent_1")]
    );
    assert_eq!(calls.last(), Some(&(8, 8)));
    assert!(dir.path().join(SCENE_FILE).is_file());
    for (agent, folder) in folders.iter().enumerate() {
        let streamed = SyntheticDataset::new(spec.with_agent(agent), FrameRange::ALL).unwrap();
        let read = crate::open(folder.to_str().unwrap(), FrameRange::ALL).unwrap();
        assert_eq!(read.len(), streamed.len());
        let (ki, ks) = (read.intrinsics(), streamed.intrinsics());
        assert_eq!((ki.width, ki.height), (ks.width, ks.height));
        for (x, y) in [
            (ki.fx, ks.fx),
            (ki.fy, ks.fy),
            (ki.cx, ks.cx),
            (ki.cy, ks.cy),
        ] {
            assert!(
                (x - y).abs() <= 1e-12 * y.abs().max(1.0),
                "intrinsics {ki:?} vs {ks:?}"
            );
        }
        for position in 0..streamed.len() {
            let (a, b) = (
                streamed.load(position).unwrap(),
                read.load(position).unwrap(),
            );
            assert_eq!(a.index, b.index);
            assert_eq!(a.timestamp, b.timestamp);
            assert_eq!(
                a.rgb, b.rgb,
                "agent {agent} frame {position}: colour differs"
            );
            assert_eq!(
                a.depth, b.depth,
                "agent {agent} frame {position}: depth differs"
            );
            // Translations survive the 17-digit pose file exactly; the reader re-orthonormalises
            // the rotation matrix iteratively (to 1e-12), which moves the last bits.
            let (pa, pb) = (
                a.world_from_camera_gt.unwrap(),
                b.world_from_camera_gt.unwrap(),
            );
            assert_eq!(
                pa.translation, pb.translation,
                "agent {agent} frame {position}"
            );
            let rotation_error = pa.rotation.angle_to(&pb.rotation);
            assert!(
                rotation_error < POSE_FILE_ROTATION_TOLERANCE_RAD,
                "agent {agent} frame {position}: rotation differs by {rotation_error} rad"
            );
        }
    }
    // A second write into the same folder is refused; after remove_written it works again.
    let err = write_seven_scenes(&spec, dir.path(), |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("agent_0") && err.contains("not empty"),
        "{err}"
    );
    let removed = remove_written(dir.path()).unwrap();
    assert_eq!(removed, 2 * (4 * 3 + 2) + 1);
    assert!(!dir.path().join("agent_0").exists());
    write_seven_scenes(&spec, dir.path(), |_, _| {}).unwrap();
}

#[test]
fn open_streams_the_synthetic_spec() {
    let ds = crate::open(
        "synthetic:agents=2,agent=1,frames=5,width=32,height=24",
        "2..".parse().unwrap(),
    )
    .unwrap();
    assert_eq!(ds.len(), 3);
    assert_eq!(ds.frame_index(0), 2);
    let frame = ds.load(0).unwrap();
    assert_eq!((frame.rgb.width(), frame.depth.height), (32, 24));
    assert!(ds.describe().contains("agent=1"));
}

/// Rendering throughput, for the record: `cargo test --release -p datasets render_speed --
/// --ignored --nocapture`.
mod speed {
    use super::*;

    #[test]
    #[ignore = "timing, not a check; run with --release"]
    fn render_speed() {
        let ds = SyntheticDataset::new(SyntheticSpec::default(), FrameRange::ALL).unwrap();
        let frames = 30;
        let started = std::time::Instant::now();
        for position in 0..frames {
            std::hint::black_box(ds.load(position * 10).unwrap());
        }
        let seconds = started.elapsed().as_secs_f64();
        println!(
            "rendered {frames} frames at 640x480 in {seconds:.2} s: {:.1} frames/s on {} threads",
            frames as f64 / seconds,
            rayon::current_num_threads()
        );
    }
}
