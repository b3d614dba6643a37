//! `subsurf bench equivalence`: the default fit against the reference preset (the exact,
//! slower path every speed-up of the default is checked against), on one scan at a time,
//! measured back to back from one sample store.
//!
//! The bar is "the same predictions, within statistical noise, and the same choices", not the
//! same bits, judged on training data only:
//! - on the training frames' outer cross-validation, a two-one-sided test (Schuirmann 1987) of
//!   the per-frame paired change in log E (Eq. 8), with its standard error clustered by outer
//!   fold (the frames of a fold share one fit; `Clustering::rule`): the 90 % interval of the
//!   mean change (t with folds − 1 degrees of freedom) must lie within ±[`MARGIN`], and the
//!   mean change must be at most [`MAX_WORSE`]. A standard error that could not be measured
//!   (one fold) or is zero fails the test, unless every paired change is exactly zero (the two
//!   paths predict the same numbers);
//! - the same test on the test frames (never fitted) is reported beside it, never part of the
//!   verdict: a default accepted because it did well on the test frames would have been chosen
//!   by them;
//! - each cross-validated choice (rounds, t1, m) may change only to a candidate within one
//!   standard error of the reference's best, in the reference's own table;
//! - the RMS change of ln R_d at the training samples and of ln alpha at the vertices at most
//!   [`MAX_RMS`];
//! - the reflectance check's bias against exact fits (`pipeline/check.rs`) at most 0.5 %:
//!   both paths fit every light position exactly, so there is no approximation to check.
//!
//! Handwritten: the criteria are the issue's own; the t quantile is `distrs`'s.
use std::collections::BTreeMap;
use std::path::Path;

use crate::crossval::{CvSettings, fit_scan_in};
use crate::dataset::Dataset;
use crate::evaluate::summary::{Clustering, ErrorSource, clustered_mean};
use crate::evaluate::{EvalPoints, FrameEval, evaluate_in, model_at};
use crate::modelfile::ModelFile;
use crate::pipeline::{Cache, Context, FitOutput, PipelineOptions, Speed, StoreOptions};
use crate::progress::Progress;

use super::acquisition::BenchError;

/// CPU time of this process so far (s; NaN where the kernel does not say).
fn cpu_seconds() -> f64 {
    crate::util::cpu_seconds().unwrap_or(f64::NAN)
}

/// The equivalence margin of the paired change in held-out log E: a tenth of the smallest
/// standard error of the shared datasets' held-out figures, so a change inside it is far below
/// what any figure a user reads can resolve.
pub const MARGIN: f64 = 0.005;
/// The largest mean change in held-out log E (worse) the default may show.
pub const MAX_WORSE: f64 = 0.002;
/// The largest RMS change of ln R_d at the samples and of ln alpha at the vertices.
pub const MAX_RMS: f64 = 0.01;

/// One side of the comparison: a fit's time and what it predicts.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Side {
    /// Wall time of the fit from the sample store (s; the one decode is not in it).
    pub wall_s: f64,
    /// CPU time of the process during the fit (s, user + system).
    pub cpu_s: f64,
    /// Mean held-out log E on the test frames (each frame's mean over its channels).
    pub test_log_e: Option<f64>,
    /// The cross-validation's choices, name → value.
    pub choices: BTreeMap<String, String>,
}

/// A paired change (default − reference) per frame and its two-one-sided test.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Tost {
    /// Frames compared.
    pub frames: usize,
    /// Clusters (outer folds for the cross-validation; turntable angles, or raster positions of
    /// a one-angle scan, for the test frames).
    pub clusters: usize,
    /// The rule that clustered them.
    pub cluster_rule: String,
    /// Degrees of freedom of the interval: clusters − 1.
    pub dof: Option<usize>,
    /// Mean paired change of log E (positive: the default predicts worse).
    pub mean: f64,
    /// Its standard error, clustered (`None` where it could not be measured).
    pub se: Option<f64>,
    /// The 90 % interval (t with clusters − 1 degrees of freedom); `None` where unbounded.
    pub interval: Option<[f64; 2]>,
    /// Every paired change exactly zero: the same predictions, equivalent without a test.
    pub identical: bool,
    /// Whether the interval lies within ±[`MARGIN`] and the mean is at most [`MAX_WORSE`] (or
    /// the predictions are identical).
    pub pass: bool,
}

/// A cross-validated choice of both paths.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ChoiceChange {
    /// The setting (`alpha_rounds`, `alpha_t1_share`, `segments`).
    pub name: String,
    /// The reference's value.
    pub reference: String,
    /// The default's value.
    pub default: String,
    /// The default's value in the reference's table (else the reference's in the default's):
    /// how much worse than that table's best and that difference's SE (`None`: a candidate
    /// in neither).
    pub worse_by: Option<(f64, f64)>,
    /// The same, or within one SE of the reference's best.
    pub pass: bool,
}

/// One scan's comparison.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CaseResult {
    /// The scan's name.
    pub name: String,
    /// Test frames given.
    pub test_frames: usize,
    /// The reference preset.
    pub reference: Side,
    /// The default.
    pub default: Side,
    /// Test frames: paired change.
    pub test: Option<Tost>,
    /// The training frames' cross-validation: both procedures fitted without each of five
    /// outer folds of whole angles and judged on it; paired change per frame.
    pub cv: Option<Tost>,
    /// The choices.
    pub choices: Vec<ChoiceChange>,
    /// RMS change of ln R_d (Eq. 9, the corners' blend at x_i) at the training frames'
    /// samples, over channels.
    pub rms_ln_rd: Option<f64>,
    /// RMS change of ln alpha at the vertices, over channels.
    pub rms_ln_alpha: Option<f64>,
}

impl CaseResult {
    /// Reference CPU time over the default's.
    pub fn speedup(&self) -> f64 {
        self.reference.cpu_s / self.default.cpu_s.max(1e-9)
    }

    /// Whether every criterion holds. Training data only: the test frames' change is reported,
    /// never part of the verdict, and without an outer cross-validation nothing is shown.
    pub fn pass(&self) -> bool {
        self.cv.as_ref().is_some_and(|t| t.pass)
            && self.choices.iter().all(|c| c.pass)
            && self.rms_ln_rd.is_none_or(|x| x <= MAX_RMS)
            && self.rms_ln_alpha.is_none_or(|x| x <= MAX_RMS)
    }
}

/// Compares the default fit with the reference preset on the scan `scan`, fitted without the
/// frames `test` and judged on them, and (with `outer_folds` ≥ 2) by an outer
/// cross-validation of both procedures over the training frames.
pub fn run_case(
    name: &str,
    scan: &Path,
    test: &[usize],
    outer_folds: usize,
    progress: &dyn Progress,
) -> Result<CaseResult, BenchError> {
    let ds = Dataset::open(scan).map_err(|e| BenchError::Invalid(format!("{name}: {e}")))?;
    let all: Vec<usize> = (0..ds.spec.frames.len()).collect();
    if let Some(&bad) = test.iter().find(|&&f| f >= all.len()) {
        return Err(BenchError::Invalid(format!(
            "{name}: test frame {bad} is not in the scan ({} frames)",
            all.len()
        )));
    }
    let train: Vec<usize> = all.iter().copied().filter(|f| !test.contains(f)).collect();
    let fail = |frames: usize| move |source| BenchError::Fit { frames, source };
    let (protocol, floor) = crate::pipeline::evaluation_protocol(&ds).map_err(fail(0))?;
    let store = StoreOptions {
        budget: crate::store::DEFAULT_BUDGET,
        cache: Cache::Off,
    };
    let base = PipelineOptions::for_dataset(&ds).with_noise_floor(floor.value);
    let run = crate::pipeline::prepare(&ds, &all, &base, &store, progress).map_err(fail(0))?;
    let judge = crate::pipeline::judge_context(&run, &all, Some(&protocol), &store, progress)
        .map_err(fail(0))?;
    let fitter = crate::fit::FitOptions::default();
    let mut fits: Vec<(FitOutput, Side, Vec<FrameEval>)> = Vec::new();
    for (speed, cv) in [
        (Speed::Reference, CvSettings::reference()),
        (Speed::Default, CvSettings::default()),
    ] {
        let ctx = run
            .with_options(PipelineOptions { speed, ..base })
            .map_err(fail(train.len()))?;
        let (t0, c0) = (std::time::Instant::now(), cpu_seconds());
        let out =
            fit_scan_in(&ctx, &judge, &train, &cv, &fitter, progress).map_err(fail(train.len()))?;
        let (wall_s, cpu_s) = (t0.elapsed().as_secs_f64(), cpu_seconds() - c0);
        let evals = if test.is_empty() {
            Vec::new()
        } else {
            evaluate_in(&judge, &out.model, test, EvalPoints::Vertices, &())?.0
        };
        let choices = out
            .report
            .cross_validation
            .iter()
            .flat_map(|r| &r.choices)
            .map(|c| (c.name.clone(), c.chosen.clone()))
            .collect();
        let side = Side {
            wall_s,
            cpu_s,
            test_log_e: mean_of(&frame_errors(&evals)),
            choices,
        };
        fits.push((out, side, evals));
    }
    let (def_out, def_side, def_evals) = fits.pop().expect("two fits");
    let (ref_out, ref_side, ref_evals) = fits.pop().expect("two fits");
    let test_tost = (!test.is_empty()).then(|| {
        let clusters = Clustering::of_frames(&ds, &ref_evals);
        tost(
            &frame_errors(&ref_evals),
            &frame_errors(&def_evals),
            &clusters,
        )
    });
    // The training frames' cross-validation: both procedures (each with its own inner
    // cross-validation) fitted without each outer fold of whole turntable angles and judged
    // on it, frame by frame.
    let (outer, _) = crate::crossval::folds(&ds, &train, outer_folds.max(1));
    let mut cv_a = BTreeMap::new();
    let mut cv_b = BTreeMap::new();
    if outer_folds >= 2 && outer.len() >= 2 {
        for fold in &outer {
            let inner: Vec<usize> = train
                .iter()
                .copied()
                .filter(|f| !fold.contains(f))
                .collect();
            for (speed, cv, errs) in [
                (Speed::Reference, CvSettings::reference(), &mut cv_a),
                (Speed::Default, CvSettings::default(), &mut cv_b),
            ] {
                let ctx = run
                    .with_options(PipelineOptions { speed, ..base })
                    .map_err(fail(inner.len()))?;
                // A fold whose fit fails predicts none of its frames, on both sides.
                let Ok(out) = fit_scan_in(&ctx, &judge, &inner, &cv, &fitter, &()) else {
                    continue;
                };
                let evals = evaluate_in(&judge, &out.model, fold, EvalPoints::Vertices, &())?.0;
                errs.extend(frame_errors(&evals));
            }
        }
    }
    // Cross-validated errors: clustered by the outer fold that held each frame out.
    let cv_tost = (!cv_a.is_empty() && !cv_b.is_empty()).then(|| {
        let judged: Vec<(usize, Option<[f64; 3]>)> = cv_a.keys().map(|&f| (f, None)).collect();
        tost(
            &cv_a,
            &cv_b,
            &Clustering::rule(&ds, &judged, ErrorSource::Folds(&outer)),
        )
    });
    let choices = choice_changes(&ref_out, &def_out);
    let rms_ln_rd = rms_ln_rd(&judge, &ref_out.model, &def_out.model, &train);
    let rms_ln_alpha = rms_ln_alpha(&ref_out.model, &def_out.model);
    Ok(CaseResult {
        name: name.to_string(),
        test_frames: test.len(),
        reference: ref_side,
        default: def_side,
        test: test_tost,
        cv: cv_tost,
        choices,
        rms_ln_rd,
        rms_ln_alpha,
    })
}

fn channel_mean(v: &[f64; 3]) -> Option<f64> {
    let f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    (!f.is_empty()).then(|| f.iter().sum::<f64>() / f.len() as f64)
}

/// Each judged frame's log E, the mean over its channels.
pub(crate) fn frame_errors(evals: &[FrameEval]) -> BTreeMap<usize, f64> {
    evals
        .iter()
        .filter(|e| e.skipped.is_none())
        .filter_map(|e| channel_mean(&e.log_e.map(|x| x.unwrap_or(f64::NAN))).map(|m| (e.frame, m)))
        .collect()
}

fn mean_of(m: &BTreeMap<usize, f64>) -> Option<f64> {
    (!m.is_empty()).then(|| m.values().sum::<f64>() / m.len() as f64)
}

/// The two-one-sided test of the paired change `b − a` over the frames both judged, at the
/// 5 % level each side (the 90 % t-interval with clusters − 1 degrees of freedom). An SE that
/// could not be measured or is zero is infinite
/// ([`crate::evaluate::summary::ClusteredMean::decision_se`]): the test fails, unless every
/// change is exactly zero.
fn tost(a: &BTreeMap<usize, f64>, b: &BTreeMap<usize, f64>, clusters: &Clustering) -> Tost {
    tost_at(a, b, clusters, MARGIN, MAX_WORSE)
}

/// [`tost`] at another `margin` and largest worse mean `max_worse` (`bench acquisition`'s
/// declared margin): `pass` when the 90 % interval of the paired change `b − a` lies inside
/// ±`margin` and its mean is at most `max_worse`, or every change is exactly zero. The interval's
/// upper end below `margin` alone is the one-sided non-inferiority test at 5 % ([`Tost::interval`]).
pub fn tost_at(
    a: &BTreeMap<usize, f64>,
    b: &BTreeMap<usize, f64>,
    clusters: &Clustering,
    margin: f64,
    max_worse: f64,
) -> Tost {
    let d: Vec<(f64, f64, (bool, usize))> = a
        .iter()
        .filter_map(|(f, x)| b.get(f).map(|y| (y - x, 1.0, clusters.cluster(*f))))
        .collect();
    let Some(m) = clustered_mean(&d) else {
        return Tost {
            cluster_rule: clusters.rule.clone(),
            ..Tost::default()
        };
    };
    let identical = d.iter().all(|v| v.0 == 0.0);
    let interval = m.interval(0.90);
    let pass = identical
        || interval.is_some_and(|[lo, hi]| lo > -margin && hi < margin && m.mean <= max_worse);
    Tost {
        frames: m.frames,
        clusters: m.clusters,
        cluster_rule: clusters.rule.clone(),
        dof: m.dof(),
        mean: m.mean,
        se: m.se.filter(|s| s.is_finite()),
        interval,
        identical,
        pass,
    }
}

/// Each choice of the reference's cross-validation beside the default's: the same value, or
/// values within one standard error of each other, in either path's table (the reference
/// scores rounds the default's early stop does not reach, and the other way round).
fn choice_changes(reference: &FitOutput, default: &FitOutput) -> Vec<ChoiceChange> {
    let Some(r) = &reference.report.cross_validation else {
        return Vec::new();
    };
    let d = default.report.cross_validation.as_ref();
    let within = |table: &crate::pipeline::CvChoice, value: &str| {
        table
            .candidates
            .iter()
            .find(|x| x.value == value)
            // A choice within an SE that could not be measured is not shown to be equivalent.
            .and_then(|x| Some((x.worse_by?, x.se.filter(|s| *s > 0.0 && s.is_finite())?)))
    };
    r.choices
        .iter()
        .filter(|c| !c.candidates.is_empty())
        .map(|c| {
            let theirs = d.and_then(|d| d.choices.iter().find(|x| x.name == c.name));
            let chosen = theirs.map_or_else(|| c.chosen.clone(), |x| x.chosen.clone());
            let worse_by = within(c, &chosen);
            let back = theirs.and_then(|t| within(t, &c.chosen));
            let pass = chosen == c.chosen
                || worse_by.is_some_and(|(w, se)| w <= se)
                || back.is_some_and(|(w, se)| w <= se);
            ChoiceChange {
                name: c.name.clone(),
                reference: c.chosen.clone(),
                default: chosen,
                worse_by: worse_by.or(back),
                pass,
            }
        })
        .collect()
}

/// RMS over the training frames' vertex samples and channels of the change of ln R_d at the
/// sample (the corners' blend at x_i, Eq. 9; alpha apart).
fn rms_ln_rd(judge: &Context, a: &ModelFile, b: &ModelFile, frames: &[usize]) -> Option<f64> {
    use rayon::prelude::*;
    let store = judge.store()?;
    let (sum, n) = frames
        .par_iter()
        .filter_map(|&k| {
            let reg = crate::pipeline::register_one(judge, k).ok()?;
            let (ma, mb) = (
                model_at(judge, a, reg.triangle, reg.x_i)?,
                model_at(judge, b, reg.triangle, reg.x_i)?,
            );
            let fs = store
                .samples(k, crate::store::PointSet::Vertices)
                .ok()
                .flatten()?;
            let (mut s, mut n) = (0.0, 0usize);
            for smp in fs.samples.iter() {
                let x_o = judge.ds.mesh.positions[smp.vertex as usize];
                let (r, phi) = ma.frame.polar(reg.x_i, x_o);
                let (la, lb) = (ma.ln_eval(r, phi), mb.ln_eval(r, phi));
                for c in 0..3 {
                    if smp.valid & (1 << c) != 0 && la[c].is_finite() && lb[c].is_finite() {
                        s += (la[c] - lb[c]).powi(2);
                        n += 1;
                    }
                }
            }
            Some((s, n))
        })
        .reduce(|| (0.0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
    (n > 0).then(|| (sum / n as f64).sqrt())
}

/// RMS over the vertices and channels of the change of ln alpha (Eq. 6).
fn rms_ln_alpha(a: &ModelFile, b: &ModelFile) -> Option<f64> {
    let (mut s, mut n) = (0.0, 0usize);
    for (va, vb) in a.vertices.iter().zip(&b.vertices) {
        for c in 0..3 {
            let d = (va.alpha[c] as f64).ln() - (vb.alpha[c] as f64).ln();
            if d.is_finite() {
                s += d * d;
                n += 1;
            }
        }
    }
    (n > 0).then(|| (s / n as f64).sqrt())
}

/// The comparison as a Markdown table, a row per scan.
pub fn table(cases: &[CaseResult]) -> String {
    let mut out = String::from(
        "| scan | reference (CPU / wall s) | default (CPU / wall s) | speed-up (CPU) | test frames (reported, not judged): change ± SE [90 % interval] | training CV: change ± SE [90 % interval] | choices (reference → default) | RMS Δ ln R_d | RMS Δ ln alpha | equivalent (training data) |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    let tost = |t: &Option<Tost>| match t {
        None => "–".to_string(),
        Some(t) => format!(
            "{:+.4} ± {} {} ({} frames, {} clusters by {}, {} dof){}",
            t.mean,
            t.se.map_or("–".into(), |s| format!("{s:.4}")),
            match (t.identical, t.interval) {
                (true, _) => "identical".to_string(),
                (false, Some([lo, hi])) => format!("[{lo:+.4}, {hi:+.4}]"),
                (false, None) => "[unbounded]".to_string(),
            },
            t.frames,
            t.clusters,
            t.cluster_rule,
            t.dof.unwrap_or(0),
            if t.pass { "" } else { " FAILS" }
        ),
    };
    let opt = |x: Option<f64>| x.map_or("–".into(), |v| format!("{v:.4}"));
    for c in cases {
        let choices: Vec<String> = c
            .choices
            .iter()
            .map(|x| {
                let w = x
                    .worse_by
                    .map_or(String::new(), |(w, se)| format!(" (+{w:.5} ± {se:.5})"));
                format!(
                    "{} {} → {}{}{}",
                    x.name,
                    x.reference,
                    x.default,
                    w,
                    if x.pass { "" } else { " FAILS" }
                )
            })
            .collect();
        out.push_str(&format!(
            "| {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2}× | {} | {} | {} | {} | {} | {} |\n",
            c.name,
            c.reference.cpu_s,
            c.reference.wall_s,
            c.default.cpu_s,
            c.default.wall_s,
            c.speedup(),
            tost(&c.test),
            tost(&c.cv),
            choices.join("; "),
            opt(c.rms_ln_rd),
            opt(c.rms_ln_alpha),
            if c.pass() { "yes" } else { "no" }
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn clusters(of: &[(usize, usize)]) -> Clustering {
        Clustering::of_folds(
            &of.iter()
                .fold(BTreeMap::<usize, Vec<usize>>::new(), |mut m, &(f, c)| {
                    m.entry(c).or_default().push(f);
                    m
                })
                .into_values()
                .collect::<Vec<_>>(),
        )
    }

    /// The test passes a change well inside the margin and fails one whose interval leaves
    /// it, or whose mean is worse than allowed.
    #[test]
    fn the_two_one_sided_test_holds_the_margin() {
        let c = clusters(&[
            (0, 0),
            (1, 0),
            (2, 1),
            (3, 1),
            (4, 2),
            (5, 2),
            (6, 3),
            (7, 3),
        ]);
        let a: BTreeMap<usize, f64> = (0..8).map(|f| (f, 0.5)).collect();
        let jitter = [
            0.0005, -0.0004, 0.0003, 0.0001, -0.0002, 0.0004, -0.0003, 0.0002,
        ];
        let small: BTreeMap<usize, f64> = (0..8).map(|f| (f, 0.5 + jitter[f])).collect();
        let t = tost(&a, &small, &c);
        assert!(t.pass, "{t:?}");
        assert_eq!((t.frames, t.clusters), (8, 4));
        let worse: BTreeMap<usize, f64> = (0..8).map(|f| (f, 0.503)).collect();
        let t = tost(&a, &worse, &c);
        assert!(!t.pass, "a mean 0.003 worse fails: {t:?}");
        let noisy: BTreeMap<usize, f64> = (0..8)
            .map(|f| (f, 0.5 + if f < 4 { 0.006 } else { -0.006 }))
            .collect();
        let t = tost(&a, &noisy, &c);
        assert!(!t.pass, "an interval wider than the margin fails: {t:?}");
        assert_eq!(t.dof, Some(3));
    }

    /// The verdict reads training data only: a failing test-frame change does not fail it, a
    /// passing one without an outer cross-validation does not pass it.
    #[test]
    fn the_verdict_never_reads_the_test_frames() {
        let side = || Side {
            wall_s: 1.0,
            cpu_s: 1.0,
            test_log_e: None,
            choices: BTreeMap::new(),
        };
        let t = |pass| Tost {
            pass,
            ..Tost::default()
        };
        let case = |test: Option<Tost>, cv: Option<Tost>| CaseResult {
            name: "x".into(),
            test_frames: 2,
            reference: side(),
            default: side(),
            test,
            cv,
            choices: Vec::new(),
            rms_ln_rd: None,
            rms_ln_alpha: None,
        };
        assert!(case(Some(t(false)), Some(t(true))).pass());
        assert!(!case(Some(t(true)), None).pass());
        assert!(!case(Some(t(true)), Some(t(false))).pass());
    }

    /// With one cluster the SE cannot be measured: the interval is unbounded and the test
    /// fails, however small the change; identical predictions pass without a test.
    #[test]
    fn one_cluster_fails_the_two_one_sided_test() {
        let one = clusters(&(0..8).map(|f| (f, 0)).collect::<Vec<_>>());
        let a: BTreeMap<usize, f64> = (0..8).map(|f| (f, 0.5)).collect();
        let small: BTreeMap<usize, f64> = (0..8)
            .map(|f| (f, 0.5 + if f % 2 == 0 { 0.0005 } else { -0.0004 }))
            .collect();
        let t = tost(&a, &small, &one);
        assert!(!t.pass, "{t:?}");
        assert_eq!((t.clusters, t.dof, t.se, t.interval), (1, None, None, None));
        let t = tost(&a, &a, &one);
        assert!(t.pass && t.identical, "{t:?}");
        // A constant shift in every cluster has SE 0: unbounded, fails.
        let four = clusters(&(0..8).map(|f| (f, f / 2)).collect::<Vec<_>>());
        let shifted: BTreeMap<usize, f64> = (0..8).map(|f| (f, 0.5001)).collect();
        assert!(!tost(&a, &shifted, &four).pass);
    }
}
