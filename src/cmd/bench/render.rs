//! `mac-ego3d bench render`: timings of the render-core device pipeline (forward, forward +
//! backward, full optimisation iteration, radix sort, forward stages) on a synthetic
//! indoor-map-like scene. Figures are wall-clock on the machine it runs on.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use harness::{
    BenchCase, BenchConfig, DEFAULT_GAUSSIAN_COUNTS, DEFAULT_IMAGE_SIZES, DEFAULT_REPEATS,
    DEFAULT_WARMUP, RasterWorkload, bench_camera, raster_workload, realistic_scene, run_case,
    run_case_on,
};
use render_core::constants::TILE_SIZE;
use render_core::context::GpuContext;
use render_core::gpu::{GpuRenderer, GradientOrder, RendererOptions, StageTimes, Subgroups};
use render_core::training::TrainingKernels;
use render_core::{Camera, RasterConfig};
use serde::Serialize;
use splats::GaussianCloud;

use crate::cmd::{fmt_num, print_json};

/// The benchmark's scene, cases and timing loops (kept out of render-core: only this command
/// uses them).
mod harness;
/// The peak (pixel, splat) evaluation rate `--workload` compares each case with.
mod peak;

const BYTES_PER_MIB: f64 = 1024.0 * 1024.0;

#[derive(Args)]
pub struct BenchRenderArgs {
    /// Scene sizes (number of Gaussians), comma-separated; every one is measured at every
    /// image size.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_GAUSSIAN_COUNTS)]
    gaussians: Vec<usize>,
    /// Image sizes "WxH", comma-separated [default: 320x240,640x480].
    #[arg(long, value_delimiter = ',')]
    sizes: Option<Vec<String>>,
    /// One image size instead of --sizes (with --height); with --map, the size its
    /// --intrinsics are for.
    #[arg(long, requires = "height")]
    width: Option<u32>,
    #[arg(long, requires = "width")]
    height: Option<u32>,
    /// Timed runs per measurement (the median is reported).
    #[arg(long, default_value_t = DEFAULT_REPEATS)]
    repeats: usize,
    /// Untimed warm-up runs per measurement.
    #[arg(long, default_value_t = DEFAULT_WARMUP)]
    warmup: usize,
    /// Time the forward pass only (skip forward + backward and the optimisation iteration).
    #[arg(long)]
    forward_only: bool,
    /// Use the rasterizer kernels without subgroup operations even when the adapter has them.
    #[arg(long)]
    no_subgroups: bool,
    /// Sum the backward pass's gradients straight into each Gaussian with atomics, in the
    /// order the threads arrive, instead of per tile/Gaussian pair and then in a fixed order
    /// (render_core::gpu::GradientOrder; compares what the fixed order costs).
    #[arg(long)]
    arrival_order: bool,
    #[arg(long)]
    json: bool,
    /// Also count each case's rasterizer workload on the host: (pixel, splat) evaluations for
    /// 16- and 8-pixel tiles walked in bands of 16, 8 or 4 rows, against the evaluations that
    /// change the image (harness::raster_workload); and time the rasterizer on a scene where
    /// every evaluation changes the image (peak.rs), to report each case's evaluations per
    /// second against that peak rate.
    #[arg(long)]
    workload: bool,
    /// Time this map (standard 3DGS PLY, e.g. a SLAM run's map.ply) instead of the synthetic
    /// scene; needs --pose, --intrinsics, --width and --height (the image size).
    #[arg(long, requires_all = ["pose", "intrinsics", "width", "height"])]
    map: Option<PathBuf>,
    /// With --map: camera-to-world pose, TUM order "tx ty tz qx qy qz qw".
    #[arg(long, allow_hyphen_values = true)]
    pose: Option<String>,
    /// With --map: pinhole intrinsics "fx,fy,cx,cy" in pixels at --width x --height.
    #[arg(long, allow_hyphen_values = true)]
    intrinsics: Option<String>,
}

#[derive(Serialize)]
struct StageReport {
    stage: String,
    ms: f64,
}

#[derive(Serialize)]
struct CaseReport {
    gaussians: usize,
    width: u32,
    height: u32,
    intersections: u32,
    forward_ms: f64,
    forward_backward_ms: Option<f64>,
    iteration_ms: Option<f64>,
    sort_ms: f64,
    /// Most device memory held by buffers at once during the case, MiB.
    peak_device_mib: f64,
    forward_stages: Vec<StageReport>,
    iteration_stages: Vec<StageReport>,
    /// With `--workload`: rasterizer work per tile size and band height.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    workload: Vec<WorkloadReport>,
    /// With `--workload`, when the renderer's band is known (subgroups of one size): its
    /// evaluations per second against the peak rate at this size.
    #[serde(skip_serializing_if = "Option::is_none")]
    rate: Option<RateReport>,
}

#[derive(Serialize)]
struct RateReport {
    /// Tile rows per band of the renderer (its subgroup's rows).
    band_rows: u32,
    evaluations: u64,
    visible_evaluations: u64,
    /// The forward rasterize stage (submitted and waited for on its own), ms.
    rasterize_ms: f64,
    evaluations_per_second: f64,
    peak_evaluations_per_second: f64,
    /// evaluations_per_second / peak_evaluations_per_second.
    fraction_of_peak: f64,
    /// The rasterize time if only the visible evaluations were made, at the peak rate.
    visible_at_peak_ms: f64,
}

#[derive(Serialize)]
struct PeakReport {
    width: u32,
    height: u32,
    layers: u32,
    evaluations: u64,
    rasterize_ms: f64,
    evaluations_per_second: f64,
}

impl From<peak::PeakRate> for PeakReport {
    fn from(p: peak::PeakRate) -> Self {
        Self {
            width: p.width,
            height: p.height,
            layers: peak::PEAK_LAYERS,
            evaluations: p.evaluations,
            rasterize_ms: p.rasterize_ms,
            evaluations_per_second: p.evaluations_per_second(),
        }
    }
}

#[derive(Serialize)]
struct WorkloadReport {
    tile_size: u32,
    band_rows: u32,
    band_columns: u32,
    pairs: u64,
    band_steps: u64,
    evaluations: u64,
    visible_evaluations: u64,
}

impl From<RasterWorkload> for WorkloadReport {
    fn from(w: RasterWorkload) -> Self {
        Self {
            tile_size: w.tile_size,
            band_rows: w.band_rows,
            band_columns: w.band_columns,
            pairs: w.pairs,
            band_steps: w.band_steps,
            evaluations: w.evaluations,
            visible_evaluations: w.visible_evaluations,
        }
    }
}

/// (tile size, band rows, band columns) counted by `--workload`: this renderer's 16-pixel
/// tiles (a band is the rows of one subgroup, 8 on lavapipe; the forward rasterizer tests
/// halves of it, as does the backward) and what other bands or tiles would do.
const WORKLOAD_LAYOUTS: [(u32, u32, u32); 7] = [
    (16, 16, 16),
    (16, 8, 16),
    (16, 8, 8),
    (16, 4, 16),
    (16, 4, 8),
    (8, 8, 8),
    (8, 4, 8),
];

/// Columns of one skip test of the forward subgroup rasterizer (rasterize_subgroup.wgsl
/// composites each band as two halves).
const FORWARD_BAND_COLUMNS: u32 = TILE_SIZE / 2;

/// The workload of each of [`WORKLOAD_LAYOUTS`], and of the forward rasterizer's own layout
/// (16-pixel tiles in bands of `band_rows`, halves of [`FORWARD_BAND_COLUMNS`]) when that is
/// not among them.
fn workload_reports(
    cloud: &GaussianCloud,
    camera: &Camera,
    band_rows: Option<u32>,
) -> anyhow::Result<Vec<WorkloadReport>> {
    let mut layouts = WORKLOAD_LAYOUTS.to_vec();
    if let Some(band) = band_rows
        && !layouts.contains(&(TILE_SIZE, band, FORWARD_BAND_COLUMNS))
    {
        layouts.push((TILE_SIZE, band, FORWARD_BAND_COLUMNS));
    }
    layouts
        .iter()
        .map(|&(tile, band, columns)| {
            raster_workload(cloud, camera, &RasterConfig::default(), tile, band, columns)
                .map(WorkloadReport::from)
                .map_err(anyhow::Error::from)
        })
        .collect()
}

#[derive(Serialize)]
struct BenchRenderReport {
    adapter: String,
    repeats: usize,
    cases: Vec<CaseReport>,
    /// With `--workload`: the peak evaluation rate at each image size measured.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    peak: Vec<PeakReport>,
}

impl From<BenchCase> for CaseReport {
    fn from(case: BenchCase) -> Self {
        Self {
            gaussians: case.gaussians,
            width: case.width,
            height: case.height,
            intersections: case.intersections,
            forward_ms: case.forward_ms,
            forward_backward_ms: case.forward_backward_ms,
            iteration_ms: case.iteration_ms,
            sort_ms: case.sort_ms,
            peak_device_mib: case.peak_device_bytes as f64 / BYTES_PER_MIB,
            forward_stages: stage_reports(case.stages),
            iteration_stages: stage_reports(case.iteration_stages),
            workload: Vec::new(),
            rate: None,
        }
    }
}

/// Rows of one band of the renderer's forward rasterizer: one subgroup's rows (one row per
/// lane, at most a tile's), known when the adapter has a single subgroup size; `None` without
/// subgroups (the workgroup rasterizer skips no splat) or when the size may vary.
fn renderer_band_rows(context: &GpuContext, renderer: &GpuRenderer) -> Option<u32> {
    let info = &context.adapter_info;
    (renderer.uses_subgroups && info.subgroup_min_size == info.subgroup_max_size)
        .then(|| info.subgroup_min_size.min(TILE_SIZE))
}

/// A case's evaluations per second (its workload in the renderer's layout over its rasterize
/// stage) against the peak rate at its size.
fn rate_report(case: &CaseReport, band_rows: u32, peak: &peak::PeakRate) -> Option<RateReport> {
    let workload = case.workload.iter().find(|w| {
        (w.tile_size, w.band_rows, w.band_columns) == (TILE_SIZE, band_rows, FORWARD_BAND_COLUMNS)
    })?;
    let rasterize_ms = case
        .forward_stages
        .iter()
        .find(|s| s.stage == peak::RASTERIZE_STAGE)?
        .ms;
    let evaluations_per_second = workload.evaluations as f64 / (rasterize_ms * 1e-3);
    let peak_evaluations_per_second = peak.evaluations_per_second();
    Some(RateReport {
        band_rows,
        evaluations: workload.evaluations,
        visible_evaluations: workload.visible_evaluations,
        rasterize_ms,
        evaluations_per_second,
        peak_evaluations_per_second,
        fraction_of_peak: evaluations_per_second / peak_evaluations_per_second,
        visible_at_peak_ms: workload.visible_evaluations as f64 / peak_evaluations_per_second * 1e3,
    })
}

fn stage_reports(stages: StageTimes) -> Vec<StageReport> {
    stages
        .0
        .into_iter()
        .map(|(stage, ms)| StageReport {
            stage: stage.to_owned(),
            ms,
        })
        .collect()
}

/// The image sizes to measure: --width x --height when given, else --sizes.
fn image_sizes(args: &BenchRenderArgs) -> anyhow::Result<Vec<(u32, u32)>> {
    let sizes = match (args.width, args.height) {
        (Some(width), Some(height)) => {
            anyhow::ensure!(
                width > 0 && height > 0,
                "--width and --height must be positive"
            );
            vec![(width, height)]
        }
        _ => match &args.sizes {
            Some(sizes) => sizes
                .iter()
                .map(|size| crate::cmd::render::parse_size(size, "--sizes"))
                .collect::<anyhow::Result<_>>()?,
            None => DEFAULT_IMAGE_SIZES.to_vec(),
        },
    };
    anyhow::ensure!(!sizes.is_empty(), "--sizes needs at least one size");
    Ok(sizes)
}

pub fn run_bench(args: &BenchRenderArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        !args.gaussians.is_empty(),
        "--gaussians needs at least one size"
    );
    let sizes = image_sizes(args)?;
    let context = GpuContext::new().context("creating the wgpu device")?;
    let renderer = GpuRenderer::with_options(
        &context,
        RendererOptions {
            subgroups: if args.no_subgroups {
                Subgroups::Never
            } else {
                Subgroups::Auto
            },
            gradient_order: if args.arrival_order {
                GradientOrder::Arrival
            } else {
                GradientOrder::Fixed
            },
            ..RendererOptions::default()
        },
    );
    let kernels = TrainingKernels::new(&context);
    let config = BenchConfig {
        gaussian_counts: args.gaussians.clone(),
        warmup: args.warmup,
        repeats: args.repeats.max(1),
        iteration: !args.forward_only,
        ..BenchConfig::default()
    };
    let band_rows = renderer_band_rows(&context, &renderer);
    let mut cases = Vec::with_capacity(config.gaussian_counts.len() * sizes.len());
    if let (Some(path), Some(pose), Some(intrinsics)) = (&args.map, &args.pose, &args.intrinsics) {
        let (width, height) = sizes[0];
        let camera = crate::cmd::render::camera_from_args(pose, intrinsics, width, height)?;
        let map = splats::ply::load_ply(path)
            .with_context(|| format!("reading map {}", path.display()))?;
        if !args.json {
            eprintln!(
                "measuring {} ({} Gaussians) at {width}x{height} ...",
                path.display(),
                map.len(),
            );
        }
        let case = run_case_on(&context, &renderer, &kernels, &config, &map, &camera)
            .with_context(|| format!("benchmarking {}", path.display()))?;
        let mut report = CaseReport::from(case);
        if args.workload {
            report.workload = workload_reports(&map, &camera, band_rows)?;
        }
        cases.push(report);
    }
    let synthetic_sizes = if args.map.is_none() {
        sizes.as_slice()
    } else {
        &[]
    };
    for &(width, height) in synthetic_sizes {
        let config = BenchConfig {
            width,
            height,
            ..config.clone()
        };
        for &count in &config.gaussian_counts {
            if !args.json {
                eprintln!("measuring {count} Gaussians at {width}x{height} ...");
            }
            let case = run_case(&context, &renderer, &kernels, &config, count)
                .with_context(|| format!("benchmarking {count} Gaussians at {width}x{height}"))?;
            let mut report = CaseReport::from(case);
            if args.workload {
                let camera = bench_camera(width, height);
                let scene = realistic_scene(&camera, count, config.seed);
                report.workload = workload_reports(&scene, &camera, band_rows)?;
            }
            cases.push(report);
        }
    }
    let mut peaks: Vec<peak::PeakRate> = Vec::new();
    if args.workload {
        for case in &mut cases {
            let size = (case.width, case.height);
            let known = peaks.iter().find(|p| (p.width, p.height) == size).copied();
            let peak = match known {
                Some(peak) => peak,
                None => {
                    if !args.json {
                        eprintln!(
                            "measuring the peak evaluation rate at {}x{} ...",
                            size.0, size.1
                        );
                    }
                    let peak = peak::peak_rate(&context, &renderer, &config, size.0, size.1)
                        .with_context(|| format!("peak rate at {}x{}", size.0, size.1))?;
                    peaks.push(peak);
                    peak
                }
            };
            case.rate = band_rows.and_then(|band| rate_report(case, band, &peak));
        }
    }
    let report = BenchRenderReport {
        adapter: if renderer.uses_subgroups {
            context.describe()
        } else {
            format!("{}, rasterizers without subgroups", context.describe())
        },
        repeats: config.repeats,
        cases,
        peak: peaks.into_iter().map(PeakReport::from).collect(),
    };
    if args.json {
        return print_json(&report);
    }
    let optional = |v: Option<f64>| v.map_or_else(|| "-".to_owned(), |ms| fmt_num(ms, 1));
    println!(
        "render benchmark (median of {} runs, ms): {}",
        report.repeats, report.adapter
    );
    println!(
        "  {:>10} {:>9} {:>11} {:>10} {:>12} {:>11} {:>9} {:>11}",
        "gaussians", "size", "pairs", "forward", "fwd+bwd", "iteration", "sort", "peak MiB"
    );
    for case in &report.cases {
        println!(
            "  {:>10} {:>9} {:>11} {:>10} {:>12} {:>11} {:>9} {:>11}",
            case.gaussians,
            format!("{}x{}", case.width, case.height),
            case.intersections,
            fmt_num(case.forward_ms, 1),
            optional(case.forward_backward_ms),
            optional(case.iteration_ms),
            fmt_num(case.sort_ms, 1),
            fmt_num(case.peak_device_mib, 1)
        );
    }
    println!("forward stages (each submitted and waited for separately, ms):");
    for case in &report.cases {
        let stages: Vec<String> = case
            .forward_stages
            .iter()
            .map(|s| format!("{} {}", s.stage, fmt_num(s.ms, 1)))
            .collect();
        println!("  {:>10}: {}", case.gaussians, stages.join(", "));
    }
    if report.cases.iter().any(|c| !c.workload.is_empty()) {
        println!(
            "rasterizer workload (host count; band = columns x rows of one skip test; evaluations = pixels x splats walked, visible = those that change the image):"
        );
        println!(
            "  {:>10} {:>6} {:>9} {:>11} {:>13} {:>12} {:>8}",
            "gaussians", "tile", "band", "pairs", "evaluations", "visible", "visible %"
        );
        for case in &report.cases {
            for w in &case.workload {
                println!(
                    "  {:>10} {:>6} {:>9} {:>11} {:>13} {:>12} {:>8}",
                    case.gaussians,
                    w.tile_size,
                    format!("{}x{}", w.band_columns, w.band_rows),
                    w.pairs,
                    w.evaluations,
                    w.visible_evaluations,
                    fmt_num(
                        100.0 * w.visible_evaluations as f64 / w.evaluations.max(1) as f64,
                        1
                    )
                );
            }
        }
    }
    print_rates(&report);
    if report.cases.iter().any(|c| !c.iteration_stages.is_empty()) {
        println!("iteration stages (each submitted and waited for separately, ms):");
        for case in &report.cases {
            let stages: Vec<String> = case
                .iteration_stages
                .iter()
                .map(|s| format!("{} {}", s.stage, fmt_num(s.ms, 1)))
                .collect();
            println!("  {:>10}: {}", case.gaussians, stages.join(", "));
        }
    }
    Ok(())
}

/// The peak rates and each case's rate against them (`--workload`).
fn print_rates(report: &BenchRenderReport) {
    if report.peak.is_empty() {
        return;
    }
    println!(
        "peak evaluation rate (forward rasterize stage on {} full-view layers, every evaluation visible):",
        peak::PEAK_LAYERS
    );
    for p in &report.peak {
        println!(
            "  {:>9}: {} evaluations in {} ms = {} M/s",
            format!("{}x{}", p.width, p.height),
            p.evaluations,
            fmt_num(p.rasterize_ms, 1),
            fmt_num(p.evaluations_per_second / 1e6, 0)
        );
    }
    if !report.cases.iter().any(|c| c.rate.is_some()) {
        println!("  (no per-case rate: the renderer's band of rows is not known on this adapter)");
        return;
    }
    println!(
        "rasterizer rate (renderer's layout; visible at peak = the rasterize time if only visible evaluations were made):"
    );
    println!(
        "  {:>10} {:>9} {:>5} {:>13} {:>12} {:>10} {:>8} {:>9} {:>16}",
        "gaussians",
        "size",
        "band",
        "evaluations",
        "visible",
        "raster ms",
        "M/s",
        "% peak",
        "visible@peak ms"
    );
    for case in &report.cases {
        let Some(r) = &case.rate else { continue };
        println!(
            "  {:>10} {:>9} {:>5} {:>13} {:>12} {:>10} {:>8} {:>9} {:>16}",
            case.gaussians,
            format!("{}x{}", case.width, case.height),
            r.band_rows,
            r.evaluations,
            r.visible_evaluations,
            fmt_num(r.rasterize_ms, 1),
            fmt_num(r.evaluations_per_second / 1e6, 0),
            fmt_num(100.0 * r.fraction_of_peak, 1),
            fmt_num(r.visible_at_peak_ms, 1)
        );
    }
}
