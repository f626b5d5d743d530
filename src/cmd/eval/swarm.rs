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
use geometry::trajectory::Trajectory;
use mac_agent::evaluation::{MapRenderer, QualitySummary};
use metrics::ate::{Alignment, DEFAULT_MAX_DT, joint_ate};
use serde::Serialize;
use serde_json::Value;

use super::held_out::{AgentFrames, Protocol, score, summary};
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
    /// The merged map on held-out frames (no map was optimised on them; one per window of
    /// `--render-every` frames, `crate::cmd::eval::held_out`), at the same world poses (`null`:
    /// not rendered, or `held_out_unavailable` says why).
    pub psnr_held_out: Option<f64>,
    pub ssim_held_out: Option<f64>,
    pub lpips_held_out: Option<f64>,
    pub depth_l1_cm_held_out: Option<f64>,
    pub held_out_frames: usize,
    pub held_out_unavailable: Option<String>,
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

/// The merged map's figures on the linked agents' frames at their world poses, under both
/// protocols (all frames, held out).
struct MergedQuality {
    all_frames: Option<QualitySummary>,
    held_out: Option<QualitySummary>,
    /// Why there are no held-out figures, when there are none.
    held_out_unavailable: Option<String>,
}

/// Renders the merged map at the linked agents' world poses; `None` when an agent's frames
/// cannot be reopened (its metrics.json lacks the dataset spec) or nothing was evaluated.
fn merged_map_quality(
    dir: &Path,
    linked: &[u32],
    agent_metrics: &[(u32, Option<Value>)],
    args: &SwarmArgs,
) -> anyhow::Result<Option<MergedQuality>> {
    if args.render_every == 0 || linked.is_empty() {
        return Ok(None);
    }
    let mut agents = Vec::new();
    for &id in linked {
        let Some(metrics) = agent_metrics
            .iter()
            .find(|(k, _)| *k == id)
            .and_then(|(_, m)| m.as_ref())
        else {
            return Ok(None);
        };
        let Some(agent) = AgentFrames::open(dir, id, metrics)? else {
            return Ok(None);
        };
        agents.push(agent);
    }
    let map_path = dir.join("map.ply");
    let map = splats::ply::load_ply(&map_path)
        .with_context(|| format!("reading the merged map {}", map_path.display()))?;
    let renderer = MapRenderer::new(&map).context("uploading the merged map")?;
    let lpips = load_lpips(args.lpips_weights.as_deref())?;
    let renders = dir.join("renders");
    if args.renders > 0 {
        std::fs::create_dir_all(&renders)
            .with_context(|| format!("creating {}", renders.display()))?;
    }
    let mut all_frames = Vec::new();
    let mut held_out = Vec::new();
    let mut held_out_unavailable = None;
    for agent in &agents {
        let id = agent.agent_id;
        let positions = agent.positions(&agents, args.render_every, Protocol::AllFrames)?;
        let comparison_every = positions.len().div_ceil(args.renders.max(1)).max(1);
        let comparisons = |i: usize, frame: usize| {
            (args.renders > 0 && i.is_multiple_of(comparison_every))
                .then(|| renders.join(format!("agent_{id}_frame_{frame:06}.png")))
        };
        all_frames.extend(score(
            &renderer,
            agent,
            &agent.world,
            &positions,
            lpips.as_ref(),
            &comparisons,
        )?);
        match agent.positions(&agents, args.render_every, Protocol::HeldOut) {
            Ok(positions) => held_out.extend(score(
                &renderer,
                agent,
                &agent.world,
                &positions,
                lpips.as_ref(),
                &|_, _| None,
            )?),
            Err(error) => held_out_unavailable = Some(format!("{error:#}")),
        }
    }
    if held_out_unavailable.is_some() {
        held_out.clear();
    }
    Ok(Some(MergedQuality {
        all_frames: summary(&all_frames),
        held_out: summary(&held_out),
        held_out_unavailable,
    }))
}

/// The LPIPS network from `given` weights, else the default lookup; `None` without weights.
pub fn load_lpips(given: Option<&Path>) -> anyhow::Result<Option<Lpips>> {
    let weights = given
        .map(Path::to_path_buf)
        .or_else(alexnet::weights::default_alexnet_weights);
    weights
        .map(|path| {
            Lpips::load(&path).with_context(|| format!("loading LPIPS weights {}", path.display()))
        })
        .transpose()
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
    // Linked agents with ground truth, in the order of `pairs`.
    let mut scored = Vec::new();
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
        linked.push(id);
        if truth.exists() {
            pairs.push((Trajectory::read_tum(&truth)?, Trajectory::read_tum(&world)?));
            scored.push(id);
        } else {
            // A live camera has no ground truth: the agent is linked, its ATE unknown.
            tracing::info!(
                agent = id,
                "no ground truth: agent left out of the joint ATE"
            );
        }
    }
    let joint = if pairs.is_empty() {
        None
    } else {
        Some(joint_ate(&pairs, Alignment::Se3, DEFAULT_MAX_DT).context("joint ATE")?)
    };
    let per_agent = agent_ids
        .iter()
        .map(|id| {
            let k = scored.iter().position(|l| l == id)?;
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
    let (held_out, held_out_unavailable) = match &merged {
        Some(q) => (
            q.held_out.clone().unwrap_or_default(),
            q.held_out_unavailable.clone(),
        ),
        None => (QualitySummary::default(), None),
    };
    let (psnr, ssim, lpips, depth_l1_cm, rendering_source, rendering_frames) =
        match merged.and_then(|q| q.all_frames) {
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
        psnr_held_out: held_out.psnr,
        ssim_held_out: held_out.ssim,
        lpips_held_out: held_out.lpips,
        depth_l1_cm_held_out: held_out.depth_l1_cm,
        held_out_frames: held_out.frames,
        held_out_unavailable,
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
    if m.held_out_frames > 0 {
        println!(
            "  {:<34} {:>12}",
            format!(
                "held out ({} frames): PSNR / SSIM / LPIPS",
                m.held_out_frames
            ),
            format!(
                "{} / {} / {}",
                num(m.psnr_held_out, 2),
                num(m.ssim_held_out, 3),
                num(m.lpips_held_out, 3)
            )
        );
    } else if let Some(why) = &m.held_out_unavailable {
        println!("  held-out frames: none ({why})");
    }
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
