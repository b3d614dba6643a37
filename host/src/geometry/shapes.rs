//! Small closed meshes built from numbers: a box and an ellipsoid (an icosphere scaled), for
//! tests and worked examples that need a known shape without a file.
//!
//! Their vertex and triangle order is fixed, so the same call gives the same mesh bit for bit
//! and results computed on it do not move between builds.

use super::V3;
use crate::dataset::Mesh;

/// The axis-aligned box from corner `lo` to corner `hi` (mm): 8 vertices, 12 triangles
/// counter-clockwise seen from outside.
pub fn block(lo: V3, hi: V3) -> Mesh {
    let p = vec![
        [lo[0], lo[1], lo[2]],
        [hi[0], lo[1], lo[2]],
        [hi[0], hi[1], lo[2]],
        [lo[0], hi[1], lo[2]],
        [lo[0], lo[1], hi[2]],
        [hi[0], lo[1], hi[2]],
        [hi[0], hi[1], hi[2]],
        [lo[0], hi[1], hi[2]],
    ];
    let t = vec![
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ];
    Mesh::new(p, t).0
}

/// The ellipsoid centred at the origin with semi-axes `axes` along x, y, z (mm): an icosahedron
/// with each face split in 4, `subdivisions` times, its vertices pushed onto the unit sphere and
/// scaled. The icosahedron's half turns about x, y and z map it onto itself, so the mesh has
/// exactly the ellipsoid's symmetries. `subdivisions` n gives 20·4ⁿ triangles.
pub fn ellipsoid(axes: V3, subdivisions: usize) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut pos: Vec<V3> = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::with_capacity(4 * tris.len());
        for tri in &tris {
            let m: [u32; 3] = std::array::from_fn(|k| {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    let (p, q) = (pos[a as usize], pos[b as usize]);
                    pos.push(std::array::from_fn(|i| 0.5 * (p[i] + q[i])));
                    pos.len() as u32 - 1
                })
            });
            next.extend([
                [tri[0], m[0], m[2]],
                [tri[1], m[1], m[0]],
                [tri[2], m[2], m[1]],
                [m[0], m[1], m[2]],
            ]);
        }
        tris = next;
    }
    let pos = pos
        .iter()
        .map(|p| {
            let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            std::array::from_fn(|i| axes[i] * p[i] / n)
        })
        .collect();
    Mesh::new(pos, tris).0
}

/// The sphere of radius `radius` centred at the origin: [`ellipsoid`] with equal axes.
pub fn icosphere(radius: f64, subdivisions: usize) -> Mesh {
    ellipsoid([radius; 3], subdivisions)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shapes_are_closed_and_of_the_size_asked() {
        let s = icosphere(2.0, 2);
        assert_eq!(s.triangles.len(), 20 * 16);
        assert_eq!(s.positions.len(), 10 * 16 + 2);
        for p in &s.positions {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((r - 2.0).abs() < 1e-12, "{r}");
        }
        let b = block([-1.0, -2.0, -3.0], [1.0, 2.0, 0.0]);
        assert_eq!((b.positions.len(), b.triangles.len()), (8, 12));
        // Every edge of a closed mesh is shared by exactly two triangles, once each way.
        for m in [&s, &b] {
            let mut edges = std::collections::HashMap::new();
            for t in &m.triangles {
                for k in 0..3 {
                    *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
                }
            }
            for (&(a, b), &n) in &edges {
                assert_eq!((n, edges.get(&(b, a))), (1, Some(&1)));
            }
        }
        // The box's normals point out of it: its top vertex normals have a positive z.
        assert!(b.normals[4..].iter().all(|n| n[2] > 0.0));
    }
}
