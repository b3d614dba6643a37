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
use super::findings::{AlphaReport, AlphaRound, BASELINE_POOL, FailReason, TermDropped};
use super::load::Context;
use super::register::RegisteredFrame;
use super::select::{ChannelSamples, GroupSample, Groups, group_samples};

mod baseline;
mod cache;
mod light;
mod rounds;

pub use baseline::*;
pub use cache::*;
pub use light::*;
pub use rounds::*;

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
    /// isotropic fit. With `start`, an isotropic fit of the rows' red samples at n terms, the
    /// fit starts from it where the fitter can ([`crate::fit::aniso::fit_colour_from`])
    /// instead of fitting those samples again.
    fn fit_colour_from(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
        start: Option<&ExpSum>,
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

    /// Whether the pipeline around this fitter takes the default's cuts that agree with the
    /// exact path within rounding, not to the bit: the loops around its solves (ln
    /// R_d of a fit at every sample, ln s, the terms' support) take the vectorised exp and ln
    /// ([`crate::model::ExpSum::ln_eval_many`], [`crate::fit::ln_many`]: within a few ulp of
    /// libm's), and a light position's shared joint fit at one segment starts from the red fit
    /// its order choice made and is checked for support itself ([`light::fit_samples`]). The
    /// default's fitter does; the reference preset's (libm's throughout, the exact path
    /// without the cuts) and any fitter that does not say do not.
    fn rounding_cuts(&self) -> bool {
        false
    }

    /// This fitter as the reference preset runs it (the exact path without the cuts: libm's
    /// exp and ln, [`crate::fit::FitOptions::libm`]); `None`: it is that already.
    fn reference(&self) -> Option<Box<dyn Fitter>> {
        None
    }

    /// Whether a term that hardly decays beside others is held at the least decay
    /// ([`light::with_least_decay`]) rather than dropped with a refit of one term fewer. Light
    /// positions hold it (their fall-off then changes continuously with their samples); the
    /// homogeneous baseline, whose shape continues every model beyond its sampled distances, drops
    /// it ([`AtMost::dropping`]), so that no constant runs on past them.
    fn holds_slow_terms(&self) -> bool {
        true
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

    fn fit_colour_from(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
        start: Option<&ExpSum>,
    ) -> Result<ColourModel, FailReason> {
        use crate::fit::aniso::{AnisoOptions, fit_colour_from};
        let opts = AnisoOptions {
            terms: n,
            segments: m,
            shared: colour == ColourMode::Shared,
            solver: self.solver,
            max_iterations: self.max_iterations * if m > 1 { JOINT_ITERATIONS } else { 1 },
            bins: self.bins,
            direction_bins: self.bins,
            anchored,
            libm: self.libm,
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
        // A start fitted to every row is no start for a subsample.
        let start = start.filter(|_| k == 1);
        let fit = fit_colour_from(&rows.r, &rows.phi, [sr, sg, sb], &opts, start)?;
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

    fn rounding_cuts(&self) -> bool {
        !self.libm
    }

    fn reference(&self) -> Option<Box<dyn Fitter>> {
        (!self.libm).then(|| {
            Box::new(crate::fit::FitOptions {
                libm: true,
                ..self.clone()
            }) as Box<dyn Fitter>
        })
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
        // foldhash, not std's SipHash: the keys are our own frame and vertex numbers (no
        // adversary), and a group whose channels differ (a channel below the noise at some
        // pixels) takes this path in every round of every fold: SipHash and the map's growth
        // were 3 % of the 655,362-vertex pebble's fit (perf). The map only numbers the rows,
        // in the order they first appear, so the rows are the same.
        let mut index: std::collections::HashMap<(u32, u32), usize, foldhash::fast::FixedState> =
            std::collections::HashMap::with_capacity_and_hasher(
                data[0].len(),
                foldhash::fast::FixedState::default(),
            );
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

/// The run's fitter narrowed: at most `n` terms where `n` is set (its own setting, `terms =
/// None`, then means n; the order choice [`fit_order`] tries each candidate n this way), and
/// terms that hardly decay dropped instead of held where `holds` is false (the baseline's rule,
/// [`Fitter::holds_slow_terms`]). One wrapper for both, so that every forwarded method is
/// written once.
pub(super) struct AtMost<'a> {
    inner: &'a dyn Fitter,
    n: Option<usize>,
    holds: bool,
}

impl<'a> AtMost<'a> {
    /// At most `n` terms, the slow-term rule of `inner`.
    pub(super) fn terms(inner: &'a dyn Fitter, n: usize) -> Self {
        Self {
            inner,
            n: Some(n),
            holds: inner.holds_slow_terms(),
        }
    }

    /// `inner`'s own order, terms that hardly decay dropped.
    pub(super) fn dropping(inner: &'a dyn Fitter) -> Self {
        Self {
            inner,
            n: None,
            holds: false,
        }
    }
}

impl Fitter for AtMost<'_> {
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason> {
        let terms = match self.n {
            Some(n) => Some(terms.map_or(n, |t| t.min(n))),
            None => terms,
        };
        self.inner.fit(r, s, terms)
    }

    fn fit_colour_from(
        &self,
        rows: &ColourRows,
        n: usize,
        m: usize,
        colour: ColourMode,
        anchored: u64,
        start: Option<&ExpSum>,
    ) -> Result<ColourModel, FailReason> {
        let n = self.n.map_or(n, |at_most| n.min(at_most));
        self.inner
            .fit_colour_from(rows, n, m, colour, anchored, start)
    }

    fn max_terms(&self) -> Option<usize> {
        self.n.or_else(|| self.inner.max_terms())
    }

    fn rounding_cuts(&self) -> bool {
        self.inner.rounding_cuts()
    }

    fn holds_slow_terms(&self) -> bool {
        self.holds
    }
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
    /// lattice pass ([`super::detail`]) uses this light position's very window.
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

    /// A fall-off of three terms whose slowest (0.15 / mm) carries the tail beyond 10 mm.
    fn three_terms() -> ExpSum {
        ExpSum::new(vec![
            Term { c: 1.0, d: -3.0 },
            Term { c: 0.2, d: -0.8 },
            Term { c: 0.01, d: -0.15 },
        ])
        .unwrap()
    }

    /// The default's shortcut for shared colour at one segment ([`light::fit_samples`] through
    /// `fit_shared_from_red`, [`Fitter::rounding_cuts`]) fits the exact path's model: on noisy
    /// samples of a three-term fall-off with channel scales, the same n and path and ln R_d
    /// within 1e-6 of the reference fitter's (libm's, the isotropic fit of all channels, the
    /// joint fit's own start), every channel, 20 µm to 15 mm. A group with a channel without
    /// samples leaves the shortcut for the exact path, which fails it.
    #[test]
    fn the_shared_shortcut_fits_the_exact_paths_model() {
        let truth = three_terms();
        let mut data: ChannelSamples = Default::default();
        for j in 0..160u32 {
            let r = 0.1 + 0.075 * f64::from(j);
            for (ch, sc) in [1.0, 0.6, 0.3].into_iter().enumerate() {
                let noise = 1.0 + 0.03 * (f64::from(j) * 12.9898 + ch as f64 * 78.233).sin();
                data[ch].push(sample(j % 7, j, r, None, sc * truth.eval(r) * noise));
            }
        }
        let choice = ModelChoice {
            colour: ColourMode::Shared,
            segments: 1,
        };
        let fast = FitOptions::default();
        let exact = FitOptions {
            libm: true,
            ..FitOptions::default()
        };
        assert!(fast.rounding_cuts() && !exact.rounding_cuts());
        assert!(light::fit_shared_from_red(&data, &fast, &mut Vec::new()).is_some());
        let (a, na, pa) = fit_samples(&data, &choice, &fast, true, &mut Vec::new()).unwrap();
        let (b, nb, pb) = fit_samples(&data, &choice, &exact, true, &mut Vec::new()).unwrap();
        assert_eq!((na, pa), (nb, pb));
        assert_eq!(na, 3);
        for k in 0..=100 {
            let r = 0.02 + 0.1498 * f64::from(k);
            let (x, y) = (a.ln_eval(r, None), b.ln_eval(r, None));
            for ch in 0..3 {
                assert!(
                    (x[ch] - y[ch]).abs() < 1e-6,
                    "r {r} ch {ch}: {x:?} vs {y:?}"
                );
            }
        }
        let mut no_blue = data.clone();
        no_blue[2].clear();
        assert!(light::fit_shared_from_red(&no_blue, &fast, &mut Vec::new()).is_none());
        let fast_err = fit_samples(&no_blue, &choice, &fast, true, &mut Vec::new()).err();
        let exact_err = fit_samples(&no_blue, &choice, &exact, true, &mut Vec::new()).err();
        assert!(fast_err.is_some() && fast_err == exact_err);
    }

    /// ln R_d at a group's samples vectorised (the default) against per sample (the
    /// reference): within a few ulp on every channel, whether a channel's samples are the red
    /// ones index by index (one evaluation, the red one plus ln s_c) or not (green lacks the
    /// red's first sample, so every later one is shifted: evaluated on its own), and the same
    /// bits per sample where a fall-off has several segments (nothing to vectorise).
    #[test]
    fn vectorised_ln_r_d_at_the_samples_is_the_per_sample_one() {
        let falloff = three_terms();
        let shared = ColourModel::Shared {
            falloff: Anisotropic {
                segments: vec![falloff],
            },
            s_g: 0.6,
            s_b: 0.3,
        };
        let mut data: ChannelSamples = Default::default();
        for j in 0..50u32 {
            for d in data.iter_mut() {
                d.push(sample(0, j, 0.05 + 0.3 * f64::from(j), Some(0.1), 1.0));
            }
        }
        data[1].remove(0);
        let segmented = ColourModel::Shared {
            falloff: truth(),
            s_g: 0.6,
            s_b: 0.3,
        };
        for model in [&shared, &segmented] {
            let ev = model.ln_evaluator();
            let exact = ln_rd_with(&ev, &data, true, false);
            let fast = ln_rd_with(&ev, &data, true, true);
            for ch in 0..3 {
                assert_eq!(exact[ch].len(), data[ch].len());
                assert_eq!(fast[ch].len(), data[ch].len());
                for (a, b) in exact[ch].iter().zip(&fast[ch]) {
                    if model == &segmented {
                        assert_eq!(a.to_bits(), b.to_bits());
                    } else {
                        assert!((a - b).abs() <= 4e-16 * a.abs().max(1.0), "{a} against {b}");
                    }
                }
            }
        }
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
        let (model, n, path) = fit_samples(&data, &choice, &fitter, true, &mut Vec::new()).unwrap();
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
            let (model, _, path) =
                fit_samples(&half, &choice, &fitter, true, &mut Vec::new()).unwrap();
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
            let (model, _, path) =
                fit_samples(&none, &choice, &fitter, true, &mut Vec::new()).unwrap();
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

    /// A term that hardly decays is held at the least decay a supported term has: at the limit
    /// the fall-off is the same on either side of it (no jump), and within ±5 % of the given one
    /// over the sampled range; terms held at one rate are joined.
    #[test]
    fn a_non_decaying_term_is_held_at_the_least_decay_continuously() {
        use super::light::with_least_decay;
        let (lo, hi) = (2.4, 12.6);
        let limit = MIN_DECAY / (hi - lo);
        let f = |d: f64| ExpSum::new(vec![Term { c: 1e-3, d: -0.7 }, Term { c: 3e-5, d }]).unwrap();
        let rs: Vec<f64> = (0..=50).map(|k| lo + (hi - lo) * k as f64 / 50.0).collect();
        // Just above the limit: supported, nothing to do; just below: held, and the same curve.
        let above = f(-limit * (1.0 + 1e-9));
        assert_eq!(unsupported_term(&above, &rs), None);
        let below = f(-limit * (1.0 - 1e-9));
        assert_eq!(
            unsupported_term(&below, &rs),
            Some(TermDropped::NonDecaying)
        );
        let held = with_least_decay(&below, lo, hi).unwrap();
        assert_eq!(unsupported_term(&held, &rs), None);
        for &r in &rs {
            assert!((held.ln_eval(r) - above.ln_eval(r)).abs() < 1e-8, "{r}");
        }
        // Far below (d ≈ −1e−16): within e^{±MIN_DECAY/2} over the range.
        let flat = f(-1e-16);
        let held = with_least_decay(&flat, lo, hi).unwrap();
        assert_eq!(held.n(), 2);
        for &r in &rs {
            assert!(
                (held.ln_eval(r) - flat.ln_eval(r)).abs() <= 0.5 * MIN_DECAY + 1e-9,
                "{r}"
            );
        }
        // Two flat terms end at one rate: joined.
        let two = ExpSum::new(vec![
            Term { c: 1e-3, d: -0.7 },
            Term { c: 2e-5, d: -1e-4 },
            Term { c: 1e-5, d: -1e-3 },
        ])
        .unwrap();
        let held = with_least_decay(&two, lo, hi).unwrap();
        assert_eq!(held.n(), 2);
        assert_eq!(unsupported_term(&held, &rs), None);
        assert_eq!(with_least_decay(&two, 3.0, 3.0), None);
    }

    /// Samples of a fall-off with a slow tail whose fit's slowest rate falls below the limit:
    /// the fit keeps both terms, the slow one held at the limit, instead of refitting one term of
    /// another shape.
    #[test]
    fn a_slow_tail_keeps_its_term_held_at_the_least_decay() {
        let truth =
            ExpSum::new(vec![Term { c: 1e-3, d: -0.7 }, Term { c: 4e-5, d: -1e-4 }]).unwrap();
        let r: Vec<f64> = (0..200).map(|k| 2.4 + 10.2 * k as f64 / 199.0).collect();
        let s: Vec<f64> = r.iter().map(|&x| truth.eval(x)).collect();
        let opts = FitOptions {
            terms: crate::fit::Terms::Fixed(2),
            ..Default::default()
        };
        let mut dropped = Vec::new();
        let f = super::light::fit_supported(&opts, &r, &s, None, &mut dropped).unwrap();
        assert_eq!(f.n(), 2, "{f:?}");
        assert_eq!(dropped, [TermDropped::HeldAtLeastDecay]);
        let worst = r
            .iter()
            .zip(&s)
            .map(|(&x, &y)| (f.ln_eval(x) - y.ln()).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.5 * MIN_DECAY, "{worst} {f:?}");
        // Dropped instead (the baseline's rule), the same samples get one term of another shape.
        let mut dropped = Vec::new();
        let g = super::light::fit_supported(&AtMost::dropping(&opts), &r, &s, None, &mut dropped);
        assert_eq!(g.map(|g| g.n()), Ok(1));
        assert_eq!(dropped, [TermDropped::NonDecaying]);
    }
}
