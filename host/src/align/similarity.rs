//! Similarity transforms `x ↦ s·R·x + t` (uniform scale, rotation, translation): the pose of the
//! user's mesh in the object frame, and the closed-form weighted fit of one to point pairs
//! (Umeyama 1991), the step of the global search's ICP.
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::geometry::V3;

/// `x ↦ scale · rotation · x + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// Uniform scale, > 0.
    pub scale: f64,
    /// Proper rotation.
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
}

impl Similarity {
    /// The rotation in words: its angle and the unit axis it turns about (right-handed, object
    /// frame), e.g. `126.40° about (0.120, -0.985, 0.100)`; the angle alone does not say where the
    /// mesh was turned.
    pub fn rotation_in_words(&self) -> String {
        match axis_angle(&self.rotation) {
            Some((axis, angle)) => format!(
                "{:.2}° about ({:.3}, {:.3}, {:.3})",
                angle.to_degrees(),
                axis[0],
                axis[1],
                axis[2]
            ),
            None => "none (0°)".to_string(),
        }
    }
}

/// The unit axis and angle (radians, in (0, π]) of a proper rotation; `None` for the identity.
/// The axis comes from `R + Rᵀ + (1 − tr R)·I = 2(1 − cos θ)·a·aᵀ`, signed by the skew part:
/// nalgebra's `axis_angle` reads only the skew part, which vanishes at a half turn, and calls a
/// half turn no rotation at all.
pub(crate) fn axis_angle(r: &Matrix3<f64>) -> Option<(Vector3<f64>, f64)> {
    let angle = ((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
    if angle.is_nan() || angle <= 1e-9 {
        return None;
    }
    let b = r + r.transpose() + (1.0 - r.trace()) * Matrix3::identity();
    let col = (0..3).max_by(|&i, &j| b.column(i).norm().total_cmp(&b.column(j).norm()))?;
    let mut axis = b.column(col).normalize();
    let skew = Vector3::new(
        r[(2, 1)] - r[(1, 2)],
        r[(0, 2)] - r[(2, 0)],
        r[(1, 0)] - r[(0, 1)],
    );
    let sign = skew.dot(&axis);
    // A half turn has no sign (and one within 1e-4 rad of it prints as one): its largest
    // component made positive.
    let half = std::f64::consts::PI - angle < 1e-4;
    let largest_negative = axis
        .iter()
        .fold(0.0f64, |m, x| if x.abs() > m.abs() { *x } else { m })
        < 0.0;
    if (half && largest_negative) || (!half && sign < 0.0) {
        axis = -axis;
    }
    axis.iter().all(|x| x.is_finite()).then_some((axis, angle))
}

pub(crate) fn v(p: V3) -> Vector3<f64> {
    Vector3::new(p[0], p[1], p[2])
}

pub(crate) fn a(p: Vector3<f64>) -> V3 {
    [p.x, p.y, p.z]
}

impl Similarity {
    /// The identity.
    pub fn identity() -> Similarity {
        Similarity {
            scale: 1.0,
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// `p` moved.
    pub fn apply(&self, p: V3) -> V3 {
        a(self.scale * self.rotation * v(p) + self.translation)
    }

    /// The direction `d` turned (no scale, no translation): normals.
    pub fn turn(&self, d: V3) -> V3 {
        a(self.rotation * v(d))
    }

    /// The inverse map applied to `p`.
    pub fn invert(&self, p: V3) -> V3 {
        a(self.rotation.transpose() * (v(p) - self.translation) / self.scale)
    }

    /// `self` followed by the small motion `delta = [σ, ω_x, ω_y, ω_z, τ_x, τ_y, τ_z]` about the
    /// point `centre`: `x ↦ e^σ·Rot(ω)·(x − centre) + centre + τ` (the exponential map, so the
    /// scale stays positive and the rotation proper however large the step).
    pub fn moved(&self, delta: &[f64; 7], centre: V3) -> Similarity {
        let grow = delta[0].exp();
        let turn = Rotation3::new(Vector3::new(delta[1], delta[2], delta[3])).into_inner();
        let c = v(centre);
        let tau = Vector3::new(delta[4], delta[5], delta[6]);
        Similarity {
            scale: self.scale * grow,
            rotation: turn * self.rotation,
            translation: grow * turn * (self.translation - c) + c + tau,
        }
    }

    /// Rotation about the turntable axis (`+z` through the origin) by `deg`, after `self`.
    pub fn turned_about_axis(&self, deg: f64) -> Similarity {
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), deg.to_radians()).into_inner();
        Similarity {
            scale: self.scale,
            rotation: r * self.rotation,
            translation: r * self.translation,
        }
    }

    /// `self` followed by `g` (`x ↦ g(self(x))`).
    pub fn then(&self, g: &Similarity) -> Similarity {
        Similarity {
            scale: g.scale * self.scale,
            rotation: g.rotation * self.rotation,
            translation: g.scale * g.rotation * self.translation + g.translation,
        }
    }

    /// Are every number finite and the scale positive?
    pub fn is_finite(&self) -> bool {
        self.scale.is_finite()
            && self.scale > 0.0
            && self.rotation.iter().all(|x| x.is_finite())
            && self.translation.iter().all(|x| x.is_finite())
    }

    /// The weighted least-squares similarity taking `from[i]` to `to[i]` (Umeyama 1991, with the
    /// reflection guard): minimises `Σ w_i |s·R·from_i + t − to_i|²`. `None` when the weighted
    /// points are degenerate (fewer than three effective points, all on a line, or all weights
    /// zero). Hand-written as a few lines on nalgebra's SVD: no crate of the field offers the
    /// weighted similarity fit.
    pub fn fit(from: &[V3], to: &[V3], w: &[f64]) -> Option<Similarity> {
        Similarity::fit_with_scale(from, to, w, None)
    }

    /// [`Similarity::fit`] with the scale held at `scale` when one is given (`subsurf align
    /// --scale`): the rotation of the weighted fit does not depend on the scale, and the
    /// translation then follows from the centroids.
    pub fn fit_with_scale(
        from: &[V3],
        to: &[V3],
        w: &[f64],
        scale: Option<f64>,
    ) -> Option<Similarity> {
        let total: f64 = w.iter().sum();
        if total.is_nan() || total <= 0.0 || from.len() < 3 {
            return None;
        }
        let mean = |p: &[V3]| {
            p.iter()
                .zip(w)
                .fold(Vector3::zeros(), |acc, (x, wi)| acc + *wi * v(*x))
                / total
        };
        let (mf, mt) = (mean(from), mean(to));
        let mut cov = Matrix3::zeros();
        let mut var = 0.0;
        for ((f, t), wi) in from.iter().zip(to).zip(w) {
            let (df, dt) = (v(*f) - mf, v(*t) - mt);
            cov += *wi * dt * df.transpose();
            var += *wi * df.norm_squared();
        }
        cov /= total;
        var /= total;
        if var.is_nan() || var <= 0.0 {
            return None;
        }
        let svd = cov.svd(true, true);
        let (u, vt) = (svd.u?, svd.v_t?);
        let mut d = Matrix3::identity();
        if (u * vt).determinant() < 0.0 {
            d[(2, 2)] = -1.0;
        }
        let sv = svd.singular_values;
        // Rank below 2: the points lie on a line (or a point) and fix no rotation about it.
        if sv[1].is_nan() || sv[1] <= 1e-12 * sv[0] {
            return None;
        }
        let rotation = u * d * vt;
        let scale =
            scale.unwrap_or((sv[0] * d[(0, 0)] + sv[1] * d[(1, 1)] + sv[2] * d[(2, 2)]) / var);
        let out = Similarity {
            scale,
            rotation,
            translation: mt - scale * rotation * mf,
        };
        out.is_finite().then_some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose() -> Similarity {
        Similarity {
            scale: 1000.0,
            rotation: Rotation3::from_euler_angles(0.3, -1.1, 2.0).into_inner(),
            translation: Vector3::new(12.0, -30.0, 45.0),
        }
    }

    /// The words name the axis and angle a rotation was built from; the identity is none.
    #[test]
    fn a_rotation_in_words_names_its_axis() {
        let axis = nalgebra::Unit::new_normalize(Vector3::new(0.0, 0.6, 0.8));
        let t = Similarity {
            rotation: Rotation3::from_axis_angle(&axis, 0.5).into_inner(),
            ..pose()
        };
        assert_eq!(t.rotation_in_words(), "28.65° about (0.000, 0.600, 0.800)");
        let id = Similarity {
            rotation: nalgebra::Matrix3::identity(),
            ..pose()
        };
        assert_eq!(id.rotation_in_words(), "none (0°)");
        // A half turn is a rotation too (nalgebra's axis_angle calls it none).
        let half = Similarity {
            rotation: Rotation3::from_axis_angle(&axis, std::f64::consts::PI).into_inner(),
            ..pose()
        };
        assert_eq!(
            half.rotation_in_words(),
            "180.00° about (0.000, 0.600, 0.800)"
        );
    }

    #[test]
    fn the_fit_recovers_a_similarity_from_exact_pairs() {
        let t = pose();
        let from: Vec<V3> = (0..9)
            .map(|k| {
                let k = k as f64;
                [0.01 * k.sin(), 0.02 * (1.3 * k).cos(), 0.005 * k]
            })
            .collect();
        let to: Vec<V3> = from.iter().map(|p| t.apply(*p)).collect();
        let got = Similarity::fit(&from, &to, &[1.0; 9]).unwrap();
        assert!((got.scale - t.scale).abs() < 1e-6 * t.scale, "{got:?}");
        assert!((got.rotation - t.rotation).norm() < 1e-9);
        assert!((got.translation - t.translation).norm() < 1e-6);
        for p in &from {
            let back = got.invert(got.apply(*p));
            assert!((v(back) - v(*p)).norm() < 1e-12);
        }
        // Collinear points fix no rotation about their line.
        let held = Similarity::fit_with_scale(&from, &to, &[1.0; 9], Some(990.0)).unwrap();
        assert_eq!(held.scale, 990.0);
        assert!((held.rotation - t.rotation).norm() < 1e-9);
        let line: Vec<V3> = (0..5).map(|k| [k as f64, 0.0, 0.0]).collect();
        assert!(Similarity::fit(&line, &line, &[1.0; 5]).is_none());
    }

    #[test]
    fn small_motions_compose_about_their_centre() {
        let t = pose();
        let c = [1.0, 2.0, 3.0];
        let m = t.moved(&[0.0; 7], c);
        assert!((m.rotation - t.rotation).norm() < 1e-15 && m.scale == t.scale);
        // A pure rotation about the centre keeps the centre's image fixed.
        let p = t.invert(c);
        let r = t.moved(&[0.0, 0.1, -0.2, 0.3, 0.0, 0.0, 0.0], c);
        assert!((v(r.apply(p)) - v(c)).norm() < 1e-9);
        let q = t.turned_about_axis(90.0).apply(p);
        assert!((q[0] + c[1]).abs() < 1e-9 && (q[1] - c[0]).abs() < 1e-9);
    }
}
