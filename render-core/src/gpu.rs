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
//! - rasterize (rasterize_tiles.wgsl + rasterize_pixels.wgsl + rasterize_subgroup.wgsl, or
//!   rasterize.wgsl without subgroups, see [`Subgroups`]): one workgroup of 16 invocations per 16x16 tile, 16 pixels
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
//! makes later frames large enough. The same holds for a binning walk that lavapipe's loop
//! limit cut short (its pairs are missing; `PairUsage::binning_cut_short`, see
//! render-core/README.md): later frames bin in smaller blocks. [`GpuRenderer::render`]
//! checks and re-renders, so one-off renders hold every pair; optimisation loops call
//! `check_pairs` outside their inner loop. A rasterizer's walk over a tile's list that the
//! loop limit cut short is reported too (`PairUsage::rasterizers_cut_short`), but not
//! re-rendered: it would end the same way. Kernels live in `src/kernels/*.wgsl`; each opens
//! with a comment on its thread mapping and invariants.
//!
//! Limits: every storage binding must fit `max_storage_buffer_binding_size` (128 MiB on
//! lavapipe). The widest per-Gaussian buffer holds 16 bytes per Gaussian and the binning
//! buffers 4 bytes per pair, so one frame handles up to `max_binding / 16` Gaussians (8.4 M
//! on lavapipe) and `max_binding / 4` pairs (33.5 M); beyond that [`GpuError::TooLarge`] is
//! returned (no chunked bindings yet). The backward pass's per-pair sums
//! ([`GradientOrder::Fixed`]) take 48 bytes per pair of capacity; a frame whose sums would not
//! fit one binding uses [`GradientOrder::Arrival`].

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use bytemuck::Zeroable;

use crate::context::{GpuContext, GpuError};
use crate::passes::{ScanPipelines, U32_BYTES, compute_pipeline};
use crate::types::{Camera, RasterConfig, RenderMode, RenderOutput, constants};
use crate::wgsl::{
    FRAME_STATUS_WORDS, RenderParams, STATUS_BINNING_CUT_SHORT, STATUS_PAIRS_NEEDED,
    STATUS_RASTERIZE_BACKWARD_CUT_SHORT, STATUS_RASTERIZE_CUT_SHORT, source,
};

pub use crate::gaussians::DeviceGaussians;
pub(crate) use crate::gaussians::LayoutId;
pub use crate::profile::StageTimes;
pub use crate::sort::DeviceSortBench;

impl RenderParams {
    pub(crate) fn new(camera: &Camera, gaussian_count: u32, config: &RasterConfig) -> Self {
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
        let [frustum_min_x, frustum_max_x, frustum_min_y, frustum_max_y] = frustum_bounds(camera);
        Self {
            camera_row0: row(0),
            camera_row1: row(1),
            camera_row2: row(2),
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            width: camera.width,
            height: camera.height,
            tiles_x,
            tiles_y,
            gaussian_count,
            min_splat_alpha: config.min_splat_alpha,
            max_splat_alpha: config.max_splat_alpha,
            min_transmittance: config.min_transmittance,
            low_pass_variance: constants::LOW_PASS_VARIANCE,
            near_plane: constants::NEAR_PLANE,
            max_log_scale: constants::MAX_LOG_SCALE,
            min_quaternion_norm_squared: constants::MIN_QUATERNION_NORM_SQUARED,
            extent_sigmas: constants::SPLAT_EXTENT_SIGMAS,
            frustum_min_x,
            frustum_max_x,
            frustum_min_y,
            frustum_max_y,
            ..Zeroable::zeroed()
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

/// Bytes of [`GradientOrder::Fixed`]'s per-pair gradient sums for a frame of `pair_capacity`
/// pairs: what decides whether the frame can use them (one binding) and what they allocate.
pub(crate) fn pair_sum_bytes(pair_capacity: u32) -> u64 {
    u64::from(pair_capacity) * u64::from(crate::wgsl::PAIR_SUM_STRIDE) * U32_BYTES
}

/// Tile/Gaussian pairs a frame needed and could hold, and which of its serial walks the
/// adapter's loop limit cut short (lavapipe ends all loops of an invocation after 65535 trips
/// in all; see render-core/README.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PairUsage {
    /// Tile/Gaussian pairs the frame needed, as counted on the device (may exceed
    /// `capacity`: then the farthest Gaussians' pairs were dropped).
    pub pairs: u32,
    /// Pairs the frame's binning buffers hold ([`DeviceFrame::pair_capacity`]).
    pub capacity: u32,
    /// A binning walk was cut short: some pairs are missing from the tile lists.
    pub binning_cut_short: bool,
    /// A forward rasterizer's walk over a tile's list was cut short: some pixels of that tile
    /// lack the splats after the cut.
    pub rasterize_cut_short: bool,
    /// A backward rasterizer's walk was cut short: the splats before the cut got no gradient
    /// from some pixels. Only set once the frame's backward pass has run.
    pub rasterize_backward_cut_short: bool,
}

impl DeviceFrame {
    /// The order this frame's backward pass sums gradients in.
    pub fn gradient_order(&self) -> GradientOrder {
        if self.pair_gradient_sums {
            GradientOrder::Fixed
        } else {
            GradientOrder::Arrival
        }
    }

    /// True when the renderer was set to [`GradientOrder::Fixed`] and this frame still sums in
    /// arrival order, because its pair sums ([`Self::fixed_order_bytes`]) would not fit one
    /// storage binding: its gradients, and so a run, no longer repeat bit for bit. Callers log
    /// it; render-core does not.
    pub fn gradient_order_fell_back(&self) -> bool {
        self.gradient_order_fell_back
    }

    /// Device memory the fixed order's per-pair sums take (or would take) for this frame.
    pub fn fixed_order_bytes(&self) -> u64 {
        pair_sum_bytes(self.pair_capacity)
    }
}

impl PairUsage {
    /// The frame dropped pairs: those of its farthest Gaussians past its capacity (see the
    /// module docs), or those of binning walks cut short. Either way later frames of the
    /// renderer get what they need (check_pairs).
    pub fn overflowed(&self) -> bool {
        self.pairs > self.capacity || self.binning_cut_short
    }

    /// A rasterizer's walk was cut short. Unlike an overflow, rendering again changes nothing:
    /// the tile's list is too long for the adapter (it would take splats far beyond today's
    /// maps, see render-core/README.md). The frame stays usable, minus those splats; callers
    /// report it.
    pub fn rasterizers_cut_short(&self) -> bool {
        self.rasterize_cut_short || self.rasterize_backward_cut_short
    }
}

/// The device-side result of one forward render (kept for a backward pass).
pub struct DeviceFrame {
    /// The camera the frame was rendered from (its size sizes the per-pixel buffers).
    pub camera: Camera,
    /// Layout of the Gaussians the frame was rendered from (checked by the backward pass).
    pub(crate) gaussian_layout: LayoutId,
    /// The `RenderParams` uniform the frame was rendered with (reused by the backward pass).
    pub(crate) params_buffer: wgpu::Buffer,
    /// Live Gaussians of the [`DeviceGaussians`] the frame was rendered from (its `len()` then);
    /// the per-Gaussian buffers below have this many entries.
    pub gaussian_count: u32,
    /// Tile/Gaussian pairs the frame's buffers hold at most (see [`GpuRenderer::check_pairs`]).
    pub pair_capacity: u32,
    /// FRAME_STATUS_WORDS words indexed by the STATUS_* constants (wgsl.rs), written on the
    /// device: pair counts and the loop-limit flags.
    pub(crate) frame_status: wgpu::Buffer,
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
    /// True when the backward pass sums gradients per pair first ([`GradientOrder::Fixed`] and
    /// the pair sums fit one binding); the binning buffers below serve that sum.
    pub(crate) pair_gradient_sums: bool,
    /// The renderer asked for [`GradientOrder::Fixed`] but the pair sums did not fit.
    pub(crate) gradient_order_fell_back: bool,
    pub(crate) bin_params: wgpu::Buffer,
    /// Gaussian indices front to back (the depth sort's output).
    pub(crate) depth_order: wgpu::Buffer,
    /// Per Gaussian in depth order, inclusive-scanned: the end of its pairs (the tiles its splat
    /// reaches, summed over it and the Gaussians in front).
    pub(crate) sorted_tile_counts: wgpu::Buffer,
    /// Per tile-list slot: its pair's depth-order index (where the per-pair gradient sums live).
    pub(crate) slot_pairs: wgpu::Buffer,
    /// Per pixel: r, g, b, depth.
    pub rgbd: wgpu::Buffer,
    /// Per pixel (f32): accumulated opacity, `1 - transmittance`.
    pub alpha: wgpu::Buffer,
    /// Per pixel (f32): the transmittance left after the last composited splat (read by the
    /// backward pass).
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
    pub(crate) sort_count_kept: wgpu::ComputePipeline,
    pub(crate) gather_counts: wgpu::ComputePipeline,
    pub(crate) pair_status: wgpu::ComputePipeline,
    pub(crate) count_pairs: wgpu::ComputePipeline,
    pub(crate) emit_pairs: wgpu::ComputePipeline,
    pub(crate) tile_ranges: wgpu::ComputePipeline,
    pub(crate) rasterize: wgpu::ComputePipeline,
    pub(crate) rasterize_backward: wgpu::ComputePipeline,
    pub(crate) pair_gradients: wgpu::ComputePipeline,
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
    /// How the backward pass adds gradients atomically.
    pub atomics: GradientAtomics,
    /// Whether the rasterizers may use subgroup operations.
    pub subgroups: Subgroups,
    /// In what order the backward pass sums a Gaussian's gradient over its tiles.
    pub gradient_order: GradientOrder,
}

impl Default for RendererOptions {
    fn default() -> Self {
        Self {
            atomics: GradientAtomics::Auto,
            subgroups: Subgroups::Auto,
            gradient_order: GradientOrder::Fixed,
        }
    }
}

/// In what order the backward pass adds up a Gaussian's gradient over the tiles it covers.
/// Float addition is not associative, so the order decides the last bits, and an optimisation
/// that runs thousands of steps carries those bits into visibly different maps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradientOrder {
    /// Each tile/Gaussian pair gets its own sum, which only its tile's workgroup touches; then
    /// pair_gradients.wgsl adds each Gaussian's pairs in depth order. The same input then gives
    /// the same bits on every run, whatever the threads' timing: on CPU adapters (a workgroup
    /// runs on one thread) and, with the subgroup kernels, on GPUs whose subgroups hold at
    /// least 8 lanes (at most two subgroups add to a pair, and two adds onto zero commute). Costs
    /// 48 bytes of device memory per pair of the frame's capacity
    /// ([`DeviceFrame::fixed_order_bytes`]); a frame whose pair sums would not fit one storage
    /// binding falls back to [`GradientOrder::Arrival`] and says so
    /// ([`DeviceFrame::gradient_order_fell_back`]).
    Fixed,
    /// Atomic adds straight into each Gaussian's sum, tiles in the order threads arrive.
    Arrival,
}

/// How the backward pass accumulates per-Gaussian gradients across pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradientAtomics {
    /// Native f32 atomic adds when the device has them, compare-exchange otherwise.
    Auto,
    /// Always the compare-exchange loop (the path for adapters without float atomics).
    CompareExchange,
}

/// Compiled kernels of the forward path.
pub struct GpuRenderer {
    pub(crate) pipelines: Pipelines,
    /// Pair capacity later frames allocate at least (grown by [`GpuRenderer::check_pairs`]).
    pair_capacity_hint: AtomicU64,
    /// Set by [`GpuRenderer::check_pairs`] once a frame's binning walk was cut short by the
    /// adapter's loop limit: later frames bin in blocks that stay within it
    /// (`forward::loop_safe_bin_block`).
    pub(crate) loop_safe_bin_blocks: AtomicBool,
    /// Checks ([`GpuRenderer::check_pairs`], also inside [`GpuRenderer::render`]) that found a
    /// rasterizer's walk cut short (see [`PairUsage::rasterizers_cut_short`]).
    checks_cut_short: AtomicU64,
    /// True when the backward pass uses native float atomics.
    pub uses_float_atomics: bool,
    /// True when the rasterizers use subgroup operations.
    pub uses_subgroups: bool,
    /// The order asked for in [`RendererOptions`]; a frame may still fall back to
    /// [`GradientOrder::Arrival`] ([`DeviceFrame::gradient_order`] says which it got).
    pub gradient_order: GradientOrder,
    /// [`GradientOrder::Fixed`]'s per-pair sums, kept between backward passes (all zeros
    /// between them, see pair_gradients.wgsl) and grown with the pair capacity; the lock is
    /// held from encoding a backward pass to its submission, so passes use it one at a time.
    pub(crate) pair_sums: Mutex<Option<wgpu::Buffer>>,
}

impl GpuRenderer {
    /// Compiles the kernels with the default [`RendererOptions`]: the fastest atomics and
    /// rasterizers `context` supports, [`GradientOrder::Fixed`].
    pub fn new(context: &GpuContext) -> Self {
        Self::with_atomics(context, GradientAtomics::Auto)
    }

    /// [`GpuRenderer::new`] with the backward pass's atomics chosen, the other options default
    /// (how the tests run the compare-exchange fallback on devices with float atomics).
    pub fn with_atomics(context: &GpuContext, atomics: GradientAtomics) -> Self {
        Self::with_options(
            context,
            RendererOptions {
                atomics,
                ..RendererOptions::default()
            },
        )
    }

    /// Compiles every kernel for `context` with the kernel choices of `options`. `Auto` choices
    /// use native float atomics and subgroups only where the device has them
    /// ([`Self::uses_float_atomics`], [`Self::uses_subgroups`] record the outcome).
    pub fn with_options(context: &GpuContext, options: RendererOptions) -> Self {
        let device = &context.device;
        let uses_float_atomics =
            options.atomics == GradientAtomics::Auto && context.has_float_atomics;
        let uses_subgroups = options.subgroups == Subgroups::Auto && context.has_subgroups;
        let atomics = if uses_float_atomics {
            source::ATOMICS_FLOAT
        } else {
            source::ATOMICS_CAS
        };
        let (rasterize, rasterize_backward) = if uses_subgroups {
            (
                source::RASTERIZE_SUBGROUP,
                source::RASTERIZE_BACKWARD_SUBGROUP,
            )
        } else {
            (source::RASTERIZE, source::RASTERIZE_BACKWARD)
        };
        let pipeline = |label, parts: &[&str], entry| compute_pipeline(device, label, parts, entry);
        let pipelines = Pipelines {
            project: pipeline("project", &[source::PROJECT], "main"),
            scan_blocks: pipeline("scan_blocks", &[source::SCAN], "scan_blocks"),
            scan_add: pipeline("scan_add", &[source::SCAN], "add_block_offsets"),
            sort_histogram: pipeline("sort_histogram", &[source::SORT], "histogram"),
            sort_scatter: pipeline("sort_scatter", &[source::SORT], "scatter"),
            sort_count_kept: pipeline("sort_count_kept", &[source::SORT], "count_kept"),
            gather_counts: pipeline("gather_counts", &[source::BIN], "gather_counts"),
            pair_status: pipeline("pair_status", &[source::BIN], "pair_status_from_scan"),
            count_pairs: pipeline("count_pairs", &[source::BIN], "count_pairs"),
            emit_pairs: pipeline("emit_pairs", &[source::BIN], "emit_pairs"),
            tile_ranges: pipeline("tile_ranges", &[source::BIN], "tile_ranges_from_table"),
            rasterize: pipeline(
                "rasterize",
                &[source::RASTERIZE_TILES, source::RASTERIZE_PIXELS, rasterize],
                "main",
            ),
            rasterize_backward: pipeline(
                "rasterize_backward",
                &[
                    atomics,
                    source::RASTERIZE_TILES,
                    source::RASTERIZE_BACKWARD_PIXELS,
                    rasterize_backward,
                ],
                "main",
            ),
            pair_gradients: pipeline("pair_gradients", &[source::PAIR_GRADIENTS], "main"),
            project_backward: pipeline("project_backward", &[source::PROJECT_BACKWARD], "main"),
            reduce: pipeline("reduce", &[source::REDUCE], "main"),
        };
        Self {
            pipelines,
            pair_capacity_hint: AtomicU64::new(0),
            loop_safe_bin_blocks: AtomicBool::new(false),
            checks_cut_short: AtomicU64::new(0),
            uses_float_atomics,
            uses_subgroups,
            gradient_order: options.gradient_order,
            pair_sums: Mutex::new(None),
        }
    }

    /// How many of this renderer's frame checks found a rasterizer's walk cut short by the
    /// adapter's loop limit ([`PairUsage::rasterizers_cut_short`]); [`GpuRenderer::render`]
    /// checks every frame it renders. Callers that render without looking at each check
    /// (evaluations) report a non-zero count.
    pub fn checks_cut_short(&self) -> u64 {
        self.checks_cut_short.load(Ordering::Relaxed)
    }

    /// Renders and reads the images back to the host. A frame whose rasterizer walks the
    /// adapter's loop limit cut short is returned as rendered and counted
    /// ([`GpuRenderer::checks_cut_short`]): rendering it again would end the same way.
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
            // check_pairs grew the capacity to fit, or made the binning blocks small enough
            // for the adapter's loop limit: the second render holds every pair.
            frame = self.render_frame(context, gaussians, camera, &RasterConfig::default())?;
            let retry = self.check_pairs(context, &frame)?;
            if retry.overflowed() {
                return Err(GpuError::TooLarge(format!(
                    "{} tile/Gaussian pairs, the adapter binds at most {}{}",
                    retry.pairs,
                    retry.capacity,
                    if retry.binning_cut_short {
                        " (and the pair binning outgrew the adapter's loop limit)"
                    } else {
                        ""
                    }
                )));
            }
        }
        self.read_output(context, &frame, mode)
    }

    /// Pair capacity of a frame of `gaussian_count` Gaussians: the grown estimate, at least
    /// INITIAL_PAIRS_PER_GAUSSIAN per Gaussian, at most what one binding holds.
    pub(crate) fn pair_capacity_for(&self, context: &GpuContext, gaussian_count: u32) -> u32 {
        let wanted = self
            .pair_capacity_hint
            .load(Ordering::Relaxed)
            .max(u64::from(gaussian_count) * INITIAL_PAIRS_PER_GAUSSIAN)
            .max(MIN_PAIR_CAPACITY);
        let binding_limit = context.max_storage_binding_bytes() / U32_BYTES;
        wanted.min(binding_limit).min(u64::from(u32::MAX)) as u32
    }

    /// Later frames allocate room for at least `pairs` tile/Gaussian pairs (within the device's
    /// binding size), as after a frame that needed them: for a caller that knows how large its
    /// frames get, to spare the first frames' overflow and the check that finds it.
    pub fn reserve_pairs(&self, pairs: u64) {
        self.pair_capacity_hint.fetch_max(pairs, Ordering::Relaxed);
    }

    /// Reads back how many tile/Gaussian pairs `frame` needed (blocking: call it outside an
    /// optimisation loop, e.g. every few hundred iterations, or after a one-off render). When
    /// the frame overflowed its capacity, later frames get room for the count plus
    /// PAIR_CAPACITY_GROWTH_PERCENT; when a binning walk was cut short, later frames bin in
    /// blocks small enough for the adapter's loop limit. It also reports the rasterizers'
    /// walks: the backward's once the frame's backward pass has been submitted.
    pub fn check_pairs(
        &self,
        context: &GpuContext,
        frame: &DeviceFrame,
    ) -> Result<PairUsage, GpuError> {
        let status: Vec<u32> =
            context.read_vec(&frame.frame_status, FRAME_STATUS_WORDS as usize)?;
        let flag = |word: u32| status[word as usize] != 0;
        let usage = PairUsage {
            pairs: status[STATUS_PAIRS_NEEDED as usize],
            capacity: frame.pair_capacity,
            binning_cut_short: flag(STATUS_BINNING_CUT_SHORT),
            rasterize_cut_short: flag(STATUS_RASTERIZE_CUT_SHORT),
            rasterize_backward_cut_short: flag(STATUS_RASTERIZE_BACKWARD_CUT_SHORT),
        };
        if usage.rasterizers_cut_short() {
            self.checks_cut_short.fetch_add(1, Ordering::Relaxed);
        }
        if usage.binning_cut_short {
            self.loop_safe_bin_blocks.store(true, Ordering::Relaxed);
        }
        if usage.pairs > usage.capacity {
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

    pub(crate) fn scan_pipelines(&self) -> ScanPipelines<'_> {
        ScanPipelines {
            blocks: &self.pipelines.scan_blocks,
            add_offsets: &self.pipelines.scan_add,
        }
    }
}
