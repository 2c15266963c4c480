"""Where step 1 loses the shirt's pixels under the world's spot lamps (issue 17, DEV split).

    python -m benchmarks.experiments.shirt_classes /work/tw_dev_shirt [--every 10]

Every ``--every``-th frame, both cameras, inside twice the shirt's ground-truth bounding box:
the share of the visible shirt pixels classified as their colour (``right``) / another colour
(``wrong``) and the other pixels classified as shirt relative to the shirt's pixel count
(``room``; props, skin, walls), for the colour model of the experiment's ``robust`` set-up
(scribbles, shading-invariant distance, 16 room colours) under:

* ``W0``: the white balance of frame 0 (what the tracker starts with);
* ``oracle``: W fitted to this frame's ground-truth colour ids (the best one W per camera
  can do: a better W re-fit cannot beat it);
* ``oracle, quadrants``: one W per image quadrant of the box, each fitted to its own
  ground truth (a spatially varying white balance, two lamp colours);
* ``oracle`` with the step-1 threshold 4.5 instead of 3, without the room colours, and with
  the brightness range (0.25, 8) instead of (0.5, 4).
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main() -> None:
    import jax
    import jax.numpy as jnp

    from jaxmocap.color import classify
    from jaxmocap.color.whitebalance import white_balance_from_ids
    from jaxmocap.experiment import cell
    from jaxmocap.experiment.config import dataset_sequences
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import shirt

    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--out")
    a = ap.parse_args()
    gain = (0.5, 4.0)
    cfg = {"body": "sequence", "garment": "sequence", "options": {}}
    variants = ["W0", "oracle", "oracle, quadrants", "oracle, T=4.5", "oracle, no room",
                "oracle, gain 0.25-8"]
    table = {}
    for s in dataset_sequences(a.dataset):
        seq = load_dataset(s.folder)
        body = cell._body(cfg, s.folder)
        garment = cell._garment(cfg, body, s.folder)
        color = cell._scribbled_color_model(seq, garment, gain=gain)
        cids = seq.groundtruth["colour_ids"]
        labels = np.stack([shirt.scribbles(m) for m in cids[0]])
        W0 = np.asarray(shirt.initial_white_balance(color, seq.frames[0], labels))
        room = cell._scene_colors(seq, W0, 16)

        @jax.jit
        def run(img, gt, W0c, color=color, room=room):
            def score(ids):
                n = jnp.maximum(jnp.sum(gt > 0), 1)
                return jnp.stack([jnp.sum((gt > 0) & (ids == gt)) / n,
                                  jnp.sum((gt > 0) & (ids > 0) & (ids != gt)) / n,
                                  jnp.sum((gt == 0) & (ids > 0)) / n])

            def cls(W, im=img, thr=3.0, bg=room, g=gain, color=color):
                return classify(color, W, im, None, thr, g, bg)[0]

            Wo = white_balance_from_ids(color, img, gt, jnp.asarray(W0c))
            h, w = gt.shape
            quads = jnp.zeros_like(gt)
            for sl in (np.s_[: h // 2, : w // 2], np.s_[: h // 2, w // 2:],
                       np.s_[h // 2:, : w // 2], np.s_[h // 2:, w // 2:]):
                Wq = white_balance_from_ids(color, img[sl], gt[sl], Wo)
                quads = quads.at[sl].set(cls(Wq, img[sl]))
            return jnp.stack([score(cls(jnp.asarray(W0c))), score(cls(Wo)), score(quads),
                              score(cls(Wo, thr=4.5)), score(cls(Wo, bg=None)),
                              score(cls(Wo, g=(0.25, 8.0)))])

        rows = []
        for t in range(0, seq.frames.shape[0], a.every):
            for c in range(seq.frames.shape[1]):
                gt = np.asarray(cids[t, c]).astype(np.int32)
                ys, xs = np.nonzero(gt)
                if len(ys) < 200:
                    continue
                cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
                hh, hw = ys.max() - ys.min() + 1, xs.max() - xs.min() + 1
                y0, y1 = int(max(cy - hh, 0)), int(min(cy + hh, gt.shape[0]))
                x0, x1 = int(max(cx - hw, 0)), int(min(cx + hw, gt.shape[1]))
                # a fixed 192 x 192 resample of the box (one compile for every box)
                yy = np.linspace(y0, y1 - 1, 192).round().astype(int)
                xx = np.linspace(x0, x1 - 1, 192).round().astype(int)
                img = np.asarray(seq.frames[t, c])[yy][:, xx]
                rows.append(np.asarray(run(jnp.asarray(img), jnp.asarray(gt[yy][:, xx]),
                                           W0[c])))
        m = np.mean(rows, 0)
        table[s.name] = {v: [round(float(x), 3) for x in m[i]] for i, v in enumerate(variants)}
        print(s.name, json.dumps(table[s.name]), flush=True)
    allm = np.mean([[table[k][v] for v in variants] for k in table], 0)
    table["all"] = {v: [round(float(x), 3) for x in allm[i]] for i, v in enumerate(variants)}
    print("all", json.dumps(table["all"]))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
