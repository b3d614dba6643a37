//! "Model only what the scene requires", per light position: the number of terms n (Eq. 1) and
//! of direction segments m (Eq. 3) of one vertex's model, chosen from fits at several (n, m).
//!
//! The rule is the corrected Akaike information criterion (AICc, Hurvich and Tsai 1989) on the
//! log residuals of Eq. 4: AICc = N·ln(RSS/N) + 2k + 2k(k+1)/(N−k−1) for N samples,
//! RSS = Σ (ln R_d − ln s)² and k parameters; of the candidates whose AICc is within
//! [`OrderRule::slack`] of the smallest, the one with the fewest parameters ("smallest within a
//! tolerance of the best"). Why AICc:
//!
//! - it estimates the error on data the fit did not see (Kullback–Leibler prediction error),
//!   which is what a model of an object is for; its small-sample term grows without bound as k
//!   approaches N, so a light position seen in few samples gets a smaller model (six parameters
//!   otherwise win by nearly interpolating eight samples);
//! - cross-validated against BIC (penalty k·ln N, which identifies the "true" order rather than
//!   the best predictor) on training frames only (docs/validation.md): BIC predicted worse on the
//!   textured simulated slab by 0.0083 ± 0.0015 (mean log E, standard error clustered by fold)
//!   and tied within noise on sample-slab, sample-torus, sample-pebble and a simulated torus;
//! - it needs one fit per candidate and nothing else (a cross-validated choice inside a vertex's
//!   samples needs one fit per fold and candidate, and the samples of one x_i are correlated
//!   along the surface, so random folds overstate what generalises);
//! - the log residual is the objective every fit minimises, so RSS is what the fits report.
//!
//! The default slack is 2 (Burnham and Anderson: models within ΔAIC 2 of the best have
//! substantial support), so the smaller of two nearly equal models wins. RSS/N is floored at [`RSS_FLOOR`] so noise-free data (RSS at rounding level) do not
//! make rounding differences look like evidence.
//!
//! [`widen`] evaluates a vertex with fewer segments on a larger segment grid, exactly, so readers
//! that need one m for all vertices (the renderer's layout, the interpolation of neighbours'
//! curves) agree with the vertex's own model.
//!
//! Pure: no files, no clocks, no threads.
use serde::{Deserialize, Serialize};

use crate::model::{Anisotropic, ExpSum, Term, hat_weights};

/// Floor of the mean squared log residual RSS/N (a relative error of 1e-4): below it, smaller
/// residuals are rounding, not evidence for a larger model.
pub const RSS_FLOOR: f64 = 1e-8;

/// How a vertex's order is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OrderRule {
    /// Candidates whose AICc is within this of the best one count as equally good; the one with
    /// the fewest parameters among them is chosen. 2 (the default): substantial support on the
    /// Burnham–Anderson scale; 0 takes the best AICc.
    pub slack: f64,
}

impl Default for OrderRule {
    fn default() -> Self {
        Self { slack: 2.0 }
    }
}

/// One fitted candidate of a vertex.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// Terms n per segment of the fit (as fitted: unsupported terms may have been dropped).
    pub terms: usize,
    /// Direction segments m.
    pub segments: usize,
    /// Parameters k the model stores.
    pub params: usize,
    /// Samples N the fit was measured on.
    pub samples: usize,
    /// Σ (ln R_d − ln s)² over those samples.
    pub rss: f64,
}

impl Candidate {
    /// AICc = N·ln(max(RSS/N, [`RSS_FLOOR`])) + 2k + 2k(k+1)/(N−k−1); `None` if it is not
    /// finite or N ≤ k + 1 (the fit then interpolates, it does not describe).
    pub fn aicc(&self) -> Option<f64> {
        if self.samples <= self.params + 1 || !(self.rss.is_finite() && self.rss >= 0.0) {
            return None;
        }
        let n = self.samples as f64;
        let k = self.params as f64;
        let b =
            n * (self.rss / n).max(RSS_FLOOR).ln() + 2.0 * k + 2.0 * k * (k + 1.0) / (n - k - 1.0);
        b.is_finite().then_some(b)
    }
}

/// The order chosen for one vertex.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Chosen {
    /// Index of the chosen candidate in the slice given to [`choose`].
    pub index: usize,
    /// Its terms n.
    pub terms: usize,
    /// Its segments m.
    pub segments: usize,
}

/// The candidate with the fewest parameters among those whose AICc is within `rule.slack` of the
/// smallest (ties: fewer segments, then fewer terms, then the earlier one). `None` when no
/// candidate has a AICc (every fit failed, or too few samples for any).
pub fn choose(candidates: &[Candidate], rule: OrderRule) -> Option<Chosen> {
    let slack = if rule.slack.is_finite() {
        rule.slack.max(0.0)
    } else {
        0.0
    };
    let scores: Vec<Option<f64>> = candidates.iter().map(Candidate::aicc).collect();
    let best = scores
        .iter()
        .flatten()
        .copied()
        .fold(f64::INFINITY, f64::min);
    if !best.is_finite() {
        return None;
    }
    let (index, c) = candidates
        .iter()
        .enumerate()
        .filter(|(i, _)| scores[*i].is_some_and(|b| b <= best + slack))
        .min_by_key(|(i, c)| (c.params, c.segments, c.terms, *i))?;
    Some(Chosen {
        index,
        terms: c.terms,
        segments: c.segments,
    })
}

/// The segment counts to try for at most `max` segments: the powers of two below `max` that
/// divide it, then `max` (so [`widen`] from any of them to `max` is exact).
pub fn segment_ladder(max: usize) -> Vec<usize> {
    let max = max.max(1);
    let mut out: Vec<usize> = (0..usize::BITS)
        .map(|p| 1usize << p)
        .take_while(|&m| m < max)
        .filter(|m| max.is_multiple_of(*m))
        .collect();
    out.push(max);
    out
}

/// The fall-off of `a` (Eq. 3, m_v = `a.m()` segments) on a grid of `m` segments: curve j is
/// R_d at the direction φ_j = 2πj/m, the hat-weighted blend of the two neighbouring segments of
/// `a` (a sum of up to 2n exponentials). When m_v divides m, the hat interpolation of these m
/// curves (Eq. 3 with m segments) equals `a` at every direction, since a piecewise-linear
/// function of φ is reproduced exactly on a finer grid that contains its nodes; with m = m_v
/// the curves are `a`'s own segments. The curves are for evaluation (`ln_eval`, `ln_slope`,
/// `eval`): they may hold more than [`crate::model::MAX_TERMS`] terms and are not validated.
pub fn widen(a: &Anisotropic, m: usize) -> Vec<ExpSum> {
    let mv = a.m();
    if mv == m || mv == 0 {
        return a.segments.clone();
    }
    (0..m)
        .map(|j| {
            let phi = std::f64::consts::TAU * j as f64 / m as f64;
            let mut terms: Vec<Term> = Vec::new();
            let w = if mv == 1 {
                [(0, 1.0), (0, 0.0)]
            } else {
                hat_weights(phi, mv)
            };
            for (l, w) in w {
                if w > 1e-12 {
                    terms.extend(
                        a.segments[l]
                            .terms
                            .iter()
                            .map(|t| Term { c: t.c * w, d: t.d }),
                    );
                }
            }
            ExpSum { terms }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::{FitOptions, Terms, fit_expsum};

    /// Deterministic noise: a fixed LCG's uniform values, scaled to `sigma` (RMS).
    fn noise(k: usize, sigma: f64) -> Vec<f64> {
        let mut x: u64 = 0x2545_f491_4f6c_dd1d;
        (0..k)
            .map(|_| {
                x = x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let u = (x >> 11) as f64 / (1u64 << 53) as f64;
                (u - 0.5) * sigma * 12f64.sqrt()
            })
            .collect()
    }

    /// Samples of `truth` at `k` distances over 0.5..12 mm with log-normal noise `sigma`.
    fn samples(truth: &ExpSum, k: usize, sigma: f64) -> (Vec<f64>, Vec<f64>) {
        let e = noise(k, sigma);
        let r: Vec<f64> = (0..k)
            .map(|i| 0.5 + 11.5 * i as f64 / (k - 1) as f64)
            .collect();
        let s = r
            .iter()
            .zip(&e)
            .map(|(&r, e)| (truth.ln_eval(r) + e).exp())
            .collect();
        (r, s)
    }

    /// Fits n = 1..=4 (isotropic) and chooses.
    fn chosen_terms(r: &[f64], s: &[f64]) -> usize {
        let cands: Vec<Candidate> = (1..=4)
            .filter_map(|n| {
                let o = FitOptions {
                    terms: Terms::Fixed(n),
                    ..FitOptions::default()
                };
                let f = fit_expsum(r, s, &o).ok()?;
                Some(Candidate {
                    terms: f.model.n(),
                    segments: 1,
                    params: 2 * f.model.n(),
                    samples: r.len(),
                    rss: f.log_e.powi(2) * r.len() as f64,
                })
            })
            .collect();
        choose(&cands, OrderRule::default()).unwrap().terms
    }

    fn three() -> ExpSum {
        ExpSum::new(vec![
            Term { c: 0.02, d: -0.35 },
            Term { c: 0.5, d: -1.2 },
            Term { c: 8.0, d: -4.0 },
        ])
        .unwrap()
    }

    #[test]
    fn data_from_one_term_pick_one() {
        let one = ExpSum::new(vec![Term { c: 1.0, d: -0.8 }]).unwrap();
        let (r, s) = samples(&one, 400, 0.05);
        assert_eq!(chosen_terms(&r, &s), 1);
    }

    #[test]
    fn data_from_three_terms_pick_three_when_samples_suffice() {
        let (r, s) = samples(&three(), 400, 0.02);
        assert_eq!(chosen_terms(&r, &s), 3);
    }

    #[test]
    fn few_samples_pick_fewer_terms() {
        // The same curve seen in 12 noisy samples does not determine three terms.
        // The curve that picks 3 from 400 samples: from a dozen or a few dozen noisy ones, fewer
        // (without the small-sample term, 8 to 16 samples pick 3: six parameters then nearly
        // interpolate them); from 100, three again.
        for (k, sigma) in [(8, 0.15), (12, 0.15), (16, 0.3), (40, 0.3)] {
            let (r, s) = samples(&three(), k, sigma);
            let n = chosen_terms(&r, &s);
            assert!(n < 3, "picked {n} terms from {k} samples");
        }
        let (r, s) = samples(&three(), 100, 0.3);
        assert_eq!(chosen_terms(&r, &s), 3);
    }

    #[test]
    fn ties_go_to_the_fewest_parameters_and_failures_are_skipped() {
        let c = |terms, segments, rss| Candidate {
            terms,
            segments,
            params: 2 + 2 * terms * segments,
            samples: 1000,
            rss,
        };
        // Equal fits: the smallest model.
        let cands = [c(1, 1, 10.0), c(2, 1, 10.0), c(1, 4, 10.0)];
        assert_eq!(choose(&cands, OrderRule::default()).unwrap().index, 0);
        // A much better larger model wins; a failed (NaN) candidate is skipped.
        let cands = [c(1, 1, 10.0), c(2, 1, f64::NAN), c(3, 1, 5.0)];
        let ch = choose(&cands, OrderRule::default()).unwrap();
        assert_eq!((ch.terms, ch.segments, ch.index), (3, 1, 2));
        // Too few samples for any candidate: no choice.
        let few = Candidate {
            samples: 3,
            ..c(1, 1, 1.0)
        };
        assert_eq!(choose(&[few], OrderRule::default()), None);
        assert_eq!(choose(&[], OrderRule::default()), None);
        // Within the slack: the smaller model, even though its AICc is a little worse.
        let n = 1000.0f64;
        // Two more parameters (+4) and a residual lower by a factor exp(-5/N): AICc lower by ~1.
        let rss2 = 10.0 * (-5.0 / n).exp();
        let cands = [c(1, 1, 10.0), c(2, 1, rss2)];
        assert_eq!(choose(&cands, OrderRule::default()).unwrap().terms, 1);
        assert_eq!(choose(&cands, OrderRule { slack: 0.0 }).unwrap().terms, 2);
    }

    #[test]
    fn the_segment_ladder_divides_the_maximum() {
        assert_eq!(segment_ladder(1), vec![1]);
        assert_eq!(segment_ladder(8), vec![1, 2, 4, 8]);
        assert_eq!(segment_ladder(6), vec![1, 2, 6]);
        assert_eq!(segment_ladder(0), vec![1]);
    }

    #[test]
    fn widening_reproduces_the_model_at_every_direction() {
        let seg = |c: f64, d: f64| ExpSum::new(vec![Term { c, d }, Term { c: 0.1, d: -0.3 }]);
        let a = Anisotropic {
            segments: vec![seg(1.0, -1.0).unwrap(), seg(3.0, -2.0).unwrap()],
        };
        let iso = Anisotropic::isotropic(seg(2.0, -1.5).unwrap());
        for (model, m) in [(&a, 8), (&a, 2), (&iso, 4)] {
            let wide = Anisotropic {
                segments: widen(model, m),
            };
            assert_eq!(wide.m(), m);
            for i in 0..50 {
                let phi = i as f64 * 0.13 - 1.0;
                for r in [0.2, 1.0, 5.0] {
                    let (x, y) = (model.ln_eval(r, Some(phi)), wide.ln_eval(r, Some(phi)));
                    assert!((x - y).abs() < 1e-12, "phi {phi} r {r}: {x} vs {y}");
                }
            }
            let (x, y) = (model.ln_eval(1.0, None), wide.ln_eval(1.0, None));
            assert!((x - y).abs() < 1e-12);
        }
    }
}
