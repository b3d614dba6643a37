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
use crate::model::TangentFrame;
use crate::modelfile::{ColourMode, ModelShape, params_of};

use super::Speed;
use super::error::OwnFit;
use super::fit::Fitter;

mod grid;

use grid::CurveGrid;

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

/// How [`fill`] runs: for which vertices, on which path, from which start.
#[derive(Debug, Clone, Copy, Default)]
pub struct FillHow<'a> {
    /// Only these vertices need a model (a fold of the cross-validation reads the corners of
    /// its held-out frames' x_i and nothing else: [`crate::evaluate::model_at`]); `None`:
    /// every vertex (the model written).
    pub needed: Option<&'a [bool]>,
    /// The default path solves the Laplace equation to [`super::FILL_TOLERANCE`]: with needed
    /// vertices as the weights of the known ones at those vertices, kept from `warm` while the
    /// known set is the same, and refits only the needed vertices; the reference solves all of
    /// it from scratch to [`crate::interpolate::RTOL`] and refits every vertex, the exact
    /// path without the cuts (the same models at the needed vertices, within the tolerance).
    pub speed: Speed,
    /// The previous round's fill of the same run.
    pub warm: Option<&'a FillState>,
}

/// What a fill keeps for the next round's ([`FillHow::warm`]).
#[derive(Debug, Clone, Default)]
pub struct FillState {
    /// The interpolation's weights at the needed vertices ([`crate::interpolate::harmonic_weights`])
    /// and the known set they hold for; shared, not copied, by the rounds and candidates that
    /// reuse them.
    weights: Option<std::sync::Arc<Weights>>,
    /// Where frames turn, the sparse Cholesky factor of the segments' fill on the lifted mesh
    /// ([`Lifted::fill`]), kept while the known set holds; shared like the weights.
    segments: Option<std::sync::Arc<crate::interpolate::FactorCache>>,
}

impl FillState {
    /// Whether it holds interpolation weights (a fold's fill on the default path; where
    /// frames turn, the head's, beside the segments' factor) that another run could start
    /// from.
    pub fn has_weights(&self) -> bool {
        self.weights.is_some()
    }
}

/// The harmonic interpolation at a fold's needed vertices as weights of the known vertices.
#[derive(Debug, Clone)]
struct Weights {
    known: Vec<bool>,
    targets: Vec<usize>,
    of: Vec<Option<Vec<(u32, f64)>>>,
}

/// A model for every vertex without its own (`None` for vertices with one, and for vertices
/// not connected to any fitted vertex). `common_n` is the order refits use at most.
pub fn fill(
    scene: &Scene,
    own: &[Option<OwnFit>],
    shape: &ModelShape,
    common_n: usize,
    fitter: &dyn Fitter,
    how: &FillHow,
) -> (Vec<Option<Refit>>, FillState) {
    let grid = CurveGrid::of(own.iter().flatten().map(|o| o.r_range));
    // The members of a light position share its fit: each distinct fit is encoded once (the
    // curves' exponentials were a tenth of a default fit's cross-validation, once per vertex).
    let mut encoded: std::collections::HashMap<Vec<u64>, Vec<f64>> =
        std::collections::HashMap::new();
    let known: Vec<Option<Vec<f64>>> = own
        .iter()
        .map(|o| {
            o.as_ref().map(|o| {
                let key: Vec<u64> = o
                    .params
                    .iter()
                    .chain(&o.r_range)
                    .map(|x| x.to_bits())
                    .chain([o.terms as u64, o.segments as u64])
                    .collect();
                encoded
                    .entry(key)
                    .or_insert_with(|| grid.encode(&o.model, o.r_range, shape.segments))
                    .clone()
            })
        })
        .collect();
    let turns = SegmentTurns::new(scene, shape.segments);
    let head = if shape.colour == ColourMode::Shared {
        4
    } else {
        2
    };
    // The reference refits every vertex, the exact path without the cuts (the models at the needed ones are
    // the same either way).
    let needed = |v: usize| {
        how.speed == Speed::Reference
            || how
                .needed
                .is_none_or(|n| n.get(v).copied().unwrap_or(false))
    };
    // One segment has no frame to turn: the plain Laplace equation. Neither has a run of m > 1
    // segments whose unknown vertices' frames turn by no whole segment against any neighbour
    // (`align` below is then the identity: the sweeps would solve the plain equation): on the
    // default path it is solved as one segment's is, which cut `--segments auto` on sample-slab
    // (a flat mesh, one frame) from 70 s to 1.5 s, the sweeps having been 89 % of it. The
    // reference keeps the sweeps.
    let turned = shape.segments > 1
        && (how.speed == Speed::Reference
            || (0..own.len()).any(|v| {
                own[v].is_none()
                    && scene
                        .neighbours(v)
                        .iter()
                        .any(|&w| turns.shift(v, w as usize, shape.segments) != 0)
            }));
    // The plain Laplace fill of per-vertex values on the mesh (a fold's by weights, see
    // [`plain_fill`]).
    let plain = |values: &[Option<Vec<f64>>]| {
        plain_fill(
            values,
            |v| scene.neighbours(v),
            own,
            how.needed,
            how.speed,
            how.warm.and_then(|w| w.weights.as_ref()),
        )
    };
    let (filled, weights, segments) = if turned && how.speed == Speed::Reference {
        let m = shape.segments;
        let swept = crate::interpolate::harmonic_aligned(
            &known,
            |v| scene.neighbours(v),
            |v, w, x| {
                let k = turns.shift(v, w, m);
                (k != 0).then(|| turn_segments(x, head, grid.r.len(), m, k))
            },
            2000,
        );
        (swept, None, None)
    } else if turned {
        // Where frames turn (a curved object's, about the frame rule's singular normal): the
        // turns are cyclic shifts of the segments, so the equation of the segments' values is
        // the plain Laplace equation on the lifted mesh ([`Lifted`]), and the head's (ranges,
        // channel scales) the plain one on the mesh. The head is filled as one segment's
        // values are (a fold's by weights), the segments by a sparse Cholesky factor of the
        // lifted rows that a fold keeps while its known set holds (weights there, m times the
        // targets over m times the known nodes, took 30 % more memory and 10 % more time on
        // sample-pebble). It replaced conjugate gradients on the connection Laplacian to
        // `FILL_TOLERANCE`: `--segments auto` on sample-pebble 72 -> 36 s of CPU, the same
        // choices.
        let m = shape.segments;
        let chunk = grid.r.len();
        // One direction of an edge defines the other, so (v, l) and (w, l - k) are each
        // other's neighbours (`twist` is antisymmetric only up to rounding).
        let turn = |v: usize, w: usize| {
            if v < w {
                turns.shift(v, w, m)
            } else {
                (m - turns.shift(w, v, m)) % m
            }
        };
        let lifted = Lifted::new(own.len(), m, |v| scene.neighbours(v), turn);
        let head_values: Vec<Option<Vec<f64>>> = known
            .iter()
            .map(|x| x.as_ref().and_then(|x| x.get(..head)).map(<[f64]>::to_vec))
            .collect();
        let (head_filled, weights) = plain(&head_values);
        let cache = how
            .warm
            .and_then(|w| w.segments.clone())
            .unwrap_or_default();
        let segments_filled = lifted.fill(&lifted.split(&known, head, chunk), how.needed, &cache);
        (
            lifted.join(&head_filled, &segments_filled, chunk),
            weights,
            how.needed.is_some().then_some(cache),
        )
    } else {
        let (filled, weights) = plain(&known);
        (filled, weights, None)
    };
    let refits = (0..own.len())
        .into_par_iter()
        .map(|v| {
            if own[v].is_some() || !needed(v) {
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
        .collect();
    let state = FillState { weights, segments };
    (refits, state)
}

/// The plain Laplace fill of `values` on the graph `neighbours` (no turns): on the default path
/// a fold's (`needed` given) as weights of the known vertices at its needed unknown ones
/// (`own[v]` `None`), kept from `warm` while the known set and those vertices are the same, and
/// otherwise solved by a sparse Cholesky factor to [`super::FILL_TOLERANCE`]; on the reference
/// by conjugate gradients to [`crate::interpolate::RTOL`]. Returns the fill and, for a fold's,
/// its weights.
fn plain_fill<'a, T>(
    values: &[Option<Vec<f64>>],
    neighbours: impl Fn(usize) -> &'a [u32] + Copy,
    own: &[Option<T>],
    needed: Option<&[bool]>,
    speed: Speed,
    warm: Option<&std::sync::Arc<Weights>>,
) -> (Vec<Option<Vec<f64>>>, Option<std::sync::Arc<Weights>>) {
    if let (Speed::Default, Some(needed)) = (speed, needed) {
        // A fold's fill: the interpolation at its needed vertices, as weights of the known
        // ones that hold while the known set does (every round of a fold, mostly).
        let known_set: Vec<bool> = values.iter().map(Option::is_some).collect();
        let targets: Vec<usize> = (0..own.len())
            .filter(|&v| needed.get(v).copied().unwrap_or(false) && own[v].is_none())
            .collect();
        let w = match warm {
            Some(w) if w.known == known_set && w.targets == targets => std::sync::Arc::clone(w),
            _ => std::sync::Arc::new(Weights {
                of: crate::interpolate::harmonic_weights(
                    &known_set,
                    neighbours,
                    &targets,
                    &crate::interpolate::Solve {
                        rtol: super::FILL_TOLERANCE,
                        ..crate::interpolate::Solve::default()
                    },
                ),
                known: known_set,
                targets,
            }),
        };
        let mut filled: Vec<Option<Vec<f64>>> = vec![None; values.len()];
        for (&t, of) in w.targets.iter().zip(&w.of) {
            let Some(of) = of else { continue };
            let mut x: Option<Vec<f64>> = None;
            for &(k, wk) in of {
                let Some(val) = values[k as usize].as_ref() else {
                    continue;
                };
                let acc = x.get_or_insert_with(|| vec![0.0; val.len()]);
                if acc.len() == val.len() {
                    for (a, b) in acc.iter_mut().zip(val) {
                        *a += wk * b;
                    }
                }
            }
            filled[t] = x;
        }
        return (filled, Some(w));
    }
    // Solved once: the factor is not kept.
    let factor = crate::interpolate::FactorCache::default();
    let solve = match speed {
        Speed::Reference => crate::interpolate::Solve::default(),
        // From the breadth-first guess, never from an earlier round's fill: the model after
        // round r of a run is the model of a fit with r rounds, byte for byte (the
        // cross-validation's rounds and the final fit are the same procedure).
        Speed::Default => crate::interpolate::Solve {
            rtol: super::FILL_TOLERANCE,
            direct: Some(&factor),
            ..crate::interpolate::Solve::default()
        },
    };
    (
        crate::interpolate::harmonic_with(values, neighbours, &solve),
        None,
    )
}

/// The mesh lifted by m direction segments: node v·m + l is vertex v's segment l, and (v, l)
/// neighbours (w, l − k) where w's frame is turned by k segments in v's (w's segment l − k
/// points nearest to v's segment l, [`turn_segments`]). Why: re-expressing a neighbour's
/// segments in a vertex's frame shifts them cyclically, so the fill's equation of the segment
/// values, Δx_v = Σ_w (P_vw x_w − x_v), is the plain Laplace equation of this graph (one
/// unknown per node and value, every edge of weight 1; symmetric where `turn(w, v)` is
/// `m − turn(v, w)`), which a sparse Cholesky factor solves exactly, as one segment's fill.
struct Lifted {
    m: usize,
    start: Vec<usize>,
    adj: Vec<u32>,
}

impl Lifted {
    fn new<'a>(
        n: usize,
        m: usize,
        neighbours: impl Fn(usize) -> &'a [u32],
        turn: impl Fn(usize, usize) -> usize,
    ) -> Self {
        let m = m.max(1);
        let mut start = Vec::with_capacity(n * m + 1);
        let mut adj = Vec::new();
        start.push(0);
        for v in 0..n {
            let ws = neighbours(v);
            for l in 0..m {
                for &w in ws {
                    let w = w as usize;
                    if w < n {
                        let k = turn(v, w) % m;
                        adj.push(u32::try_from(w * m + (l + m - k) % m).unwrap_or(u32::MAX));
                    }
                }
                start.push(adj.len());
            }
        }
        Lifted { m, start, adj }
    }

    fn neighbours(&self, u: usize) -> &[u32] {
        match (self.start.get(u), self.start.get(u + 1)) {
            (Some(&a), Some(&b)) => &self.adj[a..b],
            _ => &[],
        }
    }

    /// Each vertex's encoding (`head` values, then blocks of m segments of `chunk` values) as
    /// its segments' nodes: node (v, l) holds segment l of every block.
    fn split(
        &self,
        values: &[Option<Vec<f64>>],
        head: usize,
        chunk: usize,
    ) -> Vec<Option<Vec<f64>>> {
        let m = self.m;
        (0..values.len() * m)
            .map(|u| {
                let (v, l) = (u / m, u % m);
                let x = values[v].as_ref()?;
                let blocks = x.len().checked_sub(head)? / (m * chunk).max(1);
                Some(
                    (0..blocks)
                        .flat_map(|b| {
                            let at = head + b * m * chunk + l * chunk;
                            x[at..at + chunk].iter().copied()
                        })
                        .collect(),
                )
            })
            .collect()
    }

    /// The plain fill of node values (from [`Lifted::split`]) on the default path: exactly, by
    /// a sparse Cholesky factor of the lifted rows kept in `cache` while the known nodes and
    /// the solved ones stay the same, and only in the holes of the `needed` vertices' nodes
    /// (`None`: all; the other unknown nodes keep the breadth-first guess).
    fn fill(
        &self,
        values: &[Option<Vec<f64>>],
        needed: Option<&[bool]>,
        cache: &crate::interpolate::FactorCache,
    ) -> Vec<Option<Vec<f64>>> {
        let needed = needed.map(|n| self.lift_mask(n));
        crate::interpolate::harmonic_with(
            values,
            |u| self.neighbours(u),
            &crate::interpolate::Solve {
                rtol: super::FILL_TOLERANCE,
                direct: Some(cache),
                only: needed.as_deref(),
                ..crate::interpolate::Solve::default()
            },
        )
    }

    /// A mask of vertices as the mask of their nodes.
    fn lift_mask(&self, mask: &[bool]) -> Vec<bool> {
        mask.iter()
            .flat_map(|&b| std::iter::repeat_n(b, self.m))
            .collect()
    }

    /// [`Lifted::split`]'s inverse: a vertex's head and its segments' nodes as its encoding,
    /// where all of them are filled.
    fn join(
        &self,
        head: &[Option<Vec<f64>>],
        segments: &[Option<Vec<f64>>],
        chunk: usize,
    ) -> Vec<Option<Vec<f64>>> {
        let m = self.m;
        head.iter()
            .enumerate()
            .map(|(v, h)| {
                let h = h.as_ref()?;
                let segs: Vec<&Vec<f64>> = (0..m)
                    .map(|l| segments.get(v * m + l).and_then(Option::as_ref))
                    .collect::<Option<_>>()?;
                let blocks = segs[0].len() / chunk.max(1);
                if segs.iter().any(|s| s.len() != blocks * chunk) {
                    return None;
                }
                let mut out = h.clone();
                for b in 0..blocks {
                    for s in &segs {
                        out.extend_from_slice(&s[b * chunk..(b + 1) * chunk]);
                    }
                }
                Some(out)
            })
            .collect()
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A k × k grid's neighbours (4-connected).
    fn grid(k: usize) -> Vec<Vec<u32>> {
        (0..k * k)
            .map(|v| {
                let (i, j) = (v / k, v % k);
                let mut nb = Vec::new();
                for (di, dj) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                    let (a, b) = (i as i64 + di, j as i64 + dj);
                    if (0..k as i64).contains(&a) && (0..k as i64).contains(&b) {
                        nb.push((a as usize * k + b as usize) as u32);
                    }
                }
                nb
            })
            .collect()
    }

    /// The plain fill of the lifted mesh solves the turned equation: on a grid with two holes
    /// (border and one column known) whose frames turn by one of three segments across a line
    /// through the left hole (a head of one value, two blocks of three segments of two values),
    /// it equals the converged sweeps, and differs from the fill without turns where the turn
    /// matters; a fold that reads one vertex gets the full solve there and nothing elsewhere,
    /// and the same again from the kept factor; the lifted graph is symmetric.
    #[test]
    fn the_lifted_mesh_solves_the_turned_equation() {
        let k = 14usize;
        let adj = grid(k);
        let (m, chunk, head) = (3usize, 2usize, 1usize);
        let len = head + 2 * m * chunk;
        // Columns 0..4 are one frame, 4.. another, turned by one segment.
        let side = |v: usize| usize::from(v % k >= 4);
        let turn = |v: usize, w: usize| (m + side(w) - side(v)) % m;
        let known = |v: usize| {
            let (i, j) = (v / k, v % k);
            i == 0 || j == 0 || i + 1 == k || j + 1 == k || j == 8
        };
        let f = |v: usize| -> Vec<f64> {
            let (x, y) = ((v / k) as f64, (v % k) as f64);
            (0..len)
                .map(|e| (e as f64 + 1.0) * x - 0.5 * y * e as f64 + (x * y).sin())
                .collect()
        };
        let vals: Vec<Option<Vec<f64>>> = (0..k * k).map(|v| known(v).then(|| f(v))).collect();
        let swept = crate::interpolate::harmonic_aligned(
            &vals,
            |v| &adj[v],
            |v, w, x| {
                let t = turn(v, w);
                (t != 0).then(|| turn_segments(x, head, chunk, m, t))
            },
            100_000,
        );
        let lifted = Lifted::new(k * k, m, |v| &adj[v], turn);
        for u in 0..k * k * m {
            for &x in lifted.neighbours(u) {
                assert!(lifted.neighbours(x as usize).contains(&(u as u32)));
            }
        }
        let own: Vec<Option<()>> = (0..k * k).map(|v| known(v).then_some(())).collect();
        let head_values: Vec<Option<Vec<f64>>> = vals
            .iter()
            .map(|x| x.as_ref().map(|x| x[..head].to_vec()))
            .collect();
        let split = lifted.split(&vals, head, chunk);
        let cache = crate::interpolate::FactorCache::default();
        let solve = |needed: Option<&[bool]>| {
            let (h, hw) = plain_fill(
                &head_values,
                |v| &adj[v],
                &own,
                needed,
                Speed::Default,
                None,
            );
            assert_eq!(hw.is_some(), needed.is_some());
            lifted.join(&h, &lifted.fill(&split, needed, &cache), chunk)
        };
        let full = solve(None);
        let plain = crate::interpolate::harmonic(&vals, |v| &adj[v], 2000);
        let close = |a: &[f64], b: &[f64]| {
            a.len() == b.len()
                && a.iter()
                    .zip(b)
                    .all(|(x, y)| (x - y).abs() < 1e-8 * (1.0 + y.abs()))
        };
        let mut turned_somewhere = false;
        for v in 0..k * k {
            let (a, b) = (full[v].as_ref().unwrap(), swept[v].as_ref().unwrap());
            assert!(close(a, b), "vertex {v}: {a:?} vs {b:?}");
            let p = plain[v].as_ref().unwrap();
            turned_somewhere |= a.iter().zip(p).any(|(x, y)| (x - y).abs() > 1e-3);
        }
        assert!(turned_somewhere, "the turn changed nothing: no test");
        // A fold that reads one vertex of the left hole.
        let target = 6 * k + 2;
        let mut needed = vec![false; k * k];
        needed[target] = true;
        let part = solve(Some(&needed));
        assert!(close(
            part[target].as_ref().unwrap(),
            full[target].as_ref().unwrap()
        ));
        assert!(part[6 * k + 11].is_none() && part[6 * k + 3].is_none());
        // The next round's fill from the kept factor: the same values, to the bit.
        let again = solve(Some(&needed));
        assert_eq!(again[target], part[target]);
    }

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
