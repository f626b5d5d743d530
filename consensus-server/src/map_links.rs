//! Links between agents found by registering their maps (see [`registration::map_registration`] for the
//! registration itself and docs/method.md, The consensus: association and alignment, for why).
//!
//! Keyframe-to-keyframe alignment needs two views that see the same surfaces from similar
//! viewpoints. Two agents that walk the same room facing other ways rarely have such a pair, while
//! their maps overlap. So the engine also registers the agents' maps with each other, with no
//! initial guess:
//!
//! 1. **When** ([`MapScheduler`]): a pair of agents that is not linked yet is registered whenever
//!    either agent has published `retry_after_keyframes` new keyframes since the pair's last
//!    attempt (its map grew, so the overlap may have); a pair already linked is registered again
//!    after `refresh_after_keyframes` new keyframes, which adds an independent constraint for the
//!    pose graph.
//! 2. **What**: each agent's map in its own tracked frame, as published: the means of every
//!    Gaussian patch (agents send the Gaussians seeded since their last publication with each
//!    published keyframe) and the back-projected depth of the published keyframes, each point
//!    with its colour (the Gaussian's, the keyframe pixel's; see [`AgentMap::from_keyframes`]),
//!    which the registration uses to tell surfaces of the same shape apart.
//! 3. **Check** ([`MapJob::run`]): a registration the map registration accepted must also agree
//!    with what the cameras saw: each agent's map points, moved by the estimate into the other
//!    agent's keyframes, must not lie in the free space in front of the surfaces those keyframes
//!    measured (the keyframe alignment's depth test, in both directions).
//! 4. **Edge**: the estimate `target_agent_from_source_agent` enters the pose graph as a loop
//!    closure between the pair of keyframes (one of each agent) whose cameras are closest under
//!    it, with standard deviations from the registration's own uncertainty; the robust pose graph
//!    treats it like any other closure.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use splats::GaussianCloud;

use crate::alignment::PreparedKeyframe;
use crate::place_recognition::KeyframeRef;
use config::AlignmentConfig;
use config::MapRegistrationConfig;
use registration::alignment::verification::{DepthComparison, compare_depth};
use registration::map_registration::colour::Rgb;
use registration::map_registration::{MapPoints, MapRegistration, register_maps};

/// One agent's map as a registration input: points in its own tracked frame, their colours,
/// and the keyframes that saw them.
pub struct AgentMap {
    /// The agent whose map this is.
    pub agent_id: u32,
    /// Gaussian means and keyframe depth points, metres, in the agent's tracked frame.
    pub points: Vec<Point3<f32>>,
    /// One per point (RGB in `[0, 1]`), or `None` when some point has none: the map is then
    /// registered on its geometry alone.
    pub colours: Option<Vec<Rgb>>,
    /// Published keyframes, with `agent_from_camera` in `keyframe.agent_from_camera`.
    pub keyframes: Vec<Arc<PreparedKeyframe>>,
}

/// The colour of each of a keyframe's cloud points: its pixel's RGB / 255, the space the
/// agents' Gaussian colours are in (seeded from and fitted to those pixels). `None` when the
/// cloud does not say which pixel each point came from, or a pixel lies outside the image.
fn keyframe_point_colours(prepared: &PreparedKeyframe) -> Option<Vec<Rgb>> {
    let keyframe = &prepared.keyframe;
    let cloud = prepared.view.cloud.cloud();
    if cloud.pixels.len() != cloud.positions.len() {
        return None;
    }
    let width = keyframe.depth.width;
    let (rgb_width, rgb_height) = keyframe.rgb.dimensions();
    cloud
        .pixels
        .iter()
        .map(|&pixel| {
            let (u, v) = (pixel % width, pixel / width);
            (u < rgb_width && v < rgb_height)
                .then(|| keyframe.rgb.get_pixel(u, v).0.map(|c| f32::from(c) / 255.0))
        })
        .collect()
}

impl AgentMap {
    /// An agent's map from its published keyframes (in publication order) and the Gaussians
    /// that came with each: the Gaussian means and the keyframes' depth points moved into the
    /// agent's frame, with their colours (`None` for the whole map if any point has none).
    pub fn from_keyframes<'a>(
        agent_id: u32,
        published: impl IntoIterator<Item = (&'a Arc<PreparedKeyframe>, Option<&'a GaussianCloud>)>,
    ) -> Self {
        let mut points = Vec::new();
        let mut colours = Some(Vec::new());
        let mut keyframes = Vec::new();
        for (prepared, gaussians) in published {
            if let Some(cloud) = gaussians {
                points.extend(cloud.means.iter().map(|m| Point3::new(m[0], m[1], m[2])));
                match &mut colours {
                    Some(colours) if cloud.colours.len() == cloud.means.len() => {
                        colours.extend_from_slice(&cloud.colours)
                    }
                    _ => colours = None,
                }
            }
            let agent_from_camera = prepared.keyframe.agent_from_camera.cast::<f32>();
            points.extend(
                prepared
                    .view
                    .cloud
                    .positions()
                    .iter()
                    .map(|p| agent_from_camera * p),
            );
            match (&mut colours, keyframe_point_colours(prepared)) {
                (Some(colours), Some(found)) => colours.extend(found),
                _ => colours = None,
            }
            keyframes.push(Arc::clone(prepared));
        }
        Self {
            agent_id,
            points,
            colours,
            keyframes,
        }
    }

    /// The newest keyframe (the one an attempt is filed under when no closure comes of it).
    fn latest_keyframe(&self) -> Option<KeyframeRef> {
        self.keyframes.last().map(|k| k.keyframe.id)
    }
}

/// A map registration between two agents, free of the engine (runs on the aligner thread).
pub struct MapJob {
    /// The map moved onto the other (the higher agent id, as the engine schedules it).
    pub source: AgentMap,
    /// The map the source is registered to.
    pub target: AgentMap,
    /// The registration's parameters (`[consensus.map_registration]`), with
    /// `depth_check_points`, how many map points the depth check projects per direction.
    pub registration: MapRegistrationConfig,
    /// The keyframe alignment's parameters, whose depth test and thresholds check the result
    /// (`[consensus.alignment]`).
    pub alignment: AlignmentConfig,
}

/// Why a registration that the map registration accepted was not used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapLinkRejection {
    /// The map registration itself rejected its estimate (its reason, as text).
    #[error("{0}")]
    Registration(String),
    /// Too few decisive depth comparisons to judge the result.
    #[error(
        "{comparisons} depth comparisons against the other agent's keyframes, at least {required} needed"
    )]
    TooFewDepthComparisons {
        /// Decisive comparisons (agreeing or violating) of the direction with fewer.
        comparisons: usize,
        /// `min_depth_comparisons` of the alignment configuration.
        required: usize,
    },
    /// Too many map points lie in the free space in front of the other agent's measured depth.
    #[error(
        "map points lie in the free space of the other agent's keyframes: depth agreement {found:.3} below {required:.3}"
    )]
    DepthDisagreement {
        /// The lower depth agreement of the two directions, in `[0, 1]`.
        found: f64,
        /// `min_depth_agreement` of the alignment configuration.
        required: f64,
    },
    /// An agent has no keyframe, so no pose-graph edge can carry the link.
    #[error("an agent has no keyframe to attach the link to")]
    NoKeyframes,
}

/// Outcome of a [`MapJob`].
pub struct FinishedMapJob {
    /// The agent whose map was moved onto the other's.
    pub source_agent: u32,
    /// The agent whose map the source's was registered to.
    pub target_agent: u32,
    /// The keyframes the attempt is filed under: the closure's ends when accepted, else each
    /// agent's newest keyframe. This is the source agent's; `None` when it has no keyframe.
    pub source_keyframe: Option<KeyframeRef>,
    /// The target agent's keyframe the attempt is filed under; `None` when it has no keyframe.
    pub target_keyframe: Option<KeyframeRef>,
    /// Published keyframes of the source and the target agent when the maps were taken (what
    /// [`MapScheduler`] schedules the next attempt of the pair by).
    pub keyframes_at_attempt: (usize, usize),
    /// The map registration's estimate (`target_from_source`, agent frames), scores and verdict.
    pub registration: MapRegistration,
    /// Depth comparisons of the source map in the target agent's keyframes; all zero when the
    /// registration was rejected (the check did not run).
    pub source_in_target: DepthComparison,
    /// Depth comparisons of the target map in the source agent's keyframes; all zero when the
    /// check did not run.
    pub target_in_source: DepthComparison,
    /// The loop closure's measurement when accepted: `target_camera_from_source_camera`.
    pub closure: Option<Isometry3<f64>>,
    /// Why the link was not used; `None` when it was accepted.
    pub rejection: Option<MapLinkRejection>,
    /// Wall-clock time of the whole job (registration, checks, keyframe pair), milliseconds.
    pub elapsed_ms: f64,
}

impl MapJob {
    /// Registers the two maps, checks the result against the keyframes' depth, and picks the
    /// keyframe pair that carries it into the pose graph.
    pub fn run(self) -> FinishedMapJob {
        let clock = Instant::now();
        let _span = tracing::info_span!(
            "map registration",
            source = self.source.agent_id,
            target = self.target.agent_id
        )
        .entered();
        let registration = register_maps(
            MapPoints::coloured(&self.source.points, self.source.colours.as_deref()),
            MapPoints::coloured(&self.target.points, self.target.colours.as_deref()),
            &self.registration,
        );
        let mut finished = FinishedMapJob {
            source_agent: self.source.agent_id,
            target_agent: self.target.agent_id,
            source_keyframe: self.source.latest_keyframe(),
            target_keyframe: self.target.latest_keyframe(),
            keyframes_at_attempt: (self.source.keyframes.len(), self.target.keyframes.len()),
            source_in_target: DepthComparison::default(),
            target_in_source: DepthComparison::default(),
            closure: None,
            rejection: None,
            elapsed_ms: 0.0,
            registration,
        };
        let target_from_source = finished.registration.target_from_source;
        let verdict = match &finished.registration.verdict {
            Err(reason) => Err(MapLinkRejection::Registration(reason.to_string())),
            Ok(()) => {
                finished.source_in_target = depth_agreement(
                    &self.source.points,
                    &target_from_source,
                    &self.target.keyframes,
                    &self.alignment,
                    self.registration.depth_check_points,
                );
                finished.target_in_source = depth_agreement(
                    &self.target.points,
                    &target_from_source.inverse(),
                    &self.source.keyframes,
                    &self.alignment,
                    self.registration.depth_check_points,
                );
                check_depth(
                    finished.source_in_target,
                    finished.target_in_source,
                    &self.alignment,
                )
                .and_then(|()| {
                    closest_keyframes(&self.source, &self.target, &target_from_source)
                        .ok_or(MapLinkRejection::NoKeyframes)
                })
            }
        };
        match verdict {
            Ok((source, target)) => {
                let source_pose = source.keyframe.agent_from_camera;
                let target_pose = target.keyframe.agent_from_camera;
                finished.source_keyframe = Some(source.keyframe.id);
                finished.target_keyframe = Some(target.keyframe.id);
                finished.closure = Some(target_pose.inverse() * target_from_source * source_pose);
            }
            Err(reason) => {
                tracing::info!(%reason, "map registration not used");
                finished.rejection = Some(reason);
            }
        }
        finished.elapsed_ms = clock.elapsed().as_secs_f64() * 1e3;
        finished
    }
}

/// The keyframe depth test summed over every keyframe of `keyframes`: `points` (the other
/// agent's map, at most `max_points` of them, evenly spread) moved by `keyframes_agent_from_points`.
fn depth_agreement(
    points: &[Point3<f32>],
    keyframes_agent_from_points: &Isometry3<f64>,
    keyframes: &[Arc<PreparedKeyframe>],
    config: &AlignmentConfig,
    max_points: usize,
) -> DepthComparison {
    let step = points.len().div_ceil(max_points.max(1)).max(1);
    let sample: Vec<Point3<f32>> = points.iter().step_by(step).copied().collect();
    let mut total = DepthComparison::default();
    for prepared in keyframes {
        let keyframe = &prepared.keyframe;
        let camera_from_points = keyframe.agent_from_camera.inverse() * keyframes_agent_from_points;
        let counts = compare_depth(
            &sample,
            &camera_from_points,
            &keyframe.depth,
            &keyframe.intrinsics,
            config,
        );
        total.agreeing += counts.agreeing;
        total.violating += counts.violating;
        total.occluded += counts.occluded;
    }
    total
}

/// The keyframe alignment's depth thresholds applied to the maps' depth agreement.
fn check_depth(
    source_in_target: DepthComparison,
    target_in_source: DepthComparison,
    config: &AlignmentConfig,
) -> Result<(), MapLinkRejection> {
    let comparisons = source_in_target.decisive().min(target_in_source.decisive());
    if comparisons < config.min_depth_comparisons {
        return Err(MapLinkRejection::TooFewDepthComparisons {
            comparisons,
            required: config.min_depth_comparisons,
        });
    }
    let agreement = source_in_target
        .agreement()
        .min(target_in_source.agreement());
    if agreement < config.min_depth_agreement {
        return Err(MapLinkRejection::DepthDisagreement {
            found: agreement,
            required: config.min_depth_agreement,
        });
    }
    Ok(())
}

/// Metres of camera distance that one radian of viewing-direction difference counts as when
/// choosing the keyframe pair for a map link.
const METRES_PER_RADIAN: f64 = 0.5;

/// The keyframe pair (one of each agent) whose cameras are closest under `target_from_source`:
/// the closure between them spans the least tracking drift.
fn closest_keyframes<'a>(
    source: &'a AgentMap,
    target: &'a AgentMap,
    target_from_source: &Isometry3<f64>,
) -> Option<(&'a PreparedKeyframe, &'a PreparedKeyframe)> {
    let mut best: Option<(f64, &PreparedKeyframe, &PreparedKeyframe)> = None;
    for s in &source.keyframes {
        let placed = target_from_source * s.keyframe.agent_from_camera;
        for t in &target.keyframes {
            let pose = t.keyframe.agent_from_camera;
            let distance = (placed.translation.vector - pose.translation.vector).norm();
            let angle = placed.rotation.angle_to(&pose.rotation);
            let cost = distance + METRES_PER_RADIAN * angle;
            if best.as_ref().is_none_or(|(c, _, _)| cost < *c) {
                best = Some((cost, s, t));
            }
        }
    }
    best.map(|(_, s, t)| (s, t))
}

/// When each pair of agents is due for a map registration.
#[derive(Debug, Default)]
pub struct MapScheduler {
    /// Keyframes each agent had when the pair `(lower, higher)` was last registered.
    last_attempt: BTreeMap<(u32, u32), (usize, usize)>,
    /// Pairs with an accepted map link (they only come back for refreshes).
    linked: BTreeMap<(u32, u32), usize>,
}

impl MapScheduler {
    /// The next pair to register, if one is due: unlinked pairs first (an agent linked to the
    /// world first among them), then, with `refreshes`, linked ones. `keyframes` counts each
    /// agent's published keyframes; `placed` says whether the pose graph has placed an agent in
    /// the world. Returns `(lower, higher)` agent ids.
    pub fn next_pair(
        &mut self,
        keyframes: &BTreeMap<u32, usize>,
        placed: &dyn Fn(u32) -> bool,
        refreshes: bool,
        config: &MapRegistrationConfig,
    ) -> Option<(u32, u32)> {
        if !config.enabled {
            return None;
        }
        let agents: Vec<u32> = keyframes.keys().copied().collect();
        let mut due: Vec<(u8, (u32, u32))> = Vec::new();
        for (i, &a) in agents.iter().enumerate() {
            for &b in &agents[i + 1..] {
                let now = (keyframes[&a], keyframes[&b]);
                let linked = (placed(a) && placed(b)) || self.linked.contains_key(&(a, b));
                if linked && !refreshes {
                    continue;
                }
                let after = if linked {
                    config.refresh_after_keyframes
                } else {
                    config.retry_after_keyframes
                };
                if after == 0 {
                    continue;
                }
                let grown = match self.last_attempt.get(&(a, b)) {
                    None => true,
                    Some(&(ka, kb)) => now.0 >= ka + after || now.1 >= kb + after,
                };
                if !grown {
                    continue;
                }
                let priority = match (linked, placed(a) || placed(b)) {
                    (false, true) => 0,
                    (false, false) => 1,
                    (true, _) => 2,
                };
                due.push((priority, (a, b)));
            }
        }
        let (_, pair) = due
            .into_iter()
            .min_by_key(|(priority, pair)| (*priority, *pair))?;
        self.last_attempt
            .insert(pair, (keyframes[&pair.0], keyframes[&pair.1]));
        Some(pair)
    }

    /// Records an attempt of agents `source` and `target` made elsewhere (a stored decision of
    /// an earlier process of the run) with `keyframes_at_attempt` published keyframes each: the
    /// pair is next due once either agent has grown beyond them, as after a live attempt.
    pub fn record_attempt(
        &mut self,
        (source, target): (u32, u32),
        keyframes_at_attempt: (usize, usize),
    ) {
        let (pair, counts) = if source < target {
            ((source, target), keyframes_at_attempt)
        } else {
            (
                (target, source),
                (keyframes_at_attempt.1, keyframes_at_attempt.0),
            )
        };
        let last = self.last_attempt.entry(pair).or_insert(counts);
        *last = (last.0.max(counts.0), last.1.max(counts.1));
    }

    /// Records an accepted link between two agents.
    pub fn mark_linked(&mut self, a: u32, b: u32) {
        *self.linked.entry((a.min(b), a.max(b))).or_default() += 1;
    }
}

/// One map registration attempt as consensus.json reports it (inside the closure event).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MapAttemptScores {
    /// Source map points after voxel downsampling (the feature level).
    pub source_points: usize,
    /// Target map points after voxel downsampling (the feature level).
    pub target_points: usize,
    /// Putative correspondences between the two maps' descriptors.
    pub correspondences: usize,
    /// Correspondences that support RANSAC's best hypothesis.
    pub consistent_correspondences: usize,
    /// Source points with a target point within the finest refinement distance, over the
    /// smaller map's points.
    pub overlap_fraction: f64,
    /// RMS point-to-plane distance of the overlapping points, metres.
    pub residual_m: f64,
    /// Whether the maps' colours were used, and the overlap's colour agreement (NaN without).
    pub colour: bool,
    /// The fraction of overlapping points compared in colour that agree (NaN when none were
    /// compared).
    pub colour_agreement: f64,
    /// The free-space check's depth agreement, the lower of the two directions (0 when the
    /// check did not run).
    pub depth_agreement: f64,
    /// Decisive depth comparisons (agreeing or violating), the fewer of the two directions.
    pub depth_comparisons: usize,
}

impl FinishedMapJob {
    /// The figures consensus.json reports for this attempt.
    pub fn scores(&self) -> MapAttemptScores {
        let scores = &self.registration.scores;
        MapAttemptScores {
            source_points: scores.source_points,
            target_points: scores.target_points,
            correspondences: scores.correspondences,
            consistent_correspondences: scores.consistent_correspondences,
            overlap_fraction: scores.overlap_fraction,
            residual_m: scores.residual_m,
            colour: scores.colour,
            colour_agreement: scores.colour_agreement,
            depth_agreement: self
                .source_in_target
                .agreement()
                .min(self.target_in_source.agreement()),
            depth_comparisons: self
                .source_in_target
                .decisive()
                .min(self.target_in_source.decisive()),
        }
    }
}
