//! `subsurf fit-curve`: fit one fall-off curve (or many, `--batch`) from a CSV file. Parsing and
//! printing only; the fitting is `subsurf::curves::fitting`.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;

use subsurf::curves::fitting::{CurveFitSettings, CurveFitter, CurveModel};
use subsurf::fit::{Objective, Preset, Solver};

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

/// Runs the command.
pub fn run(args: Args) -> anyhow::Result<()> {
    let fitter = CurveFitter::new(&CurveFitSettings {
        model: match args.model {
            ModelKind::Expsum => CurveModel::Expsum,
            ModelKind::Dipole => CurveModel::Dipole,
        },
        preset: args.preset.map(|p| match p {
            PresetArg::Draft => Preset::Draft,
            PresetArg::Balanced => Preset::Balanced,
            PresetArg::Best => Preset::Best,
        }),
        objective: match args.objective {
            ObjectiveArg::Log => Objective::Log,
            ObjectiveArg::Linear => Objective::Linear,
        },
        solver: match args.solver {
            SolverArg::Specialised => Solver::Specialised,
            SolverArg::Reference => Solver::Reference,
        },
        terms: args.terms.clone(),
        tolerance: args.tolerance,
        bins: args.bins.clone(),
        max_iterations: args.max_iterations,
        start: args.start.clone(),
        eta: args.eta,
        absolute: args.absolute,
        json: args.json,
    })?;
    let fitted = fitter.fit_file(&args.input, args.batch, args.plot.is_some())?;
    // One buffered writer: a batch prints thousands of lines.
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    for line in &fitted.lines {
        writeln!(out, "{line}")?;
    }
    out.flush().context("writing the output")?;
    drop(out);
    if let Some(path) = &args.plot {
        let curve = fitted
            .first
            .context("nothing to plot: the file has no samples")?;
        fitter.plot(path, &curve, args.plot_dipole)?;
    }
    Ok(())
}
