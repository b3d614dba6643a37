//! The specialised Levenberg–Marquardt solver.
//!
//! Hand-written (rather than the `levenberg-marquardt` crate, which stays as the reference in tests
//! and benchmarks) because the fitting problems here have few parameters (6 for n = 3, ≤ ~60 for
//! the anisotropic model) and many residuals with sparse Jacobian rows: accumulating the normal
//! equations JᵀJ row by row never stores J, touches only the non-zeros of each row and solves a
//! p×p Cholesky system, where the crate builds a dense m×p Jacobian and QR-factorises it. The
//! benchmarks in BENCHMARKS.md measure the difference.

/// A least-squares problem Σ_i res_i(θ)² seen through its rows.
pub(crate) trait Problem {
    /// Number of parameters p.
    fn params(&self) -> usize;
    /// Number of residual rows (for the reference adapter's dense matrices).
    fn rows(&self) -> usize;
    /// Evaluates every residual at θ and calls `row(residual, indices, jacobian_values)`; the
    /// Jacobian slices are empty when `with_jacobian` is false. Returns `false` if anything
    /// non-finite came up (the caller treats θ as infeasible).
    fn eval<F: FnMut(f64, &[usize], &[f64])>(
        &self,
        theta: &[f64],
        with_jacobian: bool,
        row: F,
    ) -> bool;
    /// A specialised one-pass computation of JᵀJ (full, p×p), Jᵀres and the cost, where a
    /// problem has one; `None` = use `eval`. `Some(None)` = θ is infeasible.
    fn normal_equations(
        &self,
        _theta: &[f64],
        _jtj: &mut [f64],
        _jtr: &mut [f64],
    ) -> Option<Option<f64>> {
        None
    }
}

/// Solver settings.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Settings {
    /// Maximum number of iterations (trial steps).
    pub max_iterations: usize,
    /// Relative reduction of the cost below which the fit has converged.
    pub ftol: f64,
    /// Relative step length below which the fit has converged.
    pub xtol: f64,
    /// Longest step taken in one iteration, a trust-region bound on top of the damping. The
    /// parameters are logarithms, so 1.0 means no c_k or d_k changes by more than a factor e.
    pub max_step: f64,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            ftol: 1e-15,
            xtol: 1e-13,
            max_step: 4.0,
        }
    }
}

/// What the solver ended with.
#[derive(Debug, Clone)]
pub(crate) struct Outcome {
    pub theta: Vec<f64>,
    /// Σ res², at `theta`.
    pub cost: f64,
    pub iterations: usize,
    pub converged: bool,
}

struct Normal {
    jtj: Vec<f64>,
    jtr: Vec<f64>,
    cost: f64,
}

fn build<P: Problem>(problem: &P, theta: &[f64], out: &mut Normal) -> bool {
    let p = problem.params();
    if let Some(result) = problem.normal_equations(theta, &mut out.jtj, &mut out.jtr) {
        return match result {
            Some(cost) => {
                out.cost = cost;
                true
            }
            None => false,
        };
    }
    out.jtj.iter_mut().for_each(|v| *v = 0.0);
    out.jtr.iter_mut().for_each(|v| *v = 0.0);
    let mut cost = 0.0;
    let (jtj, jtr) = (&mut out.jtj, &mut out.jtr);
    let ok = problem.eval(theta, true, |res, idx, val| {
        cost += res * res;
        for (a, (&i, &vi)) in idx.iter().zip(val).enumerate() {
            jtr[i] += vi * res;
            let rowi = &mut jtj[i * p..(i + 1) * p];
            for (&j, &vj) in idx[a..].iter().zip(&val[a..]) {
                rowi[j] += vi * vj;
            }
        }
    });
    // Only (i, j) pairs in the order rows give them were filled; symmetrise.
    for i in 0..p {
        for j in (i + 1)..p {
            let s = jtj[i * p + j] + jtj[j * p + i];
            jtj[i * p + j] = s;
            jtj[j * p + i] = s;
        }
    }
    out.cost = cost;
    ok && cost.is_finite() && jtr.iter().all(|v| v.is_finite())
}

/// Solves (A + mu·D)x = b by Cholesky, D = diag(A) floored; `false` if not positive definite.
fn solve_damped(a: &[f64], b: &[f64], mu: f64, x: &mut [f64], l: &mut [f64]) -> bool {
    let p = b.len();
    let max_diag = (0..p).map(|i| a[i * p + i]).fold(0.0, f64::max);
    let floor = max_diag * 1e-14 + f64::MIN_POSITIVE;
    l.copy_from_slice(a);
    for i in 0..p {
        l[i * p + i] += mu * a[i * p + i].max(floor);
    }
    // Jacobi-scaled Cholesky: factor S A S with S = diag(1/sqrt(a_ii)) for conditioning.
    let s: Vec<f64> = (0..p)
        .map(|i| 1.0 / l[i * p + i].max(floor).sqrt())
        .collect();
    for i in 0..p {
        for j in 0..p {
            l[i * p + j] *= s[i] * s[j];
        }
    }
    for j in 0..p {
        let mut d = l[j * p + j];
        for k in 0..j {
            d -= l[j * p + k] * l[j * p + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        l[j * p + j] = d;
        for i in (j + 1)..p {
            let mut v = l[i * p + j];
            for k in 0..j {
                v -= l[i * p + k] * l[j * p + k];
            }
            l[i * p + j] = v / d;
        }
    }
    for i in 0..p {
        let mut v = b[i] * s[i];
        for k in 0..i {
            v -= l[i * p + k] * x[k];
        }
        x[i] = v / l[i * p + i];
    }
    for i in (0..p).rev() {
        let mut v = x[i];
        for k in (i + 1)..p {
            v -= l[k * p + i] * x[k];
        }
        x[i] = v / l[i * p + i];
    }
    for i in 0..p {
        x[i] *= s[i];
    }
    x.iter().all(|v| v.is_finite())
}

/// Solves A·x = b (A symmetric positive definite) by Jacobi-scaled Cholesky.
pub(crate) fn solve_plain(a: &[f64], b: &[f64], x: &mut [f64], scratch: &mut [f64]) -> bool {
    solve_damped(a, b, 0.0, x, scratch)
}

/// Levenberg–Marquardt with Nielsen's damping update and Marquardt's diagonal scaling.
/// Never panics; a non-finite start returns `None`.
pub(crate) fn minimize<P: Problem>(
    problem: &P,
    start: &[f64],
    settings: &Settings,
) -> Option<Outcome> {
    let p = problem.params();
    if start.len() != p || p == 0 {
        return None;
    }
    let mut theta = start.to_vec();
    let mut cur = Normal {
        jtj: vec![0.0; p * p],
        jtr: vec![0.0; p],
        cost: 0.0,
    };
    let mut trial = Normal {
        jtj: vec![0.0; p * p],
        jtr: vec![0.0; p],
        cost: 0.0,
    };
    if !build(problem, &theta, &mut cur) {
        return None;
    }
    let mut step = vec![0.0; p];
    let mut scratch = vec![0.0; p * p];
    let mut candidate = vec![0.0; p];
    let mut mu = 1e-3;
    let mut nu = 2.0;
    let mut iterations = 0;
    let mut converged = cur.cost == 0.0;
    while !converged && iterations < settings.max_iterations {
        iterations += 1;
        let neg_g: Vec<f64> = cur.jtr.iter().map(|v| -v).collect();
        if !solve_damped(&cur.jtj, &neg_g, mu, &mut step, &mut scratch) {
            mu *= nu;
            nu *= 2.0;
            if mu > 1e30 {
                break;
            }
            continue;
        }
        let mut step_norm = step.iter().map(|v| v * v).sum::<f64>().sqrt();
        if step_norm > settings.max_step {
            let k = settings.max_step / step_norm;
            step.iter_mut().for_each(|v| *v *= k);
            step_norm = settings.max_step;
        }
        for i in 0..p {
            candidate[i] = theta[i] + step[i];
        }
        let theta_norm = theta.iter().map(|v| v * v).sum::<f64>().sqrt();
        // Predicted reduction of Σ res² by the Gauss–Newton model: −2δᵀg − δᵀJᵀJδ.
        let predicted: f64 = (0..p)
            .map(|i| {
                let hd: f64 = (0..p).map(|j| cur.jtj[i * p + j] * step[j]).sum();
                step[i] * (2.0 * neg_g[i] - hd)
            })
            .sum();
        let ok = build(problem, &candidate, &mut trial);
        let actual = cur.cost - trial.cost;
        if ok && actual > 0.0 {
            let rho = if predicted > 0.0 {
                actual / predicted
            } else {
                1.0
            };
            std::mem::swap(&mut cur, &mut trial);
            std::mem::swap(&mut theta, &mut candidate);
            mu *= (1.0f64 / 3.0).max(1.0 - (2.0 * rho - 1.0).powi(3));
            nu = 2.0;
            if cur.cost == 0.0
                || actual <= settings.ftol * (cur.cost + actual)
                    && predicted <= settings.ftol * (cur.cost + actual)
            {
                converged = true;
            }
        } else {
            mu *= nu;
            nu *= 2.0;
        }
        if step_norm <= settings.xtol * (theta_norm + settings.xtol) {
            converged = true;
        }
        if mu > 1e30 {
            // No step direction reduces the cost any more: a minimum to machine precision.
            converged = true;
        }
    }
    Some(Outcome {
        theta,
        cost: cur.cost,
        iterations,
        converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rosenbrock as residuals (10(y − x²), 1 − x): a classic hard valley.
    struct Rosenbrock;
    impl Problem for Rosenbrock {
        fn params(&self) -> usize {
            2
        }
        fn rows(&self) -> usize {
            2
        }
        fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, t: &[f64], _: bool, mut row: F) -> bool {
            row(10.0 * (t[1] - t[0] * t[0]), &[0, 1], &[-20.0 * t[0], 10.0]);
            row(1.0 - t[0], &[0], &[-1.0]);
            true
        }
    }

    #[test]
    fn solves_rosenbrock() {
        let out = minimize(&Rosenbrock, &[-1.2, 1.0], &Settings::default()).unwrap();
        assert!(out.converged);
        assert!((out.theta[0] - 1.0).abs() < 1e-10 && (out.theta[1] - 1.0).abs() < 1e-10);
    }

    #[test]
    fn rejects_bad_start() {
        assert!(minimize(&Rosenbrock, &[1.0], &Settings::default()).is_none());
    }
}
