"""``jaxmocap demo``: the main job on bundled data.

Stage 0 of the project (foundation only): the trackers are not built yet, so the demo runs
what exists and says so. It loads the bundled upper-body model, poses it with random joint
configurations, projects its keypoints into a calibrated stereo pair, triangulates them back
and reports the round-trip error and the forward-kinematics throughput.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="run the main job on bundled data (offline)")
    p.add_argument("--out", default="jaxmocap-demo", help="output folder (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap import camera
    from jaxmocap.body import default_body, fk, keypoints, rest_pose

    print("jaxmocap demo: the trackers are not implemented yet; running the foundation "
          "(body model, forward kinematics, stereo projection and triangulation).")
    model = default_body()
    rng = np.random.default_rng(0)
    n = 1000
    lo = np.where(np.isfinite(model.chain.lower), model.chain.lower, -0.1)
    hi = np.where(np.isfinite(model.chain.upper), model.chain.upper, 0.1)
    qs = jnp.asarray(rng.uniform(lo, hi, size=(n, lo.size)), jnp.float32)
    qs = qs.at[:, :3].set(0.0).at[:, 2].set(1.0)
    batched_fk = jax.jit(jax.vmap(lambda q: fk(model.chain, q)))
    batched_fk(qs).block_until_ready()
    t0 = time.perf_counter()
    batched_fk(qs).block_until_ready()
    dt = time.perf_counter() - t0
    print(f"  fk: {n} poses x {len(model.chain.link_names)} links in {dt * 1e3:.2f} ms")

    cams = [camera.look_at(eye=(3.0, y, 1.3), target=(0.0, 0.0, 1.2), fx=600.0, fy=600.0,
                           cx=320.0, cy=240.0, width=640, height=480) for y in (-0.5, 0.5)]
    stacked = camera.stack_cameras(cams)
    pts = jax.vmap(lambda q: keypoints(model, q))(qs).reshape(-1, 3)
    uv = jnp.stack([camera.project(c, pts) for c in cams])
    rec = camera.triangulate(stacked, uv)
    err = float(jnp.max(jnp.linalg.norm(rec - pts, axis=-1)))
    print(f"  stereo: {pts.shape[0]} keypoints projected and triangulated, max error "
          f"{err * 1e3:.4f} mm")
    q0 = rest_pose(model)
    print(f"  model: {len(model.chain.dof_names)} DOF, keypoints at rest:")
    for name, p in zip(model.keypoint_names, np.asarray(keypoints(model, q0)), strict=True):
        print(f"    {name:12s} {p[0]:+.3f} {p[1]:+.3f} {p[2]:+.3f} m")
    return 0
