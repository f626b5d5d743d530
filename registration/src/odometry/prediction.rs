//! The ordinary path's initial guess (docs/method.md, One agent: Tracking, "Initial guess"):
//! the constant-velocity prediction, unless the previous pose itself finds more
//! correspondences.

use nalgebra::Isometry3;

use crate::gicp::{
    GicpParams, JointTerm, RegistrationResult, RegistrationTarget, RivalGuess,
    count_correspondences, register_joint_unless_outscored,
};
use crate::points::PointCloud;

/// The initial-guess check scores every n-th point: a few thousand searches separate a good
/// prediction from a bad one as clearly as ten thousand do, at a quarter of the cost.
const INITIAL_GUESS_SAMPLE_STEP: usize = 4;

/// Where the ordinary G-ICP starts: the constant-velocity prediction or the previous pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InitialGuess {
    Prediction,
    Still,
}

impl InitialGuess {
    fn other(self) -> Self {
        match self {
            Self::Prediction => Self::Still,
            Self::Still => Self::Prediction,
        }
    }
}

/// The constant-velocity model: the motion of the last tracked step and the time it took.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ConstantVelocity {
    /// `previous_from_current` of the last tracked step.
    pub motion: Isometry3<f64>,
    /// Seconds the motion took; `None` before two tracked frames or when their timestamps did
    /// not increase (the motion is then taken as per frame).
    pub span_s: Option<f64>,
}

impl ConstantVelocity {
    /// The motion over `span_s` seconds since the previous frame: the last step's motion scaled
    /// by the ratio of the two spans (rotation angle and translation alike), or as it is when
    /// either span is unknown.
    pub fn over(&self, span_s: Option<f64>) -> Isometry3<f64> {
        let (Some(span_s), Some(velocity_span_s)) = (span_s, self.span_s) else {
            return self.motion;
        };
        let ratio = span_s / velocity_span_s;
        if (ratio - 1.0).abs() < 1e-6 {
            return self.motion;
        }
        self.scaled(ratio)
    }

    /// The camera `offset_s` seconds later (earlier when negative) seen from the camera now, at
    /// this velocity: `now_from_later`. The identity for a zero offset, or when the velocity's
    /// span is unknown (there is no time to scale by).
    pub fn now_from_later(&self, offset_s: f64) -> Isometry3<f64> {
        match self.span_s {
            Some(span_s) if offset_s != 0.0 && offset_s.is_finite() => {
                // The motion is `previous_from_current` over `span_s`: at a constant velocity
                // it is also `now_from_later` over the same span.
                self.scaled(offset_s / span_s)
            }
            _ => Isometry3::identity(),
        }
    }

    /// The motion with its rotation angle and translation times `ratio` (negative: reversed).
    fn scaled(&self, ratio: f64) -> Isometry3<f64> {
        let rotation = self.motion.rotation.powf(ratio);
        Isometry3::from_parts((self.motion.translation.vector * ratio).into(), rotation)
    }
}

/// G-ICP of `source` against `target`, started at `world_from_previous` advanced by `velocity`,
/// unless placing the frame at the previous pose (zero motion) finds more correspondences.
///
/// Why check: where the scene constrains one direction weakly (e.g. the camera moving along a
/// counter top), G-ICP stops early and its motion estimate keeps part of the prediction's error;
/// fed forward as the next prediction the error compounds (on redkitchen frames 38-44 the
/// forward motion doubled every frame until tracking was lost). One sampled search per
/// hypothesis, no optimisation, catches a prediction that is worse than standing still.
///
/// G-ICP starts from `first`, the guess that won the previous frame, and its first search also
/// counts that guess's correspondences (`register_unless_outscored`): only the other guess gets
/// a sampled search of its own, and G-ICP starts over from it only when it wins. Without a
/// constant-velocity model (`use_velocity` false, or no motion yet) it starts from the previous
/// pose. `term` (the photometric term) is minimised with G-ICP in whichever run gives the
/// result. Returns the result and the guess it started from.
#[allow(
    clippy::too_many_arguments,
    reason = "one registration's inputs, each used once; a struct would only rename them"
)]
pub fn register_from_prediction<T: RegistrationTarget + ?Sized>(
    source: &PointCloud,
    target: &T,
    velocity: &Isometry3<f64>,
    world_from_previous: &Isometry3<f64>,
    params: &GicpParams,
    use_velocity: bool,
    first: InitialGuess,
    mut term: Option<&mut dyn JointTerm>,
) -> (RegistrationResult, InitialGuess) {
    let start = |guess: InitialGuess| match guess {
        InitialGuess::Prediction => world_from_previous * velocity,
        InitialGuess::Still => *world_from_previous,
    };
    let register = |initial: &Isometry3<f64>, rival, term: Option<&mut dyn JointTerm>| {
        register_joint_unless_outscored(source, target, initial, params, rival, term)
    };
    if !use_velocity || *velocity == Isometry3::identity() {
        let guess = InitialGuess::Still;
        let result = register(&start(guess), None, term).expect("no rival: never given up");
        return (result, guess);
    }
    let other = first.other();
    let rival = RivalGuess {
        sample_step: INITIAL_GUESS_SAMPLE_STEP,
        matches: count_correspondences(
            source,
            target,
            &start(other),
            params.max_correspondence_m,
            INITIAL_GUESS_SAMPLE_STEP,
        ),
        // A tie goes to the prediction.
        wins_ties: other == InitialGuess::Prediction,
    };
    let first_term = term.as_mut().map(|t| &mut **t as &mut dyn JointTerm);
    match register(&start(first), Some(rival), first_term) {
        Some(result) => (result, first),
        None => {
            let result = register(&start(other), None, term).expect("no rival: never given up");
            (result, other)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    #[test]
    fn the_constant_velocity_motion_scales_with_the_time_between_frames() {
        let step = Isometry3::from_parts(
            Translation3::new(0.01, -0.02, 0.005),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.02),
        );
        let mut velocity = ConstantVelocity {
            motion: step,
            span_s: None,
        };
        // Unknown spans: the motion is taken as per frame.
        assert_eq!(velocity.over(Some(0.1)), step);
        velocity.span_s = Some(1.0 / 30.0);
        assert_eq!(velocity.over(None), step);
        assert!(velocity.over(Some(1.0 / 30.0)) == step);
        // Three frame times: three times the angle about the same axis, three times the way.
        let three = velocity.over(Some(3.0 / 30.0));
        assert!((three.rotation.angle() - 0.06).abs() < 1e-12);
        let axis = three.rotation.axis().unwrap();
        assert!((axis.into_inner() - Vector3::y()).norm() < 1e-12);
        assert!((three.translation.vector - 3.0 * step.translation.vector).norm() < 1e-12);
        let half = velocity.over(Some(0.5 / 30.0));
        assert!((half.rotation.angle() - 0.01).abs() < 1e-12);
    }

    #[test]
    fn the_camera_a_moment_away_follows_the_velocity_both_ways() {
        let step = Isometry3::from_parts(
            Translation3::new(0.03, 0.0, -0.01),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.03),
        );
        let unknown_span = ConstantVelocity {
            motion: step,
            span_s: None,
        };
        assert_eq!(unknown_span.now_from_later(0.01), Isometry3::identity());
        let velocity = ConstantVelocity {
            motion: step,
            span_s: Some(0.03),
        };
        assert_eq!(velocity.now_from_later(0.0), Isometry3::identity());
        // A third of the span later: a third of the step; as much earlier: its inverse.
        let later = velocity.now_from_later(0.01);
        assert!((later.rotation.angle() - 0.01).abs() < 1e-12);
        assert!((later.translation.vector - step.translation.vector / 3.0).norm() < 1e-12);
        let earlier = velocity.now_from_later(-0.01);
        assert!((earlier * later).rotation.angle() < 1e-12);
        // Translation and rotation scale apart (first order), so the two cancel to first order only.
        assert!((earlier * later).translation.vector.norm() < 1e-3);
    }
}
