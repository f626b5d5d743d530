//! `mac-ego3d plot tcomm --csv DIR/tcomm.csv --out DIR/tcomm.png`: the T_comm benchmark's table
//! (scripts/bench_tcomm.sh) as a grid of small line charts, one figure against T_comm each.
//!
//! Charts are drawn by plotters into an RGB buffer and saved with the `image` crate. Text needs a
//! font file: plotters' `ab_glyph` feature reads a TTF we load ourselves (DejaVu Sans from the
//! `fonts-dejavu-core` package by default, which scripts/setup.sh installs), so no system font
//! library is linked at build time.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{Context, anyhow, bail};
use clap::{Args, Subcommand};
use plotters::coord::Shift;
use plotters::prelude::*;

#[derive(Subcommand)]
pub enum PlotCommand {
    /// Plot DIR/tcomm.csv (scripts/bench_tcomm.sh) against T_comm into a PNG.
    Tcomm(TcommArgs),
}

#[derive(Args)]
pub struct TcommArgs {
    /// The table written by scripts/bench_tcomm.sh.
    #[arg(long)]
    csv: PathBuf,
    /// The PNG to write.
    #[arg(long)]
    out: PathBuf,
    /// TrueType font for the charts' text.
    #[arg(long, default_value = DEFAULT_FONT)]
    font: PathBuf,
}

/// DejaVu Sans as Debian and Ubuntu install it (package fonts-dejavu-core).
pub const DEFAULT_FONT: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";
/// The name the loaded font is registered under and drawn with.
const FONT_FAMILY: &str = "sans-serif";

/// The T_comm column: the x axis of every chart.
const TCOMM_COLUMN: &str = "t_comm";

/// A plotted column: its CSV name, the chart's title, the y axis label, the factor from the
/// CSV's unit to the label's, and whether its values are whole numbers (counts).
struct Figure {
    column: &'static str,
    title: &'static str,
    y_label: &'static str,
    scale: f64,
    whole_numbers: bool,
}

const FIGURES: [Figure; 6] = [
    Figure {
        column: "ate_joint_rmse_m",
        title: "Joint ATE RMSE",
        y_label: "cm",
        scale: 100.0,
        whole_numbers: false,
    },
    Figure {
        column: "psnr",
        title: "Merged-map PSNR",
        y_label: "dB",
        scale: 1.0,
        whole_numbers: false,
    },
    Figure {
        column: "bytes_per_agent_per_s",
        title: "Data sent per agent",
        y_label: "kB/s",
        scale: 1e-3,
        whole_numbers: false,
    },
    Figure {
        column: "consensus_latency_ms_median",
        title: "Consensus latency (median)",
        y_label: "ms",
        scale: 1.0,
        whole_numbers: false,
    },
    Figure {
        column: "fps_per_agent_mean",
        title: "Frames per second per agent",
        y_label: "frames/s",
        scale: 1.0,
        whole_numbers: false,
    },
    Figure {
        column: "loop_closures_accepted",
        title: "Loop closures accepted",
        y_label: "count",
        scale: 1.0,
        whole_numbers: true,
    },
];

/// Grid layout of the image: charts per row, and each chart's size in pixels.
const GRID_COLUMNS: usize = 3;
pub const PANEL_WIDTH: u32 = 420;
pub const PANEL_HEIGHT: u32 = 320;
const TITLE_FONT_SIZE: u32 = 18;
const LABEL_FONT_SIZE: u32 = 13;
const PANEL_MARGIN: u32 = 12;
const X_LABEL_AREA: u32 = 40;
const Y_LABEL_AREA: u32 = 60;
const POINT_RADIUS: u32 = 4;
const LINE_WIDTH: u32 = 2;
const SERIES_COLOUR: RGBColor = RGBColor(0x4e, 0x79, 0xa7);
/// The x axis is logarithmic (T_comm values are usually doublings: 15, 30, 60, ...); this
/// factor of room on each side keeps the end points off the frame.
const LOG_AXIS_MARGIN_FACTOR: f64 = 1.25;
/// Fraction of the y span added above and below the data.
const Y_PADDING_FRACTION: f64 = 0.1;
/// Half-height of the y range when every value is the same.
const FLAT_Y_HALF_SPAN: f64 = 1.0;
/// Tick labels on the y axis (about; plotters rounds the step to a 1-2-5 value).
const Y_LABELS: usize = 6;

/// Size of the image for `FIGURES`.
pub fn image_size() -> (u32, u32) {
    let rows = FIGURES.len().div_ceil(GRID_COLUMNS) as u32;
    (PANEL_WIDTH * GRID_COLUMNS as u32, PANEL_HEIGHT * rows)
}

/// The table: T_comm per row (ascending) and each figure's values (`None`: the run did not
/// measure it; drawn as a gap).
#[derive(Debug, PartialEq)]
pub struct TcommTable {
    pub t_comm: Vec<f64>,
    /// One column per entry of `FIGURES`, in that order.
    pub figures: Vec<Vec<Option<f64>>>,
}

/// Parses the benchmark's CSV (plain comma-separated numbers, no quoting; a header line naming
/// the columns; other columns are ignored). Errors name the file, line and column.
pub fn parse_tcomm_csv(path: &Path, text: &str) -> anyhow::Result<TcommTable> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty());
    let Some((header_line, header)) = lines.next() else {
        bail!(
            "{}: empty; expected a header line naming {TCOMM_COLUMN} and the figures",
            path.display()
        );
    };
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let position = |column: &str| {
        names.iter().position(|n| *n == column).ok_or_else(|| {
            anyhow!(
                "{}: line {header_line}: missing column {column:?} (the header has {})",
                path.display(),
                names.join(", ")
            )
        })
    };
    let t_comm_index = position(TCOMM_COLUMN)?;
    let figure_indices = FIGURES
        .iter()
        .map(|f| position(f.column))
        .collect::<anyhow::Result<Vec<_>>>()?;

    let mut rows = Vec::new();
    for (line_number, line) in lines {
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        if cells.len() != names.len() {
            bail!(
                "{}: line {line_number}: {} cells, the header has {}",
                path.display(),
                cells.len(),
                names.len()
            );
        }
        let cell = |index: usize| -> anyhow::Result<Option<f64>> {
            parse_cell(cells[index]).map_err(|reason| {
                anyhow!(
                    "{}: line {line_number}, column {} ({}): {reason}",
                    path.display(),
                    index + 1,
                    names[index]
                )
            })
        };
        let t_comm = cell(t_comm_index)?
            .filter(|t| *t > 0.0)
            .ok_or_else(|| {
                anyhow!(
                    "{}: line {line_number}, column {} ({TCOMM_COLUMN}): every row needs a positive T_comm",
                    path.display(),
                    t_comm_index + 1
                )
            })?;
        let values = figure_indices
            .iter()
            .map(|&i| cell(i))
            .collect::<anyhow::Result<Vec<_>>>()?;
        rows.push((t_comm, values));
    }
    if rows.is_empty() {
        bail!("{}: no data rows under the header", path.display());
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(TcommTable {
        t_comm: rows.iter().map(|r| r.0).collect(),
        figures: (0..FIGURES.len())
            .map(|f| rows.iter().map(|r| r.1[f]).collect())
            .collect(),
    })
}

/// An empty cell is a figure the run did not measure; anything else must be a finite number.
fn parse_cell(text: &str) -> Result<Option<f64>, String> {
    if text.is_empty() {
        return Ok(None);
    }
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(Some(v)),
        _ => Err(format!("{text:?} is not a number")),
    }
}

/// The font file registered last (the one charts are drawn with). plotters keeps a `'static`
/// reference to the bytes, so they are leaked: drawing again with the same font reads nothing and
/// leaks nothing more.
static REGISTERED_FONT: Mutex<Option<PathBuf>> = Mutex::new(None);

/// Makes `path` the font charts are drawn with.
pub fn register_font(path: &Path) -> anyhow::Result<()> {
    let mut registered = REGISTERED_FONT
        .lock()
        .map_err(|_| anyhow!("font registry poisoned"))?;
    if registered.as_deref() == Some(path) {
        return Ok(());
    }
    if !path.is_file() {
        bail!(
            "font {} not found: install the package fonts-dejavu-core (bash scripts/setup.sh \
             does), or pass --font with a TrueType font file",
            path.display()
        );
    }
    let bytes = std::fs::read(path).with_context(|| format!("reading font {}", path.display()))?;
    let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
    plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, bytes)
        .map_err(|_| anyhow!("{}: not a TrueType/OpenType font", path.display()))?;
    *registered = Some(path.to_path_buf());
    Ok(())
}

/// The points of one figure, split at missing values so a gap is not bridged by a line.
fn segments(t_comm: &[f64], values: &[Option<f64>], scale: f64) -> Vec<Vec<(f64, f64)>> {
    let mut segments = vec![Vec::new()];
    for (t, value) in t_comm.iter().zip(values) {
        match value {
            Some(v) => segments
                .last_mut()
                .expect("never empty")
                .push((*t, v * scale)),
            None => segments.push(Vec::new()),
        }
    }
    segments.retain(|s| !s.is_empty());
    segments
}

/// The y range of a chart; a count's range spans at least one unit per tick label, so no tick
/// falls between two whole numbers.
fn y_range(points: &[(f64, f64)], whole_numbers: bool) -> std::ops::Range<f64> {
    let range = data_y_range(points);
    let min_span = if whole_numbers { Y_LABELS as f64 } else { 0.0 };
    let extra = (min_span - (range.end - range.start)).max(0.0);
    // Counts are never negative: a count's range grows upwards only.
    range.start..range.end + extra
}

/// Decimals that tell the y tick labels apart (0.05 steps -> 2, steps of 2 -> 0).
fn label_decimals(range: &std::ops::Range<f64>) -> usize {
    let rough_step = (range.end - range.start) / Y_LABELS as f64;
    (-rough_step.log10().floor()).max(0.0) as usize
}

/// The values' range with a margin (a unit-free default when there is no value or one).
fn data_y_range(points: &[(f64, f64)]) -> std::ops::Range<f64> {
    let (min, max) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    if !min.is_finite() {
        return 0.0..2.0 * FLAT_Y_HALF_SPAN;
    }
    if max - min <= 0.0 {
        return (min - FLAT_Y_HALF_SPAN)..(max + FLAT_Y_HALF_SPAN);
    }
    let pad = (max - min) * Y_PADDING_FRACTION;
    (min - pad)..(max + pad)
}

fn draw_error(what: &str, error: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("drawing {what}: {error}")
}

/// One chart: a figure against T_comm on a logarithmic axis, lines broken at gaps, a dot per run.
fn draw_panel(
    area: &DrawingArea<BitMapBackend, Shift>,
    figure: &Figure,
    t_comm: &[f64],
    values: &[Option<f64>],
) -> anyhow::Result<()> {
    let segments = segments(t_comm, values, figure.scale);
    let points: Vec<(f64, f64)> = segments.iter().flatten().copied().collect();
    let first = t_comm.first().copied().unwrap_or(1.0);
    let last = t_comm.last().copied().unwrap_or(1.0);
    let x_range = (first / LOG_AXIS_MARGIN_FACTOR)..(last * LOG_AXIS_MARGIN_FACTOR);
    let y_range = y_range(&points, figure.whole_numbers);
    let caption = if points.is_empty() {
        format!("{} (not measured)", figure.title)
    } else {
        figure.title.to_string()
    };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FONT_FAMILY, TITLE_FONT_SIZE))
        .margin(PANEL_MARGIN)
        .x_label_area_size(X_LABEL_AREA)
        .y_label_area_size(Y_LABEL_AREA)
        // Ticks at the T_comm values that were run, not at powers of ten.
        .build_cartesian_2d(
            x_range.log_scale().with_key_points(t_comm.to_vec()),
            y_range.clone(),
        )
        .map_err(|e| draw_error(figure.title, e))?;
    let x_label = |t: &f64| format!("{t:.0}");
    let decimals = label_decimals(&y_range);
    let y_label = |v: &f64| format!("{v:.decimals$}");
    chart
        .configure_mesh()
        .x_desc("T_comm (frames)")
        .y_desc(figure.y_label)
        .x_label_formatter(&x_label)
        .y_labels(Y_LABELS)
        .y_label_formatter(&y_label)
        .label_style((FONT_FAMILY, LABEL_FONT_SIZE))
        // Only the major grid: the minor lines of a log axis crowd a small chart.
        .light_line_style(TRANSPARENT)
        .draw()
        .map_err(|e| draw_error(figure.title, e))?;
    for segment in segments {
        chart
            .draw_series(LineSeries::new(
                segment,
                SERIES_COLOUR.stroke_width(LINE_WIDTH),
            ))
            .map_err(|e| draw_error(figure.title, e))?;
    }
    chart
        .draw_series(
            points
                .into_iter()
                .map(|p| Circle::new(p, POINT_RADIUS, SERIES_COLOUR.filled())),
        )
        .map_err(|e| draw_error(figure.title, e))?;
    Ok(())
}

/// The grid of charts as an RGB image; the font must be registered first.
pub fn draw_tcomm(table: &TcommTable) -> anyhow::Result<image::RgbImage> {
    let (width, height) = image_size();
    let mut buffer = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_error("background", e))?;
        let rows = FIGURES.len().div_ceil(GRID_COLUMNS);
        let panels = root.split_evenly((rows, GRID_COLUMNS));
        for ((panel, figure), values) in panels.iter().zip(&FIGURES).zip(&table.figures) {
            draw_panel(panel, figure, &table.t_comm, values)?;
        }
        root.present().map_err(|e| draw_error("the image", e))?;
    }
    image::RgbImage::from_raw(width, height, buffer)
        .ok_or_else(|| anyhow!("chart buffer does not match {width}x{height}"))
}

/// Reads the CSV, draws the charts and writes the PNG.
pub fn plot_tcomm(csv: &Path, out: &Path, font: &Path) -> anyhow::Result<()> {
    let text =
        std::fs::read_to_string(csv).with_context(|| format!("reading {}", csv.display()))?;
    let table = parse_tcomm_csv(csv, &text)?;
    register_font(font)?;
    let image = draw_tcomm(&table)?;
    image
        .save(out)
        .with_context(|| format!("writing {}", out.display()))
}

pub fn run(command: &PlotCommand) -> anyhow::Result<()> {
    match command {
        PlotCommand::Tcomm(args) => {
            plot_tcomm(&args.csv, &args.out, &args.font)?;
            println!("{}", args.out.display());
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "t_comm,ate_joint_rmse_m,psnr,bytes_per_agent_per_s,consensus_latency_ms_median,fps_per_agent_mean,loop_closures_accepted,agents_not_linked";

    #[test]
    fn empty_cells_are_gaps_and_rows_sort_by_tcomm() {
        let csv =
            format!("{HEADER}\n60,0.012,24.5,150000.0,500.0,1.9,10,0\n15,0.02,,90000.0,,1.8,3,1\n");
        let table = parse_tcomm_csv(Path::new("t.csv"), &csv).unwrap();
        assert_eq!(table.t_comm, [15.0, 60.0]);
        assert_eq!(table.figures[1], [None, Some(24.5)]);
        assert_eq!(table.figures[3], [None, Some(500.0)]);
        assert_eq!(
            segments(&[15.0, 30.0, 60.0], &[Some(1.0), None, Some(2.0)], 1.0),
            [vec![(15.0, 1.0)], vec![(60.0, 2.0)]]
        );
    }

    #[test]
    fn malformed_csv_errors_name_file_line_and_column() {
        let path = Path::new("bench/tcomm.csv");
        let error = |csv: &str| parse_tcomm_csv(path, csv).unwrap_err().to_string();

        let bad_number = error(&format!(
            "{HEADER}\n15,0.01,24,1,1,1,1,0\n30,0.01,abc,1,1,1,1,0\n"
        ));
        assert!(
            bad_number.contains("bench/tcomm.csv")
                && bad_number.contains("line 3")
                && bad_number.contains("column 3 (psnr)")
                && bad_number.contains("\"abc\""),
            "{bad_number}"
        );
        let missing = error("t_comm,ate_joint_rmse_m\n15,0.1\n");
        assert!(
            missing.contains("line 1") && missing.contains("missing column \"psnr\""),
            "{missing}"
        );
        let short_row = error(&format!("{HEADER}\n15,0.01\n"));
        assert!(short_row.contains("line 2: 2 cells"), "{short_row}");
        let no_tcomm = error(&format!("{HEADER}\n,0.01,24,1,1,1,1,0\n"));
        assert!(no_tcomm.contains("column 1 (t_comm)"), "{no_tcomm}");
        assert!(error("").contains("empty"));
        assert!(error(&format!("{HEADER}\n")).contains("no data rows"));
    }

    #[test]
    fn counts_get_whole_number_ticks() {
        let few = [(15.0, 0.0), (30.0, 1.0)];
        let range = y_range(&few, true);
        assert!(range.end - range.start >= Y_LABELS as f64);
        assert_eq!(label_decimals(&range), 0);
        assert_eq!(
            label_decimals(&y_range(&[(15.0, 0.8), (30.0, 1.1)], false)),
            2
        );
    }

    #[test]
    fn missing_font_is_named() {
        let error = register_font(Path::new("/nonexistent/font.ttf"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("/nonexistent/font.ttf") && error.contains("fonts-dejavu-core"),
            "{error}"
        );
    }

    #[test]
    fn small_table_gives_a_png_of_the_grid_size() {
        let dir = tempfile::tempdir().unwrap();
        let csv = dir.path().join("tcomm.csv");
        std::fs::write(
            &csv,
            format!(
                "{HEADER}\n15,0.02,23.0,90000.0,300.0,1.8,3,0\n30,0.015,,120000.0,420.0,1.9,5,0\n60,0.012,24.5,150000.0,,1.9,8,0\n"
            ),
        )
        .unwrap();
        let out = dir.path().join("tcomm.png");
        plot_tcomm(&csv, &out, Path::new(DEFAULT_FONT)).unwrap();
        let decoded = image::open(&out).unwrap();
        assert_eq!((decoded.width(), decoded.height()), image_size());
        // Something besides the white background was drawn.
        let rgb = decoded.to_rgb8();
        assert!(rgb.pixels().any(|p| p.0 != [255, 255, 255]));
    }
}
