"""A residual-guided proposal for the particle filter (an extension beyond Azad et al. 2007).

Azad's filter (§II) predicts with a first-order motion model and Gaussian noise only; the
distance cue p_d' (§III-D) then *weighs* particles by how close their head / hands lie to the
triangulated skin blobs. When the body moves fast (a whole-body turn, a punch) few of the
N predicted particles land near the measured points and the set lags behind. This module moves
a random fraction of the predicted particles toward configurations that satisfy such
point measurements, while keeping their random noise in every direction the points do not
constrain (for the arm: the elbow swivel about the shoulder-hand line; for the body: whatever
the head and hands leave free), so that those directions stay explored and are decided by the
other cues (the edge cue).

For one particle s (d,) with masked residual r(s) = valid * (f(s) - c) (k,) (missing
measurements give zero rows) and Jacobian J = dr/ds (k, d), each of ``n_steps`` damped
Gauss-Newton steps is the **minimum-norm** update in the metric W = diag(scale^2):

    s <- s - W J^T (J W J^T + lambda I)^{-1} r(s),

i.e. the smallest change (in units of ``scale`` per DOF) that closes the linearised residual
(up to the damping lambda, in residual units squared). The update lies in the row space of
J W^{1/2}: a change of s along the null space of J (a direction the measurements do not see)
is left exactly as the prediction drew it. With W the prediction's noise covariance and
lambda the measurement variance this is the mean shift of the Kalman update of the linearised
model -- the "optimal importance function" of Doucet et al. (2000) without its weight
correction: the importance weights are **not** corrected for the proposal (Azad's filter has
no proposal correction either; the resampling step simply treats guided particles as samples
of the prior). Azad's later work samples the redundant DOF of an arm given the hand and the
shoulder (the elbow on a circle); this is the same idea, by linearisation.

Pure JAX: :class:`GuidedProposal` is called inside the jitted filter step on the whole set
(N, d), vmapping the Gauss-Newton steps over the guided particles.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, PyTree

__all__ = [
    "GUIDED_DAMPING",
    "GUIDED_FRACTION",
    "GUIDED_STEPS",
    "GuidedProposal",
    "min_norm_steps",
    "spd_solve",
]

GUIDED_FRACTION = 0.5  # fraction of the N particles moved each frame (the others: prior only)
GUIDED_STEPS = 2  # damped Gauss-Newton steps per guided particle (1 and 3 tracked as well)
GUIDED_DAMPING = 1e-4  # lambda (residual units^2; m^2 for the distance cue: (1 cm)^2)

Residual = Callable[[Float[Array, " d"], Any], Float[Array, " k"]]
Linearize = Callable[[Float[Array, " d"], Any], tuple[Float[Array, " k"], Float[Array, "k d"]]]


def _as_array(x: ArrayLike) -> Array:
    return jnp.asarray(x)


def min_norm_steps(
    residual: Residual,
    s: Float[Array, " d"],
    observation: PyTree,
    scale: Float[ArrayLike, " d"],
    damping: Float[ArrayLike, ""],
    n_steps: int,
    linearize: Linearize | None = None,
) -> Float[Array, " d"]:
    """``n_steps`` damped minimum-norm Gauss-Newton steps on ``residual(s, observation)`` from
    ``s`` (module docstring): s <- s - W J^T (J W J^T + lambda I)^{-1} r, W = diag(scale^2).
    Zero rows of r and J (missing measurements) leave s unchanged along what they would
    constrain. ``linearize(s, observation) -> (r, J)`` gives both in closed form (default:
    ``residual`` and ``jax.jacfwd`` of it). Differentiable; jit/vmap-able."""
    w = jnp.square(jnp.asarray(scale, s.dtype))
    lam = jnp.asarray(damping, s.dtype)

    def body(_, s):
        if linearize is None:
            r = residual(s, observation)
            jac = jax.jacfwd(residual)(s, observation)  # (k, d)
        else:
            r, jac = linearize(s, observation)
        jw = jac * w[None, :]
        # A = J W J^T + lambda I and the update W J^T z as sums of broadcast products: XLA
        # fuses them; as dots or reductions they became batched library calls under vmap
        a = lam * jnp.eye(r.shape[0], dtype=s.dtype)
        for j in range(jac.shape[1]):
            a = a + jw[:, None, j] * jac[None, :, j]
        z = spd_solve(a, r)
        for i in range(r.shape[0]):
            s = s - jw[i] * z[i]
        return s

    return jax.lax.fori_loop(0, n_steps, body, s)


UNROLL_MAX = 12  # spd_solve writes the Cholesky out element by element up to this size


def spd_solve(a: Float[Array, "k k"], b: Float[Array, " k"]) -> Float[Array, " k"]:
    """x = a^-1 b for a symmetric positive definite ``a`` by Cholesky factorisation.

    Up to :data:`UNROLL_MAX` unknowns the factorisation and the two triangular solves are
    written out entry by entry (k^3 / 6 multiply-adds on scalars): under ``vmap`` over a few
    hundred particles every entry is one vector of the batch and XLA fuses the whole solve
    into a few loops, where the batched LAPACK ``cholesky`` and ``triangular_solve`` calls
    cost ~1 ms per Gauss-Newton step of 500 9x9 systems (``docs/results/realtime_profile.md``).
    Larger systems use ``jax.scipy.linalg.cho_solve``."""
    k = b.shape[0]
    if k > UNROLL_MAX:
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(a), b)
    low: dict[tuple[int, int], Array] = {}  # L[i, j], i >= j
    inv = []  # 1 / L[j, j]
    for j in range(k):
        acc = a[j, j]
        for p in range(j):
            acc = acc - low[j, p] * low[j, p]
        d = jnp.sqrt(acc)
        inv.append(1.0 / d)
        for i in range(j + 1, k):
            acc = a[i, j]
            for p in range(j):
                acc = acc - low[i, p] * low[j, p]
            low[i, j] = acc * inv[j]
    y = []  # L y = b
    for i in range(k):
        acc = b[i]
        for p in range(i):
            acc = acc - low[i, p] * y[p]
        y.append(acc * inv[i])
    x: list[Array] = [jnp.zeros((), b.dtype)] * k  # L^T x = y
    for i in reversed(range(k)):
        acc = y[i]
        for p in range(i + 1, k):
            acc = acc - low[p, i] * x[p]
        x[i] = acc * inv[i]
    return jnp.stack(x)


class GuidedProposal(eqx.Module):
    """Moves a random ``fraction`` of the predicted particles by :func:`min_norm_steps` on
    ``residual`` (the others keep the plain prediction). ``scale`` (d,) is the per-DOF unit of
    the minimum-norm metric (state units, e.g. the filter's ``sigma_max``), ``damping`` the
    Levenberg lambda (residual units^2), ``linearize`` an optional closed-form
    (residual, Jacobian) of ``residual`` (default: forward-mode autodiff). ``fraction`` and
    ``n_steps`` are static (they fix the compiled shapes); ``scale`` and ``damping`` are
    traced.

    Call: ``proposal(x (N, d), observation, key) -> x'`` (the caller re-applies its box)."""

    residual: Residual
    scale: Float[Array, " d"] = eqx.field(converter=_as_array)
    linearize: Linearize | None = None
    damping: Float[Array, ""] = eqx.field(converter=_as_array, default=GUIDED_DAMPING)
    fraction: float = eqx.field(static=True, default=GUIDED_FRACTION)
    n_steps: int = eqx.field(static=True, default=GUIDED_STEPS)

    def __check_init__(self):
        if not callable(self.residual):
            raise ValueError(
                f"GuidedProposal.residual: expected a callable, got {type(self.residual)}"
            )
        if not 0.0 <= self.fraction <= 1.0:
            raise ValueError(f"GuidedProposal.fraction: expected in [0, 1], got {self.fraction}")
        if self.n_steps < 0:
            raise ValueError(f"GuidedProposal.n_steps: expected >= 0, got {self.n_steps}")

    def n_guided(self, n: int) -> int:
        return int(round(self.fraction * n))

    def __call__(
        self, x: Float[Array, "n d"], observation: PyTree, key: PRNGKeyArray
    ) -> Float[Array, "n d"]:
        n = x.shape[0]
        m = self.n_guided(n)
        if m == 0 or self.n_steps == 0:
            return x
        idx = jax.random.permutation(key, n)[:m]
        moved = jax.vmap(min_norm_steps, in_axes=(None, 0, None, None, None, None, None))(
            self.residual, x[idx], observation, self.scale, self.damping, self.n_steps,
            self.linearize,
        )  # fmt: skip
        return x.at[idx].set(moved)
