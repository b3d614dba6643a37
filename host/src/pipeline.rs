//! Scan processing (section 5): from a dataset to a per-vertex model.
//!
//! Stages, each timed: `mesh` (BVH, adjacency) → `registration` (x_i per frame, streamed) →
//! `selection` (closest x_i per vertex) → `fit` (one fit per distinct selected light position,
//! streamed, alpha accumulated on the way, Eq. 6) → `error` (log E(x_i) with alpha, Eq. 8; frames
//! are read again rather than kept, so memory does not grow with the frame count) →
//! `interpolate` (failed vertices, harmonic in log-parameter space).
//!
//! The solver is passed in ([`Fitter`]): the pipeline never depends on how Eq. 1 is fitted.
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::baseline::Baseline;
use crate::dataset::{Dataset, DatasetError};
use crate::geometry::{Camera, GeometryError, Scene, V3, Visible, add_scaled, normalize};
use crate::model::{
    AlphaAccumulator, Anisotropic, ColourModel, ExpSum, IntensityWindow, LogEAccumulator,
    TangentFrame,
};
use crate::modelfile::{
    BaselineParams, ColourMode, ModelFile, ModelShape, VertexModel, VertexStatus, params_of,
};
use crate::registration::{RegistrationOutcome, SpotOptions, register_frame};
use crate::samples::{Sample, SampleCounts, SampleOptions, frame_samples};
use crate::selection::{Light, select};

/// Why a vertex has no fitted model of its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FailReason {
    /// No light position within the selection distance (for every needed channel).
    NoData,
    /// Too few usable samples, or at too few distances.
    TooFewSamples,
    /// The solver did not converge.
    NotConverged,
    /// log E(x_i) (Eq. 8) above the acceptance threshold.
    HighError,
    /// The fit gave non-finite or non-physical parameters (c <= 0, d >= 0, s <= 0).
    NonPhysical,
    /// The selected frame's image could not be read.
    FrameUnreadable,
}

/// Fits Eq. 1 to samples `s` at distances `r`. `terms = Some(n)` forces n terms; `None` uses the
/// fitter's own setting (which may choose the order automatically).
pub trait Fitter: Sync {
    /// One isotropic fall-off fit.
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason>;
}

/// Which model variant each vertex gets.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ModelChoice {
    /// Shared colour (Eq. 5/9) or per channel (Eq. 3).
    pub colour: ColourMode,
    /// Direction segments m (Eq. 3); 1 = isotropic (Eq. 9, the paper's choice for objects).
    pub segments: usize,
}

/// Every setting of the pipeline.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PipelineOptions {
    /// Spot detection and the laser cross-check.
    pub spot: SpotOptions,
    /// Sample extraction.
    pub samples: SampleOptions,
    /// A vertex whose closest x_i is farther than this (mm) has no data.
    pub max_select_mm: f64,
    /// The model variant.
    pub model: ModelChoice,
    /// Fits with log E(x_i) (Eq. 8, mean over channels) above this fail.
    pub max_log_e: f64,
    /// Fits with log E(x_i) above this multiple of the median over all fits (and above
    /// [`OUTLIER_MIN_LOG_E`]) fail too: outliers, interpolated from neighbours;
    /// `f64::INFINITY` disables the rule.
    pub outlier_factor: f64,
    /// Eq. 6 window [t2, t1] for alpha(x_o).
    pub alpha_window: IntensityWindow,
    /// Eq. 8 threshold t.
    pub error_threshold: f64,
    /// At most this many extra fit rounds on samples divided by the previous round's alpha(x_o)
    /// (Eq. 6); 0 fits once and treats the modulation texture as noise.
    pub alpha_rounds: usize,
    /// The rounds stop early once alpha has converged: the RMS change of ln alpha(x_o) over the
    /// vertices between two rounds is below this. Fit and Eq. 6 are a block coordinate descent
    /// that converges linearly, so a fixed small round count leaves part of the modulation
    /// texture in the fall-off (measured on the built-in scan: held-out log E 0.026 after one
    /// round, 0.014 after four); the tolerance pays only for the rounds the data need.
    pub alpha_tolerance: f64,
}

impl PipelineOptions {
    /// Defaults for a dataset: noise floor and saturation from `scan.json`.
    pub fn for_dataset(ds: &Dataset) -> PipelineOptions {
        let floor = ds.spec.noise_floor.unwrap_or(0.0);
        PipelineOptions {
            spot: SpotOptions {
                min_peak: 10.0 * floor,
                saturation: ds.spec.saturation,
                laser_tolerance_mm: 2.0,
            },
            samples: SampleOptions {
                noise_floor: floor,
                saturation: ds.spec.saturation,
                ..SampleOptions::default()
            },
            max_select_mm: 2.0,
            model: ModelChoice {
                colour: ColourMode::Shared,
                segments: 1,
            },
            max_log_e: 1.0,
            outlier_factor: 3.0,
            alpha_window: IntensityWindow {
                t2: 10.0 * floor,
                t1: f64::INFINITY,
            },
            error_threshold: floor,
            alpha_rounds: 8,
            alpha_tolerance: 2e-3,
        }
    }
}

/// Why the pipeline stopped (per-frame and per-vertex problems are reported, not errors).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// The mesh could not be prepared.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// The dataset is unusable.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// Nothing could be fitted at all.
    #[error("no vertex could be fitted: {0}")]
    NothingFitted(String),
    /// Options are inconsistent.
    #[error("invalid options: {0}")]
    Invalid(String),
}

/// Frames by what registration concluded.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FrameCounts {
    /// Frames in the dataset.
    pub total: usize,
    /// Frames selected for this run (`--frames`/`--exclude-frames`).
    pub selected: usize,
    /// Frames with x_i on the object.
    pub registered: usize,
    /// Frames without a bright enough spot.
    pub no_spot: usize,
    /// Frames whose spot is not on the mesh.
    pub spot_off_object: usize,
    /// Frames whose spot disagrees with the laser ray (flagged, not used).
    pub laser_mismatch: usize,
    /// Frames whose image could not be read.
    pub unreadable: usize,
    /// The first few read errors, verbatim.
    pub unreadable_errors: Vec<String>,
    /// Frames some vertex selected (fits run).
    pub fitted: usize,
}

/// Table-1 statistics of log E(x_i) over the fitted light positions, per channel.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LogEStats {
    /// Number of light positions with a value.
    pub count: usize,
    /// Mean per channel (Table 1).
    pub mean: [Option<f64>; 3],
    /// Median per channel.
    pub median: [Option<f64>; 3],
}

impl LogEStats {
    /// Statistics of per-light values `[r, g, b]` (NaN = missing).
    pub fn of(values: &[[f64; 3]]) -> LogEStats {
        let mut st = LogEStats {
            count: values.len(),
            ..LogEStats::default()
        };
        for c in 0..3 {
            let mut v: Vec<f64> = values
                .iter()
                .map(|x| x[c])
                .filter(|x| x.is_finite())
                .collect();
            if v.is_empty() {
                continue;
            }
            v.sort_by(f64::total_cmp);
            st.mean[c] = Some(v.iter().sum::<f64>() / v.len() as f64);
            let m = v.len() / 2;
            st.median[c] = Some(if v.len() % 2 == 1 {
                v[m]
            } else {
                0.5 * (v[m - 1] + v[m])
            });
        }
        st
    }
}

/// `fit-report.json`.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct FitReport {
    /// Vertices of the mesh.
    pub vertices: usize,
    /// Vertices with their own fit.
    pub vertices_fitted: usize,
    /// Vertices interpolated from neighbours.
    pub vertices_interpolated: usize,
    /// Vertices left without a model (not connected to any fitted vertex).
    pub vertices_no_model: usize,
    /// Failed vertices by reason (before interpolation).
    pub failures: BTreeMap<FailReason, usize>,
    /// Frames.
    pub frames: FrameCounts,
    /// Mesh problems found on loading.
    pub mesh: crate::dataset::MeshReport,
    /// Samples kept and dropped in the fit stage.
    pub samples: SampleCounts,
    /// log E(x_i) (Eq. 8, with alpha) over fitted light positions.
    pub log_e: LogEStats,
    /// Number of fitted light positions per chosen model order n.
    pub orders: BTreeMap<usize, usize>,
    /// Terms dropped because the samples do not support them, by reason (each drop refits
    /// with one term fewer; counted in the last fit round, not in interpolation refits).
    pub terms_dropped: BTreeMap<TermDropped, usize>,
    /// Where each vertex's alpha(x_o) (Eq. 6) comes from.
    pub alpha: AlphaReport,
    /// The homogeneous baseline (one isotropic fall-off for all x_i, [`crate::baseline`]).
    pub baseline: Option<BaselineReport>,
    /// The log E(x_i) acceptance threshold applied: `max_log_e`, or `outlier_factor` × the
    /// median fit's log E (at least [`OUTLIER_MIN_LOG_E`]) if lower.
    pub max_log_e: f64,
    /// Wall time per stage, seconds.
    pub stage_seconds: BTreeMap<String, f64>,
    /// Peak resident memory of the process, MiB (Linux; `None` elsewhere).
    pub peak_rss_mib: Option<f64>,
    /// The options used.
    pub options: Option<PipelineOptions>,
}

/// The homogeneous baseline in the report.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct BaselineReport {
    /// Terms n of the fit.
    pub terms: usize,
    /// Parameters in the model file's order (m = 1).
    pub params: Vec<f64>,
    /// `[r_min, r_max]` of the pooled samples, mm.
    pub r_range: [f64; 2],
    /// Channel samples pooled (every k-th of a group's samples above [`BASELINE_POOL`]).
    pub samples: usize,
    /// Table-1 statistics of log E(x_i) (Eq. 8, alpha = 1) of the baseline on the fitted light
    /// positions: compare with `log_e`.
    pub log_e: LogEStats,
}

/// At most this many samples per channel of one light position go into the baseline's pooled fit
/// (evenly strided), so its cost does not grow with the image size.
pub const BASELINE_POOL: usize = 2000;

/// One alpha round (Eq. 6) in the report.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct AlphaRound {
    /// Round (0 = the fit on the samples as captured).
    pub round: usize,
    /// Training objective after the round's fit: sum over the fitted samples of
    /// (ln alpha + ln R_d − ln s)^2 with the alpha it was fitted against.
    pub objective: f64,
    /// The same objective of the previous round's fits with this round's alpha (what the round
    /// had to beat); equals `objective` for round 0.
    pub previous: f64,
    /// Light positions whose new fit was worse than their previous one and kept the previous.
    pub fits_kept_previous: usize,
    /// Whether the round lowered the objective and was kept (a round that does not is
    /// discarded and the rounds stop).
    pub kept: bool,
}

/// Where the vertices' alpha(x_o) (Eq. 6) come from.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct AlphaReport {
    /// Eq. 6 from the vertex's own samples in the intensity window.
    pub from_samples: usize,
    /// No sample in the window (never seen by a fitted frame): interpolated from neighbours.
    pub interpolated: usize,
    /// Neither: alpha = 1.
    pub default_one: usize,
    /// Fit rounds on alpha-divided samples that were run (at most `alpha_rounds`).
    pub rounds: usize,
    /// RMS change of ln alpha(x_o) in the last round (0 when no extra round ran): below
    /// `alpha_tolerance` when the rounds converged.
    pub last_change: f64,
    /// Whether the rounds stopped because alpha converged (RMS change below the tolerance).
    pub converged: bool,
    /// Every round: its training objective and whether it was kept.
    pub round_log: Vec<AlphaRound>,
}

/// Peak resident set size of this process (`VmHWM`), MiB.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Visible vertices per (camera, turntable angle bits).
type VisCache = HashMap<(usize, u64), Arc<Vec<Visible>>>;

/// Shared state of one run: scene, cameras, cached visibility.
pub struct Context<'a> {
    /// The dataset.
    pub ds: &'a Dataset,
    /// Mesh with BVH.
    pub scene: Scene,
    cams: Vec<Camera>,
    vis: Mutex<VisCache>,
    /// Options.
    pub opts: PipelineOptions,
}

impl<'a> Context<'a> {
    /// Prepares the mesh and cameras of `ds`.
    pub fn new(ds: &'a Dataset, opts: PipelineOptions) -> Result<Context<'a>, PipelineError> {
        Ok(Context {
            ds,
            scene: Scene::new(ds.mesh.clone())?,
            cams: ds.spec.cameras.iter().map(Camera::new).collect(),
            vis: Mutex::new(HashMap::new()),
            opts,
        })
    }

    /// The camera model of camera `k`.
    pub fn camera(&self, k: usize) -> &Camera {
        &self.cams[k]
    }

    /// Visible vertices of camera `cam` at turntable angle `deg` (cached: frames share angles).
    pub fn visible(&self, cam: usize, deg: f64) -> Arc<Vec<Visible>> {
        let key = (cam, deg.to_bits());
        if let Ok(m) = self.vis.lock()
            && let Some(v) = m.get(&key)
        {
            return v.clone();
        }
        let v = Arc::new(self.scene.visible_vertices(
            &self.cams[cam],
            deg,
            self.opts.samples.cos_min,
        ));
        if let Ok(mut m) = self.vis.lock() {
            if m.len() >= 256 {
                m.clear();
            }
            m.insert(key, v.clone());
        }
        v
    }

    /// Registers frame `k` (reads its image).
    pub fn register(&self, k: usize) -> Result<RegistrationOutcome, DatasetError> {
        let img = self.ds.read_frame(k)?;
        let f = &self.ds.spec.frames[k];
        Ok(register_frame(&img, f, &self.cams[f.camera], &self.scene, &self.opts.spot).0)
    }

    /// The samples of frame `k` with light at `x_i` (reads its image).
    pub fn samples(&self, k: usize, x_i: V3) -> Result<(Vec<Sample>, SampleCounts), DatasetError> {
        let img = self.ds.read_frame(k)?;
        let f = &self.ds.spec.frames[k];
        let vis = self.visible(f.camera, f.turntable_deg);
        Ok(frame_samples(
            &img,
            f,
            &vis,
            &self.ds.mesh.positions,
            x_i,
            &self.opts.samples,
        ))
    }

    /// Interpolated unit normal at a point of triangle `tri`.
    pub fn normal_at(&self, tri: u32, p: V3) -> V3 {
        let t = self.scene.mesh.triangles[tri as usize];
        let w = self.scene.barycentric(tri, p);
        let mut n = [0.0; 3];
        for k in 0..3 {
            n = add_scaled(n, w[k], self.scene.mesh.normals[t[k] as usize]);
        }
        normalize(n).unwrap_or([0.0, 0.0, 1.0])
    }
}

/// A registered light: frame, x_i, triangle.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Reg {
    frame: usize,
    x_i: V3,
    triangle: u32,
}

/// Per-channel samples of one light-position group: (r, s, vertex, φ).
type ChannelSamples = [Vec<(f64, f64, u32, Option<f64>)>; 3];

#[derive(Clone)]
struct GroupFit {
    model: ColourModel,
    terms: usize,
    /// Sampled distance range `[r_min, r_max]` of the fit.
    r_range: [f64; 2],
}

fn fit_failure_from_model(e: crate::model::ModelError) -> FailReason {
    let _ = e;
    FailReason::NonPhysical
}

/// Why a fitted exponential term was dropped ("model only what the scene requires"): the
/// samples do not support it, so the fit is repeated with one term fewer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TermDropped {
    /// The term hardly decays over the sampled distances (|d|·(r_max − r_min) below
    /// [`MIN_DECAY`]): it is indistinguishable from a constant there and would never decay
    /// beyond (fits produce d ≈ −1e−16 such terms).
    NonDecaying,
    /// The term carries at least [`MIN_SHARE`] of R_d at fewer than [`MIN_SUPPORT`] distinct
    /// sampled distances: typically a fall-off steeper than the spacing of the samples near x_i
    /// resolves, which the fit places below the smallest sampled distance, where it explodes.
    Unresolved,
}

/// A fit within this log E (3 % RMS) is never an outlier, however good the typical fit is
/// (noise-free scans: log E ~ 1e-4 with relative spread far above `outlier_factor`).
pub const OUTLIER_MIN_LOG_E: f64 = 0.03;

/// Smallest total decay |d|·(r_max − r_min) of a supported term (see [`TermDropped`]).
pub const MIN_DECAY: f64 = 0.1;
/// Share c·e^{d·r} / R_d(r) above which a sample counts as supporting a term.
pub const MIN_SHARE: f64 = 0.05;
/// Distinct sampled distances a term needs as support (see [`TermDropped`]).
pub const MIN_SUPPORT: usize = 4;

/// The first term of `f` the sample distances `r` do not support, if any.
pub fn unsupported_term(f: &ExpSum, r: &[f64]) -> Option<TermDropped> {
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
    let ln_min_share = MIN_SHARE.ln();
    for t in &f.terms {
        let ln_c = t.c.ln();
        let support = rs
            .iter()
            .filter(|&&x| ln_c + t.d * x - f.ln_eval(x) >= ln_min_share)
            .count();
        if support < MIN_SUPPORT {
            return Some(TermDropped::Unresolved);
        }
    }
    None
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
    let mut f = fitter.fit(r, s, terms)?;
    loop {
        match unsupported_term(&f, r) {
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
fn fit_common_order(
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

/// A direction segment's fit with the isotropic order, or the isotropic fall-off where the
/// segment's fit fails or has a term that never decays. (A sector holds a fraction of the
/// samples, so the support rule for steep terms would reject most segments; the isotropic fit
/// already chose an order the samples support, and evaluation never extrapolates below the
/// sampled range.)
///
/// A segment whose steepest term decays more than [`SEGMENT_MAX_RATE_RATIO`] times faster than
/// the isotropic fit's steepest one is not a direction effect but a term fitted to a handful of
/// near samples; it also keeps the slope at r_min so steep that the continuation below r_min
/// (`evaluate::ln_eval_supported`, the renderer's self term) explodes towards r = 0.
fn fit_segment(fitter: &dyn Fitter, r: &[f64], s: &[f64], iso: &ExpSum) -> ExpSum {
    let steepest = |f: &ExpSum| f.terms.iter().map(|t| -t.d).fold(0.0, f64::max);
    match fitter.fit(r, s, Some(iso.n())) {
        Ok(f)
            if f.n() == iso.n()
                && unsupported_term(&f, r) != Some(TermDropped::NonDecaying)
                && steepest(&f) <= SEGMENT_MAX_RATE_RATIO * steepest(iso) =>
        {
            f
        }
        _ => iso.clone(),
    }
}

/// How much faster than the isotropic fit's steepest term a direction segment's steepest term
/// may decay (Eq. 3): light travelling 4x less far across the veins than the isotropic mean is
/// far beyond the anisotropy of the materials in the paper (and of the simulator's, at most
/// 1 / (1 - 0.6) = 2.5 along against across).
pub const SEGMENT_MAX_RATE_RATIO: f64 = 4.0;

/// The model variant fitted to one group's samples, its order and the terms dropped on the way.
fn fit_samples(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
    dropped: &mut Vec<TermDropped>,
) -> Result<(ColourModel, usize), FailReason> {
    let rs = |c: usize, sel: &dyn Fn(Option<f64>) -> bool| -> (Vec<f64>, Vec<f64>) {
        data[c]
            .iter()
            .filter(|x| sel(x.3))
            .map(|x| (x.0, x.1))
            .unzip()
    };
    let all = |_: Option<f64>| true;
    let m = choice.segments.max(1);
    let sector = |l: usize| {
        move |phi: Option<f64>| {
            phi.is_some_and(|p| (p * m as f64 / std::f64::consts::TAU).round() as usize % m == l)
        }
    };
    match choice.colour {
        ColourMode::PerChannel => {
            let sets: Vec<(Vec<f64>, Vec<f64>)> = (0..3).map(|c| rs(c, &all)).collect();
            let isos = fit_common_order(fitter, &sets, None, dropped)?;
            let n = isos[0].n();
            let mut chans = Vec::with_capacity(3);
            for (c, iso) in isos.into_iter().enumerate() {
                let mut segs = Vec::with_capacity(m);
                for l in 0..m {
                    if m == 1 {
                        segs.push(iso.clone());
                        continue;
                    }
                    let (r, s) = rs(c, &sector(l));
                    segs.push(fit_segment(fitter, &r, &s, &iso));
                }
                chans.push(Anisotropic { segments: segs });
            }
            let channels: [Anisotropic; 3] =
                chans.try_into().map_err(|_| FailReason::NonPhysical)?;
            let model = ColourModel::PerChannel { channels };
            model.validate().map_err(fit_failure_from_model)?;
            Ok((model, n))
        }
        ColourMode::Shared => {
            // Eq. 9 by block coordinate descent on the log objective: fit the red fall-off, set
            // ln s_c to the mean residual of channel c, refit the fall-off to all channels divided
            // by their scales, update the scales. Exact on noise-free data.
            let (r, s) = rs(0, &all);
            let red = fit_supported(fitter, &r, &s, None, dropped)?;
            let scales = |f: &ExpSum| -> Result<[f64; 3], FailReason> {
                let mut out = [1.0; 3];
                for (c, o) in out.iter_mut().enumerate().skip(1) {
                    let d = &data[c];
                    if d.is_empty() {
                        return Err(FailReason::TooFewSamples);
                    }
                    let mean =
                        d.iter().map(|x| x.1.ln() - f.ln_eval(x.0)).sum::<f64>() / d.len() as f64;
                    *o = mean.exp();
                }
                if out.iter().all(|v| v.is_finite() && *v > 0.0) {
                    Ok(out)
                } else {
                    Err(FailReason::NonPhysical)
                }
            };
            let pooled = |sc: &[f64; 3], sel: &dyn Fn(Option<f64>) -> bool| {
                let mut r = Vec::new();
                let mut s = Vec::new();
                for c in 0..3 {
                    for x in data[c].iter().filter(|x| sel(x.3)) {
                        r.push(x.0);
                        s.push(x.1 / sc[c]);
                    }
                }
                (r, s)
            };
            let sc = scales(&red)?;
            let (r, s) = pooled(&sc, &all);
            let iso = fit_supported(fitter, &r, &s, Some(red.n()), dropped)?;
            let n = iso.n();
            let sc = scales(&iso)?;
            let mut segs = Vec::with_capacity(m);
            if m == 1 {
                segs.push(iso);
            } else {
                for l in 0..m {
                    let (r, s) = pooled(&sc, &sector(l));
                    segs.push(fit_segment(fitter, &r, &s, &iso));
                }
            }
            let model = ColourModel::Shared {
                falloff: Anisotropic { segments: segs },
                s_g: sc[1],
                s_b: sc[2],
            };
            model.validate().map_err(fit_failure_from_model)?;
            Ok((model, n))
        }
    }
}

/// The result of [`fit_dataset`].
#[derive(Debug)]
pub struct FitOutput {
    /// The model (write with [`ModelFile::write`]).
    pub model: ModelFile,
    /// The report (`fit-report.json`).
    pub report: FitReport,
}

/// Runs the whole pipeline over the frames `frames` of `ds`.
pub fn fit_dataset(
    ds: &Dataset,
    frames: &[usize],
    opts: &PipelineOptions,
    fitter: &dyn Fitter,
    progress: &indicatif::ProgressBar,
) -> Result<FitOutput, PipelineError> {
    use rayon::prelude::*;
    if opts.model.segments == 0 {
        return Err(PipelineError::Invalid("segments must be >= 1".into()));
    }
    let mut report = FitReport {
        options: Some(*opts),
        mesh: ds.mesh_report.clone(),
        ..FitReport::default()
    };
    let mut t = Instant::now();
    let stage = |name: &str, t: &mut Instant, r: &mut FitReport| {
        r.stage_seconds
            .insert(name.to_string(), t.elapsed().as_secs_f64());
        *t = Instant::now();
    };
    let ctx = Context::new(ds, *opts)?;
    let nv = ds.mesh.positions.len();
    report.vertices = nv;
    report.frames.total = ds.spec.frames.len();
    report.frames.selected = frames.len();
    stage("mesh", &mut t, &mut report);

    // Registration, streamed: one image per worker at a time.
    progress.set_message("registration");
    progress.set_length(frames.len() as u64);
    progress.set_position(0);
    let regs: Vec<(usize, Result<RegistrationOutcome, String>)> = frames
        .par_iter()
        .map(|&k| {
            let r = ctx.register(k).map_err(|e| e.to_string());
            progress.inc(1);
            (k, r)
        })
        .collect();
    let mut lights = Vec::new();
    let mut reg_of = Vec::new();
    for (k, r) in regs {
        match r {
            Ok(RegistrationOutcome::Registered { x_i, triangle, .. }) => {
                report.frames.registered += 1;
                let ch = ds.spec.frames[k].channel.channels();
                lights.push(Light {
                    frame: k,
                    x_i,
                    channels: ch.iter().fold(0u8, |m, c| m | (1 << c)),
                });
                reg_of.push(Reg {
                    frame: k,
                    x_i,
                    triangle,
                });
            }
            Ok(RegistrationOutcome::NoSpot) => report.frames.no_spot += 1,
            Ok(RegistrationOutcome::SpotOffObject) => report.frames.spot_off_object += 1,
            Ok(RegistrationOutcome::LaserMismatch { .. }) => report.frames.laser_mismatch += 1,
            Err(e) => {
                report.frames.unreadable += 1;
                if report.frames.unreadable_errors.len() < 10 {
                    report.frames.unreadable_errors.push(e);
                }
            }
        }
    }
    stage("registration", &mut t, &mut report);

    // Selection: the closest x_i per vertex and channel; identical choices share one fit.
    let sel = select(&ds.mesh.positions, &lights, opts.max_select_mm);
    let mut groups: BTreeMap<[u32; 3], Vec<u32>> = BTreeMap::new();
    let mut vertex_fail: Vec<Option<FailReason>> = vec![None; nv];
    for (v, s) in sel.iter().enumerate() {
        match s {
            [Some(a), Some(b), Some(c)] => groups.entry([*a, *b, *c]).or_default().push(v as u32),
            _ => vertex_fail[v] = Some(FailReason::NoData),
        }
    }
    report.frames.fitted = groups.len();
    stage("selection", &mut t, &mut report);

    // Fit, streamed, with Eq. 6 accumulated per vertex on the way.
    let keys: Vec<[u32; 3]> = groups.keys().copied().collect();
    let load = |key: &[u32; 3]| -> Result<(ChannelSamples, SampleCounts), FailReason> {
        let mut data: ChannelSamples = Default::default();
        let mut counts = SampleCounts::default();
        let red = reg_of[key[0] as usize];
        let frame = TangentFrame::from_normal(ctx.normal_at(red.triangle, red.x_i))
            .map_err(|_| FailReason::NonPhysical)?;
        let mut distinct = key.to_vec();
        distinct.dedup();
        distinct.sort_unstable();
        distinct.dedup();
        for l in distinct {
            let reg = reg_of[l as usize];
            let (s, c) = ctx
                .samples(reg.frame, reg.x_i)
                .map_err(|_| FailReason::FrameUnreadable)?;
            counts.add(&c);
            for x in s {
                let (_, phi) = frame.polar(reg.x_i, ds.mesh.positions[x.vertex as usize]);
                for (ch, slot) in data.iter_mut().enumerate() {
                    if key[ch] == l && x.valid & (1 << ch) != 0 {
                        slot.push((x.r, x.value[ch], x.vertex, phi));
                    }
                }
            }
        }
        Ok((data, counts))
    };
    // Round 0 fits the samples as captured; each further round divides them by the previous
    // round's alpha(x_o) (Eq. 6) and refits, so the modulation texture is not mistaken for
    // noise by the fit of R_d. Every round re-reads the frames (memory does not grow with them).
    //
    // The rounds are a block coordinate descent on the log objective
    // O(R_d, alpha) = sum (ln alpha + ln R_d − ln s)^2 (+ the alpha prior): Eq. 6 in log space is
    // the exact minimiser over alpha for fixed R_d, and a light position whose refit is worse
    // than its previous fit (LM finds a local minimum) keeps the previous one, so no round can
    // increase O. A round that does not lower it is discarded and the rounds stop.
    let sq_err = |m: &ColourModel, data: &ChannelSamples| -> f64 {
        let mut o = 0.0;
        for (ch, d) in data.iter().enumerate() {
            for &(r, s, _, phi) in d {
                let e = m.ln_eval(r, phi)[ch] - s.ln();
                if e.is_finite() {
                    o += e * e;
                }
            }
        }
        o
    };
    let fit_round = |alpha_div: Option<&[[f64; 3]]>,
                     round: usize,
                     prev: Option<&[Option<GroupFit>]>|
     -> FitState {
        progress.set_message(format!("fit (round {})", round + 1));
        progress.set_length(keys.len() as u64);
        progress.set_position(0);
        keys.par_iter()
            .enumerate()
            .fold(FitState::default, |mut st, (idx, key)| {
                let mut dropped = Vec::new();
                let old = prev.and_then(|p| p.get(idx).cloned().flatten());
                let out = load(key).and_then(|(mut data, counts)| {
                    if let Some(a) = alpha_div {
                        for (ch, d) in data.iter_mut().enumerate() {
                            for x in d.iter_mut() {
                                x.1 /= a[x.2 as usize][ch];
                            }
                        }
                    }
                    let new = fit_samples(&data, &opts.model, fitter, &mut dropped).map(
                        |(model, terms)| {
                            let r_range = data
                                .iter()
                                .flatten()
                                .fold([f64::INFINITY, 0.0], |[lo, hi], x| {
                                    [lo.min(x.0), hi.max(x.0)]
                                });
                            GroupFit {
                                model,
                                terms,
                                r_range,
                            }
                        },
                    );
                    let o_old = old.as_ref().map(|g| sq_err(&g.model, &data));
                    let (g, o_new, kept_old) = match (new, o_old) {
                        (Ok(g), Some(oo)) => {
                            let on = sq_err(&g.model, &data);
                            if on <= oo {
                                (g, on, false)
                            } else {
                                (old.clone().expect("o_old implies old"), oo, true)
                            }
                        }
                        (Ok(g), None) => {
                            let on = sq_err(&g.model, &data);
                            (g, on, false)
                        }
                        (Err(_), Some(oo)) => (old.clone().expect("o_old implies old"), oo, true),
                        (Err(e), None) => return Err(e),
                    };
                    Ok((g, data, counts, o_new, o_old.unwrap_or(o_new), kept_old))
                });
                for why in dropped {
                    *st.dropped.entry(why).or_default() += 1;
                }
                match out {
                    Ok((g, data, counts, o_new, o_old, kept_old)) => {
                        st.objective += o_new;
                        st.objective_prev += o_old;
                        st.kept_previous += kept_old as usize;
                        // Eq. 6 contributions are folded right away so the samples can be dropped.
                        if st.alpha.is_empty() {
                            st.alpha = vec![[AlphaAccumulator::default(); 3]; nv];
                        }
                        for (ch, d) in data.iter().enumerate() {
                            for &(r, s, v, phi) in d {
                                // Eq. 6 compares the captured sample with R_d.
                                let s = alpha_div.map_or(s, |a| s * a[v as usize][ch]);
                                let ln_rd = g.model.ln_eval(r, phi)[ch];
                                st.alpha[v as usize][ch].add_ln(s, ln_rd, &opts.alpha_window);
                            }
                        }
                        st.counts.add(&counts);
                        st.fits.push((idx, Ok(g)));
                    }
                    Err(e) => st.fits.push((idx, Err(e))),
                }
                progress.inc(1);
                st
            })
            .reduce(FitState::default, FitState::merge)
    };
    let by_index = |st: &FitState| -> Vec<Option<GroupFit>> {
        let mut v: Vec<Option<GroupFit>> = vec![None; keys.len()];
        for (idx, f) in &st.fits {
            if let Ok(g) = f {
                v[*idx] = Some(g.clone());
            }
        }
        v
    };
    let mut state = fit_round(None, 0, None);
    let mut round_log = vec![AlphaRound {
        round: 0,
        objective: state.objective,
        previous: state.objective,
        fits_kept_previous: 0,
        kept: true,
    }];
    let mut rounds = 0;
    let mut last_change = 0.0;
    let mut converged = false;
    let mut previous: Option<Vec<[f64; 3]>> = None;
    for round in 1..=opts.alpha_rounds {
        let (a, _) = alpha_texture(&state.alpha, nv, &ctx.scene);
        if let Some(prev) = &previous {
            last_change = rms_ln_change(prev, &a);
            if last_change < opts.alpha_tolerance {
                converged = true;
                break;
            }
        }
        let prev_fits = by_index(&state);
        let next = fit_round(Some(&a), round, Some(&prev_fits));
        let kept = next.objective < next.objective_prev * (1.0 - 1e-9);
        round_log.push(AlphaRound {
            round,
            objective: next.objective,
            previous: next.objective_prev,
            fits_kept_previous: next.kept_previous,
            kept,
        });
        if !kept {
            // No gain: the previous state (its fits and their Eq. 6) stands.
            converged = true;
            break;
        }
        state = next;
        rounds = round;
        previous = Some(a);
    }
    let FitState {
        mut fits,
        alpha,
        counts,
        dropped,
        ..
    } = state;
    report.samples = counts;
    report.terms_dropped = dropped;
    fits.sort_by_key(|f| f.0);
    let (alpha, mut alpha_report) = alpha_texture(&alpha, nv, &ctx.scene);
    if let Some(prev) = &previous {
        last_change = rms_ln_change(prev, &alpha);
        converged |= last_change < opts.alpha_tolerance;
    }
    alpha_report.rounds = rounds;
    alpha_report.last_change = last_change;
    alpha_report.converged = converged || opts.alpha_rounds == 0;
    alpha_report.round_log = round_log;
    report.alpha = alpha_report;

    // The homogeneous baseline: one isotropic fall-off (m = 1, the model's colour mode) fitted
    // to every fitted light position's samples pooled, as captured (alpha = 1).
    let pooled: ChannelSamples = keys
        .par_iter()
        .map(|key| {
            let mut out: ChannelSamples = Default::default();
            if let Ok((data, _)) = load(key) {
                for (ch, d) in data.iter().enumerate() {
                    let step = d.len().div_ceil(BASELINE_POOL).max(1);
                    out[ch].extend(d.iter().step_by(step).map(|x| (x.0, x.1, x.2, None)));
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
    let baseline_choice = ModelChoice {
        colour: opts.model.colour,
        segments: 1,
    };
    let baseline = fit_samples(&pooled, &baseline_choice, fitter, &mut Vec::new())
        .ok()
        .and_then(|(model, terms)| {
            let r_range = pooled
                .iter()
                .flatten()
                .fold([f64::INFINITY, 0.0], |[lo, hi], x| {
                    [lo.min(x.0), hi.max(x.0)]
                });
            let (params, _, _) = params_of(&model).ok()?;
            params.iter().all(|p| p.is_finite()).then_some((
                Baseline { model, r_range },
                BaselineParams {
                    terms,
                    params,
                    r_range,
                },
                pooled.iter().map(Vec::len).sum::<usize>(),
            ))
        });
    drop(pooled);
    stage("fit", &mut t, &mut report);

    // Eq. 8 with alpha: read the fitted frames again (cheaper in memory than keeping samples).
    progress.set_message("error");
    progress.set_length(keys.len() as u64);
    progress.set_position(0);
    let both: Vec<(Option<[f64; 3]>, Option<[f64; 3]>)> = fits
        .par_iter()
        .map(|(idx, f)| {
            let out = f.as_ref().ok().and_then(|g| {
                let (data, _) = load(&keys[*idx]).ok()?;
                let mut acc = [LogEAccumulator::default(); 3];
                let mut base = [LogEAccumulator::default(); 3];
                for (ch, d) in data.iter().enumerate() {
                    for &(r, s, v, phi) in d {
                        let ln = alpha[v as usize][ch].ln() + g.model.ln_eval(r, phi)[ch];
                        acc[ch].add_ln(ln, s, opts.error_threshold);
                        if let Some((b, _, _)) = &baseline {
                            base[ch].add_ln(b.model.ln_eval(r, None)[ch], s, opts.error_threshold);
                        }
                    }
                }
                Some((
                    acc.map(|a| a.log_e().unwrap_or(f64::NAN)),
                    base.map(|a| a.log_e().unwrap_or(f64::NAN)),
                ))
            });
            progress.inc(1);
            (out.map(|o| o.0), out.map(|o| o.1))
        })
        .collect();
    let errors: Vec<Option<[f64; 3]>> = both.iter().map(|b| b.0).collect();
    let base_log_e: Vec<[f64; 3]> = both.iter().filter_map(|b| b.1).collect();
    report.baseline = baseline.as_ref().map(|(_, p, n)| BaselineReport {
        terms: p.terms,
        params: p.params.clone(),
        r_range: p.r_range,
        samples: *n,
        log_e: LogEStats::of(&base_log_e),
    });
    stage("error", &mut t, &mut report);

    // Per-vertex outcome.
    let shape_terms = fits
        .iter()
        .filter_map(|(_, f)| f.as_ref().ok().map(|g| g.terms))
        .max()
        .unwrap_or(0);
    if shape_terms == 0 {
        let mut reasons: BTreeMap<FailReason, usize> = BTreeMap::new();
        for (_, f) in &fits {
            if let Err(e) = f {
                *reasons.entry(*e).or_default() += 1;
            }
        }
        return Err(PipelineError::NothingFitted(format!(
            "{} registered frames of {} selected; failed fits by reason: {:?}",
            report.frames.registered, report.frames.selected, reasons
        )));
    }
    let shape = ModelShape {
        terms: shape_terms,
        segments: opts.model.segments,
        colour: opts.model.colour,
    };
    // Outliers: a fit far worse than the typical one (e.g. x_i misregistered near a
    // silhouette, so every distance is wrong) is a failure and interpolated from neighbours.
    let max_log_e = {
        let mut means: Vec<f64> = errors
            .iter()
            .flatten()
            .map(|le| {
                let f: Vec<f64> = le.iter().copied().filter(|x| x.is_finite()).collect();
                f.iter().sum::<f64>() / f.len().max(1) as f64
            })
            .filter(|m| m.is_finite())
            .collect();
        means.sort_by(f64::total_cmp);
        match means.get(means.len() / 2) {
            Some(&median) if median > 0.0 => opts
                .max_log_e
                .min((opts.outlier_factor * median).max(OUTLIER_MIN_LOG_E)),
            _ => opts.max_log_e,
        }
    };
    report.max_log_e = max_log_e;
    let mut own: Vec<Option<OwnFit>> = vec![None; nv];
    let mut light_log_e = Vec::new();
    for (((_, f), err), key) in fits.iter().zip(&errors).zip(&keys) {
        let verts = &groups[key];
        let outcome = match (f, err) {
            (Err(e), _) => Err(*e),
            (Ok(_), None) => Err(FailReason::FrameUnreadable),
            (Ok(g), Some(le)) => {
                let finite: Vec<f64> = le.iter().copied().filter(|x| x.is_finite()).collect();
                let mean = finite.iter().sum::<f64>() / finite.len().max(1) as f64;
                if finite.is_empty() {
                    Err(FailReason::TooFewSamples)
                } else if mean > max_log_e {
                    Err(FailReason::HighError)
                } else {
                    match params_of(&g.model) {
                        Ok((p, n, _)) if p.iter().all(|x| x.is_finite()) => {
                            light_log_e.push(*le);
                            *report.orders.entry(n).or_default() += 1;
                            Ok(OwnFit {
                                params: p,
                                terms: n,
                                log_e: mean as f32,
                                model: g.model.clone(),
                                r_range: g.r_range,
                            })
                        }
                        _ => Err(FailReason::NonPhysical),
                    }
                }
            }
        };
        for &v in verts {
            match &outcome {
                Ok(o) => own[v as usize] = Some(o.clone()),
                Err(e) => vertex_fail[v as usize] = Some(*e),
            }
        }
    }
    report.log_e = LogEStats::of(&light_log_e);
    for r in vertex_fail.iter().flatten() {
        *report.failures.entry(*r).or_default() += 1;
    }

    // Interpolation of every vertex without its own model (section 5). Neighbouring fits are
    // not term-aligned, so what is interpolated is each fitted vertex's curve ln R_d(r) (per
    // segment and, for per-channel models, per channel) on a common distance grid, with ln s_g,
    // ln s_b and the sampled range; the interpolated curve is then refitted (term-aligned by
    // construction) with the most common order.
    let common_n = report
        .orders
        .iter()
        .max_by_key(|(_, c)| **c)
        .map(|(n, _)| *n)
        .unwrap_or(shape_terms);
    let grid = CurveGrid::of(own.iter().flatten().map(|o| o.r_range));
    let known: Vec<Option<Vec<f64>>> = own
        .iter()
        .map(|o| o.as_ref().map(|o| grid.encode(&o.model, o.r_range)))
        .collect();
    let filled = crate::interpolate::harmonic(&known, |v| ctx.scene.neighbours(v), 2000);
    let refits: Vec<Option<Refit>> = (0..nv)
        .into_par_iter()
        .map(|v| {
            if own[v].is_some() {
                return None;
            }
            let enc = filled[v].as_ref()?;
            let mut dropped = Vec::new();
            let refit = grid
                .decode(enc, &shape, common_n, fitter, &mut dropped)
                .and_then(|(m, range)| match params_of(&m) {
                    Ok((p, n, _)) if p.iter().all(|x| x.is_finite()) => Some((p, n, range)),
                    _ => None,
                });
            // Where the interpolated curve cannot be refitted, the nearest fitted vertex's own
            // model (breadth-first over the mesh) stands in.
            refit.or_else(|| {
                nearest_fitted(v, &own, |w| ctx.scene.neighbours(w))
                    .map(|o| (o.params.clone(), o.terms, o.r_range))
            })
        })
        .collect();
    let mut vertices = Vec::with_capacity(nv);
    for v in 0..nv {
        let a = alpha[v].map(|x| x as f32);
        let vm = match &own[v] {
            Some(o) => {
                report.vertices_fitted += 1;
                VertexModel {
                    alpha: a,
                    status: VertexStatus::Fitted,
                    log_e: o.log_e,
                    terms: o.terms as u8,
                    params: o.params.clone(),
                    r_range: o.r_range.map(|x| x as f32),
                }
            }
            None => match &refits[v] {
                Some((p, n, range)) => {
                    report.vertices_interpolated += 1;
                    VertexModel {
                        alpha: a,
                        status: VertexStatus::Interpolated,
                        log_e: f32::NAN,
                        terms: *n as u8,
                        params: p.clone(),
                        r_range: range.map(|x| x as f32),
                    }
                }
                None => {
                    report.vertices_no_model += 1;
                    VertexModel {
                        alpha: a,
                        status: VertexStatus::NoModel,
                        log_e: f32::NAN,
                        terms: 0,
                        params: Vec::new(),
                        r_range: crate::modelfile::NO_RANGE,
                    }
                }
            },
        };
        vertices.push(vm);
    }
    stage("interpolate", &mut t, &mut report);
    report.peak_rss_mib = peak_rss_mib();
    let model = ModelFile {
        shape,
        positions: ds.mesh.positions.clone(),
        normals: ds.mesh.normals.clone(),
        triangles: ds.mesh.triangles.clone(),
        vertices,
        baseline: baseline.map(|(_, p, _)| p),
    };
    Ok(FitOutput { model, report })
}

/// The fitted vertex nearest to `v` in mesh hops (breadth-first), if any is connected.
fn nearest_fitted<'a, 'n>(
    v: usize,
    own: &'a [Option<OwnFit>],
    neighbours: impl Fn(usize) -> &'n [u32],
) -> Option<&'a OwnFit> {
    let mut seen = std::collections::HashSet::from([v]);
    let mut frontier = vec![v];
    while !frontier.is_empty() {
        let mut next = Vec::new();
        for &u in &frontier {
            for &w in neighbours(u) {
                let w = w as usize;
                if w < own.len() && seen.insert(w) {
                    if let Some(o) = &own[w] {
                        return Some(o);
                    }
                    next.push(w);
                }
            }
        }
        frontier = next;
    }
    None
}

/// An interpolated vertex's refit: parameters, order, sampled range.
type Refit = (Vec<f64>, usize, [f64; 2]);

/// A vertex's own fit.
#[derive(Clone)]
struct OwnFit {
    params: Vec<f64>,
    terms: usize,
    log_e: f32,
    model: ColourModel,
    r_range: [f64; 2],
}

/// Eq. 6 per vertex from the accumulated samples; vertices no fitted frame saw (Eq. 6's X is
/// empty: not visible from any camera at any selected turntable angle) take the harmonic
/// interpolation of ln alpha from their mesh neighbours, and 1 where no neighbour has data.
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

fn alpha_texture(
    acc: &[[AlphaAccumulator; 3]],
    nv: usize,
    scene: &Scene,
) -> (Vec<[f64; 3]>, AlphaReport) {
    let own: Vec<Option<Vec<f64>>> = (0..nv)
        .map(|v| {
            let a = acc.get(v)?;
            let vals: Vec<Option<f64>> = a
                .iter()
                .map(|c| c.alpha().filter(|x| x.is_finite() && *x > 0.0))
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
    let mut rep = AlphaReport::default();
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

/// The distance grid on which fitted curves ln R_d(r) are interpolated between vertices.
struct CurveGrid {
    r: Vec<f64>,
}

/// Points of [`CurveGrid`] and of each refit.
const GRID_POINTS: usize = 32;
/// Points of the refit of an interpolated curve, spread over its sampled range.
const REFIT_POINTS: usize = 24;

impl CurveGrid {
    /// Spans every fitted vertex's sampled range.
    fn of(ranges: impl Iterator<Item = [f64; 2]>) -> CurveGrid {
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for [a, b] in ranges {
            lo = lo.min(a);
            hi = hi.max(b);
        }
        if !(lo.is_finite() && hi > lo) {
            (lo, hi) = (0.5, 10.0);
        }
        let r = (0..GRID_POINTS)
            .map(|k| lo + (hi - lo) * k as f64 / (GRID_POINTS - 1) as f64)
            .collect();
        CurveGrid { r }
    }

    /// ln R_d of `f` at `r`, claimed only from `lo` on (linear continuation below, as in
    /// [`crate::evaluate::ln_eval_supported`]).
    fn ln_supported(f: &ExpSum, lo: f64, r: f64) -> f64 {
        if r >= lo {
            f.ln_eval(r)
        } else {
            f.ln_eval(lo) + f.ln_slope(lo).min(0.0) * (r - lo)
        }
    }

    /// The fall-off curves of a model: per channel (per-channel models) and segment.
    fn curves(m: &ColourModel) -> Vec<&ExpSum> {
        match m {
            ColourModel::Shared { falloff, .. } => falloff.segments.iter().collect(),
            ColourModel::PerChannel { channels } => {
                channels.iter().flat_map(|c| c.segments.iter()).collect()
            }
        }
    }

    /// `[ln r_min, ln r_max, (ln s_g, ln s_b), ln R_d on the grid for every curve]`.
    fn encode(&self, m: &ColourModel, range: [f64; 2]) -> Vec<f64> {
        let mut out = vec![range[0].max(1e-6).ln(), range[1].max(1e-6).ln()];
        if let ColourModel::Shared { s_g, s_b, .. } = m {
            out.push(s_g.ln());
            out.push(s_b.ln());
        }
        for f in Self::curves(m) {
            out.extend(self.r.iter().map(|&r| Self::ln_supported(f, range[0], r)));
        }
        out
    }

    /// ln R_d of curve `k` of an encoding at `r` (piecewise linear between grid points; the end
    /// segments continue linearly).
    fn ln_at(&self, enc: &[f64], head: usize, k: usize, r: f64) -> f64 {
        let g = &enc[head + k * self.r.len()..head + (k + 1) * self.r.len()];
        let n = self.r.len();
        let step = (self.r[n - 1] - self.r[0]) / (n - 1) as f64;
        let x = ((r - self.r[0]) / step).clamp(0.0, (n - 1) as f64);
        let i = (x.floor() as usize).min(n - 2);
        let t = (r - self.r[i]) / step;
        g[i] + (g[i + 1] - g[i]) * t
    }

    /// Refits an interpolated encoding: the model (term-aligned by construction, order at most
    /// `n`) and its range. `None` if a refit fails.
    fn decode(
        &self,
        enc: &[f64],
        shape: &ModelShape,
        n: usize,
        fitter: &dyn Fitter,
        dropped: &mut Vec<TermDropped>,
    ) -> Option<(ColourModel, [f64; 2])> {
        let range = [enc[0].exp(), enc[1].exp()];
        if range[1].partial_cmp(&range[0]) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let head = if shape.colour == ColourMode::Shared {
            4
        } else {
            2
        };
        let curves = match shape.colour {
            ColourMode::Shared => shape.segments,
            ColourMode::PerChannel => 3 * shape.segments,
        };
        if enc.len() != head + curves * self.r.len() {
            return None;
        }
        let rs: Vec<f64> = (0..REFIT_POINTS)
            .map(|k| range[0] + (range[1] - range[0]) * k as f64 / (REFIT_POINTS - 1) as f64)
            .collect();
        let sets: Vec<(Vec<f64>, Vec<f64>)> = (0..curves)
            .map(|k| {
                let s = rs
                    .iter()
                    .map(|&r| self.ln_at(enc, head, k, r).exp())
                    .collect();
                (rs.clone(), s)
            })
            .collect();
        // Lower the order when a refit fails (not converged on a smooth curve, e.g.).
        let fits = (1..=n.max(1))
            .rev()
            .find_map(|n| fit_common_order(fitter, &sets, Some(n), dropped).ok())?;
        let m = shape.segments;
        let model = match shape.colour {
            ColourMode::Shared => ColourModel::Shared {
                falloff: Anisotropic { segments: fits },
                s_g: enc[2].exp(),
                s_b: enc[3].exp(),
            },
            ColourMode::PerChannel => {
                let mut it = fits.into_iter();
                let mut ch = || Anisotropic {
                    segments: it.by_ref().take(m).collect(),
                };
                ColourModel::PerChannel {
                    channels: [ch(), ch(), ch()],
                }
            }
        };
        model.validate().ok()?;
        Some((model, range))
    }
}

#[derive(Default)]
struct FitState {
    fits: Vec<(usize, Result<GroupFit, FailReason>)>,
    /// Training objective of this round's fits (see `fit_round`).
    objective: f64,
    /// The same of the previous round's fits.
    objective_prev: f64,
    /// Light positions that kept their previous fit.
    kept_previous: usize,
    alpha: Vec<[AlphaAccumulator; 3]>,
    counts: SampleCounts,
    dropped: BTreeMap<TermDropped, usize>,
}

impl FitState {
    fn merge(mut self, mut other: FitState) -> FitState {
        self.fits.append(&mut other.fits);
        if self.alpha.is_empty() {
            self.alpha = other.alpha;
        } else if !other.alpha.is_empty() {
            for (a, b) in self.alpha.iter_mut().zip(&other.alpha) {
                for c in 0..3 {
                    a[c].merge(&b[c]);
                }
            }
        }
        self.counts.add(&other.counts);
        self.objective += other.objective;
        self.objective_prev += other.objective_prev;
        self.kept_previous += other.kept_previous;
        for (k, v) in other.dropped {
            *self.dropped.entry(k).or_default() += v;
        }
        self
    }
}

/// The fitting engine's Levenberg–Marquardt (`crate::fit`) as the pipeline's solver.
impl Fitter for crate::fit::FitOptions {
    fn fit(&self, r: &[f64], s: &[f64], terms: Option<usize>) -> Result<ExpSum, FailReason> {
        use crate::fit::{FitFailure, Terms, fit_expsum};
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
        match fit_expsum(r, s, opts) {
            Ok(f) => Ok(f.model),
            Err(FitFailure::TooFewSamples { .. } | FitFailure::TooFewDistances { .. }) => {
                Err(FailReason::TooFewSamples)
            }
            Err(FitFailure::NotConverged { .. }) => Err(FailReason::NotConverged),
            Err(_) => Err(FailReason::NonPhysical),
        }
    }
}
