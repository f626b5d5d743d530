//! The `[tracking]` and `[keyframes]` sections of the configuration file: the parameters the
//! tracker reads ([`crate::odometry`], [`crate::gicp::GicpParams::tracking`]) and, for keyframes,
//! the agent's seeding of new Gaussians. `[keyframes]` sits here rather than with the agent
//! because the odometry decides keyframes itself (overlap with the map); the agent reads the
//! seeding half of it. Defaults suit a 640x480 sensor (7-Scenes, TUM, the synthetic scene);
//! Replica-like 1200x680 data overrides `pixel_stride` and `truncation_m`.
//!
//! Unknown keys are refused so a typo does not silently fall back to a default. `validate()`
//! names the offending field by its dotted path in the file.

use geometry::checks::{FieldError, at_least_one, fraction, non_negative, positive};
use serde::{Deserialize, Serialize};

/// Tracking: point selection, per-point covariances, map-candidate selection and G-ICP.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Back-project every `pixel_stride`-th pixel in x and y (5 for 640x480, 10 for 1200x680).
    pub pixel_stride: usize,
    /// Depth at or beyond this is dropped (metres; 10 for 7-Scenes, 12 for Replica).
    pub truncation_m: f64,
    /// Neighbours used to estimate each point's covariance.
    pub covariance_neighbours: usize,
    /// G-ICP regularisation: singular values become (1, 1, epsilon) (a plane-like ellipse).
    pub covariance_epsilon: f64,
    /// Map Gaussians with opacity above this can be tracked against.
    pub trackable_min_opacity: f64,
    /// Largest point-to-Gaussian distance accepted as a correspondence (metres).
    pub max_correspondence_m: f64,
    /// Levenberg-Marquardt iterations at most.
    pub max_iterations: usize,
    /// Converged when the rotation update is below this (radians)...
    pub rotation_epsilon_rad: f64,
    /// ...and the translation update below this (metres). 1 mm, small_gicp's default, where the
    /// published method uses 0.5 mm: each correspondence search after the first moves the pose
    /// by about a quarter of the previous one, so the half-millimetre threshold costs one more
    /// search on most frames (a third of the registration time) for a correction of a tenth of a
    /// millimetre, and redkitchen's ATE is no worse with 1 mm (docs/method.md, One agent:
    /// Tracking; docs/benchmarks.md).
    pub translation_epsilon_m: f64,
    /// Predict the next pose with a constant-velocity model instead of the previous pose.
    pub constant_velocity: bool,
    /// Tracking fails (too few correspondences) when fewer than this fraction of the frame's
    /// points have a map point within `max_correspondence_m` after alignment.
    pub min_inlier_fraction: f64,

    // --- The check (registration/src/odometry/check.rs) ---
    /// Map points in view sampled to check a pose against the frame's depth.
    pub check_points: usize,
    /// A map point agrees with the measured depth within this many metres...
    pub depth_tolerance_m: f64,
    /// ...plus this fraction of the depth (depth noise grows with it).
    pub depth_tolerance_fraction: f64,
    /// Pixels around a map point's projection it is compared with as well (it agrees with any,
    /// violates only in front of all): depth edges, where a pixel's error flips foreground to
    /// background, then do not count as seeing through surfaces.
    pub depth_check_pixel_radius: u32,
    /// A pose is refused when fewer of the map points compared agree with the frame's depth
    /// (the rest lie in front of it, in space the camera sees through).
    pub min_depth_agreement: f64,
    /// ...or when fewer map points than this could be compared at all.
    pub min_depth_comparisons: usize,

    // --- Recovery (registration/src/odometry/recovery.rs) ---
    /// The wide-baseline guesses also run when a frame's overlap with the map falls by more than
    /// this fraction of the previous frame's (a pose that passed the check may still have slid).
    pub recovery_overlap_drop: f64,
    /// Coarse-to-fine G-ICP: correspondence distances before the fine `max_correspondence_m`,
    /// largest first (metres).
    pub recovery_distances_m: Vec<f64>,
    /// Iterations at most per coarse stage.
    pub recovery_max_iterations: usize,
    /// Try the FPFH registration of the frame to the map when the cheaper guesses fail (for
    /// scenes without texture; costs up to a second).
    pub recovery_geometry: bool,
    /// At sensor pace (a live camera, or `mapping.pace = "sensor"`), the most of the wall time
    /// the expensive recovery guesses (image features, geometry) may take over a long stretch;
    /// 1 = no limit. Frames keep arriving during a search and each one missed widens the next
    /// step, so failing guesses must not take the time the tracker needs to catch up with the
    /// camera (odometry/rationing.rs). Paced and offline runs are never limited.
    pub recovery_time_share: f64,
    /// ...except that after a quiet stretch a search may take up to this long at once (ms):
    /// the first stall gets every guess.
    pub recovery_burst_ms: f64,

    // --- Segments and relocalisation (registration/src/odometry/segments.rs) ---
    /// Lost frames in a row after which a new segment starts. Three frames (0.1 s at 30 Hz)
    /// ride out a burst of bad depth on the prediction.
    pub max_consecutive_failures: usize,
    /// Root keyframes kept (images) for relocalisation; the archive thins evenly when full.
    pub relocalisation_keyframes: usize,
    /// Archived keyframes, the most similar first, aligned with each keyframe of an unjoined
    /// segment.
    pub relocalisation_candidates: usize,
    /// Every this many keyframes of an unjoined segment whose keyframe alignments failed, its
    /// map is registered to the root's (0: never). With real-time frames, whose searches run on
    /// a thread of their own and skip the keyframes that come while one runs: every this many
    /// searches.
    pub relocalisation_map_every: usize,

    /// The photometric term of the ordinary path ([`crate::photometric`]).
    pub photometric: PhotometricConfig,
}

/// The photometric term minimised with G-ICP on the ordinary path (`[tracking.photometric]`;
/// docs/method.md, One agent: Tracking, "Photometric term"): the previous placed frame's
/// textured pixels, lifted by its depth, must show the same brightness where the current pose
/// projects them into the current image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhotometricConfig {
    /// Weight of a squared intensity residual (intensities in [0, 1]) against G-ICP's cost;
    /// 0 (the default) turns the term off. 0.3 is the weight measured in docs/benchmarks.md: it
    /// helps paced replays of fast rotation (tum-fr1-rpy) but costs accuracy at sensor pace,
    /// where dropped frames make larger steps, so it is off until it is gated on them
    /// (configs/tum.toml turns it on: on fr1/rpy it helped at sensor pace as well). G-ICP's
    /// cost per point is a Mahalanobis distance in its normalised covariances (eigenvalues 1,
    /// 1, `covariance_epsilon`): a point 1 cm off the surface costs
    /// about 0.05, as much as an intensity residual of 0.05 / sqrt(weight).
    pub weight: f64,
    /// Pyramid level the images are compared at (each level halves the resolution: 1 is
    /// 320x240 for a 640x480 sensor). Coarser levels see further (their gradients span more of
    /// the scene) and blur less matters; finer ones place edges more precisely.
    pub level: u32,
    /// Reference pixels at most (evenly thinned when more pass the gradient threshold).
    pub max_points: usize,
    /// A reference pixel is used when its intensity gradient is at least this (intensity per
    /// pixel of the level): flat pixels carry no pose information, only noise.
    pub min_gradient: f64,
    /// Residuals beyond this (intensity) get Huber weights (their influence stops growing):
    /// occlusions, specularities and blur the model does not explain.
    pub huber_threshold: f64,
    /// A reference point is occluded in the current frame when the current depth at its
    /// projection lies more than this (metres) in front of it; occluded points are skipped.
    pub occlusion_m: f64,
    /// A reference pixel whose depth block (the full-resolution pixels it bins) spreads by more
    /// than this fraction of its depth lies on a depth edge, where its 3-D position is
    /// unreliable; it is skipped.
    pub max_depth_spread_fraction: f64,
    /// Which placed frame the current one is compared with (see [`PhotometricReferenceFrame`]).
    pub reference: PhotometricReferenceFrame,
    /// Compare each colour image from where the camera was when it was taken: a frame whose
    /// colour and depth images are stamped apart (`colour_offset_s`, TUM's lists and ROS 2 bags)
    /// has its colour camera moved by the camera's motion over that time (the reference's at
    /// the velocity of the step that placed it, the current frame's at the velocity the pose
    /// tried implies). False (the default) compares it from the depth image's pose, as if both
    /// were taken together. With ground-truth poses the model is right (on tum-fr1-rpy it lowers
    /// the median photometric residual between frames two apart from 0.069 to 0.040), but in
    /// tracking it did not help: across weights and frame strides it was as often worse as
    /// better, with more frames sent to recovery (docs/benchmarks.md), so it stays off.
    pub model_colour_offset: bool,
}

/// The frame the photometric term compares the current one with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum PhotometricReferenceFrame {
    /// The previous placed frame: the smallest motion, but each frame's error carries on into
    /// the next through the term (frame-to-frame drift).
    PreviousFrame,
    /// The latest tracking keyframe (the frame whose points last joined the map): its pose is
    /// the map's, so the term, like G-ICP, aligns to the model and drift does not build up
    /// between keyframes.
    #[default]
    Keyframe,
}

impl Default for PhotometricConfig {
    fn default() -> Self {
        Self {
            weight: 0.0,
            level: 1,
            max_points: 4000,
            min_gradient: 0.02,
            huber_threshold: 0.05,
            occlusion_m: 0.05,
            max_depth_spread_fraction: 0.03,
            reference: PhotometricReferenceFrame::default(),
            model_colour_offset: false,
        }
    }
}

impl PhotometricConfig {
    /// True when the term runs: a positive weight and at least one reference point allowed.
    pub fn enabled(&self) -> bool {
        self.weight > 0.0 && self.max_points > 0
    }

    /// Checks ranges; returns the offending field (`tracking.photometric.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        non_negative("tracking.photometric.weight", self.weight)?;
        if self.level > 4 {
            return Err((
                "tracking.photometric.level",
                format!("must be at most 4 (1/16 resolution), got {}", self.level),
            ));
        }
        non_negative("tracking.photometric.min_gradient", self.min_gradient)?;
        positive("tracking.photometric.huber_threshold", self.huber_threshold)?;
        positive("tracking.photometric.occlusion_m", self.occlusion_m)?;
        positive(
            "tracking.photometric.max_depth_spread_fraction",
            self.max_depth_spread_fraction,
        )?;
        Ok(())
    }
}

impl Default for TrackingConfig {
    fn default() -> Self {
        Self {
            pixel_stride: 5,
            truncation_m: 10.0,
            covariance_neighbours: 10,
            covariance_epsilon: 1e-3,
            trackable_min_opacity: 0.05,
            max_correspondence_m: 0.02,
            max_iterations: 64,
            rotation_epsilon_rad: 2e-3,
            translation_epsilon_m: 1e-3,
            constant_velocity: true,
            min_inlier_fraction: 0.2,
            check_points: 4000,
            depth_tolerance_m: 0.02,
            depth_tolerance_fraction: 0.01,
            depth_check_pixel_radius: 1,
            min_depth_agreement: 0.8,
            min_depth_comparisons: 100,
            recovery_overlap_drop: 0.3,
            recovery_distances_m: vec![0.2, 0.1, 0.05],
            recovery_max_iterations: 20,
            recovery_geometry: true,
            recovery_time_share: 0.25,
            recovery_burst_ms: 1000.0,
            max_consecutive_failures: 3,
            relocalisation_keyframes: 64,
            relocalisation_candidates: 3,
            relocalisation_map_every: 3,
            photometric: PhotometricConfig::default(),
        }
    }
}

/// Keyframe selection and Gaussian seeding.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeyframeConfig {
    /// A source point overlaps the map when a map neighbour is closer than sqrt(this) (m^2).
    pub overlap_distance_sq_m2: f64,
    /// Overlapping fraction below this makes a tracking keyframe.
    pub min_overlap_fraction: f64,
    /// Otherwise every n-th frame since the last tracking keyframe is a mapping keyframe.
    pub mapping_keyframe_every: usize,
    /// At a tracking keyframe, new Gaussians farther than sqrt(this) from the map (m^2) are
    /// trackable.
    pub trackable_new_distance_sq_m2: f64,
    /// Opacity of a new Gaussian (before the logit).
    pub initial_opacity: f64,
    /// How big a new Gaussian is (see [`SeedScale`]).
    pub seed_scale: SeedScale,
    /// With `seed_scale = "sample_footprint"`: the new Gaussian's standard deviation along the
    /// surface in units of the spacing between neighbouring samples. Coverage of a surface grows
    /// with opacity x (sigma / spacing)^2: at the default initial opacity 0.1, 2 spacings give a closed
    /// surface from the first render (synthetic scene, no optimisation: PSNR 21.8 dB against
    /// 16.7 dB with 1 spacing).
    pub footprint_sigma_per_spacing: f64,
    /// At a mapping keyframe, points with a map Gaussian closer than sqrt(this) (m^2) are already
    /// covered and seed nothing. The method (docs/method.md, One agent: Seeding) makes
    /// mapping-keyframe Gaussians never trackable but does not say which points seed them; seeding every point of every 10th frame would grow the map by
    /// ~11k Gaussians per keyframe on 640x480 input, almost all duplicates of what is there.
    /// The default is the tracking overlap radius (sqrt(5e-4) m, ~2.2 cm).
    pub mapping_seed_min_distance_sq_m2: f64,
    /// Which points of a tracking keyframe seed Gaussians (see [`TrackingKeyframeSeeds`]).
    pub tracking_keyframe_seeds: TrackingKeyframeSeeds,
}

/// Which points of a tracking keyframe become new map Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TrackingKeyframeSeeds {
    /// The seeding rule of docs/method.md (One agent: Seeding) literally: every point. A tracking keyframe still overlaps the map by up to
    /// `min_overlap_fraction` (70 %), so most of its Gaussians duplicate surfaces the map already
    /// has, stacked in layers the mapper must render and optimise.
    #[default]
    All,
    /// Only the points no Gaussian covers yet (`mapping_seed_min_distance_sq_m2`), the mapping
    /// keyframe rule. Tracking is unaffected: the tracking map takes every new trackable point
    /// either way; only the mapper's map changes.
    Uncovered,
}

/// Size of a newly seeded Gaussian. Both keep the orientation of the point's G-ICP covariance
/// (wide along the surface, `sqrt(covariance_epsilon)` of that across it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SeedScale {
    /// The published seeding rule (docs/method.md, Seeding): scale = sqrt(eigenvalues of the
    /// G-ICP covariance) / max(1, 2 z^1.5). Written `"published"` (`"spec"`, its former name,
    /// is still read). The G-ICP covariance is normalised (eigenvalues 1, 1, eps), so a point
    /// 2 m away gets a disc of 0.18 m standard deviation: ~10x the spacing of the sampled
    /// points, which on a CPU rasteriser costs tens of millions of tile/Gaussian pairs.
    #[serde(alias = "spec")]
    Published,
    /// The disc scales with the point's own sample cell: standard deviation along the surface =
    /// `footprint_sigma_per_spacing` x the distance between neighbouring samples
    /// (pixel_stride * z / f), so the surface is closed whatever the depth.
    #[default]
    SampleFootprint,
}

impl Default for KeyframeConfig {
    fn default() -> Self {
        Self {
            overlap_distance_sq_m2: 5e-4,
            min_overlap_fraction: 0.7,
            mapping_keyframe_every: 10,
            trackable_new_distance_sq_m2: 5e-5,
            initial_opacity: 0.1,
            seed_scale: SeedScale::default(),
            footprint_sigma_per_spacing: 2.0,
            mapping_seed_min_distance_sq_m2: 5e-4,
            tracking_keyframe_seeds: TrackingKeyframeSeeds::default(),
        }
    }
}

impl TrackingConfig {
    /// Checks ranges; returns the offending field (`tracking.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        at_least_one("tracking.pixel_stride", self.pixel_stride)?;
        positive("tracking.truncation_m", self.truncation_m)?;
        if self.covariance_neighbours < 3 {
            return Err((
                "tracking.covariance_neighbours",
                "a covariance needs at least 3 neighbours".into(),
            ));
        }
        positive("tracking.covariance_epsilon", self.covariance_epsilon)?;
        fraction("tracking.trackable_min_opacity", self.trackable_min_opacity)?;
        positive("tracking.max_correspondence_m", self.max_correspondence_m)?;
        at_least_one("tracking.max_iterations", self.max_iterations)?;
        positive("tracking.rotation_epsilon_rad", self.rotation_epsilon_rad)?;
        positive("tracking.translation_epsilon_m", self.translation_epsilon_m)?;
        fraction("tracking.min_inlier_fraction", self.min_inlier_fraction)?;
        at_least_one("tracking.check_points", self.check_points)?;
        non_negative("tracking.depth_tolerance_m", self.depth_tolerance_m)?;
        non_negative(
            "tracking.depth_tolerance_fraction",
            self.depth_tolerance_fraction,
        )?;
        fraction("tracking.min_depth_agreement", self.min_depth_agreement)?;
        fraction("tracking.recovery_overlap_drop", self.recovery_overlap_drop)?;
        if self
            .recovery_distances_m
            .iter()
            .any(|d| !(d.is_finite() && *d > 0.0))
            || self.recovery_distances_m.windows(2).any(|w| w[1] >= w[0])
        {
            return Err((
                "tracking.recovery_distances_m",
                format!(
                    "must be positive and decreasing, got {:?}",
                    self.recovery_distances_m
                ),
            ));
        }
        at_least_one(
            "tracking.recovery_max_iterations",
            self.recovery_max_iterations,
        )?;
        if !(self.recovery_time_share > 0.0 && self.recovery_time_share <= 1.0) {
            return Err((
                "tracking.recovery_time_share",
                format!("must be in (0, 1], got {}", self.recovery_time_share),
            ));
        }
        non_negative("tracking.recovery_burst_ms", self.recovery_burst_ms)?;
        at_least_one(
            "tracking.max_consecutive_failures",
            self.max_consecutive_failures,
        )?;
        self.photometric.validate()
    }
}

impl KeyframeConfig {
    /// Checks ranges; returns the offending field (`keyframes.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        positive(
            "keyframes.overlap_distance_sq_m2",
            self.overlap_distance_sq_m2,
        )?;
        fraction("keyframes.min_overlap_fraction", self.min_overlap_fraction)?;
        at_least_one(
            "keyframes.mapping_keyframe_every",
            self.mapping_keyframe_every,
        )?;
        positive(
            "keyframes.trackable_new_distance_sq_m2",
            self.trackable_new_distance_sq_m2,
        )?;
        if !(self.initial_opacity > 0.0 && self.initial_opacity < 1.0) {
            return Err((
                "keyframes.initial_opacity",
                format!("must be in (0, 1), got {}", self.initial_opacity),
            ));
        }
        positive(
            "keyframes.footprint_sigma_per_spacing",
            self.footprint_sigma_per_spacing,
        )?;
        non_negative(
            "keyframes.mapping_seed_min_distance_sq_m2",
            self.mapping_seed_min_distance_sq_m2,
        )?;
        Ok(())
    }
}
