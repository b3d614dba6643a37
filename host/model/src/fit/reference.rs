//! The reference solver: the maintained `levenberg-marquardt` crate (MINPACK's algorithm, dense
//! Jacobian, QR) on exactly the same residuals and analytic Jacobians as the specialised solver.
//! Tests and benchmarks compare against it.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};

use super::lm::{Outcome, Problem};

struct Adapter<'a, P: Problem> {
    problem: &'a P,
    theta: DVector<f64>,
    // Shared work is cached in `set_params`: one pass gives residuals and Jacobian.
    residuals: Option<DVector<f64>>,
    jacobian: Option<DMatrix<f64>>,
}

impl<P: Problem> Adapter<'_, P> {
    fn evaluate(&mut self) {
        let m = self.problem.rows();
        let p = self.problem.params();
        let mut res = DVector::zeros(m);
        let mut jac = DMatrix::zeros(m, p);
        let mut i = 0;
        let ok = self
            .problem
            .eval(self.theta.as_slice(), true, |r, idx, val| {
                if i < m {
                    res[i] = r;
                    for (&j, &v) in idx.iter().zip(val) {
                        jac[(i, j)] = v;
                    }
                }
                i += 1;
            });
        if ok && i == m {
            self.residuals = Some(res);
            self.jacobian = Some(jac);
        } else {
            self.residuals = None;
            self.jacobian = None;
        }
    }
}

impl<P: Problem> LeastSquaresProblem<f64, Dyn, Dyn> for Adapter<'_, P> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.theta.copy_from(x);
        self.evaluate();
    }

    fn params(&self) -> DVector<f64> {
        self.theta.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        self.residuals.clone()
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        self.jacobian.clone()
    }
}

/// Minimises Σ res² with the crate from `start`; `None` if the start is infeasible.
pub(crate) fn minimize<P: Problem>(
    problem: &P,
    start: &[f64],
    max_iterations: usize,
) -> Option<Outcome> {
    let p = problem.params();
    if start.len() != p || p == 0 || problem.rows() == 0 {
        return None;
    }
    let mut adapter = Adapter {
        problem,
        theta: DVector::from_column_slice(start),
        residuals: None,
        jacobian: None,
    };
    adapter.evaluate();
    adapter.residuals.as_ref()?;
    // The crate allows patience·(p + 1) evaluations.
    let patience = max_iterations.max(1);
    let (adapter, report) = LevenbergMarquardt::new()
        .with_patience(patience)
        .minimize(adapter);
    let cost = adapter.residuals.as_ref().map(|r| r.norm_squared())?;
    Some(Outcome {
        theta: adapter.theta.as_slice().to_vec(),
        cost,
        iterations: report.number_of_evaluations,
        converged: report.termination.was_successful(),
        stalled: false,
    })
}
