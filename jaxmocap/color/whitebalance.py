"""White balance: the 3 x 3 matrix W that maps observed colours to the model's (Wang §5.1, §5.2.5).

The paper prints ``W = argmin_W sum_k ||W mu_k - mu'_k||^2``, but its text (and its use,
``W I_xy`` compared to ``mu_k``) says W maps the *observed* mean patch colours ``mu'_k`` to the
model means ``mu_k``. We implement the latter, with per-colour weights ``v_k`` (0 for a colour
that is not visible) and a Tikhonov term toward a prior ``W_0`` (identity, or the previous
frame's W):

    W = argmin_W  sum_k v_k ||(W mu'_k - mu_k) / 255||^2  +  lambda ||W - W_0||_F^2.

With fewer than three visible colours the data term is rank deficient and the prior fixes the
unseen directions; with many colours a small ``lambda`` barely biases the fit. The problem is
solved inside jit with optimistix's Gauss-Newton (one step solves this linear least-squares
problem exactly; the solver stays general should the residual become robust or nonlinear).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, UInt8

from .model import ColorModel

REGULARISATION = 1e-5  # lambda, per unit of ||W - W_0||_F^2 against colours scaled to 0..1
MIN_PIXELS = 20  # a colour needs this many labelled pixels to enter the fit (not in the paper)
_SCALE = 255.0


def fit_white_balance(
    observed: Float[Array, "k 3"],
    target: Float[Array, "k 3"],
    weights: Float[Array, " k"],
    W_prior: Float[Array, "3 3"],
    reg: float | Float[Array, ""] = REGULARISATION,
    max_steps: int = 8,
) -> Float[Array, "3 3"]:
    """Weighted least-squares ``W`` with ``W observed_k ~ target_k`` (0..255 units), see module."""
    dtype = jnp.result_type(observed.dtype, target.dtype, W_prior.dtype)
    sw = jnp.sqrt(jnp.maximum(weights.astype(dtype), 0))[:, None]
    obs, tgt = observed.astype(dtype) / _SCALE, target.astype(dtype) / _SCALE
    W_prior = W_prior.astype(dtype)
    sreg = jnp.sqrt(jnp.asarray(reg, dtype))

    def residual(W, args):
        data = sw * (obs @ W.T - tgt)  # (k, 3): rows W mu'_k - mu_k
        return jnp.concatenate([data.reshape(-1), sreg * (W - W_prior).reshape(-1)])

    tol = 1e-10 if dtype == jnp.float64 else 1e-5
    solver = optx.GaussNewton(rtol=tol, atol=tol)
    sol = optx.least_squares(residual, solver, W_prior, max_steps=max_steps, throw=False)
    return sol.value


def patch_means(
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    ids: Int[Array, "h w"],
    n_colors: int,
    mask: Bool[Array, "h w"] | None = None,
    dtype=None,
) -> tuple[Float[Array, "k 3"], Float[Array, " k"]]:
    """Per-colour pixel sums / counts (segment sums): means ``mu'_k`` (0 if absent) and counts.

    ``dtype`` defaults to the image's float dtype, or float32 for integer images.
    """
    if dtype is None:
        dtype = image.dtype if jnp.issubdtype(image.dtype, jnp.floating) else jnp.float32
    x = image.reshape(-1, 3).astype(dtype)
    seg = ids.reshape(-1)
    if mask is not None:
        seg = jnp.where(mask.reshape(-1), seg, 0)
    sums = jax.ops.segment_sum(x, seg, n_colors + 1)[1:]
    counts = jax.ops.segment_sum(jnp.ones(seg.shape, dtype), seg, n_colors + 1)[1:]
    return sums / jnp.maximum(counts, 1)[:, None], counts


def white_balance_from_ids(
    model: ColorModel,
    image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    ids: Int[Array, "h w"],
    W_prior: Float[Array, "3 3"],
    mask: Bool[Array, "h w"] | None = None,
    reg: float | Float[Array, ""] = REGULARISATION,
    min_pixels: int | Int[Array, ""] = MIN_PIXELS,
) -> Float[Array, "3 3"]:
    """``W*`` from an id map (e.g. ``r*`` rendered at the final pose, Wang §5.2 step 5); jit-able.

    ``ids`` holds colour ids (0 background, ``1..k``); colours with fewer than ``min_pixels``
    pixels get weight 0.
    """
    dtype = model.mean.dtype
    if jnp.issubdtype(image.dtype, jnp.floating):
        dtype = jnp.result_type(dtype, image.dtype)
    means, counts = patch_means(image, ids, model.n_colors, mask, dtype)
    weights = (counts >= min_pixels).astype(means.dtype)
    return fit_white_balance(means, model.mean, weights, W_prior, reg)


def white_balance_from_scribbles(
    model: ColorModel,
    images: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    W_prior: np.ndarray | Float[Array, "3 3"] | None = None,
    reg: float = REGULARISATION,
    min_pixels: int = MIN_PIXELS,
) -> Float[Array, "3 3"]:
    """Initial ``W`` from user scribbles on images of the shirt in the capture's light (§5.1).

    ``labels[i]`` is (H, W) with 0 = unlabelled and ``1..k`` = colour ids. Pixels of all images
    are pooled per colour; colours with fewer than ``min_pixels`` scribbled pixels are ignored.
    """
    if len(images) != len(labels) or len(images) == 0:
        raise ValueError(
            f"white_balance_from_scribbles: need one label mask per image (>= 1), got "
            f"{len(images)} images and {len(labels)} label masks"
        )
    k = model.n_colors
    sums, counts = np.zeros((k, 3)), np.zeros(k)
    for i, (img, lab) in enumerate(zip(images, labels, strict=True)):
        img, lab = np.asarray(img, np.float64), np.asarray(lab)
        if img.shape[:2] != lab.shape or img.shape[-1:] != (3,):
            raise ValueError(
                f"white_balance_from_scribbles: image {i} {img.shape} and labels {lab.shape} "
                "must be (H, W, 3) and (H, W)"
            )
        if lab.min() < 0 or lab.max() > k:
            raise ValueError(
                f"white_balance_from_scribbles: labels of image {i} must be in [0, {k}]"
            )
        sums += np.stack([img[lab == c + 1].sum(axis=0) for c in range(k)])
        counts += np.bincount(lab.reshape(-1), minlength=k + 1)[1:]
    dtype = model.mean.dtype
    means = jnp.asarray(sums / np.maximum(counts, 1)[:, None], dtype)
    weights = jnp.asarray(counts >= min_pixels, dtype)
    prior = jnp.eye(3, dtype=dtype) if W_prior is None else jnp.asarray(W_prior, dtype)
    return _fit_white_balance_jit(means, model.mean, weights, prior, jnp.asarray(reg, dtype))


_fit_white_balance_jit = jax.jit(fit_white_balance, static_argnames="max_steps")
