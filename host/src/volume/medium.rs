//! A heterogeneous medium as a regular grid of cells, one colour channel at a time: σ_t and the
//! single-scattering albedo constant in each cell, the grid spanning the object (points outside
//! it take the nearest cell, so a grid built on the mesh's bounds covers all of its medium).
//!
//! Free flights through it are sampled by delta tracking against the grid's largest σ_t (a
//! tentative collision is real with probability σ_t(x)/σ_max, else the photon flies on), which
//! leaves the mesh-crossing flight of the homogeneous tracer untouched; the transmittance
//! towards the camera is the exact integral of the piecewise-constant σ_t along the segment,
//! cell by cell (Amanatides and Woo's traversal), so the next-event estimate carries no
//! tracking noise.

use super::dielectric::{RoughDielectric, Surface, trace_grid_frame};
use super::trace::{
    Boundary, FrameGeometry, Photon, crossings, fly, nee, photon_seed, sample_hg, taps,
};
use crate::dataset::Image;
use crate::geometry::{Scene, V3, world_to_turntable};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

/// Tentative collisions after which a photon is given up (real and null ones together).
const MAX_EVENTS: u32 = 200_000;

/// One channel of a cell grid (object frame, mm).
#[derive(Debug, Clone, PartialEq)]
pub struct GridChannel {
    /// The grid's minimum corner, mm.
    pub origin: V3,
    /// A cell's size per axis, mm.
    pub cell_mm: V3,
    /// Cells per axis.
    pub dims: [usize; 3],
    /// σ_t per cell, 1/mm, x fastest, then y, then z.
    pub sigma_t: Vec<f64>,
    /// Single-scattering albedo per cell.
    pub albedo: Vec<f64>,
}

impl GridChannel {
    /// The cell's three indices of a point, clamped to the grid.
    pub fn cell3(&self, p: V3) -> [usize; 3] {
        std::array::from_fn(|a| {
            let f = ((p[a] - self.origin[a]) / self.cell_mm[a]).floor();
            if f.is_finite() {
                f.clamp(0.0, (self.dims[a] - 1) as f64) as usize
            } else {
                0
            }
        })
    }

    /// σ_t at a point (the nearest cell outside the grid).
    pub fn sigma_at(&self, p: V3) -> f64 {
        self.sigma_t[self.index(self.cell3(p))]
    }

    /// Albedo at a point.
    pub fn albedo_at(&self, p: V3) -> f64 {
        self.albedo[self.index(self.cell3(p))]
    }

    /// The largest σ_t: the majorant of delta tracking.
    pub fn majorant(&self) -> f64 {
        self.sigma_t.iter().cloned().fold(0.0, f64::max)
    }

    /// Optical depth ∫ σ_t along the segment from `p` in the unit direction `d` over `len` mm.
    pub fn optical_depth(&self, p: V3, d: V3, len: f64) -> f64 {
        let mut tau = 0.0;
        self.for_each_cell(p, d, len, &mut |cell, l| tau += self.sigma_t[cell] * l);
        tau
    }

    /// Calls `f(cell, length)` for each cell the segment from `p` in the unit direction `d`
    /// over `len` mm passes through, in order (Amanatides and Woo's traversal; beyond the grid
    /// the edge cell goes on, as [`GridChannel::sigma_at`] has it).
    pub fn for_each_cell(&self, p: V3, d: V3, len: f64, f: &mut dyn FnMut(usize, f64)) {
        if len <= 0.0 {
            return;
        }
        let mut cell = self.cell3(p);
        // Parametric distance to the next cell wall per axis, and between walls.
        let mut next = [f64::INFINITY; 3];
        let mut step = [f64::INFINITY; 3];
        for a in 0..3 {
            if d[a].abs() > 1e-300 {
                step[a] = self.cell_mm[a] / d[a].abs();
                let wall = if d[a] > 0.0 {
                    self.origin[a] + (cell[a] + 1) as f64 * self.cell_mm[a]
                } else {
                    self.origin[a] + cell[a] as f64 * self.cell_mm[a]
                };
                next[a] = ((wall - p[a]) / d[a]).max(0.0);
            }
        }
        let mut t = 0.0;
        let limit = self.dims.iter().sum::<usize>() + 4;
        for _ in 0..limit {
            let a = (0..3)
                .min_by(|&x, &y| next[x].total_cmp(&next[y]))
                .unwrap_or(0);
            let end = next[a].min(len);
            f(self.index(cell), end - t);
            t = end;
            if t >= len {
                return;
            }
            // Into the neighbour; beyond the grid's last cell the edge cell goes on.
            let beyond = if d[a] > 0.0 {
                cell[a] + 1 >= self.dims[a]
            } else {
                cell[a] == 0
            };
            if beyond {
                next[a] = f64::INFINITY;
            } else {
                if d[a] > 0.0 {
                    cell[a] += 1;
                } else {
                    cell[a] -= 1;
                }
                next[a] += step[a];
            }
        }
        f(self.index(cell), (len - t).max(0.0));
    }

    /// The flat index of a cell's three indices (x fastest).
    pub fn index(&self, c: [usize; 3]) -> usize {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }
}

/// Adds `k` real collisions and `l` mm of medium in `cell` to a path's cells (a grid fit's
/// records, `super::gridfit`).
pub(super) fn add_to(path: &mut Vec<(u32, u32, f64)>, cell: usize, k: u32, l: f64) {
    let cell = cell as u32;
    match path.iter_mut().find(|e| e.0 == cell) {
        Some(e) => {
            e.1 += k;
            e.2 += l;
        }
        None => path.push((cell, k, l)),
    }
}

/// One frame's next events in a grid channel: pixel coordinates and the contribution to the
/// pixel's radiance (per watt of laser) before the reconstruction filter.
#[allow(clippy::too_many_arguments)]
pub fn trace_channel(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    grid: &GridChannel,
    g: f64,
    photons: usize,
    seed: u64,
    frame: usize,
) -> Vec<(f32, f32, f64)> {
    let cam = &geo.camera;
    let centre = world_to_turntable(cam.center(), geo.deg);
    let ln_power = -(photons.max(1) as f64).ln();
    let ln_fxfy = (cam.fx * cam.fy).ln();
    let major = grid.majorant();
    if !(major > 0.0 && major.is_finite()) {
        return Vec::new();
    }
    let depth = |p: V3, d: V3, len: f64| grid.optical_depth(p, d, len);
    (0..photons)
        .into_par_iter()
        .fold(Vec::new, |mut out, n| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(photon_seed(seed, frame, n));
            let Some((entry, dir, tri)) = geo.launch(scene, &mut rng) else {
                return out;
            };
            let mut ph = Photon {
                p: entry,
                d: dir,
                skip: Some(tri),
            };
            for _ in 0..MAX_EVENTS {
                let x: f64 = rng.random();
                if !fly(scene, &mut ph, -(1.0 - x).ln() / major) {
                    break;
                }
                if boundary == Boundary::Open
                    && crossings(scene, ph.p, geo.origin).is_multiple_of(2)
                {
                    break;
                }
                // Delta tracking: a null collision leaves the photon on its way.
                if rng.random::<f64>() * major >= grid.sigma_at(ph.p) {
                    continue;
                }
                let albedo = grid.albedo_at(ph.p);
                if let Some(r) = nee(scene, cam, geo.deg, centre, &ph, g, &depth) {
                    let ln = ln_power + albedo.ln() + r.1 + ln_fxfy - r.2;
                    if ln.is_finite() {
                        out.push((r.0[0] as f32, r.0[1] as f32, ln.exp()));
                    }
                }
                if rng.random::<f64>() >= albedo {
                    break;
                }
                ph.d = sample_hg(ph.d, g, &mut rng);
                ph.skip = None;
            }
            out
        })
        .reduce(Vec::new, |mut a, mut b| {
            a.append(&mut b);
            a
        })
}

/// A frame's image in a grid medium behind `surface`, one trace per channel (each channel has
/// its own σ_t, so its own free flights).
#[allow(clippy::too_many_arguments)]
pub fn grid_image(
    scene: &Scene,
    boundary: Boundary,
    geo: &FrameGeometry,
    channels: &[GridChannel; 3],
    g: f64,
    surface: Surface,
    photons: usize,
    seed: u64,
    frame: usize,
) -> Image {
    let (w, h) = (geo.camera.width as usize, geo.camera.height as usize);
    let mut img = Image::new(w, h, 3);
    for (c, grid) in channels.iter().enumerate() {
        let events = match surface {
            Surface::IndexMatched => {
                trace_channel(scene, boundary, geo, grid, g, photons, seed, frame)
            }
            Surface::RoughDielectric { ior, alpha } => trace_grid_frame(
                scene,
                boundary,
                geo,
                grid,
                g,
                RoughDielectric { eta: ior, alpha },
                photons,
                seed,
                frame,
                &Vec::new,
                &|out: &mut Vec<(f32, f32, f64)>, uv, ln, _| {
                    if ln.is_finite() {
                        out.push((uv[0] as f32, uv[1] as f32, ln.exp()));
                    }
                },
                &|mut a, mut b| {
                    a.append(&mut b);
                    a
                },
            ),
        };
        for (u, v, e) in events {
            for (p, t) in taps(u as f64, v as f64, w, h) {
                img.data[p * 3 + c] += (e * t) as f32;
            }
        }
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> GridChannel {
        GridChannel {
            origin: [0.0, 0.0, 0.0],
            cell_mm: [1.0, 2.0, 1.0],
            dims: [3, 2, 1],
            sigma_t: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            albedo: vec![0.9; 6],
        }
    }

    #[test]
    fn optical_depth_sums_each_cells_share_of_the_segment() {
        let g = grid();
        // Along x at y = 1 (row 0): cells 1, 2, 3 over 1 mm each.
        let tau = g.optical_depth([0.0, 1.0, 0.5], [1.0, 0.0, 0.0], 3.0);
        assert!((tau - 6.0).abs() < 1e-12, "{tau}");
        // Half a cell in, half a cell on.
        let tau = g.optical_depth([0.5, 3.0, 0.5], [1.0, 0.0, 0.0], 1.0);
        assert!((tau - 0.5 * 4.0 - 0.5 * 5.0).abs() < 1e-12, "{tau}");
        // Backwards, and on past the grid's edge in the edge cell.
        let tau = g.optical_depth([2.5, 1.0, 0.5], [-1.0, 0.0, 0.0], 4.0);
        assert!((tau - (0.5 * 3.0 + 2.0 + 2.5 * 1.0)).abs() < 1e-12, "{tau}");
        // A diagonal across rows, from (0.5, 1.5) to (2.5, 3.5).
        let d = [
            std::f64::consts::FRAC_1_SQRT_2,
            std::f64::consts::FRAC_1_SQRT_2,
            0.0,
        ];
        let len = 2.0 * std::f64::consts::SQRT_2;
        let tau = g.optical_depth([0.5, 1.5, 0.5], d, len);
        // x: 0.5→2.5, y: 1.5→3.5. Pieces: cell(0,0) to x=1 (y 2.0) at s=0.5·√2: σ 1, then
        // y=2 at the same point; cell(1,1) σ 5 to x=2 (s=1.5·√2); cell(2,1) σ 6 to the end.
        let r2 = std::f64::consts::SQRT_2;
        let want = 1.0 * 0.5 * r2 + 5.0 * 1.0 * r2 + 6.0 * 0.5 * r2;
        assert!((tau - want).abs() < 1e-9, "{tau} vs {want}");
    }

    #[test]
    fn a_uniform_grid_is_sigma_times_length_in_any_direction() {
        let g = GridChannel {
            origin: [-1.0, -2.0, -3.0],
            cell_mm: [0.3, 0.7, 1.1],
            dims: [7, 5, 4],
            sigma_t: vec![2.5; 140],
            albedo: vec![0.9; 140],
        };
        for (p, d, len) in [
            ([0.0, 0.0, 0.0], [0.6, 0.0, 0.8], 3.0),
            ([0.1, 0.2, -1.0], [-0.48, 0.6, 0.64], 7.0),
            ([5.0, 5.0, 5.0], [0.0, -1.0, 0.0], 2.0),
        ] {
            let tau = g.optical_depth(p, d, len);
            assert!((tau - 2.5 * len).abs() < 1e-9, "{tau}");
        }
    }
}
