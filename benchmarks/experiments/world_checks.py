"""Checks and speed of the MuJoCo test world (docs/results/test_world.md).

    python -m benchmarks.experiments.world_checks [--frames 10]

1. projection: marker spheres on the rays of 20 chosen pixels per camera, MuJoCo
   segmentation blob centroids vs ``jaxmocap.camera.project`` (both rigs, 640x480 / 320x240);
2. id maps: MuJoCo's patch ids vs the JAX ray caster's for the same pose, body and shirt
   (a scaled mixamo-named box-limbed body in the banded shirt, and the bundled body in Wang's);
3. speed: ms per frame of the frame loop at 640x480 (two cameras, RGB + two segmentation
   passes each) and 320x240, with the machine's load average.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from jaxmocap.synth.world import render as world_render

world_render.ensure_gl()

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from jaxmocap import render  # noqa: E402
from jaxmocap.camera import pixel_rays, project, to_camera  # noqa: E402
from jaxmocap.synth.world import WorldSpec, render_world  # noqa: E402
from jaxmocap.synth.world.scene import build_scene  # noqa: E402
from jaxmocap.synth.world.spec import world_body, world_cameras, world_garment  # noqa: E402


def hidden(i: int, uv: np.ndarray, z: np.ndarray, rad: np.ndarray) -> bool:
    """Whether marker i's disc may be overlapped by a nearer marker's (predicted)."""
    d = np.linalg.norm(uv - uv[i], axis=1)
    return bool(np.any((z < z[i]) & (d < rad + rad[i] + 2)))


def projection_errors(rig: str, seed: int = 0) -> list[float]:
    spec = WorldSpec(rig=rig, n_clutter=0, n_frames=1)
    sb, shown = world_body(spec)
    cams = world_cameras(spec)
    w, h = int(cams[0].width), int(cams[0].height)
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.linspace(0.1 * w, 0.9 * w, 5), np.linspace(0.1 * h, 0.9 * h, 4))
    uv = np.stack([gx.ravel(), gy.ravel()], -1) + rng.uniform(-3, 3, (20, 2))
    o, d = pixel_rays(cams[0], jnp.asarray(uv))
    pts = np.asarray(o) + np.asarray(d) * rng.uniform(1.2, 2.2, (20, 1))
    scene = build_scene(spec, shown, world_garment(spec, sb), cams, ["cam0", "cam1"],
                        markers=pts, marker_radius=0.02)
    m = mujoco.MjModel.from_xml_string(scene.xml)
    data = mujoco.MjData(m)
    data.qpos[2] = -5.0
    data.qpos[3] = 1.0
    mujoco.mj_forward(m, data)
    r = mujoco.Renderer(m, h, w)
    r.enable_segmentation_rendering()
    opt = mujoco.MjvOption()
    opt.geomgroup[3] = 1
    yy, xx = np.mgrid[0:h, 0:w]
    errs = []
    for c, name in enumerate(["cam0", "cam1"]):
        r.update_scene(data, camera=name, scene_option=opt)
        ids = r.render()[..., 0]
        want = np.asarray(project(cams[c], jnp.asarray(pts)))
        z = np.asarray(to_camera(cams[c], jnp.asarray(pts)))[:, 2]
        rad = float(cams[c].K[0, 0]) * 0.02 / z
        for i in range(len(pts)):
            mask = ids == mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"marker{i}")
            if hidden(i, want, z, rad) or not ((want[i] > rad[i] + 2).all()
                                               and want[i][0] < w - rad[i] - 3
                                               and want[i][1] < h - rad[i] - 3):
                continue
            got = np.array([xx[mask].mean(), yy[mask].mean()])
            errs.append(float(np.linalg.norm(got - want[i])))
    r.close()
    return errs


def id_agreement(spec: WorldSpec) -> dict:
    seq = render_world(spec)
    sb, shown = world_body(spec)
    garment = world_garment(spec, sb)
    a, b = [], []
    for t in range(seq.frames.shape[0]):
        for c, cam in enumerate(seq.cameras):
            ours = np.asarray(render.render_ids(shown, garment,
                                                jnp.asarray(seq.groundtruth["q"][t]), cam).patch)
            theirs = seq.groundtruth["patch_ids"][t, c].astype(int)
            a.append(float(np.mean(theirs[ours > 0] == ours[ours > 0])))
            b.append(float(np.mean(ours[theirs > 0] == theirs[theirs > 0])))
    return {"jax_patch_pixels_agreeing": [min(a), float(np.mean(a))],
            "mujoco_patch_pixels_agreeing": [min(b), float(np.mean(b))]}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--frames", type=int, default=10)
    args = p.parse_args()
    out = {}
    for rig in ("webcams", "stereo"):
        e = projection_errors(rig)
        out[f"projection_{rig}"] = {"n": len(e), "max_px": max(e), "mean_px": float(np.mean(e))}
        print(rig, out[f"projection_{rig}"], flush=True)
    small = dict(n_frames=3, width=320, height_px=240, distance=1.8, n_clutter=0,
                 noise_sigma=0.0)
    out["ids_scaled_mixamo_box_bands"] = id_agreement(WorldSpec(
        **small, height=1.56, upper_arm=0.32, naming="mixamo", limbs="box", garment="bands"))
    out["ids_bundled_wang"] = id_agreement(WorldSpec(**small))
    print(out, flush=True)
    for rig in ("webcams", "stereo"):
        spec = WorldSpec(rig=rig, n_frames=args.frames, n_clutter=6, moving_object=True,
                         occluder=(2, 8), lamp_off=5)
        t = time.perf_counter()
        seq = render_world(spec)
        out[f"speed_{rig}"] = {
            "size": list(seq.frames.shape[2:4][::-1]), "frames": args.frames,
            "ms_per_frame_loop": 1000 * seq.render_seconds / args.frames,
            "setup_s": seq.seconds - seq.render_seconds, "wall_s": time.perf_counter() - t,
            "load_average": os.getloadavg()[0]}
        print(rig, out[f"speed_{rig}"], flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
