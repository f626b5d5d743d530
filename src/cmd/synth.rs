//! `mac-ego3d synth`: writes the embedded synthetic multi-agent dataset to disk in the 7-Scenes
//! layout (`OUT/agent_K/frame-XXXXXX.{color.png,depth.png,pose.txt}` plus `OUT/scene.json`), so
//! the scene can be inspected or fed to tools that read files. SLAM can also stream it directly
//! with the dataset spec `synthetic:agents=N,...` without touching disk.

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use datasets::synthetic::{self, SyntheticSpec};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Args, Debug, Clone)]
pub struct SynthArgs {
    /// Number of agents (one folder each).
    #[arg(long, default_value_t = synthetic::DEFAULT_AGENTS)]
    pub agents: usize,
    /// Frames per agent (30 per second).
    #[arg(long, default_value_t = synthetic::DEFAULT_FRAMES)]
    pub frames: usize,
    /// Output folder; agent K goes to OUT/agent_K.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of textures, object placement and trajectory jitter (same seed, same bytes).
    #[arg(long, default_value_t = synthetic::DEFAULT_SEED)]
    pub seed: u64,
    /// Image width in pixels (the focal length scales with it).
    #[arg(long, default_value_t = synthetic::DEFAULT_WIDTH)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = synthetic::DEFAULT_HEIGHT)]
    pub height: u32,
    /// Remove the files of an earlier `synth` run in OUT first (only agent_K frame files,
    /// intrinsics, ground truth and scene.json; nothing else is touched).
    #[arg(long)]
    pub overwrite: bool,
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let spec = SyntheticSpec {
        agents: args.agents,
        agent: 0,
        frames: args.frames,
        seed: args.seed,
        width: args.width,
        height: args.height,
    };
    spec.validate()
        .map_err(|reason| anyhow::anyhow!("invalid synthetic dataset options: {reason}"))?;
    if args.overwrite {
        let removed = synthetic::remove_written(&args.out).with_context(|| {
            format!(
                "removing an earlier synthetic dataset from {}",
                args.out.display()
            )
        })?;
        if removed > 0 {
            tracing::info!(
                "removed {removed} files of an earlier run from {}",
                args.out.display()
            );
        }
    }

    let total = (spec.agents * spec.frames) as u64;
    // Draw only for a person watching; logs and CI get the summary alone.
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::new(total)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} rendering [{bar:40}] {pos}/{len} frames ({per_sec}, eta {eta})",
        )
        .context("progress bar template")?
        .progress_chars("=> "),
    );
    let started = Instant::now();
    let folders =
        synthetic::write_seven_scenes(&spec, &args.out, |done, _| bar.set_position(done as u64))
            .with_context(|| format!("writing the synthetic dataset to {}", args.out.display()))?;
    bar.finish_and_clear();
    let seconds = started.elapsed().as_secs_f64();

    let k = spec.intrinsics();
    println!(
        "synthetic dataset ({spec}) written to {}",
        args.out.display()
    );
    for folder in &folders {
        println!("  {}  {} frames", folder.display(), spec.frames);
    }
    println!(
        "  {}  (scene description)",
        args.out.join(synthetic::SCENE_FILE).display()
    );
    println!(
        "frames: {} agents x {} = {} in {:.1} s ({:.1} frames/s, rendering and PNG encoding)",
        spec.agents,
        spec.frames,
        total,
        seconds,
        total as f64 / seconds.max(f64::MIN_POSITIVE)
    );
    println!(
        "intrinsics: {}x{} fx={} fy={} cx={} cy={} (also in each folder's camera-intrinsics.txt)",
        k.width, k.height, k.fx, k.fy, k.cx, k.cy
    );
    println!(
        "depth: 16-bit PNG in millimetres (0 = invalid); poses: camera-to-world in the room frame"
    );
    Ok(())
}
