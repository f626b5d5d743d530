//! The device radix sort (sort.wgsl, scan.wgsl): stable, least significant digit first,
//! RADIX_BITS bits per pass, one invocation walking a block of keys serially. The renderer
//! sorts depth keys with it; [`GpuRenderer::sort_pairs`], [`GpuRenderer::sort_depth_keys`] and
//! [`DeviceSortBench`] expose it to tests and the benchmark.

use bytemuck::Zeroable;

use crate::context::{GpuContext, GpuError};
use crate::gpu::GpuRenderer;
use crate::passes::{
    U32_BYTES, VEC4_BYTES, bind_group, count_buffer, dispatch_linear, prefix_scan,
};
use crate::types::constants;
use crate::wgsl::{RADIX_BITS, SERIAL_WORKGROUP_SIZE, SortParams};

const RADIX: u32 = 1 << RADIX_BITS;
/// Keys per radix-sort invocation: between these bounds, aiming at SORT_BLOCKS_TARGET blocks
/// (enough invocations to keep every CPU thread busy, few enough that the digit table,
/// RADIX entries per block that every pass scans, stays small next to the keys: 128 blocks
/// sorted a real map's depth keys faster than 256 or 64 on lavapipe, see docs/benchmarks.md).
const MIN_SORT_BLOCK_SIZE: u32 = 64;
const MAX_SORT_BLOCK_SIZE: u32 = 1024;
const SORT_BLOCKS_TARGET: u32 = 128;
// A depth sort leaves its culled keys where its first pass wrote them, so that pass's output
// buffer must be the one that ends up holding the result: an odd number of passes.
const _: () = assert!(constants::DEPTH_KEY_BITS.div_ceil(RADIX_BITS) % 2 == 1);

impl GpuRenderer {
    /// Stable LSD radix sort of (key, value) pairs on the low `key_bits` bits, ping-ponging
    /// between the two buffers of each pair. The number of pairs is read on the device from
    /// `count_buffer[0]` (so it may come from an earlier kernel) and must not exceed
    /// `max_count`, which sizes the dispatches and the digit table. With `depth_keys`, the
    /// keys are the depth keys of Gaussians 0, 1, ...: the first pass takes each key's index
    /// as its value (`values[0]` is not read) and leaves the keys equal to CULLED_DEPTH_KEY
    /// behind the others, in index order, and the later passes sort only the others
    /// (sort.wgsl): the same result as the whole sort of (key, index) pairs as long as no
    /// other key's low `key_bits` bits reach the culled key's (depth keys stay at or below
    /// LARGEST_VISIBLE_DEPTH_KEY), with an odd number of passes (the culled keys stay in the
    /// first pass's output buffer). Returns which buffer (0 or 1) holds the sorted result.
    #[allow(
        clippy::too_many_arguments,
        reason = "a GPU launch: the encoder, both ping-pong buffer pairs and the sort's sizes"
    )]
    pub(crate) fn radix_sort(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        keys: [&wgpu::Buffer; 2],
        values: [&wgpu::Buffer; 2],
        count_buffer: &wgpu::Buffer,
        max_count: u32,
        key_bits: u32,
        depth_keys: bool,
    ) -> Result<usize, GpuError> {
        let passes = key_bits.div_ceil(RADIX_BITS);
        if depth_keys && passes.is_multiple_of(2) {
            return Err(GpuError::InvalidInput(format!(
                "a depth sort needs an odd number of radix passes (its culled keys stay in the \
                 first pass's output), not {passes} for {key_bits} key bits"
            )));
        }
        let block_size = max_count
            .div_ceil(SORT_BLOCKS_TARGET)
            .clamp(MIN_SORT_BLOCK_SIZE, MAX_SORT_BLOCK_SIZE);
        let block_count = max_count.div_ceil(block_size).max(1);
        // One more bucket (table row) for the culled keys of a split pass.
        let table_entries = (RADIX + u32::from(depth_keys)) * block_count;
        let table = context.storage_buffer("sort table", u64::from(table_entries) * U32_BYTES)?;
        let kept_count = if depth_keys {
            Some(context.storage_buffer("sort kept count", VEC4_BYTES)?)
        } else {
            None
        };
        let workgroups = block_count.div_ceil(SERIAL_WORKGROUP_SIZE);
        let mut count = count_buffer;
        let mut current = 0;
        for pass in 0..passes {
            let shift = pass * RADIX_BITS;
            let digit_bits = RADIX_BITS.min(key_bits - shift);
            let digit_mask = (1 << digit_bits) - 1;
            let first_depth_pass = depth_keys && pass == 0;
            let params = SortParams {
                shift,
                digit_mask,
                block_size,
                block_count,
                depth_first_pass: u32::from(first_depth_pass),
                ..Zeroable::zeroed()
            };
            let params = context.uniform_buffer("sort params", bytemuck::bytes_of(&params));
            let histogram_group = bind_group(
                context,
                &self.pipelines.sort_histogram,
                &[(0, &params), (1, keys[current]), (3, &table), (6, count)],
            );
            dispatch_linear(
                encoder,
                &self.pipelines.sort_histogram,
                &histogram_group,
                workgroups,
            );
            prefix_scan(
                context,
                encoder,
                self.scan_pipelines(),
                &table,
                (RADIX + u32::from(first_depth_pass)) * block_count,
                true,
            )?;
            if let (true, Some(kept_count)) = (first_depth_pass, &kept_count) {
                let count_group = bind_group(
                    context,
                    &self.pipelines.sort_count_kept,
                    &[(0, &params), (3, &table), (7, kept_count)],
                );
                dispatch_linear(encoder, &self.pipelines.sort_count_kept, &count_group, 1);
            }
            let scatter_group = bind_group(
                context,
                &self.pipelines.sort_scatter,
                &[
                    (0, &params),
                    (1, keys[current]),
                    (2, values[current]),
                    (3, &table),
                    (4, keys[1 - current]),
                    (5, values[1 - current]),
                    (6, count),
                ],
            );
            dispatch_linear(
                encoder,
                &self.pipelines.sort_scatter,
                &scatter_group,
                workgroups,
            );
            if let (true, Some(kept_count)) = (first_depth_pass, &kept_count) {
                count = kept_count;
            }
            current = 1 - current;
        }
        Ok(current)
    }

    /// Sorts (key, value) pairs on the device by the low `key_bits` bits of the key, stably.
    /// A host-facing entry to the device radix sort (tests, tools).
    pub fn sort_pairs(
        &self,
        context: &GpuContext,
        keys: &[u32],
        values: &[u32],
        key_bits: u32,
    ) -> Result<(Vec<u32>, Vec<u32>), GpuError> {
        if keys.len() != values.len() {
            return Err(GpuError::InvalidInput(format!(
                "{} keys but {} values",
                keys.len(),
                values.len()
            )));
        }
        self.sort_on_device(context, keys, Some(values), key_bits)
    }

    /// Sorts the depth keys of Gaussians 0, 1, ... (render_core::depth_sort_key, or
    /// CULLED_DEPTH_KEY) the way a frame does: on DEPTH_KEY_BITS bits, the culled keys split off
    /// in the first pass. Returns the sorted keys and the Gaussians in that order: the same as
    /// [`GpuRenderer::sort_pairs`] of the keys and their indices on DEPTH_KEY_BITS bits.
    pub fn sort_depth_keys(
        &self,
        context: &GpuContext,
        keys: &[u32],
    ) -> Result<(Vec<u32>, Vec<u32>), GpuError> {
        self.sort_on_device(context, keys, None, constants::DEPTH_KEY_BITS)
    }

    /// `values`: the pairs' values, or None for depth keys (see [`GpuRenderer::radix_sort`]).
    fn sort_on_device(
        &self,
        context: &GpuContext,
        keys: &[u32],
        values: Option<&[u32]>,
        key_bits: u32,
    ) -> Result<(Vec<u32>, Vec<u32>), GpuError> {
        let count = u32::try_from(keys.len())
            .map_err(|_| GpuError::TooLarge("more than u32::MAX pairs".into()))?;
        let min = VEC4_BYTES as usize;
        let key_buffers = [
            context.storage_buffer_init("keys", bytemuck::cast_slice(keys), min),
            context.storage_buffer("keys scratch", u64::from(count) * U32_BYTES)?,
        ];
        let value_buffers = [
            match values {
                Some(values) => {
                    context.storage_buffer_init("values", bytemuck::cast_slice(values), min)
                }
                None => context.storage_buffer("values", u64::from(count) * U32_BYTES)?,
            },
            context.storage_buffer("values scratch", u64::from(count) * U32_BYTES)?,
        ];
        let mut encoder = context.device.create_command_encoder(&Default::default());
        let current = if count > 0 {
            self.radix_sort(
                context,
                &mut encoder,
                [&key_buffers[0], &key_buffers[1]],
                [&value_buffers[0], &value_buffers[1]],
                &count_buffer(context, count),
                count,
                key_bits.min(u32::BITS),
                values.is_none(),
            )?
        } else {
            0
        };
        context.queue.submit([encoder.finish()]);
        Ok((
            context.read_vec(&key_buffers[current], keys.len())?,
            context.read_vec(&value_buffers[current], keys.len())?,
        ))
    }
}

/// A device radix sort of fixed random input, for benchmarks: every [`DeviceSortBench::sort`]
/// restores the unsorted input on the device and sorts it (nothing is read back).
pub struct DeviceSortBench {
    count: u32,
    source_keys: wgpu::Buffer,
    source_values: wgpu::Buffer,
    keys: [wgpu::Buffer; 2],
    values: [wgpu::Buffer; 2],
}

impl DeviceSortBench {
    /// Uploads the (key, value) pairs to sort and allocates the sort's buffers. Fails with
    /// [`GpuError::InvalidInput`] when `keys` and `values` differ in length.
    pub fn new(context: &GpuContext, keys: &[u32], values: &[u32]) -> Result<Self, GpuError> {
        if keys.len() != values.len() {
            return Err(GpuError::InvalidInput(format!(
                "{} keys but {} values",
                keys.len(),
                values.len()
            )));
        }
        let count = u32::try_from(keys.len())
            .map_err(|_| GpuError::TooLarge("more than u32::MAX pairs".into()))?;
        let bytes = u64::from(count) * U32_BYTES;
        let min = VEC4_BYTES as usize;
        Ok(Self {
            count,
            source_keys: context.storage_buffer_init("bench keys", bytemuck::cast_slice(keys), min),
            source_values: context.storage_buffer_init(
                "bench values",
                bytemuck::cast_slice(values),
                min,
            ),
            keys: [
                context.storage_buffer("keys", bytes)?,
                context.storage_buffer("keys scratch", bytes)?,
            ],
            values: [
                context.storage_buffer("values", bytes)?,
                context.storage_buffer("values scratch", bytes)?,
            ],
        })
    }

    /// Restores the input and submits a sort on the low `key_bits` bits (does not wait).
    pub fn sort(
        &self,
        context: &GpuContext,
        renderer: &GpuRenderer,
        key_bits: u32,
    ) -> Result<(), GpuError> {
        if self.count == 0 {
            return Ok(());
        }
        let bytes = u64::from(self.count) * U32_BYTES;
        let mut encoder = context.device.create_command_encoder(&Default::default());
        encoder.copy_buffer_to_buffer(&self.source_keys, 0, &self.keys[0], 0, bytes);
        encoder.copy_buffer_to_buffer(&self.source_values, 0, &self.values[0], 0, bytes);
        renderer.radix_sort(
            context,
            &mut encoder,
            [&self.keys[0], &self.keys[1]],
            [&self.values[0], &self.values[1]],
            &count_buffer(context, self.count),
            self.count,
            key_bits.min(u32::BITS),
            false,
        )?;
        context.queue.submit([encoder.finish()]);
        Ok(())
    }
}
