//! Reports people read: one document ([`Report`]: headings, paragraphs, tables, pictures) written
//! twice — as Markdown for terminals (`report.md`, pictures linked) and as one self-contained HTML
//! page for browsers (`report.html`, pictures embedded as base64 `data:` URIs, so the file can be
//! mailed or moved on its own).
//!
//! The HTML is written by hand (an escape function and a style sheet, about 100 lines): the page
//! is static, has no script, and a template engine would add a proc-macro dependency for one page.
//! Numbers are formatted by [`fmt`] before they reach a report.

pub mod demo;
pub mod evaluate;
pub mod fit;
pub mod fmt;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use base64::Engine as _;

/// Why a report could not be written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReportError {
    /// A picture the report shows could not be read.
    #[error("reading picture {path}: {source}")]
    Picture {
        /// The picture.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The report file could not be written.
    #[error("writing {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// One picture with its caption.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    /// The image file (PNG, JPEG or SVG).
    pub path: PathBuf,
    /// What it shows.
    pub caption: String,
}

/// A table of already formatted cells; columns whose cells all look numeric are right-aligned.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Table {
    /// Column titles.
    pub header: Vec<String>,
    /// Rows, each as long as the header.
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these column titles and no rows.
    pub fn new<S: Into<String>>(header: impl IntoIterator<Item = S>) -> Table {
        Table {
            header: header.into_iter().map(Into::into).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row (padded or cut to the header's length).
    pub fn row<S: Into<String>>(&mut self, cells: impl IntoIterator<Item = S>) -> &mut Table {
        let mut r: Vec<String> = cells.into_iter().map(Into::into).collect();
        r.resize(self.header.len(), String::new());
        self.rows.push(r);
        self
    }

    /// Whether column `c` holds numbers (every non-empty cell starts with a digit, a sign or a
    /// point, or is the missing-value dash).
    fn numeric(&self, c: usize) -> bool {
        let mut any = false;
        for r in &self.rows {
            let cell = r[c].trim();
            if cell.is_empty() || cell == fmt::MISSING {
                continue;
            }
            any = true;
            let first = cell.chars().next().unwrap_or(' ');
            if !(first.is_ascii_digit() || "+-−.".contains(first)) {
                return false;
            }
        }
        any
    }
}

/// One block of a report.
#[derive(Clone, Debug, PartialEq)]
pub enum Block {
    /// A section heading.
    Heading(String),
    /// A paragraph; text between backticks is shown as code.
    Paragraph(String),
    /// A table with an optional caption under it.
    Table(Table, Option<String>),
    /// Pictures side by side (wrapping on narrow screens).
    Figures(Vec<Figure>),
}

/// A report: a title and blocks, written as Markdown and as self-contained HTML.
#[derive(Clone, Debug, PartialEq)]
pub struct Report {
    /// Page title.
    pub title: String,
    /// Content, in order.
    pub blocks: Vec<Block>,
}

impl Report {
    /// An empty report.
    pub fn new(title: impl Into<String>) -> Report {
        Report {
            title: title.into(),
            blocks: Vec::new(),
        }
    }

    /// Adds a section heading.
    pub fn heading(&mut self, text: impl Into<String>) -> &mut Report {
        self.blocks.push(Block::Heading(text.into()));
        self
    }

    /// Adds a paragraph.
    pub fn paragraph(&mut self, text: impl Into<String>) -> &mut Report {
        self.blocks.push(Block::Paragraph(text.into()));
        self
    }

    /// Adds a table with an optional caption.
    pub fn table(&mut self, table: Table, caption: Option<String>) -> &mut Report {
        self.blocks.push(Block::Table(table, caption));
        self
    }

    /// Adds pictures shown side by side.
    pub fn figures(&mut self, figures: Vec<Figure>) -> &mut Report {
        if !figures.is_empty() {
            self.blocks.push(Block::Figures(figures));
        }
        self
    }

    /// Every picture the report shows.
    pub fn pictures(&self) -> impl Iterator<Item = &Figure> {
        self.blocks.iter().flat_map(|b| match b {
            Block::Figures(f) => f.as_slice(),
            _ => &[],
        })
    }

    /// The report as Markdown; pictures are linked relative to `dir` (the folder the Markdown
    /// file is written to) when they are inside it.
    pub fn to_markdown(&self, dir: &Path) -> String {
        let mut s = format!("# {}\n\n", self.title);
        for b in &self.blocks {
            match b {
                Block::Heading(h) => {
                    let _ = writeln!(s, "## {h}\n");
                }
                Block::Paragraph(p) => {
                    let _ = writeln!(s, "{p}\n");
                }
                Block::Table(t, caption) => {
                    let cell = |c: &str| c.replace('|', "\\|");
                    let _ = writeln!(
                        s,
                        "| {} |",
                        t.header
                            .iter()
                            .map(|h| cell(h))
                            .collect::<Vec<_>>()
                            .join(" | ")
                    );
                    let align: Vec<&str> = (0..t.header.len())
                        .map(|c| if t.numeric(c) { "---:" } else { "---" })
                        .collect();
                    let _ = writeln!(s, "|{}|", align.join("|"));
                    for r in &t.rows {
                        let _ = writeln!(
                            s,
                            "| {} |",
                            r.iter().map(|c| cell(c)).collect::<Vec<_>>().join(" | ")
                        );
                    }
                    s.push('\n');
                    if let Some(c) = caption {
                        let _ = writeln!(s, "{c}\n");
                    }
                }
                Block::Figures(figs) => {
                    for f in figs {
                        let rel = f.path.strip_prefix(dir).unwrap_or(&f.path);
                        let _ = writeln!(s, "![{}]({})\n", f.caption, rel.display());
                    }
                }
            }
        }
        s
    }

    /// The report as one HTML page with every picture embedded as a base64 `data:` URI.
    pub fn to_html(&self) -> Result<String, ReportError> {
        let mut s = String::new();
        let _ = write!(
            s,
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
             <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
             <title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<main>\n<h1>{}</h1>\n",
            escape(&self.title),
            escape(&self.title)
        );
        for b in &self.blocks {
            match b {
                Block::Heading(h) => {
                    let _ = writeln!(s, "<h2>{}</h2>", inline(h));
                }
                Block::Paragraph(p) => {
                    let _ = writeln!(s, "<p>{}</p>", inline(p));
                }
                Block::Table(t, caption) => {
                    s.push_str("<table>\n");
                    if let Some(c) = caption {
                        let _ = writeln!(s, "<caption>{}</caption>", inline(c));
                    }
                    let num: Vec<bool> = (0..t.header.len()).map(|c| t.numeric(c)).collect();
                    s.push_str("<thead><tr>");
                    for (c, h) in t.header.iter().enumerate() {
                        let _ = write!(s, "<th{}>{}</th>", class(num[c]), inline(h));
                    }
                    s.push_str("</tr></thead>\n<tbody>\n");
                    for r in &t.rows {
                        s.push_str("<tr>");
                        for (c, v) in r.iter().enumerate() {
                            let _ = write!(s, "<td{}>{}</td>", class(num[c]), inline(v));
                        }
                        s.push_str("</tr>\n");
                    }
                    s.push_str("</tbody>\n</table>\n");
                }
                Block::Figures(figs) => {
                    s.push_str("<div class=\"figures\">\n");
                    for f in figs {
                        let data =
                            std::fs::read(&f.path).map_err(|source| ReportError::Picture {
                                path: f.path.clone(),
                                source,
                            })?;
                        let name = f
                            .path
                            .file_name()
                            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
                        let _ = writeln!(
                            s,
                            "<figure><img src=\"data:{};base64,{}\" alt=\"{}\">\
                             <figcaption>{} <span class=\"file\">{}</span></figcaption></figure>",
                            mime(&f.path),
                            base64::engine::general_purpose::STANDARD.encode(&data),
                            escape(&f.caption),
                            inline(&f.caption),
                            escape(&name)
                        );
                    }
                    s.push_str("</div>\n");
                }
            }
        }
        s.push_str("</main>\n</body>\n</html>\n");
        Ok(s)
    }

    /// Writes `report.md` (pictures linked) and `report.html` (pictures embedded) into `dir`
    /// under `stem` (`report` → `report.md`, `report.html`); returns both paths. The Markdown is
    /// written first, so a picture that cannot be read loses only the HTML.
    pub fn write(&self, dir: &Path, stem: &str) -> Result<[PathBuf; 2], ReportError> {
        let md = dir.join(format!("{stem}.md"));
        let html = dir.join(format!("{stem}.html"));
        write_file(&md, &self.to_markdown(dir))?;
        write_file(&html, &self.to_html()?)?;
        Ok([md, html])
    }
}

fn write_file(path: &Path, text: &str) -> Result<(), ReportError> {
    std::fs::write(path, text).map_err(|source| ReportError::Write {
        path: path.to_path_buf(),
        source,
    })
}

fn class(numeric: bool) -> &'static str {
    if numeric { " class=\"num\"" } else { "" }
}

fn mime(path: &Path) -> &'static str {
    match path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .as_deref()
    {
        Some("jpg" | "jpeg") => "image/jpeg",
        Some("svg") => "image/svg+xml",
        Some("gif") => "image/gif",
        _ => "image/png",
    }
}

/// HTML text escaping (the five characters that matter in text and attribute values).
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Escaped text with `code` spans for text between backticks (Markdown's inline code).
fn inline(s: &str) -> String {
    let mut out = String::new();
    for (k, part) in s.split('`').enumerate() {
        if k % 2 == 1 {
            let _ = write!(out, "<code>{}</code>", escape(part));
        } else {
            out.push_str(&escape(part));
        }
    }
    out
}

const STYLE: &str = "\
body{margin:0;background:#f6f6f4;color:#1d1d1f;font:15px/1.5 system-ui,-apple-system,'Segoe UI',sans-serif}\
main{max-width:1180px;margin:0 auto;padding:24px 28px 60px;background:#fff;min-height:100vh}\
h1{font-size:26px;margin:8px 0 18px}h2{font-size:19px;margin:34px 0 10px;border-bottom:1px solid #ddd;padding-bottom:4px}\
code{font:13px ui-monospace,Menlo,Consolas,monospace;background:#f0f0ee;padding:1px 4px;border-radius:3px}\
table{border-collapse:collapse;margin:10px 0 6px;font-size:14px}\
caption{caption-side:bottom;text-align:left;color:#555;font-size:13px;padding-top:6px;max-width:1100px}\
th,td{padding:4px 10px;border-bottom:1px solid #e3e3e0;text-align:left;vertical-align:top}\
th{background:#f0f0ee;font-weight:600}tbody tr:nth-child(even){background:#fafaf8}\
.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}\
.figures{display:grid;grid-template-columns:repeat(auto-fit,minmax(260px,1fr));gap:14px;margin:12px 0;align-items:start}\
figure{margin:0}figure img{display:block;max-width:100%;height:auto;border:1px solid #ddd;background:#222}\
figcaption{font-size:13px;color:#444;margin-top:4px}.file{color:#888;font-family:ui-monospace,monospace;font-size:12px}";

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(dir: &Path) -> Report {
        let png = dir.join("pic.png");
        image::RgbImage::from_fn(8, 4, |x, y| image::Rgb([(x * 30) as u8, (y * 60) as u8, 9]))
            .save(&png)
            .unwrap();
        let mut r = Report::new("A <test> & more");
        r.heading("Numbers").paragraph("See `model.ply` for 2 < 3.");
        let mut t = Table::new(["what", "log E", "time"]);
        t.row(["fit", "0.00912", "1.2 s"])
            .row(["truth", "–", "0.3 s"]);
        r.table(t, Some("Eq. 8".into()));
        r.figures(vec![Figure {
            path: png,
            caption: "a picture".into(),
        }]);
        r
    }

    #[test]
    fn html_is_self_contained_escaped_and_right_aligns_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let html = sample(dir.path()).to_html().unwrap();
        assert!(
            html.contains("<title>A &lt;test&gt; &amp; more</title>"),
            "{html}"
        );
        assert!(
            html.contains("<code>model.ply</code> for 2 &lt; 3."),
            "{html}"
        );
        assert!(
            html.contains("src=\"data:image/png;base64,iVBORw0KGgo"),
            "{html}"
        );
        assert!(
            !html.contains(dir.path().to_str().unwrap()),
            "no file paths: {html}"
        );
        assert!(html.contains("<td class=\"num\">0.00912</td>"), "{html}");
        assert!(html.contains("<td>fit</td>"), "{html}");
        assert!(!html.contains("<script"), "{html}");
    }

    #[test]
    fn markdown_links_pictures_relative_to_its_folder() {
        let dir = tempfile::tempdir().unwrap();
        let md = sample(dir.path()).to_markdown(dir.path());
        assert!(md.contains("![a picture](pic.png)"), "{md}");
        assert!(
            md.contains("| what | log E | time |\n|---|---:|---:|"),
            "{md}"
        );
    }

    #[test]
    fn a_missing_picture_is_an_error_after_the_markdown_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = Report::new("x");
        r.figures(vec![Figure {
            path: dir.path().join("gone.png"),
            caption: "gone".into(),
        }]);
        let e = r.write(dir.path(), "report").unwrap_err();
        assert!(e.to_string().contains("gone.png"), "{e}");
        assert!(dir.path().join("report.md").exists());
    }
}
