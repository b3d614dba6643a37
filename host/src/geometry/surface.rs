//! Points on the mesh surface between its vertices: the lattice points of the modulation texture
//! alpha(x_o) finer than the mesh (section 5: "determined as higher resolution texture",
//! [`crate::lattice`]), as positions and normals the visibility rule and the sample reads take.
//!
//! Why points per face, with points on shared edges and corners repeated for each face holding
//! them: a face's lattice is stored and evaluated on its own (`face_alpha`), so its points are
//! sampled on their own too, and nothing has to match points across faces of different levels.
use std::ops::Range;

use crate::dataset::Mesh;
use crate::lattice::{LatticeError, MAX_LEVEL, point_bary, point_count, points};

use super::{V3, add_scaled, cross, normalize, sub};

/// The lattice points of every face of a mesh at given per-face levels, in the storage order of
/// [`crate::lattice::FaceAlpha`]: face by face, within a face in [`crate::lattice::point_index`]
/// order. Point `p` of face `f` is at index `face_points(f).start + point_index(level, i, j)`,
/// so a per-point array in this order is exactly a `FaceAlpha` detail list.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfacePoints {
    levels: Vec<u8>,
    /// Start of each face's points (one more entry than faces).
    start: Vec<u32>,
    /// Per point: the face holding it.
    pub face: Vec<u32>,
    /// Per point: barycentric coordinates (weights of the face's corners a, b, c, its
    /// `triangles` entry in order).
    pub bary: Vec<[f64; 3]>,
    /// Per point: position (object frame, mm), the barycentric combination of the corners.
    pub positions: Vec<V3>,
    /// Per point: unit normal, the corners' vertex normals interpolated barycentrically (as
    /// [`super::Scene::normal_at`] and shading do); the face's own normal where they cancel,
    /// and zero (never visible) on a degenerate face.
    pub normals: Vec<V3>,
}

impl SurfacePoints {
    /// The lattice points of `mesh` with face `f` at level `levels[f]` (1..=[`MAX_LEVEL`]; level
    /// 1 is the three corners).
    pub fn lattice(mesh: &Mesh, levels: &[u8]) -> Result<SurfacePoints, LatticeError> {
        if levels.len() != mesh.triangles.len() {
            return Err(LatticeError::FaceCount {
                levels: levels.len(),
                faces: mesh.triangles.len(),
            });
        }
        let total: usize = levels.iter().map(|&k| point_count(k)).sum();
        let mut out = SurfacePoints {
            levels: levels.to_vec(),
            start: Vec::with_capacity(levels.len() + 1),
            face: Vec::with_capacity(total),
            bary: Vec::with_capacity(total),
            positions: Vec::with_capacity(total),
            normals: Vec::with_capacity(total),
        };
        for (f, (t, &k)) in mesh.triangles.iter().zip(levels).enumerate() {
            if !(1..=MAX_LEVEL).contains(&k) {
                return Err(LatticeError::Level { face: f, level: k });
            }
            out.start.push(out.face.len() as u32);
            let c = t.map(|v| mesh.positions[v as usize]);
            let n = t.map(|v| mesh.normals[v as usize]);
            let face_normal = normalize(cross(sub(c[1], c[0]), sub(c[2], c[0])));
            for (_, i, j) in points(k) {
                let w = point_bary(k, i, j);
                let mut p = [0.0; 3];
                let mut nn = [0.0; 3];
                for q in 0..3 {
                    p = add_scaled(p, w[q], c[q]);
                    nn = add_scaled(nn, w[q], n[q]);
                }
                out.face.push(f as u32);
                out.bary.push(w);
                out.positions.push(p);
                out.normals
                    .push(normalize(nn).or(face_normal).unwrap_or([0.0; 3]));
            }
        }
        out.start.push(out.face.len() as u32);
        Ok(out)
    }

    /// The per-face levels.
    pub fn levels(&self) -> &[u8] {
        &self.levels
    }

    /// Indices of face `face`'s points (empty past the last face).
    pub fn face_points(&self, face: usize) -> Range<usize> {
        match (self.start.get(face), self.start.get(face + 1)) {
            (Some(&a), Some(&b)) => a as usize..b as usize,
            _ => 0..0,
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.face.len()
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.face.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::dist;
    use crate::lattice::point_index;

    #[test]
    fn points_follow_the_lattice_layout_and_interpolate_the_face() {
        let m = crate::geometry::tests::grid(3, 2.0);
        let levels: Vec<u8> = (0..m.triangles.len()).map(|f| 1 + (f % 4) as u8).collect();
        let pts = SurfacePoints::lattice(&m, &levels).unwrap();
        let want: usize = levels.iter().map(|&k| point_count(k)).sum();
        assert_eq!(pts.len(), want);
        for (f, t) in m.triangles.iter().enumerate() {
            let k = levels[f];
            let r = pts.face_points(f);
            assert_eq!(r.len(), point_count(k));
            // The corners are the face's vertices; the normal of the flat grid is +z.
            let a = r.start + point_index(k, k as usize, 0);
            let b = r.start + point_index(k, 0, k as usize);
            let c = r.start + point_index(k, 0, 0);
            assert!(dist(pts.positions[a], m.positions[t[0] as usize]) < 1e-12);
            assert!(dist(pts.positions[b], m.positions[t[1] as usize]) < 1e-12);
            assert!(dist(pts.positions[c], m.positions[t[2] as usize]) < 1e-12);
            for p in r {
                assert_eq!(pts.face[p], f as u32);
                assert!(dist(pts.normals[p], [0.0, 0.0, 1.0]) < 1e-12);
                let w = pts.bary[p];
                let mut x = [0.0; 3];
                for q in 0..3 {
                    x = add_scaled(x, w[q], m.positions[t[q] as usize]);
                }
                assert!(dist(x, pts.positions[p]) < 1e-12);
            }
        }
        assert!(pts.face_points(m.triangles.len()).is_empty());
        assert!(matches!(
            SurfacePoints::lattice(&m, &[1]),
            Err(LatticeError::FaceCount { .. })
        ));
        let mut bad = levels.clone();
        bad[2] = 0;
        assert!(matches!(
            SurfacePoints::lattice(&m, &bad),
            Err(LatticeError::Level { face: 2, .. })
        ));
    }
}
