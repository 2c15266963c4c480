"""The IK energy as whitened least-squares residuals: centroid terms (optionally Cauchy-robust)
and the priors toward the blend and the previous pose; joint limits by a tanh reparametrisation."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.dtypes import float0
from jaxtyping import Array, Bool, Float

from jaxmocap.body import KinematicChain
from jaxmocap.camera import Camera
from jaxmocap.ik.anchors import PatchAnchors, _project_anchor_points, anchor_positions
from jaxmocap.ik.covariances import IKCovariances, _whiten, _whitener

LIMIT_MARGIN = 1e-6  # initial guesses on a limit start this fraction of the half range inside


def _zero_tangent(t):
    if not isinstance(t, SymbolicZero):
        return t
    return (
        np.zeros(t.aval.shape, t.aval.dtype)
        if t.aval.dtype == float0
        else jnp.zeros(t.aval.shape, t.aval.dtype)
    )


def _dense_jacobian(f):
    """``f(y, args)`` whose JVP in ``y`` builds the Jacobian once (vmapped forward mode).

    Gauss-Newton solvers call the linearised residual several times per step (Jacobian
    materialisation, predicted reduction, its transpose). With this rule those calls are
    matrix products with one dense ``J``, instead of re-emitting the linearised forward
    kinematics each time: a much smaller program (compile time) and fewer flops per step.
    Tangents in ``args`` (e.g. covariances, under ``jax.grad``) go through an ordinary JVP.
    """

    @jax.custom_jvp
    def g(y, args):
        return f(y, args)

    @functools.partial(g.defjvp, symbolic_zeros=True)
    def g_jvp(primals, tangents):
        y, args = primals
        ty, targs = tangents
        if isinstance(ty, SymbolicZero):
            out = f(y, args)
            tout = jnp.zeros_like(out)
        else:
            basis = jnp.eye(y.shape[0], dtype=y.dtype)
            push = lambda v: jax.jvp(lambda y_: f(y_, args), (y,), (v,))
            out, J = jax.vmap(push, out_axes=(None, -1))(basis)
            tout = J @ ty
        is_zero = lambda t: isinstance(t, SymbolicZero)
        if not all(map(is_zero, jax.tree.leaves(targs, is_leaf=is_zero))):
            targs = jax.tree.map(_zero_tangent, targs, is_leaf=is_zero)
            tout = tout + jax.jvp(lambda a: f(y, a), (args,), (targs,))[1]
        return out, tout

    return g


class _Terms(eqx.Module):
    """Everything the residual needs, passed as optimistix ``args`` (so it is differentiated)."""

    chain: KinematicChain
    cams: Camera
    anchors: PatchAnchors
    obs: Array  # (C, P, 2) observed centroids, 0 where invisible
    vis: Array  # (C, P) bool
    q_b: Array
    q_h: Array
    Wc: Array  # (P, 2, 2)
    Wb: Array
    Wp: Array
    robust: Array  # () Cauchy scale of the whitened centroid residuals; inf: plain squares


def robust_centroid_residual(r: Float[Array, "*b 2"], scale: Float[Array, ""]) -> Array:
    """Cauchy-robustified whitened 2D residuals: ``r`` rescaled so that its squared norm is
    ``rho(|r|^2) = c^2 log(1 + |r|^2 / c^2)`` (``c = scale``; ``inf``: unchanged). Smooth;
    ~``r`` for ``|r| << c``, and an outlier's pull fades as ``c^2 / |r|``."""
    n2 = jnp.sum(r**2, axis=-1, keepdims=True)
    big = n2 > jnp.finfo(r.dtype).tiny
    n2s = jnp.where(big, n2, 1.0)
    c2 = jnp.where(jnp.isfinite(scale), scale, 1.0) ** 2
    f = jnp.where(big, jnp.sqrt(c2 * jnp.log1p(n2s / c2) / n2s), 1.0)
    return jnp.where(jnp.isfinite(scale), f, 1.0) * r


def _centroid_residual(X: Array, t: _Terms) -> Array:
    d = _project_anchor_points(t.cams, X, t.anchors.shift) - t.obs  # (C, P, 2)
    r = robust_centroid_residual(jnp.einsum("pij,cpj->cpi", t.Wc, d), t.robust)
    return jnp.where(t.vis[..., None], r, 0.0).reshape(-1)


def _residual(q: Array, t: _Terms) -> Array:
    X = anchor_positions(t.chain, t.anchors, q)
    return jnp.concatenate(
        [_centroid_residual(X, t), _whiten(t.Wb, q - t.q_b), _whiten(t.Wp, q - t.q_h)]
    )


def _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov, robust=None) -> _Terms:
    dt = q_b.dtype
    vis = jnp.asarray(visible, bool)
    obs = jnp.where(vis[..., None], centroids.astype(dt), 0.0)
    n_p = anchors.n_patches
    if vis.shape != (cams.K.shape[0], n_p) or centroids.shape != vis.shape + (2,):
        raise ValueError(
            f"IK: expected centroids ({cams.K.shape[0]}, {n_p}, 2) and visible "
            f"({cams.K.shape[0]}, {n_p}) for {cams.K.shape[0]} cameras and {n_p} patches; got "
            f"{centroids.shape} and {vis.shape}"
        )
    if cov.blend.shape[0] != q_b.shape[0]:
        raise ValueError(
            f"IK: covariances are for {cov.blend.shape[0]} DOFs, the pose has {q_b.shape[0]}"
        )
    Wc = jnp.broadcast_to(_whitener(cov.centroid, dt), (n_p, 2, 2))
    robust = jnp.asarray(jnp.inf if robust is None else robust, dt)
    return _Terms(
        chain, cams, anchors, obs, vis, q_b, q_h.astype(dt), Wc,
        _whitener(cov.blend, dt), _whitener(cov.prior, dt), robust,
    )  # fmt: skip


def ik_residuals(
    q: Float[Array, " n_dof"],
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
) -> Float[Array, " n_res"]:
    """Whitened residual vector of the step-4 energy: ``E(q) = sum(ik_residuals(...)**2)``.

    Layout: ``n_cams * P * 2`` centroid terms (0 for invisible patches), then ``n_dof``
    blend-prior terms, then ``n_dof`` temporal-prior terms.
    """
    return _residual(q, _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov))


# ----------------------------------------------------------------------------- joint limits


def _limit_params(lower: Array, upper: Array) -> tuple[Array, Array, Array]:
    """(finite, mid, half) of the limit map; NaN-free for infinite limits."""
    finite = jnp.isfinite(lower) & jnp.isfinite(upper)
    lo = jnp.where(finite, lower, -1.0)
    hi = jnp.where(finite, upper, 1.0)
    return finite, 0.5 * (hi + lo), 0.5 * (hi - lo)


def _z_to_q(z: Array, finite: Array, mid: Array, half: Array) -> Array:
    return jnp.where(finite, mid + half * jnp.tanh(z), z)


def _q_to_z(q: Array, finite: Array, mid: Array, half: Array) -> Array:
    ratio = jnp.clip((q - mid) / half, -1.0 + LIMIT_MARGIN, 1.0 - LIMIT_MARGIN)
    return jnp.where(finite, jnp.arctanh(ratio), q)
