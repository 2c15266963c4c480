"""Azad et al. 2007 Table I: per-frame cost of the stereo particle filter, 320x240 pair, N = 1000.

Rows: image processing line (both images), N forward kinematics + projections, N likelihood
evaluations, the full jitted filter step, and a whole frame (image pipeline + blob tracker +
filter step). Baseline in the same run: the same FK + projection + edge likelihood in
vectorised NumPy (batched over particles). Paper: 14 / 23 / 29 / 66 ms on a 3 GHz CPU.

    python benchmarks/bench_stereo_pf.py
"""

import dataclasses
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent / "experiments"))
from azad_render import config, load  # noqa: E402

from benchmarks._common import Row, sized, time_call, time_compile, write_results  # noqa: E402
from jaxmocap import blobs  # noqa: E402
from jaxmocap._config import enable_side_device  # noqa: E402
from jaxmocap.body import fk  # noqa: E402
from jaxmocap.pf import cues  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams, segment_cv  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

CLIP, FRAMES = "humanoid3d_punch", 40


def numpy_fk_project_edge(chain_np, limbs_np, cams_np, q, edges):
    """Batched NumPy: FK of the limb links (3x3 + t), projection, bilinear edge SAD cue."""
    parents, o_rot, o_t, axis, dof = chain_np
    n = q.shape[0]
    w = q[:, 3:6]
    th = np.linalg.norm(w, axis=1)[:, None, None] + 1e-12
    k = np.zeros((n, 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    k -= k.transpose(0, 2, 1)
    k /= th
    root = np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * (k @ k)
    rots, trans = [], []
    for i, p in enumerate(parents):
        a = axis[i]
        kk = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        if dof[i] >= 0:
            t_ = q[:, dof[i]][:, None, None]
            local = o_rot[i] @ (np.eye(3) + np.sin(t_) * kk + (1 - np.cos(t_)) * (kk @ kk))
        else:
            local = np.broadcast_to(o_rot[i], (n, 3, 3))
        if p < 0:
            rots.append(root @ local)
            trans.append(root @ o_t[i] + q[:, :3])
        else:
            rots.append(rots[p] @ local)
            trans.append(np.einsum("nij,j->ni", rots[p], o_t[i]) + trans[p])
    if len(limbs_np) == 4:  # (link, p0, p1, radius): round limbs only
        limbs_np = (
            *limbs_np,
            np.asarray(limbs_np[3]),
            np.tile([1.0, 0.0, 0.0], (len(limbs_np[0]), 1)),
        )
    link, p0, p1, rad, dep, side = limbs_np
    r = np.stack([rots[i] for i in link], 1)
    t = np.stack([trans[i] for i in link], 1)
    a = np.einsum("nlij,lj->nli", r, p0) + t
    b = np.einsum("nlij,lj->nli", r, p1) + t
    total = np.zeros(n)
    for (K, R, tc), g in zip(cams_np, edges, strict=True):
        xa, xb = a @ R.T + tc, b @ R.T + tc
        f = K[0, 0]
        pa = f * xa[..., :2] / xa[..., 2:] + K[:2, 2]
        pb = f * xb[..., :2] / xb[..., 2:] + K[:2, 2]
        d = pb - pa
        d /= np.linalg.norm(d, axis=-1, keepdims=True) + 1e-12
        nrm = np.stack([-d[..., 1], d[..., 0]], -1)
        # silhouette half-width of the (elliptic) cross-section seen along the midpoint ray
        ax = xb - xa
        ax /= np.linalg.norm(ax, axis=-1, keepdims=True)
        sd = np.einsum("nlij,lj->nli", r, side) @ R.T
        fr = np.cross(ax, sd)
        u = np.cross(ax, 0.5 * (xa + xb))
        u /= np.linalg.norm(u, axis=-1, keepdims=True)
        h = np.sqrt((rad * np.sum(u * sd, -1)) ** 2 + (dep * np.sum(u * fr, -1)) ** 2)
        h = np.where(dep == rad, rad, h)
        ra, rb = f * h / xa[..., 2], f * h / xb[..., 2]
        tt = (np.arange(12) + 0.5) / 12
        pts = []
        for s in (1, -1):
            st, en = pa + s * nrm * ra[..., None], pb + s * nrm * rb[..., None]
            pts.append(st[..., None, :] * (1 - tt[:, None]) + en[..., None, :] * tt[:, None])
        pts = np.stack(pts, 2).reshape(n, -1, 2)
        h, w_ = g.shape
        x0, y0 = np.floor(pts[..., 0]).astype(int), np.floor(pts[..., 1]).astype(int)
        fx, fy = pts[..., 0] - x0, pts[..., 1] - y0
        gp = np.pad(g, 1)

        def at(x, y, gp=gp, h=h, w_=w_):
            return gp[np.clip(y + 1, 0, h + 1), np.clip(x + 1, 0, w_ + 1)]

        val = (at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx) * (1 - fy) + (
            at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx
        ) * fy
        total += -(1 - val.mean(1)) / (2 * cues.SIGMA_G**2)
    return total


def main():
    enable_side_device()  # as the CLI: live's host-side calls on a second CPU device
    d = load(CLIP, FRAMES)
    cams = make_cameras(config(CLIP, FRAMES), jnp.float32)
    seg = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))
    params = sp.make_params(cams, images=sp.Images(segment=seg))
    obs = sp.observe_sequence(params, d["frames"])
    first = jax.tree.map(lambda a: a[0], obs)
    state, _ = sp.init(params, jax.random.key(0), first)
    parts = state.particles.particles
    lik = params.likelihood
    rows = []

    # 1. image processing line, both images (OpenCV, host)
    frame = d["frames"][5]
    med, mn = time_call(
        lambda: [segment_cv(seg, frame[i]) for i in range(2)], n=sized(full=100, quick=10)
    )
    rows.append(Row("image processing line, 320x240 pair", "OpenCV (segment_cv x2)", med, mn, 100))
    # 2. N FK + projection (jit, vmap over particles)
    limbs = lik.limbs

    def fk_proj(x):
        def one(s):
            tr = fk(lik.model.chain, lik.full_q(s))
            a, b = cues.limb_endpoints(limbs, tr)

            def cam(c):
                return cues.project_limbs(c, a, b, cues.silhouette_radius(c, limbs, tr, a, b))

            return jax.vmap(cam)(lik.cams)

        return jax.vmap(one)(x)

    f1 = jax.jit(fk_proj)
    c1 = time_compile(lambda: f1(parts))
    med, mn = time_call(lambda: f1(parts))
    rows.append(Row("1000 FK + projection", "jaxmocap jit(vmap)", med, mn, 50, c1))
    # 3. N likelihood evaluations (FK + projection + edge sampling + distance cue)
    f2 = jax.jit(jax.vmap(lik, in_axes=(0, None)))
    c2 = time_compile(lambda: f2(parts, first))
    med, mn = time_call(lambda: f2(parts, first))
    rows.append(
        Row("1000 likelihood evaluations (incl. FK)", "jaxmocap jit(vmap)", med, mn, 50, c2)
    )
    # NumPy baseline of FK + projection + edge cue
    ch = lik.model.chain
    chain_np = (
        [t[0] for t in ch.topology],
        np.asarray(ch.joint_origin)[:, :3, :3].astype(np.float64),
        np.asarray(ch.joint_origin)[:, :3, 3].astype(np.float64),
        np.asarray(ch.joint_axis, np.float64),
        [t[2] for t in ch.topology],
    )
    limbs_np = (list(limbs.link), np.asarray(limbs.p0), np.asarray(limbs.p1),
                np.asarray(limbs.radius), np.asarray(limbs.depth),
                np.asarray(limbs.side))  # fmt: skip
    cams_np = [(np.asarray(c.K, np.float64), np.asarray(c.R, np.float64),
                np.asarray(c.t, np.float64)) for c in cams]  # fmt: skip
    qn = np.asarray(jax.vmap(lik.full_q)(parts), np.float64)
    edges = np.asarray(first.edges, np.float64)
    ref = numpy_fk_project_edge(chain_np, limbs_np, cams_np, qn, edges)
    ours = np.asarray(jax.jit(jax.vmap(lambda s: eqx_replace(lik)(s, first)))(parts), np.float64)
    med, mn = time_call(
        lambda: numpy_fk_project_edge(chain_np, limbs_np, cams_np, qn, edges),
        n=sized(full=20, quick=3),
    )
    note = f"max |ll diff| vs jaxmocap edge-only {np.abs(ref - ours).max():.2e}"
    rows.append(Row("1000 likelihood evaluations (edge cue, incl. FK)", "NumPy batched", med, mn,
                    20, notes=note))  # fmt: skip
    # 4. full filter step (jit): resample + predict + weigh + estimate
    c3 = time_compile(lambda: sp.filter_step(params, state, first))
    med, mn = time_call(lambda: sp.filter_step(params, state, first))
    rows.append(Row("filter step N=1000 (resample, predict, guided proposal, weigh)",
                    "jaxmocap jit", med, mn, 50, c3))  # fmt: skip
    # 4a. the same program compiled with stereo_pf.COMPILER_OPTIONS (XLA's classic CPU
    # emitters, as init_top_level and run_top_level are); against 4 in the same run
    top = eqx.filter_jit(sp.filter_step, compiler_options=sp.COMPILER_OPTIONS)
    c3b = time_compile(lambda: top(params, state, first))
    med, mn = time_call(lambda: top(params, state, first))
    dq = float(np.abs(np.asarray(top(params, state, first)[1].q)
                      - np.asarray(sp.filter_step(params, state, first)[1].q)).max())
    rows.append(Row("filter step N=1000, COMPILER_OPTIONS (classic CPU emitters)", "jaxmocap jit",
                    med, mn, 50, c3b,
                    notes=f"compile {c3b / c3:.2f}x of the XLA-defaults row; "
                          f"max |q diff| {dq:.1e}"))
    # 4b. the same step without the guided proposal (Azad's filter), and the proposal alone
    paper = sp.make_params(cams, images=sp.Images(segment=seg), **sp.AZAD_FILTER)
    c4 = time_compile(lambda: sp.filter_step(paper, state, first))
    med, mn = time_call(lambda: sp.filter_step(paper, state, first))
    rows.append(Row("filter step N=1000, Azad (no guided proposal, zero-padded edges, no "
                    "support cue)", "jaxmocap jit", med, mn, 50, c4))  # fmt: skip
    swivel = params.filter.proposal  # SwivelProposal(inner=GuidedProposal)
    prop = swivel.inner
    f5 = eqx.filter_jit(prop)
    key = jax.random.key(1)
    c5 = time_compile(lambda: f5(parts, first, key))
    med, mn = time_call(lambda: f5(parts, first, key))
    rows.append(Row(f"guided proposal: {prop.n_guided(len(parts))} particles x {prop.n_steps} "
                    "min-norm GN steps", "jaxmocap jit(vmap)", med, mn, 50, c5))  # fmt: skip
    jumps = eqx.filter_jit(dataclasses.replace(swivel, inner=None))
    c5b = time_compile(lambda: jumps(parts, first, key))
    med, mn = time_call(lambda: jumps(parts, first, key))
    rows.append(Row(f"elbow-swivel jumps: {round(swivel.fraction * len(parts))} particles "
                    "(FK + 2 arm rotations)", "jaxmocap jit(vmap)", med, mn, 50, c5b))  # fmt: skip
    # 5. run over the sequence (lax.scan), per frame
    sp.run(params, state, obs)
    med_r, mn_r = time_call(lambda: sp.run(params, state, obs), n=sized(full=5, quick=1), warmup=1)
    rows.append(Row(f"filter over {FRAMES} frames (lax.scan), per frame", "jaxmocap jit scan",
                    med_r / FRAMES, mn_r / FRAMES, 5))  # fmt: skip
    # 6. whole live frame: image pipeline + blob tracker + filter step
    bstate = blobs.init(sp.BLOB_PARAMS)
    pts_valid = {}

    def live():
        nonlocal bstate
        o, bstate = sp.observe(params, frame, bstate)
        pts_valid["v"] = o.valid
        return sp.filter_step(params, state, o)

    med, mn = time_call(live, n=sized(full=50, quick=5))
    rows.append(Row("whole frame: image line + blobs + filter step", "jaxmocap (host + jit)", med,
                    mn, 50))  # fmt: skip
    # 6b. the same with the parameters closed over (stereo_pf.compile_step), sequential
    step_fn = sp.compile_step(params)
    step_fn(state, first)

    def live_closed():
        nonlocal bstate
        o, bstate = sp.observe(params, frame, bstate)
        return step_fn(state, o)

    med, mn = time_call(live_closed, n=sized(full=50, quick=5))
    rows.append(Row("whole frame, compiled step (params closed over)", "jaxmocap (host + jit)",
                    med, mn, 50))  # fmt: skip
    # 7. the live stream (stereo_pf.live): frame t+1's host work overlaps frame t's filter step;
    # per frame over the clip's frames after the anchor frame (initialisation excluded)
    frames = list(d["frames"])
    t0 = sp.anchor_frame(obs)
    per_frame = []
    for _ in range(sized(full=4, quick=2)):
        stamps = []
        for _t, est in sp.live(params, jax.random.key(0), iter(frames)):
            if est is not None:
                jax.block_until_ready(est.q)
            stamps.append(time.perf_counter())
        # stamps[t]: when frame t's estimate was ready; frames t0+2.. are steady-state steps
        steady = np.diff(stamps[t0 + 1 :])
        per_frame.append(steady)
    per_frame = np.concatenate(per_frame[1:])  # the first pass compiles
    rows.append(Row(f"live stream (stereo_pf.live, host/device overlap), per frame over "
                    f"{len(steady)} frames", "jaxmocap (host + jit)",
                    1e3 * float(np.median(per_frame)), 1e3 * float(np.min(per_frame)),
                    len(per_frame)))  # fmt: skip
    summary = [
        "Paper (Azad Table I, 3 GHz CPU, 2007): image line 14 ms, 1000 FK + projection 23 ms, "
        "1000 likelihoods 29 ms, total 66 ms.",
        "Load average (1, 5, 15 min) at the end of the run: "
        + ", ".join(f"{x:.2f}" for x in os.getloadavg())
        + " (2 cores).",
    ]
    write_results("bench_stereo_pf", rows, summary)
    for r in rows:
        print(r)


def eqx_replace(lik):
    import dataclasses

    return dataclasses.replace(lik, use_distance=False, edge_outside=None, use_support=False)


if __name__ == "__main__":
    main()
