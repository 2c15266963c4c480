"""Training of the learned observation (issue 49): optax over our own renders under randomised
light, equinox's CNN example as the pattern (``make_step(model, opt_state, batch)``, one
``eqx.filter_jit``), data a pure function of a key.

The loss is the per-pixel cross-entropy, each class weighted by ``1 / sqrt(its pixel share)``
over the data set (the background fills most of a crop; a hand a few hundred pixels), so that
skin and small patches count. Every step draws ``batch`` geometry samples and new light for
each (:func:`jaxmocap.observe.scenes.shade`): no two steps see the same image.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, PRNGKeyArray

from .model import Observer
from .scenes import Geometry, shade

LEARNING_RATE = 3e-3  # AdamW, cosine-decayed to 5% over the run (a common start; not tuned)
BATCH = 6
WEIGHT_DECAY = 1e-4


class TrainConfig(NamedTuple):
    steps: int = 1500
    batch: int = BATCH
    learning_rate: float = LEARNING_RATE
    seed: int = 0


def class_weights(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """``1 / sqrt(share)`` per class, normalised to a pixel-weighted mean of 1 (absent classes
    get the largest weight of the present ones)."""
    count = np.bincount(labels.reshape(-1).astype(np.int64), minlength=n_classes)[:n_classes]
    share = count / max(count.sum(), 1)
    w = np.where(count > 0, 1 / np.sqrt(np.maximum(share, 1e-12)), 0)
    w = np.where(count > 0, w, w.max() if w.max() > 0 else 1.0)
    return (w / max(np.sum(w * share), 1e-12)).astype(np.float32)


def optimiser(config: TrainConfig) -> optax.GradientTransformation:
    sched = optax.cosine_decay_schedule(config.learning_rate, max(config.steps, 1), alpha=0.05)
    return optax.adamw(sched, weight_decay=WEIGHT_DECAY)


def loss_fn(model: Observer, images: Array, labels: Array, weights: Array) -> Array:
    """Class-weighted mean cross-entropy of a batch (images (b, n, n, 3), labels (b, n, n))."""
    logp = jax.nn.log_softmax(jax.vmap(model)(images), -1)
    nll = -jnp.take_along_axis(logp, labels[..., None], -1)[..., 0]
    w = weights[labels]
    return jnp.sum(w * nll) / jnp.sum(w)


def draw_batch(key: PRNGKeyArray, geometry: Geometry, palette: Array, batch: int):
    """``batch`` samples of the geometry, each under new light: (images, labels)."""
    k1, k2 = jax.random.split(key)
    idx = jax.random.randint(k1, (batch,), 0, geometry.label.shape[0])
    g = jax.tree.map(lambda a: a[idx], geometry)
    return jax.vmap(shade, in_axes=(0, 0, None))(jax.random.split(k2, batch), g, palette)


def make_step(optim: optax.GradientTransformation, batch: int):
    """The jitted training step ``(model, opt_state, key, geometry, palette, weights) ->
    (model, opt_state, loss)``."""

    @eqx.filter_jit
    def step(model, opt_state, key, geometry, palette, weights):
        images, labels = draw_batch(key, geometry, palette, batch)
        loss, grads = eqx.filter_value_and_grad(loss_fn)(model, images, labels, weights)
        updates, opt_state = optim.update(grads, opt_state, eqx.filter(model, eqx.is_array))
        return eqx.apply_updates(model, updates), opt_state, loss

    return step


def train(model: Observer, geometry: Geometry, palette: Array, config: TrainConfig,
          start: int = 0, opt_state=None, on_step=None, stop=None):
    """Train ``model`` from step ``start`` to ``config.steps``; returns ``(model, opt_state,
    losses)``. ``on_step(step, loss, model, opt_state)`` is called after every step (progress,
    checkpoints); ``stop()`` returning True ends early (a time budget). The key of step ``i`` is
    ``fold_in(seed, i)``, so a resumed run draws the same batches as an uninterrupted one."""
    optim = optimiser(config)
    if opt_state is None:
        opt_state = optim.init(eqx.filter(model, eqx.is_array))
    weights = jnp.asarray(class_weights(np.asarray(geometry.label), model.n_classes))
    geometry = jax.tree.map(jnp.asarray, geometry)
    step = make_step(optim, config.batch)
    base = jax.random.key(config.seed)
    losses = []
    for i in range(start, config.steps):
        model, opt_state, loss = step(model, opt_state, jax.random.fold_in(base, i), geometry,
                                      palette, weights)
        losses.append(float(loss))
        if on_step is not None:
            on_step(i, losses[-1], model, opt_state)
        if stop is not None and stop():
            break
    return model, opt_state, losses
