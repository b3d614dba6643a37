//! Judging a model against frames (Table 1 statistics for any frames, held-out ones included) and
//! predicting what a frame's camera sees (Eq. 9 with alpha; at x_i between vertices the corners'
//! predictions of ln R_d are blended, see [`ModelAt`]).
use crate::dataset::{Dataset, Image};
use crate::geometry::V3;
use crate::model::{ColourModel, LogEAccumulator, Support, TangentFrame};
use crate::modelfile::{ModelFile, VertexStatus, model_of};
use crate::pipeline::extract::StoreOptions;
use crate::pipeline::{Context, LogEStats, PipelineError, PipelineOptions, register_one};
use crate::progress::Progress;
use crate::store::StorePoints;

pub mod images;
pub mod rings;
pub mod run;
pub mod summary;
pub use images::{FrameImages, ImageProblem, Reference, evaluate_images_in};
pub use summary::{Clustering, Figures, Paired};

/// Why a model cannot be evaluated on a dataset.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EvaluateError {
    /// The model was fitted to a different mesh.
    #[error("the model has {model} vertices, the dataset's mesh {mesh}: not the same object")]
    MeshMismatch {
        /// Vertices in the model.
        model: usize,
        /// Vertices in the dataset's mesh.
        mesh: usize,
    },
    /// Evaluation at surface points needs the model's faces to be the dataset mesh's.
    #[error("the model's faces ({model}) are not the dataset mesh's ({mesh}): not the same mesh")]
    FaceMismatch {
        /// Faces in the model.
        model: usize,
        /// Faces in the dataset's mesh.
        mesh: usize,
    },
    /// The surface-point level is outside 1..=8.
    #[error("surface points: {0}")]
    Level(crate::lattice::LatticeError),
    /// Preparing the dataset failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// A frame's prediction image (`subsurf evaluate --images`) cannot be judged.
    #[error("frame {frame}: prediction image {}: {problem}", path.display())]
    Image {
        /// The frame.
        frame: usize,
        /// The image's file.
        path: std::path::PathBuf,
        /// What is wrong with it.
        problem: ImageProblem,
    },
    /// Options that do not go together.
    #[error("{0}")]
    Usage(&'static str),
    /// The volume model cannot predict frames.
    #[error("the volume model: {0}")]
    Volume(#[from] crate::volume::VolumeError),
    /// A frame could not be used.
    #[error("frame {frame}: {reason}")]
    Frame {
        /// The frame.
        frame: usize,
        /// Why.
        reason: String,
    },
}

/// One corner of the triangle holding x_i: its own model, claimed over its sampled range.
#[derive(Debug, Clone, PartialEq)]
pub struct Corner {
    /// Normalised barycentric weight of the corner at x_i.
    pub weight: f64,
    /// The corner vertex's colour model (Eq. 9, or Eq. 3 per channel).
    pub model: ColourModel,
    /// Where the corner's model is claimed: its sampled distance range (see
    /// [`crate::model::support`]).
    pub support: Support,
}

/// The model at a light position x_i between vertices: the corners of the triangle holding x_i.
///
/// Neighbouring fits are not term-aligned (a sum of exponentials has no canonical
/// parametrisation: two 3-term fits of nearly the same curve can have unrelated terms), so
/// blending parameters is meaningless. What is blended is each corner's *prediction*:
/// ln R_d(x_i → x_o) = Σ_k w_k · ln R_d^(k)(|x_o − x_i|), each corner evaluated only where its
/// samples were (the model's support rule, [`crate::model::support`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelAt {
    /// Corners with a model, weights summing to 1.
    pub corners: Vec<Corner>,
    /// Tangent frame at x_i (for anisotropic models).
    pub frame: TangentFrame,
    /// The model's homogeneous baseline, which prediction falls back towards beyond a corner's
    /// sampled distances ([`crate::baseline::with_fallback`]).
    pub baseline: Option<crate::baseline::Baseline>,
}

impl ModelAt {
    /// ln R_d per channel at distance r and direction φ from x_i (Eq. 9, blended over corners).
    ///
    /// A corner whose samples did not reach down to r (r below its r_min) only extrapolates
    /// there, so its barycentric weight is damped by [`Support::weight`]: where another corner
    /// was sampled, that corner decides; where none was, all extrapolate together. Beyond a
    /// corner's r_max its prediction moves towards the homogeneous baseline, if the model has one.
    pub fn ln_eval(&self, r: f64, phi: Option<f64>) -> [f64; 3] {
        let mut out = [0.0; 3];
        let mut total = 0.0;
        for c in &self.corners {
            let w = c.weight * c.support.weight(r);
            if w <= 0.0 {
                continue;
            }
            total += w;
            let l = self.corner_ln(c, r, phi);
            for k in 0..3 {
                out[k] += w * l[k];
            }
        }
        if total > 0.0 {
            out.map(|x| x / total)
        } else {
            // Every weight underflowed (far below every r_min): plain barycentric blend.
            let mut out = [0.0; 3];
            for c in &self.corners {
                let l = self.corner_ln(c, r, phi);
                for k in 0..3 {
                    out[k] += c.weight * l[k];
                }
            }
            out
        }
    }
}

impl ModelAt {
    /// How much of the prediction at distance r is the corners' own models rather than the
    /// baseline they fall back to beyond their sampled range ([`crate::baseline::local_weight`]),
    /// weighted as [`ModelAt::ln_eval`] weights the corners: 1 where every corner was sampled
    /// out to r, towards 0 far beyond; 1 for a model without a baseline.
    pub fn local_share(&self, r: f64) -> f64 {
        if self.baseline.is_none() {
            return 1.0;
        }
        let (mut local, mut total) = (0.0, 0.0);
        for c in &self.corners {
            let w = c.weight * c.support.weight(r);
            total += w;
            local += w * crate::baseline::local_weight(c.support, r);
        }
        if total > 0.0 {
            local / total
        } else {
            self.corners
                .iter()
                .map(|c| c.weight * crate::baseline::local_weight(c.support, r))
                .sum()
        }
    }

    fn corner_ln(&self, c: &Corner, r: f64, phi: Option<f64>) -> [f64; 3] {
        crate::baseline::ln_predict(&c.model, c.support, r, phi, self.baseline.as_ref())
    }
}

/// The corners of triangle `tri` that have a model, weighted barycentrically at `x_i` (weights
/// renormalised over those corners).
pub fn model_at(ctx: &Context, model: &ModelFile, tri: u32, x_i: V3) -> Option<ModelAt> {
    let t = *ctx.scene.mesh.triangles.get(tri as usize)?;
    let w = ctx.scene.barycentric(tri, x_i);
    let mut corners: Vec<Corner> = Vec::with_capacity(3);
    for k in 0..3 {
        let v = &model.vertices[t[k] as usize];
        if v.status == VertexStatus::NoModel {
            continue;
        }
        let Ok(m) = model_of(&model.shape, v.terms as usize, &v.params) else {
            continue;
        };
        corners.push(Corner {
            weight: w[k].max(0.0),
            model: m,
            support: v.support(),
        });
    }
    if corners.is_empty() {
        return None;
    }
    let total: f64 = corners.iter().map(|c| c.weight).sum();
    let n = corners.len() as f64;
    for c in &mut corners {
        c.weight = if total > 0.0 {
            c.weight / total
        } else {
            1.0 / n
        };
    }
    // The frame the corners' segments were fitted in (the file's rule) at x_i's own normal.
    let frame = model.frame_at(ctx.normal_at(tri, x_i))?;
    let baseline = model
        .baseline
        .as_ref()
        .and_then(|b| b.baseline(model.shape.colour));
    Some(ModelAt {
        corners,
        frame,
        baseline,
    })
}

/// alpha(x_o) (Eq. 2) at a vertex.
fn alpha_of(model: &ModelFile, v: usize) -> [f64; 3] {
    model.vertices[v].alpha.map(|a| a as f64)
}

/// Where a model is compared with a frame's pixels.
///
/// Why more than the vertices: alpha finer than the mesh (a face lattice, section 5) has detail
/// 0 at the vertices by construction, so an evaluation at vertex projections cannot see it, and
/// a model with a lattice and one without score the same there. At surface points the lattice
/// is what is judged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(tag = "at", rename_all = "kebab-case")]
pub enum EvalPoints {
    /// The mesh's vertices (one sample per vertex a frame sees).
    Vertices,
    /// The lattice points of level `level` on every face ([`crate::geometry::SurfacePoints`]):
    /// the (k+1)(k+2)/2 points of barycentric coordinates (i/k, j/k, 1 − (i+j)/k) per face,
    /// corners and edge points repeated for each face holding them. The level is fixed by the
    /// caller, not by any model's lattice, so every model compared is judged at the same points.
    Surface {
        /// Lattice level k, 1..=[`crate::lattice::MAX_LEVEL`].
        level: u8,
    },
}

impl EvalPoints {
    /// The sample store's point set these points are read from.
    pub fn point_set(self) -> crate::store::PointSet {
        match self {
            EvalPoints::Vertices => crate::store::PointSet::Vertices,
            EvalPoints::Surface { .. } => crate::store::PointSet::Lattice,
        }
    }
}

/// Table-1 statistics of one frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FrameEval {
    /// Frame index.
    pub frame: usize,
    /// log E(x_i) (Eq. 8) per channel; `None` where no sample passed the threshold.
    pub log_e: [Option<f64>; 3],
    /// Channel samples used.
    pub samples: u64,
    /// Samples used per channel r, g, b (the weights of the sample-weighted mean,
    /// [`summary::Figures`]).
    pub channel_samples: [u64; 3],
    /// The frame's light position x_i (mm, turntable frame), where it was registered: what
    /// clusters the frames of a scan with one turntable angle ([`summary::Clustering`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x_i: Option<[f64; 3]>,
    /// Share of the frame's samples the vertices' own models predicted, against the baseline
    /// they fall back to beyond their sampled range ([`ModelAt::local_share`], mean over the
    /// samples); `None` when none was compared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub local_share: Option<f64>,
    /// Of an image judged as the prediction ([`images`]): channel samples where the image is
    /// black (at or below 0) and the frame has light above the noise floor, judged as the
    /// floor; `None` for a model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unlit: Option<u64>,
    /// Why the frame was not evaluated, if it was not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
}

/// Evaluates `model` on the frames `frames` of `ds` at the vertices (each frame read once, in
/// parallel): [`evaluate_frames_at`] with [`EvalPoints::Vertices`].
pub fn evaluate_frames(
    ds: &Dataset,
    model: &ModelFile,
    frames: &[usize],
    opts: &PipelineOptions,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    evaluate_frames_at(ds, model, frames, opts, EvalPoints::Vertices, progress)
}

/// Evaluates `model` on the frames `frames` of `ds` at the points `at`, each frame decoded once
/// (the one pass of [`crate::pipeline::extract`], through the dataset's sample cache): per
/// frame, log E (Eq. 8) over the samples at those points, read by the rules of the fit's samples
/// (`samples::frame_samples`), against alpha(x_o) · R_d(x_i → x_o) with alpha from
/// [`ModelFile::alpha_at`].
pub fn evaluate_frames_at(
    ds: &Dataset,
    model: &ModelFile,
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    evaluate_frames_stored(
        ds,
        model,
        frames,
        opts,
        at,
        &StoreOptions::default(),
        progress,
    )
}

/// [`evaluate_frames_at`] with the sample store's settings `store` (memory budget, cache).
pub fn evaluate_frames_stored(
    ds: &Dataset,
    model: &ModelFile,
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    let mut out = evaluate_models_stored(ds, &[model], frames, opts, at, store, progress)?;
    Ok(out.remove(0))
}

/// [`evaluate_frames_stored`] for several models on the same frames, from one pass over them:
/// every model judged on the same samples (`subsurf evaluate --against`).
pub fn evaluate_models_stored(
    ds: &Dataset,
    models: &[&ModelFile],
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<Vec<(Vec<FrameEval>, LogEStats)>, EvaluateError> {
    if models.is_empty() {
        return Ok(Vec::new());
    }
    let ctx = judged_store(ds, models, frames, opts, at, store, progress)?;
    models
        .iter()
        .map(|m| evaluate_in(&ctx, m, frames, at, progress))
        .collect()
}

/// The images of `images` judged as predictions of `frames` of `ds` (`subsurf evaluate
/// --images`), on the samples [`evaluate_models_stored`] judges `model` on: the same store, the
/// same rules, Eq. 8 ([`images::evaluate_images_in`]). `model`, if given, says which light
/// positions apply.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_images_stored(
    ds: &Dataset,
    model: Option<&ModelFile>,
    images: &FrameImages,
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    let ctx = judged_store(ds, model.as_slice(), frames, opts, at, store, progress)?;
    evaluate_images_in(&ctx, model, images, Reference::Frames, frames, at, progress)
}

/// `frames` of `ds` judged by their rings ([`rings`], `subsurf evaluate --rings`): `model`'s
/// prediction, or with `images` those images', on the samples the per-sample evaluation uses.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_rings_stored(
    ds: &Dataset,
    model: Option<&ModelFile>,
    images: Option<&FrameImages>,
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<(Vec<rings::FrameRings>, LogEStats), EvaluateError> {
    let ctx = judged_store(ds, model.as_slice(), frames, opts, at, store, progress)?;
    let prediction = match images {
        Some(i) => rings::Prediction::Images(i, Reference::Frames),
        None => rings::Prediction::Model,
    };
    rings::evaluate_rings_in(&ctx, model, prediction, frames, at, progress)
}

/// The run that judges `models` on `frames`: the dataset under `opts` with the store of those
/// frames (at the vertices, or also at the lattice points of `at`).
pub fn judged_store<'a>(
    ds: &'a Dataset,
    models: &[&ModelFile],
    frames: &[usize],
    opts: &PipelineOptions,
    at: EvalPoints,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<Context<'a>, EvaluateError> {
    for m in models {
        check_mesh(ds, m)?;
    }
    let ctx = Context::new(ds, *opts)?;
    let points = match at {
        EvalPoints::Vertices => None,
        EvalPoints::Surface { level } => {
            if let Some(m) = models.iter().find(|m| m.triangles != ds.mesh.triangles) {
                return Err(EvaluateError::FaceMismatch {
                    model: m.triangles.len(),
                    mesh: ds.mesh.triangles.len(),
                });
            }
            let levels = vec![level; ds.mesh.triangles.len()];
            Some(StorePoints::new(&ds.mesh, levels, None).map_err(EvaluateError::Level)?)
        }
    };
    let held = crate::pipeline::extract::extract(&ctx, frames, points, store, progress)?;
    Ok(ctx.with_store(held))
}

/// The judged frames `evals` of `model` split into those its fit never saw (first) and those
/// it was fitted to (second: in-sample, optimistic), by the frames its file records
/// ([`ModelFile::fitted_frames`]); a model without the record has every frame in the first.
pub fn split_fitted(model: &ModelFile, evals: &[FrameEval]) -> (Vec<FrameEval>, Vec<FrameEval>) {
    split_frames(model.fitted_frames.as_deref(), evals)
}

/// [`split_fitted`] by the fitted frames `fitted` (sorted), if known.
pub fn split_frames(
    fitted: Option<&[usize]>,
    evals: &[FrameEval],
) -> (Vec<FrameEval>, Vec<FrameEval>) {
    let fitted = fitted.unwrap_or(&[]);
    evals
        .iter()
        .cloned()
        .partition(|e| fitted.binary_search(&e.frame).is_err())
}

fn check_mesh(ds: &Dataset, model: &ModelFile) -> Result<(), EvaluateError> {
    if model.positions.len() != ds.mesh.positions.len() {
        return Err(EvaluateError::MeshMismatch {
            model: model.positions.len(),
            mesh: ds.mesh.positions.len(),
        });
    }
    Ok(())
}

/// Evaluates `model` on the frames `frames` of a run whose sample store holds them (at the
/// vertices, or at its lattice points for [`EvalPoints::Surface`]): no frame is read. The
/// held-out frames of `subsurf fit --validate` are judged so, from the fit's own store.
pub fn evaluate_in(
    ctx: &Context,
    model: &ModelFile,
    frames: &[usize],
    at: EvalPoints,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    use rayon::prelude::*;
    check_mesh(ctx.ds, model)?;
    let set = at.point_set();
    progress.start("evaluate", frames.len() as u64);
    let evals: Vec<FrameEval> = frames
        .par_iter()
        .map(|&k| {
            let r = evaluate_one(ctx, model, k, set);
            progress.inc(1);
            r.unwrap_or_else(|reason| FrameEval {
                frame: k,
                log_e: [None; 3],
                samples: 0,
                channel_samples: [0; 3],
                x_i: None,
                local_share: None,
                unlit: None,
                skipped: Some(reason),
            })
        })
        .collect();
    let vals: Vec<[f64; 3]> = evals
        .iter()
        .filter(|e| e.skipped.is_none())
        .map(|e| e.log_e.map(|x| x.unwrap_or(f64::NAN)))
        .collect();
    Ok((evals, LogEStats::of(&vals)))
}

fn evaluate_one(
    ctx: &Context,
    model: &ModelFile,
    k: usize,
    set: crate::store::PointSet,
) -> Result<FrameEval, String> {
    let reg = register_one(ctx, k)?;
    let x_i = reg.x_i;
    let at = model_at(ctx, model, reg.triangle, x_i).ok_or("no model at x_i")?;
    let store = ctx.store().ok_or("no sample store")?;
    let fs = store
        .samples(k, set)
        .map_err(|e| e.to_string())?
        .ok_or("no samples at these points")?;
    let (positions, points) = match set {
        crate::store::PointSet::Vertices => (&ctx.ds.mesh.positions, None),
        crate::store::PointSet::Lattice => {
            let p = store.points().ok_or("no surface points in the store")?;
            (&p.points.positions, Some(&p.points))
        }
    };
    let mut acc = [LogEAccumulator::default(); 3];
    let (mut local, mut compared) = (0.0, 0u64);
    for s in fs.samples.iter() {
        let p = s.vertex as usize;
        let (x_o, a) = match points {
            None => (positions[p], alpha_of(model, p)),
            Some(pts) => (
                pts.positions[p],
                model.alpha_at(pts.face[p] as usize, pts.bary[p]),
            ),
        };
        let (r, phi) = at.frame.polar(x_i, x_o);
        let ln = at.ln_eval(r, phi);
        let mut used = false;
        for c in 0..3 {
            if s.valid & (1 << c) != 0 {
                used |= acc[c].add_ln(a[c].ln() + ln[c], s.value[c], ctx.opts.error_threshold);
            }
        }
        if used {
            local += at.local_share(r);
            compared += 1;
        }
    }
    Ok(FrameEval {
        frame: k,
        log_e: acc.map(|a| a.log_e()),
        samples: acc.iter().map(|a| a.count).sum(),
        channel_samples: acc.map(|a| a.count),
        x_i: Some(x_i),
        local_share: (compared > 0).then(|| local / compared as f64),
        unlit: None,
        skipped: None,
    })
}

/// The share of the evaluated samples of `evals` that the vertices' own models predicted
/// (each frame's [`FrameEval::local_share`] weighted by its samples); the rest is the baseline's
/// fallback beyond their sampled range. `None` when no frame has one.
pub fn local_share(evals: &[FrameEval]) -> Option<f64> {
    let (sum, n) = evals
        .iter()
        .filter_map(|e| {
            e.local_share
                .map(|s| (s * e.samples as f64, e.samples as f64))
        })
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
    (n > 0.0).then(|| sum / n)
}

/// Renders what the camera of frame `k` sees when the laser hits that frame's x_i, as the model
/// predicts it (Eq. 9 with alpha; pixel = radiance · exposure, so it compares to the capture).
pub fn predict_frame(
    ds: &Dataset,
    model: &ModelFile,
    k: usize,
    opts: &PipelineOptions,
) -> Result<Image, EvaluateError> {
    use rayon::prelude::*;
    if model.positions.len() != ds.mesh.positions.len() {
        return Err(EvaluateError::MeshMismatch {
            model: model.positions.len(),
            mesh: ds.mesh.positions.len(),
        });
    }
    if k >= ds.spec.frames.len() {
        return Err(EvaluateError::Frame {
            frame: k,
            reason: format!("dataset has {} frames", ds.spec.frames.len()),
        });
    }
    let ctx = Context::new(ds, *opts)?;
    let reg = register_one(&ctx, k).map_err(|reason| EvaluateError::Frame { frame: k, reason })?;
    let x_i = reg.x_i;
    let at = model_at(&ctx, model, reg.triangle, x_i).ok_or(EvaluateError::Frame {
        frame: k,
        reason: "no model at x_i".into(),
    })?;
    let f = &ds.spec.frames[k];
    let cam = ctx.camera(f.camera);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut img = Image::new(w, h, 3);
    img.data.par_chunks_mut(3).enumerate().for_each(|(p, px)| {
        let (u, v) = ((p % w) as f64, (p / w) as f64);
        let Some((o, d)) = cam.ray(u, v) else { return };
        let Some(hit) = ctx.scene.cast_world(o, d, f.turntable_deg) else {
            return;
        };
        // alpha(x_o) at the pixel's surface point: vertex alphas and the face lattice's detail.
        let a = model.alpha_at(
            hit.triangle as usize,
            ctx.scene.barycentric(hit.triangle, hit.point),
        );
        let (r, phi) = at.frame.polar(x_i, hit.point);
        let ln = at.ln_eval(r, phi);
        for c in 0..3 {
            px[c] = (a[c] * ln[c].exp() * f.exposure_s) as f32;
        }
    });
    Ok(img)
}

/// Figure 3's comparison on the samples `(r, s)` of one lit point: the sum of exponentials
/// (Eq. 1, n = 3, log objective) and the dipole (relative index `eta`, free scale), each `None`
/// where its fit failed.
#[derive(Debug, Clone, PartialEq)]
pub struct FalloffComparison {
    /// The sum of exponentials.
    pub expsum: Option<crate::fit::ExpFit>,
    /// The dipole.
    pub dipole: Option<crate::fit::dipole::DipoleFit>,
}

/// Fits both models of Figure 3 to the samples `(r, s)` (see [`FalloffComparison`]).
pub fn compare_falloff(r: &[f64], s: &[f64], eta: f64) -> FalloffComparison {
    use crate::fit::dipole::{DipoleOptions, fit_dipole};
    FalloffComparison {
        expsum: crate::fit::fit_expsum(r, s, &crate::fit::FitOptions::default()).ok(),
        dipole: fit_dipole(
            r,
            s,
            &DipoleOptions {
                eta,
                ..Default::default()
            },
        )
        .ok(),
    }
}
