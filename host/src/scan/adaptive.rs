//! Acquisition steered by predicted error: after each batch of frames the scan fits a
//! model from its own sample store, estimates the model's held-out error by cross-validation,
//! and asks for the next batch where the model is least certain, until that error has stopped
//! falling.
//!
//! Why: frames are the rig's expensive part (a turntable move, galvo settling and every
//! exposure bracket per frame), and how many light positions a material needs depends on the
//! material, which a plan made before anything is measured cannot know. The fit already knows
//! during the scan how well it predicts frames it has not seen.
//!
//! The loop is the same whatever serves the frames ([`FrameSource`]): the rig and a camera
//! ([`super::rigsource::RigSource`]) or a recorded dataset replayed ([`super::replay::Replay`]),
//! so a planner can be judged on recorded scans and a dense scan re-planned after the fact.
//!
//! - **Start**: a sparse coverage plan ([`start_batch`]): the candidate whose predicted x_i has
//!   the most vertices near it, then each time the one farthest from every x_i chosen.
//! - **Assess** ([`assess`]): the fit of `subsurf fit` (the cheap draft preset, no alpha
//!   lattice, no t1 candidate) with its cross-validated alpha rounds ([`crate::crossval`]); the
//!   folds' held-out log E per frame (Eq. 8, mean over its channels) is the learning curve's
//!   figure, its mean with the standard error clustered by fold (the frames of a fold share
//!   one fit: [`crate::evaluate::summary::Clustering::rule`], the rule of every judge).
//! - **Choose** ([`next_batch`]): each candidate left is scored by four signs that the model is
//!   uncertain there, each in 0..1: no acquired x_i close to its predicted x_i; vertices near it
//!   interpolated or without a model; the held-out error of the acquired frames around it
//!   (frames that failed count as the worst); the held-out error of its turntable angle (an
//!   angle not yet seen counts as the worst). The best-scoring candidates are taken greedily,
//!   each pick making its neighbourhood "close" for the next.
//! - **Stop** ([`stop_reason`]) when the cross-validated error has stopped falling: for
//!   `patience` assessments no point gained on the best so far by the cross-validation's own
//!   minimum gain ([`crate::crossval::counts_as_gain`], half a standard error of the paired
//!   difference over the frames both judged, clustered by fold; so a batch of hard frames does
//!   not look like a loss, and a slow steady fall adds up against the best), and the comparison
//!   rests on at least `min_clusters` folds; or at `until_error`, `max_frames` or `max_rig_s`,
//!   whichever comes first.
//!
//! Resumable: the batches are written to `acquisition.json` before they are acquired and the
//! assessments are deterministic, so a scan killed at any point and run again ends with the
//! same frames.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::plan::{AnglePlan, PLAN_FORMAT, RigTiming, ScanPlan, estimate_duration};
use crate::dataset::{Dataset, DatasetError, FrameChannel, WriteError, write_atomic};
use crate::evaluate::Clustering;
use crate::evaluate::summary::{ErrorSource, clustered_mean};
use crate::modelfile::VertexStatus;
use crate::pipeline::{PipelineError, PipelineOptions, StoreOptions};
use crate::progress::Progress;

/// The acquisition report a steered (or replayed) scan keeps beside `scan.json`: the frames'
/// order (candidate per frame), the batches, the learning curve and why the scan stopped.
pub const REPORT_FILE: &str = "acquisition.json";

/// `format` of [`REPORT_FILE`].
pub const REPORT_FORMAT: &str = "subsurf-acquisition/1";

/// Why a steered scan stopped short of a decision.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AdaptiveError {
    /// The scan so far could not be read back.
    #[error("reading the scan so far")]
    Dataset(#[from] DatasetError),
    /// The fit after a batch failed.
    #[error("the fit after {frames} frames failed")]
    Fit {
        /// Frames fitted.
        frames: usize,
        /// Why.
        #[source]
        source: PipelineError,
    },
    /// Writing the dataset or the report failed.
    #[error(transparent)]
    Write(#[from] WriteError),
    /// The rig or camera stopped the scan (resumable: run the same command again).
    #[error(transparent)]
    Scan(#[from] super::driver::ScanError),
    /// The report in the output directory belongs to another scan.
    #[error(
        "{path} belongs to another scan (other candidates or settings); use another --out \
         directory, or delete it to start over"
    )]
    Mismatch {
        /// The report.
        path: PathBuf,
    },
    /// The report could not be read.
    #[error("cannot read {path}: {why}")]
    Report {
        /// The report.
        path: PathBuf,
        /// Why.
        why: String,
    },
    /// Nothing can be acquired (no candidate is predicted to show a spot), or a setting is
    /// out of range.
    #[error("{0}")]
    Invalid(String),
}

/// One frame a planner may ask for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// Its id in the source: the frame index of a replayed dataset, the index among the
    /// candidate plan's frames on the rig.
    pub id: usize,
    /// Turntable angle, degrees.
    pub turntable_deg: f64,
    /// Galvo codes, where known (the rig time's settle jumps).
    pub galvo: Option<[u16; 2]>,
    /// The predicted laser spot x_i (object frame, mm); `None` where the laser is predicted to
    /// miss or the camera not to see the spot ([`super::plan::predicted_spot`]).
    pub x_i: Option<[f64; 3]>,
}

/// What serves the frames a planner asks for: the rig and a camera, or a recorded dataset.
pub trait FrameSource {
    /// The frames that may be asked for.
    fn candidates(&self) -> &[Candidate];
    /// The output dataset directory.
    fn dir(&self) -> &Path;
    /// Frames already in the output dataset (a lower bound is fine: [`FrameSource::acquire`]
    /// with nothing to do does nothing).
    fn done(&self) -> usize;
    /// Makes the output dataset hold the candidates `order` (ids), in that order: acquires those
    /// past the frames already there. Resumes after a kill.
    fn acquire(&mut self, order: &[usize], progress: &dyn Progress) -> Result<(), AdaptiveError>;
    /// The rig's timing, for the rig time of a sequence of frames ([`rig_seconds`]).
    fn timing(&self) -> &RigTiming;
    /// Exposure bracket of each frame (s).
    fn exposures_s(&self) -> &[f64];
    /// What the source is, for the report.
    fn describe(&self) -> String;
}

/// The rig time (s) of acquiring `batches` (candidate ids of `cands`, each batch in its capture
/// order) with the fits `fit_waits_s` in between, by the plan's own estimate
/// ([`estimate_duration`]): every batch is one session of the scan driver, so it starts with a
/// homing and its turntable moves start from home; then galvo settling, every exposure and the
/// per-capture overhead; the dark frames once; and the rig waits, idle, for each assessment's fit
/// (it does not capture while the fit runs). The one rig time of every planner's learning curve,
/// so replayed and simulated scans are compared alike; a fixed plan is one batch and no wait.
pub fn rig_seconds(
    cands: &[Candidate],
    batches: &[Vec<usize>],
    fit_waits_s: &[f64],
    t: &RigTiming,
    exposures_s: &[f64],
) -> f64 {
    let mut s = 0.0;
    for (k, b) in batches.iter().enumerate() {
        let e = batch_duration(cands, b, t, exposures_s);
        s += e.total_s() - if k > 0 { e.dark_s } else { 0.0 };
    }
    s += fit_waits_s.iter().filter(|w| w.is_finite()).sum::<f64>();
    if s.is_finite() { s.max(0.0) } else { 0.0 }
}

/// One batch's session from a homed rig (homing, dark frames and captures in `order`).
fn batch_duration(
    cands: &[Candidate],
    order: &[usize],
    t: &RigTiming,
    exposures_s: &[f64],
) -> super::plan::DurationEstimate {
    let by_id: BTreeMap<usize, &Candidate> = cands.iter().map(|c| (c.id, c)).collect();
    let mut angles: Vec<AnglePlan> = Vec::new();
    for id in order {
        let Some(c) = by_id.get(id) else { continue };
        let target = c.galvo.unwrap_or([0, 0]);
        match angles.last_mut() {
            Some(a) if a.turntable_deg.to_bits() == c.turntable_deg.to_bits() => {
                a.targets.push(target)
            }
            _ => angles.push(AnglePlan {
                turntable_deg: c.turntable_deg,
                targets: vec![target],
            }),
        }
    }
    let plan = ScanPlan {
        format: PLAN_FORMAT.into(),
        planner: "sequence".into(),
        target_mm: 0.0,
        exposures_s: exposures_s.to_vec(),
        channel: FrameChannel::Rgb,
        angles,
    };
    estimate_duration(&plan, t, 0)
}

/// `order` sorted by turntable angle, then id: how a fixed plan is captured, so the turntable
/// turns once round.
pub fn in_turntable_order(cands: &[Candidate], order: &[usize]) -> Vec<usize> {
    let by_id: BTreeMap<usize, f64> = cands.iter().map(|c| (c.id, c.turntable_deg)).collect();
    let mut v = order.to_vec();
    let deg = |id: &usize| by_id.get(id).map_or(0.0, |d| d.rem_euclid(360.0));
    v.sort_by(|a, b| deg(a).total_cmp(&deg(b)).then(a.cmp(b)));
    v
}

/// Settings of the adaptive planner. Every constant is an argument; the defaults are fractions
/// of the candidate pool, never chosen on any dataset's test frames.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveSettings {
    /// Frames of the sparse start; `None`: an eighth of the candidates predicted to show a spot
    /// (at least 4).
    pub start: Option<usize>,
    /// Frames per later batch; `None`: as many as the start.
    pub batch: Option<usize>,
    /// Assessments after the best so far, none gaining on it by the minimum gain, before the
    /// scan stops ([`DEFAULT_PATIENCE`], two, the cross-validation's own patience: one batch may
    /// gain within noise and the next still fall).
    pub patience: usize,
    /// The minimum gain, in standard errors of the paired difference
    /// ([`crate::crossval::MIN_GAIN_SE`], the alpha rounds' own rule).
    #[serde(default = "default_min_gain_se")]
    pub min_gain_se: f64,
    /// Clusters (folds) the comparison with the best must rest on before the scan may stop on a
    /// stalled error ([`DEFAULT_MIN_CLUSTERS`]).
    #[serde(default = "default_min_clusters")]
    pub min_clusters: usize,
    /// Which sparse start ([`start_batch`]): 0 the one that starts at the densest x_i, any other
    /// value a start at a candidate drawn by this seed.
    #[serde(default)]
    pub start_seed: u64,
    /// Stop once the cross-validated error is at most this.
    pub until_error: Option<f64>,
    /// Stop before more frames than this.
    pub max_frames: Option<usize>,
    /// Stop before more rig time than this (s, [`rig_seconds`]).
    pub max_rig_s: Option<f64>,
    /// Cross-validation folds of each assessment.
    pub folds: usize,
    /// Radius (mm) within which an acquired x_i counts as close to a vertex or a candidate:
    /// the fit's own (`PipelineOptions::max_select_mm`) unless given.
    pub near_mm: Option<f64>,
}

/// Assessments in a row within noise before the adaptive scan stops (`--patience`).
pub const DEFAULT_PATIENCE: usize = 2;

/// Clusters a stop must rest on: five, the cross-validation's default folds
/// ([`crate::crossval::DEFAULT_FOLDS`]) and the fewest at which `subsurf evaluate` stops warning
/// that the interval rests on too few degrees of freedom
/// ([`crate::evaluate::summary::FEW_CLUSTERS`]): below it a "no gain" is no evidence, since half
/// a standard error measured on two to four clusters is itself a guess.
pub const DEFAULT_MIN_CLUSTERS: usize = crate::evaluate::summary::FEW_CLUSTERS;

fn default_min_gain_se() -> f64 {
    crate::crossval::MIN_GAIN_SE
}

fn default_min_clusters() -> usize {
    DEFAULT_MIN_CLUSTERS
}

impl Default for AdaptiveSettings {
    fn default() -> Self {
        AdaptiveSettings {
            start: None,
            batch: None,
            patience: DEFAULT_PATIENCE,
            min_gain_se: crate::crossval::MIN_GAIN_SE,
            min_clusters: DEFAULT_MIN_CLUSTERS,
            start_seed: 0,
            until_error: None,
            max_frames: None,
            max_rig_s: None,
            folds: crate::crossval::DEFAULT_FOLDS,
            near_mm: None,
        }
    }
}

impl AdaptiveSettings {
    /// The start and batch sizes for a pool of `useful` candidates predicted to show a spot.
    pub fn sizes(&self, useful: usize) -> (usize, usize) {
        let start = self.start.unwrap_or(useful.div_ceil(8).max(4)).max(1);
        let batch = self.batch.unwrap_or(start).max(1);
        (start, batch)
    }

    fn check(&self) -> Result<(), AdaptiveError> {
        if let Some(e) = self.until_error
            && !(e.is_finite() && e >= 0.0)
        {
            return Err(AdaptiveError::Invalid(format!(
                "--until-error must be a finite log E >= 0, got {e}"
            )));
        }
        if let Some(t) = self.max_rig_s
            && !(t.is_finite() && t > 0.0)
        {
            return Err(AdaptiveError::Invalid(format!(
                "--max-rig-time must be positive seconds, got {t}"
            )));
        }
        if let Some(r) = self.near_mm
            && !(r.is_finite() && r > 0.0)
        {
            return Err(AdaptiveError::Invalid(format!(
                "the near radius must be positive mm, got {r}"
            )));
        }
        if !(self.min_gain_se.is_finite() && self.min_gain_se >= 0.0) {
            return Err(AdaptiveError::Invalid(format!(
                "the minimum gain must be a finite number of standard errors >= 0, got {}",
                self.min_gain_se
            )));
        }
        if self.folds < 2 {
            return Err(AdaptiveError::Invalid(
                "the adaptive planner cross-validates: it needs at least 2 folds".into(),
            ));
        }
        Ok(())
    }
}

/// One point of the learning curve: the scan after a batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    /// Batches acquired.
    pub batch: usize,
    /// Frames acquired.
    pub frames: usize,
    /// Rig time of those frames (s, [`rig_seconds`]).
    pub rig_s: f64,
    /// Cross-validated held-out log E: the mean over the frames the folds predicted.
    pub cv_log_e: Option<f64>,
    /// Its standard error, clustered by fold.
    pub cv_se: Option<f64>,
    /// Frames the folds predicted.
    pub judged: usize,
    /// Clusters (folds) they fell into.
    pub clusters: usize,
    /// The fall of the held-out error since the previous point, paired over the frames both
    /// judged (positive: better).
    pub improvement: Option<f64>,
    /// Its standard error, clustered by fold.
    pub improvement_se: Option<f64>,
    /// The batch of the best point so far after this one: it moves only by a gain on the
    /// previous best that counts ([`crate::crossval::counts_as_gain`]).
    #[serde(default)]
    pub best_batch: usize,
    /// The fall of the held-out error from the best point before this one to this one, paired
    /// over the frames both judged (positive: better).
    #[serde(default)]
    pub gain: Option<f64>,
    /// Its standard error, clustered by fold.
    #[serde(default)]
    pub gain_se: Option<f64>,
    /// Clusters (folds) of that comparison.
    #[serde(default)]
    pub gain_clusters: usize,
    /// Wall time of the fit and its cross-validation (s).
    pub fit_s: f64,
    /// Each judged frame's held-out log E (frame index → mean over its channels).
    pub per_frame: BTreeMap<usize, f64>,
}

impl CurvePoint {
    /// The point as the scan prints it while it goes.
    pub fn line(&self) -> String {
        let f = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.4}"));
        let delta = match (self.improvement, self.improvement_se) {
            (Some(d), se) => format!(", improved by {} ± {}", f(Some(d)), f(se)),
            _ => String::new(),
        };
        let best = match self.gain {
            Some(g) if self.best_batch != self.batch || self.batch > 1 => format!(
                "; against the best before: {} ± {} over {} folds, best now batch {}",
                f(Some(g)),
                f(self.gain_se),
                self.gain_clusters,
                self.best_batch
            ),
            _ => String::new(),
        };
        format!(
            "batch {}: {} frames, rig time {:.1} s, cross-validated log E {} ± {} ({} frames \
             judged, {} folds){delta}{best}; fit {:.1} s",
            self.batch,
            self.frames,
            self.rig_s,
            f(self.cv_log_e),
            f(self.cv_se),
            self.judged,
            self.clusters,
            self.fit_s
        )
    }
}

/// [`REPORT_FILE`]: what a steered or replayed scan did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AcquisitionReport {
    /// [`REPORT_FORMAT`].
    pub format: String,
    /// The planner.
    pub planner: String,
    /// What served the frames.
    pub source: String,
    /// What identifies the scan (candidates and settings) for resuming.
    pub key: String,
    /// Candidates offered.
    pub candidates: usize,
    /// The settings.
    pub settings: AdaptiveSettings,
    /// The candidate ids asked for, per batch, in capture order: frame k of the dataset is the
    /// k-th id of the concatenation.
    pub batches: Vec<Vec<usize>>,
    /// The learning curve, one point per batch assessed.
    pub curve: Vec<CurvePoint>,
    /// Why the scan stopped, once it has.
    pub stopped: Option<String>,
}

impl AcquisitionReport {
    /// The candidate ids of the dataset's frames, in order.
    pub fn order(&self) -> Vec<usize> {
        self.batches.concat()
    }

    /// Reads `dir`'s report, if it has one.
    pub fn load(dir: &Path) -> Result<Option<AcquisitionReport>, AdaptiveError> {
        let path = dir.join(REPORT_FILE);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| AdaptiveError::Report {
            path: path.clone(),
            why: e.to_string(),
        })?;
        let r: AcquisitionReport =
            serde_json::from_str(&text).map_err(|e| AdaptiveError::Report {
                path: path.clone(),
                why: e.to_string(),
            })?;
        if r.format != REPORT_FORMAT {
            return Err(AdaptiveError::Report {
                path,
                why: format!("format {:?}, not {REPORT_FORMAT}", r.format),
            });
        }
        Ok(Some(r))
    }

    /// Writes it to `dir` (atomically).
    pub fn save(&self, dir: &Path) -> Result<(), AdaptiveError> {
        let text = serde_json::to_string_pretty(self).map_err(|e| AdaptiveError::Report {
            path: dir.join(REPORT_FILE),
            why: e.to_string(),
        })?;
        Ok(write_atomic(&dir.join(REPORT_FILE), text.as_bytes())?)
    }
}

/// A finite value or nothing (every number written is finite).
fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// The model after a batch and how well it predicts frames its fit did not see.
#[derive(Debug, Clone)]
pub struct Assessment {
    /// Held-out log E per frame the folds judged (mean over its finite channels); a frame the
    /// folds could not judge (no spot, failed fit) is absent.
    pub per_frame: BTreeMap<usize, f64>,
    /// The cross-validation's folds (frames): what clusters `per_frame`'s errors, since the
    /// frames of a fold share one fit ([`crate::evaluate::summary::ErrorSource::Folds`]).
    pub folds: Vec<Vec<usize>>,
    /// Mean of `per_frame` and its standard error clustered by fold.
    pub mean: Option<f64>,
    /// See `mean`.
    pub se: Option<f64>,
    /// Clusters of the standard error.
    pub clusters: usize,
    /// Per vertex: whether its model is its own fit (not interpolated, not missing).
    pub fitted: Vec<bool>,
    /// The mesh vertices (object frame).
    pub positions: Vec<[f64; 3]>,
    /// The fit's near radius (`max_select_mm`).
    pub near_mm: f64,
    /// Wall time (s).
    pub seconds: f64,
}

/// The options of an assessment's fit: `subsurf fit --preset draft` on the dataset's noise floor,
/// without the alpha lattice (the folds judge at the vertices, where it changes nothing).
pub fn assessment_options(ds: &Dataset, floor: f64) -> (PipelineOptions, crate::fit::FitOptions) {
    let (opts, fit) = PipelineOptions::for_dataset(ds).with_preset(Some(crate::fit::Preset::Draft));
    let mut opts = opts.with_noise_floor(floor);
    opts.alpha_lattice = crate::pipeline::AlphaLattice::Off;
    (opts, fit)
}

/// The options the sample store is prepared with: those of `subsurf fit`'s default run (its
/// lattice points included), so the store a scan extracts as frames arrive
/// (`pipeline::extract::ScanExtraction`) is the one the assessment opens; the fit then drops
/// the lattice ([`assessment_options`]), which changes no extraction setting.
fn store_options(ds: &Dataset, floor: f64) -> PipelineOptions {
    PipelineOptions::for_dataset(ds).with_noise_floor(floor)
}

/// Fits the frames of the dataset in `dir` from its sample store (extracted once per frame set,
/// cached in the dataset) and cross-validates it ([`crate::crossval::fit_scan_in`]), judged by
/// the dataset's evaluation protocol ([`crate::pipeline::judge_context`]).
pub fn assess(
    dir: &Path,
    folds: usize,
    progress: &dyn Progress,
) -> Result<Assessment, AdaptiveError> {
    let clock = std::time::Instant::now();
    let ds = Dataset::open(dir)?;
    let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
    let fail = |source| AdaptiveError::Fit {
        frames: frames.len(),
        source,
    };
    let (protocol, floor) = crate::pipeline::evaluation_protocol(&ds).map_err(fail)?;
    let (opts, fit) = assessment_options(&ds, floor.value);
    let store = StoreOptions {
        budget: crate::store::DEFAULT_BUDGET,
        cache: crate::pipeline::Cache::Dataset,
    };
    let run = crate::pipeline::prepare(
        &ds,
        &frames,
        &store_options(&ds, floor.value),
        &store,
        progress,
    )
    .map_err(fail)?
    .with_options(opts)
    .map_err(fail)?;
    let judge = crate::pipeline::judge_context(&run, &frames, Some(&protocol), &store, progress)
        .map_err(fail)?;
    // The reference preset's folds and rounds rule: the planner's curve and stop were
    // validated with them (docs/acquisition.md).
    let cv = crate::crossval::CvSettings {
        folds,
        segments: crate::crossval::Segments::Fixed(1),
        t1: false,
        // The draft's error is judged at the vertices; a lattice would not change it.
        lattice: false,
        ..crate::crossval::CvSettings::reference()
    };
    let out =
        crate::crossval::fit_scan_in(&run, &judge, &frames, &cv, &fit, progress).map_err(fail)?;
    let mut per_frame = BTreeMap::new();
    let folds = out
        .report
        .cross_validation
        .as_ref()
        .map(|r| r.folds.clone())
        .unwrap_or_default();
    if let Some(r) = &out.report.cross_validation {
        for (&f, v) in &r.per_frame {
            let ch: Vec<f64> = v
                .iter()
                .flatten()
                .copied()
                .filter(|x| x.is_finite())
                .collect();
            if !ch.is_empty() {
                per_frame.insert(f, ch.iter().sum::<f64>() / ch.len() as f64);
            }
        }
    }
    let (mean, se, clusters) = clustered(&ds, &folds, &per_frame);
    Ok(Assessment {
        per_frame,
        folds,
        mean,
        se,
        clusters,
        fitted: out
            .model
            .vertices
            .iter()
            .map(|v| v.status == VertexStatus::Fitted)
            .collect(),
        positions: out.model.positions.clone(),
        near_mm: opts.max_select_mm,
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// The clusters of cross-validated per-frame errors: the folds that judged them, by the one
/// rule every judge shares ([`Clustering::rule`]).
fn fold_clusters(ds: &Dataset, folds: &[Vec<usize>], frames: &BTreeMap<usize, f64>) -> Clustering {
    let judged: Vec<(usize, Option<[f64; 3]>)> = frames.keys().map(|&f| (f, None)).collect();
    Clustering::rule(ds, &judged, ErrorSource::Folds(folds))
}

/// Mean of cross-validated per-frame errors with its standard error clustered by fold (the
/// frames of a fold share one fit); and the clusters.
fn clustered(
    ds: &Dataset,
    folds: &[Vec<usize>],
    per_frame: &BTreeMap<usize, f64>,
) -> (Option<f64>, Option<f64>, usize) {
    let clusters = fold_clusters(ds, folds, per_frame);
    let v: Vec<(f64, f64, (bool, usize))> = per_frame
        .iter()
        .map(|(&f, &e)| (e, 1.0, clusters.cluster(f)))
        .collect();
    match clustered_mean(&v) {
        Some(m) => (finite(m.mean), m.se.and_then(finite), m.clusters),
        None => (None, None, 0),
    }
}

/// The fall of the held-out error from `prev` to `cur`, paired over the frames both judged, its
/// standard error clustered by the folds of `cur`'s cross-validation (`folds`), which judged the
/// current errors (`None` with fewer than two clusters), and the clusters.
fn paired_improvement(
    ds: &Dataset,
    folds: &[Vec<usize>],
    prev: &BTreeMap<usize, f64>,
    cur: &BTreeMap<usize, f64>,
) -> (Option<f64>, Option<f64>, usize) {
    let common: BTreeMap<usize, f64> = cur
        .iter()
        .filter_map(|(f, c)| Some((*f, prev.get(f)? - c)))
        .collect();
    let clusters = fold_clusters(ds, folds, &common);
    let v: Vec<(f64, f64, (bool, usize))> = common
        .iter()
        .map(|(&f, &d)| (d, 1.0, clusters.cluster(f)))
        .collect();
    match clustered_mean(&v) {
        Some(m) => (finite(m.mean), m.se.and_then(finite), m.clusters),
        None => (None, None, 0),
    }
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// The sparse coverage start: up to `n` candidates predicted to show a spot, the first the one
/// whose x_i has the most of `vertices` within `near_mm` (`seed` 0) or one drawn by `seed`
/// (another start set, to judge the planner on more than one start), each next the one whose
/// x_i is farthest from every x_i chosen (ties to the lowest id): few frames spread over the
/// object.
pub fn start_batch(
    cands: &[Candidate],
    vertices: &[[f64; 3]],
    near_mm: f64,
    n: usize,
    seed: u64,
) -> Vec<usize> {
    use rand::{Rng, SeedableRng};
    let useful: Vec<(&Candidate, [f64; 3])> =
        cands.iter().filter_map(|c| Some((c, c.x_i?))).collect();
    let drawn = (seed != 0 && !useful.is_empty()).then(|| {
        let i = rand::rngs::StdRng::seed_from_u64(seed).random_range(0..useful.len());
        useful[i].0.id
    });
    let Some(first) = drawn.or_else(|| {
        useful
            .iter()
            .max_by_key(|(c, x)| {
                let near = vertices
                    .iter()
                    .filter(|v| dist2(**v, *x) <= near_mm * near_mm)
                    .count();
                (near, std::cmp::Reverse(c.id))
            })
            .map(|(c, _)| c.id)
    }) else {
        return Vec::new();
    };
    let mut chosen = vec![first];
    let mut gap: Vec<f64> = useful
        .iter()
        .map(|(_, x)| {
            dist2(
                *x,
                useful
                    .iter()
                    .find(|(c, _)| c.id == first)
                    .map_or(*x, |u| u.1),
            )
        })
        .collect();
    while chosen.len() < n.min(useful.len()) {
        let Some((i, _)) = useful
            .iter()
            .enumerate()
            .filter(|(_, (c, _))| !chosen.contains(&c.id))
            .max_by(|a, b| gap[a.0].total_cmp(&gap[b.0]).then(b.1.0.id.cmp(&a.1.0.id)))
        else {
            break;
        };
        chosen.push(useful[i].0.id);
        let x = useful[i].1;
        for (g, (_, y)) in gap.iter_mut().zip(&useful) {
            *g = g.min(dist2(x, *y));
        }
    }
    chosen
}

/// The coverage planner over recorded candidates: greedy set cover of `vertices` by balls of
/// `radius_mm` around the candidates' predicted x_i, each time the candidate covering the most
/// vertices not yet covered (ties to the lowest id), until no candidate adds any.
pub fn cover_order(cands: &[Candidate], vertices: &[[f64; 3]], radius_mm: f64) -> Vec<usize> {
    let r2 = radius_mm * radius_mm;
    let sets: Vec<(usize, Vec<usize>)> = cands
        .iter()
        .filter_map(|c| {
            let x = c.x_i?;
            Some((
                c.id,
                (0..vertices.len())
                    .filter(|&v| dist2(vertices[v], x) <= r2)
                    .collect(),
            ))
        })
        .collect();
    let mut covered = vec![false; vertices.len()];
    let mut taken = vec![false; sets.len()];
    let mut out = Vec::new();
    loop {
        let best = sets
            .iter()
            .enumerate()
            .filter(|(i, _)| !taken[*i])
            .map(|(i, (id, s))| (i, *id, s.iter().filter(|&&v| !covered[v]).count()))
            .max_by_key(|(_, id, n)| (*n, std::cmp::Reverse(*id)));
        match best {
            Some((i, id, n)) if n > 0 => {
                taken[i] = true;
                out.push(id);
                for &v in &sets[i].1 {
                    covered[v] = true;
                }
            }
            _ => return out,
        }
    }
}

/// The next batch of up to `n` candidates not in `order`, where the model assessed by `a` is
/// least certain (the module docs: the four signs, greedily, each pick making its
/// neighbourhood close for the next). Candidates predicted to show no spot are never asked
/// for. Sorted by turntable angle, then id, so the rig turns as little as it can.
pub fn next_batch(cands: &[Candidate], order: &[usize], a: &Assessment, n: usize) -> Vec<usize> {
    let near = a.near_mm.max(1e-9);
    let far = 2.0 * near;
    let by_id: BTreeMap<usize, &Candidate> = cands.iter().map(|c| (c.id, c)).collect();
    // The acquired frames: x_i, angle, held-out error (a frame the folds could not judge counts
    // as the worst error seen).
    let worst = a
        .per_frame
        .values()
        .copied()
        .fold(0.0f64, f64::max)
        .max(1e-9);
    let acquired: Vec<(Option<[f64; 3]>, u64, f64)> = order
        .iter()
        .enumerate()
        .filter_map(|(k, id)| {
            let c = by_id.get(id)?;
            let e = a.per_frame.get(&k).copied().unwrap_or(worst);
            Some((c.x_i, angle_key(c.turntable_deg), e))
        })
        .collect();
    let mut angle_err: BTreeMap<u64, (f64, usize)> = BTreeMap::new();
    for (_, ang, e) in &acquired {
        let s = angle_err.entry(*ang).or_default();
        s.0 += e;
        s.1 += 1;
    }
    struct Cand {
        id: usize,
        x: [f64; 3],
        ang: u64,
        gap: f64,
        vertex: f64,
        local: f64,
        angle: f64,
    }
    let taken: std::collections::BTreeSet<usize> = order.iter().copied().collect();
    let mut pool: Vec<Cand> = cands
        .iter()
        .filter(|c| !taken.contains(&c.id))
        .filter_map(|c| {
            let x = c.x_i?;
            let ang = angle_key(c.turntable_deg);
            let d = acquired
                .iter()
                .filter_map(|(y, _, _)| Some(dist2(x, (*y)?)))
                .fold(f64::INFINITY, f64::min)
                .sqrt();
            let (mut nv, mut unfitted) = (0usize, 0usize);
            for (p, ok) in a.positions.iter().zip(&a.fitted) {
                if dist2(*p, x) <= near * near {
                    nv += 1;
                    unfitted += usize::from(!ok);
                }
            }
            let local: Vec<f64> = acquired
                .iter()
                .filter(|(y, _, _)| y.is_some_and(|y| dist2(x, y) <= far * far))
                .map(|(_, _, e)| *e)
                .collect();
            Some(Cand {
                id: c.id,
                x,
                ang,
                gap: (d / far).min(1.0),
                vertex: if nv == 0 {
                    1.0
                } else {
                    unfitted as f64 / nv as f64
                },
                local: if local.is_empty() {
                    1.0
                } else {
                    (local.iter().sum::<f64>() / local.len() as f64 / worst).min(1.0)
                },
                angle: angle_err
                    .get(&ang)
                    .map_or(1.0, |(s, k)| (s / *k as f64 / worst).min(1.0)),
            })
        })
        .collect();
    let mut out = Vec::new();
    while out.len() < n && !pool.is_empty() {
        let score = |c: &Cand| c.gap + c.vertex + c.local + c.angle;
        let Some(i) = (0..pool.len()).max_by(|&i, &j| {
            score(&pool[i])
                .total_cmp(&score(&pool[j]))
                .then(pool[j].id.cmp(&pool[i].id))
        }) else {
            break;
        };
        let pick = pool.swap_remove(i);
        for c in &mut pool {
            let d = dist2(c.x, pick.x).sqrt();
            c.gap = c.gap.min((d / far).min(1.0));
            if d <= near {
                c.vertex = 0.0;
            }
        }
        out.push((pick.ang, pick.id));
    }
    let _ = by_id;
    out.sort_by(|a, b| {
        f64::from_bits(a.0)
            .total_cmp(&f64::from_bits(b.0))
            .then(a.1.cmp(&b.1))
    });
    out.into_iter().map(|(_, id)| id).collect()
}

/// A turntable angle as a key (degrees in 0..360, rounded to a micro-degree).
fn angle_key(deg: f64) -> u64 {
    let d = deg.rem_euclid(360.0);
    ((d * 1e6).round() / 1e6).to_bits()
}

/// The best point so far once `cur` joins a curve whose best so far is `best` (`None`: `cur`
/// is the first with a figure): `cur` replaces it only when its paired gain on it (`gain`, `se`
/// of `cur` against `best`) counts by the cross-validation's minimum-gain rule
/// ([`crate::crossval::counts_as_gain`]); a missing or zero SE never counts.
pub fn next_best(
    best: Option<&CurvePoint>,
    cur_batch: usize,
    cur_has_figure: bool,
    gain: Option<f64>,
    se: Option<f64>,
    min_gain_se: f64,
) -> usize {
    match best {
        Some(b) if b.cv_log_e.is_some() || !cur_has_figure => {
            let counts = gain.is_some_and(|g| {
                crate::crossval::counts_as_gain(g, se.unwrap_or(f64::INFINITY), min_gain_se)
            });
            if counts { cur_batch } else { b.batch }
        }
        _ => cur_batch,
    }
}

/// Why the scan stops after the last point of `curve`, if it does.
pub fn stop_reason(curve: &[CurvePoint], s: &AdaptiveSettings) -> Option<String> {
    let p = curve.last()?;
    if let (Some(goal), Some(e)) = (s.until_error, p.cv_log_e)
        && e <= goal
    {
        return Some(format!(
            "the cross-validated error {e:.4} reached --until-error {goal}"
        ));
    }
    let patience = s.patience.max(1);
    let stalled = p.batch.saturating_sub(p.best_batch);
    if stalled >= patience && p.gain_clusters >= s.min_clusters.max(2) && p.cv_log_e.is_some() {
        let f = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.4}"));
        return Some(format!(
            "the cross-validated error stopped falling: {stalled} batch(es) since batch {} \
             gained on it by less than {} standard errors, the last by {} ± {} over {} folds",
            p.best_batch,
            s.min_gain_se,
            f(p.gain),
            f(p.gain_se),
            p.gain_clusters
        ));
    }
    if s.max_frames.is_some_and(|m| p.frames >= m) {
        return Some(format!("--max-frames {} reached", p.frames));
    }
    if let Some(t) = s.max_rig_s
        && p.rig_s >= t
    {
        return Some(format!("--max-rig-time {t} s reached"));
    }
    None
}

/// `batch` cut so that the scan (`batches`, the fits `waits_s`, then the batch) stays within
/// `max_frames` and `max_rig_s`.
fn within_budget(
    source: &dyn FrameSource,
    batches: &[Vec<usize>],
    waits_s: &[f64],
    batch: Vec<usize>,
    s: &AdaptiveSettings,
) -> Vec<usize> {
    let done: usize = batches.iter().map(Vec::len).sum();
    let mut kept: Vec<usize> = Vec::new();
    for id in batch {
        if s.max_frames.is_some_and(|m| done + kept.len() >= m) {
            break;
        }
        kept.push(id);
        if let Some(t) = s.max_rig_s {
            let mut all = batches.to_vec();
            all.push(kept.clone());
            let rig = rig_seconds(
                source.candidates(),
                &all,
                waits_s,
                source.timing(),
                source.exposures_s(),
            );
            if rig > t {
                kept.pop();
            }
        }
    }
    kept
}

/// The string that identifies a steered scan: its candidates and settings.
fn key_of(source: &dyn FrameSource, s: &AdaptiveSettings) -> String {
    let text = serde_json::to_string(&(source.candidates(), s)).unwrap_or_default();
    format!(
        "{:016x}",
        crc::Crc::<u64>::new(&crc::CRC_64_ECMA_182).checksum(text.as_bytes())
    )
}

/// Runs the adaptive planner over `source` until it stops (or resumes it: the report in the
/// output directory says where it was); `each` sees every new point of the learning curve as it
/// is made. Returns the final report (also in [`REPORT_FILE`]).
pub fn run_adaptive(
    source: &mut dyn FrameSource,
    s: &AdaptiveSettings,
    progress: &dyn Progress,
    each: &mut dyn FnMut(&CurvePoint),
) -> Result<AcquisitionReport, AdaptiveError> {
    s.check()?;
    let dir = source.dir().to_path_buf();
    let key = key_of(source, s);
    let mut rep = match AcquisitionReport::load(&dir)? {
        Some(r) if r.key != key || r.planner != "adaptive" => {
            return Err(AdaptiveError::Mismatch {
                path: dir.join(REPORT_FILE),
            });
        }
        Some(r) => r,
        None => AcquisitionReport {
            format: REPORT_FORMAT.into(),
            planner: "adaptive".into(),
            source: source.describe(),
            key,
            candidates: source.candidates().len(),
            settings: s.clone(),
            batches: Vec::new(),
            curve: Vec::new(),
            stopped: None,
        },
    };
    let useful = source
        .candidates()
        .iter()
        .filter(|c| c.x_i.is_some())
        .count();
    if useful == 0 {
        return Err(AdaptiveError::Invalid(
            "no candidate frame is predicted to show a laser spot the camera sees".into(),
        ));
    }
    let (start, batch) = s.sizes(useful);
    loop {
        let order = rep.order();
        if source.done() < order.len() {
            source.acquire(&order, progress)?;
        }
        if rep.stopped.is_some() {
            return Ok(rep);
        }
        if rep.batches.is_empty() {
            // The start needs the mesh: the output's mesh is written before any frame.
            let vertices = mesh_vertices(source)?;
            let near = s.near_mm.unwrap_or(2.0);
            let first = within_budget(
                source,
                &[],
                &[],
                start_batch(source.candidates(), &vertices, near, start, s.start_seed),
                s,
            );
            if first.is_empty() {
                return Err(AdaptiveError::Invalid(
                    "the budget (--max-frames, --max-rig-time) leaves no frame to take".into(),
                ));
            }
            rep.batches.push(first);
            rep.save(&dir)?;
            continue;
        }
        // Every batch is acquired: assess it.
        progress.println(&format!(
            "fitting {} frames to choose the next batch",
            order.len()
        ));
        // Too few frames for any fit (a sparse start on a dim material) is not an error: the
        // curve has no figure yet and the next batch goes where no x_i is close.
        let mut a = match assess(&dir, s.folds, progress) {
            Ok(a) => a,
            Err(AdaptiveError::Fit {
                source: PipelineError::NothingFitted(why),
                ..
            }) => {
                progress.println(&format!(
                    "no model from {} frames yet ({why}): the next batch covers the object",
                    order.len()
                ));
                let positions = mesh_vertices(source)?;
                Assessment {
                    per_frame: BTreeMap::new(),
                    folds: Vec::new(),
                    mean: None,
                    se: None,
                    clusters: 0,
                    fitted: vec![false; positions.len()],
                    positions,
                    near_mm: 2.0,
                    seconds: 0.0,
                }
            }
            Err(e) => return Err(e),
        };
        if let Some(r) = s.near_mm {
            a.near_mm = r;
        }
        let ds = Dataset::open(&dir)?;
        let (improvement, improvement_se, _) = match rep.curve.last() {
            Some(prev) => paired_improvement(&ds, &a.folds, &prev.per_frame, &a.per_frame),
            None => (None, None, 0),
        };
        let best = rep
            .curve
            .last()
            .and_then(|p| rep.curve.iter().find(|q| q.batch == p.best_batch));
        let (gain, gain_se, gain_clusters) = match best {
            Some(b) => paired_improvement(&ds, &a.folds, &b.per_frame, &a.per_frame),
            None => (None, None, 0),
        };
        let batch_no = rep.batches.len();
        let best_batch = next_best(
            best,
            batch_no,
            a.mean.is_some(),
            gain,
            gain_se,
            s.min_gain_se,
        );
        let fit_s = finite(a.seconds).unwrap_or(0.0);
        let mut waits: Vec<f64> = rep.curve.iter().map(|p| p.fit_s).collect();
        waits.push(fit_s);
        let point = CurvePoint {
            batch: batch_no,
            frames: order.len(),
            rig_s: rig_seconds(
                source.candidates(),
                &rep.batches,
                &waits,
                source.timing(),
                source.exposures_s(),
            ),
            cv_log_e: a.mean,
            cv_se: a.se,
            judged: a.per_frame.len(),
            clusters: a.clusters,
            improvement,
            improvement_se,
            best_batch,
            gain,
            gain_se,
            gain_clusters,
            fit_s,
            per_frame: a.per_frame.clone(),
        };
        each(&point);
        rep.curve.push(point);
        let stop = stop_reason(&rep.curve, s);
        match stop {
            Some(why) => rep.stopped = Some(why),
            None => {
                let next = within_budget(
                    source,
                    &rep.batches,
                    &waits,
                    next_batch(source.candidates(), &order, &a, batch),
                    s,
                );
                if next.is_empty() {
                    rep.stopped = Some(
                        if source
                            .candidates()
                            .iter()
                            .filter(|c| c.x_i.is_some())
                            .all(|c| order.contains(&c.id))
                        {
                            "every candidate predicted to show a spot is acquired".into()
                        } else {
                            "the budget (--max-frames, --max-rig-time) leaves no frame to take"
                                .into()
                        },
                    );
                } else {
                    rep.batches.push(next);
                }
            }
        }
        rep.save(&dir)?;
    }
}

/// The mesh vertices of the output dataset (object frame).
fn mesh_vertices(source: &dyn FrameSource) -> Result<Vec<[f64; 3]>, AdaptiveError> {
    let dir = source.dir();
    let text = std::fs::read_to_string(dir.join("scan.json")).map_err(|e| {
        AdaptiveError::Dataset(DatasetError::Io {
            path: dir.join("scan.json"),
            source: e,
        })
    })?;
    let spec: crate::dataset::ScanSpec = serde_json::from_str(&text).map_err(|e| {
        AdaptiveError::Dataset(DatasetError::Json {
            path: dir.join("scan.json"),
            source: e,
        })
    })?;
    let p = crate::dataset::confined_path(dir, &spec.mesh)?;
    let (mesh, _) = crate::dataset::load_obj(&p).map_err(DatasetError::from)?;
    Ok(mesh.positions)
}

/// Runs a fixed order over `source` (the dense, coverage and random planners in replay): acquires
/// every id of `order` and writes the report with the order as one batch (no learning curve).
pub fn run_fixed(
    source: &mut dyn FrameSource,
    planner: &str,
    order: &[usize],
    progress: &dyn Progress,
) -> Result<AcquisitionReport, AdaptiveError> {
    let dir = source.dir().to_path_buf();
    let key = format!(
        "{:016x}",
        crc::Crc::<u64>::new(&crc::CRC_64_ECMA_182).checksum(
            serde_json::to_string(&(planner, order))
                .unwrap_or_default()
                .as_bytes()
        )
    );
    if let Some(r) = AcquisitionReport::load(&dir)?
        && r.key != key
    {
        return Err(AdaptiveError::Mismatch {
            path: dir.join(REPORT_FILE),
        });
    }
    let rep = AcquisitionReport {
        format: REPORT_FORMAT.into(),
        planner: planner.into(),
        source: source.describe(),
        key,
        candidates: source.candidates().len(),
        settings: AdaptiveSettings::default(),
        batches: vec![order.to_vec()],
        curve: Vec::new(),
        stopped: Some("the plan is complete".into()),
    };
    rep.save(&dir)?;
    source.acquire(order, progress)?;
    Ok(rep)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cand(id: usize, deg: f64, x: Option<[f64; 3]>) -> Candidate {
        Candidate {
            id,
            turntable_deg: deg,
            galvo: None,
            x_i: x,
        }
    }

    /// The start spreads over the object; candidates that show no spot are never taken.
    #[test]
    fn the_start_is_spread_and_skips_misses() {
        let cands: Vec<Candidate> = (0..10)
            .map(|i| cand(i, 0.0, (i != 3).then_some([i as f64, 0.0, 0.0])))
            .collect();
        let verts: Vec<[f64; 3]> = (0..10).map(|i| [i as f64, 0.0, 0.0]).collect();
        let s = start_batch(&cands, &verts, 1.5, 3, 0);
        assert_eq!(s.len(), 3);
        assert!(!s.contains(&3));
        // After the densest, the farthest: both ends.
        assert!(s.contains(&0) || s.contains(&9), "{s:?}");
        // Another start set: as many frames, still no miss.
        let other = start_batch(&cands, &verts, 1.5, 3, 7);
        assert_eq!(other.len(), 3);
        assert!(!other.contains(&3), "{other:?}");
        let cover = cover_order(&cands, &verts, 1.0);
        assert!(!cover.contains(&3));
        // Every vertex within 1 mm of a chosen x_i.
        for v in &verts {
            assert!(
                cover
                    .iter()
                    .any(|&id| dist2(cands[id].x_i.unwrap(), *v) <= 1.0)
            );
        }
    }

    /// The next batch goes where no x_i is close and the held-out error is high, never back.
    #[test]
    fn the_next_batch_goes_where_the_model_is_least_certain() {
        let cands: Vec<Candidate> = (0..20)
            .map(|i| {
                cand(
                    i,
                    if i < 10 { 0.0 } else { 90.0 },
                    Some([i as f64, 0.0, 0.0]),
                )
            })
            .collect();
        let order = vec![0, 2, 4, 15];
        let a = Assessment {
            per_frame: [(0, 0.1), (1, 0.1), (2, 0.1), (3, 0.3)]
                .into_iter()
                .collect(),
            folds: Vec::new(),
            mean: Some(0.1),
            se: Some(0.01),
            clusters: 1,
            fitted: vec![true; 20],
            positions: (0..20).map(|i| [i as f64, 0.0, 0.0]).collect(),
            near_mm: 1.0,
            seconds: 0.0,
        };
        let b = next_batch(&cands, &order, &a, 3);
        assert_eq!(b.len(), 3);
        assert!(b.iter().all(|id| !order.contains(id)));
        // The angle that predicts worst (90°), away from its one x_i, wins over the
        // neighbours of 0, 2, 4 at the angle that predicts well.
        assert!(b.iter().all(|&id| id >= 10), "{b:?}");
    }

    fn point(batch: usize, best_batch: usize, gain: Option<f64>, se: Option<f64>) -> CurvePoint {
        CurvePoint {
            batch,
            frames: 12 * batch,
            rig_s: 30.0,
            cv_log_e: Some(0.3),
            cv_se: Some(0.02),
            judged: 12 * batch,
            clusters: 5,
            improvement: gain,
            improvement_se: se,
            best_batch,
            gain,
            gain_se: se,
            gain_clusters: 5,
            fit_s: 1.0,
            per_frame: BTreeMap::new(),
        }
    }

    /// The best so far moves only by a gain of more than half a standard error; a missing or
    /// zero SE never counts as a gain, however large the fall.
    #[test]
    fn the_best_moves_only_by_a_gain_that_counts() {
        let best = point(1, 1, None, None);
        let g = crate::crossval::MIN_GAIN_SE;
        assert_eq!(
            next_best(Some(&best), 2, true, Some(0.05), Some(0.02), g),
            2
        );
        assert_eq!(
            next_best(Some(&best), 2, true, Some(0.005), Some(0.02), g),
            1
        );
        assert_eq!(next_best(Some(&best), 2, true, Some(0.5), None, g), 1);
        assert_eq!(next_best(Some(&best), 2, true, Some(0.5), Some(0.0), g), 1);
        assert_eq!(
            next_best(Some(&best), 2, true, Some(-0.05), Some(0.01), g),
            1
        );
        assert_eq!(next_best(None, 1, true, None, None, g), 1);
        // A first figure after points without one is the best.
        let mut none = best.clone();
        none.cv_log_e = None;
        assert_eq!(next_best(Some(&none), 2, true, None, None, g), 2);
    }

    /// The stopping rule: `patience` batches since the best stop, fewer do not; a comparison on
    /// fewer folds than `min_clusters` never stops (a missing SE there is no evidence of a
    /// plateau); the budget and the error goal stop.
    #[test]
    fn the_scan_stops_when_the_error_stops_falling() {
        let s = AdaptiveSettings::default();
        let p = point(2, 2, Some(0.05), Some(0.01));
        assert_eq!(stop_reason(std::slice::from_ref(&p), &s), None);
        // One batch since the best is not enough with the default patience; two are.
        let q = point(3, 2, Some(0.005), Some(0.01));
        assert_eq!(stop_reason(&[p.clone(), q.clone()], &s), None);
        let r = point(4, 2, Some(0.004), Some(0.01));
        assert!(stop_reason(&[p.clone(), q.clone(), r.clone()], &s).is_some());
        // The same stall on four folds, or with a missing SE on one fold, does not stop.
        let mut few = r.clone();
        few.gain_clusters = 4;
        assert_eq!(stop_reason(&[p.clone(), q.clone(), few], &s), None);
        let mut lone = point(4, 2, Some(0.3), None);
        lone.gain_clusters = 1;
        assert_eq!(stop_reason(&[p.clone(), q.clone(), lone], &s), None);
        let impatient = AdaptiveSettings {
            patience: 1,
            ..AdaptiveSettings::default()
        };
        assert!(stop_reason(&[p.clone(), q.clone()], &impatient).is_some());
        let goal = AdaptiveSettings {
            until_error: Some(0.31),
            ..AdaptiveSettings::default()
        };
        assert!(
            stop_reason(std::slice::from_ref(&p), &goal)
                .unwrap()
                .contains("until-error")
        );
        let frames = AdaptiveSettings {
            max_frames: Some(24),
            ..AdaptiveSettings::default()
        };
        assert!(
            stop_reason(std::slice::from_ref(&p), &frames)
                .unwrap()
                .contains("max-frames")
        );
        let time = AdaptiveSettings {
            max_rig_s: Some(29.0),
            ..AdaptiveSettings::default()
        };
        assert!(
            stop_reason(std::slice::from_ref(&p), &time)
                .unwrap()
                .contains("rig-time")
        );
    }

    /// Rig time grows with frames and with every new turntable angle; every batch adds a
    /// homing, and every assessment's fit is waited for.
    #[test]
    fn rig_time_counts_moves_captures_homing_and_fit_waits() {
        let t = super::super::setup::rig_timing(
            &subsurf_firmware::sim::SimParams::default().profile,
            None,
            None,
            0,
        );
        let cands: Vec<Candidate> = (0..4)
            .map(|i| cand(i, if i < 2 { 0.0 } else { 180.0 }, None))
            .collect();
        let rig = |b: &[Vec<usize>], w: &[f64]| rig_seconds(&cands, b, w, &t, &[0.01]);
        let one = rig(&[vec![0]], &[]);
        let same = rig(&[vec![0, 1]], &[]);
        let moved = rig(&[vec![0, 2]], &[]);
        assert!(
            one > 0.0 && same > one && moved > same,
            "{one} {same} {moved}"
        );
        // Two batches: a second homing (the second session starts from home).
        let split = rig(&[vec![0], vec![1]], &[]);
        assert!(t.home_s > 0.0);
        assert!(
            split >= same + t.home_s - 1e-9,
            "{split} {same} {}",
            t.home_s
        );
        // The fits are waited for.
        let waited = rig(&[vec![0], vec![1]], &[2.5, 4.0]);
        assert!((waited - split - 6.5).abs() < 1e-9, "{waited} {split}");
        assert_eq!(in_turntable_order(&cands, &[3, 0, 2, 1]), vec![0, 1, 2, 3]);
    }
}
