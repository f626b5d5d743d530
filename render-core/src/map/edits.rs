//! The structural edits of [`DeviceGaussians`] (append, prune, retain, transforms, compaction)
//! and the matching moves of [`DeviceAdam`]'s moments.

use std::ops::Range;

use crate::context::{GpuContext, GpuError};
use bytemuck::Zeroable;

use crate::gaussians::{PARAMETER_GROUP_WIDTHS, PARAMETER_GROUPS};
use crate::gpu::{DeviceGaussians, LayoutId};
use crate::passes::{U32_BYTES, VEC4_BYTES, bind_group, dispatch_linear, inclusive_scan};
use crate::training::{DeviceAdam, zero_moments};
use crate::types::{GaussianCloud, RigidTransform};
use crate::wgsl::{
    GroupTransform, PruneParams, TRANSFORM_ALL, TRANSFORM_BY_GROUP, TransformParams, WORKGROUP_SIZE,
};

use super::kernels::{
    MapKernels, Selection, compact_buffer, group_stride, grow_buffers, grown_capacity, kept_flags,
    max_capacity,
};
use super::{PruneCriteria, PruneReport};

impl DeviceGaussians {
    /// Appends `cloud` on the device and returns the indices the new Gaussians got. Uploads
    /// only the new Gaussians; when the capacity is exceeded the buffers grow (x1.5, see the
    /// module documentation) by a device-side copy. Fails with [`GpuError::TooLarge`] past
    /// the binding limit, leaving the map unchanged.
    ///
    /// Any [`DeviceAdam`] of these Gaussians goes stale; use [`DeviceMap::append`] to keep it.
    pub fn append(
        &mut self,
        context: &GpuContext,
        cloud: &GaussianCloud,
    ) -> Result<Range<usize>, GpuError> {
        cloud.validate_lengths().map_err(GpuError::InvalidInput)?;
        let start = self.len();
        if cloud.is_empty() {
            return Ok(start..start);
        }
        let required = start as u64 + cloud.len() as u64;
        if required > u64::from(self.capacity) {
            self.grow(context, required)?;
        }
        let offset = u64::from(self.count);
        let uploads: [(&wgpu::Buffer, &[u8]); PARAMETER_GROUPS] = [
            (&self.means, bytemuck::cast_slice(&cloud.means)),
            (&self.log_scales, bytemuck::cast_slice(&cloud.log_scales)),
            (&self.quaternions, bytemuck::cast_slice(&cloud.quaternions)),
            (
                &self.opacity_logits,
                bytemuck::cast_slice(&cloud.opacity_logits),
            ),
            (&self.colours, bytemuck::cast_slice(&cloud.colours)),
        ];
        for ((buffer, bytes), width) in uploads.into_iter().zip(PARAMETER_GROUP_WIDTHS) {
            context
                .queue
                .write_buffer(buffer, offset * group_stride(width), bytes);
        }
        // `required` fits the capacity, which fits u32.
        self.count = required as u32;
        self.layout = LayoutId::fresh();
        Ok(start..self.len())
    }

    /// Grows the buffers to hold at least `required` Gaussians, copying the live ones on the
    /// device.
    pub(super) fn grow(&mut self, context: &GpuContext, required: u64) -> Result<(), GpuError> {
        let capacity = grown_capacity(self.capacity, required, max_capacity(context))?;
        let mut encoder = context.device.create_command_encoder(&Default::default());
        let old = self.parameter_buffers();
        let sources = std::array::from_fn(|group| (old[group], PARAMETER_GROUP_WIDTHS[group]));
        let [means, log_scales, quaternions, opacity_logits, colours] = grow_buffers(
            context,
            &mut encoder,
            sources,
            self.count,
            capacity,
            "gaussian parameters",
        )?;
        context.queue.submit([encoder.finish()]);
        self.means = means;
        self.log_scales = log_scales;
        self.quaternions = quaternions;
        self.opacity_logits = opacity_logits;
        self.colours = colours;
        self.capacity = capacity;
        Ok(())
    }

    /// Removes, on the device, the Gaussians that fail `criteria` (or have a non-finite
    /// parameter), compacting stably; reads the keep flags back once for the report.
    ///
    /// Any [`DeviceAdam`] of these Gaussians goes stale; use [`DeviceMap::prune`] to keep it.
    pub fn prune(
        &mut self,
        context: &GpuContext,
        criteria: &PruneCriteria,
    ) -> Result<PruneReport, GpuError> {
        criteria.validate()?;
        self.compact(context, Selection::Criteria(criteria), None)
    }

    /// Keeps the Gaussians whose `keep` entry is true (one per Gaussian), compacting stably
    /// on the device. Returns the number removed. Reads nothing back.
    ///
    /// Any [`DeviceAdam`] of these Gaussians goes stale; use [`DeviceMap::retain`] to keep it.
    pub fn retain(&mut self, context: &GpuContext, keep: &[bool]) -> Result<usize, GpuError> {
        self.compact(context, Selection::Mask(keep), None)
            .map(|report| report.removed)
    }

    /// Applies `transform` (`p -> R p + t`) to every Gaussian in place on the device: means
    /// are mapped, quaternions left-multiplied by R's quaternion; scales, opacities and
    /// colours are unchanged. Matches [`GaussianCloud::transform_rigid`]. Order and count are
    /// unchanged, so Adam state stays valid.
    pub fn transform_rigid(
        &mut self,
        context: &GpuContext,
        transform: &RigidTransform,
    ) -> Result<(), GpuError> {
        self.dispatch_transform(context, &[GroupTransform::from(transform)], None)
    }

    /// Applies `transforms[group_of[i]]` to Gaussian `i` (as [`Self::transform_rigid`] does
    /// with one transform); a group index past the end of `transforms` leaves that Gaussian
    /// unchanged. A non-rigid correction: each keyframe's Gaussians move with their keyframe.
    /// Matches [`GaussianCloud::transform_groups`]; order and count are unchanged.
    pub fn transform_groups(
        &mut self,
        context: &GpuContext,
        group_of: &[u32],
        transforms: &[RigidTransform],
    ) -> Result<(), GpuError> {
        if group_of.len() != self.len() {
            return Err(GpuError::InvalidInput(format!(
                "{} group indices for {} Gaussians",
                group_of.len(),
                self.len()
            )));
        }
        if transforms.is_empty() {
            return Ok(());
        }
        let transforms: Vec<GroupTransform> = transforms.iter().map(GroupTransform::from).collect();
        self.dispatch_transform(context, &transforms, Some(group_of))
    }

    pub(super) fn dispatch_transform(
        &mut self,
        context: &GpuContext,
        transforms: &[GroupTransform],
        group_of: Option<&[u32]>,
    ) -> Result<(), GpuError> {
        if self.count == 0 {
            return Ok(());
        }
        let kernels = MapKernels::of(context);
        let mode = if group_of.is_some() {
            TRANSFORM_BY_GROUP
        } else {
            TRANSFORM_ALL
        };
        let params_buffer = context.uniform_buffer(
            "transform params",
            bytemuck::bytes_of(&TransformParams {
                gaussian_count: self.count,
                group_mode: mode,
                transform_count: transforms.len() as u32,
                padding0: 0,
            }),
        );
        let transforms_buffer = context.storage_buffer_init(
            "transforms",
            bytemuck::cast_slice(transforms),
            size_of::<GroupTransform>(),
        );
        // Read only in group mode; a one-word buffer keeps the binding valid otherwise.
        let group_buffer = context.storage_buffer_init(
            "transform groups",
            bytemuck::cast_slice(group_of.unwrap_or(&[])),
            U32_BYTES as usize,
        );
        let group = bind_group(
            context,
            &kernels.transform,
            &[
                (0, &params_buffer),
                (1, &self.means),
                (2, &self.quaternions),
                (3, &transforms_buffer),
                (4, &group_buffer),
            ],
        );
        let mut encoder = context.device.create_command_encoder(&Default::default());
        dispatch_linear(
            &mut encoder,
            &kernels.transform,
            &group,
            self.count.div_ceil(WORKGROUP_SIZE),
        );
        context.queue.submit([encoder.finish()]);
        Ok(())
    }

    /// Stable compaction of the Gaussians (and of `adam`'s moments, which must follow them)
    /// to the selected ones. The layout is renewed only when something was removed.
    pub(super) fn compact(
        &mut self,
        context: &GpuContext,
        selection: Selection,
        adam: Option<&mut DeviceAdam>,
    ) -> Result<PruneReport, GpuError> {
        let n = self.count;
        if let Selection::Mask(keep) = selection
            && keep.len() != self.len()
        {
            return Err(GpuError::InvalidInput(format!(
                "{} keep flags for {n} Gaussians",
                keep.len()
            )));
        }
        if let Some(adam) = adam.as_deref()
            && adam.gaussian_layout != self.layout
        {
            return Err(GpuError::InvalidInput(
                "the Adam state does not follow these Gaussians".into(),
            ));
        }
        if n == 0 {
            return Ok(PruneReport::default());
        }
        let kernels = MapKernels::of(context);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        // Keep flags (0/1 per Gaussian), turned in place into their inclusive prefix sum.
        let kept_through = self.encode_keep_flags(context, kernels, &mut encoder, &selection)?;
        inclusive_scan(context, &mut encoder, kernels.scan(), &kept_through, n)?;
        let parameters = self.parameter_buffers();
        let mut compacted = Vec::with_capacity(PARAMETER_GROUPS);
        for (buffer, width) in parameters.into_iter().zip(PARAMETER_GROUP_WIDTHS) {
            compacted.push(compact_buffer(
                context,
                kernels,
                &mut encoder,
                &kept_through,
                buffer,
                width,
                n,
                self.capacity,
            )?);
        }
        let mut compacted_moments = Vec::new();
        if let Some(adam) = adam.as_deref() {
            for ((first, second), width) in adam.moments.iter().zip(PARAMETER_GROUP_WIDTHS) {
                let mut compact = |moment| {
                    compact_buffer(
                        context,
                        kernels,
                        &mut encoder,
                        &kept_through,
                        moment,
                        width,
                        n,
                        adam.capacity,
                    )
                };
                compacted_moments.push((compact(first)?, compact(second)?));
            }
        }
        context.queue.submit([encoder.finish()]);
        let kept = kept_flags(context, &selection, &kept_through, n)?;
        let kept_count = kept.iter().filter(|&&k| k).count();
        let removed = self.len() - kept_count;
        let [means, log_scales, quaternions, opacity_logits, colours]: [wgpu::Buffer;
            PARAMETER_GROUPS] = compacted
            .try_into()
            .unwrap_or_else(|_| unreachable!("one buffer per parameter group"));
        self.means = means;
        self.log_scales = log_scales;
        self.quaternions = quaternions;
        self.opacity_logits = opacity_logits;
        self.colours = colours;
        // kept_count <= n, a u32.
        self.count = kept_count as u32;
        if removed > 0 {
            self.layout = LayoutId::fresh();
        }
        if let Some(adam) = adam {
            for (moments, compacted) in adam.moments.iter_mut().zip(compacted_moments) {
                *moments = compacted;
            }
            adam.count = self.count;
            adam.gaussian_layout = self.layout;
        }
        Ok(PruneReport { kept, removed })
    }

    /// Encodes the keep flags of `selection` (1 per kept Gaussian): the prune kernel's
    /// verdicts, or the caller's mask uploaded.
    pub(super) fn encode_keep_flags(
        &self,
        context: &GpuContext,
        kernels: &MapKernels,
        encoder: &mut wgpu::CommandEncoder,
        selection: &Selection,
    ) -> Result<wgpu::Buffer, GpuError> {
        let n = self.count;
        Ok(match *selection {
            Selection::Criteria(criteria) => {
                let flags = context.storage_buffer("keep flags", u64::from(n) * U32_BYTES)?;
                let [opacity_logit_threshold, max_log_scale, max_elongation, _] =
                    criteria.thresholds();
                let params = PruneParams {
                    count: n,
                    opacity_logit_threshold,
                    max_log_scale,
                    max_elongation,
                    ..Zeroable::zeroed()
                };
                let params_buffer =
                    context.uniform_buffer("prune params", bytemuck::bytes_of(&params));
                let group = bind_group(
                    context,
                    &kernels.prune,
                    &[
                        (0, &params_buffer),
                        (1, &self.means),
                        (2, &self.log_scales),
                        (3, &self.quaternions),
                        (4, &self.opacity_logits),
                        (5, &self.colours),
                        (6, &flags),
                    ],
                );
                dispatch_linear(encoder, &kernels.prune, &group, n.div_ceil(WORKGROUP_SIZE));
                flags
            }
            Selection::Mask(keep) => {
                let flags: Vec<u32> = keep.iter().map(|&kept| u32::from(kept)).collect();
                context.storage_buffer_init(
                    "keep flags",
                    bytemuck::cast_slice(&flags),
                    VEC4_BYTES as usize,
                )
            }
        })
    }
}

impl DeviceAdam {
    /// Follows [`DeviceGaussians::append`]: grows to the Gaussians' capacity when needed (a
    /// device-side copy) and gives the `appended` Gaussians zero moments.
    pub(super) fn follow_append(
        &mut self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        appended: Range<usize>,
    ) -> Result<(), GpuError> {
        let mut encoder = context.device.create_command_encoder(&Default::default());
        if self.capacity < gaussians.capacity {
            let mut grown = zero_moments(context, gaussians.capacity)?;
            for ((old, new), width) in self
                .moments
                .iter()
                .zip(&mut grown)
                .zip(PARAMETER_GROUP_WIDTHS)
            {
                if self.count > 0 {
                    let bytes = u64::from(self.count) * group_stride(width);
                    encoder.copy_buffer_to_buffer(&old.0, 0, &new.0, 0, bytes);
                    encoder.copy_buffer_to_buffer(&old.1, 0, &new.1, 0, bytes);
                }
            }
            self.moments = grown;
            self.capacity = gaussians.capacity;
        }
        // Slots past the old count may hold moments of Gaussians removed earlier.
        for ((first, second), width) in self.moments.iter().zip(PARAMETER_GROUP_WIDTHS) {
            let stride = group_stride(width);
            let offset = appended.start as u64 * stride;
            let bytes = appended.len() as u64 * stride;
            encoder.clear_buffer(first, offset, Some(bytes));
            encoder.clear_buffer(second, offset, Some(bytes));
        }
        context.queue.submit([encoder.finish()]);
        self.count = gaussians.count;
        self.gaussian_layout = gaussians.layout;
        Ok(())
    }
}
