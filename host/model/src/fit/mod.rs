//! Fitting the empirical model (section 4.2 and 5 of Fuchs et al. 2005) and the dipole to samples.
//!
//! Contract: pure functions of their inputs (no files, no clocks, no global state), deterministic,
//! and total: every input — NaN, infinities, zero or negative values, one sample, all samples at
//! one distance, 1:10⁸ dynamic range, huge or tiny units — gives either a validated model with
//! finite parameters or a [`FitFailure`] saying why. Samples that cannot be used are dropped and
//! counted in a [`SampleReport`].
//!
//! Solvers: the specialised Levenberg–Marquardt of this module (normal equations accumulated row
//! by row, analytic Jacobians, a binned pre-fit for start values) and, as the reference, the
//! `levenberg-marquardt` crate on the same residuals ([`Solver::Reference`]). Objectives: the
//! paper's logarithmic residual (Eq. 4) or the ordinary linear residual.
//!
//! Fast mode ([`FitOptions::bins`]): fit the sufficient statistics of distance bins instead of
//! the samples (see [`bins`]); the bin count trades speed for accuracy.

pub mod aniso;
pub mod bins;
pub mod dipole;
mod isotropic;
mod lm;
mod reference;
pub mod samples;
mod simd;

use std::borrow::Cow;

use serde::{Deserialize, Serialize};

use crate::model::{ExpSum, MAX_TERMS, Term};
pub use isotropic::ln_many;
pub(crate) use isotropic::ln_sum_exp_many;
pub use samples::{SampleReport, clean};

/// Which residual is minimised.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Objective {
    /// Eq. 4: ln(R_d / s), uniform relative errors across the dynamic range (the paper's choice).
    #[default]
    Log,
    /// R_d − s, the ordinary least-squares residual (dominated by the brightest samples).
    Linear,
}

/// Which Levenberg–Marquardt implementation runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Solver {
    /// The specialised solver of this module.
    #[default]
    Specialised,
    /// The `levenberg-marquardt` crate on the same residuals and Jacobians, from the same start.
    Reference,
}

/// How many exponential terms n (Eq. 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Terms {
    /// Exactly n terms, 1..=[`MAX_TERMS`].
    Fixed(usize),
    /// "Model only what the scene requires": try n = 1..=max and keep the smallest n whose log E
    /// is within `tolerance` (relative) of the best one.
    Auto {
        /// Largest n tried.
        max: usize,
        /// Relative tolerance on log E, e.g. 0.05 = within 5 % of the best.
        tolerance: f64,
    },
}

/// Settings of one fit. [`Preset`] gives tested combinations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitOptions {
    /// Number of terms, fixed or automatic.
    pub terms: Terms,
    /// Residual to minimise.
    pub objective: Objective,
    /// Solver implementation.
    pub solver: Solver,
    /// Iteration limit of each Levenberg–Marquardt run.
    pub max_iterations: usize,
    /// Fast mode: fit this many distance bins' sufficient statistics instead of the samples
    /// (log objective and specialised solver only; otherwise ignored).
    pub bins: Option<usize>,
    /// Use every k-th sample (1 = all); a cheap way to trade accuracy for speed.
    pub subsample: usize,
    /// Start values (n terms, c > 0, d < 0) instead of the automatic ones.
    pub start: Option<Vec<Term>>,
    /// Whether a fit that hit the iteration limit is a failure ([`FitFailure::NotConverged`]) or
    /// returned with `converged = false`.
    pub require_convergence: bool,
    /// Few samples: with fewer usable samples (or distinct distances) than 2n, fit the order
    /// they determine, n' = ⌊samples / 2⌋ (2 samples determine one term), instead of failing,
    /// and say so in [`ExpFit::reduced_from`]. Off by default: per-vertex fitting keeps one
    /// order and interpolates vertices with too few samples; `subsurf fit-curve` turns it on.
    pub reduce_order: bool,
    /// libm's exp and ln in the joint fit's one-segment normal equations instead of the
    /// vectorised ones of the exact isotropic fit (`isotropic::log_sum_exp_points`), and the
    /// joint solve to the last digits of its cost instead of [`aniso::JOINT_FTOL`]: the
    /// reference preset's exact path, the one every fit took before the default was made faster.
    #[serde(default)]
    pub libm: bool,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            terms: Terms::Fixed(3),
            objective: Objective::Log,
            solver: Solver::Specialised,
            max_iterations: 200,
            bins: None,
            subsample: 1,
            start: None,
            require_convergence: true,
            reduce_order: false,
            libm: false,
        }
    }
}

impl FitOptions {
    /// The same fit without the fast mode's approximations: every sample, no distance bins, at
    /// least the default iteration limit; `None` when these options are that already. What an
    /// approximate fit is checked against (the fit report's reflectance check: a
    /// preset may be noisier than the exact fit, never biased against it).
    pub fn exact_counterpart(&self) -> Option<FitOptions> {
        let exact = FitOptions {
            bins: None,
            subsample: 1,
            max_iterations: self
                .max_iterations
                .max(FitOptions::default().max_iterations),
            ..self.clone()
        };
        (exact != *self).then_some(exact)
    }
}

/// Speed/accuracy presets (their measured trade-off is in BENCHMARKS.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Fast previews: n = 3, 8 distance bins, every 2nd sample, isotropic.
    Draft,
    /// Production default: n = 3, 16 distance bins, all samples, 4 segments.
    Balanced,
    /// Exact fit on all samples, automatic n ≤ 4 (1 % tolerance), 8 segments.
    Best,
}

impl Preset {
    /// The isotropic fit options of this preset.
    pub fn options(self) -> FitOptions {
        match self {
            Self::Draft => FitOptions {
                terms: Terms::Fixed(3),
                bins: Some(8),
                subsample: 2,
                max_iterations: 30,
                ..FitOptions::default()
            },
            Self::Balanced => FitOptions {
                terms: Terms::Fixed(3),
                bins: Some(16),
                max_iterations: 100,
                ..FitOptions::default()
            },
            Self::Best => FitOptions {
                terms: Terms::Auto {
                    max: MAX_TERMS,
                    tolerance: 0.01,
                },
                max_iterations: 200,
                ..FitOptions::default()
            },
        }
    }

    /// Direction segments m for the anisotropic model (Eq. 3).
    pub fn segments(self) -> usize {
        match self {
            Self::Draft => 1,
            Self::Balanced => 4,
            Self::Best => 8,
        }
    }

    /// All presets, fastest first.
    pub const ALL: [Preset; 3] = [Self::Draft, Self::Balanced, Self::Best];

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Draft => "draft",
            Self::Balanced => "balanced",
            Self::Best => "best",
        }
    }
}

/// One candidate of automatic order selection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OrderCandidate {
    /// Number of terms (or segments) tried.
    pub order: usize,
    /// log E (Eq. 8) of that fit, or `None` if it failed.
    pub log_e: Option<f64>,
}

/// The report of automatic order selection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OrderChoice {
    /// The order chosen.
    pub chosen: usize,
    /// The relative tolerance used.
    pub tolerance: f64,
    /// Every order tried.
    pub candidates: Vec<OrderCandidate>,
}

/// "Model only what the scene requires": among candidates (order, log E or `None` if that fit
/// failed), in increasing order, the smallest order whose log E is within `tolerance` (relative)
/// of the best. `None` if every candidate failed. Shared by the automatic choice of terms
/// ([`Terms::Auto`]), of direction segments ([`aniso::fit_colour_auto_segments`]) and the
/// pipeline's `subsurf fit --segments auto`.
pub fn choose_order(candidates: &[(usize, Option<f64>)], tolerance: f64) -> Option<OrderChoice> {
    let best = candidates
        .iter()
        .filter_map(|c| c.1.filter(|v| v.is_finite()))
        .fold(f64::INFINITY, f64::min);
    let chosen = candidates
        .iter()
        .find(|c| c.1.is_some_and(|v| v <= best * (1.0 + tolerance) + 1e-15))?
        .0;
    Some(OrderChoice {
        chosen,
        tolerance,
        candidates: candidates
            .iter()
            .map(|&(order, log_e)| OrderCandidate { order, log_e })
            .collect(),
    })
}

/// A fitted isotropic fall-off (Eq. 1) and how it was obtained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExpFit {
    /// The model, terms in canonical order (slowest fall-off first).
    pub model: ExpSum,
    /// Residual sum of squares of the chosen objective over the used samples (original units for
    /// the linear objective).
    pub rss: f64,
    /// log E (Eq. 8, alpha = 1, all used samples): RMS of ln(R_d/s). In fast mode
    /// ([`FitOptions::bins`]) it is computed from the bin statistics (exact up to the cubic term
    /// of ln R_d across a bin, see [`bins`]) instead of another pass over the samples; so is
    /// `rss`.
    pub log_e: f64,
    /// Levenberg–Marquardt iterations (pre-fit plus final fit).
    pub iterations: usize,
    /// Whether the solver met its convergence test.
    pub converged: bool,
    /// Samples used and dropped.
    pub samples: SampleReport,
    /// The order selection, for [`Terms::Auto`].
    pub order: Option<OrderChoice>,
    /// The order asked for, when [`FitOptions::reduce_order`] lowered it to what the samples
    /// determine (`model.n()` is the order fitted); `None` when the order is the one asked for.
    pub reduced_from: Option<usize>,
    /// The solver stopped at a point that is not stationary (every step rejected, gradient not
    /// zero): reported, never counted as converged.
    pub stalled: bool,
}

/// Why a fit produced no model. A failure is data: callers (e.g. per-vertex fitting) count and
/// interpolate failed fits instead of aborting.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum FitFailure {
    /// Not enough usable samples for the number of parameters.
    #[error("too few usable samples: {usable}, need at least {needed}")]
    TooFewSamples {
        /// Usable samples after cleaning.
        usable: usize,
        /// Samples needed.
        needed: usize,
    },
    /// The samples lie at too few distinct distances to determine the rates.
    #[error("samples at only {distinct} distinct distance(s), need at least {needed}")]
    TooFewDistances {
        /// Distinct distances present.
        distinct: usize,
        /// Distinct distances needed.
        needed: usize,
    },
    /// The solver hit its iteration limit or stalled (and convergence was required).
    #[error("{} after {iterations} iterations (log E {log_e})", not_converged_kind(*.stalled))]
    NotConverged {
        /// Iterations used.
        iterations: usize,
        /// log E of the last iterate.
        log_e: f64,
        /// The solver stalled (no step reduced the cost, yet the gradient is not zero) rather
        /// than running out of iterations.
        stalled: bool,
    },
    /// The solver produced NaN or infinity.
    #[error("the fit produced non-finite values")]
    NonFinite,
    /// A parameter left the representable range.
    #[error("parameter out of range: {what}")]
    OutOfRange {
        /// What went out of range.
        what: &'static str,
    },
    /// The options are inconsistent.
    #[error("invalid fit options: {reason}")]
    InvalidOptions {
        /// What is wrong.
        reason: &'static str,
    },
}

fn not_converged_kind(stalled: bool) -> &'static str {
    if stalled {
        "stalled (no step reduces the cost, yet the gradient is not zero)"
    } else {
        "not converged"
    }
}

/// Samples needed for n terms: 2n parameters plus at least two degrees of freedom (and never
/// fewer than 4, so one to three samples always fail).
pub fn samples_needed(n: usize) -> usize {
    (2 * n + 2).max(4)
}

/// The largest order the samples determine: ⌊k / 2⌋ for k samples at distinct distances
/// (2n parameters need 2n equations), at most [`MAX_TERMS`].
pub fn determined_order(r: &[f64]) -> usize {
    samples::distinct_distances(r, 2 * MAX_TERMS) / 2
}

/// RMS of ln(R_d(r)/s) (Eq. 8 with alpha = 1 and t = 0) and, for `Objective::Linear`, Σ(R_d − s)².
fn errors(model: &ExpSum, r: &[f64], s: &[f64], objective: Objective) -> (f64, f64) {
    let (mut sq_log, mut sq_lin) = (0.0, 0.0);
    for (&ri, &si) in r.iter().zip(s) {
        let e = model.ln_eval(ri) - si.ln();
        sq_log += e * e;
        if objective == Objective::Linear {
            sq_lin += (model.eval(ri) - si).powi(2);
        }
    }
    let log_e = (sq_log / r.len().max(1) as f64).sqrt();
    let rss = match objective {
        Objective::Log => sq_log,
        Objective::Linear => sq_lin,
    };
    (rss, log_e)
}

/// Fits Eq. 1 to samples s(x_i, x_o) at distances r = |x_o − x_i|.
pub fn fit_expsum(r: &[f64], s: &[f64], options: &FitOptions) -> Result<ExpFit, FitFailure> {
    let (mut cr, mut cs, mut report) = clean_or_borrow(r, s);
    if options.subsample > 1 {
        cr = Cow::Owned(cr.iter().step_by(options.subsample).copied().collect());
        cs = Cow::Owned(cs.iter().step_by(options.subsample).copied().collect());
        report.skipped_subsample = report.used - cr.len();
        report.used = cr.len();
    }
    let (cr, cs) = (&*cr, &*cs);
    match options.terms {
        Terms::Fixed(n) => fit_order(cr, cs, n, options, report),
        Terms::Auto { max, tolerance } => {
            if !((1..=MAX_TERMS).contains(&max) && tolerance >= 0.0 && tolerance.is_finite()) {
                return Err(FitFailure::InvalidOptions {
                    reason: "auto order needs 1 <= max <= 4 and a finite tolerance >= 0",
                });
            }
            let mut fits: Vec<(usize, Result<ExpFit, FitFailure>)> = Vec::new();
            let max = if options.reduce_order {
                max.min(determined_order(cr)).max(1)
            } else {
                max
            };
            for n in 1..=max {
                let f = fit_order(cr, cs, n, options, report);
                let stop = matches!(
                    f,
                    Err(FitFailure::TooFewSamples { .. } | FitFailure::TooFewDistances { .. })
                );
                fits.push((n, f));
                if stop {
                    break;
                }
            }
            let log_es: Vec<(usize, Option<f64>)> = fits
                .iter()
                .map(|(n, f)| (*n, f.as_ref().ok().map(|f| f.log_e)))
                .collect();
            match choose_order(&log_es, tolerance) {
                Some(choice) => {
                    let i = fits
                        .iter()
                        .position(|(n, _)| *n == choice.chosen)
                        .ok_or(FitFailure::NonFinite)?;
                    let (_, f) = fits.swap_remove(i);
                    let mut fit = f?;
                    fit.order = Some(choice);
                    Ok(fit)
                }
                // Every order failed: report the simplest model's reason.
                None => match fits.into_iter().next() {
                    Some((_, Err(e))) => Err(e),
                    _ => Err(FitFailure::NonFinite),
                },
            }
        }
    }
}

/// [`clean`] without the copy when every sample is usable (the common case: a batch of
/// measured curves passes through here by the thousand, and copying each one is a measurable
/// part of `fit-curve --batch`); the same samples and report either way.
fn clean_or_borrow<'a>(
    r: &'a [f64],
    s: &'a [f64],
) -> (Cow<'a, [f64]>, Cow<'a, [f64]>, SampleReport) {
    // Comparisons are false for NaN: finite r >= 0 and finite s > 0, without branches (`&`,
    // not the short-circuiting `Range::contains`). Finite as x − x == 0 (NaN for ±inf and
    // NaN): written as `x < inf` the compiler turned the test into scalar bit arithmetic,
    // ~20 instructions a sample (3 % of `fit-curve --batch`, perf); as float arithmetic it
    // vectorises.
    // Under the SIMD dispatch ([`simd`]): four or eight samples a step instead of two.
    let usable = r.len() == s.len() && simd::wide(AllUsable { r, s });
    if usable {
        let report = SampleReport {
            input: r.len(),
            used: r.len(),
            ..SampleReport::default()
        };
        return (Cow::Borrowed(r), Cow::Borrowed(s), report);
    }
    let (cr, cs, report) = clean(r, s);
    (Cow::Owned(cr), Cow::Owned(cs), report)
}

/// The usability test of [`clean_or_borrow`] as a [`simd::Kernel`].
struct AllUsable<'a> {
    r: &'a [f64],
    s: &'a [f64],
}

impl simd::Kernel for AllUsable<'_> {
    type Output = bool;
    #[inline(always)]
    #[allow(clippy::eq_op)] // x − x is the finiteness test, not a mistake
    fn run(self) -> bool {
        self.r.iter().zip(self.s).fold(true, |ok, (&ri, &si)| {
            ok & (ri >= 0.0) & (ri - ri == 0.0) & (si > 0.0) & (si - si == 0.0)
        })
    }
}

fn fit_order(
    r: &[f64],
    s: &[f64],
    n: usize,
    options: &FitOptions,
    report: SampleReport,
) -> Result<ExpFit, FitFailure> {
    if !(1..=MAX_TERMS).contains(&n) {
        return Err(FitFailure::InvalidOptions {
            reason: "the number of terms must be 1..=4",
        });
    }
    if let Some(start) = &options.start
        && start.len() != n
    {
        return Err(FitFailure::InvalidOptions {
            reason: "start values must have as many terms as the fit",
        });
    }
    let requested = n;
    let n = if options.reduce_order {
        n.min(determined_order(r))
    } else {
        n
    };
    let needed = if options.reduce_order {
        2 * n.max(1)
    } else {
        samples_needed(n)
    };
    if n == 0 && r.len() >= 2 {
        return Err(FitFailure::TooFewDistances {
            distinct: samples::distinct_distances(r, 2),
            needed: 2,
        });
    }
    if n == 0 || r.len() < needed {
        return Err(FitFailure::TooFewSamples {
            usable: r.len(),
            needed,
        });
    }
    if n < requested && options.start.is_some() {
        return Err(FitFailure::InvalidOptions {
            reason: "start values were given for more terms than the samples determine",
        });
    }
    let distinct = samples::distinct_distances(r, 2 * n);
    // (No distance > 0: the first positive one ends the scan, not a pass over every sample.)
    if distinct < 2 * n || !r.iter().any(|&v| v > 0.0) {
        return Err(FitFailure::TooFewDistances {
            distinct,
            needed: 2 * n,
        });
    }
    let bins = match (options.objective, options.solver) {
        (Objective::Log, Solver::Specialised) => options.bins,
        _ => None,
    };
    let raw = isotropic::fit_fixed(
        r,
        s,
        n,
        options.objective,
        options.solver,
        bins,
        options.max_iterations,
        options.start.as_deref(),
    )?;
    let (rss, log_e) = match raw.rss_estimate {
        Some(rss) => (rss, (rss / r.len().max(1) as f64).sqrt()),
        None => errors(&raw.model, r, s, options.objective),
    };
    if !(rss.is_finite() && log_e.is_finite()) {
        return Err(FitFailure::NonFinite);
    }
    if !raw.converged && options.require_convergence {
        return Err(FitFailure::NotConverged {
            iterations: raw.iterations,
            log_e,
            stalled: raw.stalled,
        });
    }
    Ok(ExpFit {
        model: raw.model,
        rss,
        log_e,
        iterations: raw.iterations,
        converged: raw.converged,
        samples: report,
        order: None,
        reduced_from: (n < requested).then_some(requested),
        stalled: raw.stalled,
    })
}

#[cfg(test)]
mod tests;
