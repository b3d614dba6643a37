//! The store's files: Apache Arrow IPC (the Feather 2 format), so that pandas
//! (`pd.read_feather`), polars (`pl.read_ipc`) and pyarrow open them (`docs/sample-store.md`).
//!
//! A store directory holds `manifest.json` (format, [`ExtractionKey`]), `frames.arrow` (one row
//! per frame: registration's outcome, the spot, the drop counts, the batch of its samples),
//! `vertices.arrow` and, with a lattice, `points.arrow` (one record batch per registered frame:
//! frame, vertex or point, r, φ, s per channel; a null channel was not usable) and
//! `lattice.arrow` (the lattice's levels per face and its sampled points). Batches are read back
//! one at a time (the IPC file's footer indexes them), which is how a frame beyond the memory
//! budget is read per use.
//!
//! A cache directory appears only complete: it is written under a temporary name in the same
//! parent and renamed into place after every file is synced.
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use arrow_array::cast::AsArray;
use arrow_array::types::{Float64Type, UInt8Type, UInt32Type, UInt64Type};
use arrow_array::{
    Array, ArrayRef, BooleanArray, Float64Array, RecordBatch, StringArray, UInt8Array, UInt32Array,
    UInt64Array,
};
use arrow_ipc::reader::FileReader;
use arrow_ipc::writer::FileWriter;
use arrow_schema::{DataType, Field, Schema, SchemaRef};

use super::{
    Extracted, ExtractionKey, FrameRecord, PointSet, SampleStore, StoreError, StorePoints,
};
use crate::geometry::V3;
use crate::samples::{Sample, SampleCounts};
use crate::spot::{RegistrationOutcome, Spot};

/// The `format` of a store's `manifest.json`.
pub const FORMAT: &str = "subsurf-samples/1";

/// The directory in a dataset that holds its caches.
pub const CACHE_DIR: &str = ".subsurf-cache";

const MANIFEST: &str = "manifest.json";
const FRAMES: &str = "frames.arrow";
const LATTICE: &str = "lattice.arrow";

fn file_name(set: PointSet) -> &'static str {
    match set {
        PointSet::Vertices => "vertices.arrow",
        PointSet::Lattice => "points.arrow",
    }
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn format_err(path: &Path, e: impl std::fmt::Display) -> StoreError {
    StoreError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// `manifest.json`.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct Manifest {
    format: String,
    /// The program that wrote it.
    writer: String,
    key: ExtractionKey,
    /// The lattice's [`StorePoints::min_value`], if it has one (for people; the store reads
    /// `lattice_min_value_bits`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lattice_min_value: Option<f64>,
    /// The same, its IEEE 754 bits: serde_json's default parse of a float may be one ulp off
    /// the value written, and the lattice's digest (its key) includes this value to the bit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lattice_min_value_bits: Option<u64>,
}

/// The schema of `set`'s samples; `compact`: the point and the channels only (a scratch store's
/// lattice, [`Writer::create`]).
fn sample_schema(set: PointSet, compact: bool) -> SchemaRef {
    let point = match set {
        PointSet::Vertices => "vertex",
        PointSet::Lattice => "point",
    };
    let channels = ["s_r", "s_g", "s_b"].map(|c| Field::new(c, DataType::Float64, true));
    let fields = if compact {
        [Field::new(point, DataType::UInt32, false)]
            .into_iter()
            .chain(channels)
            .collect()
    } else {
        [
            Field::new("frame", DataType::UInt32, false),
            Field::new(point, DataType::UInt32, false),
            Field::new("r", DataType::Float64, false),
            Field::new("phi", DataType::Float64, true),
        ]
        .into_iter()
        .chain(channels)
        .collect::<Vec<_>>()
    };
    Arc::new(Schema::new(fields))
}

/// Where a store's files go.
#[derive(Debug, Clone)]
pub enum Target {
    /// The dataset's cache: `<root>/<key's dir_name>`, kept for later runs.
    Cache(PathBuf),
    /// A scratch directory (removed with the store), for the frames beyond the budget only; the
    /// reason there is no cache.
    Scratch(String),
}

/// Writes a store's files while it is filled.
pub struct Writer {
    tmp: PathBuf,
    target: Target,
    files: [Option<FileWriter<BufWriter<File>>>; 2],
    /// The lattice file without the frame, r and φ columns (see [`Writer::create`]).
    compact_lattice: bool,
    /// `tmp`'s lock ([`hold`]), held until the files are dropped.
    lock: Option<File>,
    next_batch: [usize; 2],
    batches: [Vec<Option<usize>>; 2],
    rows: [Vec<usize>; 2],
}

impl std::fmt::Debug for Writer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Writer").field("tmp", &self.tmp).finish()
    }
}

/// The file in a directory being written (a scratch store, a cache before it is moved into place)
/// that its run holds locked while it lives.
const LOCK: &str = ".lock";

/// Name prefix of scratch stores in the temporary directory.
const SCRATCH_PREFIX: &str = "subsurf-store-";

/// Creates `dir`'s lock file and locks it: the directory is live while the handle is.
fn hold(dir: &Path) -> Result<File, StoreError> {
    let path = dir.join(LOCK);
    let f = File::create(&path).map_err(io(&path))?;
    f.lock().map_err(io(&path))?;
    Ok(f)
}

/// Removes the directories under `root` whose names pass `ours` and whose run is gone: a store
/// being written holds its lock file locked ([`hold`]) until it is finished or dropped, and a
/// run that is killed (Ctrl-C, `timeout`, out of memory) releases it with the process, leaving
/// its files behind: 4–7 GB of scratch lattice at 1024 px. A directory without a lock file, or
/// whose lock is held, is left alone; errors are ignored (another user's temporary files).
fn sweep_stale(root: &Path, ours: impl Fn(&str) -> bool) {
    let Ok(entries) = std::fs::read_dir(root) else {
        return;
    };
    for e in entries.flatten() {
        if !ours(&e.file_name().to_string_lossy()) {
            continue;
        }
        let Ok(lock) = File::options().write(true).open(e.path().join(LOCK)) else {
            continue;
        };
        if lock.try_lock().is_ok() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

fn unique_suffix() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!("{}-{nanos}", std::process::id())
}

impl Writer {
    /// Starts the files of a store extracted under `key` (with lattice points when `lattice`).
    /// A cache that cannot be created (read-only dataset) falls back to a scratch directory,
    /// and the reason is reported.
    pub fn create(
        target: Target,
        key: &ExtractionKey,
        lattice: bool,
    ) -> Result<Writer, StoreError> {
        // Named by the key's prefix only: a store filled during a scan learns its frames'
        // identities (and so its final name, at `finish`) once they are all written.
        let (tmp, target) = match target {
            Target::Cache(root) => {
                sweep_stale(&root, |n| n.starts_with('.') && n.contains("tmp-"));
                let tmp = root.join(format!(".{}tmp-{}", key.dir_prefix(), unique_suffix()));
                match std::fs::create_dir_all(&tmp) {
                    Ok(()) => (tmp, Target::Cache(root)),
                    Err(e) => {
                        let why = format!("cannot write {}: {e}", root.display());
                        (scratch_dir()?, Target::Scratch(why))
                    }
                }
            }
            Target::Scratch(why) => (scratch_dir()?, Target::Scratch(why)),
        };
        // A scratch store's lattice is read back by this run alone, which knows each frame's
        // x_i and the points: r is their distance again (as for the lattice in memory,
        // `Packed`, the same bits) and φ the lattice pass measures itself, or not at all for
        // a model of one segment. Without those columns and the frame's, the file is 28 bytes a
        // sample instead of 48, and at 1024 px it is GBs that are written and read back.
        let compact_lattice = matches!(target, Target::Scratch(_));
        let lock = match hold(&tmp) {
            Ok(l) => l,
            Err(e) => {
                let _ = std::fs::remove_dir_all(&tmp);
                return Err(e);
            }
        };
        let open = |set: PointSet| -> Result<FileWriter<BufWriter<File>>, StoreError> {
            let path = tmp.join(file_name(set));
            let f = File::create(&path).map_err(io(&path))?;
            let schema = sample_schema(set, compact_lattice && set == PointSet::Lattice);
            FileWriter::try_new(BufWriter::with_capacity(1 << 20, f), &schema)
                .map_err(|e| format_err(&path, e))
        };
        let files = [
            Some(open(PointSet::Vertices)?),
            if lattice {
                Some(open(PointSet::Lattice)?)
            } else {
                None
            },
        ];
        Ok(Writer {
            tmp,
            target,
            files,
            compact_lattice,
            lock: Some(lock),
            next_batch: [0, 0],
            batches: [Vec::new(), Vec::new()],
            rows: [Vec::new(), Vec::new()],
        })
    }

    /// Writes one frame's samples; the batch each point set's samples went to.
    pub(super) fn push(
        &mut self,
        x: &Extracted,
        positions: &[V3],
        point_positions: Option<&[V3]>,
    ) -> Result<[Option<usize>; 2], StoreError> {
        let x_i = match x.record.outcome {
            Ok(RegistrationOutcome::Registered { x_i, .. }) => Some(x_i),
            _ => None,
        };
        let mut out = [None, None];
        for (s, set) in [
            (&x.vertices, PointSet::Vertices),
            (&x.points, PointSet::Lattice),
        ] {
            let i = set as usize;
            let pos = match set {
                PointSet::Vertices => Some(positions),
                PointSet::Lattice => point_positions,
            };
            let (Some(s), Some(w), Some(pos), Some(x_i)) = (s, self.files[i].as_mut(), pos, x_i)
            else {
                self.batches[i].push(None);
                continue;
            };
            let compact = self.compact_lattice && set == PointSet::Lattice;
            let batch = if compact {
                compact_batch(s)
            } else {
                sample_batch(set, x.record.frame, s, pos, x_i, x.tangent.as_ref())
            };
            let path = self.tmp.join(file_name(set));
            w.write(&batch).map_err(|e| format_err(&path, e))?;
            out[i] = Some(self.next_batch[i]);
            self.batches[i].push(out[i]);
            self.rows[i].push(s.len());
            self.next_batch[i] += 1;
        }
        Ok(out)
    }

    /// The batch record `i`'s samples at `set` went to.
    pub(super) fn batch_of(&self, set: PointSet, i: usize) -> Option<usize> {
        self.batches[set as usize].get(i).copied().flatten()
    }

    /// Finishes every file and, for a cache, moves the directory into place.
    pub(super) fn finish(
        mut self,
        key: &ExtractionKey,
        records: &[FrameRecord],
        points: Option<&StorePoints>,
    ) -> Result<Files, StoreError> {
        // A cache is on disk before it is moved into place, so a crash never leaves a named
        // store with missing data. A scratch store dies with the run: syncing it only made the
        // run wait for the disk (at 1024 px, GBs of lattice samples the page cache holds anyway).
        let durable = matches!(self.target, Target::Cache(_));
        for (i, w) in self.files.iter_mut().enumerate() {
            if let Some(w) = w {
                let path = self
                    .tmp
                    .join(file_name([PointSet::Vertices, PointSet::Lattice][i]));
                w.finish().map_err(|e| format_err(&path, e))?;
                w.get_mut().flush().map_err(io(&path))?;
                if durable {
                    w.get_ref().get_ref().sync_all().map_err(io(&path))?;
                }
            }
        }
        let frames = frames_batch(records, &self.batches, &self.rows);
        write_one(&self.tmp.join(FRAMES), &frames, durable)?;
        if let Some(p) = points {
            write_one(&self.tmp.join(LATTICE), &lattice_batch(p), durable)?;
        }
        let manifest = Manifest {
            format: FORMAT.into(),
            writer: format!("subsurf {}", env!("CARGO_PKG_VERSION")),
            key: key.clone(),
            lattice_min_value: points.map(|p| p.min_value),
            lattice_min_value_bits: points.map(|p| p.min_value.to_bits()),
        };
        let path = self.tmp.join(MANIFEST);
        let json = serde_json::to_vec_pretty(&manifest).map_err(|e| format_err(&path, e))?;
        let mut f = File::create(&path).map_err(io(&path))?;
        f.write_all(&json).map_err(io(&path))?;
        if durable {
            f.sync_all().map_err(io(&path))?;
        }
        let (dir, keep, not_cached) = match &self.target {
            Target::Cache(root) => {
                let dir = root.join(key.dir_name());
                // A stale cache of the same options (other frames, changed files) is replaced;
                // if another run put one in place meanwhile, ours stays a scratch copy.
                if dir.exists() {
                    let _ = std::fs::remove_dir_all(&dir);
                }
                // A cache holds no lock file; the lock itself is held until the move is done,
                // so no other run takes the directory for a stale one meanwhile.
                let _ = std::fs::remove_file(self.tmp.join(LOCK));
                match std::fs::rename(&self.tmp, &dir) {
                    Ok(()) => {
                        if let Ok(d) = File::open(root) {
                            let _ = d.sync_all();
                        }
                        // Stores this one holds everything of are superseded.
                        for (old, k, _) in candidates(root, key).unwrap_or_default() {
                            if old != dir && key.serves(&k) {
                                let _ = std::fs::remove_dir_all(&old);
                            }
                        }
                        (dir, true, None)
                    }
                    Err(e) => (
                        self.tmp.clone(),
                        false,
                        Some(format!("cannot move it into {}: {e}", dir.display())),
                    ),
                }
            }
            Target::Scratch(why) => (self.tmp.clone(), false, Some(why.clone())),
        };
        let batches = std::mem::take(&mut self.batches);
        let rows = std::mem::take(&mut self.rows);
        self.tmp = PathBuf::new();
        let lock = if keep { None } else { self.lock.take() };
        let mut files = Files::new(dir, keep, not_cached, batches, rows)?;
        files.lock = lock;
        Ok(files)
    }
}

impl Drop for Writer {
    /// A writer dropped before `finish` (an error, a panic elsewhere) leaves no half store.
    fn drop(&mut self) {
        if !self.tmp.as_os_str().is_empty() {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

fn scratch_dir() -> Result<PathBuf, StoreError> {
    let tmp = std::env::temp_dir();
    sweep_stale(&tmp, |n| n.starts_with(SCRATCH_PREFIX));
    let dir = tmp.join(format!("{SCRATCH_PREFIX}{}", unique_suffix()));
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    Ok(dir)
}

/// One batch in a file of its own, synced to disk when `durable`.
fn write_one(path: &Path, batch: &RecordBatch, durable: bool) -> Result<(), StoreError> {
    let f = File::create(path).map_err(io(path))?;
    let mut w =
        FileWriter::try_new(BufWriter::new(f), &batch.schema()).map_err(|e| format_err(path, e))?;
    w.write(batch).map_err(|e| format_err(path, e))?;
    w.finish().map_err(|e| format_err(path, e))?;
    w.get_mut().flush().map_err(io(path))?;
    if durable {
        w.get_ref().get_ref().sync_all().map_err(io(path))?;
    }
    Ok(())
}

fn read_one(path: &Path) -> Result<RecordBatch, StoreError> {
    let f = File::open(path).map_err(io(path))?;
    let mut r = FileReader::try_new_buffered(f, None).map_err(|e| format_err(path, e))?;
    match r.next() {
        Some(b) => b.map_err(|e| format_err(path, e)),
        None => Err(format_err(path, "no record batch")),
    }
}

/// One frame's samples as a record batch.
fn sample_batch(
    set: PointSet,
    frame: usize,
    s: &[Sample],
    positions: &[V3],
    x_i: V3,
    tangent: Option<&crate::model::TangentFrame>,
) -> RecordBatch {
    let phi = Float64Array::from_iter(s.iter().map(|x| {
        let x_o = positions.get(x.vertex as usize).copied()?;
        tangent?.direction(x_i, x_o)
    }));
    let columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(vec![frame as u32; s.len()])),
        Arc::new(UInt32Array::from_iter_values(s.iter().map(|x| x.vertex))),
        Arc::new(Float64Array::from_iter_values(s.iter().map(|x| x.r))),
        Arc::new(phi),
        channel_column(s, 0),
        channel_column(s, 1),
        channel_column(s, 2),
    ];
    // The columns match the schema by construction.
    RecordBatch::try_new(sample_schema(set, false), columns)
        .unwrap_or_else(|_| RecordBatch::new_empty(sample_schema(set, false)))
}

/// One frame's lattice samples as a compact batch (a scratch store's, [`Writer::create`]).
fn compact_batch(s: &[Sample]) -> RecordBatch {
    let schema = sample_schema(PointSet::Lattice, true);
    let columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(s.iter().map(|x| x.vertex))),
        channel_column(s, 0),
        channel_column(s, 1),
        channel_column(s, 2),
    ];
    // The columns match the schema by construction.
    RecordBatch::try_new(schema.clone(), columns).unwrap_or_else(|_| RecordBatch::new_empty(schema))
}

/// Channel `c` of samples `s`: the value where valid, else null.
fn channel_column(s: &[Sample], c: usize) -> ArrayRef {
    Arc::new(Float64Array::from_iter(
        s.iter()
            .map(|x| (x.valid & (1 << c) != 0).then_some(x.value[c])),
    ))
}

fn column<'a>(b: &'a RecordBatch, name: &str, path: &Path) -> Result<&'a ArrayRef, StoreError> {
    b.column_by_name(name)
        .ok_or_else(|| format_err(path, format!("no column {name:?}")))
}

fn u32_col<'a>(b: &'a RecordBatch, name: &str, path: &Path) -> Result<&'a UInt32Array, StoreError> {
    column(b, name, path)?
        .as_primitive_opt::<UInt32Type>()
        .ok_or_else(|| format_err(path, format!("column {name:?} is not u32")))
}

fn u64_col<'a>(b: &'a RecordBatch, name: &str, path: &Path) -> Result<&'a UInt64Array, StoreError> {
    column(b, name, path)?
        .as_primitive_opt::<UInt64Type>()
        .ok_or_else(|| format_err(path, format!("column {name:?} is not u64")))
}

fn f64_col<'a>(
    b: &'a RecordBatch,
    name: &str,
    path: &Path,
) -> Result<&'a Float64Array, StoreError> {
    column(b, name, path)?
        .as_primitive_opt::<Float64Type>()
        .ok_or_else(|| format_err(path, format!("column {name:?} is not f64")))
}

fn opt<T: arrow_array::ArrowPrimitiveType>(
    a: &arrow_array::PrimitiveArray<T>,
    i: usize,
) -> Option<T::Native> {
    (!a.is_null(i)).then(|| a.value(i))
}

/// A sample batch back as samples. A compact batch (no `r` column, [`compact_batch`]) takes r
/// from `at`: the points' positions and the frame's x_i.
fn samples_of(
    b: &RecordBatch,
    set: PointSet,
    path: &Path,
    at: Option<(&[V3], V3)>,
) -> Result<Vec<Sample>, StoreError> {
    let point = match set {
        PointSet::Vertices => "vertex",
        PointSet::Lattice => "point",
    };
    let p = u32_col(b, point, path)?;
    let r = match b.column_by_name("r") {
        Some(_) => RFrom::Column(f64_col(b, "r", path)?),
        None => {
            let (positions, x_i) =
                at.ok_or_else(|| format_err(path, "no column \"r\" and no x_i to measure it"))?;
            if let Some(&bad) = p.values().iter().find(|&&i| i as usize >= positions.len()) {
                return Err(format_err(
                    path,
                    format!("point {bad} is not in the lattice"),
                ));
            }
            RFrom::Points(positions, x_i)
        }
    };
    let ch = [
        f64_col(b, "s_r", path)?,
        f64_col(b, "s_g", path)?,
        f64_col(b, "s_b", path)?,
    ];
    Ok((0..b.num_rows())
        .map(|i| {
            let vertex = p.value(i);
            let r = match r {
                RFrom::Column(r) => r.value(i),
                // As `Packed::unpack` measures it: the same bits as at extraction.
                RFrom::Points(positions, x_i) => {
                    crate::geometry::dist(positions[vertex as usize], x_i)
                }
            };
            let mut s = Sample {
                vertex,
                r,
                value: [0.0; 3],
                valid: 0,
            };
            for (c, a) in ch.iter().enumerate() {
                if let Some(v) = opt(a, i) {
                    s.value[c] = v;
                    s.valid |= 1 << c;
                }
            }
            s
        })
        .collect())
}

/// Where [`samples_of`] takes r from: the file's column, or the points' positions and x_i.
#[derive(Clone, Copy)]
enum RFrom<'a> {
    Column(&'a Float64Array),
    Points(&'a [V3], V3),
}

const COUNT_NAMES: [&str; 7] = [
    "used",
    "below_noise",
    "saturated",
    "non_finite",
    "excluded",
    "uncovered",
    "pooled",
];

fn counts_array(c: &SampleCounts) -> [u64; 7] {
    [
        c.used,
        c.below_noise,
        c.saturated,
        c.non_finite,
        c.excluded,
        c.uncovered,
        c.pooled,
    ]
}

fn outcome_name(o: &Result<RegistrationOutcome, String>) -> &'static str {
    match o {
        Ok(RegistrationOutcome::Registered { .. }) => "registered",
        Ok(RegistrationOutcome::NoSpot) => "no_spot",
        Ok(RegistrationOutcome::SpotOffObject) => "spot_off_object",
        Ok(RegistrationOutcome::LaserMismatch { .. }) => "laser_mismatch",
        Err(_) => "unreadable",
    }
}

/// The frames table.
fn frames_batch(
    records: &[FrameRecord],
    batches: &[Vec<Option<usize>>; 2],
    rows: &[Vec<usize>; 2],
) -> RecordBatch {
    let x_i = |r: &FrameRecord| match r.outcome {
        Ok(RegistrationOutcome::Registered { x_i, .. })
        | Ok(RegistrationOutcome::LaserMismatch { x_i, .. }) => Some(x_i),
        _ => None,
    };
    let spot = |r: &FrameRecord| r.spot;
    let f64s = |f: &dyn Fn(&FrameRecord) -> Option<f64>| -> ArrayRef {
        Arc::new(Float64Array::from_iter(records.iter().map(f)))
    };
    let mut fields = vec![
        Field::new("frame", DataType::UInt32, false),
        Field::new("outcome", DataType::Utf8, false),
        Field::new("error", DataType::Utf8, true),
        Field::new("x_i_x", DataType::Float64, true),
        Field::new("x_i_y", DataType::Float64, true),
        Field::new("x_i_z", DataType::Float64, true),
        Field::new("triangle", DataType::UInt32, true),
        Field::new("laser_disagreement_mm", DataType::Float64, true),
        Field::new("spot_u", DataType::Float64, true),
        Field::new("spot_v", DataType::Float64, true),
        Field::new("spot_peak", DataType::Float64, true),
        Field::new("spot_peak_fit", DataType::Float64, true),
        Field::new("spot_sigma_px", DataType::Float64, true),
        Field::new("spot_saturated", DataType::Boolean, true),
        Field::new("vertex_batch", DataType::UInt32, true),
        Field::new("point_batch", DataType::UInt32, true),
        Field::new("vertex_rows", DataType::UInt32, true),
        Field::new("point_rows", DataType::UInt32, true),
    ];
    let mut columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(
            records.iter().map(|r| r.frame as u32),
        )),
        Arc::new(StringArray::from_iter_values(
            records.iter().map(|r| outcome_name(&r.outcome)),
        )),
        Arc::new(StringArray::from_iter(
            records.iter().map(|r| r.outcome.as_ref().err().cloned()),
        )),
        f64s(&|r| x_i(r).map(|p| p[0])),
        f64s(&|r| x_i(r).map(|p| p[1])),
        f64s(&|r| x_i(r).map(|p| p[2])),
        Arc::new(UInt32Array::from_iter(records.iter().map(
            |r| match r.outcome {
                Ok(RegistrationOutcome::Registered { triangle, .. }) => Some(triangle),
                _ => None,
            },
        ))),
        f64s(&|r| match r.outcome {
            Ok(RegistrationOutcome::Registered {
                laser_disagreement_mm,
                ..
            }) => laser_disagreement_mm,
            Ok(RegistrationOutcome::LaserMismatch {
                disagreement_mm, ..
            }) => disagreement_mm,
            _ => None,
        }),
        f64s(&|r| spot(r).map(|s| s.u)),
        f64s(&|r| spot(r).map(|s| s.v)),
        f64s(&|r| spot(r).map(|s| s.peak)),
        f64s(&|r| spot(r).map(|s| s.peak_fit)),
        f64s(&|r| spot(r).map(|s| s.sigma_px)),
        Arc::new(BooleanArray::from_iter(
            records.iter().map(|r| spot(r).map(|s| s.saturated)),
        )),
        Arc::new(UInt32Array::from_iter(
            batches[0].iter().map(|b| b.map(|b| b as u32)),
        )),
        Arc::new(UInt32Array::from_iter(
            (0..records.len()).map(|i| batches[1].get(i).copied().flatten().map(|b| b as u32)),
        )),
    ];
    for set in 0..2 {
        columns.push(Arc::new(UInt32Array::from_iter((0..records.len()).map(
            |i| {
                let b = batches[set].get(i).copied().flatten()?;
                rows[set].get(b).map(|&n| n as u32)
            },
        ))));
    }
    for (set, prefix) in [(0, "vertex"), (1, "point")] {
        for (j, name) in COUNT_NAMES.iter().enumerate() {
            fields.push(Field::new(
                format!("{prefix}_{name}"),
                DataType::UInt64,
                false,
            ));
            columns.push(Arc::new(UInt64Array::from_iter_values(
                records.iter().map(|r| counts_array(&r.counts[set])[j]),
            )));
        }
    }
    RecordBatch::try_new(Arc::new(Schema::new(fields)), columns)
        .unwrap_or_else(|_| RecordBatch::new_empty(Arc::new(Schema::empty())))
}

/// The lattice: per face its level, and per sampled point its face, barycentric coordinates
/// and position (object frame, mm), so that a point's samples can be placed without subsurf.
fn lattice_batch(p: &StorePoints) -> RecordBatch {
    let n = p.levels.len().max(p.which.len());
    let pad_u8 = |v: &[u8]| -> ArrayRef {
        Arc::new(UInt8Array::from_iter((0..n).map(|i| v.get(i).copied())))
    };
    let pts = &p.points;
    let at = |f: &dyn Fn(usize) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from_iter(
            (0..n).map(|i| p.which.get(i).map(|&q| f(q as usize))),
        ))
    };
    let columns: Vec<ArrayRef> = vec![
        pad_u8(&p.levels),
        Arc::new(UInt32Array::from_iter(
            (0..n).map(|i| p.which.get(i).copied()),
        )),
        Arc::new(UInt32Array::from_iter(
            (0..n).map(|i| p.which.get(i).map(|&q| pts.face[q as usize])),
        )),
        at(&|q| pts.bary[q][0]),
        at(&|q| pts.bary[q][1]),
        at(&|q| pts.bary[q][2]),
        at(&|q| pts.positions[q][0]),
        at(&|q| pts.positions[q][1]),
        at(&|q| pts.positions[q][2]),
    ];
    let schema = Schema::new(vec![
        Field::new("face_level", DataType::UInt8, true),
        Field::new("point", DataType::UInt32, true),
        Field::new("face", DataType::UInt32, true),
        Field::new("b0", DataType::Float64, true),
        Field::new("b1", DataType::Float64, true),
        Field::new("b2", DataType::Float64, true),
        Field::new("x", DataType::Float64, true),
        Field::new("y", DataType::Float64, true),
        Field::new("z", DataType::Float64, true),
    ]);
    RecordBatch::try_new(Arc::new(schema), columns)
        .unwrap_or_else(|_| RecordBatch::new_empty(Arc::new(Schema::empty())))
}

/// A reader of a shared open file at a position of its own (positioned reads), so that readers on
/// several threads never share a file offset, and a store stays readable when another run
/// replaces its directory: the files were opened when the store was made.
struct At {
    file: Arc<File>,
    pos: u64,
}

impl std::io::Read for At {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        #[cfg(unix)]
        let n = std::os::unix::fs::FileExt::read_at(&*self.file, buf, self.pos)?;
        #[cfg(windows)]
        let n = std::os::windows::fs::FileExt::seek_read(&*self.file, buf, self.pos)?;
        self.pos += n as u64;
        Ok(n)
    }
}

impl std::io::Seek for At {
    fn seek(&mut self, to: std::io::SeekFrom) -> std::io::Result<u64> {
        use std::io::SeekFrom;
        let base = match to {
            SeekFrom::Start(p) => {
                self.pos = p;
                return Ok(p);
            }
            SeekFrom::Current(d) => (self.pos, d),
            SeekFrom::End(d) => (self.file.metadata()?.len(), d),
        };
        self.pos = base
            .0
            .checked_add_signed(base.1)
            .ok_or_else(|| std::io::Error::other("seek before the start"))?;
        Ok(self.pos)
    }
}

/// A store's finished files, read back a batch at a time.
pub struct Files {
    dir: PathBuf,
    keep: bool,
    not_cached: Option<String>,
    batches: [Vec<Option<usize>>; 2],
    rows: [Vec<usize>; 2],
    /// The sample files, opened once.
    open: [Option<Arc<File>>; 2],
    /// Readers per point set, reused (making one parses the footer).
    readers: [Mutex<Vec<FileReader<BufReader<At>>>>; 2],
    /// A scratch directory's lock ([`hold`]): held while the files live.
    lock: Option<File>,
}

impl std::fmt::Debug for Files {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Files")
            .field("dir", &self.dir)
            .field("keep", &self.keep)
            .finish()
    }
}

impl Files {
    fn new(
        dir: PathBuf,
        keep: bool,
        not_cached: Option<String>,
        batches: [Vec<Option<usize>>; 2],
        rows: [Vec<usize>; 2],
    ) -> Result<Files, StoreError> {
        let mut open = [None, None];
        for set in [PointSet::Vertices, PointSet::Lattice] {
            let path = dir.join(file_name(set));
            if batches[set as usize].iter().any(Option::is_some) {
                open[set as usize] = Some(Arc::new(File::open(&path).map_err(io(&path))?));
            }
        }
        Ok(Files {
            dir,
            keep,
            not_cached,
            batches,
            rows,
            open,
            readers: [Mutex::new(Vec::new()), Mutex::new(Vec::new())],
            lock: None,
        })
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Why the files are not the dataset's cache, if they are not.
    pub fn not_cached(&self) -> Option<&str> {
        self.not_cached.as_deref()
    }

    /// Per record, the batch of its samples at `set`.
    pub(super) fn batches(&self, set: PointSet) -> &[Option<usize>] {
        &self.batches[set as usize]
    }

    /// Rows and in-memory bytes of batch `b` of `set`.
    pub(super) fn batch_size(&self, set: PointSet, b: usize) -> (usize, usize) {
        let n = self.rows[set as usize].get(b).copied().unwrap_or(0);
        (n, n * std::mem::size_of::<Sample>())
    }

    /// Batch `b` of `set`'s file as samples; `at` (the points' positions and the frame's x_i)
    /// measures r where the file does not hold it (a scratch store's lattice).
    pub(super) fn read_batch(
        &self,
        set: PointSet,
        b: usize,
        at: Option<(&[V3], V3)>,
    ) -> Result<Vec<Sample>, StoreError> {
        let path = self.dir.join(file_name(set));
        let pool = &self.readers[set as usize];
        let reader = pool.lock().ok().and_then(|mut p| p.pop());
        let mut reader = match reader {
            Some(r) => r,
            None => {
                let file = self.open[set as usize]
                    .clone()
                    .ok_or_else(|| format_err(&path, "no samples were written"))?;
                FileReader::try_new_buffered(At { file, pos: 0 }, None)
                    .map_err(|e| format_err(&path, e))?
            }
        };
        reader.set_index(b).map_err(|e| format_err(&path, e))?;
        let batch = match reader.next() {
            Some(b) => b.map_err(|e| format_err(&path, e))?,
            None => return Err(format_err(&path, format!("no batch {b}"))),
        };
        if let Ok(mut p) = pool.lock() {
            p.push(reader);
        }
        samples_of(&batch, set, &path, at)
    }
}

impl Drop for Files {
    /// Scratch files go with the store.
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// The cached store under `root` that serves `want` (see [`ExtractionKey::serves`]), loaded
/// into memory while `budget` lasts; `Ok(None)` when there is none (or it is stale: a frame
/// changed, other options). A cache that exists but cannot be read is an error.
pub fn open(
    root: &Path,
    want: &ExtractionKey,
    mesh: &crate::dataset::Mesh,
    dataset_frames: usize,
    budget: usize,
) -> Result<Option<SampleStore>, StoreError> {
    let Some((dir, key, min_value)) = candidates(root, want)?
        .into_iter()
        .find(|(_, k, _)| k.serves(want))
    else {
        return Ok(None);
    };
    open_dir(dir, key, min_value, want, mesh, dataset_frames, budget).map(Some)
}

/// The stores under `root` that could serve `want` (same rules, options, mesh and cameras), with
/// their keys; fewest frames first (the cheapest to load).
#[allow(clippy::type_complexity)]
fn candidates(
    root: &Path,
    want: &ExtractionKey,
) -> Result<Vec<(PathBuf, ExtractionKey, Option<f64>)>, StoreError> {
    let prefix = want.dir_prefix();
    let entries = match std::fs::read_dir(root) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io(root)(e)),
    };
    let mut out = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !name.starts_with(&prefix) {
            continue;
        }
        let path = e.path().join(MANIFEST);
        let Ok(text) = std::fs::read(&path) else {
            continue;
        };
        let manifest: Manifest = serde_json::from_slice(&text).map_err(|e| format_err(&path, e))?;
        if manifest.format != FORMAT {
            continue;
        }
        let min_value = manifest
            .lattice_min_value_bits
            .map(f64::from_bits)
            .or(manifest.lattice_min_value);
        out.push((e.path(), manifest.key, min_value));
    }
    out.sort_by_key(|(d, k, _)| (k.frames.len(), d.clone()));
    Ok(out)
}

fn open_dir(
    dir: PathBuf,
    key: ExtractionKey,
    min_value: Option<f64>,
    want: &ExtractionKey,
    mesh: &crate::dataset::Mesh,
    dataset_frames: usize,
    budget: usize,
) -> Result<SampleStore, StoreError> {
    let path = dir.join(FRAMES);
    let b = read_one(&path)?;
    let (records, batches, rows) = records_of(&b, &path)?;
    let mut key = key;
    if want.lattice.is_none() {
        // The vertices only are loaded.
        key.lattice = None;
    }
    let points = match &want.lattice {
        None => None,
        Some(digest) => {
            let path = dir.join(LATTICE);
            let l = read_one(&path)?;
            let levels = column(&l, "face_level", &path)?
                .as_primitive_opt::<UInt8Type>()
                .ok_or_else(|| format_err(&path, "face_level is not u8"))?;
            let levels: Vec<u8> = levels.iter().flatten().collect();
            let which: Vec<u32> = u32_col(&l, "point", &path)?.iter().flatten().collect();
            let mut p =
                StorePoints::new(mesh, levels, Some(which)).map_err(|e| format_err(&path, e))?;
            p.min_value = min_value.unwrap_or(0.0);
            if p.which.iter().any(|&q| q as usize >= p.points.len()) || &p.digest() != digest {
                return Err(format_err(&path, "the lattice does not match the manifest"));
            }
            Some(p)
        }
    };
    for set in [PointSet::Vertices, PointSet::Lattice] {
        if set == PointSet::Lattice && points.is_none() {
            continue;
        }
        let path = dir.join(file_name(set));
        let f = File::open(&path).map_err(io(&path))?;
        let r = FileReader::try_new_buffered(f, None).map_err(|e| format_err(&path, e))?;
        let n = r.num_batches();
        if batches[set as usize].iter().flatten().any(|&b| b >= n) {
            return Err(format_err(&path, "a frame names a batch the file lacks"));
        }
    }
    let files = Files::new(dir.clone(), true, None, batches, rows)?;
    SampleStore::from_files(key, dataset_frames, records, points, files, budget)
}

/// The frames table back as records and per-record batches.
#[allow(clippy::type_complexity)]
fn records_of(
    b: &RecordBatch,
    path: &Path,
) -> Result<(Vec<FrameRecord>, [Vec<Option<usize>>; 2], [Vec<usize>; 2]), StoreError> {
    let frame = u32_col(b, "frame", path)?;
    let outcome = column(b, "outcome", path)?
        .as_string_opt::<i32>()
        .ok_or_else(|| format_err(path, "outcome is not text"))?;
    let error = column(b, "error", path)?
        .as_string_opt::<i32>()
        .ok_or_else(|| format_err(path, "error is not text"))?;
    let g = |n: &str| f64_col(b, n, path);
    let (xx, xy, xz) = (g("x_i_x")?, g("x_i_y")?, g("x_i_z")?);
    let tri = u32_col(b, "triangle", path)?;
    let laser = g("laser_disagreement_mm")?;
    let (su, sv, sp, spf, ss) = (
        g("spot_u")?,
        g("spot_v")?,
        g("spot_peak")?,
        g("spot_peak_fit")?,
        g("spot_sigma_px")?,
    );
    let sat = column(b, "spot_saturated", path)?
        .as_boolean_opt()
        .ok_or_else(|| format_err(path, "spot_saturated is not boolean"))?;
    let vb = u32_col(b, "vertex_batch", path)?;
    let pb = u32_col(b, "point_batch", path)?;
    let vr = u32_col(b, "vertex_rows", path)?;
    let pr = u32_col(b, "point_rows", path)?;
    let mut counts = Vec::new();
    for prefix in ["vertex", "point"] {
        let mut cols = Vec::new();
        for name in COUNT_NAMES {
            cols.push(u64_col(b, &format!("{prefix}_{name}"), path)?);
        }
        counts.push(cols);
    }
    let mut records = Vec::with_capacity(b.num_rows());
    let mut batches = [Vec::new(), Vec::new()];
    let mut rows = [Vec::new(), Vec::new()];
    for i in 0..b.num_rows() {
        let missing = || format_err(path, format!("row {i}: a registered frame misses a value"));
        let x_i = match (opt(xx, i), opt(xy, i), opt(xz, i)) {
            (Some(x), Some(y), Some(z)) => Some([x, y, z]),
            _ => None,
        };
        let spot = match (opt(su, i), opt(sv, i), opt(sp, i), opt(spf, i), opt(ss, i)) {
            (Some(u), Some(v), Some(peak), Some(peak_fit), Some(sigma_px)) => Some(Spot {
                u,
                v,
                peak,
                saturated: !sat.is_null(i) && sat.value(i),
                peak_fit,
                sigma_px,
            }),
            _ => None,
        };
        let outcome = match outcome.value(i) {
            "registered" => Ok(RegistrationOutcome::Registered {
                x_i: x_i.ok_or_else(missing)?,
                triangle: opt(tri, i).ok_or_else(missing)?,
                laser_disagreement_mm: opt(laser, i),
                spot: spot.ok_or_else(missing)?,
            }),
            "no_spot" => Ok(RegistrationOutcome::NoSpot),
            "spot_off_object" => Ok(RegistrationOutcome::SpotOffObject),
            "laser_mismatch" => Ok(RegistrationOutcome::LaserMismatch {
                x_i: x_i.ok_or_else(missing)?,
                disagreement_mm: opt(laser, i),
            }),
            "unreadable" => Err(if error.is_null(i) {
                String::new()
            } else {
                error.value(i).to_owned()
            }),
            other => return Err(format_err(path, format!("row {i}: outcome {other:?}"))),
        };
        let c = |set: usize| {
            let v: Vec<u64> = counts[set].iter().map(|a| a.value(i)).collect();
            SampleCounts {
                used: v[0],
                below_noise: v[1],
                saturated: v[2],
                non_finite: v[3],
                excluded: v[4],
                uncovered: v[5],
                pooled: v[6],
            }
        };
        records.push(FrameRecord {
            frame: frame.value(i) as usize,
            outcome,
            spot,
            counts: [c(0), c(1)],
        });
        for (set, (bc, rc)) in [(vb, vr), (pb, pr)].into_iter().enumerate() {
            let b = opt(bc, i).map(|b| b as usize);
            if let Some(b) = b {
                let n = opt(rc, i).ok_or_else(missing)? as usize;
                if rows[set].len() <= b {
                    rows[set].resize(b + 1, 0);
                }
                rows[set][b] = n;
            }
            batches[set].push(b);
        }
    }
    Ok((records, batches, rows))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A store directory whose run is gone (its lock released with it) is removed by the next
    /// run that writes a store beside it; a live one (its lock held), one without a lock file
    /// and one of another name are left alone.
    #[test]
    fn stores_of_runs_that_are_gone_are_swept_and_live_ones_kept() {
        let root = tempfile::tempdir().unwrap();
        let make = |name: &str| {
            let d = root.path().join(name);
            std::fs::create_dir(&d).unwrap();
            std::fs::write(d.join("points.arrow"), b"samples").unwrap();
            d
        };
        let gone = make("subsurf-store-1-1");
        drop(hold(&gone).unwrap());
        let live = make("subsurf-store-2-2");
        let held = hold(&live).unwrap();
        let no_lock = make("subsurf-store-3-3");
        let other = make("other-4");
        drop(hold(&other).unwrap());
        let ours = |n: &str| n.starts_with(SCRATCH_PREFIX);
        sweep_stale(root.path(), ours);
        assert!(!gone.exists());
        assert!(live.exists() && no_lock.exists() && other.exists());
        drop(held);
        sweep_stale(root.path(), ours);
        assert!(!live.exists() && no_lock.exists() && other.exists());

        // The scratch directory a run makes sweeps the temporary directory first, and holds
        // its own lock.
        let stale = std::env::temp_dir().join(format!("{SCRATCH_PREFIX}gone-{}", unique_suffix()));
        std::fs::create_dir(&stale).unwrap();
        drop(hold(&stale).unwrap());
        let mine = scratch_dir().unwrap();
        assert!(!stale.exists(), "a gone run's scratch store is swept");
        let lock = hold(&mine).unwrap();
        sweep_stale(&std::env::temp_dir(), ours);
        assert!(mine.exists(), "a live run's scratch store stays");
        drop(lock);
        std::fs::remove_dir_all(&mine).unwrap();
    }
}
