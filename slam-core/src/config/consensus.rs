//! Parameters of the consensus's alignment (SPEC section 4, steps 2 and 3), pose graph and joint
//! photometric refinement (step 4): the `[consensus.alignment]`, `[consensus.pose_graph]` and
//! `[consensus.refinement]` tables. Every field has a
//! serde default, so a configuration file names only what it changes; the defaults suit a
//! 640x480 RGB-D sensor (7-Scenes, TUM, the synthetic scene).

use serde::{Deserialize, Serialize};

/// Keyframe-to-keyframe alignment: coarse feature registration, G-ICP refinement, verification.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignmentConfig {
    // --- Features (coarse registration) ---
    /// Keypoints kept per image over all pyramid levels (1000: enough for a few hundred matches
    /// between overlapping views, cheap to match by brute force; on synthetic pairs 1.5-2.5 m
    /// apart 1500 gave 1.5x the correct matches for 1.2x the extraction time, but aligned about
    /// as many pairs).
    pub features_per_image: usize,
    /// Image pyramid levels for FAST + BRIEF (BRIEF is not scale-invariant; levels let a view
    /// taken twice as far away still match). 5 levels of 1.25 span a 2.4x scale change.
    pub pyramid_levels: usize,
    /// Size ratio between consecutive pyramid levels.
    pub pyramid_scale_factor: f64,
    /// FAST-9 threshold (grey levels): a corner's arc must be this much brighter or darker than
    /// its centre. Low, so that plain surfaces still offer corners; the grid and the FAST score
    /// choose among them.
    pub fast_threshold: u8,
    /// Keypoints are spread over a grid of cells this many pixels wide (on each pyramid level):
    /// the strongest corner of every cell before the second of any. 0: strongest first over the
    /// whole image, which piles the keypoints onto a few high-contrast spots.
    pub keypoint_cell_px: u32,
    /// Turn the BRIEF pattern by each keypoint's intensity-centroid orientation (steered BRIEF),
    /// so that descriptors survive in-plane rotation between the views.
    pub steer_descriptors: bool,
    /// Radius (metres) of the surface patch a descriptor describes, sampled from the pyramid
    /// level whose pixels match it: the same place seen from 1 m and from 3 m gives the same
    /// patch. 0: the 31-pixel patch around the corner on its detection level.
    pub descriptor_radius_m: f64,
    /// Lay the metric patch onto the surface (normal from depth) instead of facing the camera:
    /// a surface seen obliquely by one camera and head-on by the other still gives one patch.
    pub rectify_patches: bool,
    /// Largest Hamming distance (of 256 bits) accepted for a descriptor match.
    pub max_hamming_distance: u32,
    /// Lowe's ratio test: the best match must be closer than this fraction of the second best.
    /// 1.0 only refuses ties. Views metres apart change BRIEF descriptors so much that the second
    /// best is often nearly as close as the best: on a synthetic pair 0.8 m and 11 degrees apart
    /// a ratio of 0.8 kept 6 correct matches, 1.0 kept 35 of 111. Mutual nearest neighbours and
    /// RANSAC do the filtering instead.
    pub match_ratio: f64,
    /// A keypoint lifts to 3-D only when the depths of its 3x3 neighbourhood are all valid and
    /// spread by less than this fraction of the centre depth (corners often sit on depth edges,
    /// where the depth of the pixel may belong to the background).
    pub max_depth_spread_fraction: f64,
    /// Depth at or beyond this is not used (metres; 10 for 7-Scenes, as in tracking).
    pub truncation_m: f64,

    // --- RANSAC over 3-point rigid fits ---
    /// A match is an inlier when the transformed source point lies within this distance of the
    /// target point (metres; covers Kinect depth noise of 1-2 cm at 2-3 m on both points).
    pub ransac_inlier_distance_m: f64,
    /// Hypotheses at most.
    pub ransac_max_iterations: usize,
    /// Stop early once a hypothesis with this probability of being all-inlier has been drawn.
    pub ransac_confidence: f64,
    /// Sampled points closer together than this (metres) make an ill-conditioned rotation.
    pub ransac_min_sample_spread_m: f64,
    /// Seed of the sampler: alignment is deterministic for the same inputs.
    pub ransac_seed: u64,
    /// The coarse estimate needs at least this many inlier matches.
    pub min_coarse_inliers: usize,

    // --- G-ICP refinement ---
    /// Back-project every n-th pixel of each keyframe's depth (as tracking does).
    pub pixel_stride: usize,
    /// Neighbours per G-ICP covariance and its plane regularisation (as tracking does).
    pub covariance_neighbours: usize,
    pub covariance_epsilon: f64,
    /// Coarse-to-fine correspondence distances (metres, largest first; SPEC section 4, step 2).
    pub correspondence_distances_m: Vec<f64>,
    /// Levenberg-Marquardt iterations per stage.
    pub gicp_max_iterations: usize,
    /// Converged when an update rotates less than this (radians) and translates less than
    /// `gicp_translation_epsilon_m`: tighter than tracking's, a loop closure is used for long.
    pub gicp_rotation_epsilon_rad: f64,
    pub gicp_translation_epsilon_m: f64,

    // --- Verification ---
    /// Fraction of the source keyframe's points with a target point within the finest
    /// correspondence distance after refinement. Low values mean little overlap or a wrong pose.
    pub min_inlier_fraction: f64,
    /// RMS point-to-plane distance of those correspondences (metres) at most.
    pub max_residual_m: f64,
    /// Depth agreement: a point projected into the other keyframe agrees with its depth image
    /// when it lies within `depth_tolerance_m + depth_tolerance_fraction * depth` of it.
    pub depth_tolerance_m: f64,
    pub depth_tolerance_fraction: f64,
    /// Agreeing points over agreeing plus free-space violations (a point in front of what the
    /// other camera sees) at least this fraction, in both directions.
    pub min_depth_agreement: f64,
    /// Fewer projected comparisons than this cannot vouch for a pose.
    pub min_depth_comparisons: usize,
}

impl Default for AlignmentConfig {
    fn default() -> Self {
        Self {
            features_per_image: 1000,
            pyramid_levels: 5,
            pyramid_scale_factor: 1.25,
            fast_threshold: 12,
            keypoint_cell_px: 32,
            steer_descriptors: true,
            descriptor_radius_m: 0.08,
            rectify_patches: true,
            max_hamming_distance: 80,
            match_ratio: 1.0,
            max_depth_spread_fraction: 0.05,
            truncation_m: 10.0,
            ransac_inlier_distance_m: 0.05,
            ransac_max_iterations: 5000,
            ransac_confidence: 0.999,
            ransac_min_sample_spread_m: 0.1,
            ransac_seed: 0,
            min_coarse_inliers: 15,
            pixel_stride: 5,
            covariance_neighbours: 10,
            covariance_epsilon: 1e-3,
            correspondence_distances_m: vec![0.1, 0.05, 0.02],
            gicp_max_iterations: 64,
            gicp_rotation_epsilon_rad: 1e-4,
            gicp_translation_epsilon_m: 1e-4,
            min_inlier_fraction: 0.2,
            max_residual_m: 0.01,
            depth_tolerance_m: 0.02,
            depth_tolerance_fraction: 0.01,
            min_depth_agreement: 0.8,
            min_depth_comparisons: 500,
        }
    }
}

/// Robust pose graph over all agents' keyframes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseGraphConfig {
    /// Standard deviation of an odometry edge (consecutive keyframes of one agent, from
    /// tracking): rotation (radians) and translation (metres). Measured on redkitchen with
    /// keyframes 20 frames apart: frame-to-model tracking errs by a median 24 mm and 0.9 degrees
    /// per step (90th percentile 50-90 mm, 2 degrees).
    pub odometry_rotation_sigma_rad: f64,
    pub odometry_translation_sigma_m: f64,
    /// Standard deviation of a verified loop closure: alignments on redkitchen differ from the
    /// (KinectFusion) ground truth by a median 17 mm and 0.6 degrees, part of it the ground
    /// truth's own error.
    pub loop_rotation_sigma_rad: f64,
    pub loop_translation_sigma_m: f64,
    /// Truncated least squares: a loop edge whose squared Mahalanobis residual exceeds this is an
    /// outlier (16.81: the 99 % quantile of chi-square with 6 degrees of freedom).
    pub outlier_threshold_chi2: f64,
    /// Graduated non-convexity: the control parameter mu grows by this factor per step
    /// (Yang et al. 2020 use 1.4).
    pub gnc_mu_factor: f64,
    /// GNC steps at most.
    pub gnc_max_steps: usize,
    /// Levenberg-Marquardt iterations per GNC step and for the final solve.
    pub lm_max_iterations: usize,
    /// LM stops when the largest update component falls below this (radians or metres).
    pub lm_step_tolerance: f64,
    /// Initial guess of each agent's frame: two inter-agent loop closures vote for each other
    /// when the agent-to-agent transforms they imply differ by less than this translation
    /// (metres) and rotation (radians). Generous: odometry drift between the two closures
    /// separates even correct votes.
    pub vote_translation_m: f64,
    pub vote_rotation_rad: f64,
}

impl Default for PoseGraphConfig {
    fn default() -> Self {
        Self {
            odometry_rotation_sigma_rad: 0.02,
            odometry_translation_sigma_m: 0.03,
            loop_rotation_sigma_rad: 0.01,
            loop_translation_sigma_m: 0.02,
            outlier_threshold_chi2: 16.81,
            gnc_mu_factor: 1.4,
            gnc_max_steps: 100,
            lm_max_iterations: 30,
            lm_step_tolerance: 1e-7,
            vote_translation_m: 0.3,
            vote_rotation_rad: 10f64.to_radians(),
        }
    }
}

/// Joint photometric refinement of the merged world map (SPEC section 4, step 4, second half):
/// the merged map and the keyframe poses are optimised against every placed keyframe's RGB-D
/// image with `weight_l1`, `weight_ssim`, `weight_depth` and `weight_pose_consistency` of
/// `[consensus]`. It runs when the agents are done, before the world map and trajectories are
/// written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefinementConfig {
    /// Adam iterations, one keyframe view each (0 turns refinement off). Every keyframe is
    /// visited in turn, in a shuffled order per pass.
    pub iterations: usize,
    /// Stop earlier when refinement has run this long (seconds): on a CPU Vulkan device an
    /// iteration over a few hundred thousand Gaussians costs about a second.
    pub max_seconds: f64,
    /// Views are rendered at their resolution divided by this (as `[mapping] image_downscale`).
    pub image_downscale: u32,
    /// Learning rates of the Gaussians (SPEC section 3's mapping rates; the mean rate is
    /// multiplied by the map's radius, as the mapper does).
    pub lr_means: f64,
    pub lr_colours: f64,
    pub lr_opacity: f64,
    pub lr_log_scales: f64,
    pub lr_rotations: f64,
    /// Optimise the keyframe poses too (photometric gradient plus the pose-consistency term over
    /// the pose graph's odometry and accepted loop edges). Agent 0's first keyframe stays fixed:
    /// it defines the world frame.
    pub refine_poses: bool,
    /// Poses stay fixed for this fraction of the iterations: the photometric pose gradient of
    /// a blurred map points nowhere useful (on the synthetic swarm, refining poses from the first
    /// iteration moved exact poses by up to 1.1 cm and 0.5 degrees).
    pub pose_warmup_fraction: f64,
    /// Adam step sizes of the pose (metres and radians per step; an Adam step is about this
    /// size whatever the gradient's scale): 0.2 mm and 0.01 degrees.
    pub lr_pose_translation_m: f64,
    pub lr_pose_rotation_rad: f64,
    /// A refined pose may move at most this far from the pose graph's (metres, radians);
    /// farther means the photometric term pulled it into a wrong basin, and the pose graph's
    /// pose is kept.
    pub max_pose_change_m: f64,
    pub max_pose_change_rad: f64,
    /// Seed of the view order (runs are repeatable).
    pub random_seed: u64,
}

impl Default for RefinementConfig {
    fn default() -> Self {
        Self {
            iterations: 300,
            max_seconds: 120.0,
            image_downscale: 2,
            lr_means: 5e-6,
            lr_colours: 2.5e-3,
            lr_opacity: 0.05,
            lr_log_scales: 0.01,
            lr_rotations: 0.0,
            refine_poses: true,
            pose_warmup_fraction: 0.5,
            lr_pose_translation_m: 2e-4,
            lr_pose_rotation_rad: 2e-4,
            max_pose_change_m: 0.05,
            max_pose_change_rad: 2f64.to_radians(),
            random_seed: 0,
        }
    }
}

/// How an agent applies the consensus's corrections to its local maps (SPEC section 4, step 4:
/// "corrections go back to agents, which apply them to their local maps between frames"): the
/// `[consensus.local_corrections]` table.
///
/// A correction carries the corrected pose of every keyframe the agent published. The agent
/// moves each part of its tracking map, its mapping map and its keyframe poses with the
/// correction blended at the time that part was made (the consensus's own rule for per-frame
/// trajectories), so a drift the pose graph removed is also removed from the map the agent
/// tracks against. What it publishes stays in its tracked (uncorrected) frame, which the
/// consensus's odometry edges are built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalCorrectionConfig {
    /// Apply corrections to the local maps at all (false: they are only recorded).
    pub apply: bool,
    /// A correction is applied only when it would move some keyframe by at least this much
    /// (metres) or `min_rotation_rad`. Smaller changes are mostly pose-graph noise: every solve
    /// moves every keyframe by a millimetre or two. On redkitchen (two agents, 0..600 and
    /// 400..1000) applying every change of 2 mm / 0.1 degrees moved the maps 14-18 times per
    /// agent, cost up to 6 s of tracking time and raised the joint ATE from 2.89 to 3.25 cm (the
    /// small moves of overlapping parts blur the surfaces G-ICP aligns to); 1 cm / 0.5 degrees
    /// applied 6-8 corrections (the real drift fixes) for 2.95 cm.
    pub min_translation_m: f64,
    /// Radians (0.5 degrees).
    pub min_rotation_rad: f64,
    /// Within an applied correction, a part of the tracking map or coverage index (the points
    /// one frame added) moves only when its own move reaches this (metres) or
    /// `part_min_rotation_rad`; a part that waits keeps its correction and moves the whole way
    /// later. Moving a point costs a removal and an insertion in the index, and most of the map
    /// (far from where the pose graph changed) moves by far less than the depth noise.
    pub part_min_translation_m: f64,
    /// Radians (0.1 degrees).
    pub part_min_rotation_rad: f64,
}

impl Default for LocalCorrectionConfig {
    fn default() -> Self {
        Self {
            apply: true,
            min_translation_m: 0.01,
            min_rotation_rad: 0.5_f64.to_radians(),
            part_min_translation_m: 0.002,
            part_min_rotation_rad: 0.1_f64.to_radians(),
        }
    }
}

/// Re-requesting keyframes that arrived incomplete: the `[consensus.resend]` table.
///
/// A published keyframe is three messages (descriptor, RGB-D image, Gaussian patch). One can be
/// lost: a full queue, an agent that restarted between them, a sample iceoryx2 dropped. The
/// consensus notices a keyframe with some parts and not others, waits `after_s` (the parts of
/// one keyframe go out back to back, so a longer wait means loss, not delay) and asks the agent
/// to publish it again (`ControlMessage::ResendKeyframe`), at most `max_requests` times. The
/// agent keeps its last `agent_keeps` published keyframes for that; an older one is gone and
/// the request is answered by nothing (counted on both sides).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResendConfig {
    /// Seconds an incomplete keyframe waits before (and between) requests.
    pub after_s: f64,
    /// Requests per keyframe before the consensus gives up on it (0: never ask).
    pub max_requests: usize,
    /// Published keyframes an agent keeps for re-sending (each holds its RGB-D image and its
    /// Gaussians: ~2.5 MB at 640x480 plus 56 bytes per Gaussian).
    pub agent_keeps: usize,
}

impl Default for ResendConfig {
    fn default() -> Self {
        Self {
            after_s: 2.0,
            max_requests: 3,
            agent_keeps: 8,
        }
    }
}

/// Map-level global registration between two agents' maps, without an initial guess: the
/// `[consensus.map_registration]` table (consensus-server/src/map_registration). Both maps are
/// voxel-downsampled, described by FPFH-style local geometry histograms, matched in feature
/// space, pruned by RANSAC over rigid 3-point fits, refined by G-ICP and verified.
///
/// Lengths ending in `_voxels` are multiples of the voxel size actually used, which grows above
/// `voxel_m` when a map has more than `max_points` voxels: radii and tolerances then scale with
/// the sampling, which is what they depend on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapRegistrationConfig {
    // --- When (consensus-server/src/map_links.rs) ---
    /// Register agents' maps at all (false: agents meet through keyframe pairs only).
    pub enabled: bool,
    /// A pair of agents not linked yet is registered again once either agent has published
    /// this many keyframes since the pair's last attempt (its map grew, so may the overlap).
    pub retry_after_keyframes: usize,
    /// A pair already linked is registered again after this many new keyframes of either agent:
    /// an independent constraint for the pose graph. 0: never.
    pub refresh_after_keyframes: usize,
    /// Map points (evenly spread) moved into the other agent's keyframes for the free-space
    /// check of an accepted registration (the keyframe alignment's depth test and thresholds).
    pub depth_check_points: usize,

    // --- Downsampling ---
    /// Smallest voxel edge (metres): each map is reduced to one point (the centroid) per voxel.
    /// 5 cm keeps table tops, chairs and door frames as shapes while removing the fine detail
    /// that depth noise (1-2 cm) blurs anyway. Maps must sample their surfaces at least this
    /// finely (dense SLAM maps do), or isolated-point removal thins them.
    pub voxel_m: f64,
    /// Points per map at most for the descriptors: the voxel grows (both maps get the same one,
    /// so their features describe the same scale) until both maps fit. Bounds the cost: two maps
    /// of 10k points register in 0.3-0.9 s on two cores.
    pub max_points: usize,

    // --- Normals and features ---
    /// Normal of a point: smallest principal axis of its neighbours within this radius (voxels).
    /// 2.5 voxels holds ~20 neighbours on a plane: enough for a stable normal, small enough not
    /// to round off edges.
    pub normal_radius_voxels: f64,
    /// A point with fewer neighbours (itself included) within the normal radius has no reliable
    /// normal: it is removed before the point budget is applied (isolated outliers, thin edges
    /// of the scan). A plane holds ~20 points in that radius, an edge of it ~10; points scattered
    /// through free space (a fifth of the unit test's points) rarely have 10.
    pub min_normal_neighbours: usize,
    /// Feature histograms pair a point with its neighbours within this radius (voxels); the final
    /// descriptor also folds in the neighbours' own histograms, so it sees up to twice as far.
    /// 5 voxels is the usual FPFH choice (Rusu 2009 uses ~2x the normal radius).
    pub feature_radius_voxels: f64,
    /// A point with fewer neighbours with normals within the feature radius gets no feature.
    pub min_feature_neighbours: usize,

    // --- Correspondences ---
    /// Descriptors per map that take part in matching at most: the most distinctive ones, those
    /// farthest from the map's mean descriptor (the "persistence" idea of Rusu et al. 2008).
    /// Walls and floors, most of an indoor map, all look alike and mostly add wrong matches, and
    /// matching costs the product of the two counts.
    pub max_matched_features: usize,
    /// Mutual nearest neighbours in feature space are the correspondences; when fewer than this
    /// are mutual, the best one-way matches (smallest feature distance) are added up to it.
    pub min_correspondences: usize,

    // --- Colour (used when both maps have colours) ---
    /// Weight of a point's colour signature (a histogram of its neighbourhood's hues with an
    /// achromatic bin, summing to 1, invariant to exposure; see consensus-server's
    /// map_registration/colour.rs) appended to its FPFH descriptor (three parts summing to 1).
    /// 0: colour does not take part in matching. On the synthetic wide-baseline maps 0.6 left
    /// two of the 17 pairs that 1.0 registers ambiguous; on 7-Scenes 1.0 finds as many true
    /// correspondences as geometry alone.
    pub colour_weight: f64,
    /// Two overlapping points agree in colour when their chromaticities (invariant to exposure:
    /// `((r - g) / s, (2 b - r - g) / (sqrt(3) s))` with `s = r + g + b`, an orthogonal view of
    /// `(r, g, b) / s`) are within this distance.
    pub colour_tolerance: f64,
    /// Refused when the colour agreement of the overlapping points is not at least this far
    /// above chance: Cohen's kappa `(agreement - chance) / (1 - chance)`, with `chance` the
    /// agreement of the same points paired at random (a room laid onto itself turned puts walls
    /// onto walls of other colours). Not judged when chance agreement is above 0.9 (a scene of
    /// one colour). Measured: true poses 0.34-0.37 on 7-Scenes (white balance, colour-to-depth
    /// offset), 0.88-0.98 on the synthetic room; wrong poses on 7-Scenes -0.13 to 0.16, 7-Scenes
    /// laid onto the synthetic room 0.19; a turned synthetic room whose floor agrees 0.25-0.58,
    /// which this cannot refuse.
    pub min_colour_kappa: f64,
    /// The colour agreement is only judged over at least this many compared points.
    pub min_colour_comparisons: usize,
    /// An overlap below `min_overlap_fraction` but at least this large is accepted when its
    /// colours agree with a kappa of at least `colour_confirmed_kappa`: colours that follow the
    /// pairing that closely are evidence of the right pose that a small overlap by itself is not
    /// (the overlap threshold refuses chance alignments; a chance alignment's colours agree no
    /// better than chance). Measured kappas: true poses 0.88-0.98 on the synthetic room, turned
    /// rooms 0.25-0.58 (and 0.35 for true poses on 7-Scenes, where this never applies).
    pub colour_confirmed_overlap_fraction: f64,
    pub colour_confirmed_kappa: f64,

    // --- Robust pruning (RANSAC over 3 correspondences) ---
    /// A correspondence supports a hypothesis when the hypothesis puts its source point within
    /// this distance of its target point (voxels): matched points are voxel centroids of two
    /// different samplings, up to about a voxel apart on the same surface.
    pub inlier_distance_voxels: f64,
    /// A sample's pairwise distances must agree between the maps within this tolerance
    /// (voxels) before a transform is fitted: a rigid motion preserves distances, and the test
    /// discards almost every wrong sample for the price of three subtractions.
    pub edge_tolerance_voxels: f64,
    /// Sample points closer together than this (voxels) make an ill-conditioned rotation.
    pub min_sample_spread_voxels: f64,
    /// Samples drawn at most.
    pub ransac_max_samples: usize,
    /// Stop sampling once a hypothesis as good as the best would have been drawn with this
    /// probability (and at least `ransac_min_samples` were drawn).
    pub ransac_confidence: f64,
    /// Samples drawn at least, so the runner-up hypothesis is searched for too (samples are
    /// cheap: 50 000 cost a few milliseconds, almost all discarded by the edge test).
    pub ransac_min_samples: usize,
    /// Seed of the sampler: registration is deterministic for the same inputs.
    pub ransac_seed: u64,
    /// A runner-up hypothesis counts as distinct from the best when their rotations differ by
    /// more than this (radians)...
    pub distinct_rotation_rad: f64,
    /// ...or they place the source map's centre farther apart than this (metres).
    pub distinct_translation_m: f64,

    // --- G-ICP refinement ---
    /// Neighbours per G-ICP covariance and its plane regularisation (as tracking does).
    pub covariance_neighbours: usize,
    pub covariance_epsilon: f64,
    /// Coarse-to-fine correspondence distances (voxels, largest first). The coarse ones are
    /// multiples of the feature level's voxel; the last one, the final stage's and the
    /// verification's overlap distance, of the refinement level's.
    pub refine_distances_voxels: Vec<f64>,
    /// Points per map at most for the final G-ICP stage and the verification: the refinement
    /// level keeps the finest voxel up to this many points (more than `max_points`: accuracy
    /// comes from fine sampling, and G-ICP costs only linearly in the points).
    pub refine_max_points: usize,
    /// Levenberg-Marquardt iterations per stage.
    pub gicp_max_iterations: usize,
    /// Converged when an update rotates less than this (radians) and translates less than
    /// `gicp_translation_epsilon_m`.
    pub gicp_rotation_epsilon_rad: f64,
    pub gicp_translation_epsilon_m: f64,

    // --- Verification ---
    /// RANSAC's best hypothesis needs at least this many consistent correspondences. Chance
    /// alignments of ~500 correspondences reach 8-16 on the synthetic and redkitchen maps; true
    /// ones 20-180.
    pub min_consistent_correspondences: usize,
    /// Refused as ambiguous when the best distinct runner-up hypothesis has more than this
    /// fraction of the best one's support (symmetric or repetitive structure, or a best
    /// hypothesis no better than chance). 0.5: the best must explain twice as much.
    pub max_ambiguity_ratio: f64,
    /// Fraction of the smaller map's points that must have a point of the other map within the
    /// final refinement distance after alignment.
    pub min_overlap_fraction: f64,
    /// RMS point-to-plane distance of those overlapping points (metres) at most.
    pub max_residual_m: f64,
    /// Standard deviation of one point-to-plane residual assumed by the covariance estimate
    /// when the measured RMS residual is smaller (metres): voxel centroids are not exact.
    pub residual_sigma_floor_m: f64,
    /// Refused as degenerate when the estimate's standard deviation along its worst direction
    /// exceeds this rotation (radians) or translation (metres): the overlap does not pin down all
    /// six degrees of freedom (a single plane, a corridor). The deviations treat residuals as
    /// independent (thousands of points give fractions of a millimetre), so only overlaps that
    /// leave a direction (nearly) free reach these bounds.
    pub max_rotation_sigma_rad: f64,
    pub max_translation_sigma_m: f64,
}

impl Default for MapRegistrationConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            retry_after_keyframes: 1,
            refresh_after_keyframes: 8,
            depth_check_points: 5000,
            voxel_m: 0.05,
            max_points: 10_000,
            normal_radius_voxels: 2.5,
            min_normal_neighbours: 10,
            feature_radius_voxels: 5.0,
            min_feature_neighbours: 10,
            max_matched_features: 3000,
            min_correspondences: 300,
            colour_weight: 1.0,
            colour_tolerance: 0.05,
            min_colour_kappa: 0.25,
            min_colour_comparisons: 100,
            colour_confirmed_overlap_fraction: 0.03,
            colour_confirmed_kappa: 0.75,
            inlier_distance_voxels: 1.5,
            edge_tolerance_voxels: 2.0,
            min_sample_spread_voxels: 4.0,
            ransac_max_samples: 1_000_000,
            ransac_confidence: 0.9999,
            ransac_min_samples: 50_000,
            ransac_seed: 0,
            distinct_rotation_rad: 10f64.to_radians(),
            distinct_translation_m: 0.3,
            covariance_neighbours: 10,
            covariance_epsilon: 1e-3,
            refine_distances_voxels: vec![4.0, 2.0, 1.0],
            refine_max_points: 25_000,
            gicp_max_iterations: 15,
            gicp_rotation_epsilon_rad: 1e-4,
            gicp_translation_epsilon_m: 1e-4,
            min_consistent_correspondences: 20,
            max_ambiguity_ratio: 0.5,
            min_overlap_fraction: 0.1,
            max_residual_m: 0.03,
            residual_sigma_floor_m: 0.005,
            max_rotation_sigma_rad: 2f64.to_radians(),
            max_translation_sigma_m: 0.05,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partial_config_keeps_defaults() {
        let config: super::super::ConsensusConfig =
            toml::from_str("[alignment]\nmax_residual_m = 0.02\n").unwrap();
        assert_eq!(config.alignment.max_residual_m, 0.02);
        assert_eq!(
            config.alignment.correspondence_distances_m,
            vec![0.1, 0.05, 0.02]
        );
        assert_eq!(config.pose_graph, PoseGraphConfig::default());
        assert!(toml::from_str::<AlignmentConfig>("typo = 1").is_err());
    }
}
