//! Fitting throughput: the specialised solver against the `levenberg-marquardt` crate (reference)
//! on identical data, the fast (binned) mode, the presets, and the bins → speed/accuracy curve.
//!
//! Run: `cargo bench -p subsurf --bench fit`. One fit per iteration on one core; "fits/s" is
//! 1 / (time per iteration). Time is the benchmark thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`),
//! not wall time: the project machine has 2 cores shared by seven engineers' builds (load
//! average 10–14 while these figures were taken), so wall time would measure the queue, not the
//! fitter. Accuracy lines (log E, Eq. 8) are printed once per configuration, measured on all
//! samples whatever mode produced the fit.

use std::hint::black_box;

use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use subsurf::fit::aniso::{AnisoOptions, fit_anisotropic, fit_colour_from};
use subsurf::fit::dipole::{DipoleOptions, fit_dipole};
use subsurf::fit::{FitOptions, Preset, Solver, fit_expsum};
use subsurf::model::{Anisotropic, ExpSum, Material, Term};

/// CPU time of the calling thread.
#[allow(unsafe_code)]
fn thread_cpu() -> Duration {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec through a valid pointer.
    let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) } == 0;
    if ok {
        Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
    } else {
        Duration::ZERO
    }
}

/// Criterion measurement: thread CPU time, formatted like wall time.
struct ThreadCpuTime;
static WALL: WallTime = WallTime;
impl Measurement for ThreadCpuTime {
    type Intermediate = Duration;
    type Value = Duration;
    fn start(&self) -> Duration {
        thread_cpu()
    }
    fn end(&self, start: Duration) -> Duration {
        thread_cpu().saturating_sub(start)
    }
    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }
    fn zero(&self) -> Duration {
        Duration::ZERO
    }
    fn to_f64(&self, v: &Duration) -> f64 {
        v.as_nanos() as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        WALL.formatter()
    }
}

type Crit = Criterion<ThreadCpuTime>;

#[path = "../model/examples/support/splitmix.rs"]
mod splitmix;
use splitmix::Rng;

fn marble_like() -> ExpSum {
    ExpSum::new(vec![
        Term { c: 0.05, d: -0.3 },
        Term { c: 0.5, d: -1.0 },
        Term { c: 5.0, d: -3.0 },
    ])
    .unwrap()
}

/// `count` samples of a 3-term fall-off, r = 15·u² mm (dense near x_i like a camera image),
/// 1 % multiplicative noise.
fn curve(count: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let m = marble_like();
    let mut rng = Rng(seed);
    (0..count)
        .map(|_| {
            let u = rng.uniform();
            let r = 15.0 * u * u;
            (r, m.eval(r) * (0.01 * rng.gauss()).exp())
        })
        .unzip()
}

fn log_e(m: &ExpSum, r: &[f64], s: &[f64]) -> f64 {
    let sq: f64 = r
        .iter()
        .zip(s)
        .map(|(r, s)| (m.ln_eval(*r) - s.ln()).powi(2))
        .sum();
    (sq / r.len() as f64).sqrt()
}

fn isotropic(c: &mut Crit) {
    let mut g = c.benchmark_group("isotropic_n3");
    for count in [500usize, 2_000, 20_000] {
        let (r, s) = curve(count, count as u64);
        let exact = FitOptions::default();
        let reference = FitOptions {
            solver: Solver::Reference,
            ..FitOptions::default()
        };
        let fast = FitOptions {
            bins: Some(16),
            ..FitOptions::default()
        };
        for (name, o) in [
            ("specialised", &exact),
            ("reference", &reference),
            ("fast_16_bins", &fast),
        ] {
            let f = fit_expsum(&r, &s, o).unwrap();
            eprintln!(
                "accuracy isotropic_n3/{name}/{count}: log E {:.6e} (reported {:.6e}), {} iterations, converged {}",
                log_e(&f.model, &r, &s),
                f.log_e,
                f.iterations,
                f.converged
            );
            g.bench_with_input(BenchmarkId::new(name, count), &(&r, &s), |b, (r, s)| {
                b.iter(|| fit_expsum(black_box(r), black_box(s), o).unwrap())
            });
        }
    }
    g.finish();
}

fn anisotropic(c: &mut Crit) {
    let m = 8;
    let segments: Vec<ExpSum> = (0..m)
        .map(|l| {
            let a = 1.0 + 0.4 * (l as f64 * 1.3).sin();
            ExpSum::new(vec![
                Term {
                    c: 0.05 * a,
                    d: -0.3 / a,
                },
                Term { c: 0.5, d: -a },
                Term {
                    c: 5.0 / a,
                    d: -3.0 * a,
                },
            ])
            .unwrap()
        })
        .collect();
    let model = Anisotropic { segments };
    let mut rng = Rng(8);
    let (mut r, mut phi, mut s) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..4_000 {
        let u = rng.uniform();
        let p = rng.uniform() * std::f64::consts::TAU;
        r.push(15.0 * u * u);
        phi.push(p);
        s.push(model.eval(15.0 * u * u, Some(p)) * (0.01 * rng.gauss()).exp());
    }
    let mut g = c.benchmark_group("anisotropic_m8_n3");
    g.sample_size(10);
    let exact = AnisoOptions {
        terms: 3,
        segments: m,
        ..AnisoOptions::default()
    };
    let variants = [
        ("specialised", exact),
        (
            "reference",
            AnisoOptions {
                solver: Solver::Reference,
                ..exact
            },
        ),
        (
            "fast_8_bins",
            AnisoOptions {
                direction_bins: Some(8),
                ..exact
            },
        ),
        (
            "fast_16_bins",
            AnisoOptions {
                direction_bins: Some(16),
                ..exact
            },
        ),
    ];
    for (name, o) in variants {
        let f = fit_anisotropic(&r, &phi, &s, &o).unwrap();
        eprintln!(
            "accuracy anisotropic_m8_n3/{name}/4000: log E {:.6e} (on all samples), {} iterations, converged {}",
            f.1, f.2, f.3
        );
        g.bench_function(BenchmarkId::new(name, 4_000), |b| {
            b.iter(|| fit_anisotropic(black_box(&r), black_box(&phi), black_box(&s), &o).unwrap())
        });
    }
    g.finish();
}

/// A light position as the default fit solves it in every round (Eq. 5, a hot path): 1,600
/// observations with all three channels (channel scales 0.8 and 0.6), shared colour, m = 1,
/// n = 3, started from the red samples' isotropic fit. "default" is the pipeline's solve (the
/// scales in closed form, the fall-off fitted to one curve: `aniso::separable_scales`),
/// "reference" the reference preset's (every channel's row, libm's exp and ln).
fn shared_colour(c: &mut Crit) {
    let truth = ExpSum::new(vec![
        Term { c: 0.05, d: -0.3 },
        Term { c: 0.5, d: -1.0 },
        Term { c: 5.0, d: -3.0 },
    ])
    .unwrap();
    let mut rng = Rng(11);
    let (mut r, mut phi) = (Vec::new(), Vec::new());
    let mut s: [Vec<f64>; 3] = Default::default();
    for _ in 0..1_600 {
        let u = rng.uniform();
        let x = 15.0 * u * u;
        r.push(x);
        phi.push(rng.uniform() * std::f64::consts::TAU);
        for (ch, k) in [1.0, 0.8, 0.6].into_iter().enumerate() {
            s[ch].push(k * truth.eval(x) * (0.01 * rng.gauss()).exp());
        }
    }
    let start = fit_expsum(&r, &s[0], &FitOptions::default()).unwrap().model;
    let mut g = c.benchmark_group("shared_colour_m1_n3");
    g.sample_size(20);
    let default = AnisoOptions {
        terms: 3,
        segments: 1,
        shared: true,
        ..AnisoOptions::default()
    };
    let variants = [
        ("default", default),
        (
            "reference",
            AnisoOptions {
                libm: true,
                ..default
            },
        ),
    ];
    let channels = [&s[0][..], &s[1][..], &s[2][..]];
    for (name, o) in variants {
        let f = fit_colour_from(&r, &phi, channels, &o, Some(&start)).unwrap();
        eprintln!(
            "accuracy shared_colour_m1_n3/{name}/1600: log E {:.6e} / {:.6e} / {:.6e}, {} iterations, converged {}",
            f.log_e[0], f.log_e[1], f.log_e[2], f.iterations, f.converged
        );
        g.bench_function(BenchmarkId::new(name, 1_600), |b| {
            b.iter(|| {
                fit_colour_from(black_box(&r), black_box(&phi), channels, &o, Some(&start)).unwrap()
            })
        });
    }
    g.finish();
}

fn dipole(c: &mut Crit) {
    let truth = Material::by_name("skin1").unwrap().dipole(0).unwrap();
    let mut rng = Rng(3);
    let (r, s): (Vec<f64>, Vec<f64>) = (0..2_000)
        .map(|_| {
            let u = rng.uniform();
            let r = 15.0 * u * u;
            (r, truth.r_d(r) * (0.01 * rng.gauss()).exp())
        })
        .unzip();
    let mut g = c.benchmark_group("dipole");
    for solver in [Solver::Specialised, Solver::Reference] {
        let o = DipoleOptions {
            solver,
            eta: truth.eta,
            ..DipoleOptions::default()
        };
        let f = fit_dipole(&r, &s, &o).unwrap();
        eprintln!(
            "accuracy dipole/{solver:?}/2000: log E {:.6e}, {} iterations, converged {}",
            f.log_e, f.iterations, f.converged
        );
        let name = format!("{solver:?}").to_lowercase();
        g.bench_function(BenchmarkId::new(name, 2_000), |b| {
            b.iter(|| fit_dipole(black_box(&r), black_box(&s), &o).unwrap())
        });
    }
    g.finish();
}

fn presets(c: &mut Crit) {
    let (r, s) = curve(2_000, 2_000);
    let mut g = c.benchmark_group("preset");
    for p in Preset::ALL {
        let o = p.options();
        let f = fit_expsum(&r, &s, &o).unwrap();
        eprintln!(
            "accuracy preset/{}/2000: log E {:.6e}, terms {}, {} iterations ({:?})",
            p.name(),
            log_e(&f.model, &r, &s),
            f.model.n(),
            f.iterations,
            o
        );
        g.bench_function(p.name(), |b| {
            b.iter(|| fit_expsum(black_box(&r), black_box(&s), &o).unwrap())
        });
    }
    g.finish();
}

/// Mean thread-CPU seconds per call of `f` over ~0.3 s (for the plot; criterion's own estimates
/// are not exposed to the benchmark).
fn cpu_seconds_per_call<T>(mut f: impl FnMut() -> T) -> f64 {
    let start = thread_cpu();
    let mut calls = 0u32;
    while thread_cpu() - start < Duration::from_millis(300) {
        black_box(f());
        calls += 1;
    }
    (thread_cpu() - start).as_secs_f64() / f64::from(calls.max(1))
}

fn trade_curve(c: &mut Crit) {
    let (r, s) = curve(2_000, 2_000);
    let exact = fit_expsum(&r, &s, &FitOptions::default()).unwrap();
    let e0 = log_e(&exact.model, &r, &s);
    // With SUBSURF_FIT_PLOT=path.png, also time each setting directly and draw the curve.
    let plot = std::env::var_os("SUBSURF_FIT_PLOT");
    let mut points = Vec::new();
    let mut g = c.benchmark_group("trade_bins");
    for bins in [4usize, 6, 8, 12, 16, 24, 32, 48, 64, 128] {
        let o = FitOptions {
            bins: Some(bins),
            ..FitOptions::default()
        };
        let f = fit_expsum(&r, &s, &o).unwrap();
        let e = log_e(&f.model, &r, &s);
        eprintln!(
            "accuracy trade_bins/{bins}: log E {e:.6e} = {:.5} x exact ({e0:.6e}), {} iterations",
            e / e0,
            f.iterations
        );
        g.bench_with_input(BenchmarkId::from_parameter(bins), &o, |b, o| {
            b.iter(|| fit_expsum(black_box(&r), black_box(&s), o).unwrap())
        });
        if plot.is_some() {
            let t = cpu_seconds_per_call(|| fit_expsum(black_box(&r), black_box(&s), &o));
            points.push((t, e / e0 - 1.0));
        }
    }
    g.finish();
    if let Some(path) = plot {
        let t_exact = cpu_seconds_per_call(|| {
            fit_expsum(black_box(&r), black_box(&s), &FitOptions::default())
        });
        let path = std::path::PathBuf::from(path);
        subsurf::plot::tradeoff_curve(
            &path,
            "Fast mode, n = 3, 2,000 samples: time vs. log E / exact - 1 (line: exact fit)",
            &points,
            t_exact,
        )
        .unwrap();
        eprintln!("plot: {}", path.display());
    }
}

criterion_group! {
    name = benches;
    // No HTML plots: they need system fonts, and the figures go into BENCHMARKS.md as text.
    config = Criterion::default().with_measurement(ThreadCpuTime).without_plots();
    targets = isotropic, anisotropic, shared_colour, dipole, presets, trade_curve
}
criterion_main!(benches);
