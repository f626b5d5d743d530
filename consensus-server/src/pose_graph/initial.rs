//! Initial guess of every agent's frame in the world (agent 0's frame), from the inter-agent loop
//! closures alone: no agent's start pose is known.
//!
//! Each inter-agent closure implies one transform between the two agents' frames. Correct
//! closures imply nearly the same transform (they differ by the agents' odometry drift); wrong
//! ones imply scattered transforms. So, per pair of agents, every implied transform collects the
//! votes of the closures that imply a transform within [`PoseGraphConfig::vote_translation_m`] and
//! [`PoseGraphConfig::vote_rotation_rad`] of it, and the best-supported one stands for the pair
//! (a one-dimensional form of pairwise consistency maximisation). Agents are then chained from
//! agent 0 along the best-supported pairs first (a maximum spanning tree by votes). GNC later
//! decides every closure individually; this guess only has to be close enough for it.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::Isometry3;

use config::PoseGraphConfig;

/// The transform between two agents' frames implied by one inter-agent loop closure.
#[derive(Debug, Clone, Copy)]
pub struct ImpliedTransform {
    /// The closure's agent with the lower id.
    pub lower_agent: u32,
    /// The closure's agent with the higher id.
    pub higher_agent: u32,
    /// `lower_agent_from_higher_agent`.
    pub lower_from_higher: Isometry3<f64>,
}

/// The best-supported transform of one agent pair and its number of votes.
#[derive(Debug, Clone, Copy)]
struct PairConsensus {
    lower_from_higher: Isometry3<f64>,
    votes: usize,
}

fn agree(a: &Isometry3<f64>, b: &Isometry3<f64>, config: &PoseGraphConfig) -> bool {
    let difference = a.inverse() * b;
    difference.translation.vector.norm() <= config.vote_translation_m
        && difference.rotation.angle() <= config.vote_rotation_rad
}

fn consensus_per_pair(
    implied: &[ImpliedTransform],
    config: &PoseGraphConfig,
) -> BTreeMap<(u32, u32), PairConsensus> {
    let mut groups: BTreeMap<(u32, u32), Vec<Isometry3<f64>>> = BTreeMap::new();
    for t in implied {
        groups
            .entry((t.lower_agent, t.higher_agent))
            .or_default()
            .push(t.lower_from_higher);
    }
    groups
        .into_iter()
        .map(|(pair, candidates)| {
            let votes_for = |c: &Isometry3<f64>| {
                candidates
                    .iter()
                    .filter(|other| agree(c, other, config))
                    .count()
            };
            let best = candidates
                .iter()
                .map(|c| PairConsensus {
                    lower_from_higher: *c,
                    votes: votes_for(c),
                })
                // First of the best on ties: deterministic for the same input order.
                .reduce(|best, next| if next.votes > best.votes { next } else { best })
                .expect("a group is never empty");
            (pair, best)
        })
        .collect()
}

/// `world_from_agent` of every agent linked to `world_agent` by inter-agent closures
/// (`world_agent` itself at identity). Agents without such a link are absent.
pub fn agent_frames(
    world_agent: u32,
    implied: &[ImpliedTransform],
    config: &PoseGraphConfig,
) -> BTreeMap<u32, Isometry3<f64>> {
    let pairs = consensus_per_pair(implied, config);
    let mut frames = BTreeMap::from([(world_agent, Isometry3::identity())]);
    loop {
        // The best-supported pair with exactly one agent already placed.
        let next = pairs
            .iter()
            .filter(|((a, b), _)| frames.contains_key(a) != frames.contains_key(b))
            .max_by_key(|(_, consensus)| consensus.votes);
        let Some((&(lower, higher), consensus)) = next else {
            break;
        };
        if let Some(world_from_lower) = frames.get(&lower).copied() {
            frames.insert(higher, world_from_lower * consensus.lower_from_higher);
        } else {
            let world_from_higher = frames[&higher];
            frames.insert(
                lower,
                world_from_higher * consensus.lower_from_higher.inverse(),
            );
        }
        tracing::debug!(
            lower,
            higher,
            votes = consensus.votes,
            "agent frame chained"
        );
    }
    let placed: BTreeSet<u32> = frames.keys().copied().collect();
    tracing::debug!(?placed, "initial agent frames");
    frames
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn implied(lower: u32, higher: u32, t: Isometry3<f64>) -> ImpliedTransform {
        ImpliedTransform {
            lower_agent: lower,
            higher_agent: higher,
            lower_from_higher: t,
        }
    }

    #[test]
    fn majority_wins_and_agents_chain_through_each_other() {
        let config = PoseGraphConfig::default();
        let zero_from_one = Isometry3::from_parts(
            Translation3::new(2.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 1.5),
        );
        let one_from_two = Isometry3::translation(0.0, -1.0, 0.5);
        let wrong = Isometry3::translation(5.0, 5.0, 5.0);
        let nudged = zero_from_one * Isometry3::translation(0.02, 0.0, 0.0);
        let frames = agent_frames(
            0,
            &[
                implied(0, 1, wrong),
                implied(0, 1, zero_from_one),
                implied(0, 1, nudged),
                implied(1, 2, one_from_two),
            ],
            &config,
        );
        assert_eq!(frames.len(), 3, "agent 3 has no closure and is absent");
        assert!(
            (frames[&1].inverse() * zero_from_one)
                .translation
                .vector
                .norm()
                < 1e-12
        );
        let expected_two = zero_from_one * one_from_two;
        assert!(
            (frames[&2].inverse() * expected_two)
                .translation
                .vector
                .norm()
                < 1e-12
        );
    }
}
