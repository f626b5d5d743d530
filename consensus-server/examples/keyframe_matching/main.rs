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
//!
//! Files: [`pairs`] chooses the pairs; [`measure`] measures one, with [`descriptors`] and
//! [`repeatability`]; [`report`] holds the figures, [`table`] prints them, [`dump`] writes the
//! pair images.

mod descriptors;
mod dump;
mod measure;
mod pairs;
mod repeatability;
mod report;
mod table;

use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use config::AlignmentConfig;

use measure::measure;

// The command line (see the module documentation).
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

/// `NAME=JSON`: the default configuration with the JSON object's fields changed.
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
    let mut pairs = pairs::real_pairs(&args)?;
    pairs.extend(pairs::synthetic_pairs(&args)?);
    eprintln!(
        "{} pairs chosen in {:.1} s",
        pairs.len(),
        clock.elapsed().as_secs_f64()
    );
    for pair in &pairs {
        eprintln!("  {} ({} / {})", pair.name, pair.a.label, pair.b.label);
    }

    let mut reports = Vec::new();
    table::print_header();
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
            table::print_row(&r);
            if args.verbose {
                table::print_detail(&r);
            }
            reports.push(r);
        }
    }
    table::print_totals(&variants, &reports);
    if let Some(path) = &args.json {
        std::fs::write(path, serde_json::to_string_pretty(&reports)?)?;
        eprintln!("report written to {}", path.display());
    }
    Ok(())
}
