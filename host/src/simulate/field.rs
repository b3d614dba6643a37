//! The ground-truth material: a procedural marble-like field of model parameters.
//!
//! This is deliberately an implementation of Eq. 9 (with an optional direction dependence) that is
//! independent of the `model` module, so that tests of the fitting pipeline do not check the model
//! against itself.
use crate::geometry::{V3, cross, dot, normalize, sub};

/// The material's parameter field over the object's surface.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Field {
    /// Eq. 1: `c_k` of the homogeneous base material (shared colour, red channel).
    pub c: [f64; 3],
    /// Eq. 1: `d_k` (1/mm, negative) of the base material.
    pub d: [f64; 3],
    /// Eq. 9: green and blue scales `s_g`, `s_b` of the base material.
    pub s: [f64; 2],
    /// Strength of the marble veins on the parameters (0 = homogeneous): log-amplitude.
    pub heterogeneity: f64,
    /// Strength of direction dependence in `[0, 1)`: light travels `1 / (1 - a)` times further
    /// along the veins than across them. 0 = isotropic (exactly Eq. 9).
    pub anisotropy: f64,
    /// Log-amplitude of the modulation texture alpha(x_o) (Eq. 2); 0 = alpha is 1. ln alpha is
    /// this times the vein value − 0.5 (× 0.8 green, × 1.2 blue), so it spans the amplitude.
    pub alpha_amplitude: f64,
    /// Vein wavelength, mm: the period of the one vein pattern, which drives alpha (by
    /// `alpha_amplitude`), the parameters (by `heterogeneity`) and the anisotropy's strength
    /// (by `anisotropy`). Below about two mesh edge lengths alpha varies finer than the mesh.
    pub vein_wavelength: f64,
    /// Seed of the vein pattern.
    pub seed: u64,
}

impl Default for Field {
    fn default() -> Field {
        Field {
            c: [2.0, 0.3, 0.03],
            d: [-4.0, -1.2, -0.35],
            s: [0.8, 0.55],
            heterogeneity: 0.4,
            anisotropy: 0.3,
            alpha_amplitude: 0.2,
            vein_wavelength: 25.0,
            seed: 1,
        }
    }
}

/// The true model at one light position `x_i`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueParams {
    /// `c_k`, sorted by `d_k` ascending (steepest first is last: see `d`).
    pub c: [f64; 3],
    /// `d_k < 0`.
    pub d: [f64; 3],
    /// `(1, s_g, s_b)`.
    pub scale: [f64; 3],
    /// Unit vein direction in the tangent plane of `x_i` (anisotropy axis).
    pub axis: V3,
    /// Anisotropy strength.
    pub anisotropy: f64,
}

impl TrueParams {
    /// Parameters in the model file's shared-colour order `[s_g, s_b, c_1, d_1, …]`, terms in the
    /// `model` module's canonical order (slowest fall-off first, as `docs/model-format.md` asks).
    pub fn model_params(&self) -> Vec<f64> {
        let mut idx = [0usize, 1, 2];
        idx.sort_by(|&a, &b| self.d[b].total_cmp(&self.d[a]));
        let mut p = vec![self.scale[1], self.scale[2]];
        for k in idx {
            p.push(self.c[k]);
            p.push(self.d[k]);
        }
        p
    }

    /// `log R_d(x_i → x_o)` per channel (Eq. 9 without alpha), evaluated as a log-sum-exp so
    /// that far points underflow to a finite, very negative log instead of `-inf`.
    pub fn log_rd(&self, x_i: V3, x_o: V3, normal_i: V3) -> [f64; 3] {
        let v = sub(x_o, x_i);
        let r = dot(v, v).sqrt();
        let mut r_eff = r;
        if self.anisotropy > 0.0 && r > 0.0 {
            let t = sub(v, normal_i.map(|n| n * dot(v, normal_i)));
            let tl = dot(t, t).sqrt();
            if tl > 0.0 {
                let cphi = dot(t, self.axis) / tl;
                r_eff = r * (1.0 - self.anisotropy * cphi * cphi);
            }
        }
        let terms = [0, 1, 2].map(|k| self.c[k].ln() + self.d[k] * r_eff);
        let m = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let lse = m + terms.iter().map(|t| (t - m).exp()).sum::<f64>().ln();
        self.scale.map(|s| lse + s.ln())
    }
}

fn hash01(seed: u64, k: u64) -> f64 {
    // SplitMix64: a fixed, portable pseudo-random phase per (seed, k).
    let mut z = seed
        .wrapping_add(k.wrapping_mul(0x9E37_79B9_7F4A_7C15))
        .wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// The largest |alpha amplitude| a simulation takes: alpha stays within e^±6 (channel 3 has
/// 1.2 times the amplitude over a vein value in ±0.5), far inside f32 and the sensor's range.
pub const MAX_ALPHA_AMPLITUDE: f64 = 10.0;

impl Field {
    /// Checks what the pattern needs: a finite positive vein wavelength, a finite alpha
    /// amplitude of at most [`MAX_ALPHA_AMPLITUDE`], finite heterogeneity and anisotropy (clamped to
    /// [0, 0.95] where used).
    pub fn check(&self) -> Result<(), super::SimError> {
        let bad = |what: String| Err(super::SimError::Invalid(what));
        if !(self.vein_wavelength.is_finite() && self.vein_wavelength > 0.0) {
            return bad(format!(
                "vein wavelength {} mm is not positive",
                self.vein_wavelength
            ));
        }
        if !(self.alpha_amplitude.is_finite() && self.alpha_amplitude.abs() <= MAX_ALPHA_AMPLITUDE)
        {
            return bad(format!(
                "alpha amplitude {} outside ±{MAX_ALPHA_AMPLITUDE}",
                self.alpha_amplitude
            ));
        }
        if !self.heterogeneity.is_finite() {
            return bad(format!("heterogeneity {}", self.heterogeneity));
        }
        if !self.anisotropy.is_finite() {
            return bad(format!("anisotropy {}", self.anisotropy));
        }
        Ok(())
    }

    /// Marble pattern in `[0, 1]`: a sine along a seeded direction, warped by a few octaves.
    pub fn vein(&self, p: V3) -> f64 {
        use std::f64::consts::TAU;
        let h = |k| hash01(self.seed, k);
        let dir =
            normalize([h(1) - 0.5, h(2) - 0.5, 0.3 * (h(3) - 0.5)]).unwrap_or([1.0, 0.0, 0.0]);
        let f = TAU / self.vein_wavelength.max(1e-6);
        let mut warp = 0.0;
        for o in 0..3u64 {
            let w = normalize([
                h(10 + 4 * o) - 0.5,
                h(11 + 4 * o) - 0.5,
                h(12 + 4 * o) - 0.5,
            ])
            .unwrap_or([0.0, 1.0, 0.0]);
            let fo = f * (1.7f64).powi(o as i32 + 1);
            warp += (fo * dot(p, w) + TAU * h(13 + 4 * o)).sin() / (o + 1) as f64;
        }
        0.5 + 0.5 * (f * dot(p, dir) + 1.2 * warp).sin()
    }

    /// The true parameters at light position `x_i` with surface normal `n`.
    pub fn params_at(&self, x_i: V3, n: V3) -> TrueParams {
        let v = self.vein(x_i) - 0.5;
        let h = self.heterogeneity;
        let c = [
            self.c[0] * (h * v).exp(),
            self.c[1] * (-0.6 * h * v).exp(),
            self.c[2] * (0.8 * h * v).exp(),
        ];
        let d = [
            self.d[0] * (0.5 * h * v).exp(),
            self.d[1] * (-0.4 * h * v).exp(),
            self.d[2] * (0.3 * h * v).exp(),
        ];
        let scale = [
            1.0,
            self.s[0] * (0.5 * h * v).exp(),
            self.s[1] * (-0.5 * h * v).exp(),
        ];
        // Vein axis: the gradient-free direction of the pattern projected into the tangent plane.
        let a = [
            hash01(self.seed, 2) - 0.5,
            -(hash01(self.seed, 1) - 0.5),
            0.0,
        ];
        let t = sub(a, n.map(|x| x * dot(a, n)));
        let axis = normalize(t)
            .or_else(|| normalize(cross(n, [1.0, 0.0, 0.0])))
            .unwrap_or([1.0, 0.0, 0.0]);
        TrueParams {
            c,
            d,
            scale,
            axis,
            anisotropy: self.anisotropy.clamp(0.0, 0.95) * (0.5 + v),
        }
    }

    /// An upper bound of the steepest fall-off `|d_k|` (1/mm, Eq. 1) anywhere on any surface:
    /// `1 / steepest_falloff()` is the material's shortest mean free path, the length a scan must
    /// resolve (vertex spacing, pixel footprint). Exact bound of [`Field::params_at`]: the vein
    /// value `v - 0.5` lies in `[-0.5, 0.5]`.
    pub fn steepest_falloff(&self) -> f64 {
        let h = 0.5 * self.heterogeneity.abs();
        [0.5, 0.4, 0.3]
            .iter()
            .zip(self.d)
            .map(|(k, d)| d.abs() * (k * h).exp())
            .fold(0.0, f64::max)
    }

    /// An upper bound of the radiance `alpha(x_o) · R_d(x_i → x_o)` any channel reaches (at
    /// `x_o → x_i`, Eq. 9): what an exposure must keep below the sensor's clipping level.
    pub fn peak_radiance(&self) -> f64 {
        let h = 0.5 * self.heterogeneity.abs();
        let c: f64 = [1.0, 0.6, 0.8]
            .iter()
            .zip(self.c)
            .map(|(k, c)| c * (k * h).exp())
            .sum();
        let scale = self
            .s
            .iter()
            .fold(1.0f64, |m, s| m.max(s * (0.5 * h).exp()));
        let alpha = (1.2 * 0.5 * self.alpha_amplitude.abs()).exp();
        c * scale * alpha
    }

    /// Eq. 2/6: the true modulation texture alpha(x_o), per channel.
    pub fn alpha_at(&self, x_o: V3) -> [f64; 3] {
        let v = self.vein(x_o) - 0.5;
        let a = self.alpha_amplitude;
        [(a * v).exp(), (0.8 * a * v).exp(), (1.2 * a * v).exp()]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_rd_is_a_finite_log_sum_exp() {
        let f = Field {
            anisotropy: 0.0,
            ..Field::default()
        };
        let p = f.params_at([1.0, 2.0, 0.0], [0.0, 0.0, 1.0]);
        let x = [1.0, 2.0, 0.0];
        for r in [0.0, 0.5, 3.0, 1e4] {
            let l = p.log_rd(x, [1.0 + r, 2.0, 0.0], [0.0, 0.0, 1.0]);
            assert!(l.iter().all(|v| v.is_finite()));
            if r < 10.0 {
                let direct: f64 = (0..3).map(|k| p.c[k] * (p.d[k] * r).exp()).sum();
                assert!((l[0] - direct.ln()).abs() < 1e-12);
                assert!((l[1] - (direct * p.scale[1]).ln()).abs() < 1e-12);
            }
        }
        let mp = p.model_params();
        assert!(mp[3] > mp[5] && mp[5] > mp[7]);
    }

    #[test]
    fn falloff_and_peak_bounds_hold_everywhere() {
        let f = Field::default();
        let (dmax, peak) = (f.steepest_falloff(), f.peak_radiance());
        let mut seen = (0.0f64, 0.0f64);
        for k in 0..2000 {
            let t = k as f64 * 0.37;
            let p = [10.0 * t.sin(), 7.0 * (1.3 * t).cos(), 0.05 * t];
            let n = normalize([t.cos(), t.sin(), 0.5]).unwrap();
            let tp = f.params_at(p, n);
            seen.0 = seen.0.max(tp.d.iter().fold(0.0, |m, d| m.max(d.abs())));
            let a = f.alpha_at(p);
            let c: f64 = tp.c.iter().sum();
            for (a, s) in a.iter().zip(tp.scale) {
                seen.1 = seen.1.max(a * c * s);
            }
        }
        assert!(seen.0 <= dmax && seen.0 > 0.95 * dmax, "{seen:?} {dmax}");
        assert!(seen.1 <= peak && seen.1 > 0.5 * peak, "{seen:?} {peak}");
    }

    #[test]
    fn anisotropy_makes_the_fall_off_direction_dependent() {
        let f = Field {
            anisotropy: 0.5,
            heterogeneity: 0.0,
            ..Field::default()
        };
        let n = [0.0, 0.0, 1.0];
        let p = f.params_at([0.0; 3], n);
        let along = p.log_rd([0.0; 3], p.axis.map(|a| 2.0 * a), n)[0];
        let across = p.log_rd([0.0; 3], cross(n, p.axis).map(|a| 2.0 * a), n)[0];
        assert!(p.anisotropy > 0.1);
        assert!(along > across + 0.05, "{along} {across}");
    }
}
