"""Builds the Blender scene of a `subsurf export --format blender` folder.

Run it in Blender 3.4 or newer, in the export folder or with its path, or with a Python that
imports `bpy` (the `bpy` module from PyPI, `pip install bpy`):

    blender -b --factory-startup --python build_blend.py                  # writes model.blend
    blender -b --factory-startup --python build_blend.py -- --render cycles.exr --samples 64
    blender --python build_blend.py                                       # opens the scene
    python build_blend.py -- --render cycles.exr                          # bpy as a module

It reads `bpy.app.version` and uses that version's API (custom normals without auto smooth from
4.1, Principled v2's inputs from 4.0).

It reads `model.glb` (the mesh, in metres, with the converted parameters as custom attributes:
Blender 3.4's glTF importer drops those, so this script reads the file itself) and `scene.json`
(lights, camera, render settings), and builds:

- the mesh with its normals and four point attributes: `subsurface_colour` (total diffuse
  reflectance per channel), `subsurface_radius` (metres), `alpha` (the modulation texture, Eq. 2/6
  of Fuchs et al. 2005) and `conversion_log_e`;
- the material: Attribute nodes feeding a Principled BSDF that is only its subsurface closure
  (method Christensen-Burley; 3.x: Subsurface 1, Specular 0; 4.0 on: Subsurface Weight 1,
  Subsurface Scale 1, Specular IOR Level 0, Coat and Sheen 0): the albedo (3.x Subsurface Color,
  v2 Base Color) = subsurface_colour x alpha x the Fresnel transmission out of the surface
  relative to normal incidence, Subsurface Radius = subsurface_radius; with two lobes
  (`scene.json` "lobes": 2) a second, slow Principled BSDF fed by `subsurface_colour_slow` and
  `subsurface_radius_slow`, mixed in by a Mix Shader whose factor is the `lobe_mix` attribute;
- the lights and the camera of the subsurf render, a black world, Cycles on the CPU, colour
  management "Standard" (the EXR holds linear radiance, unscaled).

Options after `--`: `--blend PATH` (default model.blend beside this script), `--render PATH.exr`
(also render the scene there), `--samples N`, `--seed N`, `--threads N` (0: all cores),
`--compare` (render as subsurf's renderer draws: pixel centres point-sampled, no light bounced
between surfaces, so the two images compare pixel for pixel), `--dir DIR` (the export folder),
`--frame K` (build scan frame K's scene from `frames.json` instead: its camera and image size,
the object turned by the turntable, the laser as a narrow spot light on x_i whose power carries
the frame's exposure; default `--blend` frames/K.blend; `subsurf export --scan --render`).

A volume model's export (`scene.json` "kind": "volume") builds instead the model's mesh with a
material that is only a Principled Volume (Density, Color, Absorption Color, Anisotropy as the
export computed them from sigma_t and albedo) behind no surface shader (index-matched: Cycles'
rays cross the surface unbent) or a GGX Glass BSDF (a dielectric boundary). A grid whose cells
differ is read by nearest lookup from two float images at the shading point's object
coordinates, and also written as `medium.vdb` (grids `density`, `color`, `absorption_color`)
where this Blender has the `openvdb` module.

Only the Python standard library is used (Debian's Blender has no numpy).
"""

import array
import json
import math
import os
import struct
import sys

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))

# The running Blender's version picks its API: the mesh's normals (auto smooth went in 4.1) and
# the Principled BSDF's inputs (Principled v2 from 4.0).
VERSION = tuple(bpy.app.version[:2])
PRINCIPLED_V2 = VERSION >= (4, 0)


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    opts = {"dir": HERE, "blend": None, "render": None, "samples": None, "seed": 0,
            "threads": 0, "compare": False, "frame": None, "measure": None}
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--compare":
            opts["compare"] = True
            i += 1
            continue
        if a not in ("--dir", "--blend", "--render", "--samples", "--seed", "--threads",
                     "--frame", "--measure"):
            raise SystemExit("build_blend.py: unknown option %r" % a)
        if i + 1 >= len(argv):
            raise SystemExit("build_blend.py: %s needs a value" % a)
        opts[a[2:]] = argv[i + 1]
        i += 2
    for k in ("samples", "seed", "threads", "frame"):
        if opts[k] is not None:
            opts[k] = int(opts[k])
    return opts


def read_glb(path):
    """The JSON and binary chunks of a binary glTF file."""
    with open(path, "rb") as f:
        data = f.read()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2 or length != len(data):
        raise SystemExit("%s is not a binary glTF 2.0 file" % path)
    at, doc, blob = 12, None, b""
    while at < len(data):
        size, kind = struct.unpack_from("<I4s", data, at)
        chunk = data[at + 8:at + 8 + size]
        if kind == b"JSON":
            doc = json.loads(chunk.decode("utf-8"))
        elif kind == b"BIN\x00":
            blob = chunk
        at += 8 + size
    if doc is None:
        raise SystemExit("%s has no JSON chunk" % path)
    return doc, blob


def accessor(doc, blob, index, code):
    """An accessor's values as a flat array of type `code` ('f' or 'I')."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    comps = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    out = array.array(code)
    out.frombytes(blob[start:start + 4 * comps * acc["count"]])
    if sys.byteorder != "little":
        out.byteswap()
    return out


def build_mesh(doc, blob):
    prim = doc["meshes"][0]["primitives"][0]
    attr = prim["attributes"]
    pos = accessor(doc, blob, attr["POSITION"], "f")
    nrm = accessor(doc, blob, attr["NORMAL"], "f")
    idx = accessor(doc, blob, prim["indices"], "I")
    nv, nt = len(pos) // 3, len(idx) // 3
    alpha, colours = None, []
    mesh = bpy.data.meshes.new("subsurf model")
    mesh.vertices.add(nv)
    mesh.vertices.foreach_set("co", pos)
    mesh.loops.add(3 * nt)
    mesh.loops.foreach_set("vertex_index", idx)
    mesh.polygons.add(nt)
    mesh.polygons.foreach_set("loop_start", array.array("i", range(0, 3 * nt, 3)))
    mesh.polygons.foreach_set("loop_total", array.array("i", [3]) * nt)
    mesh.polygons.foreach_set("use_smooth", array.array("b", [1]) * nt)
    mesh.update(calc_edges=True)
    mesh.validate()
    # The model's own normals, as the subsurf renderer shades with them. Before 4.1 custom
    # normals count only with auto smooth on; from 4.1 a mesh with custom normals uses them.
    if VERSION < (4, 1):
        mesh.use_auto_smooth = True
    mesh.normals_split_custom_set_from_vertices(
        [tuple(nrm[3 * v:3 * v + 3]) for v in range(nv)])
    for gltf_name, name, kind in (
            ("_SUBSURFACE_COLOR", "subsurface_colour", "FLOAT_COLOR"),
            ("_SUBSURFACE_RADIUS", "subsurface_radius", "FLOAT_VECTOR"),
            ("_ALPHA", "alpha", "FLOAT_COLOR"),
            ("_CONVERSION_LOG_E", "conversion_log_e", "FLOAT_VECTOR"),
            ("_SUBSURFACE_COLOR_SLOW", "subsurface_colour_slow", "FLOAT_COLOR"),
            ("_SUBSURFACE_RADIUS_SLOW", "subsurface_radius_slow", "FLOAT_VECTOR"),
            ("_LOBE_MIX", "lobe_mix", "FLOAT_VECTOR")):
        if gltf_name not in attr:
            # The slow lobe's attributes are written only with two lobes.
            continue
        values = accessor(doc, blob, attr[gltf_name], "f")
        if name == "alpha":
            alpha = values
        elif name.startswith("subsurface_colour"):
            colours.append(values)
        a = mesh.attributes.new(name, kind, "POINT")
        if kind == "FLOAT_COLOR":
            rgba = array.array("f", [1.0]) * (4 * nv)
            for c in range(3):
                rgba[c::4] = values[c::3]
            a.data.foreach_set("color", rgba)
        else:
            a.data.foreach_set("vector", values)
    largest = max((c * a for col in colours for c, a in zip(col, alpha if alpha is not None else [1.0] * len(col))), default=0.0)
    return mesh, largest


def light_scale_for(largest_albedo):
    """What the lights carry of the albedo: 1, or on Principled v2 the largest albedo above 1.

    A fitted colour is in the scan's units and may exceed 1. Blender 3.x's Principled takes it as
    it is; Principled v2 clamps its base colour to 1, so there the material's albedo is divided
    by this factor and every light's power multiplied by it: the same radiance leaves the object
    (the scene has no other surface and a black world), and the material stays below 1.
    """
    return max(1.0, largest_albedo) if PRINCIPLED_V2 else 1.0


def attribute_node(nt, name, location):
    n = nt.nodes.new("ShaderNodeAttribute")
    n.attribute_type = "GEOMETRY"
    n.attribute_name = name
    n.location = location
    return n


def principled(nt, method, location):
    """A Principled BSDF that is only its subsurface closure: no specular, sheen or coat.

    Blender 3.x: Subsurface 1 (albedo = Subsurface Color, radius = Subsurface Radius), Specular
    0, Sheen 0. Principled v2 (4.0 on): Subsurface Weight 1 and Subsurface Scale 1 (radius =
    Subsurface Radius x Scale), the Base Color is the albedo; Specular IOR Level 0 makes the
    dielectric layer's F0 zero, so Cycles builds no specular closure and the layer takes no light
    from the subsurface one beneath; Coat and Sheen weights 0. Cycles' kernel clamps v2's base
    colour to 1 (`clamped_base_color`): see `light_scale_for`.
    """
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.location = location
    if PRINCIPLED_V2 and method == "RANDOM_WALK_FIXED_RADIUS":
        # 4.0 dropped the fixed-radius walk; its nearest is the plain random walk.
        method = "RANDOM_WALK"
    bsdf.subsurface_method = method
    bsdf.inputs["Roughness"].default_value = 0.0
    if PRINCIPLED_V2:
        bsdf.inputs["Subsurface Weight"].default_value = 1.0
        bsdf.inputs["Subsurface Scale"].default_value = 1.0
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
        bsdf.inputs["Coat Weight"].default_value = 0.0
        bsdf.inputs["Sheen Weight"].default_value = 0.0
        bsdf.inputs["Metallic"].default_value = 0.0
        bsdf.inputs["Transmission Weight"].default_value = 0.0
    else:
        bsdf.inputs["Subsurface"].default_value = 1.0
        bsdf.inputs["Specular"].default_value = 0.0
        bsdf.inputs["Sheen"].default_value = 0.0
    return bsdf


def albedo_of(nt, scene, colour_name, y):
    """Attribute(colour) x alpha x the exit Fresnel factor: a lobe's Subsurface Color."""
    colour = attribute_node(nt, colour_name, (-600, y + 200))
    alpha = attribute_node(nt, "alpha", (-600, y))
    times_alpha = nt.nodes.new("ShaderNodeVectorMath")
    times_alpha.operation = "MULTIPLY"
    times_alpha.label = "colour x alpha"
    times_alpha.location = (-300, y + 150)
    nt.links.new(colour.outputs["Color"], times_alpha.inputs[0])
    nt.links.new(alpha.outputs["Color"], times_alpha.inputs[1])
    albedo = times_alpha.outputs["Vector"]
    eta = scene.get("exit_fresnel_ior")
    if eta:
        # Fresnel transmission out of the surface towards the viewer, relative to normal
        # incidence: (1 - F(theta_o)) / (1 - F(0)), as subsurf's renderer applies it.
        fres = nt.nodes.new("ShaderNodeFresnel")
        fres.inputs["IOR"].default_value = eta
        fres.location = (-300, y - 50)
        one_minus = nt.nodes.new("ShaderNodeMath")
        one_minus.operation = "SUBTRACT"
        one_minus.inputs[0].default_value = 1.0
        one_minus.location = (-100, y - 50)
        nt.links.new(fres.outputs["Fac"], one_minus.inputs[1])
        f0 = ((eta - 1.0) / (eta + 1.0)) ** 2
        relative = nt.nodes.new("ShaderNodeMath")
        relative.operation = "MULTIPLY"
        relative.inputs[1].default_value = 1.0 / (1.0 - f0)
        relative.label = "F_t(theta_o) / F_t(0)"
        relative.location = (100, y - 50)
        nt.links.new(one_minus.outputs["Value"], relative.inputs[0])
        scale = nt.nodes.new("ShaderNodeVectorMath")
        scale.operation = "SCALE"
        scale.location = (300, y + 150)
        nt.links.new(albedo, scale.inputs[0])
        nt.links.new(relative.outputs["Value"], scale.inputs["Scale"])
        albedo = scale.outputs["Vector"]
    k = scene.get("_light_scale", 1.0)
    if k != 1.0:
        # Principled v2 clamps the albedo to 1: the material holds albedo / k, the lights k.
        down = nt.nodes.new("ShaderNodeVectorMath")
        down.operation = "SCALE"
        down.label = "1 / light scale"
        down.location = (450, y + 150)
        nt.links.new(albedo, down.inputs[0])
        down.inputs["Scale"].default_value = 1.0 / k
        albedo = down.outputs["Vector"]
    return albedo


def lobe(nt, scene, colour_name, radius_name, y):
    """One Principled BSDF subsurface lobe fed by its colour and radius attributes."""
    bsdf = principled(nt, scene["method"], (600, y))
    albedo = albedo_of(nt, scene, colour_name, y)
    radius = attribute_node(nt, radius_name, (-600, y - 250))
    if not PRINCIPLED_V2:
        nt.links.new(albedo, bsdf.inputs["Subsurface Color"])
    nt.links.new(albedo, bsdf.inputs["Base Color"])
    nt.links.new(radius.outputs["Vector"], bsdf.inputs["Subsurface Radius"])
    return bsdf


def empty_material(name):
    """A new material with an empty node tree but its output node: (material, tree, output)."""
    mat = bpy.data.materials.new(name)
    if VERSION < (5, 0):
        # From 5.0 a material is always its node tree.
        mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    out.location = (1100, 0)
    return mat, nt, out


def build_material(scene):
    mat, nt, out = empty_material("subsurf material")
    near = lobe(nt, scene, "subsurface_colour", "subsurface_radius", 0)
    if scene.get("lobes", 1) == 2:
        # Two lobes: the slow Principled BSDF mixed in by the lobe_mix attribute (the slow
        # lobe's share of the light); Cycles samples the two BSSRDF closures by weight.
        slow = lobe(nt, scene, "subsurface_colour_slow", "subsurface_radius_slow", -800)
        mix = nt.nodes.new("ShaderNodeMixShader")
        mix.location = (900, 0)
        fac = attribute_node(nt, "lobe_mix", (600, 300))
        nt.links.new(fac.outputs["Fac"], mix.inputs["Fac"])
        nt.links.new(near.outputs["BSDF"], mix.inputs[1])
        nt.links.new(slow.outputs["BSDF"], mix.inputs[2])
        nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    else:
        nt.links.new(near.outputs["BSDF"], out.inputs["Surface"])
    return mat


def build_lights(sc, lights, hidden=False, scale=1.0):
    from mathutils import Matrix
    for k, l in enumerate(lights):
        name = "%s %d" % (l["type"].lower(), k)
        if l["type"] == "POINT":
            data = bpy.data.lights.new(name, "POINT")
            data.energy = l["power"] * scale
            data.shadow_soft_size = 0.0
        elif l["type"] == "SPOT":
            data = bpy.data.lights.new(name, "SPOT")
            data.energy = l["power"] * scale
            data.shadow_soft_size = 0.0
            data.spot_size = l["spot_size"]
            data.spot_blend = l["spot_blend"]
        else:
            data = bpy.data.lights.new(name, "SUN")
            data.energy = l["strength"] * scale
            data.angle = 0.0
        data.color = l["colour"]
        obj = bpy.data.objects.new(name, data)
        obj.matrix_world = Matrix(l["matrix_world"])
        if hidden:
            # A scan's laser: lights the object, never seen by the camera.
            obj.visible_camera = False
        sc.collection.objects.link(obj)


def build_volume_mesh(scene):
    mesh = bpy.data.meshes.new("subsurf volume")
    mesh.from_pydata([tuple(v) for v in scene["vertices_m"]], [],
                     [tuple(t) for t in scene["triangles"]])
    mesh.update(calc_edges=True)
    mesh.validate()
    return mesh


def grid_images(grid):
    """The cells' Color and Absorption Color as float images: cell (x, y, z) at pixel
    (x + nx z, y), so that one 2D lookup with closest interpolation reads one cell."""
    nx, ny, nz = grid["dims"]
    w, h = nx * nz, ny
    out = []
    for key in ("color", "absorption_color"):
        img = bpy.data.images.new("subsurf " + key, w, h, alpha=True, float_buffer=True)
        img.colorspace_settings.name = "Non-Color"
        px = [0.0] * (4 * w * h)
        for k, cell in enumerate(grid["cells"]):
            x, y, z = k % nx, (k // nx) % ny, k // (nx * ny)
            p = 4 * (y * w + x + nx * z)
            px[p:p + 3] = cell[key]
            px[p + 3] = 1.0
        img.pixels = px
        img.pack()
        out.append(img)
    return out


def grid_lookup(nt, grid, images):
    """Nodes reading the cell at the shading point: index = clamp(floor((p - origin) / cell)),
    the image coordinate of that cell's pixel centre; returns the two images' Color outputs."""
    nx, ny, nz = grid["dims"]
    tc = nt.nodes.new("ShaderNodeTexCoord")
    tc.location = (-1400, -400)

    def vmath(op, a, b=None, loc=(0, 0)):
        n = nt.nodes.new("ShaderNodeVectorMath")
        n.operation = op
        n.location = loc
        nt.links.new(a, n.inputs[0])
        if b is not None:
            n.inputs[1].default_value = b
        return n.outputs["Vector"]

    p = vmath("SUBTRACT", tc.outputs["Object"], grid["origin_m"], (-1200, -400))
    p = vmath("DIVIDE", p, grid["cell_m"], (-1050, -400))
    p = vmath("FLOOR", p, None, (-900, -400))
    p = vmath("MAXIMUM", p, (0.0, 0.0, 0.0), (-750, -400))
    p = vmath("MINIMUM", p, (nx - 1, ny - 1, nz - 1), (-600, -400))
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    sep.location = (-450, -400)
    nt.links.new(p, sep.inputs[0])

    def math(op, a, b, c=None, loc=(0, 0)):
        n = nt.nodes.new("ShaderNodeMath")
        n.operation = op
        n.location = loc
        nt.links.new(a, n.inputs[0])
        n.inputs[1].default_value = b
        if c is not None:
            n.inputs[2].default_value = c
        return n.outputs["Value"]

    # u = (x + nx z + 0.5) / (nx nz), v = (y + 0.5) / ny
    col = math("MULTIPLY_ADD", sep.outputs["Z"], float(nx), 0.5, (-300, -300))
    add = nt.nodes.new("ShaderNodeMath")
    add.operation = "ADD"
    add.location = (-150, -300)
    nt.links.new(sep.outputs["X"], add.inputs[0])
    nt.links.new(col, add.inputs[1])
    u = math("DIVIDE", add.outputs["Value"], float(nx * nz), None, (0, -300))
    v = math("MULTIPLY_ADD", sep.outputs["Y"], 1.0 / ny, 0.5 / ny, (0, -450))
    uv = nt.nodes.new("ShaderNodeCombineXYZ")
    uv.location = (150, -400)
    nt.links.new(u, uv.inputs["X"])
    nt.links.new(v, uv.inputs["Y"])
    outs = []
    for k, img in enumerate(images):
        t = nt.nodes.new("ShaderNodeTexImage")
        t.location = (300, -300 - 250 * k)
        t.image = img
        t.interpolation = "Closest"
        t.extension = "EXTEND"
        nt.links.new(uv.outputs["Vector"], t.inputs["Vector"])
        outs.append(t.outputs["Color"])
    return outs


def write_vdb(folder, grid):
    """The cells as OpenVDB grids for other renderers, where this Blender carries the module."""
    # Blender's own Python carries the module (`openvdb` from 4.4, `pyopenvdb` before); `bpy`
    # as a module keeps it in Blender's site-packages, outside the venv's path.
    import glob
    local = bpy.utils.resource_path("LOCAL")
    sys.path.extend(glob.glob(os.path.join(local, "python", "lib", "python3*", "site-packages")))
    vdb = None
    for name in ("openvdb", "pyopenvdb"):
        try:
            vdb = __import__(name)
            break
        except ImportError:
            pass
    if vdb is None:
        print("SUBSURF no openvdb module in this Blender: medium.vdb not written")
        return
    nx, ny, nz = grid["dims"]
    sx, sy, sz = grid["cell_m"]
    ox, oy, oz = grid["origin_m"]
    # Index (i, j, k) covers [origin + i cell, origin + (i + 1) cell): the voxel's centre.
    m = [[sx, 0, 0, 0], [0, sy, 0, 0], [0, 0, sz, 0],
         [ox + 0.5 * sx, oy + 0.5 * sy, oz + 0.5 * sz, 1]]
    grids = []
    for name, kind in (("density", vdb.FloatGrid), ("color", vdb.Vec3SGrid),
                       ("absorption_color", vdb.Vec3SGrid)):
        g = kind()
        g.name = name
        g.transform = vdb.createLinearTransform(m)
        acc = g.getAccessor()
        for k, cell in enumerate(grid["cells"]):
            ijk = (k % nx, (k // nx) % ny, k // (nx * ny))
            value = cell[name]
            acc.setValueOn(ijk, tuple(value) if isinstance(value, list) else value)
        grids.append(g)
    path = os.path.join(folder, "medium.vdb")
    vdb.write(path, grids=grids)
    print("SUBSURF wrote %s" % path)


def build_volume_material(scene, folder):
    mat, nt, out = empty_material("subsurf volume")
    pv = nt.nodes.new("ShaderNodeVolumePrincipled")
    pv.location = (700, 0)
    m = scene["medium"]
    pv.inputs["Density"].default_value = m["density"]
    pv.inputs["Color"].default_value = tuple(m["color"]) + (1.0,)
    pv.inputs["Absorption Color"].default_value = tuple(m["absorption_color"]) + (1.0,)
    pv.inputs["Anisotropy"].default_value = scene["anisotropy"]
    grid = scene.get("grid")
    if grid:
        pv.inputs["Density"].default_value = grid["cells"][0]["density"]
        colour, absorption = grid_lookup(nt, grid, grid_images(grid))
        nt.links.new(colour, pv.inputs["Color"])
        nt.links.new(absorption, pv.inputs["Absorption Color"])
        write_vdb(folder, grid)
    nt.links.new(pv.outputs["Volume"], out.inputs["Volume"])
    b = scene["boundary"]
    if b["kind"] == "glass":
        glass = nt.nodes.new("ShaderNodeBsdfGlass")
        glass.location = (700, 400)
        glass.distribution = "GGX"
        glass.inputs["Roughness"].default_value = b["roughness"]
        glass.inputs["IOR"].default_value = b["ior"]
        nt.links.new(glass.outputs["BSDF"], out.inputs["Surface"])
    # Index-matched: no surface shader, so Cycles' rays cross the surface unbent.
    if hasattr(mat, "cycles") and hasattr(mat.cycles, "homogeneous_volume"):
        mat.cycles.homogeneous_volume = not grid
    return mat


def frame_scene(folder, k):
    """Scan frame k's entry of frames.json and the file's render settings."""
    with open(os.path.join(folder, "frames.json")) as f:
        frames = json.load(f)
    for entry in frames["frames"]:
        if entry["frame"] == k:
            return frames, entry
    raise SystemExit("frames.json has no scene for frame %d" % k)


def build_camera(sc, c):
    from mathutils import Matrix
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = c["sensor_width"]
    data.lens = c["lens"]
    data.shift_x = c["shift_x"]
    data.shift_y = c["shift_y"]
    data.clip_start = c["clip_start"]
    data.clip_end = c["clip_end"]
    obj = bpy.data.objects.new("camera", data)
    obj.matrix_world = Matrix(c["matrix_world"])
    sc.collection.objects.link(obj)
    sc.camera = obj
    sc.render.resolution_x = c["width"]
    sc.render.resolution_y = c["height"]
    sc.render.resolution_percentage = 100
    sc.render.pixel_aspect_x = 1.0
    sc.render.pixel_aspect_y = 1.0


# --- The measurement of Cycles' subsurface response (`--measure OUT.json`) -------------------
#
# A slab much larger and thicker than the profile's reach, lit from straight above by a sun of
# strength 1 on one half (x < 0; a shadow caster the camera does not see covers the other), seen
# by an orthographic camera from above across the edge. The image along x is the profile's edge
# response, plateau x (1 - F(x)) on the lit side and plateau x F(x) on the dark one, with F the
# share of a point's scattered light that lands beyond a line at distance x. Fitting the
# Christensen-Burley shape (d and the plateau) to it gives, per method and albedo, what the
# export assumes: d / radius (1/(4 pi) in 3.4's kernel) and plateau x pi / albedo (1: a point
# scatters exactly its albedo). The material is the export's own (`principled`).

MEASURE_ALBEDOS = ((0.1, 0.5, 0.8), (0.95, 0.3, 0.65))
MEASURE_HALF_WIDTH = 0.8  # metres seen either side of the edge; the radius is 1 m
MEASURE_PIXELS = 160


def burley_edge(x, d):
    """F(x): the share of a unit Burley profile (shape d, truncated at 16 d and renormalised)
    beyond a line at distance x >= 0: the integral over r > x of 2 r p(r) arccos(x / r)."""
    rmax = 16.0 * d
    if x >= rmax:
        return 0.0
    cdf = 1.0 - 0.25 * math.exp(-16.0) - 0.75 * math.exp(-16.0 / 3.0)
    lo = max(x, 1e-6 * d)
    n = 200
    total = 0.0
    a, b = math.log(lo), math.log(rmax)
    h = (b - a) / n
    for k in range(n + 1):
        r = math.exp(a + k * h)
        p = (math.exp(-r / d) + math.exp(-r / (3.0 * d))) / (8.0 * math.pi * d * r) / cdf
        f = 2.0 * r * p * math.acos(min(1.0, x / r)) * r  # d r = r d ln r
        total += f * (1.0 if 0 < k < n else 0.5)
    return total * h


def fit_edge(xs, ys):
    """The Burley shape d and plateau P best fitting the edge response ys at xs (x < 0 lit):
    least squares in P for each d (closed form), golden section over ln d."""
    def model(d):
        return [1.0 - burley_edge(-x, d) if x < 0 else burley_edge(x, d) for x in xs]

    def cost(ln_d):
        m = model(math.exp(ln_d))
        p = sum(a * b for a, b in zip(m, ys)) / max(sum(a * a for a in m), 1e-30)
        return sum((p * a - b) ** 2 for a, b in zip(m, ys)), p

    grid = [math.log(0.005) + k * (math.log(0.5) - math.log(0.005)) / 24 for k in range(25)]
    best = min(range(len(grid)), key=lambda k: cost(grid[k])[0])
    lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    for _ in range(40):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        if cost(a)[0] < cost(b)[0]:
            hi = b
        else:
            lo = a
    ln_d = 0.5 * (lo + hi)
    c, p = cost(ln_d)
    rms = math.sqrt(c / len(xs)) / max(p, 1e-30)
    return math.exp(ln_d), p, rms


def measure_scene(method, albedo, samples, threads, seed):
    """Renders the half-lit slab for one method and three albedos (one per channel); returns the
    edge response per channel as (xs, [ys_r, ys_g, ys_b])."""
    from mathutils import Matrix
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    mesh = bpy.data.meshes.new("slab")
    # A box 8 m across and 4 m deep, its top face at z = 0.
    v = [(x, y, z) for z in (-4.0, 0.0) for y in (-4.0, 4.0) for x in (-4.0, 4.0)]
    f = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    mesh.from_pydata(v, [], f)
    mesh.update()
    mat = bpy.data.materials.new("measured")
    if VERSION < (5, 0):
        mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = principled(nt, method, (0, 0))
    colour = tuple(albedo) + (1.0,)
    bsdf.inputs["Base Color"].default_value = colour
    if not PRINCIPLED_V2:
        bsdf.inputs["Subsurface Color"].default_value = colour
    bsdf.inputs["Subsurface Radius"].default_value = (1.0, 1.0, 1.0)
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    mesh.materials.append(mat)
    slab = bpy.data.objects.new("slab", mesh)
    sc.collection.objects.link(slab)
    # The shadow caster over x > 0, unseen by the camera.
    cover = bpy.data.meshes.new("cover")
    cover.from_pydata([(0.0, -5.0, 1.0), (6.0, -5.0, 1.0), (6.0, 5.0, 1.0), (0.0, 5.0, 1.0)],
                      [], [(0, 1, 2, 3)])
    # Black: light the slab scatters upwards must not come back from it.
    black = bpy.data.materials.new("black")
    if VERSION < (5, 0):
        black.use_nodes = True
    bnt = black.node_tree
    for n in list(bnt.nodes):
        bnt.nodes.remove(n)
    bout = bnt.nodes.new("ShaderNodeOutputMaterial")
    dark = bnt.nodes.new("ShaderNodeBsdfDiffuse")
    dark.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    bnt.links.new(dark.outputs["BSDF"], bout.inputs["Surface"])
    cover.materials.append(black)
    cover_obj = bpy.data.objects.new("cover", cover)
    cover_obj.visible_camera = False
    sc.collection.objects.link(cover_obj)
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = 1.0
    sun.angle = 0.0
    sun_obj = bpy.data.objects.new("sun", sun)
    sc.collection.objects.link(sun_obj)
    cam = bpy.data.cameras.new("camera")
    cam.type = "ORTHO"
    cam.ortho_scale = 2.0 * MEASURE_HALF_WIDTH
    cam_obj = bpy.data.objects.new("camera", cam)
    cam_obj.matrix_world = Matrix.Translation((0.0, 0.0, 3.0))
    sc.collection.objects.link(cam_obj)
    sc.camera = cam_obj
    world = bpy.data.worlds.new("black")
    if VERSION < (5, 0):
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sc.world = world
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = samples
    sc.cycles.seed = seed
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.sample_clamp_direct = 0.0
    sc.cycles.sample_clamp_indirect = 0.0
    sc.cycles.pixel_filter_type = "BOX"
    sc.cycles.filter_width = 0.01
    if threads:
        sc.render.threads_mode = "FIXED"
        sc.render.threads = threads
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.render.resolution_x = MEASURE_PIXELS
    sc.render.resolution_y = 4
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    import tempfile
    path = os.path.join(tempfile.mkdtemp(prefix="subsurf-measure-"), "edge.exr")
    sc.render.filepath = path
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(path)
    w, h = img.size
    px = list(img.pixels)
    xs = [(-MEASURE_HALF_WIDTH + (i + 0.5) * 2.0 * MEASURE_HALF_WIDTH / w) for i in range(w)]
    ys = [[sum(px[4 * (j * w + i) + c] for j in range(h)) / h for i in range(w)]
          for c in range(3)]
    os.remove(path)
    return xs, ys


def measure(out_path, samples, threads, seed):
    """Measures every method's edge response at MEASURE_ALBEDOS; writes out_path (JSON)."""
    methods = ["BURLEY", "RANDOM_WALK",
               "RANDOM_WALK_SKIN" if PRINCIPLED_V2 else "RANDOM_WALK_FIXED_RADIUS"]
    rows = []
    for method in methods:
        for albedo in MEASURE_ALBEDOS:
            xs, ys = measure_scene(method, albedo, samples, threads, seed)
            for c in range(3):
                d, plateau, rms = fit_edge(xs, ys[c])
                rows.append({"method": method, "albedo": albedo[c], "d_per_radius": d,
                             "plateau_pi_per_albedo": plateau * math.pi / albedo[c],
                             "shape_rms": rms})
                print("SUBSURF measured %s albedo %.2f: d/radius %.4f, plateau pi/albedo %.4f, "
                      "shape rms %.4f" % (method, albedo[c], d, plateau * math.pi / albedo[c],
                                          rms))
    with open(out_path, "w") as f:
        json.dump({"format": "subsurf-cycles-response/1", "blender": bpy.app.version_string,
                   "version": list(VERSION), "samples": samples, "radius_m": 1.0,
                   "half_width_m": MEASURE_HALF_WIDTH, "pixels": MEASURE_PIXELS,
                   "rows": rows}, f, indent=1)
    print("SUBSURF wrote %s" % out_path)


def main():
    opts = parse_args()
    if opts["measure"]:
        measure(opts["measure"], opts["samples"] or 256, opts["threads"], opts["seed"])
        return
    folder = opts["dir"]
    with open(os.path.join(folder, "scene.json")) as f:
        scene = json.load(f)
    volume = scene.get("kind") == "volume"
    if volume and opts["compare"]:
        raise SystemExit("--compare is for an empirical model's export, not a volume's")
    doc, blob = (None, None) if volume else read_glb(os.path.join(folder, scene["mesh"]))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.name = "subsurf"
    sc.unit_settings.system = "METRIC"
    sc.unit_settings.scale_length = 1.0
    sc.unit_settings.length_unit = "MILLIMETERS"
    if volume:
        # A medium's light is rendered at its own power: no scale.
        mesh, k = build_volume_mesh(scene), 1.0
        print("SUBSURF Blender %s, Principled Volume" % bpy.app.version_string)
        mat = build_volume_material(scene, folder)
    else:
        mesh, largest = build_mesh(doc, blob)
        k = light_scale_for(largest)
        scene["_light_scale"] = k
        print("SUBSURF Blender %s, Principled %s, light scale %.6g"
              % (bpy.app.version_string, "v2" if PRINCIPLED_V2 else "v1", k))
        mat = build_material(scene)
        mat["subsurf_light_scale"] = k
    mesh.materials.append(mat)
    obj = bpy.data.objects.new("subsurf model", mesh)
    sc.collection.objects.link(obj)
    frames, entry = (None, None)
    if opts["frame"] is not None:
        from mathutils import Matrix
        frames, entry = frame_scene(folder, opts["frame"])
        obj.matrix_world = Matrix(entry["object_matrix"])
        build_lights(sc, [entry["laser"]], hidden=True, scale=k)
        build_camera(sc, entry["camera"])
    else:
        build_lights(sc, scene["lights"], scale=k)
        build_camera(sc, scene["camera"])
    world = bpy.data.worlds.new("black")
    if VERSION < (5, 0):
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sc.world = world
    r = scene["render"]
    sc.render.engine = "CYCLES"
    sc.render.film_transparent = True
    sc.cycles.device = "CPU"
    sc.cycles.samples = opts["samples"] or (frames["samples"] if frames else r["samples"])
    sc.cycles.seed = opts["seed"]
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    # Clamping would cut the subsurface samples' high weights (biased, darker).
    sc.cycles.sample_clamp_direct = 0.0
    sc.cycles.sample_clamp_indirect = 0.0
    if volume:
        # Every scattering event is a volume bounce; a glass boundary's crossings are
        # transmission bounces; an index-matched one's are transparent ones.
        n = r["bounces"]
        sc.cycles.max_bounces = n
        sc.cycles.volume_bounces = n
        sc.cycles.transmission_bounces = n
        sc.cycles.glossy_bounces = n
        sc.cycles.transparent_max_bounces = n
        sc.cycles.diffuse_bounces = 0
    if opts["threads"]:
        sc.render.threads_mode = "FIXED"
        sc.render.threads = opts["threads"]
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.view_settings.exposure = 0.0
    sc.view_settings.gamma = 1.0
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_mode = "RGBA"
    sc.render.image_settings.color_depth = "32"
    sc.render.image_settings.exr_codec = "ZIP"
    if entry is not None:
        # A camera pixel integrates its own area: a box filter one pixel wide.
        sc.cycles.pixel_filter_type = "BOX"
        sc.cycles.filter_width = frames["filter_width"]
        if entry.get("border"):
            # Only where the frame is read: the rest of the image stays black, full size.
            sc.render.use_border = True
            sc.render.use_crop_to_border = False
            (sc.render.border_min_x, sc.render.border_max_x,
             sc.render.border_min_y, sc.render.border_max_y) = entry["border"]
    blend = opts["blend"] or (
        os.path.join(folder, "frames", "%06d.blend" % entry["frame"]) if entry is not None
        else os.path.join(folder, scene["blend"]))
    os.makedirs(os.path.dirname(os.path.abspath(blend)), exist_ok=True)
    # A frame's scene is written again by its second seed's run: no `.blend1` backups.
    bpy.context.preferences.filepaths.save_version = 0
    bpy.ops.wm.save_as_mainfile(filepath=os.path.abspath(blend))
    print("SUBSURF wrote %s" % blend)
    if opts["render"]:
        if opts["compare"]:
            # What subsurf's renderer computes: light scattered once through the material from
            # the lights (no light bounced between surfaces), each pixel sampled at its centre.
            sc.cycles.pixel_filter_type = "BOX"
            sc.cycles.filter_width = r["compare_filter_width"]
            sc.cycles.max_bounces = r["compare_max_bounces"]
            sc.cycles.diffuse_bounces = r["compare_diffuse_bounces"]
            sc.cycles.glossy_bounces = 0
            sc.cycles.transmission_bounces = 0
            sc.cycles.volume_bounces = 0
            sc.cycles.transparent_max_bounces = 0
            sc.cycles.caustics_reflective = False
            sc.cycles.caustics_refractive = False
        sc.render.filepath = os.path.abspath(opts["render"])
        bpy.ops.render.render(write_still=True)
        print("SUBSURF rendered %s" % opts["render"])


if __name__ == "__main__":
    main()
