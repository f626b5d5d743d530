//! One frame of the forward pipeline, as named steps: allocate the frame's buffers, project,
//! depth-sort, count each Gaussian's tiles, bin the tile/Gaussian pairs, rasterize. Each step
//! only encodes work; the frame is submitted once at the end (or per stage when profiling).
//! See [`crate::gpu`] for what each stage does and why.

use bytemuck::Zeroable;

use crate::context::{GpuContext, GpuError};
use crate::gpu::{
    DeviceFrame, DeviceGaussians, GpuRenderer, GradientOrder, StageTimes, pair_sum_bytes,
};
use crate::passes::{
    U32_BYTES, VEC4_BYTES, bind_group, count_buffer, dispatch_linear, inclusive_scan, prefix_scan,
};
use crate::profile::StageProfiler;
use crate::types::{Camera, RasterConfig, constants};
use crate::wgsl::{
    BIN_WORKGROUP_SIZE, BinParams, FRAME_STATUS_WORDS, RenderParams, WORKGROUP_SIZE,
};
use std::sync::atomic::Ordering;

/// Pair-binning table entries per Gaussian the block size aims at (one (tile, block) counter
/// per entry; the binning walks each block serially, so larger blocks mean a smaller table but
/// fewer invocations).
const BIN_TABLE_ENTRIES_PER_GAUSSIAN: u32 = 1;
const MIN_BIN_BLOCK_SIZE: u32 = 32;

/// The largest block of Gaussians whose binning walk stays within
/// MAX_LOOP_TRIPS_PER_INVOCATION even when every Gaussian bins every one of `tile_count`
/// tiles: a walk makes one trip per Gaussian and one per tile it bins, and the lanes of a SIMD
/// CPU adapter wait for each other at every Gaussian. Frames use larger blocks (a smaller
/// table, a faster binning) until a walk is found cut short (`GpuRenderer::check_pairs`);
/// from then on the renderer's frames use this size.
pub(crate) fn loop_safe_bin_block(tile_count: u32) -> u32 {
    (MAX_LOOP_TRIPS_PER_INVOCATION / (tile_count + 1)).max(1)
}

/// Loop trips one shader invocation may make, all its loops together: lavapipe (gallivm) ends
/// every loop of an invocation once they have made 65535 trips in all, silently (a guard
/// against endless loops, shared by all loops of a shader), so a kernel that walks more work
/// serially loses the rest of it.
const MAX_LOOP_TRIPS_PER_INVOCATION: u32 = 65_535;

/// Block size and block count of the pair binning (bin.wgsl) for `gaussian_count`
/// Gaussians and `tile_count` tiles: the (tile, block) table aims at
/// BIN_TABLE_ENTRIES_PER_GAUSSIAN entries per Gaussian, holds blocks of at most
/// `largest_block` Gaussians (see [`loop_safe_bin_block`]) and always fits one binding.
fn bin_blocks(
    context: &GpuContext,
    gaussian_count: u32,
    tile_count: u32,
    largest_block: u32,
) -> (u32, u32) {
    let max_entries = context.max_storage_binding_bytes() / U32_BYTES;
    let mut block_size = tile_count
        .div_ceil(BIN_TABLE_ENTRIES_PER_GAUSSIAN)
        .max(MIN_BIN_BLOCK_SIZE)
        .min(largest_block.max(1));
    while u64::from(tile_count) * u64::from(gaussian_count.div_ceil(block_size).max(1))
        > max_entries
    {
        block_size *= 2;
    }
    (block_size, gaussian_count.div_ceil(block_size).max(1))
}

/// Every buffer of one frame, allocated up front (nothing is sized from a read-back).
struct FrameBuffers {
    params: wgpu::Buffer,
    bin_params: wgpu::Buffer,
    bin: BinParams,
    splat_position: wgpu::Buffer,
    splat_conic: wgpu::Buffer,
    splat_colour: wgpu::Buffer,
    tile_rects: wgpu::Buffer,
    tile_counts: wgpu::Buffer,
    /// Depth keys and Gaussian indices, each with its radix-sort scratch twin.
    depth_keys: [wgpu::Buffer; 2],
    depth_values: [wgpu::Buffer; 2],
    sorted_tile_counts: wgpu::Buffer,
    intersection_gaussians: wgpu::Buffer,
    slot_pairs: wgpu::Buffer,
    bin_table: wgpu::Buffer,
    frame_status: wgpu::Buffer,
    tile_ranges: wgpu::Buffer,
    rgbd: wgpu::Buffer,
    alpha: wgpu::Buffer,
    transmittance: wgpu::Buffer,
    last_entry: wgpu::Buffer,
}

impl FrameBuffers {
    fn allocate(
        context: &GpuContext,
        camera: &Camera,
        config: &RasterConfig,
        gaussian_count: u32,
        pair_capacity: u32,
        pair_gradient_sums: bool,
        loop_safe_blocks: bool,
    ) -> Result<Self, GpuError> {
        let count = u64::from(gaussian_count);
        let (tiles_x, tiles_y) = camera.tile_counts();
        let tile_count = tiles_x * tiles_y;
        let pixels = camera.pixel_count() as u64;
        let largest_block = if loop_safe_blocks {
            loop_safe_bin_block(tile_count)
        } else {
            u32::MAX
        };
        let (block_size, block_count) =
            bin_blocks(context, gaussian_count, tile_count, largest_block);
        let bin = BinParams {
            gaussian_count,
            pair_capacity,
            tiles_x,
            tile_count,
            block_size,
            block_count,
            ..Zeroable::zeroed()
        };
        let params = RenderParams {
            pair_gradient_sums: u32::from(pair_gradient_sums),
            ..RenderParams::new(camera, gaussian_count, config)
        };
        let per_gaussian = |label| context.storage_buffer(label, count * U32_BYTES);
        let per_gaussian_vec4 = |label| context.storage_buffer(label, count * VEC4_BYTES);
        let bin_table_entries = u64::from(tile_count) * u64::from(block_count);
        Ok(Self {
            params: context.uniform_buffer("render params", bytemuck::bytes_of(&params)),
            bin_params: context.uniform_buffer("bin params", bytemuck::bytes_of(&bin)),
            bin,
            splat_position: per_gaussian_vec4("splat_position")?,
            splat_conic: per_gaussian_vec4("splat_conic")?,
            splat_colour: per_gaussian_vec4("splat_colour")?,
            tile_rects: per_gaussian_vec4("tile_rects")?,
            tile_counts: per_gaussian("tile_counts")?,
            depth_keys: [
                per_gaussian("depth_keys")?,
                per_gaussian("depth_keys_scratch")?,
            ],
            depth_values: [
                per_gaussian("depth_order")?,
                per_gaussian("depth_order_scratch")?,
            ],
            sorted_tile_counts: per_gaussian("sorted_tile_counts")?,
            // Sized from the capacity estimate, never from a read-back (see the gpu module
            // documentation for the overflow invariant).
            intersection_gaussians: context.storage_buffer(
                "intersection_gaussians",
                u64::from(pair_capacity) * U32_BYTES,
            )?,
            slot_pairs: context
                .storage_buffer("slot_pairs", u64::from(pair_capacity) * U32_BYTES)?,
            bin_table: context.storage_buffer("bin table", bin_table_entries * U32_BYTES)?,
            // FRAME_STATUS_WORDS words (see wgsl.rs); zero-filled, which is right for an empty
            // scene.
            frame_status: context
                .storage_buffer("frame_status", u64::from(FRAME_STATUS_WORDS) * U32_BYTES)?,
            // Fresh wgpu buffers are zero-filled, so tiles read as [0, 0) when there is
            // nothing to bin.
            tile_ranges: context
                .storage_buffer("tile_ranges", u64::from(tile_count) * 2 * U32_BYTES)?,
            rgbd: context.storage_buffer("rgbd", pixels * VEC4_BYTES)?,
            alpha: context.storage_buffer("alpha", pixels * U32_BYTES)?,
            transmittance: context.storage_buffer("transmittance", pixels * U32_BYTES)?,
            last_entry: context.storage_buffer("last_entry", pixels * U32_BYTES)?,
        })
    }
}

impl GpuRenderer {
    /// [`GpuRenderer::render_frame`], optionally timing each stage (every stage is then
    /// submitted and waited for on its own, which adds synchronisation: a benchmark tool).
    pub fn render_frame_profiled(
        &self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        camera: &Camera,
        config: &RasterConfig,
        stage_times: Option<&mut StageTimes>,
    ) -> Result<DeviceFrame, GpuError> {
        let mut profiler = StageProfiler::new(context, stage_times)?;
        validate_frame(camera, config)?;
        let n = gaussians.count;
        let pair_capacity = self.pair_capacity_for(context, n);
        let pair_sums_fit = pair_sum_bytes(pair_capacity) <= context.max_storage_binding_bytes();
        let pair_gradient_sums = self.gradient_order == GradientOrder::Fixed && pair_sums_fit;
        let buffers = FrameBuffers::allocate(
            context,
            camera,
            config,
            n,
            pair_capacity,
            pair_gradient_sums,
            self.loop_safe_bin_blocks.load(Ordering::Relaxed),
        )?;
        let mut encoder = context.device.create_command_encoder(&Default::default());
        // Which `depth_values` buffer ends up holding the depth order (none without Gaussians).
        let mut sorted = 0;
        if n > 0 {
            self.encode_project(context, &mut encoder, gaussians, &buffers);
            profiler.mark(context, &mut encoder, "project")?;
            sorted = self.encode_depth_sort(context, &mut encoder, &buffers, n)?;
            profiler.mark(context, &mut encoder, "depth sort")?;
            self.encode_tile_counts(context, &mut encoder, &buffers, sorted)?;
            profiler.mark(context, &mut encoder, "tile count scan")?;
            self.encode_binning(context, &mut encoder, &buffers, sorted, &mut profiler)?;
        }
        self.encode_rasterize(context, &mut encoder, &buffers, camera);
        profiler.mark(context, &mut encoder, "rasterize")?;
        context.queue.submit([encoder.finish()]);
        let [depth_values, depth_scratch] = buffers.depth_values;
        Ok(DeviceFrame {
            camera: *camera,
            gaussian_layout: gaussians.layout,
            params_buffer: buffers.params,
            gaussian_count: n,
            pair_capacity,
            frame_status: buffers.frame_status,
            splat_position: buffers.splat_position,
            splat_conic: buffers.splat_conic,
            splat_colour: buffers.splat_colour,
            tile_ranges: buffers.tile_ranges,
            intersection_gaussians: buffers.intersection_gaussians,
            pair_gradient_sums,
            gradient_order_fell_back: self.gradient_order == GradientOrder::Fixed && !pair_sums_fit,
            bin_params: buffers.bin_params,
            depth_order: if sorted == 0 {
                depth_values
            } else {
                depth_scratch
            },
            sorted_tile_counts: buffers.sorted_tile_counts,
            slot_pairs: buffers.slot_pairs,
            rgbd: buffers.rgbd,
            alpha: buffers.alpha,
            transmittance: buffers.transmittance,
            last_entry: buffers.last_entry,
        })
    }

    /// project.wgsl: splats, tile rectangles and counts, depth keys.
    fn encode_project(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: &DeviceGaussians,
        b: &FrameBuffers,
    ) {
        let pipeline = &self.pipelines.project;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &b.params),
                (1, &gaussians.means),
                (2, &gaussians.log_scales),
                (3, &gaussians.quaternions),
                (4, &gaussians.opacity_logits),
                (5, &gaussians.colours),
                (6, &b.splat_position),
                (7, &b.splat_conic),
                (8, &b.splat_colour),
                (9, &b.tile_rects),
                (10, &b.tile_counts),
                (11, &b.depth_keys[0]),
            ],
        );
        let workgroups = b.bin.gaussian_count.div_ceil(WORKGROUP_SIZE);
        dispatch_linear(encoder, pipeline, &group, workgroups);
    }

    /// Radix sort of the depth keys; returns which `depth_values` buffer holds the
    /// front-to-back Gaussian order (the sort takes each key's index, its Gaussian, as its
    /// value). Culled Gaussians are split off in the first pass and stay behind the others
    /// in index order, as a whole sort would leave them.
    fn encode_depth_sort(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        b: &FrameBuffers,
        n: u32,
    ) -> Result<usize, GpuError> {
        self.radix_sort(
            context,
            encoder,
            [&b.depth_keys[0], &b.depth_keys[1]],
            [&b.depth_values[0], &b.depth_values[1]],
            &count_buffer(context, n),
            n,
            constants::DEPTH_KEY_BITS,
            true,
        )
    }

    /// Tile counts in depth order, inclusive-scanned: each Gaussian's first pair index.
    fn encode_tile_counts(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        b: &FrameBuffers,
        sorted: usize,
    ) -> Result<(), GpuError> {
        let pipeline = &self.pipelines.gather_counts;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &b.bin_params),
                (1, &b.depth_values[sorted]),
                (2, &b.tile_counts),
                (3, &b.sorted_tile_counts),
            ],
        );
        let n = b.bin.gaussian_count;
        dispatch_linear(encoder, pipeline, &group, n.div_ceil(WORKGROUP_SIZE));
        inclusive_scan(
            context,
            encoder,
            self.scan_pipelines(),
            &b.sorted_tile_counts,
            n,
        )
    }

    /// bin.wgsl: pair status, the (tile, block) counts, their exclusive scan, the pairs
    /// themselves and each tile's range of them.
    fn encode_binning(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        b: &FrameBuffers,
        sorted: usize,
        profiler: &mut StageProfiler,
    ) -> Result<(), GpuError> {
        let p = &self.pipelines;
        let status_group = bind_group(
            context,
            &p.pair_status,
            &[
                (0, &b.bin_params),
                (3, &b.sorted_tile_counts),
                (9, &b.frame_status),
            ],
        );
        dispatch_linear(encoder, &p.pair_status, &status_group, 1);
        let walk_entries = [
            (0, &b.bin_params),
            (1, &b.depth_values[sorted]),
            (2, &b.tile_counts),
            (3, &b.sorted_tile_counts),
            (4, &b.tile_rects),
            (5, &b.bin_table),
            (6, &b.intersection_gaussians),
            (7, &b.slot_pairs),
            (9, &b.frame_status),
        ];
        let block_workgroups = b.bin.block_count.div_ceil(BIN_WORKGROUP_SIZE);
        encoder.clear_buffer(&b.bin_table, 0, None);
        let count_group = bind_group(context, &p.count_pairs, &walk_entries);
        dispatch_linear(encoder, &p.count_pairs, &count_group, block_workgroups);
        profiler.mark(context, encoder, "count pairs")?;
        let table_entries = b.bin.tile_count * b.bin.block_count;
        let scan = self.scan_pipelines();
        prefix_scan(context, encoder, scan, &b.bin_table, table_entries, true)?;
        profiler.mark(context, encoder, "table scan")?;
        let emit_group = bind_group(context, &p.emit_pairs, &walk_entries);
        dispatch_linear(encoder, &p.emit_pairs, &emit_group, block_workgroups);
        profiler.mark(context, encoder, "emit pairs")?;
        let ranges_group = bind_group(
            context,
            &p.tile_ranges,
            &[(0, &b.bin_params), (5, &b.bin_table), (8, &b.tile_ranges)],
        );
        let tile_workgroups = b.bin.tile_count.div_ceil(WORKGROUP_SIZE);
        dispatch_linear(encoder, &p.tile_ranges, &ranges_group, tile_workgroups);
        profiler.mark(context, encoder, "tile ranges")
    }

    /// The rasterizer: one workgroup per tile.
    fn encode_rasterize(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        b: &FrameBuffers,
        camera: &Camera,
    ) {
        let pipeline = &self.pipelines.rasterize;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &b.params),
                (1, &b.tile_ranges),
                (2, &b.intersection_gaussians),
                (3, &b.splat_position),
                (4, &b.splat_conic),
                (5, &b.splat_colour),
                (6, &b.rgbd),
                (7, &b.alpha),
                (8, &b.transmittance),
                (9, &b.last_entry),
                (12, &b.frame_status),
            ],
        );
        let (tiles_x, tiles_y) = camera.tile_counts();
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(tiles_x, tiles_y, 1);
    }
}

/// The GPU path needs a non-empty image and always bins splats into tiles.
fn validate_frame(camera: &Camera, config: &RasterConfig) -> Result<(), GpuError> {
    if camera.width == 0 || camera.height == 0 {
        return Err(GpuError::InvalidInput(format!(
            "image size {}x{}",
            camera.width, camera.height
        )));
    }
    if !config.restrict_to_tiles {
        return Err(GpuError::InvalidInput(
            "the GPU path always bins splats into tiles".into(),
        ));
    }
    Ok(())
}
