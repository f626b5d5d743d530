//! Starting a segment after repeated failures, relocalising it in the root, joining it
//! (the procedure of [`super::segments`]).

use nalgebra::Isometry3;

use crate::kdtree::PointTree;
use crate::map_registration::register_maps;
use crate::points::PointCloud;
use crate::voxel_map::{ViewFrustum, VoxelMap};

use super::recovery::{Candidate, Guess, Recovery};
use super::segments::{JoinEvidence, KeyframeArchive, SegmentJoin};
use super::{
    Detached, FrameInput, Odometry, RELOCALISATION_MAP_POINTS, StageTimings, TrackedFrame,
};

impl Odometry {
    /// After `max_consecutive_failures` lost frames: a new segment starts with this frame (see
    /// [`segments`]). The root map is kept aside for relocalisation; an unjoined segment that
    /// was being tracked is given up (its poses stay in its own frame).
    pub(super) fn start_segment(
        &mut self,
        frame: PointTree,
        input: &FrameInput<'_>,
        chosen: Option<Candidate>,
        timings: StageTimings,
    ) -> TrackedFrame {
        let segment = self.next_segment;
        self.next_segment += 1;
        self.stats.segments_started += 1;
        let fresh = || VoxelMap::for_correspondence_distance(self.tracking.max_correspondence_m);
        let root_map = match self.detached.take() {
            // The unjoined segment is given up; the root stays aside.
            Some(previous) => {
                tracing::warn!(
                    given_up = previous.segment,
                    segment,
                    "the unjoined segment was lost too; it stays in its own frame"
                );
                previous.root_map
            }
            None => std::mem::replace(&mut self.map, fresh()),
        };
        self.map = fresh();
        self.segment_archive = KeyframeArchive::new(self.tracking.relocalisation_keyframes);
        self.detached = Some(Detached {
            segment,
            root_map,
            keyframes: 0,
        });
        tracing::warn!(
            segment,
            failures = self.consecutive_failures,
            "tracking lost for good: a new segment starts in a frame of its own and will be joined to the map when it is recognised"
        );
        let mut tracked = self.initialise(frame, input);
        tracked.registration = chosen.map(|c| c.result);
        tracked.timings = StageTimings {
            map_update_ms: tracked.timings.map_update_ms,
            ..timings
        };
        tracked
    }

    /// Tries to place the detached segment in the root (see [`segments`]); joins it when a
    /// candidate passes the check against the root map.
    pub(super) fn relocalise(
        &mut self,
        input: &FrameInput<'_>,
        cloud: &PointCloud,
        segment_from_camera: &Isometry3<f64>,
    ) -> Option<SegmentJoin> {
        let detached = self.detached.as_mut()?;
        detached.keyframes += 1;
        let mut guesses: Vec<(Isometry3<f64>, JoinEvidence)> = Vec::new();
        if let Some(rgb) = input.rgb {
            let aligned = self.archive.align(
                rgb,
                input.depth,
                input.intrinsics,
                self.tracking.relocalisation_candidates,
                &self.alignment,
            );
            guesses.extend(
                aligned
                    .into_iter()
                    .map(|g| (g, JoinEvidence::KeyframeAlignment)),
            );
        }
        let map_due = self.tracking.relocalisation_map_every > 0
            && detached
                .keyframes
                .is_multiple_of(self.tracking.relocalisation_map_every);
        if guesses.is_empty() && map_due {
            let segment_points = self.map.sample_all(RELOCALISATION_MAP_POINTS);
            let root_points = detached.root_map.sample_all(RELOCALISATION_MAP_POINTS);
            let registration = register_maps(&segment_points, &root_points, &self.map_registration);
            tracing::debug!(
                accepted = registration.is_accepted(),
                verdict = ?registration.verdict,
                "relocalisation: map registration of the segment to the root"
            );
            if registration.is_accepted() {
                guesses.push((
                    registration.target_from_source * segment_from_camera,
                    JoinEvidence::MapRegistration,
                ));
            }
        }
        let detached = self.detached.as_mut()?;
        for (root_from_camera, evidence) in guesses {
            detached.root_map.select_view(&ViewFrustum::new(
                &root_from_camera,
                input.intrinsics,
                self.tracking.truncation_m,
            ));
            let recovery = Recovery {
                tracking: &self.tracking,
                fine: &self.params,
                map: &detached.root_map,
                frame: cloud,
                depth: input.depth,
                rgb: input.rgb,
                intrinsics: input.intrinsics,
            };
            let candidate = recovery.wide(Guess::WidePrediction, &root_from_camera);
            tracing::debug!(?evidence, check = ?candidate.check, passes = candidate.passes(&self.tracking), "relocalisation candidate");
            if candidate.passes(&self.tracking) {
                let root_from_segment =
                    candidate.result.target_from_source * segment_from_camera.inverse();
                return Some(self.join(root_from_segment, evidence));
            }
        }
        None
    }

    /// Moves the detached segment's map and keyframes into the root and tracks on in it.
    pub(super) fn join(
        &mut self,
        root_from_segment: Isometry3<f64>,
        evidence: JoinEvidence,
    ) -> SegmentJoin {
        let detached = self.detached.take().expect("joining a detached segment");
        let mut segment_map = std::mem::replace(&mut self.map, detached.root_map);
        segment_map.transform_points(|_| Some(root_from_segment));
        for point in segment_map.iter() {
            // Finite positions are always accepted.
            let _ = self.map.insert(*point);
        }
        let mut segment_archive = std::mem::replace(
            &mut self.segment_archive,
            KeyframeArchive::new(self.tracking.relocalisation_keyframes),
        );
        segment_archive.transform(&root_from_segment);
        self.archive.absorb(segment_archive);
        if let Some(trusted) = self.trusted.as_mut() {
            trusted.world_from_camera = root_from_segment * trusted.world_from_camera;
        }
        self.stats.segments_joined += 1;
        tracing::info!(
            segment = detached.segment,
            ?evidence,
            "segment relocalised: joined to the map"
        );
        SegmentJoin {
            segment: detached.segment,
            root_from_segment,
            evidence,
        }
    }
}
