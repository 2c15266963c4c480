"""The pixel ladder of the learned observation (issue 49): which share of the visible shirt
pixels the model trained on our own renders gives their right colour, on test-world sequences,
with the crops and metric of ``appearance_ladder.py`` (a 192 x 192 resample of twice the shirt's
ground-truth bounding box, every ``--every``-th frame, both cameras).

    python -m benchmarks.experiments.learned_ladder /work/world shirt_00 shirt_03 \
        [--every 3] [--prior-scale 6] [--out ladder.json] [--figure labels.png] \
        [--poses EXPERIMENT_OUT --config learned]

Per sequence the model is trained (or loaded from the cache) for the sequence's own body and
garment files as ``jaxmocap learn`` does by default (:func:`jaxmocap.observe.learn`: fine-tuned
from the bundled model; no scribbles, nothing of the sequence's pixels). Rungs:

* ``learned``: each pixel its most probable class (step 1 of the shirt tracker on the model);
* ``learned + true pose prior``: Wang's step 3 on the model, with the true patch map's distance
  prior: a pixel goes to the patch p minimising ``-log p(colour(p)) + C d(p)`` unless
  ``-log p(not shirt)`` is lower (``C = prior_scale / 96`` per crop pixel);
* ``learned + tracked pose prior`` (with ``--poses``): the same with the prior rendered at the
  shirt tracker's own pose on the frames it reported valid (no prior on the others);
* ``skin``: of each skin part's true pixels, the share the model gives that part (head, left
  hand, right hand), and of the true shirt/room pixels the share taken for skin.

``right`` = visible shirt pixels given their colour / visible shirt pixels; ``room`` = other
pixels taken for shirt / crop pixels (appearance_ladder.py's definitions).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.experiments.appearance_ladder import PRIOR_SIDE, _box


def sequence_inputs(folder: Path):
    from jaxmocap.experiment import cell
    from jaxmocap.synth.dataset import load_dataset

    seq = load_dataset(folder)
    cfg = {"body": "sequence", "garment": "sequence", "options": {}, "name": "ladder"}
    body = cell._body(cfg, folder)
    garment = cell._garment(cfg, body, folder)
    return seq, body, garment


def run_sequence(folder: Path, every: int, prior_scale: float, model_path: str | None = None,
                 figure_frames: list | None = None, poses: Path | None = None) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxmocap.color.pose_assisted import patch_distance_maps
    from jaxmocap.observe import classes_of, learn, load, log_probs, skin_label_map

    seq, body, garment = sequence_inputs(folder)
    if model_path:
        obs, _ = load(model_path)
    else:
        obs, _, _ = learn(body, garment, progress=False)
    classes = classes_of(body, garment)
    K, P = classes.n_colours, garment.n_patches
    pc = jnp.asarray(garment.patch_colour, jnp.int32)
    cids, pids = seq.groundtruth["colour_ids"], seq.groundtruth["patch_ids"]
    w = prior_scale / PRIOR_SIDE

    tracked = None
    if poses is not None:  # the tracker's own poses (poses.npz of an experiment cell)
        d = np.load(poses)
        tracked = (np.asarray(d["q"], np.float32), np.asarray(d["valid"], bool))

    @jax.jit
    def step3(lp, prior):
        dist = patch_distance_maps(prior, P, jnp.float32)
        cost = -lp[..., pc] + w * jnp.moveaxis(dist, 0, -1)
        not_shirt = -jnp.log(jnp.exp(lp[..., 0]) + jnp.sum(jnp.exp(lp[..., K + 1:]), -1))
        return jnp.where(jnp.min(cost, -1) < not_shirt, pc[jnp.argmin(cost, -1)], 0)

    @jax.jit
    def score(img, gtc, gtp, gskin):
        lp = log_probs(obs, img)
        n = jnp.maximum(jnp.sum(gtc > 0), 1)

        def sc(ids):
            return jnp.stack([jnp.sum((gtc > 0) & (ids == gtc)) / n,
                              jnp.sum((gtc == 0) & (ids > 0)) / gtc.size])

        cls = jnp.argmax(lp, -1)
        col = jnp.where(cls <= K, cls, 0)
        dist = patch_distance_maps(gtp, P, jnp.float32)
        cost = -lp[..., pc] + w * jnp.moveaxis(dist, 0, -1)  # (h, w, P)
        not_shirt = -jnp.log(jnp.exp(lp[..., 0]) + jnp.sum(jnp.exp(lp[..., K + 1:]), -1))
        best = jnp.argmin(cost, -1)
        keep = jnp.min(cost, -1) < not_shirt
        col3 = jnp.where(keep, pc[best], 0)
        skin = skin_label_map(classes, cls)
        parts = [jnp.stack([jnp.sum((gskin == k) & (skin == k)), jnp.sum(gskin == k)])
                 for k in (1, 2, 3)]
        false_skin = jnp.sum((gskin == 0) & (skin > 0)) / gtc.size
        return sc(col), sc(col3), jnp.stack(parts), false_skin, col, lp

    rows, skin_rows, fs, pics = [], [], [], []
    T, C = seq.frames.shape[:2]
    # skin ground truth: the world's patch/colour ids have no skin; the ray caster's render of
    # the true pose gives the skin parts (same body file, same cameras)
    from jaxmocap.observe.classes import labels_of
    from jaxmocap.render import render_uv

    q_true = seq.groundtruth["q"]

    @jax.jit
    def skin_truth(q, cam, uv):
        h = render_uv(body, garment, q, cam, uv)
        return skin_label_map(classes, labels_of(classes, h.geom, h.colour))

    for t in range(T):
        for c in range(C):
            gtc = np.asarray(cids[t, c]).astype(np.int32)
            if (gtc > 0).sum() < 200 or t == 0 or t % every:
                continue
            gtp = np.asarray(pids[t, c]).astype(np.int32)
            yy, xx = _box(gtc)
            img = jnp.asarray(np.asarray(seq.frames[t, c])[yy][:, xx], jnp.float32)
            uv = jnp.asarray(np.stack(np.meshgrid(xx, yy), -1), jnp.float32)
            gsk = skin_truth(jnp.asarray(q_true[t], jnp.float32), seq.cameras[c], uv)
            gc = jnp.asarray(gtc[yy][:, xx])
            s1, s3, parts, f, col, lp = score(img, gc, jnp.asarray(gtp[yy][:, xx]), gsk)
            row = [np.asarray(s1), np.asarray(s3)]
            if tracked is not None:  # the prior at the tracker's pose where it reported valid
                prior = jnp.zeros(gc.shape, jnp.int32)
                if tracked[1][t]:
                    prior = render_uv(body, garment, jnp.asarray(tracked[0][t]), seq.cameras[c],
                                      uv).patch
                ids = step3(lp, prior)
                n = max(int(jnp.sum(gc > 0)), 1)
                row.append(np.array([float(jnp.sum((gc > 0) & (ids == gc))) / n,
                                     float(jnp.sum((gc == 0) & (ids > 0))) / gc.size]))
            rows.append(np.concatenate(row))
            skin_rows.append(np.asarray(parts))
            fs.append(float(f))
            if figure_frames is not None and len(pics) < 2:
                pics.append((np.asarray(img, np.uint8), gtc[yy][:, xx], np.asarray(col),
                             np.asarray(garment.colours)))
    m = np.mean(rows, 0)
    sk = np.sum(skin_rows, 0)
    if figure_frames is not None:
        figure_frames.extend(pics)
    out = {}
    if tracked is not None:
        out["learned + tracked pose prior"] = [round(float(m[4]), 3), round(float(m[5]), 3)]
    return {"learned": [round(float(m[0]), 3), round(float(m[1]), 3)],
            "learned + true pose prior": [round(float(m[2]), 3), round(float(m[3]), 3)],
            **out,
            "skin found (head, left, right)": [round(float(a / max(b, 1)), 3) for a, b in sk],
            "false skin": round(float(np.mean(fs)), 4)}


def colour_figure(frames: list, path: str) -> None:
    """Rows of (crop, true colours, the model's colours) for a results record, each in its
    sequence's shirt colours."""
    import cv2

    def pal(colours):
        return np.concatenate([[[40, 40, 40]], np.round(colours * 255)]).astype(np.uint8)

    rows = [np.concatenate([img, pal(c)[gt], pal(c)[pred]], 1) for img, gt, pred, c in frames]
    cv2.imwrite(path, np.concatenate(rows, 0)[..., ::-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--prior-scale", type=float, default=6.0,
                    help="C s of step 3 (Wang's 6: the tracker's observer_prior = 1)")
    ap.add_argument("--model", help="a trained model file (default: train for each sequence)")
    ap.add_argument("--out")
    ap.add_argument("--figure", help="PNG of crops, true colours and the model's colours")
    ap.add_argument("--poses", help="an experiment output folder: the rung with the prior at "
                    "the tracker's own pose (its cells' poses.npz)")
    ap.add_argument("--config", default="learned", help="the experiment's configuration")
    a = ap.parse_args()
    table, pics = {}, []
    for name in a.sequences:
        folder = Path(a.world) / name
        poses = None
        if a.poses:
            poses = Path(a.poses) / "cells" / f"{name}__{a.config}__0" / "poses.npz"
        table[name] = run_sequence(folder, a.every, a.prior_scale, a.model,
                                   pics if a.figure else None, poses)
        print(name, json.dumps(table[name]), flush=True)
    keys = [k for k in table[a.sequences[0]] if k.startswith("learned")]
    table["mean"] = {k: [round(float(np.mean([table[s][k][i] for s in a.sequences])), 3)
                         for i in (0, 1)] for k in keys}
    table["min"] = {k: round(float(np.min([table[s][k][0] for s in a.sequences])), 3)
                    for k in keys}
    print("mean", json.dumps(table["mean"]))
    if a.out:
        Path(a.out).write_text(json.dumps(table, indent=1))
    if a.figure:
        colour_figure(pics, a.figure)


if __name__ == "__main__":
    main()
