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

use std::ops::Range;

use crate::backward::DeviceGradients;
use crate::context::{GpuContext, GpuError};
use bytemuck::Zeroable;

use crate::gaussians::{PARAMETER_GROUP_WIDTHS, PARAMETER_GROUPS};
use crate::gpu::{DeviceGaussians, LayoutId};
use crate::passes::{
    ScanPipelines, U32_BYTES, VEC4_BYTES, bind_group, compute_pipeline, dispatch_linear,
    inclusive_scan,
};
use crate::training::{AdamConfig, DeviceAdam, TrainingKernels, zero_moments};
use crate::types::{GaussianCloud, RigidTransform};
use crate::wgsl::{
    CompactParams, GroupTransform, PruneParams, TRANSFORM_ALL, TRANSFORM_BY_GROUP, TransformParams,
    WORKGROUP_SIZE, source,
};

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
    pub removed: usize,
}

impl From<&RigidTransform> for GroupTransform {
    fn from(transform: &RigidTransform) -> Self {
        let r = transform.rotation;
        let t = transform.translation;
        Self {
            row0: [r[0][0], r[0][1], r[0][2], t[0]],
            row1: [r[1][0], r[1][1], r[1][2], t[1]],
            row2: [r[2][0], r[2][1], r[2][2], t[2]],
            rotation_quaternion: transform.rotation_quaternion(),
        }
    }
}

/// Compiled kernels of the map edits; one set per [`GpuContext`], built on first use.
pub(crate) struct MapKernels {
    prune: wgpu::ComputePipeline,
    compact: wgpu::ComputePipeline,
    transform: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
}

impl MapKernels {
    fn of(context: &GpuContext) -> &MapKernels {
        context.map_kernels.get_or_init(|| {
            let device = &context.device;
            let pipeline =
                |label, parts: &[&str], entry| compute_pipeline(device, label, parts, entry);
            MapKernels {
                prune: pipeline("prune", &[source::PRUNE], "main"),
                compact: pipeline("compact", &[source::COMPACT], "main"),
                transform: pipeline("transform", &[source::TRANSFORM], "main"),
                scan_blocks: pipeline("scan_blocks", &[source::SCAN], "scan_blocks"),
                scan_add: pipeline("scan_add", &[source::SCAN], "add_block_offsets"),
            }
        })
    }

    fn scan(&self) -> ScanPipelines<'_> {
        ScanPipelines {
            blocks: &self.scan_blocks,
            add_offsets: &self.scan_add,
        }
    }
}

/// Bytes per Gaussian of a parameter group of `width` f32 values.
fn group_stride(width: u32) -> u64 {
    u64::from(width) * U32_BYTES
}

/// Most Gaussians one storage binding of the widest per-Gaussian buffer can hold.
fn max_capacity(context: &GpuContext) -> u64 {
    (context.max_storage_binding_bytes() / VEC4_BYTES).min(u64::from(u32::MAX))
}

/// Capacity for `required` Gaussians when `current` is too small: geometric growth, bounded
/// by `limit` Gaussians (see [`max_capacity`]).
fn grown_capacity(current: u32, required: u64, limit: u64) -> Result<u32, GpuError> {
    if required > limit {
        return Err(GpuError::TooLarge(format!(
            "{required} Gaussians need {}-byte bindings, the adapter binds at most {} bytes \
             ({limit} Gaussians)",
            required * VEC4_BYTES,
            limit * VEC4_BYTES
        )));
    }
    let geometric = u64::from(current) * GROWTH_NUMERATOR / GROWTH_DENOMINATOR;
    let capacity = required
        .max(geometric)
        .max(MIN_GROWN_CAPACITY as u64)
        .min(limit);
    // limit <= u32::MAX.
    Ok(capacity as u32)
}

/// New buffers of `capacity` Gaussians per parameter group holding copies of the first
/// `count` Gaussians of `old` (a device-side copy; the rest is zero).
fn grow_buffers<const N: usize>(
    context: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    old: [(&wgpu::Buffer, u32); N],
    count: u32,
    capacity: u32,
    label: &str,
) -> Result<[wgpu::Buffer; N], GpuError> {
    let mut grown = Vec::with_capacity(N);
    for (buffer, width) in old {
        let stride = group_stride(width);
        let new = context.storage_buffer(label, u64::from(capacity) * stride)?;
        if count > 0 {
            encoder.copy_buffer_to_buffer(buffer, 0, &new, 0, u64::from(count) * stride);
        }
        grown.push(new);
    }
    Ok(grown
        .try_into()
        .unwrap_or_else(|_| unreachable!("one buffer per input")))
}

/// Encodes the compaction of one per-Gaussian buffer into a fresh buffer of `capacity`
/// Gaussians, using the inclusive scan of the keep flags.
#[allow(clippy::too_many_arguments)]
fn compact_buffer(
    context: &GpuContext,
    kernels: &MapKernels,
    encoder: &mut wgpu::CommandEncoder,
    kept_through: &wgpu::Buffer,
    source: &wgpu::Buffer,
    width: u32,
    count: u32,
    capacity: u32,
) -> Result<wgpu::Buffer, GpuError> {
    let destination =
        context.storage_buffer("compacted", u64::from(capacity) * group_stride(width))?;
    let params = CompactParams {
        count,
        width,
        ..Zeroable::zeroed()
    };
    let params = context.uniform_buffer("compact params", bytemuck::bytes_of(&params));
    let group = bind_group(
        context,
        &kernels.compact,
        &[
            (0, &params),
            (1, kept_through),
            (2, source),
            (3, &destination),
        ],
    );
    dispatch_linear(
        encoder,
        &kernels.compact,
        &group,
        (count * width).div_ceil(WORKGROUP_SIZE),
    );
    Ok(destination)
}

/// Where the keep flags of a compaction come from.
enum Selection<'a> {
    Criteria(&'a PruneCriteria),
    Mask(&'a [bool]),
}

/// One flag per Gaussian before a compaction: whether it was kept. A mask is its own answer;
/// the prune kernel's verdicts are read back from the scanned flags (the compaction's only
/// read-back: the scan gives both the flags and the kept count).
fn kept_flags(
    context: &GpuContext,
    selection: &Selection,
    kept_through: &wgpu::Buffer,
    count: u32,
) -> Result<Vec<bool>, GpuError> {
    Ok(match selection {
        Selection::Mask(keep) => keep.to_vec(),
        Selection::Criteria(_) => {
            let kept_through: Vec<u32> = context.read_vec(kept_through, count as usize)?;
            let mut previous = 0;
            kept_through
                .iter()
                .map(|&through| {
                    let kept = through > previous;
                    previous = through;
                    kept
                })
                .collect()
        }
    })
}

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
    fn grow(&mut self, context: &GpuContext, required: u64) -> Result<(), GpuError> {
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

    fn dispatch_transform(
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
    fn compact(
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
    fn encode_keep_flags(
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
    fn follow_append(
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

    pub fn into_parts(self) -> (DeviceGaussians, DeviceAdam) {
        (self.gaussians, self.adam)
    }

    /// The Gaussians, for rendering, backward passes and downloads.
    pub fn gaussians(&self) -> &DeviceGaussians {
        &self.gaussians
    }

    pub fn adam(&self) -> &DeviceAdam {
        &self.adam
    }

    /// Learning rates and Adam constants (e.g. to scale the mean rate by the scene size).
    pub fn adam_config_mut(&mut self) -> &mut AdamConfig {
        &mut self.adam.config
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

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

#[cfg(test)]
mod tests {
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
}
