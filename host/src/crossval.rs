//! The fit's choices made by how well the model predicts frames its fit did not see, not by
//! how well it fits: k-fold cross-validation over the training frames.
//!
//! The folds are turntable-aware ([`folds`]): whole turntable angles when the scan has several
//! (a frame at an angle the fit saw has its x_i beside a fitted one and would measure little
//! more than noise), else raster positions spread over the scan's order. Each fold's frames are
//! held out of one fit of the rest and judged as `subsurf evaluate` judges them
//! ([`crate::evaluate::evaluate_in`], at the vertices, with the run's options), from the run's
//! sample store: no frame is read again (`Context::store`).
//!
//! What is chosen so: the direction segments m with `--segments auto` (per scan, among
//! [`SEGMENT_LADDER`]), Eq. 6's t1 ([`T1_CANDIDATE`] or none) and the number of alpha rounds
//! (Eq. 6) for the chosen m, then whether the lattice of alpha finer than the mesh is written
//! ([`judge_lattice`], judged at surface points, where its detail is not 0). The rounds cost
//! nothing extra: every fold fit hands out its model after each round
//! ([`crate::pipeline::fit_prepared_rounds`]). The rule is the one-standard-error rule of
//! cross-validation (Breiman et al. 1984; Hastie, Tibshirani and Friedman, *Elements of
//! Statistical Learning*, 7.10): the simplest candidate whose mean held-out error is within one
//! standard error (paired over the held-out frames) of the best, because on a few dozen frames
//! the best candidate's lead is often noise, and the simpler model is the one that carries to
//! new light positions. Handwritten: the criterion is the product's own (Eq. 8's log E per
//! held-out frame, the figure `evaluate` prints), which no CV crate computes.
use std::collections::BTreeMap;

use crate::dataset::Dataset;
use crate::evaluate::summary::clustered_mean;
use crate::evaluate::{Clustering, EvalPoints, FrameEval, evaluate_in};
use crate::modelfile::ModelFile;
use crate::pipeline::{
    AlphaLattice, Context, CvCandidate, CvChoice, CvReport, FitOutput, FitRounds, Fitter,
    LogEStats, PipelineError, PipelineOptions, Prepared,
    fill::FillState,
    fit::{Fitted, OrderCache},
    fit_prepared_with,
};
use crate::progress::Progress;
use rayon::prelude::*;

/// Folds of `subsurf fit --cv-folds` by default: five, the usual compromise between the bias of
/// few folds (each fit sees 80 % of the frames) and the cost of many.
pub const DEFAULT_FOLDS: usize = 5;

/// Rounds in a row without a real improvement after which the folds' alpha rounds stop
/// (`--cv-patience`): two, with a real improvement being at least [`MIN_GAIN_SE`] standard
/// errors (Prechelt 1998's early stopping with a minimum improvement). Why: the rounds'
/// held-out curve of real scans moves by less than a thousandth after round 1, so most of the
/// rounds the reference preset ([`CvSettings::reference`]) scores are within noise of each
/// other. Two, not one: with one, the simulated blob's t1 choice flipped between two
/// candidates within one SE of each other and its alpha moved by 0.011 RMS in ln, above issue
/// 40's 0.01; with two, every scan of `subsurf bench equivalence` makes the reference's choices
/// (BENCHMARKS.md).
pub const DEFAULT_PATIENCE: usize = 2;

/// How much a round must lower the best cross-validated error to count as lowering it, in
/// standard errors of the paired difference (clustered by fold, as the one-SE rule takes it):
/// half. Below it, a round is noise, and with [`DEFAULT_PATIENCE`] the folds stop.
pub const MIN_GAIN_SE: f64 = 0.5;

/// The patience of the reference preset, the exact path: two rounds in a row without any
/// lower error ("a single round may tie within rounding of the best and the next still
/// fall").
pub const REFERENCE_PATIENCE: usize = 2;

/// How many direction segments m (Eq. 3) the fit uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Segments {
    /// Exactly m.
    Fixed(usize),
    /// "Model only what the scene requires": the m of [`SEGMENT_LADDER`] chosen by
    /// cross-validation (needs at least 2 folds).
    Auto,
}

/// The values of m `--segments auto` tries, simplest first.
pub const SEGMENT_LADDER: [usize; 4] = [1, 2, 4, 8];

/// What a fit chooses by cross-validation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CvSettings {
    /// Folds (`--cv-folds`); below 2 nothing is cross-validated and every setting keeps the
    /// value given.
    pub folds: usize,
    /// The direction segments.
    pub segments: Segments,
    /// Whether the number of alpha rounds (at most `PipelineOptions::alpha_rounds`) is chosen.
    pub rounds: bool,
    /// The folds' rounds stop once this many rounds in a row have not lowered the best
    /// cross-validated error by `min_gain_se` standard errors (`--cv-patience`; 0: every round
    /// to the limit is scored).
    pub patience: usize,
    /// The least improvement that counts, in clustered standard errors of the paired
    /// difference ([`MIN_GAIN_SE`]; 0: any lower mean, the reference preset's rule).
    pub min_gain_se: f64,
    /// Whether Eq. 6's upper threshold t1 is chosen per scan, off against [`T1_CANDIDATE`]
    /// (when the run's options leave it off; `subsurf fit --alpha-t1-share` fixes it).
    pub t1: bool,
    /// Whether the lattice of alpha finer than the mesh (`face_alpha`, [`crate::pipeline::detail`])
    /// is written only when the folds, judged at surface points, say it predicts better
    /// ([`judge_lattice`]); `subsurf fit --alpha-lattice` given fixes it. Only where the run's
    /// lattice is on and the fit on every frame wrote one.
    pub lattice: bool,
}

impl CvSettings {
    /// The cross-validation of the reference preset (`subsurf fit --preset reference`): the
    /// exact path without the cost cuts, kept so that the default's equivalence can be re-checked
    /// (`subsurf bench equivalence`): five folds for every choice, every round scored until two
    /// in a row do not lower the best at all.
    pub fn reference() -> Self {
        CvSettings {
            patience: REFERENCE_PATIENCE,
            min_gain_se: 0.0,
            ..CvSettings::default()
        }
    }
}

/// The t1 share ([`crate::pipeline::ALPHA_T1_SHARE`]'s alternative) the cross-validation weighs
/// against none. Why per scan: on training frames (docs/validation.md) a t1 at 0.3 of each light
/// position's brightest sample predicted better on sample-slab, sample-torus and the simulated
/// torus (by 3, 1.8 and 3.6 standard errors), the same on the textured slab, and worse within
/// noise on sample-pebble; 0.1 gained little more where t1 helped and lost more where it hurt
/// (sample-pebble: 3.8 standard errors); and on the anisotropic simulated slab of `fit_aniso`,
/// whose near field is multiple scattering blurred by the pixels, alpha needs the bright
/// samples. No constant fits every scan.
pub const T1_CANDIDATE: f64 = 0.3;

impl Default for CvSettings {
    fn default() -> Self {
        CvSettings {
            folds: DEFAULT_FOLDS,
            segments: Segments::Fixed(1),
            rounds: true,
            patience: DEFAULT_PATIENCE,
            min_gain_se: MIN_GAIN_SE,
            t1: true,
            lattice: true,
        }
    }
}

/// Splits `frames` into at most `k` folds: with at least 2 distinct turntable angles, whole
/// angles (in angle order, angle i to fold i mod k), else frames in scan order (frame j to fold
/// j mod k, so each fold's raster positions are spread over the scan). Folds are never empty;
/// the rule in words second.
pub fn folds(ds: &Dataset, frames: &[usize], k: usize) -> (Vec<Vec<usize>>, String) {
    let angle = |f: usize| ds.spec.frames[f].turntable_deg.rem_euclid(360.0);
    let angles = distinct_angles(ds, frames);
    if angles.len() >= 2 {
        let k = k.min(angles.len()).max(1);
        let mut out = vec![Vec::new(); k];
        for &f in frames {
            let i = angles
                .iter()
                .position(|a| (a - angle(f)).abs() < 1e-6)
                .unwrap_or(0);
            out[i % k].push(f);
        }
        out.retain(|f| !f.is_empty());
        let rule = format!(
            "{} folds of whole turntable angles (the scan's {} angles dealt round-robin in angle order)",
            out.len(),
            angles.len()
        );
        (out, rule)
    } else {
        let k = k.min(frames.len()).max(1);
        let mut out = vec![Vec::new(); k];
        for (j, &f) in frames.iter().enumerate() {
            out[j % k].push(f);
        }
        out.retain(|f| !f.is_empty());
        let rule = format!(
            "{} folds of raster positions (one turntable angle: frame j of the scan's order to fold j mod {})",
            out.len(),
            out.len()
        );
        (out, rule)
    }
}

/// The distinct turntable angles of `frames`, in order (within 1e-6 degrees).
fn distinct_angles(ds: &Dataset, frames: &[usize]) -> Vec<f64> {
    let mut angles: Vec<f64> = frames
        .iter()
        .map(|&f| ds.spec.frames[f].turntable_deg.rem_euclid(360.0))
        .collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    angles
}

/// Held-out log E per frame (r, g, b; NaN where missing), each frame judged by the fold fit that
/// did not see it.
type Errors = BTreeMap<usize, [f64; 3]>;

/// One grid of the cross-validation: the folds' fits of one setting, scored after every round.
struct Grid {
    /// The pooled held-out errors per number of alpha rounds 0..: entry r is the model a fit
    /// with `alpha_rounds = r` leaves (a fold whose rounds stopped before r contributes its last
    /// model).
    errors: Vec<Errors>,
    /// The most rounds any fold's fit kept.
    most: usize,
    /// Per fold (empty unless asked), its selection and its fit's state after every round it
    /// ran (`None`: the fold failed).
    states: Vec<Option<FoldState>>,
}

/// A fold's fit as the rounds left it: its model at every round it ran, and what the lattice
/// is found from.
struct FoldState {
    prepared: Prepared,
    /// After round 0, 1, ... (the last where its rounds stopped): the fit's state and the model
    /// it left (without a lattice: the folds' fits skip that stage).
    fitted: Vec<RoundModel>,
}

/// A fold fit's state after a round and the model it left.
type RoundModel = (Fitted, ModelFile);

impl Grid {
    /// Drops every fold's states but the one at `rounds` (or its last, where its rounds stopped
    /// before): the only one the lattice's judgement reads.
    fn keep_states_at(&mut self, rounds: usize) {
        for s in self.states.iter_mut().flatten() {
            let at = rounds.min(s.fitted.len().saturating_sub(1));
            s.fitted.truncate(at + 1);
            s.fitted.drain(..at);
        }
    }
}

/// The cross-validated errors of the run's options `ctx.opts` on `folds` (of `frames`), per
/// number of alpha rounds ([`Grid`]).
///
/// The folds' fits run side by side ([`crate::pipeline::Prepared`]), round by round, the folds
/// in parallel: after each round the pooled errors so far choose their best number of rounds,
/// and once `patience` rounds in a row (0: never) have not lowered it, no fold runs another
/// round ([`rounds_exhausted`]).
///
/// With `keep_states`, each fold's fit state after every round is kept with its selection
/// ([`Grid::states`]): the lattice's judgement ([`judge_lattice`]) then adds the lattice to the
/// fold's model at the rounds chosen, without fitting or finishing the fold again.
#[allow(clippy::too_many_arguments)]
fn cross_validate(
    ctx: &Context,
    judge: &Context,
    frames: &[usize],
    folds: &[Vec<usize>],
    fitter: &dyn Fitter,
    cache: &OrderCache,
    (patience, min_gain_se): (usize, f64),
    keep_states: bool,
    progress: &dyn Progress,
    fits: &mut usize,
    fills: &mut [Option<FillState>],
) -> Result<Grid, PipelineError> {
    let max_rounds = ctx.opts.alpha_rounds;
    let clusters = &Clustering::of_folds(folds);
    // The folds are judged at the vertices, where alpha finer than the mesh changes nothing
    // (`EvalPoints::Vertices`): their fits skip the lattice stage, the same errors for less.
    let ctx = &ctx.with_options(PipelineOptions {
        alpha_lattice: AlphaLattice::Off,
        ..ctx.opts
    })?;
    let trains: Vec<Vec<usize>> = folds
        .iter()
        .map(|fold| {
            frames
                .iter()
                .copied()
                .filter(|f| !fold.contains(f))
                .collect()
        })
        .collect();
    // A fold whose fit or evaluation fails (too few light positions left) predicts none of its
    // frames: it drops out of every candidate's comparison.
    let prepared: Vec<Option<Prepared>> = trains
        .par_iter()
        .map(|t| Prepared::new(ctx, t).ok())
        .collect();
    let needed: Vec<Vec<bool>> = folds.par_iter().map(|f| read_vertices(judge, f)).collect();
    let mut runs: Vec<Option<FitRounds>> = prepared
        .par_iter()
        .map(|p| p.as_ref().map(|p| p.rounds(ctx, fitter, Some(cache), &())))
        .collect();
    // The fold's fills start from its last run's (another candidate's), see
    // `FitRounds::start_fill_from`.
    for (run, fill) in runs.iter().zip(fills.iter()) {
        if let (Some(run), Some(fill)) = (run, fill) {
            run.start_fill_from(fill.clone());
        }
    }
    // A fold's run is dropped (`None`) when its rounds end; a failed fold's errors with it.
    let mut by_round: Vec<Vec<Vec<FrameEval>>> = vec![Vec::new(); folds.len()];
    let mut states: Vec<Vec<RoundModel>> = vec![Vec::new(); folds.len()];
    for r in 0..=max_rounds {
        let judged: Vec<Option<(Vec<FrameEval>, Option<RoundModel>)>> = runs
            .par_iter()
            .zip(folds)
            .zip(&needed)
            .map(|((run, fold), needed)| {
                let run = run.as_ref()?;
                let model = run.model_file_for(needed).ok()?;
                let (evals, _) =
                    evaluate_in(judge, &model, fold, EvalPoints::Vertices, &()).ok()?;
                Some((evals, keep_states.then(|| (run.fitted(), model))))
            })
            .collect();
        for (run, fill) in runs.iter().zip(fills.iter_mut()) {
            if let Some(state) = run
                .as_ref()
                .and_then(FitRounds::fill_state)
                .filter(FillState::has_weights)
            {
                *fill = Some(state);
            }
        }
        for (((run, fold), state), evals) in runs
            .iter_mut()
            .zip(&mut by_round)
            .zip(&mut states)
            .zip(judged)
        {
            match evals {
                _ if run.is_none() => {}
                Some((evals, fitted)) => {
                    fold.push(evals);
                    state.extend(fitted);
                }
                None => {
                    fold.clear();
                    state.clear();
                    *run = None;
                }
            }
        }
        if r == max_rounds
            || rounds_exhausted(&pooled(&by_round, r), clusters, patience, min_gain_se)
        {
            break;
        }
        runs.par_iter_mut().for_each(|run| {
            if run.as_mut().is_some_and(|run| !run.step()) {
                *run = None;
            }
        });
        if runs.iter().all(Option::is_none) {
            break;
        }
    }
    *fits += folds.len();
    progress.inc(folds.len() as u64);
    let most = by_round
        .iter()
        .filter_map(|b| b.len().checked_sub(1))
        .max()
        .unwrap_or(0);
    drop(runs);
    let states = if keep_states {
        prepared
            .into_iter()
            .zip(states)
            .map(|(p, fitted)| {
                p.filter(|_| !fitted.is_empty())
                    .map(|prepared| FoldState { prepared, fitted })
            })
            .collect()
    } else {
        Vec::new()
    };
    Ok(Grid {
        errors: pooled(&by_round, max_rounds),
        most,
        states,
    })
}

/// The vertices whose model judging the frames `fold` reads: the corners of each registered
/// frame's x_i triangle ([`crate::evaluate::model_at`]). A fold's fit needs a model nowhere
/// else, so its fill refits only these ([`FitRounds::model_file_for`]).
fn read_vertices(judge: &Context, fold: &[usize]) -> Vec<bool> {
    let mut read = vec![false; judge.ds.mesh.positions.len()];
    for &f in fold {
        let Ok(reg) = crate::pipeline::register_one(judge, f) else {
            continue;
        };
        if let Some(t) = judge.scene.mesh.triangles.get(reg.triangle as usize) {
            for &v in t {
                if let Some(r) = read.get_mut(v as usize) {
                    *r = true;
                }
            }
        }
    }
    read
}

/// The folds' held-out errors per number of rounds 0..=`last`, every fold with errors (a failed
/// fold has none) contributing its model after that many rounds, or its last model where its
/// rounds stopped before.
fn pooled(by_round: &[Vec<Vec<FrameEval>>], last: usize) -> Vec<Errors> {
    let mut per_round: Vec<Errors> = vec![Errors::new(); last + 1];
    for fold in by_round.iter().filter(|b| !b.is_empty()) {
        for (r, errs) in per_round.iter_mut().enumerate() {
            let evals = &fold[r.min(fold.len() - 1)];
            for e in evals.iter().filter(|e| e.skipped.is_none()) {
                errs.insert(e.frame, e.log_e.map(|v| v.unwrap_or(f64::NAN)));
            }
        }
    }
    per_round
}

/// Whether the rounds tried so far (`per_round`, 0..=r) have had `patience` rounds in a row
/// that did not lower the best so far by `min_gain_se` standard errors of their paired
/// difference (clustered by fold, as [`one_se`] takes it): early stopping with a minimum
/// improvement (Prechelt 1998), the usual cut of an iteration judged on held-out data. The
/// alpha rounds are a fixed-point iteration whose held-out error falls to a minimum and then
/// rises or levels off as the texture fits the noise (docs/validation.md, "How far the rounds
/// run"); a round that gains less than noise cannot move the one-SE choice by more than
/// noise. `min_gain_se` 0: any lower mean counts (the reference preset). `patience` 0: never
/// stop.
fn rounds_exhausted(
    per_round: &[Errors],
    clusters: &Clustering,
    patience: usize,
    min_gain_se: f64,
) -> bool {
    if patience == 0 || per_round.len() <= patience {
        return false;
    }
    if min_gain_se <= 0.0 {
        let cands: Vec<(String, &Errors)> = per_round
            .iter()
            .enumerate()
            .map(|(r, e)| (r.to_string(), e))
            .collect();
        let (_, rows) = one_se(&cands, clusters);
        let best = rows
            .iter()
            .enumerate()
            .filter_map(|(i, c)| c.score.map(|s| (i, s)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|b| b.0);
        return best.is_some_and(|b| per_round.len() - 1 - b >= patience);
    }
    let (mut best, mut stalled) = (0, 0);
    // The best so far changes only by a real gain; the rounds after it count as stalled.
    for r in 1..per_round.len() {
        match paired_gain(&per_round[best], &per_round[r], clusters) {
            Some((gain, se)) if counts_as_gain(gain, se, min_gain_se) => {
                best = r;
                stalled = 0;
            }
            _ => stalled += 1,
        }
    }
    stalled >= patience
}

/// Whether a paired fall of held-out error `gain` (positive: better) with standard error `se`
/// counts as a real gain: it exceeds `min_gain_se` standard errors ([`MIN_GAIN_SE`], half, for the
/// alpha rounds and the adaptive planner's stop alike; 0: any fall counts). An SE that could not
/// be measured, or is zero or not finite, counts as infinite
/// ([`crate::evaluate::summary::ClusteredMean::decision_se`]), so with `min_gain_se` above 0 no
/// gain counts on a spread nobody measured.
pub fn counts_as_gain(gain: f64, se: f64, min_gain_se: f64) -> bool {
    if !(gain.is_finite() && gain > 0.0) {
        return false;
    }
    if min_gain_se <= 0.0 {
        return true;
    }
    se.is_finite() && se > 0.0 && gain >= min_gain_se * se
}

/// How much `b` lowers `a`'s held-out error (mean over the frames both predicted of the paired
/// difference a − b) and that mean's standard error clustered by `clusters`.
fn paired_gain(a: &Errors, b: &Errors, clusters: &Clustering) -> Option<(f64, f64)> {
    let d: Vec<(f64, f64, (bool, usize))> = a
        .iter()
        .filter_map(|(&f, va)| {
            let (ea, eb) = (frame_error(va)?, frame_error(b.get(&f)?)?);
            Some((ea - eb, 1.0, clusters.cluster(f)))
        })
        .collect();
    // A spread that could not be measured (one fold judged) is infinite: no gain counts.
    clustered_mean(&d).map(|m| (m.mean, m.decision_se()))
}

/// Mean over its finite channels of a frame's log E.
fn frame_error(v: &[f64; 3]) -> Option<f64> {
    let f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    (!f.is_empty()).then(|| f.iter().sum::<f64>() / f.len() as f64)
}

/// The one-standard-error choice among `candidates` (value, errors), simplest first: scores over
/// the frames every candidate with data predicted; the index chosen (`None` when no candidate
/// predicted any frame) and the report's rows.
///
/// Which standard error: that of the paired difference between the candidate and the best,
/// over the frames both predicted, clustered by `clusters` (the folds: the frames of one fold
/// share one fit, and a fold holds whole turntable angles, whose frames share their views;
/// [`crate::evaluate::summary::Clustering::rule`]). Hastie, Tibshirani and Friedman (7.10) take
/// instead the standard error of the best candidate's own error over the K folds. The paired SE
/// is smaller: a fold that is hard (a grazing angle, a thin part) is hard for every candidate,
/// and that shared spread says nothing about which candidate predicts better, only how hard
/// the folds are. So this rule is less parsimonious than theirs: it keeps a more complex
/// candidate whenever the folds agree that it predicts better by more than the spread of that
/// difference, where theirs would drop it whenever the folds differ in difficulty by more than
/// the gain. We keep the paired SE because the question the rule answers is "is the gain real",
/// which is a question about the difference.
///
/// A standard error that could not be measured (one fold judged) or came out zero is infinite
/// ([`crate::evaluate::summary::ClusteredMean::decision_se`]): every candidate is then within
/// it, and the simplest candidate that predicted anything is kept.
fn one_se(
    candidates: &[(String, &Errors)],
    clusters: &Clustering,
) -> (Option<usize>, Vec<CvCandidate>) {
    let with_data: Vec<bool> = candidates
        .iter()
        .map(|(_, e)| e.values().any(|v| frame_error(v).is_some()))
        .collect();
    let common: Vec<usize> = candidates
        .iter()
        .find(|(_, e)| !e.is_empty())
        .map(|(_, e)| e.keys().copied().collect::<Vec<_>>())
        .unwrap_or_default()
        .into_iter()
        .filter(|f| {
            candidates
                .iter()
                .zip(&with_data)
                .filter(|(_, d)| **d)
                .all(|((_, e), _)| e.get(f).and_then(frame_error).is_some())
        })
        .collect();
    let err = |i: usize, f: usize| candidates[i].1.get(&f).and_then(frame_error);
    let score: Vec<Option<f64>> = (0..candidates.len())
        .map(|i| {
            (with_data[i] && !common.is_empty()).then(|| {
                common.iter().filter_map(|&f| err(i, f)).sum::<f64>() / common.len() as f64
            })
        })
        .collect();
    let best = (0..candidates.len())
        .filter_map(|i| score[i].map(|s| (i, s)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|b| b.0);
    let mut rows: Vec<CvCandidate> = candidates
        .iter()
        .map(|(value, e)| CvCandidate {
            value: value.clone(),
            held_out: LogEStats::of(&e.values().copied().collect::<Vec<_>>()),
            ..CvCandidate::default()
        })
        .collect();
    let Some(best) = best else {
        return (None, rows);
    };
    let mut chosen = None;
    for i in 0..candidates.len() {
        rows[i].score = score[i];
        if score[i].is_none() {
            rows[i].note = Some("predicted none of the compared frames".into());
            continue;
        }
        let d: Vec<(f64, f64, (bool, usize))> = common
            .iter()
            .filter_map(|&f| Some((err(i, f)? - err(best, f)?, 1.0, clusters.cluster(f))))
            .collect();
        let (mean, se, reported) = clustered_mean(&d).map_or((0.0, f64::INFINITY, None), |m| {
            (m.mean, m.decision_se(), m.se.filter(|s| s.is_finite()))
        });
        rows[i].worse_by = Some(mean);
        rows[i].se = reported;
        if chosen.is_none() && mean <= se {
            chosen = Some(i);
        }
    }
    let chosen = chosen.unwrap_or(best);
    rows[chosen].chosen = true;
    (Some(chosen), rows)
}

const ONE_SE_RULE: &str = "the simplest candidate whose mean held-out log E (frames every candidate predicted) is within one standard error of the best, the SE of the paired difference over those frames clustered by fold (tighter than the SE of the best's own error, so less parsimonious: a gain counts once the folds agree on it); an SE that could not be measured counts as infinite, keeping the simplest";

/// The choice of the number of alpha rounds among `per_round[..=most]`: the chosen number and
/// the report's choice. The fit on every frame runs at most that many rounds (fewer where its
/// rounds converge or stop lowering the objective first): no more than the folds validated.
/// Before, a choice equal to the most rounds any fold kept let the final fit run on to `max`,
/// rounds no fold had judged.
fn choose_rounds(
    per_round: &[Errors],
    most: usize,
    clusters: &Clustering,
    patience: usize,
) -> (usize, CvChoice) {
    let cands: Vec<(String, &Errors)> = per_round[..=most.min(per_round.len() - 1)]
        .iter()
        .enumerate()
        .map(|(r, e)| (r.to_string(), e))
        .collect();
    let (chosen, candidates) = one_se(&cands, clusters);
    let r = chosen.unwrap_or(most);
    let limit = r;
    let choice = CvChoice {
        name: "alpha_rounds".into(),
        rule: format!(
            "{ONE_SE_RULE}; rounds beyond the {most} any fold's fit kept are not candidates (the fits stop there on their own{})",
            if patience > 0 {
                format!(", or once {patience} rounds in a row have not lowered the best")
            } else {
                String::new()
            }
        ),
        candidates,
        chosen: r.to_string(),
    };
    (limit, choice)
}

/// The folds' held-out errors of the fit `ctx` (the settings chosen, the lattice on) at
/// surface points, without its lattice of alpha finer than the mesh (first) and with it
/// (second): per fold the fit of the other folds at the rounds the final fit runs, finished
/// with its lattice stage, its model judged twice, as it is and with its `face_alpha` dropped
/// (the lattice changes nothing else of a model: [`crate::pipeline::detail`] reads the fit,
/// never changes it).
///
/// Why at surface points: at the vertices the lattice's detail is 0 by construction, so the
/// rounds' judgement ([`cross_validate`], `EvalPoints::Vertices`) cannot see it. The points are
/// the run's lattice points (between the vertices, every face at the level its pixel footprint
/// asks for), whose samples the run's store holds, so no frame is read again; the samples
/// there are the ones the store keeps, above Eq. 6's t2 (10× the protocol's floor), by the
/// protocol's rules ([`crate::pipeline::judge_context`]). The lattice stage runs once per
/// fold, for the final round count only.
///
/// Where the rounds' grid kept the folds' fit states at the rounds chosen (`grid`,
/// [`Grid::keep_states_at`]), each fold's model is finished from its state, without fitting
/// again; else (no rounds were cross-validated) each fold is fitted once more.
#[allow(clippy::too_many_arguments)]
fn judge_lattice(
    ctx: &Context,
    judge: &Context,
    frames: &[usize],
    folds: &[Vec<usize>],
    grid: Option<&Grid>,
    fitter: &dyn Fitter,
    cache: &OrderCache,
    progress: &dyn Progress,
    fits: &mut usize,
) -> [Errors; 2] {
    // The level is not read: the run's store holds the points (`evaluate_in`).
    let at = EvalPoints::Surface {
        level: crate::lattice::MAX_LEVEL,
    };
    let states = grid
        .map(|g| &g.states[..])
        .filter(|s| s.len() == folds.len());
    let judged: Vec<Option<[Vec<FrameEval>; 2]>> = folds
        .par_iter()
        .enumerate()
        .map(|(i, fold)| {
            let model = match states {
                Some(states) => states[i].as_ref().and_then(|s| {
                    let (fitted, model) = s.fitted.last()?;
                    let mut model = model.clone();
                    model.face_alpha = s.prepared.lattice_of(ctx, fitted);
                    Some(model)
                }),
                None => {
                    let train: Vec<usize> = frames
                        .iter()
                        .copied()
                        .filter(|f| !fold.contains(f))
                        .collect();
                    Prepared::new(ctx, &train).ok().and_then(|prepared| {
                        let mut run = prepared.rounds(ctx, fitter, Some(cache), &());
                        while run.step() {}
                        run.model_file_for(&read_vertices(judge, fold)).ok()
                    })
                }
            };
            let out = model.and_then(|m| with_and_without(judge, m, fold, at));
            progress.inc(1);
            out
        })
        .collect();
    if states.is_none() {
        *fits += folds.len();
    }
    let mut out = [Errors::new(), Errors::new()];
    for pair in judged.into_iter().flatten() {
        for (errs, evals) in out.iter_mut().zip(pair) {
            for e in evals.iter().filter(|e| e.skipped.is_none()) {
                errs.insert(e.frame, e.log_e.map(|v| v.unwrap_or(f64::NAN)));
            }
        }
    }
    out
}

/// A fold's model judged on its frames `fold` at `at` without its lattice and with it (a
/// model whose own lattice stage found no detail predicts the same either way).
fn with_and_without(
    judge: &Context,
    mut model: ModelFile,
    fold: &[usize],
    at: EvalPoints,
) -> Option<[Vec<FrameEval>; 2]> {
    let with = evaluate_in(judge, &model, fold, at, &()).ok()?.0;
    let without = match model.face_alpha.take() {
        Some(_) => evaluate_in(judge, &model, fold, at, &()).ok()?.0,
        None => with.clone(),
    };
    Some([without, with])
}

/// The choice of the lattice from the folds' surface errors without it and with it
/// ([`judge_lattice`]): the one-standard-error rule, no lattice the simpler. Whether it is
/// written, and the report's choice.
fn choose_lattice(without: &Errors, with: &Errors, clusters: &Clustering) -> (bool, CvChoice) {
    let cands: Vec<(String, &Errors)> =
        vec![("off".into(), without), (LATTICE_CANDIDATE.into(), with)];
    let (chosen, candidates) = one_se(&cands, clusters);
    let keep = chosen == Some(1);
    (
        keep,
        CvChoice {
            name: "alpha_lattice".into(),
            rule: format!(
                "{ONE_SE_RULE}, judged at surface points (the run's lattice points, samples above Eq. 6's t2) with the settings chosen above"
            ),
            candidates,
            chosen: if keep { LATTICE_CANDIDATE } else { "off" }.into(),
        },
    )
}

/// The lattice candidate's name in the report: the fit's `--alpha-lattice` default.
const LATTICE_CANDIDATE: &str = "auto";

/// A fit of the prepared run `ctx` on `frames`, with the choices of `cv` made by
/// cross-validation over `frames` ([`folds`]); the report's `cross_validation` lists every
/// candidate's held-out error and the choice. Without folds (fewer than 2, or a scan with a
/// single frame) every setting keeps the value given, and `--segments auto` is refused.
pub fn fit_scan_in(
    ctx: &Context,
    judge: &Context,
    frames: &[usize],
    cv: &CvSettings,
    fitter: &dyn Fitter,
    progress: &dyn Progress,
) -> Result<FitOutput, PipelineError> {
    let start = std::time::Instant::now();
    // The reference preset fits with its own numerics throughout (libm's exp and ln).
    let reference = crate::pipeline::reference_fitter(ctx, fitter);
    let fitter = reference.as_deref().unwrap_or(fitter);
    let mut opts = ctx.opts;
    if let Segments::Fixed(m) = cv.segments {
        opts.model.segments = m;
    }
    let auto = cv.segments == Segments::Auto;
    let rounds = cv.rounds && opts.alpha_rounds > 0;
    let cache = OrderCache::default();
    let mut report = None;
    // The lattice is judged where the run's is on; the folds' fit states of the settings chosen
    // are then kept for it (`Grid::states`).
    let judge_lat = cv.lattice && opts.alpha_lattice.max_level().is_some();
    let mut chosen_grid: Option<Grid> = None;
    let k = cv.folds;
    if auto || rounds {
        let (folds, rule) = folds(ctx.ds, frames, k);
        let mut rep = CvReport {
            rule,
            folds: folds.clone(),
            ..CvReport::default()
        };
        if k < 2 || folds.len() < 2 {
            if auto {
                return Err(PipelineError::Invalid(
                    "--segments auto chooses m by cross-validation: it needs --cv-folds >= 2 and at least 2 frames".into(),
                ));
            }
            rep.skipped = Some(format!(
                "{} fold(s): nothing cross-validated, every setting as given",
                folds.len()
            ));
        } else {
            let ladder: Vec<usize> = if auto {
                SEGMENT_LADDER.to_vec()
            } else {
                vec![opts.model.segments]
            };
            let mut ctxs = Vec::with_capacity(ladder.len());
            for &m in &ladder {
                let mut o = opts;
                o.model.segments = m;
                let c = ctx.with_options(o)?;
                // Round 0's candidates of the fit on every frame, fitted once for every fold
                // that holds their frames and for the final fit (`OrderCache`).
                if let Ok(full) = Prepared::new(&c, frames) {
                    full.fill_order_cache(&c, fitter, &cache, progress);
                }
                ctxs.push(c);
            }
            let try_t1 = cv.t1 && opts.alpha_window.t1_share.is_infinite();
            progress.start(
                "cross-validation",
                ((ladder.len() + usize::from(try_t1)) * folds.len()) as u64,
            );
            let mut grids = Vec::new();
            // Each fold's last fill, the next candidate's start (`FitRounds::start_fill_from`).
            let mut fills: Vec<Option<FillState>> = vec![None; folds.len()];
            for c in &ctxs {
                grids.push(cross_validate(
                    c,
                    judge,
                    frames,
                    &folds,
                    fitter,
                    &cache,
                    (cv.patience, cv.min_gain_se),
                    judge_lat,
                    progress,
                    &mut rep.fits,
                    &mut fills,
                )?);
            }
            let fold_clusters = Clustering::of_folds(&folds);
            // Each m at its own best number of rounds, then the rounds of the m chosen.
            let per_m: Vec<(usize, CvChoice)> = grids
                .iter()
                .map(|g| choose_rounds(&g.errors, g.most, &fold_clusters, cv.patience))
                .collect();
            // Of each grid's fold states only those at its rounds can be judged for the lattice.
            for (g, (limit, _)) in grids.iter_mut().zip(&per_m) {
                g.keep_states_at(*limit);
            }
            let mut k = 0;
            if auto {
                let cands: Vec<(String, &Errors)> = ladder
                    .iter()
                    .zip(&grids)
                    .zip(&per_m)
                    .map(|((m, g), (limit, _))| (m.to_string(), &g.errors[(*limit).min(g.most)]))
                    .collect();
                let (chosen, candidates) = one_se(&cands, &fold_clusters);
                k = chosen.unwrap_or(0);
                opts.model.segments = ladder[k];
                rep.choices.push(CvChoice {
                    name: "segments".into(),
                    rule: format!("{ONE_SE_RULE} (each m with its own cross-validated rounds)"),
                    candidates,
                    chosen: ladder[k].to_string(),
                });
            }
            let (mut limit, mut choice) = per_m[k].clone();
            let mut grid_k = grids.swap_remove(k);
            if try_t1 {
                // Eq. 6's t1 for the m chosen: none (the simpler) against T1_CANDIDATE, each at
                // its own cross-validated rounds. Round 0's fits do not depend on t1: the
                // cache serves both.
                let mut o = ctxs[k].opts;
                o.alpha_window.t1_share = T1_CANDIDATE;
                let c = ctx.with_options(o)?;
                let g = cross_validate(
                    &c,
                    judge,
                    frames,
                    &folds,
                    fitter,
                    &cache,
                    (cv.patience, cv.min_gain_se),
                    judge_lat,
                    progress,
                    &mut rep.fits,
                    &mut fills,
                )?;
                let mut g = g;
                let r = choose_rounds(&g.errors, g.most, &fold_clusters, cv.patience);
                g.keep_states_at(r.0);
                let cands: Vec<(String, &Errors)> = vec![
                    ("off".into(), &grid_k.errors[limit.min(grid_k.most)]),
                    (T1_CANDIDATE.to_string(), &g.errors[r.0.min(g.most)]),
                ];
                let (chosen, candidates) = one_se(&cands, &fold_clusters);
                let with_t1 = chosen == Some(1);
                rep.choices.push(CvChoice {
                    name: "alpha_t1_share".into(),
                    rule: format!("{ONE_SE_RULE} (each with its own cross-validated rounds)"),
                    candidates,
                    chosen: if with_t1 {
                        T1_CANDIDATE.to_string()
                    } else {
                        "off".into()
                    },
                });
                if with_t1 {
                    opts.alpha_window.t1_share = T1_CANDIDATE;
                    (limit, choice) = r;
                    grid_k = g;
                }
            }
            if rounds {
                opts.alpha_rounds = limit;
                rep.choices.push(choice);
            }
            let at = if rounds { limit } else { opts.alpha_rounds };
            if let Some(errs) = grid_k
                .errors
                .get(at.min(grid_k.most))
                .or(grid_k.errors.last())
            {
                rep.per_frame = errs
                    .iter()
                    .map(|(&f, v)| (f, v.map(|x| x.is_finite().then_some(x))))
                    .collect();
            }
            // The folds' states at the rounds the final fit runs (its rounds are those the
            // folds validated: a fold's state there is its fit with the final settings).
            if judge_lat && (rounds || at == 0) {
                grid_k.keep_states_at(at);
                chosen_grid = Some(grid_k);
            }
        }
        rep.seconds = start.elapsed().as_secs_f64();
        report = Some(rep);
    }
    let final_ctx = ctx.with_options(opts)?;
    let mut out = fit_prepared_with(&final_ctx, frames, fitter, Some(&cache), progress)?;
    if judge_lat {
        let start = std::time::Instant::now();
        let (folds, rule) = folds(ctx.ds, frames, k);
        if k >= 2 && folds.len() >= 2 {
            let rep = report.get_or_insert_with(|| CvReport {
                rule,
                folds: folds.clone(),
                ..CvReport::default()
            });
            let choice = if out.model.face_alpha.is_some() {
                progress.start("cross-validation (alpha lattice)", folds.len() as u64);
                let [without, with] = judge_lattice(
                    &final_ctx,
                    judge,
                    frames,
                    &folds,
                    chosen_grid.as_ref(),
                    fitter,
                    &cache,
                    progress,
                    &mut rep.fits,
                );
                let (keep, choice) = choose_lattice(&without, &with, &Clustering::of_folds(&folds));
                if !keep {
                    drop_lattice(&mut out);
                }
                if let Some(l) = &mut out.report.alpha.lattice {
                    l.kept_by_cv = Some(keep);
                }
                choice
            } else {
                CvChoice {
                    name: "alpha_lattice".into(),
                    rule: "not judged: the fit's lattice stage found no detail above the noise, so there is none to write".into(),
                    candidates: Vec::new(),
                    chosen: "off".into(),
                }
            };
            rep.choices.push(choice);
            rep.seconds += start.elapsed().as_secs_f64();
        }
    }
    if let Some(r) = &mut report {
        (r.round0_fitted, r.round0_reused) = cache.counts();
    }
    out.report.cross_validation = report;
    Ok(out)
}

/// The fit `out` without its lattice: `face_alpha` dropped and the report's lattice saying so
/// (every face at level 1, as when nothing is written).
fn drop_lattice(out: &mut FitOutput) {
    out.model.face_alpha = None;
    let faces = out.model.triangles.len();
    if let Some(l) = &mut out.report.alpha.lattice {
        l.written = false;
        l.levels = std::iter::once((1, faces)).collect();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one minimum-gain rule: more than half an SE counts; a missing (infinite), zero or
    /// non-finite SE never does while a minimum is asked for; a fall of zero or less never does.
    #[test]
    fn a_gain_counts_only_above_the_minimum_on_a_measured_se() {
        assert!(counts_as_gain(0.06, 0.1, MIN_GAIN_SE));
        assert!(!counts_as_gain(0.04, 0.1, MIN_GAIN_SE));
        assert!(!counts_as_gain(1.0, f64::INFINITY, MIN_GAIN_SE));
        assert!(!counts_as_gain(1.0, 0.0, MIN_GAIN_SE));
        assert!(!counts_as_gain(1.0, f64::NAN, MIN_GAIN_SE));
        assert!(!counts_as_gain(0.0, 0.1, 0.0));
        assert!(!counts_as_gain(-0.1, 0.1, MIN_GAIN_SE));
        assert!(counts_as_gain(1e-9, f64::INFINITY, 0.0));
    }

    fn errors(v: &[(usize, f64)]) -> Errors {
        v.iter().map(|&(f, e)| (f, [e; 3])).collect()
    }

    /// Early stopping with a minimum improvement: a round whose gain is well above its
    /// standard error resets the count, one that gains less than half of it stalls, and the
    /// reference rule (any lower mean) would go on where the default stops.
    #[test]
    fn rounds_stop_once_a_round_gains_less_than_half_its_standard_error() {
        let folds = Clustering::of_folds(&[vec![0, 1], vec![2, 3], vec![4, 5], vec![6, 7]]);
        // Frame f's error after round r: a clear gain per round to round 2, then a gain of
        // 1e-5 with noise of ±1e-4 per fold (its SE far above twice the gain).
        let at = |r: usize| -> Errors {
            (0..8)
                .map(|f| {
                    let base = match r {
                        0 => 0.50,
                        1 => 0.45,
                        _ => 0.44 - 1e-5 * (r - 2) as f64,
                    };
                    let noise = if (f / 2) % 2 == 0 { 1e-4 } else { -1e-4 };
                    // Each frame's own small drift per round, so no gain's spread is exactly 0.
                    let drift = [0.3, -0.1, 0.2, -0.4, 0.1, 0.0, -0.2, 0.1][f] * 1e-3 * r as f64;
                    (f, [base + drift + if r >= 3 { noise } else { 0.0 }; 3])
                })
                .collect()
        };
        let curve: Vec<Errors> = (0..=3).map(at).collect();
        assert!(!rounds_exhausted(&curve[..3], &folds, 1, MIN_GAIN_SE));
        assert!(rounds_exhausted(&curve, &folds, 1, MIN_GAIN_SE));
        assert!(!rounds_exhausted(&curve, &folds, 2, MIN_GAIN_SE));
        // Patience 0 never stops.
        assert!(!rounds_exhausted(&curve, &folds, 0, MIN_GAIN_SE));
        // A gain of several SE after a stall resets the count.
        let mut more = curve.clone();
        more.push((0..8).map(|f| (f, [0.40; 3])).collect());
        assert!(!rounds_exhausted(&more, &folds, 1, MIN_GAIN_SE));
    }

    /// The simplest candidate within one standard error of the best wins; a clearly better
    /// complex one wins; a candidate without data is reported and never chosen.
    #[test]
    fn the_one_se_rule_prefers_the_simpler_within_noise() {
        // Every frame its own cluster.
        let lone = Clustering::of_folds(&[]);
        let simple = errors(&[(0, 0.30), (1, 0.20), (2, 0.41), (3, 0.25)]);
        let noisy_better = errors(&[(0, 0.28), (1, 0.22), (2, 0.37), (3, 0.25)]);
        let (c, rows) = one_se(&[("1".into(), &simple), ("2".into(), &noisy_better)], &lone);
        assert_eq!(c, Some(0), "{rows:?}");
        let clearly = errors(&[(0, 0.20), (1, 0.11), (2, 0.30), (3, 0.16)]);
        let (c, rows) = one_se(&[("1".into(), &simple), ("4".into(), &clearly)], &lone);
        assert_eq!(c, Some(1), "{rows:?}");
        assert!(rows[0].worse_by.unwrap() > rows[0].se.unwrap());
        let none = Errors::new();
        let (c, rows) = one_se(&[("1".into(), &none), ("2".into(), &simple)], &lone);
        assert_eq!(c, Some(1));
        assert_eq!(rows[0].score, None);
        assert!(rows[0].note.is_some());
        assert_eq!(one_se(&[("1".into(), &none)], &lone).0, None);
    }

    /// With one cluster no spread can be measured: the standard error is infinite, so the one-SE
    /// rule keeps the simplest candidate however much better another looks, and no round's gain
    /// counts (the rounds stop after `patience`). With two folds the same clear gain is taken.
    #[test]
    fn one_cluster_keeps_the_simplest_and_counts_no_gain() {
        let one = Clustering::of_folds(&[(0..4).collect()]);
        let simple = errors(&[(0, 0.30), (1, 0.20), (2, 0.41), (3, 0.25)]);
        let clearly = errors(&[(0, 0.20), (1, 0.11), (2, 0.30), (3, 0.16)]);
        let cands = [("1".to_string(), &simple), ("4".to_string(), &clearly)];
        let (c, rows) = one_se(&cands, &one);
        assert_eq!(c, Some(0), "{rows:?}");
        assert_eq!(
            rows[0].se, None,
            "an unmeasured SE is not written as a number"
        );
        let two = Clustering::of_folds(&[vec![0, 1], vec![2, 3]]);
        assert_eq!(one_se(&cands, &two).0, Some(1));
        // Rounds: a gain of 0.1 in every frame is no gain without a measured spread.
        let curve = vec![simple.clone(), clearly.clone()];
        assert!(rounds_exhausted(&curve, &one, 1, MIN_GAIN_SE));
        assert!(!rounds_exhausted(&curve, &two, 1, MIN_GAIN_SE));
        assert_eq!(
            paired_gain(&simple, &clearly, &one).map(|g| g.1),
            Some(f64::INFINITY)
        );
    }

    /// The lattice is written only when the folds' surface errors say it predicts better: a
    /// lattice whose gain is within the noise is dropped (no lattice the simpler), one clearly
    /// better is kept, one worse is dropped; the choice names both candidates.
    #[test]
    fn the_lattice_is_kept_only_when_it_predicts_better() {
        let folds = Clustering::of_folds(&[vec![0, 1], vec![2, 3], vec![4, 5]]);
        let base: Vec<(usize, f64)> = (0..6).map(|f| (f, 0.30 + 0.02 * f as f64)).collect();
        let without = errors(&base);
        let shifted =
            |d: &[f64]| errors(&base.iter().map(|&(f, e)| (f, e + d[f])).collect::<Vec<_>>());
        // Gains of opposite sign between folds: within one clustered standard error.
        let noise = shifted(&[-0.02, -0.02, 0.015, 0.015, 0.0, 0.0]);
        let (keep, choice) = choose_lattice(&without, &noise, &folds);
        assert!(!keep, "{choice:?}");
        assert_eq!(choice.name, "alpha_lattice");
        assert_eq!(choice.chosen, "off");
        assert_eq!(choice.candidates.len(), 2);
        // A gain in every fold.
        let better = shifted(&[-0.05, -0.04, -0.06, -0.05, -0.04, -0.05]);
        let (keep, choice) = choose_lattice(&without, &better, &folds);
        assert!(keep, "{choice:?}");
        assert_eq!(choice.chosen, LATTICE_CANDIDATE);
        let off = &choice.candidates[0];
        assert!(off.worse_by.unwrap() > off.se.unwrap(), "{choice:?}");
        // Worse everywhere.
        let worse = shifted(&[0.05; 6]);
        assert!(!choose_lattice(&without, &worse, &folds).0);
    }

    /// Early stopping: the rounds end `patience` rounds after the best, never while the error
    /// still falls, and never with patience 0.
    #[test]
    fn the_rounds_stop_patience_rounds_after_the_best() {
        let lone = Clustering::of_folds(&[]);
        let curve = |v: &[f64]| -> Vec<Errors> {
            v.iter()
                .map(|&e| errors(&[(0, e), (1, e + 0.01), (2, e - 0.01)]))
                .collect()
        };
        let rising = [0.220, 0.215, 0.217, 0.217, 0.219];
        assert!(!rounds_exhausted(&curve(&rising[..2]), &lone, 2, 0.0));
        assert!(!rounds_exhausted(&curve(&rising[..3]), &lone, 2, 0.0));
        assert!(rounds_exhausted(&curve(&rising[..4]), &lone, 2, 0.0));
        assert!(rounds_exhausted(&curve(&rising[..3]), &lone, 1, 0.0));
        assert!(!rounds_exhausted(&curve(&rising), &lone, 0, 0.0));
        let falling = [0.454, 0.445, 0.442, 0.441, 0.440, 0.439];
        assert!(!rounds_exhausted(&curve(&falling), &lone, 2, 0.0));
        // A tie with the best is not a new best: the first of equals stays the best.
        let flat = [0.30, 0.20, 0.20, 0.20];
        assert!(rounds_exhausted(&curve(&flat), &lone, 2, 0.0));
    }

    /// Frames of one fold move together: the same per-frame gain of the complex candidate,
    /// consistent within folds but of opposite sign between them, is within one clustered
    /// standard error though far outside the one that takes frames as independent.
    #[test]
    fn the_one_se_rule_clusters_by_fold() {
        // Eight frames in two folds; the complex candidate gains 0.03 on fold 0's frames and
        // loses 0.01 on fold 1's: on average it is better.
        let base: Vec<(usize, f64)> = (0..8).map(|f| (f, 0.3 + 0.001 * f as f64)).collect();
        let simple = errors(&base);
        let complex = errors(
            &base
                .iter()
                .map(|&(f, e)| (f, if f < 4 { e - 0.03 } else { e + 0.01 }))
                .collect::<Vec<_>>(),
        );
        let cands = [("1".to_string(), &simple), ("2".to_string(), &complex)];
        let lone = Clustering::of_folds(&[]);
        let folds = Clustering::of_folds(&[vec![0, 1, 2, 3], vec![4, 5, 6, 7]]);
        let (independent, rows) = one_se(&cands, &lone);
        assert_eq!(independent, Some(1), "{rows:?}");
        let (clustered, rows) = one_se(&cands, &folds);
        assert_eq!(clustered, Some(0), "{rows:?}");
        // The clustered SE of the difference, by the textbook formula (two clusters).
        let d = [0.03, 0.03, 0.03, 0.03, -0.01, -0.01, -0.01, -0.01];
        let mean: f64 = d.iter().sum::<f64>() / 8.0;
        let u0: f64 = d[..4].iter().map(|x| x - mean).sum();
        let u1: f64 = d[4..].iter().map(|x| x - mean).sum();
        let se = (2.0 * (u0 * u0 + u1 * u1)).sqrt() / 8.0;
        assert!((rows[0].se.unwrap() - se).abs() < 1e-12, "{rows:?}");
    }
}
