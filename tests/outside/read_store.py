"""Reads a subsurf sample store with pyarrow (and pandas where installed) and prints what it read
(tests/outside.rs): rows and sums per file, so that subsurf's own reader can be compared.

Usage: python read_store.py STORE_DIR
"""
import json
import math
import sys
from pathlib import Path

import pyarrow.feather as feather

d = Path(sys.argv[1])
out = {}
frames = feather.read_table(d / "frames.arrow")
out["frames"] = frames.num_rows
out["registered"] = sum(1 for o in frames.column("outcome").to_pylist() if o == "registered")
for name in ["vertices", "points"]:
    p = d / f"{name}.arrow"
    if not p.exists():
        continue
    t = feather.read_table(p)
    col = lambda c: [x for x in t.column(c).to_pylist() if x is not None]
    out[name] = {
        "rows": t.num_rows,
        "columns": t.column_names,
        "sum_r": math.fsum(col("r")),
        "sum_s": [math.fsum(col(c)) for c in ["s_r", "s_g", "s_b"]],
        "valid": [len(col(c)) for c in ["s_r", "s_g", "s_b"]],
        "frames": sorted(set(t.column("frame").to_pylist())),
    }
try:
    import pandas as pd

    s = pd.read_feather(d / "vertices.arrow")
    f = pd.read_feather(d / "frames.arrow")
    m = s.merge(f[["frame", "x_i_x", "x_i_y", "x_i_z"]], on="frame")
    out["pandas_rows"] = len(m)
except ImportError:
    pass
print(json.dumps(out))
