//! The map edits' compiled kernels, capacity growth, and the compaction of one buffer by keep
//! flags.

use crate::context::{GpuContext, GpuError};
use bytemuck::Zeroable;

use crate::passes::{
    ScanPipelines, U32_BYTES, VEC4_BYTES, bind_group, compute_pipeline, dispatch_linear,
};
use crate::types::RigidTransform;
use crate::wgsl::{CompactParams, GroupTransform, WORKGROUP_SIZE, source};

use super::{GROWTH_DENOMINATOR, GROWTH_NUMERATOR, MIN_GROWN_CAPACITY, PruneCriteria};

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
    pub(super) prune: wgpu::ComputePipeline,
    pub(super) compact: wgpu::ComputePipeline,
    pub(super) transform: wgpu::ComputePipeline,
    pub(super) scan_blocks: wgpu::ComputePipeline,
    pub(super) scan_add: wgpu::ComputePipeline,
}

impl MapKernels {
    pub(super) fn of(context: &GpuContext) -> &MapKernels {
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

    pub(super) fn scan(&self) -> ScanPipelines<'_> {
        ScanPipelines {
            blocks: &self.scan_blocks,
            add_offsets: &self.scan_add,
        }
    }
}

/// Bytes per Gaussian of a parameter group of `width` f32 values.
pub(super) fn group_stride(width: u32) -> u64 {
    u64::from(width) * U32_BYTES
}

/// Most Gaussians one storage binding of the widest per-Gaussian buffer can hold.
pub(super) fn max_capacity(context: &GpuContext) -> u64 {
    (context.max_storage_binding_bytes() / VEC4_BYTES).min(u64::from(u32::MAX))
}

/// Capacity for `required` Gaussians when `current` is too small: geometric growth, bounded
/// by `limit` Gaussians (see [`max_capacity`]).
pub(super) fn grown_capacity(current: u32, required: u64, limit: u64) -> Result<u32, GpuError> {
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
pub(super) fn grow_buffers<const N: usize>(
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
#[allow(
    clippy::too_many_arguments,
    reason = "a GPU launch: its buffers and sizes"
)]
pub(super) fn compact_buffer(
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
pub(super) enum Selection<'a> {
    Criteria(&'a PruneCriteria),
    Mask(&'a [bool]),
}

/// One flag per Gaussian before a compaction: whether it was kept. A mask is its own answer;
/// the prune kernel's verdicts are read back from the scanned flags (the compaction's only
/// read-back: the scan gives both the flags and the kept count).
pub(super) fn kept_flags(
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
