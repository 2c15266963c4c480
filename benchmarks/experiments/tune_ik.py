"""Tuning the IK covariances Sigma_c, Sigma_b, Sigma_p by gradient descent (docs/results/tuning.md).

Data (``tune_data.py shirt``): training and held-out clips rendered for the two-webcam rig and
tracked by the colour-shirt tracker; the IK inputs of every frame (measured centroids,
validity, blended pose q_b) are kept and the IK step is re-run under ``jaxmocap.tune``.

1. Start: the paper's closed-form estimate (``jaxmocap.ik.estimate_covariances``) on the
   training windows; references: the demo's hand-set isotropic covariances (what the tracker
   ran with).
2. Adam on the mean per-joint error of the IK track over the training windows.
3. Held-out: the same loss and a per-joint table for the three sets of covariances.

Writes ``tuning_ik_<start>.json`` (+ the tuned covariances) to the tune cache folder and
``docs/images/tuning_ik_<start>.png``. Run:
``python benchmarks/experiments/tune_ik.py [steps] [closed|isotropic]`` (the start; a few
minutes per 10 steps on 2 cores).
"""

from __future__ import annotations

import json
import subprocess
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
from jaxmocap.body import default_body, keypoints  # noqa: E402
from jaxmocap.camera import stack_cameras  # noqa: E402
from jaxmocap.garment import default_garment  # noqa: E402
from jaxmocap.ik import IKCovariances, anchors_from_garment  # noqa: E402
from jaxmocap.synth import SceneConfig  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
WINDOW = 10  # frames per scan window
STEPS = 20
LEARNING_RATE = 0.05


def load(clips):
    seqs = []
    for clip in clips:
        d = np.load(data.clip_file("shirt", clip))
        seqs.append((d["centroids"], d["visible"], d["q_blend"], d["q_gt"]))
    return seqs


def per_joint(setup, cov, obs):
    """(windows, T, joints) error in cm of the IK track."""
    track = jax.jit(jax.vmap(tune.ik_track, in_axes=(None, None, 0, 0, 0)))
    q, ok = track(cov, setup, obs.centroids, obs.visible, obs.q_b)
    kp = jax.jit(jax.vmap(jax.vmap(lambda q: keypoints(setup.body, q))))
    err = jnp.linalg.norm(kp(q) - kp(obs.q_gt), axis=-1) * 100
    return np.asarray(err), np.asarray(ok)


def main(steps: int = STEPS, start: str = "closed") -> None:
    enable_compilation_cache()
    if not all(data.clip_file("shirt", c).exists() for c in data.SHIRT_TRAIN + data.SHIRT_HELDOUT):
        subprocess.run([sys.executable, str(Path(data.__file__)), "shirt"], check=True)
    model = default_body()
    anchors = anchors_from_garment(model, default_garment(model), jnp.float64)
    config = SceneConfig(rig="webcams", width=data.SIZE[0], height=data.SIZE[1])
    cams = stack_cameras(make_cameras(config, jnp.float64))
    setup = tune.ik_setup(model, cams, anchors)
    train = tune.ik_observations(load(data.SHIRT_TRAIN), WINDOW, jnp.float64)
    held = tune.ik_observations(load(data.SHIRT_HELDOUT), WINDOW, jnp.float64)
    print(f"train windows {train.q_b.shape[0]}, held-out {held.q_b.shape[0]} ({WINDOW} frames)")

    closed = tune.ik_closed_form(setup, train)
    demo = IKCovariances.isotropic(2.0, 0.3, 0.5, model.n_dof)
    vg = jax.jit(jax.value_and_grad(tune.ik_loss))
    f = jax.jit(tune.ik_loss)
    held_curve = []

    def callback(i, value, theta):
        h = float(f(theta, setup, held))
        held_curve.append(h)
        print(
            f"step {i:3d}: train {100 * value:.3f} cm, held-out {100 * h:.3f} cm "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )

    t0 = time.perf_counter()
    theta0 = tune.ik_theta(closed if start == "closed" else demo)
    theta, losses = tune.fit(lambda th: vg(th, setup, train), theta0, steps, LEARNING_RATE,
                             callback, value_and_grad=True)  # fmt: skip
    elapsed = time.perf_counter() - t0
    tuned = tune.ik_covariances(theta)

    results = {"start": start, "window": WINDOW, "steps": steps, "learning_rate": LEARNING_RATE,
               "train_clips": list(data.SHIRT_TRAIN), "heldout_clips": list(data.SHIRT_HELDOUT),
               "train_loss_cm": (100 * losses).tolist(),
               "heldout_loss_cm": (100 * np.asarray(held_curve)).tolist(),
               "seconds": elapsed, "sets": {}}  # fmt: skip
    names = list(model.keypoint_names)
    for label, cov in (("demo isotropic", demo), ("closed form", closed), ("tuned", tuned)):
        row = {}
        for split, obs in (("train", train), ("heldout", held)):
            err, ok = per_joint(setup, cov, obs)
            e = err[ok]
            row[split] = {"mean_cm": float(e.mean()),
                          "per_joint_cm": dict(zip(names, e.mean(0).round(3).tolist(),
                                                   strict=True))}  # fmt: skip
        results["sets"][label] = row
        print(
            f"{label:15s} train {row['train']['mean_cm']:.3f} cm, held-out "
            f"{row['heldout']['mean_cm']:.3f} cm"
        )
    # the tracker's own output (ran with the demo covariances, float32, W feedback live)
    qt = np.concatenate([np.load(data.clip_file("shirt", c))["q_track"]
                         for c in data.SHIRT_HELDOUT])  # fmt: skip
    qg = np.concatenate([np.load(data.clip_file("shirt", c))["q_gt"] for c in data.SHIRT_HELDOUT])
    kp = jax.jit(jax.vmap(lambda q: keypoints(model, q)))
    results["tracker_heldout_cm"] = float(
        np.linalg.norm(kp(jnp.asarray(qt, jnp.float64)) - kp(jnp.asarray(qg)), axis=-1).mean() * 100
    )
    sd = lambda c: np.sqrt(np.diag(np.asarray(c)))
    results["std"] = {
        label: {"centroid_px": sd(c.centroid).tolist(), "blend": sd(c.blend).tolist(),
                "prior": sd(c.prior).tolist()}
        for label, c in (("closed form", closed), ("tuned", tuned))
    }  # fmt: skip
    results["dof_names"] = list(model.chain.dof_names)
    out = (
        data.cache_folder() / f"tuning_ik_{start}.json"
    )  # numbers copied into docs/results/tuning.md
    out.write_text(json.dumps(results, indent=1))
    tuned.save(data.cache_folder() / f"tuning_ik_tuned_{start}.npz")
    plot(results, start)
    print(f"wrote {out}")


def plot(results, start: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    x = np.arange(len(results["train_loss_cm"]))
    ax.plot(x, results["train_loss_cm"], label="train (loss)")
    ax.plot(x, results["heldout_loss_cm"], label="held-out")
    for label, style in (("closed form", ":"), ("demo isotropic", "--")):
        ax.axhline(results["sets"][label]["heldout"]["mean_cm"], ls=style, c="gray", lw=1)
        ax.text(
            x[-1],
            results["sets"][label]["heldout"]["mean_cm"],
            f" {label} (held-out)",
            va="bottom",
            ha="right",
            fontsize=7,
            color="gray",
        )
    ax.set_xlabel(
        f"Adam step (from the {'closed-form estimate' if start == 'closed' else 'demo isotropic'})"
    )
    ax.set_ylabel("mean per-joint error (cm)")
    ax.set_title("IK covariances tuned through the IK scan")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "images" / f"tuning_ik_{start}.png", dpi=120)


if __name__ == "__main__":
    main(
        int(sys.argv[1]) if len(sys.argv) > 1 else STEPS,
        sys.argv[2] if len(sys.argv) > 2 else "closed",
    )
