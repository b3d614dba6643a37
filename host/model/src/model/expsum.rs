//! Eq. 1: the sum of exponentials R_d(r) = Σ_k c_k·exp(d_k·r).

use serde::{Deserialize, Serialize};

use super::{ModelError, log_sum_exp, log_sum_exp_of};

/// Largest number of terms n the project fits (the paper uses n = 3; auto order tries 1..=4).
pub const MAX_TERMS: usize = 4;

/// One term c·exp(d·r) of Eq. 1. Valid terms have c > 0 and d < 0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Term {
    /// Amplitude c_k(x_i) > 0.
    pub c: f64,
    /// Rate d_k(x_i) < 0 (per length unit).
    pub d: f64,
}

impl Term {
    /// 2π ∫_a^b r·c·e^{d·r} dr: the diffuse reflectance this term puts on a plane between the
    /// distances `a` ≤ `b` (0 for b ≤ a). Any d ≤ 0 (an extension rule's term may be flat), in
    /// a closed form that stays exact for rates near 0, where the textbook antiderivative
    /// e^{dr}(r/d − 1/d²) cancels to nothing (fits run unsupported terms to d ≈ −1e−16).
    pub fn reflectance_between(&self, a: f64, b: f64) -> f64 {
        if b.partial_cmp(&a) != Some(std::cmp::Ordering::Greater) {
            return 0.0;
        }
        // With h = b − a and x = d·h: ∫_a^b r e^{dr} dr = e^{da}·(a·h·φ1(x) + h²·φ2(x)),
        // φ1(x) = ∫_0^1 e^{xt} dt = Σ x^k / (k!·(k+1)), φ2(x) = ∫_0^1 t·e^{xt} dt =
        // Σ x^k / (k!·(k+2)); their series below |x| = 0.01 (truncation ~1e−13), the closed
        // forms above.
        let h = b - a;
        let x = self.d * h;
        let (phi1, phi2) = if x.abs() < 0.01 {
            (
                1.0 + x * (1.0 / 2.0 + x * (1.0 / 6.0 + x * (1.0 / 24.0 + x / 120.0))),
                0.5 + x * (1.0 / 3.0 + x * (1.0 / 8.0 + x * (1.0 / 30.0 + x / 144.0))),
            )
        } else {
            let em1 = x.exp_m1();
            (em1 / x, (x * x.exp() - em1) / (x * x))
        };
        2.0 * std::f64::consts::PI * self.c * (self.d * a).exp() * (a * h * phi1 + h * h * phi2)
    }
}

/// Eq. 1: isotropic diffuse reflectance R_d(x_i → x_o) = Σ_k c_k·exp(d_k·|x_o − x_i|).
///
/// Invariant of a validated value: 1..=[`MAX_TERMS`] terms, every c_k > 0 and d_k < 0 finite, so
/// R_d > 0 everywhere and R_d → 0 as r → ∞. Terms are kept in canonical order: by rate −d_k
/// ascending (slowest fall-off first, the NIST Lanczos order), ties by c.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExpSum {
    /// The terms, in canonical order when built by [`ExpSum::new`].
    pub terms: Vec<Term>,
}

impl ExpSum {
    /// Validates and sorts the terms into canonical order.
    pub fn new(mut terms: Vec<Term>) -> Result<Self, ModelError> {
        sort_terms(&mut terms);
        let s = Self { terms };
        s.validate()?;
        Ok(s)
    }

    /// Checks the Eq. 1 constraints (term count, finite, c > 0, d < 0).
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.terms.is_empty() || self.terms.len() > MAX_TERMS {
            return Err(ModelError::TermCount {
                got: self.terms.len(),
                max: MAX_TERMS,
            });
        }
        for (index, t) in self.terms.iter().enumerate() {
            if !t.c.is_finite() {
                return Err(ModelError::NonFinite { what: "c" });
            }
            if !t.d.is_finite() {
                return Err(ModelError::NonFinite { what: "d" });
            }
            if t.c <= 0.0 {
                return Err(ModelError::NonPositiveC { index, c: t.c });
            }
            if t.d >= 0.0 {
                return Err(ModelError::NonNegativeD { index, d: t.d });
            }
        }
        Ok(())
    }

    /// Number of terms n.
    pub fn n(&self) -> usize {
        self.terms.len()
    }

    /// R_d(r), Eq. 1. Underflows to 0 gracefully for large r; use [`ExpSum::ln_eval`] when the
    /// logarithm is wanted.
    pub fn eval(&self, r: f64) -> f64 {
        self.terms.iter().map(|t| t.c * (t.d * r).exp()).sum()
    }

    /// ln R_d(r), Eq. 1 evaluated as a log-sum-exp of ln c_k + d_k·r: finite wherever the model is
    /// valid and r is finite, even where every exp(d_k·r) underflows.
    pub fn ln_eval(&self, r: f64) -> f64 {
        self.ln_terms(r, |t, _| t.c.ln())
    }

    /// The terms' ln c_k, for [`ExpSum::ln_eval_with`].
    pub fn ln_c(&self) -> Vec<f64> {
        self.terms.iter().map(|t| t.c.ln()).collect()
    }

    /// [`ExpSum::ln_eval`] with the terms' ln c_k given (`ln_c` = [`ExpSum::ln_c`]): the same
    /// bits without a log per term, for loops that evaluate one fall-off at many distances
    /// ([`super::LnEvaluator`]).
    pub fn ln_eval_with(&self, ln_c: &[f64], r: f64) -> f64 {
        if ln_c.len() < self.terms.len() {
            return log_sum_exp(self.terms.iter().zip(ln_c).map(move |(t, lc)| lc + t.d * r));
        }
        self.ln_terms(r, |_, k| ln_c[k])
    }

    /// [`ExpSum::ln_eval_with`] at every distance of `r`, into `out` (as far as both reach),
    /// vectorised: the fit's branch-free exp and ln under the SIMD dispatch, within a few ulp
    /// of the scalar evaluation (a test bounds it), not its bits. The hot loops of the default
    /// fit take it (ln R_d at every sample of a light position, every round); the
    /// reference preset keeps the scalar path. Distances where the largest term is not finite
    /// (±∞, NaN) and sums of more than [`MAX_TERMS`] terms take the scalar path, the same values.
    pub fn ln_eval_many(&self, ln_c: &[f64], r: &[f64], out: &mut [f64]) {
        let n = self.terms.len();
        let len = r.len().min(out.len());
        let (r, out) = (&r[..len], &mut out[..len]);
        if n == 0 || n > MAX_TERMS || ln_c.len() < n {
            for (o, &x) in out.iter_mut().zip(r) {
                *o = self.ln_eval_with(ln_c, x);
            }
            return;
        }
        let (mut a, mut d) = ([0.0; 4], [0.0; 4]);
        for (k, t) in self.terms.iter().enumerate() {
            a[k] = ln_c[k];
            d[k] = t.d;
        }
        if !crate::fit::ln_sum_exp_many(&a, &d, n, r, out) {
            for (o, &x) in out.iter_mut().zip(r) {
                let m = (0..n).fold(f64::NEG_INFINITY, |m, k| m.max(a[k] + d[k] * x));
                if !m.is_finite() {
                    *o = self.ln_eval_with(ln_c, x);
                }
            }
        }
    }

    /// The log-sum-exp of ln c_k + d_k·r, ln c_k = `ln_c(term, k)`: the terms' values in an array
    /// on the stack (at most [`MAX_TERMS`] of them; a longer sum, which [`ExpSum::new`] refuses,
    /// through [`log_sum_exp`]), the same values in the same order, so the same bits.
    #[inline]
    fn ln_terms(&self, r: f64, ln_c: impl Fn(&Term, usize) -> f64) -> f64 {
        let n = self.terms.len();
        if n > MAX_TERMS {
            return log_sum_exp(
                self.terms
                    .iter()
                    .enumerate()
                    .map(|(k, t)| ln_c(t, k) + t.d * r),
            );
        }
        let mut v = [0.0; MAX_TERMS];
        for (k, t) in self.terms.iter().enumerate() {
            v[k] = ln_c(t, k) + t.d * r;
        }
        log_sum_exp_of(&v[..n])
    }

    /// d/dr ln R_d(r): the local fall-off rate (negative), a convex combination of the d_k.
    pub fn ln_slope(&self, r: f64) -> f64 {
        let l = self.ln_eval(r);
        self.terms
            .iter()
            .map(|t| t.d * (t.c.ln() + t.d * r - l).exp())
            .sum()
    }

    /// ∫_0^∞ R_d(r)·2πr dr = 2π Σ c_k / d_k²: the total diffuse reflectance of the isotropic model
    /// on a plane, comparable to [`super::Dipole::total_reflectance`].
    pub fn total_reflectance(&self) -> f64 {
        self.terms
            .iter()
            .map(|t| 2.0 * std::f64::consts::PI * t.c / (t.d * t.d))
            .sum()
    }

    /// 2π ∫_a^b r·R_d(r) dr: the share of [`ExpSum::total_reflectance`] between the distances `a`
    /// and `b` (see [`Term::reflectance_between`]).
    pub fn reflectance_between(&self, a: f64, b: f64) -> f64 {
        self.terms.iter().map(|t| t.reflectance_between(a, b)).sum()
    }

    /// The same model with every amplitude multiplied by `s` (channel scales of Eq. 5).
    pub fn scaled(&self, s: f64) -> Self {
        Self {
            terms: self
                .terms
                .iter()
                .map(|t| Term { c: t.c * s, d: t.d })
                .collect(),
        }
    }
}

/// Canonical term order: rate −d ascending (slowest first), then c ascending; NaN last.
pub(crate) fn sort_terms(terms: &mut [Term]) {
    terms.sort_by(|a, b| b.d.total_cmp(&a.d).then(a.c.total_cmp(&b.c)));
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m() -> ExpSum {
        ExpSum::new(vec![
            Term { c: 1.5576, d: -5.0 },
            Term { c: 0.0951, d: -1.0 },
            Term { c: 0.8607, d: -3.0 },
        ])
        .unwrap()
    }

    #[test]
    fn canonical_order_is_slowest_first() {
        let d: Vec<f64> = m().terms.iter().map(|t| t.d).collect();
        assert_eq!(d, vec![-1.0, -3.0, -5.0]);
    }

    #[test]
    fn ln_eval_matches_eval_and_survives_underflow() {
        let m = m();
        for r in [0.0, 0.3, 1.15, 10.0] {
            assert!((m.ln_eval(r) - m.eval(r).ln()).abs() < 1e-13);
        }
        // exp(-1e4) underflows; the log does not.
        let l = m.ln_eval(1e4);
        assert!((l - (0.0951f64.ln() - 1e4)).abs() < 1e-9);
        assert_eq!(m.eval(1e4), 0.0);
    }

    #[test]
    fn slope_matches_finite_difference() {
        let m = m();
        let h = 1e-6;
        let fd = (m.ln_eval(0.5 + h) - m.ln_eval(0.5 - h)) / (2.0 * h);
        assert!((m.ln_slope(0.5) - fd).abs() < 1e-7);
    }

    #[test]
    fn rejects_invalid_terms() {
        assert!(matches!(
            ExpSum::new(vec![]),
            Err(ModelError::TermCount { .. })
        ));
        assert!(matches!(
            ExpSum::new(vec![Term { c: -1.0, d: -1.0 }]),
            Err(ModelError::NonPositiveC { .. })
        ));
        assert!(matches!(
            ExpSum::new(vec![Term { c: 1.0, d: 0.0 }]),
            Err(ModelError::NonNegativeD { .. })
        ));
        assert!(matches!(
            ExpSum::new(vec![Term {
                c: f64::NAN,
                d: -1.0
            }]),
            Err(ModelError::NonFinite { .. })
        ));
        assert!(ExpSum::new(vec![Term { c: 1.0, d: -1.0 }; 5]).is_err());
    }

    #[test]
    fn total_reflectance_is_the_integral() {
        let m = ExpSum::new(vec![Term { c: 2.0, d: -0.5 }]).unwrap();
        assert!((m.total_reflectance() - 2.0 * std::f64::consts::PI * 8.0).abs() < 1e-12);
    }

    /// The closed form against the midpoint rule (1e6 panels), across the switch between the
    /// series and the closed forms of φ1, φ2, for rates from the steepest fitted near terms to
    /// the d ≈ −1e−16 of unsupported ones (and a flat term); the pieces add up to the total.
    #[test]
    fn reflectance_between_is_the_ring_integral() {
        let midpoint = |t: Term, a: f64, b: f64| {
            let k = 1_000_000;
            let h = (b - a) / k as f64;
            (0..k)
                .map(|i| {
                    let r = a + (i as f64 + 0.5) * h;
                    r * t.c * (t.d * r).exp()
                })
                .sum::<f64>()
                * h
                * 2.0
                * std::f64::consts::PI
        };
        for d in [-30.0, -3.0, -0.011, -0.009, -1e-3, -1e-16, 0.0] {
            for (a, b) in [(0.0, 0.5), (0.5, 1.9), (1.0, 2.0)] {
                let t = Term { c: 0.7, d };
                let (got, want) = (t.reflectance_between(a, b), midpoint(t, a, b));
                assert!(
                    (got - want).abs() <= 1e-8 * want,
                    "d {d} [{a}, {b}]: {got} vs {want}"
                );
            }
        }
        let m = m();
        let parts = m.reflectance_between(0.0, 0.4) + m.reflectance_between(0.4, 1e3);
        assert!((parts - m.total_reflectance()).abs() < 1e-12 * m.total_reflectance());
        assert_eq!(m.reflectance_between(2.0, 1.0), 0.0);
        assert_eq!(m.reflectance_between(1.0, f64::NAN), 0.0);
    }
}
