"""The IK solve (Wang §5.2 step 4): optimistix Levenberg-Marquardt with MINPACK's ftol stop
(:class:`FtolLevenbergMarquardt`), implicit adjoint, :func:`solve_ik`."""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from jaxmocap.body import KinematicChain
from jaxmocap.camera import Camera
from jaxmocap.ik.anchors import PatchAnchors
from jaxmocap.ik.covariances import IKCovariances
from jaxmocap.ik.residuals import (
    _dense_jacobian,
    _limit_params,
    _make_terms,
    _q_to_z,
    _residual,
    _z_to_q,
)

DEFAULT_MAX_STEPS = 64  # fixed iteration budget of every IK solve (static: sets the program)
DEFAULT_RTOL = 1e-7  # relative tolerance on z and on the whitened residuals (traced)
DEFAULT_ATOL = 1e-9  # absolute tolerance (traced)

# Solution of the normal equations in the implicit adjoint: SVD (pseudo-inverse), so that a DOF
# saturated at a joint limit simply has zero sensitivity.
_OPTIONS = {"jac": "fwd"}  # forward-mode Jacobians: fewer ops than reverse for n_dof < n_res
_ADJOINT = optx.ImplicitAdjoint(linear_solver=lx.AutoLinearSolver(well_posed=False))


def _default_ftol(dtype) -> float:
    """8 float eps of ``dtype``: the rounding of a sum of squares
    (:class:`FtolLevenbergMarquardt`)."""
    return 8 * float(jnp.finfo(dtype).eps)


class _FtolState(eqx.Module):
    inner: PyTree
    stop: Bool[Array, ""]


class FtolLevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """``optx.LevenbergMarquardt`` plus MINPACK's ``ftol`` test (Moré 1978; ``lmder``'s
    ``info = 1``): stop when both the actual and the predicted reduction of the sum of squares
    by the last proposed step are at most ``ftol`` times it (a rejected step's actual change
    is a rise, kept only while its prediction is that small).

    optimistix's own test (Cauchy: every residual element and every parameter changed by less
    than ``atol + rtol |.|`` on an accepted step) is kept. In float32 it is rarely met: at the
    optimum the sum of squares moves by rounding (~1e-6 relative), every proposal is rejected
    and the trust region shrinks by 4x per step until ``max_steps``. Measured on the shirt
    tracker's IK (bench scene, 24 DOF): converged after 14 and 9 steps, stopped after 42 and
    31 (docs/results/realtime_profile.md). ``ftol`` defaults to 8 float eps of the
    solve's dtype (the rounding of the loss); 0 turns the test off. ``y`` and the residual are
    single arrays."""

    inner: optx.LevenbergMarquardt
    ftol: float | Array | None
    rtol: float
    atol: float
    norm: Callable = eqx.field(static=True)

    def __init__(self, rtol, atol, ftol=None):
        self.inner = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
        self.rtol, self.atol, self.norm, self.ftol = rtol, atol, self.inner.norm, ftol

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _FtolState(inner, jnp.array(False))

    def step(self, fn, y, args, options, state, tags):
        st = state.inner
        f0 = st.f_info.residual
        loss0 = jnp.sum(f0**2)
        dt = loss0.dtype
        ftol = jnp.asarray(_default_ftol(dt) if self.ftol is None else self.ftol, dt)
        model = f0 + st.f_info.jac.mv(st.y_eval - y)  # linearised residual after the step
        predicted = loss0 - jnp.sum(model**2)
        new_y, new_st, aux = self.inner.step(fn, y, args, options, st, tags)
        accepted = new_st.num_steps_since_acceptance == 0
        actual = loss0 - jnp.sum(new_st.f_info.residual**2)
        scale = ftol * loss0
        small = (jnp.abs(predicted) <= scale) & (~accepted | (jnp.abs(actual) <= scale))
        small = small & (ftol > 0)  # ftol = 0: the test is off
        return new_y, _FtolState(new_st, small & ~st.first_step), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return done | state.stop, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


class IKSolution(eqx.Module):
    """Result of an IK solve.

    ``q`` the solved pose, ``result`` the optimistix result code (``optx.RESULTS.successful``
    or why not: e.g. ``nonlinear_max_steps_reached``), ``num_steps`` iterations taken,
    ``cost`` the energy (sum of squared whitened residuals) at ``q``.
    """

    q: Float[Array, "*batch n_dof"]
    result: optx.RESULTS
    num_steps: Int[Array, "*batch"]
    cost: Float[Array, "*batch"]

    @property
    def converged(self) -> Bool[Array, "*batch"]:
        return self.result == optx.RESULTS.successful


def _free_index(free_dofs: tuple[int, ...] | None, n_dof: int) -> np.ndarray:
    if free_dofs is None:
        return np.arange(n_dof)
    idx = np.asarray(free_dofs, dtype=np.int64).reshape(-1)
    if (
        idx.size == 0
        or np.any(idx < 0)
        or np.any(idx >= n_dof)
        or len(set(idx.tolist())) != idx.size
    ):
        raise ValueError(
            f"solve_ik: free_dofs must be distinct indices in [0, {n_dof}), got {free_dofs}"
        )
    return np.sort(idx)


def solve_ik(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
    q_init: Float[Array, " n_dof"] | None = None,
    *,
    free_dofs: tuple[int, ...] | None = None,
    rtol: float | Float[Array, ""] = DEFAULT_RTOL,
    atol: float | Float[Array, ""] = DEFAULT_ATOL,
    max_steps: int = DEFAULT_MAX_STEPS,
    robust: float | Float[Array, ""] | None = None,
    ftol: float | Float[Array, ""] | None = None,
) -> IKSolution:
    """Pose refinement by IK (Wang et al. §5.2 step 4), Levenberg-Marquardt in optimistix.

    Minimises the energy of :func:`ik_residuals` over the DOFs ``free_dofs`` (default all;
    a static tuple of indices into q), the others staying at ``q_init`` (default ``q_b``),
    which is also the initial guess. Joint limits of ``chain`` hold for the result (tanh
    reparametrisation, see :mod:`jaxmocap.ik`). Levenberg-Marquardt stops on optimistix's
    test (``rtol``, ``atol``) or on MINPACK's relative reduction ``ftol``
    (:class:`FtolLevenbergMarquardt`; None: 8 float eps, 0: off); the three are traced:
    changing them does not recompile; ``free_dofs`` and ``max_steps`` are static. Never raises
    on non-convergence: check ``result`` / ``converged``. Differentiable (implicit adjoint)
    w.r.t. every array input, covariances included. Batch frames with ``jax.vmap``.

    ``robust`` (not in the paper; default None = the paper's plain squares) replaces each
    patch's whitened centroid term ``|r|^2`` by the Cauchy ``c^2 log(1 + |r|^2 / c^2)`` with
    ``c = robust`` (in standard deviations of Sigma_c; traced), so that a centroid corrupted
    by misclassified pixels cannot drag the whole pose (:func:`robust_centroid_residual`).
    """
    tol = lambda x: jnp.asarray(x, dtype=q_b.dtype)
    rob = tol(jnp.inf if robust is None else robust)
    ftol = tol(_default_ftol(q_b.dtype) if ftol is None else ftol)
    return _solve_ik(chain, cams, anchors, centroids, visible, q_b, q_h, cov, q_init,
                     free_dofs, tol(rtol), tol(atol), max_steps, rob, ftol)  # fmt: skip


@functools.partial(jax.jit, static_argnames=("free_dofs", "max_steps"))
def _solve_ik(
    chain: KinematicChain,
    cams: Camera,
    anchors: PatchAnchors,
    centroids: Float[Array, "n_cams n_patches 2"],
    visible: Bool[Array, "n_cams n_patches"],
    q_b: Float[Array, " n_dof"],
    q_h: Float[Array, " n_dof"],
    cov: IKCovariances,
    q_init: Float[Array, " n_dof"] | None,
    free_dofs: tuple[int, ...] | None,
    rtol: Float[Array, ""],
    atol: Float[Array, ""],
    max_steps: int,
    robust: Float[Array, ""],
    ftol: Float[Array, ""],
) -> IKSolution:
    """The jitted core of :func:`solve_ik` (every argument explicit, tolerances arrays)."""
    terms = _make_terms(chain, cams, anchors, centroids, visible, q_b, q_h, cov, robust)
    dt = q_b.dtype
    q0 = q_b if q_init is None else q_init.astype(dt)
    idx = _free_index(free_dofs, q_b.shape[0])
    limits = _limit_params(chain.lower[idx].astype(dt), chain.upper[idx].astype(dt))

    @_dense_jacobian
    def fn(z, args):
        q_fixed, lim, t = args
        return _residual(q_fixed.at[idx].set(_z_to_q(z, *lim)), t)

    args = (q0, limits, terms)
    z0 = _q_to_z(q0[idx], *limits)
    solver = FtolLevenbergMarquardt(rtol=rtol, atol=atol, ftol=ftol)
    sol = optx.least_squares(
        fn, solver, z0, args, max_steps=max_steps, throw=False, adjoint=_ADJOINT, options=_OPTIONS
    )
    q = q0.at[idx].set(_z_to_q(sol.value, *limits))
    cost = jnp.sum(sol.state.inner.f_info.residual**2)
    return IKSolution(q=q, result=sol.result, num_steps=sol.stats["num_steps"], cost=cost)
