"""Where the milliseconds of the shipped colour-shirt step go (issue 21), with the floor of
each stage: the shipped ``shirt.step`` (two 640x480 cameras, the shipped defaults) on the three
kinds of frame it meets, then its stages as separately jitted calls of the module-level step
functions of :mod:`jaxmocap.trackers.shirt` on the same inputs, what ``jax.vmap`` does to the
two starts (LM iterations per start alone and vmapped; ``lax.cond`` / ``while`` census of the
traced programs), and measured floors (dispatch of an empty jitted call, memory bandwidth).

Writes ``docs/results/realtime_profile.json`` (all numbers) and prints a summary; the
discussion is ``docs/results/realtime_profile.md``.

    python -m benchmarks.profile_realtime [--setup PATH.npz] [--reps N] [--out PATH.json]

``--setup``: a set-up stored by ``bench_shirt.save_setup`` (skips rendering the database).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import bench_shirt
from benchmarks._common import machine, time_call
from jaxmocap.color.pose_assisted import patch_distance_maps
from jaxmocap.ik import solve_ik
from jaxmocap.ik import view_anchors as _view_anchors
from jaxmocap.trackers import shirt as S

OUT = Path(__file__).parents[1] / "docs" / "results" / "realtime_profile.json"


def _census(jaxpr, counts=None) -> dict:
    """Primitive counts in a closed jaxpr, sub-jaxprs included (cond/while/select_n ...)."""
    counts = {} if counts is None else counts
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        counts[name] = counts.get(name, 0) + 1
        for v in eqn.params.values():
            subs = v if isinstance(v, (tuple, list)) else [v]
            for sub in subs:
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    _census(sub.jaxpr, counts)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    _census(sub, counts)
    return counts


def _pick(c: dict) -> dict:
    return {k: c.get(k, 0) for k in ("cond", "while", "select_n", "scan", "dot_general")}


def first_round(p, ctx, q_start, plain):
    """What ``shirt.rounds`` does per start, as one call: ``ik_round`` from ``q_start``, the
    result re-rendered, and its ``agreement``."""
    q1, c_obs, v_obs = S.ik_round(p, ctx, q_start, S.render_views(p, ctx, q_start), plain)
    hits = S.render_views(p, ctx, q1)
    return q1, c_obs, v_obs, hits, S.agreement(p, ctx, hits)


def _t(fn, reps):
    med, mn = time_call(fn, n=reps, warmup=1)
    return {"median_ms": round(med, 3), "min_ms": round(mn, 3)}


def floors(reps: int) -> dict:
    """Measured: an empty jitted call's round trip; read bandwidth (100 MB float32 sum)."""
    f = jax.jit(lambda x: x + 1)
    x = jnp.zeros(())
    big = np.ones(25_000_000, np.float32)
    med, mn = time_call(lambda: big.sum(), n=10, warmup=1)
    return {
        "empty_jit_call": _t(lambda: f(x), 200),
        "read_100MB_numpy_sum": {
            "median_ms": round(med, 3),
            "min_ms": round(mn, 3),
            "GB_per_s_min_time": round(0.1 / (mn / 1e3), 1),
        },  # fmt: skip
    }


def shirt_profile(s: dict, reps: int) -> dict:
    p, state0, frames = s["params"], s["state"], s["frames"]
    dt = state0.q.dtype
    res: dict = {"config": {k: getattr(p, k) for k in bench_shirt.PAPER_FRAME}}
    res["config"].update(work_size=p.search.work_size, n_cams=p.n_cams, db_size=int(p.db.size),
                         image=list(frames.shape[1:3]), n_patches=p.garment.n_patches)  # fmt: skip

    # the three kinds of frame: reacquisition (state of init: first frame / after a loss:
    # held start + reacquire_passes extra rounds), fresh (tracked < reacquire_frames: held
    # start), steady (tracked)
    t0 = time.perf_counter()
    st, out = S.step(p, state0, frames)
    jax.block_until_ready(out.q)
    res["step_compile_plus_first_call_s"] = round(time.perf_counter() - t0, 2)
    states = {"reacquisition": state0, "fresh": st}
    valid = [bool(out.valid)]
    for _ in range(p.rounds.reacquire_frames):
        st, out = S.step(p, st, frames)
        valid.append(bool(out.valid))
    states["steady"] = st
    res["valid_sequence"] = valid
    res["tracked_of_states"] = {k: int(v.tracked) for k, v in states.items()}
    res["step"] = {k: _t(lambda v=v: S.step(p, v, frames), reps) for k, v in states.items()}
    # the same frames with traced geom kinds in the renders (``static_kinds=False``: every
    # primitive evaluated and selected per geom; the shipped default renders with static kinds)
    import dataclasses

    pk = dataclasses.replace(p, rounds=dataclasses.replace(p.rounds, static_kinds=False))
    t0 = time.perf_counter()
    jax.block_until_ready(S.step(pk, state0, frames)[1].q)
    res["traced_kinds_compile_plus_first_call_s"] = round(time.perf_counter() - t0, 2)
    res["step_traced_kinds"] = {
        k: _t(lambda v=v: S.step(pk, v, frames), reps) for k, v in states.items()
    }
    res["traced_kinds_max_abs_dq_vs_shipped"] = {
        k: float(jnp.max(jnp.abs(S.step(pk, v, frames)[1].q - S.step(p, v, frames)[1].q)))
        for k, v in states.items()
    }
    # the dispatch floor of any call taking the parameters (pytree flattening, DB included)
    empty = eqx.filter_jit(lambda p, st: st.q + 0)
    res["filter_jit_call_with_params_floor"] = _t(lambda: empty(p, state0), reps * 4)

    # the stages, separately jitted, on the steady state's inputs
    st = states["steady"]
    loc = eqx.filter_jit(lambda p, st, fr: S.locate_and_classify(p, st, fr, None))
    dbf = eqx.filter_jit(lambda p, v: S.database_pose(p, v, dt))
    glo = eqx.filter_jit(lambda p, db: S.global_placement(p, db, dt))
    ctxf = eqx.filter_jit(S.round_context)
    views = loc(p, st, frames)
    db = dbf(p, views)
    q_g = glo(p, db)
    ctx = ctxf(p, st, views, db.okq, q_g)
    stages = {}
    stages["1 search + crop + classify (locate_and_classify)"] = _t(
        lambda: loc(p, st, frames), reps
    )
    stages["2 DB query + blend (database_pose)"] = _t(lambda: dbf(p, views), reps)
    stages["3 global placement (global_placement)"] = _t(lambda: glo(p, db), reps)
    stages["- round context (crop grids, widened prior)"] = _t(
        lambda: ctxf(p, st, views, db.okq, q_g), reps
    )
    render = eqx.filter_jit(S.render_views)
    hits = render(p, ctx, q_g)
    stages["4a render r^b, both crops (render_views)"] = _t(lambda: render(p, ctx, q_g), reps)
    P = p.garment.n_patches
    edt = eqx.filter_jit(lambda hits: [patch_distance_maps(h, P, dt) for h in hits.patch])
    ctx_k = ctxf(pk, st, views, db.okq, q_g)
    stages["4a' render r^b, both crops, traced geom kinds"] = _t(
        lambda: render(pk, ctx_k, q_g), reps
    )
    ws = p.search.work_size
    stages[f"4b EDT, {P} patches x {ws}^2, both crops"] = _t(lambda: edt(hits), reps)
    import cv2

    src = [
        (np.asarray(h) != k).astype(np.uint8) for h in hits.patch for k in range(1, P + 1)
    ]  # the same 2 x P masks, OpenCV's convention (distance to the nearest zero)
    stages[f"4b' cv2.distanceTransform (PRECISE), the same {2 * P} masks"] = _t(
        lambda: [cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for m in src], reps
    )
    pac = eqx.filter_jit(
        lambda p, ctx, hits: S.pose_assisted_centroids(p, ctx, hits.patch, jnp.array(False))
    )
    stages["4c EDT + pose-assisted classification + centroids, both crops"] = _t(
        lambda: pac(p, ctx, hits), reps
    )
    meas = pac(p, ctx, hits)
    c_obs, v_obs = meas.xy, meas.valid
    va = eqx.filter_jit(
        lambda p, ctx, q, hits: _view_anchors(
            p.body.chain, p.anchors, p.cams, q, hits.patch, hits.point, ctx.uvs
        )
    )
    anchors = va(p, ctx, q_g, hits)
    stages["4d per-view anchors"] = _t(lambda: va(p, ctx, q_g, hits), reps)

    @eqx.filter_jit
    def ik(p, ctx, anchors, c_obs, v_obs, q):
        return solve_ik(p.body.chain, p.cams, anchors, c_obs, v_obs, ctx.q_g, ctx.q_h, ctx.cov,
                        q, robust=p.rounds.robust)  # fmt: skip

    stages["4e full IK (solve_ik, robust, one start)"] = _t(
        lambda: ik(p, ctx, anchors, c_obs, v_obs, q_g), reps
    )
    round_ = eqx.filter_jit(S.ik_round)
    stages["4 one round = 4c + 4d + 4e (ik_round)"] = _t(lambda: round_(p, ctx, q_g, hits), reps)
    first = eqx.filter_jit(first_round)
    fal = jnp.array(False)
    stages["5 first_round, one start (render + round + render + agreement)"] = _t(
        lambda: first(p, ctx, q_g, fal), reps
    )
    starts = jnp.stack([q_g, st.q])
    plain = jnp.stack([fal, fal])
    firstv = eqx.filter_jit(
        lambda p, ctx, qs, pl: jax.vmap(lambda q, b: first_round(p, ctx, q, b))(qs, pl)
    )
    stages["5v first_round, 2 starts under vmap (shipped until session 11)"] = _t(
        lambda: firstv(p, ctx, starts, plain), reps
    )
    rounds = eqx.filter_jit(S.rounds)
    zero, one = jnp.asarray(0), jnp.asarray(1)
    stages["6 rounds, steady frame, first rounds only (2 starts)"] = _t(
        lambda: rounds(p, st, ctx, zero), reps
    )
    ctx_f = ctxf(p, states["fresh"], views, db.okq, q_g)
    stages["6f rounds, fresh frame, first rounds only (3 starts)"] = _t(
        lambda: rounds(p, states["fresh"], ctx_f, zero), reps
    )
    q1, co, vo, h1, agr = rounds(p, st, ctx, zero)
    stages["7 rounds, steady frame, 2 starts + 1 more round (the shipped steady frame)"] = _t(
        lambda: rounds(p, st, ctx, one), reps
    )

    @eqx.filter_jit
    def finish(p, st, ctx, hits, v_obs, agreement):
        valid = S.frame_validity(p, ctx, v_obs, agreement)
        return valid, S.white_balance_refit(p, st, ctx, hits, valid)

    stages["8 validity + W* re-fit + references"] = _t(
        lambda: finish(p, st, ctx, h1, vo, agr), reps
    )
    res["stages_steady"] = stages
    res["compile_s"] = {
        "step": res["step_compile_plus_first_call_s"],
        "step, traced kinds": res["traced_kinds_compile_plus_first_call_s"],
    }

    # vmap and the LM loop: iterations per start alone and under vmap, time of each
    @eqx.filter_jit
    def ik_inputs(p, ctx, q, plain):
        hits = S.render_views(p, ctx, q)
        m = S.pose_assisted_centroids(p, ctx, hits.patch, plain)
        a = _view_anchors(p.body.chain, p.anchors, p.cams, q, hits.patch, hits.point, ctx.uvs)
        return a, m.xy, m.valid

    lm = {}
    ins = [ik_inputs(p, ctx, q, fal) for q in (q_g, st.q)]
    for name, q, (a, c, v) in zip(("blend start", "previous-pose start"), (q_g, st.q), ins,
                                  strict=True):  # fmt: skip
        sol = ik(p, ctx, a, c, v, q)
        timing = _t(lambda a=a, c=c, v=v, q=q: ik(p, ctx, a, c, v, q), reps)
        lm[name] = {"num_steps": int(sol.num_steps), **timing}
    stack = jax.tree.map(lambda *x: jnp.stack(x), *ins)
    ikv = eqx.filter_jit(
        lambda p, ctx, st3, qs: jax.vmap(
            lambda s3, q: solve_ik(
                p.body.chain,
                p.cams,
                s3[0],
                s3[1],
                s3[2],
                ctx.q_g,
                ctx.q_h,
                ctx.cov,
                q,
                robust=p.rounds.robust,
            )  # fmt: skip
        )(st3, qs)
    )
    solv = ikv(p, ctx, stack, starts)
    lm["both starts under vmap"] = {"num_steps": np.asarray(solv.num_steps).tolist(),
                                    **_t(lambda: ikv(p, ctx, stack, starts), reps)}  # fmt: skip
    lm["max_abs_dq_vmap_vs_alone"] = float(
        max(jnp.max(jnp.abs(solv.q[k] - ik(p, ctx, *ins[k], starts[k]).q)) for k in range(2))
    )
    res["lm_under_vmap"] = lm

    # census of the traced programs: conds that stay conds, conds turned into selects by vmap
    one = jax.make_jaxpr(lambda q, b: first_round(p, ctx, q, b))(q_g, fal)
    two = jax.make_jaxpr(lambda qs, bs: jax.vmap(lambda q, b: first_round(p, ctx, q, b))(qs, bs))(
        starts, plain
    )
    whole = jax.make_jaxpr(lambda st, fr: S._step(p, st, fr, None))(st, frames)
    res["census"] = {
        "first_round, one start": _pick(_census(one.jaxpr)),
        "first_round, vmap over 2 starts": _pick(_census(two.jaxpr)),
        "whole _step": _pick(_census(whole.jaxpr)),
        "whole _step, equations": sum(_census(whole.jaxpr).values()),
    }
    res["floors_inputs"] = {
        "frame_pair_MB": round(frames.size / 1e6, 2),
        "db_codes_MB": round(np.asarray(p.db.codes).nbytes / 1e6, 2),
        "rays_per_render_pair": int(p.n_cams * p.search.work_size**2),
        "edt_row_pass_candidate_ops_per_crop": int(P * p.search.work_size**3),
    }
    return res


def stereo_profile(reps: int) -> dict:
    """The stereo live frame's host side split (``stereo_pf.observe``: OpenCV image line of
    both images, the blob tracker + support maps + host-to-device copies) beside the compiled
    filter step; the step's own stages are ``bench_stereo_pf``'s rows."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent / "experiments"))
    from azad_render import config, load

    from jaxmocap import blobs
    from jaxmocap.segment import HSVInterval, SegmentParams, segment_cv
    from jaxmocap.synth.scene import make_cameras
    from jaxmocap.trackers import stereo_pf as sp

    clip, n_frames = "humanoid3d_punch", 40
    d = load(clip, n_frames)
    cams = make_cameras(config(clip, n_frames), jnp.float32)
    seg = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))
    params = sp.make_params(cams, images=sp.Images(segment=seg))
    obs = sp.observe_sequence(params, d["frames"])
    state, _ = sp.init(params, jax.random.key(0), jax.tree.map(lambda a: a[0], obs))
    frame = d["frames"][5]
    out = {"N": int(state.particles.particles.shape[0]), "image": list(frame.shape[1:3])}
    out["image line (segment_cv x2)"] = _t(lambda: [segment_cv(seg, frame[i]) for i in range(2)],
                                           reps * 4)  # fmt: skip
    bs = {"s": blobs.init(sp.BLOB_PARAMS)}

    def observe():
        o, bs["s"] = sp.observe(params, frame, bs["s"])
        return o.edges

    out["observe (image line + blobs + support + copies)"] = _t(observe, reps * 4)
    step_fn = sp.compile_step(params)
    o0 = jax.tree.map(lambda a: a[5], obs)
    jax.block_until_ready(step_fn(state, o0))
    out["filter step (compile_step)"] = _t(lambda: step_fn(state, o0), reps * 4)
    return out


def edt_in_step(s: dict, reps: int) -> dict:
    """The EDT of issue 21's session 8 against the library's previous formulation
    (``bench_distance._previous_edt_sq``) inside the shipped step, same run: stage 4b
    (2 x 20 patch masks of a steady frame's render) beside ``cv2.distanceTransform``, and the
    steady / fresh / reacquisition step with each EDT (alternating calls), with the largest
    difference between their outputs (the transform is exact, so 0 is expected)."""
    import cv2

    from benchmarks.bench_distance import _previous_edt_sq
    from jaxmocap.color import pose_assisted

    p, state0, frames = s["params"], s["state"], s["frames"]
    dt = state0.q.dtype
    P = p.garment.n_patches
    new_edt = pose_assisted.edt

    def previous_edt(masks, dtype=None):
        return jnp.sqrt(_previous_edt_sq(masks).astype(dtype or jnp.result_type(float)))

    res: dict = {"load_average_at_start": list(os.getloadavg())}
    st, _ = S.step(p, state0, frames)
    states = {"reacquisition": state0, "fresh": st}
    for _ in range(p.rounds.reacquire_frames):
        st, _ = S.step(p, st, frames)
    states["steady"] = st
    views = eqx.filter_jit(lambda p, st, fr: S.locate_and_classify(p, st, fr, None))(p, st, frames)
    db = eqx.filter_jit(lambda p, v: S.database_pose(p, v, dt))(p, views)
    q_g = eqx.filter_jit(lambda p, db: S.global_placement(p, db, dt))(p, db)
    ctx = eqx.filter_jit(S.round_context)(p, st, views, db.okq, q_g)
    hits = eqx.filter_jit(S.render_views)(p, ctx, q_g)
    patches = list(hits.patch)
    stages = {}
    for name, fn in (("session 8", new_edt), ("previous", previous_edt)):
        pose_assisted.edt = fn
        f = jax.jit(lambda ps, fn=fn: [patch_distance_maps(x, P, dt) for x in ps])
        stages[f"4b EDT, {P} patches x {p.search.work_size}^2, both crops: {name}"] = _t(
            lambda f=f: f(patches), reps * 2
        )
    src = [(np.asarray(x) != k).astype(np.uint8) for x in patches for k in range(1, P + 1)]
    stages[f"4b' cv2.distanceTransform (PRECISE), the same {2 * P} masks"] = _t(
        lambda: [cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for m in src],
        reps * 2,
    )
    res["stage_4b"] = stages
    # the whole step with each EDT: two jitted programs (the EDT is looked up at trace time)
    steps, outs = {}, {}
    for name, fn in (("session 8", new_edt), ("previous", previous_edt)):
        pose_assisted.edt = fn
        f = eqx.filter_jit(lambda p, st, fr: S._step(p, st, fr, None))
        jax.block_until_ready(f(p, state0, frames)[1].q)
        steps[name], outs[name] = f, {k: f(p, v, frames) for k, v in states.items()}
    pose_assisted.edt = new_edt
    timing = {k: {} for k in states}
    for _ in range(3):  # alternate the two programs to spread the machine's load over both
        for k, v in states.items():
            for name, f in steps.items():
                timing[k].setdefault(name, []).append(_t(lambda f=f, v=v: f(p, v, frames), reps))
    res["step"] = {
        k: {name: {"median_ms": float(np.median([r["median_ms"] for r in rs])),
                   "min_ms": float(np.min([r["min_ms"] for r in rs]))}
            for name, rs in by.items()}
        for k, by in timing.items()
    }  # fmt: skip
    res["max_abs_output_difference"] = {
        k: max(
            float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))
            for a, b in zip(jax.tree.leaves(outs["session 8"][k]),
                            jax.tree.leaves(outs["previous"][k]), strict=True)
        )
        for k in states
    }  # fmt: skip
    res["load_average_at_end"] = list(os.getloadavg())
    return res


def compile_by_stage(s: dict) -> dict:
    """Cold trace + lowering and XLA compile time (s) of the shipped step and of each stage as
    its own program, on a steady frame's inputs (no persistent cache: this script does not
    enable it). The stages share sub-programs (a round renders, transforms and solves), so
    their sum exceeds the step's; the step's own split says where its compile goes."""
    p, state0, frames = s["params"], s["state"], s["frames"]
    dt = state0.q.dtype
    res: dict = {"load_average_at_start": list(os.getloadavg())}

    def timed(fn, *args):
        t0 = time.perf_counter()
        lowered = eqx.filter_jit(fn).lower(*args)
        t1 = time.perf_counter()
        lowered.compile()
        t2 = time.perf_counter()
        return {"trace_lower_s": round(t1 - t0, 2), "compile_s": round(t2 - t1, 2)}

    st = state0
    views = eqx.filter_jit(lambda p, st, fr: S.locate_and_classify(p, st, fr, None))(p, st, frames)
    db = eqx.filter_jit(lambda p, v: S.database_pose(p, v, dt))(p, views)
    q_g = eqx.filter_jit(lambda p, db: S.global_placement(p, db, dt))(p, db)
    ctx = eqx.filter_jit(S.round_context)(p, st, views, db.okq, q_g)
    hits = eqx.filter_jit(S.render_views)(p, ctx, q_g)
    fal = jnp.array(False)
    starts, plain = jnp.stack([q_g, st.q]), jnp.stack([fal, fal])
    out = {}
    out["whole step (_step)"] = timed(lambda p, st, fr: S._step(p, st, fr, None), p, st, frames)
    out["1 locate_and_classify"] = timed(
        lambda p, st, fr: S.locate_and_classify(p, st, fr, None), p, st, frames
    )
    out["2 database_pose"] = timed(lambda p, v: S.database_pose(p, v, dt), p, views)
    out["3 global_placement"] = timed(lambda p, db: S.global_placement(p, db, dt), p, db)
    # (new lambdas: a function jitted above would come from the in-memory cache)
    out["4a render_views"] = timed(lambda p, ctx, q: S.render_views(p, ctx, q), p, ctx, q_g)
    out["4c pose_assisted_centroids, both crops"] = timed(
        lambda p, ctx, hits: S.pose_assisted_centroids(p, ctx, hits.patch, fal), p, ctx, hits
    )
    meas = S.pose_assisted_centroids(p, ctx, hits.patch, fal)
    c_obs, v_obs = meas.xy, meas.valid
    out["4e solve_ik (robust), one start"] = timed(
        lambda p, ctx, c, v, q: solve_ik(p.body.chain, p.cams, p.anchors, c, v, ctx.q_g, ctx.q_h,
                                         ctx.cov, q, robust=p.rounds.robust),
        p, ctx, c_obs, v_obs, q_g,
    )  # fmt: skip
    out["4 ik_round"] = timed(lambda *a: S.ik_round(*a), p, ctx, q_g, hits)
    out["5 first_round, one start"] = timed(lambda *a: first_round(*a), p, ctx, q_g, fal)
    out["5v first_round, 2 starts under vmap"] = timed(
        lambda p, ctx, qs, pl: jax.vmap(lambda q, b: first_round(p, ctx, q, b))(qs, pl),
        p, ctx, starts, plain,
    )  # fmt: skip
    out["7 rounds (2 starts + 1 more round)"] = timed(
        lambda p, st, ctx, k: S.rounds(p, st, ctx, k), p, st, ctx, jnp.asarray(1)
    )
    res["programs"] = out
    res["load_average_at_end"] = list(os.getloadavg())
    return res


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--setup", default=None)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--out", type=Path, default=OUT,
                    help=f"the JSON written (default {OUT.relative_to(OUT.parents[2])}; with "
                         "--edt / --compile the file whose key is replaced)")  # fmt: skip
    ap.add_argument("--edt", action="store_true",
                    help="only the EDT inside the step, session 8 vs previous (key 'edt_in_step' "
                         "of the JSON; the rest of the JSON is kept)")  # fmt: skip
    ap.add_argument(
        "--compile",
        action="store_true",
        help="only the cold compile time per program (key 'compile_by_stage')",
    )
    a = ap.parse_args()
    out = a.out
    if a.setup and out.resolve() == Path(a.setup).resolve():
        print(f"profile_realtime: --out {out} would write over the --setup scene; choose another "
              "path", file=sys.stderr)  # fmt: skip
        sys.exit(2)
    s = bench_shirt.load_setup(a.setup) if a.setup else bench_shirt.setup(640, 480)
    if a.compile:
        res = json.loads(out.read_text()) if out.exists() else {}
        res["compile_by_stage"] = {"machine": machine(), **compile_by_stage(s)}
        out.write_text(json.dumps(res, indent=1))
        print(json.dumps(res["compile_by_stage"], indent=1))
        return
    if a.edt:
        res = json.loads(out.read_text()) if out.exists() else {}
        res["edt_in_step"] = {"machine": machine(), **edt_in_step(s, a.reps)}
        out.write_text(json.dumps(res, indent=1))
        print(json.dumps(res["edt_in_step"], indent=1))
        return
    res = {"machine": machine(), "load_average_at_start": list(os.getloadavg())}
    res["floors"] = floors(a.reps)
    res["stereo"] = stereo_profile(a.reps)
    res["shirt"] = shirt_profile(s, a.reps)
    res["load_average_at_end"] = list(os.getloadavg())
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
