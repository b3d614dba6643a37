//! `subsurf bench tradeoff`: the speed/accuracy curve of the whole chain — simulated scan at
//! several plan densities → fit preset → render quality — with wall time per stage and the error of
//! every configuration against the exact result, as a markdown table and a PNG with the Pareto
//! front (release mode; output pasted unedited, or written with `--write-benchmarks`).
//!
//! Everything runs through library calls (`simulate::simulate`, `pipeline::fit_dataset`,
//! `evaluate::evaluate_frames`, `render::render`), never through the binary.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::dataset::{Dataset, select_frames};
use crate::evaluate::evaluate_frames;
use crate::fit::Preset;
use crate::modelfile::ModelFile;
use crate::pipeline::{PipelineOptions, fit_dataset};
use crate::plot::TradeoffPoint;
use crate::progress::Stages;
use crate::render::{self, Camera, Image, Light, Method, Quality, RenderOptions};
use crate::scan::setup::{builtin_object, single_exposure_sim};
use crate::simulate::{SimConfig, SimObject, simulate};

/// The benchmark's settings (the command's flags).
#[derive(Debug, Clone)]
pub struct TradeoffSettings {
    /// Small sizes (one plan density, two presets, two render qualities).
    pub quick: bool,
    /// Scratch folder for the simulated scans (created; removed at the end unless `keep`).
    pub work: PathBuf,
    /// Keep the simulated scans in `work`.
    pub keep: bool,
    /// Tessellation of the built-in sphere; `None`: 64 (16 when `quick`).
    pub rings: Option<usize>,
    /// Camera image size of the simulated scans; `None`: 96 (40 when `quick`).
    pub scan_px: Option<u32>,
    /// Where the time-vs-error plot goes.
    pub plot: PathBuf,
}

/// Why the benchmark stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TradeoffError {
    /// The settings or the measurements do not allow the comparison.
    #[error("{0}")]
    Invalid(String),
    /// A step failed; `what` names it, `source` says why.
    #[error("{what}")]
    Step {
        /// The step (e.g. `simulating scan 0`).
        what: String,
        /// Why.
        #[source]
        source: Box<TradeoffError>,
    },
    /// A folder could not be made or cleared.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// A scan could not be simulated.
    #[error(transparent)]
    Simulate(#[from] crate::simulate::SimError),
    /// A scan could not be read.
    #[error(transparent)]
    Dataset(#[from] crate::dataset::DatasetError),
    /// The ground truth could not be read.
    #[error(transparent)]
    Model(#[from] crate::modelfile::ModelFileError),
    /// A fit failed.
    #[error(transparent)]
    Pipeline(#[from] crate::pipeline::PipelineError),
    /// Judging a model failed.
    #[error(transparent)]
    Evaluate(#[from] crate::evaluate::EvaluateError),
    /// The renderer refused a model.
    #[error(transparent)]
    Render(#[from] crate::render::RenderError),
    /// The plot could not be drawn.
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    /// The table could not be formatted.
    #[error(transparent)]
    Fmt(#[from] std::fmt::Error),
}

crate::util::step_context!(TradeoffError);

/// Runs the whole chain in `b.work` (cleared first; removed at the end unless `b.keep`) and
/// returns the report: the table, its notes, and the plot written to `b.plot`.
pub fn bench_tradeoff<U: Stages>(b: &TradeoffSettings, ui: &U) -> Result<String, TradeoffError> {
    let sizes = Sizes::new(b);
    if b.work.exists() {
        std::fs::remove_dir_all(&b.work).step(|| format!("clearing {}", b.work.display()))?;
    }
    std::fs::create_dir_all(&b.work).step(|| format!("creating {}", b.work.display()))?;
    let t_all = Instant::now();
    let result = run_chain(b, &sizes, ui);
    if !b.keep {
        // The scans are scratch data: never leave them behind, whatever happened.
        let _ = std::fs::remove_dir_all(&b.work);
    }
    let rows = result?;
    report(b, &sizes, &rows, t_all.elapsed().as_secs_f64())
}

/// One plan density of the simulated scan.
#[derive(Clone, Copy, Debug)]
struct Density {
    /// Turntable angles.
    angles: usize,
    /// Laser raster per side.
    raster: usize,
}

/// The sizes of one run.
struct Sizes {
    densities: Vec<Density>,
    presets: Vec<FitChoice>,
    /// `None` = exact transport.
    qualities: Vec<Option<Quality>>,
    /// Sphere tessellation.
    rings: usize,
    /// Camera image size of the simulated scan.
    scan_px: u32,
    /// Rendered image size.
    render_px: u32,
    /// Held-out scan: its density (its angles sit halfway between the training angles).
    held_out: Density,
}

impl Sizes {
    fn new(b: &TradeoffSettings) -> Sizes {
        let quick = b.quick;
        let all_q = vec![
            Some(Quality::Draft),
            Some(Quality::Balanced),
            Some(Quality::Best),
            None,
        ];
        if quick {
            Sizes {
                densities: vec![Density {
                    angles: 3,
                    raster: 5,
                }],
                presets: vec![
                    FitChoice::Preset(Preset::Draft),
                    FitChoice::Preset(Preset::Best),
                ],
                qualities: vec![Some(Quality::Draft), None],
                rings: b.rings.unwrap_or(16),
                scan_px: b.scan_px.unwrap_or(40),
                render_px: 48,
                held_out: Density {
                    angles: 2,
                    raster: 4,
                },
            }
        } else {
            Sizes {
                densities: vec![
                    Density {
                        angles: 4,
                        raster: 6,
                    },
                    Density {
                        angles: 6,
                        raster: 10,
                    },
                    Density {
                        angles: 8,
                        raster: 14,
                    },
                ],
                presets: Preset::ALL
                    .iter()
                    .map(|&p| FitChoice::Preset(p))
                    .chain([FitChoice::Default, FitChoice::Reference])
                    .collect(),
                qualities: all_q,
                rings: b.rings.unwrap_or(64),
                scan_px: b.scan_px.unwrap_or(96),
                render_px: 256,
                held_out: Density {
                    angles: 4,
                    raster: 8,
                },
            }
        }
    }
}

/// One simulated scan (`scan::setup::single_exposure_sim`): one camera orbiting at the default
/// elevation, so the frame count is angles × raster².
fn scan_config(sizes: &Sizes, d: Density, seed: u64, half_step: bool) -> SimConfig {
    let mut cfg = single_exposure_sim(object(sizes), sizes.scan_px, d.angles, d.raster);
    if half_step {
        let step = 360.0 / d.angles.max(1) as f64;
        for a in &mut cfg.turntable_deg {
            *a += step / 2.0;
        }
    }
    cfg.seed = seed;
    cfg
}

/// The built-in object (`scan::setup::builtin_object`) at the benchmark's tessellation.
fn object(sizes: &Sizes) -> SimObject {
    match builtin_object() {
        SimObject::Sphere { radius, .. } => SimObject::Sphere {
            radius,
            rings: sizes.rings,
        },
        other => other,
    }
}

fn quality_name(q: Option<Quality>) -> &'static str {
    match q {
        Some(Quality::Draft) => "draft",
        Some(Quality::Balanced) => "balanced",
        Some(Quality::Best) => "best",
        None => "exact",
    }
}

/// How a row fits: a preset, the default fit, or the reference preset (the exact path
/// without the default's cost cuts, shown beside it so the trade is measured). Rows fit
/// without cross-validation, all alike.
#[derive(Debug, Clone, Copy, PartialEq)]
enum FitChoice {
    Preset(Preset),
    Default,
    Reference,
}

impl FitChoice {
    fn name(self) -> &'static str {
        match self {
            FitChoice::Preset(p) => p.name(),
            FitChoice::Default => "default",
            FitChoice::Reference => "reference",
        }
    }

    fn options(self, ds: &Dataset) -> (PipelineOptions, crate::fit::FitOptions) {
        let preset = match self {
            FitChoice::Preset(p) => Some(p),
            FitChoice::Default | FitChoice::Reference => None,
        };
        let (mut opts, fit) = PipelineOptions::for_dataset(ds).with_preset(preset);
        if self == FitChoice::Reference {
            opts.speed = crate::pipeline::Speed::Reference;
        }
        (opts, fit)
    }
}

/// One row of the table: a (scan density, fit preset, render quality) configuration.
struct Row {
    density: usize,
    frames: usize,
    preset: FitChoice,
    quality: Option<Quality>,
    scan_s: f64,
    fit_s: f64,
    render_s: f64,
    /// Held-out mean log E (Eq. 8, mean over R, G, B).
    model_log_e: f64,
    /// Vertices fitted / interpolated.
    fitted: usize,
    interpolated: usize,
    /// The render, or why there is none.
    image: Result<Image, String>,
    render_err: f64,
    /// Against the exact render of the simulation's ground-truth model.
    truth_err: f64,
    /// The same, signed: the mean of (render − truth) / truth, a brightness bias.
    truth_signed: f64,
}

impl Row {
    fn total(&self) -> f64 {
        self.scan_s + self.fit_s + self.render_s
    }
    fn label(&self) -> String {
        format!(
            "{}f/{}/{}",
            self.frames,
            self.preset.name(),
            quality_name(self.quality)
        )
    }
}

fn run_chain<U: Stages>(
    b: &TradeoffSettings,
    sizes: &Sizes,
    ui: &U,
) -> Result<Vec<Row>, TradeoffError> {
    // The held-out scan: other turntable angles, other noise; no model ever sees it while fitting.
    let held_dir = b.work.join("held-out");
    let p = ui.stage(0, "held-out scan");
    simulate(
        &scan_config(sizes, sizes.held_out, 101, true),
        &held_dir,
        &p,
    )
    .step(|| "simulating the held-out scan".into())?;
    ui.finish(p);
    let held = Dataset::open(&held_dir).step(|| "reading the held-out scan".into())?;
    let held_frames =
        select_frames(held.spec.frames.len(), None, None).map_err(TradeoffError::Invalid)?;
    let held_opts = PipelineOptions::for_dataset(&held);

    let mut rows = Vec::new();
    let mut truth: Result<Image, String> = Err("no scan".into());
    for (di, &d) in sizes.densities.iter().enumerate() {
        let dir = b.work.join(format!("scan-{di}"));
        let p = ui.stage(0, &format!("scan {}x{}²", d.angles, d.raster));
        let t = Instant::now();
        let sum = simulate(&scan_config(sizes, d, 7, false), &dir, &p)
            .step(|| format!("simulating scan {di}"))?;
        let scan_s = t.elapsed().as_secs_f64();
        ui.finish(p);
        let ds = Dataset::open(&dir).step(|| format!("reading scan {di}"))?;
        let frames =
            select_frames(ds.spec.frames.len(), None, None).map_err(TradeoffError::Invalid)?;
        if di == 0 {
            // Every scan is of the same object and material: one ground truth for all.
            let gt =
                ModelFile::read(&dir.join("ground-truth.ply")).step(|| "ground truth".into())?;
            truth = render_image(&gt, sizes.render_px, None).map(|(i, _)| i);
        }
        for &preset in &sizes.presets {
            let (opts, fit) = preset.options(&ds);
            let p = ui.stage(0, &format!("fit {}", preset.name()));
            let t = Instant::now();
            let fitted = fit_dataset(&ds, &frames, &opts, &fit, &p)
                .step(|| format!("fitting scan {di} with preset {}", preset.name()))?;
            let fit_s = t.elapsed().as_secs_f64();
            ui.finish(p);
            let p = ui.stage(0, "evaluate");
            let (_, stats) = evaluate_frames(&held, &fitted.model, &held_frames, &held_opts, &p)
                .step(|| "evaluating on the held-out scan".into())?;
            ui.finish(p);
            let means: Vec<f64> = stats.mean.iter().flatten().copied().collect();
            let model_log_e = if means.is_empty() {
                f64::NAN
            } else {
                means.iter().sum::<f64>() / means.len() as f64
            };
            let model = &fitted.model;
            render::validate(model).step(|| "fitted model".into())?;
            for &q in &sizes.qualities {
                // A model the renderer refuses is a measured outcome of that configuration (a row
                // without an error figure), not a reason to stop the benchmark.
                let r = render_image(model, sizes.render_px, q);
                let render_s = r.as_ref().map_or(f64::NAN, |(_, s)| *s);
                let image = r.map(|(i, _)| i);
                rows.push(Row {
                    density: di,
                    frames: sum.frames,
                    preset,
                    quality: q,
                    scan_s,
                    fit_s,
                    render_s,
                    model_log_e,
                    fitted: fitted.report.vertices_fitted,
                    interpolated: fitted.report.vertices_interpolated,
                    image,
                    render_err: f64::NAN,
                    truth_err: f64::NAN,
                    truth_signed: f64::NAN,
                });
            }
        }
        if !b.keep {
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
    // The reference: the exact render of the best model, i.e. the one with the lowest held-out
    // log E among those the renderer accepts (normally the densest scan with the best preset).
    let reference = rows
        .iter()
        .enumerate()
        .filter(|(_, r)| r.quality.is_none() && r.image.is_ok() && r.model_log_e.is_finite())
        .min_by(|a, b| a.1.model_log_e.total_cmp(&b.1.model_log_e))
        .map(|(i, _)| i)
        .ok_or_else(|| {
            TradeoffError::Invalid("no model gave an exact render to compare against".into())
        })?;
    let ref_image = rows[reference]
        .image
        .clone()
        .map_err(|e| TradeoffError::Invalid(format!("reference render: {e}")))?;
    let truth_image = truth
        .as_ref()
        .map_err(|e| TradeoffError::Invalid(format!("ground-truth render: {e}")))?;
    for r in &mut rows {
        if let Ok(i) = &r.image {
            r.render_err = render::relative_pixel_error(i, &ref_image, 1e-3).unwrap_or(f64::NAN);
            (r.truth_err, r.truth_signed) =
                render::relative_pixel_errors(i, truth_image, 1e-3).unwrap_or((f64::NAN, f64::NAN));
        }
    }
    Ok(rows)
}

/// A table cell: `value` with `digits` decimals and `unit`, or "–" where there is no figure.
fn num(value: f64, digits: usize, unit: &str) -> String {
    if value.is_finite() {
        format!("{value:.digits$}{unit}")
    } else {
        "–".to_string()
    }
}

/// A signed percentage cell (`+0.3%`, `−12.1%`), or "–".
fn signed_cell(percent: f64) -> String {
    if percent.is_finite() {
        format!(
            "{}{:.1}%",
            if percent < 0.0 { "−" } else { "+" },
            percent.abs()
        )
    } else {
        "–".to_string()
    }
}

/// Renders `model` under the default lights from the default view, exactly (`None`) or at a
/// quality; the image and its wall time (seconds), or why the renderer refused.
fn render_image(
    model: &ModelFile,
    px: u32,
    quality: Option<Quality>,
) -> Result<(Image, f64), String> {
    let t = Instant::now();
    let (lo, hi) = model.bounds();
    let cam = Camera::framing(lo, hi, render::DEFAULT_VIEW, px, px).map_err(|e| e.to_string())?;
    let opts = RenderOptions {
        method: quality.map_or(Method::Exact, |q| Method::Hierarchical(q.params())),
        ..RenderOptions::default()
    };
    let lights = Light::defaults_for(model.bounds());
    let r = render::render(model, &lights, &cam, &opts).map_err(|e| e.to_string())?;
    Ok((r.image, t.elapsed().as_secs_f64()))
}

fn report(
    b: &TradeoffSettings,
    sizes: &Sizes,
    rows: &[Row],
    total_s: f64,
) -> Result<String, TradeoffError> {
    let points: Vec<TradeoffPoint> = rows
        .iter()
        .map(|r| TradeoffPoint {
            label: r.label(),
            seconds: r.total(),
            error: r.render_err,
        })
        .collect();
    if let Some(dir) = b.plot.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).step(|| format!("creating {}", dir.display()))?;
    }
    let front = crate::plot::pareto_plot(
        &b.plot,
        "Whole chain: scan density × fit preset × render quality",
        &points,
        (900, 600),
    )
    .step(|| format!("writing {}", b.plot.display()))?;
    let mut s = String::new();
    let obj = object(sizes).mesh();
    writeln!(
        s,
        "built-in sphere, {} vertices; scans {}x{} px, one camera; held-out scan {} frames \
         ({} angles between the training angles × {}² raster, other noise seed); renders {}x{} px, \
         two lights; {} rayon threads",
        obj.positions.len(),
        sizes.scan_px,
        sizes.scan_px,
        sizes.held_out.angles * sizes.held_out.raster * sizes.held_out.raster,
        sizes.held_out.angles,
        sizes.held_out.raster,
        sizes.render_px,
        sizes.render_px,
        rayon::current_num_threads()
    )?;
    writeln!(s)?;
    writeln!(
        s,
        "| scan (angles × raster²) | frames | fit preset | render | scan s | fit s | render s | total s | fitted / interp. | held-out log E | render error | vs. truth | vs. truth, signed | Pareto |"
    )?;
    writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    )?;
    for (i, r) in rows.iter().enumerate() {
        let d = sizes.densities[r.density];
        writeln!(
            s,
            "| {} × {}² | {} | {} | {} | {:.2} | {:.2} | {} | {} | {} / {} | {:.4} | {} | {} | {} | {} |",
            d.angles,
            d.raster,
            r.frames,
            r.preset.name(),
            quality_name(r.quality),
            r.scan_s,
            r.fit_s,
            num(r.render_s, 3, ""),
            num(r.total(), 2, ""),
            r.fitted,
            r.interpolated,
            r.model_log_e,
            match &r.image {
                Err(_) => "render refused ¹".to_string(),
                Ok(_) => format!("{:.3}%", 100.0 * r.render_err),
            },
            num(100.0 * r.truth_err, 1, "%"),
            signed_cell(100.0 * r.truth_signed),
            if front.contains(&i) { "★" } else { "" }
        )?;
    }
    let refused: Vec<&String> = rows.iter().filter_map(|r| r.image.as_ref().err()).collect();
    if let Some(first) = refused.first() {
        writeln!(s, "\n¹ {} renders refused, e.g. {first}", refused.len())?;
    }
    writeln!(s)?;
    writeln!(
        s,
        "render error = mean relative pixel error (channels of covered pixels above 1e-3 of the \
         maximum) against the exact render of the best model, the one with the lowest held-out \
         log E (the row with 0%); vs. truth = the same against the exact render of the \
         simulation's ground-truth model, and signed: the mean of (render − truth) / truth over \
         the same channels (a brightness bias; noise averages out of it); held-out log E = \
         Eq. 8, mean over R, G, B, on the held-out scan; ★ = Pareto front of (total s, render error). Plot: `{}`. Whole benchmark \
         {:.1} s.",
        b.plot.display(),
        total_s
    )?;
    if !front.iter().all(|&i| rows[i].render_err.is_finite()) {
        return Err(TradeoffError::Invalid(
            "a Pareto point without a finite error".into(),
        ));
    }
    Ok(s)
}

const BEGIN: &str =
    "<!-- bench-tradeoff:begin (generated by `subsurf bench tradeoff --write-benchmarks`) -->";
const END: &str = "<!-- bench-tradeoff:end -->";

/// Writes `text` into the BENCHMARKS.md at `path`: replaces the text between the markers, or
/// appends a section holding them.
pub fn write_section(path: &Path, text: &str) -> Result<(), std::io::Error> {
    let old = std::fs::read_to_string(path).unwrap_or_default();
    let body = format!("{BEGIN}\n\n{}\n\n{END}", text.trim_end());
    let new = match (old.find(BEGIN), old.find(END)) {
        (Some(a), Some(z)) if a < z => format!("{}{body}{}", &old[..a], &old[z + END.len()..]),
        _ => format!(
            "{}\n## Whole chain: speed vs. accuracy\n\n\
             Command: `cargo build --release -p subsurf && ./target/release/subsurf bench tradeoff \
             --write-benchmarks BENCHMARKS.md`\n\n{body}\n",
            old.trim_end()
        ),
    };
    let tmp = path.with_extension("md.tmp");
    std::fs::write(&tmp, new)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}
