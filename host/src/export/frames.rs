//! A scan's frames rendered in Cycles with the exported material, and judged by the frames
//! themselves (`subsurf export --scan S --frames F --render`, docs/export.md).
//!
//! Why: the export is for people who render the captured material in their own scenes, and the
//! question they have is whether Cycles, given it, looks like the object they scanned. Every
//! frame of a scan is a measured answer to "this laser ray hits the object at x_i; what does
//! this camera see". Cycles is asked the same question — the frame's camera, image size and
//! exposure, its laser as a light on x_i, the turntable's angle on the object — and its images
//! are judged like a model ([`crate::evaluate::images`]): on the samples, exclusion radius,
//! noise floor and Eq. 8 that judge subsurf's own model on the same frames, so the two figures
//! sit side by side. A second seed's render judged against the first is Cycles' own noise on
//! the same yardstick.
//!
//! - [`frame_scenes`]: per registered frame, its scene in Blender's terms (`frames.json`, read
//!   by `build_blend.py --frame K`): the camera ([`scene::camera`]), the object turned by
//!   R_z(θ) ([`scene::turntable_matrix`]), the laser as a spot [`STANDOFF_MM`] before x_i along
//!   the frame's laser ray whose footprint is half a pixel of the camera there
//!   ([`scene::laser_spot`]), its power [`scene::beam_watts`] of the scan's unit times the
//!   exposure (Blender writes radiance; the frame holds radiance × exposure_s).
//! - [`render_frames`]: Blender renders each into `frames/<frame, 6 digits>.exr`.
//! - [`judge_frames`]: Cycles' log E next to subsurf's, per frame and as a mean, and the noise.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::scene::{self, BlenderCamera, BlenderLight};
use super::{Blender, ExportError, Run};
use crate::dataset::Dataset;
use crate::evaluate::{EvalPoints, FrameEval, FrameImages, Reference, evaluate_images_in};
use crate::geometry::V3;
use crate::modelfile::ModelFile;
use crate::pipeline::{Context, register_one};
use crate::progress::Progress;
use crate::volume::{TracedFrames, VolumeModel};

/// What Cycles renders and what it is judged beside: an empirical model's material (Burley),
/// or a volume model's medium (Principled Volume, docs/volume.md), each next to subsurf's own
/// prediction of the same frames on the same samples.
#[derive(Clone, Copy, Debug)]
pub enum Subject<'a> {
    /// An empirical model: its conversion rendered, its own prediction beside; with the
    /// conversion itself, Cycles' expected render replayed in closed form beside too
    /// ([`super::replay`]).
    Empirical(&'a ModelFile, Option<&'a super::Export>),
    /// A volume model: its medium rendered, its own trace with `photons` per frame beside.
    Volume {
        /// The model.
        model: &'a VolumeModel,
        /// Photons per frame of subsurf's trace.
        photons: usize,
    },
}

impl Subject<'_> {
    fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match self {
            Subject::Empirical(m, _) => m.bounds(),
            Subject::Volume { model, .. } => model.mesh.bounds(),
        }
    }

    fn model(&self) -> Option<&ModelFile> {
        match self {
            Subject::Empirical(m, _) => Some(m),
            Subject::Volume { .. } => None,
        }
    }

    /// The Cycles beam power (W) that carries `flux` of the scan's laser unit.
    fn beam_watts(&self, flux: f64) -> f64 {
        match self {
            Subject::Empirical(..) => scene::beam_watts(flux),
            Subject::Volume { .. } => scene::volume_beam_watts(flux),
        }
    }
}

/// The frame scenes' file in an export folder.
pub const FRAMES_FILE: &str = "frames.json";
/// Where the frames' renders go: `frames/<frame, 6 digits>.exr`.
pub const FRAMES_DIR: &str = "frames";
/// Where the second seed's renders go (Cycles' own noise).
pub const NOISE_DIR: &str = "frames-seed1";
/// The format string of `frames.json`.
pub const FRAMES_FORMAT: &str = "subsurf-blender-frames/1";

/// How far before x_i, along the laser ray, the spot light sits (mm). A few millimetres: close
/// enough that no other part of the object comes between (x_i is the ray's first hit), far
/// enough that the cone is a narrow beam.
pub const STANDOFF_MM: f64 = 5.0;

/// The spot's footprint radius on x_i in pixels of the frame's camera: the beam lights a disk
/// one pixel across, no larger than what the camera resolves (a real laser spot is smaller
/// still; a wider one would blur the fall-off's first pixels, a narrower one leaves Cycles'
/// disk probes fewer lit points to find: more noise).
pub const FOOTPRINT_PX: f64 = 0.5;

/// The laser's power in the scan's units: the unit the samples are per (a dataset's pixel
/// values are radiance per unit of laser power; the shared datasets' per watt).
pub const LASER_POWER: f64 = 1.0;

/// One frame's scene.
#[derive(Clone, Debug, Serialize)]
pub struct FrameScene {
    /// Frame index.
    pub frame: usize,
    /// The render's file, relative to the export folder.
    pub image: String,
    /// The object's world matrix: the turntable's R_z(θ).
    pub object_matrix: [[f64; 4]; 4],
    /// The turntable angle θ, degrees.
    pub turntable_deg: f64,
    /// The frame's camera.
    pub camera: BlenderCamera,
    /// The laser.
    pub laser: BlenderLight,
    /// x_i, the registered light position (object frame, mm).
    pub x_i_mm: [f64; 3],
    /// The spot's footprint radius on x_i (mm).
    pub footprint_mm: f64,
    /// Whether the laser's direction is the frame's `laser` ray (else the surface normal at
    /// x_i: a dataset without laser rays).
    pub laser_ray: bool,
    /// The laser's direction (world frame, unit).
    pub laser_direction: [f64; 3],
    /// The frame's exposure (the shortest of its brackets), which the light's power carries.
    pub exposure_s: f64,
    /// The part of the image Cycles renders, `[min_x, max_x, min_y, max_y]` as fractions of
    /// the width and height from the bottom left (Blender's render border): the frame's sampled
    /// points and [`BORDER_PX`] around them; the rest of the image stays black. `None`: all.
    pub border: Option<[f64; 4]>,
}

/// Pixels kept around the sampled points' projections when the render is bordered: the
/// bilinear neighbourhood (1 px) and the box filter's reach, with a margin.
pub const BORDER_PX: f64 = 3.0;

/// A frame that has no scene, and why.
#[derive(Clone, Debug, Serialize)]
pub struct SkippedFrame {
    /// Frame index.
    pub frame: usize,
    /// Why (not registered, no model at x_i, a camera Blender cannot reproduce).
    pub reason: String,
}

/// `frames.json`.
#[derive(Clone, Debug, Serialize)]
pub struct FrameScenes {
    /// [`FRAMES_FORMAT`].
    pub format: &'static str,
    /// The laser's power in the scan's units ([`LASER_POWER`]).
    pub laser_power: f64,
    /// [`STANDOFF_MM`].
    pub standoff_mm: f64,
    /// Cycles samples per pixel.
    pub samples: u32,
    /// Pixel filter width (box, pixels): a camera pixel integrates its own area.
    pub filter_width: f64,
    /// The frames' scenes.
    pub frames: Vec<FrameScene>,
    /// Frames asked for that have none.
    pub skipped: Vec<SkippedFrame>,
}

/// `v` turned by the turntable's R_z(θ).
fn turn(v: V3, deg: f64) -> V3 {
    let (s, c) = deg.to_radians().sin_cos();
    [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]
}

/// The scenes of `frames` on the run `ctx` (registered by the evaluation protocol, as the
/// judge registers them): a frame without x_i, without a model there, or whose camera Blender
/// cannot reproduce is skipped with its reason.
pub fn frame_scenes(
    ctx: &Context,
    subject: Subject,
    frames: &[usize],
    samples: u32,
) -> Result<FrameScenes, ExportError> {
    if samples == 0 {
        return Err(ExportError::Invalid("samples must be at least 1".into()));
    }
    let ds = ctx.ds;
    // Clipping around the object at any turntable angle: its bounds swept about the axis.
    let (lo, hi) = subject.bounds();
    let reach = [lo[0], hi[0]]
        .iter()
        .flat_map(|&x| [lo[1], hi[1]].map(|y| x.hypot(y)))
        .fold(0.0f64, f64::max);
    let bounds = ([-reach, -reach, lo[2]], [reach, reach, hi[2]]);
    let mut out = FrameScenes {
        format: FRAMES_FORMAT,
        laser_power: LASER_POWER,
        standoff_mm: STANDOFF_MM,
        samples,
        filter_width: 1.0,
        frames: Vec::new(),
        skipped: Vec::new(),
    };
    for &k in frames {
        match frame_scene(ctx, subject, k, bounds) {
            Ok(s) => out.frames.push(s),
            Err(reason) => out.skipped.push(SkippedFrame { frame: k, reason }),
        }
    }
    if out.frames.is_empty() && !frames.is_empty() {
        return Err(ExportError::Invalid(format!(
            "none of the {} frames can be rendered ({} in {}): {}",
            frames.len(),
            ds.spec.frames.len(),
            ds.dir.display(),
            out.skipped
                .iter()
                .take(3)
                .map(|s| format!("frame {}: {}", s.frame, s.reason))
                .collect::<Vec<_>>()
                .join("; ")
        )));
    }
    Ok(out)
}

fn frame_scene(
    ctx: &Context,
    subject: Subject,
    k: usize,
    bounds: ([f64; 3], [f64; 3]),
) -> Result<FrameScene, String> {
    let f = ctx
        .ds
        .spec
        .frames
        .get(k)
        .ok_or_else(|| format!("the dataset has {} frames", ctx.ds.spec.frames.len()))?;
    let reg = register_one(ctx, k)?;
    if let Some(model) = subject.model() {
        crate::evaluate::model_at(ctx, model, reg.triangle, reg.x_i).ok_or("no model at x_i")?;
    }
    let cam = ctx.camera(f.camera);
    let camera = scene::camera(cam, bounds).map_err(|e| e.to_string())?;
    let hit = turn(reg.x_i, f.turntable_deg);
    let (direction, laser_ray) = match &f.laser {
        Some(l) => (l.direction, true),
        None => {
            let n = turn(ctx.normal_at(reg.triangle, reg.x_i), f.turntable_deg);
            (n.map(|x| -x), false)
        }
    };
    let eye = cam.center();
    let dist = ((0..3).map(|i| (hit[i] - eye[i]).powi(2)).sum::<f64>()).sqrt();
    let footprint_mm = FOOTPRINT_PX * dist / cam.fx;
    if !(f.exposure_s > 0.0 && f.exposure_s.is_finite()) {
        return Err(format!("exposure_s {} is not positive", f.exposure_s));
    }
    let laser = scene::laser_spot(
        hit,
        direction,
        STANDOFF_MM,
        footprint_mm,
        subject.beam_watts(LASER_POWER * f.exposure_s),
    )
    .map_err(|e| e.to_string())?;
    let border = border(ctx, k, (cam.width as f64, cam.height as f64));
    Ok(FrameScene {
        frame: k,
        image: format!("{FRAMES_DIR}/{}", crate::evaluate::images::image_name(k)),
        object_matrix: scene::turntable_matrix(f.turntable_deg),
        turntable_deg: f.turntable_deg,
        camera,
        laser,
        x_i_mm: reg.x_i,
        footprint_mm,
        laser_ray,
        laser_direction: crate::geometry::normalize(direction).unwrap_or(direction),
        exposure_s: f.exposure_s,
        border,
    })
}

/// The render border of frame `k`: the box around its sampled vertices' projections (the only
/// pixels the judge reads), [`BORDER_PX`] wider, as Blender's fractions; `None` when the
/// run holds no samples of it. Why: the laser's light reaches a small part of a frame, and a
/// path tracer's cost is per pixel; where nothing is read, nothing needs rendering.
fn border(ctx: &Context, k: usize, (w, h): (f64, f64)) -> Option<[f64; 4]> {
    let f = ctx.ds.spec.frames.get(k)?;
    let fs = ctx
        .store()?
        .samples(k, crate::store::PointSet::Vertices)
        .ok()??;
    let sampled: std::collections::HashSet<u32> = fs.samples.iter().map(|s| s.vertex).collect();
    let vis = ctx.visible(f.camera, f.turntable_deg);
    let (mut u0, mut u1, mut v0, mut v1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in vis.iter().filter(|p| sampled.contains(&p.vertex)) {
        u0 = u0.min(p.u);
        u1 = u1.max(p.u);
        v0 = v0.min(p.v);
        v1 = v1.max(p.v);
    }
    if !(u0.is_finite() && v0.is_finite()) {
        return None;
    }
    // Pixel column i covers [i − ½, i + ½): the border's edges in fractions of the image.
    let x = |u: f64| ((u + 0.5) / w).clamp(0.0, 1.0);
    let y = |v: f64| (1.0 - (v + 0.5) / h).clamp(0.0, 1.0);
    Some([
        x(u0 - BORDER_PX),
        x(u1 + BORDER_PX),
        y(v1 + BORDER_PX),
        y(v0 - BORDER_PX),
    ])
}

/// Writes `frames.json` into the export folder `dir`.
pub fn write_frame_scenes(dir: &Path, scenes: &FrameScenes) -> Result<PathBuf, ExportError> {
    super::write_json(dir, FRAMES_FILE, scenes)
}

/// Renders every scene of `scenes` (written to `dir` with the rest of the export) in Cycles
/// with seed `seed` into `dir/<out>/<frame, 6 digits>.exr`; returns the seconds per frame.
pub fn render_frames(
    blender: &Blender,
    dir: &Path,
    scenes: &FrameScenes,
    out: &str,
    seed: u32,
    progress: &dyn Progress,
) -> Result<Vec<f64>, ExportError> {
    let folder = dir.join(out);
    std::fs::create_dir_all(&folder).map_err(|e| ExportError::io(&folder, e))?;
    progress.start(&format!("Cycles {out}"), scenes.frames.len() as u64);
    let mut seconds = Vec::with_capacity(scenes.frames.len());
    for s in &scenes.frames {
        let t = std::time::Instant::now();
        let exr = folder.join(crate::evaluate::images::image_name(s.frame));
        blender.run(
            dir,
            &Run {
                render: Some(exr.clone()),
                samples: Some(scenes.samples),
                compare: false,
                threads: 0,
                seed,
                frame: Some(s.frame),
                measure: None,
            },
        )?;
        if !exr.is_file() {
            return Err(ExportError::Blender(format!(
                "frame {}: no render at {}",
                s.frame,
                exr.display()
            )));
        }
        seconds.push(t.elapsed().as_secs_f64());
        progress.inc(1);
    }
    Ok(seconds)
}

/// One frame of the comparison.
#[derive(Clone, Debug, Serialize)]
pub struct FrameRow {
    /// Frame index.
    pub frame: usize,
    /// Whether the model's fit used the frame (in-sample: optimistic for both renderers).
    pub fitted: bool,
    /// log E (Eq. 8) of Cycles' render per channel.
    pub cycles_log_e: [Option<f64>; 3],
    /// log E of subsurf's model on the same samples.
    pub subsurf_log_e: [Option<f64>; 3],
    /// log E of the second seed's render against the first on the same samples (Cycles' own
    /// noise; both renders' noise, so √2 times one render's).
    pub noise_log_e: Option<[Option<f64>; 3]>,
    /// The ring yardstick ([`crate::evaluate::rings`]): Eq. 8 over the means of linear radiance
    /// in rings around x_i, Cycles' render against the frame.
    pub cycles_ring_log_e: [Option<f64>; 3],
    /// The same rings for subsurf's model.
    pub subsurf_ring_log_e: [Option<f64>; 3],
    /// The same rings, the second seed's render against the first.
    pub noise_ring_log_e: Option<[Option<f64>; 3]>,
    /// A volume model: the same rings, Cycles' render against subsurf's trace.
    pub agreement_ring_log_e: Option<[Option<f64>; 3]>,
    /// An empirical model's conversion: Cycles' expected render ([`super::replay`]) judged
    /// like Cycles' render, per sample, by rings, and Cycles' render against it on the same
    /// rings (where the replay is right, one render's noise: the second seed's column / √2).
    pub replay: Option<ReplayRow>,
    /// Channel samples Cycles left black where the frame has light (judged at the noise floor).
    pub unlit: u64,
    /// Channel samples compared.
    pub samples: u64,
    /// Seconds of Cycles' render (Blender's start included).
    pub seconds: f64,
}

/// One frame's figures of Cycles' expected render ([`super::replay`]).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ReplayRow {
    /// log E per sample against the frame.
    pub log_e: [Option<f64>; 3],
    /// Ring log E against the frame.
    pub ring_log_e: [Option<f64>; 3],
    /// Cycles' render judged against the replay on the frame's rings.
    pub cycles_ring_log_e: [Option<f64>; 3],
}

/// Cycles judged by the frames it must reproduce, next to subsurf's model.
#[derive(Clone, Debug, Serialize)]
pub struct FramesComparison {
    /// Cycles samples per pixel.
    pub samples: u32,
    /// Mean log E over the frames both judged, per channel: Cycles.
    pub cycles_mean_log_e: [Option<f64>; 3],
    /// The same frames' mean for subsurf's model.
    pub subsurf_mean_log_e: [Option<f64>; 3],
    /// The second seed's mean log E against the first.
    pub noise_mean_log_e: Option<[Option<f64>; 3]>,
    /// Cycles' mean over subsurf's, green.
    pub ratio_green: Option<f64>,
    /// The ring yardstick's means over the frames both judged: Cycles, subsurf, and the second
    /// seed against the first.
    pub cycles_ring_mean_log_e: [Option<f64>; 3],
    /// subsurf's model on the same rings.
    pub subsurf_ring_mean_log_e: [Option<f64>; 3],
    /// The second seed against the first, on the same rings (two renders' noise).
    pub noise_ring_mean_log_e: Option<[Option<f64>; 3]>,
    /// Cycles' ring mean over subsurf's, green.
    pub ring_ratio_green: Option<f64>,
    /// A volume model: the mean over frames of Cycles' render against subsurf's trace on the
    /// same rings (the two renderers of one medium; their noise included).
    pub agreement_ring_mean_log_e: Option<[Option<f64>; 3]>,
    /// An empirical model's conversion: the replay's means over the frames judged (per
    /// sample, rings, Cycles' render against it on the rings).
    pub replay_mean_log_e: Option<[Option<f64>; 3]>,
    /// The replay's ring mean (the same frames as `subsurf_ring_mean_log_e`).
    pub replay_ring_mean_log_e: Option<[Option<f64>; 3]>,
    /// Cycles' render against the replay, ring mean.
    pub replay_agreement_ring_mean_log_e: Option<[Option<f64>; 3]>,
    /// The replay's ring mean over subsurf's, green.
    pub replay_ring_ratio_green: Option<f64>,
    /// Per frame.
    pub per_frame: Vec<FrameRow>,
    /// Frames asked for that were not rendered or not judged, and why.
    pub skipped: Vec<SkippedFrame>,
    /// The noise floor of the evaluation protocol.
    pub noise_floor: f64,
    /// Seconds of all Cycles renders (both seeds).
    pub cycles_seconds: f64,
}

/// Per channel, the mean of `f` over `rows` where every compared value is present.
fn mean_of(rows: &[&FrameRow], f: impl Fn(&FrameRow) -> Option<f64>) -> Option<f64> {
    let v: Vec<f64> = rows.iter().filter_map(|r| f(r)).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// What was rendered: seconds per frame of the first seed, and of all the second seed's
/// frames when it was rendered (`--noise`).
#[derive(Clone, Debug, Default)]
pub struct Renders {
    /// Seconds per frame, seed 0.
    pub seconds: Vec<f64>,
    /// Seconds of the second seed's renders, when there are any.
    pub noise_seconds: Option<f64>,
    /// The Cycles that rendered them (the replay follows its kernel).
    pub kernel: super::replay::Kernel,
}

/// Judges the renders of `scenes` in `dir/frames` (and, when rendered, `dir/frames-seed1`)
/// against the frames on `ctx` (the evaluation protocol's run with its store), next to
/// `subject`'s own figures on the same samples.
pub fn judge_frames(
    ctx: &Context,
    subject: Subject,
    dir: &Path,
    scenes: &FrameScenes,
    renders: &Renders,
    progress: &dyn Progress,
) -> Result<FramesComparison, ExportError> {
    let seconds = &renders.seconds[..];
    let noise = renders.noise_seconds.is_some();
    let noise_seconds = renders.noise_seconds.unwrap_or(0.0);
    let frames: Vec<usize> = scenes.frames.iter().map(|s| s.frame).collect();
    let at = EvalPoints::Vertices;
    let model = subject.model();
    use crate::evaluate::rings::{Prediction, evaluate_rings_in};
    // subsurf's own figures: the empirical model's prediction, or the volume's traced images
    // (traced once per frame, read by both yardsticks).
    let predictor = match subject {
        Subject::Volume { model: v, .. } => Some(v.predictor().map_err(|e| {
            ExportError::Invalid(format!("the volume model cannot be traced: {e}"))
        })?),
        Subject::Empirical(..) => None,
    };
    let traced = match (subject, &predictor) {
        (Subject::Volume { photons, .. }, Some(p)) => Some(TracedFrames::new(
            p,
            ctx.ds,
            photons,
            crate::evaluate::run::VOLUME_SEED,
            true,
        )),
        _ => None,
    };
    let traced = traced
        .as_ref()
        .map(|t| FrameImages::made(TracedFrames::NAME, t));
    let (ours, own) = match (model, &traced) {
        (Some(m), _) => (
            crate::evaluate::evaluate_in(ctx, m, &frames, at, progress)?.0,
            Prediction::Model,
        ),
        (None, Some(t)) => (
            evaluate_images_in(ctx, None, t, Reference::Frames, &frames, at, progress)?.0,
            Prediction::Images(t, Reference::Frames),
        ),
        (None, None) => {
            return Err(ExportError::Invalid(
                "nothing to judge the renders by".into(),
            ));
        }
    };
    let cycles = FrameImages::new(dir.join(FRAMES_DIR));
    let (theirs, _) = evaluate_images_in(
        ctx,
        model,
        &cycles,
        Reference::Frames,
        &frames,
        at,
        progress,
    )?;
    let noise_evals = if noise {
        let second = FrameImages::new(dir.join(NOISE_DIR));
        let r = Reference::Images(&cycles);
        Some(evaluate_images_in(ctx, model, &second, r, &frames, at, progress)?.0)
    } else {
        None
    };
    let (ring_ours, _) = evaluate_rings_in(ctx, model, own, &frames, at, progress)?;
    let (ring_theirs, _) = evaluate_rings_in(
        ctx,
        model,
        Prediction::Images(&cycles, Reference::Frames),
        &frames,
        at,
        progress,
    )?;
    let ring_noise = if noise {
        let second = FrameImages::new(dir.join(NOISE_DIR));
        let p = Prediction::Images(&second, Reference::Images(&cycles));
        Some(evaluate_rings_in(ctx, model, p, &frames, at, progress)?.0)
    } else {
        None
    };
    // A volume's trace is an image too: Cycles judged against it on the same rings says how
    // far the two renderers of one medium agree, apart from how far both are from the frames.
    let agreement = match &traced {
        None => None,
        Some(t) => {
            let p = Prediction::Images(&cycles, Reference::Images(t));
            Some(evaluate_rings_in(ctx, model, p, &frames, at, progress)?.0)
        }
    };
    let replay = match subject {
        Subject::Empirical(m, Some(export)) => {
            let r = super::replay::Replay::new(
                ctx,
                scenes,
                &export.mesh,
                export.scene.exit_fresnel_ior,
                renders.kernel,
            )?;
            Some(judge_replay(ctx, m, &r, &cycles, &frames, progress)?)
        }
        _ => None,
    };
    let fitted = match subject {
        Subject::Empirical(m, _) => m.fitted_frames.as_deref().unwrap_or(&[]),
        Subject::Volume { model, .. } => &model.fit.frames[..],
    };
    let mut skipped = scenes.skipped.clone();
    let mut rows = Vec::new();
    for (n, (a, b)) in theirs.iter().zip(&ours).enumerate() {
        if let Some(why) = a.skipped.as_ref().or(b.skipped.as_ref()) {
            skipped.push(SkippedFrame {
                frame: a.frame,
                reason: why.clone(),
            });
            continue;
        }
        let noise_e: Option<&FrameEval> = noise_evals.as_ref().map(|v| &v[n]);
        rows.push(FrameRow {
            frame: a.frame,
            fitted: fitted.contains(&a.frame),
            cycles_log_e: a.log_e,
            subsurf_log_e: b.log_e,
            noise_log_e: noise_e.map(|e| e.log_e),
            cycles_ring_log_e: ring_theirs[n].log_e,
            subsurf_ring_log_e: ring_ours[n].log_e,
            noise_ring_log_e: ring_noise.as_ref().map(|v| v[n].log_e),
            agreement_ring_log_e: agreement.as_ref().map(|v| v[n].log_e),
            replay: replay.as_ref().map(|v| v[n]),
            unlit: a.unlit.unwrap_or(0),
            samples: a.samples,
            seconds: seconds.get(n).copied().unwrap_or(0.0),
        });
    }
    let refs: Vec<&FrameRow> = rows.iter().collect();
    // Means over the frames where both have the channel: the same frames for both.
    let both = |c: usize| -> Vec<&FrameRow> {
        refs.iter()
            .copied()
            .filter(|r| r.cycles_log_e[c].is_some() && r.subsurf_log_e[c].is_some())
            .collect()
    };
    let cycles_mean_log_e = [0, 1, 2].map(|c| mean_of(&both(c), |r| r.cycles_log_e[c]));
    let subsurf_mean_log_e = [0, 1, 2].map(|c| mean_of(&both(c), |r| r.subsurf_log_e[c]));
    let noise_mean_log_e =
        noise.then(|| [0, 1, 2].map(|c| mean_of(&refs, |r| r.noise_log_e.and_then(|n| n[c]))));
    let ratio_green = match (cycles_mean_log_e[1], subsurf_mean_log_e[1]) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    let ring_both = |c: usize| -> Vec<&FrameRow> {
        refs.iter()
            .copied()
            .filter(|r| r.cycles_ring_log_e[c].is_some() && r.subsurf_ring_log_e[c].is_some())
            .collect()
    };
    let cycles_ring_mean_log_e =
        [0, 1, 2].map(|c| mean_of(&ring_both(c), |r| r.cycles_ring_log_e[c]));
    let subsurf_ring_mean_log_e =
        [0, 1, 2].map(|c| mean_of(&ring_both(c), |r| r.subsurf_ring_log_e[c]));
    let noise_ring_mean_log_e =
        noise.then(|| [0, 1, 2].map(|c| mean_of(&refs, |r| r.noise_ring_log_e.and_then(|n| n[c]))));
    let ring_ratio_green = match (cycles_ring_mean_log_e[1], subsurf_ring_mean_log_e[1]) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    let agreement_ring_mean_log_e = agreement
        .is_some()
        .then(|| [0, 1, 2].map(|c| mean_of(&refs, |r| r.agreement_ring_log_e.and_then(|n| n[c]))));
    let replay_of = |f: fn(&ReplayRow) -> [Option<f64>; 3]| {
        replay.is_some().then(|| {
            [0, 1, 2].map(|c| mean_of(&ring_both(c), |r| r.replay.as_ref().and_then(|p| f(p)[c])))
        })
    };
    let replay_ring_mean_log_e = replay_of(|p| p.ring_log_e);
    let replay_ring_ratio_green = match (replay_ring_mean_log_e, subsurf_ring_mean_log_e[1]) {
        (Some([_, Some(a), _]), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    Ok(FramesComparison {
        replay_mean_log_e: replay_of(|p| p.log_e),
        replay_ring_mean_log_e,
        replay_agreement_ring_mean_log_e: replay_of(|p| p.cycles_ring_log_e),
        replay_ring_ratio_green,
        agreement_ring_mean_log_e,
        cycles_ring_mean_log_e,
        subsurf_ring_mean_log_e,
        noise_ring_mean_log_e,
        ring_ratio_green,
        samples: scenes.samples,
        cycles_mean_log_e,
        subsurf_mean_log_e,
        noise_mean_log_e,
        ratio_green,
        per_frame: rows,
        skipped,
        noise_floor: ctx.opts.error_threshold,
        cycles_seconds: seconds.iter().sum::<f64>() + noise_seconds,
    })
}

/// Per frame of `frames`, the replay `replay` judged against the frames (per sample and by
/// rings) and Cycles' renders `cycles` judged against it (rings).
fn judge_replay(
    ctx: &Context,
    model: &ModelFile,
    replay: &super::replay::Replay,
    cycles: &FrameImages,
    frames: &[usize],
    progress: &dyn Progress,
) -> Result<Vec<ReplayRow>, ExportError> {
    use crate::evaluate::rings::{Prediction, evaluate_rings_in};
    let at = EvalPoints::Vertices;
    // Made once per frame: three judges read each image.
    let kept = replay.kept(frames);
    let images = FrameImages::made(super::replay::Replay::NAME, &kept);
    let m = Some(model);
    let (per_sample, _) =
        evaluate_images_in(ctx, m, &images, Reference::Frames, frames, at, progress)?;
    let p = Prediction::Images(&images, Reference::Frames);
    let (rings, _) = evaluate_rings_in(ctx, m, p, frames, at, progress)?;
    let p = Prediction::Images(cycles, Reference::Images(&images));
    let (against, _) = evaluate_rings_in(ctx, m, p, frames, at, progress)?;
    Ok(per_sample
        .iter()
        .zip(&rings)
        .zip(&against)
        .map(|((a, b), c)| ReplayRow {
            log_e: a.log_e,
            ring_log_e: b.log_e,
            cycles_ring_log_e: c.log_e,
        })
        .collect())
}

/// The whole of `subsurf export --scan --frames --render`: the protocol's run on `frames` of
/// `ds` (one decode per frame, through the sample cache `store`), their scenes written into
/// `dir`, rendered by `blender` (twice with `noise`), and judged.
#[allow(clippy::too_many_arguments)]
pub fn render_and_judge(
    ds: &Dataset,
    subject: Subject,
    frames: &[usize],
    samples: u32,
    blender: &Blender,
    dir: &Path,
    noise: bool,
    store: &crate::pipeline::StoreOptions,
    progress: &dyn Progress,
) -> Result<(FrameScenes, FramesComparison), ExportError> {
    let (opts, _) = crate::pipeline::evaluation_protocol(ds)
        .map_err(|e| ExportError::Invalid(format!("the dataset's noise floor: {e}")))?;
    let models: Vec<&ModelFile> = subject.model().into_iter().collect();
    let ctx = crate::evaluate::judged_store(
        ds,
        &models,
        frames,
        &opts,
        EvalPoints::Vertices,
        store,
        progress,
    )?;
    let scenes = frame_scenes(&ctx, subject, frames, samples)?;
    write_frame_scenes(dir, &scenes)?;
    let seconds = render_frames(blender, dir, &scenes, FRAMES_DIR, 0, progress)?;
    let noise_seconds = if noise {
        Some(
            render_frames(blender, dir, &scenes, NOISE_DIR, 1, progress)?
                .iter()
                .sum(),
        )
    } else {
        None
    };
    let renders = Renders {
        seconds,
        noise_seconds,
        kernel: super::replay::Kernel::of(blender.version),
    };
    let cmp = judge_frames(&ctx, subject, dir, &scenes, &renders, progress)?;
    Ok((scenes, cmp))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_turntable_turns_counter_clockwise_seen_from_above() {
        let p = turn([1.0, 0.0, 2.0], 90.0);
        assert!(p[0].abs() < 1e-12 && (p[1] - 1.0).abs() < 1e-12 && p[2] == 2.0);
    }
}
