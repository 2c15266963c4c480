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
   i - (last target row <= i) or (first target row >= i) - i, carried down and up the rows by
   two sequential ``lax.scan``s over whole rows of the stack (O(h w)); B = (h + w)^2 stands
   for "none" in g^2;
2. along each row, D^2(i, j) = min_l g^2(i, l) + (j - l)^2 (the 1D squared transform);
3. D = sqrt(min(D^2, B)).

Step 2 is evaluated by brute force over the candidate columns l, restricted to the columns
[lo, hi] that hold a target pixel of the mask (every other column has g^2 = B and cannot go
below the clip): a loop over blocks of ``_BLOCK`` candidates, each block a fused chain of
elementwise minima over the whole stack, run ceil(max span / ``_BLOCK``) times for the stack.
No early exit per element, so the function is jit- and vmap-friendly; under ``vmap`` the
batch is folded into the stack (``custom_vmap``), so the loop count stays one scalar. Work is
O(n h w (span + 1)): a patch of a shirt crop spans ~10-35 of 128 columns, so this is 4-10x
less than all w candidates; a mask with scattered pixels spans the image and costs
O(n h w^2) (``benchmarks/bench_distance.py`` times both kinds against OpenCV).

Squared distances are integers below 2^24 and are computed exactly in float32; where they
fit 16 bits ((h - 1)^2 + (w - 1)^2 < 2^16, e.g. up to 160^2 and the tracker's 128^2 crops;
masks at least 64 wide) the row pass runs in uint16 instead, twice the SIMD lanes, with the
same integers (:func:`_edt_sq`; 20 x 160^2: 2.6x faster than the float32 row pass, 1.4x
faster than ``cv2.distanceTransform``, ``bench_distance``). The square root is taken in the
output dtype (the default float dtype unless ``dtype`` is given).
"""

import functools

import jax
import jax.numpy as jnp
from jax import custom_batching, lax
from jax.typing import DTypeLike
from jaxtyping import Array, Bool, Float, Int, UInt16

__all__ = ["edt", "edt_to_zero", "empty_distance", "id_map_distances"]

_BLOCK = 4  # candidate columns per loop iteration (measured best for 40x40, 128x128, 160x160)
# below this width the uint16 row pass's conversions cost what its lanes save (20 masks,
# interleaved, load ~4: 40^2 0.49 vs 0.45 ms float32; 64^2 0.67 vs 0.93; 96^2 1.57 vs 2.92)
_UINT16_MIN_WIDTH = 64
_MAX_SIDE_SUM = 4096  # (h + w)^2 must stay an exact float32 integer (< 2^24)


def empty_distance(h: int, w: int) -> int:
    """The finite value (pixels) that :func:`edt` returns everywhere for an empty mask: h + w."""
    return h + w


def _default_float() -> DTypeLike:
    return jnp.result_type(float)


def _column_distance_sq(masks: Bool[Array, "n h w"]) -> Float[Array, "n h w"]:
    """g^2 along axis 1: squared distance to the nearest True entry of the same column.

    The nearest True at or above row i is max{k <= i : m_k} (below: min{k >= i : m_k}), carried
    down (up) the rows by two sequential scans over whole rows of the stack: O(h w) work with
    an (n, w) carry. Columns without any True entry get B = (h + w)^2.
    """
    n, h, w = masks.shape
    bound = empty_distance(h, w)
    rows = jnp.moveaxis(masks, 1, 0)  # (h, n, w): one scan step per row
    i = jnp.arange(h, dtype=jnp.int32)

    def carry_last(c, x):
        m, k = x
        c = jnp.where(m, k, c)
        return c, c

    _, above = lax.scan(carry_last, jnp.full((n, w), -2 * bound, jnp.int32), (rows, i))
    _, below = lax.scan(carry_last, jnp.full((n, w), 3 * bound, jnp.int32), (rows, i), reverse=True)
    ii = i[:, None, None]
    g = jnp.minimum(jnp.minimum(ii - above, below - ii), bound).astype(jnp.float32)
    return jnp.moveaxis(g * g, 0, 1)


def _column_span(masks: Bool[Array, "n h w"]) -> tuple[Int[Array, " n"], Int[Array, " n"]]:
    """First column ``lo`` holding a True pixel of each mask, and the span ``hi - lo + 1``
    (0 for an empty mask)."""
    occupied = jnp.any(masks, axis=1)  # (n, w)
    w = occupied.shape[-1]
    lo = jnp.argmax(occupied, axis=-1).astype(jnp.int32)
    hi = (w - 1 - jnp.argmax(occupied[:, ::-1], axis=-1)).astype(jnp.int32)
    return lo, jnp.where(jnp.any(occupied, axis=-1), hi - lo + 1, 0)


def _min_plus_parabola(
    g2: Float[Array, "n h w"] | UInt16[Array, "n h w"],
    lo: Int[Array, " n"],
    span: Int[Array, " n"],
    none: float | int,
) -> Float[Array, "n h w"] | UInt16[Array, "n h w"]:
    """out[m, i, j] = min_l g2[m, i, l] + (j - l)^2 over the columns l of mask m's span, in
    the dtype of ``g2`` (float32, or uint16: see :func:`_edt_sq`); ``none`` marks a column
    without a True pixel (and pads the span).

    Exact: outside [lo, lo + span) a column has no True pixel, g2 = none there, and such a
    candidate is >= none. Each mask's candidates are gathered once into a window of the
    stack's widest span starting at column 0 (``gs[m, :, c] = g2[m, :, start_m + c]``), so
    block b of the loop reads the same columns of every mask; the loop runs
    ceil(max span / _BLOCK) times (data-dependent count, no early exit per element).
    """
    n, h, w = g2.shape
    dt = g2.dtype
    width = -(-w // _BLOCK) * _BLOCK
    n_blocks = (jnp.max(span, initial=0) + _BLOCK - 1) // _BLOCK
    # the loop's window [start_m, start_m + L), L = n_blocks * _BLOCK, holds mask m's span and
    # stays inside the image where it can (start_m = min(lo_m, w - L)), so |j - l| < w - 1 +
    # _BLOCK for every candidate; columns of the window outside the span hold g2 = none
    start = jnp.maximum(jnp.minimum(lo, w - n_blocks * _BLOCK), 0)
    c = jnp.arange(width, dtype=jnp.int32)
    idx = jnp.clip(start[:, None] + c[None, :], 0, w - 1)
    gs = jnp.take_along_axis(g2, jnp.broadcast_to(idx[:, None, :], (n, h, width)), axis=2)
    gs = jnp.where((start[:, None] + c[None, :] < w)[:, None, :], gs, jnp.asarray(none, dt))
    # j - start_m per mask, so that (j - l)^2 = (j - start_m - c)^2
    # (in uint16 the differences wrap modulo 2^16, and so do their squares: exact, as every
    # |j - l| of the loop is <= w - 2 + _BLOCK <= 255 where uint16 is used)
    j_rel = (jnp.arange(w, dtype=jnp.int32)[None, :] - start[:, None])[:, None].astype(dt)

    def candidates(b):
        c0 = (b * _BLOCK).astype(dt)
        return [jnp.square(j_rel - (c0 + jnp.asarray(q, dt))) for q in range(_BLOCK)]

    def body(b, out):
        block = lax.dynamic_slice_in_dim(gs, b * _BLOCK, _BLOCK, axis=-1)
        for q, p in enumerate(candidates(b)):
            out = jnp.minimum(out, block[..., q : q + 1] + p)
        return out

    return lax.fori_loop(0, n_blocks, body, jnp.full(g2.shape, none, dt))


def _edt_sq_float(masks: Bool[Array, "n h w"]) -> Float[Array, "n h w"]:
    _, h, w = masks.shape
    bound = jnp.float32(empty_distance(h, w) ** 2)
    big = float(jnp.finfo(jnp.float32).max) / 4
    d2 = _min_plus_parabola(_column_distance_sq(masks), *_column_span(masks), big)
    return jnp.minimum(d2, bound)


@custom_batching.custom_vmap
def _edt_sq(masks: Bool[Array, "n h w"]) -> Float[Array, "n h w"]:
    """Squared exact EDT of a stack (float32, exact integers), clipped to B = (h + w)^2.

    Where (h - 1)^2 + (w - 1)^2 < 2^16 and w >= 64 the row pass runs in **uint16** (twice
    the SIMD lanes of float32). A column without a True pixel (and the window's part past
    the image) holds N = 2^16 - 1 - (w - 2 + _BLOCK)^2, so N + any (j - l)^2 of the loop stays
    below 2^16; differences and squares wrap modulo 2^16 and stay exact (|j - l| <= 255); a
    real candidate g^2 + (j - l)^2 <= (h - 1)^2 + (w - 1)^2 is exact. A result below N is a
    real candidate's minimum (every "none" candidate is >= N). Where a true distance^2 can
    reach N (160^2: N = 39,291, a pixel >= 198 px from its mask's nearest True pixel), a
    pixel of a non-empty mask with a result >= N sends the whole call to the float32 pass
    (``lax.cond``). Same integers as the float32 pass in every case.
    """
    _, h, w = masks.shape
    max_d2 = (h - 1) ** 2 + (w - 1) ** 2
    none = 2**16 - 1 - (w - 2 + _BLOCK) ** 2  # + any (j - l)^2 of the loop does not wrap
    if max_d2 >= 2**16 - 1 or (h - 1) ** 2 >= none or w < _UINT16_MIN_WIDTH:
        return _edt_sq_float(masks)  # does not fit uint16, or too narrow to gain
    bound = jnp.float32(empty_distance(h, w) ** 2)
    g2 = _column_distance_sq(masks)  # pass 1 along columns (exact integers in float32)
    g2 = jnp.minimum(g2, jnp.float32(none)).astype(jnp.uint16)  # > (h - 1)^2: "none"
    d2 = _min_plus_parabola(g2, *_column_span(masks), none)  # pass 2 along rows, uint16
    out = jnp.where(d2 >= none, bound, d2.astype(jnp.float32))
    if max_d2 < none:  # a real result is always < N: no fallback
        return out
    unsure = jnp.any((d2 >= none) & jnp.any(masks, axis=(1, 2))[:, None, None])
    return lax.cond(unsure, _edt_sq_float, lambda m: out, masks)


@_edt_sq.def_vmap
def _edt_sq_vmap(axis_size, in_batched, masks):
    # A batch of stacks is one longer stack: the masks are independent. Batched by vmap
    # instead, the row pass's loop would run to the longest member with a select per step.
    (batched,) = in_batched
    if not batched:
        return _edt_sq(masks), False
    return _edt_sq(masks.reshape((-1,) + masks.shape[2:])).reshape(masks.shape), True


@functools.partial(jax.jit, static_argnames=("dtype",))
def _edt(masks: Bool[Array, "n h w"], dtype: jnp.dtype) -> Float[Array, "n h w"]:
    return jnp.sqrt(_edt_sq(masks).astype(dtype))


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
