//! Stage `interpolate` (section 5: "vertices for which no stable fit could be achieved were
//! filtered out and interpolated from neighboring vertices"): a model for every vertex without
//! an accepted fit of its own.
//!
//! Neighbouring fits are not term-aligned, so what is interpolated is each fitted vertex's curve
//! ln R_d(r) (per segment and, for per-channel models, per channel) on a common distance grid,
//! with ln s_g, ln s_b and the sampled range; the interpolated curve is then refitted
//! (term-aligned by construction) with the most common order. Where that refit fails, the
//! nearest fitted vertex's model stands in. Owns no samples: it sees only accepted models.
//!
//! Segment l of a vertex points along φ_l in its own tangent frame (Eq. 3). Curves are never
//! averaged across a turn of the frame: a neighbour's segments are re-indexed into the receiving
//! vertex's frame by the whole number of segments its frame is turned
//! ([`crate::model::TangentFrame::twist`], [`crate::interpolate::harmonic_aligned`]), so what is
//! averaged points at most half a segment apart; under the continuous frame rule that is a
//! no-op between neighbours except near the rule's singular normal −z.
use rayon::prelude::*;

use crate::geometry::Scene;
use crate::model::{Anisotropic, ColourModel, ExpSum, Support, TangentFrame};
use crate::modelfile::{ColourMode, ModelShape, params_of};

use super::error::OwnFit;
use super::fit::{Fitter, fit_common_order};
use super::report::TermDropped;

/// An interpolated vertex's refit: parameters, order, sampled range.
#[derive(Debug, Clone, PartialEq)]
pub struct Refit {
    /// Parameters in the model file's order.
    pub params: Vec<f64>,
    /// Order n.
    pub terms: usize,
    /// Direction segments m (the run's for refits; the stand-in's own otherwise).
    pub segments: usize,
    /// Sampled range of the interpolated curve.
    pub r_range: [f64; 2],
}

/// A model for every vertex without its own (`None` for vertices with one, and for vertices
/// not connected to any fitted vertex). `common_n` is the order refits use at most.
pub fn fill(
    scene: &Scene,
    own: &[Option<OwnFit>],
    shape: &ModelShape,
    common_n: usize,
    fitter: &dyn Fitter,
) -> Vec<Option<Refit>> {
    let grid = CurveGrid::of(own.iter().flatten().map(|o| o.r_range));
    let known: Vec<Option<Vec<f64>>> = own
        .iter()
        .map(|o| {
            o.as_ref()
                .map(|o| grid.encode(&o.model, o.r_range, shape.segments))
        })
        .collect();
    let turns = SegmentTurns::new(scene, shape.segments);
    let head = if shape.colour == ColourMode::Shared {
        4
    } else {
        2
    };
    let filled = crate::interpolate::harmonic_aligned(
        &known,
        |v| scene.neighbours(v),
        |v, w, x| {
            let k = turns.shift(v, w, shape.segments);
            (k != 0).then(|| turn_segments(x, head, grid.r.len(), shape.segments, k))
        },
        2000,
    );
    (0..own.len())
        .into_par_iter()
        .map(|v| {
            if own[v].is_some() {
                return None;
            }
            let enc = filled[v].as_ref()?;
            let mut dropped = Vec::new();
            let refit = grid
                .decode(enc, shape, common_n, fitter, &mut dropped)
                .and_then(|(m, range)| match params_of(&m) {
                    Ok((p, n, m)) if p.iter().all(|x| x.is_finite()) => Some(Refit {
                        params: p,
                        terms: n,
                        segments: m,
                        r_range: range,
                    }),
                    _ => None,
                });
            // Where the interpolated curve cannot be refitted, the nearest fitted vertex's own
            // model (breadth-first over the mesh) stands in.
            refit.or_else(|| {
                nearest_fitted(v, own, |w| scene.neighbours(w)).map(|(w, o)| {
                    // Its segments, re-indexed into v's frame.
                    let k = turns.shift(v, w, o.segments);
                    let head = if shape.colour == ColourMode::Shared {
                        2
                    } else {
                        0
                    };
                    Refit {
                        params: turn_segments(&o.params, head, 2 * o.terms, o.segments, k),
                        terms: o.terms,
                        segments: o.segments,
                        r_range: o.r_range,
                    }
                })
            })
        })
        .collect()
}

/// The tangent frames (Eq. 3, the fit's rule) at every vertex normal, to compare neighbours'.
struct SegmentTurns {
    frames: Vec<Option<TangentFrame>>,
}

impl SegmentTurns {
    fn new(scene: &Scene, segments: usize) -> Self {
        Self::of_normals(&scene.mesh.normals, segments)
    }

    fn of_normals(normals: &[[f64; 3]], segments: usize) -> Self {
        let frames = if segments > 1 {
            normals
                .iter()
                .map(|&n| TangentFrame::from_normal(n).ok())
                .collect()
        } else {
            Vec::new()
        };
        SegmentTurns { frames }
    }

    /// By how many whole segments (of `m`) vertex `w`'s frame is turned in `v`'s: `w`'s segment
    /// l points nearest to `v`'s segment l + k.
    fn shift(&self, v: usize, w: usize, m: usize) -> usize {
        if m <= 1 {
            return 0;
        }
        let (Some(Some(a)), Some(Some(b))) = (self.frames.get(v), self.frames.get(w)) else {
            return 0;
        };
        a.twist(b).map_or(0, |d| {
            ((d / (std::f64::consts::TAU / m as f64)).round() as i64).rem_euclid(m as i64) as usize
        })
    }
}

/// `x` (`head` values, then blocks of `m` segments of `chunk` values each: per channel, or one
/// block) with the segments of every block turned by `k`: segment l + k of the result is
/// segment l of `x`.
fn turn_segments(x: &[f64], head: usize, chunk: usize, m: usize, k: usize) -> Vec<f64> {
    let mut out = x.to_vec();
    if k.is_multiple_of(m.max(1)) || chunk == 0 || x.len() < head {
        return out;
    }
    let block = chunk * m;
    for b in 0..(x.len() - head) / block {
        for l in 0..m {
            let to = head + b * block + ((l + k) % m) * chunk;
            let from = head + b * block + l * chunk;
            out[to..to + chunk].copy_from_slice(&x[from..from + chunk]);
        }
    }
    out
}

/// The fitted vertex nearest to `v` in mesh hops (breadth-first), if any is connected, and its
/// index.
fn nearest_fitted<'a, 'n>(
    v: usize,
    own: &'a [Option<OwnFit>],
    neighbours: impl Fn(usize) -> &'n [u32],
) -> Option<(usize, &'a OwnFit)> {
    let mut seen = std::collections::HashSet::from([v]);
    let mut frontier = vec![v];
    while !frontier.is_empty() {
        let mut next = Vec::new();
        for &u in &frontier {
            for &w in neighbours(u) {
                let w = w as usize;
                if w < own.len() && seen.insert(w) {
                    if let Some(o) = &own[w] {
                        return Some((w, o));
                    }
                    next.push(w);
                }
            }
        }
        frontier = next;
    }
    None
}

/// The distance grid on which fitted curves ln R_d(r) are interpolated between vertices.
struct CurveGrid {
    r: Vec<f64>,
}

/// Points of [`CurveGrid`] and of each refit.
const GRID_POINTS: usize = 32;
/// Points of the refit of an interpolated curve, spread over its sampled range.
const REFIT_POINTS: usize = 24;

impl CurveGrid {
    /// Spans every fitted vertex's sampled range.
    fn of(ranges: impl Iterator<Item = [f64; 2]>) -> CurveGrid {
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for [a, b] in ranges {
            lo = lo.min(a);
            hi = hi.max(b);
        }
        if !(lo.is_finite() && hi > lo) {
            (lo, hi) = (0.5, 10.0);
        }
        let r = (0..GRID_POINTS)
            .map(|k| lo + (hi - lo) * k as f64 / (GRID_POINTS - 1) as f64)
            .collect();
        CurveGrid { r }
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
    fn encode(&self, m: &ColourModel, range: [f64; 2], segments: usize) -> Vec<f64> {
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
        let g = &enc[head + k * self.r.len()..head + (k + 1) * self.r.len()];
        let n = self.r.len();
        let step = (self.r[n - 1] - self.r[0]) / (n - 1) as f64;
        let x = ((r - self.r[0]) / step).clamp(0.0, (n - 1) as f64);
        let i = (x.floor() as usize).min(n - 2);
        let t = (r - self.r[i]) / step;
        g[i] + (g[i + 1] - g[i]) * t
    }

    /// Refits an interpolated encoding: the model (term-aligned by construction, order at most
    /// `n`) and its range. `None` if a refit fails.
    fn decode(
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
        let rs: Vec<f64> = (0..REFIT_POINTS)
            .map(|k| range[0] + (range[1] - range[0]) * k as f64 / (REFIT_POINTS - 1) as f64)
            .collect();
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

    #[test]
    fn turning_segments_reindexes_every_block() {
        // head 1, two blocks of m = 4 segments of 2 values.
        let x: Vec<f64> = (0..17).map(f64::from).collect();
        let t = turn_segments(&x, 1, 2, 4, 1);
        assert_eq!(t[0], 0.0);
        // Block 0: segment 0 (values 1, 2) moves to segment 1; segment 3 (7, 8) to segment 0.
        assert_eq!(&t[1..9], &[7.0, 8.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(&t[9..17], &[15.0, 16.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0]);
        assert_eq!(turn_segments(&x, 1, 2, 4, 0), x);
        assert_eq!(turn_segments(&turn_segments(&x, 1, 2, 4, 3), 1, 2, 4, 1), x);
    }

    /// Neighbours on the lit surface share their frame (no shift); across the rule's singular
    /// normal −z the frame turns by half a circle, and the segments are re-indexed by m/2.
    #[test]
    fn segments_shift_only_where_the_frame_turns() {
        let e = 1e-3;
        let normals = [
            [0.0, 0.0, 1.0],
            [0.05, 0.02, 1.0],
            [0.92, 0.3, 0.25],
            [0.89, 0.3, 0.34],
            [e, 0.0, -1.0],
            [0.0, e, -1.0],
        ];
        let turns = SegmentTurns::of_normals(&normals, 8);
        assert_eq!(turns.shift(0, 1, 8), 0);
        assert_eq!(turns.shift(2, 3, 8), 0, "no seam at |n_x| = 0.9");
        assert_eq!(turns.shift(4, 5, 8), 4);
        assert_eq!(turns.shift(4, 5, 1), 0);
    }
}
