"""Resampling and weight bookkeeping for the particle filter (Azad et al. §II).

"For resampling the particle set, N particles from the last generation are picked proportional
to their probability" (Azad §II). Weights are kept as log-weights log pi_i; all functions take
unnormalised log-weights and are safe for -inf entries (zero weight).

* :func:`systematic` — one uniform offset u ~ U[0, 1/N), positions u + i/N: particle i is picked
  either floor(N pi_i) or ceil(N pi_i) times (lowest variance, O(N log N)).
* :func:`multinomial` — N independent draws from Categorical(pi) (the textbook Condensation
  scheme; kept for comparison).
* :func:`stop_gradient_correction` — the weights after a resampling that carry the gradient of
  the weights before it (Scibior & Wood 2021, "Differentiable particle filtering without
  modifying the forward pass"): the picked particle a_i gets log-weight
  ``-log M + log pi_{a_i} - stop_gradient(log pi_{a_i})``, which is ``-log M`` in value (the
  forward pass is unchanged, bit for bit) while its derivative is that of ``log pi_{a_i}``. The
  indices stay non-differentiable; with this correction automatic differentiation of the
  filter's log-evidence gives the classical Fisher-identity score estimate (Poyiadjis et al.
  2011) instead of ignoring every resampling's dependence on the parameters.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

__all__ = [
    "effective_sample_size",
    "multinomial",
    "normalize_log_weights",
    "stop_gradient_correction",
    "systematic",
]


def normalize_log_weights(
    log_weights: Float[Array, " n"],
) -> tuple[Float[Array, " n"], Bool[Array, ""]]:
    """log pi_i - logsumexp(log pi); NaN counts as -inf (zero weight).

    Returns:
        (normalised log-weights, degenerate). ``degenerate`` is True when no weight is finite
        and positive (every entry -inf or NaN, or an entry +inf); the weights are then reset to
        uniform, -log N each, so the filter carries on instead of propagating NaN.
    """
    n = log_weights.shape[0]
    lw = jnp.where(jnp.isnan(log_weights), -jnp.inf, log_weights)
    top = jnp.max(lw)
    degenerate = ~jnp.isfinite(top)
    safe_top = jnp.where(degenerate, jnp.zeros_like(top), top)
    shifted = lw - safe_top
    normed = shifted - jnp.log(jnp.sum(jnp.exp(shifted)))
    uniform = jnp.full_like(lw, -jnp.log(n))
    return jnp.where(degenerate, uniform, normed), degenerate


def effective_sample_size(log_weights: Float[Array, " n"]) -> Float[Array, ""]:
    """ESS = 1 / sum_i pi_i^2 of the normalised weights, in [1, N]."""
    lw, _ = normalize_log_weights(log_weights)
    return 1.0 / jnp.sum(jnp.exp(2.0 * lw))


def _invert(log_weights: Float[Array, " n"], positions: Float[Array, " m"]) -> Int[Array, " m"]:
    """Indices i with cdf_{i-1} <= position < cdf_i, for NORMALISED log-weights."""
    cdf = jnp.cumsum(jnp.exp(log_weights))
    cdf = cdf / cdf[-1]
    idx = jnp.searchsorted(cdf, positions.astype(cdf.dtype), side="right", method="scan")
    return jnp.minimum(idx, cdf.shape[0] - 1).astype(jnp.int32)


def systematic_from_uniforms(
    log_weights: Float[Array, " n"], u: Float[Array, " m"]
) -> Int[Array, " m"]:
    """:func:`systematic` for normalised log-weights, given uniforms u in [0, 1) (uses u[0])."""
    m = u.shape[0]
    return _invert(log_weights, (u[0] + jnp.arange(m, dtype=u.dtype)) / m)


def multinomial_from_uniforms(
    log_weights: Float[Array, " n"], u: Float[Array, " m"]
) -> Int[Array, " m"]:
    """:func:`multinomial` for normalised log-weights, given its m uniforms in [0, 1)."""
    return _invert(log_weights, u)


def systematic(
    key: PRNGKeyArray, log_weights: Float[Array, " n"], n_out: int | None = None
) -> Int[Array, " m"]:
    """Systematic resampling: indices of ``n_out`` (default N) particles picked prop. to pi.

    Positions (u + i) / M with one u ~ U[0, 1); each particle i is picked floor(M pi_i) or
    ceil(M pi_i) times. Indices come out sorted.
    """
    m = log_weights.shape[0] if n_out is None else n_out
    lw, _ = normalize_log_weights(log_weights)
    u = jax.random.uniform(key, (1,), dtype=log_weights.dtype)
    return systematic_from_uniforms(lw, jnp.broadcast_to(u, (m,)))


def multinomial(
    key: PRNGKeyArray, log_weights: Float[Array, " n"], n_out: int | None = None
) -> Int[Array, " m"]:
    """Multinomial resampling: ``n_out`` (default N) i.i.d. draws from Categorical(pi)."""
    m = log_weights.shape[0] if n_out is None else n_out
    lw, _ = normalize_log_weights(log_weights)
    u = jax.random.uniform(key, (m,), dtype=log_weights.dtype)
    return multinomial_from_uniforms(lw, u)


def stop_gradient_correction(
    log_weights: Float[Array, " n"], idx: Int[Array, " m"]
) -> Float[Array, " m"]:
    """``log pi_{a_i} - stop_gradient(log pi_{a_i})`` for the picked indices ``a = idx``: zero
    in value, the gradient of the picked particles' log-weights in reverse mode (Scibior &
    Wood 2021; module docstring). Added to the uniform log-weight ``-log M`` after a
    resampling. An entry whose picked log-weight is not finite (a zero-weight particle that
    only rounding of the last position can pick) contributes an exact 0 and no gradient (its
    difference would be NaN)."""
    picked = log_weights[idx]
    ok = jnp.isfinite(picked)
    safe = jnp.where(ok, picked, jnp.zeros_like(picked))
    return jnp.where(ok, safe - jax.lax.stop_gradient(safe), jnp.zeros_like(picked))
