//! `--figures FILE --figures-section HEADING` of the bench commands: the run's headline figures
//! written as entries of a docs/figures/*.json file (the fields scripts/figures.py checks), with
//! the command, commit, machine and date filled in, so that docs/benchmarks.md's "Current
//! figures" table is generated from what a bench measured rather than copied by hand. Run
//! `python3 scripts/figures.py` afterwards to rewrite the table. `bench record-figures` does
//! the same for the figures a script measured (the peer comparisons in shell and Python).

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

/// The options every bench command that has headline figures takes.
#[derive(Args, Debug, Default, Clone)]
pub struct FigureArgs {
    /// Write this run's headline figures as FILE (a docs/figures/*.json file, replaced), then
    /// run `python3 scripts/figures.py`.
    #[arg(long, value_name = "FILE", requires = "figures_section")]
    pub figures: Option<PathBuf>,
    /// The heading (without the leading '## ') of the docs/benchmarks.md entry that reports
    /// this run; scripts/figures.py links the table's row to it.
    #[arg(long, value_name = "HEADING", requires = "figures")]
    pub figures_section: Option<String>,
    /// What the run is, the start of each figure's name ("paced 2-agent swarm, redkitchen
    /// 0..600 + 400..1000"; default: the bench's own description of its input).
    #[arg(long, value_name = "TEXT", requires = "figures")]
    pub figures_label: Option<String>,
    /// Where it ran, as the table should say it (default: the CPU model, cores and OS read from
    /// /proc/cpuinfo and /etc/os-release). Say how loaded the machine was here.
    #[arg(long, value_name = "TEXT")]
    pub machine: Option<String>,
}

/// One headline figure of a bench run.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// What is measured ("tracking ATE, redkitchen 0..1000").
    pub name: String,
    /// The figure, rounded to the decimals that mean something.
    pub value: FigureValue,
    /// Its unit ("cm", "ms", "dB"; "" for none).
    pub unit: String,
}

/// A figure's value: a number (rounded to `decimals`) or a short text ("20/20/16/4").
#[derive(Debug, Clone, PartialEq)]
pub enum FigureValue {
    Number { value: f64, decimals: u32 },
    Text(String),
}

impl Figure {
    /// A number rounded to `decimals`.
    pub fn number(
        name: impl Into<String>,
        value: f64,
        decimals: u32,
        unit: impl Into<String>,
    ) -> Self {
        Self {
            name: name.into(),
            value: FigureValue::Number { value, decimals },
            unit: unit.into(),
        }
    }

    /// A short text.
    pub fn text(
        name: impl Into<String>,
        value: impl Into<String>,
        unit: impl Into<String>,
    ) -> Self {
        Self {
            name: name.into(),
            value: FigureValue::Text(value.into()),
            unit: unit.into(),
        }
    }
}

/// Where and when a run was made: the fields every figure of it shares.
#[derive(Debug, Clone)]
pub struct Provenance {
    pub command: String,
    pub commit: String,
    pub machine: String,
    pub date: String,
}

impl FigureArgs {
    /// `--figures-label`, else `default`: what each figure's name starts with.
    pub fn label(&self, default: impl FnOnce() -> String) -> String {
        self.figures_label.clone().unwrap_or_else(default)
    }

    /// Writes `figures` into `--figures` when it was given (nothing otherwise); a figure whose
    /// value is not finite is refused with its name, since the table cannot show it.
    pub fn record(&self, figures: &[Figure]) -> anyhow::Result<()> {
        self.record_as(command_line(std::env::args().collect()), figures)
    }

    /// [`Self::record`] with the command that measured the figures given (`command`).
    fn record_as(&self, command: String, figures: &[Figure]) -> anyhow::Result<()> {
        let (Some(path), Some(section)) = (&self.figures, &self.figures_section) else {
            return Ok(());
        };
        let provenance = Provenance {
            command,
            commit: commit()?,
            machine: match &self.machine {
                Some(machine) => machine.clone(),
                None => machine(),
            },
            date: utc_date(std::time::SystemTime::now()),
        };
        write_figures(path, section, &provenance, figures)?;
        eprintln!(
            "{} figure(s) written to {}; run `python3 scripts/figures.py` to update docs/benchmarks.md",
            figures.len(),
            path.display()
        );
        Ok(())
    }
}

/// `mac-ego3d bench record-figures`: headline figures a script measured, written into a
/// docs/figures file as the bench commands' `--figures` writes theirs.
#[derive(Args, Debug)]
pub struct RecordFiguresArgs {
    /// The figures: a JSON list of objects with `name`, `value` (a number, or a short text such
    /// as "20/20/16/4"), `unit` ("" for none) and, for numbers, `decimals` (what the rounding
    /// keeps). With --figures-label, each name starts with it.
    #[arg(long, value_name = "FILE")]
    pub from: PathBuf,
    /// The command that measured them, as the table shows it (the script's own command line).
    #[arg(long, value_name = "TEXT")]
    pub command: String,
    #[command(flatten)]
    pub figures: FigureArgs,
}

/// Runs `bench record-figures`.
pub fn run_record(args: &RecordFiguresArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.figures.figures.is_some(),
        "record-figures writes into --figures FILE (with --figures-section HEADING)"
    );
    let text = std::fs::read_to_string(&args.from)
        .with_context(|| format!("reading {}", args.from.display()))?;
    let mut figures = parse_figures(&text)
        .with_context(|| format!("{}: not a list of figures", args.from.display()))?;
    if let Some(label) = &args.figures.figures_label {
        for figure in &mut figures {
            figure.name = format!("{label}: {}", figure.name);
        }
    }
    args.figures
        .record_as(shared_as_variable(&args.command), &figures)
}

/// The figures of `record-figures`' input (see [`RecordFiguresArgs::from`]); an error names the
/// entry and field at fault.
fn parse_figures(text: &str) -> anyhow::Result<Vec<Figure>> {
    let entries: Vec<serde_json::Value> = serde_json::from_str(text)?;
    anyhow::ensure!(!entries.is_empty(), "no figures in the list");
    entries
        .iter()
        .enumerate()
        .map(|(index, entry)| {
            let field = |name: &str| {
                entry
                    .get(name)
                    .with_context(|| format!("figure {index}: no field {name:?}"))
            };
            let name = field("name")?
                .as_str()
                .with_context(|| format!("figure {index}: \"name\" is not a text"))?;
            let unit = match entry.get("unit") {
                None => String::new(),
                Some(unit) => unit
                    .as_str()
                    .with_context(|| format!("figure {index} ({name}): \"unit\" is not a text"))?
                    .to_string(),
            };
            Ok(match field("value")? {
                serde_json::Value::String(text) => Figure::text(name, text.clone(), unit),
                value => {
                    let number = value.as_f64().with_context(|| {
                        format!("figure {index} ({name}): \"value\" is neither a number nor a text")
                    })?;
                    let decimals = field("decimals")?
                        .as_u64()
                        .filter(|d| *d <= 6)
                        .with_context(|| {
                            format!("figure {index} ({name}): \"decimals\" is not 0-6")
                        })?;
                    Figure::number(name, number, decimals as u32, unit)
                }
            })
        })
        .collect()
}

/// Writes `figures` as the JSON file at `path` (replacing it): a list of objects with
/// scripts/figures.py's fields in its order, numbers with their decimals as rounded ("20.30"). A
/// figure whose value is not finite is refused with its name: the table cannot show it.
pub fn write_figures(
    path: &Path,
    section: &str,
    provenance: &Provenance,
    figures: &[Figure],
) -> anyhow::Result<()> {
    let quote = |text: &str| serde_json::to_string(text).expect("a string serialises");
    let mut entries = Vec::new();
    for figure in figures {
        let value = match &figure.value {
            FigureValue::Number { value, decimals } => {
                anyhow::ensure!(
                    value.is_finite(),
                    "figure {:?} is {value}: nothing to record",
                    figure.name
                );
                format!("{value:.prec$}", prec = *decimals as usize)
            }
            FigureValue::Text(text) => quote(text),
        };
        let fields = [
            ("name", quote(&figure.name)),
            ("value", value),
            ("unit", quote(&figure.unit)),
            ("command", quote(&provenance.command)),
            ("commit", quote(&provenance.commit)),
            ("machine", quote(&provenance.machine)),
            ("date", quote(&provenance.date)),
            ("source_section", quote(section)),
        ];
        let body: Vec<String> = fields
            .iter()
            .map(|(field, value)| format!("    \"{field}\": {value}"))
            .collect();
        entries.push(format!("  {{\n{}\n  }}", body.join(",\n")));
    }
    let text = format!("[\n{}\n]\n", entries.join(",\n"));
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// The command as the table shows it: the program's file name and its arguments, the shared
/// data folder written as `$MAC_EGO3D_SHARED`, and the figure options themselves left out.
pub fn command_line(args: Vec<String>) -> String {
    let mut words = Vec::new();
    let mut args = args.into_iter();
    if let Some(program) = args.next() {
        words.push(
            Path::new(&program)
                .file_name()
                .map_or(program.clone(), |name| name.to_string_lossy().into_owned()),
        );
    }
    let own = [
        "--figures",
        "--figures-section",
        "--figures-label",
        "--machine",
    ];
    while let Some(arg) = args.next() {
        if own.contains(&arg.as_str()) {
            args.next();
            continue;
        }
        if own.iter().any(|o| arg.starts_with(&format!("{o}="))) {
            continue;
        }
        let arg = shared_as_variable(&arg);
        words.push(if arg.contains(' ') {
            format!("'{arg}'")
        } else {
            arg
        });
    }
    words.join(" ")
}

/// `text` with the shared data folder written as `$MAC_EGO3D_SHARED`: the table's commands
/// hold on any machine.
fn shared_as_variable(text: &str) -> String {
    let shared = datasets::shared_data::shared_dir();
    let shared = shared.to_string_lossy();
    if shared.is_empty() {
        text.to_string()
    } else {
        text.replace(shared.as_ref(), "$MAC_EGO3D_SHARED")
    }
}

/// The checked-out commit (7 digits), noting uncommitted changes to tracked files.
fn commit() -> anyhow::Result<String> {
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .output()
            .ok()
            .filter(|out| out.status.success())
            .map(|out| String::from_utf8_lossy(&out.stdout).trim().to_string())
    };
    let hash = git(&["rev-parse", "--short=7", "HEAD"]).context(
        "--figures records the commit measured: run the bench inside the repository's checkout",
    )?;
    let changed = git(&["status", "--porcelain", "--untracked-files=no"])
        .is_some_and(|status| !status.is_empty());
    Ok(if changed {
        format!("{hash} (with uncommitted changes)")
    } else {
        hash
    })
}

/// "CPU model, N cores, OS" from /proc/cpuinfo and /etc/os-release, as far as they tell.
fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|line| line.starts_with("model name"))
                .and_then(|line| line.split_once(':'))
                .map(|(_, model)| model.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let os = std::fs::read_to_string("/etc/os-release")
        .ok()
        .and_then(|text| {
            text.lines()
                .find_map(|line| line.strip_prefix("PRETTY_NAME="))
                .map(|name| name.trim_matches('"').to_string())
        })
        .unwrap_or_else(|| std::env::consts::OS.to_string());
    format!("{cpu}, {cores} cores, {os}")
}

/// `time` as a UTC calendar date, YYYY-MM-DD (days since the epoch to the proleptic Gregorian
/// calendar, by eras of 400 years).
pub fn utc_date(time: std::time::SystemTime) -> String {
    let seconds = time
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let days = seconds.div_euclid(86_400) + 719_468;
    let era = days.div_euclid(146_097);
    let day_of_era = days - era * 146_097;
    let year_of_era =
        (day_of_era - day_of_era / 1460 + day_of_era / 36_524 - day_of_era / 146_096) / 365;
    let day_of_year = day_of_era - (365 * year_of_era + year_of_era / 4 - year_of_era / 100);
    let month_index = (5 * day_of_year + 2) / 153;
    let day = day_of_year - (153 * month_index + 2) / 5 + 1;
    let month = if month_index < 10 {
        month_index + 3
    } else {
        month_index - 9
    };
    let year = year_of_era + era * 400 + i64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}")
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, UNIX_EPOCH};

    use super::*;

    #[test]
    fn dates_are_utc_calendar_days() {
        let day = |seconds: u64| utc_date(UNIX_EPOCH + Duration::from_secs(seconds));
        assert_eq!(day(0), "1970-01-01");
        assert_eq!(day(951_782_400), "2000-02-29");
        assert_eq!(day(951_868_799), "2000-02-29");
        assert_eq!(day(951_868_800), "2000-03-01");
        assert_eq!(day(1_796_601_600), "2026-12-07");
    }

    #[test]
    fn the_command_names_the_program_and_leaves_the_figure_options_out() {
        let args = [
            "/work/target/debug/mac-ego3d",
            "bench",
            "merge",
            "--dir",
            "my run",
            "--figures",
            "docs/figures/30_swarm.json",
            "--figures-section=2026-12-07: x",
            "--machine",
            "a VM",
            "--json",
        ];
        let line = command_line(args.iter().map(|s| s.to_string()).collect());
        assert_eq!(line, "mac-ego3d bench merge --dir 'my run' --json");
    }

    #[test]
    fn a_scripts_figures_are_read_with_their_decimals_and_bad_entries_are_named() {
        let figures = parse_figures(
            r#"[{"name": "ATE", "value": 2.904, "decimals": 2, "unit": "cm"},
                {"name": "successes", "value": "20/20"}]"#,
        )
        .unwrap();
        assert_eq!(figures[0], Figure::number("ATE", 2.904, 2, "cm"));
        assert_eq!(figures[1], Figure::text("successes", "20/20", ""));
        let error = |text: &str| format!("{:#}", parse_figures(text).unwrap_err());
        assert!(error("[]").contains("no figures"));
        assert!(error(r#"[{"value": 1, "decimals": 1}]"#).contains("figure 0: no field \"name\""));
        let missing = error(r#"[{"name": "a", "value": "x"}, {"name": "ratio", "value": 1.5}]"#);
        assert!(
            missing.contains("figure 1: no field \"decimals\""),
            "{missing}"
        );
        let wrong = error(r#"[{"name": "ratio", "value": [1], "decimals": 2}]"#);
        assert!(wrong.contains("figure 0 (ratio)"), "{wrong}");
    }

    #[test]
    fn figures_are_written_with_the_fields_the_table_needs_in_its_order() {
        let dir = std::env::temp_dir().join(format!("mac-ego3d-figures-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("10_test.json");
        let provenance = Provenance {
            command: "mac-ego3d bench tracking --dataset \"x\"".into(),
            commit: "0123abc".into(),
            machine: "a VM".into(),
            date: "2026-12-07".into(),
        };
        let figures = [
            Figure::number("ATE", 3.0, 2, "cm"),
            Figure::text("successes", "20/20", ""),
        ];
        write_figures(&path, "2026-12-07: first", &provenance, &figures).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("\"value\": 3.00,"), "{text}");
        let entries: serde_json::Value = serde_json::from_str(&text).unwrap();
        let entries = entries.as_array().unwrap();
        assert_eq!(entries.len(), 2);
        assert_eq!(entries[1]["value"], "20/20");
        assert_eq!(
            entries[0]["command"],
            "mac-ego3d bench tracking --dataset \"x\""
        );
        assert_eq!(entries[0]["source_section"], "2026-12-07: first");
        let order: Vec<usize> = [
            "name",
            "value",
            "unit",
            "command",
            "commit",
            "machine",
            "date",
            "source_section",
        ]
        .iter()
        .map(|field| text.find(&format!("\"{field}\":")).unwrap())
        .collect();
        assert!(order.windows(2).all(|w| w[0] < w[1]), "{text}");
        let nan = [Figure::number("broken", f64::NAN, 2, "cm")];
        let error = write_figures(&path, "x", &provenance, &nan).unwrap_err();
        assert!(error.to_string().contains("broken"), "{error}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
