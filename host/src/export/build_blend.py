"""Builds the Blender scene of a `subsurf export --format blender` folder.

Run it in Blender 3.4 or newer, in the export folder or with its path:

    blender -b --factory-startup --python build_blend.py                  # writes model.blend
    blender -b --factory-startup --python build_blend.py -- --render cycles.exr --samples 64
    blender --python build_blend.py                                       # opens the scene

It reads `model.glb` (the mesh, in metres, with the converted parameters as custom attributes:
Blender 3.4's glTF importer drops those, so this script reads the file itself) and `scene.json`
(lights, camera, render settings), and builds:

- the mesh with its normals and four point attributes: `subsurface_colour` (total diffuse
  reflectance per channel), `subsurface_radius` (metres), `alpha` (the modulation texture, Eq. 2/6
  of Fuchs et al. 2005) and `conversion_log_e`;
- the material: Attribute nodes feeding a Principled BSDF (Subsurface 1, method Christensen-Burley,
  Specular 0, Roughness 0): Subsurface Color = subsurface_colour x alpha x the Fresnel
  transmission out of the surface relative to normal incidence, Subsurface Radius =
  subsurface_radius (Blender scales the radius by the Subsurface factor, here 1); with two lobes
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


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    opts = {"dir": HERE, "blend": None, "render": None, "samples": None, "seed": 0,
            "threads": 0, "compare": False, "frame": None}
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--compare":
            opts["compare"] = True
            i += 1
            continue
        if a not in ("--dir", "--blend", "--render", "--samples", "--seed", "--threads",
                     "--frame"):
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
    # The model's own normals, as the subsurf renderer shades with them.
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
        a = mesh.attributes.new(name, kind, "POINT")
        if kind == "FLOAT_COLOR":
            rgba = array.array("f", [1.0]) * (4 * nv)
            for c in range(3):
                rgba[c::4] = values[c::3]
            a.data.foreach_set("color", rgba)
        else:
            a.data.foreach_set("vector", values)
    return mesh


def attribute_node(nt, name, location):
    n = nt.nodes.new("ShaderNodeAttribute")
    n.attribute_type = "GEOMETRY"
    n.attribute_name = name
    n.location = location
    return n


def principled(nt, method, location):
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.location = location
    bsdf.subsurface_method = method
    bsdf.inputs["Subsurface"].default_value = 1.0
    bsdf.inputs["Specular"].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 0.0
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
    return albedo


def lobe(nt, scene, colour_name, radius_name, y):
    """One Principled BSDF subsurface lobe fed by its colour and radius attributes."""
    bsdf = principled(nt, scene["method"], (600, y))
    albedo = albedo_of(nt, scene, colour_name, y)
    radius = attribute_node(nt, radius_name, (-600, y - 250))
    nt.links.new(albedo, bsdf.inputs["Subsurface Color"])
    nt.links.new(albedo, bsdf.inputs["Base Color"])
    nt.links.new(radius.outputs["Vector"], bsdf.inputs["Subsurface Radius"])
    return bsdf


def build_material(scene):
    mat = bpy.data.materials.new("subsurf material")
    mat.use_nodes = True
    nt = mat.node_tree
    for n in list(nt.nodes):
        nt.nodes.remove(n)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    out.location = (1100, 0)
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


def build_lights(sc, lights, hidden=False):
    from mathutils import Matrix
    for k, l in enumerate(lights):
        name = "%s %d" % (l["type"].lower(), k)
        if l["type"] == "POINT":
            data = bpy.data.lights.new(name, "POINT")
            data.energy = l["power"]
            data.shadow_soft_size = 0.0
        elif l["type"] == "SPOT":
            data = bpy.data.lights.new(name, "SPOT")
            data.energy = l["power"]
            data.shadow_soft_size = 0.0
            data.spot_size = l["spot_size"]
            data.spot_blend = l["spot_blend"]
        else:
            data = bpy.data.lights.new(name, "SUN")
            data.energy = l["strength"]
            data.angle = 0.0
        data.color = l["colour"]
        obj = bpy.data.objects.new(name, data)
        obj.matrix_world = Matrix(l["matrix_world"])
        if hidden:
            # A scan's laser: lights the object, never seen by the camera.
            obj.visible_camera = False
        sc.collection.objects.link(obj)


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


def main():
    opts = parse_args()
    folder = opts["dir"]
    with open(os.path.join(folder, "scene.json")) as f:
        scene = json.load(f)
    doc, blob = read_glb(os.path.join(folder, scene["mesh"]))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.name = "subsurf"
    sc.unit_settings.system = "METRIC"
    sc.unit_settings.scale_length = 1.0
    sc.unit_settings.length_unit = "MILLIMETERS"
    mesh = build_mesh(doc, blob)
    mesh.materials.append(build_material(scene))
    obj = bpy.data.objects.new("subsurf model", mesh)
    sc.collection.objects.link(obj)
    frames, entry = (None, None)
    if opts["frame"] is not None:
        from mathutils import Matrix
        frames, entry = frame_scene(folder, opts["frame"])
        obj.matrix_world = Matrix(entry["object_matrix"])
        build_lights(sc, [entry["laser"]], hidden=True)
        build_camera(sc, entry["camera"])
    else:
        build_lights(sc, scene["lights"])
        build_camera(sc, scene["camera"])
    world = bpy.data.worlds.new("black")
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
