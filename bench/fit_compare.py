"""Compares two `subsurf fit-curve FILE --batch --terms 3 --objective log --json` outputs (A, e.g.
main's, and B, a branch's) on the curves of FILE (the scipy comparison's CSV): relative
differences of every c_k and rate, log E of each measured on every sample from the printed
parameters (as bench/scipy_compare.py does), curves whose log E got worse, convergence and
iterations. Usage: bench/.venv/bin/python bench/fit_compare.py A.json B.json FILE.csv
"""
import json
import sys

import numpy as np

a = np.loadtxt(sys.argv[3], delimiter=",", comments="#", skiprows=2)
ids = a[:, 0].astype(int)
order = np.argsort(ids, kind="stable")
a = a[order]; ids = ids[order]
starts = np.searchsorted(ids, np.arange(ids.max() + 2))

def load(path):
    rows = [json.loads(l) for l in open(path)]
    return {int(r["id"]): r for r in rows}

def log_e(row, i):
    terms = row.get("terms")
    if not terms:
        return np.nan
    sl = slice(starts[i], starts[i + 1])
    r, s = a[sl, 1], a[sl, 2]
    c = np.array([t["c"] for t in terms]); d = np.array([t["d"] for t in terms])
    t_ = np.log(c)[None, :] + np.outer(r, d)
    m = t_.max(axis=1)
    ln_rd = m + np.log(np.exp(t_ - m[:, None]).sum(axis=1))
    return float(np.sqrt(np.mean((ln_rd - np.log(s)) ** 2)))

A, B = load(sys.argv[1]), load(sys.argv[2])
keys = sorted(set(A) & set(B))
print(f"curves: {len(A)} / {len(B)}, common {len(keys)}")
ea = np.array([log_e(A[k], k) for k in keys]); eb = np.array([log_e(B[k], k) for k in keys])
for k_ in range(3):
    for what in ("c", "d"):
        va = np.array([A[k]["terms"][k_][what] for k in keys]); vb = np.array([B[k]["terms"][k_][what] for k in keys])
        rel = np.abs(vb - va) / np.abs(va)
        print(f"term {k_} {what}: max rel diff {rel.max():.3e}, median {np.median(rel):.3e}")
print(f"mean log E: A {np.mean(ea):.7f}  B {np.mean(eb):.7f}  ratio B/A {np.mean(eb)/np.mean(ea):.7f}")
worse = eb > ea * 1.001; better = eb < ea / 1.001
print(f"curves whose log E got worse by > 0.1 %: {int(worse.sum())} (better by > 0.1 %: {int(better.sum())})")
rel = (eb - ea) / ea
print(f"log E relative change: max {rel.max():.3e}, min {rel.min():.3e}, median {np.median(rel):.3e}")
for name, D in (("A", A), ("B", B)):
    conv = sum(1 for k in keys if not D[k]["converged"])
    it = np.mean([D[k]["iterations"] for k in keys])
    print(f"{name}: not converged {conv}, mean iterations {it:.3f}")
if worse.any():
    idx = np.argsort(-rel)[:5]
    for i in idx:
        print(f"  curve {keys[i]}: log E {ea[i]:.6f} -> {eb[i]:.6f}")
