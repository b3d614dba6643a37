//! The one dataset writer, crash-safe, used by `subsurf scan` and `subsurf simulate` alike. It
//! writes exactly the types the reader reads ([`ScanSpec`], [`FrameSpec`]).
//!
//! Order of operations for frame `k` (the invariant resume relies on):
//! 1. the image is written to `frames/.k.exr.tmp`, fsynced, renamed to `frames/k.exr`, and the
//!    directory is fsynced;
//! 2. then one line is appended to `.subsurf-scan/journal.jsonl` and fsynced.
//!
//! A frame is complete exactly when its journal line is. On reopening, a torn last line is cut
//! off, every journaled image is checked (size and CRC-32), leftover temporary files are removed,
//! and the capture continues at the first frame not journaled — so a half-written frame is redone.
//! Lines hold no timestamps, so a resumed dataset is byte-identical to an uninterrupted one.
//! `scan.json` is rewritten atomically from the journal now and then and at the end; the journal
//! is the truth. The directory's `identity.json` (whatever identifies the capture: plan,
//! calibration and options, or a simulation's configuration) refuses mixing two captures.

use std::fs::{self, File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::{FrameSpec, Image, ImageError, ScanSpec, encode_exr, encode_pfm};

/// Directory of the bookkeeping files inside the dataset.
pub const STATE_DIR: &str = ".subsurf-scan";

/// Why the dataset could not be written or resumed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WriteError {
    /// A file operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The disk is (nearly) full; the frame was not written and nothing partial was left.
    #[error(
        "disk full at {path}: stopped before frame {frame} ({need} bytes needed, {free} free); \
         free some space and run the same command again to resume"
    )]
    DiskFull {
        /// The directory.
        path: String,
        /// The frame that was not written.
        frame: usize,
        /// Bytes needed including the reserve.
        need: u64,
        /// Bytes free.
        free: u64,
    },
    /// The output directory holds something else.
    #[error("{0}")]
    Mismatch(String),
    /// A frame's image could not be encoded.
    #[error("frame {frame}: {source}")]
    Image {
        /// The frame.
        frame: usize,
        /// The cause.
        source: ImageError,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> WriteError + '_ {
    move |source| {
        if source.kind() == std::io::ErrorKind::StorageFull {
            WriteError::DiskFull {
                path: path.display().to_string(),
                frame: usize::MAX,
                need: 0,
                free: 0,
            }
        } else {
            WriteError::Io {
                path: path.display().to_string(),
                source,
            }
        }
    }
}

/// One journal line. The frame entry is kept as the exact JSON text first written (a string
/// field), so resuming never re-formats a float and `scan.json` comes out byte-identical.
#[derive(Serialize, Deserialize)]
struct JournalLine {
    frame: usize,
    image: String,
    bytes: u64,
    crc32: u32,
    entry: String,
}

/// Writes a dataset frame by frame; see the module docs for the guarantees.
pub struct DatasetWriter {
    dir: PathBuf,
    /// `scan.json` without its frames.
    header: ScanSpec,
    /// `frames[]` entries as JSON text.
    entries: Vec<String>,
    journal: File,
    journal_path: PathBuf,
    last_index: Instant,
    /// Bytes that must stay free on the disk after each frame.
    pub reserve_bytes: u64,
}

/// Writes `bytes` to `path` atomically: temp file, fsync, rename, fsync of the directory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = dir.join(format!(".{name}.tmp"));
    let result = (|| {
        let mut f = File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(bytes).map_err(io(&tmp))?;
        f.sync_all().map_err(io(&tmp))?;
        drop(f);
        fs::rename(&tmp, path).map_err(io(path))?;
        sync_dir(dir)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

fn sync_dir(dir: &Path) -> Result<(), WriteError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))
}

/// Free bytes on the file system holding `dir`.
#[cfg(unix)]
pub fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a valid NUL-terminated path and `s` a properly sized out-parameter.
    let r = unsafe { libc::statvfs(c.as_ptr(), &mut s) };
    (r == 0).then(|| s.f_bavail as u64 * s.f_frsize as u64)
}

/// Free bytes are not known on this platform.
#[cfg(not(unix))]
pub fn free_bytes(_dir: &Path) -> Option<u64> {
    None
}

impl DatasetWriter {
    /// Opens `dir` for the capture identified by `identity` (for a scan the plan, calibration and
    /// options as JSON): creates it, or resumes it if it holds the same capture. `header` is
    /// `scan.json` without frames (any it has are ignored); `mesh_obj` is the OBJ text written as
    /// `header.mesh`. Returns the writer and the number of frames already complete. A directory
    /// holding other files or another capture is refused.
    pub fn open(
        dir: &Path,
        identity: &str,
        mut header: ScanSpec,
        mesh_obj: &[u8],
    ) -> Result<(Self, usize), WriteError> {
        header.frames.clear();
        let state = dir.join(STATE_DIR);
        let ident_path = state.join("identity.json");
        fs::create_dir_all(dir).map_err(io(dir))?;
        // The identity is written first: a run killed at any later point is recognised as this
        // scan and resumed.
        if ident_path.exists() {
            let old = fs::read_to_string(&ident_path).map_err(io(&ident_path))?;
            if old != identity {
                return Err(WriteError::Mismatch(format!(
                    "{} holds a different scan (other plan, calibration or options); use another \
                     --out directory, or delete it to start over",
                    dir.display()
                )));
            }
        } else {
            let foreign = fs::read_dir(dir)
                .map_err(io(dir))?
                .filter_map(|e| e.ok())
                .any(|e| e.file_name() != STATE_DIR);
            if foreign {
                return Err(WriteError::Mismatch(format!(
                    "{} is not empty and holds no scan to resume; choose an empty or new --out \
                     directory",
                    dir.display()
                )));
            }
            fs::create_dir_all(&state).map_err(io(&state))?;
            write_atomic(&ident_path, identity.as_bytes())?;
        }
        // Leftover temporaries of an interrupted write.
        fs::create_dir_all(dir.join("frames")).map_err(io(dir))?;
        for d in [dir.to_path_buf(), dir.join("frames"), state.clone()] {
            for e in fs::read_dir(&d).map_err(io(&d))?.flatten() {
                let name = e.file_name().to_string_lossy().to_string();
                if name.starts_with('.') && name.ends_with(".tmp") {
                    let _ = fs::remove_file(e.path());
                }
            }
        }
        if !dir.join(&header.mesh).exists() {
            write_atomic(&dir.join(&header.mesh), mesh_obj)?;
        }
        let journal_path = state.join("journal.jsonl");
        let mut journal = OpenOptions::new()
            .create(true)
            .read(true)
            .append(true)
            .open(&journal_path)
            .map_err(io(&journal_path))?;
        let mut text = Vec::new();
        journal.read_to_end(&mut text).map_err(io(&journal_path))?;
        let mut entries = Vec::new();
        let mut good_len = 0usize;
        for line in text.split_inclusive(|b| *b == b'\n') {
            if !line.ends_with(b"\n") {
                break;
            }
            let Ok(l) = serde_json::from_slice::<JournalLine>(line) else {
                break;
            };
            if l.frame != entries.len()
                || serde_json::from_str::<FrameSpec>(&l.entry).is_err()
                || !image_intact(dir, &l)
            {
                break;
            }
            entries.push(l.entry);
            good_len += line.len();
        }
        if good_len != text.len() {
            journal
                .set_len(good_len as u64)
                .map_err(io(&journal_path))?;
            journal.sync_all().map_err(io(&journal_path))?;
        }
        journal.seek(SeekFrom::End(0)).map_err(io(&journal_path))?;
        let done = entries.len();
        let w = DatasetWriter {
            dir: dir.to_path_buf(),
            header,
            entries,
            journal,
            journal_path,
            last_index: Instant::now(),
            reserve_bytes: 16 << 20,
        };
        w.write_index()?;
        Ok((w, done))
    }

    /// Frames complete so far.
    pub fn done(&self) -> usize {
        self.entries.len()
    }

    /// The image path (relative) of frame `k`.
    pub fn image_name(k: usize) -> String {
        format!("frames/{k:06}.exr")
    }

    /// Records frame `entries.len()`: image atomically, then its journal line (see module docs).
    /// `entry.image` names the file the bytes go to.
    pub fn commit(&mut self, entry: FrameSpec, image_bytes: &[u8]) -> Result<(), WriteError> {
        let k = self.entries.len();
        let need = image_bytes.len() as u64 + 4096 + self.reserve_bytes;
        if let Some(free) = free_bytes(&self.dir)
            && free < need
        {
            return Err(WriteError::DiskFull {
                path: self.dir.display().to_string(),
                frame: k,
                need,
                free,
            });
        }
        let path = self.dir.join(&entry.image);
        write_atomic(&path, image_bytes).map_err(|e| match e {
            WriteError::DiskFull { path, .. } => WriteError::DiskFull {
                path,
                frame: k,
                need,
                free: 0,
            },
            e => e,
        })?;
        let entry_json = serde_json::to_string(&entry).map_err(|e| WriteError::Io {
            path: self.journal_path.display().to_string(),
            source: std::io::Error::other(e),
        })?;
        let line = JournalLine {
            frame: k,
            image: entry.image.clone(),
            bytes: image_bytes.len() as u64,
            crc32: crc32(image_bytes),
            entry: entry_json.clone(),
        };
        let mut text = serde_json::to_string(&line).map_err(|e| WriteError::Io {
            path: self.journal_path.display().to_string(),
            source: std::io::Error::other(e),
        })?;
        text.push('\n');
        self.journal
            .write_all(text.as_bytes())
            .and_then(|_| self.journal.sync_data())
            .map_err(io(&self.journal_path))?;
        self.entries.push(entry_json);
        if self.last_index.elapsed() > Duration::from_secs(5) {
            self.write_index()?;
        }
        Ok(())
    }

    /// Encodes `image` (float32 OpenEXR, or PFM with `pfm`), names it `frames/k.exr` (`.pfm`)
    /// and commits it as frame `k` = [`DatasetWriter::done`]. Returns `k`.
    pub fn add_image(
        &mut self,
        mut entry: FrameSpec,
        image: &Image,
        pfm: bool,
    ) -> Result<usize, WriteError> {
        let k = self.entries.len();
        let bytes = if pfm {
            entry.image = format!("frames/{k:06}.pfm");
            encode_pfm(image)
        } else {
            entry.image = Self::image_name(k);
            encode_exr(image)
        }
        .map_err(|source| WriteError::Image { frame: k, source })?;
        self.commit(entry, &bytes)?;
        Ok(k)
    }

    /// Rewrites `scan.json` from the frames journaled so far: the header pretty-printed, one
    /// frame entry per line, exactly as journaled.
    pub fn write_index(&self) -> Result<(), WriteError> {
        let path = self.dir.join("scan.json");
        let head = serde_json::to_string_pretty(&self.header).map_err(|e| WriteError::Io {
            path: path.display().to_string(),
            source: std::io::Error::other(e),
        })?;
        // `{ ...header..., "frames": [] }` → `{ ...header..., "frames": [ one entry per line ] }`
        let Some(head) = head.strip_suffix("[]\n}") else {
            return Err(WriteError::Mismatch(
                "scan.json header does not end with its empty frame list".into(),
            ));
        };
        let mut text = head.to_string();
        text.push('[');
        for (k, e) in self.entries.iter().enumerate() {
            text.push_str(if k == 0 { "\n    " } else { ",\n    " });
            text.push_str(e);
        }
        text.push_str(if self.entries.is_empty() {
            "]\n}"
        } else {
            "\n  ]\n}"
        });
        write_atomic(&path, (text + "\n").as_bytes())
    }

    /// Records the scan's dark frames and the `noise_floor` the header then carries, and
    /// rewrites `scan.json`.
    pub fn set_dark_frames(
        &mut self,
        dark: Vec<super::DarkFrame>,
        noise_floor: Option<f64>,
    ) -> Result<(), WriteError> {
        self.header.dark_frames = dark;
        self.header.noise_floor = noise_floor;
        self.write_index()
    }

    /// `scan.json` without its frames (format, units, mesh, noise floor, saturation, cameras).
    pub fn header(&self) -> &ScanSpec {
        &self.header
    }

    /// Writes the final `scan.json`.
    pub fn finish(mut self) -> Result<PathBuf, WriteError> {
        self.write_index()?;
        self.last_index = Instant::now();
        Ok(self.dir.join("scan.json"))
    }
}

fn crc32(b: &[u8]) -> u32 {
    crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(b)
}

fn image_intact(dir: &Path, l: &JournalLine) -> bool {
    if l.image.contains("..") || Path::new(&l.image).is_absolute() {
        return false;
    }
    match fs::read(dir.join(&l.image)) {
        Ok(b) => b.len() as u64 == l.bytes && crc32(&b) == l.crc32,
        Err(_) => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::dataset::{FrameChannel, LaserRay};

    fn header() -> ScanSpec {
        ScanSpec::new(
            vec![crate::calib::Calibration::builtin().camera],
            Some(1e-4),
            Some(20.0),
        )
    }

    fn entry(k: usize) -> FrameSpec {
        FrameSpec {
            image: DatasetWriter::image_name(k),
            camera: 0,
            turntable_deg: k as f64,
            exposure_s: 0.01,
            channel: FrameChannel::Rgb,
            laser: Some(LaserRay {
                origin: [0.0; 3],
                direction: [0.0, 0.0, -1.0],
            }),
            galvo: Some([k as u32, 7]),
            levels: Default::default(),
            brackets: Vec::new(),
        }
    }

    fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out = Vec::new();
        for p in ["scan.json", "object.obj", ".subsurf-scan/journal.jsonl"] {
            out.push((p.to_string(), fs::read(dir.join(p)).unwrap()));
        }
        let mut names: Vec<_> = fs::read_dir(dir.join("frames"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
            .collect();
        names.sort();
        for n in names {
            out.push((n.clone(), fs::read(dir.join("frames").join(n)).unwrap()));
        }
        out
    }

    #[test]
    fn torn_journal_and_half_written_frame_are_redone() {
        let a = tempfile::tempdir().unwrap();
        let (mut w, done) = DatasetWriter::open(a.path(), "id", header(), b"o").unwrap();
        assert_eq!(done, 0);
        for k in 0..4 {
            w.commit(entry(k), &[k as u8; 10]).unwrap();
        }
        w.finish().unwrap();

        let b = tempfile::tempdir().unwrap();
        let (mut w, _) = DatasetWriter::open(b.path(), "id", header(), b"o").unwrap();
        for k in 0..3 {
            w.commit(entry(k), &[k as u8; 10]).unwrap();
        }
        drop(w);
        // Frame 3's image renamed but not journaled, frame 2's line torn, a stray temp file.
        fs::write(b.path().join("frames/000003.exr"), b"garbage").unwrap();
        fs::write(b.path().join("frames/.000004.exr.tmp"), b"x").unwrap();
        let j = b.path().join(".subsurf-scan/journal.jsonl");
        let text = fs::read(&j).unwrap();
        fs::write(&j, &text[..text.len() - 7]).unwrap();
        let (mut w, done) = DatasetWriter::open(b.path(), "id", header(), b"o").unwrap();
        assert_eq!(done, 2);
        for k in done..4 {
            w.commit(entry(k), &[k as u8; 10]).unwrap();
        }
        w.finish().unwrap();
        assert_eq!(snapshot(a.path()), snapshot(b.path()));
    }

    #[test]
    fn refuses_foreign_directories_and_other_scans() {
        let d = tempfile::tempdir().unwrap();
        fs::write(d.path().join("holiday.jpg"), b"x").unwrap();
        let e = DatasetWriter::open(d.path(), "id", header(), b"o")
            .err()
            .unwrap();
        assert!(e.to_string().contains("not empty"), "{e}");
        let d = tempfile::tempdir().unwrap();
        DatasetWriter::open(d.path(), "id", header(), b"o").unwrap();
        let e = DatasetWriter::open(d.path(), "other", header(), b"o")
            .err()
            .unwrap();
        assert!(e.to_string().contains("different scan"), "{e}");
    }

    #[test]
    fn full_disk_stops_before_the_frame() {
        let d = tempfile::tempdir().unwrap();
        let (mut w, _) = DatasetWriter::open(d.path(), "id", header(), b"o").unwrap();
        w.commit(entry(0), b"abc").unwrap();
        w.reserve_bytes = u64::MAX / 4;
        let e = w.commit(entry(1), b"def").unwrap_err();
        assert!(matches!(e, WriteError::DiskFull { frame: 1, .. }), "{e}");
        assert!(!d.path().join("frames/000001.exr").exists());
        drop(w);
        let (_, done) = DatasetWriter::open(d.path(), "id", header(), b"o").unwrap();
        assert_eq!(done, 1);
    }
}
