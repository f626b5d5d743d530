//! Depth L1 error in centimetres over the pixels where the ground truth is valid (> 0). A rendered
//! pixel with no depth (0) counts with its full error: a hole in the map is an error.

use crate::MetricError;
use geometry::depth::DepthImage;

const CENTIMETRES_PER_METRE: f64 = 100.0;

/// Mean |estimate - ground truth| in cm over valid ground-truth pixels; `None` when the ground
/// truth has no valid pixel.
pub fn depth_l1_cm(
    ground_truth: &DepthImage,
    estimate: &DepthImage,
) -> Result<Option<f64>, MetricError> {
    if (ground_truth.width, ground_truth.height) != (estimate.width, estimate.height) {
        return Err(MetricError::SizeMismatch(
            ground_truth.width,
            ground_truth.height,
            estimate.width,
            estimate.height,
        ));
    }
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (&g, &e) in ground_truth.data.iter().zip(&estimate.data) {
        if g > 0.0 && g.is_finite() {
            let e = if e.is_finite() { e } else { 0.0 };
            sum += (e as f64 - g as f64).abs();
            count += 1;
        }
    }
    Ok((count > 0).then(|| CENTIMETRES_PER_METRE * sum / count as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_valid_ground_truth_counts() {
        let gt = DepthImage {
            width: 4,
            height: 1,
            data: vec![1.0, 2.0, 0.0, 3.0],
        };
        let est = DepthImage {
            width: 4,
            height: 1,
            data: vec![1.01, 1.98, 5.0, 0.0],
        };
        let l1 = depth_l1_cm(&gt, &est).unwrap().unwrap();
        assert!((l1 - (1.0 + 2.0 + 300.0) / 3.0).abs() < 1e-4, "{l1}");
        assert_eq!(depth_l1_cm(&DepthImage::new(4, 1), &est).unwrap(), None);
        assert!(depth_l1_cm(&gt, &DepthImage::new(2, 2)).is_err());
    }
}
