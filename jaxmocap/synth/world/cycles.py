"""The test world's second renderer: Blender Cycles through ``bpy`` (issue 36 item 3).

A sequence with ``renderer = "cycles"`` is set up exactly as a MuJoCo one (the same MJCF scene,
:func:`jaxmocap.synth.world.scene.build_scene`: body patch meshes, room, props, lamps, cameras)
and MuJoCo still gives the ground truth (poses, segmentation at the middle of the shutter);
only the images come from Blender. :func:`export_scene` writes what Blender needs as one
``.npz`` (every visible geom as a mesh in its frame with its linear albedo and material class,
its pose per frame, lamps, cameras), and :func:`render_with_blender` runs
``blender_render.py`` (beside this module) in a Python that has ``bpy``: Blender pins its own
NumPy (``bpy`` 5.0 needs NumPy 1.26, this library 2.x), so that Python is usually another
environment, named by ``--blender-python`` / ``JAXMOCAP_BLENDER_PYTHON``.

**Light of strong colour, not ours.** Lamp ``k`` of the spec keeps the MuJoCo lamp's position
and aim; lamp 0 is a spot lamp (55 deg cone, 12 cm emitter: soft shadow edges), lamp 1 an
area lamp (a 1 m soft box), further lamps alternate. Their colours come from Blender's
black-body node: warm 2700 K (tungsten), cool 6500 K (daylight), neutral 4500 K; the fill is a
broad sun (40 deg) plus a grey world light, so the room's walls and floor light the subject
indirectly. Per-frame lamp power (``lamp_off``, ``dim``) is keyframed.

**Camera.** Cycles' motion blur over ``shutter`` (when ``motion_blur > 1``; the sub-frame
count itself is MuJoCo's and has no meaning here), Blender's AgX view transform as the tone
curve, then this project's sensor noise and JPEG (as for MuJoCo: ``noise_sigma``,
``jpeg_quality``), so that both renderers share one camera model past the tone curve.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from jaxmocap.errors import InputError

SCRIPT = Path(__file__).with_name("blender_render.py")
BLENDER_PYTHON_ENV = "JAXMOCAP_BLENDER_PYTHON"
KELVIN = {"warm": 2700.0, "cool": 6500.0, "neutral": 4500.0}
# Lamp power (W) and exposure, chosen so that the lit shirt of a webcam rig at 2.6 m sits in
# the upper half of the 8-bit range without clipping on white (a render of shirt_00's set-up).
SPOT_WATTS, AREA_WATTS, AREA_SIZE, SPOT_RADIUS = 2000.0, 500.0, 1.0, 0.12
FILL_SUN, AMBIENT, EXPOSURE = 0.6, 0.25, -2.5
# MuJoCo geom types (mjtGeom): plane, sphere, capsule, ellipsoid, cylinder, box, mesh
_PLANE, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH = 0, 2, 3, 4, 5, 6, 7


class BlenderError(InputError):
    """No usable Blender Python (named in the message)."""


def blender_python(path: str | None = None) -> str:
    """The Python to run Blender in: ``path``, else ``$JAXMOCAP_BLENDER_PYTHON``, else this
    interpreter; checked by importing ``bpy`` there (one line naming what failed)."""
    exe = path or os.environ.get(BLENDER_PYTHON_ENV) or sys.executable
    where = ("--blender-python" if path else BLENDER_PYTHON_ENV
             if os.environ.get(BLENDER_PYTHON_ENV) else "this Python")
    try:
        r = subprocess.run([exe, "-c", "import bpy; print(bpy.app.version_string)"],
                           capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise BlenderError(f"{where} {exe}: cannot run it ({e})") from None
    if r.returncode != 0:
        raise BlenderError(f"{where} {exe}: cannot import bpy (Blender as a module; "
                           "`pip install bpy` into a Python 3.11 environment of its own and "
                           "name it with --blender-python)")
    return exe


def _tessellated(kind: int, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from jaxmocap.body import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE
    from jaxmocap.synth.world.scene import tessellate

    ours = {_SPHERE: SPHERE, _CAPSULE: CAPSULE, _ELLIPSOID: ELLIPSOID, _CYLINDER: CYLINDER,
            _BOX: BOX}[kind]
    return tessellate(ours, np.asarray(size, float), (48, 24))


def _texture_mean(m, tex_id: int) -> np.ndarray:
    """Mean linear albedo of a MuJoCo texture (its bytes are display values)."""
    from jaxmocap.synth.world.scene import GAMMA

    a, n = int(m.tex_adr[tex_id]), int(m.tex_width[tex_id] * m.tex_height[tex_id])
    c = int(m.tex_nchannel[tex_id])
    px = np.asarray(m.tex_data[a:a + n * c], float).reshape(n, c)[:, :3] / 255
    return np.mean(px ** GAMMA, 0)


def export_scene(path: str | os.PathLike, spec, m, poses: dict[int, tuple], cams: list,
                 levels: np.ndarray, fill_dir, threads: int = 2, silhouette: bool = False
                 ) -> Path:
    """Write the Blender scene file of a compiled world model ``m`` (module docstring).

    ``poses``: geom id -> (pos (T, 3), mat (T, 3, 3)) of every geom that moves (body and mocap
    geoms, taken at each frame's mid-shutter time); other geoms are static at ``m``'s
    compiled pose. Only geom groups 0 (body) and ``PROP_GROUP`` (room, props) are drawn.
    ``silhouette``: Blender draws the body white and everything else black, unlit, one sample,
    no pixel filter (a check of the geometry and cameras against MuJoCo's segmentation)."""
    import mujoco

    from jaxmocap.synth.world.scene import FLOOR_RGB, GAMMA, PROP_GROUP

    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    arrays, geoms = {}, []
    for g in range(m.ngeom):
        if int(m.geom_group[g]) not in (0, PROP_GROUP) or m.geom_rgba[g, 3] == 0:
            continue
        kind = int(m.geom_type[g])
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        if kind == _MESH:
            mid = int(m.geom_dataid[g])
            va, vn = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
            fa, fn = int(m.mesh_faceadr[mid]), int(m.mesh_facenum[mid])
            verts, faces = m.mesh_vert[va:va + vn], m.mesh_face[fa:fa + fn]
        elif kind == _PLANE:
            sx, sy = m.geom_size[g, :2]
            verts = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0]], float)
            faces = np.array([[0, 1, 2], [0, 2, 3]])
        else:
            verts, faces = _tessellated(kind, m.geom_size[g])
        mat_id = int(m.geom_matid[g])
        material = (mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MATERIAL, mat_id)
                    if mat_id >= 0 else "matte")
        rgb = np.clip(np.asarray(m.geom_rgba[g, :3], float), 0, 1) ** GAMMA
        if material == "wall":  # a gradient texture: its mean colour
            rgb = _texture_mean(m, int(np.max(m.mat_texid[mat_id])))
        i = len(geoms)
        arrays[f"verts{i}"] = np.asarray(verts, np.float64)
        arrays[f"faces{i}"] = np.asarray(faces, np.int64)
        arrays[f"rgb{i}"] = rgb
        moving = g in poses
        if moving:
            arrays[f"pos{i}"], arrays[f"mat{i}"] = poses[g]
        else:
            arrays[f"pos{i}"] = np.asarray(d.geom_xpos[g], float)
            arrays[f"mat{i}"] = np.asarray(d.geom_xmat[g], float).reshape(3, 3)
        geoms.append({"name": name, "material": material if material in (
            "cloth", "skin", "gloss", "matte", "floor", "wall") else "matte", "moving": moving,
            "body": int(m.geom_group[g]) == 0})
    lamps = []
    for k, c in enumerate(spec.lamps):
        li = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, f"lamp{k}")
        spot = k % 2 == 0
        lamps.append({"kind": "SPOT" if spot else "AREA", "kelvin": KELVIN[c],
                      "watts": SPOT_WATTS if spot else AREA_WATTS, "cone_deg": 110.0,
                      "radius": SPOT_RADIUS, "size": AREA_SIZE,
                      "pos": np.asarray(m.light_pos[li], float).tolist(),
                      "dir": np.asarray(m.light_dir[li], float).tolist()})
    w, h = int(cams[0].width), int(cams[0].height)
    meta = {"geoms": geoms, "lamps": lamps, "n_frames": int(levels.shape[0]),
            "n_cameras": len(cams), "width": w, "height": h, "fps": float(spec.fps),
            "samples": int(spec.samples), "seed": int(spec.seed), "threads": int(threads),
            "motion_blur": spec.motion_blur > 1, "shutter": float(spec.shutter),
            "exposure": EXPOSURE, "silhouette": bool(silhouette),
            "ambient": AMBIENT * (0.4 + spec.fill),
            "fill_sun": FILL_SUN * spec.fill / 0.25,
            "fill_dir": np.asarray(fill_dir, float).tolist()}
    arrays.update(
        meta=np.array(json.dumps(meta)), levels=np.asarray(levels, float),
        floor_rgb=np.asarray(FLOOR_RGB, float) ** GAMMA,
        K=np.stack([np.asarray(c.K, float) for c in cams]),
        R=np.stack([np.asarray(c.R, float) for c in cams]),
        t=np.stack([np.asarray(c.t, float).reshape(3) for c in cams]))
    path = Path(path)
    np.savez(path, **arrays)
    return path


def render_with_blender(scene_file: str | os.PathLike, n_frames: int, n_cams: int,
                        python: str, progress: bool = False) -> tuple[np.ndarray, dict]:
    """Run Blender on ``scene_file``; the images (T, C, H, W, 3) uint8 RGB and Blender's
    ``render.json``. Blender's own output is kept out of the way (shown on failure)."""
    import cv2

    tmp = Path(tempfile.mkdtemp(prefix="jaxmocap_cycles_"))
    try:
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n_frames, desc="synth (cycles)", unit="frame")
        log = []
        with subprocess.Popen([python, str(SCRIPT), str(scene_file), str(tmp)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True) as proc:
            assert proc.stdout is not None
            for line in proc.stdout:
                log.append(line)
                if bar is not None and line.startswith("blender_render: frame"):
                    bar.update(1)
            rc = proc.wait()
        if bar is not None:
            bar.close()
        if rc != 0:
            tail = "".join(log[-20:])
            raise RuntimeError(f"Blender ({python}) failed with exit code {rc}:\n{tail}")
        frames = None
        for t in range(n_frames):
            for c in range(n_cams):
                img = cv2.imread(str(tmp / f"c{c}_{t:04d}.png"), cv2.IMREAD_COLOR)
                if img is None:
                    raise RuntimeError(f"Blender wrote no image c{c}_{t:04d}.png")
                if frames is None:
                    frames = np.zeros((n_frames, n_cams, *img.shape), np.uint8)
                frames[t, c] = img[..., ::-1]
        info = json.loads((tmp / "render.json").read_text())
        return frames, info
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
