//! Coverage of a sample's bilinear neighbourhood: a sample s(x_i, x_o) (section 5) is the
//! bilinear read of the four pixel centres around x_o's projection, so it measures x_o only when
//! all four see the surface at x_o. At a silhouette (an open mesh's boundary, the rim of a
//! curved object) some of them see the background, behind an occluding limb some see another
//! surface: the read is then a mix (0.16–0.79 of the true value was found at the boundary
//! vertices of the simulated slab), which the fit takes for a darker alpha(x_o).
//!
//! [`CoverageMap`] holds, per pixel of one view (camera, turntable angle), the distance along the
//! pixel centre's ray to the first hit of the mesh; [`super::Scene::covers`] compares the
//! sample's neighbours with the sample's own distance. Pixels are cast on demand (only those
//! next to a sample cost a ray) and kept, so all frames of a view share them.
use std::sync::atomic::{AtomicU32, Ordering};

use super::{Camera, V3, world_to_turntable};

/// Not yet cast (never an `f32` a cast stores: misses store `+inf`, hits finite distances).
const UNSET: u32 = u32::MAX;

/// Per pixel of one view, the distance (mm, along the unit ray through the pixel centre) to the
/// first hit of the mesh, `+inf` where the ray meets only background; filled lazily and safely
/// from many threads (a pixel cast twice by a race stores the same value twice).
pub struct CoverageMap {
    pub(super) cam: Camera,
    pub(super) deg: f64,
    /// The camera centre in the object frame.
    pub(super) centre: V3,
    /// Depth tolerance in units of the pixel footprint (see [`CoverageMap::new`]).
    pub(super) tolerance_px: f64,
    depth: Vec<AtomicU32>,
}

impl std::fmt::Debug for CoverageMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CoverageMap")
            .field("width", &self.cam.width)
            .field("height", &self.cam.height)
            .field("deg", &self.deg)
            .finish()
    }
}

impl CoverageMap {
    /// An empty map of camera `cam` at turntable angle `deg`, for samples seen at up to the
    /// grazing limit `cos_min` ([`super::Scene::sees`]). The tolerance on a neighbour's depth
    /// is `1 + √2·tan θ_max` pixel footprints (θ_max = acos `cos_min`, at least 0.1): on a plane
    /// seen at θ the depth changes by `tan θ` footprints per pixel, and the farthest centre a
    /// bilinear read weights is less than √2 pixels away; the extra footprint takes curvature
    /// and the interpolated normal's difference from the facet's. A neighbour seeing the
    /// background, or a surface farther in front or behind (an occluding limb, the far side), is
    /// outside it.
    pub fn new(cam: &Camera, deg: f64, cos_min: f64) -> CoverageMap {
        let c = cos_min.clamp(0.1, 1.0);
        let tan = (1.0 - c * c).sqrt() / c;
        let n = cam.width as usize * cam.height as usize;
        CoverageMap {
            cam: cam.clone(),
            deg,
            centre: world_to_turntable(cam.center(), deg),
            tolerance_px: 1.0 + std::f64::consts::SQRT_2 * tan,
            depth: (0..n).map(|_| AtomicU32::new(UNSET)).collect(),
        }
    }

    /// Number of pixels (the memory it holds is four bytes each).
    pub fn pixels(&self) -> usize {
        self.depth.len()
    }

    /// The depth of pixel `(i, j)`, cast by `cast` on the first request.
    pub(super) fn depth(&self, i: usize, j: usize, cast: impl FnOnce() -> Option<f64>) -> f64 {
        let Some(cell) = self.depth.get(j * self.cam.width as usize + i) else {
            return f64::INFINITY;
        };
        let bits = cell.load(Ordering::Relaxed);
        if bits != UNSET {
            return f32::from_bits(bits) as f64;
        }
        let d = cast().map_or(f32::INFINITY, |t| t as f32);
        cell.store(d.to_bits(), Ordering::Relaxed);
        d as f64
    }
}
