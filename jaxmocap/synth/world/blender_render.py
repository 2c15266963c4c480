"""Render a test-world scene file with Blender Cycles. **Runs inside a Python that has ``bpy``**
(Blender as a module), as ``python blender_render.py SCENE.npz OUT_DIR``; it imports nothing
from jaxmocap (``bpy`` pins its own NumPy, so it usually lives in another environment than
this library: ``jaxmocap synth-world --blender-python PATH``).

The scene file (:func:`jaxmocap.synth.world.cycles.export_scene`) holds every visible MuJoCo
geom of the sequence as a triangle mesh in its own frame with its albedo (linear RGB) and
material class, the pose of each geom per frame (static geoms once), the lamps, the cameras
(OpenCV ``K``, ``R``, ``t``) and the render settings. What Blender adds that the MuJoCo
renderer does not have, and that this project did not write: path-traced light (area and spot
lamps of black-body colour, soft shadows, indirect light between the body, the room and the
props), physically based materials (Principled BSDF: cloth sheen, skin subsurface, glossy
props), Cycles' motion blur over the shutter interval (object motion interpolated between the
per-frame keyframes), Cycles' sampling noise after OpenImageDenoise, and Blender's view
transform (AgX) as the camera's tone curve. Output: ``OUT_DIR/c<camera>_<frame>.png`` (8-bit
sRGB after the view transform) and ``OUT_DIR/render.json`` (Blender's version, the seconds per
image).
"""

import json
import math
import sys
import time
from pathlib import Path

# Run by path, this file's folder is sys.path[0]: its ``cycles.py`` would shadow Blender's own
# ``cycles`` add-on (the Cycles engine would then be missing).
if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
    del sys.path[0]

import bpy  # noqa: E402
import mathutils  # noqa: E402
import numpy as np  # noqa: E402

ROUGHNESS = {"cloth": 0.85, "skin": 0.5, "gloss": 0.12, "matte": 0.9, "floor": 0.6,
             "wall": 0.8}


def _material(name: str, kind: str, rgb, checker=None):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*[float(v) for v in rgb], 1.0)
    bsdf.inputs["Roughness"].default_value = ROUGHNESS[kind]
    if kind == "cloth":
        bsdf.inputs["Sheen Weight"].default_value = 0.4
        bsdf.inputs["Specular IOR Level"].default_value = 0.3
    elif kind == "skin":
        bsdf.inputs["Subsurface Weight"].default_value = 0.15
        bsdf.inputs["Subsurface Radius"].default_value = (0.05, 0.02, 0.01)
    elif kind == "gloss":
        bsdf.inputs["Coat Weight"].default_value = 0.6
    if checker is not None:  # the floor: a checker of two albedos, 6 x 6 over 16 m
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Color1"].default_value = (*[float(v) for v in checker[0]], 1.0)
        tex.inputs["Color2"].default_value = (*[float(v) for v in checker[1]], 1.0)
        tex.inputs["Scale"].default_value = 6.0
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _emission(name: str, value: float):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.remove(nt.nodes["Principled BSDF"])
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (value, value, value, 1.0)
    nt.links.new(em.outputs["Emission"], nt.nodes["Material Output"].inputs["Surface"])
    return mat


def _mesh_object(name: str, verts: np.ndarray, faces: np.ndarray, mat):
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(map(float, v)) for v in verts], [], [tuple(map(int, f))
                                                             for f in faces])
    me.update()
    for poly in me.polygons:
        poly.use_smooth = True
    ob = bpy.data.objects.new(name, me)
    ob.data.materials.append(mat)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _set_pose(ob, pos, mat3):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = mat3, pos
    ob.matrix_world = mathutils.Matrix([list(map(float, row)) for row in m])


def _blackbody(light, kelvin: float) -> None:
    """The lamp's colour from Blender's black-body node (its colour science, not ours)."""
    light.use_nodes = True
    nt = light.node_tree
    em = nt.nodes["Emission"]
    bb = nt.nodes.new("ShaderNodeBlackbody")
    bb.inputs["Temperature"].default_value = float(kelvin)
    nt.links.new(bb.outputs["Color"], em.inputs["Color"])
    em.inputs["Strength"].default_value = 1.0  # the power is the lamp's energy


def main(scene_path: str, out_dir: str) -> None:
    s = np.load(scene_path, allow_pickle=False)
    meta = json.loads(str(s["meta"]))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = int(meta["samples"])
    sc.cycles.use_adaptive_sampling = True
    sc.cycles.use_denoising = True
    sc.cycles.max_bounces = 4
    sc.cycles.seed = int(meta["seed"]) % (2**31)
    sc.render.threads_mode = "FIXED"
    sc.render.threads = int(meta["threads"])
    sc.render.use_persistent_data = True
    sc.render.resolution_x, sc.render.resolution_y = int(meta["width"]), int(meta["height"])
    sc.render.resolution_percentage = 100
    sc.render.fps = max(1, round(float(meta["fps"])))
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGB"
    sc.render.image_settings.color_depth = "8"
    sc.view_settings.view_transform = "AgX"
    sc.view_settings.look = "AgX - Punchy"
    sc.view_settings.exposure = float(meta["exposure"])
    sc.render.use_motion_blur = bool(meta["motion_blur"])
    sc.render.motion_blur_shutter = float(meta["shutter"])
    world = bpy.data.worlds.new("room")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.55, 0.55, 0.55, 1)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = float(meta["ambient"])
    sc.world = world

    silhouette = bool(meta.get("silhouette", False))
    if silhouette:  # a check of geometry and camera: the body white, the rest black, exactly
        sc.view_settings.view_transform, sc.view_settings.look = "Standard", "None"
        sc.view_settings.exposure = 0.0
        sc.cycles.samples, sc.cycles.use_denoising = 1, False
        sc.cycles.filter_width = 0.01
        sc.render.use_motion_blur = False
    mats = {}
    n_frames = int(meta["n_frames"])
    for i, g in enumerate(meta["geoms"]):
        key = (g["material"], tuple(np.round(s[f"rgb{i}"], 4)))
        if silhouette:
            key = ("emit", g["body"])
            if key not in mats:
                mats[key] = _emission(f"m{len(mats)}", 1.0 if g["body"] else 0.0)
        elif key not in mats:
            checker = (s["floor_rgb"][0], s["floor_rgb"][1]) if g["material"] == "floor" else None
            mats[key] = _material(f"m{len(mats)}", g["material"], s[f"rgb{i}"], checker)
        ob = _mesh_object(g["name"], s[f"verts{i}"], s[f"faces{i}"], mats[key])
        if not g["moving"]:
            _set_pose(ob, s[f"pos{i}"], s[f"mat{i}"])
            continue
        pos, rot = s[f"pos{i}"], s[f"mat{i}"]  # (T, 3), (T, 3, 3)
        ob.rotation_mode = "QUATERNION"
        for t in range(n_frames):
            _set_pose(ob, pos[t], rot[t])
            ob.keyframe_insert("location", frame=t + 1)
            ob.keyframe_insert("rotation_quaternion", frame=t + 1)
        if ob.animation_data and ob.animation_data.action:
            for fc in _fcurves(ob.animation_data.action):
                for kp in fc.keyframe_points:
                    kp.interpolation = "LINEAR"

    for k, lamp in enumerate([] if silhouette else meta["lamps"]):
        kind = lamp["kind"]
        data = bpy.data.lights.new(f"lamp{k}", type=kind)
        if kind == "SPOT":
            data.spot_size = math.radians(lamp["cone_deg"])
            data.spot_blend = 0.35
            data.shadow_soft_size = lamp["radius"]
        else:  # AREA: a soft box
            data.shape = "RECTANGLE"
            data.size, data.size_y = lamp["size"], lamp["size"]
        data.energy = float(lamp["watts"])
        _blackbody(data, lamp["kelvin"])
        ob = bpy.data.objects.new(f"lamp{k}", data)
        sc.collection.objects.link(ob)
        pos = np.asarray(lamp["pos"], float)
        z = -np.asarray(lamp["dir"], float)  # Blender lights shine along their -z
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0, 0])
        _set_pose(ob, pos, np.stack([x, np.cross(z, x), z], 1))
        levels = s["levels"][:, k]
        for t in range(n_frames):
            data.energy = float(lamp["watts"] * levels[t])
            data.keyframe_insert("energy", frame=t + 1)
    if silhouette:
        world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sun = bpy.data.lights.new("fill", type="SUN")
    sun.energy = float(meta["fill_sun"])
    sun.angle = math.radians(40.0)  # a broad, soft sky-like fill
    ob = bpy.data.objects.new("fill", sun)
    sc.collection.objects.link(ob)
    d = np.asarray(meta["fill_dir"], float)
    z = -d / np.linalg.norm(d)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    _set_pose(ob, np.zeros(3), np.stack([x, np.cross(z, x), z], 1))

    cams = []
    for c in range(int(meta["n_cameras"])):
        K, R, t = s["K"][c], s["R"][c], s["t"][c]
        data = bpy.data.cameras.new(f"cam{c}")
        data.sensor_fit = "HORIZONTAL"
        data.sensor_width = 36.0
        data.lens = float(K[0, 0]) * 36.0 / float(meta["width"])
        data.shift_x = (float(meta["width"]) / 2 - 0.5 - float(K[0, 2])) / float(meta["width"])
        data.shift_y = (float(K[1, 2]) - float(meta["height"]) / 2 + 0.5) / float(meta["width"])
        data.clip_start, data.clip_end = 0.01, 30.0
        ob = bpy.data.objects.new(f"cam{c}", data)
        sc.collection.objects.link(ob)
        # OpenCV camera: x right, y down, looking along +z; Blender's: y up, looking along -z
        _set_pose(ob, -R.T @ t, R.T @ np.diag([1.0, -1.0, -1.0]))
        cams.append(ob)

    seconds = []
    for t in range(n_frames):
        sc.frame_set(t + 1)
        for c, cam in enumerate(cams):
            sc.camera = cam
            sc.render.filepath = str(out / f"c{c}_{t:04d}.png")
            t0 = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            seconds.append(time.perf_counter() - t0)
        print(f"blender_render: frame {t + 1}/{n_frames}", flush=True)
    (out / "render.json").write_text(json.dumps({
        "blender": bpy.app.version_string, "seconds_per_image": seconds}))


def _fcurves(action):
    """The F-curves of an action (Blender 4.4+ layered actions keep them in channel bags)."""
    if hasattr(action, "fcurves") and len(action.fcurves):
        return list(action.fcurves)
    out = []
    for layer in getattr(action, "layers", []):
        for strip in layer.strips:
            for bag in getattr(strip, "channelbags", []):
                out += list(bag.fcurves)
    return out


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
