//! `mac-ego3d bench map-registration`: global registration of two maps with no initial guess
//! (`registration::map_registration`) against ground truth and, side by side in the same run on
//! the same pairs, the peers Open3D and splatreg (`--peers open3d,splatreg --python PY`, run by
//! scripts/map_registration_peers.py, whose documentation gives their fixed settings).
//!
//! **Maps.** Each map is built from a dataset with its ground-truth poses: every `--every`-th
//! frame's depth is back-projected (every `--pixel-stride`-th pixel) into the world frame,
//! coloured by its pixels and thinned to one point per `--map-voxel` cell (a dense map's
//! spacing); the frames' depth images go with it as the map's views (the keyframes of an agent,
//! for the free-space test). Above `--points`, a seeded random subset of that many points is
//! kept. The peers get the same maps as Gaussian maps (3DGS PLY; one Gaussian per point,
//! flattened along its neighbourhood's normal, as an agent seeds them).
//!
//! **Pairs.** Without `--overlaps`, one pair per seed: map A is `--frames-a` of `--dataset` and
//! map B `--frames-b` (the default data is the embedded synthetic scene with two agents, A =
//! agent 0, B = agent 1, `--frames N` frames each; each seed changes the scene's seed). With
//! `--overlaps 80,50,30,15,0`, pairs are cropped from the two maps to those true overlaps
//! (percent of the smaller map; 0 = disjoint), `--pairs-per-bin` each (see `crops.rs`); map B
//! of a dataset then starts half a frame step later (`--every 10`: frames 5, 15, ...), so the
//! two maps of one sequence come from different frames. In every pair map B is expressed in a
//! random rigid frame (any rotation, up to 5 m away, seeded), so the true `target_from_source`
//! is known, and with `--white-balance W` its colours get random per-channel gains within
//! `1 +- W` (another camera's white balance).
//!
//! **Scores.** Errors are measured at the centre of map B (rotation angle, and the distance
//! between where the estimate and the truth put that centre). A run on overlapping maps succeeds
//! when it is accepted and within 5 cm and 2 degrees; on disjoint maps when it is refused.
//! `correct` counts estimates within the thresholds whatever the verdict. Times are each
//! method's registration alone, on `RAYON_NUM_THREADS` threads (the peers get as many).

mod crops;
mod maps;
mod peers;
mod report;

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use config::{Config, MapRegistrationConfig};
use datasets::FrameRange;
use nalgebra::{Isometry3, Point3, Vector3};
use registration::alignment::AlignmentConfig;
use registration::map_registration::{DepthView, FreeSpaceCheck, MapPoints, register_maps_checked};
use serde::Serialize;

use super::figures::FigureArgs;
use crate::cmd::{fmt_num, print_json};
use crops::{CropScene, TRUE_OVERLAP_DISTANCE_M};
use maps::{Map, MapRecipe, SplitMix, build_map, overlap_of_smaller, random_frame};
use peers::{DEFAULT_DRIVER, PairFiles, PairFolder, Peer, PeerDriver, SPLATREG_SPACING_M};
use report::{MethodRun, PairRun, pair_line, print_summary, summarise};

#[derive(Args)]
pub struct MapRegistrationArgs {
    /// Dataset folder (7-Scenes, TUM, Replica) with ground truth. Default: the embedded synthetic
    /// scene, two agents.
    #[arg(long)]
    dataset: Option<String>,
    /// Frames of map A (with --dataset).
    #[arg(long, default_value = "0..100")]
    frames_a: FrameRange,
    /// Frames of map B (with --dataset).
    #[arg(long, default_value = "500..600")]
    frames_b: FrameRange,
    /// Synthetic scene: frames per agent and image size.
    #[arg(long, alias = "frames", default_value_t = 300)]
    synthetic_frames: usize,
    #[arg(long, default_value_t = 320)]
    synthetic_width: u32,
    #[arg(long, default_value_t = 240)]
    synthetic_height: u32,
    /// Back-project every n-th frame.
    #[arg(long, default_value_t = 10)]
    every: usize,
    /// Back-project every n-th pixel in x and y.
    #[arg(long, default_value_t = 2)]
    pixel_stride: usize,
    /// Map spacing: one point per cell of this size (metres).
    #[arg(long, default_value_t = 0.02)]
    map_voxel: f64,
    /// Points per map at most (a seeded random subset above).
    #[arg(long, default_value_t = 50_000)]
    points: usize,
    /// Pairs per seed (without --overlaps): seeds 0..N (plus --first-seed). With --overlaps, the
    /// first seed of the crops.
    #[arg(long, default_value_t = 10)]
    seeds: u64,
    #[arg(long, default_value_t = 0)]
    first_seed: u64,
    /// Cropped pairs of these true overlaps (percent of the smaller map; 0: disjoint).
    #[arg(long, value_delimiter = ',')]
    overlaps: Vec<f64>,
    /// Cropped pairs per overlap.
    #[arg(long, default_value_t = 20)]
    pairs_per_bin: u64,
    /// Random per-channel gains of map B's colours, within 1 +- this.
    #[arg(long, default_value_t = 0.0)]
    white_balance: f64,
    /// Configuration file (its [consensus.map_registration] table). Default: the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Register the maps without their colours (geometry alone).
    #[arg(long)]
    no_colour: bool,
    /// Register without the free-space test of the maps' depth views (as an agent without the
    /// other's keyframes would).
    #[arg(long)]
    no_free_space: bool,
    /// Peers registering the same pairs (needs --python).
    #[arg(long, value_delimiter = ',', value_enum)]
    peers: Vec<Peer>,
    /// The peers' python (`scripts/peers_venv.sh` prints it).
    #[arg(long)]
    python: Option<PathBuf>,
    /// The peers' driver.
    #[arg(long, default_value = DEFAULT_DRIVER)]
    peers_driver: PathBuf,
    /// splatreg.register's init mode.
    #[arg(long, default_value = "robust")]
    splatreg_init: String,
    /// Keep the pairs' Gaussian maps (PLY) in this folder.
    #[arg(long)]
    keep_pairs: Option<PathBuf>,
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    figures: FigureArgs,
}

/// One pair to register: map B (the source, in a random frame), map A (the target, in the world
/// frame) and the truth.
struct BenchPair {
    bin: String,
    name: String,
    seed: u64,
    disjoint: bool,
    true_overlap: f64,
    source: Map,
    target: Map,
    target_from_source: Isometry3<f64>,
}

impl BenchPair {
    /// Map B moved into the random frame of `seed`, with another white balance.
    #[allow(clippy::too_many_arguments, reason = "a bench pair's fields")]
    fn new(
        bin: String,
        name: String,
        seed: u64,
        true_overlap: f64,
        disjoint: bool,
        a: Map,
        b: Map,
        args: &MapRegistrationArgs,
    ) -> Self {
        let frame_from_world = random_frame(seed);
        let mut rng = SplitMix(seed ^ 0x0077_6869_7465);
        let gains = [0; 3].map(|_| (1.0 + args.white_balance * (2.0 * rng.unit() - 1.0)) as f32);
        Self {
            bin,
            name,
            seed,
            disjoint,
            true_overlap,
            source: b
                .capped(args.points, seed.wrapping_add(1))
                .white_balanced(gains)
                .moved(&frame_from_world),
            target: a.capped(args.points, seed),
            target_from_source: frame_from_world.inverse(),
        }
    }
}

fn synthetic_spec(args: &MapRegistrationArgs, agent: usize, seed: u64) -> String {
    format!(
        "synthetic:agents=2,agent={agent},frames={},seed={seed},width={},height={}",
        args.synthetic_frames, args.synthetic_width, args.synthetic_height
    )
}

/// The two maps of `seed`: A and B as the module documentation says; `offset_b` starts B's
/// frames half a step later (cropped pairs of one sequence).
fn scene_maps(
    args: &MapRegistrationArgs,
    seed: u64,
    offset_b: bool,
) -> anyhow::Result<(Map, Map, String)> {
    let recipe = |spec: &'_ str, frames, offset| {
        build_map(&MapRecipe {
            spec,
            frames,
            every: args.every,
            offset,
            pixel_stride: args.pixel_stride,
            map_voxel_m: args.map_voxel,
        })
    };
    let half_step = if offset_b { args.every / 2 } else { 0 };
    match &args.dataset {
        Some(path) => Ok((
            recipe(path, args.frames_a, 0)?,
            recipe(path, args.frames_b, half_step)?,
            format!(
                "A = {path} [{}], B = {path} [{}]",
                args.frames_a, args.frames_b
            ),
        )),
        None => {
            let (a, b) = (synthetic_spec(args, 0, seed), synthetic_spec(args, 1, seed));
            Ok((
                recipe(&a, FrameRange::ALL, 0)?,
                recipe(&b, FrameRange::ALL, half_step)?,
                format!("A = {a}, B = {b}"),
            ))
        }
    }
}

/// Every pair of the run (see the module documentation), with a description of the data.
fn make_pairs(args: &MapRegistrationArgs) -> anyhow::Result<(Vec<BenchPair>, String)> {
    let mut pairs = Vec::new();
    if args.overlaps.is_empty() {
        let mut data = String::new();
        let mut fixed: Option<(Map, Map)> = None;
        for seed in args.first_seed..args.first_seed + args.seeds {
            let (a, b) = match (&fixed, &args.dataset) {
                (Some((a, b)), _) => (a.clone(), b.clone()),
                (None, dataset) => {
                    let (a, b, describe) = scene_maps(args, seed, false)?;
                    data = describe;
                    if dataset.is_some() {
                        // A dataset's maps do not change with the seed.
                        fixed = Some((a.clone(), b.clone()));
                    }
                    (a, b)
                }
            };
            let overlap = overlap_of_smaller(&a.points, &b.points, TRUE_OVERLAP_DISTANCE_M);
            pairs.push(BenchPair::new(
                "pairs".into(),
                seed.to_string(),
                seed,
                overlap,
                false,
                a,
                b,
                args,
            ));
        }
        return Ok((pairs, data));
    }
    let (a, b, data) = scene_maps(args, args.first_seed, true)?;
    let scene = CropScene::new(a, b);
    for &percent in &args.overlaps {
        anyhow::ensure!(
            (0.0..100.0).contains(&percent),
            "--overlaps: {percent} is not a percentage below 100"
        );
        let bin = if percent <= 0.0 {
            "disjoint".to_string()
        } else {
            format!("{percent}%")
        };
        for k in 0..args.pairs_per_bin {
            // Seeded by the overlap, so a bin's pairs do not depend on the other bins asked for.
            let seed = args.first_seed + k + 1000 * percent.round() as u64;
            let Some(pair) = scene.pair(percent / 100.0, seed) else {
                eprintln!(
                    "  {bin} pair {k}: no crop of these maps has that overlap (the whole maps overlap {:.0} %)",
                    scene.full_overlap * 100.0
                );
                continue;
            };
            pairs.push(BenchPair::new(
                bin.clone(),
                k.to_string(),
                seed,
                pair.true_overlap,
                percent <= 0.0,
                pair.a,
                pair.b,
                args,
            ));
        }
    }
    Ok((pairs, data))
}

#[derive(Serialize)]
struct Report {
    data: String,
    /// Whether the maps' colours were used by ours, and the free-space test.
    colour: bool,
    free_space: bool,
    threads: usize,
    white_balance: f64,
    peers: Vec<Peer>,
    splatreg_init: Option<String>,
    summary: Vec<report::BinSummary>,
    pairs: Vec<PairRun>,
}

fn centre(points: &[Point3<f32>]) -> Point3<f64> {
    Point3::from(
        points
            .iter()
            .fold(Vector3::zeros(), |sum, p| sum + p.coords.cast::<f64>())
            / points.len().max(1) as f64,
    )
}

/// Ours on one pair.
fn run_ours(
    pair: &BenchPair,
    args: &MapRegistrationArgs,
    config: &MapRegistrationConfig,
    alignment: &AlignmentConfig,
) -> MethodRun {
    let colours = |map: &Map| (!args.no_colour).then_some(map.colours.clone());
    let (source_colours, target_colours) = (colours(&pair.source), colours(&pair.target));
    fn views(map: &Map) -> Vec<DepthView<'_>> {
        map.views
            .iter()
            .map(|v| DepthView {
                depth: &v.depth,
                intrinsics: &v.intrinsics,
                map_from_camera: v.map_from_camera,
            })
            .collect()
    }
    let free_space = (!args.no_free_space).then(|| FreeSpaceCheck {
        source_views: views(&pair.source),
        target_views: views(&pair.target),
        config: alignment,
        min_agreement: config.min_depth_agreement,
        max_points: config.depth_check_points,
    });
    let result = register_maps_checked(
        MapPoints::coloured(&pair.source.points, source_colours.as_deref()),
        MapPoints::coloured(&pair.target.points, target_colours.as_deref()),
        config,
        free_space.as_ref(),
    );
    let details = serde_json::json!({ "scores": result.scores });
    MethodRun::judged(
        "ours",
        Some(result.target_from_source),
        result.is_accepted(),
        result.elapsed_ms,
        result.verdict.as_ref().err().map(ToString::to_string),
        details,
        &pair.target_from_source,
        &centre(&pair.source.points),
        pair.disjoint,
    )
}

/// The peers on one pair (its maps written as Gaussian maps into `folder`).
fn run_peers(
    pair: &BenchPair,
    driver: &mut PeerDriver,
    folder: &PairFolder,
    args: &MapRegistrationArgs,
) -> anyhow::Result<Vec<MethodRun>> {
    let stem = format!("{}-{}", pair.bin.replace('%', "pc"), pair.name);
    let file = |name: &str| folder.path.join(format!("{stem}-{name}.ply"));
    let files = PairFiles {
        source: file("source"),
        target: file("target"),
        splat_source: file("source-splatreg"),
        splat_target: file("target-splatreg"),
    };
    maps::write_gaussian_map(&files.source, &pair.source, args.map_voxel)?;
    maps::write_gaussian_map(&files.target, &pair.target, args.map_voxel)?;
    let coarse = |map: &Map| map.resampled(SPLATREG_SPACING_M);
    maps::write_gaussian_map(
        &files.splat_source,
        &coarse(&pair.source),
        SPLATREG_SPACING_M,
    )?;
    maps::write_gaussian_map(
        &files.splat_target,
        &coarse(&pair.target),
        SPLATREG_SPACING_M,
    )?;
    let answers = driver.register(&stem, &files)?;
    let centre = centre(&pair.source.points);
    Ok(answers
        .into_iter()
        .map(|(peer, answer)| {
            let estimate = if answer.error.is_none() {
                answer.transform()
            } else {
                Err(anyhow::anyhow!("no estimate"))
            };
            let reason = answer
                .error
                .clone()
                .or_else(|| estimate.as_ref().err().map(|e| e.to_string()))
                .or(answer.reason.clone());
            MethodRun::judged(
                peer.name(),
                estimate.ok(),
                answer.accepted,
                answer.time_ms,
                reason,
                answer.details,
                &pair.target_from_source,
                &centre,
                pair.disjoint,
            )
        })
        .collect())
}

pub fn run(args: &MapRegistrationArgs) -> anyhow::Result<()> {
    let (config, alignment) = match &args.config {
        Some(path) => {
            let consensus = Config::load(path)?.consensus;
            (consensus.map_registration, consensus.alignment)
        }
        None => (MapRegistrationConfig::default(), AlignmentConfig::default()),
    };
    let threads = registration::worker_threads();
    let mut driver = match (&args.peers[..], &args.python) {
        ([], _) => None,
        (peers, Some(python)) => Some(PeerDriver::start(
            python,
            &args.peers_driver,
            peers,
            threads,
            &args.splatreg_init,
        )?),
        (_, None) => anyhow::bail!(
            "--peers needs --python: the peers' python, which `scripts/peers_venv.sh` prints"
        ),
    };
    let folder = match driver {
        Some(_) => Some(PairFolder::new(args.keep_pairs.as_deref())?),
        None => None,
    };
    let (pairs, data) = make_pairs(args)?;
    anyhow::ensure!(!pairs.is_empty(), "no pairs to register");
    if !args.json {
        println!(
            "map registration ({}, {} threads): {data}",
            if args.no_colour {
                "ours without colour"
            } else {
                "ours with colour"
            },
            threads
        );
        println!(
            "  {:<10} {:>6} {:>5} {:>13} | method verdict rotation translation time",
            "bin", "pair", "ovl %", "points B/A"
        );
    }
    let mut runs = Vec::new();
    for pair in &pairs {
        let mut methods = vec![run_ours(pair, args, &config, &alignment)];
        if let (Some(driver), Some(folder)) = (driver.as_mut(), &folder) {
            methods.extend(
                run_peers(pair, driver, folder, args)
                    .with_context(|| format!("the peers on pair {} {}", pair.bin, pair.name))?,
            );
        }
        let run = PairRun {
            bin: pair.bin.clone(),
            pair: pair.name.clone(),
            seed: pair.seed,
            disjoint: pair.disjoint,
            true_overlap: pair.true_overlap,
            source_points: pair.source.points.len(),
            target_points: pair.target.points.len(),
            methods,
        };
        // With --json the table goes to stderr as progress: a full run takes an hour.
        if args.json {
            eprintln!("{}", pair_line(&run));
        } else {
            println!("{}", pair_line(&run));
        }
        runs.push(run);
    }
    let summary = summarise(&runs);
    let report = Report {
        data,
        colour: !args.no_colour,
        free_space: !args.no_free_space,
        threads,
        white_balance: args.white_balance,
        splatreg_init: args
            .peers
            .contains(&Peer::Splatreg)
            .then(|| args.splatreg_init.clone()),
        peers: args.peers.clone(),
        summary,
        pairs: runs,
    };
    let label = args
        .figures
        .label(|| format!("map registration, {}", report.data));
    args.figures
        .record(&report::headline_figures(&report.summary, &label))?;
    if args.json {
        return print_json(&report);
    }
    println!(
        "  success: accepted within {} cm and {} degrees (disjoint: refused); errors are medians of the successes",
        fmt_num(report::SUCCESS_TRANSLATION_M * 100.0, 0),
        fmt_num(report::SUCCESS_ROTATION_DEG, 0)
    );
    print_summary(&report.summary);
    Ok(())
}
