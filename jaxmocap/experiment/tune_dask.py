"""IK-covariance tuning (:mod:`jaxmocap.tune`) over many clips with each clip's gradient
computed on a Dask worker and the results summed.

The loss over clips is ``sum_c total_c / sum_c n_c`` (:func:`jaxmocap.tune.ik_loss_parts`:
per clip the summed frame errors and the number of valid frames, which does not depend on the
covariances); its gradient is ``sum_c grad total_c / sum_c n_c``. Each clip's observations
are sent to the cluster once (``scatter``); every evaluation sends only the parameters
(a few hundred numbers) and brings back one value, one count and one gradient per clip.
:func:`clip_value_and_grad` is the same computation in this process, clip after clip, and
``jax.value_and_grad(jaxmocap.tune.ik_loss)`` on all windows stacked the vmapped one
(docs/results/experiments.md compares the three).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap import tune

_PARTS_VG = eqx.filter_jit(jax.value_and_grad(tune.ik_loss_parts, has_aux=True))


def _combine(parts: list) -> tuple[float, tune.IKTheta]:
    total = sum(float(t) for (t, _), _ in parts)
    n = max(sum(float(k) for (_, k), _ in parts), 1.0)
    grads = [g for _, g in parts]
    grad = jax.tree.map(lambda *a: sum(np.asarray(x, np.float64) for x in a) / n, *grads)
    return total / n, grad


def clip_parts(theta, setup: tune.IKSetup, obs: tune.IKObservations, jitter_weight: float,
               x64: bool):
    """``((total, n), grad total)`` of one clip, as numpy (runs on a worker)."""
    if bool(jax.config.jax_enable_x64) != x64:
        jax.config.update("jax_enable_x64", x64)
    (total, n), g = _PARTS_VG(theta, setup, obs, jitter_weight)
    return jax.device_get(((total, n), g))


def _per_clip(setup, clips) -> list:
    """One setup per clip: ``setup`` shared, or a sequence of them (clips of different
    bodies, cameras or shirts)."""
    setups = list(setup) if isinstance(setup, (list, tuple)) else [setup] * len(clips)
    if len(setups) != len(clips):
        raise tune.TuneError(f"{len(setups)} setups for {len(clips)} clips")
    return setups


def clip_value_and_grad(setup: tune.IKSetup | Sequence[tune.IKSetup],
                        clips: Sequence[tune.IKObservations],
                        jitter_weight: float = 0.0) -> Callable:
    """``theta -> (loss, grad)`` over ``clips``, clip after clip in this process; ``setup``
    shared by the clips or one per clip."""
    x64 = bool(jax.config.jax_enable_x64)
    setups = _per_clip(setup, clips)

    def vg(theta):
        return _combine([clip_parts(theta, s, o, jitter_weight, x64)
                         for s, o in zip(setups, clips, strict=True)])

    return vg


def clip_loss(setup: tune.IKSetup | Sequence[tune.IKSetup],
              clips: Sequence[tune.IKObservations], jitter_weight: float = 0.0) -> Callable:
    """The scalar ``theta -> loss`` over ``clips`` as one traceable function (what an
    optimiser with a linesearch, L-BFGS, evaluates inside its jitted update): ``sum_c total_c
    / sum_c n_c``, the counts computed once (they do not depend on theta)."""
    setups = _per_clip(setup, clips)
    n = max(sum(_frames(o) for o in clips), 1.0)

    def loss(theta):
        return sum(tune.ik_loss_parts(theta, s, o, jitter_weight)[0]
                   for s, o in zip(setups, clips, strict=True)) / n

    return loss


def _frames(obs: tune.IKObservations) -> float:
    """Valid frames of ``obs`` (>= MIN_VALID_PATCHES measured centroids): the count of
    :func:`jaxmocap.tune.ik_loss_parts`."""
    from jaxmocap.trackers.shirt import MIN_VALID_PATCHES

    per_frame = np.asarray(obs.visible).sum(axis=(2, 3))
    ok = per_frame >= MIN_VALID_PATCHES
    if obs.scored is not None:
        ok &= np.asarray(obs.scored, bool)
    return float(ok.sum())


def dask_value_and_grad(client, setup: tune.IKSetup | Sequence[tune.IKSetup],
                        clips: Sequence[tune.IKObservations],
                        jitter_weight: float = 0.0) -> Callable:
    """``theta -> (loss, grad)`` over ``clips`` with one task per clip on ``client``'s
    workers (module docstring); for :func:`jaxmocap.tune.fit` ``value_and_grad=True``;
    ``setup`` shared by the clips or one per clip."""
    x64 = bool(jax.config.jax_enable_x64)
    host = lambda tree: jax.tree.map(np.asarray, tree)  # numpy: no device arrays on the wire
    setups = _per_clip(setup, clips)
    if all(s is setups[0] for s in setups):
        setup_f = [client.scatter(host(setups[0]), broadcast=True)] * len(clips)
    else:
        setup_f = [client.scatter(host(s)) for s in setups]
    clip_f = [client.scatter(host(o)) for o in clips]

    def vg(theta):
        th = host(theta)
        futures = [client.submit(_worker_parts, th, sf, f, jitter_weight, x64, pure=False)
                   for sf, f in zip(setup_f, clip_f, strict=True)]
        return _combine(client.gather(futures))

    return vg


def _worker_parts(theta, setup, obs, jitter_weight, x64):
    if bool(jax.config.jax_enable_x64) != x64:
        jax.config.update("jax_enable_x64", x64)
    to_jax = lambda tree: jax.tree.map(lambda a: jnp.asarray(a) if isinstance(a, np.ndarray)
                                       else a, tree)
    return clip_parts(to_jax(theta), to_jax(setup), to_jax(obs), jitter_weight, x64)
