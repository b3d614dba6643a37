//! Eq. 1 fitted to one fall-off curve: the least-squares problems (log objective Eq. 4, its binned
//! form, the linear objective), start values by peeling, and the driver.
//!
//! Parametrisation: θ = (a_1, b_1, …, a_n, b_n) with c_k = exp(a_k), d_k = −exp(b_k), in
//! normalised units (distances divided by the largest distance R, values by a reference level
//! exp(L)). The constraints c_k > 0, d_k < 0 of Eq. 1 hold for every finite θ, and huge or tiny
//! units only move L and R, never the conditioning of the solve.

use super::bins::{Bin, bin_by_distance};
use super::lm::{self, Problem, Settings};
use super::{FitFailure, Objective, Solver};
use crate::model::expsum::sort_terms;
use crate::model::{ExpSum, Term};
use nalgebra::{DMatrix, DVector};

/// Exact log objective (Eq. 4): residual ln R_d(r_j) − ln s_j per sample.
pub(crate) struct LogExact<'a> {
    pub r: &'a [f64],
    pub y: &'a [f64],
    pub n: usize,
}

/// Binned log objective: two residuals per bin (level and slope), see [`super::bins`].
pub(crate) struct LogBinned<'a> {
    pub bins: &'a [Bin],
    pub n: usize,
}

/// Linear objective: residual R_d(r_j) − s_j per sample.
pub(crate) struct Linear<'a> {
    pub r: &'a [f64],
    pub s: &'a [f64],
    pub n: usize,
}

const IDX: [usize; 2 * crate::model::MAX_TERMS] = [0, 1, 2, 3, 4, 5, 6, 7];

/// ln R_d(r) and the weights w_k = c_k e^{d_k r} / R_d (a log-sum-exp, so nothing underflows).
#[inline]
fn ln_and_weights(theta: &[f64], n: usize, r: f64, w: &mut [f64; 4], d: &mut [f64; 4]) -> f64 {
    let mut t = [0.0f64; 4];
    let mut m = f64::NEG_INFINITY;
    for k in 0..n {
        d[k] = -theta[2 * k + 1].exp();
        t[k] = theta[2 * k] + d[k] * r;
        m = m.max(t[k]);
    }
    let mut sum = 0.0;
    for k in 0..n {
        w[k] = (t[k] - m).exp();
        sum += w[k];
    }
    for wk in w.iter_mut().take(n) {
        *wk /= sum;
    }
    m + sum.ln()
}

impl Problem for LogExact<'_> {
    fn params(&self) -> usize {
        2 * self.n
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let n = self.n;
        let (mut w, mut d) = ([0.0; 4], [0.0; 4]);
        let mut vals = [0.0; 8];
        for (&r, &y) in self.r.iter().zip(self.y) {
            let l = ln_and_weights(theta, n, r, &mut w, &mut d);
            if !l.is_finite() {
                return false;
            }
            if jac {
                for k in 0..n {
                    vals[2 * k] = w[k];
                    vals[2 * k + 1] = w[k] * r * d[k];
                }
                row(l - y, &IDX[..2 * n], &vals[..2 * n]);
            } else {
                row(l - y, &[], &[]);
            }
        }
        true
    }
}

impl Problem for LogBinned<'_> {
    fn params(&self) -> usize {
        2 * self.n
    }
    fn rows(&self) -> usize {
        2 * self.bins.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let n = self.n;
        let (mut w, mut d) = ([0.0; 4], [0.0; 4]);
        let mut vals = [0.0; 8];
        for b in self.bins {
            let l = ln_and_weights(theta, n, b.r, &mut w, &mut d);
            if !l.is_finite() {
                return false;
            }
            let sn = b.n.sqrt();
            let g: f64 = (0..n).map(|k| w[k] * d[k]).sum();
            if jac {
                for k in 0..n {
                    vals[2 * k] = sn * w[k];
                    vals[2 * k + 1] = sn * w[k] * b.r * d[k];
                }
                row(sn * (l - b.y), &IDX[..2 * n], &vals[..2 * n]);
            } else {
                row(sn * (l - b.y), &[], &[]);
            }
            if b.srr > 0.0 {
                let ss = b.srr.sqrt();
                let beta = b.sry / b.srr;
                if jac {
                    for k in 0..n {
                        let dk = d[k] - g;
                        vals[2 * k] = ss * w[k] * dk;
                        vals[2 * k + 1] = ss * (w[k] + w[k] * b.r * dk) * d[k];
                    }
                    row(ss * (g - beta), &IDX[..2 * n], &vals[..2 * n]);
                } else {
                    row(ss * (g - beta), &[], &[]);
                }
            }
        }
        true
    }
}

impl Problem for Linear<'_> {
    fn params(&self) -> usize {
        2 * self.n
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let n = self.n;
        let mut vals = [0.0; 8];
        for (&r, &s) in self.r.iter().zip(self.s) {
            let mut v = 0.0;
            for k in 0..n {
                let d = -theta[2 * k + 1].exp();
                let e = (theta[2 * k] + d * r).exp();
                v += e;
                vals[2 * k] = e;
                vals[2 * k + 1] = e * r * d;
            }
            if !v.is_finite() {
                return false;
            }
            if jac {
                row(v - s, &IDX[..2 * n], &vals[..2 * n]);
            } else {
                row(v - s, &[], &[]);
            }
        }
        true
    }
}

/// Linear objective by variable projection (Golub–Pereyra, Kaufman's Jacobian): for given rates
/// the amplitudes are the linear least-squares solution (QR), so Levenberg–Marquardt runs over the
/// n rates only (θ = b_k, d_k = −exp(b_k)). Eliminating the amplitudes removes the long curved
/// valleys that make sums of exponentials hard for a full 2n-parameter solve.
pub(crate) struct VarPro<'a> {
    pub r: &'a [f64],
    pub s: &'a [f64],
    pub n: usize,
}

impl VarPro<'_> {
    /// Amplitudes c for rates θ, or `None` if the basis is rank deficient.
    pub(crate) fn amplitudes(
        &self,
        theta: &[f64],
    ) -> Option<(DVector<f64>, DMatrix<f64>, DMatrix<f64>)> {
        let (m, n) = (self.r.len(), self.n);
        // Coalescing rates make the basis singular (amplitudes ±∞): treat as infeasible so the
        // solver backs off instead of sliding into that limit.
        for i in 0..n {
            for j in (i + 1)..n {
                if (theta[i] - theta[j]).abs() < 1e-3 {
                    return None;
                }
            }
        }
        let d: Vec<f64> = theta.iter().map(|b| -b.exp()).collect();
        let phi = DMatrix::from_fn(m, n, |i, k| (d[k] * self.r[i]).exp());
        let qr = phi.clone().qr();
        let q = qr.q();
        let rr = qr.r();
        let y = DVector::from_column_slice(self.s);
        let c = rr.solve_upper_triangular(&(q.transpose() * &y))?;
        c.iter().all(|v| v.is_finite()).then_some((c, phi, q))
    }
}

impl Problem for VarPro<'_> {
    fn params(&self) -> usize {
        self.n
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let Some((c, phi, q)) = self.amplitudes(theta) else {
            return false;
        };
        let (m, n) = (self.r.len(), self.n);
        let y = DVector::from_column_slice(self.s);
        let res = &phi * &c - y;
        if !jac {
            for v in res.iter() {
                row(*v, &[], &[]);
            }
            return res.iter().all(|v| v.is_finite());
        }
        // Kaufman: ∂res/∂b_k ≈ P⊥·(∂Φ/∂b_k)·c, P⊥ = I − QQᵀ.
        let mut j = DMatrix::zeros(m, n);
        for k in 0..n {
            let dk = -theta[k].exp();
            let v = DVector::from_fn(m, |i, _| c[k] * self.r[i] * phi[(i, k)] * dk);
            let proj = &v - &q * (q.transpose() * &v);
            j.set_column(k, &proj);
        }
        let idx: Vec<usize> = (0..n).collect();
        let mut vals = vec![0.0; n];
        for i in 0..m {
            for k in 0..n {
                vals[k] = j[(i, k)];
            }
            row(res[i], &idx, &vals);
        }
        res.iter().all(|v| v.is_finite()) && j.iter().all(|v| v.is_finite())
    }
}

/// The linear objective with the specialised solver: variable projection from the start rates
/// with a tight and a loose trust region, and, should both end in coalescing rates or negative
/// amplitudes, a full 2n-parameter run whose rates restart the projection. The best admissible
/// (all c_k > 0) result wins.
fn linear_specialised(
    rn: &[f64],
    sn: &[f64],
    n: usize,
    theta0: &[f64],
    settings: &Settings,
) -> Option<lm::Outcome> {
    let vp = VarPro { r: rn, s: sn, n };
    let finish = |o: lm::Outcome| -> Option<lm::Outcome> {
        let (c, _, _) = vp.amplitudes(&o.theta)?;
        if c.iter().any(|v| *v <= 0.0) {
            return None;
        }
        let theta = (0..n).flat_map(|k| [c[k].ln(), o.theta[k]]).collect();
        Some(lm::Outcome { theta, ..o })
    };
    let better = |a: Option<lm::Outcome>, b: Option<lm::Outcome>| match (a, b) {
        (Some(a), Some(b)) => Some(if (b.converged, -b.cost) > (a.converged, -a.cost) {
            b
        } else {
            a
        }),
        (a, b) => a.or(b),
    };
    let rates0: Vec<f64> = (0..n).map(|k| theta0[2 * k + 1]).collect();
    let mut best: Option<lm::Outcome> = None;
    let mut iterations = 0;
    for max_step in [1.0, 4.0] {
        let s = Settings {
            max_step,
            ..*settings
        };
        if let Some(o) = lm::minimize(&vp, &rates0, &s) {
            iterations += o.iterations;
            best = better(best, finish(o));
        }
        if best.as_ref().is_some_and(|b| b.converged) {
            break;
        }
    }
    if !best.as_ref().is_some_and(|b| b.converged)
        && let Some(full) = lm::minimize(&Linear { r: rn, s: sn, n }, theta0, settings)
    {
        iterations += full.iterations;
        let rates: Vec<f64> = (0..n).map(|k| full.theta[2 * k + 1]).collect();
        let restarted = lm::minimize(&vp, &rates, settings).and_then(finish);
        if let Some(o) = &restarted {
            iterations += o.iterations;
        }
        best = better(better(best, Some(full)), restarted);
    }
    best.map(|b| lm::Outcome { iterations, ..b })
}

/// Weighted line fit y ≈ a + b·x; `None` if degenerate.
fn line_fit(pts: &[(f64, f64, f64)]) -> Option<(f64, f64)> {
    let w: f64 = pts.iter().map(|p| p.2).sum();
    if pts.len() < 2 || w <= 0.0 {
        return None;
    }
    let mx = pts.iter().map(|p| p.2 * p.0).sum::<f64>() / w;
    let my = pts.iter().map(|p| p.2 * p.1).sum::<f64>() / w;
    let sxx: f64 = pts.iter().map(|p| p.2 * (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| p.2 * (p.0 - mx) * (p.1 - my)).sum();
    if sxx.is_nan() || sxx <= 0.0 {
        return None;
    }
    let b = sxy / sxx;
    Some((my - b * mx, b))
}

/// A term whose amplitude is below 1e-6 of the largest contributes nothing the data can see: the
/// solver fell into the "switch a term off" valley and another start is worth a try.
fn has_dead_term(theta: &[f64], n: usize) -> bool {
    let amax = (0..n)
        .map(|k| theta[2 * k])
        .fold(f64::NEG_INFINITY, f64::max);
    (0..n).any(|k| theta[2 * k] < amax - 13.8)
}

/// Start candidates, best (lowest binned log cost) first: the peeled start, and rates spread
/// geometrically (factor 3 and 8 apart) around the overall fall-off rate, each with amplitudes
/// from the non-negative least-squares fit.
pub(crate) fn starts(bins: &[Bin], n: usize) -> Vec<Vec<f64>> {
    let mut out = vec![peel(bins, n)];
    if n > 1 {
        let pts: Vec<(f64, f64, f64)> = bins.iter().map(|b| (b.r, b.y, b.n)).collect();
        let rho = line_fit(&pts).map_or(1.0, |(_, b)| (-b).max(0.5));
        for q in [3.0f64, 8.0] {
            let rates: Vec<f64> = (0..n)
                .map(|k| rho * q.powf(k as f64 - (n - 1) as f64 / 2.0))
                .collect();
            let mut amps: Vec<f64> = vec![(bins.first().map_or(0.0, |b| b.y)).exp() / n as f64; n];
            nnls_amplitudes(bins, &rates, &mut amps);
            let cmax = amps.iter().cloned().fold(0.0, f64::max).max(1e-300);
            out.push(
                (0..n)
                    .flat_map(|k| [amps[k].max(cmax * 1e-3).ln(), rates[k].ln()])
                    .collect(),
            );
        }
    }
    let problem = LogBinned { bins, n };
    let cost = |t: &Vec<f64>| {
        let mut c = 0.0;
        let ok = problem.eval(t, false, |r, _, _| c += r * r);
        if ok && c.is_finite() {
            c
        } else {
            f64::INFINITY
        }
    };
    let mut scored: Vec<(f64, Vec<f64>)> = out.into_iter().map(|t| (cost(&t), t)).collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    scored.into_iter().map(|(_, t)| t).collect()
}

/// Start values by peeling the tail in log space: the slowest term is a line through ln s over
/// the farthest group of bins; it is subtracted and the next group gives the next term, up to the
/// fastest term near x_i. Rates are forced to grow by ≥ 1.5× per term (well separated, ordered),
/// then the amplitudes are re-solved by non-negative least squares with relative weights for
/// those rates. Returns θ in normalised units.
pub(crate) fn peel(bins: &[Bin], n: usize) -> Vec<f64> {
    let nb = bins.len();
    let mut resid: Vec<f64> = bins.iter().map(|b| b.y.exp()).collect();
    let mut rates = vec![0.0f64; n];
    let mut amps = vec![0.0f64; n];
    let mut prev_rate: f64 = 0.0;
    for k in (0..n).rev() {
        // Group k of n contiguous groups (k = 0 nearest).
        let lo = nb * k / n;
        let hi = (nb * (k + 1) / n).max(lo + 1).min(nb);
        let pts: Vec<(f64, f64, f64)> = (lo..hi)
            .filter(|&i| resid[i] > 0.0 && resid[i].is_finite())
            .map(|i| (bins[i].r, resid[i].ln(), bins[i].n))
            .collect();
        let fitted = line_fit(&pts).filter(|(a, b)| a.is_finite() && *b < 0.0);
        let floor = if prev_rate > 0.0 {
            prev_rate * 1.5
        } else {
            0.5
        };
        let (a, rate) = match fitted {
            Some((a, b)) if -b >= floor => (a, -b),
            _ => {
                let rate = floor.max(if prev_rate > 0.0 {
                    prev_rate * 3.0
                } else {
                    1.0
                });
                // Amplitude from the group's mean level at that rate.
                let a = if pts.is_empty() {
                    0.0
                } else {
                    pts.iter().map(|p| p.1 + rate * p.0).sum::<f64>() / pts.len() as f64
                };
                (a, rate)
            }
        };
        rates[k] = rate;
        amps[k] = a.clamp(-700.0, 700.0).exp();
        prev_rate = rate;
        for i in 0..lo {
            resid[i] -= amps[k] * (-rate * bins[i].r).exp();
        }
    }
    nnls_amplitudes(bins, &rates, &mut amps);
    let mut theta = Vec::with_capacity(2 * n);
    let cmax = amps.iter().cloned().fold(0.0, f64::max).max(1e-300);
    for k in 0..n {
        theta.push(amps[k].max(cmax * 1e-3).ln());
        theta.push(rates[k].ln());
    }
    theta
}

/// Amplitudes c ≥ 0 minimising Σ_b n_b·((Σ_k c_k e^{−rate_k r̄_b} − v_b)/v_b)² (relative error,
/// like the log objective) by a small active-set NNLS; leaves `amps` alone if nothing fits.
fn nnls_amplitudes(bins: &[Bin], rates: &[f64], amps: &mut [f64]) {
    let n = rates.len();
    let mut active: Vec<bool> = vec![true; n];
    for _ in 0..n {
        let idx: Vec<usize> = (0..n).filter(|&k| active[k]).collect();
        let m = idx.len();
        if m == 0 {
            return;
        }
        let mut a = vec![0.0; m * m];
        let mut rhs = vec![0.0; m];
        for b in bins {
            let v = b.y.exp();
            if !(v > 0.0 && v.is_finite()) {
                continue;
            }
            let wgt = b.n / (v * v);
            let e: Vec<f64> = idx.iter().map(|&k| (-rates[k] * b.r).exp()).collect();
            for i in 0..m {
                rhs[i] += wgt * e[i] * v;
                for j in 0..m {
                    a[i * m + j] += wgt * e[i] * e[j];
                }
            }
        }
        let mut x = vec![0.0; m];
        let mut scratch = vec![0.0; m * m];
        if !super::lm::solve_plain(&a, &rhs, &mut x, &mut scratch) {
            return;
        }
        if x.iter().all(|v| *v > 0.0) {
            for (i, &k) in idx.iter().enumerate() {
                amps[k] = x[i];
            }
            for k in 0..n {
                if !active[k] {
                    amps[k] = 0.0;
                }
            }
            return;
        }
        let worst = (0..m)
            .min_by(|&i, &j| x[i].total_cmp(&x[j]))
            .map(|i| idx[i])
            .unwrap_or(0);
        active[worst] = false;
    }
}

/// Bins of the pre-fit that gives the exact log fit its start (and of the start values).
pub(crate) const PREFIT_BINS: usize = 64;

/// What one fixed-order fit produced, in original units.
pub(crate) struct Raw {
    pub model: ExpSum,
    pub iterations: usize,
    pub converged: bool,
}

/// Fixed-order isotropic fit on cleaned samples (r ≥ 0 finite, s > 0 finite, enough of them).
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_fixed(
    r: &[f64],
    s: &[f64],
    n: usize,
    objective: Objective,
    solver: Solver,
    bins: Option<usize>,
    max_iterations: usize,
    start: Option<&[Term]>,
) -> Result<Raw, FitFailure> {
    let scale_r = r.iter().cloned().fold(0.0, f64::max);
    let ln_s: Vec<f64> = s.iter().map(|v| v.ln()).collect();
    let level = match objective {
        Objective::Log => ln_s.iter().sum::<f64>() / ln_s.len() as f64,
        Objective::Linear => ln_s.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    };
    let rn: Vec<f64> = r.iter().map(|v| v / scale_r).collect();
    let y: Vec<f64> = ln_s.iter().map(|v| v - level).collect();
    // Bins feed the start values and the pre-fit (the whole fit in fast mode).
    let prefit_bins = bin_by_distance(&rn, &y, bins.unwrap_or(PREFIT_BINS).max(2 * n + 2));
    let theta0 = match start {
        Some(terms) => {
            let mut t = Vec::with_capacity(2 * n);
            for term in terms {
                t.push(term.c.ln() - level);
                t.push((-term.d * scale_r).ln());
            }
            if t.len() != 2 * n || t.iter().any(|v| !v.is_finite()) {
                return Err(FitFailure::InvalidOptions {
                    reason: "start values must be n terms with c > 0 and d < 0",
                });
            }
            t
        }
        None => starts(&prefit_bins, n).swap_remove(0),
    };
    let settings = Settings {
        max_iterations,
        ..Settings::default()
    };
    let mut iterations = 0;
    let out = match (objective, solver) {
        (Objective::Log, Solver::Specialised) => {
            // Binned pre-fit (the whole fit in fast mode) from each start candidate until one
            // converges with every term alive, then polish on every sample.
            let candidates = match start {
                Some(_) => vec![theta0.clone()],
                None => starts(&prefit_bins, n),
            };
            let binned = LogBinned {
                bins: &prefit_bins,
                n,
            };
            let mut pre: Option<lm::Outcome> = None;
            for cand in &candidates {
                let Some(o) = lm::minimize(&binned, cand, &settings) else {
                    continue;
                };
                iterations += o.iterations;
                let healthy = o.converged && !has_dead_term(&o.theta, n);
                if pre.as_ref().is_none_or(|p| o.cost < p.cost) {
                    pre = Some(o);
                }
                if healthy {
                    break;
                }
            }
            if bins.is_some() {
                pre.map(|o| lm::Outcome { iterations, ..o })
            } else {
                let theta1 = pre.map_or_else(|| theta0.clone(), |o| o.theta);
                lm::minimize(&LogExact { r: &rn, y: &y, n }, &theta1, &settings)
            }
        }
        (Objective::Log, Solver::Reference) => {
            super::reference::minimize(&LogExact { r: &rn, y: &y, n }, &theta0, max_iterations)
        }
        (Objective::Linear, Solver::Specialised) => {
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            linear_specialised(&rn, &sn, n, &theta0, &settings)
        }
        (Objective::Linear, Solver::Reference) => {
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            super::reference::minimize(&Linear { r: &rn, s: &sn, n }, &theta0, max_iterations)
        }
    };
    let out = out.ok_or(FitFailure::NonFinite)?;
    iterations += out.iterations;
    let mut terms = Vec::with_capacity(n);
    for k in 0..n {
        let c = (out.theta[2 * k] + level).exp();
        let d = -out.theta[2 * k + 1].exp() / scale_r;
        if !(c.is_finite() && d.is_finite()) {
            return Err(FitFailure::NonFinite);
        }
        if c <= 0.0 {
            return Err(FitFailure::OutOfRange {
                what: "an amplitude c underflowed to 0",
            });
        }
        if d >= 0.0 {
            return Err(FitFailure::OutOfRange {
                what: "a rate d underflowed to 0",
            });
        }
        terms.push(Term { c, d });
    }
    sort_terms(&mut terms);
    let model = ExpSum::new(terms).map_err(|_| FitFailure::NonFinite)?;
    Ok(Raw {
        model,
        iterations,
        converged: out.converged,
    })
}
