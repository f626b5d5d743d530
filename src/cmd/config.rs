//! `mac-ego3d config`: a run's configuration, resolved. Loads a configuration file, applies
//! `--set key=value` overrides (validated as the file is) and writes every key, so the copy kept
//! with a run's outputs says exactly what the run used.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use config::Config;

#[derive(Args)]
pub struct ConfigArgs {
    /// Configuration file to start from (the built-in defaults without it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override one key: `--set consensus.t_comm=30`, `--set noise.target=rgb`. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Where to write the resolved configuration (stdout without it).
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn run(args: &ConfigArgs) -> anyhow::Result<()> {
    let (_, text) = resolve(args.config.as_deref(), &args.overrides)?;
    match &args.out {
        Some(path) => {
            std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?
        }
        None => print!("{text}"),
    }
    Ok(())
}

/// The configuration in `path` (the built-in defaults without one) with the `KEY=VALUE`
/// overrides applied, and its text with every key listed (what a run keeps as config.toml).
pub fn resolve(path: Option<&Path>, overrides: &[String]) -> anyhow::Result<(Config, String)> {
    let base = match path {
        Some(path) => Config::load(path)?,
        None => Config::default(),
    };
    let pairs = overrides
        .iter()
        .map(|pair| {
            pair.split_once('=')
                .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
                .with_context(|| format!("--set {pair:?}: expected KEY=VALUE"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let source = path.map_or("the defaults".to_string(), |p| p.display().to_string());
    let resolved = base
        .with_overrides(&pairs)
        .map_err(|reason| anyhow::anyhow!("{source} with {overrides:?}: {reason}"))?;
    let mut text = format!(
        "# Resolved by `mac-ego3d config` from {source}{}; every key is listed.\n",
        if overrides.is_empty() {
            String::new()
        } else {
            format!(" with {}", overrides.join(", "))
        }
    );
    text += &resolved.to_toml().map_err(anyhow::Error::msg)?;
    Ok((resolved, text))
}
