//! Small inline-SVG charts for the report: a plot area with linear axes, ticks and labels,
//! polylines, markers with hover text, and a legend column. Written by hand rather than through a
//! plotting library so the report stays text (diffable, greppable, a few kB per chart) and needs
//! no font or renderer: the browser draws the text.

use std::fmt::Write;

use super::html::escape;

/// Overall chart size in CSS pixels; wide enough for a laptop screen next to nothing else.
pub const CHART_WIDTH: f64 = 860.0;
pub const CHART_HEIGHT: f64 = 420.0;
/// Room left of the plot area for the y tick labels and the rotated y label.
const MARGIN_LEFT: f64 = 70.0;
/// Room below the plot area for the x tick labels and the x label.
const MARGIN_BOTTOM: f64 = 50.0;
const MARGIN_TOP: f64 = 15.0;
/// Right of the plot area: the legend column.
const LEGEND_WIDTH: f64 = 270.0;
const LEGEND_ROW_HEIGHT: f64 = 18.0;
const LEGEND_SWATCH_LENGTH: f64 = 24.0;
/// Ticks per axis the 1-2-5 rule aims for.
const TARGET_TICKS: usize = 6;
const TICK_LENGTH: f64 = 5.0;
const FONT_SIZE: f64 = 12.0;
const LINE_WIDTH: f64 = 1.6;
/// A reference line (ground truth) is a wide, pale, dashed band: an estimate drawn on top of it
/// stays visible, and a perfect estimate does not hide it.
const REFERENCE_LINE_WIDTH: f64 = 4.0;
const REFERENCE_OPACITY: f64 = 0.45;
const DASH_PATTERN: &str = "6 4";
const MARKER_RADIUS: f64 = 5.0;
/// A polyline longer than this is thinned evenly (first and last point kept): a browser draws
/// tens of thousands of points slowly and the screen cannot show them anyway.
pub const MAX_POLYLINE_POINTS: usize = 4000;
/// Fraction of the data span added on each side so lines do not touch the frame.
const PADDING_FRACTION: f64 = 0.05;
/// Half-width given to a range whose values are all equal, so the scale stays defined.
const DEGENERATE_HALF_SPAN: f64 = 0.5;

/// Colour per agent (Tableau 10: distinguishable, also in greyscale print).
const PALETTE: [&str; 10] = [
    "#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#edc948", "#b07aa1", "#ff9da7",
    "#9c755f", "#bab0ac",
];

/// The colour of the k-th agent (cycling when there are more agents than colours).
pub fn agent_colour(index: usize) -> &'static str {
    PALETTE[index % PALETTE.len()]
}

/// A closed interval of data values.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    pub min: f64,
    pub max: f64,
}

impl Range {
    /// The smallest range holding every finite value; `None` when there is none.
    pub fn of(values: impl IntoIterator<Item = f64>) -> Option<Self> {
        values
            .into_iter()
            .filter(|v| v.is_finite())
            .fold(None, |range: Option<Range>, v| {
                Some(match range {
                    None => Range { min: v, max: v },
                    Some(r) => Range {
                        min: r.min.min(v),
                        max: r.max.max(v),
                    },
                })
            })
    }

    pub fn span(&self) -> f64 {
        self.max - self.min
    }

    /// Widened by `PADDING_FRACTION` on each side (or to a unit span when all values are equal).
    pub fn padded(self) -> Self {
        if self.span() <= 0.0 {
            return Range {
                min: self.min - DEGENERATE_HALF_SPAN,
                max: self.max + DEGENERATE_HALF_SPAN,
            };
        }
        let pad = self.span() * PADDING_FRACTION;
        Range {
            min: self.min - pad,
            max: self.max + pad,
        }
    }

    /// Grown symmetrically to `span` (never shrunk).
    fn widened_to(self, span: f64) -> Self {
        let extra = (span - self.span()).max(0.0) / 2.0;
        Range {
            min: self.min - extra,
            max: self.max + extra,
        }
    }
}

/// Maps data values linearly onto pixels.
#[derive(Debug, Clone, Copy)]
struct Scale {
    domain: Range,
    /// Pixel of `domain.min` and of `domain.max` (for y, `start` is the bottom).
    start: f64,
    end: f64,
}

impl Scale {
    fn map(&self, value: f64) -> f64 {
        self.start + (value - self.domain.min) / self.domain.span() * (self.end - self.start)
    }
}

/// Tick values at 1, 2 or 5 times a power of ten, about `TARGET_TICKS` of them within `range`.
pub fn nice_ticks(range: Range) -> Vec<f64> {
    let step = nice_step(range.span() / TARGET_TICKS as f64);
    if !(step.is_finite() && step > 0.0) {
        return Vec::new();
    }
    let first = (range.min / step).ceil() as i64;
    let last = (range.max / step).floor() as i64;
    (first..=last).map(|k| k as f64 * step).collect()
}

fn nice_step(rough: f64) -> f64 {
    let magnitude = 10f64.powf(rough.log10().floor());
    let residual = rough / magnitude;
    let multiple = if residual <= 1.0 {
        1.0
    } else if residual <= 2.0 {
        2.0
    } else if residual <= 5.0 {
        5.0
    } else {
        10.0
    };
    multiple * magnitude
}

/// Decimals that show a tick step exactly (0.05 -> 2, 20 -> 0).
fn tick_decimals(ticks: &[f64]) -> usize {
    let step = match ticks {
        [a, b, ..] => b - a,
        _ => return 2,
    };
    (-step.log10().floor()).max(0.0) as usize
}

/// How a line is drawn.
#[derive(Debug, Clone, Copy)]
pub struct Stroke {
    pub colour: &'static str,
    /// A reference (ground truth) rather than a measured line.
    pub reference: bool,
}

/// Marker shapes; colour says one thing, the shape another.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    Circle,
    Square,
}

/// One legend row.
enum LegendEntry {
    Line(String, Stroke),
    Marker(String, Shape, &'static str),
}

/// A chart under construction: add lines and markers in data coordinates, then [`Chart::render`].
pub struct Chart {
    x: Scale,
    y: Scale,
    x_label: String,
    y_label: String,
    /// Replaces numeric y ticks with named rows (a timeline's lanes).
    y_categories: Option<Vec<String>>,
    body: String,
    legend: Vec<LegendEntry>,
}

fn plot_area() -> (f64, f64, f64, f64) {
    let left = MARGIN_LEFT;
    let right = CHART_WIDTH - LEGEND_WIDTH;
    let top = MARGIN_TOP;
    let bottom = CHART_HEIGHT - MARGIN_BOTTOM;
    (left, right, top, bottom)
}

impl Chart {
    /// A chart showing `x_range` by `y_range` (padded so data does not touch the frame).
    pub fn new(x_range: Range, y_range: Range, x_label: &str, y_label: &str) -> Self {
        let (left, right, top, bottom) = plot_area();
        Self {
            x: Scale {
                domain: x_range.padded(),
                start: left,
                end: right,
            },
            y: Scale {
                domain: y_range.padded(),
                start: bottom,
                end: top,
            },
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            y_categories: None,
            body: String::new(),
            legend: Vec::new(),
        }
    }

    /// A map view: one metre is as long across as up, so shapes are not distorted.
    pub fn equal_aspect(x_range: Range, y_range: Range, x_label: &str, y_label: &str) -> Self {
        let (left, right, top, bottom) = plot_area();
        let (x_range, y_range) = (x_range.padded(), y_range.padded());
        let metres_per_pixel =
            (x_range.span() / (right - left)).max(y_range.span() / (bottom - top));
        let mut chart = Self::new(x_range, y_range, x_label, y_label);
        chart.x.domain = x_range.widened_to(metres_per_pixel * (right - left));
        chart.y.domain = y_range.widened_to(metres_per_pixel * (bottom - top));
        chart
    }

    /// A timeline: y rows named by `lanes` (row k at y = k), x as given.
    pub fn with_lanes(x_range: Range, lanes: Vec<String>, x_label: &str, y_label: &str) -> Self {
        let last = lanes.len().saturating_sub(1) as f64;
        let mut chart = Self::new(x_range, Range { min: 0.0, max: 0.0 }, x_label, y_label);
        // Half a row above and below, so the first and last lanes' markers are not cut.
        chart.y.domain = Range {
            min: -0.5,
            max: last + 0.5,
        };
        chart.y_categories = Some(lanes);
        chart
    }

    fn pixel(&self, (x, y): (f64, f64)) -> (f64, f64) {
        (self.x.map(x), self.y.map(y))
    }

    /// A polyline through `points` (non-finite points are skipped), with a legend row.
    pub fn line(&mut self, points: &[(f64, f64)], stroke: Stroke, legend: &str) {
        let finite: Vec<(f64, f64)> = points
            .iter()
            .copied()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .collect();
        let mut coordinates = String::new();
        for point in thin(&finite, MAX_POLYLINE_POINTS) {
            let (px, py) = self.pixel(point);
            let _ = write!(coordinates, "{px:.1},{py:.1} ");
        }
        let _ = writeln!(
            self.body,
            "<polyline fill=\"none\" stroke=\"{}\"{} points=\"{}\"/>",
            stroke.colour,
            stroke_attributes(stroke.reference),
            coordinates.trim_end()
        );
        self.legend
            .push(LegendEntry::Line(legend.to_string(), stroke));
    }

    /// A marker at `point` whose hover text is `tooltip`.
    pub fn marker(&mut self, point: (f64, f64), shape: Shape, colour: &'static str, tooltip: &str) {
        let (px, py) = self.pixel(point);
        let title = format!("<title>{}</title>", escape(tooltip));
        self.body
            .push_str(&marker_element(px, py, shape, colour, &title));
        self.body.push('\n');
    }

    /// A legend row for markers drawn with [`Chart::marker`].
    pub fn marker_legend(&mut self, label: &str, shape: Shape, colour: &'static str) {
        self.legend
            .push(LegendEntry::Marker(label.to_string(), shape, colour));
    }

    /// The finished `<svg>` element.
    pub fn render(&self) -> String {
        let mut out = format!(
            "<svg width=\"{CHART_WIDTH}\" height=\"{CHART_HEIGHT}\" viewBox=\"0 0 {CHART_WIDTH} {CHART_HEIGHT}\" font-size=\"{FONT_SIZE}\" role=\"img\">\n"
        );
        out.push_str(&self.axes());
        out.push_str(&self.body);
        out.push_str(&self.legend_column());
        out.push_str("</svg>\n");
        out
    }

    fn axes(&self) -> String {
        let (left, right, top, bottom) = plot_area();
        let mut out = format!(
            "<rect x=\"{left}\" y=\"{top}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#888\"/>\n",
            right - left,
            bottom - top
        );
        let x_ticks = nice_ticks(self.x.domain);
        let decimals = tick_decimals(&x_ticks);
        for tick in &x_ticks {
            let px = self.x.map(*tick);
            let _ = writeln!(
                out,
                "<line x1=\"{px:.1}\" y1=\"{bottom}\" x2=\"{px:.1}\" y2=\"{}\" stroke=\"#888\"/><text x=\"{px:.1}\" y=\"{}\" text-anchor=\"middle\">{}</text>",
                bottom + TICK_LENGTH,
                bottom + TICK_LENGTH + FONT_SIZE + 2.0,
                format_tick(*tick, decimals)
            );
        }
        out.push_str(&self.y_ticks());
        let _ = writeln!(
            out,
            "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{}</text>",
            (left + right) / 2.0,
            CHART_HEIGHT - FONT_SIZE / 2.0,
            escape(&self.x_label)
        );
        let (label_x, label_y) = (FONT_SIZE, (top + bottom) / 2.0);
        let _ = writeln!(
            out,
            "<text x=\"{label_x}\" y=\"{label_y}\" text-anchor=\"middle\" transform=\"rotate(-90 {label_x} {label_y})\">{}</text>",
            escape(&self.y_label)
        );
        out
    }

    fn y_ticks(&self) -> String {
        let (left, ..) = plot_area();
        let ticks: Vec<(f64, String)> = match &self.y_categories {
            Some(lanes) => lanes
                .iter()
                .enumerate()
                .map(|(k, name)| (k as f64, escape(name)))
                .collect(),
            None => {
                let ticks = nice_ticks(self.y.domain);
                let decimals = tick_decimals(&ticks);
                ticks
                    .into_iter()
                    .map(|t| (t, format_tick(t, decimals)))
                    .collect()
            }
        };
        let mut out = String::new();
        for (value, label) in ticks {
            let py = self.y.map(value);
            let _ = writeln!(
                out,
                "<line x1=\"{}\" y1=\"{py:.1}\" x2=\"{left}\" y2=\"{py:.1}\" stroke=\"#888\"/><text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{label}</text>",
                left - TICK_LENGTH,
                left - TICK_LENGTH - 2.0,
                py + FONT_SIZE / 3.0
            );
        }
        out
    }

    fn legend_column(&self) -> String {
        let x = CHART_WIDTH - LEGEND_WIDTH + 15.0;
        let mut out = String::new();
        for (row, entry) in self.legend.iter().enumerate() {
            let y = MARGIN_TOP + LEGEND_ROW_HEIGHT * (row as f64 + 0.5);
            let (swatch, label) = match entry {
                LegendEntry::Line(label, stroke) => (
                    format!(
                        "<line x1=\"{x}\" y1=\"{y}\" x2=\"{}\" y2=\"{y}\" stroke=\"{}\"{}/>",
                        x + LEGEND_SWATCH_LENGTH,
                        stroke.colour,
                        stroke_attributes(stroke.reference)
                    ),
                    label,
                ),
                LegendEntry::Marker(label, shape, colour) => (
                    marker_element(x + LEGEND_SWATCH_LENGTH / 2.0, y, *shape, colour, ""),
                    label,
                ),
            };
            let _ = writeln!(
                out,
                "{swatch}<text x=\"{}\" y=\"{:.1}\">{}</text>",
                x + LEGEND_SWATCH_LENGTH + 6.0,
                y + FONT_SIZE / 3.0,
                escape(label)
            );
        }
        out
    }
}

fn stroke_attributes(reference: bool) -> String {
    if reference {
        format!(
            " stroke-width=\"{REFERENCE_LINE_WIDTH}\" stroke-opacity=\"{REFERENCE_OPACITY}\" stroke-dasharray=\"{DASH_PATTERN}\""
        )
    } else {
        format!(" stroke-width=\"{LINE_WIDTH}\"")
    }
}

fn marker_element(px: f64, py: f64, shape: Shape, colour: &str, title: &str) -> String {
    match shape {
        Shape::Circle => format!(
            "<circle cx=\"{px:.1}\" cy=\"{py:.1}\" r=\"{MARKER_RADIUS}\" fill=\"{colour}\" stroke=\"#333\">{title}</circle>"
        ),
        Shape::Square => format!(
            "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{}\" height=\"{}\" fill=\"{colour}\" stroke=\"#333\">{title}</rect>",
            px - MARKER_RADIUS,
            py - MARKER_RADIUS,
            2.0 * MARKER_RADIUS,
            2.0 * MARKER_RADIUS
        ),
    }
}

fn format_tick(value: f64, decimals: usize) -> String {
    // -0.0 prints as "-0": a tick at zero should read "0".
    let value = if value == 0.0 { 0.0 } else { value };
    format!("{value:.decimals$}")
}

/// At most `limit` points taken evenly from `points`, always keeping the first and the last.
fn thin(points: &[(f64, f64)], limit: usize) -> Vec<(f64, f64)> {
    if points.len() <= limit || limit < 2 {
        return points.to_vec();
    }
    let last = points.len() - 1;
    (0..limit).map(|k| points[k * last / (limit - 1)]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_fall_on_round_values() {
        let unit = nice_ticks(Range { min: 0.0, max: 1.0 });
        let labels: Vec<String> = unit
            .iter()
            .map(|t| format_tick(*t, tick_decimals(&unit)))
            .collect();
        assert_eq!(labels, ["0.0", "0.2", "0.4", "0.6", "0.8", "1.0"]);
        let ticks = nice_ticks(Range {
            min: -3.0,
            max: 27.0,
        });
        assert_eq!(ticks, [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]);
        assert_eq!(tick_decimals(&[0.0, 0.05]), 2);
        assert_eq!(format_tick(-0.0, 1), "0.0");
    }

    #[test]
    fn thinning_keeps_both_ends() {
        let points: Vec<(f64, f64)> = (0..10).map(|i| (i as f64, 0.0)).collect();
        let thinned = thin(&points, 4);
        assert_eq!(thinned.len(), 4);
        assert_eq!(thinned[0], (0.0, 0.0));
        assert_eq!(thinned[3], (9.0, 0.0));
        assert_eq!(thin(&points, 20).len(), 10);
    }

    #[test]
    fn equal_aspect_gives_both_axes_one_scale() {
        let chart = Chart::equal_aspect(
            Range { min: 0.0, max: 4.0 },
            Range { min: 0.0, max: 1.0 },
            "x",
            "y",
        );
        let x_per_pixel = chart.x.domain.span() / (chart.x.end - chart.x.start);
        let y_per_pixel = chart.y.domain.span() / (chart.y.start - chart.y.end);
        assert!((x_per_pixel - y_per_pixel).abs() < 1e-12);
    }

    #[test]
    fn chart_escapes_labels() {
        let mut chart = Chart::new(
            Range { min: 0.0, max: 1.0 },
            Range { min: 0.0, max: 1.0 },
            "t <s>",
            "e",
        );
        chart.line(
            &[(0.0, 0.0), (1.0, 1.0)],
            Stroke {
                colour: agent_colour(0),
                reference: true,
            },
            "a & b",
        );
        let svg = chart.render();
        assert!(
            svg.contains("t &lt;s&gt;") && svg.contains("a &amp; b"),
            "{svg}"
        );
        assert!(svg.contains("stroke-dasharray"));
    }
}
