//! `subsurf bench acquisition`: the learning curves of the planners — dense (in its
//! order), coverage, random and adaptive — as held-out error on test frames no planner may pick,
//! against frames and against rig time.
//!
//! Every planner draws from the same pool (a recorded dataset's frames minus the test frames,
//! replayed: [`crate::scan::replay::Replay`]), so the curves differ only by which frames each
//! takes. Each point is a fit of a prefix of the planner's order and its error on the test
//! frames, judged as `subsurf evaluate` judges (the dataset's evaluation protocol, at the
//! vertices, the mean over frames of Eq. 8's log E with its standard error clustered by
//! turntable angle). All fits run from one sample store of the dataset (each frame decoded once).
//! The curves' fits are the adaptive planner's own cheap fit ([`assessment_options`]); the
//! issue's comparison — the adaptive scan's final frames against the whole pool — is also made
//! with the default fit of `subsurf fit`.
use std::path::{Path, PathBuf};

use rand::SeedableRng;
use rand::seq::SliceRandom;

use crate::crossval::{CvSettings, fit_scan_in};
use crate::dataset::Dataset;
use crate::evaluate::{Clustering, EvalPoints, Figures, evaluate_in};
use crate::pipeline::{Context, PipelineError, PipelineOptions, StoreOptions};
use crate::progress::Progress;
use crate::scan::adaptive::{
    AdaptiveError, AdaptiveSettings, FrameSource, assessment_options, cover_order, rig_seconds,
    run_adaptive,
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

/// A fit's error on the test frames.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct TestError {
    /// Mean over the test frames of log E (each frame's mean over its channels).
    pub log_e: Option<f64>,
    /// Its standard error clustered by turntable angle.
    pub se: Option<f64>,
    /// Per channel r, g, b (`subsurf evaluate`'s `mean_log_e`, `se_log_e`).
    pub rgb: [Option<f64>; 3],
    /// See `rgb`.
    pub rgb_se: [Option<f64>; 3],
    /// Test frames judged.
    pub frames: usize,
    /// Why there is no figure, where there is none (too few frames for any fit).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub failed: Option<String>,
}

/// One point of a learning curve.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Point {
    /// The planner.
    pub planner: String,
    /// Frames fitted (a prefix of the planner's order).
    pub frames: usize,
    /// Their rig time (s, [`rig_seconds`]).
    pub rig_s: f64,
    /// Error on the test frames.
    pub test: TestError,
}

/// The benchmark of one dataset.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Bench {
    /// The dataset.
    pub dataset: String,
    /// The test frames (never candidates).
    pub test_frames: Vec<usize>,
    /// Candidates (pool frames).
    pub pool: usize,
    /// Every planner's curve points.
    pub points: Vec<Point>,
    /// The adaptive scan: frames, rig time, why it stopped.
    pub adaptive_frames: usize,
    /// See `adaptive_frames`.
    pub adaptive_rig_s: f64,
    /// See `adaptive_frames`.
    pub adaptive_stop: String,
    /// The pool's rig time in dense order.
    pub dense_rig_s: f64,
    /// The default fit (`subsurf fit`) on the adaptive scan's frames, on the test frames.
    pub default_adaptive: TestError,
    /// The default fit on the whole pool, on the test frames.
    pub default_pool: TestError,
    /// Wall time of the benchmark (s).
    pub seconds: f64,
}

impl Bench {
    /// The check on a recorded dataset: the adaptive scan's model (default fit) within
    /// one standard error of the whole pool's, with at most half the pool's frames.
    pub fn within_one_se_at_half(&self) -> Option<bool> {
        let (a, p) = (self.default_adaptive.log_e?, self.default_pool.log_e?);
        let se = self.default_pool.se?;
        Some(a <= p + se && 2 * self.adaptive_frames <= self.pool)
    }

    /// The check on the simulated rig: the adaptive curve's last error within 5 % of
    /// the dense scan's (the whole pool), at most 40 % of its rig time.
    pub fn within_5_percent_at_40(&self) -> Option<bool> {
        let last = |name: &str| self.points.iter().rfind(|p| p.planner == name);
        let (a, d) = (last("adaptive")?, last("dense")?);
        Some(a.test.log_e? <= 1.05 * d.test.log_e? && a.rig_s <= 0.4 * d.rig_s)
    }
}

/// The fit behind each curve point, from the run `run` (a store of every frame) judged by
/// `judge`.
fn fit_and_test(
    run: &Context,
    judge: &Context,
    frames: &[usize],
    test: &[usize],
    cv: &CvSettings,
    fit: &crate::fit::FitOptions,
) -> Result<TestError, BenchError> {
    let mut frames = frames.to_vec();
    frames.sort_unstable();
    // A prefix too short for any fit (few frames show a spot) is a point without a figure.
    let out = match fit_scan_in(run, judge, &frames, cv, fit, &()) {
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
    let per: Vec<(f64, f64, (bool, usize))> = evals
        .iter()
        .filter(|e| e.skipped.is_none())
        .filter_map(|e| {
            let ch: Vec<f64> = e.log_e.iter().flatten().copied().collect();
            (!ch.is_empty()).then(|| {
                (
                    ch.iter().sum::<f64>() / ch.len() as f64,
                    1.0,
                    clusters.cluster(e.frame),
                )
            })
        })
        .collect();
    let m = crate::evaluate::summary::clustered_mean(&per);
    let fin = |x: Option<f64>| x.filter(|v| v.is_finite());
    Ok(TestError {
        log_e: fin(m.map(|m| m.mean)),
        se: fin(m.and_then(|m| m.se)),
        rgb: fig.mean_log_e.map(fin),
        rgb_se: fig.se_log_e.map(fin),
        frames: fig.frames,
        failed: None,
    })
}

/// Benchmarks the planners on the recorded dataset `src` with `test` held out: the adaptive
/// scan replayed into `work/adaptive` (resumed if there), then every planner's curve. `seed`
/// orders the random planner.
pub fn bench_replay(
    src: &Path,
    test: &[usize],
    work: &Path,
    settings: &AdaptiveSettings,
    seed: u64,
    progress: &dyn Progress,
    log: &mut dyn FnMut(&str),
) -> Result<Bench, BenchError> {
    let clock = std::time::Instant::now();
    if test.is_empty() {
        return Err(BenchError::Invalid(
            "no test frames: say which frames no planner may pick".into(),
        ));
    }
    let mut replay = Replay::open(src, &work.join("adaptive"), test)?;
    log("adaptive scan (replayed):");
    let rep = run_adaptive(&mut replay, settings, progress, &mut |p| {
        log(&format!("  {}", p.line()))
    })?;
    log(&format!(
        "  stopped: {}",
        rep.stopped.as_deref().unwrap_or("-")
    ));
    let cands = replay.candidates().to_vec();
    let (timing, exposures) = (*replay.timing(), replay.exposures_s().to_vec());
    let ds: &Dataset = replay.recorded();
    let rig = |order: &[usize]| rig_seconds(&cands, order, &timing, &exposures);
    let adaptive_order = rep.order();
    let dense: Vec<usize> = cands.iter().map(|c| c.id).collect();
    let coverage = cover_order(&cands, &ds.mesh.positions, 2.0);
    let mut random = dense.clone();
    random.shuffle(&mut rand::rngs::StdRng::seed_from_u64(seed));
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
    let cheap_cv = CvSettings {
        folds: settings.folds,
        t1: false,
        ..CvSettings::reference()
    };
    // The curves' points: the adaptive scan's batch ends, and the same frame counts for the
    // others (up to each order's length), plus each order's end.
    let mut counts: Vec<usize> = rep.curve.iter().map(|p| p.frames).collect();
    counts.push(dense.len());
    counts.sort_unstable();
    counts.dedup();
    let mut jobs: Vec<(&str, Vec<usize>)> = Vec::new();
    for (name, order) in [
        ("dense", &dense),
        ("coverage", &coverage),
        ("random", &random),
        ("adaptive", &adaptive_order),
    ] {
        let mut ns: Vec<usize> = counts
            .iter()
            .copied()
            .filter(|&n| n < order.len())
            .collect();
        ns.push(order.len());
        ns.dedup();
        for n in ns {
            jobs.push((name, order[..n].to_vec()));
        }
    }
    progress.start("learning curves", jobs.len() as u64 + 2);
    let mut points = Vec::new();
    for (name, frames) in &jobs {
        let t = fit_and_test(&cheap_run, &judge, frames, test, &cheap_cv, &cheap_fit)?;
        points.push(Point {
            planner: name.to_string(),
            frames: frames.len(),
            rig_s: rig(frames),
            test: t,
        });
        progress.inc(1);
    }
    // The comparison, with `subsurf fit`'s default fit.
    let default_fit = crate::fit::FitOptions::default();
    let default_cv = CvSettings::default();
    let default_adaptive = fit_and_test(
        &run,
        &judge,
        &adaptive_order,
        test,
        &default_cv,
        &default_fit,
    )?;
    progress.inc(1);
    let default_pool = fit_and_test(&run, &judge, &dense, test, &default_cv, &default_fit)?;
    progress.inc(1);
    Ok(Bench {
        dataset: src.display().to_string(),
        test_frames: test.to_vec(),
        pool: dense.len(),
        points,
        adaptive_frames: adaptive_order.len(),
        adaptive_rig_s: rig(&adaptive_order),
        adaptive_stop: rep.stopped.clone().unwrap_or_default(),
        dense_rig_s: rig(&dense),
        default_adaptive,
        default_pool,
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
    /// The curves as a Markdown table (planner, frames, rig time, test log E ± SE), then the
    /// issue's comparisons, for BENCHMARKS.md.
    pub fn table(&self) -> String {
        let f = |x: Option<f64>| x.map_or("–".to_string(), |v| format!("{v:.4}"));
        let mut s = String::from(
            "| planner | frames | rig time (s) | test log E ± SE (mean of r, g, b) | r / g / b |\n\
             | --- | ---: | ---: | --- | --- |\n",
        );
        for p in &self.points {
            s.push_str(&format!(
                "| {} | {} | {:.1} | {} ± {} | {} / {} / {} |\n",
                p.planner,
                p.frames,
                p.rig_s,
                f(p.test.log_e),
                f(p.test.se),
                f(p.test.rgb[0]),
                f(p.test.rgb[1]),
                f(p.test.rgb[2]),
            ));
        }
        s.push_str(&format!(
            "\nadaptive: {} of {} pool frames, rig time {:.1} s of dense's {:.1} s ({:.0} %); {}\n\
             default fit on the adaptive frames: test log E {} ± {} (r/g/b {} / {} / {}); on the \
             whole pool: {} ± {} (r/g/b {} / {} / {})\n",
            self.adaptive_frames,
            self.pool,
            self.adaptive_rig_s,
            self.dense_rig_s,
            100.0 * self.adaptive_rig_s / self.dense_rig_s.max(1e-9),
            self.adaptive_stop,
            f(self.default_adaptive.log_e),
            f(self.default_adaptive.se),
            f(self.default_adaptive.rgb[0]),
            f(self.default_adaptive.rgb[1]),
            f(self.default_adaptive.rgb[2]),
            f(self.default_pool.log_e),
            f(self.default_pool.se),
            f(self.default_pool.rgb[0]),
            f(self.default_pool.rgb[1]),
            f(self.default_pool.rgb[2]),
        ));
        let yes = |b: Option<bool>| match b {
            Some(true) => "met",
            Some(false) => "not met",
            None => "not measurable",
        };
        s.push_str(&format!(
            "within one SE of the whole pool with at most half its frames (default fits): {}; \
             within 5 % of dense's error (last points of the curves) in at most 40 % of its rig \
             time: {}\n",
            yes(self.within_one_se_at_half()),
            yes(self.within_5_percent_at_40())
        ));
        s
    }

    /// The curves for [`crate::plot::learning_curves`].
    pub fn curves(&self) -> Vec<crate::plot::LearningCurve> {
        let mut out: Vec<crate::plot::LearningCurve> = Vec::new();
        for p in &self.points {
            let Some(e) = p.test.log_e else { continue };
            let pt = (p.frames as f64, p.rig_s, e);
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
}
