//! The modulation texture alpha(x_o) finer than the mesh (section 5: "the modulation texture
//! alpha(x_o) is determined as higher resolution texture"): per face, a barycentric lattice of
//! level k whose points carry ln alpha relative to the interpolated vertex alphas
//! (`docs/model-format.md`, elements `face_alpha` and `face_alpha_point`, since `subsurf-model/5`).
//!
//! Why a per-face barycentric lattice rather than a UV atlas: the meshes we read have no
//! parameterisation, and a lattice needs none; its level is chosen per face from what the images
//! resolve there, so texels exist only where the data can determine them, and level 1 (the three
//! corners only) is exactly the per-vertex alpha of earlier formats.
//!
//! Lattice points of level k are (i, j) with i + j <= k, at barycentric coordinates
//! (i/k, j/k, 1 − (i + j)/k) of the face's corners (a, b, c): (k, 0) is corner a, (0, k) corner b,
//! (0, 0) corner c. Points are stored in the order i = 0..=k, then j = 0..=k − i
//! ([`point_index`]). The detail at the three corners is 0 by construction, so a reader that
//! ignores the element, or a face of level 1, gives the per-vertex alpha.

/// The largest lattice level: 45 points per face. Finer than this the bilinear pixel reads of
/// neighbouring points overlap on every mesh and camera we scan.
pub const MAX_LEVEL: u8 = 8;

/// Number of lattice points of level `k`: (k + 1)(k + 2) / 2.
pub const fn point_count(k: u8) -> usize {
    let k = k as usize;
    (k + 1) * (k + 2) / 2
}

/// Index of lattice point (i, j) of level `k` in a face's detail list (i + j <= k).
pub const fn point_index(k: u8, i: usize, j: usize) -> usize {
    let k = k as usize;
    // Rows i' < i hold (k + 1 − i') points each.
    i * (k + 1) - i * i.saturating_sub(1) / 2 + j
}

/// Barycentric coordinates (weights of corners a, b, c) of lattice point (i, j) of level `k`.
pub fn point_bary(k: u8, i: usize, j: usize) -> [f64; 3] {
    let kf = k.max(1) as f64;
    let (u, v) = (i as f64 / kf, j as f64 / kf);
    [u, v, (1.0 - u - v).max(0.0)]
}

/// Every lattice point of level `k` as `(index, i, j)`, in storage order.
pub fn points(k: u8) -> impl Iterator<Item = (usize, usize, usize)> {
    let kk = k as usize;
    (0..=kk)
        .flat_map(move |i| (0..=kk - i).map(move |j| (i, j)))
        .enumerate()
        .map(|(n, (i, j))| (n, i, j))
}

/// True for the three corner points of level `k` (where the detail is 0).
pub fn is_corner(k: u8, i: usize, j: usize) -> bool {
    let k = k as usize;
    (i == k && j == 0) || (i == 0 && j == k) || (i == 0 && j == 0)
}

/// Why a face-alpha lattice is not valid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum LatticeError {
    /// One level per face is needed.
    #[error("{levels} face levels for {faces} faces")]
    FaceCount {
        /// Levels given.
        levels: usize,
        /// Faces of the mesh.
        faces: usize,
    },
    /// A level outside 1..=[`MAX_LEVEL`].
    #[error("face {face}: level {level} outside 1..={MAX_LEVEL}")]
    Level {
        /// The face.
        face: usize,
        /// Its level.
        level: u8,
    },
    /// The detail list does not match the levels.
    #[error("{got} detail points where the levels need {want}")]
    PointCount {
        /// Points held.
        got: usize,
        /// Points the levels need.
        want: usize,
    },
    /// A non-finite detail, or a corner whose detail is not 0.
    #[error("face {face}, point {point}: {what}")]
    Detail {
        /// The face.
        face: usize,
        /// The point's index in the face's list.
        point: usize,
        /// What is wrong.
        what: &'static str,
    },
}

/// ln alpha detail per face lattice point and channel, relative to the barycentric interpolation
/// of the face's three vertex alphas: alpha(x_o) = (Σ w_j alpha_j) · exp(detail(x_o)), `detail`
/// interpolated linearly over the lattice sub-triangle holding x_o ([`FaceAlpha::detail_at`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FaceAlpha {
    levels: Vec<u8>,
    /// Start of each face's points in `detail` (one more entry than faces).
    start: Vec<u32>,
    detail: Vec<[f32; 3]>,
}

impl FaceAlpha {
    /// A lattice from per-face levels and the faces' detail lists concatenated in face order,
    /// validated: levels in 1..=[`MAX_LEVEL`], the point counts, finite details, 0 at corners.
    pub fn new(levels: Vec<u8>, detail: Vec<[f32; 3]>) -> Result<FaceAlpha, LatticeError> {
        let mut start = Vec::with_capacity(levels.len() + 1);
        let mut at = 0usize;
        for (face, &level) in levels.iter().enumerate() {
            if !(1..=MAX_LEVEL).contains(&level) {
                return Err(LatticeError::Level { face, level });
            }
            start.push(at as u32);
            at += point_count(level);
        }
        start.push(at as u32);
        if detail.len() != at {
            return Err(LatticeError::PointCount {
                got: detail.len(),
                want: at,
            });
        }
        let fa = FaceAlpha {
            levels,
            start,
            detail,
        };
        for face in 0..fa.levels.len() {
            let k = fa.levels[face];
            let d = fa.face_detail(face);
            for (n, i, j) in points(k) {
                if d[n].iter().any(|x| !x.is_finite()) {
                    return Err(LatticeError::Detail {
                        face,
                        point: n,
                        what: "non-finite detail",
                    });
                }
                if is_corner(k, i, j) && d[n] != [0.0; 3] {
                    return Err(LatticeError::Detail {
                        face,
                        point: n,
                        what: "a corner's detail must be 0 (the vertex alpha holds it)",
                    });
                }
            }
        }
        Ok(fa)
    }

    /// A lattice of level 1 everywhere: no detail, the per-vertex alpha.
    pub fn flat(faces: usize) -> FaceAlpha {
        FaceAlpha::new(vec![1; faces], vec![[0.0; 3]; faces * point_count(1)])
            .expect("level 1 with zero detail is valid")
    }

    /// Number of faces.
    pub fn faces(&self) -> usize {
        self.levels.len()
    }

    /// Level of face `face`.
    pub fn level(&self, face: usize) -> u8 {
        self.levels.get(face).copied().unwrap_or(1)
    }

    /// Per-face levels.
    pub fn levels(&self) -> &[u8] {
        &self.levels
    }

    /// The detail list of face `face`, in [`point_index`] order (empty past the last face).
    pub fn face_detail(&self, face: usize) -> &[[f32; 3]] {
        match (self.start.get(face), self.start.get(face + 1)) {
            (Some(&a), Some(&b)) => &self.detail[a as usize..b as usize],
            _ => &[],
        }
    }

    /// Every face's details concatenated in face order.
    pub fn detail(&self) -> &[[f32; 3]] {
        &self.detail
    }

    /// True when no point carries detail (the per-vertex alpha alone).
    pub fn is_flat(&self) -> bool {
        self.detail.iter().all(|d| *d == [0.0; 3])
    }

    /// ln alpha detail at barycentric coordinates `bary` (weights of corners a, b, c) of face
    /// `face`: linear over the lattice sub-triangle holding the point, so continuous within the
    /// face and 0 at its corners; 0 for a face outside the lattice.
    pub fn detail_at(&self, face: usize, bary: [f64; 3]) -> [f64; 3] {
        let d = self.face_detail(face);
        if d.is_empty() {
            return [0.0; 3];
        }
        let k = self.levels[face];
        let kf = k as f64;
        let unit = |w: f64| {
            if w.is_finite() {
                w.clamp(0.0, 1.0)
            } else {
                0.0
            }
        };
        let x = unit(bary[0]) * kf;
        let y = (unit(bary[1]) * kf).min(kf - x).max(0.0);
        let kk = k as usize;
        let i0 = (x.floor() as usize).min(kk);
        let j0 = (y.floor() as usize).min(kk - i0);
        let (fx, fy) = (x - i0 as f64, y - j0 as f64);
        let at = |i: usize, j: usize| d[point_index(k, i, j)];
        // The sub-triangle holding (x, y): the "lower" one (i0, j0), (i0+1, j0), (i0, j0+1) when
        // fx + fy <= 1, else the "upper" one (i0+1, j0+1), (i0, j0+1), (i0+1, j0). On the face's
        // long edge (i0 + j0 = k) only the point itself exists.
        let (p, w): ([[f32; 3]; 3], [f64; 3]) = if i0 + j0 >= kk {
            ([at(i0, j0); 3], [1.0, 0.0, 0.0])
        } else if fx + fy <= 1.0 || i0 + j0 + 2 > kk {
            // (The second test: x + y = k rounded a hair above k.)
            (
                [at(i0, j0), at(i0 + 1, j0), at(i0, j0 + 1)],
                [1.0 - fx - fy, fx, fy],
            )
        } else {
            (
                [at(i0 + 1, j0 + 1), at(i0, j0 + 1), at(i0 + 1, j0)],
                [fx + fy - 1.0, 1.0 - fx, 1.0 - fy],
            )
        };
        let mut out = [0.0; 3];
        for (pt, wt) in p.iter().zip(w) {
            for c in 0..3 {
                out[c] += wt * pt[c] as f64;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn indices_are_dense_and_in_storage_order() {
        for k in 1..=MAX_LEVEL {
            let all: Vec<_> = points(k).collect();
            assert_eq!(all.len(), point_count(k));
            for (n, i, j) in all {
                assert_eq!(point_index(k, i, j), n, "level {k} ({i},{j})");
            }
        }
        assert_eq!(point_bary(4, 4, 0), [1.0, 0.0, 0.0]);
        assert_eq!(point_bary(4, 0, 4), [0.0, 1.0, 0.0]);
        assert_eq!(point_bary(4, 0, 0), [0.0, 0.0, 1.0]);
    }

    fn lattice(k: u8, f: impl Fn(usize, usize) -> f32) -> FaceAlpha {
        let d = points(k)
            .map(|(_, i, j)| {
                if is_corner(k, i, j) {
                    [0.0; 3]
                } else {
                    [f(i, j); 3]
                }
            })
            .collect();
        FaceAlpha::new(vec![k], d).unwrap()
    }

    #[test]
    fn detail_is_exact_at_lattice_points_and_zero_at_corners() {
        let k = 5;
        let fa = lattice(k, |i, j| (i * 10 + j) as f32 * 0.01);
        for (n, i, j) in points(k) {
            let got = fa.detail_at(0, point_bary(k, i, j))[1];
            let want = fa.face_detail(0)[n][1] as f64;
            assert!((got - want).abs() < 1e-6, "({i},{j}): {got} vs {want}");
        }
        assert_eq!(fa.detail_at(0, [1.0, 0.0, 0.0]), [0.0; 3]);
        assert_eq!(fa.detail_at(0, [0.0, 1.0, 0.0]), [0.0; 3]);
        assert_eq!(fa.detail_at(0, [0.0, 0.0, 1.0]), [0.0; 3]);
    }

    proptest! {
        /// A detail linear in (u, v) away from the corners is reproduced exactly between
        /// lattice points: the interpolation is piecewise linear over the sub-triangles.
        #[test]
        fn interpolation_is_linear_within_sub_triangles(u in 0.0f64..1.0, t in 0.0f64..1.0) {
            let k = 4u8;
            let v = (1.0 - u) * t;
            let fa = lattice(k, |i, j| (i as f32 - 2.0 * j as f32) * 0.1);
            // Interior points carry 0.1 (i − 2j); check against the sub-triangle's plane away
            // from corner cells, where the corner zeros break linearity.
            let (x, y) = (u * 4.0, v * 4.0);
            let near_corner = (x > 3.0 && y < 1.0) || (y > 3.0 && x < 1.0) || (x < 1.0 && y < 1.0);
            prop_assume!(!near_corner);
            let got = fa.detail_at(0, [u, v, 1.0 - u - v])[0];
            let want = 0.1 * (x - 2.0 * y);
            prop_assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        }

        #[test]
        fn detail_at_is_finite_for_any_coordinates(a in -2.0f64..3.0, b in -2.0f64..3.0) {
            let fa = lattice(3, |i, j| (i + j) as f32);
            let d = fa.detail_at(0, [a, b, 1.0 - a - b]);
            prop_assert!(d.iter().all(|x| x.is_finite()));
            prop_assert_eq!(fa.detail_at(7, [a, b, 0.0]), [0.0; 3]);
        }
    }

    #[test]
    fn invalid_lattices_are_refused() {
        assert!(matches!(
            FaceAlpha::new(vec![0], vec![]),
            Err(LatticeError::Level { .. })
        ));
        assert!(matches!(
            FaceAlpha::new(vec![9], vec![[0.0; 3]; point_count(9)]),
            Err(LatticeError::Level { .. })
        ));
        assert!(matches!(
            FaceAlpha::new(vec![2], vec![[0.0; 3]; 5]),
            Err(LatticeError::PointCount { .. })
        ));
        let mut d = vec![[0.0; 3]; point_count(2)];
        d[point_index(2, 1, 0)] = [f32::NAN, 0.0, 0.0];
        assert!(matches!(
            FaceAlpha::new(vec![2], d),
            Err(LatticeError::Detail { .. })
        ));
        let mut d = vec![[0.0; 3]; point_count(2)];
        d[point_index(2, 2, 0)] = [0.5, 0.0, 0.0];
        assert!(matches!(
            FaceAlpha::new(vec![2], d),
            Err(LatticeError::Detail { .. })
        ));
        assert!(FaceAlpha::flat(3).is_flat());
    }
}
