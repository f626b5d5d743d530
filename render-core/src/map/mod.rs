//! In-place structural edits of a device-resident map, with no re-upload from the host:
//!
//! - [`DeviceGaussians::append`] uploads only the new Gaussians; when the buffers are full they
//!   grow geometrically (x1.5, at least [`MIN_GROWN_CAPACITY`]) by a device-side copy of the
//!   live contents, so appending N Gaussians one batch at a time costs O(N) copies in total.
//! - [`DeviceGaussians::prune`] evaluates [`PruneCriteria`] in a kernel (prune.wgsl) and
//!   [`DeviceGaussians::retain`] takes a caller's mask; both compact every parameter buffer
//!   with a prefix sum of the keep flags (compact.wgsl), stably: the kept Gaussians keep their
//!   relative order, so per-Gaussian metadata on the host can follow with the same mask.
//! - [`DeviceGaussians::transform_rigid`] applies an agent-to-world correction and
//!   [`DeviceGaussians::transform_groups`] one transform per group of Gaussians, a keyframe's
//!   Gaussians following their keyframe (transform.wgsl).
//!
//! Adam state: [`DeviceMap`] owns the Gaussians together with their [`DeviceAdam`] and applies
//! every edit to both (new Gaussians get zero moments; compaction moves the moments with their
//! Gaussians). Editing the Gaussians alone is allowed (maps without an optimiser), but then the
//! old Adam state no longer matches: every [`DeviceGaussians`] carries a layout identity,
//! renewed by each change of order or count, and [`TrainingKernels::adam_step`] and
//! [`GpuRenderer::backward`](crate::gpu::GpuRenderer::backward) reject state, frames and
//! gradients built for another layout instead of silently mixing up Gaussians.
//!
//! Limits: capacity never exceeds what one storage binding holds for the widest per-Gaussian
//! buffer (16 bytes: quaternions and their moments), i.e. 8.4 M Gaussians with lavapipe's
//! 128 MiB; beyond that the edits return [`GpuError::TooLarge`] and leave the map unchanged.
//!
//! This file holds the criteria and [`DeviceMap`]; `edits.rs` the edits of
//! [`DeviceGaussians`] and [`DeviceAdam`], `kernels.rs` their compiled kernels and the buffer
//! growth and compaction they share.

use std::ops::Range;

use crate::backward::DeviceGradients;
use crate::context::{GpuContext, GpuError};

use crate::gpu::DeviceGaussians;
use crate::training::{AdamConfig, DeviceAdam, TrainingKernels};
use crate::types::{GaussianCloud, RigidTransform};

mod edits;
mod kernels;
#[cfg(test)]
mod tests;

pub(crate) use kernels::MapKernels;
use kernels::Selection;

/// Capacity after a growth is at least the old capacity times
/// GROWTH_NUMERATOR / GROWTH_DENOMINATOR (amortised O(1) copies per appended Gaussian).
const GROWTH_NUMERATOR: u64 = 3;
const GROWTH_DENOMINATOR: u64 = 2;
/// Smallest capacity a growth produces, so that small maps do not re-allocate per batch.
pub const MIN_GROWN_CAPACITY: usize = 256;

/// Which Gaussians a pruning pass removes (docs/method.md, One agent: Pruning). A Gaussian with any non-finite
/// parameter is always removed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PruneCriteria {
    /// Remove Gaussians whose opacity (after the sigmoid) is below this.
    pub min_opacity: f32,
    /// Remove Gaussians whose largest scale (standard deviation, metres) exceeds this: tau_s,
    /// 1.0 m by default, 0.25 m for Replica-like scenes ([`PruneCriteria::REPLICA_MAX_SCALE_M`]).
    pub max_scale_m: f32,
    /// Remove Gaussians whose largest scale exceeds this multiple of the sum of the other two.
    pub max_elongation: f32,
}

impl Default for PruneCriteria {
    fn default() -> Self {
        Self {
            min_opacity: 0.005,
            max_scale_m: 1.0,
            max_elongation: 10.0,
        }
    }
}

impl PruneCriteria {
    /// tau_s for Replica-like scenes (docs/method.md, One agent: Pruning).
    pub const REPLICA_MAX_SCALE_M: f32 = 0.25;

    fn validate(&self) -> Result<(), GpuError> {
        let valid = (0.0..=1.0).contains(&self.min_opacity)
            && self.max_scale_m > 0.0
            && self.max_elongation > 0.0;
        if valid {
            Ok(())
        } else {
            Err(GpuError::InvalidInput(format!(
                "prune criteria {self:?}: need min_opacity in [0, 1] and positive maxima"
            )))
        }
    }

    /// `[opacity logit threshold, largest allowed log-scale, max elongation, unused]`, the
    /// form the kernel and [`PruneCriteria::keeps`] compare against. Infinite thresholds are
    /// clamped to the finite range (the kernels may assume finite uniforms).
    fn thresholds(&self) -> [f32; 4] {
        let p = f64::from(self.min_opacity);
        let logit = (p / (1.0 - p)).ln();
        [
            logit as f32,
            f64::from(self.max_scale_m).ln() as f32,
            self.max_elongation,
            0.0,
        ]
        .map(|value| value.clamp(f32::MIN, f32::MAX))
    }

    /// True when Gaussian `index` of `cloud` survives pruning: the host reference of the
    /// prune kernel (same comparisons in the same order).
    pub fn keeps(&self, cloud: &GaussianCloud, index: usize) -> bool {
        let [logit_threshold, log_scale_threshold, max_elongation, _] = self.thresholds();
        let log_scale = cloud.log_scales[index];
        let finite = cloud.means[index].iter().all(|v| v.is_finite())
            && log_scale.iter().all(|v| v.is_finite())
            && cloud.quaternions[index].iter().all(|v| v.is_finite())
            && cloud.opacity_logits[index].is_finite()
            && cloud.colours[index].iter().all(|v| v.is_finite());
        if !finite {
            return false;
        }
        let transparent = cloud.opacity_logits[index] < logit_threshold;
        let largest_log_scale = log_scale[0].max(log_scale[1]).max(log_scale[2]);
        let too_large = largest_log_scale > log_scale_threshold;
        !transparent && !too_large && !is_elongated(log_scale, max_elongation)
    }

    /// [`PruneCriteria::keeps`] for every Gaussian of `cloud`.
    pub fn keep_mask(&self, cloud: &GaussianCloud) -> Vec<bool> {
        (0..cloud.len()).map(|i| self.keeps(cloud, i)).collect()
    }
}

/// Largest scale > max_elongation x (sum of the other two); mirrors `is_elongated` in
/// prune.wgsl, including which axis wins a tie.
fn is_elongated(log_scale: [f32; 3], max_elongation: f32) -> bool {
    let scale = log_scale.map(f32::exp);
    let mut largest = scale[0];
    let mut others = scale[1] + scale[2];
    if scale[1] > largest {
        largest = scale[1];
        others = scale[0] + scale[2];
    }
    if scale[2] > largest {
        largest = scale[2];
        others = scale[0] + scale[1];
    }
    largest > max_elongation * others
}

/// Outcome of [`DeviceGaussians::prune`].
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct PruneReport {
    /// One flag per Gaussian before pruning: true when it was kept. Kept Gaussians keep their
    /// relative order, so `GaussianCloud::select(&kept)` (or the same filter on any
    /// per-Gaussian host metadata) reproduces the new order.
    pub kept: Vec<bool>,
    /// Gaussians removed (the `false` entries of `kept`).
    pub removed: usize,
}

/// Gaussians on the device together with their Adam state, edited as one: the way an agent's
/// mapper should hold its map. Every structural edit moves the Adam moments with their
/// Gaussians (appended Gaussians start with zero moments; the step count, and so Adam's bias
/// correction, is shared by all Gaussians, as in 3DGS densification).
pub struct DeviceMap {
    gaussians: DeviceGaussians,
    adam: DeviceAdam,
}

impl DeviceMap {
    /// Takes `gaussians` with fresh (zero) Adam state.
    pub fn new(
        context: &GpuContext,
        gaussians: DeviceGaussians,
        config: AdamConfig,
    ) -> Result<Self, GpuError> {
        let adam = DeviceAdam::new(context, &gaussians, config)?;
        Ok(Self { gaussians, adam })
    }

    /// Uploads `cloud` with fresh (zero) Adam state.
    pub fn upload(
        context: &GpuContext,
        cloud: &GaussianCloud,
        config: AdamConfig,
    ) -> Result<Self, GpuError> {
        Self::new(context, DeviceGaussians::upload(context, cloud)?, config)
    }

    /// Joins Gaussians and an Adam state built for them (and not edited apart since).
    pub fn from_parts(gaussians: DeviceGaussians, adam: DeviceAdam) -> Result<Self, GpuError> {
        if adam.gaussian_layout != gaussians.layout {
            return Err(GpuError::InvalidInput(
                "the Adam state was built for another arrangement of the Gaussians".into(),
            ));
        }
        Ok(Self { gaussians, adam })
    }

    /// Splits the map into its Gaussians and their Adam state ([`Self::from_parts`] joins them
    /// again while neither is edited apart).
    pub fn into_parts(self) -> (DeviceGaussians, DeviceAdam) {
        (self.gaussians, self.adam)
    }

    /// The Gaussians, for rendering, backward passes and downloads.
    pub fn gaussians(&self) -> &DeviceGaussians {
        &self.gaussians
    }

    /// The Adam state (moments, step count, configuration) of the Gaussians.
    pub fn adam(&self) -> &DeviceAdam {
        &self.adam
    }

    /// Learning rates and Adam constants (e.g. to scale the mean rate by the scene size).
    pub fn adam_config_mut(&mut self) -> &mut AdamConfig {
        &mut self.adam.config
    }

    /// Number of live Gaussians.
    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    /// True when the map holds no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// Copies the Gaussians back to the host ([`DeviceGaussians::download`]; the Adam state
    /// stays on the device).
    pub fn download(&self, context: &GpuContext) -> Result<GaussianCloud, GpuError> {
        self.gaussians.download(context)
    }

    /// [`DeviceGaussians::append`]; the new Gaussians get zero moments.
    pub fn append(
        &mut self,
        context: &GpuContext,
        cloud: &GaussianCloud,
    ) -> Result<Range<usize>, GpuError> {
        let appended = self.gaussians.append(context, cloud)?;
        if !appended.is_empty() {
            self.adam
                .follow_append(context, &self.gaussians, appended.clone())?;
        }
        Ok(appended)
    }

    /// [`DeviceGaussians::prune`]; the moments are compacted with the same flags.
    pub fn prune(
        &mut self,
        context: &GpuContext,
        criteria: &PruneCriteria,
    ) -> Result<PruneReport, GpuError> {
        criteria.validate()?;
        self.gaussians
            .compact(context, Selection::Criteria(criteria), Some(&mut self.adam))
    }

    /// [`DeviceGaussians::retain`]; the moments are compacted with the same mask. Returns the
    /// number removed.
    pub fn retain(&mut self, context: &GpuContext, keep: &[bool]) -> Result<usize, GpuError> {
        self.gaussians
            .compact(context, Selection::Mask(keep), Some(&mut self.adam))
            .map(|report| report.removed)
    }

    /// [`DeviceGaussians::transform_rigid`]. The moments are left as they are: Adam's
    /// per-coordinate second moments have no exact rotated counterpart, and a correction
    /// changes where the Gaussians are, not how well each one fits.
    pub fn transform_rigid(
        &mut self,
        context: &GpuContext,
        transform: &RigidTransform,
    ) -> Result<(), GpuError> {
        self.gaussians.transform_rigid(context, transform)
    }

    /// [`DeviceGaussians::transform_groups`]; the moments stay, as for
    /// [`Self::transform_rigid`].
    pub fn transform_groups(
        &mut self,
        context: &GpuContext,
        group_of: &[u32],
        transforms: &[RigidTransform],
    ) -> Result<(), GpuError> {
        self.gaussians
            .transform_groups(context, group_of, transforms)
    }

    /// [`TrainingKernels::adam_step`] on this map's Gaussians and state.
    pub fn adam_step(
        &mut self,
        context: &GpuContext,
        kernels: &TrainingKernels,
        gradients: &DeviceGradients,
    ) -> Result<(), GpuError> {
        kernels.adam_step(context, &mut self.adam, &self.gaussians, gradients)
    }
}
