//! The sample store: what one read of the frames yields, kept so that no later stage reads a
//! frame again (`docs/sample-store.md`).
//!
//! Why: every pass of the pipeline (the fit rounds, alpha, the lattice, the error, the held-out
//! frames of `--validate`) needs the same per-frame samples s(x_i, x_o), and decoding a frame costs
//! far more than any of them (a 1024 × 1024 float EXR is 12 MB). The store holds, per frame, what
//! registration concluded (x_i and the spot, or why not) and, per registered frame, its samples at
//! the vertices and, when alpha is fitted finer than the mesh, at the lattice points
//! ([`crate::samples::frame_samples`], the one sampling rule). The one pass that fills it is
//! [`crate::pipeline::extract`].
//!
//! It stays in memory up to a byte budget; the frames beyond it live only in the store's Arrow IPC
//! files on disk (spilled) and are read back per use, which costs a copy, not a decode. The files
//! are also the cache: a later run with the same frames (same files, same `scan.json` entries)
//! and the same extraction options opens them instead of decoding the frames ([`arrow::open`]).
//!
//! Owns no sampling rule and no fit; never decodes an image.
use std::path::PathBuf;
use std::sync::Arc;

use crate::geometry::{SurfacePoints, V3};
use crate::model::TangentFrame;
use crate::samples::{Sample, SampleCounts};
use crate::spot::RegistrationOutcome;

pub mod arrow;
mod key;

pub use key::{EXTRACTION_RULES, ExtractionKey, FileIdentity, FrameIdentity, StoreKeyError};

/// The default memory budget of a store, bytes: with the rest of a fit (mesh, BVH, visibility
/// caches, the lattice's accumulators and a few frames' contributions, a few decoded frames) a
/// fit's peak RSS stays under 1 GB at any frame count. Measured on 900 frames of 1024x1024 px,
/// 20,000 vertices, 139 M lattice samples: 512 MiB gave a peak of 1,101 MiB (326 MiB besides the
/// store after extraction, 240 MiB more in the lattice stage), so 256 (BENCHMARKS.md).
pub const DEFAULT_BUDGET: usize = 256 << 20;

/// The samples of one frame at one point set (the vertices, or the lattice points).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameSamples {
    /// The samples, in the point set's visibility order (as [`crate::samples::frame_samples`]
    /// returns them); shared with the store, not copied.
    pub samples: Arc<Vec<Sample>>,
    /// Why channel samples were dropped.
    pub counts: SampleCounts,
}

/// What one read of a frame concluded.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    /// Index of the frame in `scan.json`.
    pub frame: usize,
    /// Registration's outcome, or why the image could not be read.
    pub outcome: Result<RegistrationOutcome, String>,
    /// The spot detected in the image, whatever the mesh made of it
    /// ([`crate::spot::register_frame_detected`]).
    pub spot: Option<crate::spot::Spot>,
    /// Why channel samples were dropped, at the vertices and at the lattice points.
    pub counts: [SampleCounts; 2],
}

/// Which surface points besides the vertices a store holds samples at: a per-face lattice of
/// levels `levels` ([`SurfacePoints::lattice`]), of whose points only `which` are sampled.
#[derive(Debug, Clone, PartialEq)]
pub struct StorePoints {
    /// Per face, its lattice level.
    pub levels: Vec<u8>,
    /// The lattice.
    pub points: SurfacePoints,
    /// Indices into `points` of the points sampled (ascending).
    pub which: Vec<u32>,
    /// A channel sample at or below this value is not kept (0: all are). The fit's lattice
    /// keeps only what Eq. 6's window can take (above t2, [`crate::model::IntensityWindow`]):
    /// at a lattice fine enough to resolve pixels most samples are points, and those below t2
    /// are a large share of them (the outer ring of the fall-off) that no stage would read.
    pub min_value: f64,
}

impl StorePoints {
    /// The lattice of `levels` on `mesh`, sampled at `which` (`None`: every point).
    pub fn new(
        mesh: &crate::dataset::Mesh,
        levels: Vec<u8>,
        which: Option<Vec<u32>>,
    ) -> Result<StorePoints, crate::lattice::LatticeError> {
        let points = SurfacePoints::lattice(mesh, &levels)?;
        let which = which.unwrap_or_else(|| (0..points.len() as u32).collect());
        Ok(StorePoints {
            levels,
            points,
            which,
            min_value: 0.0,
        })
    }

    /// CRC-64 of the levels, the points sampled and `min_value`: the store key's `lattice`.
    pub fn digest(&self) -> String {
        key::digest_words(
            self.levels
                .iter()
                .map(|&k| u64::from(k))
                .chain(std::iter::once(u64::MAX))
                .chain(self.which.iter().map(|&p| u64::from(p)))
                .chain(std::iter::once(self.min_value.to_bits())),
        )
    }
}

/// Which point set of a store.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PointSet {
    /// The mesh's vertices (`Sample::vertex` is the vertex).
    Vertices,
    /// The store's lattice points (`Sample::vertex` indexes [`StorePoints::points`]).
    Lattice,
}

/// Where one frame's samples at one point set are.
#[derive(Debug, Clone)]
enum Slot {
    /// Not sampled (the frame is not registered).
    Empty,
    /// In memory, as the samples (the vertices: every fit round reads them).
    Samples(Arc<Vec<Sample>>),
    /// In memory, packed (the lattice points: read once, and many).
    Packed(Arc<Packed>),
    /// Only on disk: this batch of the point set's file.
    Spilled(usize),
}

impl Slot {
    /// Bytes held in memory.
    fn bytes(&self) -> usize {
        match self {
            Slot::Samples(s) => s.len() * std::mem::size_of::<Sample>(),
            Slot::Packed(p) => p.bytes(),
            Slot::Empty | Slot::Spilled(_) => 0,
        }
    }
}

/// One frame's samples without their distances (recomputed from x_i and the points, exactly as
/// [`crate::samples::frame_samples`] measured them) and without the channels they lack: about
/// 30 bytes a sample against [`Sample`]'s 48, for the lattice points, where nearly all samples
/// are.
#[derive(Debug, Clone, PartialEq)]
struct Packed {
    point: Vec<u32>,
    valid: Vec<u8>,
    /// The valid channels' values, sample after sample, in channel order.
    value: Vec<f64>,
}

impl Packed {
    fn of(s: &[Sample]) -> Packed {
        let mut p = Packed {
            point: Vec::with_capacity(s.len()),
            valid: Vec::with_capacity(s.len()),
            value: Vec::with_capacity(s.len() * 3),
        };
        for x in s {
            p.point.push(x.vertex);
            p.valid.push(x.valid);
            for c in 0..3 {
                if x.valid & (1 << c) != 0 {
                    p.value.push(x.value[c]);
                }
            }
        }
        p.value.shrink_to_fit();
        p
    }

    fn bytes(&self) -> usize {
        self.point.len() * 5 + self.value.len() * 8
    }

    /// The samples, r = |x_o − x_i| with x_o from `positions`.
    fn unpack(&self, positions: &[V3], x_i: V3) -> Vec<Sample> {
        let mut values = self.value.iter();
        self.point
            .iter()
            .zip(&self.valid)
            .map(|(&p, &valid)| {
                let mut x = Sample {
                    vertex: p,
                    r: positions
                        .get(p as usize)
                        .map_or(f64::NAN, |&x_o| crate::geometry::dist(x_o, x_i)),
                    value: [0.0; 3],
                    valid,
                };
                for c in 0..3 {
                    if valid & (1 << c) != 0 {
                        x.value[c] = values.next().copied().unwrap_or(f64::NAN);
                    }
                }
                x
            })
            .collect()
    }
}

/// How the store came to be (`fit-report.json`: `sample_store`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct StoreReport {
    /// Frames decoded to fill it (0 when it was opened from the cache).
    pub frames_decoded: usize,
    /// Frames it holds.
    pub frames: usize,
    /// Vertex samples (one per (frame, vertex) with a usable channel).
    pub vertex_samples: u64,
    /// Lattice point samples.
    pub point_samples: u64,
    /// Bytes of samples held in memory.
    pub memory_bytes: usize,
    /// The memory budget, bytes.
    pub budget_bytes: usize,
    /// Frame sample sets (of either point set) kept only on disk because the budget was reached.
    pub spilled: usize,
    /// The directory of its Arrow files, if written.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dir: Option<PathBuf>,
    /// Opened from the cache (`true`), or extracted by this run.
    pub from_cache: bool,
    /// Why the store is not kept as the dataset's cache, if it is not (`--cache off`, a
    /// read-only dataset).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub not_cached: Option<String>,
    /// Why a cache of the same options was not used (it could not be read), if one was not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_rejected: Option<String>,
    /// Wall time of filling it (the one pass over the frames) or opening it, seconds.
    pub seconds: f64,
}

/// Why the store could not be read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// A file of the store could not be read or written.
    #[error("sample store {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A file of the store is malformed.
    #[error("sample store {path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A frame was asked for that the store does not hold, or added twice.
    #[error("frame {0} is not in the sample store, or was added twice")]
    Frame(usize),
}

/// Per frame of a run: what registration concluded, and its samples.
#[derive(Debug)]
pub struct SampleStore {
    key: ExtractionKey,
    records: Vec<FrameRecord>,
    /// Record index per dataset frame (`u32::MAX`: not held).
    index: Vec<u32>,
    vertices: Vec<Slot>,
    /// The lattice points (shared with the extraction that samples at them while this store
    /// is filled, [`StoreBuilder::shared_points`]) and each record's slot.
    points: Option<(Arc<StorePoints>, Vec<Slot>)>,
    files: Option<arrow::Files>,
    report: StoreReport,
}

/// One frame's contribution while a store is filled ([`StoreBuilder::push`]).
#[derive(Debug, Clone)]
pub struct Extracted {
    /// What the read concluded.
    pub record: FrameRecord,
    /// Samples at the vertices (registered frames only).
    pub vertices: Option<Vec<Sample>>,
    /// Samples at the store's lattice points (registered frames, when it has a lattice).
    pub points: Option<Vec<Sample>>,
    /// The tangent frame at x_i's own normal: the files give each sample's direction φ around
    /// x_i in it (Eq. 3), for people reading them; the fit measures φ in its group's frame.
    pub tangent: Option<TangentFrame>,
}

/// Fills a [`SampleStore`] frame by frame within the memory budget: once it is reached, a frame's
/// samples go only to the store's files ([`arrow::Writer`]), every frame's go there too.
pub struct StoreBuilder {
    store: SampleStore,
    writer: Option<arrow::Writer>,
}

impl StoreBuilder {
    /// An empty store for a dataset of `dataset_frames` frames, extracted under `key`, with the
    /// lattice `points` (if any), `budget` bytes of memory for samples, writing its files with
    /// `writer` (`None`: memory only, and the budget cannot be enforced).
    pub fn new(
        key: ExtractionKey,
        dataset_frames: usize,
        points: Option<StorePoints>,
        budget: usize,
        writer: Option<arrow::Writer>,
    ) -> StoreBuilder {
        StoreBuilder {
            store: SampleStore {
                key,
                records: Vec::new(),
                index: vec![u32::MAX; dataset_frames],
                vertices: Vec::new(),
                points: points.map(|p| (Arc::new(p), Vec::new())),
                files: None,
                report: StoreReport {
                    budget_bytes: budget,
                    ..StoreReport::default()
                },
            },
            writer,
        }
    }

    /// The lattice points the store samples, if any.
    pub fn points(&self) -> Option<&StorePoints> {
        self.store.points.as_ref().map(|(p, _)| &**p)
    }

    /// [`StoreBuilder::points`] as a handle of their own: the extraction samples at them while
    /// the builder, borrowed mutably by the worker that writes the store, adds the frames before
    /// ([`crate::pipeline::extract`]). Shared, never copied (a lattice at 1024 px holds
    /// millions of points).
    pub fn shared_points(&self) -> Option<Arc<StorePoints>> {
        self.store.points.as_ref().map(|(p, _)| Arc::clone(p))
    }

    /// Whether frame `k` was added.
    pub fn holds(&self, k: usize) -> bool {
        self.store.record(k).is_some()
    }

    /// The key the store is filled under.
    pub fn key(&self) -> &ExtractionKey {
        &self.store.key
    }

    /// Sets the store's key: a store filled while its frames were still being written learns
    /// their identities on disk at the end ([`StoreBuilder::finish`] names the cache by them).
    pub fn set_key(&mut self, key: ExtractionKey) {
        self.store.key = key;
    }

    /// Adds one frame (in any order; each frame once). `positions` are the mesh's vertices.
    pub fn push(&mut self, x: Extracted, positions: &[V3]) -> Result<(), StoreError> {
        let k = x.record.frame;
        match self.store.index.get_mut(k) {
            Some(slot) if *slot == u32::MAX => *slot = self.store.records.len() as u32,
            _ => return Err(StoreError::Frame(k)),
        }
        let placed = match &mut self.writer {
            Some(w) => {
                let pts = self
                    .store
                    .points
                    .as_ref()
                    .map(|(p, _)| &p.points.positions[..]);
                w.push(&x, positions, pts)?
            }
            None => [None, None],
        };
        let rep = &mut self.store.report;
        rep.frames += 1;
        rep.frames_decoded += 1;
        rep.vertex_samples += x.vertices.as_ref().map_or(0, |s| s.len() as u64);
        rep.point_samples += x.points.as_ref().map_or(0, |s| s.len() as u64);
        let v = x.vertices.map(|s| Slot::Samples(Arc::new(s)));
        let v = self.place(v, placed[0], true);
        self.store.vertices.push(v);
        if self.store.points.is_some() {
            let p = x.points.map(|s| Slot::Packed(Arc::new(Packed::of(&s))));
            let p = self.place(p, placed[1], false);
            if let Some((_, slots)) = &mut self.store.points {
                slots.push(p);
            }
        }
        self.store.records.push(x.record);
        Ok(())
    }

    /// Where a frame's samples go: memory while the budget lasts, else only the files (batch
    /// `batch`; without files, memory regardless). The vertices' samples, which every fit round
    /// reads, take the place of lattice points' already in memory (those are read once).
    fn place(&mut self, slot: Option<Slot>, batch: Option<usize>, vertices: bool) -> Slot {
        let Some(slot) = slot else {
            return Slot::Empty;
        };
        let bytes = slot.bytes();
        let rep = &mut self.store.report;
        let Some(b) = batch else {
            rep.memory_bytes += bytes;
            return slot;
        };
        if vertices && rep.memory_bytes + bytes > rep.budget_bytes {
            let (files, points) = (&self.writer, &mut self.store.points);
            if let (Some(w), Some((_, slots))) = (files, points) {
                for (i, s) in slots.iter_mut().enumerate().rev() {
                    if rep.memory_bytes + bytes <= rep.budget_bytes {
                        break;
                    }
                    if let (Slot::Packed(_), Some(pb)) = (&*s, w.batch_of(PointSet::Lattice, i)) {
                        rep.memory_bytes -= s.bytes();
                        rep.spilled += 1;
                        *s = Slot::Spilled(pb);
                    }
                }
            }
        }
        if rep.memory_bytes + bytes > rep.budget_bytes {
            rep.spilled += 1;
            Slot::Spilled(b)
        } else {
            rep.memory_bytes += bytes;
            slot
        }
    }

    /// The filled store; its files are finished (a cache is complete only now).
    pub fn finish(mut self) -> Result<SampleStore, StoreError> {
        if let Some(w) = self.writer {
            let files = w.finish(
                &self.store.key,
                &self.store.records,
                self.store.points.as_ref().map(|(p, _)| &**p),
            )?;
            self.store.report.dir = Some(files.dir().to_path_buf());
            self.store.report.not_cached = files.not_cached().map(str::to_owned);
            self.store.files = Some(files);
        }
        Ok(self.store)
    }
}

impl SampleStore {
    /// The extraction options and frames the store was filled under.
    pub fn key(&self) -> &ExtractionKey {
        &self.key
    }

    /// How the store came to be.
    pub fn report(&self) -> &StoreReport {
        &self.report
    }

    /// Records the wall time it took to fill or open the store.
    pub fn set_seconds(&mut self, seconds: f64) {
        self.report.seconds = seconds;
    }

    /// Records why a cache of the same options was not used ([`StoreReport::cache_rejected`]).
    pub fn set_cache_rejected(&mut self, why: Option<String>) {
        self.report.cache_rejected = why;
    }

    /// Every frame's record, in the order the frames were added.
    pub fn records(&self) -> &[FrameRecord] {
        &self.records
    }

    /// The record of dataset frame `k`, if the store holds it.
    pub fn record(&self, k: usize) -> Option<&FrameRecord> {
        let i = *self.index.get(k)?;
        self.records.get(i as usize)
    }

    /// Whether the store holds every frame of `frames`.
    pub fn holds(&self, frames: &[usize]) -> bool {
        frames.iter().all(|&k| self.record(k).is_some())
    }

    /// The lattice points the store holds samples at, if any.
    pub fn points(&self) -> Option<&StorePoints> {
        self.points.as_ref().map(|(p, _)| &**p)
    }

    /// The samples of dataset frame `k` at point set `set`; `Ok(None)` when the frame is held but
    /// was not sampled (not registered), or the store has no such point set.
    pub fn samples(&self, k: usize, set: PointSet) -> Result<Option<FrameSamples>, StoreError> {
        let Some(&i) = self.index.get(k).filter(|&&i| i != u32::MAX) else {
            return Err(StoreError::Frame(k));
        };
        let i = i as usize;
        let slot = match set {
            PointSet::Vertices => &self.vertices[i],
            PointSet::Lattice => match &self.points {
                Some((_, slots)) => &slots[i],
                None => return Ok(None),
            },
        };
        let samples = match slot {
            Slot::Empty => return Ok(None),
            Slot::Samples(s) => s.clone(),
            Slot::Packed(p) => {
                let (pts, x_i) = self.lattice_frame(i).ok_or(StoreError::Frame(k))?;
                Arc::new(p.unpack(pts, x_i))
            }
            Slot::Spilled(batch) => match &self.files {
                Some(f) => {
                    let at = match set {
                        PointSet::Vertices => None,
                        PointSet::Lattice => self.lattice_frame(i),
                    };
                    Arc::new(f.read_batch(set, *batch, at)?)
                }
                None => return Err(StoreError::Frame(k)),
            },
        };
        let counts = self.records[i].counts[(set == PointSet::Lattice) as usize];
        Ok(Some(FrameSamples { samples, counts }))
    }

    /// The lattice points' positions and record `i`'s x_i.
    fn lattice_frame(&self, i: usize) -> Option<(&[V3], V3)> {
        let pts = &self.points.as_ref()?.0.points.positions;
        match self.records.get(i)?.outcome {
            Ok(RegistrationOutcome::Registered { x_i, .. }) => Some((pts, x_i)),
            _ => None,
        }
    }

    /// A store opened from its files ([`arrow::open`]), frames loaded into memory while the
    /// budget lasts.
    pub(crate) fn from_files(
        key: ExtractionKey,
        dataset_frames: usize,
        records: Vec<FrameRecord>,
        points: Option<StorePoints>,
        files: arrow::Files,
        budget: usize,
    ) -> Result<SampleStore, StoreError> {
        let mut index = vec![u32::MAX; dataset_frames];
        for (i, r) in records.iter().enumerate() {
            match index.get_mut(r.frame) {
                Some(slot) if *slot == u32::MAX => *slot = i as u32,
                _ => return Err(StoreError::Frame(r.frame)),
            }
        }
        let mut report = StoreReport {
            frames: records.len(),
            budget_bytes: budget,
            dir: Some(files.dir().to_path_buf()),
            from_cache: true,
            ..StoreReport::default()
        };
        let load = |set: PointSet, report: &mut StoreReport| {
            let batches = files.batches(set);
            let mut slots = Vec::with_capacity(records.len());
            for i in 0..records.len() {
                let Some(b) = batches.get(i).copied().flatten() else {
                    slots.push(Slot::Empty);
                    continue;
                };
                let (n, bytes) = files.batch_size(set, b);
                match set {
                    PointSet::Vertices => report.vertex_samples += n as u64,
                    PointSet::Lattice => report.point_samples += n as u64,
                }
                if report.memory_bytes + bytes > budget {
                    report.spilled += 1;
                    slots.push(Slot::Spilled(b));
                    continue;
                }
                // A cache holds r (its lattice is never compact).
                let s = files.read_batch(set, b, None)?;
                let slot = match set {
                    PointSet::Vertices => Slot::Samples(Arc::new(s)),
                    PointSet::Lattice => Slot::Packed(Arc::new(Packed::of(&s))),
                };
                report.memory_bytes += slot.bytes();
                slots.push(slot);
            }
            Ok::<_, StoreError>(slots)
        };
        let vertices = load(PointSet::Vertices, &mut report)?;
        let points = match points {
            Some(p) => Some((Arc::new(p), load(PointSet::Lattice, &mut report)?)),
            None => None,
        };
        Ok(SampleStore {
            key,
            records,
            index,
            vertices,
            points,
            files: Some(files),
            report,
        })
    }
}
