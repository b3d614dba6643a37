//! `subsurf fit`'s check that the dataset's mesh sits where the scan saw the object: the laser
//! spots, triangulated without the mesh ([`super::evidence::triangulate`]), against the mesh
//! surface. A mesh in another pose or unit puts them far from it, and every spot would then land
//! on the wrong vertex (or none) with no other sign of trouble.
//!
//! `subsurf fit` checks the spots its extraction pass detected (the sample store's records,
//! [`check_spots`]: no frame is read for it); [`check_mesh`] reads up to [`CHECK_FRAMES`] frames
//! itself, for callers without a store.
use crate::dataset::{Dataset, DatasetError};
use crate::geometry::{GeometryError, Scene};
use crate::progress::Progress;

use super::evidence::{EvidenceOptions, spot_points};
use super::icp::median;

/// Frames the check reads at most (evenly spread over those with a laser ray): enough for a
/// robust median, a small share of a fit's reading.
pub const CHECK_FRAMES: usize = 48;

/// Fewest spots for a verdict.
pub const CHECK_MIN_SPOTS: usize = 5;

/// What the check found.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MeshCheck {
    /// Frames read.
    pub frames: usize,
    /// Spots triangulated.
    pub spots: usize,
    /// Median distance of the spot points from the mesh surface, mm (NaN without spots).
    pub median_mm: f64,
    /// The same in pixel footprints.
    pub median_px: f64,
    /// Share of the spots farther than `bound_mm`.
    pub far_share: f64,
    /// The bound the caller judged with, mm.
    pub bound_mm: f64,
}

impl MeshCheck {
    /// Enough spots to judge?
    pub fn conclusive(&self) -> bool {
        self.spots >= CHECK_MIN_SPOTS
    }

    /// Do the spots lie off the surface: is their median distance beyond the bound?
    pub fn far(&self) -> bool {
        self.conclusive() && (self.median_mm.is_nan() || self.median_mm > self.bound_mm)
    }
}

/// Triangulates the spots `spots` (frame, spot detected in it) of frames of `ds` with a laser ray
/// and measures their distance from the surface of `scene` (the dataset's mesh); `bound_mm` is
/// what [`MeshCheck::far`] compares the median with.
pub fn check_spots(
    ds: &Dataset,
    scene: &Scene,
    spots: &[(usize, crate::spot::Spot)],
    max_gap_px: f64,
    bound_mm: f64,
) -> MeshCheck {
    let points: Vec<super::evidence::SpotPoint> = spots
        .iter()
        .filter_map(|&(k, spot)| {
            let spec = ds.spec.frames.get(k)?;
            let cam = ds.spec.cameras.get(spec.camera)?;
            super::evidence::triangulate(k, spec, cam, &spot, max_gap_px).ok()
        })
        .collect();
    measure(scene, &points, spots.len(), bound_mm)
}

/// The distances of `points` from the surface of `scene`.
fn measure(
    scene: &Scene,
    points: &[super::evidence::SpotPoint],
    frames: usize,
    bound_mm: f64,
) -> MeshCheck {
    let (mm, px): (Vec<f64>, Vec<f64>) = points
        .iter()
        .map(|p| {
            let d = scene
                .closest(p.point, f64::INFINITY)
                .map_or(f64::INFINITY, |c| c.distance);
            (d, d / p.footprint_mm)
        })
        .unzip();
    let far = mm.iter().filter(|d| d.is_nan() || **d > bound_mm).count();
    MeshCheck {
        frames,
        spots: mm.len(),
        median_mm: median(&mm),
        median_px: median(&px),
        far_share: far as f64 / mm.len().max(1) as f64,
        bound_mm,
    }
}

/// Triangulates the spots of up to [`CHECK_FRAMES`] of `frames` (read here) and measures their
/// distance from the dataset's mesh; `bound_mm` is what [`MeshCheck::far`] compares the median
/// with.
pub fn check_mesh(
    ds: &Dataset,
    frames: &[usize],
    opts: &EvidenceOptions,
    bound_mm: f64,
    progress: &dyn Progress,
) -> Result<MeshCheck, CheckError> {
    let lit: Vec<usize> = frames
        .iter()
        .copied()
        .filter(|&k| ds.spec.frames.get(k).is_some_and(|f| f.laser.is_some()))
        .collect();
    let step = lit.len().div_ceil(CHECK_FRAMES).max(1);
    let chosen: Vec<usize> = lit.iter().copied().step_by(step).collect();
    let ev = spot_points(ds, &chosen, opts, progress)?;
    let scene = Scene::new(ds.mesh.clone())?;
    Ok(measure(&scene, &ev.points, chosen.len(), bound_mm))
}

/// Why the check could not run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CheckError {
    /// A frame could not be read.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// The mesh could not be prepared for queries.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}
