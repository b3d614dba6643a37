//! Eq. 2 / Eq. 6: the modulation texture alpha(x_o), the average multiplicative correction
//! s(x_i, x_o) / R_d(x_i → x_o) over the samples in a medium intensity window.

use serde::{Deserialize, Serialize};

/// The window X = {x_o | t1 > s(x_i, x_o) > t2} of Eq. 6: samples dominated by multiple
/// scattering, bright enough that camera noise is small, not saturated.
///
/// Section 4.2: "using all samples X within a medium intensity range [...] The scattering
/// behavior of these samples is dominated by multiple scattering and camera noise is still at a
/// minimum." t2 bounds the noise from below, so it is absolute (a multiple of the camera's noise
/// floor). t1 bounds from above the samples whose light is not yet multiple scattering: single
/// scattering and first-surface light near x_i, and the laser spot's own light spread in the
/// image. How bright those are scales with the light reaching x_i, which varies from light
/// position to light position (the laser's incidence on a curved object, the albedo at x_i), so
/// t1 is taken relative to each light position's brightest sample per channel:
/// t1(x_i) = min(`t1`, `t1_share` · max_o s(x_i, x_o)) ([`IntensityWindow::for_light`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IntensityWindow {
    /// Lower threshold t2 (exclusive), absolute radiance.
    pub t2: f64,
    /// Upper threshold t1 (exclusive), absolute radiance (`f64::INFINITY`: none).
    pub t1: f64,
    /// Upper threshold t1 relative to the light position's brightest sample in the channel
    /// (`f64::INFINITY`: none); see [`IntensityWindow::for_light`].
    #[serde(default = "no_share")]
    pub t1_share: f64,
}

fn no_share() -> f64 {
    f64::INFINITY
}

impl IntensityWindow {
    /// Whether sample value s lies strictly inside (t2, t1).
    pub fn contains(&self, s: f64) -> bool {
        s > self.t2 && s < self.t1
    }

    /// The absolute window of one light position whose brightest sample (in the channel) is
    /// `s_max`: t1 lowered to `t1_share · s_max`. A non-finite or non-positive `s_max` leaves
    /// the window as it is.
    pub fn for_light(&self, s_max: f64) -> IntensityWindow {
        let rel = self.t1_share * s_max;
        IntensityWindow {
            t1: if s_max.is_finite() && s_max > 0.0 && rel.is_finite() {
                self.t1.min(rel)
            } else {
                self.t1
            },
            ..*self
        }
    }
}

/// Pseudo-samples at ln alpha = 0 added to every texel's Eq. 6 average ([`AlphaAccumulator`])
/// when the data cannot say how many it needs ([`empirical_prior`] finds no texel seen twice):
/// a texel seen in few samples keeps alpha near 1 instead of absorbing their noise.
///
/// With per-sample log noise sigma, the mean of ln(s / R_d) over k samples has variance
/// sigma^2 / k; weighting it against `p` pseudo-samples at 0 is the posterior mean under a
/// N(0, sigma^2 / p) prior on ln alpha. The fit's default estimates p from the data instead
/// (the empirical-Bayes shrinkage, chosen by cross-validation on training frames:
/// docs/validation.md); this constant is only its fallback where no texel was seen twice.
pub const ALPHA_PRIOR: f64 = 1.0;

/// Largest prior [`empirical_prior`] returns: the texture's spread is not above the noise, so
/// alpha stays 1 to within 1e-6 of a sample's ln ratio.
pub const ALPHA_PRIOR_MAX: f64 = 1e6;

/// The pseudo-count `p = sigma^2 / tau^2` of Eq. 6's shrinkage, estimated from the texels
/// themselves (empirical Bayes, the James–Stein idea): sigma^2 is the spread of ln(s / R_d)
/// *within* a texel (noise and model error, pooled over texels seen at least twice), tau^2 the
/// spread of the true ln alpha *between* texels, the variance of the texel means less the part
/// sigma^2 / k their noise explains. The posterior mean sum / (k + p) then shrinks a texel by
/// k / (k + p): hardly at all where the texture stands well above the noise (the built-in
/// sphere: a fixed prior of 1 pseudo-sample flattened its texture to 0.58 of the truth), much
/// where it does not (sample-torus, whose Monte Carlo noise is 0.13 per sample).
/// [`ALPHA_PRIOR`] when no texel was seen twice; [`ALPHA_PRIOR_MAX`] when the texel means spread
/// no more than their noise does.
pub fn empirical_prior<'a>(texels: impl IntoIterator<Item = &'a AlphaAccumulator>) -> f64 {
    let (mut within, mut dof) = (0.0, 0.0);
    let (mut n, mut mean, mut m2, mut inv_k) = (0.0, 0.0, 0.0, 0.0);
    for t in texels {
        if t.count == 0 {
            continue;
        }
        let k = t.count as f64;
        let m = t.sum_ln / k;
        if !m.is_finite() {
            continue;
        }
        if t.count >= 2 {
            within += (t.sum_sq_ln - t.sum_ln * m).max(0.0);
            dof += k - 1.0;
        }
        // Welford over the texel means.
        n += 1.0;
        let delta = m - mean;
        mean += delta / n;
        m2 += delta * (m - mean);
        inv_k += 1.0 / k;
    }
    if dof < 1.0 || n < 2.0 {
        return ALPHA_PRIOR;
    }
    let sigma2 = within / dof;
    let tau2 = m2 / (n - 1.0) - sigma2 * inv_k / n;
    if !(sigma2.is_finite() && tau2.is_finite()) {
        return ALPHA_PRIOR;
    }
    if tau2 <= sigma2 / ALPHA_PRIOR_MAX {
        return ALPHA_PRIOR_MAX;
    }
    (sigma2 / tau2).clamp(0.0, ALPHA_PRIOR_MAX)
}

/// Streaming Eq. 6 for one texel x_o: feed (s, R_d) pairs from every x_i that sees x_o.
///
/// The average is taken in log space (a geometric mean), the estimate consistent with the log
/// objective of the fit (Eq. 4): for a fixed R_d it is the alpha minimising
/// sum (ln(alpha R_d) - ln s)^2, so a round of "fit R_d, then Eq. 6" never increases that
/// objective. The arithmetic mean of Eq. 6 taken literally is biased upwards by about
/// sigma^2 / 2 in ln alpha for log noise sigma, and the bias compounds over alternating rounds.
/// The estimate is shrunk towards 1 by [`ALPHA_PRIOR`] pseudo-samples.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct AlphaAccumulator {
    /// sum of ln(s / R_d) over accepted samples.
    pub sum_ln: f64,
    /// sum of ln(s / R_d)^2 over accepted samples (the texel's own spread, [`empirical_prior`]).
    #[serde(default)]
    pub sum_sq_ln: f64,
    /// |X|, the number of accepted samples.
    pub count: u64,
}

impl AlphaAccumulator {
    /// Adds one sample s(x_i, x_o) with model value R_d(x_i → x_o); returns whether it was used
    /// (inside the window, both finite, R_d > 0).
    pub fn add(&mut self, s: f64, r_d: f64, window: &IntensityWindow) -> bool {
        if r_d > 0.0 && r_d.is_finite() {
            self.add_ln(s, r_d.ln(), window)
        } else {
            false
        }
    }

    /// [`AlphaAccumulator::add`] with ln R_d (finite where R_d underflows).
    pub fn add_ln(&mut self, s: f64, ln_r_d: f64, window: &IntensityWindow) -> bool {
        match Self::ln_ratio(s, ln_r_d, window) {
            Some(x) => {
                self.add_ratio(x);
                true
            }
            None => false,
        }
    }

    /// The term one sample adds, ln(s / R_d), or `None` where [`AlphaAccumulator::add_ln`]
    /// would not use it: split out so that many samples' terms can be taken in parallel and
    /// only the sums ([`AlphaAccumulator::add_ratio`], in a fixed order) stay sequential.
    pub fn ln_ratio(s: f64, ln_r_d: f64, window: &IntensityWindow) -> Option<f64> {
        Self::ln_ratio_with(s, s.ln(), ln_r_d, window)
    }

    /// [`AlphaAccumulator::ln_ratio`] with `ln_s = s.ln()` given, for a caller that needs ln s
    /// itself too (the fit's objective): the same bits, one log fewer.
    pub fn ln_ratio_with(s: f64, ln_s: f64, ln_r_d: f64, window: &IntensityWindow) -> Option<f64> {
        let ln_ratio = ln_s - ln_r_d;
        (window.contains(s) && s > 0.0 && ln_ratio.is_finite()).then_some(ln_ratio)
    }

    /// Adds a term of [`AlphaAccumulator::ln_ratio`].
    pub fn add_ratio(&mut self, ln_ratio: f64) {
        self.sum_ln += ln_ratio;
        self.sum_sq_ln += ln_ratio * ln_ratio;
        self.count += 1;
    }

    /// Merges another accumulator (for parallel accumulation).
    pub fn merge(&mut self, other: &Self) {
        self.sum_ln += other.sum_ln;
        self.sum_sq_ln += other.sum_sq_ln;
        self.count += other.count;
    }

    /// ln alpha(x_o) (Eq. 6 in log space, shrunk by [`ALPHA_PRIOR`]), or `None` when no sample
    /// fell in the window.
    pub fn ln_alpha(&self) -> Option<f64> {
        self.ln_alpha_shrunk(ALPHA_PRIOR)
    }

    /// ln alpha(x_o) shrunk towards 0 by `prior` pseudo-samples (see [`empirical_prior`]), or
    /// `None` when no sample fell in the window.
    pub fn ln_alpha_shrunk(&self, prior: f64) -> Option<f64> {
        (self.count > 0).then(|| self.sum_ln / (self.count as f64 + prior.max(0.0)))
    }

    /// alpha(x_o) (Eq. 6), or `None` when no sample fell in the window.
    pub fn alpha(&self) -> Option<f64> {
        self.ln_alpha().map(f64::exp)
    }
}

/// Eq. 6 over (s, R_d) pairs in one go.
pub fn alpha(pairs: impl IntoIterator<Item = (f64, f64)>, window: &IntensityWindow) -> Option<f64> {
    let mut acc = AlphaAccumulator::default();
    for (s, r_d) in pairs {
        acc.add(s, r_d, window);
    }
    acc.alpha()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometric_mean_of_ratios_inside_window_only_shrunk_to_one() {
        let w = IntensityWindow {
            t2: 0.1,
            t1: 10.0,
            t1_share: f64::INFINITY,
        };
        let a = alpha(
            [
                (1.0, 0.5),
                (4.0, 0.5),
                (20.0, 1.0),
                (0.05, 1.0),
                (1.0, 0.0),
                (f64::NAN, 1.0),
            ],
            &w,
        )
        .unwrap();
        // ln 2 + ln 8 = 4 ln 2 over 2 samples + ALPHA_PRIOR pseudo-samples at 0.
        let expect = (4.0 * 2f64.ln() / (2.0 + ALPHA_PRIOR)).exp();
        assert!((a - expect).abs() < 1e-12, "{a} {expect}");
        assert_eq!(alpha([(20.0, 1.0)], &w), None);
    }

    /// Texels with true ln alpha ~ N(0, tau^2) seen in k samples of noise sigma each: the
    /// estimated prior is sigma^2 / tau^2 within sampling error, and the extremes hold.
    #[test]
    fn empirical_prior_recovers_noise_over_texture_variance() {
        let w = IntensityWindow {
            t2: 0.0,
            t1: f64::INFINITY,
            t1_share: f64::INFINITY,
        };
        // A small deterministic generator (no rand dependency in this crate): xorshift + Box-Muller.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut normal = move || {
            let (u, v) = (uniform().max(1e-300), uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        };
        for (tau, sigma, k, want) in [(0.05, 0.02, 4, 0.16), (0.05, 0.2, 2, 16.0)] {
            let texels: Vec<AlphaAccumulator> = (0..20_000)
                .map(|_| {
                    let ln_a = tau * normal();
                    let mut acc = AlphaAccumulator::default();
                    for _ in 0..k {
                        assert!(acc.add_ln(1.0, -(ln_a + sigma * normal()), &w));
                    }
                    acc
                })
                .collect();
            let p = empirical_prior(&texels);
            assert!(
                (p / want - 1.0).abs() < 0.15,
                "tau {tau} sigma {sigma}: {p} vs {want}"
            );
        }
        // No texture at all: alpha stays 1.
        let flat: Vec<AlphaAccumulator> = (0..1000)
            .map(|i| {
                let mut acc = AlphaAccumulator::default();
                for j in 0..3 {
                    let e = if (i + j) % 2 == 0 { 0.1 } else { -0.1 };
                    acc.add_ln(1.0, e, &w);
                }
                acc
            })
            .collect();
        assert!(empirical_prior(&flat) > 1.0);
        // Nothing seen twice: the fixed prior.
        let mut once = AlphaAccumulator::default();
        once.add_ln(2.0, 0.0, &w);
        assert_eq!(empirical_prior([&once, &once]), ALPHA_PRIOR);
        assert_eq!(empirical_prior(std::iter::empty()), ALPHA_PRIOR);
    }

    /// Both sides of Eq. 6's window: t2 absolute, t1 the smaller of the absolute bound and the
    /// share of the light position's brightest sample.
    #[test]
    fn the_window_has_both_thresholds() {
        let w = IntensityWindow {
            t2: 0.01,
            t1: 5.0,
            t1_share: 0.1,
        };
        let bright = w.for_light(20.0);
        assert_eq!(bright.t1, 2.0);
        assert!(bright.contains(1.9) && !bright.contains(2.0) && !bright.contains(0.01));
        // A dim light position: the absolute bound is above its share, its share applies.
        assert_eq!(w.for_light(1.0).t1, 0.1 * 1.0);
        // A very bright one: the absolute bound applies.
        assert_eq!(w.for_light(1000.0).t1, 5.0);
        // No brightest sample: unchanged.
        assert_eq!(w.for_light(f64::NAN), w);
        assert_eq!(w.for_light(0.0), w);
        let off = IntensityWindow {
            t1_share: f64::INFINITY,
            ..w
        };
        assert_eq!(off.for_light(20.0).t1, 5.0);
        // Reports written before t1_share read with it off.
        let old: IntensityWindow = serde_json::from_str(r#"{"t2":0.5,"t1":2.0}"#).unwrap();
        assert_eq!(old.t1_share, f64::INFINITY);
    }

    #[test]
    fn many_samples_recover_a_constant_ratio_and_underflow_is_fine() {
        let w = IntensityWindow {
            t2: 0.0,
            t1: f64::INFINITY,
            t1_share: f64::INFINITY,
        };
        let mut acc = AlphaAccumulator::default();
        for _ in 0..100_000 {
            assert!(acc.add_ln(1e-3, (1e-3f64 / 1.5).ln(), &w));
        }
        assert!((acc.alpha().unwrap() - 1.5).abs() < 1e-4);
        let mut tiny = AlphaAccumulator::default();
        assert!(tiny.add_ln(1e-3, -2000.0, &w));
        assert!(tiny.ln_alpha().unwrap().is_finite());
    }
}
