//! The pairs the example measures: real frames and synthetic views with ground-truth poses, chosen
//! by baseline and co-visibility.

use std::collections::BTreeMap;

use datasets::synthetic::{SyntheticDataset, SyntheticSpec};
use datasets::{self, Dataset, FrameRange};
use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::{Isometry3, UnitQuaternion, Vector3};

use crate::Args;

/// One RGB-D view with its ground-truth pose.
pub struct View {
    pub label: String,
    pub rgb: RgbImage,
    pub depth: DepthImage,
    pub intrinsics: Intrinsics,
    pub world_from_camera: Isometry3<f64>,
}

/// Two views of the same place, A (the source) and B (the target).
pub struct Pair {
    pub name: String,
    pub a: View,
    pub b: View,
}

/// Depth-agreement tolerance of the co-visibility measure.
pub fn depth_agrees(z: f64, observed: f64) -> bool {
    observed > 0.0 && (z - observed).abs() <= 0.05 + 0.02 * z
}

/// Fraction of A's valid depth points (every 8th pixel) that B sees with agreeing depth.
pub fn covisibility(a: &View, b: &View) -> f64 {
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

/// Distance between two camera centres (metres).
pub fn baseline(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

/// Angle between two cameras' viewing directions (degrees).
pub fn view_angle_deg(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.rotation * Vector3::z())
        .angle(&(b.rotation * Vector3::z()))
        .to_degrees()
}

/// A dataset frame with its ground-truth pose.
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

/// A copy of the view of frame `k`.
fn find(views: &[(usize, View)], k: usize) -> View {
    clone_view(&views.iter().find(|v| v.0 == k).unwrap().1)
}

/// Views hold images, which are not `Clone` through `View` itself.
pub fn clone_view(v: &View) -> View {
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

/// Pairs of real frames (at least 200 frames apart) chosen by [`choose_pairs`]; none when the
/// data set is missing.
pub fn real_pairs(args: &Args) -> anyhow::Result<Vec<Pair>> {
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

/// Pairs between the synthetic scene's two agents chosen by [`choose_pairs`], then the rolled
/// pairs of [`rolled_pairs`].
pub fn synthetic_pairs(args: &Args) -> anyhow::Result<Vec<Pair>> {
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
    let mut pairs: Vec<Pair> = chosen
        .iter()
        .take(args.synthetic_pairs)
        .map(|&(i, j, _)| Pair {
            name: format!("synthetic a0:{i}-a1:{j}"),
            a: find(&va, i),
            b: find(&vb, j),
        })
        .collect();
    if let Some(&(i, _, _)) = chosen.first() {
        pairs.extend(rolled_pairs(args, &va, &vb, &db, i));
    }
    Ok(pairs)
}

/// Rolled copies of a pair with a moderate baseline: the same geometry, the second camera
/// turned about its optical axis by each of `--rolls`. A's view is frame `i` of agent 0.
fn rolled_pairs(
    args: &Args,
    va: &[(usize, View)],
    vb: &[(usize, View)],
    db: &SyntheticDataset,
    i: usize,
) -> Vec<Pair> {
    let mut pairs = Vec::new();
    let a = find(va, i);
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
        let base = find(vb, j);
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
    pairs
}
