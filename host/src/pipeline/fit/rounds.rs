//! The alpha rounds (Eq. 6) and their keep rule: a round (the alpha step and the refit) is
//! kept only if it lowers the training objective; the modulation texture alpha(x_o) from the
//! kept round's fits.

use super::*;

/// Most parallel tasks a fit round folds the light positions in ([`fit_groups`]): each holds
/// its own alpha accumulators (one per vertex and channel), so their number bounds the memory
/// (32 × 72 bytes per vertex), and it depends on the scan alone, never on the thread count.
pub(super) const FOLD_CHUNKS: usize = 32;

/// Per vertex and channel, the sufficient statistics of the training objective over the
/// vertex's samples: with e = ln R_d − ln s (s as captured), the vertex's share of
/// O(R_d, alpha) = Σ (ln alpha + e)^2 is n·ln²alpha + 2·ln alpha·Σe + Σe² for *any* alpha. So the
/// objective of a round's fits under the alpha Eq. 6 then derives from them (the model the round
/// leaves) is known without another pass over the samples.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct ObjectiveStats {
    n: f64,
    sum: f64,
    sum_sq: f64,
}

impl ObjectiveStats {
    pub(super) fn add(&mut self, e: f64) {
        if e.is_finite() {
            self.n += 1.0;
            self.sum += e;
            self.sum_sq += e * e;
        }
    }

    pub(super) fn merge(&mut self, o: &ObjectiveStats) {
        self.n += o.n;
        self.sum += o.sum;
        self.sum_sq += o.sum_sq;
    }

    /// Σ (ln alpha + e)^2 at `ln_alpha`.
    pub(super) fn at(&self, ln_alpha: f64) -> f64 {
        (self.n * ln_alpha * ln_alpha + 2.0 * ln_alpha * self.sum + self.sum_sq).max(0.0)
    }
}

/// One round's results, folded over the groups in parallel.
///
/// A chunk of groups folds its Eq. 6 accumulators sparsely, one slot per vertex its samples
/// reach (`slots`, `vertices`); the merged state is dense, one entry per mesh vertex. Why:
/// dense per-chunk arrays cost the chunks × the vertices (32 × 144 bytes × 655,362 vertices,
/// 3 GB, on sample-pebble's mesh subdivided to scanner density) for samples that
/// reach a few thousand vertices each. The sums are added in the same order as before. The
/// slots are found with foldhash, not std's SipHash: every sample of every round of every fold
/// looks its vertex up (a twentieth of `scan1024`'s CPU with SipHash), the keys are our own
/// vertex numbers (no adversary), and the slots' order is the order of first use whatever the
/// hasher, so the sums keep their bits.
#[derive(Default)]
pub(super) struct RoundState {
    fits: Vec<(usize, Result<GroupFit, FailReason>)>,
    /// Whether a group of this state has a fit (the dense arrays exist once one has).
    any: bool,
    /// Sparse (a chunk): vertex → slot of `alpha` and `objective_stats`.
    slots: HashMap<u32, u32, foldhash::fast::FixedState>,
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
    pub(super) fn slot(&mut self, v: u32) -> usize {
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
    pub(super) fn merge_chunk(mut self, mut other: RoundState, nv: usize) -> RoundState {
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
    pub(super) fn objective_with(&self, alpha: &[[f64; 3]]) -> f64 {
        self.objective_stats
            .iter()
            .zip(alpha)
            .map(|(st, a)| (0..3).map(|c| st[c].at(a[c].ln())).sum::<f64>())
            .sum()
    }

    /// The fits by group index (`None`: the group has none).
    pub(super) fn by_index(&self, groups: usize) -> Vec<Option<GroupFit>> {
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
pub(super) fn sq_err(m: &ColourModel, data: &ChannelSamples) -> f64 {
    sq_err_at(&ln_rd_at(m, data, false), &ln_s_of(data, false))
}

/// ln s of each of a group's samples, per channel (their order); `vectorised`: by
/// [`crate::fit::ln_many`] ([`Fitter::rounding_cuts`]).
pub(super) fn ln_s_of(data: &ChannelSamples, vectorised: bool) -> [Vec<f64>; 3] {
    data.each_ref()
        .map(|d| ln_of(d.iter().map(|x| x.s), vectorised))
}

/// ln of each of `values`: vectorised ([`crate::fit::ln_many`], within a few ulp;
/// [`Fitter::rounding_cuts`]) or libm's per value (the reference's bits).
pub(super) fn ln_of(values: impl Iterator<Item = f64>, vectorised: bool) -> Vec<f64> {
    if vectorised {
        let x: Vec<f64> = values.collect();
        let mut out = vec![0.0; x.len()];
        crate::fit::ln_many(&x, &mut out);
        out
    } else {
        values.map(f64::ln).collect()
    }
}

/// ln R_d of `f` (its terms' ln c_k given, [`ExpSum::ln_c`]) at each distance of `r`:
/// vectorised ([`ExpSum::ln_eval_many`]) or per distance (the reference's bits).
pub(super) fn ln_rd_of(f: &ExpSum, ln_c: &[f64], r: &[f64], vectorised: bool) -> Vec<f64> {
    if vectorised {
        let mut v = vec![0.0; r.len()];
        f.ln_eval_many(ln_c, r, &mut v);
        v
    } else {
        r.iter().map(|&x| f.ln_eval_with(ln_c, x)).collect()
    }
}

/// ln R_d of a model at each of a group's samples, per channel (their order).
pub(super) fn ln_rd_at(m: &ColourModel, data: &ChannelSamples, vectorised: bool) -> [Vec<f64>; 3] {
    ln_rd_with(&m.ln_evaluator(), data, true, vectorised)
}

/// [`ln_rd_at`] with the model's evaluator. With shared colour (Eq. 5) a sample of channel 1 or
/// 2 at the very (r, φ) of the red sample at its index (the usual case: a frame measures its
/// channels at the same pixels) takes the red fall-off's value plus its channel's ln s_c
/// ([`crate::model::LnEvaluator::shared_offset`]): the same bits, one evaluation instead of
/// three. `directions = false` evaluates every sample without its direction (φ = `None`, as
/// the isotropic baseline is judged). `vectorised`: a fall-off of one segment at every sample
/// of a channel at once ([`crate::model::LnEvaluator::ln_eval_channel_many`], within a few
/// ulp), the red one and any channel whose samples are not the red ones.
pub(in crate::pipeline) fn ln_rd_with(
    ev: &crate::model::LnEvaluator,
    data: &ChannelSamples,
    directions: bool,
    vectorised: bool,
) -> [Vec<f64>; 3] {
    let phi = |x: &GroupSample| if directions { x.phi } else { None };
    let batch = |ch: usize| -> Option<Vec<f64>> {
        let r: Vec<f64> = data[ch].iter().map(|x| x.r).collect();
        let mut out = vec![0.0; r.len()];
        ev.ln_eval_channel_many(ch, &r, &mut out).then_some(out)
    };
    // Vectorised, the red fall-off at every sample at once where it has one segment (φ
    // changes nothing then).
    let red: Vec<f64> = vectorised.then(|| batch(0)).flatten().unwrap_or_else(|| {
        data[0]
            .iter()
            .map(|x| ev.ln_eval_channel(0, x.r, phi(x)))
            .collect()
    });
    let same = |a: &GroupSample, b: &GroupSample| {
        a.r.to_bits() == b.r.to_bits() && phi(a).map(f64::to_bits) == phi(b).map(f64::to_bits)
    };
    let other = |ch: usize| -> Vec<f64> {
        let offset = ev.shared_offset(ch);
        // A channel whose samples are not the red ones index by index (a sample of one channel
        // dropped, below the noise floor or saturated, shifts every later one) is evaluated
        // on its own: vectorised, all at once.
        let aligned = || {
            offset.is_some()
                && data[ch].len() <= data[0].len()
                && data[ch].iter().zip(&data[0]).all(|(x, y)| same(x, y))
        };
        if vectorised
            && !aligned()
            && let Some(v) = batch(ch)
        {
            return v;
        }
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
pub(super) fn sq_err_at(ln_rd: &[Vec<f64>; 3], ln_s: &[Vec<f64>; 3]) -> f64 {
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
pub(super) struct RoundRunner<'r, 'a> {
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
    pub(super) fn run(
        &self,
        alpha_div: Option<&[[f64; 3]]>,
        round: usize,
        prev: Option<&[Option<GroupFit>]>,
    ) -> RoundState {
        let (ctx, regs, groups, fitter) = (self.ctx, self.regs, self.groups, self.fitter);
        let opts = &ctx.opts;
        let nv = ctx.ds.mesh.positions.len();
        let base_model = self.base_model.as_ref();
        let vectorised = fitter.rounding_cuts();
        self.progress.start(
            &format!("fit (round {})", round + 1),
            groups.keys.len() as u64,
        );
        // Groups are folded in fixed chunks, sequentially within a chunk, and the chunks merged
        // in order: the float sums (alpha, objective) then associate the same way on every
        // run and with any number of threads, so a fit is repeatable bit for bit (rayon's
        // `fold` splits where work stealing happens to, and later alpha rounds would inherit
        // the rounding differences).
        let step = |mut st: RoundState, (idx, key): (usize, &crate::pipeline::select::GroupKey)| {
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
                let ln_s = ln_s_of(&data, vectorised);
                let scored = |m: &ColourModel| {
                    let ln_rd = ln_rd_at(m, &data, vectorised);
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
                        // The captured samples' logs at once where the fitter's are vectorised.
                        let ln_captured = (alpha_div.is_some() && vectorised)
                            .then(|| ln_of(d.iter().map(captured), true));
                        for (j, ((x, &ln_rd), &ln_s)) in
                            d.iter().zip(&ln_rd[ch]).zip(&ln_s[ch]).enumerate()
                        {
                            let s = captured(x);
                            // As captured (round 0) s is the sample itself, its log known.
                            let ln_s = match (&ln_captured, alpha_div) {
                                (Some(l), _) => l[j],
                                (None, Some(_)) => s.ln(),
                                (None, None) => ln_s,
                            };
                            let i = st.slot(x.vertex);
                            if let Some(v) =
                                AlphaAccumulator::ln_ratio_with(s, ln_s, ln_rd, &window)
                            {
                                st.alpha[i][ch].add_ratio(v);
                            }
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
    /// The alpha fill's factor, kept from round to round ([`alpha_texture`]).
    alpha_factor: crate::interpolate::FactorCache,
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
        let baseline = match cache {
            Some(c) => c.baseline(ctx, regs, groups, || {
                fit_baseline(ctx, regs, groups, fitter)
            }),
            None => fit_baseline(ctx, regs, groups, fitter),
        };
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
        let alpha_factor = crate::interpolate::FactorCache::default();
        let (alpha, alpha_report) = alpha_texture(
            &state.alpha,
            ctx.ds.mesh.positions.len(),
            &ctx.scene,
            ctx.opts.alpha_shrinkage,
            ctx.opts.speed,
            &alpha_factor,
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
            alpha_factor,
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
            opts.speed,
            &self.alpha_factor,
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

/// RMS over vertices and channels of the change of ln alpha(x_o) between two rounds.
pub(super) fn rms_ln_change(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
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
pub(super) fn alpha_texture(
    acc: &[[AlphaAccumulator; 3]],
    nv: usize,
    scene: &Scene,
    shrinkage: f64,
    speed: crate::pipeline::Speed,
    factor: &crate::interpolate::FactorCache,
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
    // The default path solves by the Laplace rows' factor, kept while the rounds of a fit keep
    // the known set (all of them, mostly): exact up to rounding, whatever round it starts from,
    // so a fit with r rounds is still round r of a longer one. The reference, as before issue
    // 40, solves by conjugate gradients from the breadth-first guess to the exact tolerance.
    let solve = crate::interpolate::Solve {
        iterations: 500,
        rtol: match speed {
            crate::pipeline::Speed::Default => crate::pipeline::FILL_TOLERANCE,
            crate::pipeline::Speed::Reference => crate::interpolate::RTOL,
        },
        direct: match speed {
            crate::pipeline::Speed::Default => Some(factor),
            crate::pipeline::Speed::Reference => None,
        },
        ..crate::interpolate::Solve::default()
    };
    let filled = crate::interpolate::harmonic_with(&own, |v| scene.neighbours(v), &solve);
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
