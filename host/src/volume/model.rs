//! The volume model as a file: the medium on a grid of cells over the object, its phase
//! function and boundary, the mesh that bounds it and what its fit saw (docs/model-format.md,
//! "The volume model").
//!
//! The file is JSON: a handful of numbers for a homogeneous medium, and a grid that any path
//! tracer can read cell by cell when the medium varies. Reading checks every field, so a model
//! that was read is one the tracer can trace: σ_t > 0, 0 < albedo < 1, |g| < 1, cells of
//! positive size, as many cells as the grid's dimensions say, and a mesh whose triangles index
//! its vertices.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::dielectric::Surface;
use super::fit::{Homogeneous, HomogeneousFit, VolumeFitError};
use super::medium::GridChannel;
use crate::dataset::{Dataset, Image, Mesh};
use crate::geometry::Scene;

/// The smallest GGX width the dielectric tracer follows.
pub const MIN_ROUGHNESS: f64 = 1e-3;

/// The `format` of a volume model file.
pub const FORMAT: &str = "subsurf-volume";
/// The `version` this build reads and writes.
pub const VERSION: u32 = 1;

/// A scattering volume: the medium inside the object's mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolumeModel {
    /// Henyey-Greenstein asymmetry of the phase function, the same in every cell.
    pub g: f64,
    /// What light does where it crosses the mesh.
    pub boundary: BoundaryModel,
    /// The medium.
    pub grid: MediumGrid,
    /// The surface that bounds the medium.
    pub mesh: VolumeMesh,
    /// What the fit saw and how it went.
    pub fit: FitInfo,
}

/// What light does at the mesh.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum BoundaryModel {
    /// The medium outside has the object's index: light crosses the surface unbent.
    IndexMatched,
    /// A rough dielectric interface of index `ior` and GGX width `roughness`
    /// ([`super::dielectric`]).
    Dielectric {
        /// Index of refraction inside over outside.
        ior: f64,
        /// GGX roughness α (0: smooth).
        roughness: f64,
    },
}

impl BoundaryModel {
    /// The file's boundary of the tracer's.
    pub fn of(s: Surface) -> BoundaryModel {
        match s {
            Surface::IndexMatched => BoundaryModel::IndexMatched,
            Surface::RoughDielectric { ior, alpha } => BoundaryModel::Dielectric {
                ior,
                roughness: alpha,
            },
        }
    }

    /// The tracer's boundary (`roughness` is the GGX width α, [`super::dielectric`]); a smooth
    /// dielectric is refused.
    pub fn surface(self) -> Result<Surface, VolumeError> {
        match self {
            BoundaryModel::IndexMatched => Ok(Surface::IndexMatched),
            BoundaryModel::Dielectric { ior, roughness } if roughness < MIN_ROUGHNESS => {
                Err(VolumeError::Dielectric { ior, roughness })
            }
            BoundaryModel::Dielectric { ior, roughness } => Ok(Surface::RoughDielectric {
                ior,
                alpha: roughness,
            }),
        }
    }
}

impl std::str::FromStr for BoundaryModel {
    type Err = String;
    /// `index-matched`, or `dielectric:IOR:ROUGHNESS` (the GGX width α).
    fn from_str(s: &str) -> Result<BoundaryModel, String> {
        let bad = || format!("boundary `{s}`: index-matched or dielectric:IOR:ROUGHNESS");
        if s == "index-matched" {
            return Ok(BoundaryModel::IndexMatched);
        }
        let mut it = s.strip_prefix("dielectric:").ok_or_else(bad)?.split(':');
        let (Some(i), Some(r), None) = (it.next(), it.next(), it.next()) else {
            return Err(bad());
        };
        let (ior, roughness): (f64, f64) =
            (i.parse().map_err(|_| bad())?, r.parse().map_err(|_| bad())?);
        let b = BoundaryModel::Dielectric { ior, roughness };
        if !(ior.is_finite() && ior > 0.0) || b.surface().is_err() || roughness > 1.0 {
            return Err(format!(
                "boundary `{s}`: the index must be > 0, the roughness {MIN_ROUGHNESS} to 1"
            ));
        }
        Ok(b)
    }
}

/// The medium on a regular grid of cells in the object frame; σ_t and albedo constant within a
/// cell, per colour channel (r, g, b).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MediumGrid {
    /// The grid's minimum corner, object frame, mm.
    pub origin: [f64; 3],
    /// A cell's size per axis, mm.
    pub cell_mm: [f64; 3],
    /// Cells per axis.
    pub dims: [usize; 3],
    /// Extinction per cell and channel, 1/mm; x fastest, then y, then z.
    pub sigma_t: Vec<[f64; 3]>,
    /// Single-scattering albedo per cell and channel, in the same order.
    pub albedo: Vec<[f64; 3]>,
}

/// The mesh bounding the medium: object frame, mm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeMesh {
    /// Vertex positions, mm.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles, indices into `vertices` (counter-clockwise seen from outside).
    pub triangles: Vec<[u32; 3]>,
}

/// What the fit saw and how it went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FitInfo {
    /// The dataset frames the medium was fitted to (sorted).
    pub frames: Vec<usize>,
    /// Photons traced per frame and round.
    pub photons: usize,
    /// Rounds of trace-and-fit.
    pub rounds: usize,
    /// Per channel the final ring loss: mean squared log ratio of the ring sums.
    pub loss: [f64; 3],
    /// Per channel the rings that loss is over.
    pub rings: [usize; 3],
    /// Wall time of the fit, s.
    pub seconds: f64,
    /// The subsurf version that fitted it.
    pub subsurf_version: String,
}

/// The file as written: the model with its format and version in front.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    format: String,
    version: u32,
    g: f64,
    boundary: BoundaryModel,
    grid: MediumGrid,
    mesh: VolumeMesh,
    fit: FitInfo,
}

/// Just enough of a file to tell its format.
#[derive(Deserialize)]
struct Head {
    format: Option<String>,
    version: Option<u32>,
}

/// Why a volume model cannot be read, written or predicted.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum VolumeError {
    /// The file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// Not JSON, or not the fields of a volume model.
    #[error("not a volume model file: {0}")]
    Json(#[from] serde_json::Error),
    /// The `format` field names another format.
    #[error("format `{0}` is not `{FORMAT}`")]
    Format(String),
    /// A version this build does not read.
    #[error("volume model version {0}: this build reads version {VERSION}")]
    Version(u32),
    /// The grid's dimensions and its arrays disagree.
    #[error("grid dims {dims:?} make {cells} cells, but sigma_t has {sigma_t} and albedo {albedo}")]
    Cells {
        /// The dimensions.
        dims: [usize; 3],
        /// Their product (0 on overflow).
        cells: usize,
        /// Entries of sigma_t.
        sigma_t: usize,
        /// Entries of albedo.
        albedo: usize,
    },
    /// A number outside its range, or not finite.
    #[error("{field} = {value}: must be {rule}")]
    Value {
        /// Where.
        field: String,
        /// The value.
        value: f64,
        /// What it must be.
        rule: &'static str,
    },
    /// A triangle names a vertex the mesh does not have.
    #[error("mesh triangle {triangle} names vertex {index}, the mesh has {vertices}")]
    MeshIndex {
        /// The triangle.
        triangle: usize,
        /// The index.
        index: u32,
        /// Vertices in the mesh.
        vertices: usize,
    },
    /// No triangle bounds the medium.
    #[error("the mesh has no triangles")]
    NoTriangles,
    /// The medium varies from cell to cell: the tracer follows one medium so far.
    #[error("a heterogeneous medium (a grid of {0} cells that differ) is not traced yet")]
    Heterogeneous(usize),
    /// A dielectric boundary the tracer cannot follow: a smooth one (a mirror-like interface is
    /// a delta the next events towards the camera never meet).
    #[error(
        "a dielectric boundary (ior {ior}, roughness {roughness}) is traced only with roughness \
         at least {MIN_ROUGHNESS}"
    )]
    Dielectric {
        /// Its index.
        ior: f64,
        /// Its GGX width.
        roughness: f64,
    },
    /// The trace failed (the mesh, the dataset).
    #[error(transparent)]
    Trace(#[from] VolumeFitError),
}

impl MediumGrid {
    /// One cell spanning `[lo, hi]` (a homogeneous medium over the object's bounds).
    pub fn homogeneous(lo: [f64; 3], hi: [f64; 3], sigma_t: [f64; 3], albedo: [f64; 3]) -> Self {
        MediumGrid {
            origin: lo,
            cell_mm: std::array::from_fn(|a| {
                let d = hi[a] - lo[a];
                if d.is_finite() && d > 0.0 { d } else { 1.0 }
            }),
            dims: [1, 1, 1],
            sigma_t: vec![sigma_t],
            albedo: vec![albedo],
        }
    }

    /// Cells in the grid (0 if the product overflows).
    pub fn cells(&self) -> usize {
        self.dims
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .unwrap_or(0)
    }

    /// The cell holding `p` (object frame, mm), or `None` outside the grid.
    pub fn cell_of(&self, p: [f64; 3]) -> Option<usize> {
        let mut c = [0usize; 3];
        for a in 0..3 {
            let f = ((p[a] - self.origin[a]) / self.cell_mm[a]).floor();
            if !(f >= 0.0 && f < self.dims[a] as f64) {
                return None;
            }
            c[a] = f as usize;
        }
        Some(self.index(c))
    }

    fn index(&self, c: [usize; 3]) -> usize {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }

    /// (σ_t, albedo) at `p`; a point outside the grid takes the nearest cell, so a grid on the
    /// mesh's bounds covers all of its medium.
    pub fn at(&self, p: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let c: [usize; 3] = std::array::from_fn(|a| {
            let f = ((p[a] - self.origin[a]) / self.cell_mm[a]).floor();
            let last = self.dims[a].saturating_sub(1) as f64;
            if f.is_finite() {
                f.clamp(0.0, last) as usize
            } else if f > 0.0 {
                last as usize
            } else {
                0
            }
        });
        let i = self.index(c);
        (self.sigma_t[i], self.albedo[i])
    }

    /// The grid of three channel grids that share their cells (`super::gridfit`'s result).
    pub fn of_channels(g: &[GridChannel; 3]) -> MediumGrid {
        let n = g[0].sigma_t.len();
        MediumGrid {
            origin: g[0].origin,
            cell_mm: g[0].cell_mm,
            dims: g[0].dims,
            sigma_t: (0..n)
                .map(|i| std::array::from_fn(|c| g[c].sigma_t[i]))
                .collect(),
            albedo: (0..n)
                .map(|i| std::array::from_fn(|c| g[c].albedo[i]))
                .collect(),
        }
    }

    /// Whether every cell holds the same medium.
    pub fn is_uniform(&self) -> bool {
        let same = |v: &[[f64; 3]]| v.iter().all(|x| *x == v[0]);
        !self.sigma_t.is_empty() && same(&self.sigma_t) && same(&self.albedo)
    }

    fn validate(&self) -> Result<(), VolumeError> {
        let cells = self.cells();
        if cells == 0 || self.sigma_t.len() != cells || self.albedo.len() != cells {
            return Err(VolumeError::Cells {
                dims: self.dims,
                cells,
                sigma_t: self.sigma_t.len(),
                albedo: self.albedo.len(),
            });
        }
        for a in 0..3 {
            finite(&format!("grid.origin[{a}]"), self.origin[a])?;
            check(
                &format!("grid.cell_mm[{a}]"),
                self.cell_mm[a],
                self.cell_mm[a] > 0.0,
                "a finite size > 0 mm",
            )?;
        }
        for (i, (s, al)) in self.sigma_t.iter().zip(&self.albedo).enumerate() {
            for c in 0..3 {
                check(
                    &format!("grid.sigma_t[{i}][{c}]"),
                    s[c],
                    s[c] > 0.0,
                    "finite and > 0 (1/mm)",
                )?;
                check(
                    &format!("grid.albedo[{i}][{c}]"),
                    al[c],
                    al[c] > 0.0 && al[c] < 1.0,
                    "finite, > 0 and < 1",
                )?;
            }
        }
        Ok(())
    }
}

fn check(field: &str, value: f64, ok: bool, rule: &'static str) -> Result<(), VolumeError> {
    if value.is_finite() && ok {
        Ok(())
    } else {
        Err(VolumeError::Value {
            field: field.to_string(),
            value,
            rule,
        })
    }
}

fn finite(field: &str, value: f64) -> Result<(), VolumeError> {
    check(field, value, true, "finite")
}

impl VolumeMesh {
    /// The mesh's positions and triangles.
    pub fn of(mesh: &Mesh) -> VolumeMesh {
        VolumeMesh {
            vertices: mesh.positions.clone(),
            triangles: mesh.triangles.clone(),
        }
    }

    /// As the tracer's mesh (normals computed; degenerate faces dropped).
    pub fn to_mesh(&self) -> Mesh {
        Mesh::new(self.vertices.clone(), self.triangles.clone()).0
    }

    /// The bounding box (min, max corner).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.vertices {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        (lo, hi)
    }

    fn validate(&self) -> Result<(), VolumeError> {
        if self.triangles.is_empty() {
            return Err(VolumeError::NoTriangles);
        }
        for (i, p) in self.vertices.iter().enumerate() {
            for (a, &x) in p.iter().enumerate() {
                finite(&format!("mesh.vertices[{i}][{a}]"), x)?;
            }
        }
        let n = self.vertices.len();
        for (t, tri) in self.triangles.iter().enumerate() {
            if let Some(&index) = tri.iter().find(|&&i| i as usize >= n) {
                return Err(VolumeError::MeshIndex {
                    triangle: t,
                    index,
                    vertices: n,
                });
            }
        }
        Ok(())
    }
}

impl VolumeModel {
    /// The model of a homogeneous fit `m` over the mesh `mesh` (one cell on its bounds).
    pub fn homogeneous(mesh: &Mesh, m: &Homogeneous, fit: FitInfo) -> VolumeModel {
        let mesh = VolumeMesh::of(mesh);
        let (lo, hi) = mesh.bounds();
        VolumeModel {
            g: m.g,
            boundary: BoundaryModel::of(m.surface),
            grid: MediumGrid::homogeneous(lo, hi, m.sigma_t, m.albedo),
            mesh,
            fit,
        }
    }

    /// Checks every field (the rules of the module docs).
    pub fn validate(&self) -> Result<(), VolumeError> {
        check("g", self.g, self.g.abs() < 1.0, "finite with |g| < 1")?;
        if let BoundaryModel::Dielectric { ior, roughness } = self.boundary {
            check("boundary.ior", ior, ior > 0.0, "finite and > 0")?;
            check(
                "boundary.roughness",
                roughness,
                (0.0..=1.0).contains(&roughness),
                "finite, 0 to 1",
            )?;
        }
        self.grid.validate()?;
        self.mesh.validate()?;
        let f = &self.fit;
        for c in 0..3 {
            check(
                &format!("fit.loss[{c}]"),
                f.loss[c],
                f.loss[c] >= 0.0,
                "finite and ≥ 0",
            )?;
        }
        check("fit.seconds", f.seconds, f.seconds >= 0.0, "finite and ≥ 0")
    }

    /// The file's text (validated first: every number written is finite).
    pub fn to_json(&self) -> Result<String, VolumeError> {
        self.validate()?;
        let file = File {
            format: FORMAT.to_string(),
            version: VERSION,
            g: self.g,
            boundary: self.boundary,
            grid: self.grid.clone(),
            mesh: self.mesh.clone(),
            fit: self.fit.clone(),
        };
        Ok(serde_json::to_string_pretty(&file)? + "\n")
    }

    /// The model of a file's text, every field checked.
    pub fn from_json(text: &str) -> Result<VolumeModel, VolumeError> {
        let head: Head = serde_json::from_str(text)?;
        match head.format.as_deref() {
            Some(FORMAT) => {}
            other => return Err(VolumeError::Format(other.unwrap_or("(none)").to_string())),
        }
        match head.version {
            Some(VERSION) => {}
            Some(v) => return Err(VolumeError::Version(v)),
            None => return Err(VolumeError::Version(0)),
        }
        let f: File = serde_json::from_str(text)?;
        let m = VolumeModel {
            g: f.g,
            boundary: f.boundary,
            grid: f.grid,
            mesh: f.mesh,
            fit: f.fit,
        };
        m.validate()?;
        Ok(m)
    }

    /// Writes the file.
    pub fn write(&self, path: &Path) -> Result<(), VolumeError> {
        let text = self.to_json()?;
        std::fs::write(path, text).map_err(|source| VolumeError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads a file.
    pub fn read(path: &Path) -> Result<VolumeModel, VolumeError> {
        let text = std::fs::read_to_string(path).map_err(|source| VolumeError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        VolumeModel::from_json(&text)
    }

    /// The medium as the homogeneous tracer takes it: a uniform grid; else why it cannot be
    /// traced as one medium.
    pub fn as_homogeneous(&self) -> Result<Homogeneous, VolumeError> {
        let surface = self.boundary.surface()?;
        if !self.grid.is_uniform() {
            return Err(VolumeError::Heterogeneous(self.grid.cells()));
        }
        Ok(Homogeneous {
            sigma_t: self.grid.sigma_t[0],
            albedo: self.grid.albedo[0],
            g: self.g,
            surface,
            loss: [0, 1, 2].map(|c| (self.fit.loss[c], self.fit.rings[c])),
        })
    }

    /// The grid one channel at a time, as the heterogeneous tracer takes it.
    pub fn channels(&self) -> [GridChannel; 3] {
        std::array::from_fn(|c| GridChannel {
            origin: self.grid.origin,
            cell_mm: self.grid.cell_mm,
            dims: self.grid.dims,
            sigma_t: self.grid.sigma_t.iter().map(|s| s[c]).collect(),
            albedo: self.grid.albedo.iter().map(|a| a[c]).collect(),
        })
    }

    /// The model's predictor of frames: its mesh prepared once. A uniform grid is traced as
    /// one medium (likelihood-ratio records, one trace for the three channels); a grid whose
    /// cells differ by delta tracking, one trace per channel.
    pub fn predictor(&self) -> Result<Predictor, VolumeError> {
        let medium = match self.as_homogeneous() {
            Ok(m) => Medium::Homogeneous(m),
            Err(VolumeError::Heterogeneous(_)) => {
                Medium::Grid(Box::new(self.channels()), self.g, self.boundary.surface()?)
            }
            Err(e) => return Err(e),
        };
        let scene = Scene::new(self.mesh.to_mesh()).map_err(VolumeFitError::from)?;
        let boundary = super::trace::Boundary::of(&scene);
        Ok(Predictor {
            scene,
            boundary,
            medium,
        })
    }
}

/// Whether the file at `path` is a volume model (JSON whose `format` is [`FORMAT`]) rather than
/// another model file (the empirical model's PLY): read to tell `subsurf evaluate` and `predict`
/// which model they were given.
pub fn is_volume_file(path: &Path) -> bool {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| serde_json::from_str::<Head>(&t).ok())
        .is_some_and(|h| h.format.as_deref() == Some(FORMAT))
}

/// A volume model ready to predict frames: its mesh as the tracer's scene.
pub struct Predictor {
    scene: Scene,
    boundary: super::trace::Boundary,
    medium: Medium,
}

enum Medium {
    Homogeneous(Homogeneous),
    /// The cells per channel, g and the boundary.
    Grid(Box<[GridChannel; 3]>, f64, Surface),
}

impl Predictor {
    /// Frame `k` of `ds` predicted with `photons` (radiance per watt of laser, the dataset's
    /// units; black where the laser ray misses the mesh), the same image as
    /// [`super::fit::predict`] gives for the same medium, mesh and seed.
    pub fn frame(
        &self,
        ds: &Dataset,
        k: usize,
        photons: usize,
        seed: u64,
    ) -> Result<Image, VolumeError> {
        match &self.medium {
            Medium::Homogeneous(m) => Ok(super::fit::predict_in(
                &self.scene,
                self.boundary,
                ds,
                k,
                m,
                photons,
                seed,
            )?),
            Medium::Grid(grid, g, surface) => Ok(super::fit::frame_image(
                &self.scene,
                ds,
                k,
                &|geo, _, _| {
                    super::medium::grid_image(
                        &self.scene,
                        self.boundary,
                        geo,
                        grid,
                        *g,
                        *surface,
                        photons,
                        seed,
                        k,
                    )
                },
            )?),
        }
    }
}

/// A volume model's frames traced when they are judged, each kept once traced when `keep` is
/// set: the per-pixel and the ring yardsticks read the same frame, and a trace costs seconds
/// where a copy costs nothing.
pub struct TracedFrames<'a> {
    predictor: &'a Predictor,
    ds: &'a Dataset,
    photons: usize,
    seed: u64,
    keep: bool,
    kept: std::sync::Mutex<Vec<(usize, Image)>>,
}

impl<'a> TracedFrames<'a> {
    /// What stands for the folder of these images in errors.
    pub const NAME: &'static str = "(volume model)";

    /// Frames of `ds` traced by `predictor` with `photons` and `seed`.
    pub fn new(
        predictor: &'a Predictor,
        ds: &'a Dataset,
        photons: usize,
        seed: u64,
        keep: bool,
    ) -> TracedFrames<'a> {
        TracedFrames {
            predictor,
            ds,
            photons,
            seed,
            keep,
            kept: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Frame `k`'s image: the kept one, or traced now (and kept when asked to).
    pub fn image(&self, k: usize) -> Result<Image, VolumeError> {
        let found = self
            .kept
            .lock()
            .ok()
            .and_then(|v| v.iter().find(|(f, _)| *f == k).map(|(_, img)| img.clone()));
        if let Some(img) = found {
            return Ok(img);
        }
        let img = self.predictor.frame(self.ds, k, self.photons, self.seed)?;
        if self.keep
            && let Ok(mut v) = self.kept.lock()
        {
            v.push((k, img.clone()));
        }
        Ok(img)
    }
}

/// The frames `frames` of `ds` predicted by the model `model` with `photons` per frame (per
/// channel for a heterogeneous grid), traced on the model's own mesh behind an index-matched
/// boundary; a dielectric boundary is an error until the tracer has it.
pub fn predict_model(
    ds: &Dataset,
    frames: &[usize],
    model: &VolumeModel,
    photons: usize,
    seed: u64,
) -> Result<Vec<(usize, Image)>, VolumeError> {
    let p = model.predictor()?;
    frames
        .iter()
        .map(|&k| Ok((k, p.frame(ds, k, photons, seed)?)))
        .collect()
}

/// Which model `subsurf fit` fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ModelKind {
    /// The empirical per-vertex model (PLY).
    #[default]
    Empirical,
    /// A homogeneous scattering volume (JSON).
    Volume,
}

impl std::str::FromStr for ModelKind {
    type Err = String;
    fn from_str(s: &str) -> Result<ModelKind, String> {
        match s {
            "empirical" => Ok(ModelKind::Empirical),
            "volume" => Ok(ModelKind::Volume),
            _ => Err(format!("model kind `{s}`: empirical or volume")),
        }
    }
}

/// The settings of `subsurf fit --model-kind volume`.
#[derive(Debug, Clone)]
pub struct VolumeFitSettings {
    /// The fit's options (photons, rounds, g, start, floor, seed).
    pub fit: HomogeneousFit,
    /// Where the model goes (`.json`).
    pub out: PathBuf,
    /// Cells along the mesh's longest side of a grid fitted cell by cell after the homogeneous
    /// medium (`super::gridfit`, with its cross-validated penalties); 1: the homogeneous medium.
    pub cells: usize,
}

impl VolumeFitSettings {
    /// The go/no-go's settings (docs/volume.md) for `ds`: 1,500 photons a frame, 12 rounds, a
    /// start at (2/mm, 0.98), g = 0, the scan's noise floor, seed 1.
    pub fn defaults(ds: &Dataset, out: PathBuf) -> VolumeFitSettings {
        VolumeFitSettings {
            fit: HomogeneousFit {
                photons: 1500,
                rounds: 12,
                g: 0.0,
                start: (2.0, 0.98),
                floor: ds.spec.noise_floor.unwrap_or(0.0),
                seed: 1,
                surface: Surface::IndexMatched,
            },
            out,
            cells: 1,
        }
    }

    /// The medium behind `surface`, with `g`: behind a dielectric 6,000 photons a frame and
    /// round, not 1,500 (there a ring's light comes only from where photons meet the surface,
    /// so its sums are noisier; chosen by cross-validation over sample-pebble's training
    /// angles, docs/volume.md).
    pub fn behind(mut self, surface: Surface, g: f64) -> VolumeFitSettings {
        if surface != Surface::IndexMatched {
            self.fit.photons = DIELECTRIC_FIT_PHOTONS;
        }
        (self.fit.surface, self.fit.g) = (surface, g);
        self
    }
}

/// Photons a frame and round of a fit behind a dielectric ([`VolumeFitSettings::behind`]).
pub const DIELECTRIC_FIT_PHOTONS: usize = 6000;

/// Fits a homogeneous volume to the frames `frames` of `ds` and writes it to `settings.out`
/// (which must end in `.json`: the empirical model's files are PLY): one stage whose steps are
/// the rounds, and a line with the medium found.
pub fn fit_volume<S: crate::progress::Stages>(
    ds: &Dataset,
    frames: &[usize],
    settings: &VolumeFitSettings,
    stages: &S,
) -> Result<VolumeModel, VolumeError> {
    use crate::progress::Progress;
    if settings.out.extension().is_none_or(|e| e != "json") {
        return Err(VolumeError::Io {
            path: settings.out.clone(),
            source: std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "a volume model is written as JSON: give --out a name ending in .json",
            ),
        });
    }
    let t0 = std::time::Instant::now();
    let opts = &settings.fit;
    check("g", opts.g, opts.g.abs() < 1.0, "finite with |g| < 1")?;
    let bar = stages.stage(opts.rounds as u64, "volume fit");
    let fitted = super::fit::fit_homogeneous(ds, frames, opts, &|round, m| {
        bar.set_message(&format!(
            "volume fit: round {} of {}, σ_t {:.3}/{:.3}/{:.3} /mm, ring loss {:.3}/{:.3}/{:.3}",
            round + 1,
            opts.rounds,
            m.sigma_t[0],
            m.sigma_t[1],
            m.sigma_t[2],
            m.loss[0].0,
            m.loss[1].0,
            m.loss[2].0
        ));
        bar.inc(1);
    });
    stages.finish(bar);
    let m = fitted?;
    let grid = if settings.cells > 1 {
        let gopts = super::gridfit::GridFit::defaults(opts.clone(), settings.cells);
        let bar = stages.stage(gopts.rounds as u64, "volume grid");
        let g = super::gridfit::fit_grid(ds, frames, &m, &gopts, &|s| {
            bar.set_message(s);
            bar.inc(1);
        });
        stages.finish(bar);
        Some(g?)
    } else {
        None
    };
    let mut used: Vec<usize> = frames.to_vec();
    used.sort_unstable();
    used.dedup();
    // The loss the file reports is that of the medium it holds: the grid's where one was fitted.
    let loss = grid.as_ref().map_or(m.loss, |g| g.loss);
    let fit = FitInfo {
        frames: used,
        photons: opts.photons,
        rounds: opts.rounds + grid.as_ref().map_or(0, |g| g.rounds),
        loss: loss.map(|l| if l.0.is_finite() { l.0 } else { 0.0 }),
        rings: loss.map(|l| l.1),
        seconds: t0.elapsed().as_secs_f64(),
        subsurf_version: env!("CARGO_PKG_VERSION").to_string(),
    };
    let mut model = VolumeModel::homogeneous(&ds.mesh, &m, fit);
    if let Some(g) = &grid {
        model.grid = MediumGrid::of_channels(&g.grid);
        stages.say(&format!(
            "volume grid: {:?} cells of {:.2} mm, {} reached by the training light; ring loss \
             {:.4}/{:.4}/{:.4}",
            model.grid.dims, model.grid.cell_mm[0], g.active, g.loss[0].0, g.loss[1].0, g.loss[2].0
        ));
    }
    model.write(&settings.out)?;
    stages.say(&format!(
        "volume: σ_t {:.4}/{:.4}/{:.4} /mm, albedo {:.5}/{:.5}/{:.5}, g {}; {} frames, {:.1} s; \
         wrote {}",
        m.sigma_t[0],
        m.sigma_t[1],
        m.sigma_t[2],
        m.albedo[0],
        m.albedo[1],
        m.albedo[2],
        m.g,
        model.fit.frames.len(),
        model.fit.seconds,
        settings.out.display()
    ));
    Ok(model)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> VolumeModel {
        VolumeModel {
            g: 0.3,
            boundary: BoundaryModel::IndexMatched,
            grid: MediumGrid {
                origin: [-1.5, 0.1, -2.0],
                cell_mm: [1.0, 0.7, 1.0 / 3.0],
                dims: [2, 1, 2],
                sigma_t: vec![
                    [2.0, 2.1, 0.1 + 0.2],
                    [1.0, 3.0, 4.0],
                    [5.0, 6.0, 7.0],
                    [std::f64::consts::PI, 1e-3, 1e3],
                ],
                albedo: vec![
                    [0.99, 0.985, 0.98],
                    [0.5, 0.25, 0.125],
                    [0.9; 3],
                    [1.0 - 1e-9, 1e-9, 0.3],
                ],
            },
            mesh: VolumeMesh {
                vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [0.0, 1.0 / 7.0, 0.0]],
                triangles: vec![[0, 1, 2]],
            },
            fit: FitInfo {
                frames: vec![0, 2, 3],
                photons: 1500,
                rounds: 12,
                loss: [0.1, 0.2, 1.0 / 3.0],
                rings: [10, 11, 12],
                seconds: 4.25,
                subsurf_version: "0.1.0".into(),
            },
        }
    }

    fn bits(m: &VolumeModel) -> Vec<u64> {
        let mut v = vec![m.g.to_bits()];
        for x in m
            .grid
            .sigma_t
            .iter()
            .chain(&m.grid.albedo)
            .chain(&m.mesh.vertices)
        {
            v.extend(x.iter().map(|f| f.to_bits()));
        }
        v.extend(
            m.grid
                .origin
                .iter()
                .chain(&m.grid.cell_mm)
                .map(|f| f.to_bits()),
        );
        v.extend(m.fit.loss.iter().map(|f| f.to_bits()));
        v.push(m.fit.seconds.to_bits());
        v
    }

    #[test]
    fn a_model_round_trips_bit_exact_through_its_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.json");
        let mut m = model();
        m.boundary = BoundaryModel::Dielectric {
            ior: 1.49,
            roughness: 0.05,
        };
        for m in [model(), m] {
            m.write(&path).unwrap();
            let back = VolumeModel::read(&path).unwrap();
            assert_eq!(back, m);
            assert_eq!(bits(&back), bits(&m));
            assert!(is_volume_file(&path));
        }
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("\"format\": \"subsurf-volume\""), "{text}");
        assert!(text.contains("\"version\": 1"), "{text}");
    }

    fn refused(text: &str) -> VolumeError {
        VolumeModel::from_json(text).expect_err("read")
    }

    fn edited(f: impl FnOnce(&mut serde_json::Value)) -> String {
        let mut v: serde_json::Value = serde_json::from_str(&model().to_json().unwrap()).unwrap();
        f(&mut v);
        v.to_string()
    }

    #[test]
    fn reading_refuses_what_is_not_a_valid_model() {
        assert!(matches!(refused("ply\nformat"), VolumeError::Json(_)));
        let e = refused(&edited(|v| v["format"] = "subsurf-model".into()));
        assert!(matches!(e, VolumeError::Format(f) if f == "subsurf-model"));
        let e = refused(&edited(|v| v["version"] = 2.into()));
        assert!(matches!(e, VolumeError::Version(2)));
        let e = refused(&edited(|v| {
            v["grid"]["dims"] = serde_json::json!([2, 2, 2])
        }));
        assert!(matches!(e, VolumeError::Cells { cells: 8, .. }), "{e}");
        let e = refused(&edited(|v| {
            v["grid"]["albedo"].as_array_mut().unwrap().pop();
        }));
        assert!(matches!(e, VolumeError::Cells { albedo: 3, .. }), "{e}");
        let e = refused(&edited(|v| {
            v["grid"]["dims"] = serde_json::json!([usize::MAX, 2, 2])
        }));
        assert!(matches!(e, VolumeError::Cells { cells: 0, .. }), "{e}");
        let value = |f: &dyn Fn(&mut serde_json::Value), field: &str| {
            let e = refused(&edited(f));
            assert!(
                matches!(&e, VolumeError::Value { field: got, .. } if got == field),
                "{field}: {e}"
            );
        };
        value(
            &|v| v["grid"]["sigma_t"][1][2] = 0.0.into(),
            "grid.sigma_t[1][2]",
        );
        value(
            &|v| v["grid"]["sigma_t"][0][0] = (-1.0).into(),
            "grid.sigma_t[0][0]",
        );
        value(
            &|v| v["grid"]["albedo"][2][1] = 1.0.into(),
            "grid.albedo[2][1]",
        );
        value(
            &|v| v["grid"]["albedo"][0][0] = 0.0.into(),
            "grid.albedo[0][0]",
        );
        value(&|v| v["g"] = 1.0.into(), "g");
        value(&|v| v["g"] = (-1.5).into(), "g");
        value(&|v| v["grid"]["cell_mm"][1] = 0.0.into(), "grid.cell_mm[1]");
        value(&|v| v["fit"]["seconds"] = (-1.0).into(), "fit.seconds");
        // JSON has no infinity: a literal beyond f64 is refused (as a number out of range).
        let text = edited(|v| v["grid"]["sigma_t"][0][1] = 7.5.into()).replacen("7.5", "1e400", 1);
        assert!(text.contains("1e400"), "{text}");
        let e = refused(&text);
        assert!(
            matches!(e, VolumeError::Json(_) | VolumeError::Value { .. }),
            "{e}"
        );
        let e = refused(&edited(|v| {
            v["mesh"]["triangles"] = serde_json::json!([[0, 1, 3]])
        }));
        assert!(matches!(e, VolumeError::MeshIndex { index: 3, .. }), "{e}");
        let e = refused(&edited(|v| v["mesh"]["triangles"] = serde_json::json!([])));
        assert!(matches!(e, VolumeError::NoTriangles), "{e}");
        let e = refused(&edited(|v| v["grid"]["sigma_t"] = serde_json::json!(null)));
        assert!(matches!(e, VolumeError::Json(_)), "{e}");
    }

    #[test]
    fn writing_refuses_numbers_that_are_not_finite() {
        let mut m = model();
        m.grid.albedo[1][0] = f64::NAN;
        assert!(matches!(m.to_json(), Err(VolumeError::Value { .. })));
        let mut m = model();
        m.mesh.vertices[0][2] = f64::INFINITY;
        assert!(matches!(m.to_json(), Err(VolumeError::Value { .. })));
    }

    #[test]
    fn the_grid_finds_cells_and_clamps_outside_points() {
        let m = model();
        let g = &m.grid;
        assert_eq!(g.cell_of([-1.4, 0.2, -1.9]), Some(0));
        assert_eq!(g.cell_of([-0.4, 0.2, -1.9]), Some(1));
        assert_eq!(g.cell_of([-1.4, 0.2, -1.5]), Some(2));
        assert_eq!(g.cell_of([0.4, 0.7, -1.4]), Some(3));
        assert_eq!(g.cell_of([0.6, 0.2, -1.9]), None);
        assert_eq!(g.cell_of([f64::NAN, 0.2, -1.9]), None);
        assert_eq!(g.at([-100.0, 0.2, -1.9]), (g.sigma_t[0], g.albedo[0]));
        assert_eq!(g.at([100.0, 9.0, 100.0]), (g.sigma_t[3], g.albedo[3]));
        assert_eq!(
            g.at([f64::INFINITY, 0.0, -1.9]),
            (g.sigma_t[1], g.albedo[1])
        );
        assert!(!g.is_uniform());
        let h = MediumGrid::homogeneous([0.0; 3], [1.0, 2.0, 0.0], [2.0; 3], [0.9; 3]);
        assert!(h.is_uniform());
        assert_eq!(h.cell_mm, [1.0, 2.0, 1.0]);
        assert_eq!(h.at([5.0, -5.0, 0.5]), ([2.0; 3], [0.9; 3]));
    }

    #[test]
    fn a_model_that_is_not_traced_yet_is_a_typed_error() {
        let m = model();
        assert!(matches!(
            m.as_homogeneous(),
            Err(VolumeError::Heterogeneous(4))
        ));
        assert!(m.predictor().is_ok(), "a heterogeneous grid is traced");
        let mut d = model();
        d.grid = MediumGrid::homogeneous([0.0; 3], [1.0; 3], [2.0; 3], [0.9; 3]);
        d.boundary = BoundaryModel::Dielectric {
            ior: 1.5,
            roughness: 0.0,
        };
        assert!(matches!(d.predictor(), Err(VolumeError::Dielectric { .. })));
        // A rough dielectric is traced around one medium and around cells that differ; a
        // smooth one around neither.
        d.boundary = BoundaryModel::Dielectric {
            ior: 1.55,
            roughness: 0.2,
        };
        let h = d.as_homogeneous().unwrap();
        assert_eq!(
            h.surface,
            Surface::RoughDielectric {
                ior: 1.55,
                alpha: 0.2
            }
        );
        assert!(d.predictor().is_ok());
        let mut g = model();
        g.boundary = d.boundary;
        assert!(g.predictor().is_ok());
        g.boundary = BoundaryModel::Dielectric {
            ior: 1.5,
            roughness: 0.0,
        };
        assert!(matches!(g.predictor(), Err(VolumeError::Dielectric { .. })));
    }

    #[test]
    fn a_boundary_is_read_from_its_flag() {
        assert_eq!("index-matched".parse(), Ok(BoundaryModel::IndexMatched));
        assert_eq!(
            "dielectric:1.55:0.2".parse(),
            Ok(BoundaryModel::Dielectric {
                ior: 1.55,
                roughness: 0.2
            })
        );
        for bad in [
            "dielectric",
            "dielectric:1.55",
            "dielectric:1.55:0.2:1",
            "dielectric:x:0.2",
            "dielectric:-1:0.2",
            "dielectric:NaN:0.2",
            "dielectric:1.55:0",
            "dielectric:1.55:2",
            "glass",
        ] {
            assert!(bad.parse::<BoundaryModel>().is_err(), "{bad}");
        }
        let b = BoundaryModel::Dielectric {
            ior: 1.4,
            roughness: 0.3,
        };
        assert_eq!(BoundaryModel::of(b.surface().unwrap()), b);
    }
}
