//! The galvo model: two DAC codes → the laser ray in the world frame, and its fit from laser
//! spots observed on a planar target.
//!
//! Model: the beam leaves a pivot `origin`; code `c` deflects it by the optical angles
//! `theta = gain · (c − centre)` about the galvo frame's y and x axes, so in the galvo frame the
//! direction is `normalize(tan θx, tan θy, 1)`, rotated into the world by `world_from_galvo`.
//! The small offset between the two mirrors of a real galvo head is not modelled; at the paper's
//! 850 mm throw it moves the spot by well under a pixel.

use super::lsq::minimize;
use super::{CalibError, cross, dot, normalize, sub};
use nalgebra::{DVector, Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Galvo codes → laser ray.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GalvoModel {
    /// Beam pivot in the world frame (mm).
    pub origin: [f64; 3],
    /// Rotation world ← galvo, row-major; the galvo frame's `+z` is the undeflected beam.
    pub world_from_galvo: [[f64; 3]; 3],
    /// Codes of the undeflected beam.
    pub centre: [f64; 2],
    /// Optical deflection in radians per code, per axis.
    pub radians_per_code: [f64; 2],
    /// Largest code the DAC accepts (codes run `0..=max_code`).
    pub max_code: u16,
}

/// One laser spot seen on the target: the codes sent and the spot's 3D position (world, mm).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GalvoObservation {
    /// Galvo codes.
    pub codes: [u16; 2],
    /// Spot position on the target, world frame (mm).
    pub point: [f64; 3],
}

impl GalvoModel {
    /// A galvo at `origin` whose centre code aims at `target`, spanning `±half_range_rad`
    /// over `0..=max_code`.
    pub fn looking_at(
        origin: [f64; 3],
        target: [f64; 3],
        max_code: u16,
        half_range_rad: f64,
    ) -> Self {
        let z = normalize(sub(target, origin));
        let x = normalize(cross([0.0, 0.0, 1.0], z));
        let y = cross(z, x);
        let half = max_code as f64 / 2.0;
        GalvoModel {
            origin,
            world_from_galvo: [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]],
            centre: [half, half],
            radians_per_code: [half_range_rad / half, half_range_rad / half],
            max_code,
        }
    }

    /// The laser ray `(origin, unit direction)` for the codes (world frame).
    pub fn ray(&self, codes: [u16; 2]) -> ([f64; 3], [f64; 3]) {
        self.ray_f([codes[0] as f64, codes[1] as f64])
    }

    /// [`GalvoModel::ray`] for fractional codes.
    pub fn ray_f(&self, codes: [f64; 2]) -> ([f64; 3], [f64; 3]) {
        let tx = (self.radians_per_code[0] * (codes[0] - self.centre[0])).tan();
        let ty = (self.radians_per_code[1] * (codes[1] - self.centre[1])).tan();
        let g = normalize([tx, ty, 1.0]);
        let r = &self.world_from_galvo;
        let d = [dot(r[0], g), dot(r[1], g), dot(r[2], g)];
        (self.origin, normalize(d))
    }

    pub(crate) fn validate(&self) -> Result<(), CalibError> {
        let finite = self
            .origin
            .iter()
            .chain(self.world_from_galvo.iter().flatten())
            .chain(self.centre.iter())
            .chain(self.radians_per_code.iter())
            .all(|v| v.is_finite());
        if !finite || self.radians_per_code.contains(&0.0) || self.max_code == 0 {
            return Err(CalibError::Invalid(
                "galvo: origin, rotation, centre and gains must be finite, gains non-zero".into(),
            ));
        }
        let r = mat(&self.world_from_galvo);
        if ((r.transpose() * r) - Matrix3::identity()).norm() > 1e-6 {
            return Err(CalibError::Invalid(
                "galvo: world_from_galvo is not a rotation".into(),
            ));
        }
        Ok(())
    }
}

fn mat(r: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| r[i][j])
}

/// Fits the galvo model to spots seen on a planar target placed at two or more distances.
///
/// Codes seen at two placements give a line each; the lines' common point is the pivot and
/// their directions give centre and gains (closed form), which Levenberg–Marquardt then refines
/// over all spots by the distance of each spot from its predicted ray. Returns the model and the
/// RMS spot-to-ray distance in mm.
pub fn fit_galvo(obs: &[GalvoObservation], max_code: u16) -> Result<(GalvoModel, f64), CalibError> {
    if obs.is_empty() {
        return Err(CalibError::TargetNotFound(
            "galvo: no laser spots were observed on the target".into(),
        ));
    }
    let mut by_code: BTreeMap<[u16; 2], Vec<[f64; 3]>> = BTreeMap::new();
    for o in obs {
        if o.point.iter().any(|v| !v.is_finite()) {
            return Err(CalibError::Invalid(format!(
                "galvo: spot for codes {:?} is not a finite point",
                o.codes
            )));
        }
        by_code.entry(o.codes).or_default().push(o.point);
    }
    // Lines through the first and farthest spot of each code.
    let mut lines = Vec::new();
    for (codes, pts) in &by_code {
        let a = pts[0];
        let Some(b) = pts
            .iter()
            .copied()
            .max_by(|p, q| dist(*p, a).total_cmp(&dist(*q, a)))
        else {
            continue;
        };
        if dist(a, b) > 1.0 {
            lines.push((*codes, a, normalize(sub(b, a))));
        }
    }
    if lines.len() < 4 {
        return Err(CalibError::NotEnoughData(format!(
            "galvo: only {} code pairs were seen at two different target distances; at least 4 \
             are needed (place the target at two or more distances)",
            lines.len()
        )));
    }
    // Pivot: least-squares point nearest to all lines.
    let mut m = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for (_, a, d) in &lines {
        let d = Vector3::from(*d);
        let p = Matrix3::identity() - d * d.transpose();
        m += p;
        rhs += p * Vector3::from(*a);
    }
    let origin = m.try_inverse().map(|mi| mi * rhs).ok_or_else(|| {
        CalibError::NotEnoughData("galvo: the spot lines are all parallel".into())
    })?;
    let origin = [origin[0], origin[1], origin[2]];
    // Orient directions away from the pivot and build a provisional frame.
    let dirs: Vec<([u16; 2], [f64; 3])> = lines
        .iter()
        .map(|(c, a, d)| {
            let s = if dot(sub(*a, origin), *d) < 0.0 {
                -1.0
            } else {
                1.0
            };
            (*c, [d[0] * s, d[1] * s, d[2] * s])
        })
        .collect();
    let mut zsum = [0.0; 3];
    for (_, d) in &dirs {
        zsum = [zsum[0] + d[0], zsum[1] + d[1], zsum[2] + d[2]];
    }
    let z0 = normalize(zsum);
    let helper = if z0[2].abs() < 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let x0 = normalize(cross(helper, z0));
    let y0 = cross(z0, x0);
    // Linear fit of tan-angles against codes: [a b]ᵀ = A [cx cy]ᵀ + t.
    let n = dirs.len();
    let mut design = nalgebra::DMatrix::zeros(n, 3);
    let mut ta = DVector::zeros(n);
    let mut tb = DVector::zeros(n);
    for (k, (c, d)) in dirs.iter().enumerate() {
        let dz = dot(*d, z0);
        design[(k, 0)] = c[0] as f64;
        design[(k, 1)] = c[1] as f64;
        design[(k, 2)] = 1.0;
        ta[k] = dot(*d, x0) / dz;
        tb[k] = dot(*d, y0) / dz;
    }
    let svd = design.clone().svd(true, true);
    let sa = svd
        .solve(&ta, 1e-12)
        .map_err(|e| CalibError::NotEnoughData(e.into()))?;
    let sb = svd
        .solve(&tb, 1e-12)
        .map_err(|e| CalibError::NotEnoughData(e.into()))?;
    let a = nalgebra::Matrix2::new(sa[0], sa[1], sb[0], sb[1]);
    let centre = a
        .try_inverse()
        .map(|ai| ai * nalgebra::Vector2::new(-sa[2], -sb[2]))
        .ok_or_else(|| {
            CalibError::NotEnoughData("galvo: codes of one axis never changed the beam".into())
        })?;
    let gx = (a[(0, 0)].powi(2) + a[(1, 0)].powi(2)).sqrt();
    let gy = (a[(0, 1)].powi(2) + a[(1, 1)].powi(2)).sqrt();
    let phi = a[(1, 0)].atan2(a[(0, 0)]);
    // Galvo x axis is the direction code 0 deflects along; y completes the frame (sign of gy
    // carries a possible mirror).
    let gxv = [
        x0[0] * phi.cos() + y0[0] * phi.sin(),
        x0[1] * phi.cos() + y0[1] * phi.sin(),
        x0[2] * phi.cos() + y0[2] * phi.sin(),
    ];
    let gyv = cross(z0, gxv);
    let ysign = if a[(1, 1)] * phi.cos() - a[(0, 1)] * phi.sin() >= 0.0 {
        1.0
    } else {
        -1.0
    };
    let r0 = Matrix3::from_columns(&[Vector3::from(gxv), Vector3::from(gyv), Vector3::from(z0)]);
    let init = GalvoModel {
        origin,
        world_from_galvo: to_rows(&r0),
        centre: [centre[0], centre[1]],
        radians_per_code: [gx, ysign * gy],
        max_code,
    };
    let model_of = |p: &DVector<f64>| -> GalvoModel {
        let rot = Rotation3::new(Vector3::new(p[3], p[4], p[5])).into_inner();
        GalvoModel {
            origin: [p[0], p[1], p[2]],
            world_from_galvo: to_rows(&(r0 * rot)),
            centre: [p[6], p[7]],
            radians_per_code: [p[8], p[9]],
            max_code,
        }
    };
    let p0 = DVector::from_vec(vec![
        init.origin[0],
        init.origin[1],
        init.origin[2],
        0.0,
        0.0,
        0.0,
        init.centre[0],
        init.centre[1],
        init.radians_per_code[0],
        init.radians_per_code[1],
    ]);
    let residual = |p: &DVector<f64>| -> DVector<f64> {
        let g = model_of(p);
        let mut r = Vec::with_capacity(obs.len() * 3);
        for o in obs {
            let (orig, d) = g.ray(o.codes);
            let v = sub(o.point, orig);
            let t = dot(v, d);
            r.extend_from_slice(&[v[0] - t * d[0], v[1] - t * d[1], v[2] - t * d[2]]);
        }
        DVector::from_vec(r)
    };
    let (p, rms) = minimize(p0, residual)
        .ok_or_else(|| CalibError::NotConverged("galvo: the ray fit did not converge".into()))?;
    let model = model_of(&p);
    model.validate()?;
    Ok((model, rms))
}

fn to_rows(r: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [
        [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
        [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
        [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
    ]
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d).sqrt()
}

/// Where a ray meets the plane `n·p = c` (`None` if parallel or behind).
pub fn ray_plane(origin: [f64; 3], dir: [f64; 3], n: [f64; 3], c: f64) -> Option<[f64; 3]> {
    let den = dot(n, dir);
    if den.abs() < 1e-12 {
        return None;
    }
    let t = (c - dot(n, origin)) / den;
    (t > 0.0).then(|| {
        [
            origin[0] + t * dir[0],
            origin[1] + t * dir[1],
            origin[2] + t * dir[2],
        ]
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spots(truth: &GalvoModel, planes: &[f64], noise: f64) -> Vec<GalvoObservation> {
        let mut out = Vec::new();
        let mut k = 0u32;
        for &y in planes {
            for cx in (2000..64000).step_by(15000) {
                for cy in (2000..64000).step_by(15000) {
                    let codes = [cx as u16, cy as u16];
                    let (o, d) = truth.ray(codes);
                    let mut p = ray_plane(o, d, [0.0, 1.0, 0.0], y).unwrap();
                    // Deterministic pseudo-noise.
                    k = k.wrapping_mul(1_103_515_245).wrapping_add(12345);
                    p[0] += noise * ((k >> 8) as f64 / (1u32 << 24) as f64 - 0.5);
                    out.push(GalvoObservation { codes, point: p });
                }
            }
        }
        out
    }

    #[test]
    fn fit_recovers_the_builtin_galvo() {
        let truth = super::super::Calibration::builtin().galvo;
        let (fit, rms) = fit_galvo(&spots(&truth, &[-40.0, 40.0], 0.01), u16::MAX).unwrap();
        assert!(rms < 0.02, "rms {rms}");
        for codes in [[0u16, 0u16], [65535, 100], [32768, 32768], [1000, 60000]] {
            let (_, d0) = truth.ray(codes);
            let (o1, d1) = fit.ray(codes);
            assert!(dist(o1, truth.origin) < 1.0, "{o1:?}");
            let ang = dot(d0, d1).clamp(-1.0, 1.0).acos();
            assert!(ang < 1e-4, "codes {codes:?}: {ang} rad");
        }
    }

    #[test]
    fn one_plane_or_nothing_says_what_is_missing() {
        let truth = super::super::Calibration::builtin().galvo;
        let e = fit_galvo(&spots(&truth, &[0.0], 0.0), 4095)
            .unwrap_err()
            .to_string();
        assert!(e.contains("two different target distances"), "{e}");
        let e = fit_galvo(&[], 4095).unwrap_err().to_string();
        assert!(e.contains("no laser spots"), "{e}");
    }
}
