"""The appearance ladder (issue 37): which share of the visible shirt pixels gets its right
colour, per rung, on a test-world split (tune on dev).

    python -m benchmarks.experiments.appearance_ladder /work/world shirt_00 shirt_03 \
        [--poses EXPERIMENT_OUT --config NAME] [--every 3] [--out ladder.json]

Every frame updates the colour states; every ``--every``-th frame (both cameras, a 192 x 192
resample of twice the shirt's ground-truth bounding box) is scored: ``right`` = visible shirt
pixels classified as their colour / visible shirt pixels, ``room`` = other pixels classified
as shirt / crop pixels. The colour model is the ``robust`` set-up's (scribbles of the first
frames, shading-invariant distance 0.5-4, 16 room colours). Rungs:

* ``W0``: the colour model under the white balance of frame 0 (what the tracker starts with);
* ``oracle W``: one W per camera fitted to this frame's ground-truth colour ids (the best a
  single white balance can do);
* ``oracle W, pose prior``: the same with Wang's step-3 distance prior of the true patch map;
* ``patch, oracle pose``: the per-patch colour states (:mod:`jaxmocap.appearance`, the
  tracker's defaults) updated every frame from the true patch map, eroded, scored without
  a prior (step 1) and ``+ prior`` with the true patch map's distance prior (step 3);
* ``patch, tracked pose`` (with ``--poses``): the states updated from the render of the
  tracker's own pose on the frames it called valid, scored with the prior rendered there
  (the tracker's loop, minus the crop search).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SIDE = 192
PRIOR_SIDE = 96.0  # the shirt spans about half the crop: C = C_s / 96 per crop pixel


def _box(gt):
    ys, xs = np.nonzero(gt)
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    hh, hw = ys.max() - ys.min() + 1, xs.max() - xs.min() + 1
    y0, y1 = int(max(cy - hh, 0)), int(min(cy + hh, gt.shape[0]))
    x0, x1 = int(max(cx - hw, 0)), int(min(cx + hw, gt.shape[1]))
    yy = np.linspace(y0, y1 - 1, SIDE).round().astype(int)
    xx = np.linspace(x0, x1 - 1, SIDE).round().astype(int)
    return yy, xx


def run_sequence(folder: Path, poses: Path | None, every: int, opts: dict | None = None) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxmocap import appearance as ap
    from jaxmocap.color import ColorModel, classify
    from jaxmocap.color.pose_assisted import patch_distance_maps, pose_assisted_classify
    from jaxmocap.color.whitebalance import white_balance_from_ids
    from jaxmocap.experiment import cell
    from jaxmocap.render import render_uv
    from jaxmocap.sampling import erode_ids
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import shirt

    gain = (0.5, 4.0)
    seq = load_dataset(folder)
    cfg = {"body": "sequence", "garment": "sequence", "options": {}, "name": "ladder"}
    body = cell._body(cfg, folder)
    garment = cell._garment(cfg, body, folder)
    color = cell._scribbled_color_model(seq, garment, gain=gain)
    cids, pids = seq.groundtruth["colour_ids"], seq.groundtruth["patch_ids"]
    labels = np.stack([shirt.scribbles(m) for m in cids[0]])
    W0 = np.asarray(shirt.initial_white_balance(color, seq.frames[0], labels), np.float32)
    room = cell._scene_colors(seq, W0, 16)
    P = garment.n_patches
    pc = jnp.asarray(garment.patch_colour, jnp.int32)
    T, C = seq.frames.shape[:2]
    k = pc - 1
    start = ap.init_parts(color.mean[k], color.cov[k])
    tracked = None
    if poses is not None:
        d = np.load(poses)
        # the valid frames' poses (poses.npz holds every frame's estimate beside its flag)
        tracked = (np.where(d["valid"][:, None], d["q"], np.nan), d["valid"])

    def colour_of(patch):
        return jnp.where(patch > 0, pc[jnp.maximum(patch - 1, 0)], 0)

    opts = dict(opts or {})
    gate = opts.pop("gate", ap.GATE)
    t1, t3 = opts.pop("t1", 3.0), opts.pop("t3", 5.0)  # Wang's T of steps 1 and 3
    prior_scale = opts.pop("prior_scale", 6.0)  # Wang's C = 6 / s

    @jax.jit
    def update(state, img, parts, W):
        x = img.astype(jnp.float32) @ W.T
        st = ap.part_statistics(state, x, erode_ids(parts), gate=gate, shading=gain)
        return ap.update_parts(state, st, jnp.array(True), **opts)[0]

    @jax.jit
    def score(img, gtc, gtp, W, s_gt, s_tr, prior_tr):
        n = jnp.maximum(jnp.sum(gtc > 0), 1)

        def sc(ids):
            return jnp.stack([jnp.sum((gtc > 0) & (ids == gtc)) / n,
                              jnp.sum((gtc == 0) & (ids > 0)) / gtc.size])

        w = prior_scale / PRIOR_SIDE
        x = img.astype(jnp.float32) @ W.T
        eye = jnp.eye(3, dtype=jnp.float32)
        Wo = white_balance_from_ids(color, img, gtc, W)
        dist = patch_distance_maps(gtp, P, jnp.float32)
        out = [sc(classify(color, W, img, None, 3.0, gain, room)[0]),
               sc(classify(color, Wo, img, None, 3.0, gain, room)[0]),
               sc(pose_assisted_classify(color, Wo, img, dist, pc, w, None, 5.0, gain,
                                         room).colour)]
        for s, prior in ((s_gt, dist), (s_tr, patch_distance_maps(prior_tr, P, jnp.float32))):
            model = ColorModel(s.mean, s.cov, shading=gain)
            out.append(sc(colour_of(classify(model, eye, x, None, t1, gain, room)[0])))
            out.append(sc(colour_of(pose_assisted_classify(
                model, eye, x, prior, jnp.arange(1, P + 1), w, None, t3, gain, room).patch)))
        return jnp.stack(out)

    def tracked_patches(q, c, uv):
        return render_uv(body, garment, q, seq.cameras[c], uv).patch

    render = jax.jit(tracked_patches, static_argnums=(1,)) if tracked is not None else None
    s_gt = [start] * C
    s_tr = [start] * C
    rows = []
    for t in range(T):
        for c in range(C):
            gtc = np.asarray(cids[t, c]).astype(np.int32)
            if (gtc > 0).sum() < 200:
                continue
            gtp = np.asarray(pids[t, c]).astype(np.int32)
            yy, xx = _box(gtc)
            img = jnp.asarray(np.asarray(seq.frames[t, c])[yy][:, xx])
            gc, gp = jnp.asarray(gtc[yy][:, xx]), jnp.asarray(gtp[yy][:, xx])
            W = jnp.asarray(W0[c])
            prior_tr = gp
            if tracked is not None:
                uv = np.stack(np.meshgrid(xx, yy), -1).astype(np.float32)
                prior_tr = render(jnp.asarray(tracked[0][t], jnp.float32), c, jnp.asarray(uv))
            if t > 0 and t % every == 0:
                rows.append(np.asarray(score(img, gc, gp, W, s_gt[c], s_tr[c], prior_tr)))
            s_gt[c] = update(s_gt[c], img, gp, W)
            if tracked is not None and bool(tracked[1][t]):
                s_tr[c] = update(s_tr[c], img, prior_tr, W)
    return np.mean(rows, 0)


RUNGS = ["W0", "oracle W", "oracle W, pose prior", "patch, oracle pose",
         "patch, oracle pose + prior", "patch, tracked pose", "patch, tracked pose + prior"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--poses", help="an experiment output folder (its cells' poses.npz)")
    ap.add_argument("--config", default="patch")
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--out")
    ap.add_argument("--gate", type=float)
    ap.add_argument("--rate", type=float)
    ap.add_argument("--max-spread", type=float)
    ap.add_argument("--min-spread", type=float)
    ap.add_argument("--no-relight", action="store_true")
    ap.add_argument("--t1", type=float, help="step-1 threshold of the patch rungs (3)")
    ap.add_argument("--t3", type=float, help="step-3 threshold of the patch rungs (5)")
    ap.add_argument("--prior-scale", type=float, help="C s of the patch rungs (6)")
    a = ap.parse_args()
    opts = {k: v for k, v in (("gate", a.gate), ("rate", a.rate), ("max_spread", a.max_spread),
                              ("min_spread", a.min_spread), ("t1", a.t1), ("t3", a.t3),
                              ("prior_scale", a.prior_scale)) if v is not None}
    if a.no_relight:
        opts["relight"] = False
    table = {}
    for name in a.sequences:
        poses = None
        if a.poses:
            poses = Path(a.poses) / "cells" / f"{name}__{a.config}__0" / "poses.npz"
        m = run_sequence(Path(a.world) / name, poses, a.every, opts)
        rungs = RUNGS if poses is not None else RUNGS[:5]
        table[name] = {r: [round(float(v), 3) for v in m[i]] for i, r in enumerate(rungs)}
        print(name, json.dumps(table[name]), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
