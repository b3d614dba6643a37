//! `subsurf bench acquisition`: the adaptive planner judged as a planner, by the protocol
//! docs/acquisition.md declares ("How the planners are judged"): at its stopping point against
//! the whole pool (a two-one-sided test at [`MARGIN`], `bench::equivalence`'s test), and against
//! coverage and random orders (several seeds) at equal frame counts and at equal rig time
//! (non-inferiority at the same margin), every comparison paired per test frame with its
//! standard error clustered by the one rule of every judge; for several start sets.
//!
//! Every planner draws from the same pool (a recorded dataset's frames minus the test frames,
//! replayed: [`crate::scan::replay::Replay`], counted over the frames predicted to show a spot),
//! so the planners differ only by which frames each takes. Each figure is a fit of a set of
//! frames and its error on the test frames, judged as `subsurf evaluate` judges (the dataset's
//! evaluation protocol, at the vertices, each frame's mean over its channels of Eq. 8's log E).
//! All fits are the adaptive planner's own assessment fit ([`assessment_options`]) from one
//! sample store of the dataset (each frame decoded once); a frame set fitted twice is fitted once.
//! The test frames judge only: nothing here chooses a setting by them.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand::seq::SliceRandom;

use super::equivalence::{Tost, frame_errors, tost_at};
use crate::crossval::{CvSettings, fit_scan_in};
use crate::dataset::Dataset;
use crate::evaluate::summary::t95;
use crate::evaluate::{Clustering, EvalPoints, Figures, evaluate_in};
use crate::pipeline::{Context, PipelineError, PipelineOptions, StoreOptions};
use crate::progress::Progress;
use crate::scan::adaptive::{
    AdaptiveError, AdaptiveSettings, FrameSource, assessment_options, cover_order,
    in_turntable_order, rig_seconds, run_adaptive,
};
use crate::scan::replay::{Replay, ReplayError};

/// Why the benchmark stopped.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BenchError {
    /// The replay could not be set up.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The adaptive scan failed.
    #[error(transparent)]
    Adaptive(#[from] AdaptiveError),
    /// A fit failed.
    #[error("fit of {frames} frames")]
    Fit {
        /// Frames fitted.
        frames: usize,
        /// Why.
        #[source]
        source: PipelineError,
    },
    /// Judging a model failed.
    #[error(transparent)]
    Evaluate(#[from] crate::evaluate::EvaluateError),
    /// Recording the simulated rig's scan failed.
    #[error("recording the simulated rig's scan: {0}")]
    Record(String),
    /// The dataset or the settings do not allow the benchmark.
    #[error("{0}")]
    Invalid(String),
}

/// The equivalence and non-inferiority margin of every test (log E), declared in
/// docs/acquisition.md before the run.
pub const MARGIN: f64 = 0.01;

/// The largest share of the pool's frames the adaptive scan may take and still meet the
/// project's bar.
pub const MAX_SHARE: f64 = 0.6;

/// What to run beside the dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchOptions {
    /// The adaptive planner's start sets (`AdaptiveSettings::start_seed`), each run to its stop.
    pub start_seeds: Vec<u64>,
    /// Seeds of the random planner's orders, each judged on its own.
    pub random_seeds: Vec<u64>,
    /// The margin ([`MARGIN`]).
    pub margin: f64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            start_seeds: vec![0, 1, 2],
            random_seeds: vec![1, 2, 3],
            margin: MARGIN,
        }
    }
}

/// A fit's error on the test frames.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct TestError {
    /// Mean over the test frames of log E (each frame's mean over its channels).
    pub log_e: Option<f64>,
    /// Its standard error clustered by the one rule (turntable angle, or raster neighbourhood).
    pub se: Option<f64>,
    /// Per channel r, g, b (`subsurf evaluate`'s `mean_log_e`, `se_log_e`).
    pub rgb: [Option<f64>; 3],
    /// See `rgb`.
    pub rgb_se: [Option<f64>; 3],
    /// Test frames judged.
    pub frames: usize,
    /// Clusters of the standard error.
    pub clusters: usize,
    /// Why there is no figure, where there is none (too few frames for any fit).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub failed: Option<String>,
    /// Each test frame's log E (mean over its channels): what the paired tests pair.
    #[serde(skip)]
    pub per_frame: BTreeMap<usize, f64>,
}

/// One point of a learning curve: a planner's first `frames` frames.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Point {
    /// The planner (`adaptive start 0`, `coverage`, `random seed 1`, ...).
    pub planner: String,
    /// Frames fitted.
    pub frames: usize,
    /// Their rig time (s, [`rig_seconds`]).
    pub rig_s: f64,
    /// Error on the test frames.
    pub test: TestError,
    /// The paired difference to the whole pool (this − pool) over the test frames.
    pub vs_pool: Tost,
}

/// One comparison of the adaptive scan at its stop with another frame set.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Comparison {
    /// The other planner.
    pub against: String,
    /// `stop` (the whole pool), `equal frames` or `equal rig time`.
    pub at: String,
    /// The other set's frames and rig time.
    pub frames: usize,
    /// See `frames`.
    pub rig_s: f64,
    /// The paired difference adaptive − other per test frame and its 90 % interval.
    pub paired: Tost,
    /// Against the pool: equivalent (the interval inside ±margin); against the others:
    /// non-inferior (its upper end below +margin).
    pub pass: bool,
}

/// One start set's adaptive scan and its comparisons.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StartRun {
    /// `AdaptiveSettings::start_seed`.
    pub start_seed: u64,
    /// Frames at the stop, and their share of the pool.
    pub frames: usize,
    /// See `frames`.
    pub share: f64,
    /// Rig time at the stop (homing per batch, the fits waited for).
    pub rig_s: f64,
    /// Why it stopped.
    pub stop: String,
    /// Its error on the test frames.
    pub test: TestError,
    /// Against the pool, then coverage and each random seed at equal frames and rig time.
    pub comparisons: Vec<Comparison>,
}

impl StartRun {
    /// The project's bar on this start set: equivalent to the whole pool with at most
    /// [`MAX_SHARE`] of its frames, and non-inferior to coverage and every random seed at equal
    /// frame counts.
    pub fn meets_the_bar(&self) -> bool {
        self.share <= MAX_SHARE
            && self
                .comparisons
                .iter()
                .filter(|c| c.at != "equal rig time")
                .all(|c| c.pass)
    }
}

/// The benchmark of one dataset.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Bench {
    /// The dataset.
    pub dataset: String,
    /// The test frames (never candidates).
    pub test_frames: Vec<usize>,
    /// Pool frames: candidates predicted to show a spot.
    pub pool: usize,
    /// The pool's rig time (one batch in turntable order).
    pub pool_rig_s: f64,
    /// The whole pool's fit on the test frames.
    pub pool_test: TestError,
    /// The margin of every test.
    pub margin: f64,
    /// Each start set's run.
    pub starts: Vec<StartRun>,
    /// The curves' points (adaptive batch ends per start set; coverage and random at the same
    /// counts).
    pub points: Vec<Point>,
    /// Fits made (frame sets fitted once each).
    pub fits: usize,
    /// Wall time of the benchmark (s).
    pub seconds: f64,
}

/// The fits of one benchmark, each frame set fitted once.
struct Fitter<'a> {
    run: &'a Context<'a>,
    judge: &'a Context<'a>,
    test: &'a [usize],
    cv: CvSettings,
    fit: crate::fit::FitOptions,
    done: BTreeMap<Vec<usize>, TestError>,
}

impl Fitter<'_> {
    /// The fit of `frames` judged on the test frames (a set too small for any fit: no figure).
    fn test(&mut self, frames: &[usize]) -> Result<TestError, BenchError> {
        let mut key = frames.to_vec();
        key.sort_unstable();
        key.dedup();
        if let Some(t) = self.done.get(&key) {
            return Ok(t.clone());
        }
        let t = fit_and_test(self.run, self.judge, &key, self.test, &self.cv, &self.fit)?;
        self.done.insert(key, t.clone());
        Ok(t)
    }
}

/// The fit of `frames` from the run `run` (a store of every frame) judged by `judge` on `test`.
fn fit_and_test(
    run: &Context,
    judge: &Context,
    frames: &[usize],
    test: &[usize],
    cv: &CvSettings,
    fit: &crate::fit::FitOptions,
) -> Result<TestError, BenchError> {
    // A set too small for any fit (few frames show a spot) is a point without a figure.
    let out = match fit_scan_in(run, judge, frames, cv, fit, &()) {
        Ok(out) => out,
        Err(PipelineError::NothingFitted(why)) => {
            return Ok(TestError {
                failed: Some(why),
                ..TestError::default()
            });
        }
        Err(source) => {
            return Err(BenchError::Fit {
                frames: frames.len(),
                source,
            });
        }
    };
    let (evals, _) = evaluate_in(judge, &out.model, test, EvalPoints::Vertices, &())?;
    let clusters = Clustering::of_frames(judge.ds, &evals);
    let fig = Figures::of(&evals, &clusters);
    let per_frame = frame_errors(&evals);
    let per: Vec<(f64, f64, (bool, usize))> = per_frame
        .iter()
        .map(|(&f, &e)| (e, 1.0, clusters.cluster(f)))
        .collect();
    let m = crate::evaluate::summary::clustered_mean(&per);
    let fin = |x: Option<f64>| x.filter(|v| v.is_finite());
    Ok(TestError {
        log_e: fin(m.map(|m| m.mean)),
        se: fin(m.and_then(|m| m.se)),
        rgb: fig.mean_log_e.map(fin),
        rgb_se: fig.se_log_e.map(fin),
        frames: fig.frames,
        clusters: m.map_or(0, |m| m.clusters),
        failed: None,
        per_frame,
    })
}

/// The paired test of `b − a` per test frame at `margin` (no mean cap beyond the margin).
fn paired(a: &TestError, b: &TestError, clusters: &Clustering, margin: f64) -> Tost {
    tost_at(&a.per_frame, &b.per_frame, clusters, margin, margin)
}

/// Non-inferiority of `adaptive` to `other`: the 90 % interval's upper end of adaptive − other
/// below `margin` (or identical predictions). Fails when the interval is unbounded.
fn non_inferior(t: &Tost, margin: f64) -> bool {
    t.identical || t.interval.is_some_and(|[_, hi]| hi < margin)
}

/// The longest prefix of `order` whose rig time (one batch in turntable order) is at most `t`.
fn prefix_within(order: &[usize], t: f64, rig: &dyn Fn(&[usize]) -> f64) -> usize {
    let mut n = 0;
    for k in 1..=order.len() {
        if rig(&order[..k]) <= t {
            n = k;
        } else {
            break;
        }
    }
    n
}

/// Benchmarks the planners on the recorded dataset `src` with `test` held out: for each start
/// set, the adaptive scan replayed into `work/adaptive-sN` (resumed if there), then the fits the
/// protocol compares. `log` sees each line as it is made.
pub fn bench_replay(
    src: &Path,
    test: &[usize],
    work: &Path,
    settings: &AdaptiveSettings,
    opts: &BenchOptions,
    progress: &dyn Progress,
    log: &mut dyn FnMut(&str),
) -> Result<Bench, BenchError> {
    let clock = std::time::Instant::now();
    if test.is_empty() {
        return Err(BenchError::Invalid(
            "no test frames: say which frames no planner may pick".into(),
        ));
    }
    if opts.start_seeds.is_empty() {
        return Err(BenchError::Invalid("no start set to run".into()));
    }
    let mut reports = Vec::new();
    let mut replay = None;
    for &seed in &opts.start_seeds {
        let mut r = Replay::open(src, &work.join(format!("adaptive-s{seed}")), test)?;
        log(&format!("adaptive scan, start set {seed} (replayed):"));
        let s = AdaptiveSettings {
            start_seed: seed,
            ..settings.clone()
        };
        let rep = run_adaptive(&mut r, &s, progress, &mut |p| {
            log(&format!("  {}", p.line()))
        })?;
        log(&format!(
            "  stopped: {}",
            rep.stopped.as_deref().unwrap_or("-")
        ));
        reports.push((seed, rep));
        replay = Some(r);
    }
    let Some(replay) = replay else {
        return Err(BenchError::Invalid("no start set to run".into()));
    };
    let cands = replay.candidates().to_vec();
    let (timing, exposures) = (*replay.timing(), replay.exposures_s().to_vec());
    let ds: &Dataset = replay.recorded();
    // A fixed plan is one batch, captured in turntable order.
    let rig = |order: &[usize]| {
        rig_seconds(
            &cands,
            &[in_turntable_order(&cands, order)],
            &[],
            &timing,
            &exposures,
        )
    };
    let pool: Vec<usize> = cands
        .iter()
        .filter(|c| c.x_i.is_some())
        .map(|c| c.id)
        .collect();
    if pool.is_empty() {
        return Err(BenchError::Invalid(
            "no pool frame is predicted to show a spot".into(),
        ));
    }
    let coverage = cover_order(&cands, &ds.mesh.positions, 2.0);
    let randoms: Vec<(u64, Vec<usize>)> = opts
        .random_seeds
        .iter()
        .map(|&seed| {
            let mut o = pool.clone();
            o.shuffle(&mut rand::rngs::StdRng::seed_from_u64(seed));
            (seed, o)
        })
        .collect();
    // One store of every frame: each fit below reads it, no frame is decoded twice.
    let all: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let (protocol, floor) = crate::pipeline::evaluation_protocol(ds)
        .map_err(|source| BenchError::Fit { frames: 0, source })?;
    let store = StoreOptions {
        budget: crate::store::DEFAULT_BUDGET,
        cache: crate::pipeline::Cache::Dir(work.join("store")),
    };
    let fail = |source| BenchError::Fit {
        frames: all.len(),
        source,
    };
    let base = PipelineOptions::for_dataset(ds).with_noise_floor(floor.value);
    let run = crate::pipeline::prepare(ds, &all, &base, &store, progress).map_err(fail)?;
    let judge = crate::pipeline::judge_context(&run, &all, Some(&protocol), &store, progress)
        .map_err(fail)?;
    let (cheap, cheap_fit) = assessment_options(ds, floor.value);
    let cheap_run = run.with_options(cheap).map_err(fail)?;
    // The adaptive planner's own assessment rule (`scan::adaptive`): the reference folds.
    let mut fitter = Fitter {
        run: &cheap_run,
        judge: &judge,
        test,
        cv: CvSettings {
            folds: settings.folds,
            t1: false,
            ..CvSettings::reference()
        },
        fit: cheap_fit,
        done: BTreeMap::new(),
    };
    let m = opts.margin;
    log("fitting the whole pool");
    let pool_test = fitter.test(&pool)?;
    let clusters = {
        let judged: Vec<(usize, Option<[f64; 3]>)> = test.iter().map(|&f| (f, None)).collect();
        Clustering::rule(ds, &judged, crate::evaluate::summary::ErrorSource::HeldOut)
    };
    let mut points = Vec::new();
    let mut point = |fitter: &mut Fitter, name: &str, frames: &[usize], rig_s: f64| {
        let t = fitter.test(frames)?;
        let vs_pool = paired(&pool_test, &t, &clusters, m);
        points.push(Point {
            planner: name.to_string(),
            frames: frames.len(),
            rig_s,
            test: t.clone(),
            vs_pool,
        });
        Ok::<TestError, BenchError>(t)
    };
    let mut starts = Vec::new();
    for (seed, rep) in &reports {
        let name = format!("adaptive start {seed}");
        log(&format!("judging {name}"));
        let mut last = TestError::default();
        for (k, p) in rep.curve.iter().enumerate() {
            let frames: Vec<usize> = rep.batches[..=k.min(rep.batches.len() - 1)].concat();
            last = point(&mut fitter, &name, &frames, p.rig_s)?;
        }
        let order = rep.order();
        let n = order.len();
        let rig_s = rep.curve.last().map_or(0.0, |p| p.rig_s);
        let mut comparisons = vec![Comparison {
            against: "whole pool".into(),
            at: "stop".into(),
            frames: pool.len(),
            rig_s: rig(&pool),
            paired: paired(&pool_test, &last, &clusters, m),
            pass: false,
        }];
        comparisons[0].pass = comparisons[0].paired.pass;
        let others: Vec<(String, &Vec<usize>)> =
            std::iter::once(("coverage".to_string(), &coverage))
                .chain(randoms.iter().map(|(s, o)| (format!("random seed {s}"), o)))
                .collect();
        for (other, o) in &others {
            let equal_frames = &o[..n.min(o.len())];
            let equal_time = &o[..prefix_within(o, rig_s, &rig)];
            for (at, frames) in [
                ("equal frames", equal_frames),
                ("equal rig time", equal_time),
            ] {
                let t = fitter.test(frames)?;
                let p = paired(&t, &last, &clusters, m);
                comparisons.push(Comparison {
                    against: other.clone(),
                    at: at.into(),
                    frames: frames.len(),
                    rig_s: rig(frames),
                    pass: non_inferior(&p, m),
                    paired: p,
                });
            }
        }
        starts.push(StartRun {
            start_seed: *seed,
            frames: n,
            share: n as f64 / pool.len() as f64,
            rig_s,
            stop: rep.stopped.clone().unwrap_or_default(),
            test: last,
            comparisons,
        });
    }
    // The others' curves at the first start set's batch ends and at the pool.
    if let Some((_, rep)) = reports.first() {
        let mut counts: Vec<usize> = rep.curve.iter().map(|p| p.frames).collect();
        counts.push(pool.len());
        counts.dedup();
        for (name, o) in std::iter::once(("coverage".to_string(), &coverage))
            .chain(randoms.iter().map(|(s, o)| (format!("random seed {s}"), o)))
        {
            log(&format!("the {name} curve"));
            let mut ns: Vec<usize> = counts.iter().map(|&c| c.min(o.len())).collect();
            ns.dedup();
            for n in ns {
                point(&mut fitter, &name, &o[..n], rig(&o[..n]))?;
            }
        }
    }
    Ok(Bench {
        dataset: src.display().to_string(),
        test_frames: test.to_vec(),
        pool: pool.len(),
        pool_rig_s: rig(&pool),
        pool_test,
        margin: m,
        starts,
        points,
        fits: fitter.done.len(),
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// Records the simulated rig's dense scan of the built-in object into `dir` (resumed if there):
/// `angles` equally spaced turntable angles × a `raster`² galvo raster, with the `sim` camera.
/// Returns the test frames: those of every third angle (the pool keeps two angles in three), so
/// no planner sees a test frame's view.
pub fn record_sim_dense(
    dir: &Path,
    angles: usize,
    raster: usize,
    progress: &dyn Progress,
) -> Result<Vec<usize>, BenchError> {
    use crate::scan::plan::{PlanOptions, PlanScene, dense_raster};
    use crate::scan::setup;
    let obj = setup::builtin_object();
    let mesh = obj.mesh();
    let calib = setup::builtin_calibration(None);
    let scene = PlanScene::new(&mesh.positions, &mesh.triangles, &calib)
        .map_err(|e| BenchError::Record(e.to_string()))?;
    let opts = PlanOptions {
        angles,
        raster,
        exposures_s: setup::scan_exposures_s(&[], true),
        ..PlanOptions::default()
    };
    let plan = dense_raster(&scene, &opts).map_err(|e| BenchError::Record(e.to_string()))?;
    let mut cfg = crate::scan::driver::ScanConfig::new(
        dir.to_path_buf(),
        plan,
        calib.clone(),
        crate::dataset::obj_bytes(&mesh),
    );
    cfg.noise_floor = Some(setup::sim_noise_floor(&cfg.plan.exposures_s));
    let mut camera =
        setup::camera_from_spec("sim", &mesh, &calib, 1, std::time::Duration::from_secs(10))
            .map_err(|e| BenchError::Record(e.to_string()))?;
    let mut connect = || {
        let link = crate::sim::SimLink::clean(crate::sim::VirtualRig::new(
            crate::sim::SimParams::default(),
        ));
        crate::rig::RigClient::connect_with_seq(link, crate::rig::ClientConfig::default(), 1)
    };
    crate::scan::driver::run_with_reconnect(&cfg, &mut connect, camera.as_mut(), progress, 3)
        .map_err(|e| BenchError::Record(e.to_string()))?;
    let test: Vec<usize> = cfg
        .plan
        .frames()
        .iter()
        .filter(|f| f.angle_index % 3 == 0)
        .map(|f| f.index)
        .collect();
    Ok(test)
}

/// Where [`bench_replay`] keeps its work for dataset `name` under `root`.
pub fn work_dir(root: &Path, name: &str) -> PathBuf {
    root.join(name)
}

impl Bench {
    /// The verdicts as Markdown: the pool, then per start set the stop and each comparison
    /// (paired mean ± SE, 90 % interval, pass), for BENCHMARKS.md and docs/acquisition.md.
    pub fn table(&self) -> String {
        let f = |x: Option<f64>| x.map_or("–".to_string(), |v| format!("{v:.4}"));
        let iv = |t: &Tost| {
            t.interval.map_or("unbounded".to_string(), |[a, b]| {
                format!("[{a:.4}, {b:.4}]")
            })
        };
        let mut s = format!(
            "pool: {} frames that show a spot, rig time {:.1} s; test log E {} ± {} ({} frames, \
             {} clusters); margin {}\n\n\
             | start | frames (share) | rig time (s) | stop | against | at | their frames | \
             adaptive − other ± SE | 90 % interval | pass |\n\
             | --- | --- | ---: | --- | --- | --- | ---: | --- | --- | --- |\n",
            self.pool,
            self.pool_rig_s,
            f(self.pool_test.log_e),
            f(self.pool_test.se),
            self.pool_test.frames,
            self.pool_test.clusters,
            self.margin
        );
        for r in &self.starts {
            for (i, c) in r.comparisons.iter().enumerate() {
                let lead = if i == 0 {
                    format!(
                        "{} | {} ({:.0} %) | {:.1} | {}",
                        r.start_seed,
                        r.frames,
                        100.0 * r.share,
                        r.rig_s,
                        r.stop.split(':').next().unwrap_or_default()
                    )
                } else {
                    " | | | ".to_string()
                };
                s.push_str(&format!(
                    "| {lead} | {} | {} | {} | {:+.4} ± {} | {} | {} |\n",
                    c.against,
                    c.at,
                    c.frames,
                    c.paired.mean,
                    f(c.paired.se),
                    iv(&c.paired),
                    if c.pass { "yes" } else { "no" }
                ));
            }
        }
        let met = self.starts.iter().filter(|r| r.meets_the_bar()).count();
        s.push_str(&format!(
            "\nthe bar (equivalent to the pool with at most {:.0} % of its frames, non-inferior to \
             coverage and every random seed at equal frames) met on {met} of {} start sets; {} \
             fits, {:.0} s\n",
            100.0 * MAX_SHARE,
            self.starts.len(),
            self.fits,
            self.seconds
        ));
        s
    }

    /// The curves for [`crate::plot::learning_curves`]: each point's paired difference to the
    /// whole pool on the test frames with its 95 % half-width (t on clusters − 1 degrees of
    /// freedom), a scale on which planners a few hundredths apart can be told apart.
    pub fn curves(&self) -> Vec<crate::plot::LearningCurve> {
        let mut out: Vec<crate::plot::LearningCurve> = Vec::new();
        for p in &self.points {
            if p.test.log_e.is_none() || p.vs_pool.frames == 0 {
                continue;
            }
            let half = match (p.vs_pool.se, p.vs_pool.dof) {
                (Some(se), Some(dof)) => t95(dof) * se,
                _ => f64::NAN,
            };
            let pt = (p.frames as f64, p.rig_s, p.vs_pool.mean, half);
            match out.iter_mut().find(|c| c.name == p.planner) {
                Some(c) => c.points.push(pt),
                None => out.push(crate::plot::LearningCurve {
                    name: p.planner.clone(),
                    points: vec![pt],
                }),
            }
        }
        out
    }

    /// Draws [`Bench::curves`] to `path`.
    pub fn plot(&self, path: &Path) -> Result<(), crate::plot::PlotError> {
        let name = Path::new(&self.dataset)
            .file_name()
            .map_or(String::new(), |n| n.to_string_lossy().to_string());
        crate::plot::learning_curves(
            path,
            &format!("learning curves: {name} (95 % intervals; dashed: the margin)"),
            "test log E − the whole pool's, paired",
            &self.curves(),
            Some(self.margin),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Non-inferiority needs a bounded interval whose upper end is below the margin; one
    /// cluster never passes, identical predictions do.
    #[test]
    fn non_inferiority_reads_the_upper_end_and_fails_on_one_cluster() {
        let four = Clustering::of_folds(&[vec![0, 1], vec![2, 3], vec![4, 5], vec![6, 7]]);
        let one = Clustering::of_folds(&[(0..8).collect()]);
        let te = |v: &[f64]| TestError {
            per_frame: v.iter().copied().enumerate().collect(),
            ..TestError::default()
        };
        let base = te(&[0.5; 8]);
        let better = te(&[0.45, 0.46, 0.44, 0.47, 0.45, 0.46, 0.44, 0.45]);
        let worse = te(&[0.55, 0.56, 0.54, 0.57, 0.55, 0.56, 0.54, 0.55]);
        // adaptive − other: better than the other passes, clearly worse fails.
        assert!(non_inferior(&paired(&base, &better, &four, MARGIN), MARGIN));
        assert!(!non_inferior(&paired(&base, &worse, &four, MARGIN), MARGIN));
        let t = paired(&base, &better, &one, MARGIN);
        assert!(!t.pass && !non_inferior(&t, MARGIN), "{t:?}");
        assert!(non_inferior(&paired(&base, &base, &one, MARGIN), MARGIN));
        // Equivalence at the declared margin: a fall of 0.05 is not equivalent.
        assert!(!paired(&base, &better, &four, MARGIN).pass);
    }

    /// The equal-rig-time prefix is the longest within the time.
    #[test]
    fn the_equal_time_prefix_is_the_longest_within_it() {
        let rig = |o: &[usize]| 10.0 * o.len() as f64;
        assert_eq!(prefix_within(&[4, 5, 6, 7], 25.0, &rig), 2);
        assert_eq!(prefix_within(&[4, 5], 5.0, &rig), 0);
        assert_eq!(prefix_within(&[4, 5], 100.0, &rig), 2);
    }
}
