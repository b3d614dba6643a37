"""A scan's float EXR frames as one 16-bit camera exposure would record them (issue 24): each
value v becomes round(v * K) / K, clipped at the camera's range (65535 - 1024 DN above black),
written back as float EXR beside a copy of scan.json and the mesh. What quantisation alone, and
clipping, do to a fit's held-out error (BENCHMARKS.md, "Camera files").

Usage (a Python with numpy and OpenEXR: `pip install numpy OpenEXR`):
  python bench/quantise_scan.py SRC DST --expose-right      # brightest pixel at 15/16 of the range
  python bench/quantise_scan.py SRC DST --dn 2.5e-6         # 1 DN = 2.5e-6: the spot's core clips
--no-clip: no range limit (quantisation alone, more than 16 bits). With --dn the copy's scan.json
gets `saturation` at the clipping level (clipped pixels dropped, as
camera files' white level does); --no-saturation leaves it out.
"""
import argparse
import json
import os
import shutil

import numpy as np
import OpenEXR

ap = argparse.ArgumentParser()
ap.add_argument("src")
ap.add_argument("dst")
ap.add_argument("--expose-right", action="store_true")
ap.add_argument("--dn", type=float, help="radiance of one DN")
ap.add_argument("--no-saturation", action="store_true")
ap.add_argument("--no-clip", action="store_true", help="no range limit: quantisation alone")
a = ap.parse_args()
spec = json.load(open(os.path.join(a.src, "scan.json")))
imgs = []
for f in spec["frames"]:
    with OpenEXR.File(os.path.join(a.src, f["image"])) as fh:
        imgs.append(np.asarray(fh.channels()["RGB"].pixels, dtype=np.float64))
W = 65535 - 1024
K = 15 / 16 * W / max(i.max() for i in imgs) if a.expose_right else 1 / a.dn
os.makedirs(os.path.join(a.dst, "frames"), exist_ok=True)
shutil.copy(os.path.join(a.src, spec["mesh"]), a.dst)
if not a.expose_right and not a.no_saturation and not a.no_clip:
    spec["saturation"] = W / K
json.dump(spec, open(os.path.join(a.dst, "scan.json"), "w"))
clipped = 0
for f, px in zip(spec["frames"], imgs):
    q = np.rint(px * K) if a.no_clip else np.minimum(np.rint(px * K), W)
    clipped += 0 if a.no_clip else int((q >= W).sum())
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": (q / K).astype(np.float32)}) as o:
        o.write(os.path.join(a.dst, f["image"]))
print(f"1 DN = {1 / K:.4g}, noise floor {spec.get('noise_floor', 0) * K:.2f} DN, "
      f"{clipped} clipped channel values")
