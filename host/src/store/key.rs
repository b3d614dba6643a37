//! What a sample store depends on, so that a cached store is used only for the very frames and
//! extraction options it was made from.
//!
//! A frame is identified as `make` and cargo identify files: its `scan.json` entry, each of its
//! image files' (its own and its brackets') size and modification time (re-reading every byte to hash it would cost the decode the
//! cache saves). The extraction is identified by its options, the mesh, the cameras, the lattice
//! points sampled and [`EXTRACTION_RULES`].
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::dataset::{Dataset, confined_path};

/// The version of the rules that turn an image into a store's content (registration, sampling):
/// bumped whenever they change, so that no cache made by older rules is used. 2: spots seen down
/// to `spot::SPOT_COS_FLOOR` are registered (the fit chooses whether to use them).
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
    /// The same of each bracket file (`frames[].brackets`), in order: empty for a frame of one
    /// file, so keys of such frames are those made before brackets existed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub brackets: Vec<FileIdentity>,
}

/// One file as a store knows it: size and modification time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileIdentity {
    /// Size, bytes.
    pub bytes: u64,
    /// Modification time, nanoseconds since the Unix epoch (0: unknown).
    pub modified_ns: u64,
}

impl FileIdentity {
    /// File `rel` of frame `frame` of `ds` as it is on disk now.
    fn of(ds: &Dataset, frame: usize, rel: &str) -> Result<FileIdentity, StoreKeyError> {
        let path = confined_path(&ds.dir, rel).unwrap_or_else(|_| Path::new("").into());
        let meta = std::fs::metadata(&path).map_err(|source| StoreKeyError::Io {
            frame,
            path: path.clone(),
            source,
        })?;
        let modified_ns = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as u64);
        Ok(FileIdentity {
            bytes: meta.len(),
            modified_ns,
        })
    }
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
        let own = FileIdentity::of(ds, k, &f.image)?;
        let brackets = f
            .brackets
            .iter()
            .map(|b| FileIdentity::of(ds, k, &b.image))
            .collect::<Result<_, _>>()?;
        Ok(FrameIdentity {
            frame: k,
            spec,
            bytes: own.bytes,
            modified_ns: own.modified_ns,
            brackets,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Every file of a bracketed frame is in its identity: rewriting a bracket file (same bytes,
    /// a later time) changes the key, so a cache made before is not used; a frame of one file
    /// has the identity it had before brackets existed (no `brackets` key in the JSON).
    #[test]
    fn a_bracket_file_that_changed_changes_the_key() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::write(
            dir.join("object.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        let img = crate::dataset::Image::new(2, 2, 3);
        for name in ["a.pfm", "b.pfm", "c.pfm"] {
            crate::dataset::write_pfm(&dir.join(name), &img).unwrap();
        }
        std::fs::write(
            dir.join("scan.json"),
            r#"{"format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj",
              "cameras": [{"width": 2, "height": 2, "fx": 10.0, "fy": 10.0, "cx": 0.5, "cy": 0.5,
                "camera_from_world": [[1,0,0,0],[0,1,0,0],[0,0,1,50],[0,0,0,1]]}],
              "frames": [{"image": "a.pfm", "turntable_deg": 0.0, "exposure_s": 0.01,
                          "brackets": [{"image": "b.pfm", "exposure_s": 0.1}]},
                         {"image": "c.pfm", "turntable_deg": 0.0}]}"#,
        )
        .unwrap();
        let key = || {
            let ds = Dataset::open(dir).unwrap();
            ExtractionKey::new(&ds, &[0, 1], "{}".into(), None).unwrap()
        };
        let before = key();
        assert_eq!(before.frames[0].brackets.len(), 1);
        let plain = serde_json::to_string(&before.frames[1]).unwrap();
        assert!(!plain.contains("brackets"), "{plain}");
        assert!(key().serves(&before));
        std::thread::sleep(std::time::Duration::from_millis(20));
        let bytes = std::fs::read(dir.join("b.pfm")).unwrap();
        std::fs::write(dir.join("b.pfm"), bytes).unwrap();
        let after = key();
        assert!(
            !before.serves(&after),
            "a changed bracket file must not be served"
        );
        assert_eq!(before.frames[1], after.frames[1]);
    }
}
