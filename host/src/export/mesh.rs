//! The mesh Blender gets: the model's vertices with their converted parameters and alpha, or,
//! when the model has alpha finer than the mesh (`face_alpha`, [`crate::lattice`]), every face
//! cut into the sub-triangles of one lattice level with alpha at each lattice point.
//!
//! Cycles interpolates a vertex attribute linearly over each triangle, as the renderer
//! interpolates a lattice's radiance over its sub-triangles, so alpha per lattice point on the
//! refined mesh is the lattice itself. The refined mesh is watertight: points on an edge are
//! made once, from the edge's corners in one order, and shared by the faces on both sides (whose
//! lattices store a point of a shared edge once each: the two ln alpha details are averaged
//! there, and the export report says by how much they differed). Every face is cut at the
//! model's largest level, so neighbours never meet at a T-junction a ray could slip through; a
//! face of a lower level gets its piecewise linear detail ([`ModelFile::alpha_at`]) sampled at
//! the finer points.

use std::collections::HashMap;

use super::convert::VertexConversion;
use crate::lattice::{is_corner, point_bary, points};
use crate::modelfile::ModelFile;

/// Per-vertex arrays of the exported mesh (object frame, mm).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExportMesh {
    /// Positions, mm.
    pub positions: Vec<[f64; 3]>,
    /// Unit normals.
    pub normals: Vec<[f64; 3]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
    /// Subsurface colour (total diffuse reflectance) per channel.
    pub colour: Vec<[f64; 3]>,
    /// Subsurface radius per channel, mm.
    pub radius_mm: Vec<[f64; 3]>,
    /// alpha(x_o) (Eq. 2/6) per channel.
    pub alpha: Vec<[f64; 3]>,
    /// Conversion log E per channel (NaN where none: no model of its own).
    pub log_e: Vec<[f64; 3]>,
    /// The slow lobe's subsurface colour per channel (two lobes, [`super::ColourRule::TwoLobe`];
    /// empty for one).
    pub slow_colour: Vec<[f64; 3]>,
    /// The slow lobe's radius per channel, mm (empty for one lobe).
    pub slow_radius_mm: Vec<[f64; 3]>,
    /// The Mix Shader's factor, the slow lobe's share, in every channel (empty for one lobe).
    pub slow_weight: Vec<[f64; 3]>,
}

/// What refining the mesh for a face lattice did.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Refinement {
    /// The level every face was cut at (1: not refined).
    pub level: u8,
    /// Lattice points on edges shared by two faces.
    pub shared_edge_points: usize,
    /// Largest |difference| of the two faces' ln alpha at a shared edge point (half of it is
    /// what the average changes on each side).
    pub max_edge_mismatch: f64,
}

/// The model's own mesh with the converted parameters and the vertex alphas.
pub fn vertex_mesh(model: &ModelFile, conv: &[VertexConversion]) -> ExportMesh {
    ExportMesh {
        positions: model.positions.clone(),
        normals: model.normals.clone(),
        triangles: model.triangles.clone(),
        colour: conv.iter().map(|v| v.colour).collect(),
        radius_mm: conv.iter().map(|v| v.radius_mm).collect(),
        alpha: model
            .vertices
            .iter()
            .map(|v| v.alpha.map(f64::from))
            .collect(),
        log_e: conv
            .iter()
            .map(|v| v.log_e.unwrap_or([f64::NAN; 3]))
            .collect(),
        slow_colour: slow(conv, |l, _| l.map_or([0.0; 3], |l| l.colour)),
        slow_radius_mm: slow(conv, |l, v| l.map_or(v.radius_mm, |l| l.radius_mm)),
        slow_weight: slow(conv, |l, _| [l.map_or(0.0, |l| l.weight); 3]),
    }
}

/// A slow-lobe array over the vertices when any vertex has a slow lobe (a vertex without one:
/// weight 0), else empty.
fn slow(
    conv: &[VertexConversion],
    get: impl Fn(Option<&super::convert::SlowLobe>, &VertexConversion) -> [f64; 3],
) -> Vec<[f64; 3]> {
    if conv.iter().all(|v| v.slow.is_none()) {
        return Vec::new();
    }
    conv.iter().map(|v| get(v.slow.as_ref(), v)).collect()
}

/// The mesh cut at the model's largest lattice level (see the module doc); the vertex mesh when
/// the model has no face lattice or only level 1.
pub fn refined_mesh(model: &ModelFile, conv: &[VertexConversion]) -> (ExportMesh, Refinement) {
    let base = vertex_mesh(model, conv);
    let Some(fa) = &model.face_alpha else {
        return (base, Refinement::default_level());
    };
    let k = fa.levels().iter().copied().max().unwrap_or(1);
    if k <= 1 {
        return (base, Refinement::default_level());
    }
    let kk = k as usize;
    let mut out = ExportMesh {
        triangles: Vec::with_capacity(model.triangles.len() * kk * kk),
        ..base
    };
    // Per created point: the sum of ln alpha over the faces that hold it, and how many.
    let mut ln_alpha_sum: Vec<[f64; 3]> = Vec::new();
    let mut holders: Vec<u32> = Vec::new();
    let mut first_ln: Vec<[f64; 3]> = Vec::new();
    let mut mismatch: f64 = 0.0;
    let nv = model.len();
    // (low corner, high corner, steps from low) → point.
    let mut edge_points: HashMap<(u32, u32, usize), u32> = HashMap::new();
    let mut ids = Vec::new();
    for (f, t) in model.triangles.iter().enumerate() {
        ids.clear();
        ids.resize(crate::lattice::point_count(k), 0u32);
        for (n, i, j) in points(k) {
            if is_corner(k, i, j) {
                ids[n] = t[if i == kk {
                    0
                } else if j == kk {
                    1
                } else {
                    2
                }];
                continue;
            }
            let w = point_bary(k, i, j);
            let la = model.alpha_at(f, w).map(|a| a.max(1e-30).ln());
            // On an edge: (from corner, towards corner, steps), in the lattice's coordinates:
            // j = 0 runs from c towards a, i = 0 from c towards b, i + j = k from a towards b.
            let edge = if j == 0 {
                Some((t[2], t[0], i))
            } else if i == 0 {
                Some((t[2], t[1], j))
            } else if i + j == kk {
                Some((t[0], t[1], j))
            } else {
                None
            };
            // Canonical: counted from the lower-numbered corner.
            let key = edge.map(|(from, to, s)| {
                if from < to {
                    (from, to, s)
                } else {
                    (to, from, kk - s)
                }
            });
            if let Some(key) = key
                && let Some(&id) = edge_points.get(&key)
            {
                ids[n] = id;
                let p = id as usize - nv;
                for c in 0..3 {
                    ln_alpha_sum[p][c] += la[c];
                    mismatch = mismatch.max((la[c] - first_ln[p][c]).abs());
                }
                holders[p] += 1;
                continue;
            }
            let id = out.positions.len() as u32;
            ids[n] = id;
            // Position and normal from the edge's corners in canonical order when on an edge,
            // so both faces build bit-identical points.
            let (x, nrm, lerp_w, corners) = match key {
                Some((lo, hi, s)) => {
                    let a = s as f64 / kk as f64;
                    let (pl, ph) = (model.positions[lo as usize], model.positions[hi as usize]);
                    let (nl, nh) = (model.normals[lo as usize], model.normals[hi as usize]);
                    (
                        [0, 1, 2].map(|d| pl[d] + a * (ph[d] - pl[d])),
                        [0, 1, 2].map(|d| nl[d] + a * (nh[d] - nl[d])),
                        [1.0 - a, a, 0.0],
                        [lo, hi, lo],
                    )
                }
                None => {
                    let lerp = |q: &dyn Fn(usize) -> [f64; 3]| {
                        let mut s = [0.0; 3];
                        for (c, &v) in t.iter().enumerate() {
                            let x = q(v as usize);
                            for d in 0..3 {
                                s[d] += w[c] * x[d];
                            }
                        }
                        s
                    };
                    (
                        lerp(&|v| model.positions[v]),
                        lerp(&|v| model.normals[v]),
                        w,
                        *t,
                    )
                }
            };
            let len = (nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]).sqrt();
            let nrm = if len > 1e-9 {
                nrm.map(|c| c / len)
            } else {
                model.normals[t[0] as usize]
            };
            let mix = |a: &[[f64; 3]]| -> [f64; 3] {
                let mut s = [0.0; 3];
                for (c, &v) in corners.iter().enumerate() {
                    for d in 0..3 {
                        s[d] += lerp_w[c] * a[v as usize][d];
                    }
                }
                s
            };
            out.positions.push(x);
            out.normals.push(nrm);
            let (col, rad, le) = (
                mix(&out.colour[..nv]),
                mix(&out.radius_mm[..nv]),
                mix(&out.log_e[..nv]),
            );
            out.colour.push(col);
            out.radius_mm.push(rad);
            out.log_e.push(le);
            if !out.slow_weight.is_empty() {
                let (sc, sr, sw) = (
                    mix(&out.slow_colour[..nv]),
                    mix(&out.slow_radius_mm[..nv]),
                    mix(&out.slow_weight[..nv]),
                );
                out.slow_colour.push(sc);
                out.slow_radius_mm.push(sr);
                out.slow_weight.push(sw);
            }
            out.alpha.push([0.0; 3]);
            ln_alpha_sum.push(la);
            first_ln.push(la);
            holders.push(1);
            if let Some(key) = key {
                edge_points.insert(key, id);
            }
        }
        let at = |i: usize, j: usize| ids[crate::lattice::point_index(k, i, j)];
        for i in 0..kk {
            for j in 0..kk - i {
                out.triangles.push([at(i, j), at(i + 1, j), at(i, j + 1)]);
                if i + j + 1 < kk {
                    out.triangles
                        .push([at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)]);
                }
            }
        }
    }
    let mut shared = 0;
    for (p, (s, &h)) in ln_alpha_sum.iter().zip(&holders).enumerate() {
        if h > 1 {
            shared += 1;
        }
        out.alpha[nv + p] = s.map(|x| (x / h as f64).exp());
    }
    (
        out,
        Refinement {
            level: k,
            shared_edge_points: shared,
            max_edge_mismatch: mismatch,
        },
    )
}

impl Refinement {
    fn default_level() -> Refinement {
        Refinement {
            level: 1,
            ..Refinement::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lattice::{FaceAlpha, point_count};

    fn square_with_lattice(levels: Vec<u8>, detail: f32) -> ModelFile {
        let p = vec![
            [0.0, 0.0, 0.0],
            [2.0, 0.0, 0.0],
            [2.0, 2.0, 0.0],
            [0.0, 2.0, 0.0],
        ];
        let t = vec![[0, 1, 2], [0, 2, 3]];
        let mut m =
            ModelFile::homogeneous(p, vec![[0.0, 0.0, 1.0]; 4], t, [1.0, 1.0], &[(0.5, -2.0)]);
        let mut d = Vec::new();
        for &k in &levels {
            for (_, i, j) in points(k) {
                d.push(if is_corner(k, i, j) {
                    [0.0; 3]
                } else {
                    [detail; 3]
                });
            }
            assert!(point_count(k) > 0);
        }
        m.face_alpha = Some(FaceAlpha::new(levels, d).unwrap());
        m
    }

    /// Two faces of level 4 sharing the diagonal: 16 sub-triangles each, the diagonal's three
    /// inner points made once, every alpha the lattice's, and no crack (each edge of the refined
    /// mesh is used by one or two triangles, the outer boundary once).
    #[test]
    fn a_lattice_becomes_a_watertight_finer_mesh_with_alpha_per_point() {
        let m = square_with_lattice(vec![4, 4], 0.5f32.ln());
        let conv = super::super::convert::convert(&m, &());
        let (mesh, r) = refined_mesh(&m, &conv);
        assert_eq!(r.level, 4);
        assert_eq!(mesh.triangles.len(), 32);
        // 4 corners + 5 edges × 3 + 2 faces × 3 inner points.
        assert_eq!(mesh.positions.len(), 4 + 15 + 6);
        assert_eq!(r.shared_edge_points, 3);
        assert!(r.max_edge_mismatch < 1e-12);
        for (v, a) in mesh.alpha.iter().enumerate() {
            let want = if v < 4 { 1.0 } else { 0.5 };
            assert!((a[0] - want).abs() < 1e-6, "{v}: {a:?}");
        }
        let mut uses: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &mesh.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *uses.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        let boundary = uses.values().filter(|&&n| n == 1).count();
        assert!(uses.values().all(|&n| n <= 2));
        assert_eq!(boundary, 16, "the square's four sides, 4 segments each");
        assert!(
            mesh.colour
                .iter()
                .all(|c| (c[0] - mesh.colour[0][0]).abs() < 1e-9)
        );
    }

    /// A face of level 2 beside one of level 4 is cut at 4 (no T-junction), its detail sampled.
    #[test]
    fn mixed_levels_are_cut_at_the_largest() {
        let m = square_with_lattice(vec![2, 4], 0.2);
        let conv = super::super::convert::convert(&m, &());
        let (mesh, r) = refined_mesh(&m, &conv);
        assert_eq!((r.level, mesh.triangles.len()), (4, 32));
        assert!(
            r.max_edge_mismatch > 0.0,
            "level 2 is linear between its points"
        );
        let (plain, r1) = refined_mesh(&square_with_lattice(vec![1, 1], 0.0), &conv);
        assert_eq!((r1.level, plain.triangles.len()), (1, 2));
    }
}
