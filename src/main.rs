//! `mac-ego3d`: the user-facing command line of mac-ego3d (multi-agent Gaussian-splat RGB-D SLAM).
//!
//! Subcommands: `synth` writes the embedded synthetic multi-agent dataset, `dataset info`
//! describes a dataset, `eval` computes metrics (ATE, PSNR/SSIM, LPIPS, depth L1), `bench`
//! measures reader throughput and metric timings, `plot tcomm` draws the T_comm benchmark, `config` resolves a run's configuration, `swarm` runs
//! and supervises a whole swarm, `chaos` soaks one under crashes.
//! `eval swarm` also writes the run's report.html (see `report`).

mod cmd;
mod report;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "mac-ego3d",
    version,
    about = "Multi-agent Gaussian-splat RGB-D SLAM: data, evaluation, benchmarks"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Write the embedded synthetic multi-agent dataset in the 7-Scenes layout.
    Synth(cmd::synth::SynthArgs),
    /// Render a saved 3DGS map (PLY) from a camera pose to PNG (colour, 16-bit depth in mm).
    Render(cmd::render::RenderArgs),
    /// Inspect datasets.
    #[command(subcommand)]
    Dataset(cmd::dataset::DatasetCommand),
    /// Evaluation metrics.
    #[command(subcommand)]
    Eval(cmd::eval::EvalCommand),
    /// Benchmarks (print a table, or JSON with --json).
    #[command(subcommand)]
    Bench(cmd::bench::BenchCommand),
    /// Write a run's configuration with overrides applied and every key listed.
    Config(cmd::config::ConfigArgs),
    /// Plots of benchmark tables (PNG).
    #[command(subcommand)]
    Plot(cmd::plot::PlotCommand),
    /// Run a swarm: one consensus and N agents (each its own process), supervised, then the
    /// run's figures (metrics.json, report.html).
    Swarm(cmd::swarm::SwarmArgs),
    /// Soak the swarm under crashes: SIGKILL its processes at seeded random times, start them
    /// again, check nothing was lost and compare with a run without kills (table + chaos.json).
    Chaos(cmd::chaos::ChaosArgs),
}

fn main() -> std::process::ExitCode {
    config::process::init_logging();
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Synth(args) => cmd::synth::run(args),
        Command::Render(args) => cmd::render::run(args),
        Command::Dataset(c) => cmd::dataset::run(c),
        Command::Eval(c) => cmd::eval::run(c),
        Command::Bench(c) => cmd::bench::run(c),
        Command::Plot(c) => cmd::plot::run(c),
        Command::Config(args) => cmd::config::run(args),
        Command::Swarm(args) => cmd::swarm::run(args),
        Command::Chaos(args) => cmd::chaos::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            if e.downcast_ref::<cmd::UsageError>().is_some() {
                std::process::ExitCode::from(2)
            } else {
                std::process::ExitCode::FAILURE
            }
        }
    }
}
