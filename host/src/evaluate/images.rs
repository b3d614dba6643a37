//! Any renderer's images judged like a model (`subsurf evaluate --images DIR`): an image per
//! frame is read as that frame's prediction, on exactly the samples, exclusion radius, noise
//! floor and Eq. 8 that judge a model ([`super::evaluate_in`]), so a figure of Cycles' renders
//! of a scan and a figure of subsurf's model of it are the same measurement.
//!
//! Why images and not a model: a renderer (Blender's Cycles with the exported material) is
//! judged by what it draws, not by the parameters it was given. A frame is a measured answer to
//! "this laser ray hits the object at x_i; what does this camera see", and the image of DIR is
//! the renderer's answer to the same question.
//!
//! The prediction of sample s(x_i, x_o) is the image's bilinear read at x_o's projection (the
//! pixel coordinates the frame's sample was read at, the same neighbourhood weights) divided by
//! the frame's `exposure_s`: in a frame's units, so `pixel / exposure_s` means what it means for
//! the capture. A prediction at or below 0 where the frame has light above the noise floor (a
//! path tracer's black pixel) cannot enter Eq. 8's logarithm: it is judged as the noise floor
//! t, the least light the frames tell from none (ln E = ln(t / s) < 0, bounded), and counted
//! ([`super::FrameEval::unlit`]).
use std::path::PathBuf;

use rayon::prelude::*;

use super::{EvalPoints, EvaluateError, FrameEval, model_at};
use crate::dataset::{Image, read_image};
use crate::model::LogEAccumulator;
use crate::modelfile::ModelFile;
use crate::pipeline::{Context, LogEStats, register_one};
use crate::progress::Progress;
use crate::store::PointSet;

/// The file of frame `k` in a folder of predicted frames: `<k, 6 digits>.exr`, as `subsurf
/// export --render` writes Cycles' renders and the dataset writer names frames.
pub fn image_name(k: usize) -> String {
    format!("{k:06}.exr")
}

/// What is wrong with a prediction image.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageProblem {
    /// No file.
    #[error("missing")]
    Missing,
    /// The file could not be decoded.
    #[error("unreadable: {0}")]
    Unreadable(crate::dataset::ImageError),
    /// Not the frame camera's size.
    #[error("{got_w}x{got_h} pixels, the frame's camera is {want_w}x{want_h}")]
    Size {
        /// Width read.
        got_w: usize,
        /// Height read.
        got_h: usize,
        /// The camera's width.
        want_w: usize,
        /// The camera's height.
        want_h: usize,
    },
    /// The model could not predict the frame.
    #[error("not made: {0}")]
    NotMade(BoxError),
    /// NaN or infinite pixels.
    #[error("{0} non-finite pixel values")]
    NonFinite(usize),
}

/// The predicted frames: a folder of images ([`image_name`]), or images made on demand (a
/// volume model traced per frame), judged alike.
#[derive(Clone)]
pub struct FrameImages<'a> {
    /// The folder (for made images: only named in errors).
    pub dir: PathBuf,
    made: Option<&'a dyn MakeImage>,
}

/// Makes frame `k`'s predicted image (the camera's size, finite values): a closure, or a volume
/// model's [`crate::volume::TracedFrames`].
pub trait MakeImage: Sync {
    /// Frame `k`'s image.
    fn make(&self, k: usize) -> Result<Image, BoxError>;
}

impl<F: Fn(usize) -> Result<Image, BoxError> + Sync> MakeImage for F {
    fn make(&self, k: usize) -> Result<Image, BoxError> {
        self(k)
    }
}

impl MakeImage for crate::volume::TracedFrames<'_> {
    fn make(&self, k: usize) -> Result<Image, BoxError> {
        Ok(self.image(k)?)
    }
}
/// Why an image could not be made.
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

impl std::fmt::Debug for FrameImages<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameImages")
            .field("dir", &self.dir)
            .field("made", &self.made.is_some())
            .finish()
    }
}

impl<'a> FrameImages<'a> {
    /// The images in `dir`.
    pub fn new(dir: impl Into<PathBuf>) -> FrameImages<'a> {
        FrameImages {
            dir: dir.into(),
            made: None,
        }
    }

    /// Images made by `make` when a frame is judged (`name` stands for the folder in errors).
    pub fn made(name: impl Into<PathBuf>, make: &'a dyn MakeImage) -> FrameImages<'a> {
        FrameImages {
            dir: name.into(),
            made: Some(make),
        }
    }

    /// Frame `k`'s file.
    pub fn path(&self, k: usize) -> PathBuf {
        self.dir.join(image_name(k))
    }

    fn error(&self, k: usize, problem: ImageProblem) -> EvaluateError {
        EvaluateError::Image {
            frame: k,
            path: self.path(k),
            problem,
        }
    }

    /// Frame `k`'s image, checked: the size of the camera `(w, h)` and every value finite.
    pub fn read(&self, k: usize, size: (usize, usize)) -> Result<Image, EvaluateError> {
        let img = match self.made {
            Some(make) => make
                .make(k)
                .map_err(|e| self.error(k, ImageProblem::NotMade(e)))?,
            None => {
                let path = self.path(k);
                if !path.is_file() {
                    return Err(self.error(k, ImageProblem::Missing));
                }
                read_image(&path).map_err(|e| self.error(k, ImageProblem::Unreadable(e)))?
            }
        };
        if (img.width, img.height) != size {
            return Err(self.error(
                k,
                ImageProblem::Size {
                    got_w: img.width,
                    got_h: img.height,
                    want_w: size.0,
                    want_h: size.1,
                },
            ));
        }
        let bad = img.data.iter().filter(|v| !v.is_finite()).count();
        if bad > 0 {
            return Err(self.error(k, ImageProblem::NonFinite(bad)));
        }
        Ok(img)
    }
}

/// What the images are compared with.
#[derive(Debug, Clone, Copy)]
pub enum Reference<'a> {
    /// The frames' own samples s(x_i, x_o): the renderer judged like a model.
    Frames,
    /// Another renderer's images at the same samples' points: how far two renders differ
    /// (two seeds of Cycles: its own noise, on the yardstick's samples).
    Images(&'a FrameImages<'a>),
}

/// Judges the images `images` as predictions of `frames` on the run `ctx` (whose sample store
/// holds those frames, read by the evaluation protocol: [`crate::pipeline::judge_context`]), at
/// the points `at`. `model` says which light positions apply, as for a model: a frame at whose
/// x_i the model has no vertex model is skipped with the same reason, and needs no image. Every
/// other frame's image must be there, of the camera's size, every value finite: any problem is
/// an error naming its frame.
pub fn evaluate_images_in(
    ctx: &Context,
    model: Option<&ModelFile>,
    images: &FrameImages,
    reference: Reference,
    frames: &[usize],
    at: EvalPoints,
    progress: &dyn Progress,
) -> Result<(Vec<FrameEval>, LogEStats), EvaluateError> {
    if let Some(model) = model {
        super::check_mesh(ctx.ds, model)?;
    }
    let set = at.point_set();
    progress.start("judge images", frames.len() as u64);
    let evals: Result<Vec<FrameEval>, EvaluateError> = frames
        .par_iter()
        .map(|&k| {
            let r = judge_one(ctx, model, images, reference, k, set);
            progress.inc(1);
            r
        })
        .collect();
    let evals = evals?;
    let vals: Vec<[f64; 3]> = evals
        .iter()
        .filter(|e| e.skipped.is_none())
        .map(|e| e.log_e.map(|x| x.unwrap_or(f64::NAN)))
        .collect();
    Ok((evals, LogEStats::of(&vals)))
}

/// A frame ready to be judged: registered, with a model at x_i, its samples and where they
/// project.
pub(super) struct Judged {
    pub(super) x_i: crate::geometry::V3,
    pub(super) samples: std::sync::Arc<Vec<crate::samples::Sample>>,
    pub(super) uv: std::collections::HashMap<u32, (f64, f64)>,
}

/// One frame: skipped for the reasons a model's frame is skipped (then its images are not
/// needed: a renderer cannot be asked about a frame without x_i); else its images read and
/// checked (a problem is an error naming the frame) and the frame judged.
fn judge_one(
    ctx: &Context,
    model: Option<&ModelFile>,
    images: &FrameImages,
    reference: Reference,
    k: usize,
    set: PointSet,
) -> Result<FrameEval, EvaluateError> {
    let f = ctx
        .ds
        .spec
        .frames
        .get(k)
        .ok_or_else(|| EvaluateError::Frame {
            frame: k,
            reason: format!("dataset has {} frames", ctx.ds.spec.frames.len()),
        })?;
    let judged = match prepare(ctx, model, k, set) {
        Ok(j) => j,
        Err(reason) => {
            return Ok(FrameEval {
                frame: k,
                log_e: [None; 3],
                samples: 0,
                channel_samples: [0; 3],
                x_i: None,
                local_share: None,
                unlit: None,
                skipped: Some(reason),
            });
        }
    };
    let cam = ctx.camera(f.camera);
    let size = (cam.width as usize, cam.height as usize);
    let img = images.read(k, size)?;
    let reference_img = match reference {
        Reference::Frames => None,
        Reference::Images(r) => Some(r.read(k, size)?),
    };
    Ok(compare(ctx, &judged, &img, reference_img.as_ref(), k))
}

/// Frame `k` registered (x_i), the model present at x_i, its samples from the store and their
/// pixel coordinates; or why the frame is not judged.
pub(super) fn prepare(
    ctx: &Context,
    model: Option<&ModelFile>,
    k: usize,
    set: PointSet,
) -> Result<Judged, String> {
    let reg = register_one(ctx, k)?;
    let x_i = reg.x_i;
    // The frames judged are the model's: where it has no model at x_i, neither is judged (a
    // volume, `None`, predicts wherever the laser meets the mesh).
    if let Some(model) = model {
        model_at(ctx, model, reg.triangle, x_i).ok_or("no model at x_i")?;
    }
    let store = ctx.store().ok_or("no sample store")?;
    let fs = store
        .samples(k, set)
        .map_err(|e| e.to_string())?
        .ok_or("no samples at these points")?;
    let f = &ctx.ds.spec.frames[k];
    // Where each sampled point projects: the visibility the extraction read the samples by.
    let visible = match set {
        PointSet::Vertices => ctx.visible(f.camera, f.turntable_deg).as_ref().clone(),
        PointSet::Lattice => {
            let p = store.points().ok_or("no surface points in the store")?;
            ctx.scene.visible_points_of(
                &p.points,
                &p.which,
                ctx.camera(f.camera),
                f.turntable_deg,
                ctx.opts.samples.cos_min,
            )
        }
    };
    let uv = visible.iter().map(|v| (v.vertex, (v.u, v.v))).collect();
    Ok(Judged {
        x_i,
        samples: fs.samples,
        uv,
    })
}

/// Eq. 8 of frame `k` with `img` as the prediction, against the frame's samples or, with
/// `reference`, against that image at the same points.
fn compare(
    ctx: &Context,
    judged: &Judged,
    img: &Image,
    reference: Option<&Image>,
    k: usize,
) -> FrameEval {
    let f = &ctx.ds.spec.frames[k];
    let t = ctx.opts.error_threshold;
    let chans = f.channel.channels();
    let mut acc = [LogEAccumulator::default(); 3];
    let mut unlit = 0u64;
    for s in judged.samples.iter() {
        // Every sample was read at a visible point's projection; one without is not compared.
        let Some(&(u, v)) = judged.uv.get(&s.vertex) else {
            continue;
        };
        let Some(read) = img.bilinear_channels(u, v, chans) else {
            continue;
        };
        let truth = match reference {
            None => None,
            Some(r) => match r.bilinear_channels(u, v, chans) {
                Some(tr) => Some(tr),
                None => continue,
            },
        };
        for &c in chans {
            if s.valid & (1 << c) == 0 {
                continue;
            }
            let s_c = match truth {
                None => s.value[c],
                Some(tr) => tr[c].0 / f.exposure_s,
            };
            let p = read[c].0 / f.exposure_s;
            let ln_p = if p > 0.0 {
                p.ln()
            } else if t > 0.0 && s_c > t {
                unlit += 1;
                t.ln()
            } else {
                continue;
            };
            acc[c].add_ln(ln_p, s_c, t);
        }
    }
    FrameEval {
        frame: k,
        log_e: acc.map(|a| a.log_e()),
        samples: acc.iter().map(|a| a.count).sum(),
        channel_samples: acc.map(|a| a.count),
        x_i: Some(judged.x_i),
        local_share: None,
        unlit: Some(unlit),
        skipped: None,
    }
}
