//! Consensus corrections applied to the agent's local maps between frames (docs/method.md, Corrections and the world frame;
//! step 4; `[consensus.local_corrections]`).
//!
//! A correction carries `world_from_agent` and the corrected world pose of every keyframe the
//! agent published. In the agent's own frame that is a [`CorrectionField`]: at each published
//! keyframe's time, `agent_from_world * world_from_camera_corrected * agent_from_camera_tracked^-1`,
//! blended in between (the consensus's rule for per-frame trajectories). Everything the agent
//! built at time `t` for its map (seeded Gaussians, keyframe poses, coverage index) moves by
//! `target(t) * applied(t)^-1`, where `applied` is the field already applied: each part of the
//! map follows the keyframe that made it, so drift the pose graph removed leaves the local map
//! too.
//!
//! Two frames, one rule: the *tracked* frame is where the odometry would have been without
//! corrections; the *local-map* frame is `applied` applied to it. Everything the agent publishes
//! or writes as its trajectory is in the tracked frame, because the consensus builds its
//! odometry edges and per-frame trajectories from tracked poses: a correction must never show
//! up as motion in them. By default the tracking map stays in the tracked frame
//! (`move_tracking_map = false`): the odometry's poses are tracked poses, and each is carried
//! into the local-map frame (`applied(t)`) for seeding and mapping. With `move_tracking_map`,
//! tracking-map points move too, tracking runs in the local-map frame and its poses are
//! converted back (`applied(t)^-1`); the current frame is after every anchor, so its conversion
//! is the newest anchor's correction, continuous across an application. That mode leaks part
//! of a non-rigid correction into the tracked poses (config/src/consensus/mod.rs says how).

use std::time::Instant;

use config::LocalCorrectionConfig;
use geometry::correction::{CorrectionField, correction};
use geometry::se3::rotation_angle;
use nalgebra::Isometry3;
use registration::odometry::Odometry;
use registration::voxel_map::MapPointId;
use serde::Serialize;
use splats::RigidTransform;

use crate::mapper::Mapper;
use crate::seeding::CoverageIndex;

/// A correction as the agent received it.
#[derive(Debug, Clone, PartialEq)]
pub struct ReceivedCorrection {
    /// The agent's tracked frame in the world (agent 0's frame): the rigid transform that best
    /// maps its tracked keyframes onto their corrected poses.
    pub world_from_agent: Isometry3<f64>,
    /// `(keyframe id, corrected world_from_camera)` of the agent's published keyframes.
    pub keyframes: Vec<(u64, Isometry3<f64>)>,
}

/// What the corrections did, for metrics.json.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LocalCorrectionStats {
    /// Corrections that moved the local maps.
    pub applied: usize,
    /// Corrections that would have moved no keyframe by the configured minimum.
    pub below_threshold: usize,
    /// Corrections received while `apply` is off.
    pub not_applied_disabled: usize,
    /// Keyframe poses in corrections that name a keyframe this run never made (an earlier
    /// incarnation's, after a restart): ignored.
    pub unknown_keyframes: usize,
    /// Largest translation of a keyframe's part of the map (or of the current pose) by an
    /// applied correction, metres.
    pub largest_translation_m: f64,
    /// Largest rotation of a keyframe's part of the map (or of the current pose) by an applied
    /// correction, in degrees.
    pub largest_rotation_deg: f64,
    /// Time the tracking thread spent applying corrections (milliseconds, all together).
    pub tracking_thread_ms: f64,
}

/// A keyframe as the corrections need it.
#[derive(Debug, Clone, Copy)]
struct KeyframeRecord {
    timestamp_s: f64,
    /// Pose in the tracked frame (as published).
    tracked_agent_from_camera: Isometry3<f64>,
    /// The correction its part of the mapping map carries now.
    applied: Isometry3<f64>,
}

/// Points of an index made at one time: ids from `first_id` up to the next run's first id.
#[derive(Debug, Clone, Copy)]
struct PointRun {
    first_id: MapPointId,
    timestamp_s: f64,
    /// The correction these points carry now.
    applied: Isometry3<f64>,
}

/// The corrections state of one agent run. See the module documentation.
#[derive(Debug)]
pub struct LocalCorrections {
    config: LocalCorrectionConfig,
    applied: CorrectionField,
    /// Indexed by keyframe id (ids count up from 0 in the order keyframes are made).
    keyframes: Vec<KeyframeRecord>,
    tracker_runs: Vec<PointRun>,
    coverage_runs: Vec<PointRun>,
    stats: LocalCorrectionStats,
}

/// The parts of the agent a correction moves.
pub struct LocalMaps<'a> {
    /// The tracker; its tracking map moves only with `move_tracking_map`.
    pub odometry: &'a mut Odometry,
    /// The seeded means that decide which points of a keyframe seed.
    pub coverage: &'a mut CoverageIndex,
    /// The mapping thread: each keyframe's Gaussians and pose move by that keyframe's share.
    pub mapper: &'a Mapper,
}

impl LocalCorrections {
    /// No correction applied yet (the identity field) and no keyframe recorded.
    pub fn new(config: &LocalCorrectionConfig) -> Self {
        Self {
            config: config.clone(),
            applied: CorrectionField::default(),
            keyframes: Vec::new(),
            tracker_runs: Vec::new(),
            coverage_runs: Vec::new(),
            stats: LocalCorrectionStats::default(),
        }
    }

    /// The field applied so far (tracked frame -> local-map frame). Parts of the tracking map
    /// and coverage index whose own move was below the part thresholds still carry an older
    /// correction, within those thresholds of this field.
    pub fn applied(&self) -> &CorrectionField {
        &self.applied
    }

    /// What the corrections did so far.
    pub fn stats(&self) -> &LocalCorrectionStats {
        &self.stats
    }

    /// A pose of the local-map frame at time `t` in the tracked frame.
    pub fn to_tracked(&self, t: f64, local_from_camera: &Isometry3<f64>) -> Isometry3<f64> {
        normalised(self.tracked_from_local(t) * local_from_camera)
    }

    /// Whether the tracking map moves with the corrections (`move_tracking_map`): then the
    /// odometry's poses are in the local-map frame, else in the tracked frame.
    fn moves_tracking_map(&self) -> bool {
        self.config.move_tracking_map
    }

    /// The pose the odometry gave for the frame at time `t`, as `(local-map frame, tracked
    /// frame)`.
    pub fn from_odometry(
        &self,
        t: f64,
        odometry_from_camera: &Isometry3<f64>,
    ) -> (Isometry3<f64>, Isometry3<f64>) {
        if self.moves_tracking_map() {
            (
                *odometry_from_camera,
                self.to_tracked(t, odometry_from_camera),
            )
        } else {
            (
                normalised(self.applied.at(t) * odometry_from_camera),
                *odometry_from_camera,
            )
        }
    }

    /// The transform from the local-map frame at time `t` to the tracked frame.
    pub fn tracked_from_local(&self, t: f64) -> Isometry3<f64> {
        self.applied.at(t).inverse()
    }

    /// Records keyframe `keyframe_id` (the next id: ids count up from 0) made at `timestamp_s`
    /// with its pose in the tracked frame.
    pub fn record_keyframe(
        &mut self,
        keyframe_id: usize,
        timestamp_s: f64,
        tracked_agent_from_camera: Isometry3<f64>,
    ) {
        debug_assert_eq!(keyframe_id, self.keyframes.len(), "keyframe ids count up");
        self.keyframes.push(KeyframeRecord {
            timestamp_s,
            tracked_agent_from_camera,
            // Made in the local-map frame as it is now.
            applied: self.applied.at(timestamp_s),
        });
    }

    /// Records that the tracking map's points from `first_id` on were made at `timestamp_s`
    /// (nothing to record when the tracking map does not move).
    pub fn record_tracker_points(&mut self, first_id: MapPointId, timestamp_s: f64) {
        if !self.moves_tracking_map() {
            return;
        }
        let applied = self.applied.at(timestamp_s);
        push_run(&mut self.tracker_runs, first_id, timestamp_s, applied);
    }

    /// Records that the coverage index's means from `first_id` on were made at `timestamp_s`.
    pub fn record_coverage_points(&mut self, first_id: MapPointId, timestamp_s: f64) {
        let applied = self.applied.at(timestamp_s);
        push_run(&mut self.coverage_runs, first_id, timestamp_s, applied);
    }

    /// The field `correction` asks for, in this agent's frame. `None` when it names none of
    /// this run's keyframes.
    fn target_field(&mut self, received: &ReceivedCorrection) -> Option<CorrectionField> {
        let agent_from_world = received.world_from_agent.inverse();
        let mut anchors = Vec::with_capacity(received.keyframes.len());
        for (keyframe_id, world_from_camera) in &received.keyframes {
            let Some(record) = usize::try_from(*keyframe_id)
                .ok()
                .and_then(|id| self.keyframes.get(id))
            else {
                self.stats.unknown_keyframes += 1;
                continue;
            };
            anchors.push((
                record.timestamp_s,
                agent_from_world * correction(world_from_camera, &record.tracked_agent_from_camera),
            ));
        }
        (!anchors.is_empty()).then(|| CorrectionField::from_anchors(anchors))
    }

    /// Applies `received` to the local maps (between frames, on the tracking thread; the mapper
    /// gets its share over its channel). `now_s` is the current frame's time. Returns true when
    /// the maps moved.
    pub fn apply(
        &mut self,
        received: &ReceivedCorrection,
        now_s: f64,
        maps: LocalMaps<'_>,
    ) -> bool {
        let clock = Instant::now();
        let Some(target) = self.target_field(received) else {
            return false;
        };
        if !self.config.apply {
            self.stats.not_applied_disabled += 1;
            return false;
        }
        // Per keyframe: how far its part of the map moves.
        let keyframe_moves: Vec<Isometry3<f64>> = self
            .keyframes
            .iter()
            .map(|k| moved_by(&target.at(k.timestamp_s), &k.applied))
            .collect();
        let current_move = moved_by(&target.at(now_s), &self.applied.at(now_s));
        let (largest_translation, largest_rotation) = keyframe_moves
            .iter()
            .chain(std::iter::once(&current_move))
            .fold((0.0f64, 0.0f64), |(t, r), m| {
                (t.max(m.translation.vector.norm()), r.max(rotation_angle(m)))
            });
        if largest_translation < self.config.min_translation_m
            && largest_rotation < self.config.min_rotation_rad
        {
            self.stats.below_threshold += 1;
            return false;
        }
        let _span = tracing::info_span!("apply correction").entered();
        let moved_points = if self.moves_tracking_map() {
            let tracker_moves = settle_runs(&mut self.tracker_runs, &target, &self.config);
            maps.odometry.apply_correction(
                |id| lookup_run(&self.tracker_runs, &tracker_moves, id),
                &current_move,
            )
        } else {
            0
        };
        let coverage_moves = settle_runs(&mut self.coverage_runs, &target, &self.config);
        maps.coverage
            .transform_points(|id| lookup_run(&self.coverage_runs, &coverage_moves, id));
        // The device transforms every Gaussian anyway: negligible moves go as they are.
        maps.mapper.correct(
            keyframe_moves
                .iter()
                .map(RigidTransform::from)
                .collect::<Vec<RigidTransform>>(),
        );
        for keyframe in &mut self.keyframes {
            keyframe.applied = normalised(target.at(keyframe.timestamp_s));
        }
        self.applied = target;
        self.stats.applied += 1;
        self.stats.largest_translation_m =
            self.stats.largest_translation_m.max(largest_translation);
        self.stats.largest_rotation_deg = self
            .stats
            .largest_rotation_deg
            .max(largest_rotation.to_degrees());
        let elapsed_ms = clock.elapsed().as_secs_f64() * 1e3;
        self.stats.tracking_thread_ms += elapsed_ms;
        tracing::info!(
            // The frame's time (dataset clock) locates the application on the trajectory.
            frame_time_s = now_s,
            current_pose_move_m = current_move.translation.vector.norm(),
            keyframes = keyframe_moves.len(),
            tracking_points = moved_points,
            largest_move_m = largest_translation,
            largest_turn_deg = largest_rotation.to_degrees(),
            elapsed_ms,
            "correction applied to the local maps"
        );
        true
    }
}

/// `target * applied^-1`: how a part that carries the correction `applied` moves to carry
/// `target`.
fn moved_by(target: &Isometry3<f64>, applied: &Isometry3<f64>) -> Isometry3<f64> {
    normalised(target * applied.inverse())
}

fn normalised(mut pose: Isometry3<f64>) -> Isometry3<f64> {
    pose.rotation.renormalize();
    pose
}

/// Per run, its move to `target`, or `None` when that is below the configured part thresholds
/// (the run stays, and keeps what it carries, so nothing skipped is lost: a later correction
/// moves it the whole way). Moved runs now carry `target`.
fn settle_runs(
    runs: &mut [PointRun],
    target: &CorrectionField,
    config: &LocalCorrectionConfig,
) -> Vec<Option<Isometry3<f64>>> {
    runs.iter_mut()
        .map(|run| {
            let wanted = target.at(run.timestamp_s);
            let moved = moved_by(&wanted, &run.applied);
            let significant = moved.translation.vector.norm() >= config.part_min_translation_m
                || rotation_angle(&moved) >= config.part_min_rotation_rad;
            significant.then(|| {
                run.applied = normalised(wanted);
                moved
            })
        })
        .collect()
}

fn push_run(
    runs: &mut Vec<PointRun>,
    first_id: MapPointId,
    timestamp_s: f64,
    applied: Isometry3<f64>,
) {
    debug_assert!(runs.last().is_none_or(|last| last.first_id <= first_id));
    runs.push(PointRun {
        first_id,
        timestamp_s,
        applied,
    });
}

/// The move of the run point `id` belongs to (`None` before the first run).
fn lookup_run(
    runs: &[PointRun],
    moves: &[Option<Isometry3<f64>>],
    id: MapPointId,
) -> Option<Isometry3<f64>> {
    let after = runs.partition_point(|run| run.first_id <= id);
    moves[after.checked_sub(1)?]
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn pose(x: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(x, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, yaw, 0.0),
        )
    }

    #[test]
    fn target_field_maps_tracked_keyframes_onto_their_corrected_poses() {
        let mut corrections = LocalCorrections::new(&LocalCorrectionConfig::default());
        let tracked = [pose(0.0, 0.0), pose(1.0, 0.1), pose(2.0, 0.2)];
        for (id, p) in tracked.iter().enumerate() {
            corrections.record_keyframe(id, id as f64, *p);
        }
        let world_from_agent = pose(5.0, 1.0);
        // The consensus moved keyframe 2 by 3 cm; 0 and 1 stay; keyframe 9 is unknown.
        let drift_fix = Isometry3::translation(0.0, 0.03, 0.0);
        let received = ReceivedCorrection {
            world_from_agent,
            keyframes: vec![
                (0, world_from_agent * tracked[0]),
                (1, world_from_agent * tracked[1]),
                (2, world_from_agent * drift_fix * tracked[2]),
                (9, Isometry3::identity()),
            ],
        };
        let field = corrections.target_field(&received).unwrap();
        assert_eq!(corrections.stats.unknown_keyframes, 1);
        for (id, p) in tracked.iter().enumerate() {
            let expected = if id == 2 { drift_fix * p } else { *p };
            let got = field.at(id as f64) * p;
            assert!(
                (got.to_homogeneous() - expected.to_homogeneous())
                    .abs()
                    .max()
                    < 1e-9,
                "keyframe {id}"
            );
        }
        // Half-way between 1 and 2 the fix is half applied.
        assert!((field.at(1.5).translation.vector.y - 0.015).abs() < 1e-9);
    }

    #[test]
    fn points_take_the_move_of_the_run_that_made_them_and_small_moves_wait() {
        let run = |first_id, timestamp_s| PointRun {
            first_id,
            timestamp_s,
            applied: Isometry3::identity(),
        };
        let mut runs = [run(0, 0.0), run(10, 1.0), run(20, 2.0)];
        // Run 0 moves 0.1 mm (below the part threshold), runs 1 and 2 by 1 and 2 cm.
        let target = CorrectionField::from_anchors([
            (0.0, Isometry3::translation(1e-4, 0.0, 0.0)),
            (1.0, Isometry3::translation(0.01, 0.0, 0.0)),
            (2.0, Isometry3::translation(0.02, 0.0, 0.0)),
        ]);
        let config = LocalCorrectionConfig::default();
        let moves = settle_runs(&mut runs, &target, &config);
        assert_eq!(lookup_run(&runs, &moves, 0), None, "too small to move");
        assert_eq!(lookup_run(&runs, &moves, 9), None);
        let x = |id| lookup_run(&runs, &moves, id).unwrap().translation.vector.x;
        assert!((x(10) - 0.01).abs() < 1e-12 && (x(19) - 0.01).abs() < 1e-12);
        assert!((x(20) - 0.02).abs() < 1e-12 && (x(1000) - 0.02).abs() < 1e-12);
        // What moved carries the target now; what waited still carries what it had, so the
        // same target again moves nothing and a larger one moves run 0 the whole way.
        assert_eq!(runs[0].applied, Isometry3::identity());
        assert!(
            settle_runs(&mut runs, &target, &config)
                .iter()
                .all(Option::is_none)
        );
        let further =
            CorrectionField::from_anchors([(0.0, Isometry3::translation(0.005, 0.0, 0.0))]);
        let moves = settle_runs(&mut runs, &further, &config);
        assert!((moves[0].unwrap().translation.vector.x - 0.005).abs() < 1e-12);
        let late = [run(5, 0.0)];
        assert_eq!(lookup_run(&late, &[Some(Isometry3::identity())], 4), None);
    }

    #[test]
    fn tracked_poses_are_continuous_across_an_application() {
        let mut corrections = LocalCorrections::new(&LocalCorrectionConfig::default());
        corrections.record_keyframe(0, 0.0, pose(0.0, 0.0));
        corrections.record_keyframe(1, 1.0, pose(1.0, 0.0));
        let fix = Isometry3::translation(0.0, 0.05, 0.0);
        let target = CorrectionField::from_anchors([(0.0, Isometry3::identity()), (1.0, fix)]);
        // The current pose (after every keyframe) in the local-map frame before and after.
        let local_before = pose(1.2, 0.05);
        let tracked_before = corrections.to_tracked(2.0, &local_before);
        let local_after = moved_by(&target.at(2.0), &corrections.applied.at(2.0)) * local_before;
        corrections.applied = target;
        let tracked_after = corrections.to_tracked(2.0, &local_after);
        assert!(
            (tracked_before.to_homogeneous() - tracked_after.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
        assert!((local_after.translation.vector.y - 0.05).abs() < 1e-12);
    }

    // A consensus correction applied to the local maps: after the tracking map is moved,
    // tracking goes on in the moved map, and the poses the agent publishes (its tracked frame)
    // do not jump. Two odometries track the same synthetic frames. One is left alone (the
    // reference). The other gets, after frame CORRECT_AFTER, a correction saying that every
    // keyframe it made sits `fix` away from where it was tracked (a rigid fix of the whole
    // map: easy to predict). From then on its local-map poses must be `fix * reference` and
    // its tracked-frame poses equal to the reference.
    mod end_to_end {
        use super::*;
        use crate::mapper::Mapper;
        use config::Config;
        use datasets::{self, FrameRange};
        use registration::odometry::OdometryMode;

        const FRAMES: usize = 24;
        const CORRECT_AFTER: usize = 12;
        /// Tracking repeats to well below a millimetre on exact synthetic depth.
        const TOLERANCE_M: f64 = 2e-3;
        const TOLERANCE_RAD: f64 = 2e-3;

        fn distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
            let d = a.inverse() * b;
            (d.translation.vector.norm(), d.rotation.angle())
        }

        #[test]
        fn tracking_continues_in_the_corrected_map_and_published_poses_do_not_jump() {
            corrected_run(true);
        }

        // With the tracking map left where the odometry put it, the odometry is plain
        // odometry (its poses are the reference's) and only the local-map poses move.
        #[test]
        fn a_tracking_map_left_alone_tracks_as_without_corrections() {
            corrected_run(false);
        }

        fn corrected_run(move_tracking_map: bool) {
            let config = Config::default();
            let dataset = datasets::open(
                &format!("synthetic:agents=2,agent=0,frames={FRAMES},width=320,height=240"),
                FrameRange::ALL,
            )
            .unwrap();
            let new_odometry = || {
                Odometry::new(
                    OdometryMode::FrameToModel,
                    &config.tracking,
                    &config.keyframes,
                )
            };
            let mut reference = new_odometry();
            let mut odometry = new_odometry();
            let mut coverage = CoverageIndex::new(0.02);
            let mapper = Mapper::spawn(&config.tracking, &config.mapping).unwrap();
            let mut corrections = LocalCorrections::new(&LocalCorrectionConfig {
                move_tracking_map,
                ..LocalCorrectionConfig::default()
            });
            let fix = Isometry3::from_parts(
                Translation3::new(0.04, -0.02, 0.03),
                UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
            );
            let mut keyframes = Vec::new();
            let mut checked = 0;
            for position in 0..dataset.len() {
                let frame = dataset.load(position).unwrap();
                let input = registration::FrameInput {
                    timestamp_s: frame.timestamp,
                    depth: &frame.depth,
                    rgb: Some(&frame.rgb),
                    intrinsics: &frame.intrinsics,
                    colour_offset_s: frame.colour_offset_s,
                    real_time: false,
                };
                let expected = reference.track(input).world_from_camera;
                let first_point = odometry.next_point_id();
                let tracked = odometry.track(input);
                if odometry.next_point_id() > first_point {
                    corrections.record_tracker_points(first_point, frame.timestamp);
                }
                let (local_pose, tracked_pose) =
                    corrections.from_odometry(frame.timestamp, &tracked.world_from_camera);
                if !move_tracking_map {
                    let (m, rad) = distance(&tracked.world_from_camera, &expected);
                    assert!(
                        m < TOLERANCE_M && rad < TOLERANCE_RAD,
                        "frame {position}: odometry {m} m / {rad} rad from the reference"
                    );
                }
                if tracked.keyframe {
                    corrections.record_keyframe(keyframes.len(), frame.timestamp, tracked_pose);
                    keyframes.push(tracked_pose);
                }
                if position > CORRECT_AFTER {
                    let (local_m, local_rad) = distance(&local_pose, &(fix * expected));
                    assert!(
                        local_m < TOLERANCE_M && local_rad < TOLERANCE_RAD,
                        "frame {position}: local-map pose {local_m} m / {local_rad} rad from fix * reference"
                    );
                    checked += 1;
                }
                let (m, rad) = distance(&tracked_pose, &expected);
                assert!(
                    m < TOLERANCE_M && rad < TOLERANCE_RAD,
                    "frame {position}: tracked-frame pose {m} m / {rad} rad from the reference"
                );
                if position == CORRECT_AFTER {
                    assert!(keyframes.len() >= 2, "the scene makes keyframes");
                    // The consensus: agent 1's frame is 3 m and 90 degrees away (irrelevant to the local
                    // maps), and every keyframe of this agent belongs `fix` away.
                    let world_from_agent = Isometry3::from_parts(
                        Translation3::new(3.0, 0.0, 0.0),
                        UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
                    );
                    let received = ReceivedCorrection {
                        world_from_agent,
                        keyframes: keyframes
                            .iter()
                            .enumerate()
                            .map(|(id, pose)| (id as u64, world_from_agent * fix * pose))
                            .collect(),
                    };
                    let mut apply_received = |corrections: &mut LocalCorrections| {
                        corrections.apply(
                            &received,
                            frame.timestamp,
                            LocalMaps {
                                odometry: &mut odometry,
                                coverage: &mut coverage,
                                mapper: &mapper,
                            },
                        )
                    };
                    assert!(apply_received(&mut corrections));
                    assert_eq!(corrections.stats().applied, 1);
                    // The same correction again moves nothing: it is below the threshold now.
                    assert!(!apply_received(&mut corrections));
                    assert_eq!(corrections.stats().below_threshold, 1);
                }
            }
            assert_eq!(checked, FRAMES - CORRECT_AFTER - 1);
            let outcome = mapper.finish(0).unwrap();
            assert_eq!(outcome.realtime.corrections, 1);
        }
    }
}
