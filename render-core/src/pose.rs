//! Adam over a camera pose on the host: the optimiser the agents' mappers (keyframe poses) and the
//! consensus's joint refinement (every view's pose) step with the pose gradient the backward pass
//! reads back ([`crate::backward::DeviceGradients::read_pose`], a [`crate::PoseGradient`]: the
//! left perturbation of `camera_from_world`, `[translation, rotation]`).

use nalgebra::Vector6;

/// Adam moment decay rates and the division guard, as the device's map optimiser uses.
const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPSILON: f64 = 1e-12;

/// Adam state of one pose's 6-vector `[translation, rotation]`.
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct PoseAdam {
    first_moment: Vector6<f64>,
    second_moment: Vector6<f64>,
    steps: i32,
}

impl PoseAdam {
    /// The perturbation to apply for `gradient`, with per-component step sizes `rates` (an Adam
    /// step is about `rates` in size whatever the gradient's scale).
    pub fn step(&mut self, gradient: &Vector6<f64>, rates: &Vector6<f64>) -> Vector6<f64> {
        self.steps += 1;
        self.first_moment = BETA1 * self.first_moment + (1.0 - BETA1) * gradient;
        self.second_moment =
            BETA2 * self.second_moment + (1.0 - BETA2) * gradient.component_mul(gradient);
        let m_hat = self.first_moment / (1.0 - BETA1.powi(self.steps));
        let v_hat = self.second_moment / (1.0 - BETA2.powi(self.steps));
        Vector6::from_fn(|k, _| -rates[k] * m_hat[k] / (v_hat[k].sqrt() + EPSILON))
    }
}

/// `[translation (3), rotation (3)]` step sizes from one translation and one rotation rate.
pub fn pose_rates(translation_m: f64, rotation_rad: f64) -> Vector6<f64> {
    Vector6::new(
        translation_m,
        translation_m,
        translation_m,
        rotation_rad,
        rotation_rad,
        rotation_rad,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_adam_moves_against_the_gradient_by_the_step_size() {
        let mut adam = PoseAdam::default();
        let rates = Vector6::from_element(1e-3);
        let step = adam.step(&Vector6::new(2.0, -3.0, 0.0, 1.0, 0.0, 0.0), &rates);
        // The first Adam step has magnitude lr in every non-zero component.
        assert!((step[0] + 1e-3).abs() < 1e-9);
        assert!((step[1] - 1e-3).abs() < 1e-9);
        assert_eq!(step[2], 0.0);
        assert!((step[3] + 1e-3).abs() < 1e-9);
    }

    #[test]
    fn rates_repeat_translation_then_rotation() {
        assert_eq!(
            pose_rates(2.0, 3.0),
            Vector6::new(2.0, 2.0, 2.0, 3.0, 3.0, 3.0)
        );
    }
}
