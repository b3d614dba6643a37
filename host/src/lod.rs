//! The level of detail the frames support: a mesh much finer than a camera pixel's
//! footprint on the object is fitted on a coarser copy of itself, and the model is carried back
//! to every vertex of the mesh given.
//!
//! Why: every sample x_o is a vertex a frame sees, and the alpha rounds' fill solves for every
//! vertex without a light position of its own. Scanners deliver meshes of hundreds of thousands
//! of vertices; a 128 px camera sees a few thousand pixels of the object. Below a pixel's
//! footprint, more vertices add no measurement: they read the same pixels again (correlated
//! samples the fit would count as independent), and they multiply the fill's unknowns. So the
//! work should grow with what the frames measure, not with the mesh.
//!
//! How: vertex clustering on a grid whose cell is the smallest pixel footprint any camera has on
//! the object (Rossignac and Borrel 1993). Written here rather than taken from a simplification
//! crate because the product needs two properties those do not promise: each coarse vertex *is*
//! a vertex of the given mesh (the one nearest its cell's centroid, so the coarse surface passes
//! through measured positions and a representative gets its own fit back exactly), and the cell
//! is tied to the cameras, not to an error budget on the shape. The model is prolonged
//! ([`prolong`]): each vertex of the given mesh reads the coarse model at its nearest coarse
//! surface point: alpha (Eq. 2/6) interpolated there (with the face lattice's detail, as a
//! renderer reads it between vertices), R_d (Eq. 1/3) from the nearest corner, whose light
//! position and fit it shares.
use std::collections::HashMap;

use rayon::prelude::*;

use crate::dataset::{Dataset, Mesh};
use crate::geometry::{GeometryError, Scene};
use crate::modelfile::{ModelFile, VertexModel};

/// A mesh is coarsened when it has more than this many times the vertices a pixel-footprint
/// lattice of its area would have: meshes near the frames' resolution (the shared datasets,
/// their meshes subdivided once) are fitted as they are.
pub const COARSEN_ABOVE: f64 = 2.0;

/// Coarsening needs the frames to resolve the object into at least this many pixel footprints.
/// A mesh whose whole surface covers fewer is not a scanner's fine mesh but one in another unit
/// or pose (a mesh in metres covers a millionth of its footprints): it is fitted as it is, and
/// the fit's mesh check against the laser spots says what is wrong with it.
pub const MIN_SUPPORTED: usize = 1_000;

/// What the frames support for a mesh, and what was done with it (the fit report's
/// `level_of_detail`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LevelOfDetail {
    /// Vertices of the mesh given.
    pub vertices: usize,
    /// The smallest footprint of a camera pixel on the object, mm ([`pixel_footprint_mm`]).
    pub pixel_footprint_mm: f64,
    /// Vertices an equilateral lattice with the footprint as its edge has over the mesh's area.
    pub supported_vertices: usize,
    /// Vertices fitted: the coarse mesh's when coarsened, else the mesh's own.
    pub fitted_vertices: usize,
    /// Whether the fit ran on a coarser mesh and the model was prolonged.
    pub coarsened: bool,
}

/// A coarse copy of a mesh by vertex clustering.
#[derive(Debug, Clone)]
pub struct Coarse {
    /// The coarse mesh; its vertex `k` is the given mesh's vertex `representative[k]`.
    pub mesh: Mesh,
    /// The given mesh's vertex each coarse vertex is.
    pub representative: Vec<u32>,
}

/// Why a mesh could not be coarsened or a model prolonged.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LodError {
    /// The coarse mesh has no triangle left (a cell larger than the object).
    #[error(
        "clustering the mesh at {cell_mm} mm left no triangle: the cell is larger than the object"
    )]
    Empty {
        /// The cell used.
        cell_mm: f64,
    },
    /// The coarse mesh could not be prepared for queries.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// A vertex of the given mesh has no coarse surface point (non-finite position).
    #[error("vertex {0} of the mesh has no nearest point on the coarse mesh")]
    Unreachable(usize),
    /// The prolonged model is not a valid model file.
    #[error("the prolonged model: {0}")]
    Model(#[from] crate::modelfile::ModelFileError),
}

/// The smallest footprint, in mm, of one pixel of any camera of `ds` on the object: the nearest
/// any vertex comes to a camera's centre over a whole turn of the turntable, over the camera's
/// focal length in pixels. A vertex at radius ρ and height z from the turntable axis comes
/// nearest to a centre at radius ρ_c and height z_c at √((ρ_c − ρ)² + (z_c − z)²), whatever the
/// angles scanned. `None` without cameras or vertices.
pub fn pixel_footprint_mm(ds: &Dataset) -> Option<f64> {
    let mesh = &ds.mesh;
    ds.spec
        .cameras
        .iter()
        .filter_map(|cam| {
            let c = cam.center();
            let rho_c = c[0].hypot(c[1]);
            let nearest = mesh
                .positions
                .iter()
                .map(|p| (rho_c - p[0].hypot(p[1])).hypot(c[2] - p[2]))
                .fold(f64::INFINITY, f64::min);
            let f = cam.fx.max(cam.fy);
            (nearest.is_finite() && f > 0.0).then(|| nearest / f)
        })
        .filter(|w| w.is_finite() && *w > 0.0)
        .min_by(f64::total_cmp)
}

/// The level of detail `ds`'s frames support for its mesh (nothing is built here).
pub fn supported(ds: &Dataset) -> Option<LevelOfDetail> {
    let h = pixel_footprint_mm(ds)?;
    let area = ds.mesh.area();
    // An equilateral lattice of edge h has 2 / (√3 h²) vertices per unit area.
    let supported = (2.0 * area / (3f64.sqrt() * h * h)).ceil();
    let n = ds.mesh.positions.len();
    Some(LevelOfDetail {
        vertices: n,
        pixel_footprint_mm: h,
        supported_vertices: if supported.is_finite() {
            supported as usize
        } else {
            usize::MAX
        },
        fitted_vertices: n,
        coarsened: false,
    })
}

impl LevelOfDetail {
    /// Whether the mesh is finer than the frames support by more than [`COARSEN_ABOVE`] (and
    /// the frames resolve at least [`MIN_SUPPORTED`] footprints on it).
    pub fn should_coarsen(&self) -> bool {
        self.supported_vertices >= MIN_SUPPORTED
            && self.vertices as f64 > COARSEN_ABOVE * self.supported_vertices as f64
    }
}

/// `mesh` clustered to about the vertex count `lod` says the frames support: first on a grid of
/// the pixel footprint; a grid cuts a curved surface obliquely and keeps more cells than a
/// lattice of the same edge has vertices, so where it kept more than 10 % too many, once more
/// with the cell widened by the square root of the excess.
pub fn coarsen(mesh: &Mesh, lod: &LevelOfDetail) -> Result<Coarse, LodError> {
    let h = lod.pixel_footprint_mm;
    let first = cluster(mesh, h)?;
    let (n, want) = (
        first.mesh.positions.len() as f64,
        lod.supported_vertices.max(1) as f64,
    );
    if n > 1.1 * want {
        cluster(mesh, h * (n / want).sqrt())
    } else {
        Ok(first)
    }
}

/// Vertex clustering of `mesh` on a grid of cell `cell_mm`: the vertices of a cell merge into
/// the one nearest their centroid; triangles with two corners in one cell vanish, duplicates go
/// ([`Mesh::new`]), and cells no triangle keeps are dropped.
pub fn cluster(mesh: &Mesh, cell_mm: f64) -> Result<Coarse, LodError> {
    let cell_of = |p: &[f64; 3]| p.map(|x| (x / cell_mm).floor() as i64);
    // foldhash: the cells are our own grid's numbers (no adversary), and a scanner's mesh has
    // hundreds of thousands of vertices to place; the numbering is by first vertex either way.
    let mut cells: HashMap<[i64; 3], u32, foldhash::fast::FixedState> = HashMap::default();
    let mut members: Vec<Vec<u32>> = Vec::new();
    let mut of: Vec<u32> = Vec::with_capacity(mesh.positions.len());
    for (v, p) in mesh.positions.iter().enumerate() {
        let next = members.len() as u32;
        let c = *cells.entry(cell_of(p)).or_insert(next);
        if c == next {
            members.push(Vec::new());
        }
        members[c as usize].push(v as u32);
        of.push(c);
    }
    // Each cell's vertex nearest its centroid stands for it.
    let rep: Vec<u32> = members
        .iter()
        .map(|m| {
            let k = m.len() as f64;
            let mut g = [0.0; 3];
            for &v in m {
                for (gi, pi) in g.iter_mut().zip(mesh.positions[v as usize]) {
                    *gi += pi / k;
                }
            }
            *m.iter()
                .min_by(|a, b| {
                    let da = crate::geometry::dist(mesh.positions[**a as usize], g);
                    let db = crate::geometry::dist(mesh.positions[**b as usize], g);
                    da.total_cmp(&db)
                })
                .expect("a cell has the vertex that made it")
        })
        .collect();
    let tris: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .map(|t| t.map(|v| of[v as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .collect();
    // Renumber the cells some triangle keeps.
    let mut index = vec![u32::MAX; members.len()];
    let mut representative = Vec::new();
    for t in &tris {
        for &c in t {
            if index[c as usize] == u32::MAX {
                index[c as usize] = representative.len() as u32;
                representative.push(rep[c as usize]);
            }
        }
    }
    let positions = representative
        .iter()
        .map(|&v| mesh.positions[v as usize])
        .collect();
    let triangles = tris.iter().map(|t| t.map(|c| index[c as usize])).collect();
    let (coarse, _report) = Mesh::new(positions, triangles);
    if coarse.triangles.is_empty() {
        return Err(LodError::Empty { cell_mm });
    }
    Ok(Coarse {
        mesh: coarse,
        representative,
    })
}

/// The coarse model `coarse` (fitted on `coarse_mesh`) carried to every vertex of `fine`: each
/// vertex reads it at its nearest point of the coarse surface. alpha is the coarse model's there
/// ([`ModelFile::alpha_at`]: barycentric, with the face lattice's detail); the rest of the vertex
/// model (R_d's terms, its status and log E) is the nearest corner's, whose light position the
/// vertex shares. A representative reads its own coarse vertex exactly. The result has `fine`'s
/// positions, normals and faces and no face lattice (the fine vertices sample it).
pub fn prolong(coarse: &ModelFile, coarse_mesh: &Mesh, fine: &Mesh) -> Result<ModelFile, LodError> {
    let scene = Scene::new(coarse_mesh.clone())?;
    let vertices: Vec<VertexModel> = fine
        .positions
        .par_iter()
        .enumerate()
        .map(|(v, &p)| {
            let hit = scene
                .closest(p, f64::INFINITY)
                .ok_or(LodError::Unreachable(v))?;
            let tri = hit.triangle as usize;
            let bary = scene.barycentric(hit.triangle, p);
            let corner = (0..3)
                .max_by(|&a, &b| bary[a].total_cmp(&bary[b]))
                .unwrap_or(0);
            let c = coarse_mesh.triangles[tri][corner] as usize;
            let mut m = coarse
                .vertices
                .get(c)
                .cloned()
                .ok_or(LodError::Unreachable(v))?;
            let a = coarse.alpha_at(tri, bary);
            m.alpha = a.map(|x| x as f32);
            Ok(m)
        })
        .collect::<Result<_, LodError>>()?;
    let out = ModelFile {
        positions: fine.positions.clone(),
        normals: fine.normals.clone(),
        triangles: fine.triangles.clone(),
        vertices,
        face_alpha: None,
        ..coarse.clone()
    };
    out.check()?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat square grid of `n × n` vertices with spacing `h`.
    fn grid(n: usize, h: f64) -> Mesh {
        let mut p = Vec::new();
        for j in 0..n {
            for i in 0..n {
                p.push([i as f64 * h, j as f64 * h, 0.0]);
            }
        }
        let mut t = Vec::new();
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = (j * n + i) as u32;
                let b = a + 1;
                let c = a + n as u32;
                let d = c + 1;
                t.push([a, b, d]);
                t.push([a, d, c]);
            }
        }
        Mesh::new(p, t).0
    }

    #[test]
    fn clustering_keeps_given_vertices_and_the_surface() {
        let fine = grid(41, 0.1);
        let coarse = cluster(&fine, 0.4).unwrap();
        let n = coarse.mesh.positions.len();
        // 4 mm square at 0.4 mm cells: about 11 × 11 cells.
        assert!((80..=150).contains(&n), "{n} coarse vertices");
        for (k, &v) in coarse.representative.iter().enumerate() {
            assert_eq!(coarse.mesh.positions[k], fine.positions[v as usize]);
        }
        // The coarse surface covers the square (area within 15 %: the border cells shrink it).
        let a = coarse.mesh.area();
        assert!((a - 16.0).abs() < 0.15 * 16.0, "area {a}");
        // Oriented as the fine mesh: every normal still +z.
        assert!(coarse.mesh.normals.iter().all(|n| n[2] > 0.99));
    }

    #[test]
    fn only_a_mesh_far_finer_than_enough_footprints_is_coarsened() {
        let lod = |vertices, supported| LevelOfDetail {
            vertices,
            pixel_footprint_mm: 0.4,
            supported_vertices: supported,
            fitted_vertices: vertices,
            coarsened: false,
        };
        assert!(lod(655_362, 10_918).should_coarsen());
        assert!(!lod(10_242, 10_918).should_coarsen());
        assert!(!lod(21_000, 10_918).should_coarsen());
        // A mesh in metres: a handful of footprints, never coarsened (the mesh check speaks).
        assert!(!lod(5_000, 1).should_coarsen());
    }

    #[test]
    fn a_cell_larger_than_the_object_is_an_error() {
        let fine = grid(5, 0.1);
        assert!(matches!(cluster(&fine, 100.0), Err(LodError::Empty { .. })));
    }

    #[test]
    fn prolonging_reads_the_coarse_model_at_the_nearest_surface_point() {
        let fine = grid(21, 0.1);
        let coarse = cluster(&fine, 0.4).unwrap();
        let m = &coarse.mesh;
        let mut model = ModelFile::homogeneous(
            m.positions.clone(),
            m.normals.clone(),
            m.triangles.clone(),
            [1.0, 1.0],
            &[(1.0, -1.0)],
        );
        // alpha = 1 + x, and vertex k's first term's weight = k, to tell the corners apart.
        for (k, v) in model.vertices.iter_mut().enumerate() {
            v.alpha = [1.0 + m.positions[k][0] as f32; 3];
            v.params[2] = k as f64 + 1.0;
            v.log_e = 0.1;
        }
        let out = prolong(&model, m, &fine).unwrap();
        assert_eq!(out.positions, fine.positions);
        assert_eq!(out.triangles, fine.triangles);
        for (v, p) in fine.positions.iter().enumerate() {
            let a = out.vertices[v].alpha[0] as f64;
            // alpha linear in x is reproduced where the coarse surface covers the point.
            let inside = p[0] > 0.4 && p[0] < 1.6 && p[1] > 0.4 && p[1] < 1.6;
            if inside {
                assert!((a - (1.0 + p[0])).abs() < 1e-5, "alpha {a} at {p:?}");
            }
        }
        for (k, &v) in coarse.representative.iter().enumerate() {
            assert_eq!(
                out.vertices[v as usize], model.vertices[k],
                "representative {k}"
            );
        }
        // R_d from the nearest corner: the weight named by a coarse vertex within one cell.
        for (v, p) in fine.positions.iter().enumerate() {
            let k = out.vertices[v].params[2] as usize - 1;
            let d = crate::geometry::dist(*p, m.positions[k]);
            assert!(
                d < 0.4 * 3f64.sqrt(),
                "vertex {v} reads a corner {d} mm away"
            );
        }
    }
}
