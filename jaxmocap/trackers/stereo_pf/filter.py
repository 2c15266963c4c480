"""The jitted filter (Azad §II, §III-D): the annealed automatic initialisation ``init``, one
frame ``filter_step``, the offline scan ``run`` (optionally fixed-lag smoothed), and their
top-level programs compiled with :data:`COMPILER_OPTIONS`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from jaxmocap import pf
from jaxmocap.body.chain import so3_exp
from jaxmocap.errors import InputError
from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.params import StereoEstimate, StereoPFParams, TrackerState
from jaxmocap.trackers.stereo_pf.start import Start, choose

# The filter's once-per-sequence programs (:data:`init_top_level`, :data:`run_top_level`: the
# annealed initialisation and the offline scan) compile with XLA CPU's classic LLVM IR emitters
# instead of its MLIR fusion emitters (XLA's default in the jax we test, 0.10). The step is
# ~500 small fused kernels (1000 particles' kinematics, the guided proposal's written-out
# solves); the classic emitters compile the filter step in ~0.6x the time (11.7 / 14.1 -> 7.2 /
# 8.9 s on this 2-core machine), ``init`` and the scan in 0.7-0.8x, with the same arithmetic
# up to float32 rounding -- but the compiled step runs 4-10% slower, so the live step
# (:func:`compile_step`, called every frame) keeps XLA's defaults
# (docs/results/realtime_profile.md). XLA takes compile options only on a
# top-level jit, so :func:`init`, :func:`filter_step` and :func:`run` stay plain and nest in a
# caller's jit. A jax older than the one tested may not know the option: it then compiles
# with its own defaults.
COMPILER_OPTIONS: dict[str, bool] = (
    {"xla_cpu_use_fusion_emitters": False} if jax.__version_info__ >= (0, 10) else {}
)
def _estimate(params: StereoPFParams, est: pf.PFEstimate) -> StereoEstimate:
    return StereoEstimate(
        q=params.full_q(est.mean),
        q_best=params.full_q(est.best),
        best_loglik=est.best_loglik,
        ess=est.ess,
        degenerate=est.degenerate,
    )


def _prior(params: StereoPFParams, key: PRNGKeyArray, obs: Observation,
           start: Start | None = None) -> pf.PFState:
    """Broad initial particle set around the triangulated head (automatic initialisation:
    :mod:`jaxmocap.trackers.stereo_pf`), or around a :class:`~.start.Start` anchor (the
    shirt silhouette) when one is given: the root so that ``start.rest`` lies on
    ``start.point``, spread with ``start.cov``."""
    n, dofs = params.n_particles, params.dofs
    dt = params.prior_lower.dtype
    k_yaw, k_tilt, k_root, k_joint = jax.random.split(key, 4)
    yaw = jax.random.uniform(k_yaw, (n,), dt, -1.0, 1.0) * params.init_yaw
    tilt = jax.random.normal(k_tilt, (n, 2), dt) * params.init_tilt
    w = jnp.concatenate([tilt, yaw[:, None]], axis=1)
    valid = obs.valid
    pts = obs.points.astype(dt)
    mean_valid = jnp.sum(jnp.where(valid[:, None], pts, 0), 0) / jnp.maximum(jnp.sum(valid), 1)
    head = jnp.where(valid[0], pts[0], jnp.where(jnp.any(valid), mean_valid, jnp.nan))
    anchored = jnp.any(valid)
    rot = so3_exp(w)
    if start is None:
        root = jnp.where(
            anchored,
            head[None, :] - (rot @ params.head_rest[:, None])[..., 0],
            params.fallback_root[None, :],
        )
        std = jnp.where(anchored, params.init_root_std, 10 * params.init_root_std)
        root = root + std * jax.random.normal(k_root, (n, 3), dt)
    else:
        root = start.point.astype(dt)[None, :] - (rot @ start.rest.astype(dt)[:, None])[..., 0]
        chol = jnp.linalg.cholesky(start.cov.astype(dt))
        root = root + jax.random.normal(k_root, (n, 3), dt) @ chol.T
    u = jax.random.uniform(k_joint, (n, len(dofs)), dt)
    lo, hi = params.prior_lower[None, :], params.prior_upper[None, :]
    x = lo + (hi - lo) * u
    x = x.at[:, :3].set(root).at[:, 3:6].set(w)
    return pf.PFState(
        particles=x,
        previous=x,
        log_weights=jnp.full((n,), -jnp.log(n), dt),
        sigma=params.filter.sigma_max.astype(dt),
    )


@eqx.filter_jit
def init(
    params: StereoPFParams, key: PRNGKeyArray, first: Observation, start: Start | None = None
) -> tuple[TrackerState, StereoEstimate]:
    """Automatic initialisation on the first frame's observation: prior + annealing layers.

    ``start``: the root prior's anchor when it is not the triangulated head (the shirt
    silhouette, :func:`jaxmocap.trackers.stereo_pf.start.choose`); the annealing's distance
    cue then takes the model head's place above the anchor as the head (:mod:`.start`). None:
    Azad's head prior.
    Returns the state (ready for :func:`step` / :func:`run` from the first frame on) and the
    first frame's estimate.
    """
    k_prior, k_anneal, k_next = jax.random.split(key, 3)
    state = _prior(params, k_prior, first, start)
    if start is not None:  # the anchor's head for the annealing's distance cue (module doc)
        head = start.point + params.head_rest - start.rest
        first = dataclasses.replace(first, points=first.points.at[0].set(head.astype(
            first.points.dtype)), valid=first.valid.at[0].set(True))
    filt = params.filter
    if not params.guided_init:
        filt = dataclasses.replace(filt, proposal=None)
    state, est = pf.anneal_step(filt, state, first, k_anneal, params.init_betas)
    return TrackerState(state, k_next), _estimate(params, est)


@eqx.filter_jit
def filter_step(
    params: StereoPFParams, state: TrackerState, obs: Observation
) -> tuple[TrackerState, StereoEstimate]:
    """One particle-filter frame on a precomputed observation (one jitted call): the
    Condensation step, or ``len(step_betas)`` annealing layers when there are several."""
    new_state, (est, _) = _filter_step_lineage(params, state, obs)  # the lineage is dropped
    return new_state, est


def _filter_step_lineage(params: StereoPFParams, state: TrackerState, obs: Observation):
    """:func:`filter_step` plus the new particle set's lineage (for :func:`run`'s smoother)."""
    k_step, k_next = jax.random.split(state.key)
    if params.step_betas.shape[0] == 1:
        ps, est, parent = pf.step_lineage(params.filter, state.particles, obs, k_step)
    else:
        ps, est, parent = pf.anneal_step_lineage(
            params.filter, state.particles, obs, k_step, params.step_betas
        )
    lineage = pf.Lineage(ps.particles, ps.log_weights, parent)
    return TrackerState(ps, k_next), (_estimate(params, est), lineage)


def online_frame(params: StereoPFParams, key: PRNGKeyArray, step, state, seen: list, obs):
    """One frame of an on-line filter over observations made frame by frame (each may depend
    on the previous estimate): before the start frame (:func:`~.start.choose`: a triangulated
    head, or after the wait the shirt or a hand) ``(None, None)``; on it :func:`init` there,
    then ``step`` from frame 0 over ``seen`` (the observations so far, ending with ``obs``), as
    :func:`run` after its init on the anchor frame; afterwards one ``step``. Returns
    ``(state, estimate)``."""
    if state is None:
        got = choose(params, obs.valid, obs.foreground, len(seen) - 1)
        if got is None:
            return None, None
        state, _ = init_top_level(params, key, obs, got[1])
        for o in seen:
            state, est = step(state, o)
        return state, est
    return step(state, obs)


@eqx.filter_jit
def run(
    params: StereoPFParams,
    state: TrackerState,
    observations: Observation,
    smooth_lag: int = 0,
) -> tuple[TrackerState, StereoEstimate]:
    """:func:`filter_step` over a sequence of observations (leading time axis), ``lax.scan``.

    ``smooth_lag`` L > 0 (static; offline use, not in Azad's paper): the estimate ``q`` of
    frame t is the lag-L genealogy smoother's mean -- frame t's ancestors of the frame-(t + L)
    particle set, weighted by that frame's weights (:mod:`jaxmocap.pf.smooth`) -- and
    ``q_filtered`` the filter's mean; the filter itself (and every other field) is unchanged.
    """
    if smooth_lag == 0:
        return jax.lax.scan(lambda s, o: filter_step(params, s, o), state, observations)
    if smooth_lag < 0:
        raise InputError(f"stereo_pf.run: smooth_lag: expected >= 0, got {smooth_lag}")
    final, (est, lineage) = jax.lax.scan(
        lambda s, o: _filter_step_lineage(params, s, o), state, observations
    )
    smoothed = params.full_q(pf.fixed_lag_smooth(lineage, smooth_lag))
    return final, dataclasses.replace(est, q=smoothed, q_filtered=est.q)


init_top_level = eqx.filter_jit(init, compiler_options=COMPILER_OPTIONS)
"""``init`` compiled as a program of its own with :data:`COMPILER_OPTIONS` (not inside a jit)."""
run_top_level = eqx.filter_jit(run, compiler_options=COMPILER_OPTIONS)
"""``run`` compiled as a program of its own with :data:`COMPILER_OPTIONS` (not inside a jit)."""


def compile_step(
    params: StereoPFParams,
) -> Callable[[TrackerState, Observation], tuple[TrackerState, StereoEstimate]]:
    """:func:`filter_step` with ``params`` closed over, for live loops: ``(state, obs) ->
    (state, estimate)``. A ``jax.jit`` closure does not flatten the ~130-leaf parameter pytree
    at every call as ``filter_step(params, ...)`` does (~0.3 ms per frame). It compiles on its
    first call; build a new one when the parameters change. It keeps XLA's default compile
    options: with :data:`COMPILER_OPTIONS` it compiles faster but steps 4-10% slower."""
    return jax.jit(lambda state, obs: filter_step(params, state, obs))
