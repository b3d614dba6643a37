//! Replay: a recorded dataset served as the rig and camera (`subsurf scan --replay`), so any
//! planner can be judged on recorded scans (the shared outside datasets) and a dense scan
//! re-planned after the fact.
//!
//! The candidates are the recorded frames (their turntable angles and laser rays) minus those
//! excluded; each frame a planner asks for is copied, with its camera files and exposure
//! brackets, into the output as frame k of a normal dataset (`docs/scan-format.md`), through the
//! one dataset writer, so a replay killed at any point resumes like a scan. Rig time is the
//! simulated rig's timing model over the order asked for ([`super::adaptive::rig_seconds`]).
use std::path::{Path, PathBuf};

use super::adaptive::{AdaptiveError, Candidate, FrameSource};
use super::plan::{RigTiming, predicted_spot};
use crate::dataset::{Dataset, DatasetError, DatasetWriter, WriteError, confined_path};
use crate::geometry::Scene;
use crate::progress::Progress;

/// Why a replay could not be set up.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReplayError {
    /// The recorded dataset could not be read.
    #[error("the recorded scan {path}")]
    Dataset {
        /// Its directory.
        path: PathBuf,
        /// Why.
        #[source]
        source: DatasetError,
    },
    /// The output could not be opened (another scan there, disk).
    #[error(transparent)]
    Write(#[from] WriteError),
    /// The excluded frames name frames the dataset does not have.
    #[error("{0}")]
    Frames(String),
}

/// A recorded dataset served frame by frame into an output dataset.
pub struct Replay {
    src: Dataset,
    out: PathBuf,
    writer: DatasetWriter,
    cands: Vec<Candidate>,
    timing: RigTiming,
    exposures_s: Vec<f64>,
}

impl Replay {
    /// Opens the recorded dataset `src` (its directory or `scan.json`) to be replayed into
    /// `out` (created, or resumed if it holds this replay), every frame but `exclude` a
    /// candidate.
    pub fn open(src: &Path, out: &Path, exclude: &[usize]) -> Result<Replay, ReplayError> {
        let ds = Dataset::open(src).map_err(|source| ReplayError::Dataset {
            path: src.to_path_buf(),
            source,
        })?;
        let n = ds.spec.frames.len();
        if let Some(k) = exclude.iter().find(|&&k| k >= n) {
            return Err(ReplayError::Frames(format!(
                "frame {k} does not exist (the recorded scan has {n})"
            )));
        }
        let dataset_err = |source| ReplayError::Dataset {
            path: src.to_path_buf(),
            source,
        };
        let scene = Scene::new(ds.mesh.clone())
            .map_err(|e| dataset_err(DatasetError::Invalid(e.to_string())))?;
        let cands: Vec<Candidate> = ds
            .spec
            .frames
            .iter()
            .enumerate()
            .filter(|(k, _)| !exclude.contains(k))
            .map(|(k, f)| Candidate {
                id: k,
                turntable_deg: f.turntable_deg,
                galvo: f
                    .galvo
                    .map(|g| g.map(|c| u16::try_from(c).unwrap_or(u16::MAX))),
                x_i: f.laser.as_ref().and_then(|l| {
                    let cam = ds.spec.cameras.get(f.camera)?;
                    predicted_spot(&scene, cam, f.turntable_deg, l.origin, l.direction)
                }),
            })
            .collect();
        let mesh_path = confined_path(&ds.dir, &ds.spec.mesh).map_err(dataset_err)?;
        let mesh_obj = std::fs::read(&mesh_path).map_err(|source| {
            dataset_err(DatasetError::Io {
                path: mesh_path.clone(),
                source,
            })
        })?;
        let mut header = ds.spec.clone();
        header.frames.clear();
        let identity = serde_json::json!({
            "replay": ds.dir.canonicalize().unwrap_or_else(|_| ds.dir.clone()),
            "scan_json_crc32": crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC)
                .checksum(&std::fs::read(ds.dir.join("scan.json")).unwrap_or_default()),
            "exclude": exclude,
        });
        let (writer, _) = DatasetWriter::open(
            out,
            &serde_json::to_string_pretty(&identity).unwrap_or_default(),
            header,
            &mesh_obj,
        )?;
        // A frame's bracket: what the rig would expose for it; merged frames count once.
        let exposures_s = match ds.spec.frames.first() {
            Some(f) if !f.brackets.is_empty() => {
                let mut e = vec![f.exposure_s];
                e.extend(f.brackets.iter().map(|b| b.exposure_s));
                e
            }
            Some(f) => vec![f.exposure_s],
            None => vec![super::setup::DEFAULT_EXPOSURE_S],
        }
        .into_iter()
        .map(|e| if e.is_finite() && e > 0.0 { e } else { 0.0 })
        .collect();
        let timing = super::setup::rig_timing(
            &subsurf_firmware::sim::SimParams::default().profile,
            None,
            None,
            0,
        );
        Ok(Replay {
            src: ds,
            out: out.to_path_buf(),
            writer,
            cands,
            timing,
            exposures_s,
        })
    }

    /// Copies recorded frame `f` as the output's next frame.
    fn copy(&mut self, f: usize) -> Result<(), AdaptiveError> {
        let k = self.writer.done();
        let mut spec = self
            .src
            .spec
            .frames
            .get(f)
            .cloned()
            .ok_or_else(|| AdaptiveError::Invalid(format!("no recorded frame {f}")))?;
        let read = |rel: &str| -> Result<(Vec<u8>, String), AdaptiveError> {
            let p = confined_path(&self.src.dir, rel)?;
            let bytes = std::fs::read(&p).map_err(|source| DatasetError::Io {
                path: p.clone(),
                source,
            })?;
            let ext = p
                .extension()
                .and_then(|e| e.to_str())
                .filter(|e| e.chars().all(|c| c.is_ascii_alphanumeric()))
                .unwrap_or("bin")
                .to_string();
            Ok((bytes, ext))
        };
        // Brackets first: the journal line of the main image commits the frame.
        for (j, b) in spec.brackets.iter_mut().enumerate() {
            let (bytes, ext) = read(&b.image)?;
            let name = format!("frames/{k:06}-b{j}.{ext}");
            crate::dataset::write_atomic(&self.out.join(&name), &bytes)?;
            b.image = name;
        }
        let (bytes, ext) = read(&spec.image)?;
        spec.image = format!("frames/{k:06}.{ext}");
        self.writer.commit(spec, &bytes)?;
        Ok(())
    }

    /// Frames in the output.
    pub fn written(&self) -> usize {
        self.writer.done()
    }

    /// The recorded dataset.
    pub fn recorded(&self) -> &Dataset {
        &self.src
    }
}

impl FrameSource for Replay {
    fn candidates(&self) -> &[Candidate] {
        &self.cands
    }
    fn dir(&self) -> &Path {
        &self.out
    }
    fn done(&self) -> usize {
        self.writer.done()
    }
    fn acquire(&mut self, order: &[usize], progress: &dyn Progress) -> Result<(), AdaptiveError> {
        if let Some(id) = order
            .iter()
            .find(|id| !self.cands.iter().any(|c| c.id == **id))
        {
            return Err(AdaptiveError::Invalid(format!(
                "frame {id} is not a candidate of this replay (excluded or absent)"
            )));
        }
        progress.start("replay", order.len() as u64);
        progress.set_position(self.writer.done() as u64);
        while self.writer.done() < order.len() {
            self.copy(order[self.writer.done()])?;
            progress.inc(1);
        }
        self.writer.write_index()?;
        Ok(())
    }
    fn timing(&self) -> &RigTiming {
        &self.timing
    }
    fn exposures_s(&self) -> &[f64] {
        &self.exposures_s
    }
    fn describe(&self) -> String {
        format!("replay of {}", self.src.dir.display())
    }
}
