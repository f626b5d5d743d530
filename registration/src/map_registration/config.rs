//! The `[consensus.map_registration]` table: map-to-map global registration without an initial
//! guess (this module's parent). It lives beside the code it configures; the config crate
//! embeds it in the `[consensus]` section.

use geometry::checks::{FieldError, at_least_one, fraction, non_negative, positive};
use serde::{Deserialize, Serialize};

/// Map-level global registration between two agents' maps, without an initial guess: the
/// `[consensus.map_registration]` table (registration/src/map_registration). Both maps are
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
    /// test (`free_space.rs`: the keyframe alignment's depth test, its tolerances and
    /// `min_depth_comparisons`).
    pub depth_check_points: usize,
    /// Each direction of the free-space test must agree at least this much. Lower than the
    /// keyframe alignment's (0.8): whole maps carry their agents' drift, which no rigid transform
    /// undoes; true transforms measured 0.75-0.86 on 7-Scenes, wrong ones 0.24-0.44.
    pub min_depth_agreement: f64,

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
    /// Mutual nearest neighbours in feature space are correspondences; so are one-way nearest
    /// neighbours whose distance is below this fraction of the distance to the second nearest
    /// (Lowe's ratio test). 0: mutual ones only.
    pub match_ratio: f64,
    /// Correspondences at most (mutual ones first, then one-way ones by ratio): the clique
    /// search's graph costs their square (5000: 3 MB, 25 million length comparisons).
    pub max_correspondences: usize,
    /// When fewer correspondences than this were found, the best remaining one-way matches
    /// (smallest feature distance) are added up to it.
    pub min_correspondences: usize,

    // --- Colour (used when both maps have colours) ---
    /// Weight of a point's colour signature (a histogram of its neighbourhood's hues with an
    /// achromatic bin, summing to 1, invariant to exposure; see consensus-server's
    /// map_registration/colour.rs) appended to its FPFH descriptor (three parts summing to 1).
    /// 0: colour does not take part in matching. On the synthetic wide-baseline maps 0.6 left
    /// two of the 17 pairs that 1.0 registers ambiguous; on 7-Scenes 1.0 finds as many true
    /// correspondences as geometry alone.
    pub colour_weight: f64,
    /// Multiply the source's colours by the two maps' relative white balance
    /// (`colour::relative_white_balance`, within `max_white_balance_gain`) before the colour
    /// signatures are computed: two cameras' white balances differ, and on 7-Scenes crops 10 %
    /// more of one channel left fewer right correspondences than geometry alone
    /// (docs/benchmarks.md).
    pub balance_colours: bool,
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
    /// The relative white balance of the two maps (`balance_colours`) is searched with each
    /// channel's gain within this factor of 1 (and its inverse); the same gains apply to the
    /// colour signatures and the verification's colour check. 1: no correction.
    pub max_white_balance_gain: f64,
    /// The colour agreement is only judged over at least this many compared points.
    pub min_colour_comparisons: usize,
    /// An overlap below `min_overlap_fraction` but at least this large is accepted when its
    /// colours agree with a kappa of at least `colour_confirmed_kappa`: colours that follow the
    /// pairing that closely are evidence of the right pose that a small overlap by itself is not
    /// (the overlap threshold refuses chance alignments; a chance alignment's colours agree no
    /// better than chance). Measured kappas: true poses 0.88-0.98 on the synthetic room, turned
    /// rooms 0.25-0.58 (and 0.35 for true poses on 7-Scenes, where this never applies).
    pub colour_confirmed_overlap_fraction: f64,
    /// The colour kappa that lets an overlap of at least `colour_confirmed_overlap_fraction`
    /// stand in for `min_overlap_fraction` (judged only over `min_colour_comparisons` points).
    pub colour_confirmed_kappa: f64,

    // --- Robust pruning: cliques of the compatibility graph, then RANSAC ---
    /// Seeds of the clique search over the compatibility graph (`compatibility.rs`): each grows
    /// one clique of mutually compatible correspondences, a hypothesis. 0: RANSAC alone.
    pub clique_seeds: usize,
    /// A clique stops growing at this many correspondences (enough for a fit; the local
    /// optimisation gathers the rest of the supporters).
    pub max_clique_size: usize,
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
    /// ...and the regularisation: a covariance's singular values become (1, 1, epsilon).
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
    /// ...and translates less than this (metres). The coarse stages use ten times both.
    pub gicp_translation_epsilon_m: f64,

    // --- Verification ---
    /// RANSAC's best hypothesis needs at least this many consistent correspondences. Chance
    /// alignments of ~500 correspondences reach 8-16 on the synthetic and redkitchen maps; true
    /// ones 20-180.
    pub min_consistent_correspondences: usize,
    /// The correspondences single out the best hypothesis when no distinct alternative has more
    /// than this fraction of its support among correspondences the best does not explain
    /// (symmetric or repetitive structure, or a best hypothesis no better than chance). 0.5: the
    /// best must explain twice as much. Otherwise the alternatives above it are refined and
    /// verified too, and the verification chooses (`decision.rs`).
    pub max_ambiguity_ratio: f64,
    /// Candidates refined and verified at most when the correspondences leave them nearly tied
    /// (the best included).
    pub max_verified_hypotheses: usize,
    /// Between two verified candidates, one wins by the free-space test when its depth
    /// agreement is higher by at least this...
    pub ambiguity_free_space_margin: f64,
    /// ...else when its residual is below this fraction of the other's with an overlap of at
    /// least this fraction of the other's. Neither: refused as tied.
    pub ambiguity_residual_ratio: f64,
    /// When the correspondences leave distinct alternatives nearly tied and only one candidate
    /// passes the verification (no verified rival to beat), the overlap's colours must confirm
    /// it with at least this kappa (judged over `min_colour_comparisons` points). Passing the
    /// geometric checks while the others fail is no evidence between the ways a symmetric room
    /// fits itself: the turned room passes them as well as the true pose does, and only colour
    /// tells the turns apart. 0.5: halfway between `min_colour_kappa`, which refuses colours
    /// that merely do not contradict, and `colour_confirmed_kappa`, which vouches for a pose on
    /// its own. Maps without colour, or an overlap of one colour, cannot confirm: refused.
    pub ambiguity_colour_kappa: f64,
    /// A refined transform must keep this fraction of its hypothesis' supporting
    /// correspondences: fewer, G-ICP slid away from what the features say (`decision.rs`).
    pub min_support_kept: f64,
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
    /// The translation bound (metres) of the degeneracy test above, taken at the overlap's
    /// centre.
    pub max_translation_sigma_m: f64,
}

impl Default for MapRegistrationConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            retry_after_keyframes: 1,
            refresh_after_keyframes: 8,
            depth_check_points: 5000,
            min_depth_agreement: 0.7,
            voxel_m: 0.05,
            max_points: 10_000,
            normal_radius_voxels: 2.5,
            min_normal_neighbours: 10,
            feature_radius_voxels: 5.0,
            min_feature_neighbours: 10,
            max_matched_features: 3000,
            match_ratio: 0.0,
            max_correspondences: 5000,
            min_correspondences: 300,
            colour_weight: 1.0,
            balance_colours: true,
            colour_tolerance: 0.05,
            min_colour_kappa: 0.25,
            max_white_balance_gain: 1.3,
            min_colour_comparisons: 100,
            colour_confirmed_overlap_fraction: 0.03,
            colour_confirmed_kappa: 0.75,
            clique_seeds: 0,
            max_clique_size: 100,
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
            max_verified_hypotheses: 4,
            ambiguity_free_space_margin: 0.05,
            ambiguity_residual_ratio: 0.8,
            ambiguity_colour_kappa: 0.5,
            min_support_kept: 0.5,
            min_overlap_fraction: 0.1,
            max_residual_m: 0.03,
            residual_sigma_floor_m: 0.005,
            max_rotation_sigma_rad: 2f64.to_radians(),
            max_translation_sigma_m: 0.05,
        }
    }
}

impl MapRegistrationConfig {
    /// Checks ranges; returns the offending field (`consensus.map_registration.*`) and why.
    pub fn validate(&self) -> Result<(), FieldError> {
        self.validate_lengths()?;
        self.validate_fractions_and_counts()?;
        self.validate_shapes()
    }

    /// Distances, tolerances and weights.
    fn validate_lengths(&self) -> Result<(), FieldError> {
        for (field, v) in [
            ("consensus.map_registration.voxel_m", self.voxel_m),
            (
                "consensus.map_registration.normal_radius_voxels",
                self.normal_radius_voxels,
            ),
            (
                "consensus.map_registration.feature_radius_voxels",
                self.feature_radius_voxels,
            ),
            (
                "consensus.map_registration.inlier_distance_voxels",
                self.inlier_distance_voxels,
            ),
            (
                "consensus.map_registration.edge_tolerance_voxels",
                self.edge_tolerance_voxels,
            ),
            (
                "consensus.map_registration.covariance_epsilon",
                self.covariance_epsilon,
            ),
            (
                "consensus.map_registration.gicp_rotation_epsilon_rad",
                self.gicp_rotation_epsilon_rad,
            ),
            (
                "consensus.map_registration.gicp_translation_epsilon_m",
                self.gicp_translation_epsilon_m,
            ),
            (
                "consensus.map_registration.max_residual_m",
                self.max_residual_m,
            ),
            (
                "consensus.map_registration.residual_sigma_floor_m",
                self.residual_sigma_floor_m,
            ),
            (
                "consensus.map_registration.max_rotation_sigma_rad",
                self.max_rotation_sigma_rad,
            ),
            (
                "consensus.map_registration.max_translation_sigma_m",
                self.max_translation_sigma_m,
            ),
            (
                "consensus.map_registration.colour_tolerance",
                self.colour_tolerance,
            ),
        ] {
            positive(field, v)?;
        }
        if !(self.max_white_balance_gain >= 1.0 && self.max_white_balance_gain.is_finite()) {
            return Err((
                "consensus.map_registration.max_white_balance_gain",
                format!(
                    "must be a finite factor of at least 1, got {}",
                    self.max_white_balance_gain
                ),
            ));
        }
        for (field, v) in [
            (
                "consensus.map_registration.min_sample_spread_voxels",
                self.min_sample_spread_voxels,
            ),
            (
                "consensus.map_registration.distinct_rotation_rad",
                self.distinct_rotation_rad,
            ),
            (
                "consensus.map_registration.distinct_translation_m",
                self.distinct_translation_m,
            ),
            (
                "consensus.map_registration.colour_weight",
                self.colour_weight,
            ),
        ] {
            non_negative(field, v)?;
        }
        Ok(())
    }

    /// Probabilities, ratios and counts.
    fn validate_fractions_and_counts(&self) -> Result<(), FieldError> {
        for (field, v) in [
            (
                "consensus.map_registration.ransac_confidence",
                self.ransac_confidence,
            ),
            (
                "consensus.map_registration.max_ambiguity_ratio",
                self.max_ambiguity_ratio,
            ),
            (
                "consensus.map_registration.min_overlap_fraction",
                self.min_overlap_fraction,
            ),
            (
                "consensus.map_registration.min_colour_kappa",
                self.min_colour_kappa,
            ),
            ("consensus.map_registration.match_ratio", self.match_ratio),
            (
                "consensus.map_registration.min_depth_agreement",
                self.min_depth_agreement,
            ),
            (
                "consensus.map_registration.ambiguity_free_space_margin",
                self.ambiguity_free_space_margin,
            ),
            (
                "consensus.map_registration.ambiguity_residual_ratio",
                self.ambiguity_residual_ratio,
            ),
            (
                "consensus.map_registration.ambiguity_colour_kappa",
                self.ambiguity_colour_kappa,
            ),
            (
                "consensus.map_registration.min_support_kept",
                self.min_support_kept,
            ),
            (
                "consensus.map_registration.colour_confirmed_overlap_fraction",
                self.colour_confirmed_overlap_fraction,
            ),
            (
                "consensus.map_registration.colour_confirmed_kappa",
                self.colour_confirmed_kappa,
            ),
        ] {
            fraction(field, v)?;
        }
        for (field, v) in [
            (
                "consensus.map_registration.depth_check_points",
                self.depth_check_points,
            ),
            ("consensus.map_registration.max_points", self.max_points),
            (
                "consensus.map_registration.max_matched_features",
                self.max_matched_features,
            ),
            (
                "consensus.map_registration.refine_max_points",
                self.refine_max_points,
            ),
            (
                "consensus.map_registration.max_correspondences",
                self.max_correspondences,
            ),
            (
                "consensus.map_registration.max_verified_hypotheses",
                self.max_verified_hypotheses,
            ),
            (
                "consensus.map_registration.ransac_max_samples",
                self.ransac_max_samples,
            ),
            (
                "consensus.map_registration.gicp_max_iterations",
                self.gicp_max_iterations,
            ),
            (
                "consensus.map_registration.min_colour_comparisons",
                self.min_colour_comparisons,
            ),
        ] {
            at_least_one(field, v)?;
        }
        Ok(())
    }

    /// What the geometry needs: enough neighbours for a plane, enough correspondences for a rigid
    /// transform, a coarse-to-fine schedule.
    fn validate_shapes(&self) -> Result<(), FieldError> {
        for (field, v) in [
            (
                "consensus.map_registration.min_normal_neighbours",
                self.min_normal_neighbours,
            ),
            (
                "consensus.map_registration.covariance_neighbours",
                self.covariance_neighbours,
            ),
        ] {
            if v < 3 {
                return Err((field, "a plane needs at least 3 neighbours".into()));
            }
        }
        if self.min_consistent_correspondences < 3 {
            return Err((
                "consensus.map_registration.min_consistent_correspondences",
                "a rigid transform needs at least 3 correspondences".into(),
            ));
        }
        if self.refine_distances_voxels.is_empty()
            || self
                .refine_distances_voxels
                .iter()
                .any(|d| !(d.is_finite() && *d > 0.0))
            || self.refine_distances_voxels.windows(2).any(|w| w[1] > w[0])
        {
            return Err((
                "consensus.map_registration.refine_distances_voxels",
                "must be a non-empty list of positive distances, coarse to fine (decreasing)"
                    .into(),
            ));
        }
        Ok(())
    }
}
