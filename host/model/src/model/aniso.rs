//! Eq. 3: the anisotropic model, m direction segments around x_i blended by hat functions, and the
//! tangent frame at x_i that defines the directions.

use serde::{Deserialize, Serialize};

use super::{ExpSum, ModelError, ln_exact_at_one, log_sum_exp, log_sum_exp_of};

/// Which rule builds the [`TangentFrame`] from a normal. A model file records the rule its
/// segments were fitted in (`docs/model-format.md`), so a reader evaluates every file in the frame
/// it was fitted in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FrameRule {
    /// The minimal rotation taking world +z to n (Rodrigues' rotation about z × n) applied to +x
    /// and +y. Continuous in n everywhere except at n = −z, the face that rests on the platter;
    /// so neighbouring vertices get nearly the same frame, and nothing jumps on the lit surface.
    /// The rule of every fit since model format 4.
    #[default]
    MinimalRotation,
    /// The rule of model formats 1–3, kept to read their files exactly: reference world +X, or
    /// world +Y when |n_x| > 0.9, projected into the tangent plane. It jumps along |n_x| = 0.9,
    /// a seam across the lit surface of curved objects.
    ReferenceAxis,
}

impl FrameRule {
    /// The rule every fit uses now ([`TangentFrame::from_normal`]); model files record it.
    pub const CURRENT: FrameRule = FrameRule::MinimalRotation;

    /// The rule's name as the model file header writes it (`comment frame <name>`).
    pub fn name(self) -> &'static str {
        match self {
            FrameRule::MinimalRotation => "minimal-rotation",
            FrameRule::ReferenceAxis => "reference-axis",
        }
    }

    /// The rule named `name` ([`FrameRule::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        [FrameRule::MinimalRotation, FrameRule::ReferenceAxis]
            .into_iter()
            .find(|r| r.name() == name)
    }
}

/// An orthonormal frame (t, b, n) at a surface point; directions around x_i are angles
/// φ = atan2(v·b, v·t) of the tangent-plane projection v of x_o − x_i.
///
/// The one definition of Eq. 3's directions for fitting, evaluation, interpolation and rendering:
/// [`TangentFrame::from_normal`] (the current rule, [`FrameRule::MinimalRotation`]: t and b are
/// +x and +y rotated by the smallest rotation taking +z to n), or [`TangentFrame::with_rule`] for a
/// file fitted under an older rule. b = n × t always.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TangentFrame {
    /// Tangent, direction φ = 0.
    pub t: [f64; 3],
    /// Bitangent n × t, direction φ = π/2.
    pub b: [f64; 3],
    /// Unit normal.
    pub n: [f64; 3],
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalized(a: [f64; 3]) -> Option<[f64; 3]> {
    // Scale first so that tiny and huge vectors normalise without under/overflow.
    let m = a[0].abs().max(a[1].abs()).max(a[2].abs());
    if !(a.iter().all(|x| x.is_finite()) && m > 0.0) {
        return None;
    }
    let s = [a[0] / m, a[1] / m, a[2] / m];
    let l = dot(s, s).sqrt();
    Some([s[0] / l, s[1] / l, s[2] / l])
}

impl TangentFrame {
    /// The frame at n = +z, the same under every rule (t = +x, b = +y): where a caller needs some
    /// frame for a degenerate normal.
    pub const OF_PLUS_Z: TangentFrame = TangentFrame {
        t: [1.0, 0.0, 0.0],
        b: [0.0, 1.0, 0.0],
        n: [0.0, 0.0, 1.0],
    };

    /// The frame at a point with normal `normal` (any non-zero finite length) by the current rule,
    /// [`FrameRule::MinimalRotation`]: the one every fit uses.
    pub fn from_normal(normal: [f64; 3]) -> Result<Self, ModelError> {
        Self::with_rule(FrameRule::CURRENT, normal)
    }

    /// The frame at a point with normal `normal` by `rule` (for models fitted under it).
    pub fn with_rule(rule: FrameRule, normal: [f64; 3]) -> Result<Self, ModelError> {
        let n = normalized(normal).ok_or(ModelError::BadNormal)?;
        let t = match rule {
            FrameRule::MinimalRotation => minimal_rotation_tangent(n),
            FrameRule::ReferenceAxis => {
                let reference = if n[0].abs() > 0.9 {
                    [0.0, 1.0, 0.0]
                } else {
                    [1.0, 0.0, 0.0]
                };
                let k = dot(reference, n);
                normalized([
                    reference[0] - k * n[0],
                    reference[1] - k * n[1],
                    reference[2] - k * n[2],
                ])
                .ok_or(ModelError::BadNormal)?
            }
        };
        let b = cross(n, t);
        Ok(Self { t, b, n })
    }

    /// The angle (radians, in (−π, π]) by which `other`'s tangent is turned about this frame's
    /// normal from this frame's tangent, after projecting it into this tangent plane: how far
    /// `other`'s segment l points from this frame's segment l. Near 0 for neighbouring points
    /// under a continuous rule; `None` when `other.t` is parallel to this normal.
    pub fn twist(&self, other: &TangentFrame) -> Option<f64> {
        let (u, w) = (dot(other.t, self.t), dot(other.t, self.b));
        (u.hypot(w) > 1e-9).then(|| w.atan2(u))
    }

    /// Distance r = |x_o − x_i| and direction φ ∈ [0, 2π) of x_o around x_i in this frame; φ is
    /// `None` when x_o − x_i has no tangential component (x_o = x_i or straight along n).
    pub fn polar(&self, x_i: [f64; 3], x_o: [f64; 3]) -> (f64, Option<f64>) {
        let v = [x_o[0] - x_i[0], x_o[1] - x_i[1], x_o[2] - x_i[2]];
        let r = v[0].hypot(v[1]).hypot(v[2]);
        (r, self.direction_of(v))
    }

    /// φ of [`TangentFrame::polar`] alone, without the distance (two `hypot`s): for callers
    /// that know r already (the sample store holds it), once per sample of every fit round.
    pub fn direction(&self, x_i: [f64; 3], x_o: [f64; 3]) -> Option<f64> {
        self.direction_of([x_o[0] - x_i[0], x_o[1] - x_i[1], x_o[2] - x_i[2]])
    }

    fn direction_of(&self, v: [f64; 3]) -> Option<f64> {
        let (u, w) = (dot(v, self.t), dot(v, self.b));
        if u == 0.0 && w == 0.0 || !(u.is_finite() && w.is_finite()) {
            return None;
        }
        let mut phi = w.atan2(u);
        if phi < 0.0 {
            phi += std::f64::consts::TAU;
        }
        if phi >= std::f64::consts::TAU {
            phi = 0.0;
        }
        Some(phi)
    }
}

/// t = R·x̂ for the rotation R about z × n that takes +z to the unit normal n = (a, b, c)
/// (Rodrigues): t = (1 − a²/(1 + c), −ab/(1 + c), −a). 1 + c is formed as (a² + b²)/(1 − c) for
/// c < 0, so t stays accurate up to the singular point n = −z; there (a = b = 0) the limit depends
/// on the direction of approach, and the rotation by π about +y is taken (t = −x, b = +y).
fn minimal_rotation_tangent(n: [f64; 3]) -> [f64; 3] {
    let [a, b, c] = n;
    let side = a * a + b * b;
    let one_plus_c = if c >= 0.0 { 1.0 + c } else { side / (1.0 - c) };
    if one_plus_c <= 0.0 || side == 0.0 && c < 0.0 {
        return [-1.0, 0.0, 0.0];
    }
    let k = 1.0 / one_plus_c;
    let t = [1.0 - a * a * k, -a * b * k, -a];
    normalized(t).unwrap_or([-1.0, 0.0, 0.0])
}

/// Eq. 3 hat-function weights w_l(φ) for m segments centred at φ_l = 2π·l/m: linear interpolation
/// between the two neighbouring centres, so Σ_l w_l = 1 and w_l(φ_l) = 1. Returns
/// `[(l0, w0), (l1, w1)]`; for m = 1 the single segment gets weight 1 (twice 0.5 on index 0). A
/// missing or non-finite direction (x_o = x_i) gives equal weights, see [`Anisotropic::eval`].
pub fn hat_weights(phi: f64, m: usize) -> [(usize, f64); 2] {
    if m <= 1 {
        return [(0, 0.5), (0, 0.5)];
    }
    let u = phi.rem_euclid(std::f64::consts::TAU) * m as f64 / std::f64::consts::TAU;
    let f = u.floor();
    let l0 = (f as usize) % m;
    let t = (u - f).clamp(0.0, 1.0);
    [(l0, 1.0 - t), ((l0 + 1) % m, t)]
}

/// Eq. 3: R_d(x_i → x_o) = Σ_l w_l(x_i, x_o) Σ_k c_kl·exp(d_kl·r), m = `segments.len()`
/// segments, segment l centred at φ_l = 2π·l/m in the [`TangentFrame`] at x_i. One segment is the
/// isotropic model of Eq. 1.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Anisotropic {
    /// Fall-off per direction segment l = 0..m.
    pub segments: Vec<ExpSum>,
}

impl Anisotropic {
    /// The isotropic model (m = 1).
    pub fn isotropic(falloff: ExpSum) -> Self {
        Self {
            segments: vec![falloff],
        }
    }

    /// Checks every segment (Eq. 1 constraints) and m ≥ 1.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.segments.is_empty() {
            return Err(ModelError::NoSegments);
        }
        self.segments.iter().try_for_each(ExpSum::validate)
    }

    /// Number of segments m.
    pub fn m(&self) -> usize {
        self.segments.len()
    }

    /// R_d at distance r and direction φ (Eq. 3). `phi = None` (x_o = x_i, no direction) blends all
    /// segments equally.
    pub fn eval(&self, r: f64, phi: Option<f64>) -> f64 {
        self.ln_eval(r, phi).exp()
    }

    /// ln R_d (Eq. 3) as a log-sum-exp over segments and terms, finite where exp underflows.
    pub fn ln_eval(&self, r: f64, phi: Option<f64>) -> f64 {
        self.ln_eval_by(phi, |l| self.segments[l].ln_eval(r))
    }

    /// [`Anisotropic::ln_eval`] with segment l's ln R_d(r) given by `segment(l)`: the one blend
    /// of the segments (Eq. 3's hat weights), shared with [`super::LnEvaluator`], which
    /// evaluates the segments with their ln c_k taken once.
    pub(crate) fn ln_eval_by(&self, phi: Option<f64>, segment: impl Fn(usize) -> f64) -> f64 {
        let m = self.segments.len();
        if m == 0 {
            return f64::NEG_INFINITY;
        }
        match phi.filter(|p| p.is_finite()) {
            Some(phi) if m > 1 => {
                let [(l0, w0), (l1, w1)] = hat_weights(phi, m);
                let a = ln_exact_at_one(w0) + segment(l0);
                let b = ln_exact_at_one(w1) + segment(l1);
                log_sum_exp_of(&[a, b])
            }
            // One segment: its own ln R_d through the same log-sum-exp (weight 1, ln 1 = 0).
            _ if m == 1 => log_sum_exp_of(&[-ln_exact_at_one(1.0) + segment(0)]),
            _ => {
                let lw = -ln_exact_at_one(m as f64);
                log_sum_exp((0..m).map(|l| lw + segment(l)))
            }
        }
    }

    /// R_d(x_i → x_o) for surface points, using the frame at x_i.
    pub fn eval_points(&self, frame: &TangentFrame, x_i: [f64; 3], x_o: [f64; 3]) -> f64 {
        let (r, phi) = frame.polar(x_i, x_o);
        self.eval(r, phi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Term;

    #[test]
    fn frame_is_orthonormal_and_deterministic() {
        for n in [
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [0.3, -0.2, 5.0],
            [-1e-200, 1e-200, 0.0],
        ] {
            let f = TangentFrame::from_normal(n).unwrap();
            assert!((dot(f.t, f.t) - 1.0).abs() < 1e-14);
            assert!((dot(f.b, f.b) - 1.0).abs() < 1e-14);
            assert!(dot(f.t, f.n).abs() < 1e-14 && dot(f.b, f.n).abs() < 1e-14);
            assert_eq!(f, TangentFrame::from_normal(n).unwrap());
        }
        let f = TangentFrame::from_normal([0.0, 0.0, 2.0]).unwrap();
        assert_eq!(f, TangentFrame::OF_PLUS_Z);
        assert_eq!(
            TangentFrame::with_rule(FrameRule::ReferenceAxis, [0.0, 0.0, 2.0]).unwrap(),
            TangentFrame::OF_PLUS_Z
        );
        assert!(TangentFrame::from_normal([0.0, 0.0, 0.0]).is_err());
        assert!(TangentFrame::from_normal([f64::NAN, 0.0, 1.0]).is_err());
    }

    /// A unit vector from two uniform numbers (uniform on the sphere).
    fn unit(u: f64, v: f64) -> [f64; 3] {
        let z = 2.0 * u - 1.0;
        let s = (1.0 - z * z).max(0.0).sqrt();
        let a = std::f64::consts::TAU * v;
        [s * a.cos(), s * a.sin(), z]
    }

    fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
        (a[0] - b[0]).hypot(a[1] - b[1]).hypot(a[2] - b[2])
    }

    /// The largest |Δt| + |Δb| over a few small steps from `n` (step length `eps`).
    fn largest_step(rule: FrameRule, n: [f64; 3], eps: f64) -> f64 {
        let f = TangentFrame::with_rule(rule, n).unwrap();
        let mut worst = 0.0f64;
        for d in [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [-0.6, 0.8, 0.0],
            [0.0, -0.6, -0.8],
        ] {
            let g = TangentFrame::with_rule(rule, [0, 1, 2].map(|k| n[k] + eps * d[k])).unwrap();
            worst = worst.max(dist(f.t, g.t) + dist(f.b, g.b));
        }
        worst
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 2000, ..Default::default() })]

        /// The frame is continuous: a change ε of the normal turns t and b by at most
        /// 4ε/|n + z| (each), everywhere but at the one singular point n = −z, where |n + z|,
        /// the chord to it, goes to 0 (near it the frame turns with twice the azimuth).
        #[test]
        fn the_frame_is_continuous_away_from_minus_z(u in 0.0f64..1.0, v in 0.0f64..1.0) {
            let n = unit(u, v);
            let chord = dist(n, [0.0, 0.0, -1.0]);
            proptest::prop_assume!(chord > 1e-3);
            let f = TangentFrame::from_normal(n).unwrap();
            proptest::prop_assert!((dot(f.t, f.t) - 1.0).abs() < 1e-12);
            proptest::prop_assert!(dot(f.t, f.n).abs() < 1e-12 && dot(f.b, f.n).abs() < 1e-12);
            proptest::prop_assert!(dist(f.b, cross(f.n, f.t)) < 1e-15);
            let eps = 1e-7;
            let step = largest_step(FrameRule::MinimalRotation, n, eps);
            proptest::prop_assert!(step <= 2.0 * 4.0 * eps / chord, "n {:?}: step {}", n, step);
        }
    }

    /// The same check finds the seam of the rule of model formats 1–3 (so the property test can
    /// fail), and the new rule has none there.
    #[test]
    fn the_old_rule_jumps_at_its_seam_and_the_new_one_does_not() {
        let n = [0.9, 0.3, 0.0f64.max((1.0f64 - 0.81 - 0.09).sqrt())];
        let eps = 1e-7;
        assert!(largest_step(FrameRule::ReferenceAxis, n, eps) > 0.5);
        assert!(largest_step(FrameRule::MinimalRotation, n, eps) < 1e-5);
        // The two rules agree where both have +z: on a slab's top face nothing changes.
        assert_eq!(
            TangentFrame::with_rule(FrameRule::ReferenceAxis, [0.0, 0.0, 1.0]).unwrap(),
            TangentFrame::from_normal([0.0, 0.0, 1.0]).unwrap()
        );
        // At the singular point itself the frame is defined (the rotation by π about +y).
        let f = TangentFrame::from_normal([0.0, 0.0, -1.0]).unwrap();
        assert_eq!((f.t, f.b), ([-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]));
        for r in [FrameRule::MinimalRotation, FrameRule::ReferenceAxis] {
            assert_eq!(FrameRule::from_name(r.name()), Some(r));
        }
    }

    #[test]
    fn twist_measures_the_turn_between_frames() {
        let f = TangentFrame::from_normal([0.0, 0.0, 1.0]).unwrap();
        let g = TangentFrame::from_normal([0.01, 0.0, 1.0]).unwrap();
        assert!(f.twist(&g).unwrap().abs() < 1e-4);
        let old = TangentFrame::with_rule(FrameRule::ReferenceAxis, [0.91, 0.3, 0.28]).unwrap();
        let old2 = TangentFrame::with_rule(FrameRule::ReferenceAxis, [0.89, 0.3, 0.34]).unwrap();
        assert!(old.twist(&old2).unwrap().abs() > 0.5);
    }

    #[test]
    fn polar_angles() {
        let f = TangentFrame::from_normal([0.0, 0.0, 1.0]).unwrap();
        let (r, phi) = f.polar([1.0, 1.0, 0.0], [1.0, 3.0, 0.0]);
        assert_eq!(r, 2.0);
        assert!((phi.unwrap() - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        assert_eq!(f.polar([0.0; 3], [0.0; 3]).1, None);
    }

    #[test]
    fn hat_weights_interpolate_and_sum_to_one() {
        let m = 8;
        let step = std::f64::consts::TAU / m as f64;
        let w = hat_weights(3.0 * step, m);
        assert_eq!(w[0], (3, 1.0));
        let w = hat_weights(7.5 * step, m);
        assert_eq!((w[0].0, w[1].0), (7, 0));
        assert!((w[0].1 - 0.5).abs() < 1e-12 && (w[1].1 - 0.5).abs() < 1e-12);
        for i in 0..100 {
            let w = hat_weights(i as f64 * 0.1 - 3.0, m);
            assert!((w[0].1 + w[1].1 - 1.0).abs() < 1e-15);
        }
    }

    #[test]
    fn eval_blends_neighbours() {
        let seg = |c| ExpSum::new(vec![Term { c, d: -1.0 }]).unwrap();
        let a = Anisotropic {
            segments: vec![seg(1.0), seg(2.0), seg(3.0), seg(4.0)],
        };
        let step = std::f64::consts::FRAC_PI_2;
        assert!((a.eval(0.0, Some(0.5 * step)) - 1.5).abs() < 1e-14);
        assert!((a.eval(0.0, Some(3.5 * step)) - 2.5).abs() < 1e-14);
        assert!((a.eval(0.0, None) - 2.5).abs() < 1e-14);
        assert!(a.ln_eval(1e5, Some(1.0)).is_finite());
    }
}
