//! `mac-ego3d eval ...`: trajectory, image, LPIPS and depth metrics (docs/method.md, Metrics).

use std::path::{Path, PathBuf};

use alexnet::lpips::Lpips;
use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use datasets::read_depth_u16;
use geometry::depth::DepthImage;
use geometry::trajectory::{Trajectory, TrajectoryFormat};
use metrics::ate::{Alignment, AteStats, DEFAULT_MAX_DT, ate, joint_ate};
use metrics::depth::depth_l1_cm;
use metrics::image::image_quality;
use serde::Serialize;

use super::{fmt_num, print_json};

pub mod held_out;
pub mod swarm;

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Absolute trajectory error. Give --gt/--est once, or once per agent for joint ATE (one
    /// alignment for all agents together, plus per-agent figures).
    Ate(AteArgs),
    /// PSNR and SSIM (3DGS zero-padded `ssim` and scikit-image valid-region `ssim_valid`).
    Image(ImageArgs),
    /// LPIPS (AlexNet, v0.1).
    Lpips(LpipsArgs),
    /// Depth L1 (cm) over pixels with valid reference depth, from 16-bit depth PNGs.
    Depth(DepthArgs),
    /// A swarm run's figures (joint ATE, closures, latency, bandwidth) -> DIR/metrics.json.
    Swarm(swarm::SwarmArgs),
}

#[derive(Args)]
pub struct AteArgs {
    /// Ground-truth trajectory (repeat once per agent).
    #[arg(long, required = true)]
    gt: Vec<PathBuf>,
    /// Estimated trajectory (repeat once per agent, same order as --gt).
    #[arg(long, required = true)]
    est: Vec<PathBuf>,
    /// Alignment of the estimate to the ground truth: se3, sim3 or none.
    #[arg(long, default_value = "se3")]
    align: Alignment,
    /// Largest timestamp difference for a pose pair, seconds.
    #[arg(long, default_value_t = DEFAULT_MAX_DT)]
    max_dt: f64,
    /// File format of both files: tum, or kitti-c2w (16 numbers per line, camera-to-world).
    #[arg(long, default_value = "tum")]
    format: TrajectoryFormat,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct ImageArgs {
    #[arg(long)]
    reference: PathBuf,
    #[arg(long)]
    rendered: PathBuf,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct LpipsArgs {
    /// First image.
    a: PathBuf,
    /// Second image.
    b: PathBuf,
    /// LPIPS AlexNet weights (.npz; scripts/get_lpips_weights.sh obtains them). Default:
    /// $MAC_EGO3D_WEIGHTS, else the cache scripts/setup.sh fills
    /// (~/.cache/mac-ego3d/weights/lpips/alexnet.npz).
    #[arg(long)]
    weights: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct DepthArgs {
    #[arg(long)]
    reference: PathBuf,
    #[arg(long)]
    rendered: PathBuf,
    /// Raw depth units per metre of both PNGs (1000 = millimetres, 5000 TUM, 6553.5 Replica).
    #[arg(long, default_value_t = 1000.0)]
    units_per_metre: f64,
    #[arg(long)]
    json: bool,
}

pub fn run(command: &EvalCommand) -> anyhow::Result<()> {
    match command {
        EvalCommand::Ate(a) => run_ate(a),
        EvalCommand::Image(a) => run_image(a),
        EvalCommand::Lpips(a) => run_lpips(a),
        EvalCommand::Depth(a) => run_depth(a),
        EvalCommand::Swarm(a) => swarm::run(a),
    }
}

fn stats_row(name: &str, s: &AteStats) -> String {
    format!(
        "{name:<22} {:>10} {:>10} {:>10} {:>10} {:>7}",
        fmt_num(s.rmse, 6),
        fmt_num(s.mean, 6),
        fmt_num(s.median, 6),
        fmt_num(s.max, 6),
        s.pairs
    )
}

fn run_ate(args: &AteArgs) -> anyhow::Result<()> {
    if args.gt.len() != args.est.len() {
        bail!(
            "--gt was given {} times and --est {} times: give one of each per agent",
            args.gt.len(),
            args.est.len()
        );
    }
    let read = |p: &Path| {
        Trajectory::read(p, args.format)
            .with_context(|| format!("reading trajectory {}", p.display()))
    };
    let mut agents = Vec::new();
    for (gt, est) in args.gt.iter().zip(&args.est) {
        agents.push((read(gt)?, read(est)?));
    }
    if agents.len() == 1 {
        let (gt, est) = &agents[0];
        let r = ate(gt, est, args.align, args.max_dt)
            .with_context(|| format!("{} vs {}", args.gt[0].display(), args.est[0].display()))?;
        if args.json {
            return print_json(&r.stats);
        }
        println!(
            "ATE (translation, metres; alignment {:?}, max dt {} s)",
            args.align, args.max_dt
        );
        println!(
            "{:<22} {:>10} {:>10} {:>10} {:>10} {:>7}",
            "", "rmse", "mean", "median", "max", "pairs"
        );
        println!("{}", stats_row("trajectory", &r.stats));
        return Ok(());
    }
    let j = joint_ate(&agents, args.align, args.max_dt)?;
    if args.json {
        #[derive(Serialize)]
        struct AgentJson<'a> {
            gt: &'a Path,
            est: &'a Path,
            joint_aligned: AteStats,
            self_aligned: AteStats,
        }
        #[derive(Serialize)]
        struct JointJson<'a> {
            #[serde(flatten)]
            joint: AteStats,
            agents: Vec<AgentJson<'a>>,
        }
        let out = JointJson {
            joint: j.joint,
            agents: (0..agents.len())
                .map(|k| AgentJson {
                    gt: &args.gt[k],
                    est: &args.est[k],
                    joint_aligned: j.per_agent_joint_aligned[k],
                    self_aligned: j.per_agent_self_aligned[k],
                })
                .collect(),
        };
        return print_json(&out);
    }
    println!(
        "Joint ATE over {} agents (translation, metres; one {:?} alignment for all)",
        agents.len(),
        args.align
    );
    println!(
        "{:<22} {:>10} {:>10} {:>10} {:>10} {:>7}",
        "", "rmse", "mean", "median", "max", "pairs"
    );
    println!("{}", stats_row("joint", &j.joint));
    for k in 0..agents.len() {
        println!(
            "{}",
            stats_row(
                &format!("agent {k} (joint align)"),
                &j.per_agent_joint_aligned[k]
            )
        );
        println!(
            "{}",
            stats_row(
                &format!("agent {k} (own align)"),
                &j.per_agent_self_aligned[k]
            )
        );
    }
    Ok(())
}

fn open_rgb(path: &Path) -> anyhow::Result<image::RgbImage> {
    Ok(image::open(path)
        .with_context(|| format!("reading image {}", path.display()))?
        .to_rgb8())
}

fn run_image(args: &ImageArgs) -> anyhow::Result<()> {
    let reference = open_rgb(&args.reference)?;
    let rendered = open_rgb(&args.rendered)?;
    let q = image_quality(&reference, &rendered).with_context(|| {
        format!(
            "{} vs {}",
            args.reference.display(),
            args.rendered.display()
        )
    })?;
    if args.json {
        return print_json(&q);
    }
    println!("PSNR  {} dB (data range 1)", fmt_num(q.psnr, 4));
    println!(
        "SSIM  {} (11x11 Gaussian, zero-padded, 3DGS style)",
        fmt_num(q.ssim, 6)
    );
    println!(
        "SSIM  {} (valid region, scikit-image style)",
        fmt_num(q.ssim_valid, 6)
    );
    Ok(())
}

fn run_lpips(args: &LpipsArgs) -> anyhow::Result<()> {
    let weights = match &args.weights {
        Some(path) => path.clone(),
        None => alexnet::weights::resolve_default()?,
    };
    let lpips = Lpips::load(&weights).with_context(|| {
        format!(
            "loading LPIPS weights {} (see scripts/get_lpips_weights.sh)",
            weights.display()
        )
    })?;
    let a = open_rgb(&args.a)?;
    let b = open_rgb(&args.b)?;
    let d = lpips
        .distance(&a, &b)
        .with_context(|| format!("{} vs {}", args.a.display(), args.b.display()))?;
    if args.json {
        return print_json(&serde_json::json!({ "lpips": d }));
    }
    println!("LPIPS {} (AlexNet, v0.1)", fmt_num(d, 6));
    Ok(())
}

fn read_depth(path: &Path, units_per_metre: f64) -> anyhow::Result<DepthImage> {
    let (w, h, raw) = read_depth_u16(path, 0)?;
    Ok(DepthImage::from_raw_u16(w, h, &raw, units_per_metre, None))
}

fn run_depth(args: &DepthArgs) -> anyhow::Result<()> {
    if !(args.units_per_metre.is_finite() && args.units_per_metre > 0.0) {
        bail!(
            "--units-per-metre must be positive, got {}",
            args.units_per_metre
        );
    }
    let reference = read_depth(&args.reference, args.units_per_metre)?;
    let rendered = read_depth(&args.rendered, args.units_per_metre)?;
    let l1 = depth_l1_cm(&reference, &rendered)?
        .with_context(|| format!("{} has no valid depth pixel", args.reference.display()))?;
    if args.json {
        return print_json(&serde_json::json!({ "depth_l1_cm": l1 }));
    }
    println!(
        "depth L1 {} cm (over valid reference pixels)",
        fmt_num(l1, 4)
    );
    Ok(())
}
