//! One module per subcommand; nested subcommands (`bench ...`, `eval ...`) are folders.

pub mod bag_info;
pub mod bench;
pub mod chaos;
pub mod config;
pub mod dataset;
pub mod eval;
pub mod live_info;
pub mod plot;
pub mod render;
pub mod swarm;
pub mod synth;

/// Prints `value` as one JSON object on stdout.
pub fn print_json(value: &impl serde::Serialize) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string_pretty(value)?);
    Ok(())
}

/// Formats a number for a table, showing non-finite values plainly.
pub fn fmt_num(v: f64, decimals: usize) -> String {
    if v.is_finite() {
        format!("{v:.decimals$}")
    } else {
        format!("{v}")
    }
}

/// A refused option or input, found before anything ran: the command exits with status 2 (as
/// for a command-line error) and this message.
#[derive(Debug)]
pub struct UsageError(pub String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}
