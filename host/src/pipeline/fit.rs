//! Stage `fit` (sections 4.2 and 5, Eq. 1/3/5/9 and Eq. 6): one model per selection group, and
//! the modulation texture alpha(x_o) by rounds of fitting samples divided by the previous
//! round's alpha.
//!
//! Owns the choice of model order (terms the samples do not support are dropped) and the alpha
//! rounds; streams the groups (samples are dropped once their Eq. 6 contributions are folded in),
//! so memory does not grow with the frame count. Never reads images itself (the `select` stage
//! does) and never judges a fit (the `error` stage does).
use std::collections::{BTreeMap, HashMap};

use rayon::prelude::*;

use crate::baseline::Baseline;
use crate::geometry::Scene;
use crate::model::{AlphaAccumulator, Anisotropic, ColourModel, ExpSum};
use crate::modelfile::{BaselineParams, ColourMode, params_of};
use crate::progress::Progress;
use crate::samples::SampleCounts;

use super::ModelChoice;
use super::load::Context;
use super::register::RegisteredFrame;
use super::report::{AlphaReport, AlphaRound, BASELINE_POOL, FailReason, TermDropped};
use super::select::{ChannelSamples, GroupSample, Groups, group_samples};

/// The solver the pipeline fits with: Eq. 1 alone (order choice, interpolation refits) and the
/// one joint Eq. 3/5/9 fit of a light position's model.
pub trait Fitter: Sync {
    /// One isotropic fall-off fit (Eq. 1) to samples `s` at distances `r`. `terms = Some(n)`
    /// forces n terms; `None` uses the fitter's own setting (which may choose the order
    /// automatically).
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason>;
    /// The joint fit of n terms and m direction segments (Eq. 3, every row weighted over the
    /// segments by the hat weights evaluation uses) and the colour model (Eq. 5/9 shared, or
    /// per channel) to `rows`; the segments of the bit mask `anchored` are held at the
    /// isotropic fit.
    fn fit_colour(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
    ) -> Result<ColourModel, FailReason>;

    /// The largest n this fitter's own setting fits (the per-vertex order choice tries 1..=it);
    /// `None`: unknown, each vertex is fitted with the fitter's own setting.
    fn max_terms(&self) -> Option<usize> {
        None
    }

    /// The same fit without this fitter's approximations (distance bins, subsampling, a short
    /// iteration limit), which the fit report checks it against ([`super::check`]); `None`:
    /// nothing to check (exact already, or unknown).
    fn exact(&self) -> Option<Box<dyn Fitter>> {
        None
    }
}

/// The fitting engine's solver failures as the pipeline's reasons (the one mapping).
impl From<crate::fit::FitFailure> for FailReason {
    fn from(e: crate::fit::FitFailure) -> Self {
        use crate::fit::FitFailure;
        match e {
            FitFailure::TooFewSamples { .. } | FitFailure::TooFewDistances { .. } => {
                FailReason::TooFewSamples
            }
            FitFailure::NotConverged { .. } => FailReason::NotConverged,
            _ => FailReason::NonPhysical,
        }
    }
}

/// The fitting engine's Levenberg–Marquardt (`crate::fit`) as the pipeline's solver: Eq. 1 by
/// `fit_expsum`, the joint Eq. 3/5/9 fit by `aniso::fit_colour` with the same solver and
/// distance bins (as direction bins of the joint solve), [`JOINT_ITERATIONS`] times the
/// iteration limit (it solves for m times the parameters), every k-th row with `subsample = k`.
impl Fitter for crate::fit::FitOptions {
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason> {
        use crate::fit::{Terms, fit_expsum};
        let mut o;
        let opts = match terms {
            Some(n) if self.terms != Terms::Fixed(n) => {
                o = self.clone();
                o.terms = Terms::Fixed(n);
                o.start = None;
                &o
            }
            _ => self,
        };
        Ok(fit_expsum(r, s, opts)?.model)
    }

    fn fit_colour(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
    ) -> Result<ColourModel, FailReason> {
        use crate::fit::aniso::{AnisoOptions, fit_colour};
        let opts = AnisoOptions {
            terms: n,
            segments: m,
            shared: colour == ColourMode::Shared,
            solver: self.solver,
            max_iterations: self.max_iterations * if m > 1 { JOINT_ITERATIONS } else { 1 },
            bins: self.bins,
            direction_bins: self.bins,
            anchored,
        };
        let k = self.subsample.max(1);
        let sub;
        let rows = if k > 1 {
            sub = rows.every(k);
            &sub
        } else {
            rows
        };
        let [sr, sg, sb] = &rows.s;
        let fit = fit_colour(&rows.r, &rows.phi, [sr, sg, sb], &opts)?;
        if self.require_convergence && !fit.converged {
            return Err(FailReason::NotConverged);
        }
        Ok(fit.model)
    }

    fn max_terms(&self) -> Option<usize> {
        match self.terms {
            crate::fit::Terms::Fixed(n) => Some(n),
            crate::fit::Terms::Auto { max, .. } => Some(max),
        }
    }

    fn exact(&self) -> Option<Box<dyn Fitter>> {
        self.exact_counterpart()
            .map(|o| Box::new(o) as Box<dyn Fitter>)
    }
}

/// The joint fit at m > 1 segments may take this many times the isotropic fit's iterations.
pub const JOINT_ITERATIONS: usize = 4;

/// A light position's samples as rows of the joint fit: one row per observation (frame, x_o),
/// with its distance r, direction φ (NaN: none, at x_i) and the value of each channel (NaN: that
/// channel was not taken from this frame, or not usable there).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ColourRows {
    /// |x_o − x_i|, mm.
    pub r: Vec<f64>,
    /// Direction around x_i in the tangent frame (Eq. 3), radians; NaN = none.
    pub phi: Vec<f64>,
    /// s(x_i, x_o) per channel r, g, b; NaN = not observed.
    pub s: [Vec<f64>; 3],
}

impl ColourRows {
    /// The rows of a group's samples, in the order their observations first appear.
    pub fn of(data: &ChannelSamples) -> Self {
        Self::aligned(data).unwrap_or_else(|| Self::joined(data))
    }

    /// [`ColourRows::of`] for any group: observations joined by (frame, x_o).
    fn joined(data: &ChannelSamples) -> Self {
        let mut index: std::collections::HashMap<(u32, u32), usize> = Default::default();
        let mut rows = ColourRows::default();
        for (ch, d) in data.iter().enumerate() {
            for x in d {
                let i = *index.entry((x.frame, x.vertex)).or_insert_with(|| {
                    rows.r.push(x.r);
                    rows.phi.push(x.phi.unwrap_or(f64::NAN));
                    for s in rows.s.iter_mut() {
                        s.push(f64::NAN);
                    }
                    rows.r.len() - 1
                });
                rows.s[ch][i] = x.s;
            }
        }
        rows
    }

    /// [`ColourRows::of`] for the usual group, whose three channels hold the same observations
    /// in the same order, each once (channel 0's (frame, x_o) strictly increasing): the rows are
    /// channel 0's samples in their order with every channel's value, as the general path makes
    /// them, without its hash map (a few % of every fit round). `None` for any other group.
    fn aligned(data: &ChannelSamples) -> Option<Self> {
        let key = |x: &GroupSample| (x.frame, x.vertex);
        let first = &data[0];
        let increasing = first.windows(2).all(|w| key(&w[0]) < key(&w[1]));
        let same = |d: &Vec<GroupSample>| {
            d.len() == first.len() && d.iter().zip(first).all(|(a, b)| key(a) == key(b))
        };
        if !(increasing && same(&data[1]) && same(&data[2])) {
            return None;
        }
        Some(ColourRows {
            r: first.iter().map(|x| x.r).collect(),
            phi: first.iter().map(|x| x.phi.unwrap_or(f64::NAN)).collect(),
            s: data.each_ref().map(|d| d.iter().map(|x| x.s).collect()),
        })
    }

    /// Every k-th row.
    fn every(&self, k: usize) -> Self {
        let pick = |v: &Vec<f64>| v.iter().copied().step_by(k).collect::<Vec<f64>>();
        ColourRows {
            r: pick(&self.r),
            phi: pick(&self.phi),
            s: [pick(&self.s[0]), pick(&self.s[1]), pick(&self.s[2])],
        }
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.r.len()
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.r.is_empty()
    }
}

/// A fitter that fits at most `n` terms: its own setting (`terms = None`) means n. The order
/// choice ([`fit_order`]) wraps the run's fitter in it for each candidate n.
struct AtMost<'a> {
    inner: &'a dyn Fitter,
    n: usize,
}

impl Fitter for AtMost<'_> {
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason> {
        let n = terms.map_or(self.n, |t| t.min(self.n));
        self.inner.fit(r, s, Some(n))
    }

    fn fit_colour(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
    ) -> Result<ColourModel, FailReason> {
        self.inner
            .fit_colour(rows, n.min(self.n), m, colour, anchored)
    }

    fn max_terms(&self) -> Option<usize> {
        Some(self.n)
    }
}

/// Smallest total decay |d|·(r_max − r_min) of a supported term (see [`TermDropped`]).
pub const MIN_DECAY: f64 = 0.1;
/// Share c·e^{d·r} / R_d(r) above which a sample counts as supporting a term.
pub const MIN_SHARE: f64 = 0.05;
/// Distinct sampled distances a term needs as support (see [`TermDropped`]).
pub const MIN_SUPPORT: usize = 4;

/// How much faster than the isotropic fit's steepest term a direction segment's steepest term
/// may decay (Eq. 3): light travelling 4x less far across the veins than the isotropic mean is
/// far beyond the anisotropy of the materials in the paper (and of the simulator's, at most
/// 1 / (1 - 0.6) = 2.5 along against across).
pub const SEGMENT_MAX_RATE_RATIO: f64 = 4.0;

/// The first term of `f` the sample distances `r` do not support, if any.
pub fn unsupported_term(f: &ExpSum, r: &[f64]) -> Option<TermDropped> {
    Distances::of(r).unsupported_term(f)
}

/// A light position's sample distances as [`unsupported_term`] judges a fall-off's terms on
/// them: their range, and (taken at the first fall-off of two terms or more) the distinct
/// distances, sorted. Held so that the fits of one set of distances (every candidate order, the
/// refits with a term fewer, the shared colour's fit of all channels, whose distances are the
/// red ones three times) sort them once: the sort was a twentieth of a fit (issue 23).
pub(crate) struct Distances<'r> {
    r: &'r [f64],
    lo: f64,
    hi: f64,
    distinct: std::cell::OnceCell<Vec<f64>>,
}

impl<'r> Distances<'r> {
    pub(crate) fn of(r: &'r [f64]) -> Self {
        let (lo, hi) = r
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        Distances {
            r,
            lo,
            hi,
            distinct: std::cell::OnceCell::new(),
        }
    }

    /// Sorted, each run of distances within 1e-9 relative of its first kept once. Equal
    /// values under `total_cmp` are the same bits, so the unstable sort orders them as a stable
    /// one would; a value repeated anywhere (the three channels' copies of one distance) is
    /// removed like any duplicate, so r repeated gives the distinct values of r.
    fn distinct(&self) -> &[f64] {
        self.distinct.get_or_init(|| {
            let mut rs: Vec<f64> = self.r.to_vec();
            rs.sort_unstable_by(f64::total_cmp);
            rs.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * b.abs().max(1.0));
            rs
        })
    }

    /// [`unsupported_term`] of `f` on these distances.
    fn unsupported_term(&self, f: &ExpSum) -> Option<TermDropped> {
        let (lo, hi) = (self.lo, self.hi);
        if hi.partial_cmp(&lo).is_none_or(|o| o.is_lt()) {
            return None;
        }
        if f.terms.iter().any(|t| -t.d * (hi - lo) < MIN_DECAY) {
            return Some(TermDropped::NonDecaying);
        }
        if f.n() < 2 {
            return None;
        }
        let rs = self.distinct();
        let ln_min_share = MIN_SHARE.ln();
        // ln R_d at each distance once, not once per term, the terms' ln c_k taken once (the
        // same values).
        let ln_cs = f.ln_c();
        let ln_rd: Vec<f64> = rs.iter().map(|&x| f.ln_eval_with(&ln_cs, x)).collect();
        for (t, &ln_c) in f.terms.iter().zip(&ln_cs) {
            let support = rs
                .iter()
                .zip(&ln_rd)
                .filter(|&(&x, &l)| ln_c + t.d * x - l >= ln_min_share)
                .count();
            if support < MIN_SUPPORT {
                return Some(TermDropped::Unresolved);
            }
        }
        None
    }
}

/// Fits Eq. 1 and drops unsupported terms: while [`unsupported_term`] finds one, refit with one
/// term fewer. `dropped` collects why.
fn fit_supported(
    fitter: &dyn Fitter,
    r: &[f64],
    s: &[f64],
    terms: Option<usize>,
    dropped: &mut Vec<TermDropped>,
) -> Result<ExpSum, FailReason> {
    fit_supported_on(fitter, &Distances::of(r), s, terms, dropped)
}

/// [`fit_supported`] of the samples at `distances`.
fn fit_supported_on(
    fitter: &dyn Fitter,
    distances: &Distances,
    s: &[f64],
    terms: Option<usize>,
    dropped: &mut Vec<TermDropped>,
) -> Result<ExpSum, FailReason> {
    let r = distances.r;
    let mut f = fitter.fit(r, s, terms)?;
    loop {
        match distances.unsupported_term(&f) {
            None => return Ok(f),
            Some(why) => {
                if f.n() <= 1 {
                    return Err(FailReason::NonPhysical);
                }
                dropped.push(why);
                f = fitter.fit(r, s, Some(f.n() - 1))?;
            }
        }
    }
}

/// Fits every sample set with one common order: the first set chooses n (as `terms` says, with
/// unsupported terms dropped), the others are fitted with n, and n is lowered until every set
/// supports all its terms.
pub(crate) fn fit_common_order(
    fitter: &dyn Fitter,
    sets: &[(Vec<f64>, Vec<f64>)],
    terms: Option<usize>,
    dropped: &mut Vec<TermDropped>,
) -> Result<Vec<ExpSum>, FailReason> {
    let (r0, s0) = sets.first().ok_or(FailReason::TooFewSamples)?;
    let first = fit_supported(fitter, r0, s0, terms, dropped)?;
    let mut n = first.n();
    let mut out = vec![first];
    'order: loop {
        out.truncate(1);
        for (r, s) in &sets[1..] {
            let f = fit_supported(fitter, r, s, Some(n), dropped)?;
            if f.n() < n {
                n = f.n();
                out[0] = fit_supported(fitter, r0, s0, Some(n), dropped)?;
                if out[0].n() < n {
                    n = out[0].n();
                }
                continue 'order;
            }
            out.push(f);
        }
        return Ok(out);
    }
}

/// The joint fit's direction segments (bit l = segment l) that are implausible beside the
/// isotropic fit `iso` of the same samples: a segment whose steepest term decays more than
/// [`SEGMENT_MAX_RATE_RATIO`] times faster than the isotropic fit's steepest one. Such a segment
/// is not a direction effect but a term fitted to a handful of near samples, and its slope at
/// r_min makes the continuation below r_min (the model's support rule) explode towards r = 0.
/// (A segment's slowest term may decay little over the sampled distances: the joint fit shares
/// every sample between two segments, and beyond r_max prediction moves to the baseline.)
fn implausible_segments(model: &ColourModel, iso: &ColourModel) -> u64 {
    let steepest = |f: &ExpSum| f.terms.iter().map(|t| -t.d).fold(0.0, f64::max);
    let mut mask = 0u64;
    for (a, i) in falloffs(model).into_iter().zip(falloffs(iso)) {
        let limit = SEGMENT_MAX_RATE_RATIO * i.segments.iter().map(steepest).fold(0.0, f64::max);
        for (l, f) in a.segments.iter().enumerate() {
            if steepest(f) > limit {
                mask |= 1 << l;
            }
        }
    }
    mask
}

/// The fall-offs of a colour model: the shared one, or one per channel.
fn falloffs(m: &ColourModel) -> Vec<&Anisotropic> {
    match m {
        ColourModel::PerChannel { channels } => channels.iter().collect(),
        ColourModel::Shared { falloff, .. } => vec![falloff],
    }
}

/// `model`'s one segment repeated m times: the isotropic model as an m-segment one (identical
/// under the hat weights, which sum to 1).
fn repeat_segments(model: ColourModel, m: usize) -> ColourModel {
    let rep = |a: Anisotropic| Anisotropic {
        segments: vec![a.segments[0].clone(); m],
    };
    match model {
        ColourModel::PerChannel { channels } => ColourModel::PerChannel {
            channels: channels.map(rep),
        },
        ColourModel::Shared { falloff, s_g, s_b } => ColourModel::Shared {
            falloff: rep(falloff),
            s_g,
            s_b,
        },
    }
}

/// Fits one light position's samples with n terms and m direction segments: THE Eq. 3/5/9 fit
/// (the joint fit with the hat weights evaluation and rendering use, `Fitter::fit_colour`).
/// The model is validated. A direction segment with fewer samples of its own than n terms need
/// is held at the isotropic fit of all samples (`aniso::ANCHOR_WEIGHT`); the fit fails
/// (`TooFewSamples`) when no segment has enough.
pub fn fit_at(
    data: &ChannelSamples,
    colour: ColourMode,
    n: usize,
    m: usize,
    fitter: &dyn Fitter,
) -> Result<ColourModel, FailReason> {
    fit_anchored(data, colour, n, m, 0, fitter)
}

/// [`fit_at`] with the segments of the bit mask `anchored` held at the isotropic fit.
fn fit_anchored(
    data: &ChannelSamples,
    colour: ColourMode,
    n: usize,
    m: usize,
    anchored: u64,
    fitter: &dyn Fitter,
) -> Result<ColourModel, FailReason> {
    let model = fitter.fit_colour(&ColourRows::of(data), n, m.max(1), colour, anchored)?;
    model.validate().map_err(|_| FailReason::NonPhysical)?;
    Ok(model)
}

/// The isotropic model whose fits choose the order n ("model only what the scene requires":
/// terms the samples do not support are dropped, see [`unsupported_term`]). Per channel: one
/// common order for the three channels. Shared (Eq. 9): the red fall-off chooses n, then one
/// fall-off is fitted to all channels divided by their scales (block coordinate descent on the
/// log objective, exact on noise-free data).
fn isotropic_order(
    data: &ChannelSamples,
    colour: ColourMode,
    fitter: &dyn Fitter,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize), FailReason> {
    let rs = |c: usize| -> (Vec<f64>, Vec<f64>) { data[c].iter().map(|x| (x.r, x.s)).unzip() };
    let one = |f: ExpSum| Anisotropic { segments: vec![f] };
    let model = match colour {
        ColourMode::PerChannel => {
            let sets: Vec<(Vec<f64>, Vec<f64>)> = (0..3).map(rs).collect();
            let isos = fit_common_order(fitter, &sets, None, dropped)?;
            let channels: [Anisotropic; 3] = isos
                .into_iter()
                .map(one)
                .collect::<Vec<_>>()
                .try_into()
                .map_err(|_| FailReason::NonPhysical)?;
            ColourModel::PerChannel { channels }
        }
        ColourMode::Shared => {
            let (r, s) = rs(0);
            let red_distances = Distances::of(&r);
            let red = fit_supported_on(fitter, &red_distances, &s, None, dropped)?;
            let scales = |f: &ExpSum| -> Result<[f64; 3], FailReason> {
                let ln_c = f.ln_c();
                let mut out = [1.0; 3];
                for (c, o) in out.iter_mut().enumerate().skip(1) {
                    let d = &data[c];
                    if d.is_empty() {
                        return Err(FailReason::TooFewSamples);
                    }
                    let mean = d
                        .iter()
                        .map(|x| x.s.ln() - f.ln_eval_with(&ln_c, x.r))
                        .sum::<f64>()
                        / d.len() as f64;
                    *o = mean.exp();
                }
                if out.iter().all(|v| v.is_finite() && *v > 0.0) {
                    Ok(out)
                } else {
                    Err(FailReason::NonPhysical)
                }
            };
            let sc = scales(&red)?;
            let (r_all, s): (Vec<f64>, Vec<f64>) = (0..3)
                .flat_map(|c| data[c].iter().map(move |x| (x.r, x.s / sc[c])))
                .unzip();
            // The usual group holds every channel at the red distances: all its distances are
            // the red ones three times, whose range and distinct values are the red ones.
            let red_thrice = data[1..].iter().all(|d| {
                d.len() == r.len() && d.iter().zip(&r).all(|(x, r)| x.r.to_bits() == r.to_bits())
            });
            let all_distances = if red_thrice {
                Distances {
                    r: &r_all,
                    ..red_distances
                }
            } else {
                Distances::of(&r_all)
            };
            let iso = fit_supported_on(fitter, &all_distances, &s, Some(red.n()), dropped)?;
            let sc = scales(&iso)?;
            ColourModel::Shared {
                falloff: one(iso),
                s_g: sc[1],
                s_b: sc[2],
            }
        }
    };
    model.validate().map_err(|_| FailReason::NonPhysical)?;
    let n = falloffs(&model)[0].segments[0].n();
    Ok((model, n))
}

/// How a light position's model was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FitPath {
    /// The joint fit at (n, m).
    Joint,
    /// Isotropic (all m segments equal): the joint fit at m failed (no segment with samples of
    /// its own, or the solve did not converge) or was implausible ([`implausible_segments`]).
    Isotropic,
}

/// A light position's model: the order n from the isotropic fits ([`isotropic_order`]), then the
/// joint fit at (n, m) ([`fit_at`]). Where that fails or is implausible the light position keeps
/// an isotropic model (the joint fit at (n, 1), else the order-choosing fit) with its segments
/// repeated, so no light position loses the model the isotropic fit gave it.
fn fit_samples(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize, FitPath), FailReason> {
    let (iso, n) = isotropic_order(data, choice.colour, fitter, dropped)?;
    let m = choice.segments.max(1);
    // Segments the joint fit made implausible are held at the isotropic fit and the rest
    // refitted, once.
    let mut joint = fit_at(data, choice.colour, n, m, fitter);
    if m > 1
        && let Ok(model) = &joint
    {
        let bad = implausible_segments(model, &iso);
        if bad != 0 {
            joint = fit_anchored(data, choice.colour, n, m, bad, fitter);
        }
    }
    if let Ok(model) = joint
        && (m == 1 || implausible_segments(&model, &iso) == 0)
    {
        return Ok((model, n, FitPath::Joint));
    }
    let one = if m > 1 {
        fit_at(data, choice.colour, n, 1, fitter).unwrap_or(iso)
    } else {
        iso
    };
    Ok((repeat_segments(one, m), n, FitPath::Isotropic))
}

/// "Model only what the scene requires", per light position: fits one group's samples at every
/// candidate (n, m) — n = 1..=`max_terms`, m from [`crate::order::segment_ladder`] up to
/// `choice.segments` — with [`fit_samples`], and keeps the one [`crate::order::choose`] picks
/// (AICc on the log residuals; fewer samples, smaller models). `at = Some((n, m))` fits that
/// order only (later alpha rounds keep the order round 0 chose); `rule = None` or an unknown
/// maximum n fits the fixed order (every vertex at the maximum). Returns the model, n, m,
/// whether it is the baseline and how it was fitted; `dropped` gets the chosen fit's dropped terms.
///
/// The smallest candidate is the homogeneous `baseline`'s fall-off with only the channel scales
/// fitted ([`scaled_baseline`], 3 parameters): where a light position's samples do not show
/// that their own curve differs from the whole object's, the object's is kept (measured on a
/// sparse simulated torus, turntable angles held out: without it, the per-vertex models
/// predicted worse than the baseline alone). The other candidates depend on the samples alone:
/// with `cache`, they are taken from (or fitted into) the run's [`OrderCache`].
#[allow(clippy::too_many_arguments)]
fn fit_order(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    rule: Option<crate::order::OrderRule>,
    baseline: Option<&ColourModel>,
    at: Option<(usize, usize, bool)>,
    cache: Option<(&OrderCache, &OrderKey)>,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize, usize, bool, FitPath), FailReason> {
    if let Some((n, m, on_baseline)) = at {
        if on_baseline && let Some(b) = baseline.and_then(|b| scaled_baseline(b, data)) {
            return Ok((b, n, 1, true, FitPath::Joint));
        }
        return fit_candidate(data, choice, fitter, Some(n), m, dropped);
    }
    let (Some(rule), Some(max_n)) = (rule, fitter.max_terms()) else {
        return fit_candidate(data, choice, fitter, None, choice.segments, dropped);
    };
    let found = match cache {
        Some((cache, key)) => {
            cache.get_or_fit(key, || order_candidates(data, choice, fitter, max_n))
        }
        None => std::sync::Arc::new(order_candidates(data, choice, fitter, max_n)),
    };
    let found = found.as_ref().as_ref().map_err(|e| *e)?;
    let mut cands = found.cands.clone();
    let base = baseline.and_then(|b| scaled_baseline(b, data));
    let base_terms = base.as_ref().and_then(|b| params_of(b).ok()).map(|p| p.1);
    let samples = found.samples;
    if let (Some(b), Some(n)) = (&base, base_terms) {
        cands.push(crate::order::Candidate {
            terms: n,
            segments: 1,
            params: 3,
            samples,
            rss: sq_err(b, data),
        });
    }
    let on_baseline = |i: usize| base_terms.is_some() && i + 1 == cands.len();
    match crate::order::choose(&cands, rule) {
        Some(c) if on_baseline(c.index) => {
            let b = base.ok_or(FailReason::NonPhysical)?;
            Ok((b, c.terms, c.segments, true, FitPath::Joint))
        }
        Some(c) => {
            let (model, d, path) = found.fits[c.index].clone();
            dropped.extend(d);
            Ok((model, c.terms, c.segments, false, path))
        }
        None => Err(found.first_err.unwrap_or(FailReason::TooFewSamples)),
    }
}

/// One light position's fit at n terms (`None`: the fitter's own setting) and m segments
/// ([`fit_samples`]): the model, n, m, `false` (not the baseline) and how it was fitted.
fn fit_candidate(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    n: Option<usize>,
    m: usize,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize, usize, bool, FitPath), FailReason> {
    let c = ModelChoice {
        segments: m,
        ..*choice
    };
    match n {
        Some(n) => fit_samples(data, &c, &AtMost { inner: fitter, n }, dropped),
        None => fit_samples(data, &c, fitter, dropped),
    }
    .map(|(model, n, path)| (model, n, m, false, path))
}

/// Round 0's candidates of one light position ([`fit_order`]): its fits at every (n, m) but the
/// baseline's, which depend on its samples alone.
#[derive(Debug)]
struct Candidates {
    /// Every candidate fitted, as the order rule scores it.
    cands: Vec<crate::order::Candidate>,
    /// Per candidate: its model, the terms its fit dropped and how it was fitted.
    fits: Vec<(ColourModel, Vec<TermDropped>, FitPath)>,
    /// Why the first candidate that failed did.
    first_err: Option<FailReason>,
    /// Positive finite samples N (AICc's).
    samples: usize,
}

/// Fits every candidate (n, m) of [`fit_order`]: n = 1..=`max_n`, m up to `choice.segments`.
/// `Err(TooFewSamples)` when the light position has too few samples for the largest isotropic
/// model.
fn order_candidates(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    max_n: usize,
) -> Result<Candidates, FailReason> {
    let samples = data
        .iter()
        .flatten()
        .filter(|x| x.s > 0.0 && x.s.is_finite())
        .count();
    let mut cands: Vec<crate::order::Candidate> = Vec::new();
    let mut fits: Vec<(ColourModel, Vec<TermDropped>, FitPath)> = Vec::new();
    let mut first_err = None;
    for m in crate::order::segment_ladder(choice.segments) {
        for n in 1..=max_n.max(1) {
            let mut d = Vec::new();
            match fit_candidate(data, choice, fitter, Some(n), m, &mut d) {
                Ok((model, n, m, _, path)) => {
                    // A candidate whose unsupported terms were dropped repeats a smaller one.
                    if cands.iter().any(|c| c.terms == n && c.segments == m) {
                        continue;
                    }
                    let Ok((params, _, _)) = params_of(&model) else {
                        continue;
                    };
                    cands.push(crate::order::Candidate {
                        terms: n,
                        segments: m,
                        params: params.len(),
                        samples,
                        rss: sq_err(&model, data),
                    });
                    fits.push((model, d, path));
                }
                // A light position with too few samples for the largest model fails as with
                // the fixed order and is interpolated from its neighbours: its own fit of
                // fewer terms predicts the frames it never saw worse, by the fit's own
                // cross-validation on the training frames (sample-torus, 5 folds of whole
                // turntable angles, mean log E r/g/b: 0.702/0.683/0.700 against
                // 0.693/0.674/0.691 with them interpolated; BENCHMARKS, issue 24).
                Err(FailReason::TooFewSamples) if m == 1 && n == max_n => {
                    return Err(FailReason::TooFewSamples);
                }
                Err(e) => {
                    first_err.get_or_insert(e);
                }
            }
        }
    }
    Ok(Candidates {
        cands,
        fits,
        first_err,
        samples,
    })
}

/// Which light position, in which model, a [`Candidates`] belongs to: its frames and anchors as
/// dataset frame numbers (a fold's registered-frame indices differ from the whole scan's), the
/// colour mode and the segments.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct OrderKey {
    frames: [Vec<usize>; 3],
    anchors: [usize; 3],
    colour: ColourMode,
    segments: usize,
}

impl OrderKey {
    fn of(choice: &ModelChoice, regs: &[RegisteredFrame], key: &super::select::GroupKey) -> Self {
        let frame = |l: &u32| regs.get(*l as usize).map_or(usize::MAX, |r| r.frame);
        OrderKey {
            frames: key.frames.each_ref().map(|f| f.iter().map(frame).collect()),
            anchors: key.anchors.each_ref().map(frame),
            colour: choice.colour,
            segments: choice.segments,
        }
    }
}

/// Round 0's candidate fits ([`Candidates`]), shared by the fits of one
/// [`crate::crossval::fit_scan_in`]: the cross-validation's fold fits and the final fit. A
/// light position's samples are those of its frames, whatever other frames a fit holds, so a
/// fold whose training frames hold all of them fits the very same candidates, bit for bit, as
/// the fit on every frame; they are fitted once ([`OrderCache::fill`]) instead of once per fold
/// and once more at the end. Only round 0 is shared: later rounds divide by the fold's own alpha.
/// The candidates depend on the fitter and the model choice too: a cache serves one fitter.
#[derive(Debug, Default)]
pub struct OrderCache {
    found: std::sync::Mutex<
        std::collections::HashMap<OrderKey, std::sync::Arc<Result<Candidates, FailReason>>>,
    >,
    hits: std::sync::atomic::AtomicUsize,
    fitted: std::sync::atomic::AtomicUsize,
}

impl OrderCache {
    /// The candidates of `key`, fitted by `fit` unless known.
    fn get_or_fit(
        &self,
        key: &OrderKey,
        fit: impl FnOnce() -> Result<Candidates, FailReason>,
    ) -> std::sync::Arc<Result<Candidates, FailReason>> {
        use std::sync::atomic::Ordering::Relaxed;
        let known = self
            .found
            .lock()
            .ok()
            .and_then(|m| m.get(key).map(std::sync::Arc::clone));
        if let Some(c) = known {
            self.hits.fetch_add(1, Relaxed);
            return c;
        }
        let c = std::sync::Arc::new(fit());
        self.fitted.fetch_add(1, Relaxed);
        if let Ok(mut m) = self.found.lock() {
            m.entry(key.clone())
                .or_insert_with(|| std::sync::Arc::clone(&c));
        }
        c
    }

    /// Fits the candidates of every group of a selection (`regs`, `groups`: the fit on every
    /// frame) with the run's model choice, the groups in parallel, before the folds start, so
    /// that the folds, running side by side, find them instead of fitting them each.
    pub fn fill(
        &self,
        ctx: &Context,
        regs: &[RegisteredFrame],
        groups: &Groups,
        fitter: &dyn Fitter,
        progress: &dyn Progress,
    ) {
        let (Some(_), Some(max_n)) = (ctx.opts.order, fitter.max_terms()) else {
            return;
        };
        let choice = &ctx.opts.model;
        progress.start("fit (round 1 candidates)", groups.keys.len() as u64);
        groups.keys.par_iter().for_each(|key| {
            let k = OrderKey::of(choice, regs, key);
            if let Ok((data, _)) = group_samples(ctx, regs, key) {
                self.get_or_fit(&k, || order_candidates(&data, choice, fitter, max_n));
            }
            progress.inc(1);
        });
    }

    /// Light positions whose candidates were fitted, and lookups that found them fitted.
    pub fn counts(&self) -> (usize, usize) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.fitted.load(Relaxed), self.hits.load(Relaxed))
    }
}

/// The baseline's fall-off with the channel scales of a light position's samples: per channel,
/// the mean of ln s − ln R_d (the least-squares scale of the log objective). `None` without
/// samples in a channel or if the result is not a valid model.
fn scaled_baseline(base: &ColourModel, data: &ChannelSamples) -> Option<ColourModel> {
    let mut a = [0.0; 3];
    let ev = base.ln_evaluator();
    for (c, d) in data.iter().enumerate() {
        let v: Vec<f64> = d
            .iter()
            .map(|x| x.s.ln() - ev.ln_eval_channel(c, x.r, x.phi))
            .filter(|v| v.is_finite())
            .collect();
        if v.is_empty() {
            return None;
        }
        a[c] = v.iter().sum::<f64>() / v.len() as f64;
    }
    let scale = |f: &Anisotropic, k: f64| Anisotropic {
        segments: f.segments.iter().map(|e| e.scaled(k.exp())).collect(),
    };
    let m = match base {
        ColourModel::Shared { falloff, s_g, s_b } => ColourModel::Shared {
            falloff: scale(falloff, a[0]),
            s_g: s_g * (a[1] - a[0]).exp(),
            s_b: s_b * (a[2] - a[0]).exp(),
        },
        ColourModel::PerChannel { channels } => ColourModel::PerChannel {
            channels: [
                scale(&channels[0], a[0]),
                scale(&channels[1], a[1]),
                scale(&channels[2], a[2]),
            ],
        },
    };
    m.validate().ok().map(|_| m)
}

/// One group's model.
#[derive(Debug, Clone)]
pub struct GroupFit {
    /// The model (validated).
    pub model: ColourModel,
    /// Its order n.
    pub terms: usize,
    /// Its direction segments m (chosen per light position, at most the run's).
    pub segments: usize,
    /// The model is the baseline's fall-off with this light position's channel scales.
    pub on_baseline: bool,
    /// Sampled distance range `[r_min, r_max]` of the fit.
    pub r_range: [f64; 2],
    /// The joint fit at m > 1 segments failed or was implausible, so the model is isotropic
    /// (its m segments equal).
    pub isotropic_fallback: bool,
    /// Per channel, the brightest sample as captured (before any division by alpha): the
    /// reference of Eq. 6's t1 ([`crate::model::IntensityWindow::for_light`]), kept so the
    /// lattice pass ([`super::lattice`]) uses this light position's very window.
    pub s_max: [f64; 3],
}

/// What the fit stage produced.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// Per group (in [`Groups`] order): its model, or why it has none.
    pub fits: Vec<Result<GroupFit, FailReason>>,
    /// alpha(x_o) per vertex and channel (Eq. 6), from the last round.
    pub alpha: Vec<[f64; 3]>,
    /// Where alpha came from, and how the rounds ended.
    pub alpha_report: AlphaReport,
    /// Samples of the last round.
    pub counts: SampleCounts,
    /// Terms dropped in the last round, by reason.
    pub dropped: BTreeMap<TermDropped, usize>,
    /// The homogeneous baseline, if its fit succeeded.
    pub baseline: Option<FittedBaseline>,
}

/// Most parallel tasks a fit round folds the light positions in ([`fit_groups`]): each holds
/// its own alpha accumulators (one per vertex and channel), so their number bounds the memory
/// (32 × 72 bytes per vertex), and it depends on the scan alone, never on the thread count.
const FOLD_CHUNKS: usize = 32;

/// Per vertex and channel, the sufficient statistics of the training objective over the
/// vertex's samples: with e = ln R_d − ln s (s as captured), the vertex's share of
/// O(R_d, alpha) = Σ (ln alpha + e)^2 is n·ln²alpha + 2·ln alpha·Σe + Σe² for *any* alpha. So the
/// objective of a round's fits under the alpha Eq. 6 then derives from them (the model the round
/// leaves) is known without another pass over the samples.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct ObjectiveStats {
    n: f64,
    sum: f64,
    sum_sq: f64,
}

impl ObjectiveStats {
    fn add(&mut self, e: f64) {
        if e.is_finite() {
            self.n += 1.0;
            self.sum += e;
            self.sum_sq += e * e;
        }
    }

    fn merge(&mut self, o: &ObjectiveStats) {
        self.n += o.n;
        self.sum += o.sum;
        self.sum_sq += o.sum_sq;
    }

    /// Σ (ln alpha + e)^2 at `ln_alpha`.
    fn at(&self, ln_alpha: f64) -> f64 {
        (self.n * ln_alpha * ln_alpha + 2.0 * ln_alpha * self.sum + self.sum_sq).max(0.0)
    }
}

/// One round's results, folded over the groups in parallel.
///
/// A chunk of groups folds its Eq. 6 accumulators sparsely, one slot per vertex its samples
/// reach (`slots`, `vertices`); the merged state is dense, one entry per mesh vertex. Why:
/// dense per-chunk arrays cost the chunks × the vertices (32 × 144 bytes × 655,362 vertices,
/// 3 GB, on sample-pebble's mesh subdivided to scanner density, issue 40) for samples that
/// reach a few thousand vertices each. The sums are added in the same order as before.
#[derive(Default)]
struct RoundState {
    fits: Vec<(usize, Result<GroupFit, FailReason>)>,
    /// Whether a group of this state has a fit (the dense arrays exist once one has).
    any: bool,
    /// Sparse (a chunk): vertex → slot of `alpha` and `objective_stats`.
    slots: HashMap<u32, u32>,
    /// Sparse (a chunk): the vertex of each slot, in the order first reached.
    vertices: Vec<u32>,
    alpha: Vec<[AlphaAccumulator; 3]>,
    /// Per vertex and channel, the objective's statistics of this round's fits.
    objective_stats: Vec<[ObjectiveStats; 3]>,
    counts: SampleCounts,
    dropped: BTreeMap<TermDropped, usize>,
    /// Training objective of this round's fits against the alpha they were fitted to.
    objective: f64,
    /// Groups that kept their previous fit.
    kept_previous: usize,
}

impl RoundState {
    /// A chunk's slot for vertex `v` (sparse), made on first use.
    fn slot(&mut self, v: u32) -> usize {
        if let Some(&i) = self.slots.get(&v) {
            return i as usize;
        }
        let i = self.vertices.len();
        self.slots.insert(v, i as u32);
        self.vertices.push(v);
        self.alpha.push([AlphaAccumulator::default(); 3]);
        self.objective_stats.push([ObjectiveStats::default(); 3]);
        i
    }

    /// `other`, a sparse chunk, merged into this dense state of `nv` vertices.
    fn merge_chunk(mut self, mut other: RoundState, nv: usize) -> RoundState {
        self.fits.append(&mut other.fits);
        if other.any {
            if !self.any {
                self.alpha = vec![[AlphaAccumulator::default(); 3]; nv];
                self.objective_stats = vec![[ObjectiveStats::default(); 3]; nv];
                self.any = true;
            }
            for (i, &v) in other.vertices.iter().enumerate() {
                let v = v as usize;
                for c in 0..3 {
                    self.alpha[v][c].merge(&other.alpha[i][c]);
                    self.objective_stats[v][c].merge(&other.objective_stats[i][c]);
                }
            }
        }
        self.counts.add(&other.counts);
        self.objective += other.objective;
        self.kept_previous += other.kept_previous;
        for (k, v) in other.dropped {
            *self.dropped.entry(k).or_default() += v;
        }
        self
    }

    /// The training objective of this round's fits with alpha `alpha` per vertex and channel.
    fn objective_with(&self, alpha: &[[f64; 3]]) -> f64 {
        self.objective_stats
            .iter()
            .zip(alpha)
            .map(|(st, a)| (0..3).map(|c| st[c].at(a[c].ln())).sum::<f64>())
            .sum()
    }

    /// The fits by group index (`None`: the group has none).
    fn by_index(&self, groups: usize) -> Vec<Option<GroupFit>> {
        let mut v: Vec<Option<GroupFit>> = vec![None; groups];
        for (idx, f) in &self.fits {
            if let Ok(g) = f {
                v[*idx] = Some(g.clone());
            }
        }
        v
    }
}

/// Sum over a group's (alpha-divided) samples of (ln R_d − ln s)^2: its share of the training
/// objective.
fn sq_err(m: &ColourModel, data: &ChannelSamples) -> f64 {
    sq_err_at(&ln_rd_at(m, data), &ln_s_of(data))
}

/// ln s of each of a group's samples, per channel (their order).
fn ln_s_of(data: &ChannelSamples) -> [Vec<f64>; 3] {
    data.each_ref()
        .map(|d| d.iter().map(|x| x.s.ln()).collect())
}

/// ln R_d of a model at each of a group's samples, per channel (their order).
fn ln_rd_at(m: &ColourModel, data: &ChannelSamples) -> [Vec<f64>; 3] {
    ln_rd_with(&m.ln_evaluator(), data, true)
}

/// [`ln_rd_at`] with the model's evaluator. With shared colour (Eq. 5) a sample of channel 1 or
/// 2 at the very (r, φ) of the red sample at its index (the usual case: a frame measures its
/// channels at the same pixels) takes the red fall-off's value plus its channel's ln s_c
/// ([`crate::model::LnEvaluator::shared_offset`]): the same bits, one evaluation instead of
/// three. `directions = false` evaluates every sample without its direction (φ = `None`, as
/// the isotropic baseline is judged).
pub(super) fn ln_rd_with(
    ev: &crate::model::LnEvaluator,
    data: &ChannelSamples,
    directions: bool,
) -> [Vec<f64>; 3] {
    let phi = |x: &GroupSample| if directions { x.phi } else { None };
    let red: Vec<f64> = data[0]
        .iter()
        .map(|x| ev.ln_eval_channel(0, x.r, phi(x)))
        .collect();
    let same = |a: &GroupSample, b: &GroupSample| {
        a.r.to_bits() == b.r.to_bits() && phi(a).map(f64::to_bits) == phi(b).map(f64::to_bits)
    };
    let other = |ch: usize| -> Vec<f64> {
        let offset = ev.shared_offset(ch);
        data[ch]
            .iter()
            .enumerate()
            .map(|(j, x)| match (offset, data[0].get(j)) {
                (Some(k), Some(y)) if same(x, y) => red[j] + k,
                _ => ev.ln_eval_channel(ch, x.r, phi(x)),
            })
            .collect()
    };
    let (g, b) = (other(1), other(2));
    [red, g, b]
}

/// [`sq_err`] from a model's ln R_d at the samples ([`ln_rd_at`]) and their ln s
/// ([`ln_s_of`]), for a caller that reuses either (a round's old and new fits, Eq. 6).
fn sq_err_at(ln_rd: &[Vec<f64>; 3], ln_s: &[Vec<f64>; 3]) -> f64 {
    let mut o = 0.0;
    for (l, s) in ln_rd.iter().zip(ln_s) {
        for (a, b) in l.iter().zip(s) {
            let e = a - b;
            if e.is_finite() {
                o += e * e;
            }
        }
    }
    o
}

/// What one fit round needs: the run, its selection, the solver and the baseline.
struct RoundRunner<'r, 'a> {
    ctx: &'r Context<'a>,
    regs: &'r [RegisteredFrame],
    groups: &'r Groups,
    fitter: &'r dyn Fitter,
    progress: &'r dyn Progress,
    base_model: Option<ColourModel>,
    /// Round 0's candidates shared with other fits of the same run ([`OrderCache`]).
    cache: Option<&'r OrderCache>,
}

impl RoundRunner<'_, '_> {
    /// One fit round: every group fitted to its samples divided by `alpha_div` (none: as
    /// captured), at the order of its previous fit `prev` when there is one (round 0 chooses
    /// it), keeping the previous fit where the new one is worse against the same alpha; the
    /// Eq. 6 accumulators and the objective's statistics of the fits, per vertex.
    fn run(
        &self,
        alpha_div: Option<&[[f64; 3]]>,
        round: usize,
        prev: Option<&[Option<GroupFit>]>,
    ) -> RoundState {
        let (ctx, regs, groups, fitter) = (self.ctx, self.regs, self.groups, self.fitter);
        let opts = &ctx.opts;
        let nv = ctx.ds.mesh.positions.len();
        let base_model = self.base_model.as_ref();
        self.progress.start(
            &format!("fit (round {})", round + 1),
            groups.keys.len() as u64,
        );
        // Groups are folded in fixed chunks, sequentially within a chunk, and the chunks merged
        // in order: the float sums (alpha, objective) then associate the same way on every
        // run and with any number of threads, so a fit is repeatable bit for bit (rayon's
        // `fold` splits where work stealing happens to, and later alpha rounds would inherit
        // the rounding differences).
        let step = |mut st: RoundState, (idx, key): (usize, &super::select::GroupKey)| {
            let mut dropped = Vec::new();
            let old = prev.and_then(|p| p.get(idx).cloned().flatten());
            let out = group_samples(ctx, regs, key).and_then(|(mut data, counts)| {
                let s_max = data
                    .each_ref()
                    .map(|d| d.iter().map(|x| x.s).fold(0.0, f64::max));
                if let Some(a) = alpha_div {
                    for (ch, d) in data.iter_mut().enumerate() {
                        for x in d.iter_mut() {
                            x.s /= a[x.vertex as usize][ch];
                        }
                    }
                }
                // Round 0 chooses each light position's order; later rounds keep it.
                let at = old.as_ref().map(|g| (g.terms, g.segments, g.on_baseline));
                let order_key = self
                    .cache
                    .map(|c| (c, OrderKey::of(&opts.model, regs, key)));
                let new = fit_order(
                    &data,
                    &opts.model,
                    fitter,
                    opts.order,
                    base_model,
                    at,
                    order_key.as_ref().map(|(c, k)| (*c, k)),
                    &mut dropped,
                )
                .map(|(model, terms, segments, on_baseline, path)| {
                    let r_range = data
                        .iter()
                        .flatten()
                        .fold([f64::INFINITY, 0.0], |[lo, hi], x| {
                            [lo.min(x.r), hi.max(x.r)]
                        });
                    GroupFit {
                        model,
                        terms,
                        segments,
                        on_baseline,
                        r_range,
                        isotropic_fallback: path == FitPath::Isotropic,
                        s_max,
                    }
                });
                // The old and new fits are scored on the same samples, and the one kept feeds
                // Eq. 6 below: each model's ln R_d and each sample's ln s are taken once.
                let ln_s = ln_s_of(&data);
                let scored = |m: &ColourModel| {
                    let ln_rd = ln_rd_at(m, &data);
                    let o = sq_err_at(&ln_rd, &ln_s);
                    (ln_rd, o)
                };
                let o_old = old.as_ref().map(|g| scored(&g.model));
                let (g, ln_rd, o_new, kept_old) = match (new, old, o_old) {
                    (Ok(g), Some(old), Some((lo, oo))) => {
                        let (ln, on) = scored(&g.model);
                        if on <= oo {
                            (g, ln, on, false)
                        } else {
                            (old, lo, oo, true)
                        }
                    }
                    (Err(_), Some(old), Some((lo, oo))) => (old, lo, oo, true),
                    (Ok(g), _, _) => {
                        let (ln, on) = scored(&g.model);
                        (g, ln, on, false)
                    }
                    (Err(e), _, _) => return Err(e),
                };
                Ok((g, data, counts, o_new, kept_old, ln_rd, ln_s))
            });
            for why in dropped {
                *st.dropped.entry(why).or_default() += 1;
            }
            match out {
                Ok((g, data, counts, o_new, kept_old, ln_rd, ln_s)) => {
                    st.objective += o_new;
                    st.kept_previous += kept_old as usize;
                    // Eq. 6 contributions are folded right away so the samples can be dropped.
                    st.any = true;
                    for (ch, d) in data.iter().enumerate() {
                        // Eq. 6 compares the captured sample with R_d.
                        let captured = |x: &GroupSample| {
                            alpha_div.map_or(x.s, |a| x.s * a[x.vertex as usize][ch])
                        };
                        // t1 relative to this light position's brightest sample.
                        let s_max = d.iter().map(captured).fold(0.0, f64::max);
                        let window = opts.alpha_window.for_light(s_max);
                        for ((x, &ln_rd), &ln_s) in d.iter().zip(&ln_rd[ch]).zip(&ln_s[ch]) {
                            let s = captured(x);
                            // As captured (round 0) s is the sample itself, its log known.
                            let ln_s = if alpha_div.is_some() { s.ln() } else { ln_s };
                            if let Some(v) =
                                AlphaAccumulator::ln_ratio_with(s, ln_s, ln_rd, &window)
                            {
                                let i = st.slot(x.vertex);
                                st.alpha[i][ch].add_ratio(v);
                            }
                            let i = st.slot(x.vertex);
                            st.objective_stats[i][ch].add(ln_rd - ln_s);
                        }
                    }
                    st.counts.add(&counts);
                    st.fits.push((idx, Ok(g)));
                }
                Err(e) => st.fits.push((idx, Err(e))),
            }
            self.progress.inc(1);
            st
        };
        let chunk = groups.keys.len().div_ceil(FOLD_CHUNKS).max(1);
        let mut state = groups
            .keys
            .par_chunks(chunk)
            .enumerate()
            .map(|(c, keys)| {
                keys.iter()
                    .enumerate()
                    .fold(RoundState::default(), |st, (j, key)| {
                        step(st, (c * chunk + j, key))
                    })
            })
            .collect::<Vec<_>>()
            .into_iter()
            .fold(RoundState::default(), |a, b| a.merge_chunk(b, nv));
        state.fits.sort_by_key(|f| f.0);
        state
    }
}

/// The fit with the alpha rounds (Eq. 6), one round at a time ([`AlphaRounds::step`]), so a
/// caller can look at the model after every round (the cross-validated choice of the number of
/// rounds, `crate::crossval`). [`fit_groups`] runs it to the end.
///
/// A round is the alpha step and the refit together: round r divides the samples by the alpha
/// Eq. 6 derived from round r − 1's fits and refits every group; the model it leaves is its
/// fits with the alpha Eq. 6 derives from *them*, as round 0's model is the fits of the samples
/// as captured with their Eq. 6 alpha. Its training objective
/// O(R_d, alpha) = Σ (ln alpha + ln R_d − ln s)^2 over the fitted samples is computed exactly
/// (per-vertex sufficient statistics), and the round is kept only if O falls below the last
/// kept round's. Neither half alone is a descent step once Eq. 6 is shrunk towards 1 and takes
/// only the samples of its intensity window (the alpha step can raise O; measured on a hidden
/// object: O fell in round 1, then rose in every round after it), so only the whole round is
/// judged: the kept rounds' objectives fall strictly, and the model returned is the last kept
/// round's.
pub struct AlphaRounds<'r, 'a> {
    runner: RoundRunner<'r, 'a>,
    baseline: Option<FittedBaseline>,
    /// The last kept round's fits and Eq. 6 accumulators.
    state: RoundState,
    /// The alpha the kept round's fits were fitted against (`None`: as captured, round 0).
    alpha_used: Option<Vec<[f64; 3]>>,
    /// Eq. 6 of the kept round's fits: the model's alpha.
    alpha: Vec<[f64; 3]>,
    alpha_report: AlphaReport,
    /// The kept round's objective (its fits with `alpha`).
    objective: f64,
    round_log: Vec<AlphaRound>,
    /// The last kept round.
    rounds: usize,
    /// The next round to try.
    next: usize,
    last_change: f64,
    converged: bool,
    stopped: bool,
}

impl<'r, 'a> AlphaRounds<'r, 'a> {
    /// The homogeneous baseline and round 0: every group fitted to its samples as captured,
    /// its order chosen.
    pub fn start(
        ctx: &'r Context<'a>,
        regs: &'r [RegisteredFrame],
        groups: &'r Groups,
        fitter: &'r dyn Fitter,
        cache: Option<&'r OrderCache>,
        progress: &'r dyn Progress,
    ) -> Self {
        // The baseline first: the per-vertex order choice has it as its smallest candidate.
        let baseline = fit_baseline(ctx, regs, groups, fitter);
        let runner = RoundRunner {
            ctx,
            regs,
            groups,
            fitter,
            progress,
            base_model: baseline.as_ref().map(|b| b.baseline.model.clone()),
            cache,
        };
        let state = runner.run(None, 0, None);
        let (alpha, alpha_report) = alpha_texture(
            &state.alpha,
            ctx.ds.mesh.positions.len(),
            &ctx.scene,
            ctx.opts.alpha_shrinkage,
        );
        let objective = state.objective_with(&alpha);
        AlphaRounds {
            runner,
            baseline,
            round_log: vec![AlphaRound {
                round: 0,
                objective,
                previous: objective,
                fitted: state.objective,
                fits_kept_previous: 0,
                kept: true,
            }],
            state,
            alpha_used: None,
            alpha,
            alpha_report,
            objective,
            rounds: 0,
            next: 1,
            last_change: 0.0,
            converged: false,
            stopped: false,
        }
    }

    /// Runs the next round; `true` when it was kept (the model moved on), `false` when the
    /// rounds are over: alpha converged (it changed by less than `alpha_tolerance` in the last
    /// kept round), the round did not lower the objective (discarded), or `alpha_rounds` ran.
    pub fn step(&mut self) -> bool {
        let opts = &self.runner.ctx.opts;
        if self.stopped || self.next > opts.alpha_rounds {
            self.stopped = true;
            return false;
        }
        let ones;
        let used = match &self.alpha_used {
            Some(a) => a,
            None => {
                ones = vec![[1.0; 3]; self.alpha.len()];
                &ones
            }
        };
        self.last_change = rms_ln_change(used, &self.alpha);
        if self.last_change < opts.alpha_tolerance {
            self.converged = true;
            self.stopped = true;
            return false;
        }
        let round = self.next;
        self.next += 1;
        let prev = self.state.by_index(self.runner.groups.keys.len());
        let next = self.runner.run(Some(&self.alpha), round, Some(&prev));
        let (alpha, report) = alpha_texture(
            &next.alpha,
            self.alpha.len(),
            &self.runner.ctx.scene,
            opts.alpha_shrinkage,
        );
        let objective = next.objective_with(&alpha);
        let kept = objective < self.objective * (1.0 - 1e-9);
        self.round_log.push(AlphaRound {
            round,
            objective,
            previous: self.objective,
            fitted: next.objective,
            fits_kept_previous: next.kept_previous,
            kept,
        });
        if !kept {
            // No gain: the last kept round's model (its fits and their Eq. 6) stands.
            self.converged = true;
            self.stopped = true;
            return false;
        }
        self.alpha_used = Some(std::mem::replace(&mut self.alpha, alpha));
        self.alpha_report = report;
        self.state = next;
        self.objective = objective;
        self.rounds = round;
        true
    }

    /// The rounds kept so far (0: only round 0).
    pub fn rounds(&self) -> usize {
        self.rounds
    }

    /// The model of the last kept round.
    pub fn fitted(&self) -> Fitted {
        let opts = &self.runner.ctx.opts;
        let mut alpha_report = self.alpha_report.clone();
        let last_change = match &self.alpha_used {
            Some(a) if !self.stopped || self.last_change == 0.0 => rms_ln_change(a, &self.alpha),
            _ => self.last_change,
        };
        alpha_report.rounds = self.rounds;
        alpha_report.last_change = last_change;
        alpha_report.converged =
            self.converged || last_change < opts.alpha_tolerance || opts.alpha_rounds == 0;
        alpha_report.round_log = self.round_log.clone();
        Fitted {
            fits: self.state.fits.iter().map(|(_, f)| f.clone()).collect(),
            alpha: self.alpha.clone(),
            alpha_report,
            counts: self.state.counts,
            dropped: self.state.dropped.clone(),
            baseline: self.baseline.clone(),
        }
    }
}

/// Fits every group, then runs the alpha rounds (Eq. 6) to the end ([`AlphaRounds`]): round 0
/// fits the samples as captured; each further round divides them by the previous round's
/// alpha(x_o) and refits, so the modulation texture is not mistaken for noise by the fit of
/// R_d, until alpha changes by less than `alpha_tolerance`, a round no longer lowers the
/// training objective, or `alpha_rounds` extra rounds ran. The report lists every round
/// (`AlphaReport::round_log`).
pub fn fit_groups(
    ctx: &Context,
    regs: &[RegisteredFrame],
    groups: &Groups,
    fitter: &dyn Fitter,
    cache: Option<&OrderCache>,
    progress: &dyn Progress,
) -> Fitted {
    let mut rounds = AlphaRounds::start(ctx, regs, groups, fitter, cache, progress);
    while rounds.step() {}
    rounds.fitted()
}

/// The homogeneous baseline: one isotropic fall-off (m = 1, the model's colour mode) fitted to
/// every group's samples pooled as captured (alpha = 1), at most [`BASELINE_POOL`] per channel
/// and group (evenly strided). `None` if that fit fails.
fn fit_baseline(
    ctx: &Context,
    regs: &[RegisteredFrame],
    groups: &Groups,
    fitter: &dyn Fitter,
) -> Option<FittedBaseline> {
    let pooled: ChannelSamples = groups
        .keys
        .par_iter()
        .map(|key| {
            let mut out: ChannelSamples = Default::default();
            if let Ok((data, _)) = group_samples(ctx, regs, key) {
                for (ch, d) in data.into_iter().enumerate() {
                    let step = d.len().div_ceil(BASELINE_POOL).max(1);
                    out[ch].extend(
                        d.into_iter()
                            .step_by(step)
                            .map(|x| GroupSample { phi: None, ..x }),
                    );
                }
            }
            out
        })
        .reduce(ChannelSamples::default, |mut a, b| {
            for (x, y) in a.iter_mut().zip(b) {
                x.extend(y);
            }
            a
        });
    let choice = ModelChoice {
        colour: ctx.opts.model.colour,
        segments: 1,
    };
    // As the interpolation's refits do: one term fewer while the fit fails. The pooled curve's
    // top term often runs its rate to 0 (a constant, which the drop rule then removes), and the
    // solver gets there slowly: at the draft preset's iteration limit that fit failed, the run
    // kept no baseline, and its renders came out 11–14 % dark (BENCHMARKS.md, issue 28).
    let max_n = fitter.max_terms().unwrap_or(1);
    let (model, terms, _) = fit_samples(&pooled, &choice, fitter, &mut Vec::new())
        .or_else(|e| {
            (1..max_n)
                .rev()
                .find_map(|n| {
                    let at_most = AtMost { inner: fitter, n };
                    fit_samples(&pooled, &choice, &at_most, &mut Vec::new()).ok()
                })
                .ok_or(e)
        })
        .ok()?;
    let r_range = pooled
        .iter()
        .flatten()
        .fold([f64::INFINITY, 0.0], |[lo, hi], x| {
            [lo.min(x.r), hi.max(x.r)]
        });
    let (params, _, _) = params_of(&model).ok()?;
    params
        .iter()
        .all(|p| p.is_finite())
        .then(|| FittedBaseline {
            baseline: Baseline { model, r_range },
            params: BaselineParams {
                terms,
                params,
                r_range,
            },
            samples: pooled.iter().map(Vec::len).sum(),
        })
}

/// The baseline of a run: for prediction, for the model file, and how many samples it pooled.
#[derive(Debug, Clone)]
pub struct FittedBaseline {
    /// As prediction uses it.
    pub baseline: Baseline,
    /// As the model file stores it.
    pub params: BaselineParams,
    /// Channel samples pooled.
    pub samples: usize,
}

/// RMS over vertices and channels of the change of ln alpha(x_o) between two rounds.
fn rms_ln_change(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let (sum, n) = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| x.iter().zip(y).map(|(p, q)| (p.ln() - q.ln()).powi(2)))
        .filter(|d| d.is_finite())
        .fold((0.0, 0usize), |(s, n), d| (s + d, n + 1));
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// The pseudo-count Eq. 6 is shrunk with: the empirical one ([`crate::model::empirical_prior`])
/// times the run's `alpha_shrinkage`; infinite (alpha = 1, no texture) when the setting is.
pub fn shrinkage_prior(empirical: f64, shrinkage: f64) -> f64 {
    if shrinkage.is_infinite() {
        f64::INFINITY
    } else {
        empirical * shrinkage.max(0.0)
    }
}

/// Eq. 6 per vertex from the accumulated samples; vertices no fitted frame saw (Eq. 6's X is
/// empty: not visible from any camera at any selected turntable angle) take the harmonic
/// interpolation of ln alpha from their mesh neighbours, and 1 where no neighbour has data.
fn alpha_texture(
    acc: &[[AlphaAccumulator; 3]],
    nv: usize,
    scene: &Scene,
    shrinkage: f64,
) -> (Vec<[f64; 3]>, AlphaReport) {
    // Eq. 6's shrinkage per channel from the texels' own spread against the noise, scaled by
    // the run's setting (infinite: alpha = 1).
    let prior: [f64; 3] = [0, 1, 2].map(|ch| {
        shrinkage_prior(
            crate::model::empirical_prior(acc.iter().map(|a| &a[ch])),
            shrinkage,
        )
    });
    let own: Vec<Option<Vec<f64>>> = (0..nv)
        .map(|v| {
            let a = acc.get(v)?;
            let vals: Vec<Option<f64>> = a
                .iter()
                .zip(prior)
                .map(|(c, p)| {
                    c.ln_alpha_shrunk(p)
                        .map(f64::exp)
                        .filter(|x| x.is_finite() && *x > 0.0)
                })
                .collect();
            // A channel without samples in the window takes the vertex's other channels' mean.
            let known: Vec<f64> = vals.iter().flatten().map(|x| x.ln()).collect();
            if known.is_empty() {
                return None;
            }
            let mean = known.iter().sum::<f64>() / known.len() as f64;
            Some(vals.iter().map(|x| x.map_or(mean, f64::ln)).collect())
        })
        .collect();
    let filled = crate::interpolate::harmonic(&own, |v| scene.neighbours(v), 500);
    let mut rep = AlphaReport {
        prior: prior.map(|p| p.min(crate::model::ALPHA_PRIOR_MAX)),
        ..AlphaReport::default()
    };
    let alpha = (0..nv)
        .map(|v| {
            if own[v].is_some() {
                rep.from_samples += 1;
            } else if filled[v].is_some() {
                rep.interpolated += 1;
            } else {
                rep.default_one += 1;
            }
            match &filled[v] {
                Some(l) if l.len() == 3 => [l[0].exp(), l[1].exp(), l[2].exp()],
                _ => [1.0; 3],
            }
        })
        .collect();
    (alpha, rep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::FitOptions;
    use crate::model::Term;
    use proptest::prelude::*;

    /// `unsupported_term` as it was, sorting the distances at every call (stably): the
    /// reference [`Distances`] is held to.
    fn unsupported_term_sorting(f: &ExpSum, r: &[f64]) -> Option<TermDropped> {
        let (lo, hi) = r
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        if hi.partial_cmp(&lo).is_none_or(|o| o.is_lt()) {
            return None;
        }
        if f.terms.iter().any(|t| -t.d * (hi - lo) < MIN_DECAY) {
            return Some(TermDropped::NonDecaying);
        }
        if f.n() < 2 {
            return None;
        }
        let mut rs: Vec<f64> = r.to_vec();
        rs.sort_by(f64::total_cmp);
        rs.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * b.abs().max(1.0));
        for t in &f.terms {
            let support = rs
                .iter()
                .filter(|&&x| t.c.ln() + t.d * x - f.ln_eval(x) >= MIN_SHARE.ln())
                .count();
            if support < MIN_SUPPORT {
                return Some(TermDropped::Unresolved);
            }
        }
        None
    }

    proptest! {
        /// The distances sorted once judge every fall-off as sorting them at every call did, and
        /// the red distances three times (the shared colour's fit of all channels) are judged
        /// as the red distances: the same range, the same distinct values.
        #[test]
        fn distances_sorted_once_judge_terms_as_before(
            base in proptest::collection::vec(0.0..20.0f64, 1..40),
            near in proptest::collection::vec((0usize..40, -2e-8..2e-8f64), 0..20),
            terms in proptest::collection::vec((0.01..10.0f64, -20.0..-0.001f64), 1..=4),
        ) {
            // Some distances repeated or within the dedup tolerance of another.
            let mut r = base.clone();
            for (i, dx) in near {
                r.push(base[i % base.len()] * (1.0 + dx));
            }
            let f = ExpSum {
                terms: terms.iter().map(|&(c, d)| Term { c, d }).collect(),
            };
            let want = unsupported_term_sorting(&f, &r);
            prop_assert_eq!(unsupported_term(&f, &r), want);
            let thrice: Vec<f64> = r.iter().chain(&r).chain(&r).copied().collect();
            prop_assert_eq!(unsupported_term_sorting(&f, &thrice), want);
            let (once, all) = (Distances::of(&r), Distances::of(&thrice));
            prop_assert_eq!(once.distinct(), all.distinct());
            prop_assert_eq!((once.lo, once.hi), (all.lo, all.hi));
        }
    }

    fn sample(frame: u32, vertex: u32, r: f64, phi: Option<f64>, s: f64) -> GroupSample {
        GroupSample {
            r,
            s,
            vertex,
            frame,
            phi,
        }
    }

    /// Samples of an Eq. 3 model (4 segments, shared colour with scales 0.5, 0.25) on a polar
    /// grid of directions `phis`.
    fn samples_of(truth: &Anisotropic, phis: &[f64]) -> ChannelSamples {
        let mut data: ChannelSamples = Default::default();
        let mut v = 0;
        for &p in phis {
            for i in 0..40 {
                let r = 0.5 + 0.2 * i as f64;
                let rd = truth.eval(r, Some(p));
                for (ch, sc) in [1.0, 0.5, 0.25].into_iter().enumerate() {
                    data[ch].push(sample(0, v, r, Some(p), sc * rd));
                }
                v += 1;
            }
        }
        data
    }

    fn truth() -> Anisotropic {
        let seg = |c: f64, d: f64| {
            ExpSum::new(vec![
                Term { c, d },
                Term {
                    c: 0.1 * c,
                    d: 0.3 * d,
                },
            ])
            .unwrap()
        };
        Anisotropic {
            segments: vec![
                seg(1.0, -2.0),
                seg(2.0, -1.0),
                seg(1.0, -2.0),
                seg(2.0, -1.0),
            ],
        }
    }

    /// A group whose channels hold the same observations in the same order takes its rows
    /// without the join, and they are the join's bits; any other group is joined.
    #[test]
    fn aligned_channels_take_the_joined_rows_to_the_bit() {
        let bits = |r: &ColourRows| -> Vec<u64> {
            r.r.iter()
                .chain(&r.phi)
                .chain(r.s.iter().flatten())
                .map(|v| v.to_bits())
                .collect()
        };
        let mut data: ChannelSamples = Default::default();
        for (ch, d) in data.iter_mut().enumerate() {
            for f in 0..3u32 {
                for v in [2u32, 5, 9] {
                    let phi = (v != 5).then_some(0.1 * f64::from(v));
                    d.push(sample(f, v, 1.0 + f64::from(v), phi, 10.0 - ch as f64));
                }
            }
        }
        let fast = ColourRows::aligned(&data).expect("aligned channels");
        assert_eq!(bits(&fast), bits(&ColourRows::joined(&data)));
        // Channel 0 not strictly increasing (an observation twice), or another channel's
        // observations elsewhere: the general join.
        let mut twice = data.clone();
        for d in twice.iter_mut() {
            d[1] = d[0];
        }
        assert!(ColourRows::aligned(&twice).is_none());
        let mut shifted = data.clone();
        shifted[2].pop();
        assert!(ColourRows::aligned(&shifted).is_none());
        assert_eq!(
            bits(&ColourRows::of(&shifted)),
            bits(&ColourRows::joined(&shifted))
        );
    }

    #[test]
    fn rows_join_the_channels_of_one_observation() {
        let mut data: ChannelSamples = Default::default();
        data[0] = vec![
            sample(0, 7, 1.0, Some(0.5), 3.0),
            sample(1, 7, 2.0, None, 5.0),
        ];
        data[1] = vec![sample(0, 7, 1.0, Some(0.5), 2.0)];
        data[2] = vec![sample(1, 7, 2.0, None, 4.0)];
        let rows = ColourRows::of(&data);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows.r, vec![1.0, 2.0]);
        assert_eq!(rows.phi[0], 0.5);
        assert!(rows.phi[1].is_nan());
        assert_eq!((rows.s[0][0], rows.s[1][0]), (3.0, 2.0));
        assert!(rows.s[2][0].is_nan() && rows.s[1][1].is_nan());
        assert_eq!((rows.s[0][1], rows.s[2][1]), (5.0, 4.0));
    }

    /// The pipeline's model is the joint hat-weighted fit: noise-free Eq. 3 data (directions
    /// between the segment centres included) are recovered, which a fit on hard sectors cannot do
    /// (a sector mixes its neighbours' fall-offs).
    #[test]
    fn the_pipeline_fit_recovers_hat_blended_data() {
        let truth = truth();
        let phis: Vec<f64> = (0..32)
            .map(|k| k as f64 * std::f64::consts::TAU / 32.0)
            .collect();
        let data = samples_of(&truth, &phis);
        let choice = ModelChoice {
            colour: ColourMode::Shared,
            segments: 4,
        };
        let fitter = FitOptions {
            terms: crate::fit::Terms::Fixed(2),
            ..FitOptions::default()
        };
        let (model, n, path) = fit_samples(&data, &choice, &fitter, &mut Vec::new()).unwrap();
        assert_eq!((n, path), (2, FitPath::Joint));
        for &p in &phis {
            for r in [0.5, 2.0, 5.0, 8.0] {
                let want = truth.ln_eval(r, Some(p));
                let got = model.ln_eval(r, Some(p));
                assert!(
                    (got[0] - want).abs() < 1e-5,
                    "r {r} phi {p}: {got:?} vs {want}"
                );
                assert!((got[1] - want - 0.5f64.ln()).abs() < 1e-5);
            }
        }
    }

    /// Direction segments without samples of their own are held at the isotropic fit; where no
    /// segment has samples of its own (no directions at all) the joint fit at m is impossible and
    /// the light position keeps an isotropic model (m equal segments) instead of losing its fit.
    #[test]
    fn segments_without_samples_are_anchored_or_fall_back_to_isotropic() {
        let truth = truth();
        // Directions only in the first half turn: segments 5..7 of 8 have no samples.
        let phis: Vec<f64> = (0..16)
            .map(|k| k as f64 * std::f64::consts::PI / 16.0)
            .collect();
        let half = samples_of(&truth, &phis);
        let mut none = half.clone();
        for d in none.iter_mut() {
            for x in d.iter_mut() {
                x.phi = None;
            }
        }
        let fitter = FitOptions::default();
        for colour in [ColourMode::Shared, ColourMode::PerChannel] {
            let choice = ModelChoice {
                colour,
                segments: 8,
            };
            // Half the directions: the light position keeps a model of 8 segments, the empty
            // ones held together where the joint fit stands.
            let (model, _, path) = fit_samples(&half, &choice, &fitter, &mut Vec::new()).unwrap();
            for f in falloffs(&model) {
                assert_eq!(f.segments.len(), 8);
                let (a, b) = (&f.segments[5], &f.segments[6]);
                assert!(
                    path == FitPath::Isotropic || (a.ln_eval(2.0) - b.ln_eval(2.0)).abs() < 1e-3
                );
            }
            assert_eq!(
                fit_at(&none, colour, 2, 8, &fitter),
                Err(FailReason::TooFewSamples)
            );
            let (model, _, path) = fit_samples(&none, &choice, &fitter, &mut Vec::new()).unwrap();
            assert_eq!(path, FitPath::Isotropic);
            for f in falloffs(&model) {
                assert_eq!(f.segments.len(), 8);
                assert!(f.segments.iter().all(|s| *s == f.segments[0]));
            }
        }
    }

    #[test]
    fn solver_failures_map_to_reasons() {
        use crate::fit::FitFailure;
        let too_few = FitFailure::TooFewSamples {
            usable: 1,
            needed: 4,
        };
        assert_eq!(FailReason::from(too_few), FailReason::TooFewSamples);
        let stalled = FitFailure::NotConverged {
            iterations: 3,
            log_e: 1.0,
            stalled: true,
        };
        assert_eq!(FailReason::from(stalled), FailReason::NotConverged);
        assert_eq!(
            FailReason::from(FitFailure::NonFinite),
            FailReason::NonPhysical
        );
    }
}
