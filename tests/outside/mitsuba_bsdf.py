"""Evaluates Mitsuba 3's rough dielectric BSDF for a table of direction pairs.

The outside reference for subsurf's rough dielectric boundary (host/src/volume/dielectric.rs):
`roughdielectric` with a GGX distribution (visible-normal sampling, Mitsuba's default), one
roughness `alpha`, `int_ior` inside (below the surface, local z < 0) and `ext_ior` outside.

    python mitsuba_bsdf.py pairs.json

pairs.json: {"alpha": a, "int_ior": n1, "ext_ior": n0, "pairs": [[wi, wo], ...]} with wi and wo
unit vectors in the surface's local frame (normal +z, pointing outside). For each pair it prints
one JSON line: Mitsuba's `eval` in radiance and in importance transport mode (the BSDF times
|cos theta_o|; wi is the direction the path came from) and its `pdf` of sampling wo from wi.
"""
import json
import sys

import mitsuba as mi

mi.set_variant("scalar_rgb")

spec = json.load(open(sys.argv[1]))
bsdf = mi.load_dict(
    {
        "type": "roughdielectric",
        "distribution": "ggx",
        "alpha": spec["alpha"],
        "int_ior": spec["int_ior"],
        "ext_ior": spec["ext_ior"],
    }
)
radiance = mi.BSDFContext(mi.TransportMode.Radiance)
importance = mi.BSDFContext(mi.TransportMode.Importance)
out = []
for wi, wo in spec["pairs"]:
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(wi)
    v = mi.Vector3f(wo)
    out.append(
        {
            "radiance": float(bsdf.eval(radiance, si, v)[0]),
            "importance": float(bsdf.eval(importance, si, v)[0]),
            "pdf": float(bsdf.pdf(radiance, si, v)),
        }
    )
print(json.dumps({"mitsuba": mi.__version__, "variant": mi.variant(), "values": out}))
