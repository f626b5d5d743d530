//! Where keyframe matching loses its matches across wide baselines: a stage-by-stage diagnostic
//! of the coarse alignment (keypoints, depth lifting, descriptor matching, RANSAC) on pairs of
//! frames whose relative pose is known from ground truth. A table on stdout, JSON with `--json`.
//!
//! ```text
//! cargo run -p mac-consensus --example keyframe_matching -- [--pairs 8] [--synthetic-pairs 8]
//!     [--seed 0] [--rolls 0,30,60,90,180] [--radius 0.03] [--verbose] [--json out.json]
//!     [--variant NAME='{"steer_descriptors": false, "descriptor_radius_m": 0}'] ...
//!     [--rgb-focal 527 --rgb-baseline -0.025] [--dump folder]
//! ```
//!
//! Pairs: redkitchen frames (the shared 7-Scenes folder) at least 200 frames apart whose cameras
//! are 1.5-3.5 m apart and of which 15-40 % of the first frame's depth points are seen by the
//! second (projected with the ground-truth poses, depth agreeing); the same between the two
//! agents of the synthetic scene; and one synthetic pair about 1 m apart re-rendered with the
//! second camera rolled about its optical axis. Real ground truth (KinectFusion) is off by 2-7 cm
//! between distant frames: it is polished with G-ICP before it scores. Per pair and configuration
//! variant (`--variant`: AlignmentConfig fields changed from the defaults) it measures:
//!
//! - detected / lifted keypoints, clustering (another keypoint within 2 pixels) and the share of
//!   an 8x6 grid holding one; how many of A's lie where B sees the same surface (`covis`);
//! - `rep`: lifted keypoints of A with a lifted keypoint of B within `--radius` after the true
//!   transform (the ceiling of what any descriptor could match; includes chance neighbours);
//! - `nn+`: keypoints of A whose nearest descriptor in B is geometrically correct, split by the
//!   local in-plane rotation and scale change between the views; `top2`: correct in the best two;
//!   `ori`: median error of the keypoint orientations;
//! - an oracle: B described exactly where A's covisible keypoints fall, its Hamming distance to
//!   A's descriptor against that of A's nearest real neighbour (descriptor invariance alone);
//! - correct / all matches: mutual with the configured cap and ratio, without the cap, with a
//!   0.8 ratio test, one-way nearest neighbours;
//! - RANSAC inliers consistent with the truth / all, the verdict, the pose error, and the time
//!   to prepare a keyframe (features and cloud) and to align a prepared pair.
//!
//! `--rgb-focal`/`--rgb-baseline` resample the real colour images onto the depth camera first
//! (7-Scenes' colour and depth are not registered), to measure what the misregistration costs.
//! Ground truth only scores; the method sees images, depth and intrinsics.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use config::AlignmentConfig;
use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{self, Dataset, FrameRange};
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use mac_consensus::alignment::features::{Features, describe_at, hamming};
use mac_consensus::alignment::{Keyframe, PreparedKeyframe, align_prepared};
use mac_consensus::place_recognition::KeyframeRef;
use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use registration::{GicpParams, register_coarse_to_fine};
use serde::Serialize;

#[derive(Parser)]
struct Args {
    /// 7-Scenes-layout folder with ground truth (default: the shared redkitchen frames).
    #[arg(long)]
    dataset: Option<String>,
    /// Real-data pairs at most.
    #[arg(long, default_value_t = 8)]
    pairs: usize,
    /// Synthetic cross-agent pairs at most.
    #[arg(long, default_value_t = 4)]
    synthetic_pairs: usize,
    /// Seed of the synthetic scene (textures, furniture, trajectories).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Extra camera rolls (degrees) of the second view of one synthetic pair.
    #[arg(long, value_delimiter = ',', default_value = "0,30,60,90")]
    rolls: Vec<f64>,
    /// Configuration variants: NAME=JSON object of AlignmentConfig fields to change. Without
    /// any, the default configuration runs as "default".
    #[arg(long)]
    variant: Vec<String>,
    /// Distance (metres) within which two keypoints are the same 3-D point.
    #[arg(long, default_value_t = 0.04)]
    radius: f64,
    /// Camera baseline range (metres) of the chosen pairs.
    #[arg(long, default_value_t = 1.5)]
    min_baseline: f64,
    #[arg(long, default_value_t = 3.5)]
    max_baseline: f64,
    /// Co-visibility range of the chosen pairs.
    #[arg(long, default_value_t = 0.15)]
    min_covisibility: f64,
    #[arg(long, default_value_t = 0.40)]
    max_covisibility: f64,
    /// Also write the report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Score against the recorded ground truth as it is (no G-ICP polish).
    #[arg(long)]
    raw_truth: bool,
    /// Write each pair side by side with its keypoints (PNG) into this folder: green a keypoint
    /// with a correct nearest neighbour, yellow one that is only repeatable, grey the rest.
    #[arg(long)]
    dump: Option<PathBuf>,
    /// Focal length (pixels) of the real data's colour camera when it differs from the depth
    /// camera's (7-Scenes: the colour images are not registered to depth): the colour image
    /// is resampled onto the depth camera's pixels before anything else (a test of how much
    /// the misregistration costs; the baseline between the two cameras is ignored).
    #[arg(long)]
    rgb_focal: Option<f64>,
    /// With `--rgb-focal`: the colour camera's offset along the depth camera's x axis (metres;
    /// redkitchen's edges agree best at 525-530 px and -0.02 to -0.03 m).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    rgb_baseline: f64,
    /// Print per-bucket detail for every pair.
    #[arg(long)]
    verbose: bool,
}

/// One RGB-D view with its ground-truth pose.
struct View {
    label: String,
    rgb: RgbImage,
    depth: DepthImage,
    intrinsics: Intrinsics,
    world_from_camera: Isometry3<f64>,
}

struct Pair {
    name: String,
    a: View,
    b: View,
}

/// Depth-agreement tolerance of the co-visibility measure.
fn depth_agrees(z: f64, observed: f64) -> bool {
    observed > 0.0 && (z - observed).abs() <= 0.05 + 0.02 * z
}

/// Fraction of A's valid depth points (every 8th pixel) that B sees with agreeing depth.
fn covisibility(a: &View, b: &View) -> f64 {
    let b_from_a = b.world_from_camera.inverse() * a.world_from_camera;
    let (mut valid, mut seen) = (0usize, 0usize);
    for v in (0..a.depth.height).step_by(8) {
        for u in (0..a.depth.width).step_by(8) {
            let z = a.depth.get(u, v) as f64;
            if !(z > 0.0 && z < 10.0) {
                continue;
            }
            valid += 1;
            let p = b_from_a * a.intrinsics.back_project(u as f64, v as f64, z);
            if let Some(pixel) = b.intrinsics.project(&p)
                && b.intrinsics.contains(&pixel)
            {
                let observed = b.depth.get(pixel.x.round() as u32, pixel.y.round() as u32) as f64;
                if depth_agrees(p.z, observed) {
                    seen += 1;
                }
            }
        }
    }
    seen as f64 / valid.max(1) as f64
}

fn baseline(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

fn view_angle_deg(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.rotation * Vector3::z())
        .angle(&(b.rotation * Vector3::z()))
        .to_degrees()
}

fn load_view(ds: &dyn Dataset, position: usize, label: String) -> anyhow::Result<View> {
    let frame = ds.load(position)?;
    Ok(View {
        label,
        rgb: frame.rgb,
        depth: frame.depth,
        intrinsics: frame.intrinsics,
        world_from_camera: frame
            .world_from_camera_gt
            .ok_or_else(|| anyhow::anyhow!("frame {position} has no ground truth"))?,
    })
}

/// Candidate pairs (i from `a`, j from `b`) whose baseline and co-visibility lie in range,
/// `count` of them spread over the baseline range, no frame used twice.
fn choose_pairs(
    args: &Args,
    a: &[(usize, View)],
    b: &[(usize, View)],
    min_frame_gap: Option<usize>,
    count: usize,
) -> Vec<(usize, usize, f64)> {
    let mut candidates = Vec::new();
    for (i, va) in a {
        for (j, vb) in b {
            if min_frame_gap.is_some_and(|gap| i.abs_diff(*j) < gap || j < i) {
                continue;
            }
            let d = baseline(&va.world_from_camera, &vb.world_from_camera);
            if d < args.min_baseline || d > args.max_baseline {
                continue;
            }
            let c = covisibility(va, vb);
            if c >= args.min_covisibility && c <= args.max_covisibility {
                candidates.push((*i, *j, d, c));
            }
        }
    }
    candidates.sort_by(|x, y| x.2.total_cmp(&y.2));
    eprintln!("{} candidate pairs in range", candidates.len());
    let mut chosen: Vec<(usize, usize, f64)> = Vec::new();
    let mut used = Vec::new();
    // Spread over the sorted baselines: walk with a stride, skipping reused frames.
    let stride = (candidates.len() / count.max(1)).max(1);
    for offset in 0..stride {
        for k in (offset..candidates.len()).step_by(stride) {
            let (i, j, _, c) = candidates[k];
            if chosen.len() >= count {
                break;
            }
            if used.contains(&(0, i)) || used.contains(&(1, j)) {
                continue;
            }
            used.push((0, i));
            used.push((1, j));
            chosen.push((i, j, c));
        }
    }
    chosen.sort_by_key(|&(i, j, _)| (i, j));
    chosen
}

fn clone_view(v: &View) -> View {
    View {
        label: v.label.clone(),
        rgb: v.rgb.clone(),
        depth: v.depth.clone(),
        intrinsics: v.intrinsics,
        world_from_camera: v.world_from_camera,
    }
}

/// The colour image resampled onto the depth camera's pixels, for a colour camera with focal
/// length `rgb_focal`, the same principal point and `baseline` metres along x (bilinear).
fn register_colour(
    rgb: &RgbImage,
    depth: &DepthImage,
    depth_camera: &Intrinsics,
    rgb_focal: f64,
    baseline: f64,
) -> RgbImage {
    let k = depth_camera;
    RgbImage::from_fn(rgb.width(), rgb.height(), |u, v| {
        let z = depth.get(u, v) as f64;
        let shift = if z > 0.0 {
            rgb_focal * baseline / z
        } else {
            0.0
        };
        let x = (u as f64 - k.cx) / k.fx * rgb_focal + k.cx + shift;
        let y = (v as f64 - k.cy) / k.fy * rgb_focal + k.cy;
        let (x0, y0) = (x.floor().max(0.0), y.floor().max(0.0));
        let (fx, fy) = (x - x0, y - y0);
        let clamp = |a: f64, limit: u32| (a as u32).min(limit - 1);
        let (xa, ya) = (clamp(x0, rgb.width()), clamp(y0, rgb.height()));
        let (xb, yb) = (clamp(x0 + 1.0, rgb.width()), clamp(y0 + 1.0, rgb.height()));
        let mut out = [0u8; 3];
        for (c, value) in out.iter_mut().enumerate() {
            let at = |x: u32, y: u32| rgb.get_pixel(x, y).0[c] as f64;
            let top = at(xa, ya) * (1.0 - fx) + at(xb, ya) * fx;
            let bottom = at(xa, yb) * (1.0 - fx) + at(xb, yb) * fx;
            *value = (top * (1.0 - fy) + bottom * fy).round() as u8;
        }
        image::Rgb(out)
    })
}

fn real_pairs(args: &Args) -> anyhow::Result<Vec<Pair>> {
    let spec = args.dataset.clone().unwrap_or_else(|| {
        datasets::shared_data::shared_dir()
            .join("datasets/7scenes-redkitchen")
            .to_string_lossy()
            .into_owned()
    });
    let ds = match datasets::open(&spec, FrameRange::ALL) {
        Ok(ds) => ds,
        Err(error) => {
            eprintln!("real-data pairs skipped: {spec}: {error}");
            return Ok(Vec::new());
        }
    };
    let views: Vec<(usize, View)> = (0..ds.len())
        .step_by(10)
        .map(|i| {
            let mut view = load_view(ds.as_ref(), i, format!("{i}"))?;
            if let Some(focal) = args.rgb_focal {
                view.rgb = register_colour(
                    &view.rgb,
                    &view.depth,
                    &view.intrinsics,
                    focal,
                    args.rgb_baseline,
                );
            }
            Ok((i, view))
        })
        .collect::<anyhow::Result<_>>()?;
    let chosen = choose_pairs(args, &views, &views, Some(200), args.pairs);
    let by_index: BTreeMap<usize, &View> = views.iter().map(|(i, v)| (*i, v)).collect();
    Ok(chosen
        .into_iter()
        .map(|(i, j, _)| Pair {
            name: format!("redkitchen {i}-{j}"),
            a: clone_view(by_index[&i]),
            b: clone_view(by_index[&j]),
        })
        .collect())
}

fn synthetic_pairs(args: &Args) -> anyhow::Result<Vec<Pair>> {
    let spec = |agent| {
        SyntheticSpec {
            agents: 2,
            frames: 300,
            seed: args.seed,
            ..SyntheticSpec::default()
        }
        .with_agent(agent)
    };
    let (da, db) = (
        SyntheticDataset::new(spec(0), FrameRange::ALL)?,
        SyntheticDataset::new(spec(1), FrameRange::ALL)?,
    );
    let load = |ds: &SyntheticDataset, agent: usize| -> anyhow::Result<Vec<(usize, View)>> {
        (0..ds.len())
            .step_by(10)
            .map(|i| Ok((i, load_view(ds, i, format!("agent{agent}:{i}"))?)))
            .collect()
    };
    let (va, vb) = (load(&da, 0)?, load(&db, 1)?);
    let chosen = choose_pairs(args, &va, &vb, None, args.synthetic_pairs.max(1));
    let find =
        |views: &[(usize, View)], k: usize| clone_view(&views.iter().find(|v| v.0 == k).unwrap().1);
    let mut pairs: Vec<Pair> = chosen
        .iter()
        .take(args.synthetic_pairs)
        .map(|&(i, j, _)| Pair {
            name: format!("synthetic a0:{i}-a1:{j}"),
            a: find(&va, i),
            b: find(&vb, j),
        })
        .collect();
    // Rolled copies of a pair with a moderate baseline: the same geometry, the second camera
    // turned about its optical axis.
    if let Some(&(i, _, _)) = chosen.first() {
        let a = find(&va, i);
        // A partner close enough that the unrolled pair is easy (about 1 m, same direction).
        let j = vb
            .iter()
            .filter(|(_, v)| view_angle_deg(&a.world_from_camera, &v.world_from_camera) < 30.0)
            .min_by(|x, y| {
                let dx = (baseline(&a.world_from_camera, &x.1.world_from_camera) - 1.0).abs();
                let dy = (baseline(&a.world_from_camera, &y.1.world_from_camera) - 1.0).abs();
                dx.total_cmp(&dy)
            })
            .map(|(j, _)| *j);
        if let Some(j) = j {
            let base = find(&vb, j);
            for &roll in &args.rolls {
                let pose = base.world_from_camera
                    * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll.to_radians());
                let (rgb, depth) = db.render_view(&pose);
                pairs.push(Pair {
                    name: format!("synthetic a0:{i}-a1:{j} roll {roll}"),
                    a: clone_view(&a),
                    b: View {
                        label: format!("agent1:{j} roll {roll}"),
                        rgb,
                        depth,
                        intrinsics: base.intrinsics,
                        world_from_camera: pose,
                    },
                });
            }
        }
    }
    Ok(pairs)
}

#[derive(Serialize, Default, Clone, Copy)]
struct Counted {
    total: usize,
    correct: usize,
}

#[derive(Serialize, Default, Clone)]
struct Bucket {
    label: String,
    repeatable: usize,
    nn_correct: usize,
    median_true_hamming: u32,
}

#[derive(Serialize)]
struct PairReport {
    pair: String,
    variant: String,
    baseline_m: f64,
    view_angle_deg: f64,
    covisibility: f64,
    /// How far G-ICP moved the recorded ground truth (cm), and whether the moved pose scored.
    truth_shift_cm: f64,
    polished_truth: bool,
    detected: [usize; 2],
    lifted: [usize; 2],
    /// Lifted keypoints of A with another lifted keypoint of A within 2 px on the same level.
    clustered_a: usize,
    /// Fraction of 8x6 image cells holding a lifted keypoint of A.
    grid_coverage_a: f64,
    covisible_a: usize,
    /// Covisible keypoints of A described in B at their true place: how many could be,
    /// median Hamming distance to A's descriptor, how many would beat A's nearest real
    /// neighbour in B, and the median distance of that nearest neighbour.
    oracle_described: usize,
    oracle_median_hamming: u32,
    oracle_wins: usize,
    nn_median_hamming: u32,
    repeatable: usize,
    nn_correct: usize,
    top2_correct: usize,
    /// Orientation error (degrees) of repeatable pairs: median of |angle_B - angle_A - roll|.
    median_orientation_error_deg: f64,
    matches: Counted,
    /// The matches by their distance under the truth: <2, 2-3, 3-5, 5-10, >= 10 cm.
    match_distances_cm: [usize; 5],
    mutual_no_cap: Counted,
    mutual_ratio_08: Counted,
    one_way_nn: Counted,
    by_rotation: Vec<Bucket>,
    by_scale: Vec<Bucket>,
    /// Per level of A: repeatable keypoints and correct matches.
    by_level: Vec<[usize; 3]>,
    ransac_inliers: usize,
    ransac_inliers_correct: usize,
    accepted: bool,
    verdict: String,
    error_cm: f64,
    error_deg: f64,
    prepare_ms: f64,
    align_ms: f64,
}

fn wrap_deg(angle: f64) -> f64 {
    let a = angle.rem_euclid(360.0);
    if a > 180.0 { a - 360.0 } else { a }
}

fn median<T: Copy + PartialOrd>(values: &mut [T]) -> Option<T> {
    values.sort_by(|a, b| a.partial_cmp(b).unwrap());
    values.get(values.len() / 2).copied()
}

/// In-plane rotation (degrees, from +x towards +y in the image) and scale change of the image neighbourhood of
/// a keypoint of A seen in B, assuming a fronto-parallel patch.
fn local_warp(
    ka: &Intrinsics,
    kb: &Intrinsics,
    b_from_a: &Isometry3<f64>,
    u: f64,
    v: f64,
    z: f64,
) -> Option<(f64, f64)> {
    const STEP: f64 = 10.0;
    let p0 = kb.project(&(b_from_a * ka.back_project(u, v, z)))?;
    let p1 = kb.project(&(b_from_a * ka.back_project(u + STEP, v, z)))?;
    let d = p1 - p0;
    // Image coordinates (y down), the convention of the keypoint orientations.
    Some((d.y.atan2(d.x).to_degrees(), d.norm() / STEP))
}

fn keyframe(view: &View, agent: u32) -> Keyframe {
    Keyframe {
        id: KeyframeRef {
            agent_id: agent,
            keyframe_id: 0,
        },
        rgb: view.rgb.clone(),
        depth: view.depth.clone(),
        intrinsics: view.intrinsics,
        agent_from_camera: view.world_from_camera,
    }
}

// Keypoint indices address several parallel arrays at once.
#[allow(clippy::needless_range_loop)]
fn measure(
    pair: &Pair,
    variant: &str,
    config: &AlignmentConfig,
    radius: f64,
    polish: bool,
    dump: Option<&std::path::Path>,
) -> PairReport {
    let clock = Instant::now();
    let target = PreparedKeyframe::new(keyframe(&pair.b, 1), config);
    let source = PreparedKeyframe::new(keyframe(&pair.a, 0), config);
    let prepare_ms = clock.elapsed().as_secs_f64() * 1e3 / 2.0;
    let clock = Instant::now();
    let result = align_prepared(&source, &target, config);
    let align_ms = clock.elapsed().as_secs_f64() * 1e3;

    let (fa, fb): (&Features, &Features) = (&source.features, &target.features);
    let recorded = pair.b.world_from_camera.inverse() * pair.a.world_from_camera;
    // Ground truth of real data is itself an estimate (KinectFusion tracking, cm-level drift
    // between distant frames): polish it with G-ICP from the truth and keep the polished pose
    // when G-ICP agrees with most of the overlap.
    let polished = register_coarse_to_fine(
        source.cloud.cloud(),
        &target.cloud,
        &recorded,
        &[0.05, 0.03, 0.02],
        &GicpParams {
            max_correspondence_m: 0.02,
            max_iterations: 64,
            rotation_epsilon_rad: 1e-5,
            translation_epsilon_m: 1e-5,
            overlap_distance_m: 0.02,
            min_inlier_fraction: 0.0,
        },
        0.0,
    );
    let shift = recorded.inverse() * polished.target_from_source;
    let truth_shift_cm = shift.translation.vector.norm() * 100.0;
    let use_polished = polish
        && polished.failure.is_none()
        && truth_shift_cm < 15.0
        && shift.rotation.angle().to_degrees() < 5.0;
    let b_from_a = if use_polished {
        polished.target_from_source
    } else {
        recorded
    };
    let moved: Vec<Point3<f64>> = fa.camera_points.iter().map(|p| b_from_a * p).collect();
    let is_correct = |i: usize, j: usize| (moved[i] - fb.camera_points[j]).norm() < radius;

    // Hamming distances, row per A keypoint.
    let nb = fb.len();
    let distances: Vec<u32> = fa
        .descriptors
        .iter()
        .flat_map(|da| fb.descriptors.iter().map(move |db| hamming(da, db)))
        .collect();
    let row = |i: usize| &distances[i * nb..(i + 1) * nb];
    let two_best = |values: &mut dyn Iterator<Item = (usize, u32)>| {
        let (mut best, mut second) = ((usize::MAX, u32::MAX), (usize::MAX, u32::MAX));
        for (k, d) in values {
            if d < best.1 {
                second = best;
                best = (k, d);
            } else if d < second.1 {
                second = (k, d);
            }
        }
        (best, second)
    };
    let forward: Vec<((usize, u32), (usize, u32))> = (0..fa.len())
        .map(|i| two_best(&mut row(i).iter().copied().enumerate()))
        .collect();
    let backward: Vec<((usize, u32), (usize, u32))> = (0..nb)
        .map(|j| two_best(&mut (0..fa.len()).map(|i| (i, distances[i * nb + j]))))
        .collect();
    let count = |filter: &dyn Fn(usize) -> Option<usize>| {
        let mut c = Counted::default();
        for i in 0..fa.len() {
            if let Some(j) = filter(i) {
                c.total += 1;
                c.correct += is_correct(i, j) as usize;
            }
        }
        c
    };
    let mutual = |i: usize, cap: u32, ratio: f64| {
        let ((j, best), (_, second)) = forward[i];
        let ((back, bbest), (_, bsecond)) = *backward.get(j)?;
        let ok = |b: u32, s: u32| b <= cap && (b as f64) < ratio * s as f64;
        (back == i && ok(best, second) && ok(bbest, bsecond)).then_some(j)
    };
    let matches = count(&|i| mutual(i, config.max_hamming_distance, config.match_ratio));
    // Truth distances of the configured matches (cm): <2, 2-3, 3-5, 5-10, >= 10.
    let mut match_distances = [0usize; 5];
    for i in 0..fa.len() {
        if let Some(j) = mutual(i, config.max_hamming_distance, config.match_ratio) {
            let d = (moved[i] - fb.camera_points[j]).norm() * 100.0;
            let bin = [2.0, 3.0, 5.0, 10.0]
                .iter()
                .position(|&e| d < e)
                .unwrap_or(4);
            match_distances[bin] += 1;
        }
    }
    let mutual_no_cap = count(&|i| mutual(i, u32::MAX, 1.0 + 1e-9));
    let mutual_ratio_08 = count(&|i| mutual(i, config.max_hamming_distance, 0.8));
    let one_way_nn = count(&|i| (forward[i].0.0 != usize::MAX).then_some(forward[i].0.0));

    // Repeatability and per-bucket discriminability.
    let rotation_edges = [15.0, 30.0, 60.0, 90.0, 180.0];
    let scale_edges = [1.25, 1.6, 2.0, 100.0];
    let mut by_rotation: Vec<(usize, usize, Vec<u32>)> = vec![(0, 0, vec![]); 5];
    let mut by_scale: Vec<(usize, usize, Vec<u32>)> = vec![(0, 0, vec![]); 4];
    let levels = config.pyramid_levels.max(1);
    let mut by_level = vec![[0usize; 3]; levels];
    let (mut repeatable, mut nn_correct, mut top2_correct, mut covisible_a) = (0, 0, 0, 0);
    let mut orientation_errors = Vec::new();
    // 0: not repeatable, 1: repeatable, 2: correct nearest neighbour.
    let mut status = vec![0u8; fa.len()];
    for i in 0..fa.len() {
        let kp = fa.keypoints[i];
        if let Some(pixel) = pair.b.intrinsics.project(&moved[i])
            && pair.b.intrinsics.contains(&pixel)
            && depth_agrees(
                moved[i].z,
                pair.b
                    .depth
                    .get(pixel.x.round() as u32, pixel.y.round() as u32) as f64,
            )
        {
            covisible_a += 1;
        }
        let partners: Vec<usize> = (0..nb).filter(|&j| is_correct(i, j)).collect();
        if partners.is_empty() {
            continue;
        }
        repeatable += 1;
        by_level[kp.level.min(levels - 1)][0] += 1;
        let true_distance = partners.iter().map(|&j| row(i)[j]).min().unwrap();
        let ((best_j, _), (second_j, _)) = forward[i];
        let nn_ok = is_correct(i, best_j);
        nn_correct += nn_ok as usize;
        status[i] = 1 + nn_ok as u8;
        top2_correct += (nn_ok || (second_j != usize::MAX && is_correct(i, second_j))) as usize;
        let Some((rotation, scale)) = local_warp(
            &pair.a.intrinsics,
            &pair.b.intrinsics,
            &b_from_a,
            kp.u,
            kp.v,
            fa.camera_points[i].z,
        ) else {
            continue;
        };
        // The partner closest in 3-D for the orientation comparison.
        let nearest = *partners
            .iter()
            .min_by(|&&x, &&y| {
                (moved[i] - fb.camera_points[x])
                    .norm()
                    .total_cmp(&(moved[i] - fb.camera_points[y]).norm())
            })
            .unwrap();
        let predicted = kp.angle as f64 + rotation.to_radians();
        orientation_errors
            .push(wrap_deg((fb.keypoints[nearest].angle as f64 - predicted).to_degrees()).abs());
        let r = rotation_edges
            .iter()
            .position(|&e| rotation.abs() < e)
            .unwrap_or(4);
        let s = scale_edges
            .iter()
            .position(|&e| scale.max(1.0 / scale) < e)
            .unwrap_or(3);
        for bucket in [&mut by_rotation[r], &mut by_scale[s]] {
            bucket.0 += 1;
            bucket.1 += nn_ok as usize;
            bucket.2.push(true_distance);
        }
    }
    for i in 0..fa.len() {
        if let Some(j) = mutual(i, config.max_hamming_distance, config.match_ratio)
            && is_correct(i, j)
        {
            by_level[fa.keypoints[i].level.min(levels - 1)][1] += 1;
        }
        if forward[i].0.0 != usize::MAX && is_correct(i, forward[i].0.0) {
            by_level[fa.keypoints[i].level.min(levels - 1)][2] += 1;
        }
    }
    let buckets = |raw: Vec<(usize, usize, Vec<u32>)>, labels: &[&str]| {
        raw.into_iter()
            .zip(labels)
            .map(|((repeatable, nn_correct, mut d), label)| Bucket {
                label: label.to_string(),
                repeatable,
                nn_correct,
                median_true_hamming: median(&mut d).unwrap_or(0),
            })
            .collect::<Vec<_>>()
    };

    // Oracle: B described exactly where A's covisible keypoints fall (scale level from the depth
    // ratio): how different are descriptors of the same place, and would they beat the best
    // of B's real keypoints?
    let mut oracle_places = Vec::new();
    let mut oracle_of = Vec::new();
    for i in 0..fa.len() {
        if let Some(pixel) = pair.b.intrinsics.project(&moved[i])
            && pair.b.intrinsics.contains(&pixel)
            && depth_agrees(
                moved[i].z,
                pair.b
                    .depth
                    .get(pixel.x.round() as u32, pixel.y.round() as u32) as f64,
            )
        {
            let ratio = fa.camera_points[i].z / moved[i].z;
            let level =
                fa.keypoints[i].level as f64 + ratio.ln() / config.pyramid_scale_factor.ln();
            oracle_places.push((pixel.x, pixel.y, level.round().max(0.0) as usize));
            oracle_of.push(i);
        }
    }
    let oracle = describe_at(
        &pair.b.rgb,
        &pair.b.depth,
        &pair.b.intrinsics,
        config,
        &oracle_places,
    );
    let mut oracle_hamming = Vec::new();
    let mut oracle_wins = 0;
    for (&i, d) in oracle_of.iter().zip(&oracle) {
        if let Some(d) = d {
            let h = hamming(&fa.descriptors[i], d);
            oracle_hamming.push(h);
            oracle_wins += (h < forward[i].0.1) as usize;
        }
    }
    let oracle_described = oracle_hamming.len();
    let oracle_median_hamming = median(&mut oracle_hamming).unwrap_or(0);
    let mut nn_hamming: Vec<u32> = oracle_of.iter().map(|&i| forward[i].0.1).collect();
    let nn_median_hamming = median(&mut nn_hamming).unwrap_or(0);

    // Keypoint spread of A.
    let mut clustered_a = 0;
    for (i, p) in fa.keypoints.iter().enumerate() {
        if fa.keypoints.iter().enumerate().any(|(k, q)| {
            k != i
                && q.level == p.level
                && (q.u - p.u).abs() <= 2.0 * (1.25f64).powi(p.level as i32)
                && (q.v - p.v).abs() <= 2.0 * (1.25f64).powi(p.level as i32)
        }) {
            clustered_a += 1;
        }
    }
    let (w, h) = (
        pair.a.intrinsics.width as f64,
        pair.a.intrinsics.height as f64,
    );
    let mut cells = [false; 48];
    for p in &fa.keypoints {
        let cx = ((p.u / w * 8.0) as usize).min(7);
        let cy = ((p.v / h * 6.0) as usize).min(5);
        cells[cy * 8 + cx] = true;
    }
    let grid_coverage_a = cells.iter().filter(|&&c| c).count() as f64 / 48.0;

    if let Some(dir) = dump {
        let (w, h) = (pair.a.rgb.width(), pair.a.rgb.height());
        let mut canvas = RgbImage::new(w + pair.b.rgb.width(), h.max(pair.b.rgb.height()));
        image::imageops::replace(&mut canvas, &pair.a.rgb, 0, 0);
        image::imageops::replace(&mut canvas, &pair.b.rgb, w as i64, 0);
        let mut mark = |x: f64, y: f64, colour: [u8; 3]| {
            for d in -3i64..=3 {
                for (px, py) in [(x as i64 + d, y as i64), (x as i64, y as i64 + d)] {
                    if px >= 0
                        && py >= 0
                        && (px as u32) < canvas.width()
                        && (py as u32) < canvas.height()
                    {
                        canvas.put_pixel(px as u32, py as u32, image::Rgb(colour));
                    }
                }
            }
        };
        for (k, p) in fa.keypoints.iter().enumerate() {
            let colour = [[160, 160, 160], [255, 255, 0], [0, 255, 0]][status[k] as usize];
            mark(p.u, p.v, colour);
        }
        for p in &fb.keypoints {
            mark(p.u + w as f64, p.v, [0, 200, 255]);
        }
        let name: String = format!("{}_{}", pair.name, variant)
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
            .collect();
        let _ = std::fs::create_dir_all(dir);
        if let Err(error) = canvas.save(dir.join(format!("{name}.png"))) {
            eprintln!("cannot write the pair image: {error}");
        }
    }

    // RANSAC outcome.
    let (ransac_inliers, ransac_inliers_correct) = match &result.coarse {
        Some(c) => {
            // Recount correctness of the inliers of the final estimate against the truth: the
            // coarse estimate's inliers are the matches it places within the inlier distance.
            let estimate = result.target_camera_from_source_camera;
            let matched: Vec<(usize, usize)> =
                mac_consensus::alignment::features::match_features(fa, fb, config);
            let correct = matched
                .iter()
                .filter(|&&(i, j)| {
                    (estimate * fa.camera_points[i] - fb.camera_points[j]).norm()
                        <= config.ransac_inlier_distance_m
                        && is_correct(i, j)
                })
                .count();
            (c.inliers, correct)
        }
        None => (0, 0),
    };
    let error = result.target_camera_from_source_camera.inverse() * b_from_a;
    PairReport {
        pair: pair.name.clone(),
        variant: variant.to_string(),
        baseline_m: baseline(&pair.a.world_from_camera, &pair.b.world_from_camera),
        view_angle_deg: view_angle_deg(&pair.a.world_from_camera, &pair.b.world_from_camera),
        covisibility: covisibility(&pair.a, &pair.b),
        truth_shift_cm,
        polished_truth: use_polished,
        detected: [fa.detected, fb.detected],
        lifted: [fa.len(), fb.len()],
        clustered_a,
        grid_coverage_a,
        covisible_a,
        oracle_described,
        oracle_median_hamming,
        oracle_wins,
        nn_median_hamming,
        repeatable,
        nn_correct,
        top2_correct,
        median_orientation_error_deg: median(&mut orientation_errors).unwrap_or(f64::NAN),
        matches,
        match_distances_cm: match_distances,
        mutual_no_cap,
        mutual_ratio_08,
        one_way_nn,
        by_rotation: buckets(by_rotation, &["<15", "15-30", "30-60", "60-90", ">90"]),
        by_scale: buckets(by_scale, &["<1.25", "1.25-1.6", "1.6-2", ">2"]),
        by_level,
        ransac_inliers,
        ransac_inliers_correct,
        accepted: result.is_accepted(),
        verdict: match &result.verdict {
            mac_consensus::alignment::Verdict::Accepted => "accepted".into(),
            mac_consensus::alignment::Verdict::Rejected(reason) => reason.to_string(),
        },
        error_cm: error.translation.vector.norm() * 100.0,
        error_deg: error.rotation.angle().to_degrees(),
        prepare_ms,
        align_ms,
    }
}

fn parse_variant(text: &str) -> anyhow::Result<(String, AlignmentConfig)> {
    let (name, json) = text
        .split_once('=')
        .ok_or_else(|| anyhow::anyhow!("--variant wants NAME=JSON, got {text:?}"))?;
    let mut value = serde_json::to_value(AlignmentConfig::default())?;
    let changes: serde_json::Value = serde_json::from_str(json)?;
    let (Some(target), Some(changes)) = (value.as_object_mut(), changes.as_object()) else {
        anyhow::bail!("variant {name}: JSON object expected");
    };
    for (key, change) in changes {
        anyhow::ensure!(
            target.contains_key(key),
            "variant {name}: unknown field {key}"
        );
        target.insert(key.clone(), change.clone());
    }
    Ok((name.to_string(), serde_json::from_value(value)?))
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let variants: Vec<(String, AlignmentConfig)> = if args.variant.is_empty() {
        vec![("default".into(), AlignmentConfig::default())]
    } else {
        args.variant
            .iter()
            .map(|v| parse_variant(v))
            .collect::<anyhow::Result<_>>()?
    };
    let clock = Instant::now();
    let mut pairs = real_pairs(&args)?;
    pairs.extend(synthetic_pairs(&args)?);
    eprintln!(
        "{} pairs chosen in {:.1} s",
        pairs.len(),
        clock.elapsed().as_secs_f64()
    );
    for pair in &pairs {
        eprintln!("  {} ({} / {})", pair.name, pair.a.label, pair.b.label);
    }

    let mut reports = Vec::new();
    println!(
        "{:<30} {:<10} {:>5} {:>5} {:>5} {:>9} {:>9} {:>5} {:>4} {:>4} {:>5} {:>5} {:>4} {:>9} {:>9} {:>9} {:>9} {:>8} {:>4} {:>6} {:>6}",
        "pair",
        "variant",
        "base",
        "angle",
        "covis",
        "lifted",
        "covis/rep",
        "clust",
        "grid",
        "nn+",
        "top2",
        "ori",
        "",
        "matches",
        "no-cap",
        "ratio.8",
        "1-way",
        "ransac",
        "ok",
        "prep",
        "align"
    );
    for pair in &pairs {
        for (name, config) in &variants {
            let r = measure(
                pair,
                name,
                config,
                args.radius,
                !args.raw_truth,
                args.dump.as_deref(),
            );
            println!(
                "{:<30} {:<10} {:>5.2} {:>5.0} {:>5.2} {:>4}/{:<4} {:>4}/{:<4} {:>5} {:>4.2} {:>4} {:>5} {:>5.0} {:>4} {:>4}/{:<4} {:>4}/{:<4} {:>4}/{:<4} {:>4}/{:<4} {:>3}/{:<4} {:>4} {:>6.0} {:>6.0}",
                r.pair,
                r.variant,
                r.baseline_m,
                r.view_angle_deg,
                r.covisibility,
                r.lifted[0],
                r.lifted[1],
                r.covisible_a,
                r.repeatable,
                r.clustered_a,
                r.grid_coverage_a,
                r.nn_correct,
                r.top2_correct,
                r.median_orientation_error_deg,
                "",
                r.matches.correct,
                r.matches.total,
                r.mutual_no_cap.correct,
                r.mutual_no_cap.total,
                r.mutual_ratio_08.correct,
                r.mutual_ratio_08.total,
                r.one_way_nn.correct,
                r.one_way_nn.total,
                r.ransac_inliers_correct,
                r.ransac_inliers,
                if r.accepted { "yes" } else { "no" },
                r.prepare_ms,
                r.align_ms
            );
            if args.verbose {
                let show = |title: &str, buckets: &[Bucket]| {
                    let cells: Vec<String> = buckets
                        .iter()
                        .map(|b| {
                            format!(
                                "{}: {}/{} (h{})",
                                b.label, b.nn_correct, b.repeatable, b.median_true_hamming
                            )
                        })
                        .collect();
                    println!("    {title}: {}", cells.join("  "));
                };
                show("rotation nn+/rep", &r.by_rotation);
                show("scale    nn+/rep", &r.by_scale);
                let levels: Vec<String> = r
                    .by_level
                    .iter()
                    .enumerate()
                    .map(|(l, [rep, m, nn])| format!("L{l}: rep {rep} nn+ {nn} match+ {m}"))
                    .collect();
                println!("    levels: {}", levels.join("  "));
                println!(
                    "    oracle: {} described, median hamming {} (nearest real {}), {} would win",
                    r.oracle_described, r.oracle_median_hamming, r.nn_median_hamming, r.oracle_wins
                );
                println!(
                    "    match truth distances <2/2-3/3-5/5-10/>10 cm: {:?}",
                    r.match_distances_cm
                );
                println!(
                    "    verdict: {} (pose error {:.1} cm, {:.1} deg); truth polished by {:.1} cm: {}",
                    r.verdict, r.error_cm, r.error_deg, r.truth_shift_cm, r.polished_truth
                );
            }
            reports.push(r);
        }
    }
    // Totals per variant.
    println!();
    println!(
        "{:<10} {:>6} {:>8} {:>9} {:>9} {:>12} {:>12} {:>9} {:>9} {:>9}",
        "variant",
        "pairs",
        "accepted",
        "repeat",
        "nn+",
        "match+/all",
        "ransac+",
        "prep ms",
        "align ms",
        "sum ms"
    );
    for (name, _) in &variants {
        let rs: Vec<&PairReport> = reports.iter().filter(|r| &r.variant == name).collect();
        let sum = |f: &dyn Fn(&PairReport) -> usize| rs.iter().map(|r| f(r)).sum::<usize>();
        let mut prep: Vec<f64> = rs.iter().map(|r| r.prepare_ms).collect();
        let mut align: Vec<f64> = rs.iter().map(|r| r.align_ms).collect();
        let mut total: Vec<f64> = rs.iter().map(|r| 2.0 * r.prepare_ms + r.align_ms).collect();
        println!(
            "{:<10} {:>6} {:>8} {:>9} {:>9} {:>5}/{:<6} {:>12} {:>9.0} {:>9.0} {:>9.0}",
            name,
            rs.len(),
            sum(&|r| r.accepted as usize),
            sum(&|r| r.repeatable),
            sum(&|r| r.nn_correct),
            sum(&|r| r.matches.correct),
            sum(&|r| r.matches.total),
            sum(&|r| r.ransac_inliers_correct),
            median(&mut prep).unwrap_or(0.0),
            median(&mut align).unwrap_or(0.0),
            median(&mut total).unwrap_or(0.0),
        );
    }
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&reports)?)?;
        eprintln!("report written to {}", path.display());
    }
    Ok(())
}
