"""Colour-shirt tracker speed (Wang et al. 2011): one two-camera frame step end to end, and the
same frame split into the paper's stages, each jitted and timed alone beside the NumPy/OpenCV
baseline of that stage where ``benchmarks/`` has one (measured in the same run).

Stages of the paper's frame (``jaxmocap.trackers.shirt.frame._step`` with the tracker's extensions
switched off by :func:`paper_frame` — per-view anchors, repeated IK rounds, robust centroid
loss, second IK start — rebuilt from the same library calls, both cameras per stage;
:func:`staged_step` composes them and :func:`stage_rows` checks that the composition
reproduces that ``shirt.step``; the tracker as shipped is timed end to end beside it):

1. histogram search (§4) on each full frame;
2. crop resampling, white balance and Gaussian classification (§5.2 step 1, with the
   reference-illumination fallback);
3. pose-database query (10-NN, tiny 40x40 map) and blend over cameras (step 2);
4. global placement: root guess + 6-DOF IK on ``r^b``'s patch centroids (step 2);
5. ``r^b`` rendered in each crop, one EDT per patch, pose-assisted classification and patch
   centroids (step 3);
6. full IK with the blend and temporal priors (step 4);
7. ``r*`` rendered, ``W*`` refitted, reference illuminations updated (step 5).

Baselines: 1 ``bench_color.np_search_cells``; 2 ``cv2.remap`` + ``bench_color.np_gemm_classify``
(no reference fallback); 3 ``bench_posedb.numpy_packed_knn`` (the 10-NN only); 5
:func:`numpy_pose_assisted` (without rendering ``r^b``); 6 ``scipy.optimize.least_squares``
on ``bench_ik``'s NumPy residual. Stages 4 and 7 have none.

Paper anchor: 120 ms per frame (two 640x480 cameras, Java, 2.4 GHz Core 2 Quad). Goal
(PERF-NOTES): <= 10 ms. Set-up: a ``DB_SIZE``-pose database (the paper uses 80,000; the fast
search's cost grows with it), white-light renders over a grey background, float32.
``JAXMOCAP_BENCH_QUICK=1``: 320x240 and a 500-pose database.
"""

from __future__ import annotations

import os
import time

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap import sampling
from jaxmocap.body import default_body
from jaxmocap.camera import look_at, stack_cameras
from jaxmocap.color import (
    classify_views_with_references,
    histogram_search,
    maybe_add_reference,
    white_balance_from_ids,
)
from jaxmocap.color.classify import THRESHOLD
from jaxmocap.color.pose_assisted import (
    POSE_THRESHOLD,
    PRIOR_SCALE,
    patch_centroids,
    patch_distance_maps,
    pose_assisted_classify,
)
from jaxmocap.garment import default_garment
from jaxmocap.ik import IKCovariances, anchors_from_garment, initial_root, solve_global, solve_ik
from jaxmocap.posedb._sample import SamplingConfig, canonical_camera, sample_poses
from jaxmocap.posedb._search import estimate_pose, make_posedb
from jaxmocap.render import (
    TINY_SIZE,
    render_rgb,
    render_uv,
    resample_ids,
    tiny_hits,
    tiny_id_maps,
    window_from_mask,
)
from jaxmocap.trackers import shirt
from jaxmocap.trackers.shirt import frame as shirt_frame

PAPER_MS = 120.0  # Wang et al. §7: 120 ms per frame, two 640x480 cameras
GOAL_MS = 10.0  # docs/PERF-NOTES.md
DB_SIZE = 2000
SIGMA_C, SIGMA_B, SIGMA_P = 2.0, 0.3, 0.5  # isotropic IK covariances (px, rad, rad), the demo's
STAGES = (
    "1 histogram search",
    "2 crop + white balance + classification",
    "3 DB query (10-NN) + blend",
    "4 global placement (6-DOF IK)",
    "5 r^b + EDT + pose-assisted classification",
    "6 full IK",
    "7 W* re-fit + references",
)


# ----------------------------------------------------------------------------- NumPy baselines


def numpy_pose_assisted(mean, cov, W, crop, prior, patch_colour, C, T):
    """Same maths in NumPy + OpenCV: Mahalanobis by one GEMM per colour, exact EDT per patch
    (cv2.distanceTransform, DIST_MASK_PRECISE), argmin over patches."""
    x = crop.reshape(-1, 3) @ W.T
    P = np.linalg.inv(cov)
    m = np.stack(
        [
            np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", x - mu, Pk, x - mu), 0))
            for mu, Pk in zip(mean, P, strict=True)
        ],
        -1,
    )
    d = np.stack(
        [
            cv2.distanceTransform(
                (prior != p).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            ).reshape(-1)
            for p in range(1, len(patch_colour) + 1)
        ],
        -1,
    )
    cost = m[:, patch_colour - 1] + C * d
    best = cost.argmin(-1)
    return np.where(cost.min(-1) < T, best + 1, 0).reshape(prior.shape)


# ----------------------------------------------------------------------------- set-up


# The tracker's extensions beyond the paper's one-pass frame, switched off for the stage
# breakdown (only those this version's shirt.Rounds has).
PAPER_FRAME = {
    "view_anchors": False,
    "ik_passes": 1,
    "robust": None,
    "temporal_start": False,
    "reacquire_start": False,
    "reacquire_passes": 0,
    "reacquire_frames": 0,
    "held_start": False,
}


def paper_frame(params):
    """``params`` with the tracker's extensions off (:data:`PAPER_FRAME`): the frame of Wang
    §5.2 that the seven stages rebuild (one pose-assisted classification, one IK)."""
    import dataclasses
    import inspect

    rounds = {k: v for k, v in PAPER_FRAME.items()
              if k in inspect.signature(shirt.Rounds).parameters}
    return dataclasses.replace(params, rounds=dataclasses.replace(params.rounds, **rounds))


def _cameras(width: int, height: int):
    fx = 554.0 * width / 640
    return [
        look_at([2.75, y, 1.3], [0.0, 0.0, 1.15], width=width, height=height, fx=fx)
        for y in (-0.75, 0.75)
    ]


def _assemble(model, garment, color, db, frames, W0, q_true, width, height) -> dict:
    params = shirt.make_params(
        color,
        model,
        garment,
        stack_cameras(_cameras(width, height)),
        anchors_from_garment(model, garment),
        IKCovariances.isotropic(SIGMA_C, SIGMA_B, SIGMA_P, model.n_dof),
        db,
    )
    state = shirt.init(params, jnp.asarray(W0), jnp.zeros(model.n_dof, jnp.float32))
    return {"params": params, "state": state, "frames": jnp.asarray(frames),
            "q_true": jnp.asarray(q_true)}  # fmt: skip


def save_setup(path, s: dict) -> None:
    """Store a :func:`setup` (database maps and poses, colour model, frames, ``W0``) as .npz."""
    p = s["params"]
    maps = np.asarray(tiny_id_maps(p.body, p.garment, p.db.poses, p.canon))
    np.savez_compressed(
        path, maps=maps, poses=np.asarray(p.db.poses), mean=np.asarray(p.color.mean),
        cov=np.asarray(p.color.cov), frames=np.asarray(s["frames"]), W0=np.asarray(s["state"].W),
        q_true=np.asarray(s["q_true"]),
    )  # fmt: skip


def load_setup(path) -> dict:
    """A :func:`setup` stored by :func:`save_setup` (no rendering, no fitting)."""
    from jaxmocap.color import ColorModel

    d = np.load(path)
    model = default_body()
    garment = default_garment(model)
    db = make_posedb(d["maps"], d["poses"], garment.n_colours)
    color = ColorModel(jnp.asarray(d["mean"]), jnp.asarray(d["cov"]), garment.colour_names)
    h, w = d["frames"].shape[1:3]
    return _assemble(model, garment, color, db, d["frames"], d["W0"], d["q_true"], w, h)


def setup(width: int = 640, height: int = 480, db_size: int = DB_SIZE, seed: int = 0) -> dict:
    """A two-camera scene: database of ``db_size`` random poses, colour model from white-light
    renders, one rendered frame pair (pose 7 of the database, over grey), ``W0`` from its
    scribbles; returns ``params``, ``state``, ``frames`` (2, height, width, 3) and ``q_true``."""
    model = default_body()
    garment = default_garment(model)
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(model.chain.lower)[6:], np.asarray(model.chain.upper)[6:]
    pool = np.zeros((300, model.n_dof), np.float32)
    pool[:, 6:] = np.clip(rng.uniform(-0.6, 0.6, (300, model.n_dof - 6)), lo, hi)
    poses = sample_poses(SamplingConfig(size=db_size, yaw_range=0.5), model, pool)
    db = make_posedb(
        np.asarray(tiny_id_maps(model, garment, jnp.asarray(poses), canonical_camera())),
        poses,
        garment.n_colours,
    )
    cams_l = _cameras(width, height)
    root = np.zeros(model.n_dof, np.float32)
    root[2] = 0.85
    color = shirt.fit_color_model_from_renders(model, garment, poses[:5] + root, cams_l[0])
    bg = jnp.full((height, width, 3), 128, jnp.uint8)
    q = jnp.asarray(poses[7] + root)
    outs = [render_rgb(model, garment, q, c, bg) for c in cams_l]
    frames = jnp.stack([o[0] for o in outs])
    labels = np.stack([shirt.scribbles(np.asarray(o[1].colour)) for o in outs])
    W0 = shirt.initial_white_balance(color, np.asarray(frames), labels)
    return _assemble(model, garment, color, db, frames, W0, q, width, height)


# ----------------------------------------------------------------------------- the stages


def _cam(params, i):
    return jax.tree.map(lambda a: a[i], params.cams)


@eqx.filter_jit
def stage_search(params, frames):
    """1: ``(x', y', s')`` per camera -> crop windows (n_cams, 4), ``s'`` and ``found``."""
    dt = params.cams.K.dtype
    wins, s, found = [], [], []
    for i in range(params.n_cams):
        r = histogram_search(frames[i], None, scales=params.search.scales)
        wins.append(
            shirt.crop_window(
                r.x.astype(dt), r.y.astype(dt), r.s.astype(dt), params.search.crop_factor
            )
        )
        s.append(r.s.astype(dt)), found.append(r.found)
    return jnp.stack(wins), jnp.stack(s), jnp.stack(found)


@eqx.filter_jit
def stage_classify(params, state, frames, windows):
    """2: crops (n_cams, n, n, 3) and the step-1 classification (batched over cameras, the
    reference fallback under one ``cond``)."""
    min_fraction = {} if params.ablations.adaptive_white_balance else {"min_fraction": 0.0}
    crops = jnp.stack([
        shirt.sample_bilinear(frames[i], shirt.crop_uv(windows[i], params.search.work_size))
        for i in range(params.n_cams)
    ])  # fmt: skip
    cls = classify_views_with_references(
        params.color, state.refs, state.W, crops, None, THRESHOLD, **min_fraction
    )
    return crops, cls


@eqx.filter_jit
def stage_database(params, ids, windows, found):
    """3: per camera (one vmap) the 10-NN blend ``q_db``, its tiny patch map and canonical
    window, the query window in the image; joint angles averaged over the cameras that found
    the shirt."""
    dt = params.cams.K.dtype

    def one(ids_i, window, found_i):
        win_c = window_from_mask(ids_i > 0)
        q_db = estimate_pose(params.db, resample_ids(ids_i, win_c, TINY_SIZE))[0].astype(dt)
        hits, win_db = tiny_hits(params.body, params.garment, q_db, params.canon)
        win_q = sampling.crop_to_image(win_c, window, params.search.work_size)
        return q_db, win_q, hits.patch, win_db, found_i & (jnp.sum(ids_i > 0) > 0)

    q_dbs, win_qs, tiny_patch, win_dbs, okq = jax.vmap(one)(ids, windows, found)
    wq = okq.astype(dt) / jnp.maximum(jnp.sum(okq), 1)
    q_b = jnp.concatenate([jnp.zeros(6, dt), jnp.sum(wq[:, None] * q_dbs[:, 6:], axis=0)])
    return q_dbs, win_qs, tiny_patch, win_dbs, okq, q_b


@eqx.filter_jit
def stage_global(params, q_dbs, win_qs, tiny_patch, win_dbs, okq, q_b):
    """4: ``r^b``'s patch centroids moved into the query windows, root guess, 6-DOF IK."""
    dt = q_b.dtype
    P = params.garment.n_patches
    cons = jax.vmap(lambda t, w: patch_centroids(t, P, w, min_pixels=2, dtype=dt))(
        tiny_patch, win_qs
    )
    c_xy, c_vis = cons.xy, cons.valid & okq[:, None]
    guesses = jax.vmap(lambda *a: shirt_frame._root_guess(params, *a))(
        params.cams, q_dbs, win_dbs, win_qs
    )
    root0, _ = initial_root(
        params.cams, params.body.chain, params.anchors, c_xy, c_vis, q_b, guesses[jnp.argmax(okq)]
    )
    return solve_global(
        params.body.chain, params.cams, params.anchors, c_xy, c_vis, q_b, root0, params.cov.centroid
    ).q


@eqx.filter_jit
def stage_pose_assisted(params, crops, windows, s_found, W, okq, q_g):
    """5: measured patch centroids (n_cams, P, 2), their validity and the frame's validity
    (one vmap over the cameras)."""
    n, P, dt = params.search.work_size, params.garment.n_patches, q_g.dtype

    def one(cam, crop, window, s_i, W_i):
        uv = shirt.crop_uv(window, n)
        rb = render_uv(params.render_body, params.garment, q_g, cam, uv).patch
        dist = patch_distance_maps(rb, P, dt)
        if params.ablations.pose_prior:
            weight, T = PRIOR_SCALE / s_i * (window[2] / n), POSE_THRESHOLD
        else:
            weight, T = shirt.TIE_BREAK_WEIGHT, THRESHOLD
        pa = pose_assisted_classify(
            params.color, W_i, crop, dist, params.garment.patch_colour, weight, None, T
        )
        return patch_centroids(pa.patch, P, window, dtype=dt)

    c = jax.vmap(one)(params.cams, crops, windows, s_found, W)
    c_obs, v_obs = c.xy, c.valid & okq[:, None]
    valid = jnp.any(okq) & (jnp.sum(v_obs) >= shirt.MIN_VALID_PATCHES)
    return c_obs, v_obs, valid


@eqx.filter_jit
def stage_ik(params, state, c_obs, v_obs, valid, q_g):
    """6: ``q*`` (the previous pose when the frame is not valid)."""
    q_h = jnp.where(state.valid, state.q, q_g)
    sol = solve_ik(
        params.body.chain, params.cams, params.anchors, c_obs, v_obs, q_g, q_h, params.cov, q_g
    )
    return jnp.where(valid, sol.q, state.q)


@eqx.filter_jit
def stage_refit(params, state, crops, windows, W_cls, okq, valid, q_star):
    """7: ``W*`` per camera (one vmap) from ``r*`` and the updated reference illuminations."""

    def one(cam, refs_i, crop, window, W_i, ok_i):
        uv = shirt.crop_uv(window, params.search.work_size)
        r_star = sampling.erode_ids(
            render_uv(params.render_body, params.garment, q_star, cam, uv).colour
        )
        W_star = white_balance_from_ids(
            params.color, crop, r_star, W_i, None, min_pixels=shirt.REFERENCE_PIXELS
        )
        ok = valid & ok_i & jnp.all(jnp.isfinite(W_star))
        W_star = jnp.where(ok, W_star, W_i)
        refs_i2, _ = maybe_add_reference(refs_i, W_star)
        return W_star, jax.tree.map(lambda a, b: jnp.where(ok, a, b), refs_i2, refs_i)

    return jax.vmap(one)(params.cams, state.refs, crops, windows, W_cls, okq)


def staged_step(params, state, frames, upto: int = len(STAGES)) -> dict:
    """Stages 1..``upto`` in order (each its own jitted call); every intermediate, by name."""
    r = {}
    r["windows"], r["s_found"], r["found"] = stage_search(params, frames)
    if upto >= 2:
        r["crops"], r["cls"] = stage_classify(params, state, frames, r["windows"])
    if upto >= 3:
        db = stage_database(params, r["cls"].ids, r["windows"], r["found"])
        r["q_dbs"], r["win_qs"], r["tiny_patch"], r["win_dbs"], r["okq"], r["q_b"] = db
    if upto >= 4:
        r["q_g"] = stage_global(params, *db)
    if upto >= 5:
        r["c_obs"], r["v_obs"], r["valid"] = stage_pose_assisted(
            params, r["crops"], r["windows"], r["s_found"], r["cls"].W, r["okq"], r["q_g"]
        )
    if upto >= 6:
        r["q_star"] = stage_ik(params, state, r["c_obs"], r["v_obs"], r["valid"], r["q_g"])
    if upto >= 7:
        r["W_new"], r["refs"] = stage_refit(
            params, state, r["crops"], r["windows"], r["cls"].W, r["okq"], r["valid"], r["q_star"]
        )
    return r


def _stage_calls(params, state, frames, r, upto: int) -> list:
    """One zero-argument call per stage 1..``upto``, on the intermediates ``r``."""
    db = tuple(r.get(k) for k in ("q_dbs", "win_qs", "tiny_patch", "win_dbs", "okq", "q_b"))
    calls = [
        lambda: stage_search(params, frames),
        lambda: stage_classify(params, state, frames, r["windows"]),
        lambda: stage_database(params, r["cls"].ids, r["windows"], r["found"]),
        lambda: stage_global(params, *db),
        lambda: stage_pose_assisted(
            params, r["crops"], r["windows"], r["s_found"], r["cls"].W, r["okq"], r["q_g"]
        ),
        lambda: stage_ik(params, state, r["c_obs"], r["v_obs"], r["valid"], r["q_g"]),
        lambda: stage_refit(
            params, state, r["crops"], r["windows"], r["cls"].W, r["okq"], r["valid"], r["q_star"]
        ),
    ]
    return calls[:upto]


def _baseline_calls(params, state, frames, r, upto: int) -> dict:
    """NumPy/OpenCV/SciPy baselines of stages 1, 2, 3, 5, 6 (those <= ``upto``) on the same
    inputs, both cameras: {stage index: (label, call)}."""
    from scipy.optimize import least_squares

    from benchmarks import bench_color, bench_posedb
    from jaxmocap.posedb import pack_map

    x64 = jax.config.jax_enable_x64
    from benchmarks import bench_ik  # sets jax_enable_x64 at import: restored below

    jax.config.update("jax_enable_x64", x64)
    n_cams, n = params.n_cams, params.search.work_size
    imgs = [np.asarray(frames[i]) for i in range(n_cams)]
    mean = np.asarray(params.color.mean, np.float64)
    cov = np.asarray(params.color.cov, np.float64)
    base = {
        0: ("NumPy cells (bench_color)",
            lambda: [bench_color.np_search_cells(im, params.search.scales) for im in imgs]),
    }  # fmt: skip
    if upto >= 2:
        wins = np.asarray(r["windows"], np.float64)
        f = (np.arange(n) + 0.5) / n
        maps = [
            tuple(m.astype(np.float32) for m in np.meshgrid(w[0] + f * w[2], w[1] + f * w[3]))
            for w in wins
        ]
        W_state = np.asarray(state.W, np.float64)

        def classify_np():
            out = []
            for i in range(n_cams):
                crop = cv2.remap(
                    imgs[i], *maps[i], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                )
                out.append(bench_color.np_gemm_classify(crop, W_state[i], mean, cov))
            return out

        base[1] = ("cv2.remap + NumPy GEMM (bench_color)", classify_np)
    if upto >= 3:
        db = params.db
        rows = np.asarray(db.codes).transpose(0, 2, 1).reshape(-1, db.codes.shape[1])
        rows = np.ascontiguousarray(rows[: db.size])
        ids = r["cls"].ids
        qcodes = [
            np.asarray(pack_map(resample_ids(ids[i], window_from_mask(ids[i] > 0), TINY_SIZE)))
            for i in range(n_cams)
        ]
        base[2] = ("NumPy packed 10-NN (bench_posedb)",
                   lambda: [bench_posedb.numpy_packed_knn(rows, qc) for qc in qcodes])  # fmt: skip
    if upto >= 5:
        W_cls = np.asarray(r["cls"].W, np.float64)
        crops = np.asarray(r["crops"], np.float64)
        priors = [
            np.asarray(render_uv(params.render_body, params.garment, r["q_g"], _cam(params, i),
                                 shirt.crop_uv(r["windows"][i], n)).patch)
            for i in range(n_cams)
        ]  # fmt: skip
        Cs = [PRIOR_SCALE / float(r["s_found"][i]) * (wins[i][2] / n) for i in range(n_cams)]
        pc = np.asarray(params.garment.patch_colour)
        base[4] = ("NumPy + cv2.distanceTransform",
                   lambda: [numpy_pose_assisted(mean, cov, W_cls[i], crops[i], priors[i], pc,
                                                Cs[i], POSE_THRESHOLD)
                            for i in range(n_cams)])  # fmt: skip
    if upto >= 6:
        c = params.cov
        diag = lambda a: np.diag(a) if a.ndim == 2 else a  # noqa: E731 - full or diagonal
        vc = float(np.asarray(c.centroid)[0, 0])
        vb, vp = diag(np.asarray(c.blend, np.float64)), diag(np.asarray(c.prior, np.float64))
        q_g = np.asarray(r["q_g"], np.float64)
        q_h = np.asarray(state.q, np.float64) if bool(state.valid) else q_g
        residual, z0, to_q = bench_ik.make_np_residual(
            params.body.chain, params.cams, params.anchors, np.asarray(r["c_obs"], np.float64),
            np.asarray(r["v_obs"]), q_g, q_h, vc, vb, vp,
        )  # fmt: skip
        base[5] = ("scipy least_squares (lm, NumPy, FD jac; bench_ik)",
                   lambda: to_q(least_squares(residual, z0, method="lm", xtol=1e-10,
                                              ftol=1e-10).x))  # fmt: skip
    return base


def _agreement(k: int, out, r, params) -> dict:
    """How closely baseline ``k``'s result matches jaxmocap's stage (independent oracle)."""
    if k == 0:  # (x', y', s') per camera
        xy = np.asarray(r["windows"][:, :2] + r["windows"][:, 2:] / 2)
        got = np.array([[float(o[0]), float(o[1])] for o in out])
        s = np.array([float(o[2]) for o in out])
        return {"search_max_dxy_px": float(np.abs(got - xy).max()),
                "search_max_ds_px": float(np.abs(s - np.asarray(r["s_found"])).max())}  # fmt: skip
    if k == 1:
        return {"classify_agreement": float(np.mean(np.stack(out) == np.asarray(r["cls"].ids)))}
    if k == 5:
        ok = np.asarray(r["valid"])
        return {"ik_max_dq_vs_scipy": float(np.abs(out - np.asarray(r["q_star"])).max()) if ok
                else float("nan")}  # fmt: skip
    return {}


def stage_rows(
    params, state, frames, reps: int = 10, baselines: bool = True, upto: int = len(STAGES)
) -> tuple[list[Row], dict]:
    """Time stages 1..``upto`` of the paper's frame (:func:`paper_frame` of ``params``; warm
    median/min of ``reps`` calls; the cold first call of all of them together is the staged
    pipeline's row) beside their baselines. With every stage, also the end-to-end
    ``shirt.step`` of the paper's frame and of the tracker as configured by ``params`` (cold
    and warm), and the check that the staged pipeline reproduces the former. Returns rows and
    a dict of checks (baseline agreement, max |dq| ...)."""
    size = f"2 cameras {frames.shape[2]}x{frames.shape[1]}"
    pp = paper_frame(params)
    rows = []
    t0 = time.perf_counter()
    r = jax.block_until_ready(staged_step(pp, state, frames, upto))  # compiles each stage
    staged_compile_s = time.perf_counter() - t0
    calls = _stage_calls(pp, state, frames, r, upto)
    base = _baseline_calls(pp, state, frames, r, upto) if baselines else {}
    checks = {}
    for k, (name, call) in enumerate(zip(STAGES[:upto], calls, strict=True)):
        med, mn = time_call(call, n=reps, warmup=1)
        rows.append(Row(f"stage {name}, {size}", "jaxmocap jit", med, mn, reps, None,
                        "cold: see the staged pipeline"))  # fmt: skip
        if k in base:
            label, fn = base[k]
            nb = max(3, reps // 2)
            bm, bn = time_call(fn, n=nb, warmup=1)
            checks.update(_agreement(k, fn(), r, pp))
            rows.append(Row(f"stage {name}, {size}", label, bm, bn, nb))
    sm, sn = time_call(lambda: staged_step(pp, state, frames, upto), n=reps, warmup=1)
    label = f"frame step, {size}" if upto == len(STAGES) else f"stages 1-{upto}, {size}"
    rows.append(Row(label, f"jaxmocap, {upto} separately jitted stages (paper's frame)", sm, sn,
                    reps, staged_compile_s * 1e3, "sum of the stages + dispatch"))  # fmt: skip
    if upto < len(STAGES):
        return rows, checks
    for what, prm in (("paper's frame", pp), ("tracker as shipped", params)):
        comp = time_compile(lambda prm=prm: shirt.step(prm, state, frames))
        med, mn = time_call(lambda prm=prm: shirt.step(prm, state, frames), n=reps, warmup=1)
        ext = {k: getattr(prm, k) for k in PAPER_FRAME if hasattr(prm, k)}
        note = f"{ext}; paper: {PAPER_MS:.0f} ms, goal {GOAL_MS:.0f} ms"
        rows.append(Row(f"frame step, {size}", f"jaxmocap jit (shirt.step, {what})", med, mn,
                        reps, comp, note))  # fmt: skip
    new_state, out = shirt.step(pp, state, frames)
    checks.update({
        "max_abs_dq_star": float(jnp.max(jnp.abs(out.q - r["q_star"]))),
        "max_abs_dq_blend": float(jnp.max(jnp.abs(out.q_blend - r["q_g"]))),
        "max_abs_dW": float(jnp.max(jnp.abs(new_state.W - r["W_new"]))),
        "same_valid": bool(out.valid == r["valid"]),
        "same_visible": bool(jnp.all(out.visible == r["v_obs"])),
    })  # fmt: skip
    return rows, checks


def main():
    width, height = sized(full=(640, 480), quick=(320, 240))
    db_size = sized(full=DB_SIZE, quick=500)
    reps = sized(full=10, quick=3)
    s = setup(width, height, db_size)
    rows, checks = stage_rows(s["params"], s["state"], s["frames"], reps)
    step = [r for r in rows if r.implementation.endswith("(shirt.step, paper's frame)")][0]
    shipped = [r for r in rows if r.implementation.endswith("(shirt.step, tracker as shipped)")][0]
    ours = {r.kernel: r for r in rows if r.implementation == "jaxmocap jit"}
    summary = [
        f"paper-frame step (two {width}x{height} cameras, DB {db_size} poses): "
        f"{step.median_ms:.1f} ms "
        f"median, {step.min_ms:.1f} ms min (paper {PAPER_MS:.0f} ms, goal {GOAL_MS:.0f} ms); "
        f"sum of the 7 stage medians {sum(r.median_ms for r in ours.values()):.1f} ms; the "
        f"tracker as shipped (extra IK rounds etc.) {shipped.median_ms:.1f} ms median",
        f"staged pipeline vs shirt.step: max |dq*| {checks['max_abs_dq_star']:.2e}, "
        f"max |dq_b| {checks['max_abs_dq_blend']:.2e}, max |dW| {checks['max_abs_dW']:.2e}, "
        f"same validity {checks['same_valid']}, same visible patches {checks['same_visible']}",
        "baseline agreement: " + ", ".join(f"{k} {v:.3g}" for k, v in checks.items()
                                           if k.startswith(("search", "classify", "ik_"))),
    ]  # fmt: skip
    for kern, r in ours.items():
        line = f"{kern}: {r.median_ms:.2f} ms"
        b = [x for x in rows if x.kernel == kern and x.implementation != "jaxmocap jit"]
        if b:
            line += f" vs {b[0].median_ms:.2f} ms {b[0].implementation} "
            line += f"({b[0].median_ms / r.median_ms:.1f}x)"
        summary.append(line)
    summary.append(f"Load average (1, 5, 15 min) at the end of the run: "
                   f"{', '.join(f'{x:.2f}' for x in os.getloadavg())} (2 cores).")  # fmt: skip
    print(write_results("bench_shirt", rows, summary).read_text())


if __name__ == "__main__":
    main()
