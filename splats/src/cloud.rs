//! [`GaussianCloud`]: a set of 3D Gaussians in structure-of-arrays layout, with the host-side
//! edits (append, select, rigid and per-group transforms) the device map mirrors.

use crate::transform::{RigidTransform, quaternion_multiply};

/// A set of 3D Gaussians in structure-of-arrays layout, all vectors of equal length.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    /// World-space centres.
    pub means: Vec<[f32; 3]>,
    /// Natural-log standard deviations along the Gaussian's local axes.
    pub log_scales: Vec<[f32; 3]>,
    /// Rotations as quaternions `[w, x, y, z]`, not necessarily normalised.
    pub quaternions: Vec<[f32; 4]>,
    /// Opacities before the sigmoid (`opacity = 1 / (1 + exp(-logit))`).
    pub opacity_logits: Vec<f32>,
    /// Linear RGB colours in `[0, 1]` (SH degree 0 after `0.5 + C0 * f_dc`).
    pub colours: Vec<[f32; 3]>,
}

impl GaussianCloud {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Appends one Gaussian.
    pub fn push(
        &mut self,
        mean: [f32; 3],
        log_scale: [f32; 3],
        quaternion: [f32; 4],
        opacity_logit: f32,
        colour: [f32; 3],
    ) {
        self.means.push(mean);
        self.log_scales.push(log_scale);
        self.quaternions.push(quaternion);
        self.opacity_logits.push(opacity_logit);
        self.colours.push(colour);
    }

    /// Appends every Gaussian of `other` (same order).
    pub fn extend_from(&mut self, other: &GaussianCloud) {
        self.means.extend_from_slice(&other.means);
        self.log_scales.extend_from_slice(&other.log_scales);
        self.quaternions.extend_from_slice(&other.quaternions);
        self.opacity_logits.extend_from_slice(&other.opacity_logits);
        self.colours.extend_from_slice(&other.colours);
    }

    /// The Gaussians whose `keep` entry is true, in their original order (the host
    /// counterpart of the device compaction). Panics if `keep` and the cloud differ in length.
    pub fn select(&self, keep: &[bool]) -> GaussianCloud {
        assert_eq!(keep.len(), self.len(), "one keep flag per Gaussian");
        fn pick<T: Copy>(values: &[T], keep: &[bool]) -> Vec<T> {
            values
                .iter()
                .zip(keep)
                .filter_map(|(value, &kept)| kept.then_some(*value))
                .collect()
        }
        GaussianCloud {
            means: pick(&self.means, keep),
            log_scales: pick(&self.log_scales, keep),
            quaternions: pick(&self.quaternions, keep),
            opacity_logits: pick(&self.opacity_logits, keep),
            colours: pick(&self.colours, keep),
        }
    }

    /// Applies `transform` to every Gaussian: means are mapped, quaternions left-multiplied
    /// by the rotation's quaternion (so covariances become `R Sigma R^T`); scales, opacities
    /// and colours are frame-independent and unchanged. The host counterpart of
    /// `DeviceGaussians::transform_rigid`.
    pub fn transform_rigid(&mut self, transform: &RigidTransform) {
        let rotation = transform.rotation_quaternion();
        for mean in &mut self.means {
            *mean = transform.transform_point(*mean);
        }
        for quaternion in &mut self.quaternions {
            *quaternion = quaternion_multiply(rotation, *quaternion);
        }
    }

    /// Applies `transforms[group_of[i]]` to Gaussian `i` as [`Self::transform_rigid`] does; a
    /// group index past the end of `transforms` leaves that Gaussian unchanged. The host
    /// counterpart of `DeviceGaussians::transform_groups`.
    ///
    /// # Panics
    /// When `group_of` does not have one entry per Gaussian.
    pub fn transform_groups(&mut self, group_of: &[u32], transforms: &[RigidTransform]) {
        assert_eq!(group_of.len(), self.len(), "one group index per Gaussian");
        let rotations: Vec<[f32; 4]> = transforms
            .iter()
            .map(RigidTransform::rotation_quaternion)
            .collect();
        for (i, &group) in group_of.iter().enumerate() {
            let Some(transform) = transforms.get(group as usize) else {
                continue;
            };
            self.means[i] = transform.transform_point(self.means[i]);
            self.quaternions[i] =
                quaternion_multiply(rotations[group as usize], self.quaternions[i]);
        }
    }

    /// Largest distance of a mean from the centroid of all means (metres; 0 when empty): the
    /// scene scale mean learning rates are multiplied by (3DGS normalises by the camera extent;
    /// a map's own radius is the stand-in before cameras are known).
    pub fn radius_around_centroid(&self) -> f64 {
        if self.is_empty() {
            return 0.0;
        }
        let count = self.len() as f64;
        let centroid = self.means.iter().fold([0.0f64; 3], |acc, m| {
            [0, 1, 2].map(|k| acc[k] + f64::from(m[k]) / count)
        });
        self.means
            .iter()
            .map(|m| {
                (0..3)
                    .map(|k| (f64::from(m[k]) - centroid[k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(0.0, f64::max)
    }

    /// Checks that all attribute vectors have the same length.
    pub fn validate_lengths(&self) -> Result<(), String> {
        let n = self.means.len();
        let lengths = [
            ("log_scales", self.log_scales.len()),
            ("quaternions", self.quaternions.len()),
            ("opacity_logits", self.opacity_logits.len()),
            ("colours", self.colours.len()),
        ];
        for (name, len) in lengths {
            if len != n {
                return Err(format!(
                    "GaussianCloud: {name} has {len} entries, means has {n}"
                ));
            }
        }
        Ok(())
    }
}
