//! `mac-ego3d bench map-registration`: global registration of two agents' maps with no initial
//! guess (`registration::map_registration`), against ground truth.
//!
//! Each map is built from a dataset with its ground-truth poses: every `--every`-th frame's depth
//! is back-projected (every `--pixel-stride`-th pixel) into the world frame, thinned to one point
//! per `--map-voxel` cell (a dense map's spacing) and, above `--points`, to a seeded random
//! subset of that many points. Map A stays in the world frame (the target); map B is expressed
//! in a random rigid frame (any rotation, up to 5 m away, seeded), so the true
//! `target_from_source` is known. The default data is the embedded synthetic scene with two
//! agents (A = agent 0, B = agent 1; `--frames N` is short for `--synthetic-frames N`); each
//! seed changes the scene's seed and the random frame.
//! With `--dataset PATH`, A and B are `--frames-a` and `--frames-b` of that dataset and seeds
//! change the random frame only.
//!
//! Each map point carries the colour of its pixel (RGB / 255, averaged per map cell), and the
//! registration uses it; `--no-colour` registers the same maps on their geometry alone. The
//! table's `kappa` is how far the accepted overlap's colours agree beyond chance.
//!
//! Errors are measured at the centre of map B (rotation angle, and the distance between where the
//! estimate and the truth put that centre), so they do not depend on where the random frame's
//! origin lies. A run succeeds when it is accepted and within 5 cm and 2 degrees.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use config::{Config, MapRegistrationConfig};
use datasets::{self, FrameRange};
use metrics::stats::median;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use registration::map_registration::colour::Rgb;
use registration::map_registration::{MapPoints, MapRegistration, register_maps};
use registration::{PointTree, points_from_depth};
use serde::Serialize;

use crate::cmd::{fmt_num, print_json};

/// Success thresholds against ground truth.
const SUCCESS_TRANSLATION_M: f64 = 0.05;
const SUCCESS_ROTATION_DEG: f64 = 2.0;
/// Largest distance of the random frame's origin (metres).
const RANDOM_FRAME_RADIUS_M: f64 = 5.0;
/// Depth beyond this is not used (metres).
const TRUNCATION_M: f64 = 8.0;
/// Two maps overlap at a point of B with a point of A this close (metres): the ground-truth
/// overlap reported for context.
const TRUE_OVERLAP_DISTANCE_M: f64 = 0.05;

#[derive(Args)]
pub struct MapRegistrationArgs {
    /// Dataset folder (7-Scenes, TUM, Replica) with ground truth. Default: the embedded synthetic
    /// scene, two agents.
    #[arg(long)]
    dataset: Option<String>,
    /// Frames of map A (with --dataset).
    #[arg(long, default_value = "0..100")]
    frames_a: FrameRange,
    /// Frames of map B (with --dataset).
    #[arg(long, default_value = "500..600")]
    frames_b: FrameRange,
    /// Synthetic scene: frames per agent and image size.
    #[arg(long, alias = "frames", default_value_t = 300)]
    synthetic_frames: usize,
    #[arg(long, default_value_t = 320)]
    synthetic_width: u32,
    #[arg(long, default_value_t = 240)]
    synthetic_height: u32,
    /// Back-project every n-th frame.
    #[arg(long, default_value_t = 10)]
    every: usize,
    /// Back-project every n-th pixel in x and y.
    #[arg(long, default_value_t = 2)]
    pixel_stride: usize,
    /// Map spacing: one point per cell of this size (metres).
    #[arg(long, default_value_t = 0.02)]
    map_voxel: f64,
    /// Points per map at most (a seeded random subset above).
    #[arg(long, default_value_t = 50_000)]
    points: usize,
    /// Runs, seeds 0..N (plus --first-seed).
    #[arg(long, default_value_t = 10)]
    seeds: u64,
    #[arg(long, default_value_t = 0)]
    first_seed: u64,
    /// Configuration file (its [consensus.map_registration] table). Default: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Register the maps without their colours (geometry alone).
    #[arg(long)]
    no_colour: bool,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct Run {
    seed: u64,
    time_ms: f64,
    source_points: usize,
    target_points: usize,
    /// Fraction of B's points within 5 cm of A's at the true transform, over the smaller map.
    true_overlap: f64,
    voxel_m: f64,
    downsampled_points: [usize; 2],
    correspondences: usize,
    inliers: usize,
    runner_up: usize,
    overlap: f64,
    residual_m: f64,
    /// Fraction of the overlapping points that agree in colour, and Cohen's kappa of that
    /// against chance (NaN without colour).
    colour_agreement: f64,
    colour_kappa: f64,
    gicp_iterations: usize,
    rotation_error_deg: f64,
    translation_error_m: f64,
    accepted: bool,
    success: bool,
    rejection: Option<String>,
    stage_ms: registration::map_registration::StageTimings,
}

#[derive(Serialize)]
struct Report {
    data: String,
    /// Whether the maps' colours were used.
    colour: bool,
    threads: usize,
    runs: Vec<Run>,
    median_time_ms: f64,
    accepted: usize,
    successes: usize,
    /// Accepted but farther than 5 cm / 2 degrees from the truth.
    false_accepts: usize,
    success_rate: f64,
}

/// SplitMix64: a few seeded random numbers without a dependency.
struct SplitMix(u64);

impl SplitMix {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A uniformly random rotation (Shoemake's method) and a translation uniform in a ball.
fn random_frame(seed: u64) -> Isometry3<f64> {
    let mut rng = SplitMix(seed ^ 0x006d_6170_5f72_6567);
    let (u1, u2, u3) = (rng.unit(), rng.unit(), rng.unit());
    let tau = std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let q = nalgebra::Quaternion::new(
        b * (tau * u3).cos(),
        a * (tau * u2).sin(),
        a * (tau * u2).cos(),
        b * (tau * u3).sin(),
    );
    let direction = loop {
        let v = Vector3::new(rng.unit(), rng.unit(), rng.unit()) * 2.0 - Vector3::repeat(1.0);
        if v.norm() <= 1.0 && v.norm() > 1e-3 {
            break v;
        }
    };
    Isometry3::from_parts(
        Translation3::from(direction * RANDOM_FRAME_RADIUS_M),
        UnitQuaternion::from_quaternion(q),
    )
}

/// A map's points and their colours.
struct Map {
    points: Vec<Point3<f32>>,
    colours: Vec<Rgb>,
}

/// World-frame map of a dataset's frames, with colours (see the module documentation).
fn build_map(
    spec: &str,
    frames: FrameRange,
    args: &MapRegistrationArgs,
    seed: u64,
) -> anyhow::Result<Map> {
    let ds = datasets::open(spec, frames).with_context(|| format!("opening {spec}"))?;
    anyhow::ensure!(!ds.is_empty(), "{spec}: no frames in {frames}");
    let mut points = Vec::new();
    let mut colours = Vec::new();
    for position in (0..ds.len()).step_by(args.every.max(1)) {
        let frame = ds.load(position)?;
        let pose = frame
            .world_from_camera_gt
            .with_context(|| format!("{spec}: frame {} has no ground-truth pose", frame.index))?;
        let cloud = points_from_depth(
            &frame.depth,
            &frame.intrinsics,
            args.pixel_stride,
            TRUNCATION_M,
        );
        points.extend(
            cloud
                .positions
                .iter()
                .map(|p| (pose * p.cast::<f64>()).cast::<f32>()),
        );
        let width = frame.rgb.width();
        colours.extend(cloud.pixels.iter().map(|&pixel| {
            let rgb = frame.rgb.get_pixel(pixel % width, pixel / width).0;
            rgb.map(|c| f32::from(c) / 255.0)
        }));
    }
    let down = registration::map_registration::downsample::voxel_downsample_coloured(
        &points,
        Some(&colours),
        args.map_voxel,
    );
    let mut map = Map {
        points: down.points,
        colours: down.colours.expect("coloured input"),
    };
    if map.points.len() > args.points {
        // Seeded partial Fisher-Yates: the first `points` entries are a uniform random subset.
        let mut rng = SplitMix(seed ^ 0x0000_7375_6273_6574);
        for i in 0..args.points {
            let j = i + (rng.next_u64() % (map.points.len() - i) as u64) as usize;
            map.points.swap(i, j);
            map.colours.swap(i, j);
        }
        map.points.truncate(args.points);
        map.colours.truncate(args.points);
    }
    Ok(map)
}

/// Fraction of `b`'s points with a point of `a` within [`TRUE_OVERLAP_DISTANCE_M`], over the
/// smaller map.
fn true_overlap(a: &[Point3<f32>], b: &[Point3<f32>]) -> f64 {
    let Ok(tree) = PointTree::new(a.to_vec()) else {
        return f64::NAN;
    };
    let limit = (TRUE_OVERLAP_DISTANCE_M * TRUE_OVERLAP_DISTANCE_M) as f32;
    let near = b
        .iter()
        .filter(|p| tree.nearest(p).is_some_and(|(_, d)| d <= limit))
        .count();
    near as f64 / a.len().min(b.len()).max(1) as f64
}

fn run_one(
    seed: u64,
    args: &MapRegistrationArgs,
    config: &MapRegistrationConfig,
) -> anyhow::Result<(Run, String)> {
    let (spec_a, spec_b, frames_a, frames_b) = match &args.dataset {
        Some(path) => (path.clone(), path.clone(), args.frames_a, args.frames_b),
        None => {
            let spec = |agent: usize| {
                format!(
                    "synthetic:agents=2,agent={agent},frames={},seed={seed},width={},height={}",
                    args.synthetic_frames, args.synthetic_width, args.synthetic_height
                )
            };
            (spec(0), spec(1), FrameRange::ALL, FrameRange::ALL)
        }
    };
    let describe = format!("A = {spec_a} [{frames_a}], B = {spec_b} [{frames_b}]");
    let map_a = build_map(&spec_a, frames_a, args, seed)?;
    let map_b_world = build_map(&spec_b, frames_b, args, seed.wrapping_add(1))?;
    let overlap = true_overlap(&map_a.points, &map_b_world.points);
    let frame_from_world = random_frame(seed);
    let map_b: Vec<Point3<f32>> = map_b_world
        .points
        .iter()
        .map(|p| (frame_from_world * p.cast::<f64>()).cast::<f32>())
        .collect();
    let truth = frame_from_world.inverse();
    let colours = |map: &Map| (!args.no_colour).then_some(map.colours.clone());
    let (colours_b, colours_a) = (colours(&map_b_world), colours(&map_a));
    let result: MapRegistration = register_maps(
        MapPoints::coloured(&map_b, colours_b.as_deref()),
        MapPoints::coloured(&map_a.points, colours_a.as_deref()),
        config,
    );
    let centre = Point3::from(
        map_b
            .iter()
            .fold(Vector3::zeros(), |sum, p| sum + p.coords.cast::<f64>())
            / map_b.len().max(1) as f64,
    );
    let rotation_error_deg = result
        .target_from_source
        .rotation
        .angle_to(&truth.rotation)
        .to_degrees();
    let translation_error_m = (result.target_from_source * centre - truth * centre).norm();
    let s = &result.scores;
    let accepted = result.is_accepted();
    let run = Run {
        seed,
        time_ms: result.elapsed_ms,
        source_points: map_b.len(),
        target_points: map_a.points.len(),
        true_overlap: overlap,
        voxel_m: s.voxel_m,
        downsampled_points: [s.source_points, s.target_points],
        correspondences: s.correspondences,
        inliers: s.consistent_correspondences,
        runner_up: s.runner_up_support,
        overlap: s.overlap_fraction,
        residual_m: s.residual_m,
        colour_agreement: s.colour_agreement,
        colour_kappa: s.colour_kappa,
        gicp_iterations: s.gicp_iterations,
        rotation_error_deg,
        translation_error_m,
        accepted,
        success: accepted
            && rotation_error_deg <= SUCCESS_ROTATION_DEG
            && translation_error_m <= SUCCESS_TRANSLATION_M,
        rejection: result.verdict.as_ref().err().map(|e| e.to_string()),
        stage_ms: s.timings.clone(),
    };
    Ok((run, describe))
}

pub fn run(args: &MapRegistrationArgs) -> anyhow::Result<()> {
    let config = match &args.config {
        Some(path) => Config::load(path)?.consensus.map_registration,
        None => MapRegistrationConfig::default(),
    };
    let mut runs = Vec::new();
    let mut data = String::new();
    for seed in args.first_seed..args.first_seed + args.seeds {
        let (run, describe) = run_one(seed, args, &config)?;
        if !args.json {
            if runs.is_empty() {
                println!(
                    "map registration {}: {describe} (first seed)",
                    if args.no_colour {
                        "without colour"
                    } else {
                        "with colour"
                    }
                );
                println!(
                    "  {:>4} {:>8} {:>13} {:>6} {:>6} {:>6} {:>5} {:>5} {:>6} {:>7} {:>6} {:>8} {:>8}  verdict",
                    "seed",
                    "ms",
                    "points B/A",
                    "truth",
                    "voxel",
                    "corr",
                    "inl",
                    "2nd",
                    "ovl",
                    "res mm",
                    "kappa",
                    "rot deg",
                    "trans cm"
                );
            }
            println!(
                "  {:>4} {:>8} {:>13} {:>6} {:>6} {:>6} {:>5} {:>5} {:>6} {:>7} {:>6} {:>8} {:>8}  {}",
                run.seed,
                fmt_num(run.time_ms, 0),
                format!("{}/{}", run.source_points, run.target_points),
                fmt_num(run.true_overlap, 2),
                fmt_num(run.voxel_m, 3),
                run.correspondences,
                run.inliers,
                run.runner_up,
                fmt_num(run.overlap, 2),
                fmt_num(run.residual_m * 1e3, 1),
                fmt_num(run.colour_kappa, 2),
                fmt_num(run.rotation_error_deg, 2),
                fmt_num(run.translation_error_m * 100.0, 1),
                match (&run.rejection, run.success) {
                    (None, true) => "accepted".to_string(),
                    (None, false) => "ACCEPTED, WRONG".to_string(),
                    (Some(reason), _) => format!("refused: {reason}"),
                }
            );
        }
        data = describe;
        runs.push(run);
    }
    let times: Vec<f64> = runs.iter().map(|r| r.time_ms).collect();
    let accepted = runs.iter().filter(|r| r.accepted).count();
    let successes = runs.iter().filter(|r| r.success).count();
    let report = Report {
        data,
        colour: !args.no_colour,
        threads: registration::worker_threads(),
        median_time_ms: median(&times).unwrap_or(f64::NAN),
        accepted,
        successes,
        false_accepts: accepted - successes,
        success_rate: successes as f64 / runs.len().max(1) as f64,
        runs,
    };
    if args.json {
        return print_json(&report);
    }
    println!(
        "  {}: median {} ms ({} threads); accepted {}/{}, within {} cm and {} degrees {}/{} ({}%), accepted but wrong {}",
        if report.colour {
            "with colour"
        } else {
            "without colour"
        },
        fmt_num(report.median_time_ms, 0),
        report.threads,
        report.accepted,
        report.runs.len(),
        SUCCESS_TRANSLATION_M * 100.0,
        SUCCESS_ROTATION_DEG,
        report.successes,
        report.runs.len(),
        fmt_num(report.success_rate * 100.0, 0),
        report.false_accepts
    );
    Ok(())
}
