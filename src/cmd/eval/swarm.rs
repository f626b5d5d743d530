//! `mac-ego3d eval swarm --dir DIR`: the figures of one swarm run (its metrics.json) from
//! what its processes wrote: DIR/consensus.json, DIR/agent_K.tum (world frame, by the
//! consensus), DIR/agent_K/{metrics.json, groundtruth.tum} (by each agent).
//!
//! Rendering figures (`psnr`, `ssim`, `depth_l1_cm`, and `lpips` with `--lpips-weights`): the
//! merged world map (DIR/map.ply) rendered at every `--render-every`-th frame of every linked
//! agent, at the pose the consensus gives it (DIR/agent_K.tum), against that dataset frame; a
//! few side-by-side PNGs go to DIR/renders/. With `--render-every 0`, or when the agents' frames
//! cannot be reopened, they are the mean of each agent's own map at its own poses instead.
//! `rendering_source` says which.
//!
//! DIR/report.html (crate::report) is written next to metrics.json: the figures, trajectories,
//! renders and consensus events of the run in one offline page.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use alexnet::lpips::Lpips;
use anyhow::{Context, bail};
use clap::Args;
use datasets::{self, FrameRange};
use geometry::trajectory::Trajectory;
use mac_agent::evaluation::{MapRenderer, QualitySummary, evaluate_frame};
use metrics::ate::{Alignment, DEFAULT_MAX_DT, joint_ate};
use serde::Serialize;
use serde_json::Value;

use crate::cmd::swarm::record::{AgentNetwork, LaunchRecord, Transport, network_per_agent};
use crate::cmd::{fmt_num, print_json};

#[derive(Args)]
pub struct SwarmArgs {
    /// The run's output directory (`mac-ego3d swarm --out`).
    #[arg(long)]
    dir: PathBuf,
    /// Print the JSON instead of a table (DIR/metrics.json is written either way).
    #[arg(long)]
    json: bool,
    /// Render the merged map at every n-th frame of each agent (0: do not render).
    #[arg(long, default_value_t = 20)]
    render_every: usize,
    /// Side-by-side comparison PNGs written per agent.
    #[arg(long, default_value_t = 2)]
    renders: usize,
    /// LPIPS weights (.npz). Default: $MAC_EGO3D_WEIGHTS, else the cache scripts/setup.sh
    /// fills; LPIPS is left out without them.
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
}

impl SwarmArgs {
    /// The figures `mac-ego3d swarm` computes at the end of a run: a table, two comparison
    /// images per agent, LPIPS with `lpips_weights` (else the default weights).
    pub fn for_run(dir: &Path, render_every: usize, lpips_weights: Option<PathBuf>) -> Self {
        Self {
            dir: dir.to_path_buf(),
            json: false,
            render_every,
            renders: 2,
            lpips_weights,
        }
    }

    /// The figures of the run in `dir`, rendering every `render_every`-th frame (0: none), with
    /// no comparison images.
    pub fn for_dir(dir: &Path, render_every: usize) -> Self {
        Self {
            dir: dir.to_path_buf(),
            json: true,
            render_every,
            renders: 0,
            lpips_weights: None,
        }
    }
}

/// DIR/metrics.json.
#[derive(Debug, Serialize)]
pub struct SwarmMetrics {
    /// One SE(3) alignment of all linked agents' world trajectories to ground truth.
    pub ate_joint_rmse_m: Option<f64>,
    /// Per agent under the joint alignment (`null`: not linked to the world frame).
    pub ate_per_agent_rmse_m: Vec<Option<f64>>,
    /// Agents the consensus never placed in the world frame.
    pub agents_not_linked: Vec<u32>,
    /// The global descriptor the agents ran for place recognition ("alexnet-gem", or
    /// "thumbnail", the classical fallback without weights), per agent (`null`: not reported).
    pub descriptor_per_agent: Vec<Option<String>>,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    pub lpips: Option<f64>,
    pub depth_l1_cm: Option<f64>,
    pub rendering_source: &'static str,
    /// Frames the rendering figures average over.
    pub rendering_frames: usize,
    pub fps_per_agent: Vec<Option<f64>>,
    pub bytes_per_agent_per_s: Vec<Option<f64>>,
    pub consensus_latency_ms_median: Option<f64>,
    pub loop_closures_accepted: u64,
    pub loop_closures_rejected: u64,
    pub inter_agent_closures_accepted: u64,
    pub wall_s: Option<f64>,
    /// Which transport carried the run (DIR/launch.json); absent for a run `mac-ego3d swarm`
    /// did not launch.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub transport: Option<Transport>,
    /// Over zenoh: each agent's traffic on the network as its host's bridge counted it (`null`
    /// for an agent whose bridge wrote no report).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub network_bytes_per_agent: Option<BTreeMap<String, Option<AgentNetwork>>>,
}

fn read_json(path: &Path) -> anyhow::Result<Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

fn mean(values: &[Option<f64>]) -> Option<f64> {
    let present: Vec<f64> = values.iter().flatten().copied().collect();
    (!present.is_empty()).then(|| present.iter().sum::<f64>() / present.len() as f64)
}

/// Renders the merged map at the linked agents' world poses; `None` when an agent's frames
/// cannot be reopened (its metrics.json lacks the dataset spec) or nothing was evaluated.
fn merged_map_quality(
    dir: &Path,
    linked: &[u32],
    agent_metrics: &[(u32, Option<Value>)],
    args: &SwarmArgs,
) -> anyhow::Result<Option<QualitySummary>> {
    if args.render_every == 0 || linked.is_empty() {
        return Ok(None);
    }
    let map_path = dir.join("map.ply");
    let map = render_core::ply::load_ply(&map_path)
        .with_context(|| format!("reading the merged map {}", map_path.display()))?;
    let renderer = MapRenderer::new(&map).context("uploading the merged map")?;
    let weights = args
        .lpips_weights
        .clone()
        .or_else(alexnet::weights::default_alexnet_weights);
    let lpips = match &weights {
        Some(path) => Some(
            Lpips::load(path)
                .with_context(|| format!("loading LPIPS weights {}", path.display()))?,
        ),
        None => None,
    };
    let renders = dir.join("renders");
    let mut qualities = Vec::new();
    for &id in linked {
        let Some(metrics) = agent_metrics
            .iter()
            .find(|(k, _)| *k == id)
            .and_then(|(_, m)| m.as_ref())
        else {
            return Ok(None);
        };
        let (Some(spec), Some(range)) = (
            metrics["dataset_spec"].as_str(),
            metrics["frame_range"].as_str(),
        ) else {
            return Ok(None);
        };
        let range: FrameRange = range
            .parse()
            .map_err(|e| anyhow::anyhow!("agent {id}: frame range {range:?}: {e}"))?;
        let dataset = datasets::open(spec, range)
            .with_context(|| format!("reopening agent {id}'s frames ({spec})"))?;
        let world = Trajectory::read_tum(&dir.join(format!("agent_{id}.tum")))?;
        let evaluated: Vec<usize> = (0..dataset.len()).step_by(args.render_every).collect();
        let comparison_every = evaluated.len().div_ceil(args.renders.max(1)).max(1);
        if args.renders > 0 {
            std::fs::create_dir_all(&renders)
                .with_context(|| format!("creating {}", renders.display()))?;
        }
        for (i, position) in evaluated.into_iter().enumerate() {
            let frame = match dataset.load(position) {
                Ok(frame) => frame,
                Err(error) => {
                    tracing::warn!(agent = id, %error, "frame skipped");
                    continue;
                }
            };
            // The agent wrote one pose per frame it tracked, stamped with the frame's time.
            let Some(pose) = world
                .stamps
                .iter()
                .position(|t| (t - frame.timestamp).abs() < TIMESTAMP_TOLERANCE_S)
                .map(|k| world.poses[k])
            else {
                continue;
            };
            let comparison = (args.renders > 0 && i % comparison_every == 0)
                .then(|| renders.join(format!("agent_{id}_frame_{:06}.png", frame.index)));
            qualities.push(evaluate_frame(
                &renderer,
                &frame,
                &pose,
                lpips.as_ref(),
                comparison.as_deref(),
            )?);
        }
    }
    Ok((!qualities.is_empty()).then(|| QualitySummary::of(&qualities)))
}

/// "alexnet-gem" when every agent ran it; otherwise the kinds per agent, the fallback named.
fn describe_descriptors(per_agent: &[Option<String>]) -> String {
    let name = |kind: &Option<String>| match kind.as_deref() {
        Some("thumbnail") => "thumbnail (classical fallback: no AlexNet weights, see \
                              scripts/get_lpips_weights.sh)"
            .to_string(),
        Some(kind) => kind.to_string(),
        None => "not reported".to_string(),
    };
    match per_agent {
        [] => "-".to_string(),
        [first, rest @ ..] if rest.iter().all(|kind| kind == first) => name(first),
        _ => per_agent
            .iter()
            .enumerate()
            .map(|(k, kind)| format!("agent {k}: {}", name(kind)))
            .collect::<Vec<_>>()
            .join(", "),
    }
}

/// Largest difference between a trajectory stamp and its frame's timestamp (the agent writes
/// them with microsecond precision).
const TIMESTAMP_TOLERANCE_S: f64 = 1e-5;

/// Computes the swarm's figures and writes DIR/metrics.json.
pub fn swarm_metrics(dir: &Path, args: &SwarmArgs) -> anyhow::Result<SwarmMetrics> {
    let consensus = read_json(&dir.join("consensus.json"))?;
    let launch = LaunchRecord::read(dir)?;
    let mut agent_ids: Vec<u32> = consensus["agents"]
        .as_object()
        .map(|agents| agents.keys().filter_map(|k| k.parse().ok()).collect())
        .unwrap_or_default();
    agent_ids.sort_unstable();
    if agent_ids.is_empty() {
        bail!(
            "{}: the consensus heard from no agent",
            dir.join("consensus.json").display()
        );
    }
    let mut pairs = Vec::new();
    let mut linked = Vec::new();
    let mut not_linked = Vec::new();
    let mut agent_metrics = Vec::new();
    for &id in &agent_ids {
        let own = dir.join(format!("agent_{id}"));
        agent_metrics.push((id, read_json(&own.join("metrics.json")).ok()));
        let world = dir.join(format!("agent_{id}.tum"));
        let truth = own.join("groundtruth.tum");
        if !world.exists() {
            not_linked.push(id);
            continue;
        }
        if !truth.exists() {
            bail!("{}: no ground truth to score agent {id}", truth.display());
        }
        pairs.push((Trajectory::read_tum(&truth)?, Trajectory::read_tum(&world)?));
        linked.push(id);
    }
    let joint = if pairs.is_empty() {
        None
    } else {
        Some(joint_ate(&pairs, Alignment::Se3, DEFAULT_MAX_DT).context("joint ATE")?)
    };
    let per_agent = agent_ids
        .iter()
        .map(|id| {
            let k = linked.iter().position(|l| l == id)?;
            Some(joint.as_ref()?.per_agent_joint_aligned[k].rmse)
        })
        .collect();
    let field = |name: &str| -> Vec<Option<f64>> {
        agent_metrics
            .iter()
            .map(|(_, m)| m.as_ref().and_then(|m| m[name].as_f64()))
            .collect()
    };
    let bytes = agent_metrics
        .iter()
        .map(|(_, m)| {
            m.as_ref()
                .and_then(|m| m["swarm"]["bytes_sent_per_s"].as_f64())
        })
        .collect();
    let descriptors = agent_metrics
        .iter()
        .map(|(_, m)| {
            m.as_ref()
                .and_then(|m| m["swarm"]["descriptor"].as_str())
                .map(str::to_string)
        })
        .collect();
    let count = |name: &str| consensus[name].as_u64().unwrap_or(0);
    let merged = merged_map_quality(dir, &linked, &agent_metrics, args)?;
    let (psnr, ssim, lpips, depth_l1_cm, rendering_source, rendering_frames) = match merged {
        Some(q) => (
            q.psnr,
            q.ssim,
            q.lpips,
            q.depth_l1_cm,
            "merged map at the consensus's world poses",
            q.frames,
        ),
        None => (
            mean(&field("psnr")),
            mean(&field("ssim")),
            mean(&field("lpips")),
            mean(&field("depth_l1_cm")),
            "mean over agents of each agent's own map at its own poses",
            0,
        ),
    };
    let metrics = SwarmMetrics {
        ate_joint_rmse_m: joint.as_ref().map(|j| j.joint.rmse),
        ate_per_agent_rmse_m: per_agent,
        agents_not_linked: not_linked,
        descriptor_per_agent: descriptors,
        psnr,
        ssim,
        lpips,
        depth_l1_cm,
        rendering_source,
        rendering_frames,
        fps_per_agent: field("fps"),
        bytes_per_agent_per_s: bytes,
        consensus_latency_ms_median: consensus["consensus_latency_ms_median"].as_f64(),
        loop_closures_accepted: count("loop_closures_accepted"),
        loop_closures_rejected: count("loop_closures_rejected"),
        inter_agent_closures_accepted: count("inter_agent_closures_accepted"),
        wall_s: consensus["wall_s"].as_f64(),
        transport: launch.as_ref().map(|record| record.transport),
        network_bytes_per_agent: match &launch {
            Some(record) if record.transport == Transport::Zenoh => {
                Some(network_per_agent(dir, record.datasets.len())?)
            }
            _ => None,
        },
    };
    let path = dir.join("metrics.json");
    std::fs::write(&path, serde_json::to_string_pretty(&metrics)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(metrics)
}

pub fn run(args: &SwarmArgs) -> anyhow::Result<()> {
    let m = swarm_metrics(&args.dir, args)?;
    let report = crate::report::write_report(&args.dir)?;
    if args.json {
        return print_json(&m);
    }
    let cm = |v: Option<f64>| v.map_or("-".into(), |v| fmt_num(v * 100.0, 2));
    let num = |v: Option<f64>, d: usize| v.map_or("-".into(), |v| fmt_num(v, d));
    println!("swarm run {}", args.dir.display());
    println!(
        "  {:<34} {:>12}",
        "joint ATE RMSE cm",
        cm(m.ate_joint_rmse_m)
    );
    for (k, ate) in m.ate_per_agent_rmse_m.iter().enumerate() {
        println!(
            "  {:<34} {:>12}",
            format!("agent {k} ATE cm (joint align)"),
            cm(*ate)
        );
    }
    if !m.agents_not_linked.is_empty() {
        println!(
            "  agents not linked to the world: {:?}",
            m.agents_not_linked
        );
    }
    println!(
        "  global descriptor: {}",
        describe_descriptors(&m.descriptor_per_agent)
    );
    println!(
        "  rendering: {} ({} frames)",
        m.rendering_source, m.rendering_frames
    );
    println!("  {:<34} {:>12}", "PSNR dB", num(m.psnr, 2));
    println!("  {:<34} {:>12}", "SSIM", num(m.ssim, 3));
    println!("  {:<34} {:>12}", "LPIPS (AlexNet)", num(m.lpips, 3));
    println!("  {:<34} {:>12}", "depth L1 cm", num(m.depth_l1_cm, 2));
    println!(
        "  {:<34} {:>12}",
        "loop closures accepted / rejected",
        format!(
            "{} / {}",
            m.loop_closures_accepted, m.loop_closures_rejected
        )
    );
    println!(
        "  {:<34} {:>12}",
        "inter-agent closures accepted", m.inter_agent_closures_accepted
    );
    println!(
        "  {:<34} {:>12}",
        "consensus latency ms (median)",
        num(m.consensus_latency_ms_median, 0)
    );
    for (k, fps) in m.fps_per_agent.iter().enumerate() {
        println!(
            "  {:<34} {:>12}",
            format!("agent {k} frames/s, kB/s sent"),
            format!(
                "{} / {}",
                num(*fps, 1),
                num(m.bytes_per_agent_per_s[k].map(|b| b / 1e3), 0)
            )
        );
    }
    println!("  metrics: {}", args.dir.join("metrics.json").display());
    println!("  report:  {}", report.display());
    Ok(())
}
