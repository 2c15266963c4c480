"""Wang et al. 2011 Fig. 6: correct vs false-positive classification as the threshold T varies,
for the baseline Gaussian (Mahalanobis) classifier (§5.2 step 1) and the pose-assisted one
(§5.2 step 3).

Frames: a held-out clip (``HELDOUT_CLIPS[0]``) rendered by the synth module at 320x240 with a
cluttered background, the scene's tinted illuminant and sensor noise; ground-truth colour ids
come from the renderer. Colour model: scribbles on five white-light renders of database-like
poses (``shirt.fit_color_model_from_renders``); white balance ``W0`` from scribbles on the first
frame of each camera (``shirt.initial_white_balance``).

Pose prior ``r^b``: rendered patch ids of a **perturbed** ground-truth pose (joint angles + N(0,
0.15 rad), root + N(0, 3 cm)), the fair case standing in for the blended database pose; the
curve with the exact ground-truth prior is also drawn (an upper bound). ``C = 6 / s`` with
``s`` the side of the shirt's bounding box (pixels).

Pixels scored: a square window around the shirt (1.5x the side of the bounding box of the
ground-truth shirt pixels), roughly the tracker's crop. Per threshold T:

* correct rate = #(pred == truth, truth > 0) / #(truth > 0)
* false-positive rate = #(pred > 0, pred != truth) / #(pixels in the window)

Both classifiers are evaluated once with T = inf; the sweep thresholds the returned scores.

    python benchmarks/experiments/wang_fig6.py [small|full]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap.body import default_body
from jaxmocap.color import classify
from jaxmocap.color.pose_assisted import patch_distance_maps, pose_assisted_classify, prior_weight
from jaxmocap.garment import default_garment
from jaxmocap.posedb import SamplingConfig, sample_poses, source_pool
from jaxmocap.render import render_rgb
from jaxmocap.synth import HELDOUT_CLIPS, SceneConfig, render_sequence
from jaxmocap.trackers import shirt

ROOT = Path(__file__).resolve().parents[2]
SCALES = {"small": dict(n_frames=4, n_cameras=1), "full": dict(n_frames=12, n_cameras=2)}
THRESHOLDS = np.array([0.5, 1, 1.5, 2, 2.5, 3, 3.5, 4, 5, 6, 7, 8, 10, 12, 15, 20, 30])
PERTURB_JOINT = 0.15  # rad
PERTURB_ROOT = 0.03  # m


def _window(truth: np.ndarray, factor: float = 1.5) -> tuple[slice, slice, float]:
    ys, xs = np.nonzero(truth)
    cy, cx = 0.5 * (ys.min() + ys.max()), 0.5 * (xs.min() + xs.max())
    side = max(ys.max() - ys.min(), xs.max() - xs.min()) + 1
    h = factor * side / 2
    H, W = truth.shape
    sy = slice(int(max(cy - h, 0)), int(min(cy + h + 1, H)))
    sx = slice(int(max(cx - h, 0)), int(min(cx + h + 1, W)))
    return sy, sx, float(side)


def _rates(pred_best, score, truth, thresholds):
    n_true = max(int((truth > 0).sum()), 1)
    out_c, out_f = [], []
    for T in thresholds:
        pred = np.where(score < T, pred_best, 0)
        out_c.append(float(((pred == truth) & (truth > 0)).sum() / n_true))
        out_f.append(float(((pred > 0) & (pred != truth)).sum() / truth.size))
    return np.array(out_c), np.array(out_f)


def main(scale: str = "small", write: bool = True) -> dict:
    """Run the experiment; returns the curves (and writes JSON + PNG when ``write``)."""
    if scale not in SCALES:
        raise ValueError(f"wang_fig6.main: scale must be one of {sorted(SCALES)}, got {scale!r}")
    s = SCALES[scale]
    model = default_body()
    garment = default_garment(model)
    cfg = SceneConfig(
        clip=HELDOUT_CLIPS[0], n_frames=s["n_frames"], n_cameras=s["n_cameras"], width=320,
        height=240, background="clutter", n_distractors=8, noise_sigma=0.01, seed=1,
    )  # fmt: skip
    seq = render_sequence(cfg, jnp.float32)
    gt = seq.groundtruth
    cams = seq.cameras
    # colour model: five white-light renders of training poses at the rig's first camera
    pool = source_pool(model, _train_clips())
    poses = sample_poses(SamplingConfig(size=5, seed=3, yaw_range=0.3), model, pool)
    poses[:, 2] = 0.85
    color = shirt.fit_color_model_from_renders(model, garment, poses, cams[0])
    labels = np.stack([shirt.scribbles(gt["colour_ids"][0, i]) for i in range(len(cams))])
    W0 = shirt.initial_white_balance(color, seq.frames[0], labels)

    bg = jnp.zeros((cfg.height, cfg.width, 3), jnp.uint8)
    prior_render = jax.jit(lambda q, cam: render_rgb(model, garment, q, cam, bg)[1].patch)
    base = jax.jit(lambda W, img: classify(color, W, img, threshold=jnp.inf))

    @jax.jit
    def assisted(W, img, prior, C):
        d = patch_distance_maps(prior, garment.n_patches, jnp.float32)
        r = pose_assisted_classify(color, W, img, d, garment.patch_colour, C, threshold=jnp.inf)
        return r.colour, r.score

    rng = np.random.default_rng(0)
    acc = {k: [] for k in ("base", "prior_gt", "prior_perturbed")}
    for t in range(seq.frames.shape[0]):
        q_gt = np.asarray(gt["q"][t], np.float32)
        q_p = q_gt.copy()
        q_p[6:] += rng.normal(0, PERTURB_JOINT, q_p[6:].shape)
        q_p[:3] += rng.normal(0, PERTURB_ROOT, 3)
        lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
        q_p[6:] = np.clip(q_p[6:], lo[6:], hi[6:])
        for i, cam in enumerate(cams):
            truth_full = gt["colour_ids"][t, i].astype(np.int32)
            if (truth_full > 0).sum() < 50:
                continue
            sy, sx, side = _window(truth_full)
            img = jnp.asarray(seq.frames[t, i])
            ids, dist = base(W0[i], img)
            # the paper's baseline: the nearest colour, kept when its distance is below T
            acc["base"].append((np.asarray(ids)[sy, sx], np.asarray(dist)[sy, sx]))
            C = prior_weight(jnp.float32(side))
            for name, q in (("prior_gt", q_gt), ("prior_perturbed", q_p)):
                prior = prior_render(jnp.asarray(q), cam)
                col, score = assisted(W0[i], img, prior, C)
                acc[name].append((np.asarray(col)[sy, sx], np.asarray(score)[sy, sx]))
            acc.setdefault("truth", []).append(truth_full[sy, sx])
    truth = np.concatenate([a.ravel() for a in acc["truth"]])
    curves = {"thresholds": THRESHOLDS.tolist(), "scale": scale, "n_images": len(acc["truth"]),
              "n_pixels": int(truth.size), "n_shirt_pixels": int((truth > 0).sum()),
              "config": cfg.to_dict()}  # fmt: skip
    for name in ("base", "prior_gt", "prior_perturbed"):
        best = np.concatenate([a[0].ravel() for a in acc[name]])
        score = np.concatenate([a[1].ravel() for a in acc[name]])
        c, f = _rates(best, score, truth, THRESHOLDS)
        curves[name] = {"correct": c.round(4).tolist(), "false_positive": f.round(4).tolist()}
    if write:
        _write(curves)
    return curves


def _train_clips():
    from jaxmocap.synth import TRAIN_CLIPS

    return TRAIN_CLIPS


def _write(curves: dict) -> None:
    out = ROOT / "docs" / "results" / "shirt_fig6.json"
    out.write_text(json.dumps(curves, indent=1) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    labels = {
        "base": "baseline Gaussian classifier (step 1)",
        "prior_perturbed": "pose-assisted, perturbed-pose prior",
        "prior_gt": "pose-assisted, ground-truth prior",
    }
    for name, style in (("base", "o-"), ("prior_perturbed", "s-"), ("prior_gt", "^--")):
        fp = 100 * np.array(curves[name]["false_positive"])
        ax.plot(fp, 100 * np.array(curves[name]["correct"]), style, ms=3, label=labels[name])
    T = curves["thresholds"]
    for k in (T.index(3), T.index(5)):
        for name in ("base", "prior_perturbed"):
            xy = (100 * curves[name]["false_positive"][k], 100 * curves[name]["correct"][k])
            ax.annotate(f"T={T[k]:g}", xy, fontsize=7)
    ax.set_xscale("symlog", linthresh=0.1)
    ax.set_xlabel("false positives (% of window pixels; linear below 0.1)")
    ax.set_ylabel("correctly classified shirt pixels (%)")
    ax.set_title(f"Fig. 6 analogue: {curves['n_images']} cluttered 320x240 images")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "images" / "shirt_fig6.png", dpi=110)


if __name__ == "__main__":
    if sys.argv[1:] == ["replot"]:  # redraw from the committed JSON
        _write(json.loads((ROOT / "docs" / "results" / "shirt_fig6.json").read_text()))
        sys.exit()
    r = main(sys.argv[1] if len(sys.argv) > 1 else "small")
    for name in ("base", "prior_perturbed", "prior_gt"):
        c, f = r[name]["correct"], r[name]["false_positive"]
        print(name, list(zip(r["thresholds"], c, f, strict=True)))
