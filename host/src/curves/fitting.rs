//! `subsurf fit-curve`: fitting the curves of a CSV file ([`crate::curves`]) one by one, as
//! the command's flags ask, and each result as a line of JSON or text; Figure 3's plot of the
//! first. The command only parses its flags and prints the lines.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde_json::{Value, json};

use super::{Curve, Grouped, ReadError, read, read_groups};
use crate::fit::dipole::{DipoleFit, DipoleOptions, fit_dipole};
use crate::fit::{ExpFit, FitFailure, FitOptions, Objective, Preset, Solver, Terms, fit_expsum};
use crate::model::{Dipole, MAX_TERMS, Term};

/// Which model to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CurveModel {
    /// Sum of exponentials, Eq. 1.
    Expsum,
    /// Dipole of Jensen et al. 2001 (sigma_s', sigma_a; eta fixed).
    Dipole,
}

/// The fit the command's flags ask for (as given: checked by [`CurveFitter::new`]).
#[derive(Debug, Clone)]
pub struct CurveFitSettings {
    /// Model to fit.
    pub model: CurveModel,
    /// Start from a preset's settings (explicit settings still apply on top).
    pub preset: Option<Preset>,
    /// Residual to minimise.
    pub objective: Objective,
    /// Solver implementation.
    pub solver: Solver,
    /// Number of exponential terms, 1..=4, or `auto`.
    pub terms: String,
    /// Relative log E tolerance of `auto` terms.
    pub tolerance: f64,
    /// `auto`, `exact` or a bin count.
    pub bins: String,
    /// Iteration limit.
    pub max_iterations: Option<usize>,
    /// Start values in NIST order c1,-d1,c2,-d2,… (expsum only).
    pub start: Option<Vec<f64>>,
    /// Fixed relative index of refraction for the dipole.
    pub eta: f64,
    /// Samples are absolute reflectance (dipole scale k = 1).
    pub absolute: bool,
    /// Each result as one JSON object instead of text.
    pub json: bool,
}

/// Why curves could not be fitted.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FitCurveError {
    /// A setting is out of range or contradicts another.
    #[error("{0}")]
    Invalid(String),
    /// `--terms` is neither a number nor `auto`.
    #[error("--terms must be 1..=4 or auto, got `{given}`")]
    Terms {
        /// What was given.
        given: String,
        /// Why it is no number.
        #[source]
        source: std::num::ParseIntError,
    },
    /// The file could not be opened.
    #[error("opening {}", path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a curve file, or reading it failed.
    #[error("in {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: ReadError,
    },
    /// A result could not be written as JSON.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The plot has nothing to show.
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    /// The plot could not be drawn (the drawing backend's message).
    #[error("{0}")]
    Draw(String),
    /// The plot could not be written.
    #[error("writing {}", path.display())]
    Write {
        /// The picture.
        path: PathBuf,
        /// Why.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// The drawing backend's error, as its message.
fn draw(e: impl std::fmt::Display) -> FitCurveError {
    FitCurveError::Draw(e.to_string())
}

fn fit_options(s: &CurveFitSettings) -> Result<FitOptions, FitCurveError> {
    let mut o = match s.preset {
        Some(p) => p.options(),
        None => FitOptions::default(),
    };
    o.require_convergence = false;
    // Users fit whatever they measured: with few samples, fit the order they determine.
    o.reduce_order = true;
    o.objective = s.objective;
    o.solver = s.solver;
    if s.preset.is_none() || s.terms != "3" {
        o.terms = if s.terms.eq_ignore_ascii_case("auto") {
            Terms::Auto {
                max: MAX_TERMS,
                tolerance: s.tolerance,
            }
        } else {
            let n: usize = s.terms.parse().map_err(|source| FitCurveError::Terms {
                given: s.terms.clone(),
                source,
            })?;
            if !(1..=MAX_TERMS).contains(&n) {
                return Err(FitCurveError::Invalid(format!(
                    "--terms must be 1..=4 or auto, got {n}"
                )));
            }
            Terms::Fixed(n)
        };
    }
    match bins_arg(&s.bins)? {
        BinsArg::Auto => {}
        BinsArg::Exact => o.bins = None,
        BinsArg::Fixed(n) => o.bins = Some(n),
    }
    if let Some(m) = s.max_iterations {
        o.max_iterations = m;
    }
    if let Some(start) = &s.start {
        let Terms::Fixed(n) = o.terms else {
            return Err(FitCurveError::Invalid(
                "--start needs a fixed --terms N".into(),
            ));
        };
        if start.len() != 2 * n {
            return Err(FitCurveError::Invalid(format!(
                "--start needs {} values (c1,-d1,…) for {n} terms, got {}",
                2 * n,
                start.len()
            )));
        }
        let terms: Vec<Term> = start
            .chunks(2)
            .map(|p| Term { c: p[0], d: -p[1] })
            .collect();
        if terms
            .iter()
            .any(|t| !(t.c > 0.0 && t.d < 0.0 && t.c.is_finite() && t.d.is_finite()))
        {
            return Err(FitCurveError::Invalid(
                "--start values must be positive: c_k > 0 and -d_k > 0".into(),
            ));
        }
        o.start = Some(terms);
    }
    Ok(o)
}

/// `--bins`: automatic, exact, or a fixed bin count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum BinsArg {
    Auto,
    Exact,
    Fixed(usize),
}

/// Curves with at least this many samples are fitted on bins by `--bins auto`.
const AUTO_BINS_MIN_SAMPLES: usize = 1_000;

/// Bins of `--bins auto`: on the scipy comparison (BENCHMARKS.md) 64 bins reproduce the exact
/// fit's log E to 1e-5 on every curve (32 bins: 1.4e-3, 16 bins: up to 2x on curves whose
/// fastest term falls off within the first bin).
const AUTO_BINS: usize = 64;

fn bins_arg(s: &str) -> Result<BinsArg, FitCurveError> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(BinsArg::Auto);
    }
    if s.eq_ignore_ascii_case("exact") {
        return Ok(BinsArg::Exact);
    }
    match s.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(BinsArg::Fixed(n)),
        _ => Err(FitCurveError::Invalid(format!(
            "--bins must be auto, exact or a bin count >= 1, got `{s}`"
        ))),
    }
}

/// The options for one curve: `--bins auto` picks bins or the exact fit by its size.
fn curve_options<'a>(
    options: &'a FitOptions,
    binned: &'a FitOptions,
    auto: bool,
    samples: usize,
) -> &'a FitOptions {
    if auto && samples >= AUTO_BINS_MIN_SAMPLES {
        binned
    } else {
        options
    }
}

fn expsum_json(fit: &Result<ExpFit, FitFailure>) -> Value {
    match fit {
        Ok(f) => json!({
            "terms": f.model.terms.iter().map(|t| json!({"c": t.c, "d": t.d})).collect::<Vec<_>>(),
            "rss": f.rss,
            "log_e": f.log_e,
            "iterations": f.iterations,
            "converged": f.converged,
            "stalled": f.stalled,
            "samples": f.samples,
            "order": f.order,
            "reduced_from": f.reduced_from,
        }),
        Err(e) => json!({"converged": false, "error": e.to_string()}),
    }
}

fn dipole_json(fit: &Result<DipoleFit, FitFailure>) -> Value {
    match fit {
        Ok(f) => json!({
            "sigma_s_prime": f.dipole.sigma_s_prime,
            "sigma_a": f.dipole.sigma_a,
            "eta": f.dipole.eta,
            "scale": f.scale,
            "total_reflectance": f.dipole.total_reflectance(),
            "rss": f.rss,
            "log_e": f.log_e,
            "iterations": f.iterations,
            "converged": f.converged,
            "stalled": f.stalled,
            "samples": f.samples,
        }),
        Err(e) => json!({"converged": false, "error": e.to_string()}),
    }
}

const CHANNELS: [&str; 3] = ["r", "g", "b"];

/// One curve's output object: the single-channel fields at top level, or `channels` for RGB.
fn curve_json(curve: &Curve, model: &str, per_channel: Vec<Value>) -> Value {
    let mut obj = json!({"id": curve.id, "model": model});
    if per_channel.len() == 1 {
        if let (Some(o), Some(Value::Object(f))) =
            (obj.as_object_mut(), per_channel.into_iter().next())
        {
            o.extend(f);
        }
    } else {
        let chans: Vec<Value> = per_channel
            .into_iter()
            .zip(CHANNELS)
            .map(|(mut v, name)| {
                if let Some(o) = v.as_object_mut() {
                    o.insert("channel".into(), json!(name));
                }
                v
            })
            .collect();
        obj["channels"] = Value::Array(chans);
    }
    obj
}

/// "converged", "stalled" (no step reduces the cost at a non-stationary point) or "not
/// converged" (iteration limit).
fn status(v: &Value) -> &'static str {
    if v["converged"] == true {
        "converged"
    } else if v["stalled"] == true {
        "STALLED (not a minimum)"
    } else {
        "NOT converged (iteration limit)"
    }
}

/// One curve's result as text: the fitted curve, its log E and how the fit ended (one line
/// per channel).
pub fn describe(curve: &Curve, v: &Value) -> String {
    let id = curve
        .id
        .as_deref()
        .map(|i| format!("id {i}: "))
        .unwrap_or_default();
    let one = |v: &Value| -> String {
        if let Some(e) = v.get("error") {
            return format!("failed: {}", e.as_str().unwrap_or(""));
        }
        if let Some(terms) = v.get("terms").and_then(Value::as_array) {
            let t: Vec<String> = terms
                .iter()
                .map(|t| {
                    format!(
                        "{:.6e}·exp({:.6e}·r)",
                        t["c"].as_f64().unwrap_or(f64::NAN),
                        t["d"].as_f64().unwrap_or(f64::NAN)
                    )
                })
                .collect();
            let reduced = match v["reduced_from"].as_u64() {
                Some(asked) => format!(
                    " (order reduced from {asked} to {}: {} samples determine at most {} term{})",
                    terms.len(),
                    v["samples"]["used"],
                    terms.len(),
                    if terms.len() == 1 { "" } else { "s" }
                ),
                None => String::new(),
            };
            format!(
                "R_d(r) = {}; log E {:.4e}; {} iterations; {}{reduced}",
                t.join(" + "),
                v["log_e"].as_f64().unwrap_or(f64::NAN),
                v["iterations"],
                status(v)
            )
        } else {
            format!(
                "dipole sigma_s' {:.6e}, sigma_a {:.6e}, eta {}, scale {:.4e}; log E {:.4e}; {}",
                v["sigma_s_prime"].as_f64().unwrap_or(f64::NAN),
                v["sigma_a"].as_f64().unwrap_or(f64::NAN),
                v["eta"],
                v["scale"].as_f64().unwrap_or(f64::NAN),
                v["log_e"].as_f64().unwrap_or(f64::NAN),
                status(v)
            )
        }
    };
    match v.get("channels").and_then(Value::as_array) {
        Some(ch) => ch
            .iter()
            .map(|c| {
                format!(
                    "{id}channel {}: {}",
                    c["channel"].as_str().unwrap_or("?"),
                    one(c)
                )
            })
            .collect::<Vec<_>>()
            .join("\n"),
        None => format!("{id}{}", one(v)),
    }
}

/// The fitted lines of a file, and its first curve (kept when asked, for the plot).
#[derive(Debug, Clone, Default)]
pub struct FittedFile {
    /// One line (JSON or text) per curve, in the order of the file.
    pub lines: Vec<String>,
    /// The file's first curve.
    pub first: Option<Curve>,
}

/// The checked settings of `fit-curve`: fits curves and writes each result as a line.
#[derive(Debug, Clone)]
pub struct CurveFitter {
    model: CurveModel,
    options: FitOptions,
    /// `options` on [`AUTO_BINS`] bins (large curves under `--bins auto`).
    binned: FitOptions,
    /// `--bins auto` without a preset.
    auto: bool,
    dipole_options: DipoleOptions,
    json: bool,
}

impl CurveFitter {
    /// Checks the settings (the command's messages name its flags).
    pub fn new(s: &CurveFitSettings) -> Result<CurveFitter, FitCurveError> {
        let options = fit_options(s)?;
        let dipole_options = DipoleOptions {
            eta: s.eta,
            absolute: s.absolute,
            solver: options.solver,
            max_iterations: options.max_iterations,
        };
        if s.model == CurveModel::Dipole && Dipole::new(1.0, 0.1, s.eta).is_err() {
            return Err(FitCurveError::Invalid(format!(
                "--eta {} is not a valid relative index of refraction",
                s.eta
            )));
        }
        // `--bins auto` without a preset (presets choose their own bins): large curves on bins.
        let auto = bins_arg(&s.bins)? == BinsArg::Auto && s.preset.is_none();
        let binned = FitOptions {
            bins: Some(AUTO_BINS),
            ..options.clone()
        };
        Ok(CurveFitter {
            model: s.model,
            options,
            binned,
            auto,
            dipole_options,
            json: s.json,
        })
    }

    /// One curve's output line: fitted, then written as JSON or as text.
    pub fn line(&self, curve: &Curve) -> Result<String, FitCurveError> {
        let v = match self.model {
            CurveModel::Expsum => {
                let o = curve_options(&self.options, &self.binned, self.auto, curve.r.len());
                let per: Vec<Value> = curve
                    .channels
                    .iter()
                    .map(|s| expsum_json(&fit_expsum(&curve.r, s, o)))
                    .collect();
                curve_json(curve, "expsum", per)
            }
            CurveModel::Dipole => {
                let per: Vec<Value> = curve
                    .channels
                    .iter()
                    .map(|s| dipole_json(&fit_dipole(&curve.r, s, &self.dipole_options)))
                    .collect();
                curve_json(curve, "dipole", per)
            }
        };
        Ok(if self.json {
            serde_json::to_string(&v)?
        } else {
            describe(curve, &v)
        })
    }

    /// Fits every curve of the file at `path` (`batch`: a leading `id` column), in parallel;
    /// keeps the first curve when `keep_first`.
    pub fn fit_file(
        &self,
        path: &Path,
        batch: bool,
        keep_first: bool,
    ) -> Result<FittedFile, FitCurveError> {
        let open = || {
            std::fs::File::open(path).map_err(|source| FitCurveError::Open {
                path: path.to_path_buf(),
                source,
            })
        };
        let in_file = |source| FitCurveError::Read {
            path: path.to_path_buf(),
            source,
        };
        let fit_one = |curve: &Curve| self.line(curve);
        // Curves are fitted as they are read, a block of the file at a time (see
        // `curves::read_groups`); the output is written once the whole file has been read, so a
        // file whose ids are interleaved is read again whole and fitted from scratch.
        let mut lines: Vec<String> = Vec::new();
        let mut first: Option<Curve> = None;
        let mut failed: Option<FitCurveError> = None;
        let grouped = read_groups(open()?, batch, |group| {
            if failed.is_some() {
                return;
            }
            if first.is_none() && keep_first {
                first = group.first().cloned();
            }
            // On one thread the block's curves are fitted right here: handing each block to
            // rayon's single worker and waiting for it cost two context switches a block (~4 % of
            // `fit-curve --batch`'s CPU time on a VM, perf), for no parallelism.
            let fitted = if rayon::current_num_threads() <= 1 {
                group.iter().map(&fit_one).collect::<Result<Vec<_>, _>>()
            } else {
                group
                    .par_iter()
                    .map(&fit_one)
                    .collect::<Result<Vec<_>, _>>()
            };
            match fitted {
                Ok(l) => lines.extend(l),
                Err(e) => failed = Some(e),
            }
        })
        .map_err(in_file)?;
        if let Some(e) = failed {
            return Err(e);
        }
        if grouped == Grouped::Interleaved {
            let curves = read(open()?, batch).map_err(in_file)?;
            lines = curves
                .par_iter()
                .map(&fit_one)
                .collect::<Result<Vec<_>, _>>()?;
            first = curves.into_iter().next();
        }
        Ok(FittedFile { lines, first })
    }

    /// Figure 3 of the paper for `curve` at `path`: its samples and the fitted sum of
    /// exponentials on a logarithmic axis, with the dipole when `dipole` (or the model is the
    /// dipole).
    pub fn plot(&self, path: &Path, curve: &Curve, dipole: bool) -> Result<(), FitCurveError> {
        plot(
            path,
            curve,
            dipole || self.model == CurveModel::Dipole,
            &self.options,
            &self.dipole_options,
        )
    }
}

/// Figure 3 of the paper: samples and fitted fall-off on a logarithmic axis, with the dipole for
/// comparison when asked.
fn plot(
    path: &Path,
    curve: &Curve,
    draw_dipole: bool,
    options: &FitOptions,
    dipole_options: &DipoleOptions,
) -> Result<(), FitCurveError> {
    use plotters::prelude::*;
    crate::plot::register_font();
    let positive: Vec<f64> = curve
        .channels
        .iter()
        .flatten()
        .copied()
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    let (ymin, ymax) = positive
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    if !(ymin.is_finite() && ymax.is_finite()) {
        return Err(crate::plot::PlotError::Empty("no positive finite samples".into()).into());
    }
    let rmax = curve
        .r
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-12);
    let colours = if curve.channels.len() == 1 {
        vec![RGBColor(40, 40, 40)]
    } else {
        vec![
            RGBColor(200, 30, 30),
            RGBColor(30, 150, 30),
            RGBColor(30, 60, 200),
        ]
    };
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(draw)?;
    let title = match &curve.id {
        Some(id) => format!("R_d(r), id {id}"),
        None => "R_d(r)".to_string(),
    };
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 24))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..rmax * 1.02, (ymin * 0.5..ymax * 2.0).log_scale())
        .map_err(draw)?;
    chart
        .configure_mesh()
        .x_desc("distance r = |x_o - x_i|")
        .y_desc("R_d")
        .draw()
        .map_err(draw)?;
    let xs: Vec<f64> = (0..=400).map(|i| rmax * i as f64 / 400.0).collect();
    for (ch, s) in curve.channels.iter().enumerate() {
        let colour = colours[ch % colours.len()];
        let pts: Vec<(f64, f64)> = curve
            .r
            .iter()
            .zip(s)
            .filter(|(r, v)| r.is_finite() && v.is_finite() && **v > 0.0 && **r >= 0.0)
            .map(|(r, v)| (*r, *v))
            .collect();
        chart
            .draw_series(
                pts.iter()
                    .map(|p| Circle::new(*p, 3, colour.mix(0.5).filled())),
            )
            .map_err(draw)?;
        let fitted = fit_expsum(&curve.r, s, options);
        if let Ok(f) = &fitted {
            let line: Vec<(f64, f64)> = xs
                .iter()
                .map(|&x| (x, f.model.eval(x)))
                .filter(|p| p.1 > 0.0 && p.1.is_finite())
                .collect();
            let series = chart
                .draw_series(LineSeries::new(line, colour.stroke_width(2)))
                .map_err(draw)?;
            if ch == 0 {
                series
                    .label(format!("sum of {} exponentials", f.model.n()))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                    });
            }
        }
        if draw_dipole && let Ok(d) = fit_dipole(&curve.r, s, dipole_options) {
            let line: Vec<(f64, f64)> = xs
                .iter()
                .map(|&x| (x, d.scale * d.dipole.r_d(x)))
                .filter(|p| p.1 > 0.0 && p.1.is_finite())
                .collect();
            let style = ShapeStyle::from(&colour).stroke_width(1);
            let series = chart
                .draw_series(DashedLineSeries::new(line, 6, 4, style))
                .map_err(draw)?;
            if ch == 0 {
                series
                    .label("dipole")
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
            }
        }
    }
    chart
        .configure_series_labels()
        .border_style(BLACK)
        .background_style(WHITE.mix(0.8))
        .draw()
        .map_err(draw)?;
    root.present().map_err(|e| FitCurveError::Write {
        path: path.to_path_buf(),
        source: Box::new(e),
    })?;
    Ok(())
}
