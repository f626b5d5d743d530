//! Deliberately wrong loop closures for robustness measurements (`[consensus.false_closures]`,
//! off by default): beside each verified closure, random ones join the pose graph until they make
//! up the configured share of its closures. They stand for what place recognition and alignment
//! get wrong in a real swarm (a repeated corridor, a symmetric room), at a rate far above what
//! verification lets through, so the robust solve has to reject them.

use std::collections::BTreeMap;

use config::FalseClosureConfig;
use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, UnitSphere};

use crate::place_recognition::KeyframeRef;
use crate::pose_graph::LoopClosure;

/// Draws the wrong closures: which keyframes and which transform, from a seed.
pub(super) struct FalseClosureInjector {
    config: FalseClosureConfig,
    rng: ChaCha8Rng,
    verified: usize,
    injected: usize,
}

impl FalseClosureInjector {
    /// `None` when the configuration injects nothing.
    pub(super) fn new(config: &FalseClosureConfig) -> Option<Self> {
        config.enabled().then(|| Self {
            config: config.clone(),
            rng: ChaCha8Rng::seed_from_u64(config.seed),
            verified: 0,
            injected: 0,
        })
    }

    /// After a verified closure joined the graph: the wrong closures now due, between keyframes
    /// of `keyframes_per_agent` (each agent's keyframes, in any order). Fewer when the graph has
    /// too few keyframes to pair; they are owed and come with the next verified closure.
    pub(super) fn after_verified(
        &mut self,
        keyframes_per_agent: &BTreeMap<u32, Vec<KeyframeRef>>,
    ) -> Vec<LoopClosure> {
        self.verified += 1;
        let mut closures = Vec::new();
        while self.injected < self.config.due(self.verified) {
            let Some((source, target)) = self.pair(keyframes_per_agent) else {
                break;
            };
            closures.push(LoopClosure {
                source,
                target,
                target_camera_from_source_camera: self.transform(),
                // As confident as a verified keyframe closure: nothing marks them as doubtful.
                sigmas: None,
            });
            self.injected += 1;
        }
        closures
    }

    /// Two distinct keyframes: of one agent or of two, half of each where both are possible.
    fn pair(
        &mut self,
        keyframes_per_agent: &BTreeMap<u32, Vec<KeyframeRef>>,
    ) -> Option<(KeyframeRef, KeyframeRef)> {
        let agents: Vec<&Vec<KeyframeRef>> = keyframes_per_agent
            .values()
            .filter(|k| !k.is_empty())
            .collect();
        let with_two: Vec<&Vec<KeyframeRef>> =
            agents.iter().copied().filter(|k| k.len() >= 2).collect();
        let inter_possible = agents.len() >= 2;
        let intra_possible = !with_two.is_empty();
        let inter = match (inter_possible, intra_possible) {
            (false, false) => return None,
            (true, false) => true,
            (false, true) => false,
            (true, true) => self.rng.random_bool(0.5),
        };
        if inter {
            let a = self.rng.random_range(0..agents.len());
            let mut b = self.rng.random_range(0..agents.len() - 1);
            if b >= a {
                b += 1;
            }
            Some((self.pick(agents[a]), self.pick(agents[b])))
        } else {
            let keyframes = with_two[self.rng.random_range(0..with_two.len())];
            let i = self.rng.random_range(0..keyframes.len());
            let mut j = self.rng.random_range(0..keyframes.len() - 1);
            if j >= i {
                j += 1;
            }
            Some((keyframes[i], keyframes[j]))
        }
    }

    fn pick(&mut self, keyframes: &[KeyframeRef]) -> KeyframeRef {
        keyframes[self.rng.random_range(0..keyframes.len())]
    }

    /// A rotation about a random axis by up to `max_rotation_deg` and a translation in a random
    /// direction of up to `max_translation_m`.
    fn transform(&mut self) -> Isometry3<f64> {
        let axis: [f64; 3] = UnitSphere.sample(&mut self.rng);
        let angle = self
            .rng
            .random_range(0.0..=self.config.max_rotation_deg.to_radians());
        let direction: [f64; 3] = UnitSphere.sample(&mut self.rng);
        let length = self.rng.random_range(0.0..=self.config.max_translation_m);
        Isometry3::from_parts(
            Translation3::from(Vector3::from(direction) * length),
            UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::from(axis)), angle),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keyframes(agents: &[(u32, u64)]) -> BTreeMap<u32, Vec<KeyframeRef>> {
        agents
            .iter()
            .map(|&(agent_id, count)| {
                let ids = (0..count)
                    .map(|keyframe_id| KeyframeRef {
                        agent_id,
                        keyframe_id,
                    })
                    .collect();
                (agent_id, ids)
            })
            .collect()
    }

    fn injector(fraction: f64, seed: u64) -> FalseClosureInjector {
        FalseClosureInjector::new(&FalseClosureConfig {
            fraction,
            seed,
            ..FalseClosureConfig::default()
        })
        .expect("enabled")
    }

    #[test]
    fn off_by_default() {
        assert!(FalseClosureInjector::new(&FalseClosureConfig::default()).is_none());
    }

    #[test]
    fn injects_the_share_of_distinct_pairs_within_and_between_agents_from_the_seed() {
        let swarm = keyframes(&[(0, 20), (1, 20)]);
        let draw = |seed| {
            let mut injector = injector(0.3, seed);
            (0..40)
                .flat_map(|_| injector.after_verified(&swarm))
                .collect::<Vec<_>>()
        };
        let closures = draw(7);
        // 30 % of the graph's closures: 0.3 / 0.7 * 40 = 17.1, so 18.
        assert_eq!(closures.len(), 18);
        assert!(closures.iter().all(|c| c.source != c.target));
        let inter = closures
            .iter()
            .filter(|c| c.source.agent_id != c.target.agent_id)
            .count();
        assert!(inter > 0 && inter < closures.len(), "{inter} inter-agent");
        for closure in &closures {
            let t = &closure.target_camera_from_source_camera;
            assert!(t.translation.vector.norm() <= 2.0 + 1e-12);
            assert!(t.rotation.angle() <= std::f64::consts::PI + 1e-12);
        }
        // The same seed draws the same closures; another seed others.
        let again = draw(7);
        let other = draw(8);
        let same = |a: &LoopClosure, b: &LoopClosure| {
            a.source == b.source
                && a.target == b.target
                && a.target_camera_from_source_camera == b.target_camera_from_source_camera
        };
        assert!(closures.iter().zip(&again).all(|(a, b)| same(a, b)));
        assert!(!closures.iter().zip(&other).all(|(a, b)| same(a, b)));
    }

    #[test]
    fn owed_closures_come_once_keyframes_can_be_paired() {
        let mut injector = injector(0.5, 1);
        assert!(injector.after_verified(&keyframes(&[(0, 1)])).is_empty());
        // Two verified closures at 50 %: two wrong ones, the first one owed.
        let closures = injector.after_verified(&keyframes(&[(0, 3)]));
        assert_eq!(closures.len(), 2);
        assert!(closures.iter().all(|c| c.source.agent_id == 0));
    }
}
