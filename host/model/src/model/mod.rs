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
pub use colour::ColourModel;
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
pub(crate) fn log_sum_exp(values: impl Iterator<Item = f64> + Clone) -> f64 {
    let m = values.clone().fold(f64::NEG_INFINITY, f64::max);
    if m == f64::NEG_INFINITY || m.is_nan() {
        return m;
    }
    if m == f64::INFINITY {
        return m;
    }
    m + values.map(|v| (v - m).exp()).sum::<f64>().ln()
}
