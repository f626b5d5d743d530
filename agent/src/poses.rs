//! Pose conversions between the SLAM side (nalgebra `Isometry3<f64>`) and render-core's
//! `RigidTransform` (row-major f32), defined once for the agent.

use nalgebra::Isometry3;
use render_core::types::RigidTransform;

/// The same transform as render-core's f32 row-major type.
pub fn rigid_from_isometry(pose: &Isometry3<f64>) -> RigidTransform {
    let rotation = pose.rotation.to_rotation_matrix();
    let matrix = rotation.matrix();
    RigidTransform {
        rotation: [0, 1, 2].map(|row| [0, 1, 2].map(|col| matrix[(row, col)] as f32)),
        translation: [0, 1, 2].map(|i| pose.translation.vector[i] as f32),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn converted_transform_maps_points_the_same_way() {
        let pose = Isometry3::new(Vector3::new(0.5, -1.0, 2.0), Vector3::new(0.3, -0.2, 1.1));
        let rigid = rigid_from_isometry(&pose);
        let p = Point3::new(0.25, 0.75, -1.5);
        let expected = pose * p;
        let got = rigid.transform_point([p.x as f32, p.y as f32, p.z as f32]);
        for k in 0..3 {
            assert!((f64::from(got[k]) - expected[k]).abs() < 1e-6);
        }
    }
}
