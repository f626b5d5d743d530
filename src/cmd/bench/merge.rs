//! `mac-ego3d bench merge --dir RUN`: what the consensus's merged map adds over each agent's own
//! map, per agent, on that agent's frames: both maps rendered on the same frames (each from the
//! poses of its own frame: the own map from agent_K/trajectory_map.tum, the merged map from the
//! consensus's agent_K.tum), under both protocols of `crate::cmd::eval::held_out` (held-out
//! frames, which no map was optimised on, and every n-th frame). With the Gaussian counts and the
//! joint refinement's time; a table, or JSON with `--json`; DIR/merge_bench.json either way.
//!
//! Beside them, the own map rendered at the world poses (`own_at_world`): what the placement
//! alone costs. The merged map is scored at the consensus's world trajectory, the own map at the
//! agent's map-frame one; where the two trajectories disagree (the pose graph places keyframes
//! by odometry and closures, the agent fitted its map to its own photometrically refined keyframe
//! poses), even the own map scores lower at the world poses, whatever the merge did. Each frame's
//! figures under the three are in the JSON (`per_frame`).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use mac_agent::evaluation::{FrameQuality, MapRenderer, QualitySummary};
use serde::Serialize;
use serde_json::Value;

use super::figures::{Figure, FigureArgs};
use crate::cmd::eval::held_out::{AgentFrames, Protocol, score, summary};
use crate::cmd::eval::swarm::load_lpips;
use crate::cmd::{fmt_num, print_json};

#[derive(Args)]
pub struct MergeArgs {
    /// A finished swarm run's folder (scripts/launch_swarm.sh --out).
    #[arg(long)]
    dir: PathBuf,
    /// One frame per window of this many frames of each agent (as `eval swarm --render-every`).
    #[arg(long, default_value_t = 20)]
    every: usize,
    /// LPIPS weights (.npz). Default: $MAC_EGO3D_WEIGHTS, else the cache scripts/setup.sh
    /// fills; LPIPS is left out without them.
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// Print the JSON instead of a table (DIR/merge_bench.json is written either way).
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    figures: FigureArgs,
}

/// Own and merged map on the same frames of one agent.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub frames: usize,
    pub own: QualitySummary,
    pub merged: QualitySummary,
    /// The own map at the merged map's (world) poses: the placement's share of the difference.
    pub own_at_world: QualitySummary,
    /// Each frame's figures under the three, in frame order: where the merge gains and where it
    /// loses.
    pub per_frame: Vec<FramePair>,
}

/// One frame scored with the own map (at its own and at the world pose) and the merged map.
#[derive(Debug, Clone, Serialize)]
pub struct FramePair {
    pub frame: usize,
    pub own: FrameQuality,
    pub merged: FrameQuality,
    pub own_at_world: FrameQuality,
}

impl Comparison {
    fn of(own: &[FrameQuality], merged: &[FrameQuality], own_at_world: &[FrameQuality]) -> Self {
        // The lists score the same positions; a frame one trajectory could not pose is left out
        // of the pairs (`score` skips it for that trajectory only).
        let at = |list: &[FrameQuality], frame| list.iter().find(|q| q.frame == frame).cloned();
        let per_frame = own
            .iter()
            .filter_map(|own| {
                Some(FramePair {
                    frame: own.frame,
                    own: own.clone(),
                    merged: at(merged, own.frame)?,
                    own_at_world: at(own_at_world, own.frame)?,
                })
            })
            .collect();
        Self {
            frames: own.len().min(merged.len()),
            own: summary(own).unwrap_or_default(),
            merged: summary(merged).unwrap_or_default(),
            own_at_world: summary(own_at_world).unwrap_or_default(),
            per_frame,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct AgentComparison {
    pub agent_id: u32,
    pub own_gaussians: usize,
    pub held_out: Comparison,
    pub all_frames: Comparison,
}

/// DIR/merge_bench.json.
#[derive(Debug, Clone, Serialize)]
pub struct MergeBench {
    pub dir: PathBuf,
    pub every: usize,
    pub agents: Vec<AgentComparison>,
    /// The merged map over every agent's held-out (and all) frames together.
    pub merged_held_out: QualitySummary,
    pub merged_all_frames: QualitySummary,
    pub merged_gaussians: usize,
    pub own_gaussians_sum: usize,
    /// `merged_gaussians / own_gaussians_sum`.
    pub gaussian_ratio: Option<f64>,
    /// The consensus's joint refinement (consensus.json; `null`: not run).
    pub refinement_seconds: Option<f64>,
    pub refinement_iterations: Option<u64>,
    pub refinement_views: Option<u64>,
}

fn read_json(path: &Path) -> anyhow::Result<Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// `own_map` moved into the world by the agent's `world_from_agent` (consensus.json).
fn in_world(
    own_map: &splats::GaussianCloud,
    consensus: &Value,
    agent_id: u32,
) -> anyhow::Result<splats::GaussianCloud> {
    let tum: Vec<f64> = serde_json::from_value(
        consensus["agents"][agent_id.to_string()]["world_from_agent"].clone(),
    )
    .with_context(|| format!("consensus.json: agent {agent_id}'s world_from_agent"))?;
    let tum: [f64; 7] = tum.try_into().map_err(|tum: Vec<f64>| {
        anyhow::anyhow!(
            "consensus.json: agent {agent_id}'s world_from_agent has {} numbers, not 7",
            tum.len()
        )
    })?;
    let world_from_agent = geometry::se3::isometry_from_tum(&tum)
        .map_err(|e| anyhow::anyhow!("consensus.json: agent {agent_id}'s world_from_agent: {e}"))?;
    let mut moved = own_map.clone();
    moved.transform_rigid(&splats::RigidTransform::from(&world_from_agent));
    Ok(moved)
}

fn load_map(path: &Path) -> anyhow::Result<splats::GaussianCloud> {
    splats::ply::load_ply(path).with_context(|| format!("reading the map {}", path.display()))
}

/// Measures the run in `dir` (see the module documentation).
pub fn measure(
    dir: &Path,
    every: usize,
    lpips_weights: Option<&Path>,
) -> anyhow::Result<MergeBench> {
    let consensus = read_json(&dir.join("consensus.json"))?;
    let mut ids: Vec<u32> = consensus["agents"]
        .as_object()
        .map(|agents| agents.keys().filter_map(|k| k.parse().ok()).collect())
        .unwrap_or_default();
    ids.sort_unstable();
    let mut agents = Vec::new();
    for id in ids {
        let metrics_path = dir.join(format!("agent_{id}/metrics.json"));
        let metrics = read_json(&metrics_path)?;
        match AgentFrames::open(dir, id, &metrics)? {
            Some(agent) if agent.own_map_poses.is_some() => agents.push(agent),
            Some(_) => bail!(
                "agent {id} wrote no agent_{id}/{}: its own map's poses are unknown",
                mac_agent::views::MAP_TRAJECTORY_FILE
            ),
            None => tracing::warn!(agent = id, "not linked to the world: left out"),
        }
    }
    if agents.is_empty() {
        bail!("{}: no agent linked to the world", dir.display());
    }
    let merged_map = load_map(&dir.join("map.ply"))?;
    let merged = MapRenderer::new(&merged_map).context("uploading the merged map")?;
    let lpips = load_lpips(lpips_weights)?;
    let mut rows = Vec::new();
    let (mut merged_held_out, mut merged_all) = (Vec::new(), Vec::new());
    let mut own_gaussians_sum = 0;
    for agent in &agents {
        let id = agent.agent_id;
        let own_map = load_map(&dir.join(format!("agent_{id}/map.ply")))?;
        own_gaussians_sum += own_map.len();
        let own = MapRenderer::new(&own_map).context("uploading an agent's map")?;
        let own_in_world = MapRenderer::new(&in_world(&own_map, &consensus, id)?)
            .context("uploading an agent's map in the world")?;
        let own_poses = agent.own_map_poses.as_ref().expect("checked above");
        let compare = |protocol| -> anyhow::Result<(Comparison, Vec<FrameQuality>)> {
            let positions = agent.positions(&agents, every, protocol)?;
            let _span = tracing::info_span!("scoring", agent = id, ?protocol).entered();
            let at = |map: &MapRenderer, poses| {
                score(map, agent, poses, &positions, lpips.as_ref(), &|_, _| None)
            };
            let own_q = at(&own, own_poses)?;
            let merged_q = at(&merged, &agent.world)?;
            let own_at_world_q = at(&own_in_world, &agent.world)?;
            Ok((Comparison::of(&own_q, &merged_q, &own_at_world_q), merged_q))
        };
        let (held_out, merged_q) = compare(Protocol::HeldOut)?;
        merged_held_out.extend(merged_q);
        let (all_frames, merged_q) = compare(Protocol::AllFrames)?;
        merged_all.extend(merged_q);
        rows.push(AgentComparison {
            agent_id: id,
            own_gaussians: own_map.len(),
            held_out,
            all_frames,
        });
    }
    let refinement = &consensus["refinement"];
    Ok(MergeBench {
        dir: dir.to_path_buf(),
        every,
        agents: rows,
        merged_held_out: summary(&merged_held_out).unwrap_or_default(),
        merged_all_frames: summary(&merged_all).unwrap_or_default(),
        merged_gaussians: merged_map.len(),
        own_gaussians_sum,
        gaussian_ratio: (own_gaussians_sum > 0)
            .then(|| merged_map.len() as f64 / own_gaussians_sum as f64),
        refinement_seconds: refinement["seconds"].as_f64(),
        refinement_iterations: refinement["iterations"].as_u64(),
        refinement_views: refinement["views"].as_u64(),
    })
}

pub fn run(args: &MergeArgs) -> anyhow::Result<()> {
    let bench = measure(&args.dir, args.every, args.lpips_weights.as_deref())?;
    let path = args.dir.join("merge_bench.json");
    std::fs::write(&path, serde_json::to_string_pretty(&bench)?)
        .with_context(|| format!("writing {}", path.display()))?;
    let label = args
        .figures
        .label(|| format!("swarm run {}", args.dir.display()));
    args.figures.record(&headline_figures(&bench, &label))?;
    if args.json {
        return print_json(&bench);
    }
    print_table(&bench);
    println!("  json: {}", path.display());
    Ok(())
}

/// What `--figures` records: per agent, merged over own on its held-out frames; the merged
/// map's quality on them; its size against the own maps'.
fn headline_figures(bench: &MergeBench, label: &str) -> Vec<Figure> {
    let per_agent = |value: &dyn Fn(&AgentComparison) -> Option<f64>, signed: bool| {
        let values: Vec<String> = bench
            .agents
            .iter()
            .map(|agent| match value(agent) {
                Some(v) if signed => format!("{v:+.2}"),
                Some(v) => format!("{v:.2}"),
                None => "-".into(),
            })
            .collect();
        values.join(" / ")
    };
    let gain =
        |agent: &AgentComparison| Some(agent.held_out.merged.psnr? - agent.held_out.own.psnr?);
    let quality = |q: &QualitySummary| {
        let num = |v: Option<f64>, d: usize| v.map_or("-".into(), |v| format!("{v:.d$}"));
        format!(
            "{} / {} / {}",
            num(q.psnr, 2),
            num(q.ssim, 3),
            num(q.lpips, 3)
        )
    };
    let mut figures = vec![
        Figure::text(
            format!("{label}: merged over own map PSNR on each agent's held-out frames"),
            per_agent(&gain, true),
            "dB",
        ),
        Figure::text(
            format!(
                "{label}: merged map PSNR / SSIM / LPIPS on the agents' held-out frames (one per {} frames)",
                bench.every
            ),
            quality(&bench.merged_held_out),
            "",
        ),
    ];
    if let Some(ratio) = bench.gaussian_ratio {
        figures.push(Figure::number(
            format!("{label}: merged map Gaussians over the sum of the own maps'"),
            ratio,
            2,
            "x",
        ));
    }
    figures
}

fn print_table(bench: &MergeBench) {
    let num = |v: Option<f64>, d: usize| v.map_or("-".into(), |v| fmt_num(v, d));
    println!(
        "merged map against each agent's own map, {} (one frame per {} of each agent)",
        bench.dir.display(),
        bench.every
    );
    println!(
        "  {:<7} {:<11} {:>6} {:>15} {:>15} {:>13} {:>15} {:>15}",
        "agent",
        "frames",
        "count",
        "PSNR own/merged",
        "delta dB",
        "own at world",
        "SSIM own/merged",
        "LPIPS own/merged"
    );
    for row in &bench.agents {
        for (name, c) in [("held out", &row.held_out), ("all", &row.all_frames)] {
            let delta = match (c.own.psnr, c.merged.psnr) {
                (Some(own), Some(merged)) => format!("{:+.2}", merged - own),
                _ => "-".into(),
            };
            println!(
                "  {:<7} {:<11} {:>6} {:>15} {:>15} {:>13} {:>15} {:>15}",
                row.agent_id,
                name,
                c.frames,
                format!("{} / {}", num(c.own.psnr, 2), num(c.merged.psnr, 2)),
                delta,
                num(c.own_at_world.psnr, 2),
                format!("{} / {}", num(c.own.ssim, 3), num(c.merged.ssim, 3)),
                format!("{} / {}", num(c.own.lpips, 3), num(c.merged.lpips, 3)),
            );
        }
    }
    let q = &bench.merged_held_out;
    println!(
        "  merged, every agent's held-out frames ({}): PSNR {} SSIM {} LPIPS {} depth L1 {} cm",
        q.frames,
        num(q.psnr, 2),
        num(q.ssim, 3),
        num(q.lpips, 3),
        num(q.depth_l1_cm, 2)
    );
    let q = &bench.merged_all_frames;
    println!(
        "  merged, every agent's frames ({}):          PSNR {} SSIM {} LPIPS {} depth L1 {} cm",
        q.frames,
        num(q.psnr, 2),
        num(q.ssim, 3),
        num(q.lpips, 3),
        num(q.depth_l1_cm, 2)
    );
    println!(
        "  Gaussians: merged {}, own maps {} in all (ratio {}); own per agent: {}",
        bench.merged_gaussians,
        bench.own_gaussians_sum,
        num(bench.gaussian_ratio, 2),
        bench
            .agents
            .iter()
            .map(|a| a.own_gaussians.to_string())
            .collect::<Vec<_>>()
            .join(" / ")
    );
    println!(
        "  joint refinement: {} iterations over {} views, {} s",
        bench
            .refinement_iterations
            .map_or("-".into(), |v| v.to_string()),
        bench.refinement_views.map_or("-".into(), |v| v.to_string()),
        num(bench.refinement_seconds, 1)
    );
}
