//! `subsurf fit-curve`: fit one fall-off curve (or many, `--batch`) from a CSV file.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use rayon::prelude::*;
use serde_json::{Value, json};
use std::io::Write;

use subsurf::curves::{Curve, Grouped, read, read_groups};
use subsurf::fit::dipole::{DipoleFit, DipoleOptions, fit_dipole};
use subsurf::fit::{ExpFit, FitFailure, FitOptions, Objective, Preset, Solver, Terms, fit_expsum};
use subsurf::model::{MAX_TERMS, Term};

/// Which model to fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelKind {
    /// Sum of exponentials, Eq. 1.
    Expsum,
    /// Dipole of Jensen et al. 2001 (sigma_s', sigma_a; eta fixed).
    Dipole,
}

/// Residual to minimise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ObjectiveArg {
    /// ln(R_d/s), Eq. 4 (the paper's choice).
    Log,
    /// R_d − s.
    Linear,
}

/// Solver implementation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SolverArg {
    /// The specialised Levenberg–Marquardt.
    Specialised,
    /// The `levenberg-marquardt` crate (reference).
    Reference,
}

/// Speed/accuracy preset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PresetArg {
    /// n = 3, 8 bins, every 2nd sample.
    Draft,
    /// n = 3, 16 bins.
    Balanced,
    /// Exact, automatic n.
    Best,
}

/// Fit R_d(r) to a CSV of samples: header `r,value` or `r,r_value,g_value,b_value` (a leading
/// `id` column with --batch); `#` starts a comment.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The CSV file.
    pub input: PathBuf,
    /// Model to fit.
    #[arg(long, value_enum, default_value = "expsum")]
    pub model: ModelKind,
    /// Number of exponential terms, 1..=4, or `auto` (smallest within --tolerance of the best).
    #[arg(long, default_value = "3")]
    pub terms: String,
    /// Residual: log (Eq. 4) or linear.
    #[arg(long, value_enum, default_value = "log")]
    pub objective: ObjectiveArg,
    /// Start values in NIST order c1,-d1,c2,-d2,… (expsum only).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub start: Option<Vec<f64>>,
    /// Write a Figure-3-style log plot of samples and fit (first curve with --batch).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Also fit the dipole and draw it in the plot.
    #[arg(long)]
    pub plot_dipole: bool,
    /// The CSV has a leading `id` column; each id is fitted on its own, in parallel.
    #[arg(long)]
    pub batch: bool,
    /// Print one JSON object per fitted curve, one per line.
    #[arg(long)]
    pub json: bool,
    /// Fixed relative index of refraction for the dipole.
    #[arg(long, default_value_t = 1.3)]
    pub eta: f64,
    /// Treat samples as absolute reflectance (dipole scale k = 1).
    #[arg(long)]
    pub absolute: bool,
    /// Relative log E tolerance of --terms auto.
    #[arg(long, default_value_t = 0.05)]
    pub tolerance: f64,
    /// Speed/accuracy: `auto` (default) fits the sufficient statistics of 64 distance bins
    /// instead of the samples for every curve with at least 1,000 samples (its log E is within
    /// 1e-5 of the exact fit's on the scipy comparison of BENCHMARKS.md, and the reported log E
    /// is computed from the bin statistics: exact up to a cubic term per bin), and the exact fit
    /// on all samples below that; `exact` always fits every sample (several times slower on
    /// large curves); a number N always fits N bins (fewer = faster, less exact).
    #[arg(long, default_value = "auto")]
    pub bins: String,
    /// Start from a preset's settings (explicit flags still apply on top).
    #[arg(long, value_enum)]
    pub preset: Option<PresetArg>,
    /// Solver implementation.
    #[arg(long, value_enum, default_value = "specialised")]
    pub solver: SolverArg,
    /// Iteration limit.
    #[arg(long)]
    pub max_iterations: Option<usize>,
}

fn fit_options(args: &Args) -> anyhow::Result<FitOptions> {
    let mut o = match args.preset {
        Some(PresetArg::Draft) => Preset::Draft.options(),
        Some(PresetArg::Balanced) => Preset::Balanced.options(),
        Some(PresetArg::Best) => Preset::Best.options(),
        None => FitOptions::default(),
    };
    o.require_convergence = false;
    // Users fit whatever they measured: with few samples, fit the order they determine.
    o.reduce_order = true;
    o.objective = match args.objective {
        ObjectiveArg::Log => Objective::Log,
        ObjectiveArg::Linear => Objective::Linear,
    };
    o.solver = match args.solver {
        SolverArg::Specialised => Solver::Specialised,
        SolverArg::Reference => Solver::Reference,
    };
    if args.preset.is_none() || args.terms != "3" {
        o.terms = if args.terms.eq_ignore_ascii_case("auto") {
            Terms::Auto {
                max: MAX_TERMS,
                tolerance: args.tolerance,
            }
        } else {
            let n: usize = args
                .terms
                .parse()
                .with_context(|| format!("--terms must be 1..=4 or auto, got `{}`", args.terms))?;
            if !(1..=MAX_TERMS).contains(&n) {
                bail!("--terms must be 1..=4 or auto, got {n}");
            }
            Terms::Fixed(n)
        };
    }
    match bins_arg(&args.bins)? {
        BinsArg::Auto => {}
        BinsArg::Exact => o.bins = None,
        BinsArg::Fixed(n) => o.bins = Some(n),
    }
    if let Some(m) = args.max_iterations {
        o.max_iterations = m;
    }
    if let Some(start) = &args.start {
        let Terms::Fixed(n) = o.terms else {
            bail!("--start needs a fixed --terms N");
        };
        if start.len() != 2 * n {
            bail!(
                "--start needs {} values (c1,-d1,…) for {n} terms, got {}",
                2 * n,
                start.len()
            );
        }
        let terms: Vec<Term> = start
            .chunks(2)
            .map(|p| Term { c: p[0], d: -p[1] })
            .collect();
        if terms
            .iter()
            .any(|t| !(t.c > 0.0 && t.d < 0.0 && t.c.is_finite() && t.d.is_finite()))
        {
            bail!("--start values must be positive: c_k > 0 and -d_k > 0");
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

fn bins_arg(s: &str) -> anyhow::Result<BinsArg> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(BinsArg::Auto);
    }
    if s.eq_ignore_ascii_case("exact") {
        return Ok(BinsArg::Exact);
    }
    match s.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(BinsArg::Fixed(n)),
        _ => bail!("--bins must be auto, exact or a bin count >= 1, got `{s}`"),
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

fn describe(curve: &Curve, v: &Value) -> String {
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

/// Runs the command.
pub fn run(args: Args) -> anyhow::Result<()> {
    let options = fit_options(&args)?;
    let dipole_options = DipoleOptions {
        eta: args.eta,
        absolute: args.absolute,
        solver: options.solver,
        max_iterations: options.max_iterations,
    };
    if args.model == ModelKind::Dipole && Dipole::new(1.0, 0.1, args.eta).is_err() {
        bail!(
            "--eta {} is not a valid relative index of refraction",
            args.eta
        );
    }
    // `--bins auto` without a preset (presets choose their own bins): large curves on bins.
    let auto = bins_arg(&args.bins)? == BinsArg::Auto && args.preset.is_none();
    let binned = FitOptions {
        bins: Some(AUTO_BINS),
        ..options.clone()
    };
    // One curve's output line: fitted, then written as JSON or as text.
    let fit_one = |curve: &Curve| -> anyhow::Result<String> {
        let v = match args.model {
            ModelKind::Expsum => {
                let o = curve_options(&options, &binned, auto, curve.r.len());
                let per: Vec<Value> = curve
                    .channels
                    .iter()
                    .map(|s| expsum_json(&fit_expsum(&curve.r, s, o)))
                    .collect();
                curve_json(curve, "expsum", per)
            }
            ModelKind::Dipole => {
                let per: Vec<Value> = curve
                    .channels
                    .iter()
                    .map(|s| dipole_json(&fit_dipole(&curve.r, s, &dipole_options)))
                    .collect();
                curve_json(curve, "dipole", per)
            }
        };
        Ok(if args.json {
            serde_json::to_string(&v)?
        } else {
            describe(curve, &v)
        })
    };
    let open = || {
        std::fs::File::open(&args.input)
            .with_context(|| format!("opening {}", args.input.display()))
    };
    // Curves are fitted as they are read, a block of the file at a time (see
    // `curves::read_groups`); the output is written once the whole file has been read, so a
    // file whose ids are interleaved is read again whole and fitted from scratch.
    let mut lines: Vec<String> = Vec::new();
    let mut first: Option<Curve> = None;
    let mut failed: Option<anyhow::Error> = None;
    let grouped = read_groups(open()?, args.batch, |group| {
        if failed.is_some() {
            return;
        }
        if first.is_none() && args.plot.is_some() {
            first = group.first().cloned();
        }
        // On one thread the block's curves are fitted right here: handing each block to
        // rayon's single worker and waiting for it cost two context switches a block (~4 % of
        // `fit-curve --batch`'s CPU time on a VM, perf), for no parallelism.
        let fitted = if rayon::current_num_threads() <= 1 {
            group
                .iter()
                .map(&fit_one)
                .collect::<anyhow::Result<Vec<_>>>()
        } else {
            group
                .par_iter()
                .map(&fit_one)
                .collect::<anyhow::Result<Vec<_>>>()
        };
        match fitted {
            Ok(l) => lines.extend(l),
            Err(e) => failed = Some(e),
        }
    })
    .with_context(|| format!("in {}", args.input.display()))?;
    if let Some(e) = failed {
        return Err(e);
    }
    if grouped == Grouped::Interleaved {
        let curves =
            read(open()?, args.batch).with_context(|| format!("in {}", args.input.display()))?;
        lines = curves
            .par_iter()
            .map(&fit_one)
            .collect::<anyhow::Result<Vec<_>>>()?;
        first = curves.into_iter().next();
    }
    // One buffered writer: a batch prints thousands of lines.
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    for line in &lines {
        writeln!(out, "{line}")?;
    }
    out.flush().context("writing the output")?;
    drop(out);
    if let Some(path) = &args.plot {
        let curve = first.context("nothing to plot: the file has no samples")?;
        plot(path, &curve, &args, &options, &dipole_options)?;
    }
    Ok(())
}

use subsurf::model::Dipole;

/// Figure 3 of the paper: samples and fitted fall-off on a logarithmic axis, with the dipole for
/// comparison when asked.
fn plot(
    path: &Path,
    curve: &Curve,
    args: &Args,
    options: &FitOptions,
    dipole_options: &DipoleOptions,
) -> anyhow::Result<()> {
    use plotters::prelude::*;
    subsurf::plot::register_font();
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
        bail!("nothing to plot: no positive finite samples");
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
    root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
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
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    chart
        .configure_mesh()
        .x_desc("distance r = |x_o - x_i|")
        .y_desc("R_d")
        .draw()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
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
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let fitted = fit_expsum(&curve.r, s, options);
        if let Ok(f) = &fitted {
            let line: Vec<(f64, f64)> = xs
                .iter()
                .map(|&x| (x, f.model.eval(x)))
                .filter(|p| p.1 > 0.0 && p.1.is_finite())
                .collect();
            let series = chart
                .draw_series(LineSeries::new(line, colour.stroke_width(2)))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            if ch == 0 {
                series
                    .label(format!("sum of {} exponentials", f.model.n()))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2))
                    });
            }
        }
        if (args.plot_dipole || args.model == ModelKind::Dipole)
            && let Ok(d) = fit_dipole(&curve.r, s, dipole_options)
        {
            let line: Vec<(f64, f64)> = xs
                .iter()
                .map(|&x| (x, d.scale * d.dipole.r_d(x)))
                .filter(|p| p.1 > 0.0 && p.1.is_finite())
                .collect();
            let style = ShapeStyle::from(&colour).stroke_width(1);
            let series = chart
                .draw_series(DashedLineSeries::new(line, 6, 4, style))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
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
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
