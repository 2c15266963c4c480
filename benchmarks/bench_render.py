"""Ray-caster speed: a 640x480 stereo pair (ids, and ids + shaded RGB) and the pose database's
80,000 tiny 40x40 id maps (Wang et al. 2011 §5.2), against a NumPy implementation of the same
ray-casting maths (rays -> geom frames -> analytic entries -> nearest -> patch lookup).

Run: ``python benchmarks/bench_render.py [--maps 8000]``. The tiny-map rate is measured on
``--maps`` maps and extrapolated linearly to 80,000 (the work is the same per map).
"""

from __future__ import annotations

import argparse

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap import render
from jaxmocap.body import CAPSULE, ELLIPSOID, SPHERE, default_body, fk, geom_world_poses
from jaxmocap.camera import look_at, stack_cameras
from jaxmocap.garment import default_garment

DB_SIZE = 80_000  # Wang et al. §5.2


# ----------------------------------------------------------------------------- NumPy baseline


def np_geoms(model, q):
    """Geom world rotations/positions at q (FK done once, outside the timed NumPy code)."""
    T = np.asarray(geom_world_poses(model, fk(model.chain, jnp.asarray(q))), np.float32)
    return T[:, :3, :3], T[:, :3, 3]


def np_near(a, b, c):
    disc = b * b - a * c
    ok = (disc >= 0) & (a > 1e-12)
    t = (-b - np.sqrt(np.where(ok, disc, 0))) / np.where(ok, a, 1)
    return np.where(ok & (t >= 0), t, np.inf)


def np_cast(R, p, size, kind, garment, origin, dirs):
    """Nearest hit patch id per ray (the same maths as jaxmocap.render, in NumPy)."""
    o = np.einsum("gji,gj->gi", R, origin[None] - p)
    d = np.einsum("gji,nj->ngi", R, dirs)
    t = np.full(d.shape[:2], np.inf, np.float32)
    for k in np.unique(kind):
        g = np.flatnonzero(kind == k)
        dg, og, sg = d[:, g], o[None, g], size[None, g]
        if k in (SPHERE, ELLIPSOID):
            radii = np.repeat(sg[..., :1], 3, -1) if k == SPHERE else sg
            os_, ds = og / radii, dg / radii
            t[:, g] = np_near((ds * ds).sum(-1), (os_ * ds).sum(-1), (os_ * os_).sum(-1) - 1)
        elif k == CAPSULE:
            r, h = sg[..., 0], sg[..., 1]
            best = np.full(dg.shape[:2], np.inf, np.float32)
            for s in (-1, 1):
                oc = og - s * np.stack([0 * h, 0 * h, h], -1)
                best = np.minimum(
                    best, np_near((dg * dg).sum(-1), (oc * dg).sum(-1), (oc * oc).sum(-1) - r * r)
                )
            a = dg[..., 0] ** 2 + dg[..., 1] ** 2
            b = og[..., 0] * dg[..., 0] + og[..., 1] * dg[..., 1]
            c = og[..., 0] ** 2 + og[..., 1] ** 2 - r * r
            ts = np_near(a, b, c)
            z = og[..., 2] + np.where(np.isfinite(ts), ts, 0) * dg[..., 2]
            t[:, g] = np.minimum(best, np.where(np.abs(z) <= h, ts, np.inf))
        else:
            raise NotImplementedError(k)
    row = np.argmin(t, axis=1)
    tmin = t[np.arange(len(row)), row]
    hit = np.isfinite(tmin)
    pl = o[row] + np.where(hit, tmin, 0)[:, None] * d[np.arange(len(row)), row]
    planes = np.asarray(garment.patch_planes, np.float32)
    vals = np.einsum("nk,pjk->npj", pl, planes[..., :3]) + planes[None, :, :, 3]
    inside = (vals <= 0).all(-1) & (np.asarray(garment.patch_geom)[None] == row[:, None])
    return np.where(hit & inside.any(1), inside.argmax(1) + 1, 0)


def np_render_ids(model, garment, geoms, cam):
    R, p = geoms
    K, dist = np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64)
    uu, vv = np.meshgrid(np.arange(cam.width, dtype=np.float32), np.arange(cam.height))
    uv = np.stack([uu, vv], -1).reshape(-1, 1, 2).astype(np.float32)
    xy = cv2.undistortPoints(uv, K, dist).reshape(-1, 2)
    Rc = np.asarray(cam.R, np.float32)
    dirs = np.concatenate([xy, np.ones_like(xy[:, :1])], -1) @ Rc
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origin = -Rc.T @ np.asarray(cam.t, np.float32)
    size = np.asarray(model.geometry.size, np.float32)
    kind = np.asarray(model.geometry.kind)
    patch = np_cast(R, p, size, kind, garment, origin, dirs.astype(np.float32))
    return patch.reshape(cam.height, cam.width)


# ----------------------------------------------------------------------------- main


def main(n_maps: int = 8000) -> None:
    model, garment = default_body(), default_garment()
    rng = np.random.default_rng(0)
    q = np.zeros(model.n_dof, np.float32)
    q[2] = 1.0
    q[6:] = rng.uniform(-0.4, 0.4, model.n_dof - 6)
    dist = [-0.2, 0.05, 0.0, 0.0, 0.0]
    cams = [
        look_at((3.0, 0.6, 1.5), (0, 0, 1.25), width=640, height=480, fx=600.0, dist=dist),
        look_at((3.0, -0.6, 1.5), (0, 0, 1.25), width=640, height=480, fx=600.0, dist=dist),
    ]
    cams = [jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), c) for c in cams]
    stereo = stack_cameras(cams)
    bg = jnp.asarray(rng.integers(0, 256, (2, 480, 640, 3), dtype=np.uint8))
    qj = jnp.asarray(q)
    rows, summary = [], []

    ids = jax.jit(jax.vmap(lambda c: render.render_ids(model, garment, qj, c).patch))
    rgb = jax.jit(jax.vmap(lambda c, b: render.render_rgb(model, garment, qj, c, b)[0]))
    c_ids = time_compile(lambda: ids(stereo))
    c_rgb = time_compile(lambda: rgb(stereo, bg))
    m_ids, n_ids = time_call(lambda: ids(stereo), n=5, warmup=1)
    m_rgb, n_rgb = time_call(lambda: rgb(stereo, bg), n=5, warmup=1)
    geoms = np_geoms(model, q)
    ref = [np_render_ids(model, garment, geoms, c) for c in cams]
    agree = np.mean(np.asarray(ids(stereo)) == np.stack(ref))
    m_np, n_np = time_call(lambda: [np_render_ids(model, garment, geoms, c) for c in cams],
                           n=3, warmup=1)  # fmt: skip
    kernel = "640x480 stereo pair, 12 geoms"
    rows += [
        Row(kernel, "jaxmocap ids (jit vmap cams)", m_ids, n_ids, 5, c_ids),
        Row(kernel, "jaxmocap ids + shaded RGB", m_rgb, n_rgb, 5, c_rgb),
        Row(kernel, "NumPy ids (same maths, cv2 undistort)", m_np, n_np, 3,
            notes=f"pixel agreement with jaxmocap {agree:.4f}"),
    ]  # fmt: skip
    summary.append(f"stereo pair ids: {m_ids:.1f} ms jaxmocap vs {m_np:.1f} ms NumPy "
                   f"({m_np / m_ids:.1f}x); with shaded RGB {m_rgb:.1f} ms")  # fmt: skip

    db_cam = look_at((3.0, 0.0, 1.3), (0, 0, 1.3), width=640, height=480, fx=600.0)
    db_cam = jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), db_cam)
    qs = np.tile(q, (n_maps, 1))
    qs[:, 3:6] = rng.uniform(-0.5, 0.5, (n_maps, 3)) * [0.3, 0.3, 1.0]
    qs[:, 6:] = rng.uniform(-0.6, 0.6, (n_maps, model.n_dof - 6))
    qs = jnp.asarray(qs, jnp.float32)
    tiny = jax.jit(lambda qs: render.tiny_id_maps(model, garment, qs, db_cam, chunk=256))
    c_tiny = time_compile(lambda: tiny(qs))
    m_tiny, n_tiny = time_call(lambda: tiny(qs), n=2, warmup=0)
    # NumPy: the same rays through the same windows, one map at a time
    wins = np.asarray(jax.jit(jax.vmap(
        lambda q: render.shirt_window(model, garment, q, db_cam)))(qs[:64]))  # fmt: skip
    size = np.asarray(model.geometry.size, np.float32)
    kind = np.asarray(model.geometry.kind)
    K = np.asarray(db_cam.K)
    Rc = np.asarray(db_cam.R)
    origin = -Rc.T @ np.asarray(db_cam.t)
    poses = [np_geoms(model, np.asarray(qs[i])) for i in range(64)]

    def np_tiny(i):
        f = (np.arange(40) + 0.5) / 40
        uu, vv = np.meshgrid(wins[i, 0] + f * wins[i, 2], wins[i, 1] + f * wins[i, 3])
        xy = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1]], -1).reshape(-1, 2)
        dirs = np.concatenate([xy, np.ones_like(xy[:, :1])], -1) @ Rc
        dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
        return np_cast(*poses[i], size, kind, garment, origin, dirs)

    m_np_tiny, n_np_tiny = time_call(lambda: [np_tiny(i) for i in range(64)], n=3, warmup=1)
    np_maps = np.stack([np.concatenate([[0], np.asarray(garment.patch_colour)])[np_tiny(i)]
                        for i in range(64)]).reshape(64, 40, 40)  # fmt: skip
    agree_tiny = np.mean(np.asarray(tiny(qs[:64])) == np_maps)
    per_map_jax = m_tiny / n_maps
    per_map_np = m_np_tiny / 64
    db_s = per_map_jax * DB_SIZE / 1e3
    kernel = f"tiny 40x40 id maps ({n_maps} timed, x{DB_SIZE // n_maps} for 80,000)"
    rows += [
        Row(kernel, "jaxmocap tiny_id_maps (vmap 256, lax.map)", m_tiny, n_tiny, 2, c_tiny,
            notes=f"{1e3 / per_map_jax:.0f} maps/s; 80,000 maps ~{db_s:.0f} s",
            extra={"maps_per_s": 1e3 / per_map_jax}),
        Row("tiny 40x40 id maps (64 timed)", "NumPy, one map at a time", m_np_tiny, n_np_tiny, 3,
            notes=f"{1e3 / per_map_np:.0f} maps/s; agreement with jaxmocap {agree_tiny:.4f}",
            extra={"maps_per_s": 1e3 / per_map_np}),
    ]  # fmt: skip
    summary.append(f"tiny maps: {1e3 / per_map_jax:.0f} maps/s jaxmocap vs "
                   f"{1e3 / per_map_np:.0f} maps/s NumPy ({per_map_np / per_map_jax:.1f}x); "
                   f"80,000 maps ~{per_map_jax * DB_SIZE / 1e3:.0f} s (extrapolated from "
                   f"{n_maps})")  # fmt: skip
    summary.append("Measured on a shared 2-core machine under heavy contention from other jobs.")
    path = write_results("bench_render", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--maps", type=int, default=None,
                        help="tiny maps to render (default 8000; 800 with JAXMOCAP_BENCH_QUICK=1)")
    n = parser.parse_args().maps
    main(n if n is not None else sized(full=8000, quick=800))
