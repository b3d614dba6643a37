//! Stage `extract` (section 5: "the acquired data"): every frame decoded once, registered
//! (sections 4.1, 5: the spot and x_i) and sampled at the vertices and at the lattice points of
//! alpha finer than the mesh, into the run's [`SampleStore`]. No later stage reads a frame: the
//! fit rounds, alpha, the lattice, the error and the held-out frames of `--validate` all read the
//! store.
//!
//! One streaming, parallel pass: frames are taken view by view (camera, turntable angle), so the
//! lattice points' visibility is cast once per view and dropped with it, and within a view a few
//! frames per worker at a time, so memory holds a handful of decoded images, never the scan. A
//! store cached in the dataset by an earlier run (or by `subsurf scan`, which extracts each frame
//! as it arrives) with the same frames and extraction options is opened instead.
use std::collections::BTreeMap;
use std::path::PathBuf;

use rayon::prelude::*;

use crate::dataset::{Dataset, Image};
use crate::geometry::{Camera, SurfacePoints, Visible};
use crate::lattice::{is_corner, points};
use crate::model::TangentFrame;
use crate::progress::Progress;
use crate::registration::RegistrationOutcome;
use crate::store::arrow::{CACHE_DIR, Target, Writer};
use crate::store::{Extracted, ExtractionKey, FrameRecord, SampleStore, StoreBuilder, StorePoints};

use super::lattice::face_levels;
use super::load::Context;
use super::{PipelineError, PipelineOptions};

/// Where a run keeps its sample store, and how much of it in memory.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoreOptions {
    /// Bytes of samples held in memory; beyond, frames are read back from the store's files.
    pub budget: usize,
    /// Where the store's files go.
    pub cache: Cache,
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions {
            budget: crate::store::DEFAULT_BUDGET,
            cache: Cache::Dataset,
        }
    }
}

/// Where a store's files go (`--cache`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Cache {
    /// In the dataset (`.subsurf-cache/`), reused by later runs.
    Dataset,
    /// In this directory, reused by later runs that name it.
    Dir(PathBuf),
    /// Nowhere kept: a scratch directory for the frames beyond the budget, removed at the end.
    Off,
}

impl std::str::FromStr for Cache {
    type Err = String;

    /// `dataset`, `off`, or a directory.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "" => Err("--cache must be dataset, off or a directory".into()),
            "dataset" => Ok(Cache::Dataset),
            "off" => Ok(Cache::Off),
            dir => Ok(Cache::Dir(dir.into())),
        }
    }
}

impl Cache {
    /// The directory caches live in for dataset `ds`; `None` when off.
    pub fn root(&self, ds: &Dataset) -> Option<PathBuf> {
        match self {
            Cache::Dataset => Some(ds.dir.join(CACHE_DIR)),
            Cache::Dir(d) => Some(d.clone()),
            Cache::Off => None,
        }
    }
}

/// The extraction settings a store depends on (spot detection and the sample rules), as the
/// JSON its key records.
pub fn extraction_options(opts: &PipelineOptions) -> serde_json::Value {
    serde_json::json!({ "spot": opts.spot, "samples": opts.samples })
}

/// The lattice points a fit of `frames` samples alpha at (section 5's "higher resolution
/// texture", [`super::lattice`]): each face's level by [`face_levels`] over the views (camera,
/// turntable angle) of the frames, the points between the corners (a corner is a vertex, whose
/// alpha the fit rounds give). `None` when the lattice is off.
pub fn fit_points(ctx: &Context, frames: &[usize]) -> Option<StorePoints> {
    let max_level = ctx.opts.alpha_lattice.max_level()?;
    let views: Vec<(&Camera, f64)> = views_of(ctx.ds, frames)
        .keys()
        .map(|&(c, d)| (ctx.camera(c), f64::from_bits(d)))
        .collect();
    let levels = face_levels(&ctx.scene, &views, ctx.opts.samples.cos_min, max_level);
    let pts = SurfacePoints::lattice(&ctx.ds.mesh, &levels).ok()?;
    let mut which = Vec::new();
    for (f, &k) in levels.iter().enumerate() {
        let start = pts.face_points(f).start;
        for (n, i, j) in points(k) {
            if !is_corner(k, i, j) {
                which.push((start + n) as u32);
            }
        }
    }
    Some(StorePoints {
        levels,
        points: pts,
        which,
        // Eq. 6 takes only samples above t2 (the lattice pass's window).
        min_value: ctx.opts.alpha_window.t2,
    })
}

/// The frames of `frames` per view (camera, turntable angle bits), each view's in the order given.
fn views_of(ds: &Dataset, frames: &[usize]) -> BTreeMap<(usize, u64), Vec<usize>> {
    let mut by_view: BTreeMap<(usize, u64), Vec<usize>> = BTreeMap::new();
    for &k in frames {
        if let Some(f) = ds.spec.frames.get(k) {
            by_view
                .entry((f.camera, f.turntable_deg.to_bits()))
                .or_default()
                .push(k);
        }
    }
    by_view
}

/// The store of frames `frames` (each decoded once), with samples at `points` besides the
/// vertices: opened from the cache when one serves, else extracted and (by `store`) cached.
pub fn extract(
    ctx: &Context,
    frames: &[usize],
    points: Option<StorePoints>,
    store: &StoreOptions,
    progress: &dyn Progress,
) -> Result<SampleStore, PipelineError> {
    let clock = std::time::Instant::now();
    let ds = ctx.ds;
    if let Some(&k) = frames.iter().find(|&&k| k >= ds.spec.frames.len()) {
        return Err(PipelineError::Invalid(format!(
            "frame {k} requested, the dataset has {}",
            ds.spec.frames.len()
        )));
    }
    let key = ExtractionKey::new(
        ds,
        frames,
        extraction_options(&ctx.opts),
        points.as_ref().map(StorePoints::digest),
    )
    .map_err(|e| PipelineError::Invalid(e.to_string()))?;
    let root = store.cache.root(ds);
    if let Some(root) = &root {
        match crate::store::arrow::open(root, &key, &ds.mesh, ds.spec.frames.len(), store.budget) {
            Ok(Some(mut s)) => {
                s.set_seconds(clock.elapsed().as_secs_f64());
                return Ok(s);
            }
            Ok(None) => {}
            // A cache that cannot be read is rebuilt, never trusted.
            Err(e) => progress.println(&format!("ignoring the sample cache: {e}")),
        }
    }
    let target = match root {
        Some(r) => Target::Cache(r),
        None => Target::Scratch("--cache off".into()),
    };
    let writer = Writer::create(target, &key, points.is_some())?;
    let mut builder = StoreBuilder::new(
        key,
        ds.spec.frames.len(),
        points,
        store.budget,
        Some(writer),
    );
    progress.start("extract", frames.len() as u64);
    let threads = rayon::current_num_threads().max(1);
    for ((cam, deg), view) in views_of(ds, frames) {
        let deg = f64::from_bits(deg);
        let visible = builder.points().map(|p| {
            ctx.scene.visible_points_of(
                &p.points,
                &p.which,
                ctx.camera(cam),
                deg,
                ctx.opts.samples.cos_min,
            )
        });
        // A few frames per worker at a time: their samples wait for the (sequential) store.
        for chunk in view.chunks(2 * threads) {
            let out: Vec<Extracted> = chunk
                .par_iter()
                .map(|&k| {
                    let x = extract_frame(ctx, k, builder.points(), visible.as_deref());
                    progress.inc(1);
                    x
                })
                .collect();
            for x in out {
                builder.push(x, &ds.mesh.positions)?;
            }
        }
    }
    let mut held = builder.finish()?;
    held.set_seconds(clock.elapsed().as_secs_f64());
    Ok(held)
}

/// One frame: decoded, registered and, when registered, sampled at the vertices and at `points`
/// (of which `visible` are seen from its view).
pub fn extract_frame(
    ctx: &Context,
    k: usize,
    points: Option<&StorePoints>,
    visible: Option<&[Visible]>,
) -> Extracted {
    match ctx.ds.read_frame(k) {
        Ok(img) => extract_image(ctx, k, &img, points, visible),
        Err(e) => Extracted {
            record: FrameRecord {
                frame: k,
                outcome: Err(e.to_string()),
                spot: None,
                counts: Default::default(),
            },
            vertices: None,
            points: None,
            tangent: None,
        },
    }
}

/// [`extract_frame`] of an image already in memory (`subsurf scan` as frames arrive).
pub fn extract_image(
    ctx: &Context,
    k: usize,
    img: &Image,
    points: Option<&StorePoints>,
    visible: Option<&[Visible]>,
) -> Extracted {
    let (outcome, detected) = ctx.register_image(img, k);
    let mut x = Extracted {
        record: FrameRecord {
            frame: k,
            outcome: Ok(outcome),
            spot: detected,
            counts: Default::default(),
        },
        vertices: None,
        points: None,
        tangent: None,
    };
    let RegistrationOutcome::Registered {
        x_i,
        triangle,
        spot,
        ..
    } = outcome
    else {
        return x;
    };
    let (v, vc) = ctx.vertex_samples(img, k, x_i, &spot);
    x.vertices = Some(v);
    x.record.counts[0] = vc;
    if let (Some(p), Some(vis)) = (points, visible) {
        let (mut s, c) = ctx.surface_samples(img, k, x_i, &spot, &p.points, vis);
        p.keep(&mut s);
        x.points = Some(s);
        x.record.counts[1] = c;
    }
    x.tangent = TangentFrame::from_normal(ctx.normal_at(triangle, x_i)).ok();
    x
}

/// Decodes every frame of `frames` once, in parallel, and drops it: the physical limit of any
/// processing of the frames, which `subsurf bench one-pass` compares a fit with. Returns the
/// frames decoded and the pixels they held.
pub fn decode_pass(ds: &Dataset, frames: &[usize], progress: &dyn Progress) -> (usize, u64) {
    progress.start("decode", frames.len() as u64);
    frames
        .par_iter()
        .map(|&k| {
            let n = ds.read_frame(k).map_or(0, |img| img.data.len() as u64);
            progress.inc(1);
            (usize::from(n > 0), n)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}
