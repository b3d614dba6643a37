//! `subsurf bench fit-scale`: how `subsurf fit` grows with frames, vertices and image size
//! (the size axis: a camera-resolution fit against its one decode pass). For every (size, vertices, frames) it simulates a sphere scan with `subsurf
//! simulate`, fits it with `subsurf fit` in a fresh process (so each run's peak RSS is its own),
//! reads the stage timings and peak memory from the fit report, deletes the dataset before the next
//! one is written (the disk holds one dataset at a time); then the table, the growth ratios and a
//! PNG (time and peak RSS against frames).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use crate::progress::Progress;

/// Why the benchmark stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitScaleError {
    /// A file, folder or child process failed; `what` says which.
    #[error("{what}")]
    Io {
        /// What was being done.
        what: String,
        /// Why it failed.
        #[source]
        source: std::io::Error,
    },
    /// A fit report or an earlier run's JSON could not be parsed.
    #[error("{what}")]
    Json {
        /// What was being parsed.
        what: String,
        /// Why it failed.
        #[source]
        source: serde_json::Error,
    },
    /// `subsurf simulate` or `subsurf fit` failed (its command line and output).
    #[error("{0}")]
    Child(String),
    /// The settings do not allow the benchmark.
    #[error("{0}")]
    Invalid(String),
    /// The plot could not be drawn.
    #[error("{0}")]
    Draw(String),
}

/// An I/O error with what was being done.
fn io(what: String) -> impl FnOnce(std::io::Error) -> FitScaleError {
    move |source| FitScaleError::Io { what, source }
}

/// The grid to measure (the command's flags).
#[derive(Debug, Clone)]
pub struct FitScaleSettings {
    /// Approximate vertex counts of the simulated sphere.
    pub vertices: Vec<usize>,
    /// Frame counts; each is rounded down to whole turntable angles of `raster × raster` laser
    /// positions.
    pub frames: Vec<usize>,
    /// Image widths and heights (px).
    pub size: Vec<u32>,
    /// Laser raster per axis and turntable angle.
    pub raster: usize,
    /// Scratch directory for the datasets, models and reports.
    pub dir: PathBuf,
    /// Extra arguments passed to `subsurf fit`.
    pub fit_args: Vec<String>,
}

/// One measured (vertices, frames) point.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Row {
    /// Image width and height (px).
    pub size: u32,
    /// Vertices of the simulated sphere.
    pub vertices: usize,
    /// Frames of the scan.
    pub frames: usize,
    /// Frames registered by the fit.
    pub registered: usize,
    /// Frames fitted.
    pub fits: usize,
    /// Size of the dataset on disk (MB).
    pub dataset_mb: f64,
    /// Wall time of `subsurf simulate` (s).
    pub simulate_s: f64,
    /// Wall time of the whole `subsurf fit` process (loading, stages, writing the model).
    pub wall_s: f64,
    /// The pipeline's own stage timings (`fit-report.json`).
    pub stages: BTreeMap<String, f64>,
    /// `VmHWM` of the fit process after everything was written.
    pub peak_rss_mib: f64,
    /// Frame files read by the fit (each frame once: `frames.reads.total`).
    pub frames_read: usize,
}

impl Row {
    /// The stages over the frames' samples: the decode pass (extract), fit, lattice, error.
    pub fn frame_stages_s(&self) -> f64 {
        ["registration", "extract", "fit", "lattice", "error"]
            .iter()
            .filter_map(|s| self.stages.get(*s))
            .sum()
    }
    /// A stage's seconds from the fit report (NaN when it has none).
    pub fn stage(&self, name: &str) -> f64 {
        self.stages.get(name).copied().unwrap_or(f64::NAN)
    }
}

fn dir_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            match e.metadata() {
                Ok(m) if m.is_dir() => stack.push(e.path()),
                Ok(m) => total += m.len(),
                Err(_) => {}
            }
        }
    }
    total
}

fn run_child(cmd: &mut Command, what: &str) -> Result<String, FitScaleError> {
    let out = cmd.output().map_err(|source| FitScaleError::Io {
        what: format!("starting {what}: {cmd:?}"),
        source,
    })?;
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        return Err(FitScaleError::Child(format!(
            "{what} failed ({}): {cmd:?}\n{stdout}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    Ok(stdout)
}

fn measure(
    b: &FitScaleSettings,
    exe: &Path,
    size: u32,
    vertices: usize,
    frames: usize,
    bar: &dyn Progress,
    out: &mut dyn FnMut(&str),
) -> Result<Row, FitScaleError> {
    let per_angle = b.raster.max(1) * b.raster.max(1);
    let angles = (frames / per_angle).max(1);
    let data = b.dir.join(format!("scan-s{size}-v{vertices}-f{frames}"));
    let model = b
        .dir
        .join(format!("model-s{size}-v{vertices}-f{frames}.ply"));
    let report = b
        .dir
        .join(format!("report-s{size}-v{vertices}-f{frames}.json"));
    if data.exists() {
        std::fs::remove_dir_all(&data).map_err(io(format!("removing {}", data.display())))?;
    }
    bar.set_message(&format!(
        "simulating {frames} frames of {size}x{size}, {vertices} vertices"
    ));
    let t = Instant::now();
    let sim_out = run_child(
        Command::new(exe)
            .arg("simulate")
            .arg("--out")
            .arg(&data)
            .args(["--object", "sphere", "--cameras", "1", "--seed", "3"])
            .args(["--vertices", &vertices.to_string()])
            .args(["--size", &size.to_string()])
            .args(["--angles", &angles.to_string()])
            .args(["--raster", &b.raster.to_string()]),
        "subsurf simulate",
    )?;
    let simulate_s = t.elapsed().as_secs_f64();
    bar.inc(1);
    out(&format!("  {sim_out}"));
    bar.set_message(&format!(
        "fitting {frames} frames of {size}x{size}, {vertices} vertices"
    ));
    let dataset_mb = dir_bytes(&data) as f64 / 1e6;
    let t = Instant::now();
    let fit_out = run_child(
        Command::new(exe)
            .arg("fit")
            .arg("--scan")
            .arg(&data)
            .arg("--out")
            .arg(&model)
            .arg("--report")
            .arg(&report)
            .arg("--no-pictures")
            .args(&b.fit_args),
        "subsurf fit",
    );
    let wall_s = t.elapsed().as_secs_f64();
    // The dataset goes before anything else can fail: the disk is shared.
    std::fs::remove_dir_all(&data).map_err(io(format!("removing {}", data.display())))?;
    let fit_out = fit_out?;
    bar.inc(1);
    for line in fit_out.lines() {
        out(&format!("    {line}\n"));
    }
    let text =
        std::fs::read_to_string(&report).map_err(io(format!("reading {}", report.display())))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|source| FitScaleError::Json {
            what: format!("parsing {}", report.display()),
            source,
        })?;
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let count = |v: &serde_json::Value| v.as_u64().unwrap_or(0) as usize;
    let stages: BTreeMap<String, f64> = json["stage_seconds"]
        .as_object()
        .map(|m| m.iter().map(|(k, v)| (k.clone(), num(v))).collect())
        .unwrap_or_default();
    let peak = json
        .get("process_peak_rss_mib")
        .or_else(|| json.get("peak_rss_mib"))
        .map_or(f64::NAN, num);
    let _ = std::fs::remove_file(&model);
    Ok(Row {
        size,
        frames_read: count(&json["frames"]["reads"]["total"]),
        vertices: count(&json["vertices"]),
        frames: count(&json["frames"]["total"]),
        registered: count(&json["frames"]["registered"]),
        fits: count(&json["frames"]["fitted"]),
        dataset_mb,
        simulate_s,
        wall_s,
        stages,
        peak_rss_mib: peak,
    })
}

/// Measures every (size, vertices, frames) of `b` with the `subsurf` binary `exe`, in that
/// order, in `b.dir` (which must exist). `bar` counts the child processes (two a point) and names the running one; `out`
/// receives the text for stdout (newlines included): each point's heading, the children's
/// output and its figures.
pub fn measure_grid(
    b: &FitScaleSettings,
    exe: &Path,
    bar: &dyn Progress,
    out: &mut dyn FnMut(&str),
) -> Result<Vec<Row>, FitScaleError> {
    let total = b.size.len() * b.vertices.len() * b.frames.len();
    let mut rows = Vec::with_capacity(total);
    for &px in &b.size {
        for &v in &b.vertices {
            for &f in &b.frames {
                out(&format!(
                    "[{}/{total}] {px}x{px} px, {v} vertices, {f} frames\n",
                    rows.len() + 1
                ));
                let row = measure(b, exe, px, v, f, bar, out)?;
                out(&format!(
                    "  simulate {:.1} s, dataset {:.0} MB; fit wall {:.2} s (extract {:.2} s), peak RSS {:.0} MiB\n",
                    row.simulate_s,
                    row.dataset_mb,
                    row.wall_s,
                    row.stage("extract"),
                    row.peak_rss_mib
                ));
                rows.push(row);
            }
        }
    }
    Ok(rows)
}

/// The rows of an earlier run's `--json`.
pub fn read_rows(json: &Path) -> Result<Vec<Row>, FitScaleError> {
    serde_json::from_slice(&std::fs::read(json).map_err(io(format!("reading {}", json.display())))?)
        .map_err(|source| FitScaleError::Json {
            what: format!("parsing {}", json.display()),
            source,
        })
}

/// The rows as a Markdown table (BENCHMARKS.md), after an empty line.
pub fn table(rows: &[Row]) -> String {
    let mut t = String::from("\n");
    t.push_str(
        "| size | vertices | frames | registered | fits | dataset MB | frames read | extract s | ms / frame decoded | fit s | lattice s | error s | interpolate s | fit wall s | fit wall / extract | peak RSS MiB |\n",
    );
    t.push_str(
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in rows {
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.0} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.0} |\n",
            r.size,
            r.vertices,
            r.frames,
            r.registered,
            r.fits,
            r.dataset_mb,
            r.frames_read,
            r.stage("extract"),
            1e3 * r.stage("extract") / r.frames.max(1) as f64,
            r.stage("fit"),
            r.stage("lattice"),
            r.stage("error"),
            r.stage("interpolate"),
            r.wall_s,
            r.wall_s / r.stage("extract"),
            r.peak_rss_mib
        ));
    }
    t
}

/// Ratios between consecutive rows that double one quantity and keep the other.
pub fn growth(rows: &[Row]) -> String {
    let mut t = String::from("\ngrowth (later / earlier):\n");
    for (i, a) in rows.iter().enumerate() {
        for b in &rows[i + 1..] {
            let same_size = a.size == b.size;
            let frames_doubled = same_size && a.vertices == b.vertices && b.frames == 2 * a.frames;
            let vertices_doubled = same_size
                && a.frames == b.frames
                && (b.vertices as f64 / a.vertices.max(1) as f64 - 2.0).abs() < 0.1;
            let size_doubled =
                a.vertices == b.vertices && a.frames == b.frames && b.size == 2 * a.size;
            let what = if frames_doubled {
                format!(
                    "frames {} -> {} at {} vertices, {} px",
                    a.frames, b.frames, a.vertices, a.size
                )
            } else if vertices_doubled {
                format!(
                    "vertices {} -> {} at {} frames, {} px",
                    a.vertices, b.vertices, a.frames, a.size
                )
            } else if size_doubled {
                format!(
                    "size {} -> {} px (4x the pixels) at {} vertices, {} frames",
                    a.size, b.size, a.vertices, a.frames
                )
            } else {
                continue;
            };
            t.push_str(&format!(
                "  {what}: extract x{:.2}, fit x{:.2}, error x{:.2}, frame stages x{:.2}, \
                 interpolate x{:.2}, wall x{:.2}, peak RSS x{:.2}\n",
                b.stage("extract") / a.stage("extract"),
                b.stage("fit") / a.stage("fit"),
                b.stage("error") / a.stage("error"),
                b.frame_stages_s() / a.frame_stages_s(),
                b.stage("interpolate") / a.stage("interpolate"),
                b.wall_s / a.wall_s,
                b.peak_rss_mib / a.peak_rss_mib
            ));
        }
    }
    t
}

/// A series' size label: none when the series are by image size (size is the x axis).
fn px_label(px: u32) -> String {
    if px == 0 {
        String::new()
    } else {
        format!("{px} px, ")
    }
}

/// Two panels: seconds against frames or image size (fit wall time, the frame stages, the
/// decode pass) and peak RSS, one line per series, both axes from zero so linearity reads
/// directly.
pub fn plot(path: &Path, rows: &[Row]) -> Result<(), FitScaleError> {
    use plotters::coord::Shift;
    use plotters::coord::types::RangedCoordf64;
    use plotters::prelude::*;
    /// One panel's axes: x from 0 to `xmax` (two decimals), y from 0 to `y.0` named `y.1`.
    fn axes<'a, 'b>(
        area: &'a DrawingArea<BitMapBackend<'b>, Shift>,
        caption: String,
        x_desc: &str,
        xmax: f64,
        y: (f64, &str),
    ) -> Result<
        ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
        String,
    > {
        let mut chart = ChartBuilder::on(area)
            .caption(caption, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..xmax, 0.0..y.0)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .x_label_formatter(&|v| format!("{v:.2}"))
            .y_desc(y.1)
            .draw()
            .map_err(|e| e.to_string())?;
        Ok(chart)
    }
    crate::plot::register_font();
    let err =
        |e: &dyn std::fmt::Display| FitScaleError::Draw(format!("drawing {}: {e}", path.display()));
    let root = BitMapBackend::new(path, (1200, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (left, right) = root.split_horizontally(600);
    // Against image size when the frame count is fixed (the `--size` ladder), else frames.
    let distinct = |f: fn(&Row) -> u64| {
        rows.iter()
            .map(f)
            .collect::<std::collections::BTreeSet<_>>()
            .len()
    };
    let by_size = distinct(|r| r.frames as u64) == 1 && distinct(|r| u64::from(r.size)) > 1;
    let xv = move |r: &Row| {
        if by_size {
            f64::from(r.size).powi(2) / 1e6
        } else {
            r.frames as f64
        }
    };
    let (x_desc, what) = if by_size {
        (
            format!(
                "megapixels per frame ({} frames)",
                rows.first().map_or(0, |r| r.frames)
            ),
            "image size",
        )
    } else {
        ("frames".to_string(), "frames")
    };
    let fmax = rows.iter().map(xv).fold(0.0, f64::max).max(1e-3) * 1.05;
    let tmax = rows.iter().map(|r| r.wall_s).fold(0.0, f64::max).max(1e-3) * 1.1;
    let mmax = rows
        .iter()
        .map(|r| r.peak_rss_mib)
        .filter(|m| m.is_finite())
        .fold(0.0, f64::max)
        .max(1.0)
        * 1.25;
    let mut by_v: BTreeMap<(u32, usize), Vec<&Row>> = BTreeMap::new();
    for r in rows {
        let series = if by_size { 0 } else { r.size };
        by_v.entry((series, r.vertices)).or_default().push(r);
    }
    let colours = [
        RGBColor(31, 119, 180),
        RGBColor(214, 39, 40),
        RGBColor(44, 160, 44),
        RGBColor(148, 103, 189),
    ];
    let mut chart = axes(
        &left,
        format!("subsurf fit: time vs {what}"),
        &x_desc,
        fmax,
        (tmax, "seconds"),
    )
    .map_err(|e| err(&e))?;
    for (i, ((px, v), rs)) in by_v.iter().enumerate() {
        let c = colours[i % colours.len()];
        let mut rs = rs.clone();
        rs.sort_by(|a, b| xv(a).total_cmp(&xv(b)));
        let wall: Vec<(f64, f64)> = rs.iter().map(|r| (xv(r), r.wall_s)).collect();
        let decode: Vec<(f64, f64)> = rs.iter().map(|r| (xv(r), r.stage("extract"))).collect();
        let frame: Vec<(f64, f64)> = rs.iter().map(|r| (xv(r), r.frame_stages_s())).collect();
        chart
            .draw_series(LineSeries::new(wall.clone(), c.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label(format!("{}{v} vertices: fit wall", px_label(*px)))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], c.stroke_width(2)));
        chart
            .draw_series(wall.iter().map(|&p| Circle::new(p, 3, c.filled())))
            .map_err(|e| err(&e))?;
        chart
            .draw_series(LineSeries::new(frame.clone(), c.mix(0.6).stroke_width(1)))
            .map_err(|e| err(&e))?
            .label(format!(
                "{}{v} vertices: extract+fit+lattice+error",
                px_label(*px)
            ))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], c.mix(0.6)));
        chart
            .draw_series(frame.iter().map(|&p| TriangleMarker::new(p, 4, c.mix(0.6))))
            .map_err(|e| err(&e))?;
        chart
            .draw_series(LineSeries::new(
                decode,
                ShapeStyle::from(c.mix(0.9)).stroke_width(1),
            ))
            .map_err(|e| err(&e))?
            .label(format!(
                "{}{v} vertices: extract (the one decode pass)",
                px_label(*px)
            ))
            .legend(move |(x, y)| PathElement::new([(x, y + 2), (x + 18, y + 2)], c.mix(0.9)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;
    let mut chart = axes(
        &right,
        format!("subsurf fit: peak RSS vs {what}"),
        &x_desc,
        fmax,
        (mmax, "peak RSS (MiB)"),
    )
    .map_err(|e| err(&e))?;
    for (i, ((px, v), rs)) in by_v.iter().enumerate() {
        let c = colours[i % colours.len()];
        let mut rs = rs.clone();
        rs.sort_by(|a, b| xv(a).total_cmp(&xv(b)));
        let pts: Vec<(f64, f64)> = rs.iter().map(|r| (xv(r), r.peak_rss_mib)).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label(format!("{}{v} vertices", px_label(*px)))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], c.stroke_width(2)));
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
            .map_err(|e| err(&e))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}
