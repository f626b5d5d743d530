//! What the soak checks in a finished run folder: every keyframe each agent's last run
//! delivered is in the final consensus.json, and every output is there and readable.

use std::collections::BTreeSet;
use std::path::Path;

use geometry::trajectory::Trajectory;
use serde::Serialize;

use super::read_json;
use crate::cmd::eval::swarm::SwarmMetrics;

/// One run's figures and what failed in it.
#[derive(Debug, Clone, Serialize)]
pub struct RunChecks {
    /// Keyframes the agents' last runs delivered to the consensus (metrics.json
    /// `swarm.keyframes_published_ids`; a killed run writes no metrics).
    pub keyframes_delivered: usize,
    pub keyframes_in_final_state: usize,
    /// Keyframes in consensus.json (`keyframe_info`).
    pub consensus_keyframes: usize,
    /// Keyframes lost with a killed consensus that their agent no longer held
    /// (`swarm.keyframes_unrecoverable`).
    pub keyframes_unrecoverable: usize,
    pub agents_linked: usize,
    pub ate_joint_rmse_m: Option<f64>,
    pub psnr: Option<f64>,
    pub failures: Vec<String>,
}

/// Checks the finished run in `dir` of `agents` agents over `frames` frames each.
pub fn check_run(
    dir: &Path,
    agents: u32,
    frames: usize,
    metrics: &SwarmMetrics,
) -> anyhow::Result<RunChecks> {
    let mut failures = Vec::new();
    let consensus = read_json(&dir.join("consensus.json"))?;
    if consensus["snapshot"] == true || consensus["interrupted"] == true {
        failures.push("consensus.json is a snapshot or an interrupted run's".to_string());
    }
    let held: BTreeSet<(u64, u64)> = consensus["keyframe_info"]
        .as_array()
        .map(|entries| {
            entries
                .iter()
                .filter_map(|entry| {
                    Some((
                        entry[0]["agent_id"].as_u64()?,
                        entry[0]["keyframe_id"].as_u64()?,
                    ))
                })
                .collect()
        })
        .unwrap_or_default();
    let mut checks = RunChecks {
        keyframes_delivered: 0,
        keyframes_in_final_state: 0,
        consensus_keyframes: held.len(),
        keyframes_unrecoverable: 0,
        agents_linked: 0,
        ate_joint_rmse_m: metrics.ate_joint_rmse_m,
        psnr: metrics.psnr,
        failures: Vec::new(),
    };
    for k in 0..agents {
        let agent = read_json(&dir.join(format!("agent_{k}/metrics.json")))?;
        let swarm = &agent["swarm"];
        let delivered: Vec<u64> = swarm["keyframes_published_ids"]
            .as_array()
            .map(|ids| ids.iter().filter_map(|id| id.as_u64()).collect())
            .unwrap_or_default();
        let missing: Vec<u64> = delivered
            .iter()
            .copied()
            .filter(|id| !held.contains(&(u64::from(k), *id)))
            .collect();
        checks.keyframes_delivered += delivered.len();
        checks.keyframes_in_final_state += delivered.len() - missing.len();
        checks.keyframes_unrecoverable += swarm["keyframes_unrecoverable"]
            .as_array()
            .map_or(0, Vec::len);
        if !missing.is_empty() {
            failures.push(format!(
                "agent {k}: keyframes {missing:?} delivered but not in consensus.json"
            ));
        }
        check_trajectory(
            &dir.join(format!("agent_{k}/trajectory.tum")),
            frames,
            &mut failures,
        );
        let world = dir.join(format!("agent_{k}.tum"));
        if world.exists() {
            checks.agents_linked += 1;
            check_trajectory(&world, frames, &mut failures);
        } else if k == 0 {
            failures.push("agent 0 (the world frame) has no world trajectory".to_string());
        }
    }
    let map = dir.join("map.ply");
    match splats::ply::load_ply(&map) {
        Ok(cloud) if !cloud.is_empty() => {}
        Ok(_) => failures.push(format!("{}: no Gaussians", map.display())),
        Err(error) => failures.push(format!("{}: {error:#}", map.display())),
    }
    checks.failures = failures;
    Ok(checks)
}

/// A trajectory file that reads back with one pose per frame.
fn check_trajectory(path: &Path, frames: usize, failures: &mut Vec<String>) {
    match Trajectory::read_tum(path) {
        Ok(poses) if poses.len() == frames => {}
        Ok(poses) => failures.push(format!(
            "{}: {} poses, {frames} frames",
            path.display(),
            poses.len()
        )),
        Err(error) => failures.push(format!("{}: {error:#}", path.display())),
    }
}
