"""The global 6-DOF placement (Wang §5.2 step 2): a closed-form guess (triangulation + Kabsch)
and the 6-DOF IK of the root against the blend's centroids in every camera."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float

from jaxmocap.body import ROOT_DOFS, KinematicChain
from jaxmocap.camera import Camera, triangulate
from jaxmocap.ik.anchors import PatchAnchors, _project_anchor_points, anchor_positions
from jaxmocap.ik.covariances import _whitener
from jaxmocap.ik.residuals import _dense_jacobian
from jaxmocap.ik.solver import (
    _ADJOINT,
    _OPTIONS,
    DEFAULT_ATOL,
    DEFAULT_MAX_STEPS,
    DEFAULT_RTOL,
    FtolLevenbergMarquardt,
    IKSolution,
    _default_ftol,
)
from jaxmocap.rotations import so3_exp, so3_log

MIN_KABSCH_PATCHES = 3  # a rigid fit needs 3 non-collinear triangulated anchors
KABSCH_MIN_SPREAD = 1e-6  # 2nd singular value / 1st below this: anchors collinear, fit refused


def _kabsch(
    X: Float[Array, "n 3"], Y: Float[Array, "n 3"], w: Float[Array, " n"]
) -> tuple[Array, Array, Array]:
    """Weighted rigid fit ``Y ~ R X + t`` (Kabsch); returns (R, t, well_conditioned)."""
    sw = jnp.maximum(w.sum(), jnp.finfo(X.dtype).tiny)
    mx = (w[:, None] * X).sum(0) / sw
    my = (w[:, None] * Y).sum(0) / sw
    H = jnp.einsum("n,ni,nj->ij", w, X - mx[None], Y - my[None])
    U, S, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(Vt.T @ U.T))
    D = jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), jnp.where(d == 0, 1.0, d)]))
    R = Vt.T @ D @ U.T
    t = my - R @ mx
    return R, t, S[1] > KABSCH_MIN_SPREAD * S[0]


def _root_frame(q_b: Array) -> Array:
    """q_b with the root DOFs zeroed: the body in its root-placement frame."""
    return q_b.at[:ROOT_DOFS].set(0.0)


@jax.jit
def initial_root(
    cams: Camera,
    chain: KinematicChain,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_prev: Float[Array, 6],
) -> tuple[Float[Array, 6], Bool[Array, ""]]:
    """Initial root (translation m, rotation vector rad) for the global solve (step 2).

    With 2+ cameras, patches seen by at least two of them are triangulated (N-view DLT,
    :func:`jaxmocap.camera.triangulate`); if at least ``MIN_KABSCH_PATCHES`` non-collinear
    ones are, the root is the closed-form rigid (Kabsch) fit of the anchors of ``q_b`` (in
    the root-placement frame) to them. Otherwise ``root_prev`` (e.g. the previous frame's
    root) is kept. Returns (root, whether the fit was used). Not differentiated.
    """
    dt = q_b.dtype
    root_prev = root_prev.astype(dt)
    if cams.K.ndim != 3 or cams.K.shape[0] < 2:
        return root_prev, jnp.array(False)
    vis = jnp.asarray(visible, bool)
    X = anchor_positions(chain, anchors, _root_frame(q_b))
    if X.ndim == 3:  # per-view anchors: their mean over cameras
        X = X.mean(0)
    Y = triangulate(cams, centroids.astype(dt), refine=False, weights=vis.astype(dt))
    seen = vis.sum(0) >= 2
    Y = jnp.where(seen[:, None], Y, 0.0)
    R, t, well = _kabsch(X, Y, seen.astype(dt))
    use = (seen.sum() >= MIN_KABSCH_PATCHES) & well
    root = jnp.where(use, jnp.concatenate([t, so3_log(R)]), root_prev)
    return jax.lax.stop_gradient(root), use


def solve_global(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_init: Float[Array, 6],
    centroid_cov: Float[Array, "*patches 2 2"] | None = None,
    *,
    rtol: float | Float[Array, ""] = DEFAULT_RTOL,
    atol: float | Float[Array, ""] = DEFAULT_ATOL,
    max_steps: int = DEFAULT_MAX_STEPS,
    ftol: float | Float[Array, ""] | None = None,
) -> IKSolution:
    """Global position and orientation (Wang et al. §5.2 step 2): a 6-DOF IK.

    The joints stay at ``q_b``; the root (``q[0:6]``, whose value in ``q_b`` is ignored) is
    found by minimising ``sum_{i,k} ||c^{*i}_k(q) - c^{ki}||^2_{Sigma_c}`` over visible
    patches in all cameras (Sigma_c default: identity, pixels), starting from ``root_init``
    (see :func:`initial_root`). The rotation is solved as a left increment
    ``exp([dw]_x) R_init`` (well conditioned for any ``root_init``). Returns an
    :class:`IKSolution` (``q`` = q_b with the solved root). Tolerances traced, as
    :func:`solve_ik`.
    """
    tol = lambda x: jnp.asarray(x, dtype=q_b.dtype)
    ftol = tol(_default_ftol(q_b.dtype) if ftol is None else ftol)
    return _solve_global(chain, cams, anchors, centroids, visible, q_b, root_init, centroid_cov,
                         tol(rtol), tol(atol), max_steps, ftol)  # fmt: skip


@functools.partial(jax.jit, static_argnames=("max_steps",))
def _solve_global(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    root_init: Float[Array, 6],
    centroid_cov: Float[Array, "*patches 2 2"] | None,
    rtol: Float[Array, ""],
    atol: Float[Array, ""],
    max_steps: int,
    ftol: Float[Array, ""],
) -> IKSolution:
    """The jitted core of :func:`solve_global`."""
    dt = q_b.dtype
    n_p = anchors.n_patches
    cov_c = jnp.eye(2, dtype=dt) if centroid_cov is None else centroid_cov
    vis = jnp.asarray(visible, bool)
    if vis.shape != (cams.K.shape[0], n_p) or centroids.shape != vis.shape + (2,):
        raise ValueError(
            f"solve_global: expected centroids (n_cams, {n_p}, 2) and visible (n_cams, {n_p}); "
            f"got {centroids.shape} and {vis.shape}"
        )
    X = anchor_positions(chain, anchors, _root_frame(q_b))
    root_init = root_init.astype(dt)
    R0, t0 = so3_exp(root_init[3:6]), root_init[0:3]
    obs = jnp.where(vis[..., None], centroids.astype(dt), 0.0)
    Wc = jnp.broadcast_to(_whitener(cov_c, dt), (n_p, 2, 2))

    def place(y, R0, t0):
        R = so3_exp(y[3:6]) @ R0
        return R, t0 + y[0:3]

    @_dense_jacobian
    def fn(y, args):
        X, R0, t0, cams, obs, vis, Wc, shift = args
        R, t = place(y, R0, t0)
        d = _project_anchor_points(cams, X @ R.T + t.reshape((1,) * (X.ndim - 1) + (3,)), shift)
        d = d - obs
        r = jnp.einsum("pij,cpj->cpi", Wc, d)
        return jnp.where(vis[..., None], r, 0.0).reshape(-1)

    args = (X, R0, t0, cams, obs, vis, Wc, anchors.shift)
    solver = FtolLevenbergMarquardt(rtol=rtol, atol=atol, ftol=ftol)
    sol = optx.least_squares(
        fn,
        solver,
        jnp.zeros(6, dt),
        args,
        max_steps=max_steps,
        throw=False,
        adjoint=_ADJOINT,
        options=_OPTIONS,
    )
    R, t = place(sol.value, R0, t0)
    q = q_b.at[0:3].set(t).at[3:6].set(so3_log(R))
    cost = jnp.sum(sol.state.inner.f_info.residual**2)
    return IKSolution(q=q, result=sol.result, num_steps=sol.stats["num_steps"], cost=cost)
