//! Tests of the isotropic fitter: recovery, the NIST Lanczos1 problem, the reference solver, and
//! the extremes the issue lists.

use super::*;
use crate::model::Term;

fn model(terms: &[(f64, f64)]) -> ExpSum {
    ExpSum::new(terms.iter().map(|&(c, d)| Term { c, d }).collect()).unwrap()
}

fn lanczos() -> (Vec<f64>, Vec<f64>) {
    let text = include_str!("../../tests/data/lanczos1.csv");
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.starts_with('r'))
        .map(|l| {
            let mut it = l.split(',').map(|v| v.trim().parse::<f64>().unwrap());
            (it.next().unwrap(), it.next().unwrap())
        })
        .unzip()
}

const CERTIFIED: [f64; 6] = [
    9.5100000027E-02,
    1.0000000001E+00,
    8.6070000013E-01,
    3.0000000002E+00,
    1.5575999998E+00,
    5.0000000001E+00,
];

fn nist_vector(m: &ExpSum) -> Vec<f64> {
    m.terms.iter().flat_map(|t| [t.c, -t.d]).collect()
}

fn digits(got: &[f64], want: &[f64]) -> f64 {
    got.iter()
        .zip(want)
        .map(|(g, w)| -((g - w).abs() / w.abs()).max(1e-16).log10())
        .fold(f64::INFINITY, f64::min)
}

fn start(v: [f64; 6]) -> Vec<Term> {
    v.chunks(2).map(|p| Term { c: p[0], d: -p[1] }).collect()
}

#[test]
fn lanczos1_linear_objective_both_starts_both_solvers() {
    let (r, s) = lanczos();
    for st in [[1.2, 0.3, 5.6, 5.5, 6.5, 7.6], [0.5, 0.7, 3.6, 4.2, 4.0, 6.3]] {
        for solver in [Solver::Specialised, Solver::Reference] {
            let opts = FitOptions {
                objective: Objective::Linear,
                solver,
                start: Some(start(st)),
                ..FitOptions::default()
            };
            let fit = match fit_expsum(&r, &s, &opts) {
                Ok(f) => f,
                Err(e) => {
                    eprintln!("{solver:?} {st:?}: {e:?}");
                    continue;
                }
            };
            let dg = digits(&nist_vector(&fit.model), &CERTIFIED);
            eprintln!("{solver:?} {st:?}: {dg:.2} digits, rss {:e}, it {}", fit.rss, fit.iterations);
            if solver == Solver::Specialised {
                assert!(dg >= 9.0, "{dg}");
                assert!(fit.rss < 1.5e-25);
            }
        }
    }
}

#[test]
fn lanczos1_log_objective_recovers_generating_values() {
    let (r, s) = lanczos();
    let fit = fit_expsum(&r, &s, &FitOptions::default()).unwrap();
    let dg = digits(&nist_vector(&fit.model), &[0.0951, 1.0, 0.8607, 3.0, 1.5576, 5.0]);
    eprintln!("log: {dg:.2} digits, it {}", fit.iterations);
    assert!(dg >= 9.0, "{dg}");
}
