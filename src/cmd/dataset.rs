//! `mac-ego3d dataset info PATH`: what a dataset holds, read through the same readers SLAM uses.

use std::path::Path;

use anyhow::Context;
use clap::{Args, Subcommand};
use serde::Serialize;
use slam_core::camera::Intrinsics;
use slam_core::dataset::{self, Dataset, FrameRange};
use slam_core::trajectory::Trajectory;

use super::{fmt_num, print_json};

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Frames, resolution, intrinsics, depth validity and trajectory length of a dataset (a
    /// folder, a folder of agent folders, or a `synthetic:...` spec).
    Info(InfoArgs),
    /// Decode one frame through the dataset reader and write it as lossless PNGs (RGB, and depth
    /// as 16-bit millimetres).
    Frame(FrameArgs),
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
    /// Dataset folder or `synthetic[:agents=3,agent=0,frames=300,seed=0]`.
    path: String,
    /// Frame range, e.g. 0..600.
    #[arg(long, default_value = "0..")]
    frames: FrameRange,
    /// Frames decoded to measure depth validity (evenly spread).
    #[arg(long, default_value_t = 20)]
    samples: usize,
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
}

fn export_frame(args: &FrameArgs) -> anyhow::Result<()> {
    let range = FrameRange {
        first: args.frame,
        end: Some(args.frame + 1),
    };
    let ds = dataset::open(&args.path, range)
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
        dataset::write_depth_png(depth, &frame.depth, MILLIMETRES_PER_METRE)?;
    }
    Ok(())
}

const MILLIMETRES_PER_METRE: f64 = 1000.0;

pub fn run(command: &DatasetCommand) -> anyhow::Result<()> {
    let args = match command {
        DatasetCommand::Info(args) => args,
        DatasetCommand::Frame(args) => return export_frame(args),
    };
    let path = Path::new(&args.path);
    // A folder of agent folders (synth output, Multi-agent Replica) -> one block per agent.
    let sources: Vec<String> = if path.is_dir() && dataset::detect_layout(path).is_err() {
        let agents = dataset::agent_folders(path)?;
        if agents.is_empty() {
            dataset::detect_layout(path)?; // reports the unknown layout
        }
        agents
            .iter()
            .map(|p| p.to_string_lossy().into_owned())
            .collect()
    } else {
        vec![args.path.clone()]
    };
    let mut infos = Vec::new();
    for source in &sources {
        let ds = dataset::open(source, args.frames)
            .with_context(|| format!("opening dataset {source}"))?;
        infos.push(
            info(ds.as_ref(), args.samples).with_context(|| format!("reading dataset {source}"))?,
        );
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
