//! Wide-baseline guesses (docs/method.md, One agent: Tracking, "Recovery"): where to start G-ICP
//! when the small-motion prior is doubtful, and how to choose among the answers.
//!
//! The frame-to-model G-ICP matches each point to the nearest map point within 2 cm, so it only
//! converges from a guess within a few centimetres (and a degree or two) of the truth. When the
//! check (crate::odometry::check) refuses its pose, or its overlap with the map drops suddenly,
//! the frame is tried again from guesses that need no small motion, cheapest first:
//! 1. coarse-to-fine G-ICP from the constant-velocity prediction and from the previous pose:
//!    correspondence distances `recovery_distances_m` (20, 10, 5 cm) before the fine one, each
//!    stage on every k-th point of the frame (k = stage distance / fine distance: a coarse
//!    stage's matches are coarse anyway, and the search around each point grows with the
//!    distance, so fewer points keep each stage about as cheap as the fine one);
//! 2. image features: FAST + BRIEF keypoints of the frame and of the last trusted frame, lifted
//!    to 3-D with depth and fitted by RANSAC (the keyframe alignment of
//!    registration/src/alignment), the relative pose chained onto the trusted frame's pose;
//! 3. geometry alone, for scenes without texture: the frame's points registered to the map's
//!    points around the last trusted pose by FPFH features and RANSAC (the map registration of
//!    registration/src/map_registration).
//!
//! Every guess ends with the fine G-ICP against the map and is judged by the same check; the
//! best passing one (most of the frame on the map, then the depth agreement) wins, the result of
//! the ordinary path included. A stage is only run when the cheaper ones found no passing pose.

use std::borrow::Cow;
use std::sync::OnceLock;

use geometry::camera::Intrinsics;
use geometry::depth::DepthImage;
use image::RgbImage;
use nalgebra::Isometry3;
use serde::Serialize;

use crate::alignment::{AlignmentConfig, AlignmentInput, PreparedView};
use crate::config::TrackingConfig;
use crate::gicp::{GicpParams, RegistrationResult, register};
use crate::map_registration::{MapRegistrationConfig, register_maps};
use crate::points::PointCloud;
use crate::voxel_map::VoxelMap;

use super::check::FrameCheck;

/// Where the G-ICP of a frame's final pose started.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Guess {
    /// The ordinary path: fine G-ICP from the constant-velocity prediction or the previous pose.
    Ordinary,
    /// Coarse-to-fine G-ICP from the constant-velocity prediction.
    WidePrediction,
    /// Coarse-to-fine G-ICP from the previous pose.
    WidePrevious,
    /// Image features against the last trusted frame.
    ImageFeatures,
    /// FPFH registration of the frame's points to the map.
    MapGeometry,
}

/// What the image features gave.
pub enum FeatureGuess {
    /// No colour, or the images did not align (too little texture or overlap): the geometry
    /// guess is worth its cost.
    Unavailable,
    /// A pose, refined and checked.
    Found(Candidate),
}

/// One candidate pose of a frame: the G-ICP result and its check.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// Where the final G-ICP started.
    pub guess: Guess,
    /// The final G-ICP run (`target_from_source` is `world_from_camera`).
    pub result: RegistrationResult,
    /// The depth check of the result's pose against the map.
    pub check: FrameCheck,
}

impl Candidate {
    /// G-ICP gave a pose (converged, or out of iterations while still improving).
    pub fn has_pose(&self) -> bool {
        self.result
            .failure
            .as_ref()
            .is_none_or(|failure| failure.pose_is_usable())
    }

    /// G-ICP gave a pose and the check accepted it.
    pub fn passes(&self, tracking: &TrackingConfig) -> bool {
        self.has_pose() && self.check.verdict(tracking).is_ok()
    }
}

/// A frame whose pose was trusted, kept for image alignment: the last one, for the feature
/// guess, and the keyframes archived for relocalisation (super::segments).
///
/// The last one stays the same through a streak of lost frames, each of which may try the
/// feature guess against it, and an archived keyframe may be aligned with many frames: its
/// features and cloud are prepared on the first alignment and kept.
pub struct TrustedFrame {
    /// Its colour image.
    pub rgb: RgbImage,
    /// Its depth image (metres).
    pub depth: DepthImage,
    /// Its camera.
    pub intrinsics: Intrinsics,
    /// Its pose, in the frame of the map tracked against (moved into the root when a segment
    /// is joined).
    pub world_from_camera: Isometry3<f64>,
    /// Its features and cloud, once a feature guess needed them.
    prepared: OnceLock<PreparedView>,
}

impl TrustedFrame {
    /// A frame placed at `world_from_camera`, nothing prepared yet.
    pub fn new(
        rgb: RgbImage,
        depth: DepthImage,
        intrinsics: Intrinsics,
        world_from_camera: Isometry3<f64>,
    ) -> Self {
        Self {
            rgb,
            depth,
            intrinsics,
            world_from_camera,
            prepared: OnceLock::new(),
        }
    }

    /// Its features and cloud (prepared with `config` on the first call).
    pub fn prepared(&self, config: &AlignmentConfig) -> &PreparedView {
        self.prepared
            .get_or_init(|| PreparedView::new(&self.rgb, &self.depth, &self.intrinsics, config))
    }

    /// Whether its features and cloud are prepared already.
    fn is_prepared(&self) -> bool {
        self.prepared.get().is_some()
    }
}

/// What the guesses of one frame share.
pub struct Recovery<'a> {
    /// Recovery distances and iterations, and the check's thresholds.
    pub tracking: &'a TrackingConfig,
    /// The fine G-ICP every guess ends with (the tracking parameters).
    pub fine: &'a GicpParams,
    /// The map tracked against (world frame).
    pub map: &'a VoxelMap,
    /// The frame's points in its camera frame, with covariances.
    pub frame: &'a PointCloud,
    /// The frame's depth image (metres), for the check and the feature guess.
    pub depth: &'a DepthImage,
    /// The frame's colour image; without it the feature guess is unavailable.
    pub rgb: Option<&'a RgbImage>,
    /// The frame's camera.
    pub intrinsics: &'a Intrinsics,
}

impl Recovery<'_> {
    /// Fine G-ICP from `start` and its check.
    pub fn fine(&self, guess: Guess, start: &Isometry3<f64>) -> Candidate {
        let result = register(self.frame, self.map, start, self.fine);
        self.judge(guess, result)
    }

    /// Coarse-to-fine G-ICP from `start` (see the module documentation) and its check.
    pub fn wide(&self, guess: Guess, start: &Isometry3<f64>) -> Candidate {
        let mut pose = *start;
        let mut iterations = 0;
        // Stages no coarser than the fine distance (widened for sparse points, see
        // super::spacing) would repeat the fine stage.
        let coarse = self
            .tracking
            .recovery_distances_m
            .iter()
            .filter(|&&distance| distance > self.fine.max_correspondence_m);
        for &distance in coarse {
            let step = (distance / self.fine.max_correspondence_m).round().max(1.0) as usize;
            let sample = every_nth(self.frame, step);
            let scale = step as f64;
            let params = GicpParams {
                max_correspondence_m: distance,
                max_iterations: self.tracking.recovery_max_iterations,
                rotation_epsilon_rad: self.fine.rotation_epsilon_rad * scale,
                translation_epsilon_m: self.fine.translation_epsilon_m * scale,
                ..self.fine.clone()
            };
            let stage = register(&sample, self.map, &pose, &params);
            iterations += stage.iterations;
            if stage
                .failure
                .as_ref()
                .is_some_and(|failure| !failure.pose_is_usable())
            {
                let mut failed = stage;
                failed.iterations = iterations;
                return self.judge(guess, failed);
            }
            pose = stage.target_from_source;
        }
        let mut result = register(self.frame, self.map, &pose, self.fine);
        result.iterations += iterations;
        self.judge(guess, result)
    }

    /// The feature guess against `trusted`, refined by coarse-to-fine G-ICP.
    pub fn features(&self, trusted: &TrustedFrame, config: &AlignmentConfig) -> FeatureGuess {
        let Some(rgb) = self.rgb else {
            return FeatureGuess::Unavailable;
        };
        let prepare_current = || PreparedView::new(rgb, self.depth, self.intrinsics, config);
        let (current, previous) = if trusted.is_prepared() {
            (prepare_current(), trusted.prepared(config))
        } else {
            rayon::join(prepare_current, || trusted.prepared(config))
        };
        let alignment = crate::alignment::align(
            AlignmentInput {
                prepared: &current,
                depth: self.depth,
                intrinsics: self.intrinsics,
            },
            AlignmentInput {
                prepared: previous,
                depth: &trusted.depth,
                intrinsics: &trusted.intrinsics,
            },
            config,
        );
        if !alignment.is_accepted() {
            tracing::debug!(verdict = ?alignment.verdict, "feature guess refused");
            return FeatureGuess::Unavailable;
        }
        let start = trusted.world_from_camera * alignment.target_camera_from_source_camera;
        FeatureGuess::Found(self.wide(Guess::ImageFeatures, &start))
    }

    /// The geometry guess: the frame's points registered to `map_points` (world frame) without
    /// an initial guess, refined by coarse-to-fine G-ICP.
    pub fn geometry(
        &self,
        map_points: &[nalgebra::Point3<f32>],
        config: &MapRegistrationConfig,
    ) -> Option<Candidate> {
        let registration = register_maps(&self.frame.positions, map_points, config);
        if !registration.is_accepted() {
            tracing::debug!(verdict = ?registration.verdict, "geometry guess refused");
            return None;
        }
        Some(self.wide(Guess::MapGeometry, &registration.target_from_source))
    }

    fn judge(&self, guess: Guess, result: RegistrationResult) -> Candidate {
        let check = FrameCheck::measure(
            self.map,
            &result,
            self.depth,
            self.intrinsics,
            self.tracking,
        );
        Candidate {
            guess,
            result,
            check,
        }
    }
}

/// The best of `candidates` that passes the check, else the best with a pose, else the first.
pub fn choose(candidates: Vec<Candidate>, tracking: &TrackingConfig) -> Option<Candidate> {
    for candidate in &candidates {
        tracing::debug!(
            guess = ?candidate.guess,
            passes = candidate.passes(tracking),
            check = ?candidate.check,
            world_from_camera = ?candidate.result.target_from_source.translation.vector,
            "tracking candidate"
        );
    }
    let best_of = |filter: &dyn Fn(&Candidate) -> bool| {
        candidates
            .iter()
            .filter(|c| filter(c))
            .reduce(|best, c| {
                if c.check.better_than(&best.check) {
                    c
                } else {
                    best
                }
            })
            .cloned()
    };
    best_of(&|c| c.passes(tracking))
        .or_else(|| best_of(&|c| c.has_pose()))
        .or_else(|| candidates.first().cloned())
}

/// Every `step`-th point of `cloud` with its covariance (no pixels, no grid); the cloud itself
/// for a step of 1.
fn every_nth(cloud: &PointCloud, step: usize) -> Cow<'_, PointCloud> {
    if step <= 1 {
        return Cow::Borrowed(cloud);
    }
    Cow::Owned(PointCloud {
        positions: cloud.positions.iter().step_by(step).copied().collect(),
        covariances: cloud.covariances.iter().step_by(step).copied().collect(),
        pixels: Vec::new(),
        grid: None,
    })
}
