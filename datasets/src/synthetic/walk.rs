//! The agents' camera paths: smooth loops around the table, alternating direction, with gaze
//! wander, head-bob and roll; consecutive agents cover overlapping stretches of the same loop.

use std::f64::consts::TAU;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::RngExt;

use super::spec::SyntheticSpec;
use super::{TRAJECTORY_STREAM, stream_rng, symmetric};

/// The agents' walking loop: an ellipse around the table, radii in metres.
const LOOP_RADII: [f64; 2] = [1.85, 1.35];
/// Per-agent scale of the loop (agents walk slightly different loops) and its slow wobble.
const LOOP_SCALE_JITTER: f64 = 0.05;
const LOOP_WOBBLE: f64 = 0.05;
/// Walking speed: metres per frame at 30 Hz (0.6 m/s), varying by +-SPEED_VARIATION.
const STEP_LENGTH: f64 = 0.02;
const SPEED_VARIATION: f64 = 0.25;
const SPEED_PERIOD_FRAMES: f64 = 210.0;
/// Eye height, its slow variation and the walking head-bob (one bob per step, ~2 steps/s).
const EYE_HEIGHT: f64 = 1.45;
const EYE_HEIGHT_SWAY: f64 = 0.1;
const EYE_HEIGHT_PERIOD_FRAMES: f64 = 420.0;
const HEAD_BOB: f64 = 0.006;
const HEAD_BOB_PERIOD_FRAMES: f64 = 16.0;
/// The gaze point wanders around the table so views sweep over different parts of the room.
const GAZE_CENTER_HEIGHT: f64 = 0.8;
/// The gaze point lies beyond the room's centre by this fraction of the camera's horizontal
/// distance to the centre: the camera looks across the room (more walls in view) and, the gaze
/// point being farther, walking turns the view more gently.
const GAZE_BEYOND_CENTER: f64 = 0.4;
const GAZE_WANDER: [f64; 3] = [0.55, 0.45, 0.3];
const GAZE_PERIOD_FRAMES: [f64; 3] = [400.0, 330.0, 280.0];
/// Slow camera roll (radians) of a hand-held camera.
const ROLL_AMPLITUDE: f64 = 0.04;
const ROLL_PERIOD_FRAMES: f64 = 300.0;
/// Start-angle jitter around the evenly spread starting points (radians).
const START_ANGLE_JITTER: f64 = 0.1;
/// Angle step for the numerical derivative of the loop.
const LOOP_DERIVATIVE_STEP: f64 = 1e-5;

/// Smooth, seeded parameters of one agent's walk.
struct Walk {
    start_angle: f64,
    /// +1 counter-clockwise, -1 clockwise; agents alternate so neighbours walk towards each
    /// other's stretches and see the same places from similar viewpoints.
    pub(super) direction: f64,
    pub(super) scale: f64,
    wobble_phase: f64,
    speed_phase: f64,
    height_phase: f64,
    bob_phase: f64,
    gaze_phases: [f64; 3],
    roll_phase: f64,
}

impl Walk {
    pub(super) fn new(seed: u64, agents: usize, agent: usize) -> Self {
        let mut rng = stream_rng(seed, TRAJECTORY_STREAM.wrapping_add(agent as u64));
        let mut phase = || rng.random_range(0.0..TAU);
        let gaze_phases = [phase(), phase(), phase()];
        let (wobble_phase, speed_phase, height_phase, bob_phase, roll_phase) =
            (phase(), phase(), phase(), phase(), phase());
        let start_angle =
            TAU * agent as f64 / agents as f64 + symmetric(&mut rng, START_ANGLE_JITTER);
        let scale = 1.0 + symmetric(&mut rng, LOOP_SCALE_JITTER);
        let direction = if agent.is_multiple_of(2) { 1.0 } else { -1.0 };
        Self {
            start_angle,
            direction,
            scale,
            wobble_phase,
            speed_phase,
            height_phase,
            bob_phase,
            gaze_phases,
            roll_phase,
        }
    }

    /// Horizontal position on the loop at `angle`.
    fn loop_point(&self, angle: f64) -> [f64; 2] {
        let radius_scale =
            self.scale * (1.0 + LOOP_WOBBLE * (2.0 * angle + self.wobble_phase).sin());
        [
            radius_scale * LOOP_RADII[0] * angle.cos(),
            radius_scale * LOOP_RADII[1] * angle.sin(),
        ]
    }

    /// Metres walked per radian of loop angle at `angle`.
    fn loop_speed(&self, angle: f64) -> f64 {
        let a = self.loop_point(angle - LOOP_DERIVATIVE_STEP);
        let b = self.loop_point(angle + LOOP_DERIVATIVE_STEP);
        (b[0] - a[0]).hypot(b[1] - a[1]) / (2.0 * LOOP_DERIVATIVE_STEP)
    }

    pub(super) fn pose(&self, angle: f64, frame: f64) -> Isometry3<f64> {
        let [x, y] = self.loop_point(angle);
        let z = EYE_HEIGHT
            + EYE_HEIGHT_SWAY * (TAU * frame / EYE_HEIGHT_PERIOD_FRAMES + self.height_phase).sin()
            + HEAD_BOB * (TAU * frame / HEAD_BOB_PERIOD_FRAMES + self.bob_phase).sin();
        let position = Vector3::new(x, y, z);
        let wander = |axis: usize| {
            GAZE_WANDER[axis]
                * (TAU * frame / GAZE_PERIOD_FRAMES[axis] + self.gaze_phases[axis]).sin()
        };
        let gaze = Vector3::new(
            wander(0) - GAZE_BEYOND_CENTER * x,
            wander(1) - GAZE_BEYOND_CENTER * y,
            GAZE_CENTER_HEIGHT + wander(2),
        );
        let roll = ROLL_AMPLITUDE * (TAU * frame / ROLL_PERIOD_FRAMES + self.roll_phase).sin();
        Isometry3::from_parts(
            Translation3::from(position),
            look_at(&position, &gaze, roll),
        )
    }
}

/// Camera orientation (x right, y down, z forward) looking from `eye` to `target` with the world
/// z axis up, then rolled about the optical axis.
pub(super) fn look_at(eye: &Vector3<f64>, target: &Vector3<f64>, roll: f64) -> UnitQuaternion<f64> {
    let forward = (target - eye).normalize();
    let right = forward.cross(&Vector3::z()).normalize();
    let down = forward.cross(&right);
    let world_from_camera = Matrix3::from_columns(&[right, down, forward]);
    let rolled =
        world_from_camera * Rotation3::from_axis_angle(&Vector3::z_axis(), roll).into_inner();
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rolled))
}

/// Ground-truth `world_from_camera` of every frame of one agent.
pub(super) fn trajectory(spec: &SyntheticSpec) -> Vec<Isometry3<f64>> {
    let walk = Walk::new(spec.seed, spec.agents, spec.agent);
    let mut angle = walk.start_angle;
    let mut poses = Vec::with_capacity(spec.frames);
    for frame in 0..spec.frames {
        let frame = frame as f64;
        poses.push(walk.pose(angle, frame));
        let step = STEP_LENGTH
            * (1.0
                + SPEED_VARIATION * (TAU * frame / SPEED_PERIOD_FRAMES + walk.speed_phase).sin());
        angle += walk.direction * step / walk.loop_speed(angle);
    }
    poses
}
