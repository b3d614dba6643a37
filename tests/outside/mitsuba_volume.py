"""Renders a homogeneous medium inside a mesh with Mitsuba 3's volumetric path tracer.

The outside reference for subsurf's volume tracer (host/src/volume/trace.rs): the same mesh
(an OBJ subsurf writes), an index-matched boundary (a `null` BSDF with the medium inside), a
Henyey-Greenstein phase function, a spot light of 1 W and a pinhole camera, in millimetres.
Mitsuba traces from the camera with next-event estimation to the spot light; subsurf traces
from the light with next-event estimation to the camera: two estimators of the same image.

    python mitsuba_volume.py scene.json out.exr

scene.json: {"mesh": path, "sigma_t": s, "albedo": [r, g, b], "g": g,
             "camera": {"width", "height", "fov_x_deg", "origin", "target", "up"},
             "spot": {"position", "target", "cutoff_deg"}, "spp": n, "seed": k}

With "bsdf": a Mitsuba BSDF dict (e.g. {"type": "roughdielectric", "distribution": "ggx",
"alpha": 0.2, "int_ior": 1.55, "ext_ior": 1.0}) the boundary is that BSDF instead of the
index-matched `null`.

With "grid": {"origin", "cell_mm", "dims", "sigma_t": [per cell], "albedo": [[r, g, b] per
cell]} (cells x fastest, then y, then z) the medium is heterogeneous instead: Mitsuba's
`heterogeneous` medium over two `gridvolume`s with nearest-cell lookup, piecewise constant as
subsurf's grid.
"""
import json
import math
import sys

import mitsuba as mi

mi.set_variant("scalar_rgb")

spec = json.load(open(sys.argv[1]))
cam = spec["camera"]
spot = spec["spot"]
cutoff = spot["cutoff_deg"]
# 1 W spread uniformly over the cone's solid angle (beam_width just inside the cutoff: Mitsuba
# blends the two smoothly, a sliver that changes the power by far less than the noise).
intensity = 1.0 / (2.0 * math.pi * (1.0 - math.cos(math.radians(cutoff))))
T = mi.ScalarTransform4f


def interior(spec):
    phase = {"type": "hg", "g": spec["g"]}
    grid = spec.get("grid")
    if grid is None:
        return {
            "type": "homogeneous",
            "sigma_t": spec["sigma_t"],
            "albedo": {"type": "rgb", "value": spec["albedo"]},
            "phase": phase,
        }
    import numpy as np

    nx, ny, nz = grid["dims"]
    size = [c * n for c, n in zip(grid["cell_mm"], grid["dims"])]
    to_world = T().translate(grid["origin"]) @ T().scale(size)
    sigma = np.array(grid["sigma_t"], dtype=np.float32).reshape(nz, ny, nx, 1)
    albedo = np.array(grid["albedo"], dtype=np.float32).reshape(nz, ny, nx, 3)
    return {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(sigma),
            "filter_type": "nearest",
            "to_world": to_world,
        },
        "albedo": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(albedo),
            "filter_type": "nearest",
            "to_world": to_world,
        },
        "scale": 1.0,
        "phase": phase,
    }

scene = mi.load_dict(
    {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 1000},
        "sensor": {
            "type": "perspective",
            "fov": cam["fov_x_deg"],
            "fov_axis": "x",
            "near_clip": 1.0,
            "far_clip": 1e5,
            "to_world": T().look_at(origin=cam["origin"], target=cam["target"], up=cam["up"]),
            "film": {
                "type": "hdrfilm",
                "width": cam["width"],
                "height": cam["height"],
                "pixel_format": "rgb",
                "rfilter": {"type": "gaussian"},
            },
            "sampler": {"type": "independent", "sample_count": spec["spp"], "seed": spec["seed"]},
        },
        "light": {
            "type": "spot",
            "to_world": T().look_at(
                origin=spot["position"], target=spot["target"], up=[0.0, 1.0, 0.0]
                if abs(spot["target"][1] - spot["position"][1]) < 0.9 * math.dist(spot["target"], spot["position"])
                else [1.0, 0.0, 0.0]
            ),
            "cutoff_angle": cutoff,
            "beam_width": cutoff * 0.999,
            "intensity": {"type": "rgb", "value": [intensity] * 3},
        },
        "object": {
            "type": "obj",
            "filename": spec["mesh"],
            "face_normals": True,
            "bsdf": spec.get("bsdf", {"type": "null"}),
            "interior": interior(spec),
        },
    }
)
img = mi.render(scene, spp=spec["spp"], seed=spec["seed"])
mi.util.write_bitmap(sys.argv[2], img, write_async=False)
print(json.dumps({"mitsuba": mi.__version__, "variant": mi.variant()}))
