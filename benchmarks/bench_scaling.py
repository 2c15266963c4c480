"""Scaling curves: how each hot path's cost grows with its size, against its NumPy/OpenCV baseline.

* **particles** N = 100 .. 10,000: the stereo particle filter's real likelihood (Azad cues:
  FK + projection + edge cue x 2 cameras + distance cue, ``jit(vmap)``) on a rendered 320x240
  frame of ``azad_render``; baseline: the batched NumPy FK + projection + edge cue of
  ``bench_stereo_pf``. (The whole filter step is not swept: its ~30 s compile per N is too
  dear; the likelihood is its dominant cost, see ``bench_stereo_pf``.)
* **image size** 320x240 .. 1280x720: Wang's histogram search, the 10-colour Gaussian
  classification and Azad's segmentation pipeline; baselines: ``bench_color``'s NumPy stride-6
  integral histogram and one-GEMM classifier, OpenCV ``segment_cv``.
* **pose database** 10k .. 320k poses: ``posedb.query_exact`` / ``query_fast`` on synthetic
  random packed codes of the real layout (building real 320k-pose maps takes hours here);
  baseline: ``bench_posedb``'s NumPy packed distance with ``np.bitwise_count``.
* **cameras** 1 .. 4: projecting 10,000 points into each camera (vmap) vs ``cv2.projectPoints``
  per camera, and n-view triangulation (DLT + refinement) vs a batched NumPy SVD DLT.
* **batch** B = 1 .. 64 sequences under ``vmap``: ``pf.run`` (T = 20, N = 1000, 14-D toy
  likelihood of ``bench_pf``) vs a NumPy loop of ``bench_pf.numpy_step`` over the sequences.

Writes ``results/bench_scaling.{json,md}`` and ``results/scaling_<curve>.png``.

    python benchmarks/bench_scaling.py [--quick]     (or JAXMOCAP_BENCH_QUICK=1)
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent / "experiments"))
import benchmarks._common as common  # noqa: E402
from benchmarks import bench_color, bench_pf, bench_posedb, bench_stereo_pf  # noqa: E402
from benchmarks._common import Row, time_call, time_compile, write_results  # noqa: E402
from jaxmocap import camera, pf, posedb  # noqa: E402
from jaxmocap.body import default_body  # noqa: E402
from jaxmocap.color import ColorModel, classify  # noqa: E402
from jaxmocap.color.search import histogram_search  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams, segment_cv, segment_views  # noqa: E402

FULL = {
    "particles": (100, 300, 1000, 3000, 10000),
    "image": ((320, 240), (640, 480), (960, 540), (1280, 720)),
    "posedb": (10_000, 20_000, 40_000, 80_000, 160_000, 320_000),
    "cameras": (1, 2, 3, 4),
    "batch": (1, 4, 16, 64),
}
QUICK = {
    "particles": (100, 1000),
    "image": ((320, 240), (640, 480)),
    "posedb": (10_000, 40_000),
    "cameras": (1, 2),
    "batch": (1, 4),
}
UNITS = {
    "particles": "particles N",
    "image": "pixels (millions)",
    "posedb": "database poses",
    "cameras": "cameras",
    "batch": "sequences B",
}


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _row(curve, size, impl, t, n, comp=None, notes=""):
    return Row(
        f"{curve} {size}",
        impl,
        t[0],
        t[1],
        n,
        comp,
        notes,
        extra={"curve": curve, "size": size, "peak_rss_mib": peak_rss_mib()},
    )


def particles(sizes, reps):
    from azad_render import config, load

    from jaxmocap.synth.scene import make_cameras
    from jaxmocap.trackers import stereo_pf as sp

    clip, frames = bench_stereo_pf.CLIP, bench_stereo_pf.FRAMES
    d = load(clip, frames)
    cams = make_cameras(config(clip, frames), jnp.float32)
    params = sp.make_params(
        cams, images=sp.Images(segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV)))
    )
    obs = sp.observe_sequence(params, d["frames"][:2])
    first = jax.tree.map(lambda a: a[0], obs)
    lik = params.likelihood
    ch = lik.model.chain
    chain_np = (
        [t[0] for t in ch.topology],
        np.asarray(ch.joint_origin)[:, :3, :3] * 1.0,
        np.asarray(ch.joint_origin)[:, :3, 3] * 1.0,
        np.asarray(ch.joint_axis, float),
        [t[2] for t in ch.topology],
    )
    limbs = lik.limbs
    limbs_np = (
        list(limbs.link),
        np.asarray(limbs.p0),
        np.asarray(limbs.p1),
        np.asarray(limbs.radius),
    )
    cams_np = [
        (np.asarray(c.K, float), np.asarray(c.R, float), np.asarray(c.t, float)) for c in cams
    ]
    edges = np.asarray(first.edges, np.float64)
    f = jax.jit(jax.vmap(lik, in_axes=(0, None)))
    rows, rng = [], np.random.default_rng(0)
    # particles spread around the first frame's initialised estimate (the tracker's own init)
    state, _ = sp.init(params, jax.random.key(0), first)
    mid = np.asarray(state.particles.particles).mean(0)
    for n in sizes:
        x = jnp.asarray(mid + 0.05 * rng.standard_normal((n, mid.shape[0])), jnp.float32)
        comp = time_compile(lambda x=x: f(x, first))
        rows.append(
            _row(
                "particles",
                n,
                "jaxmocap jit(vmap) likelihood (edge x2 + distance)",
                time_call(lambda x=x: f(x, first), n=reps),
                reps,
                comp,
            )
        )
        qn = np.asarray(jax.vmap(lik.full_q)(x), np.float64)
        t = time_call(
            lambda qn=qn: bench_stereo_pf.numpy_fk_project_edge(
                chain_np, limbs_np, cams_np, qn, edges
            ),
            n=max(2, reps // 4),
            warmup=1,
        )
        rows.append(
            _row("particles", n, "NumPy batched (edge cue, bench_stereo_pf)", t, max(2, reps // 4))
        )
    return rows


def image(sizes, reps):
    rng = np.random.default_rng(0)
    search = jax.jit(histogram_search, static_argnames=("scales", "stride"))
    cls = jax.jit(classify)
    mean, cov = bench_color.random_model(rng)
    W = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    model = ColorModel(mean=jnp.asarray(mean, jnp.float32), cov=jnp.asarray(cov, jnp.float32))
    jW = jnp.asarray(W, jnp.float32)
    seg = SegmentParams()
    rows = []
    for w, h in sizes:
        size = f"{w}x{h}"
        img = bench_color.scene(rng, h, w)
        jimg = jnp.asarray(img)
        comp = time_compile(lambda jimg=jimg: search(jimg))
        rows.append(
            _row(
                "image search",
                size,
                "jaxmocap histogram_search jit",
                time_call(lambda jimg=jimg: search(jimg), n=reps),
                reps,
                comp,
            )
        )
        rows.append(
            _row(
                "image search",
                size,
                "NumPy stride-6 cell integral histogram",
                time_call(lambda img=img: bench_color.np_search_cells(img), n=max(2, reps // 4)),
                max(2, reps // 4),
            )
        )
        comp = time_compile(lambda jimg=jimg: cls(model, jW, jimg))
        rows.append(
            _row(
                "image classify",
                size,
                "jaxmocap classify jit",
                time_call(lambda jimg=jimg: cls(model, jW, jimg), n=reps),
                reps,
                comp,
            )
        )
        rows.append(
            _row(
                "image classify",
                size,
                "NumPy one-GEMM quadratic form",
                time_call(
                    lambda img=img: bench_color.np_gemm_classify(img, W, mean, cov),
                    n=max(2, reps // 4),
                ),
                max(2, reps // 4),
            )
        )
        pair = jnp.asarray(np.stack([img, img[:, ::-1]]))
        comp = time_compile(lambda pair=pair: segment_views(seg, pair))
        rows.append(
            _row(
                "image segment pair",
                size,
                "jaxmocap segment_views jit",
                time_call(lambda pair=pair: segment_views(seg, pair), n=reps),
                reps,
                comp,
            )
        )
        rows.append(
            _row(
                "image segment pair",
                size,
                "OpenCV segment_cv x2",
                time_call(
                    lambda img=img: [segment_cv(seg, img), segment_cv(seg, img[:, ::-1])], n=reps
                ),
                reps,
            )
        )
    return rows


def database(sizes, reps):
    rng = np.random.default_rng(0)
    n_dof = default_body().n_dof
    chunk = posedb._search.SEARCH_CHUNK
    tiny = rng.integers(0, 11, (posedb._search.TINY_SIZE,) * 2)
    qcode = np.asarray(posedb._search.pack_map(jnp.asarray(tiny)))
    rows = []
    for n in sizes:
        codes = rng.integers(0, 2**32, (n, posedb._search.CODE_WORDS), dtype=np.uint32)
        c = -(-n // chunk)
        padded = np.zeros((c * chunk, codes.shape[1]), np.uint32)
        padded[:n] = codes
        db = posedb.PoseDB(
            poses=jnp.zeros((n, n_dof), jnp.float32),
            codes=jnp.asarray(padded.reshape(c, chunk, -1).transpose(0, 2, 1)),
            n_colours=10,
        )
        jt = jnp.asarray(tiny)
        for name, fn in (("query_exact", posedb.query_exact), ("query_fast", posedb.query_fast)):
            comp = time_compile(lambda fn=fn, db=db, jt=jt: fn(db, jt))
            rows.append(
                _row(
                    "posedb",
                    n,
                    f"jaxmocap {name}",
                    time_call(lambda fn=fn, db=db, jt=jt: fn(db, jt), n=reps),
                    reps,
                    comp,
                )
            )
        rows.append(
            _row(
                "posedb",
                n,
                "NumPy packed codes + np.bitwise_count",
                time_call(
                    lambda codes=codes: bench_posedb.numpy_packed_knn(codes, qcode),
                    n=max(2, reps // 4),
                ),
                max(2, reps // 4),
            )
        )
        del db, codes, padded
    return rows


def numpy_dlt(Ps, uv):
    """Batched n-view DLT in NumPy: uv (v, n, 2) undistorted pixels, Ps (v, 3, 4)."""
    a = uv[..., 0:1] * Ps[:, None, 2] - Ps[:, None, 0]
    b = uv[..., 1:2] * Ps[:, None, 2] - Ps[:, None, 1]
    A = np.concatenate([a, b], 0).transpose(1, 0, 2)
    X = np.linalg.svd(A)[2][:, -1]
    return X[:, :3] / X[:, 3:]


def cameras(sizes, reps):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.5, 0.5, (10_000, 3)) + np.array([0.0, 0.0, 1.0])
    all_cams = [
        camera.look_at(eye, (0.0, 0.0, 1.0), width=640, height=480, fx=550.0)
        for eye in ((3, -1, 1.3), (3, 1, 1.3), (2, -2.5, 1.5), (2, 2.5, 1.5))
    ]
    proj = jax.jit(jax.vmap(camera.project, in_axes=(0, None)))
    tri = jax.jit(camera.triangulate)
    X = jnp.asarray(pts, jnp.float32)
    rows = []
    for v in sizes:
        cams = camera.stack_cameras(all_cams[:v])
        comp = time_compile(lambda cams=cams: proj(cams, X))
        rows.append(
            _row(
                "cameras project 1e4",
                v,
                "jaxmocap jit(vmap(project))",
                time_call(lambda cams=cams: proj(cams, X), n=reps),
                reps,
                comp,
            )
        )
        cv = [
            (
                cv2.Rodrigues(np.asarray(c.R, float))[0],
                np.asarray(c.t, float),
                np.asarray(c.K, float),
                np.asarray(c.dist, float),
            )
            for c in all_cams[:v]
        ]
        rows.append(
            _row(
                "cameras project 1e4",
                v,
                "cv2.projectPoints per camera",
                time_call(lambda cv=cv: [cv2.projectPoints(pts, *c) for c in cv], n=reps),
                reps,
            )
        )
        if v < 2:
            continue
        uv = proj(cams, X)
        comp = time_compile(lambda cams=cams, uv=uv: tri(cams, uv))
        rows.append(
            _row(
                "cameras triangulate 1e4",
                v,
                "jaxmocap jit(triangulate) DLT + refine",
                time_call(lambda cams=cams, uv=uv: tri(cams, uv), n=reps),
                reps,
                comp,
            )
        )
        Ps = np.stack(
            [
                np.asarray(c.K, float)
                @ np.concatenate([np.asarray(c.R, float), np.asarray(c.t, float)[:, None]], 1)
                for c in all_cams[:v]
            ]
        )
        uvn = np.asarray(uv, np.float64)
        rows.append(
            _row(
                "cameras triangulate 1e4",
                v,
                "NumPy batched SVD DLT",
                time_call(lambda Ps=Ps, uvn=uvn: numpy_dlt(Ps, uvn), n=max(2, reps // 4)),
                max(2, reps // 4),
            )
        )
    return rows


def batch(sizes, reps, t_seq=20):
    n, d = bench_pf.N, bench_pf.D
    rng = np.random.default_rng(0)
    lo, hi = -np.pi * np.ones(d), np.pi * np.ones(d)
    smin, smax = 0.01 * np.ones(d), 0.2 * np.ones(d)
    params = pf.PFParams(
        bench_pf.loglik,
        lower=jnp.asarray(lo, jnp.float32),
        upper=jnp.asarray(hi, jnp.float32),
        sigma_min=jnp.asarray(smin, jnp.float32),
        sigma_max=jnp.asarray(smax, jnp.float32),
        damping=bench_pf.DAMPING,
    )
    target = rng.uniform(-1, 1, d)
    state = pf.init(jax.random.key(0), params, jnp.asarray(target, jnp.float32), 0.3, n)
    run = jax.jit(jax.vmap(lambda z, k: pf.run(params, state, z, k)))
    rows = []
    for b in sizes:
        zs = jnp.asarray(np.sin(target) + 0.01 * rng.standard_normal((b, t_seq, d)), jnp.float32)
        keys = jax.random.split(jax.random.key(1), b)
        comp = time_compile(lambda zs=zs, keys=keys: run(zs, keys))
        rows.append(
            _row(
                "batch pf.run",
                b,
                f"jaxmocap jit(vmap(pf.run)), T={t_seq}, N={n}",
                time_call(lambda zs=zs, keys=keys: run(zs, keys), n=max(2, reps // 4)),
                max(2, reps // 4),
                comp,
            )
        )
        zn = np.asarray(zs, np.float64)

        def numpy_loop(zn=zn):
            g = np.random.default_rng(2)
            for z_seq in zn:
                x = target + 0.3 * g.standard_normal((n, d))
                st = (x, x, np.full(n, -np.log(n)), smax)
                for z in z_seq:
                    st, _ = bench_pf.numpy_step(g, *st, z, lo, hi, smin, smax)

        rows.append(
            _row(
                "batch pf.run",
                b,
                "NumPy loop of bench_pf.numpy_step",
                time_call(numpy_loop, n=2, warmup=1),
                2,
            )
        )
    return rows


def plot(rows, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    curves = sorted({r.extra["curve"] for r in rows})
    for curve in curves:
        fig, ax = plt.subplots(figsize=(6, 4))
        for impl in dict.fromkeys(r.implementation for r in rows if r.extra["curve"] == curve):
            pts = [r for r in rows if r.extra["curve"] == curve and r.implementation == impl]
            xs = [_x(r.extra["size"]) for r in pts]
            ax.plot(
                xs,
                [r.median_ms for r in pts],
                marker="o",
                label=impl,
                ls="-" if impl.startswith("jaxmocap") else "--",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        key = curve.split()[0] if curve.split()[0] in UNITS else curve
        ax.set_xlabel(UNITS.get(key, "size"))
        ax.set_ylabel("median time per call (ms)")
        ax.set_title(curve)
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"scaling_{curve.replace(' ', '_')}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        names.append(name)
    return names


def _x(size):
    if isinstance(size, str):
        w, h = size.split("x")
        return int(w) * int(h) / 1e6
    return size


def main() -> None:
    sizes, reps = common.sized(full=(FULL, 20), quick=(QUICK, 5))
    quick = common.is_quick()
    rows = []
    for fn, key in (
        (image, "image"),
        (cameras, "cameras"),
        (database, "posedb"),
        (batch, "batch"),
        (particles, "particles"),
    ):
        print(f"[scaling] {key} {sizes[key]}", flush=True)
        rows += fn(sizes[key], reps)
    out = common.RESULTS
    out.mkdir(parents=True, exist_ok=True)
    plots = plot(rows, out)
    summary = [
        f"{'Quick' if quick else 'Full'} sizes: {sizes}.",
        "Pose database: synthetic random packed codes of the real layout (real maps at 320k "
        "poses take hours to render here). Particles: the real stereo likelihood, not the "
        "whole filter step (one ~30 s compile per N).",
        "peak_rss_mib in each row's extra: the process high-water mark after that row "
        "(monotone; it includes everything measured before).",
        "Measured on a shared 2-core machine under contention from other engineers' jobs.",
        "Plots: " + ", ".join(plots),
    ]
    path = write_results("bench_scaling", rows, summary)
    # the plot list in the JSON, for the summary's links
    import json

    payload = json.loads((out / "bench_scaling.json").read_text())
    payload["plots"] = plots
    (out / "bench_scaling.json").write_text(json.dumps(payload, indent=2) + "\n")
    print(path.read_text())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes")
    args = parser.parse_args()
    if args.quick:
        os.environ[common.QUICK_ENV] = "1"
    main()
