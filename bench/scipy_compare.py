"""subsurf fit-curve --batch against scipy least_squares(method="lm") (issue 13).

Run through bench/scipy-compare, which sets up the venv and pins everything to one thread.

Curves: 3 well-separated terms, rates uniform in 0.2-8 /mm with consecutive rates >= 2x apart,
amplitudes c_k = rate_k^2 * 10^U(-1/2, 1/2), distances R*u^2 (u uniform, R = 10 / slowest rate),
1 % log-normal noise: the recipe of `random_curves_converge_from_the_automatic_start` in
host/model/src/fit/tests.rs, at the issue's size (2,000 curves of 2,000 samples).

subsurf: `RAYON_NUM_THREADS=1 subsurf fit-curve FILE --batch --terms 3 --objective log --json`,
timed as a whole process (reading and parsing the CSV, fitting, writing JSON) by the CPU time
(user + sys) the child used, from getrusage(RUSAGE_CHILDREN) before and after: the machine is
shared, and wall time would count waiting for a core. Wall time is printed beside it. The command
runs --repeat times (5) with the same output; the speed-up is taken at the median run.
scipy: least_squares(method="lm") on the same log residuals ln(sum c_k exp(-l_k r)) - ln s, over
(ln c_k, ln l_k) with the analytic Jacobian, from one naive start (rates 0.5, 2, 6 /mm, amplitudes
max(s)/3), timed over the fits only (the curves are already in memory).
"""

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time

import numpy as np
from scipy.optimize import least_squares


def draw_curves(count, samples, seed):
    rng = np.random.default_rng(seed)
    curves = []
    while len(curves) < count:
        rates = np.sort(rng.uniform(0.2, 8.0, 3))
        if rates[1] < 2 * rates[0] or rates[2] < 2 * rates[1]:
            continue
        amps = rates**2 * 10 ** rng.uniform(-0.5, 0.5, 3)
        r = 10.0 / rates[0] * rng.uniform(0, 1, samples) ** 2
        s = (amps[None, :] * np.exp(-np.outer(r, rates))).sum(axis=1)
        s *= np.exp(0.01 * rng.standard_normal(samples))
        curves.append((amps, rates, r, s))
    return curves


def write_csv(path, curves):
    with open(path, "w") as f:
        f.write("# bench/scipy_compare.py curves\nid,r,value\n")
        for i, (_, _, r, s) in enumerate(curves):
            ids = np.full(len(r), i)
            block = np.column_stack([ids, r, s])
            np.savetxt(f, block, fmt=["%d", "%.10g", "%.10g"], delimiter=",")


def scipy_fit(r, s):
    y = np.log(s)

    def model(theta):
        a, lam = theta[0::2], np.exp(theta[1::2])
        t = a[None, :] - np.outer(r, lam)
        m = t.max(axis=1)
        e = np.exp(t - m[:, None])
        tot = e.sum(axis=1)
        return m + np.log(tot), e / tot[:, None], lam

    def fun(theta):
        return model(theta)[0] - y

    def jac(theta):
        _, w, lam = model(theta)
        j = np.empty((len(r), 6))
        j[:, 0::2] = w
        j[:, 1::2] = -w * np.outer(r, lam)
        return j

    x0 = np.array(
        [np.log(s.max() / 3), np.log(0.5), np.log(s.max() / 3), np.log(2.0),
         np.log(s.max() / 3), np.log(6.0)]
    )
    res = least_squares(fun, x0, jac=jac, method="lm")
    log_e = float(np.sqrt(np.mean(res.fun**2)))
    return res.success, log_e, res.nfev


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--subsurf", required=True)
    ap.add_argument("--curves", type=int, default=2000)
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--subsurf-args", default="",
                    help='extra fit-curve arguments, e.g. "--bins 16"')
    ap.add_argument("--repeat", type=int, default=5,
                    help="run subsurf this many times; its figure is the median CPU time")
    ap.add_argument("--scipy-curves", type=int, default=None,
                    help="fit only the first N curves with scipy (rate and log E over those)")
    a = ap.parse_args()
    curves = draw_curves(a.curves, a.samples, a.seed)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "curves.csv")
        write_csv(path, curves)
        size = os.path.getsize(path)
        cmd = [a.subsurf, "fit-curve", path, "--batch", "--terms", "3", "--objective", "log",
               "--json"] + shlex.split(a.subsurf_args)
        env = dict(os.environ, RAYON_NUM_THREADS="1")
        # The whole command `--repeat` times (the machine is shared: one run's CPU time varies by
        # ~10 %); the median is the figure, every run's output must be the same.
        runs, out = [], None
        for _ in range(max(1, a.repeat)):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            got = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout
            wall = time.perf_counter() - t0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            runs.append((cpu, wall))
            assert out is None or got == out, "subsurf's output differs between runs"
            out = got
        cpus = sorted(c for c, _ in runs)
        t_subsurf = float(np.median(cpus))
        wall_subsurf = float(np.median([w for _, w in runs]))
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == a.curves, len(rows)
    # log E of subsurf's model measured on the samples here (the fast mode reports an estimate).
    def measured(row, curve):
        terms = row.get("terms")
        if not terms:
            return np.nan
        _, _, r, s = curve
        c = np.array([t["c"] for t in terms])
        d = np.array([t["d"] for t in terms])
        t_ = np.log(c)[None, :] + np.outer(r, d)
        m = t_.max(axis=1)
        ln_rd = m + np.log(np.exp(t_ - m[:, None]).sum(axis=1))
        return float(np.sqrt(np.mean((ln_rd - np.log(s)) ** 2)))

    ss_log_e = np.array([measured(row, c) for row, c in zip(rows, curves)], dtype=float)
    ss_conv = np.array([bool(r.get("converged")) for r in rows])
    ss_it = np.array([r.get("iterations", 0) for r in rows], dtype=float)

    k = a.scipy_curves or a.curves
    sp = []
    t0 = time.process_time()
    for _, _, r, s in curves[:k]:
        sp.append(scipy_fit(r, s))
    t_scipy = time.process_time() - t0
    sp_conv = np.array([x[0] for x in sp])
    sp_log_e = np.array([x[1] for x in sp])
    sp_nfev = np.array([x[2] for x in sp], dtype=float)

    rate_ss = a.curves / t_subsurf
    rate_sp = k / t_scipy
    both = slice(0, k)
    mean_ss = np.nanmean(ss_log_e[both])
    mean_sp = np.nanmean(sp_log_e)
    print(f"subsurf command: {' '.join(cmd[:1] + ['fit-curve', 'FILE'] + cmd[3:])}")
    print(f"curves: {a.curves} x {a.samples} samples, seed {a.seed}, CSV {size / 1e6:.1f} MB")
    print(f"subsurf: {t_subsurf:.3f} s CPU, median of {len(cpus)} runs (min {cpus[0]:.3f}, max "
          f"{cpus[-1]:.3f}; {wall_subsurf:.3f} s wall, load "
          f"{os.getloadavg()[0]:.2f}) for {a.curves} curves (parse + fit + JSON) = "
          f"{rate_ss:.0f} fits/s; not converged {int((~ss_conv).sum())} "
          f"({100 * (~ss_conv).mean():.2f} %); mean iterations {ss_it.mean():.1f}")
    print(f"scipy:   {t_scipy:.2f} s CPU for {k} curves (fits only) = {rate_sp:.1f} fits/s; "
          f"not converged {int((~sp_conv).sum())} ({100 * (~sp_conv).mean():.2f} %); "
          f"mean evaluations {sp_nfev.mean():.1f}")
    print(f"speed-up (CPU time): {rate_ss / rate_sp:.0f}x (subsurf's median run; its slowest "
          f"{a.curves / cpus[-1] / rate_sp:.0f}x, its fastest {a.curves / cpus[0] / rate_sp:.0f}x)")
    print(f"mean log E over the {k} curves both fitted: subsurf {mean_ss:.6f}, scipy "
          f"{mean_sp:.6f}, ratio {mean_ss / mean_sp:.4f}")
    worse = int((ss_log_e[both] > sp_log_e * 1.02).sum())
    print(f"curves where subsurf's log E exceeds scipy's by > 2 %: {worse}; "
          f"where scipy's exceeds subsurf's by > 2 %: {int((sp_log_e > ss_log_e[both] * 1.02).sum())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
