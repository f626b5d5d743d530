//! The agent's per-frame work (docs/method.md, One agent), one method per stage: track the
//! frame, decide whether it is a keyframe, seed Gaussians from it, publish it to the swarm,
//! hand it to the mapper, then apply what the consensus sent back. [`crate::run`] drives these
//! stages frame by frame and writes the outputs.
//!
//! Tracking never waits for the mapper (keyframes go to the mapping thread over a channel),
//! except under `mapping.pace = "paced"`, where each keyframe waits for its mapping budget.

use std::time::Instant;

use config::Config;
use datasets::Frame;
use live_view::LiveView;
use nalgebra::Isometry3;
use registration::config::TrackingKeyframeSeeds;
use registration::odometry::{
    FrameInput, Odometry, OdometryMode, Placement, SegmentJoin, TrackedFrame, TrackingOutcome,
};
use splats::{GaussianCloud, RigidTransform};

use crate::local_corrections::{LocalCorrections, LocalMaps};
use crate::mapper::{KeyframeKind, Mapper, MappingKeyframe};
use crate::progress::{Progress, Stage};
use crate::ros2_live::LiveOutputs;
use crate::seeding::{CoverageIndex, SeedFrame, seed_gaussians};
use crate::segments::PendingKeyframes;
use crate::source::SourceFrame;
use crate::swarm::{PublishableKeyframe, SwarmLink, run_anchor};

/// Keyframes an unjoined tracking segment may hold back at most (crate::segments): 64 keyframes
/// of 640x480 images are about 130 MB.
const PENDING_KEYFRAMES: usize = 64;

/// One frame's estimate, as the outputs report it.
#[derive(Clone, Copy)]
pub struct TrackedPose {
    /// Position in the frame source (what `Dataset::load` takes).
    pub position: usize,
    /// The frame's timestamp, seconds on the dataset's (or camera's) clock.
    pub timestamp: f64,
    /// In the tracked frame (the consensus's frame for this agent), or, while
    /// `placement` is an unjoined segment, in that segment's frame.
    pub world_from_camera: Isometry3<f64>,
    /// The dataset's ground-truth `world_from_camera`; `None` when it has none for this frame.
    pub ground_truth: Option<Isometry3<f64>>,
    /// The root map, or the unjoined tracking segment whose frame `world_from_camera` is in.
    pub placement: Placement,
    /// The tracker placed the frame (false: lost, the pose is the prediction).
    pub tracked: bool,
    /// The frame's tracking confidence (see `registration::TrackedFrame::confidence`).
    pub confidence: f64,
    /// Wall time of the frame's pass through the loop's stages (tracking, keyframe,
    /// corrections), ms.
    pub loop_ms: f64,
    /// Of the tracking, the wide-baseline guesses' wall time (0 when the ordinary path
    /// passed), ms.
    pub recovery_ms: f64,
    /// Of the tracking, the map update and relocalisation attempts, ms.
    pub map_update_ms: f64,
}

/// Keyframes made so far, by the rule that made them.
#[derive(Debug, Clone, Copy, Default)]
pub struct KeyframeCounts {
    /// Tracking keyframes: too little overlap with the tracking map.
    pub tracking: usize,
    /// Mapping keyframes: every `mapping_keyframe_every`-th frame otherwise.
    pub mapping: usize,
}

impl KeyframeCounts {
    /// All keyframes made; also the next keyframe's id.
    pub fn total(&self) -> usize {
        self.tracking + self.mapping
    }
}

/// A keyframe handed to the mapper: one of the views its map is optimised on (keyframes.csv,
/// which held-out evaluation reads to leave them out).
#[derive(Debug, Clone, Copy)]
pub struct KeyframeMade {
    /// Keyframe id, counting up from 0 in the order keyframes are made.
    pub keyframe_id: usize,
    /// The frame's number in its sequence ([`Frame::index`]).
    pub frame_index: usize,
    /// The frame's timestamp, seconds.
    pub timestamp_s: f64,
    /// Which rule made it.
    pub kind: KeyframeKind,
}

/// The tracker's answer for one frame.
#[derive(Clone)]
pub struct Tracked {
    /// The odometry's answer with its pose in the local-map frame, where mapping runs (and
    /// tracking, when the tracking map moves with corrections: `move_tracking_map`).
    pub local: TrackedFrame,
    /// The same pose in the tracked frame (crate::local_corrections explains the two frames).
    pub world_from_camera: Isometry3<f64>,
    /// The odometry's own pose (in an unjoined segment's frame while it tracks one).
    pub odometry_from_camera: Isometry3<f64>,
    /// Depth was present and the tracker found a pose: the frame may become a mapping keyframe.
    pub usable: bool,
}

/// A frame the keyframe rule selected, with the points that seed new Gaussians.
#[derive(Clone)]
pub struct KeyframeDecision {
    /// Which rule selected the frame.
    pub kind: KeyframeKind,
    /// Per point of the frame's `frame_points`: whether it seeds a Gaussian. Empty while the
    /// keyframe waits for an unjoined segment: its seeds are chosen when the segment is joined.
    pub seed_mask: Vec<bool>,
}

/// What the frame loop leaves for the outputs (the mapper and the swarm link are handed back
/// separately: finishing them consumes them).
pub struct FinishedPipeline {
    /// The tracker, for its counters (metrics.json's tracking block).
    pub odometry: Odometry,
    /// The consensus corrections: their counters, and the field that places frames in the map.
    pub corrections: LocalCorrections,
    /// Every frame the loop took, in order, lost ones and those of unjoined segments included.
    pub poses: Vec<TrackedPose>,
    /// Per placed frame: the wall clock when its pose was placed minus the frame's stamp,
    /// milliseconds (a live camera's latency from capture to pose; meaningless for recordings,
    /// whose stamps are another day's).
    pub stamp_to_pose_ms: Vec<f64>,
    /// Keyframes made, by kind.
    pub keyframes: KeyframeCounts,
    /// Every keyframe the mapper was given, in order.
    pub keyframes_made: Vec<KeyframeMade>,
    /// Keyframes of segments never joined, dropped from the map.
    pub keyframes_dropped_unjoined: usize,
    /// The live DDS outputs, when `[ros2] publish` is on: the final map goes there too.
    pub ros2_live: Option<LiveOutputs>,
}

/// The per-frame state of one agent.
pub struct AgentPipeline<'a> {
    config: &'a Config,
    /// The dataset argument, which names the run in the swarm announcement.
    dataset_spec: &'a str,
    odometry: Odometry,
    mapper: Mapper,
    coverage: CoverageIndex,
    /// Consensus corrections of the local maps (the identity when standalone).
    corrections: LocalCorrections,
    swarm: Option<SwarmLink>,
    keyframes: KeyframeCounts,
    keyframes_made: Vec<KeyframeMade>,
    frames_since_tracking_keyframe: usize,
    poses: Vec<TrackedPose>,
    stamp_to_pose_ms: Vec<f64>,
    agent_id: u32,
    /// Frames, keyframes, seeded points and placements for the rerun viewer (off the hot path:
    /// each call only queues, or drops when the queue is full).
    live_view: LiveView,
    /// Keyframes of an unjoined tracking segment, waiting to be joined (crate::segments).
    pending: PendingKeyframes,
    /// tf, path and map published over DDS as they are made (`[ros2] publish`).
    ros2_live: Option<LiveOutputs>,
}

impl<'a> AgentPipeline<'a> {
    /// Starts the agent's stages: the tracker, the mapping thread and, with `[ros2] publish`,
    /// the live DDS outputs; fails when either of the last two cannot start. `swarm` is the link
    /// to the consensus (`None`: standalone); `frames_expected` only sizes the per-frame records.
    pub fn new(
        config: &'a Config,
        dataset_spec: &'a str,
        swarm: Option<SwarmLink>,
        frames_expected: usize,
        agent_id: u32,
        live_view: LiveView,
    ) -> anyhow::Result<Self> {
        use anyhow::Context;
        let standalone = swarm.is_none();
        Ok(Self {
            config,
            dataset_spec,
            odometry: Odometry::new(
                OdometryMode::FrameToModel,
                &config.tracking,
                &config.keyframes,
            ),
            mapper: Mapper::spawn(&config.tracking, &config.mapping)
                .context("starting the mapping thread")?,
            coverage: CoverageIndex::new(config.keyframes.mapping_seed_min_distance_sq_m2.sqrt()),
            corrections: LocalCorrections::new(&config.consensus.local_corrections),
            swarm,
            keyframes: KeyframeCounts::default(),
            keyframes_made: Vec::new(),
            frames_since_tracking_keyframe: 0,
            poses: Vec::with_capacity(frames_expected),
            stamp_to_pose_ms: Vec::with_capacity(frames_expected),
            agent_id,
            live_view,
            pending: PendingKeyframes::new(PENDING_KEYFRAMES),
            ros2_live: LiveOutputs::start(&config.ros2, agent_id, standalone)
                .context("starting the live ROS 2 outputs")?,
        })
    }

    /// Announces this agent to the consensus with its first frame, the one its run starts at.
    pub fn announce(&mut self, frame: &Frame) {
        if let Some(swarm) = self.swarm.as_mut()
            && !swarm.is_announced()
        {
            let anchor = run_anchor(self.dataset_spec, frame.index, frame.timestamp);
            swarm.announce(&frame.intrinsics, anchor);
        }
    }

    /// Frame-to-model G-ICP against the trackable Gaussians (docs/method.md, Tracking). When
    /// the tracker joins a segment to the map at this frame, the segment's poses and waiting
    /// keyframes move into the agent's frame first. `real_time`: the frames come from a live
    /// camera or a sensor-paced replay (see `registration::FrameInput::real_time`).
    pub fn track(&mut self, item: &SourceFrame, real_time: bool) -> Tracked {
        let frame = &item.frame;
        let tracker_first_point = self.odometry.next_point_id();
        let local = self.odometry.track(FrameInput {
            timestamp_s: frame.timestamp,
            depth: &frame.depth,
            rgb: Some(&frame.rgb),
            intrinsics: &frame.intrinsics,
            colour_offset_s: frame.colour_offset_s,
            real_time,
        });
        if self.odometry.next_point_id() > tracker_first_point {
            self.corrections
                .record_tracker_points(tracker_first_point, frame.timestamp);
        }
        if let Some(join) = local.join {
            self.join_segment(&join);
        }
        self.placed(frame.timestamp, local, item.has_depth)
    }

    /// The odometry's answer with its pose in the two frames of crate::local_corrections.
    fn placed(&self, timestamp: f64, mut local: TrackedFrame, has_depth: bool) -> Tracked {
        let odometry_from_camera = local.world_from_camera;
        let (local_from_camera, world_from_camera) = self
            .corrections
            .from_odometry(timestamp, &odometry_from_camera);
        local.world_from_camera = local_from_camera;
        let usable = has_depth
            && (local.outcome == TrackingOutcome::Initialised || local.outcome.is_tracked());
        Tracked {
            local,
            world_from_camera,
            odometry_from_camera,
            usable,
        }
    }

    /// A segment joined to the map: its recorded poses move into the agent's frame, and its
    /// waiting keyframes are handled, in order, as if they had just been made there.
    fn join_segment(&mut self, join: &SegmentJoin) {
        for pose in &mut self.poses {
            if let Some((placement, moved)) = join.moved(pose.placement, &pose.world_from_camera) {
                pose.placement = placement;
                pose.world_from_camera = moved;
            }
        }
        let released = self.pending.release(join);
        tracing::info!(
            segment = join.segment,
            keyframes = released.len(),
            "tracking segment joined: its keyframes join the map"
        );
        for (frame, tracked, decision) in released {
            let mut local = tracked.local;
            local.world_from_camera = join.root_from_segment * tracked.odometry_from_camera;
            local.placement = Placement::Root;
            let tracked = self.placed(frame.timestamp, local, true);
            let seed_mask = self.seed_mask(decision.kind, &frame, &tracked);
            self.make_keyframe(
                &frame,
                &tracked,
                KeyframeDecision {
                    kind: decision.kind,
                    seed_mask,
                },
            );
        }
    }

    /// Seeds, publishes and maps a keyframe the rule selected, or, while the tracker follows an
    /// unjoined segment, keeps it until the segment is joined (crate::segments).
    pub fn keyframe(&mut self, frame: &Frame, tracked: &Tracked, decision: KeyframeDecision) {
        match tracked.local.placement {
            Placement::Root => self.make_keyframe(frame, tracked, decision),
            Placement::Unjoined(segment) => {
                self.pending
                    .hold(segment, frame.clone(), tracked.clone(), decision)
            }
        }
    }

    fn make_keyframe(&mut self, frame: &Frame, tracked: &Tracked, decision: KeyframeDecision) {
        let keyframe_id = self.next_keyframe_id();
        let seeds = self.seed(keyframe_id, frame, tracked, &decision);
        self.publish(keyframe_id, frame, tracked, &seeds);
        self.hand_to_mapper(keyframe_id, frame, tracked, decision, seeds);
    }

    /// The keyframe rule (docs/method.md, Keyframes): a tracking keyframe when too few points
    /// found the map (the tracker decides and marks the trackable points), else a mapping
    /// keyframe every `mapping_keyframe_every` frames since the last tracking keyframe.
    pub fn decide_keyframe(
        &mut self,
        frame: &Frame,
        tracked: &Tracked,
    ) -> Option<KeyframeDecision> {
        self.frames_since_tracking_keyframe += 1;
        let keyframes = &self.config.keyframes;
        let kind = if tracked.local.trackable.is_some() {
            self.frames_since_tracking_keyframe = 0;
            KeyframeKind::Tracking
        } else if tracked.usable
            && self
                .frames_since_tracking_keyframe
                .is_multiple_of(keyframes.mapping_keyframe_every)
        {
            KeyframeKind::Mapping
        } else {
            return None;
        };
        // The seeds of a keyframe held for an unjoined segment are chosen when it is joined:
        // the coverage index is in the agent's frame.
        let seed_mask = match tracked.local.placement {
            Placement::Root => self.seed_mask(kind, frame, tracked),
            Placement::Unjoined(_) => Vec::new(),
        };
        Some(KeyframeDecision { kind, seed_mask })
    }

    /// Which points of a keyframe seed Gaussians (docs/method.md, Seeding).
    fn seed_mask(&self, kind: KeyframeKind, frame: &Frame, tracked: &Tracked) -> Vec<bool> {
        let points = tracked.local.frame_points.len();
        match (kind, self.config.keyframes.tracking_keyframe_seeds) {
            (KeyframeKind::Tracking, TrackingKeyframeSeeds::All) => vec![true; points],
            _ => self.uncovered_points(frame, tracked),
        }
    }

    /// New Gaussians from the keyframe's selected points (docs/method.md, Seeding); they join
    /// the coverage index that decides later keyframes' seeds.
    pub fn seed(
        &mut self,
        keyframe_id: usize,
        frame: &Frame,
        tracked: &Tracked,
        decision: &KeyframeDecision,
    ) -> GaussianCloud {
        let seeds = seed_gaussians(
            &seed_frame(frame, tracked),
            &decision.seed_mask,
            &self.config.tracking,
            &self.config.keyframes,
        );
        self.corrections
            .record_coverage_points(self.coverage.next_id(), frame.timestamp);
        self.coverage.insert(&seeds);
        self.corrections
            .record_keyframe(keyframe_id, frame.timestamp, tracked.world_from_camera);
        seeds
    }

    /// Queues the keyframe for the consensus (swarm only), in the tracked frame, the
    /// consensus's frame for this agent; the link decides when it goes out (every T_comm).
    pub fn publish(
        &mut self,
        keyframe_id: usize,
        frame: &Frame,
        tracked: &Tracked,
        seeds: &GaussianCloud,
    ) {
        let Some(swarm) = self.swarm.as_mut() else {
            return;
        };
        let mut gaussians = seeds.clone();
        gaussians.transform_rigid(&RigidTransform::from(
            &self.corrections.tracked_from_local(frame.timestamp),
        ));
        swarm.on_keyframe(PublishableKeyframe {
            keyframe_id: keyframe_id as u64,
            frame_index: frame.index as u64,
            timestamp_s: frame.timestamp,
            agent_from_camera: tracked.world_from_camera,
            intrinsics: frame.intrinsics,
            rgb: frame.rgb.clone(),
            depth: frame.depth.clone(),
            gaussians,
        });
    }

    /// Hands the keyframe and its new Gaussians to the mapping thread (docs/method.md, Map
    /// optimisation), in the local-map frame. Paced (`mapping.pace`), returns once the mapper
    /// has spent its iterations on it.
    pub fn hand_to_mapper(
        &mut self,
        keyframe_id: usize,
        frame: &Frame,
        tracked: &Tracked,
        decision: KeyframeDecision,
        seeds: GaussianCloud,
    ) {
        self.live_view
            .keyframe(self.agent_id, &tracked.local.world_from_camera);
        self.live_view
            .map_points(self.agent_id, &seeds.means, &seeds.colours, false);
        if let Some(live) = self.ros2_live.as_mut() {
            live.keyframe(&seeds);
        }
        match decision.kind {
            KeyframeKind::Tracking => self.keyframes.tracking += 1,
            KeyframeKind::Mapping => self.keyframes.mapping += 1,
        }
        self.keyframes_made.push(KeyframeMade {
            keyframe_id,
            frame_index: frame.index,
            timestamp_s: frame.timestamp,
            kind: decision.kind,
        });
        tracing::debug!(
            frame = frame.index,
            kind = ?decision.kind,
            new_gaussians = seeds.len(),
            "keyframe"
        );
        self.mapper.add_keyframe(MappingKeyframe {
            keyframe_id,
            frame_index: frame.index,
            timestamp_s: frame.timestamp,
            kind: decision.kind,
            world_from_camera: tracked.local.world_from_camera,
            intrinsics: frame.intrinsics,
            rgb: frame.rgb.clone(),
            depth: frame.depth.clone(),
            new_gaussians: seeds,
        });
        self.mapper.wait_for_budget();
    }

    /// Applies a correction the consensus sent (swarm only) to the mapper's map and the coverage
    /// index (and the tracker's model with `move_tracking_map`).
    pub fn apply_corrections(&mut self, frame: &Frame) {
        let Some(correction) = self.swarm.as_mut().and_then(SwarmLink::after_frame) else {
            return;
        };
        self.corrections.apply(
            &correction,
            frame.timestamp,
            LocalMaps {
                odometry: &mut self.odometry,
                coverage: &mut self.coverage,
                mapper: &self.mapper,
            },
        );
        // The local-map frame (where the live view shows the agent) is the world frame seen
        // from the agent's frame: the agent's placement puts it in the world.
        self.live_view
            .agent_placement(self.agent_id, &correction.world_from_agent);
    }

    /// Keeps the frame's pose and its time in the loop (started at `clock`).
    pub fn record(&mut self, item: &SourceFrame, tracked: &Tracked, clock: Instant) {
        let loop_ms = clock.elapsed().as_secs_f64() * 1e3;
        let placed = tracked.local.placement == Placement::Root
            && (tracked.local.outcome.is_tracked()
                || tracked.local.outcome == TrackingOutcome::Initialised);
        if placed {
            let now_s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            self.stamp_to_pose_ms
                .push((now_s - item.frame.timestamp) * 1e3);
        }
        if let Some(live) = self.ros2_live.as_mut()
            && placed
        {
            live.frame(item.frame.timestamp, &tracked.world_from_camera);
        }
        self.poses.push(TrackedPose {
            position: item.position,
            timestamp: item.frame.timestamp,
            world_from_camera: tracked.world_from_camera,
            ground_truth: item.frame.world_from_camera_gt,
            placement: tracked.local.placement,
            tracked: tracked.local.outcome.is_tracked()
                || tracked.local.outcome == TrackingOutcome::Initialised,
            confidence: tracked.local.confidence(),
            loop_ms,
            recovery_ms: tracked.local.timings.recovery_ms,
            map_update_ms: tracked.local.timings.map_update_ms,
        });
        self.live_view.frame(
            self.agent_id,
            item.frame.index,
            &tracked.local.world_from_camera,
            &item.frame.intrinsics,
            &item.frame.rgb,
        );
    }

    /// The next keyframe's id: keyframes are numbered in the order they are made.
    pub fn next_keyframe_id(&self) -> usize {
        self.keyframes.total()
    }

    /// The consensus asked this agent to stop: its reason.
    pub fn stop_requested_by_consensus(&self) -> Option<&str> {
        self.swarm.as_ref().and_then(|s| s.stop_requested())
    }

    /// A one-line summary for the progress bar.
    pub fn progress_message(&self) -> String {
        use std::sync::atomic::Ordering;
        let progress = &self.mapper.progress;
        format!(
            "{} keyframes, {} Gaussians, {} mapping iterations",
            self.keyframes.total(),
            progress.gaussians.load(Ordering::Relaxed),
            progress.iterations.load(Ordering::Relaxed)
        )
    }

    /// What progress.json says now.
    pub fn progress(&self, stage: Stage, frames_total: Option<usize>) -> Progress {
        progress_snapshot(
            stage,
            self.poses.len(),
            frames_total,
            self.keyframes.total(),
            self.swarm.as_ref(),
        )
    }

    /// Frames the loop has taken so far (lost ones included).
    pub fn frames_done(&self) -> usize {
        self.poses.len()
    }

    /// Ends the frame loop: keyframes still held for an unjoined segment are given up, and the
    /// mapper, the swarm link (when there is one) and what the outputs need are handed back.
    pub fn finish(mut self) -> (Mapper, Option<SwarmLink>, FinishedPipeline) {
        // A real-time run may end while its segment's place is still being searched for.
        if let Some(join) = self.odometry.finish_search() {
            self.join_segment(&join);
        }
        self.pending.give_up();
        let finished = FinishedPipeline {
            odometry: self.odometry,
            corrections: self.corrections,
            poses: self.poses,
            stamp_to_pose_ms: self.stamp_to_pose_ms,
            keyframes: self.keyframes,
            keyframes_made: self.keyframes_made,
            keyframes_dropped_unjoined: self.pending.dropped,
            ros2_live: self.ros2_live,
        };
        (self.mapper, self.swarm, finished)
    }

    /// The frame's points not yet covered by the map: mapping keyframes seed only these.
    fn uncovered_points(&self, frame: &Frame, tracked: &Tracked) -> Vec<bool> {
        self.coverage.uncovered(
            &seed_frame(frame, tracked),
            self.config.keyframes.mapping_seed_min_distance_sq_m2,
        )
    }
}

/// Progress of a run, with the swarm link's state when there is one.
pub fn progress_snapshot(
    stage: Stage,
    frames_done: usize,
    frames_total: Option<usize>,
    keyframes: usize,
    swarm: Option<&SwarmLink>,
) -> Progress {
    let link = swarm.map(SwarmLink::status);
    Progress {
        stage,
        frames_done,
        frames_total,
        keyframes,
        link_up: link.map(|l| l.up),
        queued_keyframes: link.map(|l| l.queued_keyframes),
    }
}

fn seed_frame<'f>(frame: &'f Frame, tracked: &'f Tracked) -> SeedFrame<'f> {
    SeedFrame {
        points: &tracked.local.frame_points,
        world_from_camera: &tracked.local.world_from_camera,
        rgb: &frame.rgb,
        intrinsics: &frame.intrinsics,
    }
}
