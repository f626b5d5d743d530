//! The agent's side of tracking segments (docs/method.md, One agent: Tracking, "Relocalisation";
//! the tracker's side is registration/src/odometry/segments.rs).
//!
//! While the tracker follows a segment that is not joined to the agent's map, its poses are in
//! a frame of their own: nothing of it may reach the mapper or the consensus, which both work
//! in the agent's frame. Its keyframes wait here, with their images, until the segment is joined
//! (then they are moved into the agent's frame and handled as if they had just been made, in
//! order) or given up (a newer segment started, or the run ended: they are dropped and
//! counted). At most `capacity` wait; beyond that the oldest is dropped, so a long unjoined
//! segment cannot exhaust memory.

use std::collections::VecDeque;

use datasets::Frame;
use registration::odometry::{SegmentId, SegmentJoin};
use serde::Serialize;

use crate::pipeline::{KeyframeDecision, Tracked};

/// Keyframes of an unjoined segment waiting to be joined (see the module documentation).
pub struct PendingKeyframes {
    segment: Option<SegmentId>,
    waiting: VecDeque<(Frame, Tracked, KeyframeDecision)>,
    capacity: usize,
    /// Dropped because their segment was given up or never joined, or the queue was full.
    pub dropped: usize,
}

impl PendingKeyframes {
    /// An empty queue that holds at most `capacity` keyframes (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            segment: None,
            waiting: VecDeque::new(),
            capacity,
            dropped: 0,
        }
    }

    /// Holds a keyframe of the unjoined `segment`; an older segment's keyframes are given up.
    pub fn hold(
        &mut self,
        segment: SegmentId,
        frame: Frame,
        tracked: Tracked,
        decision: KeyframeDecision,
    ) {
        if self.segment != Some(segment) {
            self.give_up();
            self.segment = Some(segment);
        }
        if self.waiting.len() >= self.capacity.max(1) {
            self.waiting.pop_front();
            self.dropped += 1;
            tracing::warn!(
                segment,
                capacity = self.capacity,
                "too many keyframes wait for their segment to be joined: the oldest is dropped"
            );
        }
        self.waiting.push_back((frame, tracked, decision));
    }

    /// The waiting keyframes of the segment `join` placed, in the order they were made (the
    /// caller moves them into the agent's frame); any others are given up.
    pub fn release(&mut self, join: &SegmentJoin) -> Vec<(Frame, Tracked, KeyframeDecision)> {
        if self.segment != Some(join.segment) {
            self.give_up();
            return Vec::new();
        }
        self.segment = None;
        self.waiting.drain(..).collect()
    }

    /// Drops every waiting keyframe (their segment will not be joined).
    pub fn give_up(&mut self) {
        if !self.waiting.is_empty() {
            tracing::warn!(
                segment = self.segment,
                keyframes = self.waiting.len(),
                "a segment that was never joined: its keyframes are dropped from the map"
            );
        }
        self.dropped += self.waiting.len();
        self.waiting.clear();
        self.segment = None;
    }

    /// Keyframes waiting now.
    pub fn len(&self) -> usize {
        self.waiting.len()
    }

    /// Whether no keyframe waits.
    pub fn is_empty(&self) -> bool {
        self.waiting.is_empty()
    }
}

/// What metrics.json reports of tracking: failures, recoveries and segments
/// (registration's `OdometryStats`, plus what the agent made of them).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TrackingReport {
    /// Frames no guess placed: their pose is the constant-velocity prediction.
    pub frames_lost: usize,
    /// Frames whose ordinary G-ICP result the check refused (divergence detected).
    pub divergences_detected: usize,
    /// Frames placed by a wide-baseline guess.
    pub recoveries: usize,
    /// Segments started after repeated failures.
    pub segments_started: usize,
    /// Segments joined to the map.
    pub segments_joined: usize,
    /// Frames of segments never joined: in trajectory_segment_K.tum, not in trajectory.tum.
    pub frames_unjoined: usize,
    /// Keyframes of unjoined segments, dropped from the map.
    pub keyframes_dropped_unjoined: usize,
    /// At sensor pace: image-feature or geometry guesses and relocalisation attempts not
    /// started because their share of the time was spent (`tracking.recovery_time_share`).
    pub searches_rationed: usize,
    /// Median per-frame confidence (the check's depth agreement, in [0, 1]) over placed frames;
    /// `None` when no frame was placed.
    pub confidence_median: Option<f64>,
    /// Lowest per-frame confidence over placed frames; `None` when no frame was placed.
    pub confidence_min: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mapper::KeyframeKind;
    use nalgebra::Isometry3;
    use registration::odometry::{JoinEvidence, Placement};

    fn keyframe(index: usize) -> (Frame, Tracked, KeyframeDecision) {
        let dataset = datasets::open(
            "synthetic:agents=1,frames=3,width=32,height=24",
            Default::default(),
        )
        .unwrap();
        let frame = dataset.load(index % 3).unwrap();
        let mut odometry = registration::Odometry::new(
            registration::OdometryMode::FrameToModel,
            &Default::default(),
            &Default::default(),
        );
        let local = odometry.track(registration::FrameInput {
            timestamp_s: frame.timestamp,
            depth: &frame.depth,
            rgb: Some(&frame.rgb),
            intrinsics: &frame.intrinsics,
            colour_offset_s: frame.colour_offset_s,
            real_time: false,
        });
        let tracked = Tracked {
            local: registration::TrackedFrame {
                placement: Placement::Unjoined(1),
                ..local
            },
            world_from_camera: Isometry3::identity(),
            odometry_from_camera: Isometry3::identity(),
            usable: true,
        };
        let decision = KeyframeDecision {
            kind: KeyframeKind::Tracking,
            seed_mask: Vec::new(),
        };
        (frame, tracked, decision)
    }

    fn join(segment: SegmentId) -> SegmentJoin {
        SegmentJoin {
            segment,
            root_from_segment: Isometry3::identity(),
            evidence: JoinEvidence::KeyframeAlignment,
        }
    }

    #[test]
    fn a_joined_segment_releases_its_keyframes_in_order_and_others_are_dropped() {
        let mut pending = PendingKeyframes::new(2);
        for index in 0..3 {
            let (frame, tracked, decision) = keyframe(index);
            pending.hold(1, frame, tracked, decision);
        }
        // Full at 2: the oldest went.
        assert_eq!((pending.len(), pending.dropped), (2, 1));
        let released = pending.release(&join(1));
        let indices: Vec<usize> = released.iter().map(|(f, _, _)| f.index).collect();
        assert_eq!(indices, [1, 2]);
        assert!(pending.is_empty());
        // A newer segment gives the older one's keyframes up; a join of another segment too.
        let (frame, tracked, decision) = keyframe(0);
        pending.hold(2, frame, tracked, decision);
        let (frame, tracked, decision) = keyframe(1);
        pending.hold(3, frame, tracked, decision);
        assert_eq!((pending.len(), pending.dropped), (1, 2));
        assert!(pending.release(&join(2)).is_empty());
        assert_eq!(pending.dropped, 3);
        let (frame, tracked, decision) = keyframe(2);
        pending.hold(4, frame, tracked, decision);
        pending.give_up();
        assert_eq!((pending.len(), pending.dropped), (0, 4));
    }
}
