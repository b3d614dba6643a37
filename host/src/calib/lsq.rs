//! A least-squares problem given by a residual closure, solved with the `levenberg-marquardt`
//! crate. The Jacobian is by central differences: calibration problems here have at most a few
//! dozen parameters, so an analytic Jacobian would add code without a measurable gain.

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{DMatrix, DVector, Dyn, Owned};

pub(crate) struct ClosureProblem<F: Fn(&DVector<f64>) -> DVector<f64>> {
    params: DVector<f64>,
    f: F,
}

impl<F: Fn(&DVector<f64>) -> DVector<f64>> LeastSquaresProblem<f64, Dyn, Dyn>
    for ClosureProblem<F>
{
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.params.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.params.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        let r = (self.f)(&self.params);
        r.iter().all(|v| v.is_finite()).then_some(r)
    }

    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let r0 = (self.f)(&self.params);
        let mut j = DMatrix::zeros(r0.len(), self.params.len());
        let mut p = self.params.clone();
        for k in 0..p.len() {
            let h = 1e-6 * (1.0 + p[k].abs());
            let v = p[k];
            p[k] = v + h;
            let rp = (self.f)(&p);
            p[k] = v - h;
            let rm = (self.f)(&p);
            p[k] = v;
            if rp.len() != r0.len() || rm.len() != r0.len() {
                return None;
            }
            j.set_column(k, &((rp - rm) / (2.0 * h)));
        }
        j.iter().all(|v| v.is_finite()).then_some(j)
    }
}

/// Minimises `|f(p)|²` from `p0`; returns the parameters and the RMS residual.
pub(crate) fn minimize<F: Fn(&DVector<f64>) -> DVector<f64>>(
    p0: DVector<f64>,
    f: F,
) -> Option<(DVector<f64>, f64)> {
    let problem = ClosureProblem { params: p0, f };
    let (problem, report) = LevenbergMarquardt::new()
        .with_patience(200)
        .minimize(problem);
    if !report.termination.was_successful() {
        return None;
    }
    let r = (problem.f)(&problem.params);
    let rms = (r.norm_squared() / r.len().max(1) as f64).sqrt();
    (rms.is_finite() && problem.params.iter().all(|v| v.is_finite()))
        .then_some((problem.params, rms))
}
