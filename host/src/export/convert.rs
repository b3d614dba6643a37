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

use super::cycles::{RADIUS_PER_D, TRUNCATE, fit_shape, fit_shape_free, fit_two_lobes, ln_profile};
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
    /// The second, slow lobe of [`ColourRule::TwoLobe`] (`None` for one lobe): then `colour` and
    /// `radius_mm` are the near lobe's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub slow: Option<SlowLobe>,
}

/// The slow one of two Principled BSDF subsurface lobes mixed by a Mix Shader
/// ([`ColourRule::TwoLobe`]).
///
/// A Mix Shader with factor `f` scales the near BSDF's closures by `1 − f` and this one's by
/// `f`, and Cycles scatters `weight × colour` through each lobe's own profile (it picks one
/// BSSRDF closure per path by weight, so the mix is unbiased). So a lobe holding the light `A`
/// gets the colour `A / weight`: the near lobe `A_near / (1 − f)`, this one `A_slow / f`. The
/// factor is one number per vertex (the Mix Shader's Fac is a scalar): the slow share of the
/// light, averaged over channels; the colours carry each channel's own split.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SlowLobe {
    /// Subsurface colour per channel (`A_slow / weight`).
    pub colour: [f64; 3],
    /// Subsurface radius per channel, mm (`4π d_slow`).
    pub radius_mm: [f64; 3],
    /// The Mix Shader's factor: the slow lobe's share of the total reflectance, mean over
    /// channels, in [0, 1].
    pub weight: f64,
}

/// What the subsurface colour is (the conversion candidates, chosen by how well Cycles
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
    /// Two Burley lobes, a near and a slow one, mixed by a Mix Shader: the
    /// fitted exponentials (Eq. 1, every direction segment's, Eq. 3 averaged) split at the
    /// largest gap in their rates into a fast and a slow group; T is split between the lobes as
    /// the groups' own reflectances `Σ 2π c_k / d_k²` split it, and each lobe's radius is the
    /// Burley shape of its group's curve. One Burley shape cannot hold a near and a slow term at
    /// once; two can, with the slow term's light where it falls instead of near x_i or nowhere.
    TwoLobe,
}

impl ColourRule {
    /// The rule's name on the command line and in the files (`total`, `fitted`, `two-lobe`).
    pub fn name(self) -> &'static str {
        match self {
            ColourRule::Total => "total",
            ColourRule::Fitted => "fitted",
            ColourRule::TwoLobe => "two-lobe",
        }
    }
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

/// Per vertex, the total diffuse reflectance `∫ R̄_d 2πr dr` of its fall-off as the renderer
/// evaluates it (what it gathers on a plane under unit irradiance); `None` without a model.
pub fn totals(model: &ModelFile) -> Vec<Option<[f64; 3]>> {
    let f = Falloffs::new(model);
    (0..model.len())
        .into_par_iter()
        .map(|i| {
            (model.vertices[i].status != VertexStatus::NoModel && f.is_active(i))
                .then(|| Integrated::of(&f, i).map(|p| p.total))
                .flatten()
        })
        .collect()
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
        slow: None,
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
    // Per channel the converted profile as lobes `(A, d)`: `Σ_j A_j R(r; d_j)`.
    let mut lobes = [[(0.0, 1.0); 2]; 3];
    let two = if rule == ColourRule::TwoLobe {
        let Some(t) = two_lobes(model, i, &rs, &ln_mean) else {
            return none;
        };
        Some(t)
    } else {
        None
    };
    for c in 0..3 {
        let y: Vec<f64> = ln_mean.iter().map(|l| l[c]).collect();
        lobes[c] = match (rule, &two) {
            (ColourRule::TwoLobe, Some(t)) => t[c],
            (ColourRule::Fitted, _) => {
                let Some((d, a, _)) = fit_shape_free(&rs, &y) else {
                    return none;
                };
                [(a, d), (0.0, d)]
            }
            _ => {
                let total = profile.total[c];
                let Some((d, _)) = fit_shape(&rs, &y, total) else {
                    return none;
                };
                [(total, d), (0.0, d)]
            }
        };
    }
    let ln_conv = |c: usize, r: f64| -> f64 { ln_lobes(&lobes[c], r) };
    let mut log_e = [0.0; 3];
    let mut tail = [0.0; 3];
    let mut beyond = [0.0; 3];
    for c in 0..3 {
        let err: Vec<f64> = rs
            .iter()
            .zip(&ln_mean)
            .map(|(&r, l)| l[c] - ln_conv(c, r))
            .collect();
        log_e[c] = (err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt();
        let outer = &err[err.len() * 3 / 4..];
        tail[c] = outer.iter().sum::<f64>() / outer.len() as f64;
        // Cycles' reach: 16 d of the farthest lobe holding light.
        let reach = lobes[c]
            .iter()
            .filter(|(a, _)| *a > 0.0)
            .map(|(_, d)| TRUNCATE * d)
            .fold(0.0, f64::max);
        beyond[c] = profile.share_beyond(c, reach);
    }
    // What the node tree gets: the near lobe's colour and radius (with two lobes, its light over
    // its Mix Shader weight), the slow lobe apart.
    let (colour, radius, slow) = match &two {
        Some(_) => {
            let w = (0..3)
                .map(|c| {
                    let t = lobes[c][0].0 + lobes[c][1].0;
                    if t > 0.0 { lobes[c][1].0 / t } else { 0.0 }
                })
                .sum::<f64>()
                / 3.0;
            let w = if w.is_finite() {
                w.clamp(0.0, 1.0)
            } else {
                0.0
            };
            let near_colour = [0, 1, 2].map(|c| {
                if 1.0 - w > 1e-9 {
                    lobes[c][0].0 / (1.0 - w)
                } else {
                    0.0
                }
            });
            let near_radius = [0, 1, 2].map(|c| RADIUS_PER_D * lobes[c][0].1);
            let slow = if w > 1e-9 {
                SlowLobe {
                    colour: [0, 1, 2].map(|c| lobes[c][1].0 / w),
                    radius_mm: [0, 1, 2].map(|c| RADIUS_PER_D * lobes[c][1].1),
                    weight: w,
                }
            } else {
                // No slow light: a lobe of weight 0 (the near one's values, so interpolation
                // in ln colour and ln radius stays finite).
                SlowLobe {
                    colour: near_colour,
                    radius_mm: near_radius,
                    weight: 0.0,
                }
            };
            (near_colour, near_radius, Some(slow))
        }
        None => (
            [0, 1, 2].map(|c| lobes[c][0].0),
            [0, 1, 2].map(|c| RADIUS_PER_D * lobes[c][0].1),
            None,
        ),
    };
    let m = f.segments();
    let (anisotropy, total_log_e) = if m > 1 {
        let (a, t) = anisotropy_cost(f, i, &rs, &ln_mean, &ln_conv);
        (Some(a), t)
    } else {
        (None, log_e)
    };
    let finite = |x: &[f64; 3]| x.iter().all(|v| v.is_finite());
    if !(finite(&colour) && finite(&radius) && finite(&log_e) && finite(&total_log_e))
        || slow.is_some_and(|l| !(finite(&l.colour) && finite(&l.radius_mm)))
    {
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
        slow,
    }
}

/// `ln Σ_j A_j R(r; d_j)` of Cycles' Burley lobes (log-sum-exp: finite where a lobe
/// underflows; lobes with no light are skipped).
fn ln_lobes(lobes: &[(f64, f64); 2], r: f64) -> f64 {
    let l: Vec<f64> = lobes
        .iter()
        .filter(|(a, _)| *a > 0.0)
        .map(|&(a, d)| a.ln() + ln_profile(r, d))
        .collect();
    let m = l.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !m.is_finite() {
        return m;
    }
    m + l.iter().map(|x| (x - m).exp()).sum::<f64>().ln()
}

/// The two lobes `[(A_near, d_near), (A_slow, d_slow)]` per channel of vertex `i`
/// ([`ColourRule::TwoLobe`]), fitted to its direction-averaged fall-off `ln_mean` at the
/// compared distances `rs`; `None` when the vertex's parameters do not read as a model.
///
/// The pool is every exponential of every direction segment, weighted `1/m` (Eq. 3 averaged,
/// as the one-lobe conversion averages the segments), with the channel's scale (Eq. 5/9). Sorted
/// by rate, it is cut at the largest ratio between neighbouring rates: the fast group is the
/// near lobe, the rest the slow one (a vertex whose terms all share one rate has no slow lobe:
/// `A_slow = 0`). Each group's reflectance is `Σ 2π c_k / d_k²` (closed form), and the lobes'
/// light is split in that ratio. The two shapes and the amplitude are fitted together in log
/// space over the compared distances ([`fit_two_lobes`]): fitted to each group's own curve
/// with the amplitude fixed to T (tried first), the near lobe came out far too wide — Burley's
/// `e^{−r/d}/r` is no exponential, and T as the renderer integrates it (the support rule below
/// r_min) is about twice the terms' closed form on sample-torus — and its conversion log E was
/// 1.5 (median, sample-torus) against 0.19 for one fitted lobe; fitted together, 0.026.
fn two_lobes(
    model: &ModelFile,
    i: usize,
    rs: &[f64],
    ln_mean: &[[f64; 3]],
) -> Option<[[(f64, f64); 2]; 3]> {
    use crate::model::ColourModel;
    let vm = &model.vertices[i];
    let cm = crate::modelfile::model_of(&model.shape, vm.terms as usize, &vm.params).ok()?;
    let mut out = [[(0.0, 1.0); 2]; 3];
    let (mut done, mut shares) = ([[(0.0, 1.0); 2]; 3], [f64::NAN; 3]);
    for (c, lobes) in out.iter_mut().enumerate() {
        let (aniso, scale) = match &cm {
            ColourModel::Shared { falloff, s_g, s_b } => (falloff, [1.0, *s_g, *s_b][c]),
            ColourModel::PerChannel { channels } => (&channels[c], 1.0),
        };
        let m = aniso.segments.len().max(1) as f64;
        let mut pool: Vec<(f64, f64)> = aniso
            .segments
            .iter()
            .flat_map(|seg| seg.terms.iter().map(|t| (t.c * scale / m, -t.d)))
            .filter(|&(a, s)| a > 0.0 && s > 0.0 && a.is_finite() && s.is_finite())
            .collect();
        if pool.is_empty() {
            return None;
        }
        pool.sort_by(|a, b| b.1.total_cmp(&a.1));
        // Cut at the largest rate ratio (none when every rate is the same to 1 %).
        let cut = (1..pool.len())
            .map(|k| (k, pool[k - 1].1 / pool[k].1))
            .filter(|&(_, ratio)| ratio > 1.01)
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(pool.len(), |(k, _)| k);
        let (near, slow) = pool.split_at(cut);
        let reflectance = |g: &[(f64, f64)]| {
            g.iter()
                .map(|&(a, s)| std::f64::consts::TAU * a / (s * s))
                .sum::<f64>()
        };
        let (t_near, t_slow) = (reflectance(near), reflectance(slow));
        let share = t_slow / (t_near + t_slow);
        if !share.is_finite() {
            return None;
        }
        // The shapes and the amplitude over the vertex's compared distances, the share fixed.
        let y: Vec<f64> = ln_mean.iter().map(|l| l[c]).collect();
        // A channel that is an earlier one scaled (Eq. 5/9: shared colour) with the same split
        // has its shapes: only the amplitude differs (the fit is the slow part of an export).
        let offset = |p: usize| -> Option<f64> {
            let diff: Vec<f64> = ln_mean.iter().map(|l| l[c] - l[p]).collect();
            let mean = diff.iter().sum::<f64>() / diff.len() as f64;
            diff.iter().all(|x| (x - mean).abs() < 1e-9).then_some(mean)
        };
        if let Some((p, shift)) = shares[..c]
            .iter()
            .enumerate()
            .filter(|(_, s)| (**s - share).abs() < 1e-12)
            .find_map(|(p, _)| offset(p).map(|o| (p, o)))
        {
            let [(a1, d1), (a2, d2)] = done[p];
            *lobes = [(a1 * shift.exp(), d1), (a2 * shift.exp(), d2)];
            done[c] = *lobes;
            shares[c] = share;
            continue;
        }
        let (d_near, d_slow, amp, _) = if slow.is_empty() {
            let (d, a, rms) = fit_shape_free(rs, &y)?;
            (d, d, a, rms)
        } else {
            fit_two_lobes(rs, &y, share)?
        };
        *lobes = [(amp * (1.0 - share), d_near), (amp * share, d_slow)];
        done[c] = *lobes;
        shares[c] = share;
    }
    Some(out)
}

/// `(log E of R̄ against R(r, φ), log E of the converted profile against R(r, φ))` per channel,
/// over the compared distances and 4m directions φ (Eq. 3's hat weights).
fn anisotropy_cost(
    f: &Falloffs,
    i: usize,
    rs: &[f64],
    ln_mean: &[[f64; 3]],
    ln_conv: &dyn Fn(usize, f64) -> f64,
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
                let et = ln_conv(c, r) - lf;
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
    // ln colour and ln radius (and with two lobes the slow lobe's, and its weight) per vertex.
    let two = out.iter().any(|v| v.slow.is_some());
    let width = if two { 13 } else { 6 };
    let known: Vec<Option<Vec<f64>>> = out
        .iter()
        .map(|v| {
            let slow_ok = !two
                || v.slow
                    .is_some_and(|l| l.colour.iter().chain(&l.radius_mm).all(|&c| c > 0.0));
            (v.source != Source::None && v.colour.iter().all(|&c| c > 0.0) && slow_ok).then(|| {
                let mut x: Vec<f64> = v
                    .colour
                    .iter()
                    .chain(&v.radius_mm)
                    .map(|x| x.ln())
                    .collect();
                if let (true, Some(l)) = (two, &v.slow) {
                    x.extend(l.colour.iter().chain(&l.radius_mm).map(|x| x.ln()));
                    x.push(l.weight);
                }
                x
            })
        })
        .collect();
    let filled = crate::interpolate::harmonic(&known, |v| &adj[v], 200);
    for (v, f) in out.iter_mut().zip(filled) {
        if v.source != Source::None {
            continue;
        }
        if let Some(x) = f.filter(|x| x.len() == width && x.iter().all(|y| y.is_finite())) {
            v.colour = [x[0].exp(), x[1].exp(), x[2].exp()];
            v.radius_mm = [x[3].exp(), x[4].exp(), x[5].exp()];
            if two {
                v.slow = Some(SlowLobe {
                    colour: [x[6].exp(), x[7].exp(), x[8].exp()],
                    radius_mm: [x[9].exp(), x[10].exp(), x[11].exp()],
                    weight: x[12].clamp(0.0, 1.0),
                });
            }
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

    /// Two lobes: the slow lobe's weight is the slow term's share of the terms' closed-form
    /// reflectance, the radii are ordered, and the pair fits the two-term fall-off better than
    /// one lobe; a one-term vertex has a slow lobe of weight 0.
    #[test]
    fn two_lobes_split_the_light_as_the_terms_do_and_fit_better_than_one() {
        let terms = [(0.5, -2.0), (0.02, -0.4)];
        let m = plate(&terms);
        let two = convert_with(&m, ColourRule::TwoLobe, &());
        let one = convert_with(&m, ColourRule::Fitted, &());
        let v = &two[4];
        let t: Vec<f64> = terms
            .iter()
            .map(|&(c, d)| std::f64::consts::TAU * c / (d * d))
            .collect();
        let share = t[1] / (t[0] + t[1]);
        let slow = v.slow.expect("a slow lobe");
        assert!(
            (slow.weight - share).abs() < 1e-9,
            "{} vs {share}",
            slow.weight
        );
        assert!(slow.radius_mm[0] >= v.radius_mm[0], "{slow:?} {v:?}");
        let (l2, l1) = (v.log_e.unwrap()[0], one[4].log_e.unwrap()[0]);
        assert!(l2 < l1, "two lobes {l2}, one {l1}");
        let single = convert_with(&plate(&[(0.5, -2.0)]), ColourRule::TwoLobe, &());
        assert_eq!(single[4].slow.map(|l| l.weight), Some(0.0));
        // The mesh carries the slow lobe to the glTF.
        let mesh = super::super::mesh::vertex_mesh(&m, &two);
        assert_eq!(mesh.slow_weight.len(), mesh.positions.len());
        assert!(mesh.slow_weight.iter().all(|w| (w[0] - share).abs() < 1e-9));
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
