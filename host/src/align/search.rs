//! Global initialisation: poses to start ICP from that do not depend on where the mesh starts.
//! The principal axes of the mesh's surface and of the spot points are matched in all 24 ways a
//! right-handed frame can be laid on another (the eigenvectors' order and signs are not
//! determined by the data), at three scales around the ratio of their spreads. The spots cover
//! only what the camera and the laser both reached, so neither their centre nor their axes are
//! the surface's: the hypotheses only need to fall inside ICP's basin, and ICP from each decides.
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::similarity::{Similarity, v};
use crate::dataset::Mesh;
use crate::geometry::V3;

/// Centroid and covariance of the surface, area-weighted (a triangle's exact second moment), so
/// a finely meshed patch does not outweigh a coarse one.
pub(crate) fn surface_moments(mesh: &Mesh) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let mut area = 0.0;
    let mut first = Vector3::zeros();
    let mut second = Matrix3::zeros();
    for t in &mesh.triangles {
        let [p, q, r] = t.map(|i| v(mesh.positions[i as usize]));
        let a = 0.5 * (q - p).cross(&(r - p)).norm();
        if !a.is_finite() {
            continue;
        }
        let s = p + q + r;
        area += a;
        first += a * s / 3.0;
        second += a / 12.0
            * (p * p.transpose() + q * q.transpose() + r * r.transpose() + s * s.transpose());
    }
    if area.is_nan() || area <= 0.0 {
        return None;
    }
    let c = first / area;
    Some((c, second / area - c * c.transpose()))
}

/// Centroid and covariance of points.
pub(crate) fn point_moments(points: &[V3]) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |acc, p| acc + v(*p)) / n;
    let cov = points.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = v(*p) - c;
        acc + d * d.transpose()
    }) / n;
    Some((c, cov))
}

/// Eigenvectors as columns, largest eigenvalue first, made right-handed.
pub(crate) fn axes(cov: &Matrix3<f64>) -> Matrix3<f64> {
    let eig = SymmetricEigen::new(*cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let mut u = Matrix3::from_columns(&order.map(|k| eig.eigenvectors.column(k).into_owned()));
    if u.determinant() < 0.0 {
        u.set_column(2, &(-u.column(2)));
    }
    u
}

/// The 24 rotations that map the coordinate axes onto themselves (signed permutations with
/// determinant +1).
pub(crate) fn axis_rotations() -> Vec<Matrix3<f64>> {
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut out = Vec::with_capacity(24);
    for p in perms {
        for signs in 0..8u32 {
            let mut m = Matrix3::zeros();
            for (row, &col) in p.iter().enumerate() {
                m[(row, col)] = if signs >> row & 1 == 1 { -1.0 } else { 1.0 };
            }
            if m.determinant() > 0.0 {
                out.push(m);
            }
        }
    }
    out
}

/// The starting poses: 24 axis matchings × scales 0.8, 1, 1.25 of the spread ratio (or the
/// one known `scale`), each placing the mesh's centroid on the points'.
pub(crate) fn hypotheses(mesh: &Mesh, points: &[V3], scale: Option<f64>) -> Vec<Similarity> {
    let (Some((cm, covm)), Some((cp, covp))) = (surface_moments(mesh), point_moments(points))
    else {
        return Vec::new();
    };
    let spread = (covp.trace() / covm.trace()).sqrt();
    if !(spread.is_finite() && spread > 0.0) {
        return Vec::new();
    }
    let scales = match scale {
        Some(s) => vec![s],
        None => vec![0.8 * spread, spread, 1.25 * spread],
    };
    let (um, up) = (axes(&covm), axes(&covp));
    let mut out = Vec::new();
    for s in axis_rotations() {
        let rotation = up * s * um.transpose();
        for &scale in &scales {
            out.push(Similarity {
                scale,
                rotation,
                translation: cp - scale * rotation * cm,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_24_axis_rotations_are_distinct_proper_rotations() {
        let r = axis_rotations();
        assert_eq!(r.len(), 24);
        for (i, a) in r.iter().enumerate() {
            assert!((a.determinant() - 1.0).abs() < 1e-12);
            assert!((a * a.transpose() - Matrix3::identity()).norm() < 1e-12);
            for b in &r[i + 1..] {
                assert!((a - b).norm() > 0.5);
            }
        }
    }

    #[test]
    fn surface_moments_of_a_unit_square_are_exact() {
        let (m, _) = Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        );
        let (c, cov) = surface_moments(&m).unwrap();
        assert!((c - Vector3::new(0.5, 0.5, 0.0)).norm() < 1e-12);
        // Var of a uniform [0, 1] is 1/12.
        assert!((cov[(0, 0)] - 1.0 / 12.0).abs() < 1e-12, "{cov}");
        assert!((cov[(1, 1)] - 1.0 / 12.0).abs() < 1e-12);
        assert!(cov[(0, 1)].abs() < 1e-12 && cov[(2, 2)].abs() < 1e-12);
    }
}
