"""Generic particle filter step: jaxmocap.pf (jit, vmapped likelihood) vs NumPy, same algorithm.

Azad et al.'s setting: N = 1000 particles, a 14-DOF state, one step = systematic resampling,
first-order motion + adaptive Gaussian noise, box constraints, N likelihood evaluations,
weighted mean / best / ESS. The likelihood here is cheap on purpose (a smooth 14-D energy),
so the numbers measure the filter's own overhead; the stereo cues are benchmarked elsewhere.
Run: python benchmarks/bench_pf.py
"""

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap import pf

N, D = 1000, 14
T_SEQ = sized(full=50, quick=10)  # frames of the lax.scan run
LIK_STD = 0.3
DAMPING = 0.5


def loglik(s, z):
    """A cheap smooth energy: -1/2 sum ((sin s - z) / 0.3)^2."""
    r = (jnp.sin(s) - z) / LIK_STD
    return -0.5 * jnp.sum(r * r)


def numpy_step(rng, x, xp, logw, sigma, z, lo, hi, smin, smax, error_scale=1.0):
    """The same step as pf.step (systematic resampling every frame), vectorised NumPy."""
    w = np.exp(logw - logw.max())
    cdf = np.cumsum(w)
    cdf /= cdf[-1]
    idx = np.minimum(np.searchsorted(cdf, (rng.random() + np.arange(N)) / N, side="right"), N - 1)
    x, xp = x[idx], xp[idx]
    x_new = np.clip(x + DAMPING * (x - xp) + sigma * rng.standard_normal((N, D)), lo, hi)
    r = (np.sin(x_new) - z) / LIK_STD
    ll = -0.5 * np.einsum("nd,nd->n", r, r)
    lw = ll - ll.max()
    lw -= np.log(np.exp(lw).sum())
    w = np.exp(lw)
    mean = w @ x_new
    best = x_new[np.argmax(ll)]
    ess = 1.0 / np.sum(w * w)
    err = max(-ll.max(), 0.0)
    sigma = smin + (smax - smin) * (1 - np.exp(-err / error_scale))
    return (x_new, x, lw, sigma), (mean, best, ess)


def _bench_jax(resampling, target, z, lo, hi, smin, smax, np_ms):
    params = pf.PFParams(
        loglik,
        lower=lo.astype(np.float32),
        upper=hi.astype(np.float32),
        sigma_min=smin.astype(np.float32),
        sigma_max=smax.astype(np.float32),
        damping=DAMPING,
        resampling=resampling,
    )
    state = pf.init(jax.random.key(0), params, jnp.asarray(target, jnp.float32), 0.3, N)
    zj = jnp.asarray(z, jnp.float32)
    key = jax.random.key(1)
    kernel = f"PF step N={N} d={D}"
    comp = time_compile(lambda: pf.step(params, state, zj, key))
    ms, mn = time_call(lambda: pf.step(params, state, zj, key))
    rows = [Row(kernel, f"jaxmocap.pf.step ({resampling}, jit, f32)", ms, mn, 50, comp)]
    summary = [
        f"{kernel} ({resampling}): jaxmocap {ms:.3f} ms vs NumPy {np_ms:.3f} ms "
        f"(NumPy/jax = {np_ms / ms:.2f}x)"
    ]
    if resampling != "systematic":
        return rows, summary
    zs = jnp.broadcast_to(zj, (T_SEQ, D))
    comp = time_compile(lambda: pf.run(params, state, zs, key))
    ms_seq, mn_seq = time_call(lambda: pf.run(params, state, zs, key), n=sized(full=20, quick=3))
    rows.append(
        Row(
            f"PF sequence T={T_SEQ} N={N} d={D}, per frame",
            "jaxmocap.pf.run (lax.scan)",
            ms_seq / T_SEQ,
            mn_seq / T_SEQ,
            20,
            comp,
        )
    )
    summary.append(
        f"PF run (lax.scan, T={T_SEQ}): {ms_seq / T_SEQ:.3f} ms per frame "
        f"(NumPy step / jax frame = {np_ms / (ms_seq / T_SEQ):.2f}x)"
    )
    betas = jnp.asarray([0.05, 0.2, 0.5, 1.0], jnp.float32)
    comp = time_compile(lambda: pf.anneal_step(params, state, zj, key, betas))
    ms_a, mn_a = time_call(lambda: pf.anneal_step(params, state, zj, key, betas))
    rows.append(
        Row(
            f"PF annealed step N={N} d={D}, 4 layers",
            "jaxmocap.pf.anneal_step (jit)",
            ms_a,
            mn_a,
            50,
            comp,
        )
    )
    return rows, summary


def main() -> None:
    rng = np.random.default_rng(0)
    lo, hi = -np.pi * np.ones(D), np.pi * np.ones(D)
    smin, smax = np.full(D, 0.01), np.full(D, 0.2)
    target = rng.uniform(-1, 1, D)
    z = np.sin(target)

    # NumPy baseline (float64; float32 is not faster in NumPy for these ops)
    x0 = target + 0.3 * rng.standard_normal((N, D))
    state_np = (x0, x0.copy(), np.full(N, -np.log(N)), smax.copy())
    np_ms, np_min = time_call(lambda: numpy_step(rng, *state_np, z, lo, hi, smin, smax))
    rows = [Row(f"PF step N={N} d={D}", "NumPy (vectorised, systematic)", np_ms, np_min, 50)]
    summary = []
    for resampling in ("systematic", "multinomial"):
        r, s = _bench_jax(resampling, target, z, lo, hi, smin, smax, np_ms)
        rows += r
        summary += s
    summary.append("Measured on a 2-core machine shared with other engineers' jobs (noisy).")
    path = write_results("bench_pf", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
