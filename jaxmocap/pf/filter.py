"""A generic particle filter (Condensation) and Deutscher's annealed variant, in JAX.

Azad et al. §II: the posterior over configurations s (n DOF) is a particle set
S = {(s_1, pi_1), ..., (s_N, pi_N)}; each frame the filter

1. **resamples**: N particles "picked proportional to their probability" (systematic by
   default, multinomial for comparison; see :mod:`jaxmocap.pf.resample`);
2. **predicts** with "a first-order linear motion model together with adaptive Gaussian noise":

       s_t = s_{t-1} + delta (s_{t-1} - s_{t-2}) + sigma_t * eps,   eps ~ N(0, I),

   each particle carrying its own previous state s_{t-2} (its velocity); ``delta`` is the
   damping (0: random walk, 1: constant velocity). The result is kept inside the joint-limit
   box [lower, upper] by clipping or by one reflection at the violated bound (then clipping);
3. **weights** each particle with the user's likelihood, vmapped over particles:
   log pi_i = loglik(s_i, z) (+ the carried log-weight when it did not resample); the
   log-evidence increment log p^(z_t | z_{1:t-1}) = log sum_i pi^prior_i p(z_t | s_i) is
   reported beside the estimate (``PFEstimate.log_evidence``);
4. **estimates** the weighted mean sum_i pi_i s_i and the best particle argmax_i pi_i;
5. **adapts the noise**: "whose amount is decreased or increased depending on the current
   errors". We take the current error to be e_t = -max_i loglik(s_i, z), the energy of the
   best particle (Azad's cues are exp(-E/2) with E >= 0, so e_t = E_best / 2 >= 0 and
   e_t = 0 is a perfect fit), and set per dimension

       sigma_{t+1} = sigma_min + (sigma_max - sigma_min) * (1 - exp(-max(e_t, 0) / e_0)),

   which rises monotonically from sigma_min (perfect fit) to sigma_max (lost track); e_0 is
   ``error_scale``. sigma_min == sigma_max gives a fixed noise. A degenerate frame (every
   likelihood -inf or NaN) counts as e_t = inf: sigma goes to sigma_max, weights are reset to
   uniform and the estimate is flagged ``degenerate``.

:func:`anneal_step` is the annealed particle filter of Deutscher, Blake & Reid (CVPR 2000),
used for automatic initialisation: within one frame, layers m = 1..M weight with
pi ∝ p(z|s)^beta_m (beta increasing to 1), resample, and diffuse with a noise proportional to
the particle spread (alpha * weighted std per dimension, clamped to [sigma_min, sigma_max]).

Everything is pure and jit-compiled: ``init`` / ``step`` / ``anneal_step`` / ``run``
(``run`` = ``lax.scan`` of ``step`` over a sequence). Results are deterministic given the key.

**Gradients through the recursion** (``PFParams.resampling_gradient``): the resampling indices
are discrete, so by default (``"stop"``) every resampling gives its picked particles the
log-weight ``-log N + log pi_a - stop_gradient(log pi_a)`` (Scibior & Wood 2021,
:func:`jaxmocap.pf.resample.stop_gradient_correction`): the same numbers as before in the
forward pass, bit for bit (tested against ``"none"``), while ``jax.grad`` of anything computed
from later weights (the estimate, the log-evidence) now sees how the parameters changed the
weights of the particles' ancestors -- the Fisher-identity score estimate, consistent as N
grows (tested against the Kalman filter's exact gradient on a linear-Gaussian model).
``"none"``: the weights after a resampling are the constant ``-log N`` and a gradient only sees
the current frame's weights and the particles' paths (biased; kept for comparison). The
annealing layers carry the same correction from layer to layer (their forward pass is also
unchanged). Gradients also flow pathwise through the particles (the motion model's noise scale,
a proposal's moves), as in any reparameterised sampler.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray, PyTree

from jaxmocap.pf import resample as _resample
from jaxmocap.pf.smooth import Lineage

__all__ = [
    "ANNEAL_ALPHA",
    "DAMPING",
    "ERROR_SCALE",
    "RESAMPLE_THRESHOLD",
    "PFEstimate",
    "PFParams",
    "PFState",
    "anneal_step",
    "anneal_step_lineage",
    "init",
    "init_uniform",
    "run",
    "run_lineage",
    "step",
    "step_lineage",
]

# Defaults. Azad et al. name the ingredients (first-order motion, adaptive noise) but give no
# values; these are ours, documented as such.
DAMPING = 0.5  # delta of the first-order linear motion model (0 = random walk)
ERROR_SCALE = 1.0  # e_0: best-particle energy at which the noise is 63% of the way to max
RESAMPLE_THRESHOLD = 1.0  # resample when ESS < threshold * N; 1.0 = every frame (Condensation)
ANNEAL_ALPHA = 0.5  # Deutscher et al.: layer noise = alpha * particle spread

_RESAMPLERS = {
    "systematic": _resample.systematic_from_uniforms,
    "multinomial": _resample.multinomial_from_uniforms,
}
_BOUNDARIES = ("clip", "reflect")
_RESAMPLING_GRADIENTS = ("stop", "none")

LogLik = Callable[[Float[Array, " d"], Any], Float[Array, ""]]
Proposal = Callable[[Float[Array, "n d"], Any, PRNGKeyArray], Float[Array, "n d"]]


def _as_array(x: ArrayLike) -> Array:
    return jnp.asarray(x)


class PFParams(eqx.Module):
    """What stays fixed over a sequence: the likelihood, the box, the noise range, the model.

    ``loglik(s, z) -> scalar`` is the log-likelihood of one configuration s (d,) given the
    observation pytree z; the filter vmaps it over particles. It may be a plain function or an
    ``eqx.Module`` with array fields (then those are traced, e.g. for tuning).
    Arrays of shape (d,): ``lower``/``upper`` (joint limits; +-inf allowed for ``clip``),
    ``sigma_min``/``sigma_max`` (noise std range, state units). Scalars (traced, no recompile
    when changed): ``damping`` delta, ``error_scale`` e_0, ``resample_threshold``.
    ``proposal(x (N, d), z, key) -> x'`` (optional, default None = Azad's plain prediction):
    moves the predicted particles before they are weighed (e.g. toward measurements,
    :class:`jaxmocap.pf.guided.GuidedProposal`); the box is re-applied after it and the
    weights are not corrected for it. ``resampling_gradient`` (static): ``"stop"`` (default)
    or ``"none"``, how a gradient crosses a resampling (module docstring; the forward pass is
    the same).
    """

    loglik: LogLik
    lower: Float[Array, " d"] = eqx.field(converter=_as_array)
    upper: Float[Array, " d"] = eqx.field(converter=_as_array)
    sigma_min: Float[Array, " d"] = eqx.field(converter=_as_array)
    sigma_max: Float[Array, " d"] = eqx.field(converter=_as_array)
    damping: Float[Array, ""] = eqx.field(converter=_as_array, default=DAMPING)
    error_scale: Float[Array, ""] = eqx.field(converter=_as_array, default=ERROR_SCALE)
    resample_threshold: Float[Array, ""] = eqx.field(
        converter=_as_array, default=RESAMPLE_THRESHOLD
    )
    resampling: str = eqx.field(static=True, default="systematic")
    boundary: str = eqx.field(static=True, default="clip")
    proposal: Proposal | None = None
    resampling_gradient: str = eqx.field(static=True, default="stop")

    def __check_init__(self):
        if not callable(self.loglik):
            raise ValueError(f"PFParams.loglik: expected a callable, got {type(self.loglik)}")
        if self.proposal is not None and not callable(self.proposal):
            raise ValueError(
                f"PFParams.proposal: expected a callable or None, got {type(self.proposal)}"
            )
        if self.resampling not in _RESAMPLERS:
            raise ValueError(
                f"PFParams.resampling: expected one of {sorted(_RESAMPLERS)}, "
                f"got {self.resampling!r}"
            )
        if self.resampling_gradient not in _RESAMPLING_GRADIENTS:
            raise ValueError(
                f"PFParams.resampling_gradient: expected one of {_RESAMPLING_GRADIENTS}, "
                f"got {self.resampling_gradient!r}"
            )
        if self.boundary not in _BOUNDARIES:
            raise ValueError(
                f"PFParams.boundary: expected one of {_BOUNDARIES}, got {self.boundary!r}"
            )
        d = self.lower.shape
        for name in ("upper", "sigma_min", "sigma_max"):
            if getattr(self, name).shape != d:
                raise ValueError(
                    f"PFParams.{name}: expected shape {d} (as lower), "
                    f"got {getattr(self, name).shape}"
                )


class PFState(eqx.Module):
    """The particle set carried from frame to frame.

    particles: s_{t-1}^i (N, d); previous: s_{t-2}^i (N, d), the motion model's memory;
    log_weights: normalised log pi_i (N,); sigma: current adaptive noise std (d,).
    """

    particles: Float[Array, "n d"]
    previous: Float[Array, "n d"]
    log_weights: Float[Array, " n"]
    sigma: Float[Array, " d"]


class PFEstimate(eqx.Module):
    """Per-frame output: weighted mean and variance, best particle, diagnostics."""

    mean: Float[Array, " d"]  # sum_i pi_i s_i
    var: Float[Array, " d"]  # sum_i pi_i (s_i - mean)^2
    best: Float[Array, " d"]  # the particle with the largest likelihood
    best_loglik: Float[Array, ""]
    ess: Float[Array, ""]  # effective sample size 1 / sum pi_i^2 after weighting
    degenerate: Bool[Array, ""]  # no particle had a finite likelihood: weights reset
    # log p^(z_t | z_{1:t-1}) = logsumexp_i(log pi^prior_i + loglik_i) (-inf when degenerate);
    # summed over frames, the filter's log-marginal-likelihood estimate. In an annealing step
    # it is the last layer's normaliser (of its tempered weights), not an evidence estimate.
    log_evidence: Float[Array, ""]


def _constrain(x: Float[Array, "n d"], params: PFParams) -> Float[Array, "n d"]:
    lo, hi = params.lower.astype(x.dtype)[None, :], params.upper.astype(x.dtype)[None, :]
    if params.boundary == "reflect":
        x = jnp.where(x < lo, 2 * lo - x, x)
        x = jnp.where(x > hi, 2 * hi - x, x)
    return jnp.clip(x, lo, hi)


def _weigh(params: PFParams, x: Float[Array, "n d"], observation: PyTree):
    ll = jax.vmap(params.loglik, in_axes=(0, None))(x, observation)
    return jnp.where(jnp.isnan(ll), -jnp.inf, ll.astype(x.dtype))


def _adapt_sigma(params: PFParams, best_ll: Float[Array, ""], dtype) -> Float[Array, " d"]:
    error = jnp.maximum(jnp.where(jnp.isfinite(best_ll), -best_ll, jnp.inf), 0.0)
    frac = -jnp.expm1(-error / params.error_scale.astype(dtype))
    lo, hi = params.sigma_min.astype(dtype), params.sigma_max.astype(dtype)
    return lo + (hi - lo) * frac


def _draws(key: PRNGKeyArray, n: int, d: int, dtype) -> tuple[Array, Array]:
    """N uniforms in [0, 1) for resampling and (N, d) standard normals, from ONE threefry call.

    The normals are sqrt(2) erfinv(v), v ~ U(-1, 1), exactly how ``jax.random.normal`` makes
    them; drawing everything at once keeps the compiled step small (threefry is the largest
    part of the program and of its compile time on CPU).
    """
    lo = jnp.nextafter(jnp.asarray(-1.0, dtype), jnp.asarray(0.0, dtype))
    v = jax.random.uniform(key, (n * (d + 1),), dtype, minval=lo, maxval=1.0)
    u = jnp.clip((v[:n] + 1.0) / 2.0, 0.0, 1.0 - jnp.finfo(dtype).epsneg)
    eps = jnp.sqrt(jnp.asarray(2.0, dtype)) * jax.scipy.special.erfinv(v[n:])
    return u, eps.reshape(n, d)


def _resample_pairs(params, u, log_weights, x, xp):
    """Resampled (x, xp), the indices and the log-weight correction the picked particles carry
    (zero in value; :func:`jaxmocap.pf.resample.stop_gradient_correction`, or constant zeros
    with ``resampling_gradient="none"``)."""
    idx = _RESAMPLERS[params.resampling](log_weights, u)
    if params.resampling_gradient == "stop":
        corr = _resample.stop_gradient_correction(log_weights, idx)
    else:
        corr = jnp.zeros(idx.shape, log_weights.dtype)
    return x[idx], xp[idx], idx, corr


def _predict(params: PFParams, state: PFState, key: PRNGKeyArray):
    """Resample (when ESS < threshold N), then first-order motion + noise, then the box.
    Returns (predicted, their previous, prior log-weights, parents, the resampling's
    log-weight correction: zeros where the frame did not resample)."""
    n, d = state.particles.shape
    dtype = state.particles.dtype
    u, eps = _draws(key, n, d, dtype)
    ess = 1.0 / jnp.sum(jnp.exp(2.0 * state.log_weights))  # log_weights are normalised
    do_res = ess < params.resample_threshold * n
    xr, xpr, idx, corr = _resample_pairs(
        params, u, state.log_weights, state.particles, state.previous
    )
    x = jnp.where(do_res, xr, state.particles)
    xp = jnp.where(do_res, xpr, state.previous)
    corr = jnp.where(do_res, corr, jnp.zeros_like(corr))
    prior_lw = jnp.where(
        do_res, jnp.full_like(state.log_weights, -jnp.log(n)) + corr, state.log_weights
    )
    parent = jnp.where(do_res, idx, jnp.arange(n, dtype=idx.dtype))
    x_new = x + params.damping.astype(dtype) * (x - xp) + state.sigma[None, :] * eps
    return _constrain(x_new, params), x, prior_lw, parent, corr


def _propose(params: PFParams, x, observation, key):
    """The optional proposal move after the prediction (then the box again)."""
    if params.proposal is None:
        return x
    return _constrain(params.proposal(x, observation, key), params)


def _split_proposal_key(params: PFParams, key: PRNGKeyArray):
    """(key for the prediction, key for the proposal); without a proposal the prediction keeps
    the whole key, so Azad's filter draws exactly the same numbers with or without the hook."""
    if params.proposal is None:
        return key, key
    k_pred, k_prop = jax.random.split(key)
    return k_pred, k_prop


def _finish(params, x_new, x_prev, lw, ll, degenerate, log_evidence
            ) -> tuple[PFState, PFEstimate]:
    w = jnp.exp(lw)
    mean = w @ x_new
    var = w @ jnp.square(x_new - mean[None, :])
    ib = jnp.argmax(ll)
    best_ll = ll[ib]
    est = PFEstimate(
        mean=mean,
        var=var,
        best=x_new[ib],
        best_loglik=best_ll,
        ess=1.0 / jnp.sum(jnp.square(w)),
        degenerate=degenerate,
        log_evidence=log_evidence,
    )
    sigma = _adapt_sigma(params, best_ll, x_new.dtype)
    return PFState(particles=x_new, previous=x_prev, log_weights=lw, sigma=sigma), est


@eqx.filter_jit
def init(
    key: PRNGKeyArray,
    params: PFParams,
    mean: Float[Array, " d"],
    std: Float[ArrayLike, "..."],
    n_particles: int,
) -> PFState:
    """N particles s^i ~ N(mean, diag(std^2)) inside the box, at rest (previous = particles).

    The dtype of ``mean`` is the filter's dtype. The noise starts at ``sigma_max``.
    """
    d = mean.shape[0]
    std = jnp.broadcast_to(jnp.asarray(std, mean.dtype), (d,))
    x = mean[None, :] + std[None, :] * jax.random.normal(key, (n_particles, d), mean.dtype)
    x = _constrain(x, params)
    return PFState(
        particles=x,
        previous=x,
        log_weights=jnp.full((n_particles,), -jnp.log(n_particles), mean.dtype),
        sigma=params.sigma_max.astype(mean.dtype),
    )


@eqx.filter_jit
def init_uniform(
    key: PRNGKeyArray, params: PFParams, n_particles: int, dtype: Any = None
) -> PFState:
    """N particles uniform in the box [lower, upper] (which must be finite), at rest.

    The starting set of automatic initialisation (then :func:`anneal_step` on the first frames).
    """
    dtype = dtype or jnp.result_type(float)
    lo, hi = params.lower.astype(dtype), params.upper.astype(dtype)
    lo = eqx.error_if(
        lo,
        ~jnp.all(jnp.isfinite(lo) & jnp.isfinite(hi)),
        "init_uniform: PFParams.lower/upper must be finite",
    )
    u = jax.random.uniform(key, (n_particles, lo.shape[0]), dtype)
    x = lo[None, :] + (hi - lo)[None, :] * u
    return PFState(
        particles=x,
        previous=x,
        log_weights=jnp.full((n_particles,), -jnp.log(n_particles), dtype),
        sigma=params.sigma_max.astype(dtype),
    )


def _step(params, state, observation, key):
    k_pred, k_prop = _split_proposal_key(params, key)
    x_new, x_prev, prior_lw, parent, _ = _predict(params, state, k_pred)
    x_new = _propose(params, x_new, observation, k_prop)
    ll = _weigh(params, x_new, observation)
    lw, degenerate = _resample.normalize_log_weights(prior_lw + ll)
    log_evidence = jax.nn.logsumexp(prior_lw + ll)
    return (*_finish(params, x_new, x_prev, lw, ll, degenerate, log_evidence), parent)


@eqx.filter_jit
def step(
    params: PFParams, state: PFState, observation: PyTree, key: PRNGKeyArray
) -> tuple[PFState, PFEstimate]:
    """One Condensation frame: resample, predict (motion + adaptive noise), [propose,] weigh,
    estimate."""
    new_state, est, _ = _step(params, state, observation, key)
    return new_state, est


@eqx.filter_jit
def step_lineage(
    params: PFParams, state: PFState, observation: PyTree, key: PRNGKeyArray
) -> tuple[PFState, PFEstimate, Int[Array, " n"]]:
    """:func:`step` that also returns each new particle's parent: ``parent[i]`` is the index
    in ``state.particles`` of the particle that particle i of the new set was predicted from
    (the identity when the frame did not resample). Same numbers as :func:`step`."""
    return _step(params, state, observation, key)


def _anneal(params, state, observation, key, betas, alpha):
    k_pred, k_layers = jax.random.split(key)
    k_pred, k_prop = _split_proposal_key(params, k_pred)
    x, x_prev, _, parent, corr = _predict(params, state, k_pred)
    x = _propose(params, x, observation, k_prop)
    dtype = x.dtype
    n, d = x.shape
    betas = betas.astype(dtype)
    alpha = jnp.asarray(alpha, dtype)

    def layer(carry, inputs):
        x, xp, parent, degen, corr = carry
        beta, k = inputs
        u, eps = _draws(k, n, d, dtype)
        ll = _weigh(params, x, observation)
        lw, deg = _resample.normalize_log_weights(corr + beta * ll)
        w = jnp.exp(lw)
        mean = w @ x
        spread = jnp.sqrt(w @ jnp.square(x - mean[None, :]))
        sigma = jnp.clip(
            alpha * spread, params.sigma_min.astype(dtype), params.sigma_max.astype(dtype)
        )
        x, xp, idx, corr = _resample_pairs(params, u, lw, x, xp)
        x = _constrain(x + sigma[None, :] * eps, params)
        return (x, xp, parent[idx], degen | deg, corr), None

    keys = jax.random.split(k_layers, betas.shape[0] - 1)
    (x, x_prev, parent, degen, corr), _ = jax.lax.scan(
        layer, (x, x_prev, parent, jnp.array(False), corr), (betas[:-1], keys)
    )
    ll = _weigh(params, x, observation)
    lw, deg = _resample.normalize_log_weights(corr + betas[-1] * ll)
    log_evidence = jax.nn.logsumexp(corr + betas[-1] * ll) - jnp.log(n)
    return (*_finish(params, x, x_prev, lw, ll, degen | deg, log_evidence), parent)


@eqx.filter_jit
def anneal_step(
    params: PFParams,
    state: PFState,
    observation: PyTree,
    key: PRNGKeyArray,
    betas: Float[Array, " m"],
    alpha: Float[ArrayLike, ""] = ANNEAL_ALPHA,
) -> tuple[PFState, PFEstimate]:
    """One frame of the annealed particle filter (Deutscher et al. 2000), M = len(betas) layers.

    Predict (and propose) as :func:`step`; then for m = 1..M-1: weigh with beta_m * loglik,
    resample, diffuse with sigma_m = clip(alpha * weighted std, sigma_min, sigma_max) and
    re-apply the box; the last layer weighs with beta_M (normally 1) and gives the estimate.
    ``degenerate`` is True if any layer degenerated.
    """
    new_state, est, _ = _anneal(params, state, observation, key, betas, alpha)
    return new_state, est


@eqx.filter_jit
def anneal_step_lineage(
    params: PFParams,
    state: PFState,
    observation: PyTree,
    key: PRNGKeyArray,
    betas: Float[Array, " m"],
    alpha: Float[ArrayLike, ""] = ANNEAL_ALPHA,
) -> tuple[PFState, PFEstimate, Int[Array, " n"]]:
    """:func:`anneal_step` that also returns each final particle's parent in
    ``state.particles`` (composed through the layers' resamplings; see :func:`step_lineage`)."""
    return _anneal(params, state, observation, key, betas, alpha)


@eqx.filter_jit
def run(
    params: PFParams, state: PFState, observations: PyTree, key: PRNGKeyArray
) -> tuple[PFState, PFEstimate]:
    """Filter a whole sequence with ``lax.scan``: observations carry a leading time axis T.

    Returns the final state and the per-frame estimates stacked along a leading axis T.
    Frame t uses key ``jax.random.split(key, T)[t]``, so ``run`` equals a Python loop of
    :func:`step` with those keys.
    """
    t = jax.tree_util.tree_leaves(observations)[0].shape[0]
    keys = jax.random.split(key, t)

    def body(s, inputs):
        obs, k = inputs
        return step(params, s, obs, k)

    return jax.lax.scan(body, state, (observations, keys))


@eqx.filter_jit
def run_lineage(
    params: PFParams, state: PFState, observations: PyTree, key: PRNGKeyArray
) -> tuple[PFState, PFEstimate, Lineage]:
    """:func:`run` (same keys, same numbers) that also returns the per-frame particle sets and
    their parents, for :func:`jaxmocap.pf.smooth.fixed_lag_smooth`."""
    t = jax.tree_util.tree_leaves(observations)[0].shape[0]
    keys = jax.random.split(key, t)

    def body(s, inputs):
        obs, k = inputs
        new, est, parent = _step(params, s, obs, k)
        return new, (est, Lineage(new.particles, new.log_weights, parent))

    final, (est, lineage) = jax.lax.scan(body, state, (observations, keys))
    return final, est, lineage
