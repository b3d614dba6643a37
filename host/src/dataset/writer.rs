//! Writing a dataset: mesh first, frames one at a time (never all in memory), `scan.json` last, so
//! an interrupted capture never leaves a description that names missing images.
use std::path::{Path, PathBuf};

use super::{
    CameraSpec, DatasetError, FORMAT, FrameSpec, Image, Mesh, ScanSpec, write_exr, write_obj,
    write_pfm,
};

/// Streams a dataset to disk.
#[derive(Debug)]
pub struct DatasetWriter {
    dir: PathBuf,
    spec: ScanSpec,
    pfm: bool,
}

impl DatasetWriter {
    /// Creates `dir` (and `dir/frames`) and writes the mesh as `object.obj`. With `pfm` frames are
    /// written as PFM (uncompressed, quick), otherwise as float32 OpenEXR.
    pub fn create(
        dir: &Path,
        mesh: &Mesh,
        cameras: Vec<CameraSpec>,
        noise_floor: Option<f64>,
        saturation: Option<f64>,
        pfm: bool,
    ) -> Result<DatasetWriter, DatasetError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| DatasetError::Io { path, source }
        };
        let frames = dir.join("frames");
        std::fs::create_dir_all(&frames).map_err(io(&frames))?;
        write_obj(&dir.join("object.obj"), mesh)?;
        Ok(DatasetWriter {
            dir: dir.to_path_buf(),
            spec: ScanSpec {
                format: FORMAT.into(),
                units: "mm".into(),
                mesh: "object.obj".into(),
                noise_floor,
                saturation,
                cameras,
                frames: Vec::new(),
            },
            pfm,
        })
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Number of frames written so far.
    pub fn frame_count(&self) -> usize {
        self.spec.frames.len()
    }

    /// Writes one frame's image and records it; `frame.image` is replaced by the file's name.
    /// Returns the frame's index.
    pub fn add_frame(
        &mut self,
        mut frame: FrameSpec,
        image: &Image,
    ) -> Result<usize, DatasetError> {
        let k = self.spec.frames.len();
        let ext = if self.pfm { "pfm" } else { "exr" };
        frame.image = format!("frames/{k:06}.{ext}");
        let path = self.dir.join(&frame.image);
        let res = if self.pfm {
            write_pfm(&path, image)
        } else {
            write_exr(&path, image)
        };
        res.map_err(|source| DatasetError::Frame { frame: k, source })?;
        self.spec.frames.push(frame);
        Ok(k)
    }

    /// Validates and writes `scan.json` (through a temporary file and a rename).
    pub fn finish(self) -> Result<PathBuf, DatasetError> {
        self.spec.validate()?;
        let path = self.dir.join("scan.json");
        let tmp = self.dir.join("scan.json.tmp");
        let text =
            serde_json::to_string_pretty(&self.spec).map_err(|source| DatasetError::Json {
                path: path.clone(),
                source,
            })?;
        std::fs::write(&tmp, text).map_err(|source| DatasetError::Io {
            path: tmp.clone(),
            source,
        })?;
        std::fs::rename(&tmp, &path).map_err(|source| DatasetError::Io {
            path: path.clone(),
            source,
        })?;
        Ok(path)
    }
}
