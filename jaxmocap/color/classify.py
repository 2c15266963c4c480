"""Gaussian colour classification (Wang et al. 2011, §5.2 step 1).

After white balancing with a 3 x 3 matrix ``W``, pixel ``I_xy`` (RGB, 0..255 units) gets the id

    r_xy = argmin_k ||W I_xy - mu_k||_{Sigma_k}   if that distance is < T,   else 0 (background)

with the Mahalanobis distance ``||X||_Sigma = sqrt(X^T Sigma^{-1} X)``, ``T = 3`` and ids
``1..k``. A foreground mask (background subtraction) sets masked-out pixels to 0.

Evaluation: the quadratic form is expanded once per call into ten coefficients per colour,

    d_k^2(x) = x^T A_k x + b_k^T x + c_k,   x = I - 127.5,
    A_k = W^T P_k W,   b_k = -2 W^T P_k m_k,   c_k = m_k^T P_k m_k,   m_k = mu_k - 127.5 W 1,

(``P_k = Sigma_k^{-1}``; centring at 127.5 halves the magnitudes that cancel). In NumPy the best
evaluation is one ``(N, 10) @ (10, k)`` GEMM because a per-class loop materialises k arrays; in
XLA the unrolled loop over the k classes with a running minimum fuses into a *single* pass over
the pixels (no ``(N, 10)`` feature or ``(N, k)`` distance array is ever written), which measured
~7x faster than the GEMM form on 640 x 480 (see ``benchmarks/bench_color.py``).

The soft form gives per-class responsibilities ``softmax(-d_k^2 / (2 t))`` with a background
class whose squared distance is ``T^2``; it is differentiable w.r.t. ``mu``, ``Sigma`` (use
:func:`~jaxmocap.color.model.cov_from_log_cholesky` for unconstrained parameters), ``W``, ``T``
and the temperature ``t``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from .model import ColorModel

THRESHOLD = 3.0  # Wang §5.2 step 1: "T = 3 performs well in practice" (standard deviations)
CENTRE = 127.5  # RGB units; centring of the expanded quadratic form (numerics only)


def _dtype(model: ColorModel, W: Array, image: Array) -> jnp.dtype:
    if jnp.issubdtype(image.dtype, jnp.floating):
        return jnp.result_type(model.mean.dtype, W.dtype, image.dtype)
    return jnp.result_type(model.mean.dtype, W.dtype)


def precision(cov: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 3 3"]:
    """``Sigma^{-1}`` through the Cholesky factor (symmetric by construction)."""
    chol = jnp.linalg.cholesky(cov)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=cov.dtype), cov.shape)
    inv_chol = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
    return jnp.swapaxes(inv_chol, -1, -2) @ inv_chol


def quadratic_coefficients(model: ColorModel, W: Float[Array, "3 3"]) -> Float[Array, "10 k"]:
    """Rows ``A00, A11, A22, 2A01, 2A02, 2A12, b0, b1, b2, c`` of ``d_k^2`` in ``x = I - 127.5``."""
    P = precision(model.cov)  # (k, 3, 3)
    A = jnp.einsum("ji,kjl,lm->kim", W, P, W)
    m = model.mean - CENTRE * W.sum(axis=1)[None, :]  # mu_k - W (127.5, 127.5, 127.5)
    Pm = jnp.einsum("kij,kj->ki", P, m)
    b = -2.0 * Pm @ W  # (W^T P m)_i = sum_j W_ji (P m)_j
    c = jnp.einsum("ki,ki->k", m, Pm)
    return jnp.stack(
        [
            A[:, 0, 0],
            A[:, 1, 1],
            A[:, 2, 2],
            2 * A[:, 0, 1],
            2 * A[:, 0, 2],
            2 * A[:, 1, 2],
            b[:, 0],
            b[:, 1],
            b[:, 2],
            c,
        ]
    )


def _features(image: Array, dtype) -> list[Array]:
    x0, x1, x2 = (image[..., c].astype(dtype) - CENTRE for c in range(3))
    return [x0 * x0, x1 * x1, x2 * x2, x0 * x1, x0 * x2, x1 * x2, x0, x1, x2]


def _squared_distances(coef: Array, feats: list[Array]) -> list[Array]:
    out = []
    for k in range(coef.shape[1]):
        d = coef[9, k] + feats[0] * coef[0, k]
        for j in range(1, 9):
            d = d + feats[j] * coef[j, k]
        out.append(d)
    return out


def mahalanobis_sq(
    model: ColorModel,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
) -> Float[Array, "h w k"]:
    """Squared Mahalanobis distances ``||W I_xy - mu_k||^2_{Sigma_k}`` to every colour."""
    dtype = _dtype(model, W, image)
    coef = quadratic_coefficients(model, W.astype(dtype)).astype(dtype)
    return jnp.stack(_squared_distances(coef, _features(image, dtype)), axis=-1)


def classify(
    model: ColorModel,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    threshold: float | Float[Array, ""] = THRESHOLD,
) -> tuple[Int[Array, "h w"], Float[Array, "h w"]]:
    """Id map ``r`` (0 background, ``1..k`` colours; int32) and the winner's distance.

    The distance (standard deviations) is ``min_k ||W I_xy - mu_k||_{Sigma_k}`` for every pixel,
    also where the id is 0 (above ``threshold`` or outside ``mask``).
    """
    dtype = _dtype(model, W, image)
    coef = quadratic_coefficients(model, W.astype(dtype)).astype(dtype)
    feats = _features(image, dtype)
    best, idx = None, None
    for k, d in enumerate(_squared_distances(coef, feats)):
        if best is None:
            best, idx = d, jnp.ones(d.shape, jnp.int32)
        else:
            better = d < best
            best = jnp.where(better, d, best)
            idx = jnp.where(better, jnp.int32(k + 1), idx)
    keep = best < jnp.asarray(threshold, dtype) ** 2
    if mask is not None:
        keep = keep & mask
    return jnp.where(keep, idx, 0), jnp.sqrt(jnp.maximum(best, 0))


def classified_fraction(
    ids: Int[Array, "h w"], mask: Bool[Array, "h w"] | None = None
) -> Float[Array, ""]:
    """Fraction of (foreground) pixels that got a colour id (0 if there is no foreground)."""
    n_fg = ids.size if mask is None else jnp.sum(mask)
    return jnp.sum(ids > 0) / jnp.maximum(n_fg, 1)


def soft_classify(
    model: ColorModel,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    threshold: float | Float[Array, ""] = THRESHOLD,
    temperature: float | Float[Array, ""] = 1.0,
) -> Float[Array, "h w k1"]:
    """Responsibilities ``softmax(-d^2 / (2 t))`` over ``[background, colour 1..k]``.

    The background's squared distance is ``T^2``, so as ``t -> 0`` the argmax equals
    :func:`classify`. Channel 0 is background, channel ``k`` colour id ``k``.
    """
    d2 = mahalanobis_sq(model, W, image)
    dtype = d2.dtype
    bg = jnp.broadcast_to(jnp.asarray(threshold, dtype) ** 2, d2.shape[:-1])[..., None]
    logits = -jnp.concatenate([bg, d2], axis=-1) / (2 * jnp.asarray(temperature, dtype))
    return jax.nn.softmax(logits, axis=-1)
