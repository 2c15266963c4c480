"""Tuning the stereo filter's cue widths sigma_g, sigma_d (docs/results/tuning.md).

Data (``tune_data.py stereo``): Azad et al.'s set-up (stereo pair 11 cm apart, 320x240,
single-colour shirt) rendered for ``STEREO_TRAIN`` / ``STEREO_HELDOUT`` and passed through the
tracker's host pipeline (edge maps, triangulated head and hands): the observations z_t.

Surrogate (:func:`jaxmocap.tune.pf_loss`): per frame ``N_PARTICLES`` fixed particles around the
true pose — a shared offset (prediction error) and per-particle diffusion, both with standard
deviations ``sqrt(sigma_min sigma_max)`` of the filter's adaptive noise per DOF kind — and the
mean per-joint error of the likelihood-weighted mean. Start: the module defaults
(``SIGMA_G`` = 0.2, ``SIGMA_D`` = 0.04 m). Check: the real filter (N = 1000, automatic
initialisation, ``lax.scan``) on the held-out clip with the default and the tuned widths, same
key.

Writes ``tuning_pf.json`` to the tune cache folder and ``docs/images/tuning_pf.png``.
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

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import tune_data as data  # noqa: E402

from jaxmocap import tune  # noqa: E402
from jaxmocap._config import enable_compilation_cache  # noqa: E402
from jaxmocap.body import keypoint_index, keypoints  # noqa: E402
from jaxmocap.pf import cues  # noqa: E402
from jaxmocap.pf.cues import Observation  # noqa: E402
from jaxmocap.synth import SceneConfig  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
PF_JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")  # the demo's
N_PARTICLES = 200
STEPS = 40
LEARNING_RATE = 0.05
SEEDS = (0, 1, 2)  # filter runs per setting on the held-out clip


def load(clips, dofs):
    obs, s_gt = [], []
    for clip in clips:
        d = np.load(data.clip_file("stereo", clip))
        obs.append(Observation(jnp.asarray(d["edges"]), jnp.asarray(d["points"]),
                               jnp.asarray(d["valid"]), jnp.asarray(d["foreground"])))  # fmt: skip
        s_gt.append(d["q_gt"][:, dofs])
    z = jax.tree.map(lambda *a: jnp.concatenate(a), *obs)
    return z, jnp.asarray(np.concatenate(s_gt))


def with_sigmas(params, sigma_g, sigma_d):
    lik = eqx.tree_at(lambda m: (m.sigma_g, m.sigma_d), params.likelihood,
                      (jnp.asarray(sigma_g), jnp.asarray(sigma_d)))  # fmt: skip
    return eqx.tree_at(lambda p: (p.likelihood, p.filter.loglik), params, (lik, lik))


def filter_error(params, z, q_gt, joints, seed) -> float:
    state, _ = sp.init(params, jax.random.key(seed), jax.tree.map(lambda a: a[0], z))
    _, est = sp.run(params, state, z)
    kp = jax.vmap(lambda q: keypoints(params.model, q)[joints])
    return float(jnp.linalg.norm(kp(est.q) - kp(jnp.asarray(q_gt)), axis=-1).mean() * 100)


def main(steps: int = STEPS) -> None:
    enable_compilation_cache()
    if not all(data.clip_file("stereo", c).exists()
               for c in data.STEREO_TRAIN + data.STEREO_HELDOUT):  # fmt: skip
        subprocess.run([sys.executable, str(Path(data.__file__)), "stereo"], check=True)
    config = SceneConfig(rig="stereo", garment="single", background="plain")
    params = sp.make_params(make_cameras(config, jnp.float64), dtype=jnp.float64)
    dofs = params.dofs
    joints = jnp.asarray(keypoint_index(params.model, PF_JOINTS))
    kind = np.where(dofs < 3, 0, np.where(dofs < 6, 1, 2))
    std = np.sqrt(np.asarray(sp.SIGMA_MIN) * np.asarray(sp.SIGMA_MAX))[kind]
    z_tr, s_tr = load(data.STEREO_TRAIN, dofs)
    z_he, s_he = load(data.STEREO_HELDOUT, dofs)
    lo, hi = params.filter.lower, params.filter.upper
    train = tune.PFData(z_tr, tune.pf_particles(s_tr, std, std, N_PARTICLES, jax.random.key(0),
                                                lo, hi), s_tr)  # fmt: skip
    held = tune.PFData(z_he, tune.pf_particles(s_he, std, std, N_PARTICLES, jax.random.key(1),
                                               lo, hi), s_he)  # fmt: skip
    lik = params.likelihood
    loss = jax.jit(tune.pf_loss)
    held_curve, path = [], []

    def callback(i, value, theta):
        held_curve.append(float(loss(theta, lik, held, joints)))
        path.append([float(jnp.exp(theta.sigma_g)), float(jnp.exp(theta.sigma_d))])
        if i % 10 == 0:
            print(
                f"step {i:3d}: train {100 * value:.3f} cm, held-out {100 * held_curve[-1]:.3f}"
                f" cm, sigma_g {path[-1][0]:.4f}, sigma_d {path[-1][1]:.4f}",
                flush=True,
            )

    t0 = time.perf_counter()
    theta, losses = tune.fit(lambda th: tune.pf_loss(th, lik, train, joints),
                             tune.pf_theta(cues.SIGMA_G, cues.SIGMA_D), steps, LEARNING_RATE,
                             callback)  # fmt: skip
    elapsed = time.perf_counter() - t0
    sg, sd = float(jnp.exp(theta.sigma_g)), float(jnp.exp(theta.sigma_d))
    res = {"steps": steps, "seconds": elapsed, "n_particles": N_PARTICLES,
           "train_loss_cm": (100 * losses).tolist(),
           "heldout_loss_cm": (100 * np.asarray(held_curve)).tolist(), "path": path,
           "tuned": {"sigma_g": sg, "sigma_d": sd},
           "default": {"sigma_g": cues.SIGMA_G, "sigma_d": cues.SIGMA_D}}  # fmt: skip
    q_gt = np.load(data.clip_file("stereo", data.STEREO_HELDOUT[0]))["q_gt"]
    for label, (g, d) in (("default", (cues.SIGMA_G, cues.SIGMA_D)), ("tuned", (sg, sd))):
        p = with_sigmas(params, g, d)
        errs = [filter_error(p, z_he, q_gt, joints, s) for s in SEEDS]
        res[label]["filter_heldout_cm"] = errs
        print(
            f"{label}: sigma_g {g:.4f} sigma_d {d:.4f}: filter error {np.mean(errs):.2f} cm "
            f"({errs})",
            flush=True,
        )
    (data.cache_folder() / "tuning_pf.json").write_text(json.dumps(res, indent=1))
    plot(res)


def plot(res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(8, 3.4))
    ax[0].plot(res["train_loss_cm"], label="train")
    ax[0].plot(res["heldout_loss_cm"], label="held-out")
    ax[0].set_xlabel("Adam step (from sigma_g = 0.2, sigma_d = 0.04 m)")
    ax[0].set_ylabel("surrogate: weighted-mean error (cm)")
    ax[0].legend(fontsize=8)
    p = np.asarray(res["path"])
    ax[1].plot(p[:, 0], 100 * p[:, 1], ".-")
    ax[1].set_xlabel("sigma_g")
    ax[1].set_ylabel("sigma_d (cm)")
    ax[1].set_title("path of the cue widths", fontsize=9)
    fig.tight_layout()
    fig.savefig(ROOT / "docs" / "images" / "tuning_pf.png", dpi=120)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else STEPS)
