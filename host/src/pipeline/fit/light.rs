//! The fit of one light position (section 5, Eq. 1/3/5/9): the order candidates (n, m) and
//! the choice among them, the support of each term, the joint fit of the direction segments and
//! its isotropic fallback.

use super::*;
use crate::model::Term;

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
    Distances::of(r).unsupported_term(f, false)
}

/// A light position's sample distances as [`unsupported_term`] judges a fall-off's terms on
/// them: their range, and (taken at the first fall-off of two terms or more) the distinct
/// distances, sorted. Held so that the fits of one set of distances (every candidate order, the
/// refits with a term fewer, the shared colour's fit of all channels, whose distances are the
/// red ones three times) sort them once: the sort was a twentieth of a fit.
pub(crate) struct Distances<'r> {
    r: &'r [f64],
    pub(super) lo: f64,
    pub(super) hi: f64,
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
    pub(super) fn distinct(&self) -> &[f64] {
        self.distinct.get_or_init(|| {
            let mut rs: Vec<f64> = self.r.to_vec();
            rs.sort_unstable_by(f64::total_cmp);
            rs.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * b.abs().max(1.0));
            rs
        })
    }

    /// [`unsupported_term`] of `f` on these distances; `vectorised`: ln R_d at the distances
    /// by [`ExpSum::ln_eval_many`] ([`Fitter::rounding_cuts`]).
    pub(super) fn unsupported_term(&self, f: &ExpSum, vectorised: bool) -> Option<TermDropped> {
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
        let ln_rd = ln_rd_of(f, &ln_cs, rs, vectorised);
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
/// term fewer (a term that hardly decays beside others is held at the least decay instead,
/// [`with_least_decay`], where the fitter [holds](Fitter::holds_slow_terms) them). `dropped`
/// collects why.
pub(super) fn fit_supported(
    fitter: &dyn Fitter,
    r: &[f64],
    s: &[f64],
    terms: Option<usize>,
    dropped: &mut Vec<TermDropped>,
) -> Result<ExpSum, FailReason> {
    fit_supported_on(fitter, &Distances::of(r), s, terms, dropped)
}

/// [`fit_supported`] of the samples at `distances`.
pub(super) fn fit_supported_on(
    fitter: &dyn Fitter,
    distances: &Distances,
    s: &[f64],
    terms: Option<usize>,
    dropped: &mut Vec<TermDropped>,
) -> Result<ExpSum, FailReason> {
    let r = distances.r;
    let mut f = fitter.fit(r, s, terms)?;
    loop {
        match distances.unsupported_term(&f, fitter.rounding_cuts()) {
            None => return Ok(f),
            Some(why) => {
                // A fall-off of one term that does not decay is no fall-off: it fails below.
                if why == TermDropped::NonDecaying
                    && f.n() >= 2
                    && fitter.holds_slow_terms()
                    && let Some(g) = with_least_decay(&f, distances.lo, distances.hi)
                {
                    dropped.push(TermDropped::HeldAtLeastDecay);
                    f = g;
                    continue;
                }
                if f.n() <= 1 {
                    return Err(FailReason::NonPhysical);
                }
                dropped.push(why);
                f = fitter.fit(r, s, Some(f.n() - 1))?;
            }
        }
    }
}

/// `f` with every term that hardly decays over the sampled distances `[lo, hi]` given the
/// least decay a supported term has (|d|·(hi − lo) = [`MIN_DECAY`]), its value kept at the
/// middle of the range (so within e^{±MIN_DECAY/2}, ±5 %, over it); terms that end at one rate
/// are joined. `None` where the range is empty or the result is not a valid fall-off.
///
/// Why not drop the term and refit with one fewer: such a term is the far, slow part of the
/// fall-off the samples do show (a glow across the object at a few times the noise floor), and
/// dropping it swaps the curve for a steeper one of another shape. Whether the fit's slowest
/// rate lands just above or just below the limit then decides between two models, and a move of
/// the mesh by a few hundredths of a millimetre flips it: on sample-pebble that flip was one
/// held-out frame's log E between 0.42 and 0.76. Held at the limit, the fall-off changes
/// continuously with the samples.
pub(super) fn with_least_decay(f: &ExpSum, lo: f64, hi: f64) -> Option<ExpSum> {
    let span = hi - lo;
    if !(span > 0.0 && span.is_finite()) {
        return None;
    }
    // A hair beyond the limit, so the support test sees it as met whatever the rounding.
    let d_min = -MIN_DECAY / span * (1.0 + 1e-12);
    let mid = 0.5 * (lo + hi);
    let mut terms: Vec<Term> = Vec::with_capacity(f.n());
    let mut held: Option<Term> = None;
    for t in &f.terms {
        if -t.d * span < MIN_DECAY {
            let c = (t.c.ln() + (t.d - d_min) * mid).exp();
            let h = held.get_or_insert(Term { c: 0.0, d: d_min });
            h.c += c;
        } else {
            terms.push(*t);
        }
    }
    terms.extend(held);
    ExpSum::new(terms).ok()
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
pub(super) fn implausible_segments(model: &ColourModel, iso: &ColourModel) -> u64 {
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
pub(super) fn falloffs(m: &ColourModel) -> Vec<&Anisotropic> {
    match m {
        ColourModel::PerChannel { channels } => channels.iter().collect(),
        ColourModel::Shared { falloff, .. } => vec![falloff],
    }
}

/// `model`'s one segment repeated m times: the isotropic model as an m-segment one (identical
/// under the hat weights, which sum to 1).
pub(super) fn repeat_segments(model: ColourModel, m: usize) -> ColourModel {
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
/// (the joint fit with the hat weights evaluation and rendering use, `Fitter::fit_colour_from`).
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
    fit_anchored(data, colour, n, m, 0, fitter, None)
}

/// [`fit_at`] with the segments of the bit mask `anchored` held at the isotropic fit, started
/// from `start` where the fitter can ([`Fitter::fit_colour_from`]).
pub(super) fn fit_anchored(
    data: &ChannelSamples,
    colour: ColourMode,
    n: usize,
    m: usize,
    anchored: u64,
    fitter: &dyn Fitter,
    start: Option<&ExpSum>,
) -> Result<ColourModel, FailReason> {
    let rows = ColourRows::of(data);
    let model = fitter.fit_colour_from(&rows, n, m.max(1), colour, anchored, start)?;
    model.validate().map_err(|_| FailReason::NonPhysical)?;
    Ok(model)
}

/// The isotropic model whose fits choose the order n ("model only what the scene requires":
/// terms the samples do not support are dropped, see [`unsupported_term`]). Per channel: one
/// common order for the three channels. Shared (Eq. 9): the red fall-off chooses n, then one
/// fall-off is fitted to all channels divided by their scales (block coordinate descent on the
/// log objective, exact on noise-free data).
pub(super) fn isotropic_order(
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
                    let vectorised = fitter.rounding_cuts();
                    let r: Vec<f64> = d.iter().map(|x| x.r).collect();
                    let ln_s = ln_of(d.iter().map(|x| x.s), vectorised);
                    let ln_rd = ln_rd_of(f, &ln_c, &r, vectorised);
                    let mean =
                        ln_s.iter().zip(&ln_rd).map(|(a, b)| a - b).sum::<f64>() / d.len() as f64;
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
            let all_distances = if red_thrice(data, &r) {
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

/// Whether every other channel holds the red samples' distances `r`, index by index (the usual
/// group: a frame measures its channels at the same pixels). Then all the group's distances are
/// the red ones three times, whose range and distinct values are the red ones: their
/// [`Distances`] serve a fit of all channels without another sort.
fn red_thrice(data: &ChannelSamples, r: &[f64]) -> bool {
    data[1..]
        .iter()
        .all(|d| d.len() == r.len() && d.iter().zip(r).all(|(x, r)| x.r.to_bits() == r.to_bits()))
}

/// The default's path of [`fit_samples`] for shared colour at one segment
/// ([`Fitter::rounding_cuts`]): the red fall-off chooses n (terms its samples do not support
/// dropped, as in [`isotropic_order`]), the joint fit of every channel (Eq. 5) starts from it
/// instead of fitting it again, and the joint fall-off's terms are checked for support on every
/// channel's distances, as the exact path checks its isotropic fit of all channels. Why: that
/// isotropic fit, which the joint fit does not start from and which sets nothing but n where
/// the joint fit succeeds, and the joint fit's own refit of the red samples were a fifth of the
/// cross-validation's CPU on `scan1024`. `None` where any fit or the support check fails, or a
/// channel has no samples: the exact path then runs, so a light position fails or falls back
/// as there.
pub(super) fn fit_shared_from_red(
    data: &ChannelSamples,
    fitter: &dyn Fitter,
    dropped: &mut Vec<TermDropped>,
) -> Option<(ColourModel, usize)> {
    if data[1..].iter().any(|d| d.is_empty()) {
        return None;
    }
    let (r, s): (Vec<f64>, Vec<f64>) = data[0].iter().map(|x| (x.r, x.s)).unzip();
    let red_distances = Distances::of(&r);
    let mut own = Vec::new();
    let red = fit_supported_on(fitter, &red_distances, &s, None, &mut own).ok()?;
    let n = red.n();
    let model = fit_anchored(data, ColourMode::Shared, n, 1, 0, fitter, Some(&red)).ok()?;
    let ColourModel::Shared { falloff, .. } = &model else {
        return None;
    };
    let [f] = falloff.segments.as_slice() else {
        return None;
    };
    // Every channel's distances, as `isotropic_order` judges its fit of all channels on them.
    let unsupported = if red_thrice(data, &r) {
        red_distances.unsupported_term(f, true)
    } else {
        let all: Vec<f64> = data.iter().flatten().map(|x| x.r).collect();
        Distances::of(&all).unsupported_term(f, true)
    };
    if unsupported.is_some() {
        return None;
    }
    dropped.extend(own);
    Some((model, n))
}

/// How a light position's model was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum FitPath {
    /// The joint fit at (n, m).
    Joint,
    /// Isotropic (all m segments equal): the joint fit at m failed (no segment with samples of
    /// its own, or the solve did not converge) or was implausible ([`implausible_segments`]).
    Isotropic,
}

/// A light position's model: the order n from the isotropic fits ([`isotropic_order`]), then the
/// joint fit at (n, m) ([`fit_at`]). Where that fails or is implausible the light position keeps
/// an isotropic model (the joint fit at (n, 1), else the order-choosing fit) with its segments
/// repeated, so no light position loses the model the isotropic fit gave it. `order_kept`: a
/// round after the first, which keeps the n the first chose; where the fitter allows
/// ([`Fitter::rounding_cuts`]) shared colour at one segment then takes
/// [`fit_shared_from_red`]. The first round's candidates, which choose n, always take the
/// exact path (they are fitted once per run, [`OrderCache`]), so every light position starts
/// from the order the reference gives it.
pub(super) fn fit_samples(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    order_kept: bool,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize, FitPath), FailReason> {
    let m = choice.segments.max(1);
    if m == 1
        && order_kept
        && choice.colour == ColourMode::Shared
        && fitter.rounding_cuts()
        && let Some((model, n)) = fit_shared_from_red(data, fitter, dropped)
    {
        return Ok((model, n, FitPath::Joint));
    }
    let (iso, n) = isotropic_order(data, choice.colour, fitter, dropped)?;
    // Segments the joint fit made implausible are held at the isotropic fit and the rest
    // refitted, once.
    let mut joint = fit_at(data, choice.colour, n, m, fitter);
    if m > 1
        && let Ok(model) = &joint
    {
        let bad = implausible_segments(model, &iso);
        if bad != 0 {
            joint = fit_anchored(data, choice.colour, n, m, bad, fitter, None);
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
pub(super) fn fit_order(
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
        return fit_candidate(data, choice, fitter, Some(n), m, true, dropped);
    }
    let (Some(rule), Some(max_n)) = (rule, fitter.max_terms()) else {
        return fit_candidate(data, choice, fitter, None, choice.segments, false, dropped);
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
pub(super) fn fit_candidate(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    n: Option<usize>,
    m: usize,
    order_kept: bool,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize, usize, bool, FitPath), FailReason> {
    let c = ModelChoice {
        segments: m,
        ..*choice
    };
    match n {
        Some(n) => fit_samples(data, &c, &AtMost::terms(fitter, n), order_kept, dropped),
        None => fit_samples(data, &c, fitter, order_kept, dropped),
    }
    .map(|(model, n, path)| (model, n, m, false, path))
}

/// Round 0's candidates of one light position ([`fit_order`]): its fits at every (n, m) but the
/// baseline's, which depend on its samples alone.
#[derive(Debug)]
pub(super) struct Candidates {
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
pub(super) fn order_candidates(
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
            match fit_candidate(data, choice, fitter, Some(n), m, false, &mut d) {
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
                // 0.693/0.674/0.691 with them interpolated; BENCHMARKS.md).
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
