//! The dipole diffusion approximation of Jensen, Marschner, Levoy and Hanrahan 2001 ("A Practical
//! Model for Subsurface Light Transport"), which the paper compares against (Figures 3 and 5), and
//! the measured materials published with it.

use serde::{Deserialize, Serialize};

use super::{ModelError, log_sum_exp};

/// The dipole R_d(r) for one channel of a homogeneous medium. Coefficients are per length unit
/// (the table in [`MATERIALS`] is in mm⁻¹, so r is then in mm).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Dipole {
    /// Reduced scattering coefficient sigma_s' > 0.
    pub sigma_s_prime: f64,
    /// Absorption coefficient sigma_a ≥ 0.
    pub sigma_a: f64,
    /// Relative index of refraction eta > 0.
    pub eta: f64,
}

/// Diffuse Fresnel reflectance F_dr(eta), the polynomial fit used by Jensen et al. 2001:
/// F_dr = −1.440/eta² + 0.710/eta + 0.668 + 0.0636·eta.
pub fn f_dr(eta: f64) -> f64 {
    -1.440 / (eta * eta) + 0.710 / eta + 0.668 + 0.0636 * eta
}

/// Internal reflection parameter A = (1 + F_dr) / (1 − F_dr).
pub fn a_of_eta(eta: f64) -> f64 {
    let f = f_dr(eta);
    (1.0 + f) / (1.0 - f)
}

impl Dipole {
    /// Validates: sigma_s' > 0, sigma_a ≥ 0, eta > 0 with F_dr < 1, all finite.
    pub fn new(sigma_s_prime: f64, sigma_a: f64, eta: f64) -> Result<Self, ModelError> {
        let d = Self {
            sigma_s_prime,
            sigma_a,
            eta,
        };
        d.validate()?;
        Ok(d)
    }

    /// Checks the parameter ranges of [`Dipole::new`].
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |what, value| Err(ModelError::DipoleParameter { what, value });
        if !(self.sigma_s_prime.is_finite() && self.sigma_s_prime > 0.0) {
            return bad("sigma_s_prime", self.sigma_s_prime);
        }
        if !(self.sigma_a.is_finite() && self.sigma_a >= 0.0) {
            return bad("sigma_a", self.sigma_a);
        }
        let f = f_dr(self.eta);
        if !(self.eta.is_finite() && self.eta > 0.0 && f < 1.0 && f.is_finite()) {
            return bad("eta", self.eta);
        }
        Ok(())
    }

    /// Reduced extinction sigma_t' = sigma_s' + sigma_a.
    pub fn sigma_t_prime(&self) -> f64 {
        self.sigma_s_prime + self.sigma_a
    }

    /// Reduced albedo alpha' = sigma_s' / sigma_t'.
    pub fn albedo(&self) -> f64 {
        self.sigma_s_prime / self.sigma_t_prime()
    }

    /// Effective transport coefficient sigma_tr = sqrt(3·sigma_a·sigma_t').
    pub fn sigma_tr(&self) -> f64 {
        (3.0 * self.sigma_a * self.sigma_t_prime()).sqrt()
    }

    /// Depths of the real and virtual source: z_r = 1/sigma_t', z_v = z_r·(1 + 4A/3).
    pub fn depths(&self) -> (f64, f64) {
        let z_r = 1.0 / self.sigma_t_prime();
        (z_r, z_r * (1.0 + 4.0 * a_of_eta(self.eta) / 3.0))
    }

    /// ln R_d(r): the dipole's two sources as a log-sum-exp, finite far beyond where R_d underflows.
    /// R_d(r) = alpha'/(4π) Σ_{z ∈ {z_r, z_v}} z·(sigma_tr·d + 1)·exp(−sigma_tr·d)/d³,
    /// d = sqrt(r² + z²).
    pub fn ln_r_d(&self, r: f64) -> f64 {
        let s = self.sigma_tr();
        let (z_r, z_v) = self.depths();
        let term = |z: f64| {
            let d = r.hypot(z);
            z.ln() + (s * d).ln_1p() - s * d - 3.0 * d.ln()
        };
        (self.albedo() / (4.0 * std::f64::consts::PI)).ln()
            + log_sum_exp([term(z_r), term(z_v)].into_iter())
    }

    /// R_d(r) of the dipole.
    pub fn r_d(&self, r: f64) -> f64 {
        self.ln_r_d(r).exp()
    }

    /// Closed-form total diffuse reflectance ∫_0^∞ R_d(r)·2πr dr =
    /// (alpha'/2)·(1 + exp(−(4/3)·A·sqrt(3(1 − alpha'))))·exp(−sqrt(3(1 − alpha'))).
    pub fn total_reflectance(&self) -> f64 {
        let a = self.albedo();
        let k = (3.0 * (1.0 - a)).max(0.0).sqrt();
        0.5 * a * (1.0 + (-4.0 / 3.0 * a_of_eta(self.eta) * k).exp()) * (-k).exp()
    }
}

/// A measured material from Jensen et al. 2001, Figure 5 (coefficients in mm⁻¹, channels r, g, b).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Material {
    /// Lower-case preset name, e.g. `"marble"`, `"skin1"`, `"skimmilk"`.
    pub name: &'static str,
    /// sigma_s' per channel, mm⁻¹.
    pub sigma_s_prime: [f64; 3],
    /// sigma_a per channel, mm⁻¹.
    pub sigma_a: [f64; 3],
    /// Relative index of refraction.
    pub eta: f64,
    /// The diffuse reflectance the paper lists (two digits), for reference. The closed form
    /// [`Dipole::total_reflectance`] reproduces it to ±0.03 (chicken1 blue deviates most, 0.026).
    pub published_reflectance: [f64; 3],
}

impl Material {
    /// The dipole of one channel (0 = r, 1 = g, 2 = b); `None` for a channel above 2.
    pub fn dipole(&self, channel: usize) -> Option<Dipole> {
        Some(Dipole {
            sigma_s_prime: *self.sigma_s_prime.get(channel)?,
            sigma_a: *self.sigma_a.get(channel)?,
            eta: self.eta,
        })
    }

    /// Looks a preset up by name (case-insensitive; `-`, `_` and spaces ignored, so
    /// `"Skim milk"` finds `skimmilk`).
    pub fn by_name(name: &str) -> Option<&'static Material> {
        let key: String = name
            .chars()
            .filter(|c| !matches!(c, '-' | '_' | ' '))
            .flat_map(char::to_lowercase)
            .collect();
        MATERIALS.iter().find(|m| m.name == key)
    }
}

macro_rules! material {
    ($name:literal, $s:expr, $a:expr, $eta:expr, $rd:expr) => {
        Material {
            name: $name,
            sigma_s_prime: $s,
            sigma_a: $a,
            eta: $eta,
            published_reflectance: $rd,
        }
    };
}

/// The measured table of Jensen et al. 2001 (Figure 5): sigma_s', sigma_a in mm⁻¹, eta, and the
/// diffuse reflectance they report.
pub const MATERIALS: &[Material] = &[
    material!(
        "apple",
        [2.29, 2.39, 1.97],
        [0.0030, 0.0034, 0.046],
        1.3,
        [0.85, 0.84, 0.53]
    ),
    material!(
        "chicken1",
        [0.15, 0.21, 0.38],
        [0.015, 0.077, 0.19],
        1.3,
        [0.31, 0.15, 0.10]
    ),
    material!(
        "chicken2",
        [0.19, 0.25, 0.32],
        [0.018, 0.088, 0.20],
        1.3,
        [0.32, 0.16, 0.10]
    ),
    material!(
        "cream",
        [7.38, 5.47, 3.15],
        [0.0002, 0.0028, 0.0163],
        1.3,
        [0.98, 0.90, 0.73]
    ),
    material!(
        "ketchup",
        [0.18, 0.07, 0.03],
        [0.061, 0.97, 1.45],
        1.3,
        [0.16, 0.01, 0.00]
    ),
    material!(
        "marble",
        [2.19, 2.62, 3.00],
        [0.0021, 0.0041, 0.0071],
        1.5,
        [0.83, 0.79, 0.75]
    ),
    material!(
        "potato",
        [0.68, 0.70, 0.55],
        [0.0024, 0.0090, 0.12],
        1.3,
        [0.77, 0.62, 0.21]
    ),
    material!(
        "skimmilk",
        [0.70, 1.22, 1.90],
        [0.0014, 0.0025, 0.0142],
        1.3,
        [0.81, 0.81, 0.69]
    ),
    material!(
        "skin1",
        [0.74, 0.88, 1.01],
        [0.032, 0.17, 0.48],
        1.3,
        [0.44, 0.22, 0.13]
    ),
    material!(
        "skin2",
        [1.09, 1.59, 1.79],
        [0.013, 0.070, 0.145],
        1.3,
        [0.63, 0.44, 0.34]
    ),
    material!(
        "spectralon",
        [11.6, 20.4, 14.9],
        [0.00, 0.00, 0.00],
        1.3,
        [1.00, 1.00, 1.00]
    ),
    material!(
        "wholemilk",
        [2.55, 3.21, 3.77],
        [0.0011, 0.0024, 0.014],
        1.3,
        [0.91, 0.88, 0.76]
    ),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_valid_and_match_published_reflectance() {
        // A transcription check: a typo in sigma_s' or sigma_a moves the closed form off the
        // published two-digit reflectance.
        assert_eq!(MATERIALS.len(), 12);
        for m in MATERIALS {
            for ch in 0..3 {
                let d = m.dipole(ch).unwrap();
                d.validate().unwrap();
                let rd = d.total_reflectance();
                assert!(
                    (rd - m.published_reflectance[ch]).abs() < 0.03,
                    "{} channel {ch}: {rd} vs {}",
                    m.name,
                    m.published_reflectance[ch]
                );
            }
        }
        assert_eq!(Material::by_name("Skim milk").unwrap().name, "skimmilk");
        assert!(Material::by_name("unobtainium").is_none());
    }

    /// ∫_0^∞ R_d(r)·2πr dr by the trapezoid rule in u = ln r: the integrand R_d(e^u)·2π·e^{2u} is
    /// analytic in a strip of half-width π/2 and decays exponentially both ways, so the rule
    /// converges geometrically (error ~ exp(−π²/h)).
    fn integrate(d: &Dipole) -> f64 {
        let (z_r, _) = d.depths();
        let centre = z_r.ln();
        let h = 0.05;
        let k = (60.0 / h) as i64;
        (-k..=k)
            .map(|i| {
                let u = centre + i as f64 * h;
                (d.ln_r_d(u.exp()) + 2.0 * u).exp() * 2.0 * std::f64::consts::PI * h
            })
            .sum()
    }

    #[test]
    fn numerical_integral_matches_closed_form_total_reflectance() {
        for m in MATERIALS {
            for ch in 0..3 {
                let d = m.dipole(ch).unwrap();
                let (numeric, closed) = (integrate(&d), d.total_reflectance());
                let rel = (numeric - closed).abs() / closed;
                assert!(
                    rel < 1e-8,
                    "{} channel {ch}: {numeric} vs {closed} ({rel:e})",
                    m.name
                );
            }
        }
    }

    #[test]
    fn ln_r_d_is_finite_where_r_d_underflows() {
        let d = Material::by_name("ketchup").unwrap().dipole(2).unwrap();
        assert_eq!(d.r_d(1e4), 0.0);
        assert!(d.ln_r_d(1e4).is_finite());
        assert!((d.ln_r_d(1.0) - d.r_d(1.0).ln()).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_parameters() {
        assert!(Dipole::new(0.0, 0.1, 1.3).is_err());
        assert!(Dipole::new(1.0, -0.1, 1.3).is_err());
        assert!(Dipole::new(1.0, 0.1, f64::NAN).is_err());
        assert!(Dipole::new(1.0, 0.0, 1.3).is_ok());
    }
}
