//! Fitting the dipole (Jensen et al. 2001) to one channel's samples, for the comparison of
//! Figure 3: sigma_s' and sigma_a with eta fixed, and a free overall scale k (camera samples are
//! relative, not absolute reflectance) unless [`DipoleOptions::absolute`] fixes k = 1.
//!
//! Objective: the log residual ln(k·R_d(r)) − ln s (Eq. 4). Parameters are ln sigma_s',
//! ln sigma_a, ln k. The Jacobian is by central differences: the dipole's two sources make the
//! analytic form long, there are only three parameters, and the reference solver sees the same
//! residuals.

use serde::{Deserialize, Serialize};

use super::bins::bin_samples;
use super::lm::{self, Problem, Settings};
use super::{FitFailure, SampleReport, Solver, clean};
use crate::model::Dipole;

/// Settings of a dipole fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DipoleOptions {
    /// Fixed relative index of refraction eta.
    pub eta: f64,
    /// Samples are absolute R_d (k = 1) instead of relative.
    pub absolute: bool,
    /// Solver implementation.
    pub solver: Solver,
    /// Iteration limit.
    pub max_iterations: usize,
}

impl Default for DipoleOptions {
    fn default() -> Self {
        Self {
            eta: 1.3,
            absolute: false,
            solver: Solver::Specialised,
            max_iterations: 200,
        }
    }
}

/// A fitted dipole.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DipoleFit {
    /// The dipole (eta as given).
    pub dipole: Dipole,
    /// Overall scale k between samples and R_d (1 when absolute).
    pub scale: f64,
    /// Σ (ln(k·R_d) − ln s)².
    pub rss: f64,
    /// log E (Eq. 8, alpha = 1): RMS of ln(k·R_d/s).
    pub log_e: f64,
    /// Solver iterations.
    pub iterations: usize,
    /// Whether the solver met its convergence test.
    pub converged: bool,
    /// Samples used and dropped.
    pub samples: SampleReport,
}

pub(crate) struct DipoleProblem<'a> {
    pub r: &'a [f64],
    pub y: &'a [f64],
    pub w: Option<&'a [f64]>,
    pub eta: f64,
    pub absolute: bool,
}

impl DipoleProblem<'_> {
    fn ln_model(&self, theta: &[f64], r: f64) -> f64 {
        let d = Dipole {
            sigma_s_prime: theta[0].exp(),
            sigma_a: theta[1].exp(),
            eta: self.eta,
        };
        let k = if self.absolute { 0.0 } else { theta[2] };
        k + d.ln_r_d(r)
    }
}

impl Problem for DipoleProblem<'_> {
    fn params(&self) -> usize {
        if self.absolute { 2 } else { 3 }
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let p = self.params();
        let idx = [0, 1, 2];
        let mut vals = [0.0; 3];
        for (i, (&r, &y)) in self.r.iter().zip(self.y).enumerate() {
            let sw = self.w.map_or(1.0, |w| w[i].sqrt());
            let l = self.ln_model(theta, r);
            if !l.is_finite() {
                return false;
            }
            if jac {
                let mut t = [theta[0], theta[1], if p == 3 { theta[2] } else { 0.0 }];
                for j in 0..p {
                    let h = 1e-6 * (1.0 + theta[j].abs());
                    let orig = t[j];
                    t[j] = orig + h;
                    let up = self.ln_model(&t, r);
                    t[j] = orig - h;
                    let down = self.ln_model(&t, r);
                    t[j] = orig;
                    vals[j] = sw * (up - down) / (2.0 * h);
                }
                row(sw * (l - y), &idx[..p], &vals[..p]);
            } else {
                row(sw * (l - y), &[], &[]);
            }
        }
        true
    }
}

/// Fits the dipole to samples s at distances r (one channel).
pub fn fit_dipole(r: &[f64], s: &[f64], options: &DipoleOptions) -> Result<DipoleFit, FitFailure> {
    if Dipole::new(1.0, 0.1, options.eta).is_err() {
        return Err(FitFailure::InvalidOptions {
            reason: "eta must be finite and > 0 with F_dr(eta) < 1",
        });
    }
    let (r, s, samples) = clean(r, s);
    let p: usize = if options.absolute { 2 } else { 3 };
    let needed = super::samples_needed(p.div_ceil(2));
    if r.len() < needed {
        return Err(FitFailure::TooFewSamples {
            usable: r.len(),
            needed,
        });
    }
    let distinct = super::samples::distinct_distances(&r, p);
    if distinct < p {
        return Err(FitFailure::TooFewDistances {
            distinct,
            needed: p,
        });
    }
    let y: Vec<f64> = s.iter().map(|v| v.ln()).collect();
    let scale_r = r.iter().sum::<f64>() / r.len() as f64;
    let scale_r = if scale_r > 0.0 { scale_r } else { 1.0 };
    // Start: a grid over sigma_s' and sigma_a/sigma_s' on binned data, k in closed form.
    let binned = bin_samples(&r, &s, 32);
    let bins = binned.bins.as_slice();
    let br: Vec<f64> = bins.iter().map(|b| b.r * binned.scale_r).collect();
    let by: Vec<f64> = bins.iter().map(|b| b.y + binned.level).collect();
    let bw: Vec<f64> = bins.iter().map(|b| b.n).collect();
    let coarse = DipoleProblem {
        r: &br,
        y: &by,
        w: Some(&bw),
        eta: options.eta,
        absolute: options.absolute,
    };
    let mut best = (f64::INFINITY, vec![0.0; p]);
    for i in 0..11 {
        let ss = 10f64.powf(-2.0 + 0.5 * i as f64) / scale_r;
        for j in 0..13 {
            let sa = ss * 10f64.powf(-5.0 + 0.5 * j as f64);
            let mut theta = vec![ss.ln(), sa.ln(), 0.0];
            theta.truncate(p);
            if !options.absolute {
                // Best k for this shape: weighted mean of ln s − ln R_d.
                let (mut num, mut den) = (0.0, 0.0);
                for b in bins {
                    num += b.n * (b.y - coarse.ln_model(&theta, b.r));
                    den += b.n;
                }
                theta[2] = num / den;
            }
            let mut cost = 0.0;
            let ok = coarse.eval(&theta, false, |res, _, _| cost += res * res);
            if ok && cost < best.0 {
                best = (cost, theta);
            }
        }
    }
    if !best.0.is_finite() {
        return Err(FitFailure::NonFinite);
    }
    let problem = DipoleProblem {
        r: &r,
        y: &y,
        w: None,
        eta: options.eta,
        absolute: options.absolute,
    };
    let settings = Settings {
        max_iterations: options.max_iterations,
        ..Settings::default()
    };
    let out = match options.solver {
        Solver::Specialised => lm::minimize(&problem, &best.1, &settings),
        Solver::Reference => super::reference::minimize(&problem, &best.1, options.max_iterations),
    }
    .ok_or(FitFailure::NonFinite)?;
    let dipole = Dipole {
        sigma_s_prime: out.theta[0].exp(),
        sigma_a: out.theta[1].exp(),
        eta: options.eta,
    };
    let scale = if options.absolute {
        1.0
    } else {
        out.theta[2].exp()
    };
    if !(scale.is_finite() && scale > 0.0) || dipole.validate().is_err() || dipole.sigma_a <= 0.0 {
        return Err(FitFailure::OutOfRange {
            what: "dipole coefficients or scale left the representable range",
        });
    }
    let rss = out.cost;
    let log_e = (rss / r.len() as f64).sqrt();
    if !(rss.is_finite() && log_e.is_finite()) {
        return Err(FitFailure::NonFinite);
    }
    Ok(DipoleFit {
        dipole,
        scale,
        rss,
        log_e,
        iterations: out.iterations,
        converged: out.converged,
        samples,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Material;

    #[test]
    fn recovers_a_preset_dipole() {
        for (name, ch) in [("marble", 1), ("skin1", 0), ("ketchup", 0)] {
            let truth = Material::by_name(name).unwrap().dipole(ch).unwrap();
            let r: Vec<f64> = (0..300).map(|i| 0.05 * i as f64).collect();
            let s: Vec<f64> = r.iter().map(|&v| 3.0 * truth.r_d(v)).collect();
            for solver in [Solver::Specialised, Solver::Reference] {
                let fit = fit_dipole(
                    &r,
                    &s,
                    &DipoleOptions {
                        solver,
                        eta: truth.eta,
                        ..DipoleOptions::default()
                    },
                )
                .unwrap();
                let e1 = (fit.dipole.sigma_s_prime / truth.sigma_s_prime - 1.0).abs();
                let e2 = (fit.dipole.sigma_a / truth.sigma_a - 1.0).abs();
                assert!(e1 < 1e-5 && e2 < 1e-5, "{name} {solver:?}: {fit:?}");
                assert!((fit.scale / 3.0 - 1.0).abs() < 1e-5);
            }
            let fit = fit_dipole(
                &r,
                &s.iter().map(|v| v / 3.0).collect::<Vec<_>>(),
                &DipoleOptions {
                    absolute: true,
                    eta: truth.eta,
                    ..DipoleOptions::default()
                },
            )
            .unwrap();
            assert!((fit.dipole.sigma_a / truth.sigma_a - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn fails_cleanly() {
        let o = DipoleOptions::default();
        assert!(matches!(
            fit_dipole(&[1.0], &[1.0], &o),
            Err(FitFailure::TooFewSamples { .. })
        ));
        assert!(matches!(
            fit_dipole(&[1.0; 10], &[1.0; 10], &o),
            Err(FitFailure::TooFewDistances { .. })
        ));
        let bad_eta = DipoleOptions { eta: f64::NAN, ..o };
        assert!(fit_dipole(&[1.0, 2.0], &[1.0, 1.0], &bad_eta).is_err());
    }
}
