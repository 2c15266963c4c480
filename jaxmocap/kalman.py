"""Offline smoothing of per-frame pose estimates: a Rauch-Tung-Striebel (forward-backward)
smoother on a constant-velocity model, one independent model per DOF.

**Model.** Each DOF ``y`` (a root coordinate, a rotation-vector component or a joint angle)
is a position ``p`` with velocity ``v`` driven by white acceleration noise of spectral density
``q``, observed once per frame with noise variance ``r / w_t``. In frame units (state
``x = [p, u]``, ``u = v dt``)::

    x_{t+1} = F x_t + e_t,  F = [[1, 1], [0, 1]],  Cov e_t = lam [[1/3, 1/2], [1/2, 1]] r
    y_t     = p_t + n_t,    Var n_t = r / w_t

``w_t`` is frame t's weight (its relative precision): 1 for an estimate the tracker trusts,
0 for a **missing observation** (an invalid frame, a frame without an estimate): the
smoother ignores it and bridges it with the model. The smoothed mean is the minimiser of the
quadratic energy ``sum_t w_t (y_t - p_t)^2 + sum_t e_t^T Cov_e^-1 e_t / r`` (plus a diffuse
prior on the first state), so it depends on ``r`` and ``q`` only through
``lam = q dt^3 / r``; ``r`` is 1 here and the variances returned are in units of ``r``.

**One parameter, a cut-off frequency.** Far from the sequence's ends, the smoother is the
non-causal Wiener filter of a doubly integrated white noise seen in white noise: its
frequency response is ``1 / (1 + (f / f_c)^4)`` (no phase lag), gain 1/2 at ``f_c``, with
``lam = (2 pi f_c / fps)^4`` (:func:`process_ratio`). Biomechanics low-passes marker data at a
few Hz (Winter: 6 Hz Butterworth); the default here, 4 Hz, keeps upper-body motion and
removes the frame-to-frame scatter of a per-frame IK.

**Poses.** :func:`smooth_poses` smooths a pose sequence (:mod:`jaxmocap.body` layout): the root
rotation vector is first unwrapped (the same rotation written with the angle nearest the
previous frame's, so that no component jumps by 2 pi between frames), smoothed per component
and wrapped back to angles <= pi; frames outside the span of weighted frames keep their own
estimate (there the smoother would only extrapolate), and a frame without an estimate stays
without one.

Pure JAX: :func:`rts_smooth` is one ``lax.scan`` forward and one backward, jit/vmap/grad-able
(the smoothed mean is linear in ``y`` for fixed weights).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = [
    "DEFAULT_CUTOFF_HZ",
    "PRIOR_VARIANCE",
    "Smoothed",
    "process_ratio",
    "rts_smooth",
    "smooth_poses",
    "unwrap_rotvec",
    "wrap_rotvec",
]

DEFAULT_CUTOFF_HZ = 4.0  # gain 1/2 of the smoother's frequency response (module docstring)
PRIOR_VARIANCE = 1e4  # the first state's prior variance (position and velocity), units of r


class Smoothed(NamedTuple):
    """:func:`rts_smooth`'s result: the smoothed positions ``mean`` (T, D) and their posterior
    variances ``var`` (T, D) in units of the observation variance ``r``."""

    mean: Float[Array, "t d"]
    var: Float[Array, "t d"]


def process_ratio(cutoff_hz, fps):
    """``lam = (2 pi f_c / fps)^4``: the process-to-observation noise ratio (per frame) whose
    smoother has gain 1/2 at ``cutoff_hz`` (module docstring)."""
    return (2.0 * np.pi * cutoff_hz / fps) ** 4


def _one(y, w, lam):
    """The smoother of one DOF: ``y`` (T,), ``w`` (T,) >= 0 (0 where ``y`` is not finite),
    ``lam`` (): (mean (T,), var (T,))."""
    dt = y.dtype
    F = jnp.array([[1.0, 1.0], [0.0, 1.0]], dt)
    Q = lam * jnp.array([[1.0 / 3.0, 0.5], [0.5, 1.0]], dt)
    y = jnp.where(w > 0, y, 0.0)
    first = jnp.argmax(w > 0)  # the prior's mean: the first weighted observation, at rest
    m0 = jnp.stack([y[first], jnp.zeros((), dt)])
    P0 = PRIOR_VARIANCE * jnp.eye(2, dtype=dt)

    def update(m, P, yt, wt):
        # K = P H^T / (H P H^T + 1/w), written so that w = 0 gives K = 0 (no observation)
        K = wt * P[:, 0] / (wt * P[0, 0] + 1.0)
        m = m + K * (yt - m[0])
        P = P - jnp.outer(K, P[0, :])
        return m, 0.5 * (P + P.T)

    def forward(carry, inp):
        m_pred, P_pred = carry
        m, P = update(m_pred, P_pred, *inp)
        return (F @ m, F @ P @ F.T + Q), (m, P, m_pred, P_pred)

    _, (mf, Pf, mp, Pp) = jax.lax.scan(forward, (m0, P0), (y, w))

    def backward(carry, inp):
        ms_next, Ps_next = carry
        m, P, m_pred_next, P_pred_next = inp
        G = P @ F.T @ jnp.linalg.inv(P_pred_next)
        ms = m + G @ (ms_next - m_pred_next)
        Ps = P + G @ (Ps_next - P_pred_next) @ G.T
        Ps = 0.5 * (Ps + Ps.T)
        return (ms, Ps), (ms, Ps)

    last = (mf[-1], Pf[-1])
    inputs = (mf[:-1], Pf[:-1], mp[1:], Pp[1:])
    _, (ms, Ps) = jax.lax.scan(backward, last, inputs, reverse=True)
    ms = jnp.concatenate([ms, mf[-1:]])
    Ps = jnp.concatenate([Ps, Pf[-1:]])
    return ms[:, 0], Ps[:, 0, 0]


@jax.jit
def rts_smooth(y: Float[Array, "t d"], weight, lam) -> Smoothed:
    """The RTS smoother of the module docstring over each column of ``y`` (T, D).

    ``weight``: (T,) or (T, D) relative precision of each observation (1 nominal, 0 missing;
    a non-finite ``y`` is missing whatever its weight); ``lam``: () or (D,) the process ratio
    (:func:`process_ratio`). A column without any weighted observation comes back as the
    prior (zeros, variance ``PRIOR_VARIANCE``-sized)."""
    y = jnp.asarray(y)
    if y.ndim != 2:
        raise ValueError(f"rts_smooth: y must be (T, D), got shape {y.shape}")
    w = jnp.asarray(weight, y.dtype)
    if w.ndim == 1:
        w = w[:, None]
    w = jnp.broadcast_to(w, y.shape)
    w = jnp.where(jnp.isfinite(y) & (w > 0), w, 0.0)
    lam = jnp.broadcast_to(jnp.asarray(lam, y.dtype), y.shape[1:])
    mean, var = jax.vmap(_one, in_axes=(1, 1, 0), out_axes=1)(y, w, lam)
    return Smoothed(mean, var)


def unwrap_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (T, 3) rewritten, each as the same rotation ``n (theta + 2 pi k)``
    with the ``k`` that brings it nearest the previous (unwrapped) one: no 2 pi jumps."""
    r = np.array(r, np.float64)
    for t in range(1, len(r)):
        theta = np.linalg.norm(r[t])
        if theta < 1e-12:
            continue
        n = r[t] / theta
        k = np.round((n @ r[t - 1] - theta) / (2 * np.pi))
        r[t] = n * (theta + 2 * np.pi * k)
    return r


def wrap_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) written with angles in [0, pi] (the same rotations)."""
    r = np.array(r, np.float64)
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    wrapped = theta - 2 * np.pi * np.round(theta / (2 * np.pi))  # in [-pi, pi]
    scale = np.divide(wrapped, theta, out=np.ones_like(theta), where=theta > 1e-12)
    return r * scale


def smooth_poses(q: np.ndarray, weight: np.ndarray, fps: float,
                 cutoff_hz: float = DEFAULT_CUTOFF_HZ, rotvec: slice = slice(3, 6)) -> np.ndarray:
    """Smoothed poses (T, n_dof) of the per-frame estimates ``q`` (T, n_dof) with weights
    ``weight`` (T,) (e.g. the valid flags: invalid frames are missing observations), the
    root rotation vector at ``rotvec`` unwrapped first and wrapped back (module docstring).
    Frames before the first and after the last weighted frame keep their own estimate, frames
    without one (non-finite rows) stay so; with fewer than two weighted frames ``q`` comes back
    unchanged."""
    q = np.array(q, np.float64)
    if not fps > 0 or not 0 < cutoff_hz < fps / 2:
        raise ValueError(f"smooth_poses: cutoff_hz must be in (0, fps/2) = (0, {fps / 2:g}), "
                         f"got {cutoff_hz}")
    w = np.asarray(weight, np.float64) * np.isfinite(q).all(axis=1)
    idx = np.flatnonzero(w > 0)
    if len(idx) < 2:
        return q
    a, b = idx[0], idx[-1] + 1
    y = q[a:b].copy()
    seen = w[a:b] > 0
    y[seen, rotvec] = unwrap_rotvec(y[seen, rotvec])
    y[~seen] = np.nan
    out = np.array(rts_smooth(jnp.asarray(y), jnp.asarray(w[a:b]),
                                process_ratio(cutoff_hz, fps)).mean, np.float64)
    out[:, rotvec] = wrap_rotvec(out[:, rotvec])
    has = np.isfinite(q[a:b]).all(axis=1)
    q[a:b][has] = out[has]
    return q
