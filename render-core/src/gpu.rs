//! The wgpu forward renderer: project -> depth sort -> pair binning -> rasterize.
//!
//! - project (project.wgsl): per Gaussian its splat (mean, conic, opacity, depth), its tile
//!   rectangle and, for rectangles of up to 32 tiles, the mask of tiles its visible ellipse
//!   reaches; depth keys.
//! - depth sort (sort.wgsl, scan.wgsl): stable LSD radix sort of the depth keys, 8-bit digits,
//!   one invocation walking a block of keys serially.
//! - pair binning (bin.wgsl): the depth-ordered Gaussians are cut into blocks; a (tile, block)
//!   counter table is filled by one serial walk per block, exclusive-scanned, and a second
//!   walk writes every Gaussian into its tiles' lists. Each tile's list comes out in depth
//!   order without sorting the pairs.
//! - rasterize (rasterize_pixels.wgsl + rasterize_subgroup.wgsl, or rasterize.wgsl without
//!   subgroups, see [`Subgroups`]): one workgroup of 16 invocations per 16x16 tile, 16 pixels
//!   per invocation.
//!
//! Why the kernels look the way they do: on CPU adapters (lavapipe, the target of this crate
//! in CI and on GPU-less machines) every load or store of a non-uniform address is a
//! per-lane scalar loop costing as much as dozens of arithmetic operations, while workgroup
//! barriers and cross-invocation cooperation are expensive. So kernels walk blocks serially
//! per invocation (sort, scan, binning, reductions) and the rasterizers share splat loads
//! between lanes with subgroup shuffles and between 16 pixels per invocation.
//!
//! Nothing is read back to the host inside [`GpuRenderer::render_frame`]. The number of
//! tile/Gaussian pairs is only known on the device, so the binning buffers are allocated with
//! a capacity estimate ([`DeviceFrame::pair_capacity`]: at least 8 pairs per Gaussian, grown
//! by [`GpuRenderer::check_pairs`]) and every pair kernel reads the real count from the
//! device. Invariant: a frame whose pairs exceed its capacity keeps exactly the first
//! `capacity` pairs in depth order, i.e. it drops the pairs of its farthest Gaussians and
//! stays a valid (slightly incomplete) render; [`GpuRenderer::check_pairs`] reports it and
//! makes later frames large enough. [`GpuRenderer::render`] checks and re-renders, so
//! one-off renders are always complete; optimisation loops call `check_pairs` outside their
//! inner loop. Kernels live in `src/kernels/*.wgsl`; each opens with a comment on its thread
//! mapping and invariants.
//!
//! Limits: every storage binding must fit `max_storage_buffer_binding_size` (128 MiB on
//! lavapipe). The widest per-Gaussian buffer holds 16 bytes per Gaussian and the binning
//! buffers 4 bytes per pair, so one frame handles up to `max_binding / 16` Gaussians (8.4 M
//! on lavapipe) and `max_binding / 4` pairs (33.5 M); beyond that [`GpuError::TooLarge`] is
//! returned (no chunked bindings yet).

use std::sync::atomic::{AtomicU64, Ordering};

use bytemuck::{Pod, Zeroable};

use crate::context::{GpuContext, GpuError};
use crate::types::{Camera, GaussianCloud, RasterConfig, RenderMode, RenderOutput, constants};

/// Invocations per workgroup of the 1D kernels (project, gather, tile ranges, reduce).
pub(crate) const WORKGROUP_SIZE: u32 = 256;
/// Invocations per workgroup of the kernels where one invocation walks a block or chunk
/// serially (scan, radix sort; WORKGROUP_SIZE in their kernels).
const SERIAL_WORKGROUP_SIZE: u32 = 64;
/// Values per invocation of the prefix scan (CHUNK in scan.wgsl).
const SCAN_CHUNK: u32 = 256;
/// WebGPU's limit on workgroups per dispatch dimension; larger 1D grids spill into y.
const MAX_WORKGROUPS_PER_DIMENSION: u32 = 65_535;
/// Digit width of the radix sort (must match RADIX_BITS in sort.wgsl).
const RADIX_BITS: u32 = 8;
const RADIX: u32 = 1 << RADIX_BITS;
/// Keys per radix-sort invocation: between these bounds, aiming at SORT_BLOCKS_TARGET blocks
/// (enough invocations to keep every CPU thread busy, few enough that the digit table,
/// RADIX entries per block, stays small next to the keys).
const MIN_SORT_BLOCK_SIZE: u32 = 64;
const MAX_SORT_BLOCK_SIZE: u32 = 1024;
const SORT_BLOCKS_TARGET: u32 = 256;
/// Pair-binning table entries per Gaussian the block size aims at (one (tile, block) counter
/// per entry; the binning walks each block serially, so larger blocks mean a smaller table but
/// fewer invocations).
const BIN_TABLE_ENTRIES_PER_GAUSSIAN: u32 = 1;
const MIN_BIN_BLOCK_SIZE: u32 = 32;
/// Invocations per workgroup of the pair binning (BLOCK_WORKGROUP_SIZE in bin.wgsl). There are
/// only ~100 blocks at 100k Gaussians, and a CPU adapter runs each workgroup on one thread:
/// small workgroups spread the blocks evenly over the threads (with 64-wide ones, the 84 blocks
/// of 100k Gaussians at 640x480 made workgroups of 64 and 20, so one of two cores walked three
/// quarters of the pairs; 8-wide ones cut the binning there from 23 to 15 ms).
const BIN_WORKGROUP_SIZE: u32 = 8;
pub(crate) const U32_BYTES: u64 = 4;
/// Parameter groups of a Gaussian: means, log-scales, quaternions, opacity logits, colours.
pub(crate) const PARAMETER_GROUPS: usize = 5;
/// f32 values per Gaussian of each parameter group, in the order of [`PARAMETER_GROUPS`].
pub(crate) const PARAMETER_GROUP_WIDTHS: [u32; PARAMETER_GROUPS] = [3, 3, 4, 1, 3];
pub(crate) const VEC4_BYTES: u64 = 16;

pub(crate) const COMMON_WGSL: &str = include_str!("kernels/common.wgsl");
const PROJECT_WGSL: &str = include_str!("kernels/project.wgsl");
pub(crate) const SCAN_WGSL: &str = include_str!("kernels/scan.wgsl");
const SORT_WGSL: &str = include_str!("kernels/sort.wgsl");
const BIN_WGSL: &str = include_str!("kernels/bin.wgsl");
const RASTERIZE_PIXELS_WGSL: &str = include_str!("kernels/rasterize_pixels.wgsl");
const RASTERIZE_WGSL: &str = include_str!("kernels/rasterize.wgsl");
const RASTERIZE_SUBGROUP_WGSL: &str = include_str!("kernels/rasterize_subgroup.wgsl");

/// Mirrors `RenderParams` in common.wgsl.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct RenderParams {
    camera_row0: [f32; 4],
    camera_row1: [f32; 4],
    camera_row2: [f32; 4],
    intrinsics: [f32; 4],
    image_size: [u32; 4],
    counts: [u32; 4],
    thresholds: [f32; 4],
    culling: [f32; 4],
    frustum: [f32; 4],
}

impl RenderParams {
    fn new(camera: &Camera, gaussian_count: u32, config: &RasterConfig) -> Self {
        let rotation = camera.camera_from_world.rotation;
        let translation = camera.camera_from_world.translation;
        let row = |i: usize| {
            [
                rotation[i][0],
                rotation[i][1],
                rotation[i][2],
                translation[i],
            ]
        };
        let (tiles_x, tiles_y) = camera.tile_counts();
        Self {
            camera_row0: row(0),
            camera_row1: row(1),
            camera_row2: row(2),
            intrinsics: [camera.fx, camera.fy, camera.cx, camera.cy],
            image_size: [camera.width, camera.height, tiles_x, tiles_y],
            counts: [gaussian_count, 0, 0, 0],
            thresholds: [
                config.min_splat_alpha,
                config.max_splat_alpha,
                config.min_transmittance,
                constants::LOW_PASS_VARIANCE,
            ],
            culling: [
                constants::NEAR_PLANE,
                constants::MAX_LOG_SCALE,
                constants::MIN_QUATERNION_NORM_SQUARED,
                constants::SPLAT_EXTENT_SIGMAS,
            ],
            frustum: frustum_bounds(camera),
        }
    }
}

/// `[min x/z, max x/z, min y/z, max y/z]` of the means that are projected (see
/// [`constants::FRUSTUM_GUARD_BAND`]); the CPU reference uses the same bounds.
pub(crate) fn frustum_bounds(camera: &Camera) -> [f32; 4] {
    let guard = constants::FRUSTUM_GUARD_BAND;
    let (width, height) = (camera.width as f32, camera.height as f32);
    [
        (-guard * width - camera.cx) / camera.fx,
        ((1.0 + guard) * width - camera.cx) / camera.fx,
        (-guard * height - camera.cy) / camera.fy,
        ((1.0 + guard) * height - camera.cy) / camera.fy,
    ]
}

/// Pairs the binning buffers get per Gaussian before any frame has reported its real need.
const INITIAL_PAIRS_PER_GAUSSIAN: u64 = 8;
/// Smallest pair capacity of a frame.
const MIN_PAIR_CAPACITY: u64 = 1024;
/// Head-room added when a frame overflowed its pair capacity.
const PAIR_CAPACITY_GROWTH_PERCENT: u64 = 50;

/// Tile/Gaussian pairs a frame needed and could hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PairUsage {
    pub pairs: u32,
    pub capacity: u32,
}

impl PairUsage {
    /// The frame dropped pairs (those of its farthest Gaussians, see the module docs).
    pub fn overflowed(&self) -> bool {
        self.pairs > self.capacity
    }
}

/// Wall-clock milliseconds per forward stage, in pipeline order (see [`GpuRenderer::render_frame_profiled`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StageTimes(pub Vec<(&'static str, f64)>);

impl StageTimes {
    /// Per-stage medians of several profiled runs (stages matched by position).
    pub fn median_of(runs: &[StageTimes]) -> StageTimes {
        let Some(first) = runs.first() else {
            return StageTimes::default();
        };
        StageTimes(
            first
                .0
                .iter()
                .enumerate()
                .map(|(stage, (name, _))| {
                    let mut values: Vec<f64> = runs
                        .iter()
                        .filter_map(|run| run.0.get(stage).map(|(_, ms)| *ms))
                        .collect();
                    values.sort_by(f64::total_cmp);
                    (*name, values[values.len() / 2])
                })
                .collect(),
        )
    }
}

/// Splits a frame into separately submitted and waited-for stages when profiling; a no-op
/// otherwise (then the stages share command encoders as usual).
pub(crate) struct StageProfiler<'a> {
    times: Option<&'a mut StageTimes>,
    last_mark: std::time::Instant,
}

impl<'a> StageProfiler<'a> {
    pub(crate) fn new(
        context: &GpuContext,
        times: Option<&'a mut StageTimes>,
    ) -> Result<Self, GpuError> {
        if times.is_some() {
            context.wait_idle()?;
        }
        Ok(Self {
            times,
            last_mark: std::time::Instant::now(),
        })
    }

    /// Ends stage `name`: when profiling, submits `encoder`, waits for the device and records
    /// the elapsed time, leaving a fresh encoder in place.
    pub(crate) fn mark(
        &mut self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        name: &'static str,
    ) -> Result<(), GpuError> {
        let Some(times) = self.times.as_deref_mut() else {
            return Ok(());
        };
        let finished = std::mem::replace(
            encoder,
            context.device.create_command_encoder(&Default::default()),
        );
        context.queue.submit([finished.finish()]);
        context.wait_idle()?;
        let now = std::time::Instant::now();
        times
            .0
            .push((name, (now - self.last_mark).as_secs_f64() * 1e3));
        self.last_mark = now;
        Ok(())
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
        )?;
        context.queue.submit([encoder.finish()]);
        Ok(())
    }
}

/// Gaussian parameters resident on the device (same layout and conventions as
/// [`GaussianCloud`]: means/log-scales/colours as packed f32 triples, quaternions `[w, x, y, z]`).
///
/// The buffers hold `capacity()` Gaussians of which the first `len()` are live; every kernel
/// works on the live count only. Structural edits (append, prune, retain, rigid transform)
/// happen in place on the device, see [`crate::map`].
pub struct DeviceGaussians {
    pub(crate) count: u32,
    /// Gaussians the buffers have room for (`>= count`).
    pub(crate) capacity: u32,
    /// Identifies the current order and number of Gaussians: renewed by every change of
    /// either, so frames, gradients and Adam state built for an older layout are rejected.
    pub(crate) layout: LayoutId,
    pub(crate) means: wgpu::Buffer,
    pub(crate) log_scales: wgpu::Buffer,
    pub(crate) quaternions: wgpu::Buffer,
    pub(crate) opacity_logits: wgpu::Buffer,
    pub(crate) colours: wgpu::Buffer,
}

impl DeviceGaussians {
    pub fn upload(context: &GpuContext, cloud: &GaussianCloud) -> Result<Self, GpuError> {
        cloud.validate_lengths().map_err(GpuError::InvalidInput)?;
        let count = u32::try_from(cloud.len())
            .map_err(|_| GpuError::TooLarge(format!("{} Gaussians exceed u32", cloud.len())))?;
        let widest = cloud.len() as u64 * VEC4_BYTES;
        if widest > context.max_storage_binding_bytes() {
            return Err(GpuError::TooLarge(format!(
                "{} Gaussians need {widest}-byte bindings, the adapter allows {}",
                cloud.len(),
                context.max_storage_binding_bytes()
            )));
        }
        let min = VEC4_BYTES as usize;
        Ok(Self {
            count,
            capacity: count,
            layout: LayoutId::fresh(),
            means: context.storage_buffer_init("means", bytemuck::cast_slice(&cloud.means), min),
            log_scales: context.storage_buffer_init(
                "log_scales",
                bytemuck::cast_slice(&cloud.log_scales),
                min,
            ),
            quaternions: context.storage_buffer_init(
                "quaternions",
                bytemuck::cast_slice(&cloud.quaternions),
                min,
            ),
            opacity_logits: context.storage_buffer_init(
                "opacity_logits",
                bytemuck::cast_slice(&cloud.opacity_logits),
                min,
            ),
            colours: context.storage_buffer_init(
                "colours",
                bytemuck::cast_slice(&cloud.colours),
                min,
            ),
        })
    }

    pub fn len(&self) -> usize {
        self.count as usize
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Gaussians the device buffers hold before [`DeviceGaussians::append`] must grow them.
    pub fn capacity(&self) -> usize {
        self.capacity as usize
    }

    /// The parameter buffers in [`PARAMETER_GROUP_WIDTHS`] order.
    pub(crate) fn parameter_buffers(&self) -> [&wgpu::Buffer; PARAMETER_GROUPS] {
        [
            &self.means,
            &self.log_scales,
            &self.quaternions,
            &self.opacity_logits,
            &self.colours,
        ]
    }

    /// Copies the parameters back to the host.
    pub fn download(&self, context: &GpuContext) -> Result<GaussianCloud, GpuError> {
        let n = self.len();
        Ok(GaussianCloud {
            means: context.read_vec(&self.means, n)?,
            log_scales: context.read_vec(&self.log_scales, n)?,
            quaternions: context.read_vec(&self.quaternions, n)?,
            opacity_logits: context.read_vec(&self.opacity_logits, n)?,
            colours: context.read_vec(&self.colours, n)?,
        })
    }
}

/// Identity of one arrangement (order and count) of a [`DeviceGaussians`]' entries; unique
/// within the process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LayoutId(u64);

impl LayoutId {
    pub(crate) fn fresh() -> Self {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        Self(NEXT.fetch_add(1, Ordering::Relaxed))
    }
}

/// The device-side result of one forward render (kept for a backward pass).
pub struct DeviceFrame {
    pub camera: Camera,
    /// Layout of the Gaussians the frame was rendered from (checked by the backward pass).
    pub(crate) gaussian_layout: LayoutId,
    /// The `RenderParams` uniform the frame was rendered with (reused by the backward pass).
    pub(crate) params_buffer: wgpu::Buffer,
    pub gaussian_count: u32,
    /// Tile/Gaussian pairs the frame's buffers hold at most (see [`GpuRenderer::check_pairs`]).
    pub pair_capacity: u32,
    /// `[pairs kept, pairs needed, 0, 0]`, written on the device.
    pub(crate) pair_status: wgpu::Buffer,
    /// Per Gaussian: mean2d.xy, opacity, camera z.
    pub splat_position: wgpu::Buffer,
    /// Per Gaussian: conic a, b, c, radius.
    pub splat_conic: wgpu::Buffer,
    /// Per Gaussian: rgb, unused.
    pub splat_colour: wgpu::Buffer,
    /// Per tile: [start, end) into `intersection_gaussians`.
    pub tile_ranges: wgpu::Buffer,
    /// Gaussian indices, grouped by tile, front to back within a tile.
    pub intersection_gaussians: wgpu::Buffer,
    /// Per pixel: r, g, b, depth.
    pub rgbd: wgpu::Buffer,
    pub alpha: wgpu::Buffer,
    pub transmittance: wgpu::Buffer,
    /// Per pixel: number of tile-list entries consumed up to the last contributing splat.
    pub last_entry: wgpu::Buffer,
}

pub(crate) struct Pipelines {
    pub(crate) project: wgpu::ComputePipeline,
    pub(crate) scan_blocks: wgpu::ComputePipeline,
    pub(crate) scan_add: wgpu::ComputePipeline,
    pub(crate) sort_histogram: wgpu::ComputePipeline,
    pub(crate) sort_scatter: wgpu::ComputePipeline,
    pub(crate) gather_counts: wgpu::ComputePipeline,
    pub(crate) pair_status: wgpu::ComputePipeline,
    pub(crate) count_pairs: wgpu::ComputePipeline,
    pub(crate) emit_pairs: wgpu::ComputePipeline,
    pub(crate) tile_ranges: wgpu::ComputePipeline,
    pub(crate) rasterize: wgpu::ComputePipeline,
    pub(crate) rasterize_backward: wgpu::ComputePipeline,
    pub(crate) project_backward: wgpu::ComputePipeline,
    pub(crate) reduce: wgpu::ComputePipeline,
}

/// Whether the rasterizers use subgroup operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Subgroups {
    /// Subgroup kernels when the device has them (`GpuContext::has_subgroups`), workgroup
    /// memory otherwise.
    Auto,
    /// Always the workgroup-memory kernels (the path for adapters without subgroups).
    Never,
}

/// Kernel choices of a [`GpuRenderer`]; [`Default`] picks the fastest the device supports.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RendererOptions {
    pub atomics: GradientAtomics,
    pub subgroups: Subgroups,
}

impl Default for RendererOptions {
    fn default() -> Self {
        Self {
            atomics: GradientAtomics::Auto,
            subgroups: Subgroups::Auto,
        }
    }
}

/// How the backward pass accumulates per-Gaussian gradients across pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradientAtomics {
    /// Native f32 atomic adds when the device has them, compare-exchange otherwise.
    Auto,
    /// Always the compare-exchange loop (the path for adapters without float atomics).
    CompareExchange,
}

pub(crate) fn compute_pipeline(
    device: &wgpu::Device,
    label: &str,
    source: &str,
    entry: &str,
) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
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
    let params = context.uniform_buffer(
        "scan params",
        &four_u32([count, u32::from(exclusive), 0, 0]),
    );
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

/// Block size and block count of the pair binning (bin.wgsl) for `gaussian_count`
/// Gaussians and `tile_count` tiles: the (tile, block) table aims at
/// BIN_TABLE_ENTRIES_PER_GAUSSIAN entries per Gaussian and always fits one binding.
fn bin_blocks(context: &GpuContext, gaussian_count: u32, tile_count: u32) -> (u32, u32) {
    let max_entries = context.max_storage_binding_bytes() / U32_BYTES;
    let mut block_size = tile_count
        .div_ceil(BIN_TABLE_ENTRIES_PER_GAUSSIAN)
        .max(MIN_BIN_BLOCK_SIZE);
    while u64::from(tile_count) * u64::from(gaussian_count.div_ceil(block_size).max(1))
        > max_entries
    {
        block_size *= 2;
    }
    (block_size, gaussian_count.div_ceil(block_size).max(1))
}

/// A storage buffer holding one host-known element count (for kernels that read their count
/// from the device, such as the radix sort).
pub(crate) fn count_buffer(context: &GpuContext, count: u32) -> wgpu::Buffer {
    context.storage_buffer_init("count", &four_u32([count, 0, 0, 0]), VEC4_BYTES as usize)
}

pub(crate) fn four_u32(values: [u32; 4]) -> [u8; 16] {
    bytemuck::cast(values)
}

/// Compiled kernels of the forward path.
pub struct GpuRenderer {
    pub(crate) pipelines: Pipelines,
    /// Pair capacity later frames allocate at least (grown by [`GpuRenderer::check_pairs`]).
    pair_capacity_hint: AtomicU64,
    /// True when the backward pass uses native float atomics.
    pub uses_float_atomics: bool,
    /// True when the rasterizers use subgroup operations.
    pub uses_subgroups: bool,
}

const RASTERIZE_BACKWARD_PIXELS_WGSL: &str = include_str!("kernels/rasterize_backward_pixels.wgsl");
const RASTERIZE_BACKWARD_WGSL: &str = include_str!("kernels/rasterize_backward.wgsl");
const RASTERIZE_BACKWARD_SUBGROUP_WGSL: &str =
    include_str!("kernels/rasterize_backward_subgroup.wgsl");
const ATOMICS_FLOAT_WGSL: &str = include_str!("kernels/atomics_float.wgsl");
const ATOMICS_CAS_WGSL: &str = include_str!("kernels/atomics_cas.wgsl");
const PROJECT_BACKWARD_WGSL: &str = include_str!("kernels/project_backward.wgsl");
const REDUCE_WGSL: &str = include_str!("kernels/reduce.wgsl");
/// Line of rasterize_backward.wgsl replaced by one of the atomics snippets.
const GRADIENT_ATOMICS_MARKER: &str = "\n#gradient_atomics\n";

impl GpuRenderer {
    pub fn new(context: &GpuContext) -> Self {
        Self::with_atomics(context, GradientAtomics::Auto)
    }

    pub fn with_atomics(context: &GpuContext, atomics: GradientAtomics) -> Self {
        Self::with_options(
            context,
            RendererOptions {
                atomics,
                ..RendererOptions::default()
            },
        )
    }

    pub fn with_options(context: &GpuContext, options: RendererOptions) -> Self {
        let device = &context.device;
        let uses_float_atomics =
            options.atomics == GradientAtomics::Auto && context.has_float_atomics;
        let uses_subgroups = options.subgroups == Subgroups::Auto && context.has_subgroups;
        let atomics_source = if uses_float_atomics {
            ATOMICS_FLOAT_WGSL
        } else {
            ATOMICS_CAS_WGSL
        };
        let (rasterize_main, rasterize_backward_main) = if uses_subgroups {
            (RASTERIZE_SUBGROUP_WGSL, RASTERIZE_BACKWARD_SUBGROUP_WGSL)
        } else {
            (RASTERIZE_WGSL, RASTERIZE_BACKWARD_WGSL)
        };
        let rasterize_source = format!("{COMMON_WGSL}\n{RASTERIZE_PIXELS_WGSL}\n{rasterize_main}");
        let rasterize_backward_source = format!(
            "{COMMON_WGSL}\n{}\n{rasterize_backward_main}",
            RASTERIZE_BACKWARD_PIXELS_WGSL
                .replace(GRADIENT_ATOMICS_MARKER, &format!("\n{atomics_source}\n"))
        );
        let with_common = |source: &str| format!("{COMMON_WGSL}\n{source}");
        let pipelines = Pipelines {
            project: compute_pipeline(device, "project", &with_common(PROJECT_WGSL), "main"),
            scan_blocks: compute_pipeline(device, "scan_blocks", SCAN_WGSL, "scan_blocks"),
            scan_add: compute_pipeline(device, "scan_add", SCAN_WGSL, "add_block_offsets"),
            sort_histogram: compute_pipeline(device, "sort_histogram", SORT_WGSL, "histogram"),
            sort_scatter: compute_pipeline(device, "sort_scatter", SORT_WGSL, "scatter"),
            gather_counts: compute_pipeline(device, "gather_counts", BIN_WGSL, "gather_counts"),
            pair_status: compute_pipeline(device, "pair_status", BIN_WGSL, "pair_status_from_scan"),
            count_pairs: compute_pipeline(device, "count_pairs", BIN_WGSL, "count_pairs"),
            emit_pairs: compute_pipeline(device, "emit_pairs", BIN_WGSL, "emit_pairs"),
            tile_ranges: compute_pipeline(
                device,
                "tile_ranges",
                BIN_WGSL,
                "tile_ranges_from_table",
            ),
            rasterize: compute_pipeline(device, "rasterize", &rasterize_source, "main"),
            rasterize_backward: compute_pipeline(
                device,
                "rasterize_backward",
                &rasterize_backward_source,
                "main",
            ),
            project_backward: compute_pipeline(
                device,
                "project_backward",
                &with_common(PROJECT_BACKWARD_WGSL),
                "main",
            ),
            reduce: compute_pipeline(device, "reduce", REDUCE_WGSL, "main"),
        };
        Self {
            pipelines,
            pair_capacity_hint: AtomicU64::new(0),
            uses_float_atomics,
            uses_subgroups,
        }
    }

    /// Renders and reads the images back to the host.
    pub fn render(
        &self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        camera: &Camera,
        mode: RenderMode,
    ) -> Result<RenderOutput, GpuError> {
        let mut frame = self.render_frame(context, gaussians, camera, &RasterConfig::default())?;
        let usage = self.check_pairs(context, &frame)?;
        if usage.overflowed() {
            // check_pairs grew the capacity to fit: the second render holds every pair.
            frame = self.render_frame(context, gaussians, camera, &RasterConfig::default())?;
            let retry = self.check_pairs(context, &frame)?;
            if retry.overflowed() {
                return Err(GpuError::TooLarge(format!(
                    "{} tile/Gaussian pairs, the adapter binds at most {}",
                    retry.pairs, retry.capacity
                )));
            }
        }
        self.read_output(context, &frame, mode)
    }

    /// Pair capacity of a frame of `gaussian_count` Gaussians: the grown estimate, at least
    /// INITIAL_PAIRS_PER_GAUSSIAN per Gaussian, at most what one binding holds.
    fn pair_capacity_for(&self, context: &GpuContext, gaussian_count: u32) -> u32 {
        let wanted = self
            .pair_capacity_hint
            .load(Ordering::Relaxed)
            .max(u64::from(gaussian_count) * INITIAL_PAIRS_PER_GAUSSIAN)
            .max(MIN_PAIR_CAPACITY);
        let binding_limit = context.max_storage_binding_bytes() / U32_BYTES;
        wanted.min(binding_limit).min(u64::from(u32::MAX)) as u32
    }

    /// Reads back how many tile/Gaussian pairs `frame` needed (blocking: call it outside an
    /// optimisation loop, e.g. every few hundred iterations, or after a one-off render). When
    /// the frame overflowed its capacity, later frames get room for the count plus
    /// PAIR_CAPACITY_GROWTH_PERCENT.
    pub fn check_pairs(
        &self,
        context: &GpuContext,
        frame: &DeviceFrame,
    ) -> Result<PairUsage, GpuError> {
        let status: Vec<u32> = context.read_vec(&frame.pair_status, 2)?;
        let usage = PairUsage {
            pairs: status[1],
            capacity: frame.pair_capacity,
        };
        if usage.overflowed() {
            let grown = u64::from(usage.pairs) * (100 + PAIR_CAPACITY_GROWTH_PERCENT) / 100;
            self.pair_capacity_hint.fetch_max(grown, Ordering::Relaxed);
        }
        Ok(usage)
    }

    /// Reads the images of `frame` selected by `mode` back to the host.
    pub fn read_output(
        &self,
        context: &GpuContext,
        frame: &DeviceFrame,
        mode: RenderMode,
    ) -> Result<RenderOutput, GpuError> {
        let pixels = frame.camera.pixel_count();
        let alpha: Vec<f32> = context.read_vec(&frame.alpha, pixels)?;
        let rgbd: Vec<[f32; 4]> = context.read_vec(&frame.rgbd, pixels)?;
        Ok(RenderOutput {
            width: frame.camera.width,
            height: frame.camera.height,
            rgb: mode
                .has_rgb()
                .then(|| rgbd.iter().map(|v| [v[0], v[1], v[2]]).collect()),
            depth: mode
                .has_depth()
                .then(|| rgbd.iter().map(|v| v[3]).collect()),
            alpha,
        })
    }

    /// Runs the forward pipeline, leaving every intermediate on the device. `config` supplies
    /// the thresholds; the GPU always restricts splats to their tiles.
    pub fn render_frame(
        &self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        camera: &Camera,
        config: &RasterConfig,
    ) -> Result<DeviceFrame, GpuError> {
        self.render_frame_profiled(context, gaussians, camera, config, None)
    }

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
        let n = gaussians.count;
        let count = u64::from(n);
        let (tiles_x, tiles_y) = camera.tile_counts();
        let tile_count = tiles_x * tiles_y;
        let pixels = camera.pixel_count() as u64;
        let params = RenderParams::new(camera, n, config);
        let params_buffer = context.uniform_buffer("render params", bytemuck::bytes_of(&params));

        let splat_position = context.storage_buffer("splat_position", count * VEC4_BYTES)?;
        let splat_conic = context.storage_buffer("splat_conic", count * VEC4_BYTES)?;
        let splat_colour = context.storage_buffer("splat_colour", count * VEC4_BYTES)?;
        let tile_rects = context.storage_buffer("tile_rects", count * VEC4_BYTES)?;
        let tile_counts = context.storage_buffer("tile_counts", count * U32_BYTES)?;
        let depth_keys = [
            context.storage_buffer("depth_keys", count * U32_BYTES)?,
            context.storage_buffer("depth_keys_scratch", count * U32_BYTES)?,
        ];
        let depth_values = [
            context.storage_buffer("depth_order", count * U32_BYTES)?,
            context.storage_buffer("depth_order_scratch", count * U32_BYTES)?,
        ];
        let sorted_tile_counts = context.storage_buffer("sorted_tile_counts", count * U32_BYTES)?;
        // Tile/Gaussian pairs: sized from the capacity estimate, never from a read-back (see
        // the module documentation for the overflow invariant).
        let pair_capacity = self.pair_capacity_for(context, n);
        let pair_bytes = u64::from(pair_capacity) * U32_BYTES;
        let intersection_gaussians =
            context.storage_buffer("intersection_gaussians", pair_bytes)?;
        let (bin_block_size, bin_blocks) = bin_blocks(context, n, tile_count);
        let bin_table_entries = u64::from(tile_count) * u64::from(bin_blocks);
        let bin_table = context.storage_buffer("bin table", bin_table_entries * U32_BYTES)?;
        // [pairs kept, pairs needed]; zero-filled, which is right for an empty scene.
        let pair_status = context.storage_buffer("pair_status", VEC4_BYTES)?;
        // Fresh wgpu buffers are zero-filled, so tiles read as [0, 0) when there is nothing
        // to bin.
        let tile_ranges =
            context.storage_buffer("tile_ranges", u64::from(tile_count) * 2 * U32_BYTES)?;
        let rgbd = context.storage_buffer("rgbd", pixels * VEC4_BYTES)?;
        let alpha = context.storage_buffer("alpha", pixels * U32_BYTES)?;
        let transmittance = context.storage_buffer("transmittance", pixels * U32_BYTES)?;
        let last_entry = context.storage_buffer("last_entry", pixels * U32_BYTES)?;

        let mut encoder = context.device.create_command_encoder(&Default::default());
        let p = &self.pipelines;
        let mut sorted_gaussians = &depth_values[0];
        let bin_params = context.uniform_buffer(
            "bin params",
            bytemuck::cast_slice(&[
                n,
                pair_capacity,
                tiles_x,
                tile_count,
                bin_block_size,
                bin_blocks,
                0,
                0,
            ]),
        );
        if n > 0 {
            let project_group = bind_group(
                context,
                &p.project,
                &[
                    (0, &params_buffer),
                    (1, &gaussians.means),
                    (2, &gaussians.log_scales),
                    (3, &gaussians.quaternions),
                    (4, &gaussians.opacity_logits),
                    (5, &gaussians.colours),
                    (6, &splat_position),
                    (7, &splat_conic),
                    (8, &splat_colour),
                    (9, &tile_rects),
                    (10, &tile_counts),
                    (11, &depth_keys[0]),
                    (12, &depth_values[0]),
                ],
            );
            dispatch_linear(
                &mut encoder,
                &p.project,
                &project_group,
                n.div_ceil(WORKGROUP_SIZE),
            );
            profiler.mark(context, &mut encoder, "project")?;
            let current = self.radix_sort(
                context,
                &mut encoder,
                [&depth_keys[0], &depth_keys[1]],
                [&depth_values[0], &depth_values[1]],
                &count_buffer(context, n),
                n,
                constants::DEPTH_KEY_BITS,
            )?;
            sorted_gaussians = &depth_values[current];
            profiler.mark(context, &mut encoder, "depth sort")?;
            let gather_group = bind_group(
                context,
                &p.gather_counts,
                &[
                    (0, &bin_params),
                    (1, sorted_gaussians),
                    (2, &tile_counts),
                    (3, &sorted_tile_counts),
                ],
            );
            dispatch_linear(
                &mut encoder,
                &p.gather_counts,
                &gather_group,
                n.div_ceil(WORKGROUP_SIZE),
            );
            self.inclusive_scan(context, &mut encoder, &sorted_tile_counts, n)?;
            profiler.mark(context, &mut encoder, "tile count scan")?;
        }
        if n > 0 {
            let status_group = bind_group(
                context,
                &p.pair_status,
                &[
                    (0, &bin_params),
                    (3, &sorted_tile_counts),
                    (9, &pair_status),
                ],
            );
            dispatch_linear(&mut encoder, &p.pair_status, &status_group, 1);
            let walk_entries = [
                (0, &bin_params),
                (1, sorted_gaussians),
                (2, &tile_counts),
                (3, &sorted_tile_counts),
                (4, &tile_rects),
                (5, &bin_table),
                (6, &intersection_gaussians),
            ];
            let bin_workgroups = bin_blocks.div_ceil(BIN_WORKGROUP_SIZE);
            encoder.clear_buffer(&bin_table, 0, None);
            let count_group = bind_group(context, &p.count_pairs, &walk_entries);
            dispatch_linear(&mut encoder, &p.count_pairs, &count_group, bin_workgroups);
            profiler.mark(context, &mut encoder, "count pairs")?;
            prefix_scan(
                context,
                &mut encoder,
                self.scan_pipelines(),
                &bin_table,
                tile_count * bin_blocks,
                true,
            )?;
            profiler.mark(context, &mut encoder, "table scan")?;
            let emit_group = bind_group(context, &p.emit_pairs, &walk_entries);
            dispatch_linear(&mut encoder, &p.emit_pairs, &emit_group, bin_workgroups);
            profiler.mark(context, &mut encoder, "emit pairs")?;
            let ranges_group = bind_group(
                context,
                &p.tile_ranges,
                &[(0, &bin_params), (5, &bin_table), (8, &tile_ranges)],
            );
            dispatch_linear(
                &mut encoder,
                &p.tile_ranges,
                &ranges_group,
                tile_count.div_ceil(WORKGROUP_SIZE),
            );
            profiler.mark(context, &mut encoder, "tile ranges")?;
        }
        let raster_group = bind_group(
            context,
            &p.rasterize,
            &[
                (0, &params_buffer),
                (1, &tile_ranges),
                (2, &intersection_gaussians),
                (3, &splat_position),
                (4, &splat_conic),
                (5, &splat_colour),
                (6, &rgbd),
                (7, &alpha),
                (8, &transmittance),
                (9, &last_entry),
            ],
        );
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&p.rasterize);
            pass.set_bind_group(0, &raster_group, &[]);
            pass.dispatch_workgroups(tiles_x, tiles_y, 1);
        }
        profiler.mark(context, &mut encoder, "rasterize")?;
        context.queue.submit([encoder.finish()]);
        Ok(DeviceFrame {
            camera: *camera,
            gaussian_layout: gaussians.layout,
            params_buffer,
            gaussian_count: n,
            pair_capacity,
            pair_status,
            splat_position,
            splat_conic,
            splat_colour,
            tile_ranges,
            intersection_gaussians,
            rgbd,
            alpha,
            transmittance,
            last_entry,
        })
    }

    fn scan_pipelines(&self) -> ScanPipelines<'_> {
        ScanPipelines {
            blocks: &self.pipelines.scan_blocks,
            add_offsets: &self.pipelines.scan_add,
        }
    }

    /// In-place inclusive prefix sum of the first `count` u32 of `values`.
    fn inclusive_scan(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        values: &wgpu::Buffer,
        count: u32,
    ) -> Result<(), GpuError> {
        inclusive_scan(context, encoder, self.scan_pipelines(), values, count)
    }

    /// Stable LSD radix sort of (key, value) pairs on the low `key_bits` bits, ping-ponging
    /// between the two buffers of each pair. The number of pairs is read on the device from
    /// `count_buffer[0]` (so it may come from an earlier kernel) and must not exceed
    /// `max_count`, which sizes the dispatches and the digit table. Returns which buffer
    /// (0 or 1) holds the sorted result.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn radix_sort(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        keys: [&wgpu::Buffer; 2],
        values: [&wgpu::Buffer; 2],
        count_buffer: &wgpu::Buffer,
        max_count: u32,
        key_bits: u32,
    ) -> Result<usize, GpuError> {
        let block_size = max_count
            .div_ceil(SORT_BLOCKS_TARGET)
            .clamp(MIN_SORT_BLOCK_SIZE, MAX_SORT_BLOCK_SIZE);
        let block_count = max_count.div_ceil(block_size).max(1);
        let table_entries = RADIX * block_count;
        let table = context.storage_buffer("sort table", u64::from(table_entries) * U32_BYTES)?;
        let workgroups = block_count.div_ceil(SERIAL_WORKGROUP_SIZE);
        let mut current = 0;
        for pass in 0..key_bits.div_ceil(RADIX_BITS) {
            let shift = pass * RADIX_BITS;
            let digit_bits = RADIX_BITS.min(key_bits - shift);
            let digit_mask = (1 << digit_bits) - 1;
            let params = context.uniform_buffer(
                "sort params",
                &four_u32([shift, digit_mask, block_size, block_count]),
            );
            let histogram_group = bind_group(
                context,
                &self.pipelines.sort_histogram,
                &[
                    (0, &params),
                    (1, keys[current]),
                    (3, &table),
                    (6, count_buffer),
                ],
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
                table_entries,
                true,
            )?;
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
                    (6, count_buffer),
                ],
            );
            dispatch_linear(
                encoder,
                &self.pipelines.sort_scatter,
                &scatter_group,
                workgroups,
            );
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
        let count = u32::try_from(keys.len())
            .map_err(|_| GpuError::TooLarge("more than u32::MAX pairs".into()))?;
        let min = VEC4_BYTES as usize;
        let key_buffers = [
            context.storage_buffer_init("keys", bytemuck::cast_slice(keys), min),
            context.storage_buffer("keys scratch", u64::from(count) * U32_BYTES)?,
        ];
        let value_buffers = [
            context.storage_buffer_init("values", bytemuck::cast_slice(values), min),
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
