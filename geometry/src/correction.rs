//! Pose-graph corrections applied to poses and maps that are not keyframes
//! (docs/method.md, The consensus: pose graph).
//!
//! The consensus moves each keyframe; its *correction* is `world_from_camera_corrected *
//! agent_from_camera_tracked^-1`, a `world_from_agent` transform valid near that keyframe. A frame
//! tracked between two keyframes takes the correction blended between theirs in proportion to
//! where it lies in time, so that a tracking error that built up between them is spread over the
//! frames instead of appearing as a jump at the next keyframe. [`CorrectionField`] is that rule
//! over a whole trajectory: the consensus uses it for the per-frame world trajectories, and an
//! agent uses it to move each part of its local map with the keyframe that made it.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// The correction at a keyframe: maps its tracked (agent-frame) pose onto its corrected pose.
pub fn correction(
    world_from_camera_corrected: &Isometry3<f64>,
    agent_from_camera_tracked: &Isometry3<f64>,
) -> Isometry3<f64> {
    world_from_camera_corrected * agent_from_camera_tracked.inverse()
}

/// The correction a fraction `fraction` (0 = `before`, 1 = `after`, clamped) of the way from one
/// keyframe's correction to the next: translation interpolated linearly, rotation along the
/// geodesic.
pub fn blend(before: &Isometry3<f64>, after: &Isometry3<f64>, fraction: f64) -> Isometry3<f64> {
    let fraction = if fraction.is_finite() {
        fraction.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let rotation_step = (before.rotation.inverse() * after.rotation).scaled_axis() * fraction;
    Isometry3::from_parts(
        Translation3::from(
            before
                .translation
                .vector
                .lerp(&after.translation.vector, fraction),
        ),
        before.rotation * UnitQuaternion::from_scaled_axis(rotation_step),
    )
}

/// Corrections anchored at keyframe times, blended between neighbours in time and held constant
/// before the first and after the last anchor. Without anchors it is the identity everywhere.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CorrectionField {
    /// `(time, correction)`, sorted by time, finite times only.
    anchors: Vec<(f64, Isometry3<f64>)>,
}

impl CorrectionField {
    /// The field through `anchors` (any order; anchors with a non-finite time are left out).
    pub fn from_anchors(anchors: impl IntoIterator<Item = (f64, Isometry3<f64>)>) -> Self {
        let mut anchors: Vec<(f64, Isometry3<f64>)> =
            anchors.into_iter().filter(|(t, _)| t.is_finite()).collect();
        anchors.sort_by(|a, b| a.0.total_cmp(&b.0));
        Self { anchors }
    }

    /// True when the field is the identity everywhere (no anchors).
    pub fn is_empty(&self) -> bool {
        self.anchors.is_empty()
    }

    /// Number of anchors (keyframe corrections) the field holds.
    pub fn len(&self) -> usize {
        self.anchors.len()
    }

    /// The correction at time `t`.
    pub fn at(&self, t: f64) -> Isometry3<f64> {
        let Some(first) = self.anchors.first() else {
            return Isometry3::identity();
        };
        let after = self.anchors.partition_point(|(stamp, _)| *stamp <= t);
        if after == 0 {
            return first.1;
        }
        if after == self.anchors.len() {
            return self.anchors[after - 1].1;
        }
        let (t0, c0) = &self.anchors[after - 1];
        let (t1, c1) = &self.anchors[after];
        let span = (t1 - t0).max(f64::EPSILON);
        blend(c0, c1, (t - t0) / span)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blend_runs_from_one_correction_to_the_other() {
        let a = Isometry3::from_parts(
            Translation3::new(1.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2),
        );
        let b = Isometry3::from_parts(
            Translation3::new(3.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6),
        );
        assert_eq!(blend(&a, &b, 0.0), a);
        assert!(
            (blend(&a, &b, 1.0).to_homogeneous() - b.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
        let half = blend(&a, &b, 0.5);
        assert!((half.translation.vector.x - 2.0).abs() < 1e-12);
        assert!((half.rotation.euler_angles().2 - 0.4).abs() < 1e-12);
        assert_eq!(
            blend(&a, &b, f64::NAN),
            a,
            "a degenerate fraction keeps the first"
        );
        assert_eq!(blend(&a, &b, -3.0), a);
        let tracked = Isometry3::translation(0.5, 0.5, 0.0);
        let corrected = a * tracked;
        assert!(
            (correction(&corrected, &tracked).to_homogeneous() - a.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
    }

    #[test]
    fn field_blends_between_anchors_and_holds_beyond_them() {
        assert_eq!(CorrectionField::default().at(5.0), Isometry3::identity());
        let a = Isometry3::translation(1.0, 0.0, 0.0);
        let b = Isometry3::translation(3.0, 0.0, 0.0);
        // Out of order and with a non-finite time: sorted, the NaN anchor left out.
        let field = CorrectionField::from_anchors([
            (20.0, b),
            (f64::NAN, Isometry3::translation(9.0, 9.0, 9.0)),
            (10.0, a),
        ]);
        assert_eq!(field.len(), 2);
        assert_eq!(field.at(0.0), a, "before the first anchor");
        assert_eq!(field.at(10.0), a);
        assert!((field.at(15.0).translation.vector.x - 2.0).abs() < 1e-12);
        assert_eq!(field.at(99.0), b, "after the last anchor");
    }
}
