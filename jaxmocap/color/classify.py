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

**Shading-invariant option** (``gain=(lo, hi)``; not in the paper): spot lamps, shadows and
the cloth's curvature scale a patch's colour by a spatially varying factor that one global ``W``
cannot follow. Each pixel is then compared to each colour at its best brightness,

    d_k^2(x) = min_{lo <= a <= hi} ||a W x - mu_k||^2_{Sigma_k}
             = a*^2 x^T A_k x + a* b_k^T x + c_k,   a* = clip(-b_k^T x / (2 x^T A_k x), lo, hi),

(uncentred ``A_k = W^T P_k W``, ``b_k = -2 W^T P_k mu_k``, ``c_k = mu_k^T P_k mu_k``): the
chromatic part of the Gaussian is kept, brightness is free within ``[lo, hi]`` (so black,
near-grey and very dark pixels, whose chromaticity is noise, stay far from every colour). Its
covariances are fitted on brightness-normalised scribbles
(:func:`jaxmocap.color.fit_color_model` ``gain=``), the same geometry.

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


def gain_coefficients(model: ColorModel, W: Float[Array, "3 3"]) -> Float[Array, "10 k"]:
    """Uncentred rows ``A00, A11, A22, 2A01, 2A02, 2A12, b0, b1, b2, c`` of
    ``||W x - mu_k||^2_{Sigma_k}`` (the shading-invariant form needs ``x`` itself)."""
    P = precision(model.cov)
    A = jnp.einsum("ji,kjl,lm->kim", W, P, W)
    Pm = jnp.einsum("kij,kj->ki", P, model.mean)
    b = -2.0 * Pm @ W
    c = jnp.einsum("ki,ki->k", model.mean, Pm)
    return jnp.stack([A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], 2 * A[:, 0, 1], 2 * A[:, 0, 2],
                      2 * A[:, 1, 2], b[:, 0], b[:, 1], b[:, 2], c])


def _gain_squared_distances(coef: Array, image: Array, dtype, gain) -> list[Array]:
    x0, x1, x2 = (image[..., c].astype(dtype) for c in range(3))
    quad = [x0 * x0, x1 * x1, x2 * x2, x0 * x1, x0 * x2, x1 * x2]
    lo, hi = (jnp.asarray(g, dtype) for g in gain)
    out = []
    for k in range(coef.shape[1]):
        q = quad[0] * coef[0, k]
        for j in range(1, 6):
            q = q + quad[j] * coef[j, k]
        lin = x0 * coef[6, k] + x1 * coef[7, k] + x2 * coef[8, k]
        a = jnp.clip(-lin / (2 * jnp.maximum(q, 1e-12)), lo, hi)
        out.append(jnp.maximum(a * a * q + a * lin + coef[9, k], 0))
    return out


def _distances(model: ColorModel, W: Array, image: Array, dtype, gain) -> list[Array]:
    """Per-colour squared distances (the paper's, or the shading-invariant ones)."""
    if gain is None:
        coef = quadratic_coefficients(model, W.astype(dtype)).astype(dtype)
        return _squared_distances(coef, _features(image, dtype))
    coef = gain_coefficients(model, W.astype(dtype)).astype(dtype)
    return _gain_squared_distances(coef, image, dtype, gain)


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
    gain: tuple[float, float] | None = None,
) -> Float[Array, "h w k"]:
    """Squared Mahalanobis distances ``||W I_xy - mu_k||^2_{Sigma_k}`` to every colour (with
    ``gain``: at each pixel's best brightness, module docstring)."""
    dtype = _dtype(model, W, image)
    return jnp.stack(_distances(model, W, image, dtype, gain), axis=-1)


def classify(
    model: ColorModel,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    threshold: float | Float[Array, ""] = THRESHOLD,
    gain: tuple[float, float] | None = None,
    background: ColorModel | None = None,
) -> tuple[Int[Array, "h w"], Float[Array, "h w"]]:
    """Id map ``r`` (0 background, ``1..k`` colours; int32) and the winner's distance.

    The distance (standard deviations) is ``min_k ||W I_xy - mu_k||_{Sigma_k}`` for every pixel,
    also where the id is 0 (above ``threshold`` or outside ``mask``); ``gain``: the
    shading-invariant distance (module docstring); ``background``: Gaussians of the scene's
    colours (:func:`background_mask`), a pixel nearer one of them than every colour is 0.
    """
    dtype = _dtype(model, W, image)
    best, idx = None, None
    for k, d in enumerate(_distances(model, W, image, dtype, gain)):
        if best is None:
            best, idx = d, jnp.ones(d.shape, jnp.int32)
        else:
            better = d < best
            best = jnp.where(better, d, best)
            idx = jnp.where(better, jnp.int32(k + 1), idx)
    keep = best < jnp.asarray(threshold, dtype) ** 2
    if mask is not None:
        keep = keep & mask
    if background is not None:
        keep = keep & (best < nearest_sq(background, W, image, gain))
    return jnp.where(keep, idx, 0), jnp.sqrt(jnp.maximum(best, 0))


def nearest_sq(
    model: ColorModel,
    W: Float[Array, "3 3"],
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    gain: tuple[float, float] | None = None,
) -> Float[Array, "h w"]:
    """``min_k`` of the squared distances to ``model``'s Gaussians (one fused pass)."""
    dtype = _dtype(model, W, image)
    best = None
    for d in _distances(model, W, image, dtype, gain):
        best = d if best is None else jnp.minimum(best, d)
    return best


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
