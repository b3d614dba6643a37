//! A small, repeatable workload for profiling the dipole fit under callgrind, whose instruction
//! counts (unlike times) do not depend on the load of the shared machine (see BENCHMARKS.md,
//! "Dipole against the reference crate"). Times come from `cargo bench -p subsurf --bench fit --
//! dipole`; this binary only does the work.
//!
//! `dipole_profile [specialised|reference] [fits]`: the benchmark's data (skin1 red, 2,000
//! samples at r = 15u² mm, 1 % log-normal noise, the same generator and seed), fitted `fits`
//! times (default 1) with the chosen solver; prints log E, iterations and the coefficients.
//! `dipole_profile table`: Jensen's whole measured table, every channel, free scale and
//! absolute, exact and with 1 % noise (the unit test's profile r = 0.05·1.04^k mm, 140 points);
//! prints the total solver iterations and the worst relative coefficient error of each kind
//! (with noise, the worst is a material whose 140 samples cannot determine sigma_a to 5 %; the
//! unit test `jensen_table_round_trip` bounds those by the Cramér–Rao bound instead).

use subsurf_model::fit::Solver;
use subsurf_model::fit::dipole::{DipoleOptions, fit_dipole};
use subsurf_model::model::{MATERIALS, Material};

#[path = "support/splitmix.rs"]
mod splitmix;
use splitmix::Rng;

fn table() -> Result<(), String> {
    let r: Vec<f64> = (0..140).map(|k| 0.05 * 1.04f64.powi(k)).collect();
    let mut rng = Rng(13);
    let (mut iterations, mut fits, mut failed) = (0usize, 0usize, 0usize);
    let mut worst = [0.0f64; 2];
    for m in MATERIALS {
        for truth in (0..3).filter_map(|ch| m.dipole(ch)) {
            for absolute in [false, true] {
                let k = if absolute { 1.0 } else { 0.37 };
                let options = DipoleOptions {
                    eta: truth.eta,
                    absolute,
                    ..DipoleOptions::default()
                };
                for (slot, noise) in [0.0f64, 0.01].into_iter().enumerate() {
                    let s: Vec<f64> = r
                        .iter()
                        .map(|&x| k * truth.r_d(x) * (noise * rng.gauss()).exp())
                        .collect();
                    let fit =
                        fit_dipole(&r, &s, &options).map_err(|e| format!("{}: {e}", m.name))?;
                    iterations += fit.iterations;
                    fits += 1;
                    if !fit.converged || fit.stalled {
                        failed += 1;
                    }
                    let es = (fit.dipole.sigma_s_prime / truth.sigma_s_prime - 1.0).abs();
                    let ea = if truth.sigma_a > 0.0 {
                        (fit.dipole.sigma_a / truth.sigma_a - 1.0).abs()
                    } else {
                        fit.dipole.sigma_a / truth.sigma_t_prime()
                    };
                    worst[slot] = worst[slot].max(es.max(ea));
                }
            }
        }
    }
    println!(
        "table: {fits} fits, {iterations} iterations, {failed} not converged, worst relative error exact {:.3e}, 1 % noise {:.3e}",
        worst[0], worst[1]
    );
    Ok(())
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let solver = match args.get(1).map(String::as_str) {
        None | Some("specialised") => Solver::Specialised,
        Some("reference") => Solver::Reference,
        Some("table") => return table(),
        Some(other) => return Err(format!("unknown mode {other}")),
    };
    let fits: usize = match args.get(2) {
        Some(v) => v.parse().map_err(|e| format!("fits {v}: {e}"))?,
        None => 1,
    };
    let truth = Material::by_name("skin1")
        .and_then(|m| m.dipole(0))
        .ok_or("skin1 preset")?;
    let mut rng = Rng(3);
    let (r, s): (Vec<f64>, Vec<f64>) = (0..2_000)
        .map(|_| {
            let u = rng.uniform();
            let r = 15.0 * u * u;
            (r, truth.r_d(r) * (0.01 * rng.gauss()).exp())
        })
        .unzip();
    let options = DipoleOptions {
        solver,
        eta: truth.eta,
        ..DipoleOptions::default()
    };
    for _ in 1..fits {
        fit_dipole(std::hint::black_box(&r), std::hint::black_box(&s), &options)
            .map_err(|e| e.to_string())?;
    }
    let fit = fit_dipole(&r, &s, &options).map_err(|e| e.to_string())?;
    println!(
        "{solver:?}: log E {:.6e}, {} iterations, converged {}, sigma_s' {:.12}, sigma_a {:.12}, scale {:.12}",
        fit.log_e,
        fit.iterations,
        fit.converged,
        fit.dipole.sigma_s_prime,
        fit.dipole.sigma_a,
        fit.scale
    );
    Ok(())
}
