//! `mac-ego3d dataset info PATH`: what a dataset holds, read through the same readers SLAM uses
//! (for a ROS 2 bag also its topics, types, counts and rates, and which topics it would use);
//! `dataset frame` exports one frame; `dataset covisibility` measures how much two sequences (two
//! agents) share, from their ground truth.

use std::path::Path;

use anyhow::Context;
use clap::{Args, Subcommand};
use datasets::{self, Dataset, FrameRange};
use geometry::camera::Intrinsics;
use geometry::trajectory::Trajectory;
use serde::Serialize;

use super::bag_info::{BagInfo, bag_info, print_bag_info};
use super::{fmt_num, print_json};

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Frames, resolution, intrinsics, depth validity and trajectory length of a dataset (a
    /// folder, a folder of agent folders, or a `synthetic:...` spec).
    Info(InfoArgs),
    /// Decode one frame through the dataset reader and write it as lossless PNGs (RGB, and depth
    /// as 16-bit millimetres).
    Frame(FrameArgs),
    /// How much two sequences with ground truth in one world frame (two agents) share: the
    /// co-visibility of every sampled cross pair of frames (the largest is what keyframe matching
    /// can hope for) and the share of each sequence's surface the other one saw at all (the
    /// maps' overlap), plus the distance and viewing-angle difference of the first frames.
    Covisibility(CovisibilityArgs),
}

#[derive(Args)]
pub struct CovisibilityArgs {
    /// First sequence: dataset folder or `synthetic:...` spec.
    a: String,
    /// Second sequence.
    b: String,
    #[arg(long, default_value = "0..")]
    frames_a: FrameRange,
    #[arg(long, default_value = "0..")]
    frames_b: FrameRange,
    /// Use every n-th frame of each sequence.
    #[arg(long, default_value_t = 10)]
    every: usize,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct FrameArgs {
    /// Dataset folder or `synthetic:...` spec.
    path: String,
    /// Frame number (as in the file name).
    #[arg(long)]
    frame: usize,
    /// Output colour PNG.
    #[arg(long)]
    rgb: std::path::PathBuf,
    /// Output depth PNG (16-bit, millimetres, 0 = invalid).
    #[arg(long)]
    depth: Option<std::path::PathBuf>,
}

#[derive(Args)]
pub struct InfoArgs {
    /// Dataset folder, bag, `synthetic[:agents=3,agent=0,frames=300,seed=0]`, or a live camera
    /// `ros2:[NAMESPACE]` (the topics on the DDS domain and what comes on the agent's).
    path: String,
    /// Frame range, e.g. 0..600.
    #[arg(long, default_value = "0..")]
    frames: FrameRange,
    /// Frames decoded to measure depth validity (evenly spread).
    #[arg(long, default_value_t = 20)]
    samples: usize,
    /// Configuration whose `[ros2]` topics (and `[camera]` lens) the readers use.
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct DatasetInfo {
    source: String,
    frames: usize,
    first_frame: usize,
    last_frame: usize,
    duration_s: f64,
    width: u32,
    height: u32,
    intrinsics: Intrinsics,
    /// Mean fraction of pixels with valid depth over the sampled frames.
    depth_valid_fraction: f64,
    depth_min_m: f64,
    depth_median_m: f64,
    depth_max_m: f64,
    sampled_frames: usize,
    ground_truth_poses: usize,
    trajectory_length_m: Option<f64>,
    /// A ROS 2 bag's topics and what the reader takes from them.
    #[serde(skip_serializing_if = "Option::is_none")]
    bag: Option<BagInfo>,
}

fn info(ds: &dyn Dataset, samples: usize) -> anyhow::Result<DatasetInfo> {
    let n = ds.len();
    let k = ds.intrinsics();
    let mut gt = Trajectory::default();
    for i in 0..n {
        if let Some(p) = ds.ground_truth(i)? {
            gt.push(ds.timestamp(i), p);
        }
    }
    let samples = samples.clamp(1, n);
    let mut valid_fraction = 0.0;
    // A fixed-size histogram keeps memory flat: 1 mm bins up to 20 m cover every sensor here.
    const BIN_M: f64 = 0.001;
    const BINS: usize = 20_000;
    let mut histogram = vec![0u64; BINS + 1];
    let (mut min, mut max) = (f64::INFINITY, 0.0f64);
    for s in 0..samples {
        let position = s * n / samples;
        let frame = ds.load(position)?;
        valid_fraction += frame.depth.valid_count() as f64 / frame.depth.data.len() as f64;
        for &d in frame.depth.data.iter().filter(|d| **d > 0.0) {
            let d = d as f64;
            min = min.min(d);
            max = max.max(d);
            histogram[((d / BIN_M) as usize).min(BINS)] += 1;
        }
    }
    let total: u64 = histogram.iter().sum();
    let mut seen = 0;
    let mut median = f64::NAN;
    for (bin, &count) in histogram.iter().enumerate() {
        seen += count;
        if total > 0 && seen * 2 >= total {
            median = (bin as f64 + 0.5) * BIN_M;
            break;
        }
    }
    Ok(DatasetInfo {
        source: ds.describe(),
        frames: n,
        first_frame: ds.frame_index(0),
        last_frame: ds.frame_index(n - 1),
        duration_s: ds.timestamp(n - 1) - ds.timestamp(0),
        width: k.width,
        height: k.height,
        intrinsics: k,
        depth_valid_fraction: valid_fraction / samples as f64,
        depth_min_m: if total > 0 { min } else { f64::NAN },
        depth_median_m: median,
        depth_max_m: max,
        sampled_frames: samples,
        ground_truth_poses: gt.len(),
        trajectory_length_m: (!gt.is_empty()).then(|| gt.path_length()),
        bag: None,
    })
}

fn print_info(i: &DatasetInfo) {
    println!("{}", i.source);
    println!(
        "  frames            {} (numbers {}..={}, {:.2} s)",
        i.frames, i.first_frame, i.last_frame, i.duration_s
    );
    println!("  resolution        {}x{}", i.width, i.height);
    let k = &i.intrinsics;
    println!(
        "  intrinsics        fx {} fy {} cx {} cy {}",
        k.fx, k.fy, k.cx, k.cy
    );
    println!(
        "  depth             {:.1}% valid, {}..{} m, median {} m ({} frames sampled)",
        100.0 * i.depth_valid_fraction,
        fmt_num(i.depth_min_m, 3),
        fmt_num(i.depth_max_m, 3),
        fmt_num(i.depth_median_m, 3),
        i.sampled_frames
    );
    match i.trajectory_length_m {
        Some(len) => println!(
            "  ground truth      {} poses, path length {len:.3} m",
            i.ground_truth_poses
        ),
        None => println!("  ground truth      none"),
    }
    if let Some(bag) = &i.bag {
        print_bag_info(bag);
    }
}

fn export_frame(args: &FrameArgs) -> anyhow::Result<()> {
    let range = FrameRange::new(args.frame, Some(args.frame + 1));
    let ds = datasets::open(&args.path, range)
        .with_context(|| format!("opening dataset {}", args.path))?;
    anyhow::ensure!(
        !ds.is_empty() && ds.frame_index(0) == args.frame,
        "{}: no frame {}",
        args.path,
        args.frame
    );
    let frame = ds.load(0)?;
    frame
        .rgb
        .save(&args.rgb)
        .with_context(|| format!("writing {}", args.rgb.display()))?;
    if let Some(depth) = &args.depth {
        datasets::write_depth_png(depth, &frame.depth, MILLIMETRES_PER_METRE)?;
    }
    Ok(())
}

const MILLIMETRES_PER_METRE: f64 = 1000.0;

pub fn run(command: &DatasetCommand) -> anyhow::Result<()> {
    let args = match command {
        DatasetCommand::Info(args) => args,
        DatasetCommand::Frame(args) => return export_frame(args),
        DatasetCommand::Covisibility(args) => return covisibility(args),
    };
    if datasets::live::is_live(&args.path) {
        let config = match &args.config {
            Some(path) => config::Config::load(path)?,
            None => config::Config::default(),
        };
        let info = super::live_info::live_info(&args.path, &config.ros2)?;
        return if args.json {
            print_json(&info)
        } else {
            super::live_info::print_live_info(&info);
            Ok(())
        };
    }
    let path = Path::new(&args.path);
    // A folder of agent folders (synth output, Multi-agent Replica) -> one block per agent.
    let sources: Vec<String> = if path.is_dir() && datasets::detect_layout(path).is_err() {
        let agents = datasets::agent_folders(path)?;
        if agents.is_empty() {
            datasets::detect_layout(path)?; // reports the unknown layout
        }
        agents
            .iter()
            .map(|p| p.to_string_lossy().into_owned())
            .collect()
    } else {
        vec![args.path.clone()]
    };
    let config = match &args.config {
        Some(path) => config::Config::load(path)?,
        None => config::Config::default(),
    };
    let mut infos = Vec::new();
    for source in &sources {
        let ds = datasets::open_with(source, args.frames, &config.dataset_options())
            .with_context(|| format!("opening dataset {source}"))?;
        let mut dataset_info =
            info(ds.as_ref(), args.samples).with_context(|| format!("reading dataset {source}"))?;
        if datasets::rosbag::is_bag(source) {
            dataset_info.bag = Some(bag_info(source, &config.ros2)?);
        }
        infos.push(dataset_info);
    }
    if args.json {
        return if infos.len() == 1 {
            print_json(&infos[0])
        } else {
            print_json(&infos)
        };
    }
    for i in &infos {
        print_info(i);
    }
    Ok(())
}

/// What `dataset covisibility` prints.
#[derive(Debug, Serialize)]
pub struct CovisibilityReport {
    pub frames_a: usize,
    pub frames_b: usize,
    /// Distance between the two sequences' first camera centres (metres).
    pub start_distance_m: f64,
    /// Angle between their first optical axes (degrees).
    pub start_view_angle_deg: f64,
    /// Over every sampled cross pair, the larger of both directions' co-visibility.
    pub pair_covisibility_max: f64,
    pub pair_covisibility_median: f64,
    /// Share of A's sampled surface seen by some sampled frame of B, and the reverse.
    pub map_overlap_a_in_b: f64,
    pub map_overlap_b_in_a: f64,
}

/// Every `every`-th frame of a sequence with its ground-truth pose.
fn posed_frames(
    spec: &str,
    range: FrameRange,
    every: usize,
) -> anyhow::Result<Vec<(datasets::Frame, nalgebra::Isometry3<f64>)>> {
    let ds = datasets::open(spec, range).with_context(|| format!("opening dataset {spec}"))?;
    anyhow::ensure!(!ds.is_empty(), "{spec}: no frames in the range");
    (0..ds.len())
        .step_by(every.max(1))
        .map(|position| {
            let frame = ds
                .load(position)
                .with_context(|| format!("{spec}: frame {}", ds.frame_index(position)))?;
            let pose = frame.world_from_camera_gt.with_context(|| {
                format!("{spec}: frame {} has no ground-truth pose", frame.index)
            })?;
            Ok((frame, pose))
        })
        .collect()
}

fn posed<'a>(
    frame: &'a datasets::Frame,
    pose: &'a nalgebra::Isometry3<f64>,
) -> metrics::covisibility::PosedDepth<'a> {
    metrics::covisibility::PosedDepth {
        depth: &frame.depth,
        intrinsics: &frame.intrinsics,
        world_from_camera: pose,
    }
}

fn covisibility(args: &CovisibilityArgs) -> anyhow::Result<()> {
    use metrics::covisibility::{CovisibilityParams, PosedDepth, covisibility_with_any};
    let a = posed_frames(&args.a, args.frames_a, args.every)?;
    let b = posed_frames(&args.b, args.frames_b, args.every)?;
    let a_posed: Vec<PosedDepth> = a.iter().map(|(f, p)| posed(f, p)).collect();
    let b_posed: Vec<PosedDepth> = b.iter().map(|(f, p)| posed(f, p)).collect();
    let params = CovisibilityParams::default();
    let mut pairs = Vec::new();
    for fa in &a_posed {
        for fb in &b_posed {
            let ab = covisibility_with_any(*fa, std::slice::from_ref(fb), &params).unwrap_or(0.0);
            let ba = covisibility_with_any(*fb, std::slice::from_ref(fa), &params).unwrap_or(0.0);
            pairs.push(ab.max(ba));
        }
    }
    pairs.sort_by(f64::total_cmp);
    let overlap = |of: &[PosedDepth], by: &[PosedDepth]| {
        let shares: Vec<f64> = of
            .iter()
            .filter_map(|f| covisibility_with_any(*f, by, &params))
            .collect();
        shares.iter().sum::<f64>() / shares.len().max(1) as f64
    };
    let (pose_a, pose_b) = (&a[0].1, &b[0].1);
    let axis = |p: &nalgebra::Isometry3<f64>| p.rotation * nalgebra::Vector3::z();
    let report = CovisibilityReport {
        frames_a: a.len(),
        frames_b: b.len(),
        start_distance_m: (pose_a.translation.vector - pose_b.translation.vector).norm(),
        start_view_angle_deg: axis(pose_a).angle(&axis(pose_b)).to_degrees(),
        pair_covisibility_max: pairs.last().copied().unwrap_or(0.0),
        pair_covisibility_median: pairs[pairs.len() / 2],
        map_overlap_a_in_b: overlap(&a_posed, &b_posed),
        map_overlap_b_in_a: overlap(&b_posed, &a_posed),
    };
    if args.json {
        print_json(&report)?;
    } else {
        println!(
            "{} frames of A, {} of B (every {})",
            report.frames_a, report.frames_b, args.every
        );
        println!(
            "  first frames        {:.2} m apart, optical axes {:.0} degrees apart",
            report.start_distance_m, report.start_view_angle_deg
        );
        println!(
            "  frame pairs         co-visibility max {:.1} %, median {:.1} %",
            100.0 * report.pair_covisibility_max,
            100.0 * report.pair_covisibility_median
        );
        println!(
            "  maps                {:.1} % of A seen by B, {:.1} % of B seen by A",
            100.0 * report.map_overlap_a_in_b,
            100.0 * report.map_overlap_b_in_a
        );
    }
    Ok(())
}
