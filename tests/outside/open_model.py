"""Opens a subsurf model PLY with outside readers and prints what they read (tests/outside.rs).

Usage: python open_model.py MODEL.ply
Prints one JSON object per reader: vertex and face counts, the first and last vertex, normal and
face, and the sums of all positions and normals (to compare with subsurf's own reader).
"""
import json
import sys

import numpy as np
import trimesh

path = sys.argv[1]


def summary(v, n, f):
    v, n, f = np.asarray(v, float), np.asarray(n, float), np.asarray(f, int)
    return {
        "vertices": len(v),
        "faces": len(f),
        "first": [v[0].tolist(), n[0].tolist(), f[0].tolist()],
        "last": [v[-1].tolist(), n[-1].tolist(), f[-1].tolist()],
        "sum_positions": v.sum(axis=0).tolist(),
        "sum_normals": n.sum(axis=0).tolist(),
    }


out = {}
m = trimesh.load(path, process=False)
out["trimesh"] = summary(m.vertices, m.vertex_normals, m.faces)
try:
    import open3d as o3d
except ImportError:
    o3d = None
if o3d is not None:
    m = o3d.io.read_triangle_mesh(path)
    assert m.has_vertex_normals(), "Open3D read no normals"
    out["open3d"] = summary(m.vertices, m.vertex_normals, m.triangles)
print(json.dumps(out))
