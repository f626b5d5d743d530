//! Conversions between the wire's [`Pose`] and nalgebra's `Isometry3<f64>`, which every process
//! uses for geometry. Defined here, next to the wire type, so that both directions exist once.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::messages::Pose;

impl From<&Isometry3<f64>> for Pose {
    fn from(isometry: &Isometry3<f64>) -> Self {
        let t = isometry.translation.vector;
        let q = isometry.rotation.quaternion();
        Pose {
            translation: [t.x, t.y, t.z],
            rotation_wxyz: [q.w, q.i, q.j, q.k],
        }
    }
}

impl Pose {
    /// The isometry this pose describes. The quaternion is renormalised: senders validate it to
    /// unit norm within a tolerance, and geometry downstream wants an exact rotation.
    pub fn to_isometry(&self) -> Isometry3<f64> {
        let [w, x, y, z] = self.rotation_wxyz;
        let [tx, ty, tz] = self.translation;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn round_trip_keeps_the_transform() {
        let isometry = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.3, -0.2, 1.1));
        let back = Pose::from(&isometry).to_isometry();
        assert!(
            (back.to_homogeneous() - isometry.to_homogeneous())
                .abs()
                .max()
                < 1e-12
        );
    }
}
