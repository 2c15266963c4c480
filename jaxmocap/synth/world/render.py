"""Rendering a test-world sequence with MuJoCo (images of ``renderer = "cycles"`` sequences from
Blender: :mod:`jaxmocap.synth.world.cycles`) and writing it as a ``jaxmocap synth`` dataset.

Per frame and camera: the subject's pose (our ``q`` -> MuJoCo ``qpos``,
:func:`jaxmocap.body.write.qpos_from_q`), the lamps' power (:func:`spec.lamp_levels`), the moving
ball and the occluder panel (mocap bodies) are set, MuJoCo's OpenGL renderer draws the image
(offscreen: ``MUJOCO_GL=egl`` by default, ``osmesa`` where EGL is missing; set before MuJoCo
is imported), motion blur averages ``motion_blur`` sub-frame renders over the shutter
interval; then sensor noise (Gaussian, ``noise_sigma`` x 255, seeded per frame and camera) and
JPEG compression (``jpeg_quality``) are applied.

Ground truth (the keys of :func:`jaxmocap.synth.sequence.render_sequence`): ``q`` and
``keypoints`` from **our** FK of the scaled body (``dof_names`` as the world's body names
them, ``keypoint_names`` the library's); ``patch_ids`` / ``colour_ids`` from **MuJoCo's**
segmentation render (the patch of the mesh geom seen at each pixel, 0 for background, skin,
props, and body parts hidden by props); ``visible`` / ``body_pixels`` from a second
segmentation pass with the room and props hidden, ``occluded_fraction`` from both;
``illuminant`` is ``diag(sum_l level_l c_l + fill) / mean(sum_l c_l + fill)`` (the lamps'
summed colour relative to all lamps on; a summary of the light, not a model of the images)
and ``intensity`` ones; ``times`` in seconds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxmocap.synth.world.spec import (
    WorldSpec,
    lamp_levels,
    world_body,
    world_cameras,
    world_garment,
    world_motion,
)


def ensure_gl() -> str:
    """Make MuJoCo render offscreen without a display: ``MUJOCO_GL`` = ``egl`` (or ``osmesa``
    where no EGL library is found) unless set. If MuJoCo was already imported with another
    backend (e.g. by pytorch-kinematics, before this ran), its renderer's context class is
    switched to the offscreen one. Returns the backend."""
    import sys

    from jaxmocap._config import choose_offscreen_gl

    backend = choose_offscreen_gl()
    if "mujoco" in sys.modules:
        from mujoco.rendering.classic import gl_context

        if getattr(gl_context, "_MUJOCO_GL", backend) not in ("egl", "osmesa", "glx"):
            if backend == "egl":
                from mujoco.egl import GLContext
            else:
                os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
                from mujoco.osmesa import GLContext
            gl_context.GLContext = GLContext
            gl_context._MUJOCO_GL = backend
    return backend


class WorldSequence(NamedTuple):
    """A rendered test-world sequence (the fields of :class:`jaxmocap.synth.Sequence` plus the
    spec, the body as shown and the render time)."""

    frames: np.ndarray  # (T, C, H, W, 3) uint8 RGB
    cameras: list
    camera_names: list[str]
    groundtruth: dict[str, np.ndarray]
    spec: WorldSpec
    body: object  # BodyModel as the world names it
    garment: object  # the shirt on that body (geom indices shared with it)
    seconds: float  # total, set-up (retargeting, tessellation, MuJoCo compile) included
    render_seconds: float  # the frame loop only (MuJoCo renders, noise, JPEG)
    blender: dict | None = None  # Cycles: Blender's version and seconds per image


def _subframe_offsets(spec: WorldSpec) -> np.ndarray:
    s = spec.motion_blur
    return spec.shutter * ((np.arange(s) + 0.5) / s - 0.5)


def _mocap_positions(spec: WorldSpec, t_sub: np.ndarray) -> dict[str, np.ndarray]:
    """Positions (T, S, 3) of the moving ball and the occluder panel at sub-frame times."""
    from jaxmocap.synth.world.scene import (
        MOVER_PERIOD,
        MOVER_SWING,
        MOVER_X,
        OCCLUDER_HALF,
        OCCLUDER_X,
        OCCLUDER_Z,
    )

    time = t_sub / spec.fps
    phase = 2 * np.pi * time / MOVER_PERIOD
    out = {"mover": np.stack([np.full_like(time, MOVER_X), MOVER_SWING * np.sin(phase),
                              1.3 + 0.25 * np.cos(2 * phase)], -1)}
    if spec.occluder is not None:
        r = spec.rig_settings()
        a, b = spec.occluder
        span = (r["distance"] - OCCLUDER_X) * math.tan(math.radians(r["fov"]) / 2)
        span += r["baseline"] / 2 + OCCLUDER_HALF[1] + 0.1
        y = -span + 2 * span * np.clip((t_sub - a) / (b - a), 0, 1)
        out["occluder"] = np.stack([np.full_like(time, OCCLUDER_X), y,
                                    np.full_like(time, OCCLUDER_Z)], -1)
    return out


def render_world(spec: WorldSpec, progress: bool = False, segments=None,
                 blender_python: str | None = None, silhouette: bool = False) -> WorldSequence:
    """Render ``spec`` in memory (module docstring). With ``spec.renderer == "cycles"`` the
    images come from Blender (:mod:`jaxmocap.synth.world.cycles`, run in ``blender_python``;
    ``silhouette``: the body white on black, a check of Blender's geometry and cameras),
    everything else from MuJoCo as here."""
    import time as _time

    ensure_gl()
    import jax
    import jax.numpy as jnp
    import mujoco

    from jaxmocap.body import keypoints
    from jaxmocap.body.write import qpos_from_q
    from jaxmocap.garment import colour_of
    from jaxmocap.synth.scene import interpolate_poses
    from jaxmocap.synth.world.scene import PROP_GROUP, SEGMENTS, build_scene

    t0 = _time.perf_counter()
    sb, shown = world_body(spec)
    garment = world_garment(spec, sb)
    q_frames = world_motion(spec, sb)
    n = q_frames.shape[0]
    t_sub = np.arange(n)[:, None] + _subframe_offsets(spec)[None]
    q_sub = interpolate_poses(q_frames, t_sub)
    cams = world_cameras(spec)
    names = [f"cam{i}" for i in range(len(cams))]
    scene = build_scene(spec, shown, garment, cams, names, segments or SEGMENTS)
    m = mujoco.MjModel.from_xml_string(scene.xml)
    d = mujoco.MjData(m)
    h, w = int(cams[0].height), int(cams[0].width)
    rgb_r = None if spec.renderer == "cycles" else mujoco.Renderer(m, h, w)  # Blender's images
    seg_r = mujoco.Renderer(m, h, w)
    seg_r.enable_segmentation_rendering()
    everything = mujoco.MjvOption()  # MuJoCo hides geom groups 3-5 by default
    everything.geomgroup[PROP_GROUP] = 1
    body_only = mujoco.MjvOption()
    body_only.geomgroup[PROP_GROUP] = 0
    geom_patch = np.zeros(m.ngeom + 1, np.int64)  # index geom id + 1 (background -1)
    is_body = np.zeros(m.ngeom + 1, bool)
    for name, p in scene.geom_patch.items():
        gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
        geom_patch[gid + 1], is_body[gid + 1] = p, True
    lamp_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, nm) for nm in scene.lamps]
    diffuse = np.array([m.light_diffuse[i] for i in lamp_ids])
    specular = np.array([m.light_specular[i] for i in lamp_ids])
    ambient = np.array([m.light_ambient[i] for i in lamp_ids])
    levels = lamp_levels(spec, n)
    mocap = _mocap_positions(spec, t_sub)
    mocap_ids = {nm: m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, nm)]
                 for nm in scene.mocap}
    qpos = np.stack([[qpos_from_q(shown, m, q) for q in qs] for qs in q_sub])
    frames = np.zeros((n, len(cams), h, w, 3), np.uint8)
    patch_ids = np.zeros((n, len(cams), h, w), np.uint8)
    body_px = np.zeros((n, len(cams)), np.int64)
    shown_px = np.zeros((n, len(cams)), np.int64)
    mid = spec.motion_blur // 2
    cycles = spec.renderer == "cycles"
    if cycles:
        from jaxmocap.synth.world import cycles as cy

        python = cy.blender_python(blender_python)
        moving = [g for g in range(m.ngeom) if int(m.geom_bodyid[g]) != 0]
        poses = {g: (np.zeros((n, 3)), np.zeros((n, 3, 3))) for g in moving}
    t_loop = _time.perf_counter()
    it = range(n)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="synth (ground truth)" if cycles else "synth (mujoco)", unit="frame")
    for t in it:
        for k, li in enumerate(lamp_ids):
            lv = levels[t, k]
            m.light_active[li] = int(lv > 0)
            m.light_diffuse[li] = diffuse[k] * lv
            m.light_specular[li] = specular[k] * lv
            m.light_ambient[li] = ambient[k] * lv
        acc = None if cycles else np.zeros((len(cams), h, w, 3))
        for s in range(spec.motion_blur):
            if cycles and s != mid:  # Blender blurs between the frames' keyframes itself
                continue
            d.qpos[:] = qpos[t, s]
            for nm, mid_id in mocap_ids.items():
                d.mocap_pos[mid_id] = mocap[nm][t, s]
            mujoco.mj_forward(m, d)
            if cycles:
                for g in moving:
                    poses[g][0][t] = d.geom_xpos[g]
                    poses[g][1][t] = d.geom_xmat[g].reshape(3, 3)
            for c, cname in enumerate(names):
                if not cycles:
                    rgb_r.update_scene(d, camera=cname, scene_option=everything)
                    acc[c] += rgb_r.render()
                if s == mid:
                    seg_r.update_scene(d, camera=cname, scene_option=everything)
                    ids = seg_r.render()[..., 0]
                    patch_ids[t, c] = geom_patch[ids + 1]
                    shown_px[t, c] = is_body[ids + 1].sum()
                    seg_r.update_scene(d, camera=cname, scene_option=body_only)
                    body_px[t, c] = is_body[seg_r.render()[..., 0] + 1].sum()
        if not cycles:
            _camera(spec, acc / spec.motion_blur, t, frames[t])
    if rgb_r is not None:
        rgb_r.close()
    seg_r.close()
    blender = None
    if cycles:
        with tempfile.TemporaryDirectory(prefix="jaxmocap_world_") as tmp:
            fill = m.light_dir[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, "fill")]
            scene_file = cy.export_scene(Path(tmp) / "scene.npz", spec, m, poses, cams,
                                         levels, fill, threads=os.cpu_count() or 1,
                                         silhouette=silhouette)
            linear, blender = cy.render_with_blender(scene_file, n, len(cams), python,
                                                     progress=progress)
        for t in range(n):
            _camera(spec, linear[t].astype(np.float64), t, frames[t])
    t_loop = _time.perf_counter() - t_loop
    dt = jnp.result_type(float)
    kp = jax.jit(jax.vmap(lambda q: keypoints(sb.model, q)))(jnp.asarray(q_frames, dt))
    lamp_rgb = scene.lamp_rgb
    fill = np.full(3, spec.fill)
    total = levels @ lamp_rgb + fill
    illum = total / np.mean(lamp_rgb.sum(0) + fill)
    gt = {
        "q": q_frames.astype(np.dtype(dt)),
        "dof_names": np.array(shown.chain.dof_names),
        "keypoints": np.asarray(kp),
        "keypoint_names": np.array(sb.model.keypoint_names),
        "patch_ids": patch_ids,
        "colour_ids": np.asarray(colour_of(garment, jnp.asarray(patch_ids, jnp.int32))
                                 ).astype(np.uint8),
        "illuminant": (illum[:, :, None] * np.eye(3)[None]).astype(np.dtype(dt)),
        "intensity": np.ones(n, np.dtype(dt)),
        "visible": body_px > 0,
        "occluded_fraction": np.where(body_px > 0, 1 - shown_px / np.maximum(body_px, 1), 0.0),
        "body_pixels": body_px,
        "times": np.arange(n) / spec.fps,
        "lamp_levels": levels,
    }
    return WorldSequence(frames, cams, names, gt, spec, shown, garment,
                         _time.perf_counter() - t0, t_loop, blender)


def _camera(spec: WorldSpec, images: np.ndarray, t: int, out: np.ndarray) -> None:
    """The camera past the renderer: sensor noise (``noise_sigma`` x 255, seeded per frame and
    camera), 8-bit rounding, JPEG (``jpeg_quality``); ``images`` (C, H, W, 3) in 0..255."""
    import cv2

    for c in range(images.shape[0]):
        rng = np.random.default_rng([spec.seed, t, c])
        v = images[c] + spec.noise_sigma * 255 * rng.standard_normal(images[c].shape)
        v = np.clip(np.round(v), 0, 255).astype(np.uint8)
        if spec.jpeg_quality is not None:
            ok, buf = cv2.imencode(".jpg", v[..., ::-1],
                                   [cv2.IMWRITE_JPEG_QUALITY, spec.jpeg_quality])
            v = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
        out[c] = v


def sequence_body_file(folder: str | os.PathLike) -> tuple[Path, dict]:
    """The body file of a world sequence folder and its ``load_body`` keywords: its
    ``body.urdf``, or the package file that its ``body.json`` names."""
    from jaxmocap.errors import InputError

    folder = Path(folder)
    if (folder / "body.urdf").is_file():
        return folder / "body.urdf", {}
    if (folder / "body.json").is_file():
        from jaxmocap.body.packages import package_body_file

        doc = json.loads((folder / "body.json").read_text())
        return package_body_file(doc.get("package_body", ""))
    raise InputError(f"{folder}: no body.urdf or body.json in the sequence folder")


def scene_config(spec: WorldSpec, n_frames: int):
    """The nearest :class:`~jaxmocap.synth.scene.SceneConfig` (what ``scene.json``'s
    ``scene`` field must hold for :func:`~jaxmocap.synth.load_dataset`); the full world spec
    is stored beside it, under ``world``."""
    from jaxmocap.synth.scene import SceneConfig

    r = spec.rig_settings()
    return SceneConfig(
        clip=spec.clip, fps=float(spec.fps), start=spec.start, n_frames=n_frames, rig=spec.rig,
        n_cameras=2, width=int(r["width"]), height=int(r["height"]),
        baseline=float(r["baseline"]), distance=float(r["distance"]),
        garment="single" if spec.garment == "single" else "shirt",
        shirt_rgb=tuple(float(v) for v in spec.shirt_rgb), noise_sigma=float(spec.noise_sigma),
        lamp_off=spec.lamp_off, motion_blur=spec.motion_blur, shutter=float(spec.shutter),
        background="clutter", n_distractors=min(spec.n_clutter, 8),
        moving_object=spec.moving_object, occluder=spec.occluder, seed=spec.seed)


def write_world(seq: WorldSequence, folder: str | os.PathLike, video: bool = True,
                png: bool = False, sheet: bool = False) -> Path:
    """Write ``seq`` as a dataset folder (the layout of :func:`jaxmocap.synth.write_dataset`,
    read by :func:`jaxmocap.synth.load_dataset`), atomically, plus ``body.urdf`` and
    ``body.xml`` (the subject's body as the world names it; for a package body instead
    ``body.json``, which names the file in its package: :func:`sequence_body_file`),
    ``garment.json`` (its shirt on that body, :func:`jaxmocap.io.garment_file.save_garment`)
    and, in ``scene.json``, ``render.renderer`` (``mujoco`` or ``cycles``, with Blender's
    version and seconds per image) and ``world`` (the :class:`WorldSpec`)."""
    from jaxmocap.body.write import write_mjcf, write_urdf
    from jaxmocap.io.garment_file import save_garment
    from jaxmocap.synth.dataset import _check_target, write_dataset
    from jaxmocap.synth.sequence import Sequence

    folder = Path(folder)
    _check_target(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        cfg = scene_config(seq.spec, seq.frames.shape[0])
        s = Sequence(frames=seq.frames, cameras=seq.cameras, camera_names=seq.camera_names,
                     groundtruth=seq.groundtruth, config=cfg)
        inner = write_dataset(s, tmp / "d", video=video, png=png, sheet=sheet)
        doc = json.loads((inner / "scene.json").read_text())
        doc["render"]["renderer"] = seq.spec.renderer
        doc["render"]["mujoco_gl"] = os.environ.get("MUJOCO_GL")
        if seq.blender is not None:
            sec = seq.blender["seconds_per_image"]
            doc["render"]["blender"] = seq.blender["blender"]
            doc["render"]["seconds_per_image"] = round(float(np.mean(sec)), 2)
        doc["render"]["seconds"] = round(seq.seconds, 2)
        doc["render"]["render_seconds"] = round(seq.render_seconds, 2)
        doc["world"] = seq.spec.to_dict()
        (inner / "scene.json").write_text(json.dumps(doc, indent=2) + "\n")
        if seq.spec.body == "scaled":
            write_urdf(seq.body, inner / "body.urdf")
            write_mjcf(seq.body, inner / "body.xml")
        else:  # a package body is read from its own file, as it comes (body.json names it)
            from jaxmocap.body.packages import PACKAGE_BODIES

            package, parts, kw = PACKAGE_BODIES[seq.spec.body]
            (inner / "body.json").write_text(json.dumps(
                {"package_body": seq.spec.body, "package": package, "path": "/".join(parts),
                 **kw}, indent=1) + "\n")
        save_garment(inner / "garment.json", seq.garment, seq.body)
        _check_target(folder)
        if folder.is_dir():
            folder.rmdir()
        os.rename(inner, folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder
