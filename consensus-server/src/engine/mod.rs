//! The consensus's state, free of any transport (the process feeds it from iceoryx2, tests feed it
//! directly): keyframes arrive with their global descriptor, images and Gaussians; selection
//! proposes loop candidates; a bounded number of candidates is aligned per call; the robust pose
//! graph is re-solved whenever a closure was added. Every decision is recorded for
//! consensus.json.
//!
//! Candidates of a new keyframe, in order:
//! 1. the agent's previous published keyframe (an odometry check: the verified relative pose
//!    corrects tracking where it slipped between two publications);
//! 2. the best `max_candidates_per_keyframe` proposals of place recognition.
//!
//! Besides keyframe pairs, pairs of agents are registered map to map ([`crate::map_links`]):
//! an agent pair not linked yet goes before the keyframe candidates, a linked one is refreshed
//! when nothing else waits.
//!
//! Duplicate keyframes (a message that arrived twice, or an agent that restarted and re-sent)
//! replace nothing and propose nothing.
//!
//! Files: this one holds the engine's intake, job scheduling and solving; `jobs.rs` the work it
//! hands to the aligner thread; `decisions.rs` what a finished job decides and how the pose
//! graph takes it (live, or stored by an earlier process of the run); `records.rs` what it
//! records per keyframe and attempt; `world.rs` what it produces at the end (merged map, refinement problem, world
//! trajectories); `false_closures.rs` the wrong closures injected for robustness measurements.

mod decisions;
mod false_closures;
mod fuse;
mod jobs;
mod merge;
mod records;
mod world;

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use geometry::se3::isometry_to_tum;
use protocol::messages::FINAL_MAP_KEYFRAME_ID;
use splats::GaussianCloud;

use crate::alignment::{Keyframe, PreparedKeyframe};
use crate::map_links::{AgentMap, MapJob, MapScheduler};
use crate::place_recognition::{KeyframeRef, PlaceDatabase, SelectionThresholds};
use crate::pose_graph::{PoseGraph, PoseGraphError, PoseGraphSolution};
use config::ConsensusConfig;

pub use decisions::{Decision, MapAttempt};
use false_closures::FalseClosureInjector;
use jobs::Candidate;
pub use jobs::{AlignmentJob, CandidateSource, Finished, FinishedAlignment, Job};
pub use records::{AttemptKind, ClosureEvent, ClosureMeasurement, ExactIsometry, KeyframeInfo};
use world::agent_range;

/// One published keyframe as the consensus receives it.
pub struct KeyframeArrival {
    /// The keyframe's images, camera and pose in its agent's own frame.
    pub keyframe: Keyframe,
    /// Index of the keyframe's frame in its agent's input sequence (place recognition does not
    /// compare same-agent keyframes closer than `same_agent_min_frame_gap` in it).
    pub frame_index: u64,
    /// Capture time of the frame, seconds (dataset clock).
    pub timestamp_s: f64,
    /// L2-normalised global descriptor.
    pub descriptor: Vec<f32>,
    /// The keyframe's Gaussians in the agent's own world frame (may be empty).
    pub gaussians: GaussianCloud,
}

/// The consensus state: see the module documentation.
pub struct Engine {
    config: ConsensusConfig,
    started: Instant,
    database: PlaceDatabase,
    /// Shared with alignment jobs, which may run on another thread ([`AlignmentJob`]).
    prepared: BTreeMap<KeyframeRef, Arc<PreparedKeyframe>>,
    info: BTreeMap<KeyframeRef, KeyframeInfo>,
    gaussians: BTreeMap<KeyframeRef, GaussianCloud>,
    /// Each agent's final optimised map (its own frame), once it has sent it.
    final_maps: BTreeMap<u32, GaussianCloud>,
    graph: PoseGraph,
    queue: VecDeque<Candidate>,
    attempted: BTreeSet<(KeyframeRef, KeyframeRef)>,
    last_of_agent: BTreeMap<u32, KeyframeRef>,
    events: Vec<ClosureEvent>,
    /// Published keyframes per agent (what map registration is scheduled by).
    keyframes_per_agent: BTreeMap<u32, usize>,
    map_scheduler: MapScheduler,
    /// Index in `events` of each closure added to the graph, in graph order.
    closure_events: Vec<usize>,
    solution: Option<PoseGraphSolution>,
    /// A closure or keyframe arrived since the last solve.
    dirty: bool,
    solve_ms: Vec<f64>,
    /// Wrong closures added beside the verified ones (`[consensus.false_closures]`; off: `None`).
    false_closures: Option<FalseClosureInjector>,
    /// Decisions of an earlier process of the run waiting for their keyframes
    /// ([`Self::resume_decisions`]).
    stored_decisions: Vec<Decision>,
}

impl Engine {
    /// An engine with no keyframes, run by the `[consensus]` configuration and its sections;
    /// its clock (`at_s` of the events) starts now.
    pub fn new(config: ConsensusConfig) -> Self {
        Self {
            false_closures: FalseClosureInjector::new(&config.false_closures),
            database: PlaceDatabase::new(SelectionThresholds::from_config(&config)),
            config,
            started: Instant::now(),
            prepared: BTreeMap::new(),
            info: BTreeMap::new(),
            gaussians: BTreeMap::new(),
            final_maps: BTreeMap::new(),
            graph: PoseGraph::new(),
            queue: VecDeque::new(),
            attempted: BTreeSet::new(),
            last_of_agent: BTreeMap::new(),
            events: Vec::new(),
            keyframes_per_agent: BTreeMap::new(),
            map_scheduler: MapScheduler::default(),
            closure_events: Vec::new(),
            solution: None,
            dirty: false,
            solve_ms: Vec::new(),
            stored_decisions: Vec::new(),
        }
    }

    /// Stores a keyframe and queues its candidates. Returns false for a duplicate.
    pub fn add_keyframe(&mut self, arrival: KeyframeArrival) -> bool {
        let id = arrival.keyframe.id;
        if self.prepared.contains_key(&id) {
            tracing::debug!(?id, "keyframe already known: duplicate ignored");
            return false;
        }
        let _span =
            tracing::info_span!("keyframe", agent = id.agent_id, id = id.keyframe_id).entered();
        let proposals =
            self.database
                .insert_and_query(id, arrival.frame_index, &arrival.descriptor);
        let pose = arrival.keyframe.agent_from_camera;
        self.info.insert(
            id,
            KeyframeInfo {
                frame_index: arrival.frame_index,
                timestamp_s: arrival.timestamp_s,
                agent_from_camera: isometry_to_tum(&pose),
            },
        );
        self.graph.add_keyframe(id, pose, arrival.frame_index);
        *self.keyframes_per_agent.entry(id.agent_id).or_default() += 1;
        self.gaussians.insert(id, arrival.gaussians);
        self.prepared.insert(
            id,
            Arc::new(PreparedKeyframe::new(
                arrival.keyframe,
                &self.config.alignment,
            )),
        );
        // Before its candidates are queued: a pair decided by an earlier process of the run is
        // taken as decided, not aligned again.
        self.apply_stored_decisions();
        if let Some(previous) = self.last_of_agent.insert(id.agent_id, id)
            && previous != id
        {
            self.queue.push_back(Candidate {
                source: id,
                target: previous,
                score: None,
                origin: CandidateSource::Odometry,
            });
        }
        for proposal in proposals
            .into_iter()
            .take(self.config.max_candidates_per_keyframe)
        {
            self.queue.push_back(Candidate {
                source: proposal.query,
                target: proposal.matched,
                score: Some(proposal.score),
                origin: CandidateSource::PlaceRecognition,
            });
        }
        self.dirty = true;
        true
    }

    /// Sets (replaces) a known keyframe's Gaussians, or an agent's final map (keyframe id
    /// [`FINAL_MAP_KEYFRAME_ID`]); hands them back when the keyframe is not known yet.
    pub fn set_gaussians(
        &mut self,
        id: KeyframeRef,
        gaussians: GaussianCloud,
    ) -> Result<(), GaussianCloud> {
        if id.keyframe_id == FINAL_MAP_KEYFRAME_ID {
            self.final_maps.insert(id.agent_id, gaussians);
            return Ok(());
        }
        match self.gaussians.get_mut(&id) {
            Some(stored) => {
                *stored = gaussians;
                Ok(())
            }
            None => Err(gaussians),
        }
    }

    /// Candidates waiting for alignment.
    pub fn pending(&self) -> usize {
        self.queue.len()
    }

    /// The next piece of work, as a job that can run on any thread while the engine takes
    /// keyframes and solves; its outcome comes back through [`Self::decide`] and
    /// [`Self::apply`]. In order: a map registration of two agents not linked yet, the next
    /// keyframe candidate, a map registration that refreshes a link. `None` when nothing is due.
    pub fn next_job(&mut self) -> Option<Job> {
        if let Some(job) = self.next_map_job(false) {
            return Some(Job::Maps(Box::new(job)));
        }
        if let Some(job) = self.next_alignment() {
            return Some(Job::Keyframes(Box::new(job)));
        }
        self.next_map_job(true).map(|job| Job::Maps(Box::new(job)))
    }

    /// Takes the next queued candidate (skipping pairs already attempted either way round).
    fn next_alignment(&mut self) -> Option<AlignmentJob> {
        let candidate = loop {
            let candidate = self.queue.pop_front()?;
            let key = (candidate.source, candidate.target);
            let reverse = (candidate.target, candidate.source);
            if self.attempted.contains(&key) || self.attempted.contains(&reverse) {
                continue;
            }
            self.attempted.insert(key);
            break candidate;
        };
        Some(AlignmentJob {
            source: Arc::clone(&self.prepared[&candidate.source]),
            target: Arc::clone(&self.prepared[&candidate.target]),
            candidate,
            config: self.config.alignment.clone(),
        })
    }

    /// A map registration of the next due agent pair ([`MapScheduler`]); the higher agent id is
    /// the source.
    fn next_map_job(&mut self, refreshes: bool) -> Option<MapJob> {
        let placed = |agent: u32| {
            self.solution
                .as_ref()
                .and_then(|s| s.world_from_agent.get(&agent).copied().flatten())
                .is_some()
        };
        let (target, source) = self.map_scheduler.next_pair(
            &self.keyframes_per_agent,
            &placed,
            refreshes,
            &self.config.map_registration,
        )?;
        Some(MapJob {
            source: self.agent_map(source),
            target: self.agent_map(target),
            registration: self.config.map_registration.clone(),
            alignment: self.config.alignment.clone(),
        })
    }

    /// An agent's map as published, in its tracked frame: its patches' Gaussian means and its
    /// keyframes' depth points, with their colours.
    fn agent_map(&self, agent_id: u32) -> AgentMap {
        AgentMap::from_keyframes(
            agent_id,
            self.prepared
                .range(agent_range(agent_id))
                .map(|(id, prepared)| (prepared, self.gaussians.get(id))),
        )
    }

    /// Re-solves the pose graph if anything changed since the last solve. Returns the new
    /// solution, or `None` when nothing changed or agent 0 (the world frame) has not published
    /// yet.
    pub fn solve_if_changed(&mut self) -> Option<&PoseGraphSolution> {
        if !self.dirty {
            return None;
        }
        let clock = Instant::now();
        match self.graph.solve(&self.config.pose_graph) {
            Ok(solution) => {
                self.dirty = false;
                self.solve_ms.push(clock.elapsed().as_secs_f64() * 1e3);
                for (decision, &event) in solution.loops.iter().zip(&self.closure_events) {
                    self.events[event].accepted_by_pose_graph = Some(decision.accepted);
                }
                self.solution = Some(solution);
                self.solution.as_ref()
            }
            Err(PoseGraphError::NoWorldAgent) => None,
            Err(error) => {
                tracing::error!(%error, "pose graph not solved");
                self.dirty = false;
                None
            }
        }
    }

    /// The latest pose-graph solution; `None` before the first successful solve.
    pub fn solution(&self) -> Option<&PoseGraphSolution> {
        self.solution.as_ref()
    }

    /// Every attempt applied so far (verified, rejected, or wrong closures injected), in the
    /// order applied.
    pub fn events(&self) -> &[ClosureEvent] {
        &self.events
    }

    /// Every keyframe received, with its frame index, capture time and tracked pose.
    pub fn keyframes(&self) -> &BTreeMap<KeyframeRef, KeyframeInfo> {
        &self.info
    }

    /// Wall-clock time of each successful pose-graph solve, milliseconds, oldest first.
    pub fn solve_ms(&self) -> &[f64] {
        &self.solve_ms
    }
}
