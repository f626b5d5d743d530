//! Starting a segment after repeated failures, relocalising it in the root, joining it
//! (the procedure of [`super::segments`]).
//!
//! A search for the segment's place in the root takes tenths of a second to seconds on a CPU
//! (image alignments with archived keyframes, a map registration, G-ICP against the root map).
//! Paced and offline frames search at every keyframe of the segment, on the tracking thread.
//! Real-time frames (a live camera does not wait) hand each search to a thread of its own, one
//! at a time, and track on in the segment meanwhile: the join found is applied at the first
//! frame after the search ended, and the segment's poses and map move into the root as they
//! would have at the keyframe.

use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::{Isometry3, Point3};

use crate::alignment::AlignmentConfig;
use crate::config::TrackingConfig;
use crate::gicp::GicpParams;
use crate::kdtree::PointTree;
use crate::map_registration::{MapRegistrationConfig, register_maps};
use crate::points::PointCloud;
use crate::voxel_map::{ViewFrustum, VoxelMap};

use super::recovery::{Candidate, Guess, Recovery};
use super::segments::{JoinEvidence, KeyframeArchive, SegmentId, SegmentJoin};
use super::{
    Detached, FrameInput, Odometry, RELOCALISATION_MAP_POINTS, StageTimings, TrackedFrame,
};

/// A search running on its own thread for a real-time segment.
pub(super) struct PendingSearch {
    segment: SegmentId,
    handle: JoinHandle<Option<(Isometry3<f64>, JoinEvidence)>>,
}

/// The root's keyframe archive, shared with a search thread.
pub(super) type SharedArchive = Arc<Mutex<KeyframeArchive>>;

/// The archive, whether or not a search thread panicked while holding it (a search only reads
/// it; the prepared views it caches are built whole or not at all).
pub(super) fn lock(archive: &SharedArchive) -> std::sync::MutexGuard<'_, KeyframeArchive> {
    archive.lock().unwrap_or_else(PoisonError::into_inner)
}

/// What one search needs of the keyframe that starts it, owned, so that it can run on a thread.
struct JoinSearch {
    rgb: Option<RgbImage>,
    depth: DepthImage,
    intrinsics: Intrinsics,
    /// The keyframe's points in its camera frame, with covariances.
    cloud: PointCloud,
    segment_from_camera: Isometry3<f64>,
    /// The segment map's points, when a map registration is due at this keyframe.
    segment_points: Option<Vec<Point3<f32>>>,
    tracking: TrackingConfig,
    params: GicpParams,
    alignment: AlignmentConfig,
    map_registration: MapRegistrationConfig,
}

impl JoinSearch {
    /// `root_from_segment` and its evidence when a guess places the keyframe so that it passes
    /// the check against `root_map`: the `relocalisation_candidates` archived keyframes most
    /// like it aligned by image features, then, when those gave nothing and it is due, the
    /// segment's map registered to the root's.
    fn run(
        &self,
        root_map: &mut VoxelMap,
        archive: &KeyframeArchive,
    ) -> Option<(Isometry3<f64>, JoinEvidence)> {
        let mut guesses: Vec<(Isometry3<f64>, JoinEvidence)> = Vec::new();
        if let Some(rgb) = &self.rgb {
            let aligned = archive.align(
                rgb,
                &self.depth,
                &self.intrinsics,
                self.tracking.relocalisation_candidates,
                &self.alignment,
            );
            guesses.extend(
                aligned
                    .into_iter()
                    .map(|g| (g, JoinEvidence::KeyframeAlignment)),
            );
        }
        if guesses.is_empty()
            && let Some(segment_points) = &self.segment_points
        {
            let root_points = root_map.sample_all(RELOCALISATION_MAP_POINTS);
            let registration = register_maps(segment_points, &root_points, &self.map_registration);
            tracing::debug!(
                accepted = registration.is_accepted(),
                verdict = ?registration.verdict,
                "relocalisation: map registration of the segment to the root"
            );
            if registration.is_accepted() {
                guesses.push((
                    registration.target_from_source * self.segment_from_camera,
                    JoinEvidence::MapRegistration,
                ));
            }
        }
        for (root_from_camera, evidence) in guesses {
            root_map.select_view(&ViewFrustum::new(
                &root_from_camera,
                &self.intrinsics,
                self.tracking.truncation_m,
            ));
            let recovery = Recovery {
                tracking: &self.tracking,
                fine: &self.params,
                map: root_map,
                frame: &self.cloud,
                depth: &self.depth,
                rgb: self.rgb.as_ref(),
                intrinsics: &self.intrinsics,
            };
            let candidate = recovery.wide(Guess::WidePrediction, &root_from_camera);
            tracing::debug!(?evidence, check = ?candidate.check, passes = candidate.passes(&self.tracking), "relocalisation candidate");
            if candidate.passes(&self.tracking) {
                let root_from_segment =
                    candidate.result.target_from_source * self.segment_from_camera.inverse();
                return Some((root_from_segment, evidence));
            }
        }
        None
    }
}

impl Odometry {
    /// After `max_consecutive_failures` lost frames: a new segment starts with this frame (see
    /// [`segments`]). The root map is kept aside for relocalisation; an unjoined segment that
    /// was being tracked is given up (its poses stay in its own frame), and a search still
    /// running for it is left to end unheard.
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
        self.pending_search = None;
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
            None => Arc::new(std::mem::replace(&mut self.map, fresh())),
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

    /// At a keyframe of the detached segment: searches for its place in the root (see
    /// [`segments`]) and joins it when found. A real-time frame starts the search on its own
    /// thread instead, unless one is running, and returns `None`; [`Self::collect_search`]
    /// joins what it finds.
    pub(super) fn relocalise(
        &mut self,
        input: &FrameInput<'_>,
        cloud: &PointCloud,
        segment_from_camera: &Isometry3<f64>,
    ) -> Option<SegmentJoin> {
        if input.real_time && self.pending_search.is_some() {
            return None;
        }
        let detached = self.detached.as_mut()?;
        detached.keyframes += 1;
        let map_due = self.tracking.relocalisation_map_every > 0
            && detached
                .keyframes
                .is_multiple_of(self.tracking.relocalisation_map_every);
        let segment = detached.segment;
        let search = JoinSearch {
            rgb: input.rgb.cloned(),
            depth: input.depth.clone(),
            intrinsics: *input.intrinsics,
            cloud: cloud.clone(),
            segment_from_camera: *segment_from_camera,
            segment_points: map_due.then(|| self.map.sample_all(RELOCALISATION_MAP_POINTS)),
            tracking: self.tracking.clone(),
            params: self.params.clone(),
            alignment: self.alignment.clone(),
            map_registration: self.map_registration.clone(),
        };
        if input.real_time {
            let root_map = Arc::clone(&detached.root_map);
            let archive = Arc::clone(&self.archive);
            let spawned = std::thread::Builder::new()
                .name("relocalisation".into())
                .spawn(move || {
                    // The root map stays with the tracker (corrections may move it meanwhile):
                    // the search selects views in a copy of its own.
                    let mut root_map = VoxelMap::clone(&root_map);
                    search.run(&mut root_map, &lock(&archive))
                });
            match spawned {
                Ok(handle) => self.pending_search = Some(PendingSearch { segment, handle }),
                Err(e) => tracing::warn!("relocalisation thread not started: {e}"),
            }
            return None;
        }
        let found = search.run(Arc::make_mut(&mut detached.root_map), &lock(&self.archive));
        found.map(|(root_from_segment, evidence)| self.join(root_from_segment, evidence))
    }

    /// The join a finished search thread found, applied: `None` while it runs, when it found
    /// nothing, or when its segment is no longer the detached one.
    pub(super) fn collect_search(&mut self) -> Option<SegmentJoin> {
        let pending = self
            .pending_search
            .take_if(|pending| pending.handle.is_finished())?;
        self.apply_search(pending)
    }

    /// Waits for a relocalisation search still running on its own thread (real-time frames)
    /// and applies the join it found, if any: at the end of a stream, so that a segment about to
    /// be recognised is not left out. The caller moves the segment's poses by the join.
    pub fn finish_search(&mut self) -> Option<SegmentJoin> {
        let pending = self.pending_search.take()?;
        self.apply_search(pending)
    }

    fn apply_search(&mut self, pending: PendingSearch) -> Option<SegmentJoin> {
        // A search that panicked found nothing; the tracker goes on.
        let found = pending.handle.join().ok().flatten();
        let detached = self.detached.as_ref()?;
        if detached.segment != pending.segment {
            return None;
        }
        let (root_from_segment, evidence) = found?;
        Some(self.join(root_from_segment, evidence))
    }

    /// Moves the detached segment's map and keyframes into the root and tracks on in it.
    pub(super) fn join(
        &mut self,
        root_from_segment: Isometry3<f64>,
        evidence: JoinEvidence,
    ) -> SegmentJoin {
        let detached = self.detached.take().expect("joining a detached segment");
        let root_map = Arc::unwrap_or_clone(detached.root_map);
        let mut segment_map = std::mem::replace(&mut self.map, root_map);
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
        lock(&self.archive).absorb(segment_archive);
        if let Some(trusted) = self.trusted.as_mut() {
            trusted.world_from_camera = root_from_segment * trusted.world_from_camera;
        }
        // A join found aside lands at any frame, not only at a keyframe that would renew it.
        if let Some(reference) = self.photometric_reference.as_mut() {
            reference.transform(&root_from_segment);
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
