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

use crate::dataset::{Dataset, DatasetError};
use crate::geometry::{Camera, GeometryError, Scene, V3, Visible, add_scaled, normalize};
use crate::model::{
    AlphaAccumulator, Anisotropic, ColourModel, ExpSum, IntensityWindow, LogEAccumulator,
    TangentFrame,
};
use crate::modelfile::{
    ColourMode, ModelFile, ModelShape, VertexModel, VertexStatus, model_of, params_of,
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
    /// Eq. 6 window [t2, t1] for alpha(x_o).
    pub alpha_window: IntensityWindow,
    /// Eq. 8 threshold t.
    pub error_threshold: f64,
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
            alpha_window: IntensityWindow {
                t2: 10.0 * floor,
                t1: f64::INFINITY,
            },
            error_threshold: floor,
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
    /// Wall time per stage, seconds.
    pub stage_seconds: BTreeMap<String, f64>,
    /// Peak resident memory of the process, MiB (Linux; `None` elsewhere).
    pub peak_rss_mib: Option<f64>,
    /// The options used.
    pub options: Option<PipelineOptions>,
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

struct GroupFit {
    model: ColourModel,
    terms: usize,
}

fn fit_failure_from_model(e: crate::model::ModelError) -> FailReason {
    let _ = e;
    FailReason::NonPhysical
}

/// The model variant fitted to one group's samples.
fn fit_samples(
    data: &ChannelSamples,
    choice: &ModelChoice,
    fitter: &dyn Fitter,
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
            let (r, s) = rs(0, &all);
            let red = fitter.fit(&r, &s, None)?;
            let n = red.n();
            let mut chans = Vec::with_capacity(3);
            for c in 0..3 {
                let iso = if c == 0 {
                    red.clone()
                } else {
                    let (r, s) = rs(c, &all);
                    fitter.fit(&r, &s, Some(n))?
                };
                let mut segs = Vec::with_capacity(m);
                for l in 0..m {
                    if m == 1 {
                        segs.push(iso.clone());
                        continue;
                    }
                    let (r, s) = rs(c, &sector(l));
                    // A segment without enough samples keeps the isotropic fall-off.
                    segs.push(fitter.fit(&r, &s, Some(n)).unwrap_or_else(|_| iso.clone()));
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
            let red = fitter.fit(&r, &s, None)?;
            let n = red.n();
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
            let iso = fitter.fit(&r, &s, Some(n))?;
            let sc = scales(&iso)?;
            let mut segs = Vec::with_capacity(m);
            if m == 1 {
                segs.push(iso);
            } else {
                for l in 0..m {
                    let (r, s) = pooled(&sc, &sector(l));
                    segs.push(fitter.fit(&r, &s, Some(n)).unwrap_or_else(|_| iso.clone()));
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
    progress.set_message("fit");
    progress.set_length(keys.len() as u64);
    progress.set_position(0);
    let state = keys
        .par_iter()
        .enumerate()
        .fold(FitState::default, |mut st, (idx, key)| {
            let out = load(key).and_then(|(data, counts)| {
                let (model, terms) = fit_samples(&data, &opts.model, fitter)?;
                Ok((GroupFit { model, terms }, data, counts))
            });
            match out {
                Ok((g, data, counts)) => {
                    // Eq. 6 contributions are folded right away so the samples can be dropped.
                    if st.alpha.is_empty() {
                        st.alpha = vec![[AlphaAccumulator::default(); 3]; nv];
                    }
                    for (ch, d) in data.iter().enumerate() {
                        for &(r, s, v, phi) in d {
                            let rd = g.model.ln_eval(r, phi)[ch].exp();
                            st.alpha[v as usize][ch].add(s, rd, &opts.alpha_window);
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
        .reduce(FitState::default, FitState::merge);
    let FitState {
        mut fits,
        alpha,
        counts,
    } = state;
    report.samples = counts;
    fits.sort_by_key(|f| f.0);
    let alpha: Vec<[f64; 3]> = (0..nv)
        .map(|v| {
            [0, 1, 2].map(|c| {
                alpha
                    .get(v)
                    .and_then(|a| a[c].alpha())
                    .filter(|a| a.is_finite() && *a > 0.0)
                    .unwrap_or(1.0)
            })
        })
        .collect();
    stage("fit", &mut t, &mut report);

    // Eq. 8 with alpha: read the fitted frames again (cheaper in memory than keeping samples).
    progress.set_message("error");
    progress.set_length(keys.len() as u64);
    progress.set_position(0);
    let errors: Vec<Option<[f64; 3]>> = fits
        .par_iter()
        .map(|(idx, f)| {
            let out = f.as_ref().ok().and_then(|g| {
                let (data, _) = load(&keys[*idx]).ok()?;
                let mut acc = [LogEAccumulator::default(); 3];
                for (ch, d) in data.iter().enumerate() {
                    for &(r, s, v, phi) in d {
                        let ln = alpha[v as usize][ch].ln() + g.model.ln_eval(r, phi)[ch];
                        acc[ch].add_ln(ln, s, opts.error_threshold);
                    }
                }
                Some(acc.map(|a| a.log_e().unwrap_or(f64::NAN)))
            });
            progress.inc(1);
            out
        })
        .collect();
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
    let mut own: Vec<Option<(Vec<f64>, usize, f32)>> = vec![None; nv];
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
                } else if mean > opts.max_log_e {
                    Err(FailReason::HighError)
                } else {
                    match params_of(&g.model) {
                        Ok((p, n, _)) if p.iter().all(|x| x.is_finite()) => {
                            light_log_e.push(*le);
                            *report.orders.entry(n).or_default() += 1;
                            Ok((p, n, mean as f32))
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

    // Interpolation of every vertex without its own model (section 5), among the vertices that
    // use the most common order.
    let common_n = report
        .orders
        .iter()
        .max_by_key(|(_, c)| **c)
        .map(|(n, _)| *n)
        .unwrap_or(shape_terms);
    let known: Vec<Option<Vec<f64>>> = own
        .iter()
        .map(|o| {
            o.as_ref()
                .filter(|(_, n, _)| *n == common_n)
                .map(|(p, _, _)| crate::interpolate::to_log(&shape, p))
        })
        .collect();
    let filled = crate::interpolate::harmonic(&known, |v| ctx.scene.neighbours(v), 2000);
    let mut vertices = Vec::with_capacity(nv);
    for v in 0..nv {
        let a = alpha[v].map(|x| x as f32);
        let vm = match &own[v] {
            Some((p, n, le)) => {
                report.vertices_fitted += 1;
                VertexModel {
                    alpha: a,
                    status: VertexStatus::Fitted,
                    log_e: *le,
                    terms: *n as u8,
                    params: p.clone(),
                }
            }
            None => {
                let interp = filled[v]
                    .as_ref()
                    .map(|l| crate::interpolate::from_log(&shape, l))
                    .and_then(|p| model_of(&shape, common_n, &p).ok())
                    .and_then(|m| params_of(&m).ok());
                match interp {
                    Some((p, n, _)) if p.iter().all(|x| x.is_finite()) => {
                        report.vertices_interpolated += 1;
                        VertexModel {
                            alpha: a,
                            status: VertexStatus::Interpolated,
                            log_e: f32::NAN,
                            terms: n as u8,
                            params: p,
                        }
                    }
                    _ => {
                        report.vertices_no_model += 1;
                        VertexModel {
                            alpha: a,
                            status: VertexStatus::NoModel,
                            log_e: f32::NAN,
                            terms: 0,
                            params: Vec::new(),
                        }
                    }
                }
            }
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
    };
    Ok(FitOutput { model, report })
}

#[derive(Default)]
struct FitState {
    fits: Vec<(usize, Result<GroupFit, FailReason>)>,
    alpha: Vec<[AlphaAccumulator; 3]>,
    counts: SampleCounts,
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
