//! Where a fitted model is claimed: the distances `[r_min, r_max]` its samples covered (the
//! `r_min`/`r_max` of the model file). The one rule every user of a model applies — the fit's
//! interpolation of failed vertices, evaluation against frames, and the renderer:
//!
//! - **below r_min** ln R_d continues linearly with its slope at r_min, never rising (an
//!   exponential through the nearest sample): terms steeper than the samples resolve are not
//!   determined by them and would explode towards r = 0;
//! - **from r_min on, above r_max included**, the model itself: every term decays (d_k < 0), so
//!   its tail beyond the samples falls and stays finite;
//! - **an unknown range** (`r_max <= r_min` or `r_min <= 0`: ground truth, files written before
//!   the range existed) claims the model everywhere.
use serde::{Deserialize, Serialize};

use super::{ColourModel, hat_weights};

/// The sampled distance range of a fit (mm, like every distance of the model).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Support {
    /// Smallest sampled distance.
    pub r_min: f64,
    /// Largest sampled distance.
    pub r_max: f64,
}

impl Support {
    /// No known range: the model is claimed everywhere.
    pub const UNKNOWN: Support = Support {
        r_min: 0.0,
        r_max: 0.0,
    };

    /// The range `[r_min, r_max]`.
    pub fn new(r_min: f64, r_max: f64) -> Support {
        Support { r_min, r_max }
    }

    /// Whether the range is known (`r_max > r_min > 0`).
    pub fn is_known(&self) -> bool {
        self.r_max > self.r_min && self.r_min > 0.0
    }

    /// The distance at which the model itself is evaluated for a prediction at `r`: r_min below a
    /// known range, `r` everywhere else.
    pub fn anchor(&self, r: f64) -> f64 {
        if self.is_known() && r < self.r_min {
            self.r_min
        } else {
            r
        }
    }

    /// ln R_d at `r` from the model's ln R_d and its slope d ln R_d / dr at [`Support::anchor`]`(r)`.
    pub fn extend(&self, r: f64, ln_at_anchor: f64, slope_at_anchor: f64) -> f64 {
        let a = self.anchor(r);
        if a == r {
            ln_at_anchor
        } else {
            let (ln_c, g) = self.below(ln_at_anchor, slope_at_anchor);
            ln_c + g * r
        }
    }

    /// The fall-off below r_min as one exponential term `(ln c, g)`, R_d(r) = c·e^{g·r}, from the
    /// model's ln R_d and slope at r_min (for closed forms such as the renderer's disk integral).
    pub fn below(&self, ln_at_r_min: f64, slope_at_r_min: f64) -> (f64, f64) {
        let g = slope_at_r_min.min(0.0);
        (ln_at_r_min - g * self.r_min, g)
    }

    /// How much the model is trusted at `r` when several models are blended: 1 inside a known
    /// range (and for an unknown one), decaying as exp(−(r_min − r) / (0.1·r_min)) below it.
    pub fn weight(&self, r: f64) -> f64 {
        if !self.is_known() || r >= self.r_min {
            1.0
        } else {
            (-(self.r_min - r) / (0.1 * self.r_min)).exp()
        }
    }
}

/// ln R_d per channel of `model` at distance `r` and direction φ (Eq. 3/5/9) under the support
/// rule of this module.
pub fn ln_eval_supported(
    model: &ColourModel,
    support: Support,
    r: f64,
    phi: Option<f64>,
) -> [f64; 3] {
    let a = support.anchor(r);
    let ln = model.ln_eval(a, phi);
    if a == r {
        return ln;
    }
    let slope = ln_slope(model, a, phi);
    [0, 1, 2].map(|c| support.extend(r, ln[c], slope[c]))
}

/// d ln R_d / dr per channel (Eq. 3: the hat-weighted blend of the segments' slopes, each
/// weighted by its share of R_d): the slope the extension below r_min continues with.
pub fn ln_slope(model: &ColourModel, r: f64, phi: Option<f64>) -> [f64; 3] {
    let aniso = |a: &super::Anisotropic| -> f64 {
        let m = a.segments.len();
        let weights: Vec<(usize, f64)> = match phi.filter(|p| p.is_finite()) {
            Some(p) if m > 1 => hat_weights(p, m).to_vec(),
            _ => (0..m).map(|l| (l, 1.0 / m as f64)).collect(),
        };
        let total = a.ln_eval(r, phi);
        weights
            .iter()
            .filter(|(_, w)| *w > 0.0)
            .map(|&(l, w)| {
                let s = &a.segments[l];
                (w.ln() + s.ln_eval(r) - total).exp() * s.ln_slope(r)
            })
            .sum()
    };
    match model {
        ColourModel::PerChannel { channels } => [0, 1, 2].map(|c| aniso(&channels[c])),
        // The channel scales do not change the slope.
        ColourModel::Shared { falloff, .. } => [aniso(falloff); 3],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Anisotropic, ExpSum, Term};

    fn shared(segments: Vec<ExpSum>) -> ColourModel {
        ColourModel::Shared {
            falloff: Anisotropic { segments },
            s_g: 0.5,
            s_b: 0.25,
        }
    }

    fn two_terms(c: f64) -> ExpSum {
        ExpSum::new(vec![Term { c, d: -0.5 }, Term { c: 10.0, d: -4.0 }]).unwrap()
    }

    #[test]
    fn inside_and_above_the_range_the_model_itself() {
        let m = shared(vec![two_terms(1.0)]);
        let s = Support::new(1.0, 5.0);
        for r in [1.0, 2.5, 5.0, 50.0] {
            assert_eq!(ln_eval_supported(&m, s, r, None), m.ln_eval(r, None));
        }
        // An unknown range claims the model everywhere, below r_min too.
        assert_eq!(
            ln_eval_supported(&m, Support::UNKNOWN, 0.1, None),
            m.ln_eval(0.1, None)
        );
        assert_eq!(Support::new(2.0, 2.0).anchor(0.5), 0.5);
    }

    #[test]
    fn below_r_min_ln_rd_continues_with_its_slope_at_r_min() {
        let phi = Some(0.3);
        let m = shared(vec![two_terms(1.0), two_terms(3.0), two_terms(0.2)]);
        let s = Support::new(1.0, 5.0);
        let h = 1e-6;
        let at = m.ln_eval(1.0, phi);
        let fd = m.ln_eval(1.0 + h, phi);
        for r in [0.0, 0.5, 0.99] {
            let got = ln_eval_supported(&m, s, r, phi);
            for c in 0..3 {
                let slope = (fd[c] - at[c]) / h;
                let want = at[c] + slope * (r - 1.0);
                assert!((got[c] - want).abs() < 1e-5, "{r} {c}: {got:?} vs {want}");
                // Far steeper than the model's own continuation would be at r = 0.
                assert!(got[c] < m.ln_eval(r, phi)[c]);
            }
        }
    }

    #[test]
    fn the_continuation_never_rises_and_trust_decays_below_r_min() {
        let s = Support::new(2.0, 4.0);
        assert_eq!(s.extend(1.0, -1.0, 3.0), -1.0);
        assert_eq!(s.extend(1.0, -1.0, -2.0), 1.0);
        assert_eq!(s.weight(3.0), 1.0);
        assert!((s.weight(1.8) - (-1.0f64).exp()).abs() < 1e-12);
        assert_eq!(Support::UNKNOWN.weight(0.01), 1.0);
    }
}
