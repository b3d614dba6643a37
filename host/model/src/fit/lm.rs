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
    /// A constant part of the objective that no parameter changes (≥ 0): the binned fast mode's
    /// Σ scatter (see [`super::bins`]), which the binned cost leaves out. The relative tests
    /// (`ftol`, [`STATIONARY_RTOL`]) are relative to cost + offset, the objective's true size;
    /// without it they would demand digits of a small remainder that log E never shows.
    pub cost_offset: f64,
    /// The damping mu of the first trial step (relative to diag(JᵀJ)). 1e-3, Marquardt's
    /// customary value, suits a start from a grid; a start that is already a converged fit of
    /// the same model (the dipole's full fit after its binned pre-fit) is inside the region
    /// where Gauss–Newton converges, and damping there only slows the last digits down.
    pub initial_damping: f64,
    /// Stop, without evaluating the trial, when the Gauss–Newton model promises a decrease of
    /// at most `ftol` of the cost and the point is stationary ([`stationary`]): the cost cannot
    /// show a smaller decrease through its own rounding (a sum of m squares is known to about
    /// m·ε), so the trial would be accepted or rejected by rounding noise, and a rejection only
    /// raises the damping towards the same end. Off by default (the fits tuned without it keep
    /// their iteration counts).
    pub stop_on_predicted: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            ftol: 1e-15,
            xtol: 1e-13,
            max_step: 4.0,
            cost_offset: 0.0,
            initial_damping: 1e-3,
            stop_on_predicted: false,
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
    /// The convergence test was met: the cost stopped falling (relative change ≤ ftol) or no
    /// step changes θ any more, *and* the point is stationary ([`stationary`]).
    pub converged: bool,
    /// The solver stopped without meeting it although iterations were left: every trial step
    /// was rejected (or θ stopped moving) at a point that is not stationary. Reported as a
    /// failure, never as convergence.
    pub stalled: bool,
}

struct Normal {
    jtj: Vec<f64>,
    jtr: Vec<f64>,
    cost: f64,
}

/// What the solver builds at θ ([`build`]): whether θ is feasible, JᵀJ, Jᵀres and the cost;
/// for tests that hold a problem's specialised normal equations to the generic ones.
#[cfg(test)]
pub(crate) fn built<P: Problem>(problem: &P, theta: &[f64]) -> (bool, Vec<f64>, Vec<f64>, f64) {
    let p = problem.params();
    let mut out = Normal {
        jtj: vec![0.0; p * p],
        jtr: vec![0.0; p],
        cost: 0.0,
    };
    let ok = build(problem, theta, &mut out);
    (ok, out.jtj, out.jtr, out.cost)
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

/// Parameters up to which per-iteration scratch vectors live on the stack.
const STACK_PARAMS: usize = 64;

/// Solves (A + mu·D)x = b by Cholesky, D = diag(A) floored; `false` if not positive definite.
fn solve_damped(a: &[f64], b: &[f64], mu: f64, x: &mut [f64], l: &mut [f64]) -> bool {
    let p = b.len();
    let max_diag = (0..p).map(|i| a[i * p + i]).fold(0.0, f64::max);
    let floor = max_diag * 1e-14 + f64::MIN_POSITIVE;
    l.copy_from_slice(a);
    for i in 0..p {
        l[i * p + i] += mu * a[i * p + i].max(floor);
    }
    // Jacobi-scaled Cholesky: factor S A S with S = diag(1/sqrt(a_ii)) for conditioning. S on
    // the stack for the usual sizes (this runs in every iteration of every fit).
    let mut stack = [0.0f64; STACK_PARAMS];
    let mut heap = Vec::new();
    let s: &mut [f64] = if p <= STACK_PARAMS {
        &mut stack[..p]
    } else {
        heap.resize(p, 0.0);
        &mut heap
    };
    for i in 0..p {
        s[i] = 1.0 / l[i * p + i].max(floor).sqrt();
    }
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
    let mut mu = settings.initial_damping;
    let mut nu = 2.0;
    let mut iterations = 0;
    let mut converged = cur.cost == 0.0;
    let mut stalled = false;
    let mut neg_g = vec![0.0; p];
    while !converged && iterations < settings.max_iterations {
        iterations += 1;
        for (ng, g) in neg_g.iter_mut().zip(&cur.jtr) {
            *ng = -g;
        }
        if !solve_damped(&cur.jtj, &neg_g, mu, &mut step, &mut scratch) {
            mu *= nu;
            nu *= 2.0;
            if mu > 1e30 {
                // Not even a heavily damped system factors: stalled unless stationary.
                converged = stationary(&cur, &theta, settings.cost_offset, &mut step, &mut scratch);
                stalled = !converged;
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
        if settings.stop_on_predicted
            && predicted <= settings.ftol * (cur.cost + settings.cost_offset)
            && stationary(&cur, &theta, settings.cost_offset, &mut step, &mut scratch)
        {
            // Not a trial step: nothing was evaluated.
            iterations -= 1;
            converged = true;
            break;
        }
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
            let size = cur.cost + actual + settings.cost_offset;
            if cur.cost == 0.0
                || actual <= settings.ftol * size && predicted <= settings.ftol * size
            {
                // The cost stopped falling; a heavily damped step does that far from a minimum
                // too, so it counts only where the gradient vanishes.
                converged = stationary(&cur, &theta, settings.cost_offset, &mut step, &mut scratch);
            }
        } else {
            mu *= nu;
            nu *= 2.0;
        }
        if step_norm <= settings.xtol * (theta_norm + settings.xtol) && !converged {
            // θ no longer moves: a minimum only if the gradient says so.
            if stationary(&cur, &theta, settings.cost_offset, &mut step, &mut scratch) {
                converged = true;
            } else if mu > 1e30 || step_norm == 0.0 {
                stalled = true;
                break;
            }
        }
        if mu > 1e30 && !converged {
            // No step direction reduces the cost any more: a minimum to machine precision only
            // if the point is stationary; otherwise the run stalled.
            converged = stationary(&cur, &theta, settings.cost_offset, &mut step, &mut scratch);
            stalled = !converged;
            break;
        }
    }
    Some(Outcome {
        theta,
        cost: cur.cost,
        iterations,
        converged,
        stalled,
    })
}

/// Gauss–Newton refinement of a converged least-squares solution on the dense Jacobian by SVD.
///
/// Levenberg–Marquardt stops when the cost stops falling, but where residuals are small against
/// the data (the linear objective of NIST Lanczos3: residuals 3e-5 on values near 1) the cost is
/// only known to ~1e-11 relative, so cost comparisons cannot resolve the last digits of a flat
/// valley. The Gauss–Newton step −J⁺·res is known to rounding of res times ‖J⁺‖ instead, so
/// steps are taken while they shrink (a contracting iteration) and the cost does not rise beyond
/// its own rounding; the iterate before the first step that fails either test is kept. Few
/// parameters only (the SVD of an m×p matrix): used for the isotropic linear objective.
pub(crate) fn polish_gauss_newton<P: Problem>(problem: &P, outcome: Outcome) -> Outcome {
    use nalgebra::{DMatrix, DVector};
    let p = problem.params();
    let m = problem.rows();
    let dense = |theta: &[f64]| -> Option<(DVector<f64>, DMatrix<f64>)> {
        let mut res = DVector::zeros(m);
        let mut jac = DMatrix::zeros(m, p);
        let mut i = 0;
        let ok = problem.eval(theta, true, |r, idx, val| {
            if i < m {
                res[i] = r;
                for (&j, &v) in idx.iter().zip(val) {
                    jac[(i, j)] += v;
                }
            }
            i += 1;
        });
        (ok && i == m).then_some((res, jac))
    };
    let mut best = outcome;
    let mut last_step = f64::INFINITY;
    for _ in 0..8 {
        let Some((res, jac)) = dense(&best.theta) else {
            break;
        };
        let svd = jac.svd(true, true);
        let tol = svd.singular_values.max() * 1e-15 * m.max(p) as f64;
        let Ok(step) = svd.solve(&(-res), tol) else {
            break;
        };
        let norm = step.norm();
        if !norm.is_finite() || norm >= last_step {
            break;
        }
        let theta: Vec<f64> = best
            .theta
            .iter()
            .zip(step.iter())
            .map(|(a, b)| a + b)
            .collect();
        let Some((res2, _)) = dense(&theta) else {
            break;
        };
        let cost = res2.norm_squared();
        // Rounding of Σ res² where the residuals cancel against the data: allow 1e-9 relative.
        if !(cost.is_finite() && cost <= best.cost * (1.0 + 1e-9)) {
            break;
        }
        last_step = norm;
        best = Outcome {
            theta,
            cost,
            iterations: best.iterations + 1,
            ..best
        };
        let theta_norm = best.theta.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm <= 1e-15 * (1.0 + theta_norm) {
            break;
        }
    }
    best
}

/// The stationarity (gradient) test: the undamped Gauss–Newton model at θ predicts that the cost
/// can fall by at most gᵀ(JᵀJ)⁻¹g (g = Jᵀres), which is zero exactly at a stationary point. It
/// holds when that predicted decrease is at most [`STATIONARY_RTOL`] of the cost, or below what
/// rounding θ to f64 can change (ε²·Σ_i (JᵀJ)_ii·(1 + |θ_i|)², times a safety factor): a
/// zero-residual fit such as NIST Lanczos1 ends there. Scale-free in the residuals and, through
/// the Jacobi scaling of the solve, in the parameters. `cost_offset`: see
/// [`Settings::cost_offset`].
fn stationary(
    cur: &Normal,
    theta: &[f64],
    cost_offset: f64,
    x: &mut [f64],
    scratch: &mut [f64],
) -> bool {
    let p = theta.len();
    if cur.cost == 0.0 {
        return true;
    }
    let neg_g: Vec<f64> = cur.jtr.iter().map(|v| -v).collect();
    let floor: f64 = (0..p)
        .map(|i| cur.jtj[i * p + i] * (1.0 + theta[i].abs()).powi(2))
        .sum::<f64>()
        * f64::EPSILON
        * f64::EPSILON
        * 1e4;
    // A whisper of damping keeps the solve defined on a rank-deficient JᵀJ (a term switched
    // off); it can only make the predicted decrease smaller by a relative 1e-12.
    let decrease = if solve_damped(&cur.jtj, &neg_g, 1e-12, x, scratch) {
        x.iter().zip(&neg_g).map(|(a, b)| a * b).sum::<f64>()
    } else {
        // Not even the damped system factors: fall back to the Jacobi-scaled gradient.
        (0..p)
            .map(|i| {
                let d = cur.jtj[i * p + i];
                if d > 0.0 {
                    neg_g[i] * neg_g[i] / d
                } else {
                    0.0
                }
            })
            .sum()
    };
    decrease.is_finite() && decrease <= STATIONARY_RTOL * (cur.cost + cost_offset) + floor
}

/// Relative decrease of the cost that the Gauss–Newton model may still promise at a point called
/// stationary. With m residuals of noise sigma, a decrease of 1e-6·cost is a parameter error of
/// about sqrt(1e-6·m) standard errors (0.05 for m = 2,000).
pub(crate) const STATIONARY_RTOL: f64 = 1e-6;

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

    /// Rosenbrock with a third residual x + y − 1 that the valley's floor cannot zero: the
    /// minimum has a non-zero cost, so its last digits are decided by rounding.
    struct Tilted;
    impl Problem for Tilted {
        fn params(&self) -> usize {
            2
        }
        fn rows(&self) -> usize {
            3
        }
        fn eval<F: FnMut(f64, &[usize], &[f64])>(&self, t: &[f64], _: bool, mut row: F) -> bool {
            Rosenbrock.eval(t, true, &mut row);
            row(t[0] + t[1] - 1.0, &[0, 1], &[1.0, 1.0]);
            true
        }
    }

    /// The stop on the predicted decrease ends at the same minimum without the trial steps
    /// that rounding decides, and reports it as converged.
    #[test]
    fn stop_on_predicted_saves_the_rounding_steps() {
        let plain = minimize(&Tilted, &[-1.2, 1.0], &Settings::default()).unwrap();
        let early = Settings {
            stop_on_predicted: true,
            ..Settings::default()
        };
        let out = minimize(&Tilted, &[-1.2, 1.0], &early).unwrap();
        assert!(plain.converged && plain.cost > 0.1);
        assert!(out.converged && !out.stalled);
        assert!(
            (out.cost / plain.cost - 1.0).abs() < 1e-14,
            "{out:?} vs {plain:?}"
        );
        for i in 0..2 {
            assert!(
                (out.theta[i] - plain.theta[i]).abs() < 1e-7,
                "{out:?} vs {plain:?}"
            );
        }
        assert!(out.iterations < plain.iterations, "{out:?} vs {plain:?}");
    }

    #[test]
    fn rejects_bad_start() {
        assert!(minimize(&Rosenbrock, &[1.0], &Settings::default()).is_none());
    }
}
