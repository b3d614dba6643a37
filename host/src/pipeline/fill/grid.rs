//! The distance grid of stage `interpolate`: fitted curves ln R_d(r) encoded on one grid of
//! distances so that neighbours' curves can be averaged, and an averaged encoding refitted as a
//! model ([`CurveGrid::decode`]).
use crate::model::{Anisotropic, ColourModel, ExpSum, Support};
use crate::modelfile::{ColourMode, ModelShape};

use super::super::findings::TermDropped;
use super::super::fit::{Fitter, fit_common_order};

/// The distance grid on which fitted curves ln R_d(r) are interpolated between vertices.
///
/// Spaced geometrically from the smallest sampled distance (see [`spread`]): a near term
/// c·e^{d·r} with |d| of several per mm changes ln R_d by |d|·Δr between grid points, so an even
/// grid over the whole object's range (0.6 mm steps over 20 mm at 32 points) cut it to one or
/// two points and the refit lost it; geometric steps are 0.04 mm at 0.5 mm and grow with r as
/// the slower terms take over.
pub(super) struct CurveGrid {
    pub(super) r: Vec<f64>,
}

/// Points of [`CurveGrid`].
pub(super) const GRID_POINTS: usize = 48;
/// Points of the refit of an interpolated curve, spread over its sampled range like the grid.
const REFIT_POINTS: usize = 32;

/// `points` distances from `lo` to `hi` whose steps grow geometrically away from `lo`:
/// r_k = lo + h·((1 + (hi − lo)/h)^{k/(points−1)} − 1) with h = max(lo, (hi − lo)/1000), the
/// geometric series lo·(hi/lo)^{k/(points−1)} when lo > 0 (equal steps in ln r, the scale on
/// which the terms of Eq. 1 separate), kept finite when lo = 0.
pub(super) fn spread(lo: f64, hi: f64, points: usize) -> Vec<f64> {
    let h = lo.max((hi - lo) / 1000.0).max(1e-9);
    let q = 1.0 + (hi - lo) / h;
    let last = (points.max(2) - 1) as f64;
    (0..points.max(2))
        .map(|k| {
            if k as f64 == last {
                hi
            } else {
                lo + h * (q.powf(k as f64 / last) - 1.0)
            }
        })
        .collect()
}

impl CurveGrid {
    /// Spans every fitted vertex's sampled range.
    pub(super) fn of(ranges: impl Iterator<Item = [f64; 2]>) -> CurveGrid {
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for [a, b] in ranges {
            lo = lo.min(a);
            hi = hi.max(b);
        }
        if !(lo.is_finite() && lo >= 0.0 && hi > lo) {
            (lo, hi) = (0.5, 10.0);
        }
        CurveGrid {
            r: spread(lo, hi, GRID_POINTS),
        }
    }

    /// ln R_d of `f` at `r` under the model's support rule ([`crate::model::support`]).
    fn ln_supported(f: &ExpSum, support: Support, r: f64) -> f64 {
        let a = support.anchor(r);
        support.extend(r, f.ln_eval(a), f.ln_slope(a))
    }

    /// The fall-off curves of a model: per channel (per-channel models) and segment, on the
    /// run's `segments` (a light position that chose fewer is widened exactly,
    /// [`crate::order::widen`]), so every vertex's encoding has one length.
    fn curves(m: &ColourModel, segments: usize) -> Vec<ExpSum> {
        use crate::order::widen;
        match m {
            ColourModel::Shared { falloff, .. } => widen(falloff, segments),
            ColourModel::PerChannel { channels } => {
                channels.iter().flat_map(|c| widen(c, segments)).collect()
            }
        }
    }

    /// `[ln r_min, ln r_max, (ln s_g, ln s_b), ln R_d on the grid for every curve]`.
    pub(super) fn encode(&self, m: &ColourModel, range: [f64; 2], segments: usize) -> Vec<f64> {
        let mut out = vec![range[0].max(1e-6).ln(), range[1].max(1e-6).ln()];
        if let ColourModel::Shared { s_g, s_b, .. } = m {
            out.push(s_g.ln());
            out.push(s_b.ln());
        }
        for f in Self::curves(m, segments) {
            let support = Support::new(range[0], range[1]);
            out.extend(self.r.iter().map(|&r| Self::ln_supported(&f, support, r)));
        }
        out
    }

    /// ln R_d of curve `k` of an encoding at `r` (piecewise linear between grid points; the end
    /// segments continue linearly).
    fn ln_at(&self, enc: &[f64], head: usize, k: usize, r: f64) -> f64 {
        let n = self.r.len();
        let g = &enc[head + k * n..head + (k + 1) * n];
        let i = self.r.partition_point(|&x| x <= r).clamp(1, n - 1) - 1;
        let t = (r - self.r[i]) / (self.r[i + 1] - self.r[i]);
        g[i] + (g[i + 1] - g[i]) * t
    }

    /// Refits an interpolated encoding: the model (term-aligned by construction, order at most
    /// `n`) and its range. `None` if a refit fails.
    pub(super) fn decode(
        &self,
        enc: &[f64],
        shape: &ModelShape,
        n: usize,
        fitter: &dyn Fitter,
        dropped: &mut Vec<TermDropped>,
    ) -> Option<(ColourModel, [f64; 2])> {
        let range = [enc[0].exp(), enc[1].exp()];
        if range[1].partial_cmp(&range[0]) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let head = if shape.colour == ColourMode::Shared {
            4
        } else {
            2
        };
        let curves = match shape.colour {
            ColourMode::Shared => shape.segments,
            ColourMode::PerChannel => 3 * shape.segments,
        };
        if enc.len() != head + curves * self.r.len() {
            return None;
        }
        let rs = spread(range[0], range[1], REFIT_POINTS);
        let sets: Vec<(Vec<f64>, Vec<f64>)> = (0..curves)
            .map(|k| {
                let s = rs
                    .iter()
                    .map(|&r| self.ln_at(enc, head, k, r).exp())
                    .collect();
                (rs.clone(), s)
            })
            .collect();
        // Lower the order when a refit fails (not converged on a smooth curve, e.g.).
        let fits = (1..=n.max(1))
            .rev()
            .find_map(|n| fit_common_order(fitter, &sets, Some(n), dropped).ok())?;
        let m = shape.segments;
        let model = match shape.colour {
            ColourMode::Shared => ColourModel::Shared {
                falloff: Anisotropic { segments: fits },
                s_g: enc[2].exp(),
                s_b: enc[3].exp(),
            },
            ColourMode::PerChannel => {
                let mut it = fits.into_iter();
                let mut ch = || Anisotropic {
                    segments: it.by_ref().take(m).collect(),
                };
                ColourModel::PerChannel {
                    channels: [ch(), ch(), ch()],
                }
            }
        };
        model.validate().ok()?;
        Some((model, range))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::FitOptions;
    use crate::model::Term;

    /// A steep near term (decaying e-fold every 0.17 mm, the larger part of R_d below 1 mm)
    /// survives the failed-vertex path: encoded on the grid of an object whose sampled
    /// distances reach 20 mm, decoded and refitted, ln R_d is kept within 2 % over the vertex's
    /// range, near x_i included. On an even 32-point grid (0.63 mm steps) the near term had two
    /// grid points and two refit points, and the refit dropped it as unresolved.
    #[test]
    fn a_steep_near_term_survives_the_refit() {
        let truth = ExpSum::new(vec![
            Term { c: 20.0, d: -6.0 },
            Term { c: 1.0, d: -1.0 },
            Term { c: 0.05, d: -0.2 },
        ])
        .unwrap();
        let model = ColourModel::Shared {
            falloff: Anisotropic {
                segments: vec![truth.clone()],
            },
            s_g: 0.5,
            s_b: 0.25,
        };
        let range = [0.5, 15.0];
        let grid = CurveGrid::of([range, [0.6, 20.0]].into_iter());
        let shape = ModelShape {
            terms: 3,
            segments: 1,
            colour: ColourMode::Shared,
        };
        let enc = grid.encode(&model, range, 1);
        let mut dropped = Vec::new();
        let (refit, got_range) = grid
            .decode(&enc, &shape, 3, &FitOptions::default(), &mut dropped)
            .unwrap();
        assert!((got_range[0] - 0.5).abs() < 1e-9 && (got_range[1] - 15.0).abs() < 1e-9);
        assert!(dropped.is_empty(), "{dropped:?}");
        for r in [0.5, 0.6, 0.75, 0.9, 1.1, 1.5, 2.0, 5.0, 10.0, 15.0] {
            let want = truth.ln_eval(r);
            let got = refit.ln_eval(r, None);
            assert!((got[0] - want).abs() < 0.02, "r {r}: {} vs {want}", got[0]);
            assert!((got[2] - want - 0.25f64.ln()).abs() < 0.02);
        }
    }

    #[test]
    fn the_grid_is_dense_near_the_smallest_distance_and_spans_the_range() {
        let g = spread(0.5, 20.0, GRID_POINTS);
        assert_eq!(g.len(), GRID_POINTS);
        assert_eq!((g[0], g[GRID_POINTS - 1]), (0.5, 20.0));
        assert!(g.windows(2).all(|w| w[1] > w[0]));
        assert!(g[1] - g[0] < 0.05);
        // Equal steps in ln r.
        let q = g[1] / g[0];
        assert!(g.windows(2).all(|w| (w[1] / w[0] - q).abs() < 1e-9));
        // From zero: finite, increasing.
        let z = spread(0.0, 10.0, 8);
        assert!(z[0] == 0.0 && z.windows(2).all(|w| w[1] > w[0]));
    }
}
