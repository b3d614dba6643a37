//! Fitting the dipole (Jensen et al. 2001) to one channel's samples, for the comparison of
//! Figure 3: sigma_s' and sigma_a with eta fixed, and a free overall scale k (camera samples are
//! relative, not absolute reflectance) unless [`DipoleOptions::absolute`] fixes k = 1.
//!
//! Objective: the log residual ln(k·R_d(r)) − ln s (Eq. 4). Parameters are ln sigma_s' and
//! ln sigma_a; ln k is eliminated in closed form (see [`DipoleProblem`]). The Jacobian is
//! analytic (checked against finite differences in the tests), and the reference solver sees the
//! same residuals. Start values: a grid over the albedo and the length scale, then a pre-fit on
//! binned samples from the best few grid rows (see [`grid_starts`]).

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
    /// The solver stalled at a non-stationary point (reported, not counted as converged).
    pub stalled: bool,
    /// Samples used and dropped.
    pub samples: SampleReport,
}

/// The dipole's log residuals ln(k·R_d(r_j)) − ln s_j over θ = (ln sigma_s', ln sigma_a), with
/// optional weights.
///
/// The scale is eliminated exactly (variable projection for an additive constant): for given
/// sigma_s', sigma_a the best ln k is the weighted mean of ln s − ln R_d, so the residuals are the
/// weighted-centred ln R_d − ln s and their Jacobian the centred columns of ∂ln R_d. The solver
/// then searches two shape parameters only, and no valley along k exists for it to follow.
/// With `absolute`, k = 1 and nothing is centred.
pub(crate) struct DipoleProblem<'a> {
    pub r: &'a [f64],
    pub y: &'a [f64],
    pub w: Option<&'a [f64]>,
    pub eta: f64,
    pub absolute: bool,
}

/// ln R_d and its gradient for one parameter point, with the per-θ constants computed once
/// (Jensen et al. 2001, Eq. 4–5 of that paper; names as in [`Dipole::ln_r_d`]).
struct DipoleEval {
    sigma_tr: f64,
    z: [f64; 2],
    ln_prefactor: f64,
    /// ∂/∂(ln sigma_s', ln sigma_a) of ln sigma_t', ln sigma_tr and ln alpha'.
    g: [f64; 2],
    h: [f64; 2],
    e: [f64; 2],
}

impl DipoleEval {
    fn new(theta: &[f64], eta: f64) -> Option<Self> {
        let (s, a) = (theta[0].exp(), theta[1].exp());
        let t = s + a;
        let alpha = s / t;
        let sigma_tr = (3.0 * a * t).sqrt();
        let z_r = 1.0 / t;
        let z_v = z_r * (1.0 + 4.0 * crate::model::dipole::a_of_eta(eta) / 3.0);
        let q = a / t;
        let out = Self {
            sigma_tr,
            z: [z_r, z_v],
            ln_prefactor: (alpha / (4.0 * std::f64::consts::PI)).ln(),
            g: [alpha, q],
            h: [0.5 * alpha, 0.5 * (1.0 + q)],
            e: [q, -q],
        };
        (out.ln_prefactor.is_finite() && sigma_tr.is_finite() && z_v.is_finite() && z_r > 0.0)
            .then_some(out)
    }

    /// ln R_d(r) and ∂ln R_d/∂(ln sigma_s', ln sigma_a). With t = sigma_t', u = sigma_tr·d and
    /// T_z = z(1 + u)e^{−u}/d³ (z ∝ 1/t): ∂ln z = −∂ln t, ∂ln d = (z/d)²·∂ln z and
    /// ∂ln T_z = ∂ln z − u²/(1 + u)·(∂ln sigma_tr + ∂ln d) − 3·∂ln d; the two sources combine
    /// with their log-sum-exp weights, and ln alpha' adds its own derivative.
    #[inline]
    #[allow(clippy::needless_range_loop)] // index loops over parallel arrays
    fn eval(&self, r: f64) -> (f64, [f64; 2]) {
        let mut lt = [0.0; 2];
        let mut dl = [[0.0; 2]; 2];
        for (i, &z) in self.z.iter().enumerate() {
            let d2 = r * r + z * z;
            let d = d2.sqrt();
            let u = self.sigma_tr * d;
            lt[i] = z.ln() + u.ln_1p() - u - 1.5 * d2.ln();
            let f = u * u / (1.0 + u);
            let zd = z * z / d2;
            for p in 0..2 {
                let dln_d = -zd * self.g[p];
                dl[i][p] = -self.g[p] - f * (self.h[p] + dln_d) - 3.0 * dln_d;
            }
        }
        let m = lt[0].max(lt[1]);
        let (a, b) = ((lt[0] - m).exp(), (lt[1] - m).exp());
        let sum = a + b;
        let (wr, wv) = (a / sum, b / sum);
        let l = self.ln_prefactor + m + sum.ln();
        (
            l,
            [
                self.e[0] + wr * dl[0][0] + wv * dl[1][0],
                self.e[1] + wr * dl[0][1] + wv * dl[1][1],
            ],
        )
    }
}

impl DipoleProblem<'_> {
    /// Residuals (weighted, centred unless absolute), their Jacobian rows and the fitted ln k;
    /// `None` if anything is non-finite.
    fn residuals(&self, theta: &[f64]) -> Option<(Vec<f64>, Vec<[f64; 2]>, f64)> {
        let ev = DipoleEval::new(theta, self.eta)?;
        let m = self.r.len().min(self.y.len());
        let mut res = Vec::with_capacity(m);
        let mut jac = Vec::with_capacity(m);
        let (mut sw, mut mr, mut mj) = (0.0, 0.0, [0.0; 2]);
        for j in 0..m {
            let (l, g) = ev.eval(self.r[j]);
            let w = self.w.map_or(1.0, |w| w[j]);
            let rj = l - self.y[j];
            sw += w;
            mr += w * rj;
            mj[0] += w * g[0];
            mj[1] += w * g[1];
            res.push(rj);
            jac.push(g);
        }
        let ln_k = if self.absolute || sw <= 0.0 {
            0.0
        } else {
            let k = -mr / sw;
            for (rj, g) in res.iter_mut().zip(jac.iter_mut()) {
                *rj += k;
                g[0] -= mj[0] / sw;
                g[1] -= mj[1] / sw;
            }
            k
        };
        if let Some(w) = self.w {
            for ((rj, g), w) in res.iter_mut().zip(jac.iter_mut()).zip(w) {
                let s = w.sqrt();
                *rj *= s;
                g[0] *= s;
                g[1] *= s;
            }
        }
        (ln_k.is_finite()
            && res.iter().all(|v| v.is_finite())
            && jac.iter().flatten().all(|v| v.is_finite()))
        .then_some((res, jac, ln_k))
    }

    /// Σ res² at θ, infinite where infeasible.
    fn cost(&self, theta: &[f64]) -> f64 {
        self.residuals(theta)
            .map_or(f64::INFINITY, |(r, _, _)| r.iter().map(|v| v * v).sum())
    }
}

impl Problem for DipoleProblem<'_> {
    fn params(&self) -> usize {
        2
    }
    fn rows(&self) -> usize {
        self.r.len()
    }
    fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, theta: &[f64], jac: bool, mut row: F) -> bool {
        let Some((res, j, _)) = self.residuals(theta) else {
            return false;
        };
        for (r, g) in res.iter().zip(&j) {
            if jac {
                row(*r, &[0, 1], g);
            } else {
                row(*r, &[], &[]);
            }
        }
        true
    }
}

/// Start candidates for θ = (ln sigma_s', ln sigma_a), best first. The dipole's shape depends on
/// sigma_t' only through the length 1/sigma_t' and otherwise on the albedo alone, so the grid
/// runs over ln sigma_t' (half-decade steps over six decades around the data's length scale)
/// and over logit(sigma_a/sigma_t') (from 1e-7, the clearest marble, to 0.999, darker than
/// ketchup's blue channel), scored on binned data. The best grid point of each albedo row is
/// a candidate; distinct rows keep starts in different basins (the low-albedo materials have a
/// false minimum at sigma_a → 0 next to the true one).
fn grid_starts(coarse: &DipoleProblem, scale_r: f64) -> Vec<(f64, [f64; 2])> {
    let mut rows: Vec<(f64, [f64; 2])> = Vec::new();
    for i in 0..21 {
        // logit q from ln 1e-7 to ln 1e3.
        let lq = (1e-7f64).ln() + i as f64 * (1e10f64).ln() / 20.0;
        let q = 1.0 / (1.0 + (-lq).exp());
        let mut best = (f64::INFINITY, [0.0; 2]);
        for j in 0..13 {
            let t = 10f64.powf(-3.0 + 0.5 * j as f64) / scale_r;
            let theta = [((1.0 - q) * t).ln(), (q * t).ln()];
            let c = coarse.cost(&theta);
            if c < best.0 {
                best = (c, theta);
            }
        }
        if best.0.is_finite() {
            rows.push(best);
        }
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    rows
}

/// Fits the dipole to samples s at distances r (one channel).
pub fn fit_dipole(r: &[f64], s: &[f64], options: &DipoleOptions) -> Result<DipoleFit, FitFailure> {
    if Dipole::new(1.0, 0.1, options.eta).is_err() {
        return Err(FitFailure::InvalidOptions {
            reason: "eta must be finite and > 0 with F_dr(eta) < 1",
        });
    }
    let (r, s, samples) = clean(r, s);
    // Shape (sigma_s', sigma_a) plus the scale unless absolute.
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
    // Pre-fit on the bins from the best few grid rows; the best pre-fit starts the fit on
    // every sample.
    let mut iterations = 0;
    let mut start: Option<(f64, Vec<f64>)> = None;
    for (_, theta) in grid_starts(&coarse, scale_r).into_iter().take(4) {
        let pre = lm::minimize(
            &coarse,
            &theta,
            &Settings {
                ftol: 1e-10,
                ..settings
            },
        );
        let (cost, th) = match pre {
            Some(o) => {
                iterations += o.iterations;
                (problem.cost(&o.theta), o.theta)
            }
            None => (problem.cost(&theta), theta.to_vec()),
        };
        if cost.is_finite() && start.as_ref().is_none_or(|s| cost < s.0) {
            start = Some((cost, th));
        }
    }
    let Some((_, start)) = start else {
        return Err(FitFailure::NonFinite);
    };
    let out = match options.solver {
        Solver::Specialised => lm::minimize(&problem, &start, &settings),
        Solver::Reference => super::reference::minimize(&problem, &start, options.max_iterations),
    }
    .ok_or(FitFailure::NonFinite)?;
    let ln_k = problem
        .residuals(&out.theta)
        .map(|(_, _, k)| k)
        .ok_or(FitFailure::NonFinite)?;
    let dipole = Dipole {
        sigma_s_prime: out.theta[0].exp(),
        sigma_a: out.theta[1].exp(),
        eta: options.eta,
    };
    let scale = ln_k.exp();
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
        iterations: iterations + out.iterations,
        converged: out.converged,
        stalled: out.stalled,
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

    /// The profile of the issue: eta of the material, r = 0.05·1.04^k mm, 140 points.
    fn jensen_r() -> Vec<f64> {
        (0..140).map(|k| 0.05 * 1.04f64.powi(k)).collect()
    }

    /// Deterministic N(0, 1) draws (SplitMix64 + Box–Muller).
    fn gauss(seed: &mut u64) -> f64 {
        let mut u = || {
            *seed = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = *seed;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            (((z ^ (z >> 31)) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let (u1, u2) = (u(), u());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// Relative error of the recovered coefficients: sigma_s' relative, sigma_a relative (or,
    /// for spectralon's sigma_a = 0, relative to sigma_t').
    fn errors(fit: &DipoleFit, truth: &Dipole) -> (f64, f64) {
        let es = (fit.dipole.sigma_s_prime / truth.sigma_s_prime - 1.0).abs();
        let ea = if truth.sigma_a > 0.0 {
            (fit.dipole.sigma_a / truth.sigma_a - 1.0).abs()
        } else {
            fit.dipole.sigma_a / truth.sigma_t_prime()
        };
        (es, ea)
    }

    /// Standard deviations of (ln sigma_s', ln sigma_a) by the Cramér–Rao bound for samples with
    /// multiplicative noise sigma: sigma²·(JᵀJ)⁻¹ at the truth (J of the scale-eliminated
    /// residuals, so the scale's uncertainty is accounted for). Spectralon (sigma_a = 0) gets
    /// zeros: its absorption has no relative error to bound.
    fn crb(r: &[f64], truth: &Dipole, absolute: bool, sigma: f64) -> [f64; 2] {
        if truth.sigma_a <= 0.0 || sigma == 0.0 {
            return [0.0; 2];
        }
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x)).collect();
        let p = DipoleProblem {
            r,
            y: &y,
            w: None,
            eta: truth.eta,
            absolute,
        };
        let (_, j, _) = p
            .residuals(&[truth.sigma_s_prime.ln(), truth.sigma_a.ln()])
            .unwrap();
        let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
        for g in &j {
            a += g[0] * g[0];
            b += g[0] * g[1];
            c += g[1] * g[1];
        }
        let det = a * c - b * b;
        [sigma * (c / det).sqrt(), sigma * (a / det).sqrt()]
    }

    /// Issue 13: every material of Jensen's measured table, every channel, free scale and
    /// absolute, from exact profiles (1e-4) and with 1 % multiplicative noise (5 %).
    #[test]
    fn jensen_table_round_trip() {
        use crate::model::dipole::MATERIALS;
        let r = jensen_r();
        let mut seed = 13u64;
        let mut worst = [(0.0f64, String::new()), (0.0f64, String::new())];
        for m in MATERIALS {
            for ch in 0..3 {
                let truth = m.dipole(ch).unwrap();
                for absolute in [false, true] {
                    let k = if absolute { 1.0 } else { 0.37 };
                    let options = DipoleOptions {
                        eta: truth.eta,
                        absolute,
                        ..DipoleOptions::default()
                    };
                    for (noise, tol, slot) in [(0.0f64, 1e-4f64, 0), (0.01, 0.05, 1)] {
                        let s: Vec<f64> = r
                            .iter()
                            .map(|&x| k * truth.r_d(x) * (noise * gauss(&mut seed)).exp())
                            .collect();
                        let what = format!("{} ch {ch} absolute {absolute} noise {noise}", m.name);
                        let fit =
                            fit_dipole(&r, &s, &options).unwrap_or_else(|e| panic!("{what}: {e}"));
                        let (es, ea) = errors(&fit, &truth);
                        assert!(fit.converged && !fit.stalled, "{what}: {fit:?}");
                        // The right basin: the fit explains the samples at least as well as
                        // the generating coefficients do (a wrong minimum cannot).
                        let y: Vec<f64> = s.iter().map(|v| v.ln()).collect();
                        let at_truth = DipoleProblem {
                            r: &r,
                            y: &y,
                            w: None,
                            eta: truth.eta,
                            absolute,
                        }
                        .cost(&[truth.sigma_s_prime.ln(), truth.sigma_a.max(1e-300).ln()]);
                        assert!(
                            fit.rss <= at_truth * (1.0 + 1e-9) + 1e-20,
                            "{what}: {fit:?}"
                        );
                        // The coefficients to the tolerance, or, where 140 samples
                        // with 1 % noise cannot determine them that well, to 4 standard
                        // deviations of the Cramér–Rao bound.
                        let sd = crb(&r, &truth, absolute, noise);
                        let bound = [tol.max(4.0 * sd[0]), tol.max(4.0 * sd[1])];
                        assert!(
                            es < bound[0] && ea < bound[1],
                            "{what}: {es:e} {ea:e} (bounds {bound:?}) {fit:?}"
                        );
                        if sd[0].max(sd[1]) * 4.0 > tol {
                            eprintln!(
                                "{what}: Cramér–Rao sd of ln sigma_s', ln sigma_a {sd:?}; errors {es:.3e} {ea:.3e}"
                            );
                        }
                        if !absolute {
                            assert!(
                                (fit.scale / k - 1.0).abs() < 10.0 * tol.max(4.0 * sd[0]),
                                "{what}: {fit:?}"
                            );
                        }
                        if es.max(ea) > worst[slot].0 {
                            worst[slot] = (es.max(ea), what);
                        }
                    }
                }
            }
        }
        eprintln!("worst exact {:?}, worst noisy {:?}", worst[0], worst[1]);
    }

    #[test]
    fn dipole_jacobian_matches_finite_differences() {
        use super::super::aniso::tests::check_jacobian;
        let r = jensen_r();
        let truth = Material::by_name("skin1").unwrap().dipole(2).unwrap();
        let y: Vec<f64> = r.iter().map(|&x| truth.ln_r_d(x) + 0.1 * x.sin()).collect();
        let w: Vec<f64> = (0..r.len()).map(|i| 1.0 + (i % 3) as f64).collect();
        for theta in [[0.1, -1.0], [-2.0, 0.5], [1.0, -6.0]] {
            for absolute in [false, true] {
                for weights in [None, Some(w.as_slice())] {
                    let p = DipoleProblem {
                        r: &r,
                        y: &y,
                        w: weights,
                        eta: 1.3,
                        absolute,
                    };
                    check_jacobian(&p, &theta);
                }
            }
        }
        // The evaluator agrees with the model's own ln R_d.
        let ev =
            DipoleEval::new(&[truth.sigma_s_prime.ln(), truth.sigma_a.ln()], truth.eta).unwrap();
        for &x in &r {
            assert!((ev.eval(x).0 - truth.ln_r_d(x)).abs() < 1e-12);
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
