"""Imports a PLY with Blender's own importer and prints what it read (tests/outside.rs).

Usage: blender -b --factory-startup --python blender_ply.py -- MODEL.ply
Prints one line `BLENDER {json}`: vertex and face counts, the first and last vertex and face.
"""
import json
import sys

import bpy

path = sys.argv[sys.argv.index("--") + 1]
bpy.ops.wm.read_factory_settings(use_empty=True)
if bpy.app.version >= (4, 0, 0):  # Blender 4: the C++ importer
    bpy.ops.wm.ply_import(filepath=path)
else:  # Blender 3: the io_mesh_ply add-on
    bpy.ops.import_mesh.ply(filepath=path)
me = bpy.context.selected_objects[0].data
v, f = me.vertices, me.polygons
print("BLENDER " + json.dumps({
    "vertices": len(v),
    "faces": len(f),
    "first": [list(v[0].co), list(f[0].vertices)],
    "last": [list(v[-1].co), list(f[-1].vertices)],
}))
