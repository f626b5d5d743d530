//! HTML building blocks of the report: escaping, the document shell, tables and notes. Every
//! piece of text that comes from a run's files goes through [`escape`]; the report is opened from
//! disk and must not run or fetch anything a file name or a rejection message happens to contain.

use std::fmt::Write;

/// Escapes text for HTML element content and double- or single-quoted attribute values (inline
/// SVG inside HTML follows the same rules).
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// Styles of the report, inline so the file opens offline and stays one file.
const STYLE: &str = "
body { font-family: sans-serif; margin: 2em auto; max-width: 1100px; padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
td.number { text-align: right; font-variant-numeric: tabular-nums; }
p.note { color: #8a4b00; background: #fff6e5; border-left: 4px solid #f0a030; padding: 0.3em 0.6em; }
figure { display: inline-block; margin: 0.5em; } figure img { max-width: 100%; }
figcaption { font-size: 0.9em; color: #555; }
svg { background: #fff; } svg text { font-family: sans-serif; }
pre { background: #f6f6f6; padding: 0.5em; overflow-x: auto; }
";

/// The whole document: a title and the sections' HTML, in order.
pub fn document(title: &str, sections: &[String]) -> String {
    let mut out = String::new();
    out.push_str("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n");
    let _ = writeln!(out, "<title>{}</title>", escape(title));
    let _ = writeln!(out, "<style>{STYLE}</style>\n</head>\n<body>");
    let _ = writeln!(out, "<h1>{}</h1>", escape(title));
    for section in sections {
        out.push_str(section);
        out.push('\n');
    }
    out.push_str("</body>\n</html>\n");
    out
}

/// A section: a heading (also its anchor id) and its body HTML.
pub fn section(id: &str, heading: &str, body: &str) -> String {
    format!(
        "<section id=\"{}\">\n<h2>{}</h2>\n{body}</section>",
        escape(id),
        escape(heading)
    )
}

/// A highlighted line saying what is missing or why a part could not be drawn.
pub fn note(text: &str) -> String {
    format!("<p class=\"note\">{}</p>\n", escape(text))
}

/// A plain paragraph.
pub fn paragraph(text: &str) -> String {
    format!("<p>{}</p>\n", escape(text))
}

/// One table cell: text, and whether it holds a number (right-aligned).
pub struct Cell {
    pub text: String,
    pub numeric: bool,
}

impl Cell {
    pub fn text(text: impl Into<String>) -> Self {
        Self {
            text: text.into(),
            numeric: false,
        }
    }

    pub fn number(text: impl Into<String>) -> Self {
        Self {
            text: text.into(),
            numeric: true,
        }
    }
}

/// A table with a header row; cell text is escaped.
pub fn table(header: &[&str], rows: &[Vec<Cell>]) -> String {
    let mut out = String::from("<table>\n<tr>");
    for name in header {
        let _ = write!(out, "<th>{}</th>", escape(name));
    }
    out.push_str("</tr>\n");
    for row in rows {
        out.push_str("<tr>");
        for cell in row {
            let class = if cell.numeric {
                " class=\"number\""
            } else {
                ""
            };
            let _ = write!(out, "<td{class}>{}</td>", escape(&cell.text));
        }
        out.push_str("</tr>\n");
    }
    out.push_str("</table>\n");
    out
}

/// Collapsible block, closed by default: long detail (every event, the run's config) that
/// would otherwise push the charts apart.
pub fn details(summary: &str, body: &str) -> String {
    format!(
        "<details>\n<summary>{}</summary>\n{body}</details>\n",
        escape(summary)
    )
}

/// Preformatted text (a config file), escaped.
pub fn preformatted(text: &str) -> String {
    format!("<pre>{}</pre>\n", escape(text))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escape_covers_markup_and_quotes() {
        assert_eq!(
            escape(r#"<script>alert("x & 'y'")</script>"#),
            "&lt;script&gt;alert(&quot;x &amp; &#39;y&#39;&quot;)&lt;/script&gt;"
        );
        assert_eq!(escape("plain 1.5 cm"), "plain 1.5 cm");
    }

    #[test]
    fn table_escapes_cells_and_marks_numbers() {
        let html = table(
            &["Metric", "Value"],
            &[vec![Cell::text("a<b"), Cell::number("1.00")]],
        );
        assert!(html.contains("<td>a&lt;b</td>"), "{html}");
        assert!(html.contains("<td class=\"number\">1.00</td>"), "{html}");
    }
}
