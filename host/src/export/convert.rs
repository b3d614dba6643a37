//! Per vertex, the fitted fall-off (Eq. 1/3/5/9, as the renderer evaluates it: support rule,
//! baseline beyond r_max) converted into Cycles' subsurface colour and radius ([`super::cycles`]).
//!
//! - **Subsurface colour** per channel: the total diffuse reflectance `∫_0^∞ R̄_d(r) 2πr dr` of
//!   the direction-averaged fall-off `R̄_d = (1/m) Σ_l R_l` (Eq. 3 averaged over its segments).
//!   Cycles' profile scatters exactly its albedo, so under uniform light the two agree to the
//!   last digit whatever the shape.
//! - **Radius** per channel: `4π d` with `d` the Burley shape fitted in log space to ln R̄_d on
//!   32 distances spaced geometrically over the vertex's sampled range `[r_min, r_max]` (where
//!   the model is claimed; the range holding the middle 98 % of the light when the file has none).
//! - **What it costs**, per channel: log E (Eq. 8's RMS of ln ratios) of the converted profile
//!   against R̄_d over those distances; with anisotropy (m > 1), log E of R̄_d against the
//!   direction-dependent fall-off (Eq. 3 with its hat weights, 4m directions), and of the
//!   converted profile against it; the tail excess (mean ln ratio of fitted to converted over the
//!   outer quarter of the range: positive where a slow term carries light further than one
//!   Burley shape can); the share of light beyond Cycles' truncation at 16 d.
//!
//! Vertices without a model get the harmonic interpolation of their neighbours' ln colour and
//! ln radius (Cycles shades a point with its own parameters, the renderer with its sources': a
//! vertex with no model of its own still glows with its neighbours' light there).

use rayon::prelude::*;

use super::cycles::{RADIUS_PER_D, TRUNCATE, fit_shape, fit_shape_free, ln_profile};
use crate::model::hat_weights;
use crate::modelfile::{ModelFile, VertexStatus};
use crate::progress::Progress;
use crate::render::Falloffs;

/// Distances per vertex at which the converted profile is compared with the fitted one (the
/// pipeline's interpolation compares curves on 32 geometrically spaced points too).
pub const COMPARE_POINTS: usize = 32;

/// Intervals of the Simpson rule in ln r for the total reflectance.
const INTEGRAL_STEPS: usize = 400;

/// Share of a fall-off's light left beyond the integration's upper end.
const TAIL_TOL: f64 = 1e-9;

/// Where a vertex's parameters came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    /// Converted from the vertex's own fit.
    Fitted,
    /// Converted from the vertex's interpolated model (its fit failed, `VertexStatus::Interpolated`).
    Interpolated,
    /// The vertex has no model: ln colour and ln radius interpolated from its neighbours'.
    Filled,
    /// No model and no neighbour with one: black (the renderer shows it black too).
    None,
}

/// One vertex's Cycles parameters and what the conversion costs there.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct VertexConversion {
    /// Subsurface colour per channel: the total diffuse reflectance of the averaged fall-off.
    pub colour: [f64; 3],
    /// Subsurface radius per channel, mm (`4π d`).
    pub radius_mm: [f64; 3],
    /// log E of the converted profile against the direction-averaged fitted one, per channel.
    pub log_e: Option<[f64; 3]>,
    /// log E of the direction-averaged fall-off against the direction-dependent one (Eq. 3),
    /// per channel; `None` for isotropic vertices.
    pub anisotropy_log_e: Option<[f64; 3]>,
    /// log E of the converted profile against the full (direction-dependent) model.
    pub total_log_e: Option<[f64; 3]>,
    /// Mean ln(fitted / converted) over the outer quarter of the compared distances.
    pub tail_excess: Option<[f64; 3]>,
    /// Share of the fitted fall-off's light beyond Cycles' truncation radius 16 d.
    pub beyond_truncation: Option<[f64; 3]>,
    /// The distances compared `[from, to]`, mm.
    pub range_mm: [f64; 2],
    /// Where the parameters came from.
    pub source: Source,
}

/// What the subsurface colour is (issue 43's conversion candidates, chosen by how well Cycles
/// predicts a scan's training frames: docs/export.md). The default is [`ColourRule::Fitted`]:
/// on sample-torus's training frames Cycles' mean log E (green) was 1.36 with it against 2.01
/// with [`ColourRule::Total`] (subsurf's model 0.80 on the same samples).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColourRule {
    /// The fall-off's total diffuse reflectance T: under uniform light on a flat surface Cycles
    /// then scatters exactly the model's light, whatever the shape (what a comparison with
    /// subsurf's own renderer needs: the demo's Blender column).
    Total,
    /// Amplitude and shape fitted together in log space over the sampled distances
    /// ([`super::cycles::fit_shape_free`]): the profile matches the fall-off where it was
    /// measured, and the light of a slow term no Burley shape holds is given up.
    #[default]
    Fitted,
}

/// Converts every vertex of `model` (validated by [`crate::render::validate`]) by
/// [`ColourRule::Total`] (the mesh tests' reference).
pub fn convert(model: &ModelFile, progress: &dyn Progress) -> Vec<VertexConversion> {
    convert_with(model, ColourRule::Total, progress)
}

/// Converts every vertex of `model` with the colour rule `rule`.
pub fn convert_with(
    model: &ModelFile,
    rule: ColourRule,
    progress: &dyn Progress,
) -> Vec<VertexConversion> {
    let falloffs = Falloffs::new(model);
    let n = model.len();
    progress.start("converting", n as u64);
    let mut out: Vec<VertexConversion> = (0..n)
        .into_par_iter()
        .map(|i| {
            let v = convert_one(model, &falloffs, i, rule);
            progress.inc(1);
            v
        })
        .collect();
    fill_missing(model, &mut out);
    out
}

fn convert_one(model: &ModelFile, f: &Falloffs, i: usize, rule: ColourRule) -> VertexConversion {
    let vm = &model.vertices[i];
    let none = VertexConversion {
        colour: [0.0; 3],
        radius_mm: [0.0; 3],
        log_e: None,
        anisotropy_log_e: None,
        total_log_e: None,
        tail_excess: None,
        beyond_truncation: None,
        range_mm: [0.0; 2],
        source: Source::None,
    };
    if vm.status == VertexStatus::NoModel || !f.is_active(i) {
        return none;
    }
    let Some(profile) = Integrated::of(f, i) else {
        return none;
    };
    let support = vm.support();
    let range = if support.is_known() {
        [support.r_min, support.r_max]
    } else {
        profile.energy_range(0.01, 0.99)
    };
    let rs = geometric(range, COMPARE_POINTS);
    let ln_mean: Vec<[f64; 3]> = rs.iter().map(|&r| f.ln_eval_mean(i, r)).collect();
    let mut colour = [0.0; 3];
    let mut radius = [0.0; 3];
    let mut log_e = [0.0; 3];
    let mut tail = [0.0; 3];
    let mut beyond = [0.0; 3];
    let mut d_of = [0.0; 3];
    for c in 0..3 {
        let y: Vec<f64> = ln_mean.iter().map(|l| l[c]).collect();
        let (d, total, rms) = match rule {
            ColourRule::Total => {
                let total = profile.total[c];
                let Some((d, rms)) = fit_shape(&rs, &y, total) else {
                    return none;
                };
                (d, total, rms)
            }
            ColourRule::Fitted => {
                let Some(fit) = fit_shape_free(&rs, &y) else {
                    return none;
                };
                fit
            }
        };
        d_of[c] = d;
        colour[c] = total;
        radius[c] = RADIUS_PER_D * d;
        log_e[c] = rms;
        let outer = &rs[rs.len() * 3 / 4..];
        tail[c] = outer
            .iter()
            .zip(&y[rs.len() * 3 / 4..])
            .map(|(&r, &yk)| yk - (total.ln() + ln_profile(r, d)))
            .sum::<f64>()
            / outer.len() as f64;
        beyond[c] = profile.share_beyond(c, TRUNCATE * d);
    }
    let m = f.segments();
    let (anisotropy, total_log_e) = if m > 1 {
        let (a, t) = anisotropy_cost(f, i, &rs, &ln_mean, colour, d_of);
        (Some(a), t)
    } else {
        (None, log_e)
    };
    let finite = |x: &[f64; 3]| x.iter().all(|v| v.is_finite());
    if !(finite(&colour) && finite(&radius) && finite(&log_e) && finite(&total_log_e)) {
        return none;
    }
    VertexConversion {
        colour,
        radius_mm: radius,
        log_e: Some(log_e),
        anisotropy_log_e: anisotropy,
        total_log_e: Some(total_log_e),
        tail_excess: finite(&tail).then_some(tail),
        beyond_truncation: finite(&beyond).then_some(beyond),
        range_mm: range,
        source: match vm.status {
            VertexStatus::Interpolated => Source::Interpolated,
            _ => Source::Fitted,
        },
    }
}

/// `(log E of R̄ against R(r, φ), log E of the converted profile against R(r, φ))` per channel,
/// over the compared distances and 4m directions φ (Eq. 3's hat weights).
fn anisotropy_cost(
    f: &Falloffs,
    i: usize,
    rs: &[f64],
    ln_mean: &[[f64; 3]],
    colour: [f64; 3],
    d: [f64; 3],
) -> ([f64; 3], [f64; 3]) {
    let m = f.segments();
    let dirs = 4 * m;
    let mut w = vec![0.0; m];
    let (mut sa, mut st, mut n) = ([0.0; 3], [0.0; 3], [0usize; 3]);
    for j in 0..dirs {
        let phi = std::f64::consts::TAU * j as f64 / dirs as f64;
        w.iter_mut().for_each(|x| *x = 0.0);
        for (l, wl) in hat_weights(phi, m) {
            w[l] += wl;
        }
        for (k, &r) in rs.iter().enumerate() {
            let full = f.eval(i, r, &w);
            for c in 0..3 {
                if !(full[c] > 0.0 && full[c].is_finite()) {
                    continue;
                }
                let lf = full[c].ln();
                let ea = ln_mean[k][c] - lf;
                let et = colour[c].ln() + ln_profile(r, d[c]) - lf;
                sa[c] += ea * ea;
                st[c] += et * et;
                n[c] += 1;
            }
        }
    }
    let rms = |s: [f64; 3]| [0, 1, 2].map(|c| (s[c] / n[c].max(1) as f64).sqrt());
    (rms(sa), rms(st))
}

/// `count` distances spaced geometrically over `[lo, hi]`.
fn geometric([lo, hi]: [f64; 2], count: usize) -> Vec<f64> {
    let (a, b) = (lo.max(1e-9).ln(), hi.max(lo * (1.0 + 1e-9)).max(1e-9).ln());
    (0..count)
        .map(|k| (a + (b - a) * k as f64 / (count - 1).max(1) as f64).exp())
        .collect()
}

/// A vertex's direction-averaged fall-off integrated over the plane: the cumulative
/// `∫_0^ρ R̄ 2πr dr` on a grid in ln r (Simpson), and the total.
struct Integrated {
    /// ln r of the grid.
    u: Vec<f64>,
    /// Cumulative integral at each grid point, per channel.
    cumulative: Vec<[f64; 3]>,
    /// The total per channel.
    total: [f64; 3],
}

impl Integrated {
    fn of(f: &Falloffs, i: usize) -> Option<Integrated> {
        let hi = f.cutoff(i, TAIL_TOL);
        if !(hi.is_finite() && hi > 0.0) {
            return None;
        }
        let (a, b) = ((hi * 1e-8).ln(), hi.ln());
        let n = INTEGRAL_STEPS;
        let h = (b - a) / n as f64;
        let u: Vec<f64> = (0..=n).map(|k| a + h * k as f64).collect();
        // The integrand in ln r: R̄(r) 2π r².
        let g: Vec<[f64; 3]> = u
            .iter()
            .map(|&u| {
                let l = f.ln_eval_mean(i, u.exp());
                l.map(|l| (l + 2.0 * u).exp() * std::f64::consts::TAU)
            })
            .collect();
        // Simpson over each pair of intervals; odd points by the trapezoid-corrected half step.
        let mut cumulative = vec![[0.0; 3]; n + 1];
        for k in 1..=n {
            for c in 0..3 {
                let step = if k % 2 == 0 {
                    h / 3.0 * (g[k - 2][c] + 4.0 * g[k - 1][c] + g[k][c])
                } else {
                    0.5 * h * (g[k - 1][c] + g[k][c])
                };
                cumulative[k][c] = if k % 2 == 0 {
                    cumulative[k - 2][c] + step
                } else {
                    cumulative[k - 1][c] + step
                };
            }
        }
        let total = cumulative[n];
        total
            .iter()
            .all(|t| t.is_finite() && *t > 0.0)
            .then_some(Integrated {
                u,
                cumulative,
                total,
            })
    }

    /// The distances within which the fractions `lo` and `hi` of the light lie (the larger over
    /// channels for `hi`, the smaller for `lo`).
    fn energy_range(&self, lo: f64, hi: f64) -> [f64; 2] {
        let at = |q: f64, c: usize| -> f64 {
            let target = q * self.total[c];
            let k = self
                .cumulative
                .iter()
                .position(|x| x[c] >= target)
                .unwrap_or(self.u.len() - 1);
            self.u[k].exp()
        };
        let a = (0..3).map(|c| at(lo, c)).fold(f64::INFINITY, f64::min);
        let b = (0..3).map(|c| at(hi, c)).fold(0.0, f64::max);
        [a, b.max(a * 1.5)]
    }

    /// The share of channel `c`'s light beyond `rho`.
    fn share_beyond(&self, c: usize, rho: f64) -> f64 {
        let x = rho.ln();
        let k = self.u.partition_point(|&u| u < x);
        if k >= self.u.len() {
            return 0.0;
        }
        super::cycles::energy_beyond_truncation(self.cumulative[k][c], self.total[c])
    }
}

/// Vertices without a model: ln colour and ln radius from their neighbours (harmonic
/// interpolation over the mesh graph, [`crate::interpolate::harmonic`]).
fn fill_missing(model: &ModelFile, out: &mut [VertexConversion]) {
    if out.iter().all(|v| v.source != Source::None) {
        return;
    }
    let n = out.len();
    let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n];
    for t in &model.triangles {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            if (a as usize) < n && (b as usize) < n {
                adj[a as usize].push(b);
                adj[b as usize].push(a);
            }
        }
    }
    let known: Vec<Option<Vec<f64>>> = out
        .iter()
        .map(|v| {
            (v.source != Source::None && v.colour.iter().all(|&c| c > 0.0)).then(|| {
                v.colour
                    .iter()
                    .chain(&v.radius_mm)
                    .map(|x| x.ln())
                    .collect()
            })
        })
        .collect();
    let filled = crate::interpolate::harmonic(&known, |v| &adj[v], 200);
    for (v, f) in out.iter_mut().zip(filled) {
        if v.source != Source::None {
            continue;
        }
        if let Some(x) = f.filter(|x| x.len() == 6 && x.iter().all(|y| y.is_finite())) {
            v.colour = [x[0].exp(), x[1].exp(), x[2].exp()];
            v.radius_mm = [x[3].exp(), x[4].exp(), x[5].exp()];
            v.source = Source::Filled;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plate(terms: &[(f64, f64)]) -> ModelFile {
        let mut p = Vec::new();
        let mut f = Vec::new();
        for j in 0..3 {
            for i in 0..3 {
                p.push([i as f64, j as f64, 0.0]);
            }
        }
        for j in 0..2u32 {
            for i in 0..2u32 {
                let a = j * 3 + i;
                f.push([a, a + 1, a + 4]);
                f.push([a, a + 4, a + 3]);
            }
        }
        ModelFile::homogeneous(p, vec![[0.0, 0.0, 1.0]; 9], f, [0.8, 0.5], terms)
    }

    /// The colour is the closed-form total reflectance Σ 2π c_k / d_k² of the fit; a sum of
    /// exponentials is not a Burley shape, and its log E says how far it is.
    #[test]
    fn colour_is_the_total_reflectance_and_the_error_shows_what_cycles_cannot_represent() {
        let terms = [(0.5, -2.0), (0.02, -0.4)];
        let m = plate(&terms);
        let conv = convert(&m, &());
        let want: f64 = terms
            .iter()
            .map(|&(c, d)| std::f64::consts::TAU * c / (d * d))
            .sum();
        let v = &conv[4];
        assert_eq!(v.source, Source::Fitted);
        for (c, s) in [1.0, 0.8, 0.5].iter().enumerate() {
            assert!(
                (v.colour[c] / (want * s) - 1.0).abs() < 1e-6,
                "{:?} vs {}",
                v.colour,
                want * s
            );
        }
        let le = v.log_e.unwrap();
        assert!(le[0] > 0.05 && (le[0] - le[2]).abs() < 1e-9, "{le:?}");
        assert!(v.anisotropy_log_e.is_none() && v.total_log_e == v.log_e);
        assert!(v.tail_excess.unwrap()[0].is_finite(), "{:?}", v.tail_excess);
        assert!(v.radius_mm.iter().all(|r| *r > 0.0));

        // One term only: e^{-2r} is not (e^{-r/d} + e^{-r/3d})/r either, and says so.
        let one = convert(&plate(&[(0.5, -2.0)]), &());
        let l1 = one[4].log_e.unwrap()[0];
        assert!(l1 > 0.01 && l1.is_finite(), "{l1}");
    }

    /// A vertex without a model takes its neighbours' parameters.
    #[test]
    fn vertices_without_a_model_are_filled_from_their_neighbours() {
        let mut m = plate(&[(0.5, -2.0)]);
        m.vertices[4].status = VertexStatus::NoModel;
        m.vertices[4].terms = 0;
        m.vertices[4].segments = 0;
        m.vertices[4].params.clear();
        let conv = convert(&m, &());
        assert_eq!(conv[4].source, Source::Filled);
        assert!((conv[4].colour[0] / conv[0].colour[0] - 1.0).abs() < 1e-9);
        assert!(conv[4].log_e.is_none());
    }
}
