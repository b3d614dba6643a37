//! Stage `extract` (section 5: "the acquired data"): every frame decoded once, registered
//! (sections 4.1, 5: the spot and x_i) and sampled at the vertices and at the lattice points of
//! alpha finer than the mesh, into the run's [`SampleStore`]. No later stage reads a frame: the
//! fit rounds, alpha, the lattice, the error and the held-out frames of `--validate` all read the
//! store.
//!
//! One streaming, parallel pass: frames are taken view by view (camera, turntable angle), so the
//! lattice points' visibility is cast once per view and dropped with it, and within a view a few
//! frames per worker at a time, so memory holds a handful of decoded images, never the scan; each
//! chunk's samples go to the store while the next chunk is taken, in the order taken. A
//! store cached in the dataset by an earlier run (or by `subsurf scan`, which extracts each frame
//! as it arrives) with the same frames and extraction options is opened instead.
use std::collections::BTreeMap;
use std::path::PathBuf;

use rayon::prelude::*;

use crate::dataset::{Dataset, FrameSpec, Image};
use crate::geometry::{Camera, SurfacePoints, Visible};
use crate::lattice::{is_corner, points};
use crate::model::TangentFrame;
use crate::progress::Progress;
use crate::spot::RegistrationOutcome;
use crate::store::arrow::{CACHE_DIR, Target, Writer};
use crate::store::{
    Extracted, ExtractionKey, FrameRecord, SampleStore, StoreBuilder, StoreError, StorePoints,
};

use super::detail::face_levels;
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

impl StoreOptions {
    /// The default memory budget with the store's files in `cache`.
    pub fn cached(cache: Cache) -> StoreOptions {
        StoreOptions {
            cache,
            ..Default::default()
        }
    }
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
/// JSON text its key records.
pub fn extraction_options(opts: &PipelineOptions) -> String {
    serde_json::json!({ "spot": opts.spot, "samples": opts.samples }).to_string()
}

/// The lattice points a fit of `frames` samples alpha at (section 5's "higher resolution
/// texture", [`super::detail`]): each face's level by [`face_levels`] over the views (camera,
/// turntable angle) of the frames, the points between the corners (a corner is a vertex, whose
/// alpha the fit rounds give). `None` when the lattice is off.
pub fn fit_points(ctx: &Context, frames: &[usize]) -> Option<StorePoints> {
    let views: Vec<(usize, f64)> = views_of(ctx.ds, frames)
        .keys()
        .map(|&(c, d)| (c, f64::from_bits(d)))
        .collect();
    lattice_points(ctx, &views)
}

/// [`fit_points`] of the frames seen from `views` (camera, turntable angle).
pub fn lattice_points(ctx: &Context, views: &[(usize, f64)]) -> Option<StorePoints> {
    let max_level = ctx.opts.alpha_lattice.max_level()?;
    let views: Vec<(&Camera, f64)> = views.iter().map(|&(c, d)| (ctx.camera(c), d)).collect();
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
    let mut rejected = None;
    if let Some(root) = &root {
        match crate::store::arrow::open(root, &key, &ds.mesh, ds.spec.frames.len(), store.budget) {
            Ok(Some(mut s)) => {
                s.set_seconds(clock.elapsed().as_secs_f64());
                return Ok(s);
            }
            Ok(None) => {}
            // A cache that cannot be read is rebuilt, never trusted; the report says why.
            Err(e) => {
                progress.println(&format!("ignoring the sample cache: {e}"));
                rejected = Some(e.to_string());
            }
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
    let points = builder.shared_points();
    let positions = &ds.mesh.positions[..];
    // The store is written while the workers take the next frames: in line, its Arrow batches
    // (the φ of every sample, the IPC encoding) held every worker idle, ~10 % of a fit's CPU at
    // 1024 px. Each chunk is pushed by one worker (`rayon::join`) while the others, and that one
    // once done, extract the next: one chunk more in memory than a serial pass, chunks pushed
    // in the order taken, so the store is the same bytes. On the pool's own workers, not a
    // thread of its own: a writer thread's allocator arena kept ~50 MB more resident through
    // the fit (glibc, measured at 1024 px).
    let mut pending: Vec<Extracted> = Vec::new();
    let push = |builder: &mut StoreBuilder, xs: Vec<Extracted>| -> Result<(), StoreError> {
        xs.into_iter().try_for_each(|x| builder.push(x, positions))
    };
    for ((cam, deg), view) in views_of(ds, frames) {
        let deg = f64::from_bits(deg);
        let (pushed, visible) = rayon::join(
            || push(&mut builder, std::mem::take(&mut pending)),
            || {
                points.as_deref().map(|p| {
                    ctx.scene.visible_points_of(
                        &p.points,
                        &p.which,
                        ctx.camera(cam),
                        deg,
                        ctx.opts.samples.cos_min,
                    )
                })
            },
        );
        pushed?;
        // A few frames per worker at a time: their samples wait for the next chunk's push.
        for chunk in view.chunks(2 * threads) {
            let (pushed, out) = rayon::join(
                || push(&mut builder, std::mem::take(&mut pending)),
                || {
                    chunk
                        .par_iter()
                        .map(|&k| {
                            let x = extract_frame(ctx, k, points.as_deref(), visible.as_deref());
                            progress.inc(1);
                            x
                        })
                        .collect::<Vec<Extracted>>()
                },
            );
            pushed?;
            pending = out;
        }
    }
    push(&mut builder, pending)?;
    let mut held = builder.finish()?;
    held.set_seconds(clock.elapsed().as_secs_f64());
    held.set_cache_rejected(rejected);
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
        Ok(img) => extract_image(ctx, k, &ctx.ds.spec.frames[k], &img, points, visible),
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

/// [`extract_frame`] of frame `k` (its `scan.json` entry `spec`) whose image `img` is in memory
/// already (`subsurf scan`, as frames arrive).
pub fn extract_image(
    ctx: &Context,
    k: usize,
    spec: &FrameSpec,
    img: &Image,
    points: Option<&StorePoints>,
    visible: Option<&[Visible]>,
) -> Extracted {
    let (outcome, detected) = ctx.register_image(img, spec);
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
    let (v, vc) = ctx.vertex_samples(img, spec, x_i, &spot);
    x.vertices = Some(v);
    x.record.counts[0] = vc;
    if let (Some(p), Some(vis)) = (points, visible) {
        let (s, c) = ctx.surface_samples(img, spec, x_i, &spot, p, vis);
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

/// The extraction pass run while a scan is captured (`subsurf scan`): each frame, as it is
/// committed, goes to a worker thread that registers and samples it from the image in memory
/// into a sample store, with the options a later `subsurf fit` of the whole scan uses by default;
/// when the scan ends the store is cached in the dataset, so that fit starts from it.
///
/// The scan never waits for it: a frame that arrives while the worker is a few frames behind is
/// read back from its file at the end instead (as are frames of an earlier, resumed run). Any
/// failure leaves the dataset without a cache and is reported, never fails the scan.
pub struct ScanExtraction {
    store: StoreOptions,
    tx: Option<std::sync::mpsc::SyncSender<(usize, FrameSpec, Image)>>,
    worker: Option<std::thread::JoinHandle<Result<String, String>>>,
    failed: Option<String>,
}

impl ScanExtraction {
    /// A sink for `subsurf scan` with the store's settings `store`.
    pub fn new(store: StoreOptions) -> ScanExtraction {
        ScanExtraction {
            store,
            tx: None,
            worker: None,
            failed: None,
        }
    }
}

/// `x` as it reads back from its JSON in `scan.json`.
fn as_read_back<T: serde::Serialize + serde::de::DeserializeOwned>(x: &T) -> Option<T> {
    serde_json::from_str(&serde_json::to_string(x).ok()?).ok()
}

/// Frames the worker may be behind before the scan stops waiting for it.
const SCAN_QUEUE: usize = 4;

impl crate::scan::driver::FrameSink for ScanExtraction {
    fn begin(
        &mut self,
        dir: &std::path::Path,
        header: &crate::dataset::ScanSpec,
        frames: usize,
        views: &[(usize, f64)],
    ) {
        let mesh_path = match crate::dataset::confined_path(dir, &header.mesh) {
            Ok(p) => p,
            Err(e) => {
                self.failed = Some(e.to_string());
                return;
            }
        };
        let (mesh, mesh_report) = match crate::dataset::load_obj(&mesh_path) {
            Ok(m) => m,
            Err(e) => {
                self.failed = Some(format!("{}: {e}", mesh_path.display()));
                return;
            }
        };
        let (tx, rx) = std::sync::mpsc::sync_channel(SCAN_QUEUE);
        // What a later `subsurf fit` reads back from scan.json (JSON need not round-trip a
        // number to the bit), so that this store is the one it would extract.
        let Some(mut spec) = as_read_back(header) else {
            self.failed = Some("the scan's header does not read back".into());
            return;
        };
        spec.frames.clear();
        let planned = Dataset::in_progress(dir.to_path_buf(), spec, mesh, mesh_report);
        let views = views.to_vec();
        let store = self.store.clone();
        self.tx = Some(tx);
        self.worker = Some(std::thread::spawn(move || {
            scan_worker(planned, frames, &views, &store, rx)
        }));
    }

    fn frame(&mut self, k: usize, entry: &FrameSpec, image: Image) {
        if let Some(tx) = &self.tx
            && let Some(entry) = as_read_back(entry)
            && tx.try_send((k, entry, image)).is_err()
        {
            // The worker is behind (or gone): the frame is read back from its file at the end.
        }
    }

    fn finish(&mut self) -> Result<String, String> {
        if let Some(why) = self.failed.take() {
            return Err(why);
        }
        self.tx = None;
        match self.worker.take() {
            Some(w) => w
                .join()
                .map_err(|_| "the extraction thread panicked".to_string())?,
            None => Err("the extraction never started".into()),
        }
    }
}

/// The worker of [`ScanExtraction`]: extracts what arrives on `rx` from the images in memory,
/// then, once the scan is complete, the frames it did not get from their files, and caches the
/// store under the key a later `subsurf fit` of all frames asks for.
fn scan_worker(
    planned: Dataset,
    frames: usize,
    views: &[(usize, f64)],
    store: &StoreOptions,
    rx: std::sync::mpsc::Receiver<(usize, FrameSpec, Image)>,
) -> Result<String, String> {
    let clock = std::time::Instant::now();
    let opts = PipelineOptions::for_dataset(&planned);
    let ctx = Context::new(&planned, opts).map_err(|e| e.to_string())?;
    let points = lattice_points(&ctx, views);
    let digest = points.as_ref().map(StorePoints::digest);
    let key = ExtractionKey::new(&planned, &[], extraction_options(&opts), digest.clone())
        .map_err(|e| e.to_string())?;
    let root = store
        .cache
        .root(&planned)
        .ok_or("--cache off: no sample store is kept")?;
    let writer =
        Writer::create(Target::Cache(root), &key, points.is_some()).map_err(|e| e.to_string())?;
    let mut builder = StoreBuilder::new(key, frames, points, store.budget, Some(writer));
    let mut used: Vec<Option<FrameSpec>> = vec![None; frames];
    let mut visible: Option<((usize, u64), Vec<Visible>)> = None;
    let mut extract = |k: usize, spec: &FrameSpec, img: &Image, builder: &mut StoreBuilder| {
        let view = (spec.camera, spec.turntable_deg.to_bits());
        let vis = builder.points().map(|p| {
            if visible.as_ref().is_none_or(|(v, _)| *v != view) {
                let cam = ctx.camera(spec.camera);
                let pv = ctx.scene.visible_points_of(
                    &p.points,
                    &p.which,
                    cam,
                    spec.turntable_deg,
                    ctx.opts.samples.cos_min,
                );
                visible = Some((view, pv));
            }
            visible.as_ref().map_or(&[][..], |(_, v)| &v[..])
        });
        let x = extract_image(&ctx, k, spec, img, builder.points(), vis);
        builder
            .push(x, &ctx.ds.mesh.positions)
            .map_err(|e| e.to_string())
    };
    let mut live = 0usize;
    let mut ended = None;
    for (k, spec, img) in rx.iter().chain(std::iter::from_fn(|| {
        ended = Some(std::time::Instant::now());
        None
    })) {
        if k >= frames || builder.holds(k) {
            return Err(format!("frame {k} is not one of the plan's {frames}"));
        }
        extract(k, &spec, &img, &mut builder)?;
        used[k] = Some(spec);
        live += 1;
    }
    // The scan is complete: the dataset as written, and the frames the worker did not get.
    let ds = Dataset::open(&planned.dir).map_err(|e| e.to_string())?;
    if ds.spec.frames.len() != frames {
        return Err(format!(
            "the scan holds {} frames, the plan {frames}",
            ds.spec.frames.len()
        ));
    }
    if PipelineOptions::for_dataset(&ds) != opts {
        return Err("the dataset's options are not the ones extracted with".into());
    }
    for (k, f) in used.iter().enumerate() {
        if f.as_ref().is_some_and(|f| *f != ds.spec.frames[k]) {
            return Err(format!("frame {k} in scan.json is not the one extracted"));
        }
    }
    for k in 0..frames {
        if !builder.holds(k) {
            let img = ds.read_frame(k).map_err(|e| e.to_string())?;
            extract(k, &ds.spec.frames[k], &img, &mut builder)?;
        }
    }
    let all: Vec<usize> = (0..frames).collect();
    let seen: Vec<(usize, f64)> = views_of(&ds, &all)
        .keys()
        .map(|&(c, d)| (c, f64::from_bits(d)))
        .collect();
    if lattice_points(&ctx, &seen).map(|p| p.digest()) != digest {
        return Err("the scan's views are not the plan's".into());
    }
    let key = ExtractionKey::new(&ds, &all, extraction_options(&opts), digest)
        .map_err(|e| e.to_string())?;
    builder.set_key(key);
    let held = builder.finish().map_err(|e| e.to_string())?;
    let after = ended.map_or(0.0, |t| t.elapsed().as_secs_f64());
    Ok(format!(
        "sample store of {frames} frames written in {:.1} s, {after:.1} s of it after the scan's \
         end ({live} frames extracted as they arrived, {} read back from their files) in {}",
        clock.elapsed().as_secs_f64(),
        frames - live,
        held.report()
            .dir
            .as_deref()
            .map_or("-".into(), |d| d.display().to_string())
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::{simulate, top_down_slab_config};
    use crate::store::StoreError;

    /// 25 frames of one view ([`top_down_slab_config`]): several chunks of the pass.
    fn slab(dir: &std::path::Path) -> Dataset {
        simulate(&top_down_slab_config(), dir, &()).unwrap();
        Dataset::open(dir).unwrap()
    }

    /// Every file of the one store under cache root `root`, by name, with its bytes.
    fn store_files(root: &std::path::Path) -> Vec<(String, Vec<u8>)> {
        let dirs: Vec<_> = std::fs::read_dir(root)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        assert_eq!(dirs.len(), 1, "one store in {}: {dirs:?}", root.display());
        let mut files: Vec<_> = std::fs::read_dir(&dirs[0])
            .unwrap()
            .map(|e| {
                let p = e.unwrap().path();
                let name = p.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read(&p).unwrap())
            })
            .collect();
        files.sort();
        files
    }

    /// A scratch store's lattice file holds no frame, r or φ (its run measures r again from
    /// the points and x_i): spilled entirely, every frame reads back the samples a cache, which
    /// holds r, reads back, to the bit, with the same counts.
    #[test]
    fn a_scratch_store_reads_back_the_samples_a_cache_holds() {
        use crate::samples::SampleCounts;
        use crate::store::{FrameSamples, PointSet};
        let tmp = tempfile::tempdir().unwrap();
        let ds = slab(&tmp.path().join("scan"));
        let ctx = Context::new(&ds, PipelineOptions::for_dataset(&ds)).unwrap();
        let frames: Vec<usize> = (0..ds.spec.frames.len()).collect();
        let points = fit_points(&ctx, &frames);
        let spilled = |cache| StoreOptions { budget: 0, cache };
        let dir = Cache::Dir(tmp.path().join("cache"));
        let cached = extract(&ctx, &frames, points.clone(), &spilled(dir), &()).unwrap();
        let files = store_files(&tmp.path().join("cache"));
        assert!(
            files.iter().all(|(name, _)| name != ".lock"),
            "a cache holds no lock"
        );
        let scratch = extract(&ctx, &frames, points, &spilled(Cache::Off), &()).unwrap();
        assert!(scratch.report().spilled > 0 && scratch.report().memory_bytes == 0);
        type Bits = (u32, u8, u64, [u64; 3]);
        let bits = |s: Option<FrameSamples>| -> Option<(SampleCounts, Vec<Bits>)> {
            s.map(|s| {
                let v = s.samples.iter().map(|x| {
                    let value = [0, 1, 2]
                        .map(|c| (x.valid & (1 << c) != 0).then_some(x.value[c].to_bits()));
                    (
                        x.vertex,
                        x.valid,
                        x.r.to_bits(),
                        value.map(|v| v.unwrap_or(0)),
                    )
                });
                (s.counts, v.collect())
            })
        };
        let mut lattice = 0;
        for &k in &frames {
            for set in [PointSet::Vertices, PointSet::Lattice] {
                let want = bits(cached.samples(k, set).unwrap());
                let got = bits(scratch.samples(k, set).unwrap());
                if set == PointSet::Lattice {
                    lattice += want.as_ref().map_or(0, |w| w.1.len());
                }
                assert_eq!(got, want, "frame {k} {set:?}");
            }
        }
        assert!(lattice > 0, "the lattice is sampled");
    }

    /// The pass writes each chunk's samples to the store while the next chunk decodes; the
    /// frames must still reach it in the order they were taken, so its files are the bytes of a
    /// serial pass (frames taken in an order of their own, spilled beyond a small budget, so
    /// that any reordering shows in the batches, the records and the spills).
    #[test]
    fn the_overlapped_pass_writes_the_bytes_of_a_serial_pass() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = slab(&tmp.path().join("scan"));
        let opts = PipelineOptions::for_dataset(&ds);
        let ctx = Context::new(&ds, opts).unwrap();
        let n = ds.spec.frames.len();
        // Odd frames backwards, then even frames forwards: an order of its own.
        let frames: Vec<usize> = (0..n)
            .rev()
            .filter(|k| k % 2 == 1)
            .chain((0..n).filter(|k| k % 2 == 0))
            .collect();
        let points = fit_points(&ctx, &frames);
        assert!(points.is_some(), "the slab's lattice is sampled");
        let budget = 64 << 10;
        let overlapped = tmp.path().join("overlapped");
        let store = StoreOptions {
            budget,
            cache: Cache::Dir(overlapped.clone()),
        };
        let held = extract(&ctx, &frames, points.clone(), &store, &()).unwrap();
        assert_eq!(held.records().len(), frames.len());
        assert!(
            held.report().spilled > 0,
            "the budget spills: {:?}",
            held.report()
        );

        let serial = tmp.path().join("serial");
        let key = ExtractionKey::new(
            &ds,
            &frames,
            extraction_options(&opts),
            points.as_ref().map(StorePoints::digest),
        )
        .unwrap();
        let writer = Writer::create(Target::Cache(serial.clone()), &key, true).unwrap();
        let mut builder = StoreBuilder::new(key, n, points, budget, Some(writer));
        let f = &ds.spec.frames[frames[0]];
        let visible = builder.points().map(|p| {
            ctx.scene.visible_points_of(
                &p.points,
                &p.which,
                ctx.camera(f.camera),
                f.turntable_deg,
                opts.samples.cos_min,
            )
        });
        for &k in &frames {
            let x = extract_frame(&ctx, k, builder.points(), visible.as_deref());
            builder.push(x, &ds.mesh.positions).unwrap();
        }
        let reference = builder.finish().unwrap();
        assert_eq!(reference.records(), held.records());
        assert_eq!(store_files(&serial), store_files(&overlapped));
    }

    /// An error of the store's writer (here: a frame added twice) ends the pass with that error,
    /// whatever the workers were doing, and leaves no half store behind.
    #[test]
    fn the_writers_error_is_the_pass_error() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = slab(&tmp.path().join("scan"));
        let ctx = Context::new(&ds, PipelineOptions::for_dataset(&ds)).unwrap();
        let frames: Vec<usize> = (0..ds.spec.frames.len()).chain([3]).chain(0..4).collect();
        let points = fit_points(&ctx, &frames);
        let root = tmp.path().join("cache");
        let store = StoreOptions {
            budget: crate::store::DEFAULT_BUDGET,
            cache: Cache::Dir(root.clone()),
        };
        match extract(&ctx, &frames, points, &store, &()) {
            Err(PipelineError::Store(StoreError::Frame(3))) => {}
            other => panic!("expected the writer's error for frame 3, got {other:?}"),
        }
        let left: Vec<_> = std::fs::read_dir(&root).unwrap().collect();
        assert!(left.is_empty(), "a failed pass leaves no store: {left:?}");
    }
}
