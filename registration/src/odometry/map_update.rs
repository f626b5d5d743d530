//! What a placed frame leaves behind: keyframe points in the map, the frame-to-frame target, the
//! trusted frame and the keyframe archive the guesses use; and a segment's first frame.

use image::RgbImage;
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::covariance::Covariance;
use crate::gicp::MIN_POINTS_FOR_A_POSE;
use crate::kdtree::PointTree;
use crate::points::PointCloud;
use crate::voxel_map::{MapPoint, VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE, VoxelMap};

use super::prediction::ConstantVelocity;
use super::recovery::{Candidate, TrustedFrame};
use super::segments::ArchivedKeyframe;
use super::{FrameInput, Odometry, OdometryMode, StageTimings, TrackedFrame, TrackingOutcome};

impl Odometry {
    /// Keyframe insertion (frame-to-model), the frame-to-frame target, and what the guesses
    /// keep of trusted frames. Returns the trackable flags of a keyframe.
    pub(super) fn update_map(
        &mut self,
        frame: &PointTree,
        input: &FrameInput<'_>,
        chosen: &Option<Candidate>,
        outcome: &TrackingOutcome,
        world_from_camera: &Isometry3<f64>,
    ) -> Option<Vec<bool>> {
        let tracked = outcome.is_tracked();
        if tracked {
            self.previous_overlap = chosen.as_ref().map(|c| c.result.overlap_fraction);
            if let Some(rgb) = input.rgb {
                self.trusted = Some(trusted_frame(input, rgb, world_from_camera));
            }
        }
        let trackable = match self.mode {
            OdometryMode::FrameToFrame => {
                // A frame with too few points cannot serve as the next target; keep the last one.
                if frame.len() >= MIN_POINTS_FOR_A_POSE {
                    self.previous_frame = Some(self.frame_target(frame.cloud()));
                }
                None
            }
            OdometryMode::FrameToModel => {
                let overlap = chosen.as_ref().map_or(0.0, |c| c.result.overlap_fraction);
                (tracked && overlap < self.keyframes.min_overlap_fraction)
                    .then(|| self.add_keyframe(frame.cloud(), world_from_camera, false))
                    .filter(|added| added.contains(&true))
            }
        };
        if trackable.is_some() {
            self.stats.keyframes += 1;
            self.archive_keyframe(input, world_from_camera);
        }
        trackable
    }

    /// Keeps a keyframe's images for relocalisation (the root's archive, or the detached
    /// segment's).
    pub(super) fn archive_keyframe(
        &mut self,
        input: &FrameInput<'_>,
        world_from_camera: &Isometry3<f64>,
    ) {
        let Some(rgb) = input.rgb else {
            return;
        };
        let mut root_archive;
        let archive = if self.detached.is_some() {
            &mut self.segment_archive
        } else {
            root_archive = super::relocalisation::lock(&self.archive);
            &mut *root_archive
        };
        archive.offer(|| ArchivedKeyframe::of(trusted_frame(input, rgb, world_from_camera)));
    }

    pub(super) fn frame_target(&self, cloud: &PointCloud) -> VoxelMap {
        VoxelMap::from_cloud(
            cloud,
            VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE * self.tracking.max_correspondence_m,
        )
    }

    /// Starts tracking with `frame` at the identity of the current segment's frame.
    pub(super) fn initialise(&mut self, frame: PointTree, input: &FrameInput<'_>) -> TrackedFrame {
        let points = frame.len();
        let world_from_camera = Isometry3::identity();
        self.consecutive_failures = 0;
        self.velocity = ConstantVelocity::default();
        self.prior_doubtful = false;
        self.previous_overlap = None;
        self.world_from_previous = Some(world_from_camera);
        self.trusted = input
            .rgb
            .map(|rgb| trusted_frame(input, rgb, &world_from_camera));
        let trackable = match self.mode {
            OdometryMode::FrameToFrame => {
                self.previous_frame = Some(self.frame_target(frame.cloud()));
                None
            }
            OdometryMode::FrameToModel => {
                Some(self.add_keyframe(frame.cloud(), &world_from_camera, true))
                    .filter(|added| added.contains(&true))
            }
        };
        let keyframe = trackable.is_some();
        if keyframe {
            self.stats.keyframes += 1;
            self.archive_keyframe(input, &world_from_camera);
        }
        TrackedFrame {
            world_from_camera,
            placement: self.placement(),
            outcome: TrackingOutcome::Initialised,
            registration: None,
            check: None,
            join: None,
            points,
            keyframe,
            frame_points: frame.into_cloud(),
            trackable,
            timings: StageTimings::default(),
        }
    }

    /// Adds a keyframe's points (camera frame, with covariances) to the map at `world_from_camera`.
    /// Unless `all_points`, only points farther than the trackable-new distance from the current
    /// map are added. Returns, per point of `cloud`, whether it was added.
    pub(super) fn add_keyframe(
        &mut self,
        cloud: &PointCloud,
        world_from_camera: &Isometry3<f64>,
        all_points: bool,
    ) -> Vec<bool> {
        let rotation = world_from_camera.rotation.to_rotation_matrix().into_inner();
        let novelty_sq = self.keyframes.trackable_new_distance_sq_m2 as f32;
        let map = &self.map;
        let candidates: Vec<Option<(Point3<f32>, Covariance)>> = cloud
            .positions
            .par_iter()
            .zip(cloud.covariances.par_iter())
            .map(|(p, c)| {
                let world = (world_from_camera * p.cast::<f64>()).cast::<f32>();
                if !all_points && map.nearest_in_map(&world, novelty_sq).is_some() {
                    return None;
                }
                let covariance =
                    Covariance::from_matrix(&(rotation * c.to_matrix() * rotation.transpose()));
                Some((world, covariance))
            })
            .collect();
        let added = candidates.iter().map(Option::is_some).collect();
        for (position, covariance) in candidates.iter().flatten() {
            let point = MapPoint {
                id: self.next_point_id,
                position: *position,
                covariance: *covariance,
            };
            self.next_point_id += 1;
            // Positions are finite (transformed finite points), so insertion cannot be refused.
            let _ = self.map.insert(point);
        }
        added
    }
}

/// The frame of `input` (with its colour `rgb`) placed at `world_from_camera`, kept for image
/// alignment.
fn trusted_frame(
    input: &FrameInput<'_>,
    rgb: &RgbImage,
    world_from_camera: &Isometry3<f64>,
) -> TrustedFrame {
    TrustedFrame::new(
        rgb.clone(),
        input.depth.clone(),
        *input.intrinsics,
        *world_from_camera,
    )
}
