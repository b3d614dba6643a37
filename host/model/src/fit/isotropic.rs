//! Eq. 1 fitted to one fall-off curve: the least-squares problems (log objective Eq. 4, its binned
//! form, the linear objective), start values by peeling, and the driver.
//!
//! Parametrisation: θ = (a_1, b_1, …, a_n, b_n) with c_k = exp(a_k), d_k = −exp(b_k), in
//! normalised units (distances divided by the largest distance R, values by a reference level
//! exp(L)). The constraints c_k > 0, d_k < 0 of Eq. 1 hold for every finite θ, and huge or tiny
//! units only move L and R, never the conditioning of the solve.

use super::bins::{Bin, bin_samples, coarsen};
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

/// ln(x) for finite x > 0, branch-free so loops vectorise (companion of [`exp_nonpositive`]):
/// x = 2^e·m with m ∈ [√½, √2), ln m = 2·atanh(s), s = (m − 1)/(m + 1), |s| ≤ 0.172, by its odd
/// series to s²³ (truncation < 1e-18). Subnormal inputs are scaled by 2^54 first; the exponent
/// reaches f64 through the 2^52 bit trick instead of an int→float conversion (which x86-64's
/// baseline SIMD lacks).
#[inline(always)]
pub(crate) fn ln_positive(x: f64) -> f64 {
    const TWO_52: f64 = 4_503_599_627_370_496.0;
    let sub = x < f64::MIN_POSITIVE;
    let x = if sub { x * 18_014_398_509_481_984.0 } else { x };
    let shift = if sub { 54.0 } else { 0.0 };
    let bits = x.to_bits();
    // Biased exponent field as an f64: 2^52 + field, minus 2^52.
    let field = f64::from_bits((bits >> 52) | 0x4330_0000_0000_0000) - TWO_52;
    let m = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    let big = m > std::f64::consts::SQRT_2;
    let m = if big { m * 0.5 } else { m };
    let ef = field - 1023.0 - shift + if big { 1.0 } else { 0.0 };
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
    ef * LN2_HI + (2.0 * s * p + ef * LN2_LO)
}

/// Points per block of the log-sum-exp kernel: long enough for the exponentials to vectorise,
/// short enough to stay in registers and L1.
const CHUNK: usize = 16;

/// The log-sum-exp kernel shared by every log objective (exact samples and bins): for points
/// j = 0..len at distances `r_at(j)`, calls `point(j, r_j, ln R_d(r_j), w)` with the weights
/// w_k = c_k e^{d_k r_j} / R_d (Eq. 1 evaluated as a log-sum-exp, so nothing underflows). The
/// exponentials of a block run in loops of constant bounds with [`exp_nonpositive`], which the
/// compiler vectorises.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn log_sum_exp_points<const N: usize>(
    len: usize,
    r_at: impl Fn(usize) -> f64,
    a: &[f64; 4],
    d: &[f64; 4],
    mut point: impl FnMut(usize, f64, f64, &[f64; 4]),
) {
    let mut t = [[0.0f64; CHUNK]; 4];
    let mut rr = [0.0f64; CHUNK];
    let mut m = [0.0f64; CHUNK];
    let mut sum = [0.0f64; CHUNK];
    let mut start = 0;
    while start < len {
        let l = CHUNK.min(len - start);
        for j in 0..l {
            rr[j] = r_at(start + j);
        }
        m[..l].fill(f64::NEG_INFINITY);
        for k in 0..N {
            for j in 0..l {
                t[k][j] = a[k] + d[k] * rr[j];
                m[j] = m[j].max(t[k][j]);
            }
        }
        sum[..l].fill(0.0);
        for k in 0..N {
            for j in 0..l {
                t[k][j] = exp_nonpositive(t[k][j] - m[j]);
                sum[j] += t[k][j];
            }
        }
        for j in 0..l {
            let inv = 1.0 / sum[j];
            let mut w = [0.0f64; 4];
            for k in 0..N {
                w[k] = t[k][j] * inv;
            }
            point(start + j, rr[j], m[j] + ln_positive(sum[j]), &w);
        }
        start += l;
    }
}

/// The residual rows of a log objective at one point, from the kernel's ln R_d and weights.
/// Written once per objective and used both by the one-pass normal equations (the solver's hot
/// path) and by the generic row evaluation (reference solver, tests), so the two cannot drift.
trait LogRows {
    /// Number of exponential terms n.
    fn terms(&self) -> usize;
    /// Number of points.
    fn points(&self) -> usize;
    /// Distance of point j (normalised).
    fn r(&self, j: usize) -> f64;
    /// Residual rows at point j: `emit(residual, jacobian_row)`, row over θ = (a_1, b_1, …).
    fn rows<const N: usize>(
        &self,
        j: usize,
        ln_rd: f64,
        w: &[f64; 4],
        d: &[f64; 4],
        emit: impl FnMut(f64, &[f64; 8]),
    );
    /// Residual rows per point (for the reference adapter's dense matrices).
    fn rows_per_point(&self, j: usize) -> usize;
    /// JᵀJ, Jᵀres and the cost in one pass (the solver's hot path): [`log_normal`] unless an
    /// objective has a faster form of the same sums.
    fn normal(&self, theta: &[f64], jtj: &mut [f64], jtr: &mut [f64]) -> Option<f64>
    where
        Self: Sized,
    {
        log_normal(self, self.terms(), theta, jtj, jtr)
    }
}

/// Splits θ into amplitudes a_k = ln c_k and rates d_k = −exp(b_k).
#[inline]
fn split(theta: &[f64], n: usize) -> ([f64; 4], [f64; 4]) {
    let mut a = [0.0; 4];
    for k in 0..n.min(4) {
        a[k] = theta[2 * k];
    }
    (a, rates(theta, n))
}

/// JᵀJ, Jᵀres and the cost of a log objective in one pass, monomorphised per term count so
/// every inner loop has constant bounds.
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn log_normal_n<const N: usize, O: LogRows>(
    problem: &O,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    let p = 2 * N;
    let (a, d) = split(theta, N);
    let mut cost = 0.0;
    let mut acc = [[0.0f64; 8]; 8];
    let mut g = [0.0f64; 8];
    log_sum_exp_points::<N>(
        problem.points(),
        |j| problem.r(j),
        &a,
        &d,
        |j, _, l, w| {
            problem.rows::<N>(j, l, w, &d, |res, row| {
                cost += res * res;
                for i in 0..p {
                    g[i] += row[i] * res;
                    for k in i..p {
                        acc[i][k] += row[i] * row[k];
                    }
                }
            });
        },
    );
    finish_normal(p, &acc, &g, cost, jtj, jtr)
}

/// The normal equations from their upper-triangle sums `acc` and gradient `g` over p
/// parameters: JᵀJ mirrored into `jtj`, Jᵀres into `jtr`; the cost where it and the gradient
/// are finite (the row kernels' common end).
fn finish_normal(
    p: usize,
    acc: &[[f64; 8]; 8],
    g: &[f64; 8],
    cost: f64,
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    for i in 0..p {
        jtr[i] = g[i];
        for k in i..p {
            jtj[i * p + k] = acc[i][k];
            jtj[k * p + i] = acc[i][k];
        }
    }
    (cost.is_finite() && g[..p].iter().all(|v| v.is_finite())).then_some(cost)
}

fn log_normal<O: LogRows>(
    problem: &O,
    n: usize,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    match n {
        1 => log_normal_n::<1, O>(problem, theta, jtj, jtr),
        2 => log_normal_n::<2, O>(problem, theta, jtj, jtr),
        3 => log_normal_n::<3, O>(problem, theta, jtj, jtr),
        _ => log_normal_n::<4, O>(problem, theta, jtj, jtr),
    }
}

/// The generic row-by-row evaluation of a log objective (same rows as [`log_normal`]).
fn log_eval_n<const N: usize, O: LogRows, F: FnMut(f64, &[usize], &[f64])>(
    problem: &O,
    theta: &[f64],
    jac: bool,
    row: &mut F,
) -> bool {
    let (a, d) = split(theta, N);
    let mut ok = true;
    log_sum_exp_points::<N>(
        problem.points(),
        |j| problem.r(j),
        &a,
        &d,
        |j, _, l, w| {
            ok &= l.is_finite();
            problem.rows::<N>(j, l, w, &d, |res, vals| {
                if jac {
                    row(res, &IDX[..2 * N], &vals[..2 * N]);
                } else {
                    row(res, &[], &[]);
                }
            });
        },
    );
    ok
}

fn log_eval<O: LogRows, F: FnMut(f64, &[usize], &[f64])>(
    problem: &O,
    n: usize,
    theta: &[f64],
    jac: bool,
    mut row: F,
) -> bool {
    match n {
        1 => log_eval_n::<1, O, F>(problem, theta, jac, &mut row),
        2 => log_eval_n::<2, O, F>(problem, theta, jac, &mut row),
        3 => log_eval_n::<3, O, F>(problem, theta, jac, &mut row),
        _ => log_eval_n::<4, O, F>(problem, theta, jac, &mut row),
    }
}

impl LogRows for LogExact<'_> {
    fn terms(&self) -> usize {
        self.n
    }
    /// [`exact_normal_n`] under the SIMD dispatch: the same sums as [`log_normal`], bit for bit.
    fn normal(&self, theta: &[f64], jtj: &mut [f64], jtr: &mut [f64]) -> Option<f64> {
        super::simd::wide(ExactNormal {
            problem: self,
            theta,
            jtj,
            jtr,
        })
    }
    fn points(&self) -> usize {
        self.r.len().min(self.y.len())
    }
    fn r(&self, j: usize) -> f64 {
        self.r[j]
    }
    fn rows_per_point(&self, _: usize) -> usize {
        1
    }
    /// Eq. 4: ln R_d(r_j) − ln s_j; ∂/∂a_k = w_k, ∂/∂b_k = w_k·r·d_k.
    #[inline(always)]
    fn rows<const N: usize>(
        &self,
        j: usize,
        ln_rd: f64,
        w: &[f64; 4],
        d: &[f64; 4],
        mut emit: impl FnMut(f64, &[f64; 8]),
    ) {
        let r = self.r[j];
        let mut row = [0.0f64; 8];
        for k in 0..N {
            row[2 * k] = w[k];
            row[2 * k + 1] = w[k] * r * d[k];
        }
        emit(ln_rd - self.y[j], &row);
    }
}

/// The terms of Eq. 1 at a block of [`CHUNK`] distances `r` as a log-sum-exp: `t[k][j]` =
/// exp(a_k + d_k r_j − m_j) with m_j the largest exponent, and per lane (m_j, Σ_k t[k][j]), so
/// ln R_d = m + ln Σ and the weights are t / Σ. Constant-bound lane loops with
/// [`exp_nonpositive`], which vectorise in the kernels that inline it ([`exact_normal_n`],
/// [`binned_normal_kernel`]).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn block_terms<const N: usize>(
    a: &[f64; 4],
    d: &[f64; 4],
    r: &[f64; CHUNK],
    t: &mut [[f64; CHUNK]; N],
) -> ([f64; CHUNK], [f64; CHUNK]) {
    let mut m = [f64::NEG_INFINITY; CHUNK];
    for k in 0..N {
        for j in 0..CHUNK {
            t[k][j] = a[k] + d[k] * r[j];
            m[j] = m[j].max(t[k][j]);
        }
    }
    let mut sum = [0.0f64; CHUNK];
    for k in 0..N {
        for j in 0..CHUNK {
            t[k][j] = exp_nonpositive(t[k][j] - m[j]);
            sum[j] += t[k][j];
        }
    }
    (m, sum)
}

/// ln Σ_k exp(a_k + d_k·r_j) (Eq. 1 as a log-sum-exp, a_k = ln c_k) at every distance of `r`,
/// into `out` (as far as both reach), `n` ≤ 4 terms: the fit's own block kernel
/// ([`block_terms`]) under the SIMD dispatch, so a model's ln R_d at a light position's
/// thousands of samples costs what its normal equations' exponentials cost, not a libm call per
/// term and sample (the scalar [`crate::model::ExpSum::ln_eval_with`] was a sixth of the
/// cross-validation's CPU on `scan1024`). Within a few ulp of libm's (the tests
/// bound it), not its bits: the reference preset keeps the scalar path. A lane whose largest
/// exponent is not finite (a distance of ±∞ or NaN) gets an unspecified value and makes it
/// return `false`: the caller then takes the scalar path for those.
pub(crate) fn ln_sum_exp_many(
    a: &[f64; 4],
    d: &[f64; 4],
    n: usize,
    r: &[f64],
    out: &mut [f64],
) -> bool {
    super::simd::wide(LnSumExpMany { a, d, n, r, out })
}

/// The arguments of [`ln_sum_exp_many`] as a [`super::simd::Kernel`].
struct LnSumExpMany<'a> {
    a: &'a [f64; 4],
    d: &'a [f64; 4],
    n: usize,
    r: &'a [f64],
    out: &'a mut [f64],
}

impl super::simd::Kernel for LnSumExpMany<'_> {
    /// Whether every lane's largest exponent was finite (else some lanes need the fallback).
    type Output = bool;
    #[inline(always)]
    fn run(self) -> bool {
        let LnSumExpMany { a, d, n, r, out } = self;
        match n {
            1 => ln_sum_exp_many_n::<1>(a, d, r, out),
            2 => ln_sum_exp_many_n::<2>(a, d, r, out),
            3 => ln_sum_exp_many_n::<3>(a, d, r, out),
            _ => ln_sum_exp_many_n::<4>(a, d, r, out),
        }
    }
}

/// [`ln_sum_exp_many`] at N terms: blocks of [`CHUNK`] distances (the last padded with 0).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn ln_sum_exp_many_n<const N: usize>(
    a: &[f64; 4],
    d: &[f64; 4],
    r: &[f64],
    out: &mut [f64],
) -> bool {
    let len = r.len().min(out.len());
    let mut finite = true;
    let mut t = [[0.0f64; CHUNK]; N];
    let mut start = 0;
    while start < len {
        let l = CHUNK.min(len - start);
        let mut rr = [0.0f64; CHUNK];
        rr[..l].copy_from_slice(&r[start..start + l]);
        let (m, sum) = block_terms::<N>(a, d, &rr, &mut t);
        let mut v = [0.0f64; CHUNK];
        for j in 0..CHUNK {
            v[j] = m[j] + ln_positive(sum[j]);
        }
        for j in 0..l {
            finite &= m[j].is_finite();
        }
        out[start..start + l].copy_from_slice(&v[..l]);
        start += l;
    }
    finite
}

/// ln x at every value of `x`, into `out` (as far as both reach), by [`ln_positive`] under
/// the SIMD dispatch: what the fit's samples' ln s cost once per round and light position
/// (a hot path of the default fit). Within a few ulp of `f64::ln`; values that are not finite
/// and positive (0, negative, NaN, ∞, whose logs are −∞, NaN or ∞) take `f64::ln` itself.
pub fn ln_many(x: &[f64], out: &mut [f64]) {
    let len = x.len().min(out.len());
    let (x, out) = (&x[..len], &mut out[..len]);
    if !super::simd::wide(LnMany { x, out }) {
        for (o, &v) in out.iter_mut().zip(x) {
            if !(v > 0.0 && v.is_finite()) {
                *o = v.ln();
            }
        }
    }
}

/// The arguments of [`ln_many`] as a [`super::simd::Kernel`].
struct LnMany<'a> {
    x: &'a [f64],
    out: &'a mut [f64],
}

impl super::simd::Kernel for LnMany<'_> {
    /// Whether every value was finite and positive (else the caller fixes the others up).
    type Output = bool;
    #[inline(always)]
    fn run(self) -> bool {
        let LnMany { x, out } = self;
        let mut ok = true;
        for (xs, os) in x.chunks(CHUNK).zip(out.chunks_mut(CHUNK)) {
            let mut v = [1.0f64; CHUNK];
            for (j, &xv) in xs.iter().enumerate() {
                let good = xv > 0.0 && xv <= f64::MAX;
                ok &= good;
                v[j] = if good { xv } else { 1.0 };
            }
            let mut l = [0.0f64; CHUNK];
            for j in 0..CHUNK {
                l[j] = ln_positive(v[j]);
            }
            os.copy_from_slice(&l[..os.len()]);
        }
        ok
    }
}

/// The arguments of [`exact_normal_n`] as a [`super::simd::Kernel`].
struct ExactNormal<'a, 'p> {
    problem: &'a LogExact<'p>,
    theta: &'a [f64],
    jtj: &'a mut [f64],
    jtr: &'a mut [f64],
}

impl super::simd::Kernel for ExactNormal<'_, '_> {
    type Output = Option<f64>;
    #[inline(always)]
    fn run(self) -> Option<f64> {
        let ExactNormal {
            problem,
            theta,
            jtj,
            jtr,
        } = self;
        match problem.n {
            1 => exact_normal_n::<1>(problem, theta, jtj, jtr),
            2 => exact_normal_n::<2>(problem, theta, jtj, jtr),
            3 => exact_normal_n::<3>(problem, theta, jtj, jtr),
            _ => exact_normal_n::<4>(problem, theta, jtj, jtr),
        }
    }
}

/// [`log_normal_n`] of the exact log objective written out as loops over blocks of
/// [`CHUNK`] samples, the same operations in the same order (so the same bits, on every
/// instruction set): under the SIMD dispatch the block's exp and ln run at the CPU's full
/// width, where the closures of the shared kernel ([`log_sum_exp_points`], [`LogRows::rows`])
/// are not forced inline into it (measured: the exact isotropic fit was a quarter of the
/// default fit's CPU on `scan1024`).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
fn exact_normal_n<const N: usize>(
    problem: &LogExact,
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    let p = 2 * N;
    let (a, d) = split(theta, N);
    let len = problem.r.len().min(problem.y.len());
    let mut cost = 0.0;
    let mut acc = [[0.0f64; 8]; 8];
    let mut g = [0.0f64; 8];
    let mut t = [[0.0f64; CHUNK]; N];
    let mut rr = [0.0f64; CHUNK];
    let mut start = 0;
    while start < len {
        let l = CHUNK.min(len - start);
        rr[..l].copy_from_slice(&problem.r[start..start + l]);
        rr[l..].fill(0.0);
        let (m, sum) = block_terms::<N>(&a, &d, &rr, &mut t);
        let mut ln_rd = [0.0f64; CHUNK];
        let mut inv = [0.0f64; CHUNK];
        for j in 0..CHUNK {
            inv[j] = 1.0 / sum[j];
            ln_rd[j] = m[j] + ln_positive(sum[j]);
        }
        for j in 0..l {
            let r = rr[j];
            let mut row = [0.0f64; 8];
            for k in 0..N {
                let w = t[k][j] * inv[j];
                row[2 * k] = w;
                row[2 * k + 1] = w * r * d[k];
            }
            let res = ln_rd[j] - problem.y[start + j];
            cost += res * res;
            for i in 0..p {
                g[i] += row[i] * res;
                for k in i..p {
                    acc[i][k] += row[i] * row[k];
                }
            }
        }
        start += l;
    }
    finish_normal(p, &acc, &g, cost, jtj, jtr)
}

impl LogBinned<'_> {
    /// The binned cost alone (the residuals of [`binned_normal_n`] without the Jacobian):
    /// scoring the start candidates, four per fit, took 6 % of `fit-curve --batch` through the
    /// generic row evaluation (perf, BENCHMARKS.md).
    pub(crate) fn cost(&self, theta: &[f64]) -> Option<f64> {
        let (mut jtj, mut jtr) = ([0.0; 0], [0.0; 0]);
        match self.n {
            1 => binned_normal_n::<1, 2, 3, false>(self.bins, theta, &mut jtj, &mut jtr),
            2 => binned_normal_n::<2, 4, 10, false>(self.bins, theta, &mut jtj, &mut jtr),
            3 => binned_normal_n::<3, 6, 21, false>(self.bins, theta, &mut jtj, &mut jtr),
            _ => binned_normal_n::<4, 8, 36, false>(self.bins, theta, &mut jtj, &mut jtr),
        }
    }
}

impl LogRows for LogBinned<'_> {
    fn terms(&self) -> usize {
        self.n
    }
    fn normal(&self, theta: &[f64], jtj: &mut [f64], jtr: &mut [f64]) -> Option<f64> {
        match self.n {
            1 => binned_normal_n::<1, 2, 3, true>(self.bins, theta, jtj, jtr),
            2 => binned_normal_n::<2, 4, 10, true>(self.bins, theta, jtj, jtr),
            3 => binned_normal_n::<3, 6, 21, true>(self.bins, theta, jtj, jtr),
            _ => binned_normal_n::<4, 8, 36, true>(self.bins, theta, jtj, jtr),
        }
    }
    fn points(&self) -> usize {
        self.bins.len()
    }
    fn r(&self, j: usize) -> f64 {
        self.bins[j].r
    }
    fn rows_per_point(&self, _: usize) -> usize {
        3
    }
    /// The bin's three rows U·v − z, v = (L − ȳ, g, h/2) (see [`super::bins`]), with
    /// g = Σ w_k d_k and h = Σ w_k d_k² − g² the first two derivatives of ln R_d at r̄, and
    /// ∂g/∂a_k = w_k(d_k − g), ∂h/∂a_k = w_k((d_k − g)² − h), ∂/∂b_k = d_k·∂/∂d_k with
    /// ∂g/∂d_k = w_k(1 + r(d_k − g)), ∂h/∂d_k = w_k(2(d_k − g) + r((d_k − g)² − h)).
    #[inline(always)]
    #[allow(clippy::needless_range_loop)]
    fn rows<const N: usize>(
        &self,
        j: usize,
        ln_rd: f64,
        w: &[f64; 4],
        d: &[f64; 4],
        mut emit: impl FnMut(f64, &[f64; 8]),
    ) {
        let b = &self.bins[j];
        let r = b.r;
        let (mut g, mut q) = (0.0, 0.0);
        for k in 0..N {
            g += w[k] * d[k];
            q += w[k] * d[k] * d[k];
        }
        let h = q - g * g;
        let v = [ln_rd - b.y, g, 0.5 * h];
        // Jacobian rows of v.
        let mut jv = [[0.0f64; 8]; 3];
        for k in 0..N {
            let dk = d[k] - g;
            let e = dk * dk - h;
            jv[0][2 * k] = w[k];
            jv[0][2 * k + 1] = w[k] * r * d[k];
            jv[1][2 * k] = w[k] * dk;
            jv[1][2 * k + 1] = w[k] * (1.0 + r * dk) * d[k];
            jv[2][2 * k] = 0.5 * w[k] * e;
            jv[2][2 * k + 1] = 0.5 * w[k] * (2.0 * dk + r * e) * d[k];
        }
        let u = &b.u;
        let rows_u = [[u[0], u[1], u[2]], [0.0, u[3], u[4]], [0.0, 0.0, u[5]]];
        for (i, ui) in rows_u.iter().enumerate() {
            let mut row = [0.0f64; 8];
            for c in 0..2 * N {
                row[c] = ui[0] * jv[0][c] + ui[1] * jv[1][c] + ui[2] * jv[2][c];
            }
            emit(ui[0] * v[0] + ui[1] * v[1] + ui[2] * v[2] - b.z[i], &row);
        }
    }
}

/// [`LogBinned`]'s normal equations (the same rows as its [`LogRows::rows`], which the tests
/// compare), a block of [`CHUNK`] bins at a time in structure-of-arrays form: every quantity
/// of a bin (weights, g, h, the Jacobian of v, the three rows U·∂v) is an array over the block,
/// so each step is a loop of constant length over independent bins, which the compiler
/// vectorises, and JᵀJ gathers one partial sum per entry and bin lane instead of one serial
/// chain per entry. This is the fast mode's whole fit (`fit-curve --batch`, BENCHMARKS.md).
fn binned_normal_n<const N: usize, const P: usize, const T: usize, const JAC: bool>(
    bins: &[Bin],
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    super::simd::wide(BinnedNormal::<N, P, T, JAC> {
        bins,
        theta,
        jtj,
        jtr,
    })
}

/// The arguments of [`binned_normal_kernel`] as a [`super::simd::Kernel`].
struct BinnedNormal<'a, const N: usize, const P: usize, const T: usize, const JAC: bool> {
    bins: &'a [Bin],
    theta: &'a [f64],
    jtj: &'a mut [f64],
    jtr: &'a mut [f64],
}

impl<const N: usize, const P: usize, const T: usize, const JAC: bool> super::simd::Kernel
    for BinnedNormal<'_, N, P, T, JAC>
{
    type Output = Option<f64>;
    #[inline(always)]
    fn run(self) -> Option<f64> {
        binned_normal_kernel::<N, P, T, JAC>(self.bins, self.theta, self.jtj, self.jtr)
    }
}

/// The body of [`binned_normal_n`], inlined into its SIMD dispatch (and called directly, for
/// the baseline, by the test that compares the two).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // index loops over parallel arrays vectorise
pub(crate) fn binned_normal_kernel<
    const N: usize,
    const P: usize,
    const T: usize,
    const JAC: bool,
>(
    bins: &[Bin],
    theta: &[f64],
    jtj: &mut [f64],
    jtr: &mut [f64],
) -> Option<f64> {
    // P = 2N (the parameters), a parameter of its own because array lengths cannot be 2·N
    // on stable Rust: arrays sized for N = 4 whatever N was, zeroed on every call and block,
    // were 38 % of this function's instructions (memset) on the scipy comparison (callgrind).
    // T = P(P + 1)/2, the entries of JᵀJ's upper triangle, likewise.
    debug_assert!(P == 2 * N && T == P * (P + 1) / 2);
    let p = P;
    let (a, d) = split(theta, N);
    let mut acc = [[0.0f64; CHUNK]; T];
    let mut grad = [[0.0f64; CHUNK]; P];
    let mut cost = [0.0f64; CHUNK];
    // Per-block arrays, set up once: every lane is written in each block (padding lanes of a
    // short last block get U = 0 and z = 0: zero rows, zero residuals).
    let (mut r, mut y) = ([0.0f64; CHUNK], [0.0f64; CHUNK]);
    let mut u = [[0.0f64; CHUNK]; 6];
    let mut z = [[0.0f64; CHUNK]; 3];
    let mut w = [[0.0f64; CHUNK]; N];
    let mut rows = [[[0.0f64; CHUNK]; P]; 3];
    for block in bins.chunks(CHUNK) {
        for j in 0..CHUNK {
            let b = block.get(j).copied().unwrap_or_default();
            r[j] = b.r;
            y[j] = b.y;
            for i in 0..6 {
                u[i][j] = b.u[i];
            }
            for i in 0..3 {
                z[i][j] = b.z[i];
            }
        }
        // ln R_d and the weights w_k = c_k e^{d_k r} / R_d (the log-sum-exp kernel's).
        let (m, sum) = block_terms::<N>(&a, &d, &r, &mut w);
        let mut v = [[0.0f64; CHUNK]; 3];
        let (mut g, mut h) = ([0.0f64; CHUNK], [0.0f64; CHUNK]);
        let mut inv = [0.0f64; CHUNK];
        for j in 0..CHUNK {
            inv[j] = 1.0 / sum[j];
            v[0][j] = m[j] + ln_positive(sum[j]) - y[j];
        }
        for k in 0..N {
            for j in 0..CHUNK {
                w[k][j] *= inv[j];
                g[j] += w[k][j] * d[k];
                h[j] += w[k][j] * d[k] * d[k];
            }
        }
        for j in 0..CHUNK {
            h[j] -= g[j] * g[j];
            v[1][j] = g[j];
            v[2][j] = 0.5 * h[j];
        }
        let mut res = [[0.0f64; CHUNK]; 3];
        for j in 0..CHUNK {
            res[0][j] = u[0][j] * v[0][j] + u[1][j] * v[1][j] + u[2][j] * v[2][j] - z[0][j];
            res[1][j] = u[3][j] * v[1][j] + u[4][j] * v[2][j] - z[1][j];
            res[2][j] = u[5][j] * v[2][j] - z[2][j];
        }
        for i in 0..3 {
            for j in 0..CHUNK {
                cost[j] += res[i][j] * res[i][j];
            }
        }
        if !JAC {
            continue;
        }
        // The rows U·∂v straight from the Jacobian of v (see `LogRows::rows` of LogBinned):
        // U = [[u0, u1, u2], [0, u3, u4], [0, 0, u5]].
        for k in 0..N {
            for j in 0..CHUNK {
                let dk = d[k] - g[j];
                let e = dk * dk - h[j];
                let wk = w[k][j];
                let ja = [wk, wk * dk, 0.5 * wk * e];
                let jb = [
                    wk * r[j] * d[k],
                    wk * (1.0 + r[j] * dk) * d[k],
                    0.5 * wk * (2.0 * dk + r[j] * e) * d[k],
                ];
                for (c, jv) in [(2 * k, ja), (2 * k + 1, jb)] {
                    rows[0][c][j] = u[0][j] * jv[0] + u[1][j] * jv[1] + u[2][j] * jv[2];
                    rows[1][c][j] = u[3][j] * jv[1] + u[4][j] * jv[2];
                    rows[2][c][j] = u[5][j] * jv[2];
                }
            }
        }
        // The three rows' contributions to an entry are added in row order (the order of the
        // rows' emission, so the sums match `LogRows::rows` bit for bit) in one pass per entry:
        // one load and store of each partial sum per block instead of three.
        for c in 0..p {
            for j in 0..CHUNK {
                let mut s = grad[c][j];
                s += rows[0][c][j] * res[0][j];
                s += rows[1][c][j] * res[1][j];
                s += rows[2][c][j] * res[2][j];
                grad[c][j] = s;
            }
        }
        let mut t = 0;
        for c in 0..p {
            for c2 in c..p {
                for j in 0..CHUNK {
                    let mut s = acc[t][j];
                    s += rows[0][c][j] * rows[0][c2][j];
                    s += rows[1][c][j] * rows[1][c2][j];
                    s += rows[2][c][j] * rows[2][c2][j];
                    acc[t][j] = s;
                }
                t += 1;
            }
        }
    }
    let lane_sum = |x: &[f64; CHUNK]| x.iter().sum::<f64>();
    if !JAC {
        let cost = lane_sum(&cost);
        return cost.is_finite().then_some(cost);
    }
    let mut t = 0;
    for i in 0..p {
        jtr[i] = lane_sum(&grad[i]);
        for k in i..p {
            let s = lane_sum(&acc[t]);
            t += 1;
            jtj[i * p + k] = s;
            jtj[k * p + i] = s;
        }
    }
    let cost = lane_sum(&cost);
    (cost.is_finite() && jtr[..p].iter().all(|v| v.is_finite())).then_some(cost)
}

/// Every log objective is a [`Problem`] through its rows: the one-pass normal equations for the
/// solver, the generic row evaluation for the reference solver and the tests.
impl<O: LogRows> Problem for O {
    fn params(&self) -> usize {
        2 * self.terms()
    }
    fn normal_equations(
        &self,
        theta: &[f64],
        jtj: &mut [f64],
        jtr: &mut [f64],
    ) -> Option<Option<f64>> {
        Some(self.normal(theta, jtj, jtr))
    }
    fn rows(&self) -> usize {
        (0..self.points()).map(|j| self.rows_per_point(j)).sum()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, row: F) -> bool {
        log_eval(self, self.terms(), theta, jac, row)
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
    // The last digits by Gauss–Newton on all 2n parameters (see `polish_gauss_newton`).
    best.map(|b| {
        let before = b.iterations;
        let b = if b.converged {
            lm::polish_gauss_newton(&Linear { r: rn, s: sn, n }, b)
        } else {
            b
        };
        lm::Outcome {
            iterations: iterations + (b.iterations - before),
            ..b
        }
    })
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
    starts_scored(bins, bins, n)
}

/// [`starts`] built from `bins` (the peeling's line fits), with the amplitudes' NNLS and the
/// ranking by binned cost on `score`: statistics of the same samples, e.g. the coarse level of
/// [`fit_fixed`]'s coarse-to-fine solve, where both cost a quarter of the work (10 % of the
/// instructions of `fit-curve --batch` on 64 bins).
pub(crate) fn starts_scored(bins: &[Bin], score: &[Bin], n: usize) -> Vec<Vec<f64>> {
    // Each bin's mean level e^ȳ, used by both peels and every amplitude fit: computed once here
    // instead of in each (libm `exp` was 4 % of `fit-curve --batch`, perf).
    let levels: Vec<f64> = bins.iter().map(|b| b.y.exp()).collect();
    let score_levels: Vec<f64> = if std::ptr::eq(score, bins) {
        levels.clone()
    } else {
        score.iter().map(|b| b.y.exp()).collect()
    };
    let nnls = (score, score_levels.as_slice());
    let mut out = vec![peel(bins, &levels, nnls, n, false)];
    if n > 1 {
        out.push(peel(bins, &levels, nnls, n, true));
    }
    if n > 1 {
        let pts: Vec<(f64, f64, f64)> = bins.iter().map(|b| (b.r, b.y, b.n)).collect();
        let rho = line_fit(&pts).map_or(1.0, |(_, b)| (-b).max(0.5));
        for q in [3.0f64, 8.0] {
            let rates: Vec<f64> = (0..n)
                .map(|k| rho * q.powf(k as f64 - (n - 1) as f64 / 2.0))
                .collect();
            let mut amps: Vec<f64> = vec![(bins.first().map_or(0.0, |b| b.y)).exp() / n as f64; n];
            nnls_amplitudes(score, &score_levels, &rates, &mut amps);
            let cmax = amps.iter().cloned().fold(0.0, f64::max).max(1e-300);
            out.push(
                (0..n)
                    .flat_map(|k| [amps[k].max(cmax * 1e-3).ln(), rates[k].ln()])
                    .collect(),
            );
        }
    }
    let problem = LogBinned { bins: score, n };
    let cost = |t: &Vec<f64>| problem.cost(t).unwrap_or(f64::INFINITY);
    let mut scored: Vec<(f64, Vec<f64>)> = out.into_iter().map(|t| (cost(&t), t)).collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    scored.into_iter().map(|(_, t)| t).collect()
}

/// Start values by peeling the tail in log space: the slowest term is a line through ln s over
/// the farthest group of bins; it is subtracted and the next group gives the next term, up to the
/// fastest term near x_i. With `visible`, the groups of the faster terms split only the bins
/// where the remainder is still a visible part of the signal: on the scipy comparison's curves
/// (BENCHMARKS.md) that halved the iterations (a mean of 8.6 to 4.5), because n equal groups put
/// the middle term's group where the slowest term's tail swamps it. Without it, n equal groups:
/// alone, the visible-range start led some of the pipeline's per-vertex fits to other minima
/// (the anisotropic simulated slab's in-sample log E 0.267 -> 0.324), so [`starts`] offers both
/// and the lower start cost goes first. Rates are forced to grow by ≥ 1.5× per term (well separated, ordered),
/// then the amplitudes are re-solved by non-negative least squares with relative weights for
/// those rates over `nnls.0` (statistics of the same samples: `bins` itself, or the coarse
/// level of [`fit_fixed`], where the exponentials of the NNLS cost a quarter), whose e^ȳ are
/// `nnls.1`. `levels` are the e^ȳ of `bins`. Returns θ in normalised units.
pub(crate) fn peel(
    bins: &[Bin],
    levels: &[f64],
    nnls: (&[Bin], &[f64]),
    n: usize,
    visible: bool,
) -> Vec<f64> {
    /// Share of the signal that the remaining terms must carry for a bin to count in their
    /// groups.
    const PEEL_VISIBLE: f64 = 0.05;
    let nb = bins.len();
    let mut resid: Vec<f64> = levels.to_vec();
    let mut rates = vec![0.0f64; n];
    let mut amps = vec![0.0f64; n];
    let mut prev_rate: f64 = 0.0;
    // Bins [0, end) are still to be explained by terms 0..=k.
    let mut end = nb;
    for k in (0..n).rev() {
        // The farthest of k + 1 contiguous groups of [0, end) (k = 0: all of it).
        let (lo, hi) = if visible {
            let lo = end * k / (k + 1);
            (lo, end.max(lo + 1).min(nb))
        } else {
            // Group k of n equal groups (k = 0 nearest).
            let lo = nb * k / n;
            (lo, (nb * (k + 1) / n).max(lo + 1).min(nb))
        };
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
        // The faster terms only matter where what is left is a visible part of the signal
        // (5 %, far above the noise of a bin's mean): their groups split that range, not all
        // nearer bins, where the slower terms' tails would swamp them.
        end = (0..lo)
            .rev()
            .find(|&i| resid[i] > PEEL_VISIBLE * levels[i])
            .map_or(lo, |i| i + 1)
            .max(2 * k)
            .min(lo);
    }
    nnls_amplitudes(nnls.0, nnls.1, &rates, &mut amps);
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
/// `levels` are the bins' v_b = e^ȳ. Runs for every start candidate of every curve: the
/// exponentials are computed once for all active-set rounds (a round only drops terms), and
/// the normal equations live on the stack.
fn nnls_amplitudes(bins: &[Bin], levels: &[f64], rates: &[f64], amps: &mut [f64]) {
    const MT: usize = crate::model::MAX_TERMS;
    let n = rates.len().min(MT).min(amps.len());
    // Per usable bin: the weight n_b / v_b², v_b and e^{−rate_k r̄_b} for every term.
    let mut table: Vec<(f64, f64, [f64; MT])> = Vec::with_capacity(bins.len());
    for (b, &v) in bins.iter().zip(levels) {
        if !(v > 0.0 && v.is_finite()) {
            continue;
        }
        let mut e = [0.0f64; MT];
        for (ek, rate) in e.iter_mut().zip(&rates[..n]) {
            *ek = (-rate * b.r).exp();
        }
        table.push((b.n / (v * v), v, e));
    }
    let mut active = [false; MT];
    active[..n].fill(true);
    for _ in 0..n {
        let mut idx = [0usize; MT];
        let mut m = 0;
        for k in (0..n).filter(|&k| active[k]) {
            idx[m] = k;
            m += 1;
        }
        let (a, rhs) = match m {
            0 => return,
            1 => nnls_normal::<1>(&table, &idx),
            2 => nnls_normal::<2>(&table, &idx),
            3 => nnls_normal::<3>(&table, &idx),
            _ => nnls_normal::<4>(&table, &idx),
        };
        let mut x = [0.0f64; MT];
        let mut scratch = [0.0f64; MT * MT];
        let x = &mut x[..m];
        if !super::lm::solve_plain(&a[..m * m], &rhs[..m], x, &mut scratch[..m * m]) {
            return;
        }
        if x.iter().all(|v| *v > 0.0) {
            for (i, &k) in idx[..m].iter().enumerate() {
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

/// The normal equations (row-major M×M matrix, right-hand side) of [`nnls_amplitudes`] over the
/// terms `idx[..M]`, monomorphised so the loops have constant bounds.
#[inline]
fn nnls_normal<const M: usize>(
    table: &[(f64, f64, [f64; crate::model::MAX_TERMS])],
    idx: &[usize; crate::model::MAX_TERMS],
) -> (
    [f64; crate::model::MAX_TERMS * crate::model::MAX_TERMS],
    [f64; crate::model::MAX_TERMS],
) {
    let mut a = [0.0f64; crate::model::MAX_TERMS * crate::model::MAX_TERMS];
    let mut rhs = [0.0f64; crate::model::MAX_TERMS];
    for (wgt, v, e) in table {
        let e: [f64; M] = std::array::from_fn(|i| e[idx[i]]);
        for i in 0..M {
            // (w·e_i)·v and (w·e_i)·e_j: the products in the order of the textbook sums.
            let we = wgt * e[i];
            rhs[i] += we * v;
            for j in 0..M {
                a[i * M + j] += we * e[j];
            }
        }
    }
    (a, rhs)
}

/// Convergence tolerance of the fast mode's binned fit: log E is then settled to ~6 digits, far
/// below the binning error the bin count trades for speed.
const FAST_FTOL: f64 = 1e-6;

/// Convergence tolerance (relative cost reduction) of the exact polish after the binned pre-fit.
const POLISH_FTOL: f64 = 1e-10;

/// Fine bins merged into one bin of the coarse level of the binned fit ([`fit_fixed`]).
const COARSE_MERGE: usize = 4;

/// Fewest (non-empty) fine bins for which the binned fit has a coarse level: below that the
/// coarse bins would be too few and too wide for their quadratic model.
const COARSE_MIN_BINS: usize = 48;

/// Convergence tolerance of the coarse level's runs: they only bring the start next to the
/// minimum, which the fine level then finds. (The runs stop at a stationary point anyway, see
/// `lm::stationary`; 1e-4 took 0.4 more coarse iterations a curve for the same fits.)
const COARSE_FTOL: f64 = 1e-2;

/// Initial damping of the fine level's run from the coarse minimum, which is inside the region
/// where Gauss–Newton converges (see [`Settings::initial_damping`]).
const FINE_DAMPING: f64 = 1e-6;

/// Bins of the pre-fit that gives the exact log fit its start (and of the start values).
pub(crate) const PREFIT_BINS: usize = 64;

/// What one fixed-order fit produced, in original units.
pub(crate) struct Raw {
    pub model: ExpSum,
    pub iterations: usize,
    pub converged: bool,
    /// The solver stalled at a non-stationary point.
    pub stalled: bool,
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
    // Bins feed the start values and the pre-fit (the whole fit in fast mode). Binning computes
    // ln s, the scale and the level on the fly, so the fast mode touches each sample once.
    let binned = bin_samples(r, s, bins.unwrap_or(PREFIT_BINS).max(2 * n + 2));
    let scale_r = binned.scale_r;
    let (level, prefit_bins) = match objective {
        Objective::Log => (binned.level, binned.bins),
        Objective::Linear => {
            // Values relative to the largest one, where the linear residual has its weight.
            let level = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max).ln();
            let shift = level - binned.level;
            let bins = binned
                .bins
                .into_iter()
                .map(|b| b.normalised(1.0, shift))
                .collect();
            (level, bins)
        }
    };
    // Per-sample normalised data, only for the solves that use every sample.
    let per_sample = || -> (Vec<f64>, Vec<f64>) {
        (
            r.iter().map(|v| v / scale_r).collect(),
            s.iter().map(|&v| ln_positive(v) - level).collect(),
        )
    };
    let given = match start {
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
            Some(t)
        }
        None => None,
    };
    // The best start candidate by cost, for the solvers that run from one start.
    let theta0 = || match &given {
        Some(t) => t.clone(),
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
            let binned = LogBinned {
                bins: &prefit_bins,
                n,
            };
            // The binned fit only approximates the exact one (its log E differs in the 3rd–5th
            // digit), so iterating it to machine precision buys nothing.
            // Relative tests count the scatter the bins' cost leaves out (see
            // `Settings::cost_offset`): with 1 % noise most of the objective is scatter.
            let binned_settings = Settings {
                ftol: if bins.is_some() {
                    FAST_FTOL
                } else {
                    POLISH_FTOL
                },
                cost_offset: prefit_bins.iter().map(|b| b.scatter).sum(),
                ..settings
            };
            // Coarse to fine: every COARSE_MERGE bins merged (exact statistics of the same
            // samples on a quarter of the bins) are where the candidates get their amplitudes
            // and ranking and each run takes its first steps, a quarter of the work per step;
            // the fine bins then take the last 1–2 steps (BENCHMARKS.md, "Third pass"). A
            // given start skips it (it is meant to be used as it is). Fast mode only: there it
            // finds the same minima (the 2,000 curves of the scipy comparison: mean log E equal
            // to 7 digits), but as the exact fit's pre-fit it led some of the pipeline's
            // per-vertex fits on sample-torus to other minima, so the exact mode keeps the
            // candidates ranked on the fine bins (its result must not depend on a coarsening).
            let coarse_bins =
                (given.is_none() && bins.is_some() && prefit_bins.len() >= COARSE_MIN_BINS)
                    .then(|| coarsen(&prefit_bins, COARSE_MERGE));
            let coarse = coarse_bins.as_deref().map(|bins| LogBinned { bins, n });
            let coarse_settings = Settings {
                ftol: COARSE_FTOL,
                cost_offset: coarse_bins
                    .as_deref()
                    .map_or(0.0, |b| b.iter().map(|b| b.scatter).sum()),
                ..settings
            };
            let mut pre: Option<lm::Outcome> = None;
            // One run; whether it converged with every term alive.
            let mut run = |cand: &[f64]| -> bool {
                // Coarse to fine: the run on the coarse bins only brings the start next to the
                // minimum; the fine run from there decides the fit, so its minimum is the
                // fine objective's.
                let coarse_run = coarse
                    .as_ref()
                    .and_then(|c| lm::minimize(c, cand, &coarse_settings));
                if let Some(o) = &coarse_run {
                    iterations += o.iterations;
                }
                let cand = coarse_run.as_ref().map_or(cand, |o| &o.theta[..]);
                // From the coarse minimum, Gauss–Newton steps converge at once: little damping,
                // and no trial step whose decrease only rounding could show (mean fine
                // iterations on the scipy comparison's curves 2.5 -> 1.25, same minima).
                let fine_settings = if coarse_run.is_some() {
                    Settings {
                        initial_damping: FINE_DAMPING,
                        stop_on_predicted: true,
                        ..binned_settings
                    }
                } else {
                    binned_settings
                };
                let Some(o) = lm::minimize(&binned, cand, &fine_settings) else {
                    return false;
                };
                iterations += o.iterations;
                let healthy = o.converged && !has_dead_term(&o.theta, n);
                if pre.as_ref().is_none_or(|p| o.cost < p.cost) {
                    pre = Some(o);
                }
                healthy
            };
            // The candidates of [`starts`] in order of cost until one converges with every term
            // alive. (Trying the peeled start alone first gave the same fits on the scipy
            // comparison's curves but worse ones on the anisotropic slab of the `fit_aniso`
            // test, where another candidate starts lower.)
            let candidates = match &given {
                Some(t) => vec![t.clone()],
                None => starts_scored(
                    &prefit_bins,
                    coarse_bins.as_deref().unwrap_or(&prefit_bins),
                    n,
                ),
            };
            let first = candidates[0].clone();
            for cand in &candidates {
                if run(cand) {
                    break;
                }
            }
            if bins.is_some() {
                // log E from the statistics: the binned cost plus each bin's scatter about its
                // own quadratic (the part no smooth model can explain).
                rss_estimate = pre
                    .as_ref()
                    .map(|o| o.cost + prefit_bins.iter().map(|b| b.scatter).sum::<f64>());
                // Every run's iterations are counted above already.
                pre.map(|o| lm::Outcome { iterations: 0, ..o })
            } else {
                let theta1 = pre.map_or(first, |o| o.theta);
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
            super::reference::minimize(&LogExact { r: &rn, y: &y, n }, &theta0(), max_iterations)
        }
        (Objective::Linear, Solver::Specialised) => {
            let (rn, y) = per_sample();
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            linear_specialised(&rn, &sn, n, &theta0(), &settings)
        }
        (Objective::Linear, Solver::Reference) => {
            let (rn, y) = per_sample();
            let sn: Vec<f64> = y.iter().map(|v| v.exp()).collect();
            super::reference::minimize(&Linear { r: &rn, s: &sn, n }, &theta0(), max_iterations)
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
        stalled: out.stalled,
        rss_estimate,
    })
}
