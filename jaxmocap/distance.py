"""Exact Euclidean distance transform (EDT) in JAX, for stacks of binary masks.

Wang et al. §5.2 step 3 (pose-assisted classification) needs, for every pixel (x, y) and every
colour id k of the rasterised prior id map r^b,

    d_xy(r, k) = min_{(u, v) in S_k} ||(u, v) - (x, y)||,   S_k = {(u, v) | r_uv = k},

in pixels. :func:`id_map_distances` computes it for all ids at once; :func:`edt` is the
underlying transform for any stack of masks.

Conventions
-----------
* :func:`edt` ``(masks)`` is the distance from each pixel to the nearest **True** pixel of its
  own mask (0 on True pixels). This is the convention of the paper's ``d_xy``.
* :func:`edt_to_zero` ``(masks)`` is the distance to the nearest **False** pixel (0 on False
  pixels), i.e. the convention of ``cv2.distanceTransform(src, cv2.DIST_L2,
  cv2.DIST_MASK_PRECISE)`` and ``scipy.ndimage.distance_transform_edt(src)``, which measure the
  distance from each non-zero pixel to the nearest zero pixel.
* A mask without any target pixel has no finite distance; every pixel then gets
  ``h + w`` (:func:`empty_distance`), which exceeds every true distance in an h x w image
  (at most sqrt((h-1)^2 + (w-1)^2)). Downstream terms such as Wang's ``C * d`` stay finite:
  no inf, no NaN.

Algorithm
---------
Separable and exact (the squared EDT decomposes over axes, as in Felzenszwalb & Huttenlocher):

1. along each column, g(i, j) = distance to the nearest target pixel of column j (1D, exact):
   i - (last target row <= i) or (first target row >= i) - i, from a prefix maximum and a
   suffix minimum (associative scans, O(log h) steps); B = (h + w)^2 stands for "none" in g^2;
2. along each row, D^2(i, j) = min_l g^2(i, l) + (j - l)^2 (the 1D squared transform);
3. D = sqrt(min(D^2, B)).

Step 2 is evaluated by brute force over all candidates l with a fixed number of iterations
(no data-dependent exit, so it is jit-, vmap- and scan-friendly): a ``fori_loop`` over blocks
of ``_BLOCK`` candidate columns, each block a fused chain of elementwise minima over the whole
stack, along the minor axis (step 1 runs on the transposed stack for the same reason), which
is what vectorises best with XLA on CPU (see ``benchmarks/bench_distance.py``). Work is
O(n h w (w + log h)); for the paper's sizes (40 x 40 tiny id maps, ~160 x 160 crops) this
beats a sequential lower envelope.

Squared distances are integers below 2^24 and are computed exactly in float32; the square
root is taken in the output dtype (the default float dtype unless ``dtype`` is given).
"""

import functools

import jax
import jax.numpy as jnp
from jax import lax
from jax.typing import DTypeLike
from jaxtyping import Array, Bool, Float, Int

__all__ = ["edt", "edt_to_zero", "empty_distance", "id_map_distances"]

_BLOCK = 4  # candidate columns per loop iteration (measured best for 40x40 and 160x160)
_MAX_SIDE_SUM = 4096  # (h + w)^2 must stay an exact float32 integer (< 2^24)


def empty_distance(h: int, w: int) -> int:
    """The finite value (pixels) that :func:`edt` returns everywhere for an empty mask: h + w."""
    return h + w


def _min_plus_parabola(f: Float[Array, "... l"]) -> Float[Array, "... l"]:
    """out[..., j] = min_k f[..., k] + (j - k)^2 along the last axis (exact, brute force)."""
    length = f.shape[-1]
    n_blocks = -(-length // _BLOCK)
    pad = n_blocks * _BLOCK - length
    big = jnp.asarray(jnp.finfo(f.dtype).max / 4, f.dtype)
    fp = jnp.pad(f, [(0, 0)] * (f.ndim - 1) + [(0, pad)], constant_values=big)
    j = jnp.arange(length, dtype=f.dtype).reshape((1,) * (f.ndim - 1) + (length,))

    def body(b, out):
        block = lax.dynamic_slice_in_dim(fp, b * _BLOCK, _BLOCK, axis=-1)
        k0 = (b * _BLOCK).astype(f.dtype)
        for q in range(_BLOCK):
            out = jnp.minimum(out, block[..., q : q + 1] + jnp.square(j - (k0 + q)))
        return out

    return lax.fori_loop(0, n_blocks, body, jnp.full(f.shape, big, f.dtype))


def _default_float() -> DTypeLike:
    return jnp.result_type(float)


def _column_distance_sq(masks_t: Bool[Array, "n w h"]) -> Float[Array, "n w h"]:
    """g^2 along the last axis: squared distance to the nearest True entry of the same line.

    1D distances need no min-plus: the nearest True at or above i is max{k <= i : m_k}, a
    prefix maximum (and a suffix minimum below), computed by associative scans in O(h log h).
    Lines without any True entry get B = (h + w)^2.
    """
    h = masks_t.shape[-1]
    bound = empty_distance(h, masks_t.shape[-2])
    i = jnp.arange(h, dtype=jnp.int32).reshape(1, 1, h)
    above = lax.associative_scan(jnp.maximum, jnp.where(masks_t, i, -2 * bound), axis=2)
    below = lax.associative_scan(
        jnp.minimum, jnp.where(masks_t, i, 3 * bound), axis=2, reverse=True
    )
    g = jnp.minimum(jnp.minimum(i - above, below - i), bound).astype(jnp.float32)
    return g * g


@functools.partial(jax.jit, static_argnames=("dtype",))
def _edt(masks: Bool[Array, "n h w"], dtype: jnp.dtype) -> Float[Array, "n h w"]:
    _, h, w = masks.shape
    bound = jnp.float32(empty_distance(h, w) ** 2)
    # pass 1 along columns (on the transposed stack so that the axis is minor)
    g2 = jnp.swapaxes(_column_distance_sq(jnp.swapaxes(masks, 1, 2)), 1, 2)
    # pass 2 along rows: the min-plus transform with the parabola (j - l)^2
    d2 = jnp.minimum(_min_plus_parabola(g2), bound)
    return jnp.sqrt(d2.astype(dtype))


def _check_masks(masks, name: str) -> None:
    if masks.ndim != 3:
        raise ValueError(
            f"{name}: expected a stack of masks with shape (n, h, w), got shape {masks.shape}"
        )
    _, h, w = masks.shape
    if h + w > _MAX_SIDE_SUM:
        raise ValueError(
            f"{name}: h + w = {h + w} exceeds {_MAX_SIDE_SUM}; squared distances "
            "would no longer be exact in float32"
        )


def edt(masks: Bool[Array, "n h w"], dtype: DTypeLike | None = None) -> Float[Array, "n h w"]:
    """Exact Euclidean distance (pixels) from every pixel to the nearest True pixel of its mask.

    Args:
        masks: stack of n binary masks, shape (n, h, w), bool.
        dtype: output float dtype; default the default float dtype (float32, or float64 with
            x64 enabled).

    Returns:
        D of shape (n, h, w): D[m, y, x] = min over True pixels (v, u) of mask m of
        sqrt((x - u)^2 + (y - v)^2); 0 on True pixels; ``h + w`` everywhere if mask m has no
        True pixel (see :func:`empty_distance`).

    Jit-compiled (one compilation per shape and dtype); vmap adds leading axes.
    """
    masks = jnp.asarray(masks)
    _check_masks(masks, "edt(masks)")
    return _edt(masks.astype(bool), jnp.dtype(dtype or _default_float()))


def edt_to_zero(
    masks: Bool[Array, "n h w"], dtype: DTypeLike | None = None
) -> Float[Array, "n h w"]:
    """Distance from every pixel to the nearest **False** pixel (OpenCV / SciPy convention).

    ``edt_to_zero(m)[i] == cv2.distanceTransform(m[i].astype(uint8), cv2.DIST_L2,
    cv2.DIST_MASK_PRECISE)`` and ``== scipy.ndimage.distance_transform_edt(m[i])``. A mask with
    no False pixel gets ``h + w`` everywhere.
    """
    masks = jnp.asarray(masks)
    _check_masks(masks, "edt_to_zero(masks)")
    return _edt(~masks.astype(bool), jnp.dtype(dtype or _default_float()))


def id_map_distances(
    id_map: Int[Array, "h w"], n_ids: int, dtype: DTypeLike | None = None
) -> Float[Array, "n_ids h w"]:
    """Wang et al. §5.2 step 3: d_xy(r, k) for every id k in 0..n_ids-1 at once (pixels).

    Args:
        id_map: rasterised id map r (e.g. the blended prior r^b), integer ids; id 0 is the
            background by the project's convention and gets its channel like any other id.
        n_ids: number of ids (static); ids outside [0, n_ids) are ignored.
        dtype: output float dtype (default float dtype if None).

    Returns:
        d of shape (n_ids, h, w): d[k, y, x] = distance from (x, y) to the nearest pixel with
        id k; ``h + w`` for an id absent from the map.
    """
    id_map = jnp.asarray(id_map)
    if id_map.ndim != 2:
        raise ValueError(f"id_map_distances(id_map): expected shape (h, w), got {id_map.shape}")
    if n_ids < 1:
        raise ValueError(f"id_map_distances(n_ids): expected a positive count, got {n_ids}")
    masks = id_map[None, :, :] == jnp.arange(n_ids, dtype=id_map.dtype)[:, None, None]
    return edt(masks, dtype)
