//! The fall-off `R_d(x_i → x_o)` of every source vertex, prepared for fast evaluation.
//!
//! Each term `c_kl e^{d_kl r}` is stored as `(ln c_kl, d_kl)` and evaluated as `e^{ln c + d r}`, so
//! a huge `c` with a tiny exponential neither overflows nor underflows before the product is formed.

use super::model::uniform_params;
use crate::baseline::{Baseline, channel_terms, local_weight};
use crate::model::{FrameRule, Support, TangentFrame, hat_weights};
use crate::modelfile::{ColourMode, ModelFile, VertexStatus};

/// Per-vertex fall-off parameters (Eq. 1/3/5/9) in a layout made for inner loops.
#[derive(Clone, Debug)]
pub struct Falloffs {
    n: usize,
    m: usize,
    shared: bool,
    /// Per vertex: `blocks × m × n` values of `ln c` (1 block when shared, 3 per channel).
    lnc: Vec<f64>,
    /// Same layout: `d` (1/mm, negative).
    d: Vec<f64>,
    /// Channel scales `(1, s_g, s_b)` (Eq. 5/9); `(1, 1, 1)` per channel.
    scale: Vec<[f64; 3]>,
    /// False for vertices without a model: they emit nothing.
    active: Vec<bool>,
    /// Per vertex: where its model is claimed ([`crate::model::support`]; below r_min R_d
    /// continues exponentially from its value and slope there).
    support: Vec<Support>,
    /// The model's homogeneous baseline: beyond a source's r_max its fall-off moves towards it
    /// (the rule of evaluation, [`crate::baseline::with_fallback`]).
    baseline: Option<Baseline>,
    /// The baseline's terms `(c, d)` per channel ([`crate::baseline::channel_terms`]).
    base_terms: Option<[Vec<(f64, f64)>; 3]>,
    /// Per vertex: ln B(r_min) per channel, the baseline at the vertex's r_min (empty without a
    /// baseline), so that a fall-off below r_min costs one baseline evaluation, not two.
    base_at_r_min: Vec<[f64; 3]>,
    /// The rule of the tangent frame the segments are defined in (the model file's).
    frame_rule: FrameRule,
}

impl Falloffs {
    /// Prepares the fall-offs of a (validated, [`super::validate`]) model.
    pub fn new(model: &ModelFile) -> Self {
        let colour = model.shape.colour;
        let uniform = uniform_params(model);
        let (n, m) = (uniform.terms, uniform.segments);
        let shared = colour == ColourMode::Shared;
        let blocks = if shared { 1 } else { 3 };
        let nv = model.len();
        let mut lnc = Vec::with_capacity(nv * blocks * n * m);
        let mut d = Vec::with_capacity(nv * blocks * n * m);
        let mut scale = Vec::with_capacity(nv);
        let mut active = Vec::with_capacity(nv);
        for v in 0..nv {
            let p = uniform.vertex(v, colour);
            let on = model.vertices[v].status != VertexStatus::NoModel;
            let terms = if shared {
                scale.push([1.0, p[0], p[1]]);
                &p[2..]
            } else {
                scale.push([1.0; 3]);
                p
            };
            for cd in terms.chunks_exact(2) {
                if on {
                    lnc.push(cd[0].ln());
                    d.push(cd[1]);
                } else {
                    lnc.push(f64::NEG_INFINITY);
                    d.push(-1.0);
                }
            }
            active.push(on);
        }
        let support: Vec<Support> = model.vertices.iter().map(|v| v.support()).collect();
        let baseline = model.baseline.as_ref().and_then(|b| b.baseline(colour));
        let base_terms = baseline.as_ref().map(channel_terms);
        let base_at_r_min = match &base_terms {
            Some(t) => support.iter().map(|s| Self::ln_base(t, s.r_min)).collect(),
            None => Vec::new(),
        };
        Self {
            n,
            m,
            shared,
            lnc,
            d,
            scale,
            active,
            support,
            baseline,
            base_terms,
            base_at_r_min,
            frame_rule: model.frame,
        }
    }

    /// The tangent frame (Eq. 3) of the source with unit normal `normal` (the vertex normal: x_i's
    /// own normal when x_i is the vertex), by the model's rule; a degenerate normal falls back to
    /// the frame of +z rather than failing the render.
    pub fn frame_at(&self, normal: [f64; 3]) -> TangentFrame {
        TangentFrame::with_rule(self.frame_rule, normal).unwrap_or(TangentFrame::OF_PLUS_Z)
    }

    /// ln of the baseline per channel at `r` (log-sum-exp: finite where every term underflows).
    #[inline]
    fn ln_base(terms: &[Vec<(f64, f64)>; 3], r: f64) -> [f64; 3] {
        [0, 1, 2].map(|c| {
            let mx = terms[c]
                .iter()
                .map(|&(k, d)| k.ln() + d * r)
                .fold(f64::NEG_INFINITY, f64::max);
            if mx == f64::NEG_INFINITY {
                return mx;
            }
            mx + terms[c]
                .iter()
                .map(|&(k, d)| (k.ln() + d * r - mx).exp())
                .sum::<f64>()
                .ln()
        })
    }

    /// Below a source's r_min: the baseline's rise from r_min to `r` per channel,
    /// ln B(r) − ln B(r_min) (the rule of [`crate::baseline::ln_predict`]), or `None` without a
    /// baseline (then the support rule's slope extension applies).
    #[inline]
    fn base_rise(&self, i: usize, r: f64) -> Option<[f64; 3]> {
        let t = self.base_terms.as_ref()?;
        let (a, b) = (Self::ln_base(t, r), self.base_at_r_min[i]);
        Some([0, 1, 2].map(|c| {
            let x = a[c] - b[c];
            if x.is_finite() { x.max(0.0) } else { 0.0 }
        }))
    }

    /// Blends a source's prediction `ln_local` at `r` towards the baseline beyond its r_max, in
    /// log space ([`crate::baseline::with_fallback`]; the weight is 1 inside its range).
    #[inline]
    fn fall_back(&self, i: usize, r: f64, ln_local: [f64; 3]) -> [f64; 3] {
        let support = self.support[i];
        match &self.baseline {
            Some(b) if support.is_known() && r > support.r_max => {
                let w = local_weight(support, r);
                let base = b.model.ln_eval(r, None);
                [0, 1, 2].map(|c| {
                    if ln_local[c] == f64::NEG_INFINITY {
                        ln_local[c]
                    } else {
                        w * ln_local[c] + (1.0 - w) * base[c]
                    }
                })
            }
            _ => ln_local,
        }
    }

    /// Direction segments m (Eq. 3).
    pub fn segments(&self) -> usize {
        self.m
    }

    /// Whether vertex `i` has a model and so can act as a source.
    pub fn is_active(&self, i: usize) -> bool {
        self.active[i]
    }

    fn stride(&self) -> usize {
        self.n * self.m * if self.shared { 1 } else { 3 }
    }

    /// Σ_k c_kl e^{d_kl r} of one block (one channel, or the shared fall-off), one segment, and
    /// its derivative in r.
    #[inline]
    fn segment_sum(&self, base: usize, r: f64) -> (f64, f64) {
        let (mut s, mut ds) = (0.0, 0.0);
        for k in base..base + self.n {
            let e = (self.lnc[k] + self.d[k] * r).exp();
            s += e;
            ds += self.d[k] * e;
        }
        (s, ds)
    }

    /// `R_d(x_i → x_o)` per channel at distance `r` (mm), blended over direction segments with the
    /// weights `w_l(x_i, x_o)` of Eq. 3 (`w` has one entry per segment; ignored when `m = 1`).
    /// Below the source's `r_min` the fall-off continues as the model's support rule says
    /// ([`crate::model::support`]).
    #[inline]
    pub fn eval(&self, i: usize, r: f64, w: &[f64]) -> [f64; 3] {
        let support = self.support[i];
        let a = support.anchor(r);
        if a == r {
            let f = self.eval_model(i, r, w).map(|(f, _)| f);
            if self.baseline.is_some() && support.is_known() && r > support.r_max {
                return self
                    .fall_back(
                        i,
                        r,
                        f.map(|f| if f > 0.0 { f.ln() } else { f64::NEG_INFINITY }),
                    )
                    .map(f64::exp);
            }
            return f;
        }
        let at = self.eval_model(i, a, w);
        if let Some(rise) = self.base_rise(i, r) {
            return [0, 1, 2].map(|c| at[c].0 * rise[c].exp());
        }
        at.map(|(f, df)| {
            if f > 0.0 {
                support.extend(r, f.ln(), df / f).exp()
            } else {
                f
            }
        })
    }

    /// The model itself (no support range) and its derivative in r, per channel.
    #[inline]
    fn eval_model(&self, i: usize, r: f64, w: &[f64]) -> [(f64, f64); 3] {
        let base = i * self.stride();
        let block = self.n * self.m;
        let one = |b: usize| -> (f64, f64) {
            if self.m == 1 {
                self.segment_sum(b, r)
            } else {
                let (mut s, mut ds) = (0.0, 0.0);
                for (l, &wl) in w.iter().enumerate().take(self.m) {
                    if wl != 0.0 {
                        let (a, da) = self.segment_sum(b + l * self.n, r);
                        s += wl * a;
                        ds += wl * da;
                    }
                }
                (s, ds)
            }
        };
        if self.shared {
            let (f, df) = one(base);
            let s = self.scale[i];
            [(f, df), (f * s[1], df * s[1]), (f * s[2], df * s[2])]
        } else {
            [one(base), one(base + block), one(base + 2 * block)]
        }
    }

    /// `ln` of the direction-averaged fall-off `(1/m) Σ_l R_l(r)` per channel, as a log-sum-exp so
    /// that it stays finite where every exponential underflows. Used to build cluster tables.
    /// Below the source's `r_min` it continues linearly in `ln` with its slope there (as
    /// [`Falloffs::eval`]).
    pub fn ln_eval_mean(&self, i: usize, r: f64) -> [f64; 3] {
        let support = self.support[i];
        let a = support.anchor(r);
        if a == r {
            return self.fall_back(i, r, self.ln_eval_mean_model(i, r).map(|(l, _)| l));
        }
        let at = self.ln_eval_mean_model(i, a);
        if let Some(rise) = self.base_rise(i, r) {
            return [0, 1, 2].map(|c| at[c].0 + rise[c]);
        }
        at.map(|(l, g)| support.extend(r, l, g))
    }

    /// The log-sum-exp of [`Falloffs::ln_eval_mean`] without the support range, and its
    /// derivative in r (0 where every term is zero).
    fn ln_eval_mean_model(&self, i: usize, r: f64) -> [(f64, f64); 3] {
        let base = i * self.stride();
        let block = self.n * self.m;
        let lse = |b: usize| -> (f64, f64) {
            let mut mx = f64::NEG_INFINITY;
            for k in b..b + block {
                mx = mx.max(self.lnc[k] + self.d[k] * r);
            }
            if mx == f64::NEG_INFINITY {
                return (mx, 0.0);
            }
            let (mut s, mut ds) = (0.0, 0.0);
            for k in b..b + block {
                let e = (self.lnc[k] + self.d[k] * r - mx).exp();
                s += e;
                ds += self.d[k] * e;
            }
            (mx + s.ln() - (self.m as f64).ln(), ds / s)
        };
        if self.shared {
            let (f, g) = lse(base);
            let s = self.scale[i];
            [(f, g), (f + s[1].ln(), g), (f + s[2].ln(), g)]
        } else {
            [lse(base), lse(base + block), lse(base + 2 * block)]
        }
    }

    /// `∫_0^ρ R_d(r) 2πr dr` per channel, averaged over segments: the light a source keeps within
    /// the disk of radius `ρ` around itself. Used for the `x_o = x_i` term, where the point sum would
    /// put all of a vertex's own area at distance 0 and overestimate sharp fall-offs.
    pub fn disk_integral(&self, i: usize, rho: f64) -> [f64; 3] {
        let support = self.support[i];
        if !support.is_known() {
            return self.disk_integral_model(i, rho);
        }
        let lo = support.r_min;
        // Below r_min the fall-off is one exponential through the model's value and slope at
        // r_min (the support rule, see `eval`), averaged over segments like the model part.
        let w = vec![1.0 / self.m as f64; self.m];
        let at = self.eval_model(i, lo, &w);
        let base_at = self.base_at_r_min.get(i).copied();
        let inner = |r: f64| -> [f64; 3] {
            if let (Some(t), Some(b_lo)) = (&self.base_terms, base_at) {
                // The baseline's shape through the model's value at r_min
                // ([`crate::baseline::ln_predict`]): Σ_k s·c_k e^{d_k r}, s = R(r_min) / B(r_min).
                return [0, 1, 2].map(|c| {
                    let s = (at[c].0.max(0.0).ln() - b_lo[c]).exp();
                    if !s.is_finite() {
                        return 0.0;
                    }
                    t[c].iter().map(|&(k, d)| exp_disk(s * k, d, r)).sum()
                });
            }
            at.map(|(f, df)| {
                if f > 0.0 {
                    let (ln_c, g) = support.below(f.ln(), df / f);
                    exp_disk(ln_c.exp(), g, r)
                } else {
                    0.0
                }
            })
        };
        if rho <= lo {
            return inner(rho);
        }
        let (a, b, c) = (
            inner(lo),
            self.disk_integral_model(i, rho),
            self.disk_integral_model(i, lo),
        );
        [0, 1, 2].map(|k| a[k] + b[k] - c[k])
    }

    fn disk_integral_model(&self, i: usize, rho: f64) -> [f64; 3] {
        let base = i * self.stride();
        let block = self.n * self.m;
        let one = |b: usize| -> f64 {
            let mut s = 0.0;
            for k in b..b + block {
                s += exp_disk(self.lnc[k].exp(), self.d[k], rho);
            }
            s / self.m as f64
        };
        if self.shared {
            let f = one(base);
            let s = self.scale[i];
            [f, f * s[1], f * s[2]]
        } else {
            [one(base), one(base + block), one(base + 2 * block)]
        }
    }

    /// The distance beyond which vertex `i` sends less than the fraction `tol` of its light, the
    /// largest over channels and segments (see [`tail_cutoff`]). `tol <= 0` gives infinity.
    pub fn cutoff(&self, i: usize, tol: f64) -> f64 {
        if !self.active[i] {
            return 0.0;
        }
        let base = i * self.stride();
        let blocks = if self.shared { 1 } else { 3 };
        let mut terms = Vec::with_capacity(self.n);
        let mut r: f64 = 0.0;
        for b in 0..blocks * self.m {
            terms.clear();
            for k in base + b * self.n..base + (b + 1) * self.n {
                terms.push((self.lnc[k].exp(), self.d[k]));
            }
            r = r.max(tail_cutoff(&terms, tol));
        }
        // Beyond r_max the fall-off moves towards the baseline, whose tail may reach further.
        if let Some(b) = &self.baseline
            && self.support[i].is_known()
        {
            let falloffs: Vec<&crate::model::Anisotropic> = match &b.model {
                crate::model::ColourModel::Shared { falloff, .. } => vec![falloff],
                crate::model::ColourModel::PerChannel { channels } => channels.iter().collect(),
            };
            for seg in falloffs.iter().flat_map(|a| &a.segments) {
                let terms: Vec<(f64, f64)> = seg.terms.iter().map(|t| (t.c, t.d)).collect();
                r = r.max(tail_cutoff(&terms, tol));
            }
        }
        r
    }
}

/// The radius `R` beyond which a fall-off `Σ c_k e^{d_k r}` (Eq. 1) keeps at most the fraction
/// `tol` of its total diffuse reflectance `∫_0^∞ R_d(r) 2πr dr`. Closed form of the tail,
/// `∫_R^∞ c e^{dr} 2πr dr = 2πc e^{dR}(1 − dR)/d²`, which falls monotonically, so bisection is
/// exact to the tolerance. `tol <= 0` gives infinity (no cutoff).
pub fn tail_cutoff(terms: &[(f64, f64)], tol: f64) -> f64 {
    if tol <= 0.0 || terms.is_empty() {
        return f64::INFINITY;
    }
    let total: f64 = terms.iter().map(|&(c, d)| c / (d * d)).sum();
    if total.is_nan() || total <= 0.0 || !total.is_finite() {
        return 0.0;
    }
    let tail = |r: f64| -> f64 {
        terms
            .iter()
            .map(|&(c, d)| c * (d * r).exp() * (1.0 - d * r) / (d * d))
            .sum::<f64>()
            / total
    };
    let slowest = terms.iter().map(|&(_, d)| -d).fold(f64::INFINITY, f64::min);
    let mut hi = 1.0 / slowest;
    let mut guard = 0;
    while tail(hi) > tol && guard < 200 {
        hi *= 2.0;
        guard += 1;
    }
    let mut lo = 0.0;
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if tail(mid) > tol {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

/// Eq. 3's weights `w_l(x_i, x_o)` into `w` (one per segment): the hat functions of
/// [`crate::model::hat_weights`] over the angle of `x_o − x_i` in the [`TangentFrame`] at `x_i`
/// (the rule shared with fitting); a direction with no tangential part gets equal weights.
pub fn segment_weights(frame: &TangentFrame, x_i: [f64; 3], x_o: [f64; 3], w: &mut [f64]) {
    let m = w.len();
    if m == 0 {
        return;
    }
    if m == 1 {
        w[0] = 1.0;
        return;
    }
    w.iter_mut().for_each(|x| *x = 0.0);
    match frame.polar(x_i, x_o).1 {
        Some(phi) => {
            for (l, wl) in hat_weights(phi, m) {
                w[l] += wl;
            }
        }
        None => w.iter_mut().for_each(|x| *x = 1.0 / m as f64),
    }
}

/// `∫_0^ρ c e^{d r} 2π r dr` for `d <= 0` (`π c ρ²` at `d = 0`).
fn exp_disk(c: f64, d: f64, rho: f64) -> f64 {
    if d == 0.0 {
        return std::f64::consts::PI * c * rho * rho;
    }
    let x = d * rho;
    // (e^{dρ}(dρ − 1) + 1)/d², written with exp_m1 for small dρ; for large |dρ| (ρ = ∞ included)
    // the exp_m1 form cancels to NaN or 0, the direct one is exact.
    let g = if x > -1.0 {
        x.exp_m1() * (x - 1.0) + x
    } else if x > -745.0 {
        1.0 + x.exp() * (x - 1.0)
    } else {
        1.0
    };
    2.0 * std::f64::consts::PI * c * g / (d * d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disk_integral_to_infinity_is_the_total_reflectance() {
        let model = ModelFile::homogeneous(
            vec![[0.0; 3]; 3],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [0.5, 2.0],
            &[(2.0, -3.0), (0.2, -0.5)],
        );
        let f = Falloffs::new(&model);
        let total = 2.0 * std::f64::consts::PI * (2.0 / 9.0 + 0.2 / 0.25);
        let got = f.disk_integral(0, 1e3);
        assert!((got[0] / total - 1.0).abs() < 1e-12);
        assert!((got[1] / (0.5 * total) - 1.0).abs() < 1e-12);
        assert!((got[2] / (2.0 * total) - 1.0).abs() < 1e-12);
        let inf = f.disk_integral(0, f64::INFINITY);
        assert!((inf[0] / total - 1.0).abs() < 1e-12, "{inf:?}");
        // Small radius: R(0) π ρ² to first order.
        let rho = 1e-6;
        let small = f.disk_integral(0, rho)[0];
        assert!((small / (2.2 * std::f64::consts::PI * rho * rho) - 1.0).abs() < 1e-5);
    }

    #[test]
    fn log_eval_matches_direct_eval_and_survives_underflow() {
        let model = ModelFile::homogeneous(
            vec![[0.0; 3]; 3],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [0.5, 2.0],
            &[(2.0, -3.0), (0.2, -0.5)],
        );
        let f = Falloffs::new(&model);
        let direct = f.eval(0, 1.7, &[1.0]);
        let ln = f.ln_eval_mean(0, 1.7);
        for ch in 0..3 {
            assert!((ln[ch].exp() / direct[ch] - 1.0).abs() < 1e-12);
        }
        // At 10 m every term underflows in linear space; the log stays finite and exact.
        let far = f.ln_eval_mean(0, 1e4)[0];
        assert!((far - (0.2f64.ln() - 0.5e4)).abs() < 1e-9);
    }

    #[test]
    fn below_r_min_the_fall_off_continues_with_its_slope_there() {
        // A steep term the samples (r >= 1) did not resolve: huge at r -> 0 as a model.
        let mut model = ModelFile::homogeneous(
            vec![[0.0; 3]; 3],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [1.0, 1.0],
            &[(1e6, -20.0), (0.5, -0.5)],
        );
        let free = Falloffs::new(&model);
        assert!(free.eval(0, 0.1, &[1.0])[0] > 1e5);
        for v in &mut model.vertices {
            v.r_range = [1.0, 5.0];
        }
        let f = Falloffs::new(&model);
        // At and beyond r_min: the model.
        for r in [1.0, 2.5] {
            assert_eq!(f.eval(0, r, &[1.0]), free.eval(0, r, &[1.0]));
        }
        // Below: value and slope at r_min, continued exponentially, in both evaluations.
        let (r1, g) = {
            let a = free.eval(0, 1.0, &[1.0])[0];
            let h = 1e-6;
            let b = free.eval(0, 1.0 + h, &[1.0])[0];
            (a, (b.ln() - a.ln()) / h)
        };
        for r in [0.0, 0.3, 0.9] {
            let want = r1 * (g * (r - 1.0)).exp();
            let got = f.eval(0, r, &[1.0])[0];
            assert!((got / want - 1.0).abs() < 1e-5, "r {r}: {got} vs {want}");
            let ln = f.ln_eval_mean(0, r)[0];
            assert!(
                (ln - want.ln()).abs() < 1e-4,
                "r {r}: ln {ln} vs {}",
                want.ln()
            );
        }
        // The self-term disk integral matches a numerical integral of `eval`.
        disk_integral_matches_eval(&f);
    }

    /// `disk_integral` of vertex 0 against a midpoint-rule integral of `eval`, to 1e-6.
    fn disk_integral_matches_eval(f: &Falloffs) {
        for rho in [0.5, 2.0] {
            let steps = 200_000;
            let dr = rho / steps as f64;
            let num: f64 = (0..steps)
                .map(|k| {
                    let r = (k as f64 + 0.5) * dr;
                    f.eval(0, r, &[1.0])[0] * 2.0 * std::f64::consts::PI * r * dr
                })
                .sum();
            let got = f.disk_integral(0, rho)[0];
            assert!((got / num - 1.0).abs() < 1e-6, "rho {rho}: {got} vs {num}");
        }
    }

    #[test]
    fn with_a_baseline_the_fall_off_takes_its_shape_below_r_min_and_its_tail_beyond_r_max() {
        let mut model = ModelFile::homogeneous(
            vec![[0.0; 3]; 3],
            vec![[0.0, 0.0, 1.0]; 3],
            vec![[0, 1, 2]],
            [1.0, 1.0],
            &[(1e6, -20.0), (0.5, -0.5)],
        );
        for v in &mut model.vertices {
            v.r_range = [1.0, 5.0];
        }
        let free = Falloffs::new(&model);
        let stored = crate::modelfile::BaselineParams {
            terms: 2,
            params: vec![1.0, 1.0, 4.0, -6.0, 0.2, -0.2],
            r_range: [0.2, 30.0],
        };
        let base = stored.baseline(ColourMode::Shared).unwrap();
        let b = |r: f64| base.model.ln_eval(r, None)[0];
        model.baseline = Some(stored);
        let f = Falloffs::new(&model);
        // Inside the range: the model, untouched.
        for r in [1.0, 2.5, 5.0] {
            assert_eq!(f.eval(0, r, &[1.0]), free.eval(0, r, &[1.0]));
        }
        // Below r_min: the model's value at r_min times the baseline's rise, in both evaluations.
        let at = free.eval(0, 1.0, &[1.0])[0];
        for r in [0.0, 0.3, 0.9] {
            let want = at.ln() + b(r) - b(1.0);
            let got = f.eval(0, r, &[1.0])[0].ln();
            assert!((got - want).abs() < 1e-9, "r {r}: {got} vs {want}");
            assert!((f.ln_eval_mean(0, r)[0] - want).abs() < 1e-9);
        }
        // Beyond r_max: towards the baseline (log-space blend), all of it far out.
        let far = 5.0 + 40.0 * crate::baseline::FALLBACK_SCALE * 5.0;
        assert!((f.eval(0, far, &[1.0])[0].ln() - b(far)).abs() < 1e-6 * far);
        let mid = 7.0;
        let w = crate::baseline::local_weight(Support::new(1.0, 5.0), mid);
        let want = w * free.eval(0, mid, &[1.0])[0].ln() + (1.0 - w) * b(mid);
        assert!((f.eval(0, mid, &[1.0])[0].ln() - want).abs() < 1e-9);
        assert!((f.ln_eval_mean(0, mid)[0] - want).abs() < 1e-9);
        // The cutoff reaches at least as far as the baseline's tail needs.
        assert!(f.cutoff(0, 1e-3) >= free.cutoff(0, 1e-3));
        // The self-term disk integral matches a numerical integral of `eval`.
        disk_integral_matches_eval(&f);
    }

    #[test]
    fn tail_cutoff_leaves_the_requested_fraction() {
        let terms = [(1.0, -2.0), (0.01, -0.2)];
        let total: f64 = terms.iter().map(|&(c, d)| c / (d * d)).sum();
        for tol in [1e-2, 1e-4, 1e-6] {
            let r = tail_cutoff(&terms, tol);
            let tail: f64 = terms
                .iter()
                .map(|&(c, d)| c * (d * r).exp() * (1.0 - d * r) / (d * d))
                .sum();
            assert!((tail / total / tol - 1.0).abs() < 1e-6, "tol {tol}");
        }
        assert!(tail_cutoff(&terms, 0.0).is_infinite());
    }

    #[test]
    fn segment_weights_are_hats_that_sum_to_one() {
        let mut w = [0.0; 4];
        let frame = TangentFrame::from_normal([0.0, 0.0, 1.0]).unwrap();
        for k in 0..64 {
            let a = k as f64 * 0.1;
            segment_weights(&frame, [0.0; 3], [a.cos(), a.sin(), 0.3], &mut w);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!(w.iter().filter(|&&x| x > 0.0).count() <= 2);
        }
        // Along the frame's tangent: all weight on segment 0; a quarter turn: segment 1.
        segment_weights(&frame, [0.0; 3], frame.t, &mut w);
        assert!((w[0] - 1.0).abs() < 1e-12);
        segment_weights(&frame, [0.0; 3], frame.b, &mut w);
        assert!((w[1] - 1.0).abs() < 1e-12);
        segment_weights(&frame, [0.0; 3], [0.0, 0.0, 1.0], &mut w);
        assert_eq!(w, [0.25; 4]);
    }
}
