"""A scan's float EXR frames as one 16-bit camera exposure would record them (issue 24): each
value v becomes round(v * K) / K, clipped at the camera's range (65535 - 1024 DN above black),
written back as float EXR beside a copy of scan.json and the mesh. What quantisation alone, and
clipping, do to a fit's held-out error (BENCHMARKS.md, "Camera files").

Usage (a Python with numpy and OpenEXR: `pip install numpy OpenEXR`; tifffile for --brackets):
  python bench/quantise_scan.py SRC DST --expose-right      # brightest pixel at 15/16 of the range
  python bench/quantise_scan.py SRC DST --dn 2.5e-6         # 1 DN = 2.5e-6: the spot's core clips
  python bench/quantise_scan.py SRC DST --brackets 1,64     # HDR: one 16-bit TIFF per exposure
--no-clip: no range limit (quantisation alone, more than 16 bits). With --dn the copy's scan.json
gets `saturation` at the clipping level (clipped pixels dropped, as
camera files' white level does); --no-saturation leaves it out.
--brackets G1,G2,...: exposures G times the exposed-to-the-right one (G1 = 1 is it), each written
as a 16-bit RGB TIFF (black level 1024 DN, white 65535, clipped) as a camera program writes a
bracket; the first is the frame's `image`, the others its `brackets` in scan.json
(docs/scan-format.md), the levels and the noise floor (in decoded units) in scan.json.
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
ap.add_argument("--brackets", help="exposure multiples, e.g. 1,64,4096: 16-bit TIFF brackets")
a = ap.parse_args()
spec = json.load(open(os.path.join(a.src, "scan.json")))
imgs = []
for f in spec["frames"]:
    with OpenEXR.File(os.path.join(a.src, f["image"])) as fh:
        imgs.append(np.asarray(fh.channels()["RGB"].pixels, dtype=np.float64))
W = 65535 - 1024
K = 15 / 16 * W / max(i.max() for i in imgs) if a.expose_right or a.brackets else 1 / a.dn
os.makedirs(os.path.join(a.dst, "frames"), exist_ok=True)
shutil.copy(os.path.join(a.src, spec["mesh"]), a.dst)
if a.brackets:
    import tifffile

    gains = [float(g) for g in a.brackets.split(",")]
    assert gains == sorted(gains) and gains[0] > 0, "exposures shortest first"
    spec["black_level"], spec["white_level"] = 1024, 65535
    if "noise_floor" in spec:
        spec["noise_floor"] *= K / W
    clipped = [0] * len(gains)
    for k, (f, px) in enumerate(zip(spec["frames"], imgs)):
        e = f.get("exposure_s", 1.0)
        names = [f"frames/{k:06}_{b}.tif" for b in range(len(gains))]
        for b, (g, name) in enumerate(zip(gains, names)):
            q = np.minimum(np.rint(px * K * g), W)
            clipped[b] += int((q >= W).sum())
            tifffile.imwrite(os.path.join(a.dst, name), (q + 1024).astype(np.uint16),
                             photometric="rgb")
        f["image"], f["exposure_s"] = names[0], e * gains[0]
        f["brackets"] = [{"image": n, "exposure_s": e * g} for n, g in zip(names[1:], gains[1:])]
    json.dump(spec, open(os.path.join(a.dst, "scan.json"), "w"))
    print(f"1 DN = {1 / K:.4g} at x{gains[0]:g}, noise floor {spec.get('noise_floor', 0) * W:.2f} "
          f"DN there; clipped channel values per exposure {clipped}")
    raise SystemExit
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
