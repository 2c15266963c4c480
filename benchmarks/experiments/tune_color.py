"""Tuning the colour model's covariances Sigma_k and the threshold T (docs/results/tuning.md).

Data (``tune_data.py shirt``): the rendered two-webcam clips with ground-truth colour-id maps.
The base colour model is the first training clip's scribble fit (Wang §5.1, as the demo);
each clip's white balance W0 is refitted against it from the scribbles of its first frame and
held fixed (the tracker then adapts W; that loop is not part of this loss). Pixels come from
the shirt's neighbourhood — the ground-truth body box enlarged by ``BOX_MARGIN``, about what
the tracker's crop holds — of every ``FRAME_STRIDE``-th frame and both cameras: ``N_PIXELS``
per image, half of them on the shirt. Loss: the soft classifier's cross-entropy
(:func:`jaxmocap.tune.color_loss`). Evaluated with the hard classifier (Wang's rule) on all
pixels of the held-out clips' boxes: misclassified fraction, and the split into shirt pixels
with a wrong or no colour and background pixels given a colour.

Writes ``tuning_color.json`` to the tune cache folder and ``docs/images/tuning_color.png``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import tune_data as data  # noqa: E402

from jaxmocap import tune  # noqa: E402
from jaxmocap._config import enable_compilation_cache  # noqa: E402
from jaxmocap.color import ColorModel, classify  # noqa: E402
from jaxmocap.trackers.shirt import initial_white_balance, scribbles  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FRAME_STRIDE = 5
N_PIXELS = 2000
BOX_MARGIN = 0.3
STEPS = 60
LEARNING_RATE = 0.05


def boxes(ids: np.ndarray):
    """(y0, y1, x0, x1) of the body pixels enlarged by BOX_MARGIN, clipped to the image."""
    ys, xs = np.nonzero(ids > 0)
    h, w = ids.shape
    dy, dx = BOX_MARGIN * (ys.max() - ys.min()), BOX_MARGIN * (xs.max() - xs.min())
    return (max(0, int(ys.min() - dy)), min(h, int(ys.max() + dy) + 1),
            max(0, int(xs.min() - dx)), min(w, int(xs.max() + dx) + 1))  # fmt: skip


def clip_images(clip: str, base: ColorModel):
    d = np.load(data.clip_file("shirt", clip))
    frames, ids = d["frames"], d["colour_ids"]
    labels = np.stack([scribbles(m) for m in ids[0]])
    W0 = np.asarray(initial_white_balance(base, frames[0], labels))
    out = []
    for t in range(0, frames.shape[0], FRAME_STRIDE):
        for c in range(frames.shape[1]):
            if not np.any(ids[t, c] > 0):
                continue
            y0, y1, x0, x1 = boxes(ids[t, c])
            out.append((frames[t, c, y0:y1, x0:x1], ids[t, c, y0:y1, x0:x1], W0[c]))
    return out


def sample(images, seed=0) -> tune.ColorData:
    rng = np.random.default_rng(seed)
    pix, lab, Ws = [], [], []
    for im, ids, W in images:
        flat, fl = im.reshape(-1, 3), ids.reshape(-1)
        fg = np.flatnonzero(fl > 0)
        n_fg = min(fg.size, N_PIXELS // 2)
        pick = np.concatenate(
            [
                rng.choice(fg, n_fg, replace=False),
                rng.choice(fl.size, N_PIXELS - n_fg, replace=fl.size < N_PIXELS),
            ]
        )
        pix.append(flat[pick]), lab.append(fl[pick]), Ws.append(W)
    return tune.ColorData(
        jnp.asarray(np.stack(pix), jnp.float64),
        jnp.asarray(np.stack(lab), jnp.int32),
        jnp.asarray(np.stack(Ws)),
    )


def hard_errors(model: ColorModel, T, images) -> dict:
    fn = jax.jit(lambda W, im: classify(model, W, im, threshold=T)[0])
    n = wrong = fg = fg_wrong = bg = bg_wrong = 0
    for im, ids, W in images:
        r = np.asarray(fn(jnp.asarray(W), jnp.asarray(im)))
        f = ids > 0
        n += ids.size
        wrong += int(np.sum(r != ids))
        fg += int(f.sum())
        fg_wrong += int(np.sum((r != ids) & f))
        bg += int((~f).sum())
        bg_wrong += int(np.sum((r != 0) & ~f))
    return {"error": wrong / n, "shirt_wrong": fg_wrong / fg, "background_as_colour": bg_wrong / bg}


def main(steps: int = STEPS) -> None:
    enable_compilation_cache()
    d0 = np.load(data.clip_file("shirt", data.SHIRT_TRAIN[0]))
    base = ColorModel(jnp.asarray(d0["color_mean"], jnp.float64),
                      jnp.asarray(d0["color_cov"], jnp.float64))  # fmt: skip
    train_imgs = [x for c in data.SHIRT_TRAIN for x in clip_images(c, base)]
    held_imgs = [x for c in data.SHIRT_HELDOUT for x in clip_images(c, base)]
    train, held = sample(train_imgs, 0), sample(held_imgs, 1)
    print(f"{len(train_imgs)} training / {len(held_imgs)} held-out images, {N_PIXELS} pixels each")
    theta0 = tune.color_theta(base, 3.0)
    loss = jax.jit(tune.color_loss)
    held_curve = []

    def callback(i, value, theta):
        held_curve.append(float(loss(theta, base, held)))
        if i % 10 == 0:
            print(f"step {i:3d}: train {value:.4f}, held-out {held_curve[-1]:.4f}", flush=True)

    t0 = time.perf_counter()
    theta, losses = tune.fit(lambda th: tune.color_loss(th, base, train), theta0, steps,
                             LEARNING_RATE, callback)  # fmt: skip
    elapsed = time.perf_counter() - t0
    tuned, T = tune.color_model(theta, base)
    res = {"steps": steps, "learning_rate": LEARNING_RATE, "seconds": elapsed,
           "train_loss": losses.tolist(), "heldout_loss": held_curve, "threshold": float(T),
           "cov_det_ratio": (np.linalg.det(np.asarray(tuned.cov))
                             / np.linalg.det(np.asarray(base.cov))).tolist(),
           "names": list(base.names)}  # fmt: skip
    for label, (m, t) in (("paper fit, T = 3", (base, 3.0)), ("tuned", (tuned, T))):
        res[label] = {
            "train": hard_errors(m, t, train_imgs),
            "heldout": hard_errors(m, t, held_imgs),
        }
        print(label, res[label])
    (data.cache_folder() / "tuning_color.json").write_text(json.dumps(res, indent=1))
    plot(res)


def plot(res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(res["train_loss"], label="train")
    ax.plot(res["heldout_loss"], label="held-out")
    ax.set_xlabel("Adam step (from the scribble fit, T = 3)")
    ax.set_ylabel("cross-entropy of the soft classifier (nats / pixel)")
    ax.set_title("Colour covariances and threshold")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "images" / "tuning_color.png", dpi=120)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else STEPS)
