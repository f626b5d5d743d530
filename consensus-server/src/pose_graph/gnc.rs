//! Graduated non-convexity with a truncated least-squares kernel (Yang, Antonante, Tzoumas,
//! Carlone, "Graduated Non-Convexity for Robust Spatial Perception", RA-L 2020).
//!
//! Truncated least squares costs `min(r^2, c^2)` per loop edge: an edge whose squared Mahalanobis
//! residual exceeds `c^2` costs a constant, so it cannot bend the graph. That cost has many local
//! minima; GNC starts from a convex surrogate controlled by `mu` (small `mu`: nearly convex) and
//! tightens it step by step (`mu <- mu * factor`), each step a weighted least-squares solve with
//! the weights below, until the weights are binary: 1 = inlier, 0 = outlier.

/// Weight of an edge with squared residual `residual_sq` at control parameter `mu`, for the
/// truncated least-squares threshold `threshold_sq` (Yang et al., equation 14).
pub fn tls_weight(residual_sq: f64, threshold_sq: f64, mu: f64) -> f64 {
    if residual_sq >= (mu + 1.0) / mu * threshold_sq {
        0.0
    } else if residual_sq <= mu / (mu + 1.0) * threshold_sq {
        1.0
    } else {
        (threshold_sq * mu * (mu + 1.0) / residual_sq).sqrt() - mu
    }
}

/// The starting `mu`: the surrogate is convex over every residual present,
/// `mu_0 = c^2 / (2 max r^2 - c^2)` (Yang et al., Remark 5). `None` when no residual exceeds the
/// threshold: then every edge is an inlier and no graduation is needed.
pub fn initial_mu(largest_residual_sq: f64, threshold_sq: f64) -> Option<f64> {
    (largest_residual_sq > threshold_sq)
        .then(|| threshold_sq / (2.0 * largest_residual_sq - threshold_sq))
}

/// Weights closer than this to 0 or 1 count as decided.
const DECIDED_TOLERANCE: f64 = 1e-3;

/// True when every weight is (numerically) 0 or 1: GNC has converged.
pub fn weights_are_binary(weights: &[f64]) -> bool {
    weights
        .iter()
        .all(|w| *w < DECIDED_TOLERANCE || *w > 1.0 - DECIDED_TOLERANCE)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_go_from_smooth_to_binary() {
        let c2 = 16.0;
        // Large mu: the kernel is the truncated quadratic itself.
        assert_eq!(tls_weight(15.0, c2, 1e6), 1.0);
        assert_eq!(tls_weight(17.0, c2, 1e6), 0.0);
        // Small mu: a far outlier still gets a (small) weight, nothing is decided yet.
        let mu = initial_mu(1600.0, c2).unwrap();
        let far = tls_weight(1600.0, c2, mu);
        assert!(far > 0.0 && far < 0.1, "{far}");
        let near = tls_weight(1.0, c2, mu);
        assert!(near > far && near <= 1.0);
        assert!(initial_mu(10.0, c2).is_none());
        assert!(weights_are_binary(&[0.0, 1.0, 0.9999]));
        assert!(!weights_are_binary(&[0.5]));
    }
}
