//! Applying a pose-graph solution to poses that are not keyframes.
//!
//! The solution moves each keyframe; its *correction* is `world_from_camera_corrected *
//! agent_from_camera_tracked^-1`, a `world_from_agent` transform valid near that keyframe. A frame
//! tracked between two keyframes takes the correction blended between theirs in proportion to
//! where it lies, so that a tracking error that built up between them is spread over the frames
//! instead of appearing as a jump at the next keyframe.

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
}
