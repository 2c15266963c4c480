"""Azad et al. 2007 Fig. 1: iterations to converge vs initial distance for p_g, p_r and p_d.

The set-up of §III-B: a static square of edge length k = 70 px, tracked along the line through
its centre (one DOF, x). The observation is the intersection of the square with that line: a
1D foreground F (1 inside [c - k/2, c + k/2]), its gradient spread by a Gaussian (sigma 2 px)
and remapped to [0, 1] (the edge map g). Particles s = x; the update applies "Gaussian noise
only, with an amplification factor omega = 3" -- we read it as a fixed noise std of
omega px per iteration (no motion model). Cues (1D versions of :mod:`jaxmocap.pf.cues`):

* p_g: SSD over the M_g = 2 projected edge points x +- k/2 (bilinear in g);
* p_r: Eq. (1) over the M_r = k + 1 pixels of the projected square (nearest, in F);
* p_d: -(x - c)^2 / (2 sigma_d^2) with c the observed centre.

Converged: the weighted mean within 1 px of c; 100 = not found within 100 iterations (as in
the paper's figure). N = 100 particles, median over 10 seeds per initial distance.
Writes ``docs/results/stereo_pf_fig1.json`` and ``docs/images/stereo_pf_fig1.png``.
"""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap import pf
from jaxmocap.pf import cues

ROOT = Path(__file__).resolve().parents[2]
K_EDGE = 70  # px, Azad §III-B
OMEGA = 3.0  # noise amplification (std, px per iteration)
LENGTH = 400  # px of the line
CENTRE = 200.0
N = 100
MAX_IT = 100
SEEDS = 10
DISTANCES = np.arange(0, 161, 10)
SIGMA_G = SIGMA_R = 0.2
SIGMA_D = 10.0  # px


def observation():
    x = np.arange(LENGTH)
    fg = (np.abs(x - CENTRE) <= K_EDGE / 2).astype(np.float64)
    grad = np.zeros(LENGTH)
    grad[:-1] = fg[1:] != fg[:-1]
    kern = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    g = np.convolve(grad, kern, mode="same")
    return jnp.asarray(fg), jnp.asarray(g / g.max())


def logliks():
    fg, g = observation()
    img_g, img_f = g[None, :], fg[None, :]  # 1-row images for the 2D samplers

    def p_g(s, _):
        pts = jnp.stack([s[0] - K_EDGE / 2, s[0] + K_EDGE / 2])
        uv = jnp.stack([pts, jnp.zeros_like(pts)], -1)
        return cues.edge_loglik(cues.sample_bilinear(img_g, uv), SIGMA_G, "ssd")

    def p_r(s, _):
        pts = s[0] + jnp.arange(-K_EDGE / 2, K_EDGE / 2 + 1)
        uv = jnp.stack([pts, jnp.zeros_like(pts)], -1)
        return cues.region_loglik(cues.sample_nearest(img_f, uv), SIGMA_R)

    def p_d(s, _):
        return cues.distance_loglik(
            s[None, :], jnp.full((1, 1), CENTRE), jnp.ones(1, bool), SIGMA_D
        )

    return {"p_g": p_g, "p_r": p_r, "p_d": p_d}


def iterations(loglik, x0, key):
    params = pf.PFParams(
        loglik=loglik, lower=jnp.array([-1e9]), upper=jnp.array([1e9]),
        sigma_min=jnp.array([OMEGA]), sigma_max=jnp.array([OMEGA]), damping=0.0,
    )  # fmt: skip
    state = pf.init(key, params, jnp.array([x0]), 0.0, N)

    def body(carry, k):
        s, done_at, t = carry
        s, est = pf.step(params, s, None, k)
        ok = jnp.abs(est.mean[0] - CENTRE) <= 1.0
        done_at = jnp.where((done_at == MAX_IT) & ok, t, done_at)
        return (s, done_at, t + 1), None

    (_, done_at, _), _ = jax.lax.scan(
        body, (state, jnp.asarray(MAX_IT), jnp.asarray(1)), jax.random.split(key, MAX_IT)
    )
    return done_at


def main():
    result = {}
    for name, ll in logliks().items():
        fn = jax.jit(jax.vmap(jax.vmap(lambda x0, k, ll=ll: iterations(ll, x0, k), (None, 0)),
                              (0, None)))  # fmt: skip
        its = np.asarray(fn(jnp.asarray(CENTRE + DISTANCES, float),
                            jax.random.split(jax.random.key(0), SEEDS)))  # fmt: skip
        result[name] = np.median(its, axis=1).tolist()
        print(name, result[name], flush=True)
    out = {"distances_px": DISTANCES.tolist(), "median_iterations": result, "N": N,
           "omega": OMEGA, "k": K_EDGE, "seeds": SEEDS}  # fmt: skip
    (ROOT / "docs" / "results").mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "results" / "stereo_pf_fig1.json").write_text(json.dumps(out, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    for name, its in result.items():
        ax.plot(DISTANCES, its, marker="o", label=name)
    ax.set_xlabel("initial distance (px)")
    ax.set_ylabel("iterations (100 = not found)")
    ax.set_title("1D square, k = 70 px, omega = 3 (cf. Azad Fig. 1)")
    ax.legend()
    fig.tight_layout()
    (ROOT / "docs" / "images").mkdir(parents=True, exist_ok=True)
    fig.savefig(ROOT / "docs" / "images" / "stereo_pf_fig1.png", dpi=100)


if __name__ == "__main__":
    main()
