//! Scan datasets (`docs/scan-format.md`, `subsurf-scan/1`): reading and validating `scan.json`, the
//! OBJ mesh and the frame images, and writing the same format. [`ScanSpec`] / [`FrameSpec`] are
//! the one `scan.json` type set and [`DatasetWriter`] the one (crash-safe) writer: `subsurf scan`
//! and `subsurf simulate` both write through them, `subsurf fit` reads them.
//!
//! Contract: a dataset made by any program that follows the format loads without change; unknown
//! keys are ignored; every path a dataset names is confined to the dataset directory. Frames are
//! never all in memory: [`Dataset::read_frame`] loads one image at a time, so the caller streams.
use std::path::{Component, Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::geometry::Camera;

mod alignment;
mod camera_file;
mod hdr;
mod image;
mod ljpeg;
mod mesh;
mod obj;
mod writer;

pub use alignment::{Alignment, Symmetry, Turn, aligned_name};
pub use camera_file::{CLIPPED, FileKind, Levels};
pub use hdr::{Bracket, MergeOptions, merge_hdr};
pub use image::{
    Image, ImageError, bilinear_taps, encode_exr, encode_pfm, read_exr_with_alpha, read_image,
    read_image_with, write_exr, write_pfm,
};
pub use mesh::{Mesh, MeshError, MeshReport, load_obj, obj_bytes, triangle_area, write_obj};
pub use writer::{DatasetWriter, STATE_DIR, WriteError, write_atomic};

/// The only format string this version reads and writes.
pub const FORMAT: &str = "subsurf-scan/1";

/// Why a dataset could not be opened.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// `scan.json` could not be read from disk.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// `scan.json` is not valid JSON or misses a required key.
    #[error("{path} is not a valid scan description: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The cause, with line and column.
        source: serde_json::Error,
    },
    /// The JSON parsed but breaks the contract (wrong format string, bad index, bad number).
    #[error("invalid scan.json: {0}")]
    Invalid(String),
    /// A path in `scan.json` is absolute or leaves the dataset directory.
    #[error("path {0:?} in scan.json is absolute or leaves the dataset directory")]
    PathEscapes(String),
    /// A file that `scan.json` names does not exist.
    #[error("file {0} named in scan.json is missing")]
    Missing(PathBuf),
    /// The mesh could not be loaded.
    #[error(transparent)]
    Mesh(#[from] MeshError),
    /// A frame image could not be read.
    #[error("frame {frame}: {source}")]
    Frame {
        /// Index of the frame in `scan.json`.
        frame: usize,
        /// The cause.
        source: ImageError,
    },
}

/// The laser ray of a frame in the world frame, as the galvo calibration predicts it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LaserRay {
    /// Ray origin, mm.
    pub origin: [f64; 3],
    /// Ray direction (need not be unit length, must not be zero).
    pub direction: [f64; 3],
}

/// Which colour a frame records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum FrameChannel {
    /// All three colours lit at once.
    #[default]
    Rgb,
    /// Only the red laser lit.
    R,
    /// Only the green laser lit.
    G,
    /// Only the blue laser lit.
    B,
}

impl FrameChannel {
    /// The colour channels (0 = r, 1 = g, 2 = b) this frame measures.
    pub fn channels(self) -> &'static [usize] {
        match self {
            FrameChannel::Rgb => &[0, 1, 2],
            FrameChannel::R => &[0],
            FrameChannel::G => &[1],
            FrameChannel::B => &[2],
        }
    }
}

fn default_exposure() -> f64 {
    1.0
}

/// One captured image: which camera, at which turntable angle, with which laser ray.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameSpec {
    /// Image path relative to the dataset directory.
    pub image: String,
    /// Index into `cameras`.
    #[serde(default)]
    pub camera: usize,
    /// Turntable angle in degrees: mesh point `p` is at `R_z(turntable_deg)·p` in the world.
    pub turntable_deg: f64,
    /// Exposure time; radiance is `pixel / exposure_s`.
    #[serde(default = "default_exposure")]
    pub exposure_s: f64,
    /// The colour(s) lit in this frame.
    #[serde(default)]
    pub channel: FrameChannel,
    /// The laser ray the rig's calibration predicts (a prior, not ground truth).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserRay>,
    /// Galvo DAC codes used (the project's rig writes 16-bit codes; other programs may write
    /// wider ones).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub galvo: Option<[u32; 2]>,
    /// Black and white level of this frame's TIFF or PNG file (`black_level`, `white_level`),
    /// over the dataset's.
    #[serde(flatten)]
    pub levels: Levels,
    /// Extension of this project: further exposures of the same view, each at least as long as
    /// `exposure_s` (`image` is the shortest, the one a reader that ignores this key reads
    /// alone), merged with it per pixel into one radiance image by [`Dataset::read_frame`]
    /// ([`merge_hdr`]): the way an HDR capture written by another camera program arrives.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub brackets: Vec<BracketSpec>,
}

/// One further exposure of a frame (`frames[].brackets[]` in `scan.json`): its file, exposure
/// time and, for TIFF and PNG, levels over the frame's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BracketSpec {
    /// Image path relative to the dataset directory, confined like the frame's.
    pub image: String,
    /// Exposure time (s); at least the frame's own `exposure_s`.
    pub exposure_s: f64,
    /// Black and white level of this file (TIFF, PNG), over the frame's and the dataset's.
    #[serde(flatten)]
    pub levels: Levels,
}

impl FrameSpec {
    /// Every image file of this frame, relative to the dataset directory: `image`, then its
    /// brackets' files.
    pub fn files(&self) -> impl Iterator<Item = &str> {
        std::iter::once(self.image.as_str()).chain(self.brackets.iter().map(|b| b.image.as_str()))
    }
}

/// The content of `scan.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanSpec {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always `mm`.
    pub units: String,
    /// OBJ path relative to the dataset directory.
    pub mesh: String,
    /// Radiance (pixel / exposure) under which a pixel is noise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_floor: Option<f64>,
    /// Extension of this project (see `docs/scan-format.md`): raw pixel value at or above which the
    /// sensor clipped. Absent: only infinite pixels count as saturated, or, in a dataset of camera
    /// files, the white level ([`Dataset::saturation`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub saturation: Option<f64>,
    /// Black and white level of the TIFF and PNG frames (`black_level`, `white_level`; a frame
    /// may override either). Raw files carry their own.
    #[serde(flatten)]
    pub levels: Levels,
    /// Extension of this project: how `subsurf align` placed the user's mesh in the object frame
    /// (then `mesh` is the aligned copy). Absent: the mesh was given in the object frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alignment: Option<Alignment>,
    /// Extension of this project: the dark frames (every laser off) `subsurf scan` took, one
    /// per exposure, and what they measured; `noise_floor` is then theirs unless the user gave
    /// one (docs/scan-format.md, [`crate::scan::dark`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dark_frames: Vec<DarkFrame>,
    /// The cameras (the one camera model, [`crate::geometry::Camera`]).
    pub cameras: Vec<Camera>,
    /// The frames, in capture order.
    pub frames: Vec<FrameSpec>,
}

/// One dark frame of a scan (`scan.json`'s `dark_frames`): the camera's record with every laser
/// off, at one exposure of the scan's bracket, and the statistics of its raw pixels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DarkFrame {
    /// The image, relative to the dataset directory (raw values, not divided by the exposure).
    pub image: String,
    /// Exposure, s.
    pub exposure_s: f64,
    /// Median raw value (the offset a black level left).
    pub median: f64,
    /// Robust standard deviation of the raw values (1.4826 × the median absolute deviation):
    /// the read noise.
    pub sigma: f64,
    /// The radiance this frame detects: 3 sigma / exposure_s where the dark level was subtracted
    /// from the lit frames (`subtracted`), else (max(median, 0) + 3 sigma) / exposure_s.
    pub floor: f64,
    /// The second dark frame of the same exposure, whose difference from the first gives
    /// `sigma` without the offset or the sensor's fixed pattern in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub second: Option<String>,
    /// What was subtracted from every lit frame of this exposure before it was written (its
    /// pixels are then light alone); `None`: nothing (older scans, or one dark frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub subtracted: Option<DarkSubtracted>,
}

/// The dark level a scan subtracted from the lit frames of one exposure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DarkSubtracted {
    /// The dark frames' median (`median`) from every pixel: the sensor's fixed pattern is below
    /// what two dark frames resolve.
    Median,
    /// Each pixel's own dark level, the mean of the two dark frames, written as this image
    /// (raw values): the fixed pattern stands above the noise of that mean.
    PerPixel {
        /// The level image, relative to the dataset directory.
        image: String,
    },
}

/// Rejects absolute paths and any `..`, so a dataset can only name files inside its directory.
pub fn confined_path(dir: &Path, rel: &str) -> Result<PathBuf, DatasetError> {
    let p = Path::new(rel);
    if rel.is_empty() || rel.starts_with('/') || rel.starts_with('\\') || rel.contains(':') {
        return Err(DatasetError::PathEscapes(rel.to_owned()));
    }
    for c in p.components() {
        match c {
            Component::Normal(_) | Component::CurDir => {}
            _ => return Err(DatasetError::PathEscapes(rel.to_owned())),
        }
    }
    if rel.split(['/', '\\']).any(|s| s == "..") {
        return Err(DatasetError::PathEscapes(rel.to_owned()));
    }
    Ok(dir.join(p))
}

fn finite_all(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

impl ScanSpec {
    /// The dataset-level part of a new `scan.json` (no frames yet): this version's format and
    /// units, the mesh as `object.obj`.
    pub fn new(cameras: Vec<Camera>, noise_floor: Option<f64>, saturation: Option<f64>) -> Self {
        ScanSpec {
            format: FORMAT.into(),
            units: "mm".into(),
            mesh: "object.obj".into(),
            noise_floor,
            saturation,
            levels: Levels::default(),
            alignment: None,
            dark_frames: Vec::new(),
            cameras,
            frames: Vec::new(),
        }
    }

    /// Checks every rule of the contract that does not need the file system.
    pub fn validate(&self) -> Result<(), DatasetError> {
        let bad = |m: String| Err(DatasetError::Invalid(m));
        if self.format != FORMAT {
            return bad(format!("format is {:?}, expected {FORMAT:?}", self.format));
        }
        if self.units != "mm" {
            return bad(format!("units are {:?}, expected \"mm\"", self.units));
        }
        if let Some(n) = self.noise_floor
            && !(n.is_finite() && n >= 0.0)
        {
            return bad(format!("noise_floor {n} must be finite and >= 0"));
        }
        if let Some(s) = self.saturation
            && !(s.is_finite() && s > 0.0)
        {
            return bad(format!("saturation {s} must be finite and > 0"));
        }
        self.levels
            .check()
            .or_else(|m| bad(format!("dataset levels: {m}")))?;
        if let Some(a) = &self.alignment {
            a.validate()?;
        }
        if self.cameras.is_empty() {
            return bad("no cameras".into());
        }
        for (i, c) in self.cameras.iter().enumerate() {
            c.check().or_else(|m| bad(format!("camera {i}: {m}")))?;
        }
        if self.frames.is_empty() {
            return bad("no frames".into());
        }
        for (i, f) in self.frames.iter().enumerate() {
            if f.camera >= self.cameras.len() {
                return bad(format!("frame {i}: camera {} does not exist", f.camera));
            }
            if !f.turntable_deg.is_finite() {
                return bad(format!("frame {i}: turntable_deg is not finite"));
            }
            if !(f.exposure_s.is_finite() && f.exposure_s > 0.0) {
                return bad(format!("frame {i}: exposure_s must be positive"));
            }
            f.levels
                .check()
                .or_else(|m| bad(format!("frame {i}: {m}")))?;
            for (b, x) in f.brackets.iter().enumerate() {
                if !(x.exposure_s.is_finite() && x.exposure_s > 0.0) {
                    return bad(format!(
                        "frame {i}: bracket {b}: exposure_s must be positive"
                    ));
                }
                if x.exposure_s < f.exposure_s {
                    return bad(format!(
                        "frame {i}: bracket {b} ({}) is exposed {} s, shorter than the frame's \
                         own {} s: name the shortest exposure as the frame's image and \
                         exposure_s (the merged frame is in its units, so its white level stays \
                         the clipping level), the longer ones in brackets",
                        x.image, x.exposure_s, f.exposure_s
                    ));
                }
                x.levels
                    .check()
                    .or_else(|m| bad(format!("frame {i}: bracket {b}: {m}")))?;
            }
            if let Some(l) = &f.laser {
                let d = l.direction;
                if !finite_all(&l.origin) || !finite_all(&d) || d == [0.0; 3] {
                    return bad(format!("frame {i}: laser ray must be finite and non-zero"));
                }
            }
        }
        for (i, d) in self.dark_frames.iter().enumerate() {
            let numbers = [d.median, d.sigma, d.floor];
            if !(d.exposure_s.is_finite()
                && d.exposure_s > 0.0
                && numbers.iter().all(|v| v.is_finite()))
                || d.sigma < 0.0
                || d.floor < 0.0
            {
                return bad(format!(
                    "dark_frames[{i}]: exposure_s must be positive and median, sigma, floor \
                     finite (sigma and floor not negative)"
                ));
            }
            confined_path(Path::new("."), &d.image)?;
        }
        Ok(())
    }
}

/// How often this process read the frames' images ([`Dataset::read_frame`]): a fit reads each
/// frame once (the extraction pass), or none when the sample cache serves.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct FrameReads {
    /// Reads in all.
    pub total: u64,
    /// Frames read at least once.
    pub frames: usize,
    /// The most reads of one frame.
    pub most: u32,
}

/// An opened, validated dataset: its description and mesh; frames are read on demand.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The dataset directory.
    pub dir: PathBuf,
    /// The manifest file read (`dir/scan.json`, or the JSON file given).
    pub manifest: PathBuf,
    /// `scan.json`.
    pub spec: ScanSpec,
    /// The mesh, in the object frame.
    pub mesh: Mesh,
    /// What loading the mesh found (degenerate and duplicate faces).
    pub mesh_report: MeshReport,
    /// How many frames are (or have a bracket that is) camera files (TIFF, PNG, DNG: decoded
    /// with the white level at [`CLIPPED`]), told by their file names' extensions (opening every frame here would read
    /// each twice per run; the decoder tells the kind by the first bytes).
    pub camera_files: usize,
    /// Reads of each frame's image by this process (shared by clones).
    reads: std::sync::Arc<Vec<std::sync::atomic::AtomicU32>>,
}

impl Dataset {
    /// The same dataset with another mesh of the same object (a coarser level of detail,
    /// [`crate::lod`]): the frames, cameras and read counts are shared.
    pub fn with_mesh(&self, mesh: Mesh) -> Dataset {
        Dataset {
            mesh,
            mesh_report: MeshReport::default(),
            ..self.clone()
        }
    }

    /// Opens a dataset given as its folder (`dir/scan.json` is read) or as its manifest file
    /// itself (`dir/scan.json`, or any JSON file: its folder is the dataset's): users pass either,
    /// and every `--scan` goes through here. Validates the manifest, checks that every named file
    /// exists inside the folder, and loads the mesh. Images are not read here.
    pub fn open(dir: impl AsRef<Path>) -> Result<Dataset, DatasetError> {
        let given = dir.as_ref();
        let (dir, path) = if given.is_file() {
            let parent = given
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or_else(|| Path::new("."));
            (parent.to_path_buf(), given.to_path_buf())
        } else {
            (given.to_path_buf(), given.join("scan.json"))
        };
        let text = std::fs::read_to_string(&path).map_err(|source| DatasetError::Io {
            path: path.clone(),
            source,
        })?;
        let spec: ScanSpec = serde_json::from_str(&text).map_err(|source| DatasetError::Json {
            path: path.clone(),
            source,
        })?;
        spec.validate()?;
        let mesh_path = confined_path(&dir, &spec.mesh)?;
        if !mesh_path.is_file() {
            return Err(DatasetError::Missing(mesh_path));
        }
        let mut camera_files = 0;
        for f in &spec.frames {
            for name in f.files() {
                let p = confined_path(&dir, name)?;
                if !p.is_file() {
                    return Err(DatasetError::Missing(p));
                }
            }
            if f.files().any(is_camera_file_name) {
                camera_files += 1;
            }
        }
        if camera_files > 0
            && let Some(s) = spec.saturation
            && s > CLIPPED
        {
            return Err(DatasetError::Invalid(format!(
                "saturation {s}: camera files (TIFF, PNG, DNG) are read with the white level at \
                 {CLIPPED}, so nothing reaches {s}; leave saturation out (the white level is \
                 the clipping level) or give it in those units"
            )));
        }
        let (mesh, mesh_report) = load_obj(&mesh_path)?;
        let reads = (0..spec.frames.len()).map(|_| Default::default()).collect();
        Ok(Dataset {
            dir,
            manifest: path,
            spec,
            mesh,
            mesh_report,
            camera_files,
            reads: std::sync::Arc::new(reads),
        })
    }

    /// A dataset being written (`subsurf scan`): its directory, `scan.json` so far and mesh,
    /// nothing checked on disk.
    pub fn in_progress(
        dir: PathBuf,
        spec: ScanSpec,
        mesh: Mesh,
        mesh_report: MeshReport,
    ) -> Dataset {
        let reads = (0..spec.frames.len()).map(|_| Default::default()).collect();
        let camera_files = spec
            .frames
            .iter()
            .filter(|f| f.files().any(is_camera_file_name))
            .count();
        Dataset {
            manifest: dir.join("scan.json"),
            dir,
            spec,
            mesh,
            mesh_report,
            camera_files,
            reads: std::sync::Arc::new(reads),
        }
    }

    /// How often each frame's image was read by this process, per frame.
    pub fn frame_read_counts(&self) -> Vec<u32> {
        use std::sync::atomic::Ordering;
        self.reads
            .iter()
            .map(|r| r.load(Ordering::Relaxed))
            .collect()
    }

    /// [`Dataset::frame_read_counts`] summed up.
    pub fn frame_reads(&self) -> FrameReads {
        let c = self.frame_read_counts();
        FrameReads {
            total: c.iter().map(|&n| u64::from(n)).sum(),
            frames: c.iter().filter(|&&n| n > 0).count(),
            most: c.iter().copied().max().unwrap_or(0),
        }
    }

    /// The raw value at which frames clip, for spot detection and samples: `saturation` from
    /// `scan.json`, else, when frames are camera files, their white level ([`CLIPPED`] after
    /// decoding); `None` (only infinite pixels clip) for float frames without it.
    pub fn saturation(&self) -> Option<f64> {
        self.spec
            .saturation
            .or((self.camera_files > 0).then_some(CLIPPED))
    }

    /// Reads frame `k`'s image, checking that its size matches its camera. A frame with
    /// `brackets` is their HDR merge with its own image ([`merge_hdr`], clipping at
    /// [`Dataset::saturation`] in each file's units) in the units of its own (shortest)
    /// exposure: a pixel divided by `exposure_s` is radiance, as for one file, and a pixel
    /// clipped in every exposure stays at or above the saturation, so samples touching it are
    /// dropped and spots fitted from their ring as for one file.
    pub fn read_frame(&self, k: usize) -> Result<Image, DatasetError> {
        let f = self.spec.frames.get(k).ok_or_else(|| {
            DatasetError::Invalid(format!(
                "frame {k} requested, dataset has {}",
                self.spec.frames.len()
            ))
        })?;
        if let Some(n) = self.reads.get(k) {
            n.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        let levels = f.levels.or(self.spec.levels);
        let img = self.read_file(k, f, &f.image, levels)?;
        if f.brackets.is_empty() {
            return Ok(img);
        }
        let mut brackets = vec![Bracket {
            exposure_s: f.exposure_s,
            image: img,
        }];
        for b in &f.brackets {
            let image = self.read_file(k, f, &b.image, b.levels.or(levels))?;
            if image.channels != brackets[0].image.channels {
                return Err(DatasetError::Frame {
                    frame: k,
                    source: ImageError::Format(format!(
                        "bracket {} has {} channels, the frame's image {} has {}",
                        b.image, image.channels, f.image, brackets[0].image.channels
                    )),
                });
            }
            brackets.push(Bracket {
                exposure_s: b.exposure_s,
                image,
            });
        }
        let opts = MergeOptions {
            saturation: self.saturation().map_or(f32::INFINITY, |s| s as f32),
            noise_floor: 0.0,
        };
        let mut merged = merge_hdr(&brackets, &opts)
            .map_err(|source| DatasetError::Frame { frame: k, source })?;
        for v in &mut merged.data {
            *v = (*v as f64 * f.exposure_s) as f32;
        }
        Ok(merged)
    }

    /// One image file of frame `f` (its own or a bracket's), checked against its camera.
    fn read_file(
        &self,
        k: usize,
        f: &FrameSpec,
        name: &str,
        levels: Levels,
    ) -> Result<Image, DatasetError> {
        let path = confined_path(&self.dir, name)?;
        let img = read_image_with(&path, levels)
            .map_err(|source| DatasetError::Frame { frame: k, source })?;
        let cam = &self.spec.cameras[f.camera];
        if img.width != cam.width as usize || img.height != cam.height as usize {
            return Err(DatasetError::Frame {
                frame: k,
                source: ImageError::Format(format!(
                    "{name}: image is {}x{}, camera {} is {}x{}",
                    img.width, img.height, f.camera, cam.width, cam.height
                )),
            });
        }
        Ok(img)
    }
}

/// Whether a frame's file name says it is a camera file (TIFF, PNG, DNG): the extension,
/// case-insensitive.
fn is_camera_file_name(name: &str) -> bool {
    Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| {
            ["tif", "tiff", "png", "dng"]
                .iter()
                .any(|c| e.eq_ignore_ascii_case(c))
        })
}

/// Parses a frame selection such as `3,17,40-59` into sorted, unique frame indices.
pub fn parse_frame_list(s: &str) -> Result<Vec<usize>, String> {
    parse_frame_list_checked(s)
}

/// The longest range a frame list may hold (a list read from a file must not allocate without
/// bound): 16.7 million frames, decades of rig time.
pub const MAX_FRAME_RANGE: usize = 1 << 24;

/// Sorted, distinct frame indices as the ranges [`parse_frame_list`] reads, e.g. `0-95,104`.
pub fn format_frame_list(frames: &[usize]) -> String {
    let mut v = frames.to_vec();
    v.sort_unstable();
    v.dedup();
    let mut parts = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let mut j = i;
        while j + 1 < v.len() && v[j + 1] == v[j] + 1 {
            j += 1;
        }
        parts.push(if j == i {
            v[i].to_string()
        } else {
            format!("{}-{}", v[i], v[j])
        });
        i = j + 1;
    }
    parts.join(",")
}

fn parse_frame_list_checked(s: &str) -> Result<Vec<usize>, String> {
    let mut out = Vec::new();
    for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        if let Some((a, b)) = part.split_once('-') {
            let a: usize = a
                .trim()
                .parse()
                .map_err(|_| format!("bad frame range {part:?}"))?;
            let b: usize = b
                .trim()
                .parse()
                .map_err(|_| format!("bad frame range {part:?}"))?;
            if b < a {
                return Err(format!("empty frame range {part:?}"));
            }
            if b - a >= MAX_FRAME_RANGE {
                return Err(format!(
                    "frame range {part:?} spans more than {MAX_FRAME_RANGE} frames"
                ));
            }
            out.extend(a..=b);
        } else {
            out.push(
                part.parse()
                    .map_err(|_| format!("bad frame index {part:?}"))?,
            );
        }
    }
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

/// The frames a command works on: `include` (default all) minus `exclude`, both in the syntax
/// of [`parse_frame_list`]; indices beyond the dataset are an error.
pub fn select_frames(
    total: usize,
    include: Option<&str>,
    exclude: Option<&str>,
) -> Result<Vec<usize>, String> {
    let mut frames = match include {
        Some(s) => parse_frame_list(s)?,
        None => (0..total).collect(),
    };
    if let Some(&k) = frames.iter().find(|&&k| k >= total) {
        return Err(format!(
            "frame {k} does not exist (the dataset has {total})"
        ));
    }
    if let Some(ex) = exclude {
        let ex = parse_frame_list(ex)?;
        frames.retain(|k| ex.binary_search(k).is_err());
    }
    Ok(frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_leaving_the_dataset_are_rejected() {
        let d = Path::new("/data/scan");
        assert!(confined_path(d, "frames/0.exr").is_ok());
        assert!(confined_path(d, "./frames/0.exr").is_ok());
        for bad in [
            "../x.exr",
            "frames/../../x.exr",
            "/etc/passwd",
            "",
            "a/..",
            "C:\\x",
        ] {
            assert!(
                matches!(confined_path(d, bad), Err(DatasetError::PathEscapes(_))),
                "{bad}"
            );
        }
    }

    #[test]
    fn a_dataset_opens_from_its_folder_or_its_scan_json() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("scan");
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::write(
            dir.join("object.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        let img = Image {
            width: 4,
            height: 4,
            channels: 3,
            data: vec![0.5; 48],
        };
        write_pfm(&dir.join("frames/0.pfm"), &img).unwrap();
        std::fs::write(
            dir.join("scan.json"),
            r#"{"format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj",
              "cameras": [{"width": 4, "height": 4, "fx": 10.0, "fy": 10.0, "cx": 1.5, "cy": 1.5,
                "camera_from_world": [[1,0,0,0],[0,1,0,0],[0,0,1,50],[0,0,0,1]]}],
              "frames": [{"image": "frames/0.pfm", "turntable_deg": 0.0}]}"#,
        )
        .unwrap();
        let by_dir = Dataset::open(&dir).unwrap();
        let by_file = Dataset::open(dir.join("scan.json")).unwrap();
        assert_eq!(by_dir.dir, dir);
        assert_eq!(by_file.dir, dir);
        assert_eq!(by_file.spec, by_dir.spec);
        by_file.read_frame(0).unwrap();
        // A folder without a manifest still says which file it looked for.
        let e = Dataset::open(tmp.path()).unwrap_err();
        assert!(e.to_string().contains("scan.json"), "{e}");
    }

    /// A dataset of camera files: levels from scan.json (a frame's over the dataset's), the
    /// white level as the saturation, so clipped pixels are dropped as for float frames with
    /// `saturation`; a `saturation` above the white level is refused.
    #[test]
    fn camera_file_frames_read_with_their_levels_and_clip_at_the_white_level() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::write(
            dir.join("object.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        let mut png = Vec::new();
        ::image::DynamicImage::ImageRgb16(::image::ImageBuffer::from_fn(2, 2, |i, _| {
            ::image::Rgb([100u16, 100 + 400 * i as u16, 4200])
        }))
        .write_to(
            &mut std::io::Cursor::new(&mut png),
            ::image::ImageFormat::Png,
        )
        .unwrap();
        std::fs::write(dir.join("frames/0.png"), &png).unwrap();
        std::fs::write(dir.join("frames/1.png"), &png).unwrap();
        let manifest = |saturation: &str| {
            format!(
                r#"{{"format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj",
                  "black_level": 100, "white_level": 900 {saturation},
                  "cameras": [{{"width": 2, "height": 2, "fx": 10.0, "fy": 10.0, "cx": 0.5,
                    "cy": 0.5, "camera_from_world": [[1,0,0,0],[0,1,0,0],[0,0,1,50],[0,0,0,1]]}}],
                  "frames": [{{"image": "frames/0.png", "turntable_deg": 0.0}},
                    {{"image": "frames/1.png", "turntable_deg": 0.0, "white_level": 500}}]}}"#
            )
        };
        std::fs::write(dir.join("scan.json"), manifest("")).unwrap();
        let ds = Dataset::open(dir).unwrap();
        assert_eq!((ds.camera_files, ds.saturation()), (2, Some(CLIPPED)));
        let (a, b) = (ds.read_frame(0).unwrap(), ds.read_frame(1).unwrap());
        assert_eq!(&a.data[..6], &[0.0, 0.0, 5.125, 0.0, 0.5, 5.125]);
        assert_eq!(&b.data[..6], &[0.0, 0.0, 10.25, 0.0, 1.0, 10.25]);
        // Round trip of the keys: the frame's own level, the dataset's.
        assert_eq!(ds.spec.frames[1].levels.white, Some(500.0));
        assert_eq!(ds.spec.levels.black, Some(100.0));
        let text = serde_json::to_string(&ds.spec).unwrap();
        assert!(text.contains("\"white_level\":500.0"), "{text}");
        std::fs::write(dir.join("scan.json"), manifest(", \"saturation\": 4.0")).unwrap();
        let e = Dataset::open(dir).unwrap_err().to_string();
        assert!(e.contains("white level"), "{e}");
        std::fs::write(
            dir.join("scan.json"),
            manifest("").replace("\"white_level\": 900", "\"white_level\": 50"),
        )
        .unwrap();
        assert!(Dataset::open(dir).is_err(), "white below black");
    }

    /// A frame listing brackets (another camera program's HDR capture): 16-bit PNGs of one view
    /// at 10 ms and 40 ms (the longer one with its own white level), merged into the units of
    /// the shortest. A dim pixel is read mostly from the long exposure (finer steps), a pixel
    /// clipped only in the long one from the short one, a pixel clipped in both stays at or
    /// above the saturation (samples touching it are dropped). Bracket paths are confined and
    /// checked like the frame's; an exposure shorter than the frame's own is refused.
    #[test]
    fn bracketed_frames_merge_their_exposures_and_keep_clipped_pixels_clipped() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        std::fs::create_dir_all(dir.join("frames")).unwrap();
        std::fs::write(
            dir.join("object.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        // Radiance (white level = 1 after 10 ms) of the three grey pixels and the DN each
        // exposure records: black 0, white 1000 DN (the long file: 2000, so its DN are twice as
        // fine: decoded values are relative to each file's white level), rounded, clipped.
        let radiance = [0.0123, 0.6, 3.0];
        let png = |name: &str, gain: f64, white: f64| {
            let dn: Vec<u16> = radiance
                .iter()
                .map(|r| (r * gain * white).round().min(white) as u16)
                .collect();
            let mut bytes = Vec::new();
            ::image::DynamicImage::ImageLuma16(
                ::image::ImageBuffer::from_raw(3, 1, dn.clone()).unwrap(),
            )
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                ::image::ImageFormat::Png,
            )
            .unwrap();
            std::fs::write(dir.join(name), bytes).unwrap();
            dn
        };
        assert_eq!(png("frames/0a.png", 1.0, 1000.0), [12, 600, 1000]);
        assert_eq!(png("frames/0b.png", 4.0, 2000.0), [98, 2000, 2000]);
        let manifest = |frame: &str| {
            format!(
                r#"{{"format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj",
                  "white_level": 1000,
                  "cameras": [{{"width": 3, "height": 1, "fx": 10.0, "fy": 10.0, "cx": 1.0,
                    "cy": 0.0, "camera_from_world": [[1,0,0,0],[0,1,0,0],[0,0,1,50],[0,0,0,1]]}}],
                  "frames": [{frame}]}}"#
            )
        };
        let frame = |first: &str, exposure: f64, second: &str| {
            format!(
                r#"{{"image": "{first}", "turntable_deg": 0.0, "exposure_s": {exposure},
                  "brackets": [{{"image": "{second}", "exposure_s": 0.04, "white_level": 2000}}]}}"#
            )
        };
        std::fs::write(
            dir.join("scan.json"),
            manifest(&frame("frames/0a.png", 0.01, "frames/0b.png")),
        )
        .unwrap();
        let ds = Dataset::open(dir).unwrap();
        assert_eq!((ds.camera_files, ds.saturation()), (1, Some(CLIPPED)));
        let m = ds.read_frame(0).unwrap();
        assert_eq!(
            ds.frame_reads().total,
            1,
            "one read of the frame, all its files"
        );
        // Dim: both brackets count, the long one (weight 4 × its 4 times larger hat) most:
        // between the short one's 12 DN and the long one's 98 DN / 4, nearer the latter.
        let (short, long) = (0.012f32, 98.0 / 2000.0 / 4.0);
        assert!(m.data[0] > short && m.data[0] < long, "{}", m.data[0]);
        assert!(
            (m.data[0] - long).abs() < 0.1 * (long - short),
            "{}",
            m.data[0]
        );
        // Clipped in the long exposure only: the short one's value, unclipped.
        assert!((m.data[1] - 0.6).abs() < 1e-6, "{}", m.data[1]);
        // Clipped in both: still clipped at the dataset's saturation.
        assert!(m.data[2] as f64 >= CLIPPED, "{}", m.data[2]);
        // The bracket survives a round trip; a frame without brackets writes no key.
        let text = serde_json::to_string(&ds.spec).unwrap();
        assert!(
            text.contains("\"brackets\":[{\"image\":\"frames/0b.png\""),
            "{text}"
        );
        let mut plain = ds.spec.clone();
        plain.frames[0].brackets.clear();
        assert!(!serde_json::to_string(&plain).unwrap().contains("brackets"));

        for (bad, want) in [
            (
                frame("frames/0a.png", 0.01, "../0b.png"),
                "leaves the dataset",
            ),
            (frame("frames/0a.png", 0.01, "frames/none.png"), "missing"),
            (frame("frames/0a.png", 0.05, "frames/0b.png"), "shorter"),
        ] {
            std::fs::write(dir.join("scan.json"), manifest(&bad)).unwrap();
            let e = Dataset::open(dir).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        }
        // A bracket of another size than its camera is an error naming the file.
        ::image::DynamicImage::ImageLuma16(::image::ImageBuffer::new(2, 1))
            .save(dir.join("frames/0c.png"))
            .unwrap();
        std::fs::write(
            dir.join("scan.json"),
            manifest(&frame("frames/0a.png", 0.01, "frames/0c.png")),
        )
        .unwrap();
        let e = Dataset::open(dir).unwrap().read_frame(0).unwrap_err();
        assert!(e.to_string().contains("0c.png"), "{e}");
    }

    #[test]
    fn frame_lists_parse() {
        assert_eq!(
            parse_frame_list("3,17,40-42, 17").unwrap(),
            vec![3, 17, 40, 41, 42]
        );
        assert!(parse_frame_list("5-2").is_err());
        assert!(parse_frame_list("x").is_err());
    }

    #[test]
    fn the_documented_example_parses_and_validates() {
        let text = r#"{
          "format": "subsurf-scan/1", "units": "mm", "mesh": "object.obj", "noise_floor": 1e-4,
          "unknown_key": {"ignored": true},
          "cameras": [{"width": 128, "height": 128, "fx": 3200.0, "fy": 3200.0, "cx": 63.5,
            "cy": 63.5, "distortion": [0.0, 0.0, 0.0, 0.0, 0.0],
            "camera_from_world": [[1,0,0,0],[0,-1,0,0],[0,0,-1,600],[0,0,0,1]]}],
          "frames": [{"image": "frames/000000.exr", "camera": 0, "turntable_deg": 0.0,
            "exposure_s": 0.01, "channel": "rgb",
            "laser": {"origin": [0, 0, 850], "direction": [0, 0, -1]}, "galvo": [2048, 2048]},
            {"image": "frames/000001.exr", "turntable_deg": 10.0, "channel": "g"}]
        }"#;
        let s: ScanSpec = serde_json::from_str(text).unwrap();
        s.validate().unwrap();
        assert_eq!(s.frames[1].exposure_s, 1.0);
        assert_eq!(s.frames[1].channel, FrameChannel::G);
        let mut bad = s.clone();
        bad.frames[0].camera = 3;
        assert!(bad.validate().is_err());
        let mut bad = s;
        bad.format = "subsurf-scan/2".into();
        assert!(bad.validate().is_err());
    }
}
