//! Fitting the dipole (Jensen et al. 2001) to one channel's samples, for the comparison of
//! Figure 3: sigma_s' and sigma_a with eta fixed, and a free overall scale k (camera samples are
//! relative, not absolute reflectance) unless [`DipoleOptions::absolute`] fixes k = 1.
//!
//! Objective: the log residual ln(k·R_d(r)) − ln s (Eq. 4). Parameters are ln sigma_s' and
//! ln sigma_a; ln k is eliminated in closed form (see [`DipoleProblem`]). The Jacobian is
//! analytic (checked against finite differences in the tests), and the reference solver sees the
//! same residuals. Start values: a grid over the albedo and the length scale, then a pre-fit on
//! binned samples from the best few grid rows (see [`grid_starts`]).

use std::cell::RefCell;

use serde::{Deserialize, Serialize};

use super::bins::bin_samples;
use super::lm::{self, Problem, Settings};
use super::{FitFailure, SampleReport, Solver, clean};
use crate::model::Dipole;

/// Settings of a dipole fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DipoleOptions {
    /// Fixed relative index of refraction eta.
    pub eta: f64,
    /// Samples are absolute R_d (k = 1) instead of relative.
    pub absolute: bool,
    /// Solver implementation.
    pub solver: Solver,
    /// Iteration limit.
    pub max_iterations: usize,
}

impl Default for DipoleOptions {
    fn default() -> Self {
        Self {
            eta: 1.3,
            absolute: false,
            solver: Solver::Specialised,
            max_iterations: 200,
        }
    }
}

/// A fitted dipole.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DipoleFit {
    /// The dipole (eta as given).
    pub dipole: Dipole,
    /// Overall scale k between samples and R_d (1 when absolute).
    pub scale: f64,
    /// Σ (ln(k·R_d) − ln s)².
    pub rss: f64,
    /// log E (Eq. 8, alpha = 1): RMS of ln(k·R_d/s).
    pub log_e: f64,
    /// Solver iterations.
    pub iterations: usize,
    /// Whether the solver met its convergence test.
    pub converged: bool,
    /// The solver stalled at a non-stationary point (reported, not counted as converged).
    pub stalled: bool,
    /// Samples used and dropped.
    pub samples: SampleReport,
}

/// The dipole's log residuals ln(k·R_d(r_j)) − ln s_j over θ = (ln sigma_s', ln sigma_a), with
/// optional weights.
///
/// The scale is eliminated exactly (variable projection for an additive constant): for given
/// sigma_s', sigma_a the best ln k is the weighted mean of ln s − ln R_d, so the residuals are the
/// weighted-centred ln R_d − ln s and their Jacobian the centred columns of ∂ln R_d. The solver
/// then searches two shape parameters only, and no valley along k exists for it to follow.
/// With `absolute`, k = 1 and nothing is centred.
///
/// Every evaluation makes two passes: the first evaluates the model per sample (the
/// transcendental work, once per sample for residual and Jacobian together, see [`DipoleEval`])
/// into a scratch buffer and sums the weighted means; the second centres and accumulates. The
/// buffer lives with the problem and is reused, so an evaluation allocates nothing; centring
/// from stored values keeps the cost exact where a one-pass Σe² − W·ē² would cancel (a free
/// scale far from 1 with exact samples leaves residuals 1e-8 on an ē near 1).
pub(crate) struct DipoleProblem<'a> {
    r: &'a [f64],
    y: &'a [f64],
    w: Option<&'a [f64]>,
    eta: f64,
    absolute: bool,
    scratch: RefCell<Scratch>,
}

/// The reusable first-pass buffer, and the centring shifts ē of the last few parameter points
/// (the fitted ln k = −ē of the solver's final point is then looked up, not recomputed).
#[derive(Default)]
struct Scratch {
    terms: Vec<Terms>,
    recent: [Option<([f64; 2], f64)>; 4],
    next: usize,
}

/// One sample's first-pass values: the residual e = ln R_d − y before centring and the two
/// source sums (A, B) of [`DipoleEval::terms`] that its gradient is affine in.
#[derive(Clone, Copy, Default)]
struct Terms {
    e: f64,
    a: f64,
    b: f64,
}

/// Weighted sums of the first pass.
struct Sums {
    w: f64,
    e: f64,
    a: f64,
    b: f64,
}

/// ln R_d and its gradient for one parameter point, with the per-θ constants computed once
/// (Jensen et al. 2001, Eq. 4–5 of that paper; names as in [`Dipole::ln_r_d`]).
///
/// Per sample it costs two square roots, one exp, one ln and (with the gradient) four
/// divisions: with d_i = sqrt(r² + z_i²), u_i = sigma_tr·d_i and T_i = z_i(1 + u_i)e^{−u_i}/d_i³
/// the two sources, ln R_d = ln(alpha'/4π) + ln z_r − u_r + ln P with
/// P = e^{u_r}(T_r + T_v)/z_r = (1 + u_r)/d_r³ + (z_v/z_r)(1 + u_v)e^{−(u_v − u_r)}/d_v³. The
/// exponent u_v − u_r is ≥ 0 (z_v > z_r), so P is the log-sum-exp of the two sources with the
/// real one factored out: no overflow, and the virtual source can only add (P is at most
/// (1 + z_v/z_r) times the first term). Its rounding, about ε·u_v absolute, is the one the
/// two separate exponents of [`Dipole::ln_r_d`] have. Where d³ itself leaves the range of f64
/// (distances or depths beyond about 1e±100) the same sum is taken in logs instead.
struct DipoleEval {
    sigma_tr: f64,
    /// z_r², z_v².
    z2: [f64; 2],
    /// z_v / z_r.
    ratio: f64,
    /// ln(alpha'/4π) + ln z_r.
    c0: f64,
    /// ∂/∂(ln sigma_s', ln sigma_a) of ln sigma_t' (g) and ln sigma_tr (h), and ∂ln alpha' − g
    /// (c): the gradient of ln R_d is c + g·A − h·B (see [`DipoleEval::gradient`]).
    g: [f64; 2],
    h: [f64; 2],
    c: [f64; 2],
}

/// One sample's sources (see [`DipoleEval`]): d_i², u_i, 1/d_i², T_r·e^{u_r}/z_r and P.
struct Sources {
    d2: [f64; 2],
    u: [f64; 2],
    i2: [f64; 2],
    tr: f64,
    p: f64,
}

impl DipoleEval {
    fn new(theta: &[f64], eta: f64) -> Option<Self> {
        let (s, a) = (theta[0].exp(), theta[1].exp());
        let t = s + a;
        let alpha = s / t;
        let sigma_tr = (3.0 * a * t).sqrt();
        let z_r = 1.0 / t;
        let z_v = z_r * (1.0 + 4.0 * crate::model::dipole::a_of_eta(eta) / 3.0);
        let q = a / t;
        let c0 = (alpha / (4.0 * std::f64::consts::PI)).ln() + z_r.ln();
        let out = Self {
            sigma_tr,
            z2: [z_r * z_r, z_v * z_v],
            ratio: z_v / z_r,
            c0,
            g: [alpha, q],
            h: [0.5 * alpha, 0.5 * (1.0 + q)],
            // ∂ln alpha' = (q, −q).
            c: [q - alpha, -q - q],
        };
        (c0.is_finite()
            && sigma_tr.is_finite()
            && out.ratio.is_finite()
            && out.z2[1].is_finite()
            && z_r > 0.0)
            .then_some(out)
    }

    /// The two sources at distance r, up to the shared factor (see the type's comment).
    #[inline]
    fn sources(&self, r: f64) -> Sources {
        let r2 = r * r;
        let (d2r, d2v) = (r2 + self.z2[0], r2 + self.z2[1]);
        let (dr, dv) = (d2r.sqrt(), d2v.sqrt());
        let (ur, uv) = (self.sigma_tr * dr, self.sigma_tr * dv);
        let du = uv - ur;
        let (ir, iv) = (1.0 / dr, 1.0 / dv);
        let (i2r, i2v) = (ir * ir, iv * iv);
        let tr = (1.0 + ur) * i2r * ir;
        let tv = self.ratio * (1.0 + uv) * (-du).exp() * i2v * iv;
        Sources {
            d2: [d2r, d2v],
            u: [ur, uv],
            i2: [i2r, i2v],
            tr,
            p: tr + tv,
        }
    }

    /// ln R_d(r) alone.
    #[inline]
    fn value(&self, r: f64) -> f64 {
        let s = self.sources(r);
        let ln_p = if s.p.is_normal() && s.tr.is_normal() {
            s.p.ln()
        } else {
            self.terms_wide(s.d2, s.u).0
        };
        self.c0 - s.u[0] + ln_p
    }

    /// ln R_d(r) and the source sums A = Σ_i w_i(f_i + 3)ζ_i, B = Σ_i w_i f_i that its gradient
    /// is affine in ([`DipoleEval::gradient`]); w_i = T_i/(T_r + T_v) are the sources' shares,
    /// f_i = u_i²/(1 + u_i), ζ_i = z_i²/d_i². Derivation: with t = sigma_t' and z ∝ 1/t,
    /// ∂ln z = −∂ln t, ∂ln d = −ζ·∂ln t and
    /// ∂ln T = ∂ln z − f·(∂ln sigma_tr + ∂ln d) − 3·∂ln d = −∂ln t(1 − (f + 3)ζ) − f·∂ln sigma_tr;
    /// the sources combine with their shares, and ln alpha' adds its own derivative. One
    /// division serves both f_i.
    #[inline]
    fn terms(&self, r: f64) -> (f64, f64, f64) {
        let s = self.sources(r);
        let [ur, uv] = s.u;
        let q = 1.0 / ((1.0 + ur) * (1.0 + uv));
        let wr = s.tr / s.p;
        let wv = 1.0 - wr;
        // u²/(1 + u) with the other source's factor cancelling: u·(u/(1 + u)).
        let (fr, fv) = (ur * (ur * ((1.0 + uv) * q)), uv * (uv * ((1.0 + ur) * q)));
        let (zr, zv) = (self.z2[0] * s.i2[0], self.z2[1] * s.i2[1]);
        let fast = s.p.is_normal() && s.tr.is_normal() && q.is_normal() && s.i2[0].is_finite();
        let (ln_p, a, b) = if fast {
            (
                s.p.ln(),
                wr * (fr + 3.0) * zr + wv * (fv + 3.0) * zv,
                wr * fr + wv * fv,
            )
        } else {
            self.terms_wide(s.d2, s.u)
        };
        (self.c0 - ur + ln_p, a, b)
    }

    /// ln P and the source sums (A, B) of [`DipoleEval::terms`] where d³ or (1 + u_r)(1 + u_v)
    /// leave the range of f64, from ratios that stay in range: ρ = T_v/T_r =
    /// (z_v/z_r)·((1 + u_v)/(1 + u_r))·(d_r²/d_v²)^1.5·e^{−(u_v − u_r)}, ln P =
    /// ln(1 + u_r) − 1.5·ln d_r² + ln(1 + ρ), and each quotient divided on its own.
    #[cold]
    fn terms_wide(&self, [d2r, d2v]: [f64; 2], [ur, uv]: [f64; 2]) -> (f64, f64, f64) {
        let rho = self.ratio * ((1.0 + uv) / (1.0 + ur)) * (d2r / d2v).powf(1.5) * (ur - uv).exp();
        let wr = 1.0 / (1.0 + rho);
        let wv = 1.0 - wr;
        let (fr, fv) = (ur * (ur / (1.0 + ur)), uv * (uv / (1.0 + uv)));
        let (zr, zv) = (self.z2[0] / d2r, self.z2[1] / d2v);
        (
            ur.ln_1p() - 1.5 * d2r.ln() + rho.ln_1p(),
            wr * (fr + 3.0) * zr + wv * (fv + 3.0) * zv,
            wr * fr + wv * fv,
        )
    }

    /// ∂ln R_d/∂(ln sigma_s', ln sigma_a) from the source sums of [`DipoleEval::terms`].
    #[inline]
    fn gradient(&self, a: f64, b: f64) -> [f64; 2] {
        [
            self.c[0] + self.g[0] * a - self.h[0] * b,
            self.c[1] + self.g[1] * a - self.h[1] * b,
        ]
    }
}

impl<'a> DipoleProblem<'a> {
    pub(crate) fn new(
        r: &'a [f64],
        y: &'a [f64],
        w: Option<&'a [f64]>,
        eta: f64,
        absolute: bool,
    ) -> Self {
        Self {
            r,
            y,
            w,
            eta,
            absolute,
            scratch: RefCell::new(Scratch::default()),
        }
    }

    fn len(&self) -> usize {
        let m = self.r.len().min(self.y.len());
        self.w.map_or(m, |w| m.min(w.len()))
    }

    /// First pass: e_j (and A_j, B_j with `terms`) into the scratch buffer, and their weighted
    /// sums; `None` if θ is infeasible or anything is non-finite.
    fn first_pass(
        &self,
        theta: &[f64],
        terms: bool,
        scratch: &mut Scratch,
    ) -> Option<(DipoleEval, Sums)> {
        let ev = DipoleEval::new(theta, self.eta)?;
        let out = &mut scratch.terms;
        let m = self.len();
        out.clear();
        out.resize(m, Terms::default());
        let mut sums = Sums {
            w: 0.0,
            e: 0.0,
            a: 0.0,
            b: 0.0,
        };
        let (r, y) = (&self.r[..m], &self.y[..m]);
        if terms {
            for ((t, &x), &yj) in out.iter_mut().zip(r).zip(y) {
                let (l, a, b) = ev.terms(x);
                *t = Terms { e: l - yj, a, b };
            }
        } else {
            for ((t, &x), &yj) in out.iter_mut().zip(r).zip(y) {
                t.e = ev.value(x) - yj;
            }
        }
        match self.w {
            Some(w) => {
                for (t, &wj) in out.iter().zip(w) {
                    sums.w += wj;
                    sums.e += wj * t.e;
                    sums.a += wj * t.a;
                    sums.b += wj * t.b;
                }
            }
            None => {
                sums.w = m as f64;
                for t in out.iter() {
                    sums.e += t.e;
                    sums.a += t.a;
                    sums.b += t.b;
                }
            }
        }
        if !(sums.e.is_finite() && sums.a.is_finite() && sums.b.is_finite()) {
            return None;
        }
        let e0 = self.shifts(&sums).0;
        let next = scratch.next;
        scratch.recent[next] = Some(([theta[0], theta[1]], e0));
        scratch.next = (next + 1) % scratch.recent.len();
        Some((ev, sums))
    }

    /// The centring shifts (ē, Ā, B̄): the weighted means with a free scale, zero when absolute
    /// (or without weight). −ē is the fitted ln k.
    fn shifts(&self, sums: &Sums) -> (f64, f64, f64) {
        if self.absolute || sums.w <= 0.0 {
            (0.0, 0.0, 0.0)
        } else {
            (sums.e / sums.w, sums.a / sums.w, sums.b / sums.w)
        }
    }

    /// The Jacobian row (before the weight) of a sample with source sums (a, b): the gradient
    /// of ln R_d, centred unless absolute (the constant part of the gradient then cancels).
    #[inline]
    fn row(&self, ev: &DipoleEval, t: &Terms, shift: (f64, f64)) -> [f64; 2] {
        if self.absolute {
            ev.gradient(t.a, t.b)
        } else {
            let (a, b) = (t.a - shift.0, t.b - shift.1);
            [ev.g[0] * a - ev.h[0] * b, ev.g[1] * a - ev.h[1] * b]
        }
    }

    /// The fitted ln k at θ (0 when absolute); `None` if infeasible. Looked up when θ was one
    /// of the last few points evaluated.
    fn ln_k(&self, theta: &[f64]) -> Option<f64> {
        self.with_scratch(|scratch| self.ln_k_in(theta, scratch))
    }

    /// [`DipoleProblem::ln_k`] in `scratch`.
    fn ln_k_in(&self, theta: &[f64], scratch: &mut Scratch) -> Option<f64> {
        let hit = scratch
            .recent
            .iter()
            .flatten()
            .find(|(t, _)| t[..] == theta[..2]);
        if let Some((_, e0)) = hit {
            return Some(-e0);
        }
        let (_, sums) = self.first_pass(theta, false, scratch)?;
        let k = -self.shifts(&sums).0;
        k.is_finite().then_some(k)
    }

    /// Σ res² at θ, infinite where infeasible.
    fn cost(&self, theta: &[f64]) -> f64 {
        self.with_scratch(|scratch| self.cost_in(theta, scratch))
    }

    /// [`DipoleProblem::cost`] in `scratch`.
    fn cost_in(&self, theta: &[f64], scratch: &mut Scratch) -> f64 {
        let Some((_, sums)) = self.first_pass(theta, false, scratch) else {
            return f64::INFINITY;
        };
        let buf = &scratch.terms;
        let (e0, _, _) = self.shifts(&sums);
        let cost = match self.w {
            Some(w) => buf
                .iter()
                .zip(w)
                .map(|(t, &wj)| wj * (t.e - e0) * (t.e - e0))
                .sum(),
            None => buf.iter().map(|t| (t.e - e0) * (t.e - e0)).sum::<f64>(),
        };
        if cost.is_finite() {
            cost
        } else {
            f64::INFINITY
        }
    }
}

impl Problem for DipoleProblem<'_> {
    fn params(&self) -> usize {
        2
    }
    fn rows(&self) -> usize {
        self.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, row: F) -> bool {
        self.with_scratch(|scratch| self.eval_rows(theta, jac, scratch, row))
    }

    /// One evaluation of the model per sample and θ for cost, gradient and JᵀJ together.
    fn normal_equations(
        &self,
        theta: &[f64],
        jtj: &mut [f64],
        jtr: &mut [f64],
    ) -> Option<Option<f64>> {
        Some(self.with_scratch(|scratch| self.normal(theta, jtj, jtr, scratch)))
    }
}

impl DipoleProblem<'_> {
    /// Runs `f` on the shared scratch buffer, or on a buffer of its own where the shared one is
    /// in use (a row callback of [`Problem::eval`] that evaluates this problem again): never a
    /// panic.
    fn with_scratch<T>(&self, f: impl FnOnce(&mut Scratch) -> T) -> T {
        match self.scratch.try_borrow_mut() {
            Ok(mut shared) => f(&mut shared),
            Err(_) => f(&mut Scratch::default()),
        }
    }

    /// The rows of [`Problem::eval`], evaluated in `scratch`.
    fn eval_rows<F: FnMut(f64, &[usize], &[f64])>(
        &self,
        theta: &[f64],
        jac: bool,
        scratch: &mut Scratch,
        mut row: F,
    ) -> bool {
        let Some((ev, sums)) = self.first_pass(theta, jac, scratch) else {
            return false;
        };
        let buf = &scratch.terms;
        let (e0, a0, b0) = self.shifts(&sums);
        for (j, t) in buf.iter().enumerate() {
            let s = self.w.map_or(1.0, |w| w[j].sqrt());
            let res = s * (t.e - e0);
            if !res.is_finite() {
                return false;
            }
            if jac {
                let g = self.row(&ev, t, (a0, b0));
                let g = [s * g[0], s * g[1]];
                if !(g[0].is_finite() && g[1].is_finite()) {
                    return false;
                }
                row(res, &[0, 1], &g);
            } else {
                row(res, &[], &[]);
            }
        }
        true
    }

    /// The normal equations of [`Problem::normal_equations`]; `None` if θ is infeasible.
    fn normal(
        &self,
        theta: &[f64],
        jtj: &mut [f64],
        jtr: &mut [f64],
        scratch: &mut Scratch,
    ) -> Option<f64> {
        let (ev, sums) = self.first_pass(theta, true, scratch)?;
        let buf = &scratch.terms;
        let (e0, a0, b0) = self.shifts(&sums);
        let (mut cost, mut g0r, mut g1r, mut g00, mut g01, mut g11) =
            (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut add = |w: f64, t: &Terms| {
            let res = t.e - e0;
            let g = self.row(&ev, t, (a0, b0));
            let (wg0, wg1) = (w * g[0], w * g[1]);
            cost += w * res * res;
            g0r += wg0 * res;
            g1r += wg1 * res;
            g00 += wg0 * g[0];
            g01 += wg0 * g[1];
            g11 += wg1 * g[1];
        };
        match self.w {
            Some(w) => buf.iter().zip(w).for_each(|(t, &wj)| add(wj, t)),
            None => buf.iter().for_each(|t| add(1.0, t)),
        }
        jtj.copy_from_slice(&[g00, g01, g01, g11]);
        jtr.copy_from_slice(&[g0r, g1r]);
        let ok = [cost, g0r, g1r, g00, g01, g11]
            .iter()
            .all(|v| v.is_finite());
        ok.then_some(cost)
    }
}

/// Start candidates for θ = (ln sigma_s', ln sigma_a), best first. The dipole's shape depends on
/// sigma_t' only through the length 1/sigma_t' and otherwise on the albedo alone, so the grid
/// runs over ln sigma_t' (half-decade steps over six decades around the data's length scale)
/// and over logit(sigma_a/sigma_t') (from 1e-7, the clearest marble, to 0.999, darker than
/// ketchup's blue channel), scored on binned data. The best grid point of each albedo row is
/// a candidate; distinct rows keep starts in different basins (the low-albedo materials have a
/// false minimum at sigma_a → 0 next to the true one).
fn grid_starts(coarse: &DipoleProblem, scale_r: f64) -> Vec<(f64, [f64; 2])> {
    let mut rows: Vec<(f64, [f64; 2])> = Vec::new();
    for i in 0..21 {
        // logit q from ln 1e-7 to ln 1e3.
        let lq = (1e-7f64).ln() + i as f64 * (1e10f64).ln() / 20.0;
        let q = 1.0 / (1.0 + (-lq).exp());
        let mut best = (f64::INFINITY, [0.0; 2]);
        for j in 0..13 {
            let t = 10f64.powf(-3.0 + 0.5 * j as f64) / scale_r;
            let theta = [((1.0 - q) * t).ln(), (q * t).ln()];
            let c = coarse.cost(&theta);
            if c < best.0 {
                best = (c, theta);
            }
        }
        if best.0.is_finite() {
            rows.push(best);
        }
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    rows
}

/// Fits the dipole to samples s at distances r (one channel).
pub fn fit_dipole(r: &[f64], s: &[f64], options: &DipoleOptions) -> Result<DipoleFit, FitFailure> {
    if Dipole::new(1.0, 0.1, options.eta).is_err() {
        return Err(FitFailure::InvalidOptions {
            reason: "eta must be finite and > 0 with F_dr(eta) < 1",
        });
    }
    let (r, s, samples) = clean(r, s);
    // Shape (sigma_s', sigma_a) plus the scale unless absolute.
    let p: usize = if options.absolute { 2 } else { 3 };
    let needed = super::samples_needed(p.div_ceil(2));
    if r.len() < needed {
        return Err(FitFailure::TooFewSamples {
            usable: r.len(),
            needed,
        });
    }
    let distinct = super::samples::distinct_distances(&r, p);
    if distinct < p {
        return Err(FitFailure::TooFewDistances {
            distinct,
            needed: p,
        });
    }
    let y: Vec<f64> = s.iter().map(|v| v.ln()).collect();
    let scale_r = r.iter().sum::<f64>() / r.len() as f64;
    let scale_r = if scale_r > 0.0 { scale_r } else { 1.0 };
    let binned = bin_samples(&r, &s, 32);
    let bins = binned.bins.as_slice();
    let br: Vec<f64> = bins.iter().map(|b| b.r * binned.scale_r).collect();
    let by: Vec<f64> = bins.iter().map(|b| b.y + binned.level).collect();
    let bw: Vec<f64> = bins.iter().map(|b| b.n).collect();
    let coarse = DipoleProblem::new(&br, &by, Some(&bw), options.eta, options.absolute);
    let problem = DipoleProblem::new(&r, &y, None, options.eta, options.absolute);
    let settings = Settings {
        max_iterations: options.max_iterations,
        ..Settings::default()
    };
    // Pre-fit on the bins from the best few grid rows; the best pre-fit, scored on every
    // sample, starts the fit on every sample. Pre-fits from different rows mostly end in the
    // same minimum: one within 1e-6 (in ln sigma_s' and ln sigma_a) of a pre-fit already
    // scored is not scored again (its cost could differ by ~1e-12 relative, and the full fit
    // from either start ends in the same place).
    let mut iterations = 0;
    // (cost on every sample, θ, whether θ is a converged pre-fit)
    let mut scored: Vec<(f64, Vec<f64>, bool)> = Vec::with_capacity(4);
    for (_, theta) in grid_starts(&coarse, scale_r).into_iter().take(4) {
        let pre = lm::minimize(
            &coarse,
            &theta,
            &Settings {
                ftol: 1e-10,
                stop_on_predicted: true,
                ..settings
            },
        );
        let (th, converged) = match pre {
            Some(o) => {
                iterations += o.iterations;
                (o.theta, o.converged)
            }
            None => (theta.to_vec(), false),
        };
        let seen = scored
            .iter()
            .any(|(_, t, _)| t.iter().zip(&th).all(|(a, b)| (a - b).abs() <= 1e-6));
        if !seen {
            scored.push((problem.cost(&th), th, converged));
        }
    }
    let Some((_, start, converged_start)) = scored
        .into_iter()
        .filter(|(c, _, _)| c.is_finite())
        .min_by(|a, b| a.0.total_cmp(&b.0))
    else {
        return Err(FitFailure::NonFinite);
    };
    // A converged pre-fit is a fit of the same model to the same samples' bins, inside the
    // region where Gauss–Newton converges: little initial damping from there (1e-3 cost two
    // extra evaluations of 2,000 samples on the benchmark). The stop on the model's predicted
    // decrease saves the evaluations that rounding would decide.
    let final_settings = Settings {
        initial_damping: if converged_start { 1e-6 } else { 1e-3 },
        stop_on_predicted: true,
        ..settings
    };
    let out = match options.solver {
        Solver::Specialised => lm::minimize(&problem, &start, &final_settings),
        Solver::Reference => super::reference::minimize(&problem, &start, options.max_iterations),
    }
    .ok_or(FitFailure::NonFinite)?;
    let ln_k = problem.ln_k(&out.theta).ok_or(FitFailure::NonFinite)?;
    let dipole = Dipole {
        sigma_s_prime: out.theta[0].exp(),
        sigma_a: out.theta[1].exp(),
        eta: options.eta,
    };
    let scale = ln_k.exp();
    if !(scale.is_finite() && scale > 0.0) || dipole.validate().is_err() || dipole.sigma_a <= 0.0 {
        return Err(FitFailure::OutOfRange {
            what: "dipole coefficients or scale left the representable range",
        });
    }
    let rss = out.cost;
    let log_e = (rss / r.len() as f64).sqrt();
    if !(rss.is_finite() && log_e.is_finite()) {
        return Err(FitFailure::NonFinite);
    }
    Ok(DipoleFit {
        dipole,
        scale,
        rss,
        log_e,
        iterations: iterations + out.iterations,
        converged: out.converged,
        stalled: out.stalled,
        samples,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Material;

    #[test]
    fn recovers_a_preset_dipole() {
        for (name, ch) in [("marble", 1), ("skin1", 0), ("ketchup", 0)] {
            let truth = Material::by_name(name).unwrap().dipole(ch).unwrap();
            let r: Vec<f64> = (0..300).map(|i| 0.05 * i as f64).collect();
            let s: Vec<f64> = r.iter().map(|&v| 3.0 * truth.r_d(v)).collect();
            for solver in [Solver::Specialised, Solver::Reference] {
                let fit = fit_dipole(
                    &r,
                    &s,
                    &DipoleOptions {
                        solver,
                        eta: truth.eta,
                        ..DipoleOptions::default()
                    },
                )
                .unwrap();
                let e1 = (fit.dipole.sigma_s_prime / truth.sigma_s_prime - 1.0).abs();
                let e2 = (fit.dipole.sigma_a / truth.sigma_a - 1.0).abs();
                assert!(e1 < 1e-5 && e2 < 1e-5, "{name} {solver:?}: {fit:?}");
                assert!((fit.scale / 3.0 - 1.0).abs() < 1e-5);
            }
            let fit = fit_dipole(
                &r,
                &s.iter().map(|v| v / 3.0).collect::<Vec<_>>(),
                &DipoleOptions {
                    absolute: true,
                    eta: truth.eta,
                    ..DipoleOptions::default()
                },
            )
            .unwrap();
            assert!((fit.dipole.sigma_a / truth.sigma_a - 1.0).abs() < 1e-5);
        }
    }

    /// The profile of the issue: eta of the material, r = 0.05·1.04^k mm, 140 points.
    fn jensen_r() -> Vec<f64> {
        (0..140).map(|k| 0.05 * 1.04f64.powi(k)).collect()
    }

    /// Deterministic N(0, 1) draws (SplitMix64 + Box–Muller).
    fn gauss(seed: &mut u64) -> f64 {
        let mut u = || {
            *seed = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = *seed;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            (((z ^ (z >> 31)) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let (u1, u2) = (u(), u());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Relative error of the recovered coefficients: sigma_s' relative, sigma_a relative (or,
    /// for spectralon's sigma_a = 0, relative to sigma_t').
    fn errors(fit: &DipoleFit, truth: &Dipole) -> (f64, f64) {
        let es = (fit.dipole.sigma_s_prime / truth.sigma_s_prime - 1.0).abs();
        let ea = if truth.sigma_a > 0.0 {
            (fit.dipole.sigma_a / truth.sigma_a - 1.0).abs()
        } else {
            fit.dipole.sigma_a / truth.sigma_t_prime()
        };
        (es, ea)
    }

    /// Standard deviations of (ln sigma_s', ln sigma_a) by the Cramér–Rao bound for samples with
    /// multiplicative noise sigma: sigma²·(JᵀJ)⁻¹ at the truth (J of the scale-eliminated
    /// residuals, so the scale's uncertainty is accounted for). Spectralon (sigma_a = 0) gets
    /// zeros: its absorption has no relative error to bound.
    fn crb(r: &[f64], truth: &Dipole, absolute: bool, sigma: f64) -> [f64; 2] {
        if truth.sigma_a <= 0.0 || sigma == 0.0 {
            return [0.0; 2];
        }
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x)).collect();
        let p = DipoleProblem::new(r, &y, None, truth.eta, absolute);
        let mut j = Vec::new();
        assert!(p.eval(
            &[truth.sigma_s_prime.ln(), truth.sigma_a.ln()],
            true,
            |_, _, g| j.push([g[0], g[1]])
        ));
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for g in &j {
            a += g[0] * g[0];
            b += g[0] * g[1];
            c += g[1] * g[1];
        }
        let det = a * c - b * b;
        [sigma * (c / det).sqrt(), sigma * (a / det).sqrt()]
    }

    /// The fit's accuracy on measured materials: every material of Jensen's measured table,
    /// every channel, free scale and absolute, from exact profiles (1e-4) and with 1 %
    /// multiplicative noise (5 %).
    #[test]
    fn jensen_table_round_trip() {
        use crate::model::dipole::MATERIALS;
        let r = jensen_r();
        let mut seed = 13u64;
        let mut worst = [(0.0f64, String::new()), (0.0f64, String::new())];
        for m in MATERIALS {
            for ch in 0..3 {
                let truth = m.dipole(ch).unwrap();
                for absolute in [false, true] {
                    let k = if absolute { 1.0 } else { 0.37 };
                    let options = DipoleOptions {
                        eta: truth.eta,
                        absolute,
                        ..DipoleOptions::default()
                    };
                    for (noise, tol, slot) in [(0.0f64, 1e-4f64, 0), (0.01, 0.05, 1)] {
                        let s: Vec<f64> = r
                            .iter()
                            .map(|&x| k * truth.r_d(x) * (noise * gauss(&mut seed)).exp())
                            .collect();
                        let what = format!("{} ch {ch} absolute {absolute} noise {noise}", m.name);
                        let fit =
                            fit_dipole(&r, &s, &options).unwrap_or_else(|e| panic!("{what}: {e}"));
                        let (es, ea) = errors(&fit, &truth);
                        assert!(fit.converged && !fit.stalled, "{what}: {fit:?}");
                        // The right basin: the fit explains the samples at least as well as
                        // the generating coefficients do (a wrong minimum cannot).
                        let y: Vec<f64> = s.iter().map(|v| v.ln()).collect();
                        let at_truth = DipoleProblem::new(&r, &y, None, truth.eta, absolute)
                            .cost(&[truth.sigma_s_prime.ln(), truth.sigma_a.max(1e-300).ln()]);
                        assert!(
                            fit.rss <= at_truth * (1.0 + 1e-9) + 1e-20,
                            "{what}: {fit:?}"
                        );
                        // The coefficients to the tolerance, or, where 140 samples
                        // with 1 % noise cannot determine them that well, to 4 standard
                        // deviations of the Cramér–Rao bound.
                        let sd = crb(&r, &truth, absolute, noise);
                        let bound = [tol.max(4.0 * sd[0]), tol.max(4.0 * sd[1])];
                        assert!(
                            es < bound[0] && ea < bound[1],
                            "{what}: {es:e} {ea:e} (bounds {bound:?}) {fit:?}"
                        );
                        if sd[0].max(sd[1]) * 4.0 > tol {
                            eprintln!(
                                "{what}: Cramér–Rao sd of ln sigma_s', ln sigma_a {sd:?}; errors {es:.3e} {ea:.3e}"
                            );
                        }
                        if !absolute {
                            assert!(
                                (fit.scale / k - 1.0).abs() < 10.0 * tol.max(4.0 * sd[0]),
                                "{what}: {fit:?}"
                            );
                        }
                        if es.max(ea) > worst[slot].0 {
                            worst[slot] = (es.max(ea), what);
                        }
                    }
                }
            }
        }
        eprintln!("worst exact {:?}, worst noisy {:?}", worst[0], worst[1]);
    }

    #[test]
    fn dipole_jacobian_matches_finite_differences() {
        use super::super::aniso::tests::check_jacobian;
        let r = jensen_r();
        let truth = Material::by_name("skin1").unwrap().dipole(2).unwrap();
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x) + 0.1 * x.sin()).collect();
        let w: Vec<f64> = (0..r.len()).map(|i| 1.0 + (i % 3) as f64).collect();
        for theta in [[0.1, -1.0], [-2.0, 0.5], [1.0, -6.0]] {
            for absolute in [false, true] {
                for weights in [None, Some(w.as_slice())] {
                    let p = DipoleProblem::new(&r, &y, weights, 1.3, absolute);
                    check_jacobian(&p, &theta);
                }
            }
        }
        // The evaluator agrees with the model's own ln R_d.
        let ev =
            DipoleEval::new(&[truth.sigma_s_prime.ln(), truth.sigma_a.ln()], truth.eta).unwrap();
        for &x in &r {
            assert!((ev.value(x) - truth.ln_r_d(x)).abs() < 1e-12);
        }
    }

    /// The fused normal equations (the specialised solver's path) are the ones the Jacobian
    /// rows give (the reference solver's and the finite-difference check's path).
    #[test]
    fn normal_equations_match_the_rows() {
        let r = jensen_r();
        let truth = Material::by_name("ketchup").unwrap().dipole(1).unwrap();
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x) + 0.2 * x.cos()).collect();
        let w: Vec<f64> = (0..r.len()).map(|i| 0.5 + (i % 4) as f64).collect();
        for theta in [[0.3, -0.5], [-1.0, -4.0], [2.0, 1.0]] {
            for absolute in [false, true] {
                for weights in [None, Some(w.as_slice())] {
                    let p = DipoleProblem::new(&r, &y, weights, truth.eta, absolute);
                    let (mut jtj, mut jtr, mut cost) = ([0.0; 4], [0.0; 2], 0.0);
                    assert!(p.eval(&theta, true, |res, idx, g| {
                        assert_eq!(idx, &[0, 1]);
                        cost += res * res;
                        for i in 0..2 {
                            jtr[i] += g[i] * res;
                            for j in 0..2 {
                                jtj[2 * i + j] += g[i] * g[j];
                            }
                        }
                    }));
                    let (mut njtj, mut njtr) = ([0.0; 4], [0.0; 2]);
                    let ncost = p
                        .normal_equations(&theta, &mut njtj, &mut njtr)
                        .unwrap()
                        .unwrap();
                    let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-12 * scale;
                    assert!(close(ncost, cost, cost), "{theta:?} {absolute}");
                    assert!(close(p.cost(&theta), cost, cost));
                    let gscale = (jtj[0] * cost).sqrt().max((jtj[3] * cost).sqrt());
                    for i in 0..2 {
                        assert!(close(njtr[i], jtr[i], gscale), "{theta:?} {absolute}");
                    }
                    for i in 0..4 {
                        assert!(close(njtj[i], jtj[i], jtj[0].max(jtj[3])));
                    }
                }
            }
        }
    }

    /// A row callback may evaluate the same problem again (the scratch buffer is then its own).
    #[test]
    fn rows_may_evaluate_the_problem_again() {
        let r = jensen_r();
        let truth = Material::by_name("marble").unwrap().dipole(0).unwrap();
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x)).collect();
        let p = DipoleProblem::new(&r, &y, None, truth.eta, false);
        let theta = [truth.sigma_s_prime.ln(), truth.sigma_a.ln() + 0.1];
        let mut inner = Vec::new();
        assert!(p.eval(&theta, true, |_, _, _| inner.push(p.cost(&theta))));
        assert_eq!(inner.len(), r.len());
        assert!(inner.iter().all(|&c| c == p.cost(&theta) && c > 0.0));
    }

    /// Where d³ leaves the range of f64 (depths of 1e-120, distances of 1e110) the evaluator
    /// takes its cold path in logs and still agrees with the model's own ln R_d; its gradient
    /// stays finite.
    #[test]
    fn evaluator_covers_the_range_where_d_cubed_leaves_f64() {
        for (s, a, rs) in [
            (1e120, 1e119, [0.0, 1e-121, 1e-119]),
            (1.0, 0.1, [1e110, 3e120, 0.5]),
            (1e-100, 1e-101, [1.0, 1e95, 1e105]),
        ] {
            let d = Dipole::new(s, a, 1.3).unwrap();
            let ev = DipoleEval::new(&[s.ln(), a.ln()], 1.3).unwrap();
            for r in rs {
                let (l, ta, tb) = ev.terms(r);
                let want = d.ln_r_d(r);
                assert!(
                    (l - want).abs() <= 1e-12 * want.abs().max(1.0),
                    "s {s} a {a} r {r}: {l} vs {want}"
                );
                let g = ev.gradient(ta, tb);
                assert!(g.iter().all(|v| v.is_finite()), "s {s} a {a} r {r}: {g:?}");
            }
        }
    }

    #[test]
    fn fails_cleanly() {
        let o = DipoleOptions::default();
        assert!(matches!(
            fit_dipole(&[1.0], &[1.0], &o),
            Err(FitFailure::TooFewSamples { .. })
        ));
        assert!(matches!(
            fit_dipole(&[1.0; 10], &[1.0; 10], &o),
            Err(FitFailure::TooFewDistances { .. })
        ));
        let bad_eta = DipoleOptions { eta: f64::NAN, ..o };
        assert!(fit_dipole(&[1.0, 2.0], &[1.0, 1.0], &bad_eta).is_err());
    }
}
