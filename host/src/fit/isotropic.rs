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

/// d_k = −exp(b_k) for θ = (a_1, b_1, …).
#[inline]
fn rates(theta: &[f64], n: usize) -> [f64; 4] {
    let mut d = [0.0; 4];
    for k in 0..n.min(4) {
        d[k] = -theta[2 * k + 1].exp();
    }
    d
}

/// exp(x) for x ∈ [−708, 0] (inputs are clamped into it), branch-free so that loops over
/// samples vectorise: x = k·ln 2 + f with |f| ≤ ln 2 / 2, exp(f) by its degree-13 Taylor
/// polynomial (truncation < 1e-17 relative), 2^k by building the exponent bits. Hand-written
/// because `f64::exp` is an opaque libm call that stops the compiler from vectorising the
/// per-sample loop of the exact log fit, the hottest loop of per-vertex fitting; the
/// `isotropic_n3` benchmark measures the gain, and a test checks it against `f64::exp`.
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f64) -> f64 {
    // ln 2 split so that k·LN2_HI is exact (fdlibm's constants).
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    // Round-to-nearest by the 1.5·2^52 trick: k lands in the low mantissa bits of `kk`, with no
    // libm `round` and no float→int conversion, both of which block vectorisation.
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    let x = x.clamp(-708.0, 0.0);
    let kk = x * std::f64::consts::LOG2_E + MAGIC;
    let k = kk - MAGIC;
    let k_int = (kk.to_bits() as i64).wrapping_sub(MAGIC.to_bits() as i64);
    let f = (x - k * LN2_HI) - k * LN2_LO;
    // Horner, coefficients 1/j!.
    let mut p = 1.0 / 6_227_020_800.0;
    for c in [
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ] {
        p = p * f + c;
    }
    // k ∈ [−1022, 0]: 2^k is a normal number.
    let scale = f64::from_bits((k_int.wrapping_add(1023) as u64) << 52);
    p * scale
}

/// ln(x) for finite x > 0, branch-light so loops vectorise (companion of [`exp_nonpositive`]):
/// x = 2^e·m with m ∈ [√½, √2), ln m = 2·atanh(s), s = (m − 1)/(m + 1), |s| ≤ 0.172, by its odd
/// series to s²³ (truncation < 1e-18). Subnormal inputs take `f64::ln`.
#[inline(always)]
pub(crate) fn ln_positive(x: f64) -> f64 {
    if x < f64::MIN_POSITIVE {
        return x.ln();
    }
    let bits = x.to_bits();
    let mut e = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mut m = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    if m > std::f64::consts::SQRT_2 {
        m *= 0.5;
        e += 1;
    }
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let mut p = 1.0 / 23.0;
    for c in [
        1.0 / 21.0,
        1.0 / 19.0,
        1.0 / 17.0,
        1.0 / 15.0,
        1.0 / 13.0,
        1.0 / 11.0,
        1.0 / 9.0,
        1.0 / 7.0,
        1.0 / 5.0,
        1.0 / 3.0,
        1.0,
    ] {
        p = p * s2 + c;
    }
    // ln 2 split so that k·LN2_HI is exact (fdlibm's constants).
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    let ef = e as f64;
    ef * LN2_HI + (2.0 * s * p + ef * LN2_LO)
}

/// The exact log objective's normal equations JᵀJ, Jᵀres and cost in one pass, in chunks of
/// samples laid out so the exponentials vectorise (see [`exp_nonpositive`]). Same residuals and
/// Jacobian as [`LogExact`]'s `eval`.
fn log_exact_normal(
    problem: &LogExact<'_>,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    // Monomorphised per term count so every inner loop has constant bounds and unrolls.
    match problem.n {
        1 => log_exact_normal_n::<1>(problem, theta, jtj, jtr),
        2 => log_exact_normal_n::<2>(problem, theta, jtj, jtr),
        3 => log_exact_normal_n::<3>(problem, theta, jtj, jtr),
        _ => log_exact_normal_n::<4>(problem, theta, jtj, jtr),
    }
}

#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn log_exact_normal_n<const N: usize>(
    problem: &LogExact<'_>,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    const CHUNK: usize = 16;
    let n = N;
    let p = 2 * N;
    let d = rates(theta, n);
    let mut a = [0.0; 4];
    for k in 0..n {
        a[k] = theta[2 * k];
    }
    let mut cost = 0.0;
    let mut acc = [[0.0f64; 8]; 8];
    let mut g = [0.0f64; 8];
    let mut t = [[0.0f64; CHUNK]; 4];
    let mut m = [0.0f64; CHUNK];
    let mut sum = [0.0f64; CHUNK];
    for (rc, yc) in problem.r.chunks(CHUNK).zip(problem.y.chunks(CHUNK)) {
        let len = rc.len();
        m[..len].fill(f64::NEG_INFINITY);
        for k in 0..n {
            for j in 0..len {
                t[k][j] = a[k] + d[k] * rc[j];
                m[j] = m[j].max(t[k][j]);
            }
        }
        sum[..len].fill(0.0);
        for k in 0..n {
            for j in 0..len {
                t[k][j] = exp_nonpositive(t[k][j] - m[j]);
                sum[j] += t[k][j];
            }
        }
        for j in 0..len {
            let res = m[j] + ln_positive(sum[j]) - yc[j];
            let inv = 1.0 / sum[j];
            let mut row = [0.0f64; 8];
            for k in 0..n {
                let w = t[k][j] * inv;
                row[2 * k] = w;
                row[2 * k + 1] = w * rc[j] * d[k];
            }
            cost += res * res;
            for i in 0..p {
                g[i] += row[i] * res;
                for l in i..p {
                    acc[i][l] += row[i] * row[l];
                }
            }
        }
    }
    for i in 0..p {
        jtr[i] = g[i];
        for l in i..p {
            jtj[i * p + l] = acc[i][l];
            jtj[l * p + i] = acc[i][l];
        }
    }
    (cost.is_finite() && g[..p].iter().all(|v| v.is_finite())).then_some(cost)
}

/// [`LogBinned`]'s normal equations in one pass with vectorisable exponentials (the fast mode's
/// inner loop). Same residuals and Jacobian as its `eval`.
fn log_binned_normal(
    problem: &LogBinned<'_>,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    // Monomorphised per term count so every inner loop has constant bounds and unrolls.
    match problem.n {
        1 => log_binned_normal_n::<1>(problem, theta, jtj, jtr),
        2 => log_binned_normal_n::<2>(problem, theta, jtj, jtr),
        3 => log_binned_normal_n::<3>(problem, theta, jtj, jtr),
        _ => log_binned_normal_n::<4>(problem, theta, jtj, jtr),
    }
}

#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn log_binned_normal_n<const N: usize>(
    problem: &LogBinned<'_>,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    const CHUNK: usize = 16;
    let n = N;
    let p = 2 * N;
    let d = rates(theta, n);
    let mut a = [0.0; 4];
    for k in 0..n {
        a[k] = theta[2 * k];
    }
    let mut cost = 0.0;
    let mut acc = [[0.0f64; 8]; 8];
    let mut g8 = [0.0f64; 8];
    let mut t = [[0.0f64; CHUNK]; 4];
    let mut m = [0.0f64; CHUNK];
    let mut sum = [0.0f64; CHUNK];
    let mut add = |row: &[f64; 8], res: f64, cost: &mut f64| {
        *cost += res * res;
        for i in 0..p {
            g8[i] += row[i] * res;
            for l in i..p {
                acc[i][l] += row[i] * row[l];
            }
        }
    };
    for bc in problem.bins.chunks(CHUNK) {
        let len = bc.len();
        m[..len].fill(f64::NEG_INFINITY);
        for k in 0..n {
            for j in 0..len {
                t[k][j] = a[k] + d[k] * bc[j].r;
                m[j] = m[j].max(t[k][j]);
            }
        }
        sum[..len].fill(0.0);
        for k in 0..n {
            for j in 0..len {
                t[k][j] = exp_nonpositive(t[k][j] - m[j]);
                sum[j] += t[k][j];
            }
        }
        for j in 0..len {
            let b = &bc[j];
            let inv = 1.0 / sum[j];
            let sn = b.n.sqrt();
            let mut w = [0.0f64; 4];
            let mut g = 0.0;
            for k in 0..n {
                w[k] = t[k][j] * inv;
                g += w[k] * d[k];
            }
            let mut row = [0.0f64; 8];
            for k in 0..n {
                row[2 * k] = sn * w[k];
                row[2 * k + 1] = sn * w[k] * b.r * d[k];
            }
            add(&row, sn * (m[j] + ln_positive(sum[j]) - b.y), &mut cost);
            if b.srr > 0.0 {
                let ss = b.srr.sqrt();
                for k in 0..n {
                    let dk = d[k] - g;
                    row[2 * k] = ss * w[k] * dk;
                    row[2 * k + 1] = ss * (w[k] + w[k] * b.r * dk) * d[k];
                }
                add(&row, ss * (g - b.sry / b.srr), &mut cost);
            }
        }
    }
    for i in 0..p {
        jtr[i] = g8[i];
        for l in i..p {
            jtj[i * p + l] = acc[i][l];
            jtj[l * p + i] = acc[i][l];
        }
    }
    (cost.is_finite() && g8[..p].iter().all(|v| v.is_finite())).then_some(cost)
}

/// ln R_d(r) and the weights w_k = c_k e^{d_k r} / R_d (a log-sum-exp, so nothing underflows).
#[inline]
fn ln_and_weights(theta: &[f64], n: usize, r: f64, w: &mut [f64; 4], d: &[f64; 4]) -> f64 {
    let mut t = [0.0f64; 4];
    let mut m = f64::NEG_INFINITY;
    for k in 0..n {
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
    fn normal_equations(
        &self,
        theta: &[f64],
        jtj: &mut [f64],
        jtr: &mut [f64],
    ) -> Option<Option<f64>> {
        Some(log_exact_normal(self, theta, jtj, jtr))
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let n = self.n;
        let (mut w, d) = ([0.0; 4], rates(theta, n));
        let mut vals = [0.0; 8];
        for (&r, &y) in self.r.iter().zip(self.y) {
            let l = ln_and_weights(theta, n, r, &mut w, &d);
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
    fn normal_equations(
        &self,
        theta: &[f64],
        jtj: &mut [f64],
        jtr: &mut [f64],
    ) -> Option<Option<f64>> {
        Some(log_binned_normal(self, theta, jtj, jtr))
    }
    fn rows(&self) -> usize {
        2 * self.bins.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let n = self.n;
        let (mut w, d) = ([0.0; 4], rates(theta, n));
        let mut vals = [0.0; 8];
        for b in self.bins {
            let l = ln_and_weights(theta, n, b.r, &mut w, &d);
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

/// Convergence tolerance of the fast mode's binned fit: log E is then settled to ~6 digits, far
/// below the binning error the bin count trades for speed.
const FAST_FTOL: f64 = 1e-6;

/// Convergence tolerance (relative cost reduction) of the exact polish after the binned pre-fit.
const POLISH_FTOL: f64 = 1e-10;

/// Bins of the pre-fit that gives the exact log fit its start (and of the start values).
pub(crate) const PREFIT_BINS: usize = 64;

/// What one fixed-order fit produced, in original units.
pub(crate) struct Raw {
    pub model: ExpSum,
    pub iterations: usize,
    pub converged: bool,
    /// Σ(ln R_d − ln s)² for the log objective: the solver's final cost (exact fits) or the
    /// estimate from the bin statistics (fast mode).
    pub rss_estimate: Option<f64>,
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
    let ln_s: Vec<f64> = s.iter().map(|&v| ln_positive(v)).collect();
    let level = match objective {
        Objective::Log => ln_s.iter().sum::<f64>() / ln_s.len() as f64,
        Objective::Linear => ln_s.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    };
    // Bins feed the start values and the pre-fit (the whole fit in fast mode). They are built
    // from the raw samples and normalised afterwards, so the fast mode touches each sample once.
    let prefit_bins: Vec<Bin> =
        bin_by_distance(r, &ln_s, bins.unwrap_or(PREFIT_BINS).max(2 * n + 2))
            .into_iter()
            .map(|b| b.normalised(scale_r, level))
            .collect();
    // Per-sample normalised data, only for the solves that use every sample.
    let per_sample = || -> (Vec<f64>, Vec<f64>) {
        (
            r.iter().map(|v| v / scale_r).collect(),
            ln_s.iter().map(|v| v - level).collect(),
        )
    };
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
    let mut rss_estimate = None;
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
            // The binned fit only approximates the exact one (its log E differs in the 3rd–5th
            // digit), so iterating it to machine precision buys nothing.
            let binned_settings = Settings {
                ftol: if bins.is_some() {
                    FAST_FTOL
                } else {
                    POLISH_FTOL
                },
                ..settings
            };
            let mut pre: Option<lm::Outcome> = None;
            for cand in &candidates {
                let Some(o) = lm::minimize(&binned, cand, &binned_settings) else {
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
                // log E from the statistics: the binned cost plus each bin's scatter about its
                // own regression line (the part no smooth model can explain).
                rss_estimate = pre.as_ref().map(|o| {
                    o.cost
                        + prefit_bins
                            .iter()
                            .map(|b| {
                                if b.srr > 0.0 {
                                    (b.syy - b.sry * b.sry / b.srr).max(0.0)
                                } else {
                                    b.syy
                                }
                            })
                            .sum::<f64>()
                });
                pre.map(|o| lm::Outcome { iterations, ..o })
            } else {
                let theta1 = pre.map_or_else(|| theta0.clone(), |o| o.theta);
                let (rn, y) = per_sample();
                // The pre-fit lands next to the optimum: a relative cost change of 1e-10 per
                // step already leaves log E exact to ~10 digits.
                let polish = Settings {
                    ftol: POLISH_FTOL,
                    ..settings
                };
                lm::minimize(&LogExact { r: &rn, y: &y, n }, &theta1, &polish)
            }
        }
        (Objective::Log, Solver::Reference) => {
            let (rn, y) = per_sample();
            super::reference::minimize(&LogExact { r: &rn, y: &y, n }, &theta0, max_iterations)
        }
        (Objective::Linear, Solver::Specialised) => {
            let (rn, y) = per_sample();
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            linear_specialised(&rn, &sn, n, &theta0, &settings)
        }
        (Objective::Linear, Solver::Reference) => {
            let (rn, y) = per_sample();
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            super::reference::minimize(&Linear { r: &rn, s: &sn, n }, &theta0, max_iterations)
        }
    };
    let out = out.ok_or(FitFailure::NonFinite)?;
    iterations += out.iterations;
    // The log objective's cost is Σ(ln R_d − ln s)² itself (unit-free), so the exact fits need
    // no extra pass for log E; the fast mode has its bin-statistics estimate.
    if objective == Objective::Log && rss_estimate.is_none() {
        rss_estimate = Some(out.cost);
    }
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
        rss_estimate,
    })
}
