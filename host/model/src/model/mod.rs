//! The empirical subsurface-scattering model of Fuchs et al. 2005 (sections 3–5) and the dipole of
//! Jensen et al. 2001 it is compared against, as plain, serializable data with evaluation.
//!
//! Contract: everything here is pure (no I/O, no allocation beyond the model's own vectors) and
//! never panics on input. Constructors (`new`) validate; the fields are public so models can be
//! deserialized and built by fitters, and [`ExpSum::validate`] and friends re-check any value.
//! Distances are in the dataset's length unit (millimetres in this project) and rates in its
//! inverse; nothing here assumes a unit.
//!
//! - [`ExpSum`]: R_d(r) = Σ_k c_k·exp(d_k·r), Eq. 1, with c_k > 0 and d_k < 0.
//! - [`Anisotropic`]: m direction segments blended by hat functions w_l, Eq. 3, in the
//!   [`TangentFrame`] at x_i.
//! - [`ColourModel`]: per-channel fall-off (Eq. 3 per channel) or a shared fall-off with channel
//!   scales s_g, s_b (Eq. 5 and 9).
//! - [`alpha`]: the modulation texture alpha(x_o), Eq. 2, estimated by Eq. 6.
//! - [`error`]: reconstruction error E (Eq. 7), log E(x_i) (Eq. 8) and the Table-1 mean.
//! - [`dipole`]: the dipole diffusion approximation and the published measured materials.
//! - [`support`]: where a fitted model is claimed (below r_min, above r_max): one rule for every
//!   user of a model.

pub mod alpha;
pub mod aniso;
pub mod colour;
pub mod dipole;
pub mod error;
pub mod expsum;
pub mod support;

pub use alpha::{ALPHA_PRIOR, ALPHA_PRIOR_MAX, AlphaAccumulator, IntensityWindow, empirical_prior};
pub use aniso::{Anisotropic, FrameRule, TangentFrame, hat_weights};
pub use colour::{ColourModel, LnEvaluator};
pub use dipole::{Dipole, MATERIALS, Material};
pub use error::{LogEAccumulator, reconstruction_error, table1_mean};
pub use expsum::{ExpSum, MAX_TERMS, Term};
pub use support::{Support, ln_eval_supported, ln_slope};

/// Why a model value was rejected. Models are data; this is what `validate` reports.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ModelError {
    /// Eq. 1 needs between 1 and [`MAX_TERMS`] terms.
    #[error("a sum of exponentials needs 1..={max} terms, got {got}")]
    TermCount {
        /// Number of terms given.
        got: usize,
        /// Largest number allowed.
        max: usize,
    },
    /// A parameter is NaN or infinite.
    #[error("{what} is not finite")]
    NonFinite {
        /// Which parameter.
        what: &'static str,
    },
    /// c_k must be > 0 (Eq. 1 with R_d > 0).
    #[error("term {index}: c = {c} must be > 0")]
    NonPositiveC {
        /// Term index.
        index: usize,
        /// The offending value.
        c: f64,
    },
    /// d_k must be < 0 so that R_d → 0 as r → ∞ (section 3.1).
    #[error("term {index}: d = {d} must be < 0")]
    NonNegativeD {
        /// Term index.
        index: usize,
        /// The offending value.
        d: f64,
    },
    /// The anisotropic model needs at least one segment.
    #[error("an anisotropic model needs at least one segment")]
    NoSegments,
    /// A colour scale s_g / s_b (Eq. 5) must be finite and > 0.
    #[error("channel scale {what} = {value} must be finite and > 0")]
    BadScale {
        /// `s_g` or `s_b`.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// A dipole parameter is out of its physical range.
    #[error("dipole parameter {what} = {value} is out of range")]
    DipoleParameter {
        /// Which parameter.
        what: &'static str,
        /// The offending value.
        value: f64,
    },
    /// The tangent frame needs a finite, non-zero normal.
    #[error("normal is zero or not finite")]
    BadNormal,
}

/// log(Σ exp(v_i)) without overflow or underflow; −∞ for an empty input or all −∞ terms.
///
/// Each value is computed once (up to [`LSE_INLINE`] values held on the stack, more in a `Vec`):
/// the values are closures over `ln c_k + d_k·r`, and running them twice, once for the maximum
/// and once for the sum, cost a log per term per evaluation, on the fit's hottest path.
/// The arithmetic is the one it was, so the result is the same to the bit.
pub(crate) fn log_sum_exp(values: impl Iterator<Item = f64>) -> f64 {
    let mut held = [0.0; LSE_INLINE];
    let mut n = 0;
    let mut values = values.peekable();
    while n < LSE_INLINE {
        match values.next() {
            Some(v) => held[n] = v,
            None => break,
        }
        n += 1;
    }
    if values.peek().is_none() {
        return log_sum_exp_of(&held[..n]);
    }
    let all: Vec<f64> = held.into_iter().chain(values).collect();
    log_sum_exp_of(&all)
}

/// Values [`log_sum_exp`] holds on the stack: more than any model's terms × segments in use.
const LSE_INLINE: usize = 32;

/// [`log_sum_exp`] of values already held: for callers with a handful of values in an array
/// (a fall-off's n ≤ [`MAX_TERMS`] terms, a blend's one or two segments), the same bits without
/// the iterator and the 32 slots [`log_sum_exp`] clears on every call (with them,
/// `log_sum_exp` itself was a tenth of a cross-validated fit's CPU at 1024 px).
#[inline]
pub(crate) fn log_sum_exp_of(held: &[f64]) -> f64 {
    let m = held.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if m == f64::NEG_INFINITY || m.is_nan() {
        return m;
    }
    if m == f64::INFINITY {
        return m;
    }
    m + ln_exact_at_one(held.iter().map(|&v| exp_exact_at_zero(v - m)).sum::<f64>())
}

/// `x.exp()`, skipping the call at ±0 where it is exactly 1: the largest term of every
/// log-sum-exp is exp(0), and a one-term sum is nothing else (a third of the fit's
/// exps). Bit for bit `x.exp()`.
#[inline]
pub(crate) fn exp_exact_at_zero(x: f64) -> f64 {
    if x == 0.0 { 1.0 } else { x.exp() }
}

/// `x.ln()`, skipping the call at 1 where it is exactly +0: the sum of a one-term log-sum-exp
/// and the weight of an unsegmented model. Bit for bit `x.ln()`.
#[inline]
pub(crate) fn ln_exact_at_one(x: f64) -> f64 {
    if x == 1.0 { 0.0 } else { x.ln() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The two-pass form `log_sum_exp` had: the reference its bits are held to.
    fn log_sum_exp_twice(values: impl Iterator<Item = f64> + Clone) -> f64 {
        let m = values.clone().fold(f64::NEG_INFINITY, f64::max);
        if m == f64::NEG_INFINITY || m.is_nan() {
            return m;
        }
        if m == f64::INFINITY {
            return m;
        }
        m + values.map(|v| (v - m).exp()).sum::<f64>().ln()
    }

    fn value() -> impl Strategy<Value = f64> {
        prop_oneof![
            8 => -800.0..800.0f64,
            1 => Just(0.0),
            1 => Just(-0.0),
            1 => Just(f64::NEG_INFINITY),
            1 => Just(f64::INFINITY),
            1 => Just(f64::NAN),
        ]
    }

    /// A term (c_k, d_k): mostly of comparable size, so that every term counts in the sum and
    /// an order of summation other than the reference's would show, sometimes extreme.
    fn term() -> impl Strategy<Value = (f64, f64)> {
        prop_oneof![
            4 => (0.1..10.0f64, -5.0..-0.01f64),
            1 => (1e-300..1e3f64, -1e3..-1e-9f64),
        ]
    }

    proptest! {
        /// Holding the values on the stack changes no bit of the result: the same values, the
        /// same max, the same sum in the same order (and the skipped exp(0), ln(1) are exact).
        #[test]
        fn log_sum_exp_is_the_two_pass_sum_to_the_bit(
            v in proptest::collection::vec(value(), 0..(LSE_INLINE + 4)),
        ) {
            let got = log_sum_exp(v.iter().copied());
            let want = log_sum_exp_twice(v.iter().copied());
            prop_assert!(got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                "{got} against {want} for {v:?}");
        }

        /// A fall-off's ln R_d (Eq. 1) through its terms' array ([`log_sum_exp_of`]) and a model of
        /// one or two segments' blend (Eq. 3) are the two-pass sum of the same values to the bit,
        /// with ln c_k taken in the call or given.
        #[test]
        fn falloffs_and_blends_are_the_two_pass_sum_to_the_bit(
            terms in proptest::collection::vec(term(), 1..=MAX_TERMS),
            other in proptest::collection::vec(term(), 1..=MAX_TERMS),
            r in prop_oneof![4 => 0.0..5.0f64, 1 => Just(0.0), 1 => 1e3..1e6f64],
            phi in prop_oneof![2 => Just(None), 3 => (-10.0..10.0f64).prop_map(Some)],
        ) {
            let of = |t: &[(f64, f64)]| ExpSum {
                terms: t.iter().map(|&(c, d)| Term { c, d }).collect(),
            };
            let (e, f) = (of(&terms), of(&other));
            let ln = |e: &ExpSum| {
                log_sum_exp_twice(e.terms.iter().map(|t| t.c.ln() + t.d * r))
            };
            let same = |a: f64, b: f64| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
            prop_assert!(same(e.ln_eval(r), ln(&e)));
            prop_assert!(same(e.ln_eval_with(&e.ln_c(), r), ln(&e)));
            let one = Anisotropic { segments: vec![e.clone()] };
            let want = log_sum_exp_twice([-ln_exact_at_one(1.0) + ln(&e)].into_iter());
            prop_assert!(same(one.ln_eval(r, phi), want));
            let two = Anisotropic { segments: vec![e.clone(), f.clone()] };
            let want = match phi {
                Some(p) => {
                    let [(l0, w0), (l1, w1)] = aniso::hat_weights(p, 2);
                    let seg = |l: usize| ln(if l == 0 { &e } else { &f });
                    log_sum_exp_twice(
                        [ln_exact_at_one(w0) + seg(l0), ln_exact_at_one(w1) + seg(l1)].into_iter(),
                    )
                }
                None => log_sum_exp_twice(
                    [-ln_exact_at_one(2.0) + ln(&e), -ln_exact_at_one(2.0) + ln(&f)].into_iter(),
                ),
            };
            prop_assert!(same(two.ln_eval(r, phi), want));
        }
    }

    #[test]
    fn the_skipped_calls_are_exact() {
        for x in [0.0f64, -0.0] {
            assert_eq!(exp_exact_at_zero(x).to_bits(), x.exp().to_bits());
        }
        assert_eq!(ln_exact_at_one(1.0).to_bits(), 1.0f64.ln().to_bits());
        for x in [
            1e-300,
            0.5,
            2.0,
            1.0 + f64::EPSILON,
            1.0 - f64::EPSILON / 2.0,
        ] {
            assert_eq!(ln_exact_at_one(x).to_bits(), x.ln().to_bits());
            assert_eq!(
                exp_exact_at_zero(x - 1.0).to_bits(),
                (x - 1.0).exp().to_bits()
            );
        }
    }
}
