//! Building blocks of every launcher: pipelines from kernel sources, bind groups, 1D
//! dispatches over a 2D grid, and the device prefix scan.

use bytemuck::Zeroable;

use crate::context::{GpuContext, GpuError};
use crate::wgsl::{self, SCAN_CHUNK, SERIAL_WORKGROUP_SIZE, ScanParams};

pub(crate) const U32_BYTES: u64 = 4;
pub(crate) const VEC4_BYTES: u64 = 16;
/// WebGPU's limit on workgroups per dispatch dimension; larger 1D grids spill into y.
const MAX_WORKGROUPS_PER_DIMENSION: u32 = 65_535;

/// Compiles entry point `entry` of the kernel made of `parts` (see [`wgsl::compose`]: the
/// generated prelude and common.wgsl come first).
pub(crate) fn compute_pipeline(
    device: &wgpu::Device,
    label: &str,
    parts: &[&str],
    entry: &str,
) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(wgsl::compose(parts).into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: None,
        module: &module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// Bind group 0 of `pipeline` with the given (binding, buffer) pairs; the pipelines use
/// automatic layouts, so exactly the bindings an entry point uses must be listed.
pub(crate) fn bind_group(
    context: &GpuContext,
    pipeline: &wgpu::ComputePipeline,
    entries: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = entries
        .iter()
        .map(|(binding, buffer)| wgpu::BindGroupEntry {
            binding: *binding,
            resource: buffer.as_entire_binding(),
        })
        .collect();
    context
        .device
        .create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
}

/// Dispatches `workgroups` workgroups of a 1D kernel, spilling into y past the per-axis limit.
pub(crate) fn dispatch_linear(
    encoder: &mut wgpu::CommandEncoder,
    pipeline: &wgpu::ComputePipeline,
    bind_group: &wgpu::BindGroup,
    workgroups: u32,
) {
    if workgroups == 0 {
        return;
    }
    let x = workgroups.min(MAX_WORKGROUPS_PER_DIMENSION);
    let y = workgroups.div_ceil(MAX_WORKGROUPS_PER_DIMENSION);
    let mut pass = encoder.begin_compute_pass(&Default::default());
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind_group, &[]);
    pass.dispatch_workgroups(x, y, 1);
}

/// The two entry points of scan.wgsl.
#[derive(Clone, Copy)]
pub(crate) struct ScanPipelines<'a> {
    pub(crate) blocks: &'a wgpu::ComputePipeline,
    pub(crate) add_offsets: &'a wgpu::ComputePipeline,
}

/// Encodes an in-place inclusive prefix sum of the first `count` u32 of `values`.
pub(crate) fn inclusive_scan(
    context: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    pipelines: ScanPipelines,
    values: &wgpu::Buffer,
    count: u32,
) -> Result<(), GpuError> {
    prefix_scan(context, encoder, pipelines, values, count, false)
}

/// Encodes an in-place prefix sum (inclusive, or exclusive: entry i = sum of entries < i) of
/// the first `count` u32 of `values` (scan.wgsl: chunk sums, their inclusive scan by
/// recursion, then a serial rescan of every chunk from its offset).
pub(crate) fn prefix_scan(
    context: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    pipelines: ScanPipelines,
    values: &wgpu::Buffer,
    count: u32,
    exclusive: bool,
) -> Result<(), GpuError> {
    if count == 0 {
        return Ok(());
    }
    let chunks = count.div_ceil(SCAN_CHUNK);
    let workgroups = chunks.div_ceil(SERIAL_WORKGROUP_SIZE);
    let block_sums = context.storage_buffer("scan block sums", u64::from(chunks) * U32_BYTES)?;
    let params = ScanParams {
        count,
        exclusive: u32::from(exclusive),
        ..Zeroable::zeroed()
    };
    let params = context.uniform_buffer("scan params", bytemuck::bytes_of(&params));
    let entries = [(0, &params), (1, values), (2, &block_sums)];
    if chunks > 1 {
        let group = bind_group(context, pipelines.blocks, &entries);
        dispatch_linear(encoder, pipelines.blocks, &group, workgroups);
        prefix_scan(context, encoder, pipelines, &block_sums, chunks, false)?;
    }
    let group = bind_group(context, pipelines.add_offsets, &entries);
    dispatch_linear(encoder, pipelines.add_offsets, &group, workgroups);
    Ok(())
}

/// A storage buffer holding one host-known element count (for kernels that read their count
/// from the device, such as the radix sort).
pub(crate) fn count_buffer(context: &GpuContext, count: u32) -> wgpu::Buffer {
    context.storage_buffer_init(
        "count",
        bytemuck::bytes_of(&[count, 0, 0, 0]),
        VEC4_BYTES as usize,
    )
}
