"""Fixed-lag smoothing by particle genealogy (Kitagawa 1996), an offline extension.

Azad et al.'s filter is online: the estimate of frame t uses the images up to t. When a whole
sequence is at hand, the particles of frame t can be re-weighted by what frames t+1..t+L
showed. The resampling steps already record which particle of frame t each particle of frame
t+L descends from (its *lineage*), so the smoothed estimate is the mean of frame t's ancestors
of the frame-(t+L) set, weighted by the frame-(t+L) weights:

    E[s_t | z_1..z_{t+L}]  ~=  sum_i pi_{t+L}^i  s_t^{a_t(i)},

    a_t(i) = parent_{t+1}( parent_{t+2}( ... parent_{t+L}(i) ) ),

(Kitagawa, "Monte Carlo filter and smoother for non-Gaussian nonlinear state space models",
J. Comput. Graph. Stat. 1996; Doucet & Johansen's tutorial, §4.3). The last L frames use
the last frame's set (a shorter lag). The lineages coalesce as L grows (path degeneracy:
after some frames every particle shares one ancestor), so the lag should stay short -- a few
frames at 25 Hz; L = 0 is the filter itself.

Pure JAX; :func:`fixed_lag_smooth` jit/vmap/grad-able in the particles and the weights.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

__all__ = ["Lineage", "fixed_lag_smooth"]


class Lineage(eqx.Module):
    """A filtered sequence's particle sets: ``particles`` (T, N, d) and normalised
    ``log_weights`` (T, N) after each frame's weighting, and ``parents`` (T, N): the index in
    frame t-1's set of each particle of frame t (``parents[0]`` refers to the set the run
    started from and is not used)."""

    particles: Float[Array, "*t n d"]
    log_weights: Float[Array, "*t n"]
    parents: Int[Array, "*t n"]


def fixed_lag_smooth(lineage: Lineage, lag: int) -> Float[Array, "t d"]:
    """The lag-``lag`` smoothed means (T, d) (module docstring): frame t's ancestors of the
    frame-min(t + lag, T - 1) particle set, weighted by that frame's weights. ``lag`` is static
    (>= 0; 0 gives the filter's weighted means)."""
    lag = int(lag)
    if lag < 0:
        raise ValueError(f"fixed_lag_smooth: lag: expected >= 0, got {lag}")
    t_len, n = lineage.log_weights.shape
    if lineage.particles.shape[:2] != (t_len, n) or lineage.parents.shape != (t_len, n):
        raise ValueError(
            "fixed_lag_smooth: lineage: expected particles (T, N, d), log_weights and parents "
            f"(T, N), got {lineage.particles.shape}, {lineage.log_weights.shape}, "
            f"{lineage.parents.shape}"
        )

    def one(t):
        s = jnp.minimum(t + lag, t_len - 1)

        def back(j, lin):
            k = s - j
            return jnp.where(k > t, lineage.parents[k][lin], lin)

        lin = jax.lax.fori_loop(0, lag, back, jnp.arange(n))
        w = jnp.exp(lineage.log_weights[s])
        return w @ lineage.particles[t][lin]

    return jax.vmap(one)(jnp.arange(t_len))
