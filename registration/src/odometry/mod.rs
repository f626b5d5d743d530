//! Step 5 of the pipeline: the RGB-D odometry driver built from the pieces above. The agent and
//! the benchmark (`mac-ego3d bench tracking`) both run it (docs/method.md, One agent: Tracking).
//!
//! Per frame ([`Odometry::track`]):
//! 1. points from depth and their covariances;
//! 2. the ordinary path: G-ICP at the fine correspondence distance from the constant-velocity
//!    prediction (or the previous pose, [`prediction`]) against the map of keyframe points in the
//!    predicted view (frame-to-model) or the previous frame (frame-to-frame); frame-to-model, with
//!    colour, it minimises the photometric term against the previous placed frame with it
//!    ([`crate::photometric`]);
//! 3. the check ([`check`]): the map's points in view must agree with the frame's depth at the
//!    estimated pose; a refused pose, a sudden drop of the overlap with the map, or a doubtful
//!    prior (the previous frame recovered or lost) sends the frame to the wide-baseline guesses
//!    ([`recovery`]), and the best passing pose wins;
//! 4. failures: a frame no guess places is lost (its pose is the prediction, nothing of it joins
//!    the map); after `max_consecutive_failures` in a row a new segment starts, in a frame of
//!    its own, and is relocalised in the root when it can be ([`segments`]);
//! 5. keyframes (frame-to-model): when fewer than `keyframes.min_overlap_fraction` of the frame's
//!    points have a map point within sqrt(`keyframes.overlap_distance_sq_m2`), the frame is a
//!    tracking keyframe and its points farther than sqrt(`keyframes.trackable_new_distance_sq_m2`)
//!    from the map join it (the trackable-Gaussian rule of docs/method.md, One agent: Keyframes,
//!    with points for Gaussians).
//!
//! Frame-to-frame mode (a benchmark baseline) runs steps 1, 2 and 4 without segments.
//!
//! When the frames' points lie further apart than the correspondence distance (low resolution,
//! large stride), a frame with too few correspondences is registered again at a distance that
//! follows the spacing ([`spacing`]).

pub mod check;
mod map_update;
mod photometric;
mod prediction;
pub mod rationing;
pub mod recovery;
mod relocalisation;
pub mod segments;
pub mod spacing;
mod types;

use std::sync::{Arc, Mutex};
use std::time::Instant;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use nalgebra::Isometry3;

use crate::alignment::AlignmentConfig;
use crate::config::{KeyframeConfig, PhotometricReferenceFrame, TrackingConfig};
use crate::gicp::{GicpParams, JointTerm, MIN_POINTS_FOR_A_POSE, RegistrationFailure};
use crate::kdtree::PointTree;
use crate::map_registration::MapRegistrationConfig;
use crate::photometric::{PhotometricFrame, PhotometricReference, PhotometricTerm};
use crate::points::{PointCloud, points_from_depth};
use crate::voxel_map::{MapPointId, ViewFrustum, VoxelMap};
pub use check::{Divergence, FrameCheck};
use prediction::{ConstantVelocity, InitialGuess, register_from_prediction};
use rationing::RecoveryRation;
pub use recovery::Guess;
use recovery::{Candidate, FeatureGuess, Recovery, TrustedFrame};
use relocalisation::{PendingSearch, SharedArchive};
use segments::KeyframeArchive;
pub use segments::{JoinEvidence, SegmentId, SegmentJoin};
pub use types::{
    FrameInput, OdometryMode, OdometryStats, Placement, StageTimings, TrackedFrame,
    TrackingFailure, TrackingOutcome,
};

fn elapsed_ms(since: &Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

/// Map points the map registration of a segment against the root samples from each (its cost
/// bound; the registration downsamples further to its own `max_points`).
const RELOCALISATION_MAP_POINTS: usize = 20_000;

/// The segment being tracked while it is not joined to the root, and the root kept aside.
struct Detached {
    segment: SegmentId,
    /// Shared with a search thread while one runs (a correction then moves a copy).
    root_map: Arc<VoxelMap>,
    /// Keyframes the segment made, for the map registration's every-few-keyframes schedule.
    keyframes: usize,
}

/// Frame-to-frame or frame-to-model RGB-D odometry. See the module documentation.
pub struct Odometry {
    mode: OdometryMode,
    tracking: TrackingConfig,
    keyframes: KeyframeConfig,
    params: GicpParams,
    alignment: AlignmentConfig,
    map_registration: MapRegistrationConfig,
    /// The map tracked against: the root's, or the detached segment's.
    map: VoxelMap,
    /// Frame-to-frame target: the previous frame in its own camera frame, in a voxel map (whose
    /// searches are bounded by the correspondence distance, unlike the kd-tree's).
    previous_frame: Option<VoxelMap>,
    world_from_previous: Option<Isometry3<f64>>,
    velocity: ConstantVelocity,
    /// Timestamp of the previous frame.
    previous_timestamp_s: Option<f64>,
    /// Depth timestamp of the previous frame.
    previous_depth_timestamp_s: Option<f64>,
    /// Seconds between the previous frame's depth image and the current one's, when both are
    /// stamped.
    depth_since_previous_s: Option<f64>,
    /// Overlap fraction of the previous placed frame (the drop trigger of the recovery).
    previous_overlap: Option<f64>,
    /// The previous frame needed a wide-baseline guess or was lost: the prior is doubtful.
    prior_doubtful: bool,
    consecutive_failures: usize,
    next_point_id: u64,
    stats: OdometryStats,
    /// Where the previous frame's ordinary G-ICP started: this frame's tries it first.
    last_initial_guess: InitialGuess,
    trusted: Option<TrustedFrame>,
    /// The time the expensive recovery work may take at sensor pace ([`rationing`]).
    ration: RecoveryRation,
    archive: SharedArchive,
    /// A relocalisation search running on its own thread (real-time frames only).
    pending_search: Option<PendingSearch>,
    /// The segment's own archive while detached (joined into `archive` with it).
    segment_archive: KeyframeArchive,
    detached: Option<Detached>,
    next_segment: SegmentId,
    /// Whether the point spacing was measured yet (on the first frame).
    spacing_checked: bool,
    /// The ordinary path's parameters at the sparse-points distance ([`spacing`]), when the
    /// frames' points lie further apart than the correspondence distance.
    sparse_params: Option<GicpParams>,
    /// The previous placed frame's textured points for the photometric term, in the frame of
    /// the map tracked against.
    photometric_reference: Option<PhotometricReference>,
}

impl Odometry {
    /// An odometry with an empty map, waiting for its first frame (which it places at the
    /// identity). The image alignment of recovery and relocalisation uses the tracking's pixel
    /// stride and truncation and otherwise its defaults; the map registration, its defaults.
    pub fn new(mode: OdometryMode, tracking: &TrackingConfig, keyframes: &KeyframeConfig) -> Self {
        Self {
            mode,
            tracking: tracking.clone(),
            keyframes: keyframes.clone(),
            params: GicpParams::tracking(tracking, keyframes),
            alignment: AlignmentConfig {
                pixel_stride: tracking.pixel_stride,
                truncation_m: tracking.truncation_m,
                ..AlignmentConfig::default()
            },
            map_registration: MapRegistrationConfig::default(),
            map: VoxelMap::for_correspondence_distance(tracking.max_correspondence_m),
            previous_frame: None,
            world_from_previous: None,
            velocity: ConstantVelocity::default(),
            previous_timestamp_s: None,
            previous_depth_timestamp_s: None,
            depth_since_previous_s: None,
            previous_overlap: None,
            prior_doubtful: false,
            consecutive_failures: 0,
            next_point_id: 0,
            stats: OdometryStats::default(),
            last_initial_guess: InitialGuess::Prediction,
            trusted: None,
            ration: RecoveryRation::new(tracking.recovery_time_share, tracking.recovery_burst_ms),
            archive: Arc::new(Mutex::new(KeyframeArchive::new(
                tracking.relocalisation_keyframes,
            ))),
            pending_search: None,
            segment_archive: KeyframeArchive::new(tracking.relocalisation_keyframes),
            detached: None,
            next_segment: 1,
            spacing_checked: false,
            sparse_params: None,
            photometric_reference: None,
        }
    }

    /// What each frame is aligned against.
    pub fn mode(&self) -> OdometryMode {
        self.mode
    }

    /// The map tracked against (the detached segment's while one is tracked; empty in
    /// frame-to-frame mode).
    pub fn map(&self) -> &VoxelMap {
        &self.map
    }

    /// Counters over the frames tracked so far.
    pub fn stats(&self) -> &OdometryStats {
        &self.stats
    }

    /// Where poses are reported now.
    pub fn placement(&self) -> Placement {
        match &self.detached {
            Some(detached) => Placement::Unjoined(detached.segment),
            None => Placement::Root,
        }
    }

    /// Id the next map point will get: map points are numbered in the order keyframes add
    /// them, so a caller that notes this before and after a keyframe knows which points it made.
    pub fn next_point_id(&self) -> MapPointId {
        self.next_point_id
    }

    /// Moves the root map non-rigidly (a consensus correction, docs/method.md, The consensus:
    /// pose graph): each map point by `transform_of(its id)` (unchanged when `None`), and the
    /// last pose by `current`, the correction at the current frame, so that the next prediction
    /// lands in the moved map. While a segment is detached its own map and poses are in its own
    /// frame, which corrections of the root do not concern: only the kept root map moves. The
    /// constant-velocity motion is relative and stays. Returns how many points moved.
    pub fn apply_correction(
        &mut self,
        transform_of: impl FnMut(MapPointId) -> Option<Isometry3<f64>>,
        current: &Isometry3<f64>,
    ) -> usize {
        if let Some(detached) = self.detached.as_mut() {
            return Arc::make_mut(&mut detached.root_map).transform_points(transform_of);
        }
        if let Some(world_from_previous) = self.world_from_previous.as_mut() {
            *world_from_previous = current * *world_from_previous;
            world_from_previous.rotation.renormalize();
        }
        if let Some(reference) = self.photometric_reference.as_mut() {
            reference.transform(current);
        }
        self.map.transform_points(transform_of)
    }

    /// Points of a depth image with covariances, indexed for neighbour search.
    pub fn prepare_frame(&self, depth: &DepthImage, intrinsics: &Intrinsics) -> PointTree {
        let cloud = points_from_depth(
            depth,
            intrinsics,
            self.tracking.pixel_stride,
            self.tracking.truncation_m,
        );
        PointTree::with_covariances(
            cloud,
            self.tracking.covariance_neighbours,
            self.tracking.covariance_epsilon,
        )
        // Back-projected points are finite whenever the intrinsics are (the readers validate
        // them), so an error here means corrupted intrinsics: track nothing rather than garbage.
        .unwrap_or_else(|error| {
            tracing::warn!(%error, "frame points cannot be indexed; frame has no usable points");
            PointTree::new(Vec::new()).expect("an empty cloud always indexes")
        })
    }

    /// Prepares the sparse-points retry ([`spacing`]) when `cloud`'s points lie further apart
    /// than the correspondence distance; once, on the first frame with points.
    fn fit_distances_to_spacing(&mut self, cloud: &PointCloud, intrinsics: &Intrinsics) {
        self.spacing_checked = true;
        let Some(spacing_m) =
            spacing::median_point_spacing_m(cloud, intrinsics, self.tracking.pixel_stride)
        else {
            return;
        };
        let fine_m = self.tracking.max_correspondence_m;
        let sparse_m = spacing::sparse_correspondence_m(spacing_m, fine_m);
        if sparse_m > fine_m {
            tracing::info!(
                spacing_m,
                fine_m,
                sparse_m,
                "frame points lie further apart than the correspondence distance: frames with too \
                 few correspondences are registered again at the sparse distance"
            );
            self.sparse_params = Some(self.params.with_max_correspondence(sparse_m));
        }
    }

    /// Tracks one frame and updates the map. Never panics on bad depth: a frame without enough
    /// valid points is a counted failure whose pose is the prediction.
    pub fn track(&mut self, input: FrameInput<'_>) -> TrackedFrame {
        let clock = Instant::now();
        let frame = self.prepare_frame(input.depth, input.intrinsics);
        let photometric = self.photometric_frame(&input);
        let mut timings = StageTimings {
            points_ms: elapsed_ms(&clock),
            ..StageTimings::default()
        };
        self.stats.frames += 1;
        let since_previous_s = self
            .previous_timestamp_s
            .replace(input.timestamp_s)
            .map(|previous| input.timestamp_s - previous)
            .filter(|span| span.is_finite() && *span > 0.0);
        // The poses are the depth images': the colour's motion is scaled by the time between
        // them (a frame's stamp is its colour image's; colour and depth may be up to a frame
        // interval apart, differently in each frame).
        let depth_timestamp_s = input.timestamp_s - input.colour_offset_s;
        self.depth_since_previous_s = self
            .previous_depth_timestamp_s
            .replace(depth_timestamp_s)
            .map(|previous| depth_timestamp_s - previous)
            .filter(|span| span.is_finite() && *span > 0.0);
        if !self.spacing_checked && !frame.is_empty() {
            self.fit_distances_to_spacing(frame.cloud(), input.intrinsics);
        }
        let Some(world_from_previous) = self.world_from_previous else {
            let tracked = self.initialise(frame, &input);
            self.note_photometric_reference(photometric, &input, &tracked.world_from_camera);
            return tracked;
        };
        let velocity = self.velocity.over(since_previous_s);
        let predicted = if self.tracking.constant_velocity {
            world_from_previous * velocity
        } else {
            world_from_previous
        };
        let clock = Instant::now();
        let chosen = match self.mode {
            OdometryMode::FrameToFrame => {
                self.frame_to_frame(frame.cloud(), &velocity, &world_from_previous)
            }
            OdometryMode::FrameToModel => self.frame_to_model(
                frame.cloud(),
                &input,
                photometric.as_ref(),
                &velocity,
                &world_from_previous,
                &mut timings,
            ),
        };
        timings.registration_ms = elapsed_ms(&clock) - timings.recovery_ms;
        self.stats.searches_rationed = self.ration.refused();
        let (world_from_camera, outcome) = self.judge(&chosen, predicted, frame.len());
        if let TrackingOutcome::Lost(_) = outcome
            && self.mode == OdometryMode::FrameToModel
            && self.consecutive_failures >= self.tracking.max_consecutive_failures
            && frame.len() >= MIN_POINTS_FOR_A_POSE
        {
            let tracked = self.start_segment(frame, &input, chosen, timings);
            self.note_photometric_reference(photometric, &input, &tracked.world_from_camera);
            return tracked;
        }
        self.update_motion(
            &outcome,
            &predicted,
            frame.cloud(),
            &world_from_previous,
            &world_from_camera,
            since_previous_s,
        );
        let clock = Instant::now();
        let trackable = self.update_map(&frame, &input, &chosen, &outcome, &world_from_camera);
        let keyframe = trackable.is_some();
        let mut world_from_camera = world_from_camera;
        let join = self.collect_search().or_else(|| {
            (keyframe && self.detached.is_some())
                .then(|| self.relocalise(&input, frame.cloud(), &world_from_camera))
                .flatten()
        });
        if let Some(join) = &join {
            world_from_camera = join.root_from_segment * world_from_camera;
        }
        self.world_from_previous = Some(world_from_camera);
        let new_reference = match self.tracking.photometric.reference {
            PhotometricReferenceFrame::PreviousFrame => outcome.is_tracked(),
            PhotometricReferenceFrame::Keyframe => keyframe,
        };
        if new_reference || (outcome.is_tracked() && self.photometric_reference.is_none()) {
            self.note_photometric_reference(photometric, &input, &world_from_camera);
        }
        timings.map_update_ms = elapsed_ms(&clock);
        tracing::debug!(
            frame = self.stats.frames - 1,
            outcome = ?outcome,
            agreement = chosen.as_ref().map_or(f64::NAN, |c| c.check.agreement),
            decisive = chosen.as_ref().map_or(0, |c| c.check.decisive()),
            overlap = chosen.as_ref().map_or(f64::NAN, |c| c.check.overlap_fraction),
            "frame tracked"
        );
        TrackedFrame {
            world_from_camera,
            placement: self.placement(),
            outcome,
            check: chosen.as_ref().map(|c| c.check),
            registration: chosen.map(|c| c.result),
            join,
            points: frame.len(),
            keyframe,
            frame_points: frame.into_cloud(),
            trackable,
            timings,
        }
    }

    /// The ordinary path against the previous frame (no check: the benchmark baseline).
    fn frame_to_frame(
        &mut self,
        cloud: &PointCloud,
        velocity: &Isometry3<f64>,
        world_from_previous: &Isometry3<f64>,
    ) -> Option<Candidate> {
        let previous = self
            .previous_frame
            .as_ref()
            .expect("set together with world_from_previous");
        let (mut result, guess) = register_from_prediction(
            cloud,
            previous,
            velocity,
            &Isometry3::identity(),
            &self.params,
            self.tracking.constant_velocity,
            self.last_initial_guess,
            None,
        );
        self.note_initial_guess(guess);
        result.target_from_source = world_from_previous * result.target_from_source;
        let check = FrameCheck {
            agreeing: 0,
            violating: 0,
            occluded: 0,
            agreement: 1.0,
            inlier_fraction: result.inlier_fraction(),
            overlap_fraction: result.overlap_fraction,
        };
        Some(Candidate {
            guess: Guess::Ordinary,
            result,
            check,
        })
    }

    /// The ordinary path, its check, and the wide-baseline guesses when they are needed.
    fn frame_to_model(
        &mut self,
        cloud: &PointCloud,
        input: &FrameInput<'_>,
        photometric: Option<&PhotometricFrame>,
        velocity: &Isometry3<f64>,
        world_from_previous: &Isometry3<f64>,
        timings: &mut StageTimings,
    ) -> Option<Candidate> {
        let prediction = world_from_previous * velocity;
        // The view is selected at the constant-velocity prediction: with a frustum, the small
        // difference to the previous pose only matters at the image border.
        self.select_view(&prediction, input.intrinsics);
        let mut candidates = Vec::new();
        // Without enough points no guess can place the frame: the ordinary path says why.
        if !self.prior_doubtful || cloud.len() < MIN_POINTS_FOR_A_POSE {
            let ordinary = self.ordinary(cloud, input, photometric, velocity, world_from_previous);
            let passes = ordinary.passes(&self.tracking);
            let overlap_dropped = self.overlap_dropped(&ordinary);
            let converged = ordinary.result.converged;
            if !passes && ordinary.has_pose() {
                self.stats.divergences += 1;
            }
            if (passes && !overlap_dropped && converged) || cloud.len() < MIN_POINTS_FOR_A_POSE {
                return Some(ordinary);
            }
            tracing::debug!(
                frame = self.stats.frames - 1,
                passes,
                overlap_dropped,
                converged,
                check = ?ordinary.check,
                "ordinary path doubtful: trying wide-baseline guesses"
            );
            candidates.push(ordinary);
        }
        let clock = Instant::now();
        // A guess that passes the check but overlaps the map far less than the previous frame
        // did is not enough to stop looking: a wide G-ICP can slide along a wall into a pose
        // that the little depth it still explains agrees with (fr1/rpy after a stall: 22 %
        // overlap, 0.92 agreement, 0.7 m off). The other guesses are tried, and the best by
        // inliers wins.
        let passed = |candidates: &[Candidate]| {
            candidates
                .iter()
                .any(|c| c.passes(&self.tracking) && !self.overlap_dropped(c))
        };
        let recovery = self.recovery(cloud, input);
        candidates.push(recovery.wide(Guess::WidePrediction, &prediction));
        tracing::debug!(ms = elapsed_ms(&clock), "wide guess from the prediction");
        if !self.tracking.constant_velocity || !passed(&candidates) {
            candidates.push(recovery.wide(Guess::WidePrevious, world_from_previous));
            tracing::debug!(ms = elapsed_ms(&clock), "wide guess from the previous pose");
        }
        let mut texture_failed = true;
        if !passed(&candidates)
            && let Some(trusted) = &self.trusted
            && self.may_search(input.real_time)
        {
            let started = Instant::now();
            let guess = recovery.features(trusted, &self.alignment);
            self.pay_search(input.real_time, &started);
            if let FeatureGuess::Found(candidate) = guess {
                texture_failed = false;
                candidates.push(candidate);
            }
        }
        // Geometry alone only where the images could not place the frame (no texture, no
        // colour), and once per streak of lost frames: it costs up to a second, and the frames
        // after a loss are the segment logic's.
        if self.tracking.recovery_geometry
            && texture_failed
            && self.consecutive_failures == 0
            && !passed(&candidates)
            && self.may_search(input.real_time)
        {
            let started = Instant::now();
            // The map around the last trusted pose (the prediction may be far off by now), then
            // the view at the prediction again for the check.
            let anchor = self
                .trusted
                .as_ref()
                .map_or(*world_from_previous, |t| t.world_from_camera);
            self.select_view(&anchor, input.intrinsics);
            let around = self.map.sample_view(RELOCALISATION_MAP_POINTS);
            self.select_view(&prediction, input.intrinsics);
            let recovery = self.recovery(cloud, input);
            if let Some(candidate) = recovery.geometry(&around, &self.map_registration) {
                candidates.push(candidate);
            }
            self.pay_search(input.real_time, &started);
        }
        timings.recovery_ms = elapsed_ms(&clock);
        tracing::debug!(ms = timings.recovery_ms, "recovery guesses done");
        recovery::choose(candidates, &self.tracking)
    }

    /// Whether an expensive guess (image features, geometry) may start: always, but for a
    /// real-time frame when the ration is spent ([`rationing`]).
    fn may_search(&self, real_time: bool) -> bool {
        !real_time || self.ration.allows(Instant::now())
    }

    /// Pays the ration for a guess of a real-time frame that started at `started`.
    fn pay_search(&self, real_time: bool, started: &Instant) {
        if real_time {
            self.ration.pay(elapsed_ms(started), Instant::now());
        }
    }

    /// Whether `candidate` overlaps the map by `recovery_overlap_drop` less (relatively) than
    /// the previous placed frame did.
    fn overlap_dropped(&self, candidate: &Candidate) -> bool {
        self.previous_overlap.is_some_and(|previous| {
            candidate.check.overlap_fraction
                < (1.0 - self.tracking.recovery_overlap_drop) * previous
        })
    }

    /// The ordinary path (see [`prediction`]), with the photometric term when there are images
    /// for it, and its check.
    fn ordinary(
        &mut self,
        cloud: &PointCloud,
        input: &FrameInput<'_>,
        photometric: Option<&PhotometricFrame>,
        velocity: &Isometry3<f64>,
        world_from_previous: &Isometry3<f64>,
    ) -> Candidate {
        let mut term =
            photometric
                .zip(self.photometric_reference.as_ref())
                .map(|(current, reference)| {
                    let term = PhotometricTerm::new(
                        reference,
                        current,
                        input.depth,
                        &self.tracking.photometric,
                    );
                    match self.colour_motion(input, world_from_previous) {
                        Some(motion) => term.with_colour_motion(motion),
                        None => term,
                    }
                });
        let register = |params: &GicpParams, term: Option<&mut dyn JointTerm>| {
            register_from_prediction(
                cloud,
                &self.map,
                velocity,
                world_from_previous,
                params,
                self.tracking.constant_velocity,
                self.last_initial_guess,
                term,
            )
        };
        let (mut result, mut initial) =
            register(&self.params, term.as_mut().map(|t| t as &mut dyn JointTerm));
        if let Some(sparse) = &self.sparse_params
            && matches!(
                result.failure,
                Some(RegistrationFailure::TooFewCorrespondences { .. })
            )
        {
            let (retry, retry_initial) = register(sparse, None);
            if retry.is_success() {
                (result, initial) = (retry, retry_initial);
            }
        }
        self.note_initial_guess(initial);
        let check = FrameCheck::measure(
            &self.map,
            &result,
            input.depth,
            input.intrinsics,
            &self.tracking,
        );
        Candidate {
            guess: Guess::Ordinary,
            result,
            check,
        }
    }

    fn recovery<'a>(&'a self, cloud: &'a PointCloud, input: &FrameInput<'a>) -> Recovery<'a> {
        Recovery {
            tracking: &self.tracking,
            fine: &self.params,
            map: &self.map,
            frame: cloud,
            depth: input.depth,
            rgb: input.rgb,
            intrinsics: input.intrinsics,
        }
    }

    fn select_view(&mut self, world_from_camera: &Isometry3<f64>, intrinsics: &Intrinsics) {
        self.map.select_view(&ViewFrustum::new(
            world_from_camera,
            intrinsics,
            self.tracking.truncation_m,
        ));
    }

    fn note_initial_guess(&mut self, guess: InitialGuess) {
        self.stats.still_starts += usize::from(guess == InitialGuess::Still);
        self.last_initial_guess = guess;
    }

    /// The pose and outcome of the chosen candidate, counting failures.
    fn judge(
        &mut self,
        chosen: &Option<Candidate>,
        predicted: Isometry3<f64>,
        points: usize,
    ) -> (Isometry3<f64>, TrackingOutcome) {
        let frame = self.stats.frames - 1;
        let Some(c) = chosen else {
            let failure = RegistrationFailure::TooFewSourcePoints {
                found: points,
                required: MIN_POINTS_FOR_A_POSE,
            };
            return self.lose(
                frame,
                TrackingFailure::Registration(failure),
                predicted,
                points,
            );
        };
        if let Some(failure) = c.result.failure.as_ref().filter(|f| !f.pose_is_usable()) {
            let failure = TrackingFailure::Registration(failure.clone());
            return self.lose(frame, failure, predicted, points);
        }
        // Frame-to-frame mode has no map to check against.
        if self.mode == OdometryMode::FrameToModel
            && let Err(divergence) = c.check.verdict(&self.tracking)
        {
            return self.lose(
                frame,
                TrackingFailure::Diverged(divergence),
                predicted,
                points,
            );
        }
        let outcome = match (c.guess, c.result.converged) {
            (Guess::Ordinary, true) => TrackingOutcome::Tracked,
            (Guess::Ordinary, false) => {
                self.stats.not_converged += 1;
                TrackingOutcome::TrackedNotConverged
            }
            (guess, _) => {
                self.stats.recoveries += 1;
                tracing::debug!(frame, ?guess, check = ?c.check, "recovered");
                TrackingOutcome::Recovered(guess)
            }
        };
        let mut pose = c.result.target_from_source;
        // Keep the rotation exactly unit: nalgebra inverts a unit quaternion by conjugation, so a
        // norm error in the pose doubles through `previous.inverse() * current` and the
        // constant-velocity prediction every frame (1.0035 after 150 frames before this).
        pose.rotation.renormalize();
        (pose, outcome)
    }

    fn lose(
        &mut self,
        frame: usize,
        failure: TrackingFailure,
        predicted: Isometry3<f64>,
        points: usize,
    ) -> (Isometry3<f64>, TrackingOutcome) {
        self.stats.failures += 1;
        self.consecutive_failures += 1;
        tracing::warn!(
            frame,
            %failure,
            points,
            consecutive = self.consecutive_failures,
            "tracking lost; the frame keeps the constant-velocity prediction and adds nothing to the map"
        );
        (predicted, TrackingOutcome::Lost(failure))
    }

    /// The constant-velocity motion after a placed frame, and whether the next frame's prior
    /// is doubtful: after a lost frame, or a recovered one whose pose lies farther from the
    /// prediction than the ordinary path can reach (points at the frame's mean depth moved by
    /// more than twice the correspondence distance).
    fn update_motion(
        &mut self,
        outcome: &TrackingOutcome,
        predicted: &Isometry3<f64>,
        frame: &PointCloud,
        world_from_previous: &Isometry3<f64>,
        world_from_camera: &Isometry3<f64>,
        since_previous_s: Option<f64>,
    ) {
        self.prior_doubtful = match outcome {
            TrackingOutcome::Lost(_) => true,
            TrackingOutcome::Recovered(_) => {
                let mean_depth = if frame.is_empty() {
                    0.0
                } else {
                    frame.positions.iter().map(|p| f64::from(p.z)).sum::<f64>() / frame.len() as f64
                };
                let offset = predicted.inverse() * world_from_camera;
                let moved = offset.translation.vector.norm() + offset.rotation.angle() * mean_depth;
                moved > 2.0 * self.tracking.max_correspondence_m
            }
            _ => false,
        };
        if outcome.is_tracked() {
            self.consecutive_failures = 0;
            let mut motion = world_from_previous.inverse() * world_from_camera;
            motion.rotation.renormalize();
            self.velocity = ConstantVelocity {
                motion,
                span_s: since_previous_s,
            };
        }
    }
}

#[cfg(test)]
mod tests;
