//! `subsurf evaluate` as one call: the dataset's protocol with the flags' changes, the store of
//! the frames judged, the figures of the model (the empirical model's own prediction, a folder
//! of images, or a volume model traced per frame) and the report, with its rings if asked.
//!
//! A volume model is judged as a renderer's images are (`--images`, [`super::images`]): its
//! prediction of a frame is an image, made when the frame is judged and read at the samples'
//! projections by the same rules; no file is written in between.
use std::path::PathBuf;

use super::images::FrameImages;
use super::rings::{FrameRings, Prediction};
use super::{EvalPoints, EvaluateError, FrameEval, Reference};
use crate::dataset::{Dataset, Image};
use crate::modelfile::ModelFile;
use crate::pipeline::{LogEStats, ProtocolChanges, StoreOptions, evaluation_protocol_with};
use crate::progress::Progress;
use crate::report::evaluate::{EvaluateReport, Protocol};
use crate::volume::{TracedFrames, VolumeModel};

/// Photons per frame of a volume model's predictions unless told otherwise: enough that the
/// trace's own noise is well below the figures'. Measured on training frames (sample-torus's
/// homogeneous medium judged on eight frames it was fitted to): green log E 0.824, 0.762 and
/// 0.756 at 0.1, 1 and 4 million photons (docs/volume.md).
pub const VOLUME_PHOTONS: usize = 1_000_000;
/// The same behind a dielectric boundary: there the camera sees a photon only where it meets
/// the surface from inside, one pixel per event, not from every collision in the medium, so a
/// pixel's noise falls as slowly as its events accumulate. Measured on training frames
/// (sample-pebble's medium behind its dielectric judged on eight frames it was fitted to):
/// green log E 0.973, 0.469 and 0.397 at 0.1, 1 and 4 million photons, still falling at the
/// cost of about 20 s a frame on 2 cores (docs/volume.md).
pub const DIELECTRIC_PHOTONS: usize = 4_000_000;

/// Photons per frame of `model`'s predictions: `photons` if given, else its boundary's default.
pub fn volume_photons(model: &VolumeModel, photons: Option<usize>) -> usize {
    use crate::volume::model::BoundaryModel;
    photons.unwrap_or(match model.boundary {
        BoundaryModel::IndexMatched => VOLUME_PHOTONS,
        BoundaryModel::Dielectric { .. } => DIELECTRIC_PHOTONS,
    })
}

/// Seed of a volume model's predictions.
pub const VOLUME_SEED: u64 = 7;

/// The model `subsurf evaluate` judges.
#[derive(Debug, Clone, Copy)]
pub enum Judged<'a> {
    /// An empirical model (PLY): its own prediction, or with `images` the images in that folder;
    /// `against` a second model judged on the same samples.
    Empirical {
        /// The model.
        model: &'a ModelFile,
        /// The second model.
        against: Option<&'a ModelFile>,
        /// The folder of images judged instead of the model's prediction.
        images: Option<&'a std::path::Path>,
    },
    /// A volume model, each frame traced with `photons`.
    Volume {
        /// The model.
        model: &'a VolumeModel,
        /// Photons per frame.
        photons: usize,
    },
}

/// A model file of either kind, told apart by its content ([`crate::volume::model::is_volume_file`]).
#[derive(Debug, Clone)]
pub enum AnyModel {
    /// The empirical model (PLY).
    Empirical(Box<ModelFile>),
    /// A volume model (JSON).
    Volume(Box<VolumeModel>),
}

/// Why a model file could not be read.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AnyModelError {
    /// The empirical model's file.
    #[error("reading {}: {source}", path.display())]
    Empirical {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        source: crate::modelfile::ModelFileError,
    },
    /// The volume model's file.
    #[error("reading {}: {source}", path.display())]
    Volume {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        source: crate::volume::VolumeError,
    },
}

impl AnyModel {
    /// Reads the model at `path`, of whichever kind it is.
    pub fn read(path: &std::path::Path) -> Result<AnyModel, AnyModelError> {
        let path_buf = || path.to_path_buf();
        if crate::volume::model::is_volume_file(path) {
            VolumeModel::read(path)
                .map(|m| AnyModel::Volume(Box::new(m)))
                .map_err(|source| AnyModelError::Volume {
                    path: path_buf(),
                    source,
                })
        } else {
            ModelFile::read(path)
                .map(|m| AnyModel::Empirical(Box::new(m)))
                .map_err(|source| AnyModelError::Empirical {
                    path: path_buf(),
                    source,
                })
        }
    }

    /// What `subsurf evaluate` judges of this model: an empirical one with `against` and
    /// `images`, a volume traced with `photons` (which take neither; by default
    /// [`volume_photons`]).
    pub fn judged<'a>(
        &'a self,
        against: Option<&'a ModelFile>,
        images: Option<&'a std::path::Path>,
        photons: Option<usize>,
    ) -> Result<Judged<'a>, EvaluateError> {
        match self {
            AnyModel::Empirical(model) => Ok(Judged::Empirical {
                model,
                against,
                images,
            }),
            AnyModel::Volume(model) if against.is_none() && images.is_none() => {
                Ok(Judged::Volume {
                    model,
                    photons: volume_photons(model, photons),
                })
            }
            AnyModel::Volume(_) => Err(EvaluateError::Usage(
                "a volume model is judged by its own images: --against and --images take an \
                 empirical model",
            )),
        }
    }
}

/// `subsurf predict`: frame `k` of `ds` as `model` predicts it (a volume traced with
/// `photons`, by default [`volume_photons`]; the empirical model under the dataset's pipeline
/// options).
pub fn predict_any(
    ds: &Dataset,
    model: &AnyModel,
    k: usize,
    photons: Option<usize>,
) -> Result<Image, EvaluateError> {
    match model {
        AnyModel::Empirical(m) => {
            let opts = crate::pipeline::PipelineOptions::for_dataset(ds);
            super::predict_frame(ds, m, k, &opts)
        }
        AnyModel::Volume(m) => {
            let n = volume_photons(m, photons);
            Ok(m.predictor()?.frame(ds, k, n, VOLUME_SEED)?)
        }
    }
}

/// How `subsurf evaluate` judges.
#[derive(Debug, Clone)]
pub struct EvaluateSettings {
    /// The flags' changes to the dataset's protocol.
    pub changes: ProtocolChanges,
    /// Where the predictions are compared.
    pub points: EvalPoints,
    /// The sample store.
    pub store: StoreOptions,
    /// Also judge by rings around x_i.
    pub rings: bool,
}

/// The rings of the frames judged ([`super::rings`]): per frame, and the mean over frames.
pub type Rings = (Vec<FrameRings>, LogEStats);

/// The report of `judged` on `frames` of `ds`, and with `settings.rings` its rings (per frame,
/// and the mean over frames).
pub fn evaluate_report(
    ds: &Dataset,
    frames: &[usize],
    judged: Judged,
    settings: &EvaluateSettings,
    progress: &dyn Progress,
) -> Result<(EvaluateReport, Option<Rings>), EvaluateError> {
    // Every model of a dataset is judged by the dataset's protocol, never by its fit's options
    // (docs/validation.md); flags change the protocol for every model alike.
    let (opts, source, overridden) = evaluation_protocol_with(ds, settings.changes)?;
    let (points, store) = (settings.points, &settings.store);
    match judged {
        Judged::Empirical {
            model,
            against,
            images,
        } => {
            let images = images.map(FrameImages::new);
            let evals = match &images {
                Some(images) => vec![super::evaluate_images_stored(
                    ds,
                    Some(model),
                    images,
                    frames,
                    &opts,
                    points,
                    store,
                    progress,
                )?],
                None => {
                    let models: Vec<&ModelFile> = std::iter::once(model).chain(against).collect();
                    super::evaluate_models_stored(
                        ds, &models, frames, &opts, points, store, progress,
                    )?
                }
            };
            let protocol = Protocol::of(&opts, overridden, source, Some(model));
            let b = against.zip(evals.get(1)).map(|(m, e)| (m, &e.0[..]));
            let mut report = EvaluateReport::new(ds, model, &evals[0].0, b, points, protocol);
            report.images = images.as_ref().map(|i| i.dir.clone());
            let rings = match settings.rings {
                true => Some(super::evaluate_rings_stored(
                    ds,
                    Some(model),
                    images.as_ref(),
                    frames,
                    &opts,
                    points,
                    store,
                    progress,
                )?),
                false => None,
            };
            Ok((report, rings))
        }
        Judged::Volume { model, photons } => {
            let predictor = model.predictor()?;
            // The rings read each frame's image again: kept while both judge.
            let traced = TracedFrames::new(&predictor, ds, photons, VOLUME_SEED, settings.rings);
            let images = FrameImages::made(TracedFrames::NAME, &traced);
            let ctx = super::judged_store(ds, &[], frames, &opts, points, store, progress)?;
            let (evals, _) = super::evaluate_images_in(
                &ctx,
                None,
                &images,
                Reference::Frames,
                frames,
                points,
                progress,
            )?;
            let protocol = Protocol::of(&opts, overridden, source, None);
            let mut report = volume_report(ds, model, &evals, points, protocol);
            report.volume_photons = Some(photons);
            let rings = match settings.rings {
                true => Some(super::rings::evaluate_rings_in(
                    &ctx,
                    None,
                    Prediction::Images(&images, Reference::Frames),
                    frames,
                    points,
                    progress,
                )?),
                false => None,
            };
            Ok((report, rings))
        }
    }
}

fn volume_report(
    ds: &Dataset,
    model: &VolumeModel,
    evals: &[FrameEval],
    points: EvalPoints,
    protocol: Protocol,
) -> EvaluateReport {
    let fitted = Some(&model.fit.frames[..]);
    EvaluateReport::of_frames(ds, fitted, evals, None, points, protocol)
}

/// The report as `subsurf evaluate` prints it: one JSON object (with the rings' keys), or text.
pub fn report_text(
    report: &EvaluateReport,
    rings: Option<&Rings>,
    json: bool,
) -> Result<String, serde_json::Error> {
    if json {
        let mut v = serde_json::to_value(report)?;
        if let (Some((per, st)), Some(obj)) = (rings, v.as_object_mut()) {
            obj.extend(super::rings::json_keys(per, st));
        }
        return Ok(format!("{v}\n"));
    }
    let mut o = report.text();
    if let Some((_, st)) = rings {
        o.push_str(&format!("ring mean log E (r, g, b): {:?}\n", st.mean));
    }
    Ok(o)
}
