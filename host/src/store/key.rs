//! What a sample store depends on, so that a cached store is used only for the very frames and
//! extraction options it was made from.
//!
//! A frame is identified as `make` and cargo identify files: its `scan.json` entry, the image
//! file's size and modification time (re-reading every byte to hash it would cost the decode the
//! cache saves). The extraction is identified by its options, the mesh, the cameras, the lattice
//! points sampled and [`EXTRACTION_RULES`].
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::dataset::{Dataset, confined_path};

/// The version of the rules that turn an image into a store's content (registration, sampling):
/// bumped whenever they change, so that no cache made by older rules is used. 2: spots seen down
/// to `registration::SPOT_COS_FLOOR` are registered (the fit chooses whether to use them).
pub const EXTRACTION_RULES: u32 = 2;

/// Why a key could not be made.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreKeyError {
    /// A frame's image file could not be inspected.
    #[error("frame {frame}: cannot inspect {path}: {source}")]
    Io {
        /// The frame.
        frame: usize,
        /// The file.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
}

/// One frame as a store knows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameIdentity {
    /// Index in `scan.json`.
    pub frame: usize,
    /// CRC-64 of the frame's `scan.json` entry (JSON).
    pub spec: String,
    /// Size of the image file, bytes.
    pub bytes: u64,
    /// Modification time of the image file, nanoseconds since the Unix epoch (0: unknown).
    pub modified_ns: u64,
}

/// What a store's content depends on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExtractionKey {
    /// [`EXTRACTION_RULES`].
    pub rules: u32,
    /// The extraction options (spot detection, sample rules), as JSON text: compared as text,
    /// since a number read back from JSON need not equal the one written to the bit.
    pub options: String,
    /// CRC-64 of the mesh (positions, triangles, normals).
    pub mesh: String,
    /// CRC-64 of the cameras (JSON).
    pub cameras: String,
    /// CRC-64 of the lattice points sampled (levels and point list); `None`: vertices only.
    pub lattice: Option<String>,
    /// The frames the store holds.
    pub frames: Vec<FrameIdentity>,
}

fn crc() -> crc::Crc<u64> {
    crc::Crc::<u64>::new(&crc::CRC_64_ECMA_182)
}

/// CRC-64 of `bytes`, as 16 hex digits.
pub(crate) fn digest(bytes: &[u8]) -> String {
    format!("{:016x}", crc().checksum(bytes))
}

/// CRC-64 of a sequence of f64/u32 words (their little-endian bytes).
pub(crate) fn digest_words(words: impl IntoIterator<Item = u64>) -> String {
    let c = crc();
    let mut d = c.digest();
    for w in words {
        d.update(&w.to_le_bytes());
    }
    format!("{:016x}", d.finalize())
}

impl FrameIdentity {
    /// Frame `k` of `ds` as it is on disk now.
    pub fn of(ds: &Dataset, k: usize) -> Result<FrameIdentity, StoreKeyError> {
        let f = &ds.spec.frames[k];
        let spec = digest(serde_json::to_string(f).unwrap_or_default().as_bytes());
        let path = confined_path(&ds.dir, &f.image).unwrap_or_else(|_| Path::new("").into());
        let meta = std::fs::metadata(&path).map_err(|source| StoreKeyError::Io {
            frame: k,
            path: path.clone(),
            source,
        })?;
        let modified_ns = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as u64);
        Ok(FrameIdentity {
            frame: k,
            spec,
            bytes: meta.len(),
            modified_ns,
        })
    }
}

impl ExtractionKey {
    /// The key of extracting frames `frames` of `ds` with `options` (JSON of the extraction
    /// options) and lattice digest `lattice`.
    pub fn new(
        ds: &Dataset,
        frames: &[usize],
        options: String,
        lattice: Option<String>,
    ) -> Result<ExtractionKey, StoreKeyError> {
        let m = &ds.mesh;
        let mesh = digest_words(
            m.positions
                .iter()
                .chain(&m.normals)
                .flat_map(|p| p.map(f64::to_bits))
                .chain(m.triangles.iter().flat_map(|t| t.map(u64::from))),
        );
        let cameras = digest(
            serde_json::to_string(&ds.spec.cameras)
                .unwrap_or_default()
                .as_bytes(),
        );
        let frames = frames
            .iter()
            .map(|&k| FrameIdentity::of(ds, k))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(ExtractionKey {
            rules: EXTRACTION_RULES,
            options,
            mesh,
            cameras,
            lattice,
            frames,
        })
    }

    /// The start of the names of the cache directories whose stores may serve this key: a
    /// digest of the rules, options, mesh and cameras (`samples-<digest>-`).
    pub fn dir_prefix(&self) -> String {
        let base = serde_json::json!([self.rules, self.options, self.mesh, self.cameras]);
        format!("samples-{}-", digest(base.to_string().as_bytes()))
    }

    /// The name of this store's cache directory: [`ExtractionKey::dir_prefix`] and a digest of
    /// the lattice and the frames, so that stores of other frames live beside it.
    pub fn dir_name(&self) -> String {
        let rest = serde_json::json!([self.lattice, self.frames]);
        format!(
            "{}{}",
            self.dir_prefix(),
            digest(rest.to_string().as_bytes())
        )
    }

    /// Whether a store made under `self` serves a run asking for `want`: the same rules,
    /// options, mesh and cameras, the same lattice points (any, when `want` asks for the
    /// vertices only), and every frame `want` asks for held with the same identity.
    pub fn serves(&self, want: &ExtractionKey) -> bool {
        let held: std::collections::HashMap<usize, &FrameIdentity> =
            self.frames.iter().map(|f| (f.frame, f)).collect();
        self.rules == want.rules
            && self.options == want.options
            && self.mesh == want.mesh
            && self.cameras == want.cameras
            && (want.lattice.is_none() || self.lattice == want.lattice)
            && want.frames.iter().all(|w| held.get(&w.frame) == Some(&w))
    }
}
