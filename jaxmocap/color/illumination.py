"""Reference illuminations: recovering from abrupt lighting changes (Wang et al. 2011, §5.2).

The tracker keeps a set of white-balance matrices seen so far. When fewer than 40% of the
foreground pixels are classified with the current ``W`` (a lamp switched off), the frame is
re-classified with every stored matrix and the one that classifies the most pixels wins
(step 1). After the frame, the refined ``W*`` joins the set if ``min_W ||W* - W||_F > 0.5``
(step 5).

The set is a fixed-capacity buffer (static ``capacity``, a traced ``count``) so that adding a
matrix never changes shapes or recompiles. When the buffer is full the oldest entry is
overwritten (ring buffer; not in the paper, which keeps an unbounded list).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from .classify import THRESHOLD, classified_fraction
from .classify import classify as _classify
from .model import ColorModel

MIN_CLASSIFIED_FRACTION = 0.4  # Wang §5.2 step 1: "less than 40% of the foreground pixels"
MIN_FROBENIUS_DISTANCE = 0.5  # Wang §5.2 step 5: add W* if min ||W* - W||_F > 0.5
CAPACITY = 16  # buffer size (static); not in the paper


class ReferenceIlluminations(eqx.Module):
    """Buffer of white-balance matrices: slots ``[0, min(count, capacity))`` are valid."""

    W: Float[Array, "capacity 3 3"]
    count: Int[Array, ""]

    @property
    def capacity(self) -> int:
        return self.W.shape[0]

    @property
    def valid(self) -> Bool[Array, " capacity"]:
        return jnp.arange(self.capacity) < self.count


def init_references(W0: Float[Array, "3 3"], capacity: int = CAPACITY) -> ReferenceIlluminations:
    """A buffer holding only ``W0`` (the user-labelled initial white balance, §5.1)."""
    if capacity < 1:
        raise ValueError(f"init_references: capacity must be >= 1, got {capacity}")
    W = jnp.broadcast_to(W0, (capacity, 3, 3)) * (jnp.arange(capacity) == 0)[:, None, None]
    return ReferenceIlluminations(W=W, count=jnp.array(1, jnp.int32))


def maybe_add_reference(
    refs: ReferenceIlluminations,
    W_star: Float[Array, "3 3"],
    min_distance: float | Float[Array, ""] = MIN_FROBENIUS_DISTANCE,
) -> tuple[ReferenceIlluminations, Bool[Array, ""]]:
    """Add ``W*`` if its Frobenius distance to every stored matrix exceeds ``min_distance``."""
    dist = jnp.sqrt(jnp.sum((refs.W - W_star[None]) ** 2, axis=(1, 2)))
    nearest = jnp.min(jnp.where(refs.valid, dist, jnp.inf))
    add = nearest > min_distance
    slot = refs.count % refs.capacity
    W = jnp.where(add & (jnp.arange(refs.capacity) == slot)[:, None, None], W_star[None], refs.W)
    return ReferenceIlluminations(W=W, count=refs.count + add.astype(refs.count.dtype)), add


class ReferenceClassification(eqx.Module):
    """Output of :func:`classify_with_references`."""

    ids: Int[Array, "h w"]
    distance: Float[Array, "h w"]
    W: Float[Array, "3 3"]  # the matrix used (current W, or the best reference)
    fraction: Float[Array, ""]  # classified fraction of foreground pixels with that matrix
    used_reference: Bool[Array, ""]


def classify_with_references(
    model: ColorModel,
    refs: ReferenceIlluminations,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    threshold: float | Float[Array, ""] = THRESHOLD,
    min_fraction: float | Float[Array, ""] = MIN_CLASSIFIED_FRACTION,
    gain: tuple[float, float] | None = None,
    background: ColorModel | None = None,
) -> ReferenceClassification:
    """Classify with ``W``; below ``min_fraction`` classified, use the best stored reference.

    Pure jit code: the fallback is a ``lax.cond`` (only evaluated when needed on CPU; a select
    under vmap) whose branch classifies with every stored matrix (``vmap`` over the buffer),
    keeps the one with the most classified pixels, and uses it only if it beats ``W``.
    ``gain`` / ``background``: :func:`jaxmocap.color.classify`'s options.
    """

    classify = _classifier(model, image, mask, threshold, gain, background)
    first = _first(classify, W, mask)
    fallback = lambda: _with_best_reference(classify, refs, first, mask)  # noqa: E731
    return jax.lax.cond(first.fraction < min_fraction, fallback, lambda: first)


def _classifier(model, image, mask, threshold, gain, background):
    """``W -> (ids, distance)`` of ``image`` (:func:`jaxmocap.color.classify`)."""
    return lambda W: _classify(model, W, image, mask, threshold, gain, background)


def _first(classify, W, mask) -> ReferenceClassification:
    """The classification with the current ``W`` (no reference used)."""
    ids, dist = classify(W)
    return ReferenceClassification(ids, dist, W, classified_fraction(ids, mask), jnp.array(False))


def _with_best_reference(classify, refs: ReferenceIlluminations, first: ReferenceClassification,
                         mask) -> ReferenceClassification:  # fmt: skip
    """The fallback of :func:`classify_with_references`: classify with every stored matrix
    (``vmap`` over the buffer), keep the one with the most classified pixels, and use it only
    if it beats ``first`` (the classification with the current ``W``)."""
    W = first.W
    counts = jax.vmap(lambda Wr: jnp.sum(classify(Wr)[0] > 0))(refs.W.astype(W.dtype))
    counts = jnp.where(refs.valid, counts, -1)
    best = jnp.argmax(counts)
    better = counts[best] > jnp.sum(first.ids > 0)
    W_best = jnp.where(better, refs.W[best].astype(W.dtype), W)
    ids_b, dist_b = classify(W_best)
    return ReferenceClassification(ids_b, dist_b, W_best, classified_fraction(ids_b, mask), better)


def classify_views_with_references(
    model: ColorModel,
    refs: ReferenceIlluminations,
    W: Float[Array, "n 3 3"],
    images: UInt8[Array, "n h w 3"] | Float[Array, "n h w 3"],
    masks: Bool[Array, "n h w"] | None = None,
    threshold: float | Float[Array, ""] = THRESHOLD,
    min_fraction: float | Float[Array, ""] = MIN_CLASSIFIED_FRACTION,
    gain: tuple[float, float] | None = None,
    background: ColorModel | None = None,
) -> ReferenceClassification:
    """:func:`classify_with_references` for ``n`` views at once (each with its own ``refs``,
    stacked, its ``W`` and image), outputs stacked. The views are classified under one
    ``vmap``; the fallback runs, for every view (a view that does not need it keeps its first
    classification), under one ``lax.cond`` taken when some view classified less than
    ``min_fraction``: ``vmap`` of :func:`classify_with_references` would turn that ``cond``
    into a select and run the fallback (a classification per stored matrix) every time."""

    def first_of(W, image, mask):
        return _first(_classifier(model, image, mask, threshold, gain, background), W, mask)

    def fallback_of(refs, first, image, mask):
        classify = _classifier(model, image, mask, threshold, gain, background)
        return _with_best_reference(classify, refs, first, mask)

    m_ax = None if masks is None else 0
    first = jax.vmap(first_of, in_axes=(0, 0, m_ax))(W, images, masks)
    need = first.fraction < min_fraction

    def fallback():
        fb = jax.vmap(fallback_of, in_axes=(0, 0, 0, m_ax))(refs, first, images, masks)
        pick = lambda a, b: jnp.where(need.reshape(need.shape + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
        return jax.tree.map(pick, fb, first)

    return jax.lax.cond(jnp.any(need), fallback, lambda: first)
