//! Capacity growth and prune thresholds.

use super::kernels::grown_capacity;
use super::*;

#[test]
fn growth_is_geometric_and_bounded_by_the_binding_limit() {
    const LIMIT: u64 = 10_000;
    assert_eq!(
        grown_capacity(0, 1, LIMIT).unwrap() as usize,
        MIN_GROWN_CAPACITY
    );
    assert_eq!(grown_capacity(1000, 1001, LIMIT).unwrap(), 1500);
    assert_eq!(grown_capacity(1000, 4000, LIMIT).unwrap(), 4000);
    assert_eq!(grown_capacity(9000, 9001, LIMIT).unwrap() as u64, LIMIT);
    assert_eq!(grown_capacity(9000, LIMIT, LIMIT).unwrap() as u64, LIMIT);
    assert!(matches!(
        grown_capacity(9000, LIMIT + 1, LIMIT),
        Err(GpuError::TooLarge(_))
    ));
}

#[test]
fn thresholds_are_finite_and_in_stored_units() {
    let [logit, log_scale, elongation, _] = PruneCriteria::default().thresholds();
    assert!((logit - (0.005f32 / 0.995).ln()).abs() < 1e-6);
    assert!(log_scale.abs() < 1e-7);
    assert_eq!(elongation, 10.0);
    let extreme = PruneCriteria {
        min_opacity: 1.0,
        max_scale_m: f32::INFINITY,
        max_elongation: f32::INFINITY,
    };
    assert!(extreme.thresholds().iter().all(|v| v.is_finite()));
    assert_eq!(extreme.thresholds()[0], f32::MAX);
}
